"""The sub-goal learners: one Q-function per sub-goal, all of them stacked and updated in one call.

Each sub-goal ``g`` has a Double DQN learner (section 5.1: "DDQN with prioritized experience replay"): an
SB3 ``QNetwork`` of its own, with its own target network, Adam moments, epsilon and step counters. Their
parameters live stacked along a leading sub-goal axis, and one call of :meth:`StackedDQN.train` updates every
due sub-goal together (batched matrix products for MLPs; a CNN's learners one after the other), on batches that
one :class:`~sb3_hhp.hierarchy.replay.SharedReplay` draws and relabels for each of them. So neither the memory
nor the Python overhead of a primitive step grows with the number of sub-goals. :meth:`StackedDQN.policy`
gives any sub-goal's learner back as an SB3 ``DQNPolicy``.

What the networks read of an observation (``view``, ``overview``, ``one_hot``) is :mod:`sb3_hhp.hierarchy.encoders`;
the Adam step of the rows, :mod:`sb3_hhp.hierarchy.row_adam`; the keyword arguments and their defaults,
:mod:`sb3_hhp.hierarchy.learner_kwargs`; the learners as heads of one network (:class:`.SharedHeadsDQN`),
:mod:`sb3_hhp.hierarchy.heads`.
"""

from collections import deque
from collections.abc import Callable, Hashable
from typing import Any, Optional, Sequence

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.dqn.policies import CnnPolicy, DQNPolicy, MlpPolicy
from torch.func import functional_call
from torch.nn import functional as F

from sb3_hhp.dqn.buffers import buffer_state, load_buffer_state
from sb3_hhp.hierarchy.encoders import GridInput, Indicators
from sb3_hhp.hierarchy.learner_kwargs import (  # noqa: F401  (the kwargs re-exported: sb3_hhp.hhp imports them from here)
    DEFAULT_SUBPOLICY_KWARGS, PAPER_SUBPOLICY_KWARGS, check_learners_state, check_optional_count, check_range,
    checked_subpolicy_kwargs, default_subpolicy_kwargs, lower_bound_option,
)
from sb3_hhp.hierarchy.replay import SharedReplay
from sb3_hhp.hierarchy.row_adam import RowAdam


def _mlp_layers(q_net: th.nn.Module) -> Optional[list[tuple[str, Any]]]:
    """The layers of an SB3 ``QNetwork`` that is a flattened input through Linear layers and parameter-free
    activations, as ``("linear", parameter prefix)`` / ``("activation", module)``; None for any other network."""
    if not isinstance(q_net.features_extractor, FlattenExtractor):
        return None
    layers: list[tuple[str, Any]] = []
    for name, module in q_net.q_net.named_children():
        if isinstance(module, th.nn.Linear) and module.bias is not None:
            layers.append(("linear", f"q_net.{name}"))
        elif not any(True for _ in module.parameters()):
            layers.append(("activation", module))
        else:
            return None
    return layers


class StackedDQN:
    """Every sub-goal's Double DQN learner, stacked, over one shared replay of primitive transitions.

    :param observation_space: the primitive observation space (Box)
    :param action_space: the primitive action space (Discrete)
    :param achieved: ``done(s, g)`` from two sub-goal keys
    :param policy: "MlpPolicy" or "CnnPolicy" (SB3's DQN policies; the Q-network of one sub-goal)
    :param subpolicy_kwargs: SB3 DQN's keyword arguments for every sub-goal's learner (over the paper's defaults);
        ``buffer_size`` is the shared replay's size in primitive transitions, ``train_freq`` and
        ``target_update_interval`` count a sub-goal's learning ticks (its own steps, or every primitive step with
        ``train_shared``), ``replay_buffer_kwargs=dict(off_policy_lower_bound=True)`` adds the lower bound
    :param alpha: weight of the intrinsic reward in eq. 6
    :param exploration_steps: own steps over which a sub-goal's epsilon decays to its final value
    :param exploration_run_steps: with ``train_shared``, a second clock: a sub-goal's epsilon also decays over the
        primitive steps (of all envs) since it was added, and the learner explores at the lower of the two rates. A
        sub-goal the meta-controller seldom chooses (the last walks of a long plan) then stops acting at random once
        the run has gone on that long, its greedy policy having learnt from every learner's steps; None: own steps only
    :param share_experience: every sub-goal learns from every transition (relabelled); False: only from its own
    :param train_shared: every sub-goal takes a learning tick on every primitive step, not only while it acts
    :param n_envs: number of env streams stepped together
    :param device: torch device
    :param seed: seed of the initialisations (sub-goal ``g`` gets ``seed + g``), exploration and draws
    :param max_updates: most sub-goal learners updated in one learning round: the sub-goals some env pursues now
        first, then those that waited longest for an update; the others skip that round. Bounds the cost of a step
        as sub-goals accumulate. None: every sub-goal whose update is due
    :param grouped_rounds: the learning rounds due at one step of the envs (8 envs and ``train_freq`` 4: two) in one
        grouped call: their batches drawn together and every gradient computed from the parameters as they were
        before the step, then applied round after round, each an Adam step of its own. A later round's gradient is
        thus one update old. False: one call per round, each from the parameters the round before left
    :param action_mask: the primitive actions a learner may take in each state of a batch (the goal space's
        :meth:`~sb3_hhp.goals.base.GoalSpace.action_mask`), applied to acting, exploring and the max of the targets;
        None: every action
    :param view: the learners read only the central ``view`` x ``view`` cells of an ``(H, W, C)`` observation (on
        MiniGrid's egocentric canvas: the cells around the agent), odd; ``"inner"``: every cell but the outermost ring
        (on MiniGrid's canvas it only ever shows the grid's border wall, so the learners lose nothing and their first
        layer reads a quarter fewer inputs); the replay keeps whole observations (the goal space reads them). None: the
        whole observation
    :param overview: the learners also read a coarse copy of the whole observation (:class:`.Overview`): blocks of
        ``overview`` x ``overview`` cells, each as its most salient cell, so that a learner with a small ``view`` sees
        in which direction a far object lies; odd, >= 3; MlpPolicy only. None: no overview
    :param carry_relabel: the share of a drawn batch, for a sub-goal that carries an object, replaced where possible
        by steps taken with empty hands as they would have gone carrying it (``counterfactual``, the goal space's
        :meth:`~sb3_hhp.goals.base.GoalSpace.carried_counterfactual`), as one-step returns; 0: none
    :param one_hot: the learners read each channel ``c`` of ``(H, W, C)`` uint8 codes (after ``view``) as one-hot
        indicators of the codes ``one_hot[c]`` (a count n: codes 0 to n - 1; a list: those codes; 0 or ``[]``: the
        channel left out) instead of its code as a number; MiniGrid's canvas: ``[11, 6, 3]`` (every object, colour and
        state); ``[[2, 4, 5, 8], [], [1, 2]]``: walls, doors, keys, goal squares, closed and locked (DoorKey). A ReLU
        unit tells "a door here" from one input, where the codes put the door (4) between the wall (2) and the key
        (5). Each indicator is an input of the first layer, which costs that many times more. None: the codes as numbers
    :param input_codes: what the learners read in place of observations, as a function of them, before ``view``,
        ``overview`` and ``one_hot`` (:class:`.GridInput`): the goal space's
        :meth:`~sb3_hhp.goals.base.GoalSpace.learner_codes` (MiniGrid with relative colours: whether each cell has the
        carried object's colour). None: the observations
    :param target_range: ``(low, high)``: every TD target clipped to the returns the learners' rewards allow, as HER
        clips its targets (Andrychowicz et al., 2017). With ``alpha`` 0, eq. 5's rewards (+1 on reaching the sub-goal,
        -1 on ending without it, else 0) put every return in ``[-1, 1]``; noisy values above 1 then no longer feed
        themselves through the max of the targets, under which the step that reaches a sub-goal (a reward of exactly
        1) can lose to going on. None: unclipped
    """

    #: one priority tree for all sub-goals (the heads' shared batch) instead of one per sub-goal
    _shared_priorities = False
    #: with ``one_hot``, the shared replay keeps the places of the set indicators of what it stores (:meth:`_encoded`),
    #: and the written-out MLP update of :meth:`train_rounds` reads them (:class:`.Indicators`: the first layer's
    #: product as sums of a few dozen weight columns) instead of encoding every drawn state densely
    _encoded_replay = True

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Discrete,
        achieved: Callable[[Hashable, Hashable], bool],
        policy: str = "MlpPolicy",
        subpolicy_kwargs: Optional[dict[str, Any]] = None,
        alpha: float = 0.5,
        exploration_steps: int = 5_000,
        exploration_run_steps: Optional[int] = None,
        share_experience: bool = True,
        train_shared: bool = False,
        n_envs: int = 1,
        device: th.device | str = "cpu",
        seed: Optional[int] = None,
        max_updates: Optional[int] = None,
        grouped_rounds: bool = False,
        action_mask: Optional[Callable[[np.ndarray], Optional[np.ndarray]]] = None,
        view: Optional[int] = None,
        carry_relabel: float = 0.0,
        counterfactual: Optional[Callable] = None,
        one_hot: Optional[Sequence[int]] = None,
        overview: Optional[int] = None,
        target_range: Optional[Sequence[float]] = None,
        input_codes: Optional[Callable[[np.ndarray], np.ndarray]] = None,
    ) -> None:
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"StackedDQN needs a Discrete action space, got {action_space}")
        self.target_range = check_range(target_range)
        check_optional_count("max_updates", max_updates)
        self.max_updates = None if max_updates is None else int(max_updates)
        self.action_mask = action_mask  # the goal space's (GoalSpace.action_mask): actions no learner takes in a state
        self.grouped_rounds = bool(grouped_rounds)
        self.rounds = 0  # learning rounds so far
        if exploration_steps < 1:
            raise ValueError(f"exploration_steps must be >= 1, got {exploration_steps}")
        check_optional_count("exploration_run_steps", exploration_run_steps)
        if exploration_run_steps is not None and not (train_shared or self._shared_priorities):
            raise ValueError("exploration_run_steps (subgoal_learner_kwargs) counts the steps every learner learns "
                             "from: it needs train_shared=True (without it a learner learns only from its own steps, "
                             "and its exploration is all it has)")
        kw = checked_subpolicy_kwargs(subpolicy_kwargs)
        self.observation_space, self.action_space = observation_space, action_space
        self.view, self.overview = view, overview
        self.input = GridInput(observation_space, view, overview, one_hot, input_codes)  # what the networks read
        self._overview, self._one_hot = self.input.overview, self.input.one_hot
        self.kwargs = kw
        self.lr, self.gamma = float(kw["learning_rate"]), float(kw["gamma"])
        self.batch_size, self.learning_starts = int(kw["batch_size"]), int(kw["learning_starts"])
        self.train_freq, self.gradient_steps = int(kw["train_freq"]), int(kw["gradient_steps"])
        self.target_update_interval = int(kw["target_update_interval"])
        self.eps_initial, self.eps_final = float(kw["exploration_initial_eps"]), float(kw["exploration_final_eps"])
        self.max_grad_norm, self.double_q = float(kw["max_grad_norm"]), bool(kw["double_q"])
        self.exploration_steps, self.train_shared = int(exploration_steps), bool(train_shared)
        self.exploration_run_steps = None if exploration_run_steps is None else int(exploration_run_steps)
        self.device = th.device(device)
        self.seed = seed
        lower_bound = lower_bound_option(kw, subpolicy_kwargs)
        self.buffer_size = int(kw["buffer_size"])
        self._replay_kwargs = dict(
            observation_space=observation_space, action_space=action_space,
            achieved=achieved, alpha=alpha, gamma=self.gamma, n_steps=int(kw["n_steps"]), lower_bound=lower_bound,
            share_experience=share_experience, shared_priorities=self._shared_priorities,
            priority_alpha=kw["prioritized_replay_alpha"], priority_beta=kw["prioritized_replay_beta"],
            priority_eps=kw["prioritized_replay_eps"], carry_relabel=carry_relabel, counterfactual=counterfactual, seed=seed,
        )
        # SB3's CNN reads channel-first images: the env's channel-last frames are turned when they reach a network
        net_space = self.input.space
        self._transpose = is_image_space(net_space) and not is_image_space_channels_first(net_space)
        if self._transpose:
            h, w, c = net_space.shape
            net_space = spaces.Box(0, 255, (c, h, w), net_space.dtype)
        policy_class = {"MlpPolicy": MlpPolicy, "CnnPolicy": CnnPolicy}.get(policy) if isinstance(policy, str) else policy
        if policy_class is None:
            raise ValueError(f"Sub-goal learners use 'MlpPolicy' or 'CnnPolicy', got {policy!r}")
        if self._overview is not None and issubclass(policy_class, CnnPolicy):
            raise ValueError(f"overview (subgoal_learner_kwargs) adds cells that are not an image: it needs the "
                             f"sub-goal learners' MlpPolicy, got {policy!r}; leave overview out or use MlpPolicy")
        policy_kwargs = {k: v for k, v in dict(kw["policy_kwargs"] or {}).items() if k != "optimizer_kwargs"}
        # an SB3 policy of the learners' shape on their device: the template, fresh weights, and policy(g)'s views
        self._make_policy = lambda: policy_class(net_space, action_space, lambda _: self.lr, **policy_kwargs).to(self.device)
        self._template = self._make_policy().q_net
        self._normalize_images = self._template.normalize_images
        self._scale_images = is_image_space(net_space) and self._normalize_images  # as SB3's preprocess_obs scales
        named = list(self._template.named_parameters())
        self._names = [name for name, _ in named]
        self._shapes = [tuple(value.shape) for _, value in named]
        self._layers = _mlp_layers(self._template)  # a plain MLP: batched matrix products (else _each)
        # a ReLU MLP (SB3's default): its backward pass is written out, no autograd graph per update
        self._relu_mlp = self._layers is not None and all(
            kind == "linear" or isinstance(item, th.nn.ReLU) for kind, item in self._layers)
        self._keeps_encoded = (self._encoded_replay and self._one_hot is not None and self._relu_mlp and not self._transpose
                               and self._names[0] == self._layers[0][1] + ".weight")
        self._layout()
        self.replay = self._make_replay(n_envs)
        # every sub-goal's parameters as one row of a (capacity, P) tensor: the update is one Adam step on one tensor
        self.params = th.zeros((0, self._row_size), device=self.device)
        self.target = th.zeros_like(self.params)
        self._views: dict[Any, Any] = {}  # views of the stacked tensors (_unflatten)
        self._optimizer: Optional[RowAdam] = None  # Adam over the rows of params (_adam), made when first needed
        self.exp_avg = th.zeros_like(self.params)
        self.exp_avg_sq = th.zeros_like(self.params)
        self.adam_steps = th.zeros(0, device=self.device)  # each sub-goal's Adam step count (float, as torch's Adam keeps it)
        self._capacity = 0
        self.own_steps = np.zeros(0, dtype=np.int64)  # steps each sub-goal acted
        self.ticks = np.zeros(0, dtype=np.int64)  # learning ticks
        self.n_updates = np.zeros(0, dtype=np.int64)
        self.last_round = np.zeros(0, dtype=np.int64)  # the learning round of each sub-goal's last update
        self.recent: list[deque] = []
        self.successes: list[int] = []
        self.attempts: list[int] = []
        self._rng = np.random.default_rng(seed)
        self.last_loss = float("nan")

    # ------------------------------------------------------------------ the set
    def __len__(self) -> int:
        return len(self.recent)

    def _layout(self) -> None:
        """Where each parameter lies in a learner's row of the stacked tensors (:attr:`params`, :attr:`target`, Adam's
        moments): SB3's parameters in their order, each flattened, except that with the replay's kept places
        (:attr:`_keeps_encoded`) the first layer's weight ``(H, D)`` is kept as ``D`` rows of ``H`` (input ``i``'s
        weights in row ``i``), then a zero row, and the learner's row is padded with zeros to a whole number of
        ``H``: every learner's first layer is then rows of one ``(-1, H)`` view of a stacked tensor, which
        :class:`.Indicators` sums and adds gradients to in place (no copy of the weights a step). The zeros get no
        gradient, so Adam leaves them zero. Saved models hold SB3's order (:meth:`_canonical`)."""
        self._numels = [int(np.prod(shape)) for shape in self._shapes]
        self._starts, position = [], 0
        for i, numel in enumerate(self._numels):
            self._starts.append(position)
            position += numel + (self._shapes[0][0] if i == 0 and self._keeps_encoded else 0)
        width = self._shapes[0][0] if self._keeps_encoded else 1
        self._row_size = -(-position // width) * width
        self._table_rows = self._row_size // width  # a learner's rows in the (-1, H) view

    def _unflatten(self, flat: th.Tensor, rest: bool = False) -> dict[str, th.Tensor]:
        """Named parameter views of rows of the stacked layout (:meth:`_layout`; any leading shape), in SB3's shapes
        (a first layer kept as rows is viewed transposed); ``rest``: ``flat`` holds the rows from the first layer's bias
        on, and the first weight is left out. The views of :attr:`params` or :attr:`target` (read at every update) are
        kept: those tensors are only ever changed in place."""
        base, shift = flat._base, self._starts[1] if rest else 0
        stacked = (base is not None and (base is self.params or base is self.target)
                   and flat.data_ptr() - base.data_ptr() == shift * flat.element_size())  # their first rows
        key = (id(base), tuple(flat.shape), rest) if stacked else None
        if key is not None and key in self._views:
            return self._views[key]
        lead = flat.shape[:-1]
        views = {}
        for i, (name, shape, start, numel) in enumerate(zip(self._names, self._shapes, self._starts, self._numels)):
            if i == 0 and rest:
                continue
            piece = flat[..., start - shift : start - shift + numel]
            if i == 0 and self._keeps_encoded:
                views[name] = piece.view(*lead, shape[1], shape[0]).transpose(-1, -2)
            else:
                views[name] = piece.view(*lead, *shape)
        if key is not None:  # a view holds its base, so the id stays that tensor's while the entry lives
            self._views[key] = views
        return views

    def _canonical(self, rows: th.Tensor) -> th.Tensor:
        """Rows ``(n, P)`` of the stacked layout in SB3's: each parameter flattened as its module holds it, in order."""
        views = self._unflatten(rows)
        return th.cat([views[name].reshape(len(rows), numel) for name, numel in zip(self._names, self._numels)], dim=1)

    def _stored(self, canonical: th.Tensor) -> th.Tensor:
        """The inverse of :meth:`_canonical`: rows of SB3's order as rows of the stacked layout."""
        rows = th.zeros((len(canonical), self._row_size), dtype=canonical.dtype, device=self.device)
        views = self._unflatten(rows)
        offsets = np.cumsum([0, *self._numels])
        for name, shape, start, stop in zip(self._names, self._shapes, offsets[:-1], offsets[1:]):
            views[name].copy_(canonical[:, start:stop].reshape(len(canonical), *shape))
        return rows

    def _first_rows(self, stacked: th.Tensor, goals: np.ndarray) -> tuple[th.Tensor, th.Tensor]:
        """The first layers of a stacked tensor as the table :class:`.Indicators` reads (a view) and the first row of
        each learner of ``goals`` in it."""
        return (stacked.view(-1, self._shapes[0][0]),
                th.as_tensor(np.asarray(goals, dtype=np.int64) * self._table_rows, device=self.device))

    def _rows(self, goals: np.ndarray) -> Any:
        """An index of the learners ``goals`` into the stacked tensors: a slice (rows read in place) when they are the
        first ``len(goals)`` in order (every sub-goal, the usual case), else a tensor (rows gathered)."""
        if np.array_equal(goals, np.arange(len(goals))):
            return slice(0, len(goals))
        return th.as_tensor(goals, device=self.device)

    @staticmethod
    def _take(stacked: th.Tensor, index: Any) -> th.Tensor:
        """The rows ``index`` (of :meth:`_rows`) of a stacked tensor: a view for a slice, else gathered with
        ``index_select`` (several times faster than indexing with a tensor on a CPU)."""
        return stacked[index] if isinstance(index, slice) else th.index_select(stacked, 0, index)

    def _mlp_input(self, obs: th.Tensor) -> th.Tensor:
        """What a plain MLP reads of ``obs`` ``(T, N, ...)``: SB3's preprocessing, flattened to ``(T, N, D)``."""
        x = obs.float()  # SB3's preprocessing of a Box (an MLP reads no other): as a float, images scaled to [0, 1]
        if self._scale_images:
            x = x / 255.0
        return x.reshape(*obs.shape[:2], -1)

    def _vq(self, stacked: th.Tensor, goals: np.ndarray, obs: th.Tensor) -> th.Tensor:
        """Q-values ``(T, B, A)`` of the learners ``goals``, their parameters the rows of ``stacked`` (:attr:`params` or
        :attr:`target`), at ``obs`` ``(T, B, ...)``: a plain MLP's rows gathered for batched products, another
        network's rows read in place, one learner after the other."""
        if self._layers is None:
            return self._each(self._named(stacked, goals), obs)
        return self._mlp_forward(self._take(stacked, self._rows(goals)), self._mlp_input(obs))[-1]

    def _named(self, stacked: th.Tensor, goals: np.ndarray) -> list[dict[str, th.Tensor]]:
        """Each learner of ``goals``'s named parameters: views of its row of ``stacked`` (nothing gathered)."""
        return [self._unflatten(stacked[int(goal)]) for goal in goals]

    def _each(self, pieces: Sequence[dict[str, th.Tensor]], obs: th.Tensor) -> th.Tensor:
        """Q-values ``(T, B, A)`` of a network that is not a plain MLP (a CNN), one learner after the other with its
        named parameters ``pieces[i]``: a convolution of one learner's weights runs near an SB3 module's speed, where
        ``vmap`` over the stacked weights took twice as long forward and backward (design decisions: CNN learners)."""
        return th.stack([functional_call(self._template, named, (x,)) for named, x in zip(pieces, obs)])

    def _leaves(self, goals: np.ndarray) -> list[dict[str, th.Tensor]]:
        """Each learner of ``goals``'s named parameters copied from :attr:`params`, each a leaf of its own that autograd
        differentiates (a gradient through views of one row would add every parameter's into a zeroed row of ``P``)."""
        return [{name: piece.detach().clone().requires_grad_() for name, piece in named.items()}
                for named in self._named(self.params, goals)]

    def _row_gradients(self, loss: th.Tensor, leaves: list[dict[str, th.Tensor]]) -> th.Tensor:
        """The gradient ``(T, P)`` of ``loss`` with respect to :meth:`_leaves`, in the rows' layout."""
        grads = iter(th.autograd.grad(loss, [leaf for named in leaves for leaf in named.values()]))
        grad = th.empty((len(leaves), self._row_size), device=self.device)
        for row, named in zip(grad, leaves):
            for name, view in self._unflatten(row).items():
                view.copy_(next(grads))
        return grad

    def _mlp_forward(self, flat: th.Tensor, x: Any, first: Optional[tuple[th.Tensor, th.Tensor]] = None
                     ) -> list[th.Tensor]:
        """A plain MLP's forward pass for every learner at once (batched matrix products): the output of every
        layer, the input first and the Q-values ``(T, N, A)`` last (the backward pass reads them). ``x``: a tensor
        ``(T, N, D)``, or :class:`.Indicators` with ``first``, the learners' first layers as rows
        (:meth:`_first_rows`), and then ``flat`` holds the rest of each learner's row (:meth:`_unflatten` ``rest``)."""
        params = self._unflatten(flat, rest=isinstance(x, Indicators))
        outputs = [x]
        for kind, item in self._layers:
            if kind == "linear":
                bias = params[item + ".bias"]
                if isinstance(x, Indicators):  # one-hot inputs: sums of the weights' columns
                    x = x.linear(*first, bias)
                else:
                    x = th.baddbmm(bias.unsqueeze(1), x, params[item + ".weight"].transpose(1, 2))
            elif self._relu_mlp:  # in place: the backward pass reads only the activated output
                x = th.relu_(x)
            else:
                x = item(x)
            outputs.append(x)
        return outputs

    def _mlp_backward(self, flat: th.Tensor, outputs: list[th.Tensor], grad_q: th.Tensor,
                      rows: Optional[slice] = None, out: Optional[th.Tensor] = None) -> th.Tensor:
        """The gradient ``(T, P)`` of a loss with respect to the learners' rows (:meth:`_layout`) of a ReLU MLP, from
        the gradient ``grad_q`` ``(T, B, A)`` with respect to its Q-values at the inputs ``rows`` of ``outputs`` (a
        :meth:`_mlp_forward` pass over ``flat``; the first ``B`` by default): backpropagation written out, a few
        batched matrix products; one-hot inputs (:class:`.Indicators`) add each sample's gradient to the rows of its
        set places. ``out``: zeros ``(T, P)`` (contiguous) to write it in, else new ones."""
        params = self._unflatten(flat, rest=isinstance(outputs[0], Indicators))
        n = slice(0, grad_q.shape[1]) if rows is None else rows
        if out is None:
            out = th.zeros((len(grad_q), self._row_size), dtype=grad_q.dtype, device=grad_q.device)
        grads = self._unflatten(out)
        grad = grad_q  # with respect to the output of the layer being undone
        for i in range(len(self._layers) - 1, -1, -1):
            kind, item = self._layers[i]
            if kind == "linear":
                layer_input = outputs[i][:, n]
                if isinstance(layer_input, Indicators):
                    layer_input.add_outer(grad, *self._first_rows(out, np.arange(len(out))))
                else:
                    grads[item + ".weight"].copy_(th.bmm(grad.transpose(1, 2), layer_input))
                grads[item + ".bias"].copy_(grad.sum(dim=1))
                if i > 0:
                    grad = th.bmm(grad, params[item + ".weight"])
            else:  # ReLU: the gradient passes where the output is positive
                grad = grad * (outputs[i + 1][:, n] > 0)
        return out

    def _grow(self, capacity: int) -> None:
        def extend(old: th.Tensor) -> th.Tensor:
            new = th.zeros((capacity, old.shape[1]), dtype=old.dtype, device=self.device)
            new[: old.shape[0]] = old
            return new

        self.params, self.target = extend(self.params), extend(self.target)
        self._views.clear()
        self._optimizer = None  # its rows are views of the old tensors
        self.exp_avg, self.exp_avg_sq = extend(self.exp_avg), extend(self.exp_avg_sq)
        steps = th.zeros(capacity, device=self.device)
        steps[: len(self.adam_steps)] = self.adam_steps
        self.adam_steps = steps
        self._capacity = capacity

    def add(self, goal_key: Hashable) -> int:
        """A freshly initialised learner for a new sub-goal (section 5.1: random initialisation); its batches
        are relabelled from everything already stored."""
        goal = len(self)
        if goal >= self._capacity:
            self._grow(max(4, 2 * self._capacity))
        with th.random.fork_rng(devices=[]):
            if self.seed is not None:
                th.manual_seed(self.seed + goal)
            fresh = self._make_policy().q_net
        flat = self._stored(th.cat([value.detach().reshape(1, -1) for _, value in fresh.named_parameters()], dim=1))[0]
        self.params[goal] = flat
        self.target[goal] = flat
        self.exp_avg[goal] = 0.0
        self.exp_avg_sq[goal] = 0.0
        self.adam_steps[goal] = 0
        return self._add_counters(goal_key)

    def _add_counters(self, goal_key: Hashable) -> int:
        """The counters of a new sub-goal and its place in the replay; returns its id."""
        self.own_steps = np.append(self.own_steps, 0)
        self.ticks = np.append(self.ticks, 0)
        self.n_updates = np.append(self.n_updates, 0)
        self.last_round = np.append(self.last_round, self.rounds - 1)  # waiting since before this round
        self.recent.append(deque(maxlen=100))
        self.successes.append(0)
        self.attempts.append(0)
        return self.replay.add_goal(goal_key)

    def _counters(self) -> dict[str, Any]:
        return {"own_steps": self.own_steps.tolist(), "ticks": self.ticks.tolist(), "n_updates": self.n_updates.tolist(),
                "last_round": self.last_round.tolist(), "rounds": self.rounds,
                "recent": [list(r) for r in self.recent], "successes": list(self.successes),
                "attempts": list(self.attempts), "goal_keys": list(self.replay.goal_keys)}

    def _load_counters(self, state: dict[str, Any]) -> None:
        self.own_steps = np.array(state["own_steps"], dtype=np.int64)
        self.ticks = np.array(state["ticks"], dtype=np.int64)
        self.n_updates = np.array(state["n_updates"], dtype=np.int64)
        self.rounds = int(state["rounds"])
        self.last_round = np.array(state["last_round"], dtype=np.int64)
        self.recent = [deque(r, maxlen=100) for r in state["recent"]]
        self.successes, self.attempts = list(state["successes"]), list(state["attempts"])

    @property
    def n_envs(self) -> int:
        return self.replay.n_envs

    def _make_replay(self, n_envs: int) -> SharedReplay:
        """The shared replay of ``n_envs`` env streams: ``buffer_size`` transitions in all, as SB3's replay buffers
        divide their size among the envs."""
        capacity = max(self.buffer_size // n_envs, int(self._replay_kwargs["n_steps"]) + 1)
        replay = SharedReplay(capacity, n_envs=n_envs, **self._replay_kwargs)
        if self._keeps_encoded:
            replay.keep_encoded(self._encoded)
        return replay

    def _encoded(self, obs: np.ndarray) -> np.ndarray:
        """What the networks read of observations ``(..., H, W, C)`` with ``one_hot``, as the places of the set
        indicators (:meth:`.GridInput.places`; the replay keeps them: :meth:`SharedReplay.keep_encoded`)."""
        return self.input.places(obs)

    def set_n_envs(self, n_envs: int) -> None:
        """Step ``n_envs`` envs from now on: a new, empty replay with a stream per env (as SB3's ``set_env`` starts
        from an empty buffer after ``load``), the sub-goals kept."""
        replay = self._make_replay(n_envs)
        for key in self.replay.goal_keys:
            replay.add_goal(key)
        self.replay = replay

    def exploration_rate(self, goal: int) -> float:
        """Epsilon of sub-goal ``goal``: linear from the initial to the final value over ``exploration_steps`` own steps
        or, with ``exploration_run_steps``, over that many primitive steps since it was added (its learning ticks,
        one a primitive step with ``train_shared``), whichever is further along."""
        fraction = min(1.0, self.own_steps[goal] / self.exploration_steps)
        if self.exploration_run_steps is not None:
            fraction = max(fraction, min(1.0, self.ticks[goal] / self.exploration_run_steps))
        return self.eps_initial + fraction * (self.eps_final - self.eps_initial)

    def record_outcome(self, goal: int, success: bool) -> None:
        self.attempts[goal] += 1
        self.successes[goal] += int(success)
        self.recent[goal].append(bool(success))

    def success_rate(self, goal: int) -> Optional[float]:
        """Share of the sub-goal's last 100 tries that reached it (None before any)."""
        return float(np.mean(self.recent[goal])) if self.recent[goal] else None

    # ------------------------------------------------------------------ acting
    def _tensor(self, obs: np.ndarray, cropped: bool = False) -> th.Tensor:
        """Observations as the networks' input tensor (:meth:`.GridInput.encode`; ``cropped``: already cropped)."""
        obs = self.input.encode(obs, cropped)
        obs = np.moveaxis(obs, -1, -3) if self._transpose else obs
        return th.as_tensor(np.ascontiguousarray(obs), device=self.device)

    def q_values(self, goals: np.ndarray, obs: np.ndarray) -> th.Tensor:
        """Q-values ``(n, A)`` of sub-goal ``goals[i]``'s learner at ``obs[i]``."""
        goals = np.asarray(goals, dtype=np.int64)
        # each distinct learner reads every observation (envs often pursue the same sub-goals): its parameters
        # are read once, in place when they are the first rows, instead of gathered once per env
        distinct, inverse = np.unique(goals, return_inverse=True)
        with th.no_grad():
            obs_t = self._tensor(np.asarray(obs))
            q = self._vq(self.params, distinct, obs_t.unsqueeze(0).expand(len(distinct), *obs_t.shape))  # (U, n, A)
            return q[th.as_tensor(inverse.reshape(-1), device=self.device), th.arange(len(goals), device=self.device)]

    def act(self, goals: np.ndarray, obs: np.ndarray, deterministic: bool = False,
            avoid: Optional[np.ndarray] = None) -> np.ndarray:
        """One primitive action per env: sub-goal ``goals[i]``'s learner at ``obs[i]``, epsilon-greedy unless
        ``deterministic``; ``avoid`` ``(n, A)``: actions the greedy choice passes over where another allowed action is
        left (the policy breaking a cycle, :meth:`~sb3_hhp.hhp.acting.HierarchicalActing.predict`)."""
        q = self.q_values(goals, obs)
        mask = self.allowed_actions(obs)
        if mask is not None:
            q = q.masked_fill(~th.as_tensor(mask, device=self.device), -th.inf)
        if avoid is not None and avoid.any():
            rest = q.masked_fill(th.as_tensor(avoid, device=self.device), -th.inf)
            q = th.where(th.isfinite(rest).any(dim=1, keepdim=True), rest, q)
        actions = q.argmax(dim=1).cpu().numpy()
        if not deterministic:
            explore = self._rng.random(len(actions)) < np.array([self.exploration_rate(int(g)) for g in goals])
            if explore.any() and mask is None:
                actions[explore] = self._rng.integers(int(self.action_space.n), size=int(explore.sum()))
            elif explore.any():  # uniform over each state's allowed actions
                actions[explore] = np.argmax(self._rng.random((int(explore.sum()), mask.shape[-1])) * mask[explore], axis=1)
        return actions

    def allowed_actions(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """The goal space's mask of primitive actions for a batch of states, boolean (None: every action)."""
        mask = None if self.action_mask is None else self.action_mask(np.asarray(obs))
        return None if mask is None else np.asarray(mask, dtype=bool)

    def _allowed(self, obs: np.ndarray) -> Optional[th.Tensor]:
        """:meth:`allowed_actions` as a tensor on the learners' device."""
        mask = self.allowed_actions(obs)
        return None if mask is None else th.as_tensor(mask, device=self.device)

    # ------------------------------------------------------------------ learning
    def observe(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray, keys: list, terminated: np.ndarray,
                truncated: np.ndarray, gave_up: np.ndarray, acting: np.ndarray, intrinsic: np.ndarray) -> None:
        """One primitive step of every env (Algorithm 1 lines 19-20): store it once, then the learning ticks
        of the sub-goals it counts for, and their updates when due (one grouped update for all of them)."""
        replay = self.replay
        key_ids = np.array([replay.key_id(key) for key in keys], dtype=np.int32)
        acting = np.asarray(acting, dtype=np.int64)
        replay.add(obs, actions, next_obs, key_ids, terminated, truncated, gave_up, acting, intrinsic)
        n_goals = len(self)
        counted = acting[acting >= 0]
        np.add.at(self.own_steps, counted, 1)
        before = self.ticks.copy()
        if self.train_shared:
            self.ticks += len(acting)
        else:
            np.add.at(self.ticks, counted, 1)
        due_updates = self.ticks // self.train_freq - before // self.train_freq  # (K,) update rounds due
        due_targets = self.ticks // self.target_update_interval > before // self.target_update_interval
        ready = replay.size() * replay.n_envs >= max(self.learning_starts, self.batch_size)
        if ready and due_updates.any():
            totals = replay.trees.total(np.arange(n_goals))
            rounds = int(due_updates.max()) * self.gradient_steps
            plan, first_round = [], self.rounds
            for r in range(rounds):
                goals = np.flatnonzero((due_updates * self.gradient_steps > r) & (totals > 0))
                if len(goals):
                    goals = self.bounded(goals, acting)
                    if not self.grouped_rounds:
                        self.train_rounds([goals], first_round=self.rounds)
                    plan.append(goals)
                    self.last_round[goals] = self.rounds
                    self.rounds += 1
            if self.grouped_rounds and plan:
                self.train_rounds(plan, first_round=first_round)
        if due_targets.any():
            index = th.as_tensor(np.flatnonzero(due_targets), device=self.device)
            self.target[index] = self.params[index]

    def bounded(self, goals: np.ndarray, acting: np.ndarray) -> np.ndarray:
        """The sub-goals of ``goals`` (due for an update) that this round updates, at most ``max_updates``: those
        an env pursues now (``acting``) first, then those that waited longest; sorted."""
        if self.max_updates is None or len(goals) <= self.max_updates:
            return goals
        pursued = (goals[:, None] == np.asarray(acting)[None, :]).any(axis=1)  # np.isin, without its fixed cost
        order = np.lexsort((goals, self.last_round[goals], ~pursued))  # pursued first, then the longest waiting
        return np.sort(goals[order[: self.max_updates]])

    def train(self, goals: np.ndarray) -> float:
        """One gradient step for each sub-goal of ``goals``, all in one grouped call: a prioritized batch per
        sub-goal, the Double DQN target of its n-step returns (raised to the behaviour's return with the lower
        bound), the importance-weighted Huber loss, each sub-goal's gradient clipped to ``max_grad_norm``, Adam."""
        return self.train_rounds([np.asarray(goals)], first_round=self.rounds)

    def train_rounds(self, plan: list[np.ndarray], first_round: int = 0) -> float:
        """The learning rounds ``plan`` (the sub-goals of each, in order; ``first_round``: the number of the first) as
        :meth:`train` does one, in one grouped call: every round's batches drawn at once, every gradient from the
        parameters as they are now, then one Adam step per round, in order (``grouped_rounds``)."""
        goals = np.concatenate(plan) if len(plan) > 1 else np.asarray(plan[0])
        batch = self.replay.sample(goals, self.batch_size)
        as_t = lambda x: th.as_tensor(x, device=self.device)  # noqa: E731
        lower_bound = batch.behaviour_returns is not None
        # the closing states of the own returns and (lower bound) of the behaviour's
        next_obs = batch.next_observations
        if lower_bound:
            next_obs = np.concatenate([next_obs, batch.behaviour_next_observations], axis=1)
        n = len(batch.returns[0])
        actions = as_t(batch.actions.reshape(len(goals), -1, 1).astype(np.int64))
        weights = as_t(batch.weights)
        # rounds of the same sub-goals (grouped rounds before any sub-goal has to wait) read the same parameters: each
        # network reads every round's rows in one pass, and no parameters are gathered twice
        same = len(plan) > 1 and self._relu_mlp and all(np.array_equal(p, plan[0]) for p in plan[1:])
        reps = len(plan) if same else 1
        learners = len(goals) // reps
        index = self._rows(goals[:learners])
        first = None  # with the replay's kept places: the first layers read in place as rows, the rest gathered
        if self._relu_mlp and batch.encoded_observations is not None:
            first, rest = self._first_rows(self.params, goals[:learners]), slice(self._starts[1], None)
            params = self._take(self.params[:, rest], index)
        elif self._relu_mlp:  # (another network's learners copy their rows as leaves: _leaves)
            params = self._take(self.params, index)

        def per_learner(a: np.ndarray) -> np.ndarray:  # (reps * learners, m, ...) in plan order -> (learners, reps * m, ...)
            if reps == 1:
                return a
            return a.reshape(reps, learners, *a.shape[1:]).swapaxes(0, 1).reshape(learners, -1, *a.shape[2:])

        def per_round(t: th.Tensor) -> th.Tensor:  # the inverse, for the networks' outputs
            if reps == 1:
                return t
            return t.reshape(learners, reps, -1, *t.shape[2:]).transpose(0, 1).reshape(reps * learners, -1, *t.shape[2:])

        if self._relu_mlp:  # one forward pass of the online networks over s and the closing states, backward by hand
            if first is not None:  # the places of the set indicators, kept by the replay
                closing = batch.encoded_next_observations
                if lower_bound:
                    closing = np.concatenate([closing, batch.encoded_behaviour_next_observations], axis=1)
                x = np.concatenate([per_learner(batch.encoded_observations), per_learner(closing)], axis=1)
                size = self._shapes[0][1]
                most = max(int((x < size).sum(axis=-1).max()), 1)  # each state's places first: cut the padding
                inputs = Indicators(th.as_tensor(x[..., :most].astype(np.int64), device=self.device), size)
            else:
                crop = self.input.crop
                x = np.concatenate([per_learner(crop(batch.observations)), per_learner(crop(next_obs))], axis=1)
                inputs = self._mlp_input(self._tensor(x, cropped=True))
            outputs = self._mlp_forward(params, inputs, first)
            q_s = per_round(outputs[-1][:, : reps * n])
            q, next_q_online = q_s.gather(-1, actions)[..., 0], per_round(outputs[-1][:, reps * n :])
        else:
            leaves = self._leaves(goals[:learners])
            q = self._each(leaves, self._tensor(batch.observations)).gather(-1, actions)[..., 0]
            next_q_online = None
        with th.no_grad():
            if self._relu_mlp:  # the closing states as the online pass read them (converted once)
                closing = outputs[0][:, reps * n :]
                target = self.target
                if first is not None:
                    first, target = self._first_rows(self.target, goals[:learners]), self.target[:, rest]
                # (T, B or 2B, A): the closing states of the own returns, and of the behaviour's with the lower bound
                next_q_target = per_round(self._mlp_forward(self._take(target, index), closing, first)[-1])
            else:
                next_obs_t = self._tensor(next_obs)
                next_q_target = self._vq(self.target, goals[:learners], next_obs_t)
            if not self.double_q:
                next_q_online = next_q_target
            elif next_q_online is None:
                next_q_online = self._each(leaves, next_obs_t)
            allowed = self._allowed(next_obs)
            if allowed is not None:  # the max of the target over the actions a learner may take there
                next_q_online = next_q_online.masked_fill(~allowed, -th.inf)
            next_q = next_q_target.gather(-1, next_q_online.argmax(-1, keepdim=True))[..., 0]
            y = as_t(batch.returns) + as_t(batch.discounts) * (1 - as_t(batch.dones)) * next_q[:, :n]
            if lower_bound:  # optimality tightening: the behaviour's return is a lower bound
                y_behaviour = (as_t(batch.behaviour_returns)
                               + as_t(batch.behaviour_discounts) * (1 - as_t(batch.behaviour_dones)) * next_q[:, n:])
                y = th.maximum(y, y_behaviour)
            y = self._in_range(y)
        loss = (weights * F.smooth_l1_loss(q, y, reduction="none")).mean(dim=1)  # (T,): each sub-goal's own loss
        if self._relu_mlp:
            # d loss / d q: the Huber loss's derivative clamp(q - y, -1, 1), weighted, over the batch, at the actions taken
            grad_q = th.zeros_like(q_s).scatter_(-1, actions, ((weights * (q - y).clamp(-1, 1)) / n)[..., None])
            grad = th.zeros((reps * learners, self._row_size), dtype=grad_q.dtype, device=grad_q.device)
            for r in range(reps):  # each round's gradient from its own rows, into its own rows of grad
                self._mlp_backward(params, outputs, grad_q[r * learners : (r + 1) * learners], slice(r * n, (r + 1) * n),
                                   out=grad[r * learners : (r + 1) * learners])
        else:
            grad = self._row_gradients(loss.sum(), leaves)
        grad = self._clip(grad)  # grad is ours
        start = 0
        for number, round_goals in enumerate(plan, start=first_round):
            self._adam(round_goals, grad[start : start + len(round_goals)], number)
            start += len(round_goals)
        td_errors = (y - q).detach().abs().cpu().numpy()
        self.replay.update_priorities(goals, batch.leaves, td_errors)  # a later round's over an earlier one's
        np.add.at(self.n_updates, goals, 1)
        self.last_loss = float(loss.mean().detach())
        return self.last_loss

    def _in_range(self, y: th.Tensor) -> th.Tensor:
        """TD targets ``y`` clipped to ``target_range`` (as they are without one)."""
        return y if self.target_range is None else y.clamp(*self.target_range)

    def _clip(self, grad: th.Tensor) -> th.Tensor:
        """Each row's (sub-goal's) gradient norm clipped to ``max_grad_norm``, as SB3 clips a model's (in place)."""
        return grad.mul_(th.clamp(self.max_grad_norm / (th.linalg.vector_norm(grad, dim=1, keepdim=True) + 1e-6), max=1.0))

    def _adam(self, goals: np.ndarray, grad: th.Tensor, round_number: int) -> None:
        """Adam with each sub-goal's own step count and moments (:class:`~sb3_hhp.hierarchy.row_adam.RowAdam`) on the
        (clipped, :meth:`_clip`) gradient rows ``grad`` of ``goals`` (distinct), updated in place; ``round_number``: the
        learning round's (every 1,000th flushes the moments' subnormal floats)."""
        if self._optimizer is None:  # made again when the stacked tensors grow
            self._optimizer = RowAdam(self.params, self.exp_avg, self.exp_avg_sq, self.adam_steps, lr=self.lr)
        self._optimizer.step(goals, grad)
        if round_number % 1000 == 0:
            self._optimizer.flush_subnormals()

    # ------------------------------------------------------------------ SB3 views, save / load
    def policy(self, goal: int) -> DQNPolicy:
        """Sub-goal ``goal``'s learner as an SB3 ``DQNPolicy`` (its online and target networks), on the learners' device."""
        policy = self._make_policy()
        policy.q_net.load_state_dict({name: value.clone() for name, value in self._unflatten(self.params[goal]).items()})
        policy.q_net_target.load_state_dict({name: value.clone() for name, value in self._unflatten(self.target[goal]).items()})
        return policy

    def state_dict(self) -> dict[str, Any]:
        """Weights, target weights, Adam moments and counters of every sub-goal (the replay is not saved, as in SB3)."""
        n = len(self)
        return {
            "format": "sb3_hhp.StackedDQN",
            "names": list(self._names),
            # SB3's order (:meth:`_canonical`), whatever the layout kept in memory
            "params": self._canonical(self.params[:n]),
            "target": self._canonical(self.target[:n]),
            "exp_avg": self._canonical(self.exp_avg[:n]),
            "exp_avg_sq": self._canonical(self.exp_avg_sq[:n]),
            "adam_steps": self.adam_steps[:n].clone(),
            **self._counters(),
        }

    def replay_state(self) -> dict[str, Any]:
        """The shared replay's stored transitions, priorities and sub-goal keys, for a file (:meth:`~sb3_hhp.hhp.hhp.HhP.save_replay_buffer`)."""
        return {"format": "sb3_hhp.SharedReplay", "goal_keys": list(self.replay.goal_keys),
                "replay": buffer_state(self.replay, self.replay.capacity, self.replay.size(),
                                       skip=("_achieved", *SharedReplay.DERIVED))}

    def load_replay_state(self, state: Any, truncate_last_traj: bool = True) -> None:
        """Refill the shared replay from :meth:`replay_state` (the learners' sub-goals must be the file's).
        ``truncate_last_traj``: the newest transition of every env is taken as cut by a time limit, so no n-step
        return runs on into the first step of the fresh episodes that training goes on with (as SB3 truncates a
        loaded HER buffer's last episode)."""
        if not isinstance(state, dict) or state.get("format") != "sb3_hhp.SharedReplay":
            raise ValueError("the file holds no shared replay of stacked sub-goal learners")
        if list(state["goal_keys"]) != list(self.replay.goal_keys):
            raise ValueError(f"the file's replay belongs to a model with {len(state['goal_keys'])} sub-goals, this one "
                             f"has {len(self.replay.goal_keys)} (or others): load the replay saved with this model")
        load_buffer_state(self.replay, state["replay"], self.replay.capacity, "the sub-goal learners' replay")
        replay = self.replay
        if self._keeps_encoded:  # not in the file: encoded again from the stored observations
            replay.keep_encoded(self._encoded)
        if truncate_last_traj and replay.size() > 0:
            newest = (replay.pos - 1) % replay.capacity
            replay.truncated[newest] |= ~replay.terminated[newest]

    def load_state_dict(self, state: Any) -> None:
        check_learners_state(state, "StackedDQN", "stacked")
        for key in state["goal_keys"]:
            self.add(key)
        n = len(self)
        if list(state["names"]) != self._names or state["params"].shape[1] != sum(self._numels):
            raise ValueError("The saved sub-goal learners have another network than subpolicy_kwargs builds: load the "
                             "model with the subpolicy_kwargs it was trained with")
        self.params[:n], self.target[:n] = self._stored(state["params"]), self._stored(state["target"])
        self.exp_avg[:n], self.exp_avg_sq[:n] = self._stored(state["exp_avg"]), self._stored(state["exp_avg_sq"])
        self.adam_steps[:n] = state["adam_steps"]
        self._load_counters(state)
