"""The preference predictor ``p_hat(s, g)``: a siamese network trained from pairwise preferences.

Section 4.1.1 of the paper: a person compares two sub-goals ``g1``, ``g2`` in a state ``s``; the
predictor is fitted with the Bradley-Terry cross-entropy (eq. 1, 2) and its score
``b = p_hat(s, g)`` becomes the meta-controller's preference bonus (eq. 3). Section 4.1.3: a
dropout layer sits before every weight layer, and the spread of the score over many dropout masks
(MC dropout, eq. 4) measures how unsure the predictor is, which decides when to ask (line 26).
"""

import contextlib
import copy
import math
import types
from collections.abc import Iterator
from typing import Any, Optional, Union

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F
from stable_baselines3.common.preprocessing import (
    is_image_space,
    is_image_space_channels_first,
    preprocess_obs,
)
from stable_baselines3.common.utils import get_device
from torch import nn

from sb3_hhp.arrays import distinct_rows
from sb3_hhp.preferences.seeding import OwnRandomState
from sb3_hhp.preferences.types import Label

HEADS = ("linear", "sigmoid", "relu")
ARCHITECTURES = ("auto", "cnn", "mlp")
SPREADS = ("std", "var")
# Smallest image side that "auto" sends through the convolutional branch (NatureCNN's minimum).
MIN_CNN_SIDE = 36


def check_int(name: str, value: Any, minimum: int) -> None:
    """A clear error unless ``value`` is a whole number (not a bool) >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _check_box(observation_space: Any) -> None:
    if not isinstance(observation_space, gymnasium.spaces.Box):
        raise ValueError(
            "The preference predictor supports gymnasium.spaces.Box observation spaces only "
            "(uint8 images, channel-last or channel-first, or vectors of any dtype); "
            f"got {observation_space!r}. Flatten Dict/Discrete spaces into a Box first."
        )


class PreferenceNetwork(nn.Module):
    """Siamese score network ``p_hat(s, g)`` of section 5.1.

    Two branches of identical structure but **separate weights** read the state and the goal: for
    images, three convolutions (32, 64, 64 filters; kernels 8, 4, 3; strides 4, 2, 1; padding 1),
    each followed by a ReLU; for vectors (or small images), two ``Linear(hidden_dim)`` + ReLU. The
    two feature vectors are concatenated and go through two fully connected layers of
    ``hidden_dim`` units (ReLU) and a final ``Linear`` to one score. A ``Dropout(p=dropout)`` sits
    immediately before every weight layer (every Conv and Linear, the first ones included), so that
    MC dropout (eq. 4) samples the whole network.

    Inputs are raw observations as the environment gives them: uint8 images, channel-last or
    channel-first (divided by 255 by SB3's ``preprocess_obs``, channel-last ones transposed), or
    Box vectors of any dtype (cast to float).

    :param observation_space: the Box space of both states and goals
    :param hidden_dim: units of the fully connected layers (>= 1; paper: 256)
    :param dropout: dropout probability before every weight layer, in [0, 1) (paper: 0.1)
    :param head: output activation: "linear" (raw score, default), "sigmoid" (the paper's output)
        or "relu" (non-negative, for regressing returns)
    :param architecture: "cnn" (image branches), "mlp" (vector branches) or "auto": "cnn" for
        image spaces whose sides are all >= 36 pixels, "mlp" otherwise
    """

    def __init__(
        self,
        observation_space: gymnasium.spaces.Box,
        hidden_dim: int = 256,
        dropout: float = 0.1,
        head: str = "linear",
        architecture: str = "auto",
    ) -> None:
        super().__init__()
        _check_box(observation_space)
        check_int("hidden_dim", hidden_dim, 1)
        if not 0.0 <= float(dropout) < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout!r}")
        if head not in HEADS:
            raise ValueError(f"head must be one of {HEADS}, got {head!r}")
        if architecture not in ARCHITECTURES:
            raise ValueError(f"architecture must be one of {ARCHITECTURES}, got {architecture!r}")

        self.observation_space = observation_space
        self.hidden_dim = int(hidden_dim)
        self.dropout = float(dropout)
        self.head_name = head
        self.is_image = is_image_space(observation_space)
        self.channels_first = self.is_image and is_image_space_channels_first(observation_space)
        if self.is_image:
            shape = observation_space.shape
            self.image_chw = (shape[0], shape[1], shape[2]) if self.channels_first else (shape[2], shape[0], shape[1])
        if architecture == "auto":
            big_enough = self.is_image and min(self.image_chw[1:]) >= MIN_CNN_SIDE
            architecture = "cnn" if big_enough else "mlp"
        elif architecture == "cnn" and not self.is_image:
            raise ValueError(
                "architecture='cnn' needs an image space: a uint8 Box of shape (H, W, C) or (C, H, W) with "
                f"bounds [0, 255]; got {observation_space!r}. Use architecture='mlp' or 'auto'."
            )
        self.architecture = architecture

        self.state_branch = self._make_branch()
        self.goal_branch = self._make_branch()
        n_features = self._branch_features()
        p = self.dropout
        self.head = nn.Sequential(
            nn.Dropout(p),
            nn.Linear(2 * n_features, self.hidden_dim),
            nn.ReLU(),
            nn.Dropout(p),
            nn.Linear(self.hidden_dim, self.hidden_dim),
            nn.ReLU(),
            nn.Dropout(p),
            nn.Linear(self.hidden_dim, 1),
        )
        self.output_activation = {"linear": nn.Identity(), "sigmoid": nn.Sigmoid(), "relu": nn.ReLU()}[head]

    def _make_branch(self) -> nn.Sequential:
        p = self.dropout
        if self.architecture == "cnn":
            n_channels = self.image_chw[0]
            return nn.Sequential(
                nn.Dropout(p),
                nn.Conv2d(n_channels, 32, kernel_size=8, stride=4, padding=1),
                nn.ReLU(),
                nn.Dropout(p),
                nn.Conv2d(32, 64, kernel_size=4, stride=2, padding=1),
                nn.ReLU(),
                nn.Dropout(p),
                nn.Conv2d(64, 64, kernel_size=3, stride=1, padding=1),
                nn.ReLU(),
                nn.Flatten(),
            )
        n_input = int(np.prod(self.observation_space.shape))
        return nn.Sequential(
            nn.Dropout(p),
            nn.Linear(n_input, self.hidden_dim),
            nn.ReLU(),
            nn.Dropout(p),
            nn.Linear(self.hidden_dim, self.hidden_dim),
            nn.ReLU(),
        )

    def _branch_features(self) -> int:
        if self.architecture == "mlp":
            return self.hidden_dim
        try:
            with torch.no_grad():
                return int(self.state_branch(torch.zeros(1, *self.image_chw)).shape[1])
        except RuntimeError as error:
            raise ValueError(
                f"Images of shape {self.observation_space.shape} are too small for the convolutional branch; "
                "use architecture='mlp' or 'auto'"
            ) from error

    def preprocess(self, obs: torch.Tensor) -> torch.Tensor:
        """Turn a batch of raw observations ``(B, *obs_shape)`` into the branch input (float, images in [0, 1])."""
        if tuple(obs.shape[1:]) != tuple(self.observation_space.shape):
            raise ValueError(
                f"Expected a batch of observations of shape (B, {', '.join(map(str, self.observation_space.shape))}), "
                f"got {tuple(obs.shape)}"
            )
        obs = preprocess_obs(obs, self.observation_space)
        if self.architecture == "cnn":
            return obs if self.channels_first else obs.permute(0, 3, 1, 2)
        return obs.flatten(start_dim=1)

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Scores ``p_hat(s, g)``.

        :param states: raw states ``(B, *obs_shape)``, or ``(1, *obs_shape)`` to pair one state with every goal
        :param goals: raw goal observations ``(B, *obs_shape)``, or ``(1, *obs_shape)``
        :return: the scores, shape (B,)
        """
        state_features = self.state_branch(self.preprocess(states))
        goal_features = self.goal_branch(self.preprocess(goals))
        if state_features.shape[0] != goal_features.shape[0]:
            if state_features.shape[0] == 1:
                state_features = state_features.expand(goal_features.shape[0], -1)
            elif goal_features.shape[0] == 1:
                goal_features = goal_features.expand(state_features.shape[0], -1)
            else:
                raise ValueError(
                    f"states and goals need the same batch size (or one of them 1), got "
                    f"{state_features.shape[0]} and {goal_features.shape[0]}"
                )
        features = torch.cat([state_features, goal_features], dim=1)
        return self.output_activation(self.head(features)).squeeze(-1)

    def score_matrix(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Scores ``p_hat(s_i, g_j)`` of every state with every goal, ``(N, G)``, without dropout (eval mode).

        Each branch runs once per state and once per goal, and the head's first layer, linear in the concatenated
        features, is split into its state and goal halves (``W [f_s; f_g] = W_s f_s + W_g f_g``): only the rest
        of the head runs per pair. Equal to :meth:`forward` on every pair."""
        first = self.head[1]
        n_features = first.in_features // 2
        state_part = self.state_branch(self.preprocess(states)) @ first.weight[:, :n_features].T + first.bias
        goal_part = self.goal_branch(self.preprocess(goals)) @ first.weight[:, n_features:].T
        hidden = (state_part[:, None, :] + goal_part[None, :, :]).reshape(-1, first.out_features)
        scores = self.output_activation(self.head[2:](hidden)).squeeze(-1)
        return scores.reshape(len(state_part), len(goal_part))


@contextlib.contextmanager
def _shared_masks(network: nn.Module, sets: int) -> Iterator[None]:
    """Inside, every ``Dropout`` of ``network`` draws its masks for the first of ``sets`` equal parts of a batch and
    applies them to the others too: row ``i`` of each part sees the same mask. ``sets`` 1: dropout as it is."""
    if sets == 1:
        yield
        return

    def shared(module: nn.Dropout, x: torch.Tensor) -> torch.Tensor:
        part = x.shape[0] // sets
        mask = F.dropout(torch.ones_like(x[:part]), module.p, training=True)
        return x * mask.repeat(sets, *[1] * (x.dim() - 1))

    dropouts = [module for module in network.modules() if isinstance(module, nn.Dropout)]
    for module in dropouts:
        module.forward = types.MethodType(shared, module)
    try:
        yield
    finally:
        for module in dropouts:
            del module.forward


#: most inputs whose spread (eq. 4) is kept for the current version of the network
MAX_CACHED_CONFIDENCES = 100_000


class PreferencePredictor(OwnRandomState):
    """The preference predictor ``p_hat`` with its preference buffer ``R`` (Algorithm 1, lines 25-27).

    It scores (state, sub-goal) pairs (the bonus ``b``), measures its own uncertainty by MC dropout
    (eq. 4) and trains on labelled tuples ``(s, g1, g2, v)`` with the Bradley-Terry loss (eq. 1, 2).

    Randomness (initial weights, dropout masks, minibatch order) comes from the predictor's own
    generators, derived from ``seed``; it neither reads nor disturbs the global torch RNG, so a
    seeded predictor is reproducible whatever else draws random numbers.

    :param observation_space: the Box space of states and goal observations
    :param hidden_dim: units of the fully connected layers (paper: 256)
    :param dropout: dropout probability before every weight layer, in [0, 1) (paper: 0.1)
    :param n_masks: number of dropout masks for the confidence (eq. 4), >= 1 (paper: 500)
    :param head: output activation of the network: "linear", "sigmoid" (the paper's) or "relu"
    :param spread: "var" (eq. 4 as written: variance over masks) or "std" (its square root, the
        default, so that t_qry 0.26 / 0.42 are reachable; design decisions: the predictor head)
    :param learning_rate: Adam learning rate, > 0 (paper: 1e-3)
    :param batch_size: minibatch size for training, >= 1 (paper: 128)
    :param n_epochs: epochs over the buffer per :meth:`train` call, >= 1 (paper: 4)
    :param min_updates: fewest minibatch updates per :meth:`train` call, >= 0: with a buffer smaller than a
        minibatch, ``n_epochs`` epochs are ``n_epochs`` updates, too few to fit a label that has just arrived (the
        paper's 4 epochs were over hundreds of labels); whole epochs are added until there are at least this many.
        0: ``n_epochs`` epochs
    :param buffer_size: capacity of the FIFO preference buffer ``R``, >= 1 (paper: the query budget)
    :param mask_batch_size: most rows (input x mask) sent through the network at once by
        :meth:`confidence` and :meth:`score`, >= 1; lower it for image inputs (one 84x84x4 frame
        pair is about 0.2 MB of float input, so e.g. 2,000 rows on a small machine)
    :param architecture: "auto", "cnn" or "mlp" (see :class:`PreferenceNetwork`)
    :param device: torch device ("cpu", "cuda", "auto")
    :param seed: seed of the predictor's generators; None draws one from the global torch RNG
        (so SB3's ``set_random_seed`` still makes runs reproducible)
    """

    def __init__(
        self,
        observation_space: gymnasium.spaces.Box,
        hidden_dim: int = 256,
        dropout: float = 0.1,
        n_masks: int = 500,
        head: str = "linear",
        spread: str = "std",
        learning_rate: float = 1e-3,
        batch_size: int = 128,
        n_epochs: int = 4,
        min_updates: int = 0,
        buffer_size: int = 200,
        mask_batch_size: int = 50_000,
        architecture: str = "auto",
        device: Union[str, torch.device] = "cpu",
        seed: Optional[int] = None,
    ) -> None:
        _check_box(observation_space)
        check_int("n_masks", n_masks, 1)
        check_int("batch_size", batch_size, 1)
        check_int("n_epochs", n_epochs, 1)
        check_int("min_updates", min_updates, 0)
        check_int("buffer_size", buffer_size, 1)
        check_int("mask_batch_size", mask_batch_size, 1)
        if not float(learning_rate) > 0:
            raise ValueError(f"learning_rate must be > 0, got {learning_rate!r}")
        if spread not in SPREADS:
            raise ValueError(f"spread must be one of {SPREADS}, got {spread!r}")
        if seed is not None:
            check_int("seed", seed, 0)

        self.observation_space = observation_space
        #: changes whenever the network's weights do (train, load): scores cached under another version are stale
        self.version = 0
        self._confidences: dict[bytes, float] = {}  # eq. 4 of each input met under ``_confidence_version``
        self._confidence_version = -1
        self.dropout = float(dropout)
        self.n_masks = int(n_masks)
        self.spread = spread
        self.learning_rate = float(learning_rate)
        self.batch_size = int(batch_size)
        self.n_epochs = int(n_epochs)
        self.min_updates = int(min_updates)
        self.buffer_size = int(buffer_size)
        self.mask_batch_size = int(mask_batch_size)
        self.device = get_device(device)

        self._init_random_state(seed)

        with self._torch_rng():
            self.network = PreferenceNetwork(observation_space, hidden_dim, dropout, head, architecture)
        self.network.to(self.device).eval()
        self.optimizer = torch.optim.Adam(self.network.parameters(), lr=self.learning_rate)

        # The preference buffer R (FIFO): raw observations as the env gives them.
        shape, dtype = observation_space.shape, observation_space.dtype
        self._states = np.zeros((self.buffer_size, *shape), dtype=dtype)
        self._goals1 = np.zeros((self.buffer_size, *shape), dtype=dtype)
        self._goals2 = np.zeros((self.buffer_size, *shape), dtype=dtype)
        self._labels = np.zeros(self.buffer_size, dtype=np.int64)
        self._targets = np.zeros((self.buffer_size, 2), dtype=np.float32)
        self._pos = 0
        self._size = 0

    # ------------------------------------------------------------------ randomness
    # ------------------------------------------------------------------ inputs
    def _batched(self, obs: Union[np.ndarray, torch.Tensor], name: str) -> torch.Tensor:
        """``obs`` as a batch ``(N, *obs_shape)`` where it is (a single observation gains a leading 1), checked."""
        obs = torch.as_tensor(np.asarray(obs) if not isinstance(obs, torch.Tensor) else obs)
        shape = tuple(self.observation_space.shape)
        if tuple(obs.shape) == shape:
            obs = obs.unsqueeze(0)
        if tuple(obs.shape[1:]) != shape:
            raise ValueError(f"{name} must have shape (N, {', '.join(map(str, shape))}), got {tuple(obs.shape)}")
        return obs

    def _to_tensor(self, obs: Union[np.ndarray, torch.Tensor], name: str) -> torch.Tensor:
        return self._batched(obs, name).to(self.device)

    def _pairs(
        self, states: Union[np.ndarray, torch.Tensor], goals: Union[np.ndarray, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor, int]:
        states_t, goals_t = self._to_tensor(states, "states"), self._to_tensor(goals, "goals")
        n_states, n_goals = states_t.shape[0], goals_t.shape[0]
        if n_states != n_goals and 1 not in (n_states, n_goals):
            raise ValueError(f"states and goals need the same length (or one of them 1), got {n_states} and {n_goals}")
        return states_t, goals_t, max(n_states, n_goals)

    # ------------------------------------------------------------------ inference
    def score(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """The preference bonus ``b = p_hat(s, g)`` (Algorithm 1, line 13), without dropout.

        :param states: raw states ``(N, *obs_shape)`` (or a single one, paired with every goal)
        :param goals: raw goal observations ``(N, *obs_shape)`` (or a single one)
        :return: scores, shape (N,)
        """
        states_t, goals_t, n = self._pairs(states, goals)
        self.network.eval()
        scores = torch.empty(n, device=self.device)
        with torch.no_grad():
            for start in range(0, n, self.mask_batch_size):
                end = min(n, start + self.mask_batch_size)
                s = states_t if states_t.shape[0] == 1 else states_t[start:end]
                g = goals_t if goals_t.shape[0] == 1 else goals_t[start:end]
                scores[start:end] = self.network(s, g).expand(end - start)
        return scores.cpu().numpy()

    def score_matrix(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Scores ``p_hat(s_i, g_j)`` of every state with every goal, shape ``(N, G)``, without dropout: what
        :meth:`score` gives on every pair, with each state and each goal read once (the meta-controller's bonus
        is centred over all sub-goals of each sampled state) and each distinct state scored once (a batch of
        layout-free descriptions repeats a few of them).

        :param states: raw states ``(N, *obs_shape)``
        :param goals: raw goal observations ``(G, *obs_shape)``
        """
        # a batch repeats states: each is scored once (found where the states are, before they go to the device)
        distinct, inverse = distinct_rows(self._batched(states, "states").cpu().numpy())
        states_t, goals_t = torch.as_tensor(distinct, device=self.device), self._to_tensor(goals, "goals")
        self.network.eval()
        rows = max(1, self.mask_batch_size // max(1, goals_t.shape[0]))
        with torch.no_grad():
            scores = [self.network.score_matrix(states_t[start : start + rows], goals_t)
                      for start in range(0, states_t.shape[0], rows)]
        return torch.cat(scores).cpu().numpy()[inverse]

    def confidence(self, states: np.ndarray, goals: np.ndarray, seconds: Optional[np.ndarray] = None) -> np.ndarray:
        """Predictive spread of the score over ``n_masks`` dropout masks (eq. 4); higher = less sure.

        ``c(s, g) = E_j [p_hat^{d_j}(s, g) - p]^2`` with ``p = E_j p_hat^{d_j}(s, g)``; with
        ``spread="std"`` its square root. Each input is repeated ``n_masks`` times along the batch
        dimension with dropout active, so each row draws its own mask, in chunks of at most
        ``mask_batch_size`` rows. Without dropout (or with a single mask) every mask gives the same
        score, so the spread is 0.

        With ``seconds``, the spread of the question's answer instead. Under mask ``d_j`` the answer "g over g2" has the
        Bradley-Terry probability (eq. 2) ``P_j = sigmoid(p_hat^{d_j}(s, g) - p_hat^{d_j}(s, g2))``, each mask applied
        to both scores; over the masks, ``P = E_j P_j``, and the answer (a Bernoulli) has the variance
        ``P (1 - P) = E_j [P_j - P]^2 + E_j P_j (1 - P_j)``: eq. 4 on the answer plus the answer's own spread under
        each mask. It lies in [0, 0.25] (``spread="std"``: [0, 0.5]) whatever the scores' scale; it is largest for a
        predictor that has not learnt to tell the two apart, and falls as it orders them surely (design decisions:
        Fetch asks where the answer to the question is unsure).

        :param states: raw states ``(N, *obs_shape)`` (or a single one, paired with every goal)
        :param goals: raw goal observations ``(N, *obs_shape)`` (or a single one)
        :param seconds: raw observations of the sub-goals each ``goal`` would be compared with, like ``goals``
        :return: confidences, shape (N,)
        """
        states_t, goals_t, n = self._pairs(states, goals)
        inputs = [states_t, goals_t]
        if seconds is not None:
            seconds_t = self._to_tensor(seconds, "seconds")
            if seconds_t.shape[0] not in (1, goals_t.shape[0]):
                raise ValueError(f"seconds must have the length of goals ({goals_t.shape[0]}) or 1, got "
                                 f"{seconds_t.shape[0]}")
            inputs.append(seconds_t)
        if self.dropout == 0.0 or self.n_masks < 2 or n == 0:
            return np.zeros(n, dtype=np.float32)
        # equal inputs have one spread: the masks run once on each distinct input, and once per version of the
        # network (an input met again before the predictor trains keeps the spread it was given)
        flat = [x.expand(n, *x.shape[1:]).reshape(n, -1) for x in inputs]
        distinct, inverse = torch.unique(torch.cat(flat, dim=1), dim=0, return_inverse=True)
        if self._confidence_version != self.version or len(self._confidences) > MAX_CACHED_CONFIDENCES:
            self._confidences, self._confidence_version = {}, self.version
        keys = [(len(inputs), row.tobytes()) for row in distinct.cpu().numpy()]
        new = [i for i, key in enumerate(keys) if key not in self._confidences]
        if new:
            rows, stops = distinct[new], np.cumsum([0] + [x.shape[1] for x in flat])
            parts = [rows[:, a:b].reshape(len(new), *x.shape[1:]) for a, b, x in zip(stops[:-1], stops[1:], inputs)]
            spreads = self._spread(*parts[:2], len(new)) if len(parts) == 2 else self._pair_spread(*parts, len(new))
            self._confidences.update(zip((keys[i] for i in new), spreads))
        return np.array([self._confidences[key] for key in keys], dtype=np.float32)[inverse.cpu().numpy()]

    def _spread(self, states_t: torch.Tensor, goals_t: torch.Tensor, n: int) -> np.ndarray:
        """Eq. 4 on tensors of ``n`` inputs (or one state / goal broadcast)."""
        p_dj = self._masked_scores(states_t, [goals_t], n)[0]  # p_hat^{d_j}(s, g)
        p = p_dj.mean(dim=1, keepdim=True)  # predictive posterior mean
        return self._spread_of(((p_dj - p) ** 2).mean(dim=1))  # eq. 4

    def _pair_spread(self, states_t: torch.Tensor, goals_t: torch.Tensor, seconds_t: torch.Tensor, n: int) -> np.ndarray:
        """The variance of the answer "g over g2", ``P (1 - P)`` with ``P`` the mean over the masks of ``P_j`` (eq. 2
        under each), or its square root (:meth:`confidence` with ``seconds``)."""
        first, second = self._masked_scores(states_t, [goals_t, seconds_t], n)
        p = torch.sigmoid(first - second).mean(dim=1)
        return self._spread_of(p * (1.0 - p))

    def _spread_of(self, c: torch.Tensor) -> np.ndarray:
        """A variance as the predictor's ``spread`` reads it: itself, or with ``spread="std"`` its square root."""
        if self.spread == "std":
            c = c.sqrt()  # design decisions: the predictor head
        return c.float().cpu().numpy()

    def _masked_scores(self, states_t: torch.Tensor, goal_sets: list[torch.Tensor], n: int) -> list[torch.Tensor]:
        """Scores ``(n, n_masks)`` of each state with each of its goals in every set, under ``n_masks`` dropout masks;
        with several sets, mask ``j`` of input ``i`` is the same for every set's goal (:func:`_shared_masks`)."""
        n_rows, sets = n * self.n_masks, len(goal_sets)
        predictions = torch.empty(sets, n_rows, device=self.device)
        chunk = max(1, self.mask_batch_size // sets)
        self.network.train()
        try:
            with torch.no_grad(), self._torch_rng(), _shared_masks(self.network, sets):
                for start in range(0, n_rows, chunk):
                    end = min(n_rows, start + chunk)
                    # row r is mask r % n_masks of input r // n_masks (repeat_interleave, chunk by chunk)
                    inputs = torch.arange(start, end, device=self.device) // self.n_masks
                    s = states_t[inputs if states_t.shape[0] > 1 else torch.zeros_like(inputs)]
                    g = torch.cat([goals[inputs if goals.shape[0] > 1 else torch.zeros_like(inputs)]
                                   for goals in goal_sets])
                    predictions[:, start:end] = self.network(s.repeat(sets, *[1] * (s.dim() - 1)), g).view(sets, -1)
        finally:
            self.network.eval()
        return [p.view(n, self.n_masks).double() for p in predictions]

    # ------------------------------------------------------------------ the buffer R
    def add(self, state: np.ndarray, goal1: np.ndarray, goal2: np.ndarray, label: Any) -> bool:
        """Store one labelled tuple ``(s, g1, g2, v)`` in the preference buffer ``R`` (FIFO).

        :param state: raw state observation ``(*obs_shape)``
        :param goal1: raw observation of the first sub-goal (the meta-controller's choice)
        :param goal2: raw observation of the second sub-goal
        :param label: a :class:`~sb3_hhp.preferences.types.Label` or anything ``Label.parse`` reads
        :return: True if stored; False for INCOMPARABLE, which is never trained on
        """
        label = Label.parse(label)
        if label == Label.INCOMPARABLE:
            return False
        # one-hot targets (v_0, v_1) of eq. 1; "equal" teaches (0.5, 0.5) (design decisions: EQUAL)
        target = {Label.FIRST: (1.0, 0.0), Label.SECOND: (0.0, 1.0), Label.EQUAL: (0.5, 0.5)}[label]
        shape = tuple(self.observation_space.shape)
        arrays = {"state": np.asarray(state), "goal1": np.asarray(goal1), "goal2": np.asarray(goal2)}
        for name, array in arrays.items():
            if array.shape != shape:
                raise ValueError(f"{name} must have the observation shape {shape}, got {array.shape}")
        self._states[self._pos] = arrays["state"]
        self._goals1[self._pos] = arrays["goal1"]
        self._goals2[self._pos] = arrays["goal2"]
        self._labels[self._pos] = int(label)
        self._targets[self._pos] = target
        self._pos = (self._pos + 1) % self.buffer_size
        self._size = min(self._size + 1, self.buffer_size)
        return True

    def __len__(self) -> int:
        return self._size

    # ------------------------------------------------------------------ training
    def loss(
        self, states: torch.Tensor, goals1: torch.Tensor, goals2: torch.Tensor, targets: torch.Tensor
    ) -> torch.Tensor:
        """Bradley-Terry cross-entropy (eq. 1, 2), with the network in its current mode.

        :param states: raw states ``(B, *obs_shape)``
        :param goals1: raw observations of the first sub-goals ``(B, *obs_shape)``
        :param goals2: raw observations of the second sub-goals ``(B, *obs_shape)``
        :param targets: (v_0, v_1) per tuple (B, 2): (1, 0) FIRST, (0, 1) SECOND, (0.5, 0.5) EQUAL
        :return: the mean loss over the batch (a scalar)
        """
        n = states.shape[0]
        if goals1.shape[0] != n or goals2.shape[0] != n or tuple(targets.shape) != (n, 2):
            raise ValueError(
                f"loss needs B states, goals1, goals2 and (B, 2) targets, got {tuple(states.shape)}, "
                f"{tuple(goals1.shape)}, {tuple(goals2.shape)} and {tuple(targets.shape)}"
            )
        scores = self.network(torch.cat([states, states]), torch.cat([goals1, goals2]))
        logits = torch.stack([scores[:n], scores[n:]], dim=1)  # p_hat(s, g1), p_hat(s, g2)
        log_p = F.log_softmax(logits, dim=1)  # eq. 2: log P[g1 > g2], log P[g2 > g1]
        return -(targets.to(log_p) * log_p).sum(dim=1).mean()  # eq. 1

    def _batch(self, indices: np.ndarray) -> tuple[torch.Tensor, ...]:
        return tuple(
            torch.as_tensor(array[indices], device=self.device)
            for array in (self._states, self._goals1, self._goals2, self._targets)
        )

    def train(self, n_epochs: Optional[int] = None) -> dict[str, float]:
        """Fit the predictor on the buffer ``R`` (Algorithm 1, line 27): minibatch Adam on eq. 1-2.

        :param n_epochs: passes over the buffer (>= 1); None uses ``self.n_epochs`` (paper: 4); more whole passes
            when they would make fewer than ``min_updates`` minibatch updates
        :return: ``loss``: mean training loss over the minibatches of this call; ``accuracy``:
            fraction of FIRST/SECOND tuples whose order the trained network (without dropout)
            predicts (nan without any). Both nan, and nothing trained, when the buffer is empty.
        """
        if n_epochs is None:
            n_epochs = self.n_epochs
        check_int("n_epochs", n_epochs, 1)
        if self._size == 0:
            return {"loss": math.nan, "accuracy": math.nan}
        per_epoch = math.ceil(self._size / self.batch_size)
        n_epochs = max(n_epochs, math.ceil(self.min_updates / per_epoch))  # at least min_updates minibatch updates
        self.version += 1
        total_loss, total_count = 0.0, 0
        self.network.train()
        try:
            with self._torch_rng():
                for _ in range(n_epochs):
                    order = self._np_rng.permutation(self._size)
                    for start in range(0, self._size, self.batch_size):
                        indices = order[start : start + self.batch_size]
                        loss = self.loss(*self._batch(indices))
                        self.optimizer.zero_grad()
                        loss.backward()
                        self.optimizer.step()
                        total_loss += loss.item() * len(indices)
                        total_count += len(indices)
        finally:
            self.network.eval()
        return {"loss": total_loss / total_count, "accuracy": self.accuracy()}

    def accuracy(self) -> float:
        """Fraction of the buffer's FIRST/SECOND tuples ordered right by the network without dropout (nan if none)."""
        labels = self._labels[: self._size]
        indices = np.flatnonzero((labels == Label.FIRST) | (labels == Label.SECOND))
        if len(indices) == 0:
            return math.nan
        states, goals1, goals2, _ = self._batch(indices)
        score1 = self.score(states, goals1)
        score2 = self.score(states, goals2)
        first = labels[indices] == Label.FIRST
        correct = np.where(first, score1 > score2, score2 > score1)
        return float(correct.mean())

    # ------------------------------------------------------------------ save / load
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly: network, optimizer, buffer and generator states.

        Holds only tensors, numbers, strings and dicts, so ``torch.load(..., weights_only=True)`` reads it.
        """
        size = self._size
        return {
            "network": copy.deepcopy(self.network.state_dict()),
            "optimizer": copy.deepcopy(self.optimizer.state_dict()),
            "buffer": {
                "states": torch.from_numpy(self._states.copy()),
                "goals1": torch.from_numpy(self._goals1.copy()),
                "goals2": torch.from_numpy(self._goals2.copy()),
                "labels": torch.from_numpy(self._labels.copy()),
                "targets": torch.from_numpy(self._targets.copy()),
                "pos": self._pos,
                "size": size,
            },
            **self._random_state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` saved (the predictor must be built with the same space and sizes)."""
        buffer = state["buffer"]
        if tuple(buffer["states"].shape) != tuple(self._states.shape):
            raise ValueError(
                f"The saved buffer holds {tuple(buffer['states'].shape)}, this predictor {tuple(self._states.shape)}: "
                "build it with the same observation space and buffer_size"
            )
        self.network.load_state_dict(state["network"])
        self.version += 1
        self.optimizer.load_state_dict(state["optimizer"])
        self._states[:] = buffer["states"].numpy()
        self._goals1[:] = buffer["goals1"].numpy()
        self._goals2[:] = buffer["goals2"].numpy()
        self._labels[:] = buffer["labels"].numpy()
        self._targets[:] = buffer["targets"].numpy()
        self._pos = int(buffer["pos"])
        self._size = int(buffer["size"])
        self._load_random_state_dict(state)
        self.network.eval()
