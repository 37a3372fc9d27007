"""One replay of primitive transitions shared by every sub-goal, relabelled when a batch is sampled.

Every primitive step of every env is stored once: ``s, a, s'``, the id of the sub-goal key of ``s'``,
``terminated`` / ``truncated``, whether the acting sub-goal gave up there, which sub-goal acted, and the
intrinsic reward ``r^i`` (eq. 7). A sub-goal's reward (eq. 5, 6) and terminal flag are computed only when a
batch is drawn for it, from ``done(s', g)`` (as HER relabels goals at sample time), so memory does not grow
with the number of sub-goals K and a sub-goal found late learns at once from everything stored before it.

What the learners rest on is kept from the per-sub-goal buffers this replaces:

- n-step returns along the sub-goal's own behaviour: from a transition where ``g`` acted, the return runs
  over the following transitions of the same env while ``g`` still acts, and stops at ``terminal(s, g)``, at a
  time limit (the env's, or ``g``'s give-up) or at the newest transition; a transition where another sub-goal
  acted is a one-step transition for ``g``;
- optionally (``lower_bound``), the n-step return along the stored behaviour, whoever acted, as a lower bound
  on the target ("optimality tightening");
- proportional prioritized replay, one sum tree per sub-goal (a transition can matter to one sub-goal and
  not to another).
"""

from collections.abc import Callable, Hashable
from typing import NamedTuple, Optional

import numpy as np
from gymnasium import spaces

from sb3_hhp.hierarchy.rewards import pseudo_reward, subpolicy_reward


class GoalTrees:
    """``n_trees`` proportional-priority sum trees over the same ``capacity`` leaves, stored as one array.

    New leaves get the largest priority seen so far in their tree; their ancestors are refreshed lazily, in one
    vectorised pass before the next draw, so the per-step cost does not grow with the number of trees.
    """

    def __init__(self, n_trees: int, capacity: int) -> None:
        self.capacity = int(capacity)
        self._size = 1 << int(np.ceil(np.log2(max(2, self.capacity))))
        self._depth = int(np.log2(self._size))
        self._sum = np.zeros((n_trees, 2 * self._size), dtype=np.float64)
        self.max_priority = np.ones(n_trees, dtype=np.float64)
        self._pending: list[np.ndarray] = []

    @property
    def n_trees(self) -> int:
        return self._sum.shape[0]

    def grow(self, n_trees: int) -> None:
        """Room for ``n_trees`` trees (new ones empty)."""
        if n_trees > self.n_trees:
            self._flush()
            extra = n_trees - self.n_trees
            self._sum = np.concatenate([self._sum, np.zeros((extra, self._sum.shape[1]))])
            self.max_priority = np.concatenate([self.max_priority, np.ones(extra)])

    def fill(self, tree: int, leaves: np.ndarray, priority: float = 1.0) -> None:
        """Give every leaf of ``leaves`` the priority ``priority`` in tree ``tree`` (a new sub-goal)."""
        self._flush()
        self._sum[tree] = 0.0
        self._sum[tree, self._size + leaves] = priority
        for level in range(self._depth - 1, -1, -1):  # rebuild bottom-up
            start, stop = 1 << level, 2 << level
            self._sum[tree, start:stop] = self._sum[tree, 2 * start : 2 * stop : 2] + self._sum[tree, 2 * start + 1 : 2 * stop : 2]

    def add(self, leaves: np.ndarray, trees: np.ndarray) -> None:
        """New ``leaves`` with each tree's largest priority, in the trees where ``trees[k]`` is True, 0 elsewhere."""
        self._sum[:, self._size + leaves] = np.where(trees[:, None], self.max_priority[:, None], 0.0)
        self._pending.append(np.asarray(leaves))

    def _flush(self) -> None:
        if not self._pending:
            return
        leaves = np.unique(np.concatenate(self._pending))
        self._pending = []
        if leaves[-1] - leaves[0] + 1 == len(leaves):  # one run of leaves (the usual case): its ancestors are runs too
            low, high = (int(leaves[0]) + self._size) >> 1, (int(leaves[-1]) + self._size) >> 1
            for _ in range(self._depth):
                self._sum[:, low : high + 1] = self._sum[:, 2 * low : 2 * high + 2 : 2] + self._sum[:, 2 * low + 1 : 2 * high + 2 : 2]
                low, high = low >> 1, high >> 1
            return
        nodes = (leaves + self._size) >> 1
        for _ in range(self._depth):
            nodes = np.unique(nodes)
            self._sum[:, nodes] = self._sum[:, 2 * nodes] + self._sum[:, 2 * nodes + 1]
            nodes = nodes >> 1

    def total(self, trees: np.ndarray) -> np.ndarray:
        self._flush()
        return self._sum[trees, 1]

    def _bases(self, trees: np.ndarray) -> np.ndarray:
        """Where each tree of ``trees`` starts in the flattened array, as a column ``(T, 1)`` (one flat index per
        node is faster to gather than a pair of indices)."""
        return (np.asarray(trees, dtype=np.int64) * self._sum.shape[1])[:, None]

    def update(self, trees: np.ndarray, leaves: np.ndarray, priorities: np.ndarray) -> None:
        """Set ``priorities`` (shape ``(T, B)``) of ``leaves`` (same shape) in ``trees`` (shape ``(T,)``); where a tree
        and leaf appear twice, the later row's priority is kept."""
        self._flush()
        flat, bases = self._sum.reshape(-1), self._bases(trees)
        flat[bases + self._size + leaves] = priorities
        np.maximum.at(self.max_priority, trees, priorities.max(axis=1))  # a tree may appear twice (grouped rounds)
        nodes = bases + ((self._size + leaves) >> 1)
        for _ in range(self._depth):
            flat[nodes] = flat[nodes + (nodes - bases)] + flat[nodes + (nodes - bases) + 1]
            nodes = bases + ((nodes - bases) >> 1)

    def sample(self, trees: np.ndarray, batch_size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``batch_size`` stratified draws in each of ``trees``: leaves ``(T, B)`` and their probabilities."""
        totals = self.total(trees)
        values = (np.arange(batch_size)[None, :] + rng.random((len(trees), batch_size))) * (totals[:, None] / batch_size)
        flat, bases = self._sum.reshape(-1), self._bases(trees)
        nodes = np.ones(values.shape, dtype=np.int64)
        for _ in range(self._depth):
            left = bases + 2 * nodes
            left_sum = flat[left]
            go_right = (values >= left_sum) & (flat[left + 1] > 0)
            values = values - left_sum * go_right
            nodes = 2 * nodes + go_right
        return nodes - self._size, flat[bases + nodes] / totals[:, None]


class GoalBatch(NamedTuple):
    """A batch drawn for each of T sub-goals, as NumPy arrays with a leading ``(T, B)``."""

    goals: np.ndarray  # (T,) the sub-goals the batch was drawn for
    observations: np.ndarray  # (T, B, *obs)
    actions: np.ndarray  # (T, B, *act)
    returns: np.ndarray  # (T, B) n-step returns of eq. 6 rewards
    next_observations: np.ndarray  # (T, B, *obs) the state closing the return
    dones: np.ndarray  # (T, B) terminal(s, g) at the closing state (time limits excluded)
    discounts: np.ndarray  # (T, B) gamma^m
    weights: np.ndarray  # (T, B) importance-sampling weights, largest 1 in each sub-goal's batch
    leaves: np.ndarray  # (T, B) flat indices, for the priority update
    behaviour_returns: Optional[np.ndarray] = None  # the lower bound: the same along the stored behaviour
    behaviour_next_observations: Optional[np.ndarray] = None
    behaviour_dones: Optional[np.ndarray] = None
    behaviour_discounts: Optional[np.ndarray] = None
    # what the networks read of each state, kept by the replay (:meth:`SharedReplay.keep_encoded`), else None
    encoded_observations: Optional[np.ndarray] = None
    encoded_next_observations: Optional[np.ndarray] = None
    encoded_behaviour_next_observations: Optional[np.ndarray] = None


class SharedReplay:
    """The primitive transitions of ``n_envs`` envs, ``capacity`` per env, for every sub-goal at once.

    :param capacity: transitions kept per env (the oldest are overwritten), ``>= 1``
    :param observation_space: the primitive observation space (stored in its own dtype: uint8 grids stay uint8)
    :param action_space: the primitive action space
    :param achieved: ``done(s, g)`` from two sub-goal keys (the goal space's :meth:`~sb3_hhp.goals.base.GoalSpace.achieved`)
    :param n_envs: number of env streams
    :param alpha: weight of the intrinsic reward in eq. 6
    :param gamma: discount of the n-step returns
    :param n_steps: length of the n-step returns (1: one-step)
    :param lower_bound: also draw the return along the stored behaviour (needs ``n_steps > 1``)
    :param share_experience: every sub-goal learns from every transition; False: only from its own
    :param shared_priorities: one sum tree for every sub-goal (a transition's priority is set by whoever draws it,
        :class:`~sb3_hhp.hierarchy.heads.SharedHeadsDQN`), instead of one tree per sub-goal
    :param priority_alpha, priority_beta, priority_eps: prioritized replay's alpha, beta and epsilon
    :param carry_relabel: the share of each drawn batch, for a sub-goal that carries an object, replaced where possible
        by steps taken with empty hands as they would have gone carrying it (``counterfactual``); one-step returns
    :param counterfactual: the goal space's :meth:`~sb3_hhp.goals.base.GoalSpace.carried_counterfactual`
    :param seed: seed of the draws
    """

    #: what the learners' networks read of an observation, kept beside it (:meth:`keep_encoded`); None: nothing kept
    _encode: Optional[Callable[[np.ndarray], np.ndarray]] = None
    encoded_observations: Optional[np.ndarray] = None
    encoded_next_observations: Optional[np.ndarray] = None
    #: attributes computed from the stored ones, left out of a saved replay (found again when it is loaded)
    DERIVED = ("_encode", "encoded_observations", "encoded_next_observations")

    def __init__(
        self,
        capacity: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        achieved: Callable[[Hashable, Hashable], bool],
        n_envs: int = 1,
        alpha: float = 0.5,
        gamma: float = 0.99,
        n_steps: int = 1,
        lower_bound: bool = False,
        share_experience: bool = True,
        shared_priorities: bool = False,
        priority_alpha: float = 0.6,
        priority_beta: float = 0.4,
        priority_eps: float = 1e-6,
        carry_relabel: float = 0.0,
        counterfactual: Optional[Callable] = None,
        seed: Optional[int] = None,
    ) -> None:
        if not 0.0 <= carry_relabel <= 1.0:
            raise ValueError(f"carry_relabel must be in [0, 1], got {carry_relabel}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        if int(n_steps) != n_steps or n_steps < 1:
            raise ValueError(f"n_steps must be an integer >= 1, got {n_steps}")
        if lower_bound and n_steps < 2:
            raise ValueError("off_policy_lower_bound needs n_steps > 1 (it is an n-step return along the behaviour)")
        if isinstance(observation_space, spaces.Dict):
            raise ValueError("the shared replay stores Box observations; flatten Dict observations first")
        self.capacity, self.n_envs = int(capacity), int(n_envs)
        self.alpha, self.gamma, self.n_steps = float(alpha), float(gamma), int(n_steps)
        self.lower_bound, self.share_experience = bool(lower_bound), bool(share_experience)
        self.priority_alpha, self.priority_beta, self.priority_eps = priority_alpha, priority_beta, priority_eps
        self._achieved = achieved
        self.carry_relabel, self.counterfactual = float(carry_relabel), counterfactual
        shape = (self.capacity, self.n_envs)
        self.observations = np.zeros((*shape, *observation_space.shape), dtype=observation_space.dtype)
        self.next_observations = np.zeros_like(self.observations)
        self.actions = np.zeros((*shape, *action_space.shape), dtype=action_space.dtype)
        self.key_ids = np.zeros(shape, dtype=np.int32)  # id of the sub-goal key of s'
        self.terminated = np.zeros(shape, dtype=bool)
        self.truncated = np.zeros(shape, dtype=bool)  # the env's time limit
        self.gave_up = np.zeros(shape, dtype=bool)  # the acting sub-goal's give-up (its own time limit)
        self.acting = np.full(shape, -1, dtype=np.int32)  # the sub-goal that acted (-1: none)
        self.intrinsic = np.zeros(shape, dtype=np.float32)  # r^i (eq. 7)
        self.pos, self.full = 0, False
        self.keys: dict[Hashable, int] = {}
        self.goal_keys: list[Hashable] = []
        self._done_table = np.zeros((16, 4), dtype=bool)  # done(key id, goal id)
        self.shared_priorities = bool(shared_priorities)
        self.trees = GoalTrees(1 if shared_priorities else 4, self.capacity * self.n_envs)
        self._rng = np.random.default_rng(seed)

    # ------------------------------------------------------------------ keys and sub-goals
    @property
    def n_goals(self) -> int:
        return len(self.goal_keys)

    def size(self) -> int:
        """Transitions stored per env."""
        return self.capacity if self.full else self.pos

    def key_id(self, key: Hashable) -> int:
        """The id of a sub-goal key (new keys get the next id and their row of ``done``)."""
        key_id = self.keys.get(key)
        if key_id is None:
            key_id = self.keys[key] = len(self.keys)
            if key_id >= self._done_table.shape[0]:
                self._done_table = np.concatenate([self._done_table, np.zeros_like(self._done_table)])
            self._done_table[key_id, : self.n_goals] = [self._achieved(key, goal) for goal in self.goal_keys]
        return key_id

    def add_goal(self, goal_key: Hashable) -> int:
        """A new sub-goal: its column of ``done`` and its sum tree over everything stored (it may learn from it all)."""
        goal = self.n_goals
        self.goal_keys.append(goal_key)
        if goal >= self._done_table.shape[1]:
            self._done_table = np.concatenate([self._done_table, np.zeros_like(self._done_table)], axis=1)
        for key, key_id in self.keys.items():
            self._done_table[key_id, goal] = self._achieved(key, goal_key)
        if self.shared_priorities:  # the one tree already holds every stored transition
            return goal
        self.trees.grow(max(self.trees.n_trees * (2 if goal >= self.trees.n_trees else 1), goal + 1))
        stored = np.arange(self.size() * self.n_envs)
        if not self.share_experience:
            stored = stored[self.acting.reshape(-1)[stored] == goal]
        self.trees.fill(goal, stored)
        return goal

    def keep_encoded(self, encode: Optional[Callable[[np.ndarray], np.ndarray]], chunk: int = 1024) -> None:
        """Keep ``encode(observation)`` beside every stored observation and next observation (``encode`` maps
        ``(..., *obs)`` to ``(..., *encoded)``, e.g. the places of the learners' one-hot indicators), written once when a
        step is stored instead of at every draw; drawn batches then carry the encoded rows (``encoded_*``). The
        transitions stored so far are encoded now, ``chunk`` rows at a time; None keeps nothing. Not saved with the
        replay (:func:`~sb3_hhp.dqn.buffers.buffer_state` skips it): a loaded replay is encoded again."""
        self._encode = encode
        if encode is None:
            self.encoded_observations = self.encoded_next_observations = None
            return
        probe = np.asarray(encode(self.observations[:1, :1]))
        self.encoded_observations = np.zeros((self.capacity, self.n_envs, *probe.shape[2:]), dtype=probe.dtype)
        self.encoded_next_observations = np.zeros_like(self.encoded_observations)
        for start in range(0, self.size(), chunk):
            rows = slice(start, min(start + chunk, self.size()))
            self.encoded_observations[rows] = encode(self.observations[rows])
            self.encoded_next_observations[rows] = encode(self.next_observations[rows])

    def done(self, key_ids: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """``done(s, g)`` for arrays of key ids and sub-goals (broadcast)."""
        return self._done_table[key_ids, goals]

    # ------------------------------------------------------------------ storing
    def add(self, obs: np.ndarray, action: np.ndarray, next_obs: np.ndarray, key_ids: np.ndarray, terminated: np.ndarray,
            truncated: np.ndarray, gave_up: np.ndarray, acting: np.ndarray, intrinsic: np.ndarray) -> None:
        """One primitive transition per env (arrays with a leading ``n_envs``)."""
        pos = self.pos
        self.observations[pos] = obs
        self.next_observations[pos] = next_obs
        self.actions[pos] = np.asarray(action).reshape(self.actions.shape[1:])
        self.key_ids[pos] = key_ids
        self.terminated[pos] = terminated
        self.truncated[pos] = truncated
        self.gave_up[pos] = gave_up
        self.acting[pos] = acting
        self.intrinsic[pos] = intrinsic
        if self._encode is not None:  # one call for the step's states and next states
            self.encoded_observations[pos], self.encoded_next_observations[pos] = self._encode(
                np.stack([self.observations[pos], self.next_observations[pos]]))
        leaves = pos * self.n_envs + np.arange(self.n_envs)
        n_goals = self.n_goals
        if self.shared_priorities or self.share_experience:
            learns = np.ones(self.trees.n_trees, dtype=bool)
        else:
            learns = (np.arange(self.trees.n_trees)[:, None] == np.asarray(acting)[None, :]).any(axis=1)
        learns[n_goals:] = self.shared_priorities  # trees not yet given to a sub-goal stay empty
        self.trees.add(leaves, learns)
        self.pos = (pos + 1) % self.capacity
        self.full = self.full or self.pos == 0

    # ------------------------------------------------------------------ drawing
    def sample(self, goals: np.ndarray, batch_size: int) -> GoalBatch:
        """A prioritized batch of ``batch_size`` transitions for each sub-goal of ``goals``, with that sub-goal's
        n-step returns of eq. 6 rewards computed now from ``done(s', g)``."""
        goals = np.asarray(goals, dtype=np.int64)
        leaves, probabilities = self.trees.sample(goals, batch_size, self._rng)
        weights = self.importance_weights(probabilities)
        rows, cols = np.divmod(leaves, self.n_envs)
        goal_grid = goals[:, None]
        (returns, last, discounts, dones), behaviour = self.n_step_returns(rows, cols, goal_grid, behaviour=self.lower_bound)
        extra = {}
        if behaviour is not None:
            b_returns, b_last, b_discounts, b_dones = behaviour
            extra = dict(behaviour_returns=b_returns, behaviour_next_observations=self.next_observations[b_last, cols],
                         behaviour_dones=b_dones, behaviour_discounts=b_discounts)
        if self._encode is not None:
            extra.update(encoded_observations=self.encoded_observations[rows, cols],
                         encoded_next_observations=self.encoded_next_observations[last, cols])
            if behaviour is not None:
                extra["encoded_behaviour_next_observations"] = self.encoded_next_observations[b_last, cols]
        batch = GoalBatch(
            goals=goals, observations=self.observations[rows, cols], actions=self.actions[rows, cols], returns=returns,
            next_observations=self.next_observations[last, cols], dones=dones, discounts=discounts,
            weights=weights, leaves=leaves, **extra,
        )
        if self.carry_relabel > 0 and self.counterfactual is not None:
            self._relabel_carried(batch, rows, cols)
        return batch

    def _relabel_carried(self, batch: GoalBatch, rows: np.ndarray, cols: np.ndarray) -> None:
        """For each sub-goal of ``batch`` that carries an object, a ``carry_relabel`` share of its rows (in place):
        the steps taken with empty hands among them as they would have gone carrying it (the goal space's
        ``counterfactual``), each a one-step return of eq. 6 from ``done(s'', g)`` of the changed state ``s''``, its
        lower bound the same return."""
        lower_bound = batch.behaviour_returns is not None
        for t, goal in enumerate(batch.goals):
            chosen = np.flatnonzero(self._rng.random(len(rows[t])) < self.carry_relabel)
            if not len(chosen):
                continue
            r, c = rows[t, chosen], cols[t, chosen]
            changed = self.counterfactual(self.goal_keys[goal], self.observations[r, c], self.actions[r, c],
                                          self.next_observations[r, c])
            if changed is None:
                continue
            usable, obs, next_obs, next_keys = changed
            if not usable.any():
                continue
            at = chosen[usable]
            r, c = r[usable], c[usable]
            done = self.done(np.array([self.key_id(key) for key in next_keys]), int(goal))
            terminal = done | self.terminated[r, c]
            reward = subpolicy_reward(pseudo_reward(done, terminal), self.intrinsic[r, c], self.alpha)  # eq. 5, 6
            batch.observations[t, at], batch.next_observations[t, at] = obs[usable], next_obs[usable]
            batch.returns[t, at], batch.dones[t, at], batch.discounts[t, at] = reward, terminal, self.gamma
            if lower_bound:
                batch.behaviour_returns[t, at], batch.behaviour_dones[t, at] = reward, terminal
                batch.behaviour_next_observations[t, at], batch.behaviour_discounts[t, at] = next_obs[usable], self.gamma
            if batch.encoded_observations is not None:  # the changed states, encoded as the stored ones are (one call)
                encoded, encoded_next = self._encode(np.stack([obs[usable], next_obs[usable]]))
                batch.encoded_observations[t, at], batch.encoded_next_observations[t, at] = encoded, encoded_next
                if lower_bound:
                    batch.encoded_behaviour_next_observations[t, at] = encoded_next

    def importance_weights(self, probabilities: np.ndarray) -> np.ndarray:
        """``w = (N * P(i))^-beta``, normalised by the largest weight of each row of draws."""
        weights = (self.size() * self.n_envs * np.maximum(probabilities, 1e-12)) ** (-self.priority_beta)
        return (weights / weights.max(axis=-1, keepdims=True)).astype(np.float32)

    def rewards(self, rows: np.ndarray, cols: np.ndarray, goals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 5 and 6 for sub-goals ``goals`` at stored transitions: the reward, ``terminal(s', g)`` (the env's
        own end, or ``done(s', g)``) and whether a time limit cut ``g`` there (the env's, or ``g``'s give-up)."""
        return self._rewards_at(rows * self.n_envs + cols, goals)

    def _rewards_at(self, at: np.ndarray, goals: np.ndarray, acts: Optional[np.ndarray] = None) -> tuple:
        """:meth:`rewards` at the flat indices ``at`` (``row * n_envs + col``: one index read from every array, faster
        than a pair); ``acts``: whether ``goals`` acted there, when the caller has it."""
        if acts is None:
            acts = self.acting.ravel().take(at) == goals
        done = self.done(self.key_ids.ravel().take(at), goals)
        terminal = done | self.terminated.ravel().take(at)
        cut = (self.truncated.ravel().take(at) | (self.gave_up.ravel().take(at) & acts)) & ~terminal
        reward = subpolicy_reward(pseudo_reward(done, terminal), self.intrinsic.ravel().take(at), self.alpha)  # eq. 5, 6
        return np.asarray(reward, dtype=np.float64), terminal, cut

    def _n_step(self, rows: np.ndarray, cols: np.ndarray, goals: np.ndarray, own: bool):
        """The n-step return from each drawn transition (shapes ``(T, B)``): it runs over the transitions of
        the same env stored after it and stops at ``terminal(s, g)``, a time limit, the newest transition or
        after n; with ``own``, also where ``g`` did not act next (a transition ``g`` did not act in is a
        one-step return). :return: returns, the row closing each return, ``gamma^m``, and its terminal flag."""
        return self.n_step_returns(rows, cols, goals, own=own, behaviour=not own)[0 if own else 1]

    def n_step_returns(self, rows: np.ndarray, cols: np.ndarray, goals: np.ndarray, own: bool = True,
                       behaviour: bool = False) -> tuple:
        """``_n_step`` for the own returns and (``behaviour``) the returns along the stored behaviour, from one
        relabelling of the n transitions after each drawn one. :return: ``(own or None, behaviour or None)``."""
        steps = np.arange(self.n_steps)
        ahead = (rows[..., None] + np.arange(self.n_steps + 1)) % self.capacity  # (T, B, n + 1): n and the one after
        at = ahead * self.n_envs + cols[..., None]
        seq_goals = goals[..., None]
        acted = self.acting.ravel().take(at) == seq_goals  # whether g acted at each of them
        seq = ahead[..., :-1]  # (T, B, n)
        reward, terminal, cut = self._rewards_at(at[..., :-1], seq_goals, acted[..., :-1])
        discounted = reward * self.gamma ** steps
        newer = (self.pos - 1 - rows) % self.capacity  # transitions of this env stored after the drawn one
        stop = terminal | cut | (steps >= newer[..., None])

        def closed(stop: np.ndarray) -> tuple:
            stop[..., -1] = True
            last = stop.argmax(axis=-1)  # m - 1
            returns = (discounted * (steps <= last[..., None])).sum(axis=-1).astype(np.float32)
            last_rows = np.take_along_axis(seq, last[..., None], axis=-1)[..., 0]
            dones = np.take_along_axis(terminal, last[..., None], axis=-1)[..., 0].astype(np.float32)
            return returns, last_rows, (self.gamma ** (last + 1)).astype(np.float32), dones

        own_result = None
        if own:  # g acted at each transition and at the one after it
            own_result = closed(stop | ~acted[..., :-1] | ~acted[..., 1:])
        return own_result, (closed(stop.copy()) if behaviour else None)

    def update_priorities(self, goals: np.ndarray, leaves: np.ndarray, td_errors: np.ndarray) -> None:
        """``p = (|delta| + eps)^alpha`` for the drawn transitions of each sub-goal."""
        self.trees.update(np.asarray(goals), leaves, (np.abs(td_errors) + self.priority_eps) ** self.priority_alpha)

    def nbytes(self) -> int:
        arrays = (self.observations, self.next_observations, self.actions, self.key_ids, self.terminated, self.truncated,
                  self.gave_up, self.acting, self.intrinsic, self.encoded_observations, self.encoded_next_observations)
        return sum(array.nbytes for array in arrays if array is not None)
