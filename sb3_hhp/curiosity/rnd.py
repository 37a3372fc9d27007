"""Random Network Distillation (RND): the intrinsic reward (eq. 7), the memory Omega and novelty progress (eq. 8)."""

import copy
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.torch_layers import NatureCNN
from torch import nn

from sb3_hhp.arrays import distinct_rows

#: Smallest spatial side an image needs for the Nature conv stack (8x8/4, 4x4/2, 3x3/1) to leave one pixel.
MIN_IMAGE_SIDE = 36
#: Added to the observation variance before the square root, so that constant features do not divide by 0.
OBS_EPSILON = 1e-8
#: Largest number of states pushed through a network at once (bounds memory for long episodes of images).
MAX_CHUNK = 4096


@dataclass
class RNDSnapshot:
    """
    One earlier novelty model kept in the memory Omega: the predictor and the observation statistics
    it was trained with, frozen when it was stored. The target network never changes, so it is shared.

    :param predictor: frozen deep copy of the predictor network f_hat(. | theta_old)
    :param obs_rms: copy of the observation normalisation statistics at that time
    :param num_steps: value of ``RND.num_steps`` when the snapshot was taken (environment steps)
    """

    predictor: nn.Module
    obs_rms: RunningMeanStd
    num_steps: int


def _rms_to_dict(rms: RunningMeanStd) -> dict[str, Any]:
    # Tensors rather than numpy arrays, so that ``th.load(..., weights_only=True)`` accepts the state
    return {"mean": th.as_tensor(rms.mean).clone(), "var": th.as_tensor(rms.var).clone(), "count": float(rms.count)}


def _rms_from_dict(state: dict[str, Any]) -> RunningMeanStd:
    mean, var = (th.as_tensor(state[key]).cpu().numpy().astype(np.float64) for key in ("mean", "var"))
    rms = RunningMeanStd(shape=mean.shape)
    rms.mean, rms.var, rms.count = mean, var, float(state["count"])
    return rms


def _orthogonal_init(module: nn.Module) -> None:
    # The RND paper's initialisation: orthogonal weights (gain sqrt(2)), zero biases
    if isinstance(module, (nn.Linear, nn.Conv2d)):
        nn.init.orthogonal_(module.weight, gain=np.sqrt(2))
        nn.init.zeros_(module.bias)


class RND:
    """
    Random Network Distillation (Burda et al., 2018) as used by HhP (section 4.2), shared by every subpolicy.

    A fixed, randomly initialised target network ``f`` maps a normalised observation to an embedding; a predictor
    ``f_hat`` is trained to reproduce it. The intrinsic reward is the prediction error (eq. 7):

    ``r^i_t = ||f_hat(s_{t+1}) - f(s_{t+1})||^2``

    computed on observations normalised by a running mean and standard deviation and clipped to
    ``[-obs_clip, obs_clip]``, then divided by the running standard deviation of the discounted (non-episodic)
    intrinsic returns (RND's "reward forward filter" with discount ``gamma``), so that its scale stays stable
    while the predictor learns.

    Every ``refresh_interval`` (T) environment steps a frozen copy of the predictor and of the observation
    statistics is pushed into the memory Omega, which keeps the ``memory_size`` (M) newest ones. The novelty
    progress of a state (eq. 8) is

    ``rho(s) = 1/|Omega| * sum_{theta_old in Omega} [ err_theta(s) - err_theta_old(s) ]``

    with ``err_theta(s) = ||f_hat(s | theta) - f(s)||^2`` the raw (not reward-normalised) prediction error of the
    current model and ``err_theta_old`` that of an earlier one, each on the observation normalised with its own
    statistics. ``rho`` is 0 while Omega is empty.

    Vector observations use an MLP; images (``uint8`` in ``[0, 255]``, both spatial sides at least 36 pixels,
    channel-first or channel-last) use the Nature DQN conv stack (32/64/64 filters), as in the RND paper.
    Observation statistics are only updated by :meth:`update`; before the first update observations are used
    as they come (mean 0, variance 1), clipped.

    :param observation_space: the environment's observation space (a ``gymnasium.spaces.Box``)
    :param embedding_dim: size ``k`` of the embeddings ``f(s), f_hat(s)`` (>= 1)
    :param hidden_dim: units of the hidden layers, and of the conv features for images (>= 1)
    :param learning_rate: Adam learning rate of the predictor (> 0)
    :param memory_size: M, number of earlier models kept in Omega (>= 1)
    :param refresh_interval: T, environment steps between two snapshots pushed into Omega (>= 1)
    :param gamma: discount of the intrinsic returns whose running std normalises the reward, in (0, 1]
    :param obs_clip: normalised observations are clipped to ``[-obs_clip, obs_clip]`` (> 0)
    :param batch_size: minibatch size of the predictor updates (>= 1)
    :param device: torch device of the networks
    :param seed: seed of the network initialisation and of the minibatch shuffling; ``None`` for a random one
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        embedding_dim: int = 64,
        hidden_dim: int = 256,
        learning_rate: float = 1e-3,
        memory_size: int = 4,
        refresh_interval: int = 15_000,
        gamma: float = 0.99,
        obs_clip: float = 5.0,
        batch_size: int = 128,
        device: str | th.device = "cpu",
        seed: int | None = None,
    ) -> None:
        if not isinstance(observation_space, spaces.Box):
            raise ValueError(
                "RND supports gymnasium.spaces.Box observation spaces only (vectors or uint8 images), "
                f"got {observation_space}; flatten or select the observation first"
            )
        for name, value in (
            ("embedding_dim", embedding_dim),
            ("hidden_dim", hidden_dim),
            ("memory_size", memory_size),
            ("refresh_interval", refresh_interval),
            ("batch_size", batch_size),
        ):
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value}")
        if not learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {learning_rate}")
        if not 0 < gamma <= 1:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}")
        if not obs_clip > 0:
            raise ValueError(f"obs_clip must be > 0, got {obs_clip}")

        self.observation_space = observation_space
        self.embedding_dim = int(embedding_dim)
        self.hidden_dim = int(hidden_dim)
        self.learning_rate = float(learning_rate)
        self.memory_size = int(memory_size)
        self.refresh_interval = int(refresh_interval)
        self.gamma = float(gamma)
        self.obs_clip = float(obs_clip)
        self.batch_size = int(batch_size)
        self.device = th.device(device)
        self.obs_shape: tuple[int, ...] = tuple(observation_space.shape)

        self.is_image = is_image_space(observation_space, check_channels=False)
        self.channels_last = False
        if self.is_image:
            self.channels_last = not is_image_space_channels_first(observation_space)
            spatial = self.obs_shape[:2] if self.channels_last else self.obs_shape[1:]
            self.is_image = min(spatial) >= MIN_IMAGE_SIDE

        self._generator = th.Generator()
        if seed is None:
            self._generator.seed()
        else:
            self._generator.manual_seed(int(seed))
        with th.random.fork_rng(devices=[]):
            th.manual_seed(int(th.randint(0, 2**62, (1,), generator=self._generator)))
            self.target = self._build_network(predictor=False).to(self.device)
            self.predictor = self._build_network(predictor=True).to(self.device)
        self.target.requires_grad_(False)
        self.target.eval()
        self.optimizer = th.optim.Adam(self.predictor.parameters(), lr=self.learning_rate)

        self.obs_rms = RunningMeanStd(shape=self.obs_shape)
        # Forward filter: running discounted sum of raw intrinsic rewards, and the statistics of those returns
        self.reward_filter = 0.0
        self.reward_rms = RunningMeanStd(shape=())
        self.num_steps = 0
        self._memory: deque[RNDSnapshot] = deque(maxlen=self.memory_size)

    # ------------------------------------------------------------------ networks

    def _build_network(self, predictor: bool) -> nn.Module:
        """
        The target ends in one linear layer after the body; the predictor, as in the RND paper, has two more
        hidden layers so that it can fit the target.
        """
        if self.is_image:
            c_first_shape = (self.obs_shape[2], *self.obs_shape[:2]) if self.channels_last else self.obs_shape
            # Only used for its shape: normalised inputs are floats, hence normalized_image=True
            space = spaces.Box(low=-self.obs_clip, high=self.obs_clip, shape=c_first_shape, dtype=np.float32)
            body: nn.Module = NatureCNN(space, features_dim=self.hidden_dim, normalized_image=True)
        else:
            n_input = int(np.prod(self.obs_shape))
            body = nn.Sequential(
                nn.Flatten(),
                nn.Linear(n_input, self.hidden_dim),
                nn.ReLU(),
                nn.Linear(self.hidden_dim, self.hidden_dim),
                nn.ReLU(),
            )
        layers: list[nn.Module] = [body]
        if predictor:
            layers += [nn.Linear(self.hidden_dim, self.hidden_dim), nn.ReLU()]
        layers.append(nn.Linear(self.hidden_dim, self.embedding_dim))
        net = nn.Sequential(*layers)
        net.apply(_orthogonal_init)
        return net

    # ------------------------------------------------------------------ helpers

    def _as_batch(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs)
        if obs.shape == self.obs_shape:
            obs = obs[None]
        if obs.shape[1:] != self.obs_shape:
            raise ValueError(f"Expected observations of shape (N, *{self.obs_shape}), got {obs.shape}")
        return obs

    def normalize_obs(self, obs: np.ndarray, obs_rms: RunningMeanStd | None = None) -> th.Tensor:
        """
        ``clip((obs - mean) / sqrt(var + 1e-8), -obs_clip, obs_clip)`` as a float tensor on the device, images
        transposed to channel-first.

        :param obs: batch of observations, shape ``(N, *obs_shape)``
        :param obs_rms: statistics to use; the current ones when ``None``
        :return: network input, shape ``(N, *obs_shape)`` (``(N, C, H, W)`` for images)
        """
        rms = self.obs_rms if obs_rms is None else obs_rms
        normalized = np.clip((obs - rms.mean) / np.sqrt(rms.var + OBS_EPSILON), -self.obs_clip, self.obs_clip)
        tensor = th.as_tensor(normalized, dtype=th.float32, device=self.device)
        if self.is_image and self.channels_last:
            tensor = tensor.permute(0, 3, 1, 2)
        return tensor

    def _errors(self, obs: np.ndarray, predictor: nn.Module, obs_rms: RunningMeanStd) -> np.ndarray:
        # ||f_hat(s) - f(s)||^2 for a batch, one forward pass per network (chunked only for very large batches)
        errors = []
        with th.no_grad():
            for start in range(0, len(obs), MAX_CHUNK):
                x = self.normalize_obs(obs[start : start + MAX_CHUNK], obs_rms)
                errors.append((predictor(x) - self.target(x)).pow(2).sum(dim=1))
        return th.cat(errors).cpu().numpy() if errors else np.zeros(0, np.float32)

    # ------------------------------------------------------------------ eq. 7

    def prediction_error(self, obs: np.ndarray) -> np.ndarray:
        """
        Raw prediction error ``||f_hat(s) - f(s)||^2`` of the current model, without reward normalisation.
        Changes no statistics.

        :param obs: observations, shape ``(N, *obs_shape)`` (a single unbatched observation is accepted)
        :return: errors, shape ``(N,)``, float32
        """
        return self._errors(self._as_batch(obs), self.predictor, self.obs_rms)

    def intrinsic_reward(self, next_obs: np.ndarray) -> np.ndarray:
        """
        Intrinsic reward of eq. 7, ``r^i = ||f_hat(s') - f(s')||^2 / std(R^i)``, where ``R^i`` are the
        discounted intrinsic returns of the forward filter ``R_t = gamma * R_{t-1} + err_t``. The rows of
        ``next_obs`` are taken as consecutive steps of one stream: the filter runs over them in order, the
        running statistics of the returns are updated with the N new returns, then every error is divided by
        the updated std. While fewer than two returns have ever been seen their std is undefined and the raw
        errors are returned.

        :param next_obs: next observations ``s_{t+1}``, shape ``(N, *obs_shape)``
        :return: intrinsic rewards, shape ``(N,)``, float32
        """
        errors = self.prediction_error(next_obs)
        returns = np.empty(len(errors), np.float64)
        discounted = self.reward_filter
        for i, error in enumerate(errors):
            discounted = self.gamma * discounted + float(error)
            returns[i] = discounted
        self.reward_filter = discounted
        if len(returns) > 0:
            self.reward_rms.update(returns)
        if self.reward_rms.count < 2:
            return errors
        std = max(float(np.sqrt(self.reward_rms.var)), OBS_EPSILON)
        return (errors / std).astype(np.float32)  # eq. 7, normalised

    # ------------------------------------------------------------------ training

    def update(self, obs: np.ndarray, n_epochs: int = 1) -> float:
        """
        Update the observation statistics with ``obs``, then train the predictor on shuffled minibatches of
        ``batch_size`` observations for ``n_epochs`` passes, minimising the mean of ``||f_hat(s) - f(s)||^2``.

        :param obs: observations (e.g. the states of one episode), shape ``(N, *obs_shape)``, N >= 1
        :param n_epochs: passes over ``obs`` (>= 1)
        :return: mean loss over the minibatches
        """
        obs = self._as_batch(obs)
        if len(obs) == 0:
            raise ValueError("update() needs at least one observation, got an empty batch")
        if int(n_epochs) != n_epochs or n_epochs < 1:
            raise ValueError(f"n_epochs must be an integer >= 1, got {n_epochs}")
        self.obs_rms.update(obs.astype(np.float64))
        inputs = self.normalize_obs(obs)
        self.predictor.train()
        losses = []
        for _ in range(int(n_epochs)):
            permutation = th.randperm(len(inputs), generator=self._generator).to(self.device)
            for start in range(0, len(inputs), self.batch_size):
                batch = inputs[permutation[start : start + self.batch_size]]
                with th.no_grad():
                    target = self.target(batch)
                loss = (self.predictor(batch) - target).pow(2).sum(dim=1).mean()
                self.optimizer.zero_grad()
                loss.backward()
                self.optimizer.step()
                losses.append(loss.item())
        return float(np.mean(losses))

    # ------------------------------------------------------------------ Omega and eq. 8

    @property
    def memory(self) -> list[RNDSnapshot]:
        """The snapshots in Omega, oldest first (at most ``memory_size``)."""
        return list(self._memory)

    def _snapshot(self) -> RNDSnapshot:
        predictor = copy.deepcopy(self.predictor)
        predictor.requires_grad_(False)
        predictor.eval()
        return RNDSnapshot(predictor=predictor, obs_rms=self.obs_rms.copy(), num_steps=self.num_steps)

    def on_steps(self, n_steps: int) -> None:
        """
        Advance the environment-step counter by ``n_steps``; each time it crosses a multiple of
        ``refresh_interval`` (T), push a frozen copy of the current model into Omega, dropping the oldest
        beyond ``memory_size`` (M).

        :param n_steps: primitive environment steps taken since the last call (>= 0)
        """
        if int(n_steps) != n_steps or n_steps < 0:
            raise ValueError(f"n_steps must be an integer >= 0, got {n_steps}")
        before = self.num_steps
        self.num_steps += int(n_steps)
        n_refresh = self.num_steps // self.refresh_interval - before // self.refresh_interval
        # Crossing several multiples at once stores the (same) current model once per crossing, at most M times
        for _ in range(min(n_refresh, self.memory_size)):
            self._memory.append(self._snapshot())

    def novelty_progress(self, obs: np.ndarray) -> np.ndarray:
        """
        Novelty progress of eq. 8, ``rho(s) = 1/|Omega| * sum_{old} [err_current(s) - err_old(s)]``, with raw
        prediction errors; zeros when Omega is empty. Changes no statistics.

        :param obs: states, shape ``(N, *obs_shape)``
        :return: novelty progress, shape ``(N,)``, float32
        """
        obs = self._as_batch(obs)
        if not self._memory:
            return np.zeros(len(obs), np.float32)
        # an episode revisits states (a random DoorKey-16x16 episode: 548 distinct of 2,561): each distinct one once
        distinct, inverse = distinct_rows(obs)
        current = self._errors(distinct, self.predictor, self.obs_rms)
        old = np.mean([self._errors(distinct, snap.predictor, snap.obs_rms) for snap in self._memory], axis=0)
        return (current - old).astype(np.float32)[inverse]  # eq. 8

    # ------------------------------------------------------------------ save / load

    def state_dict(self) -> dict[str, Any]:
        """
        Everything needed to resume exactly: networks, optimizer, observation and reward statistics, forward
        filter, step counter, shuffling generator and Omega. Holds only tensors and plain Python data, so it
        can be written with ``th.save`` and read back with ``th.load(..., weights_only=True)``.

        :return: the state
        """
        return {
            "target": copy.deepcopy(self.target.state_dict()),
            "predictor": copy.deepcopy(self.predictor.state_dict()),
            "optimizer": copy.deepcopy(self.optimizer.state_dict()),
            "obs_rms": _rms_to_dict(self.obs_rms),
            "reward_rms": _rms_to_dict(self.reward_rms),
            "reward_filter": float(self.reward_filter),
            "num_steps": int(self.num_steps),
            "generator": self._generator.get_state(),
            "memory": [
                {
                    "predictor": copy.deepcopy(snap.predictor.state_dict()),
                    "obs_rms": _rms_to_dict(snap.obs_rms),
                    "num_steps": int(snap.num_steps),
                }
                for snap in self._memory
            ],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """
        Restore a state produced by :meth:`state_dict` of an ``RND`` built with the same observation space and
        network sizes.

        :param state: the state
        """
        self.target.load_state_dict(state["target"])
        self.predictor.load_state_dict(state["predictor"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.obs_rms = _rms_from_dict(state["obs_rms"])
        self.reward_rms = _rms_from_dict(state["reward_rms"])
        self.reward_filter = float(state["reward_filter"])
        self.num_steps = int(state["num_steps"])
        self._generator.set_state(state["generator"])
        self._memory.clear()
        for snap_state in state["memory"][-self.memory_size :]:
            with th.random.fork_rng(devices=[]):  # the weights are overwritten: leave the global RNG untouched
                predictor = self._build_network(predictor=True).to(self.device)
            predictor.load_state_dict(snap_state["predictor"])
            predictor.requires_grad_(False)
            predictor.eval()
            obs_rms = _rms_from_dict(snap_state["obs_rms"])
            self._memory.append(RNDSnapshot(predictor=predictor, obs_rms=obs_rms, num_steps=int(snap_state["num_steps"])))
