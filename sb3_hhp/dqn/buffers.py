"""Proportional prioritized experience replay (Schaul et al., 2016) as an SB3 replay buffer."""

from collections.abc import Collection
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_hhp.dqn.sum_tree import SumTree


class PrioritizedReplayBufferSamples(NamedTuple):
    """
    A batch drawn from a :class:`PrioritizedReplayBuffer`: the fields of SB3's
    ``ReplayBufferSamples`` plus the importance-sampling weights and the buffer indices needed to
    update the priorities afterwards.
    """

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    discounts: th.Tensor | None
    weights: th.Tensor
    indices: np.ndarray
    # with ``off_policy_lower_bound``: the n-step return along the stored behaviour, off-policy rows included
    behaviour_rewards: th.Tensor | None = None
    behaviour_next_observations: th.Tensor | None = None
    behaviour_dones: th.Tensor | None = None
    behaviour_discounts: th.Tensor | None = None


class PrioritizedReplayBuffer(ReplayBuffer):
    """
    Replay buffer with proportional prioritization (Schaul et al., 2016, "Prioritized Experience
    Replay", https://arxiv.org/abs/1511.05952).

    Transition ``i`` is drawn with probability ``P(i) = p_i^alpha / sum_k p_k^alpha`` where
    ``p_i = |delta_i| + epsilon`` is its last absolute TD error; a new transition gets the largest
    priority currently stored (1.0 in an empty buffer) so that it is replayed at least once soon.
    Each draw carries the importance-sampling weight ``w_i = (N * P(i))^-beta / max_j w_j``,
    normalised by the largest weight over *all* stored transitions (the one of the smallest
    priority, as in the paper's reference implementation), so weights lie in ``(0, 1]``.

    The sum tree stores ``p^alpha``. A transition's index is ``pos * n_envs + env_index``.
    ``beta`` is a public attribute: a callback may anneal it towards 1 during training.

    Dict observation spaces are not supported (SB3's ``ReplayBuffer`` does not store them).

    :param buffer_size: Max number of transitions (over all envs), ``>= 1``.
    :param observation_space: Observation space.
    :param action_space: Action space.
    :param device: PyTorch device of the sampled tensors.
    :param n_envs: Number of parallel environments, ``>= 1``.
    :param optimize_memory_usage: Store each observation once (see SB3's ``ReplayBuffer``); the
        invalid transition at ``pos`` then gets priority 0 so it is never drawn.
    :param handle_timeout_termination: Do not treat time-limit truncations as terminal.
    :param alpha: Prioritization exponent in ``[0, 1]`` (0: uniform sampling).
    :param beta: Importance-sampling exponent in ``[0, 1]`` (1: full correction).
    :param epsilon: Constant ``> 0`` added to ``|delta|`` so that no transition has priority 0.
    :param n_steps: Sample n-step returns ``sum_{k<m} gamma^k r_{t+k}`` up to the first terminal,
        timeout or newest transition (``m <= n_steps``), with ``s_{t+m}`` as next observation and
        ``gamma^m`` as the per-sample discount of the bootstrap (1: one-step transitions). A transition
        added with ``info["off_policy"] = True`` (another policy's behaviour, relabelled) is always a one-step
        transition, and an n-step return stops before it: without importance weights, only one-step
        targets are sound on another policy's actions.
    :param gamma: Discount of the n-step returns, in ``[0, 1]``.
    :param off_policy_lower_bound: Also sample, for every transition, the n-step return along the behaviour
        that was stored after it, off-policy transitions included (same stops otherwise), as ``behaviour_*``
        fields. The return of any behaviour is a lower bound on the optimal value, so
        :class:`~sb3_hhp.dqn.dqn.DoubleDQN` raises its target to it where it is higher ("optimality tightening",
        He et al., 2017): relabelled experience then carries a reward back n steps at a time, as own n-step
        returns do, without the bias of an n-step target on another policy's actions. Needs ``n_steps > 1``.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        alpha: float = 0.6,
        beta: float = 0.4,
        epsilon: float = 1e-6,
        n_steps: int = 1,
        gamma: float = 0.99,
        off_policy_lower_bound: bool = False,
    ) -> None:
        if buffer_size < 1:
            raise ValueError(f"buffer_size must be >= 1, got {buffer_size}")
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {beta}")
        if not epsilon > 0.0:
            raise ValueError(f"epsilon must be > 0, got {epsilon}")
        if int(n_steps) != n_steps or n_steps < 1:
            raise ValueError(f"n_steps must be an integer >= 1, got {n_steps}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if off_policy_lower_bound and n_steps < 2:
            raise ValueError("off_policy_lower_bound needs n_steps > 1 (it is an n-step return along the behaviour)")
        if n_steps > 1 and optimize_memory_usage:
            raise ValueError("n_steps > 1 needs optimize_memory_usage=False (next observations are read from the n-th transition)")
        if isinstance(observation_space, spaces.Dict):
            raise ValueError(
                "PrioritizedReplayBuffer does not support Dict observation spaces; "
                "flatten the observation (e.g. gymnasium.wrappers.FlattenObservation) or use a Box space"
            )
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            optimize_memory_usage=optimize_memory_usage,
            handle_timeout_termination=handle_timeout_termination,
        )
        self.alpha = float(alpha)
        self.beta = float(beta)
        self.epsilon = float(epsilon)
        self.n_steps = int(n_steps)
        self.gamma = float(gamma)
        self.off_policy_lower_bound = bool(off_policy_lower_bound)
        self.tree = SumTree(self.buffer_size * self.n_envs)
        self.off_policy = np.zeros((self.buffer_size, self.n_envs), dtype=bool)
        # Seeded from the global NumPy state, which SB3's `set_random_seed` has fixed beforehand.
        self._rng = np.random.default_rng(np.random.randint(0, 2**31 - 1))

    def _row_indices(self, pos: int) -> np.ndarray:
        """Flat indices of the ``n_envs`` transitions stored at row ``pos``."""
        return pos * self.n_envs + np.arange(self.n_envs)

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        Store one transition per env with the largest priority currently stored (1.0 at first).

        Arguments as in SB3's ``ReplayBuffer.add``.
        """
        new_indices = self._row_indices(self.pos)
        self.off_policy[self.pos] = [bool(info.get("off_policy", False)) for info in infos]
        super().add(obs, next_obs, action, reward, done, infos)
        max_priority = self.tree.max_priority  # already p^alpha
        self.tree.update(new_indices, max_priority if max_priority > 0 else 1.0)
        if self.optimize_memory_usage and self.full:
            # observations[pos] now holds the next observation of the transition just added, so
            # the transition stored at `pos` is invalid until overwritten.
            self.tree.update(self._row_indices(self.pos), 0.0)

    def reset(self) -> None:
        """Empty the buffer and zero every priority."""
        super().reset()
        if hasattr(self, "tree"):
            self.tree = SumTree(self.tree.capacity)
            self.off_policy[:] = False

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray | th.Tensor) -> None:
        """
        Set ``p_i = |delta_i| + epsilon`` for the given transitions (the tree stores ``p_i^alpha``).

        :param indices: Flat buffer indices as returned in ``PrioritizedReplayBufferSamples.indices``.
        :param td_errors: TD errors ``delta_i`` of those transitions, any shape with ``len(indices)``
            elements (NumPy array or torch tensor).
        """
        if isinstance(td_errors, th.Tensor):
            td_errors = td_errors.detach().cpu().numpy()
        indices = np.asarray(indices).reshape(-1)
        td_errors = np.asarray(td_errors, dtype=np.float64).reshape(-1)
        if td_errors.shape != indices.shape:
            raise ValueError(f"td_errors must have one value per index ({indices.size}), got {td_errors.size}")
        priorities = (np.abs(td_errors) + self.epsilon) ** self.alpha
        if self.optimize_memory_usage and self.full:
            priorities[indices // self.n_envs == self.pos] = 0.0
        self.tree.update(indices, priorities)

    def sample(  # type: ignore[override]
        self, batch_size: int, env: VecNormalize | None = None
    ) -> PrioritizedReplayBufferSamples:
        """
        Draw ``batch_size`` transitions with probability ``P(i)`` (stratified over the total).

        :param batch_size: Number of transitions, ``>= 1``.
        :param env: Associated VecNormalize to normalize the observations/rewards, if any.
        :return: The batch, with importance-sampling weights of shape ``(batch_size, 1)`` and the
            flat indices of the drawn transitions.
        """
        if self.size() == 0:
            raise ValueError("cannot sample from an empty PrioritizedReplayBuffer; add transitions first")
        indices, scaled_priorities = self.tree.sample(batch_size, self._rng)
        total = self.tree.total
        n_stored = self.size() * self.n_envs  # N (it cancels out in the normalised weight)
        probabilities = scaled_priorities / total  # P(i) = p_i^alpha / sum_k p_k^alpha
        min_probability = self.tree.min_priority / total
        # w_i = (N * P(i))^-beta / max_j w_j, the max being reached at the smallest P(j)
        weights = (n_stored * probabilities) ** (-self.beta) / (n_stored * min_probability) ** (-self.beta)

        batch_inds, env_inds = np.divmod(indices, self.n_envs)
        if self.n_steps > 1:
            rewards, last_rows, discounts = self._n_step_returns(batch_inds, env_inds, env)
        else:
            rewards = self._normalize_reward(self.rewards[batch_inds, env_inds].reshape(-1, 1), env)
            last_rows, discounts = batch_inds, None
        next_obs, dones = self._closing(last_rows, env_inds, env)
        behaviour: dict[str, th.Tensor] = {}
        if self.off_policy_lower_bound:
            b_rewards, b_last_rows, b_discounts = self._n_step_returns(batch_inds, env_inds, env, behaviour=True)
            b_next_obs, b_dones = self._closing(b_last_rows, env_inds, env)
            behaviour = dict(
                behaviour_rewards=self.to_torch(b_rewards.astype(np.float32)),
                behaviour_next_observations=self.to_torch(b_next_obs),
                behaviour_dones=self.to_torch(b_dones),
                behaviour_discounts=self.to_torch(b_discounts),
            )
        return PrioritizedReplayBufferSamples(
            observations=self.to_torch(self._normalize_obs(self.observations[batch_inds, env_inds, :], env)),
            actions=self.to_torch(self.actions[batch_inds, env_inds, :]),
            next_observations=self.to_torch(next_obs),
            dones=self.to_torch(dones),
            rewards=self.to_torch(rewards.astype(np.float32)),
            discounts=None if discounts is None else self.to_torch(discounts),
            weights=self.to_torch(weights.astype(np.float32).reshape(-1, 1)),
            indices=indices,
            **behaviour,
        )

    def _closing(
        self, last_rows: np.ndarray, env_inds: np.ndarray, env: VecNormalize | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The (normalised) next observation and the done flag ``(B, 1)`` of the transition closing a return."""
        if self.optimize_memory_usage:
            next_obs = self.observations[(last_rows + 1) % self.buffer_size, env_inds, :]
        else:
            next_obs = self.next_observations[last_rows, env_inds, :]
        # Only use dones that are not due to timeouts
        dones = self.dones[last_rows, env_inds] * (1 - self.timeouts[last_rows, env_inds])
        return self._normalize_obs(next_obs, env), dones.reshape(-1, 1)

    def _n_step_returns(
        self, batch_inds: np.ndarray, env_inds: np.ndarray, env: VecNormalize | None, behaviour: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The n-step return from each drawn transition: it runs over the transitions stored after it
        (same env) and stops at the first terminal or timeout, at the newest transition, after n, or before
        an off-policy transition; an off-policy transition is a one-step return. ``behaviour``: off-policy
        transitions do not stop it (the return along the stored behaviour, a lower bound).

        :return: the returns ``(B, 1)``, the buffer row of the last transition summed (its next
            observation and done flag close the return), and the bootstrap discounts ``gamma^m`` ``(B, 1)``
        """
        steps = np.arange(self.n_steps)
        rows = (batch_inds[:, None] + steps) % self.buffer_size  # (B, n)
        cols = env_inds[:, None]
        newer = (self.pos - 1 - batch_inds) % self.buffer_size  # transitions of this env stored after the drawn one
        stop = self.dones[rows, cols].astype(bool) | self.timeouts[rows, cols].astype(bool) | (steps >= newer[:, None])
        off_policy = self.off_policy[rows, cols]
        next_off_policy = self.off_policy[(rows + 1) % self.buffer_size, cols]
        if not behaviour:
            stop |= off_policy | next_off_policy  # a relabelled transition stands alone and ends an own return
        stop[:, -1] = True
        last = stop.argmax(axis=1)  # m - 1: the index of the last transition summed
        mask = steps[None, :] <= last[:, None]
        rewards = self._normalize_reward(self.rewards[rows, cols], env)
        returns = (rewards * self.gamma ** steps[None, :] * mask).sum(axis=1, keepdims=True)
        discounts = (self.gamma ** (last + 1)).astype(np.float32).reshape(-1, 1)
        return returns, rows[np.arange(len(rows)), last], discounts


# ---------------------------------------------------------------------- replay buffers in a file


def buffer_state(buffer: Any, capacity: int, filled: int, skip: Collection[str] = ("device",)) -> dict[str, Any]:
    """What a replay buffer holds, for a file: its arrays of ``capacity`` rows cut to the ``filled`` rows in use (a
    buffer allocated for 500,000 sub-goal choices writes the ones it has stored), every other attribute as it is,
    but those of ``skip`` (what the live buffer rebuilds: functions, devices)."""
    attributes = {}
    for name, value in vars(buffer).items():
        if name in skip:
            continue
        if isinstance(value, np.ndarray) and value.ndim > 0 and value.shape[0] == capacity:
            value = value[:filled]
        attributes[name] = value
    return {"class": type(buffer).__name__, "capacity": int(capacity), "filled": int(filled), "attributes": attributes}


def load_buffer_state(buffer: Any, state: dict[str, Any], capacity: int, what: str,
                      progress: Collection[str] = ("pos", "full")) -> None:
    """Fill the live ``buffer`` with a :func:`buffer_state`: its rows and the rest of what it stored (priorities, draws'
    generator, ...). Settings (numbers, strings, shapes, spaces) must be the live buffer's own, but ``progress`` (where
    it writes next): a file saved with another buffer size, number of envs or n-step length is refused, naming the
    setting. Rows past the stored ones are never read."""
    if not isinstance(state, dict) or "attributes" not in state:
        raise ValueError(f"{what}: the file holds no saved replay buffer")
    if state.get("class") != type(buffer).__name__:
        raise ValueError(f"{what}: the file holds a {state.get('class')}, the model a {type(buffer).__name__}")
    saved_envs, live_envs = state["attributes"].get("n_envs"), getattr(buffer, "n_envs", None)
    if saved_envs is not None and live_envs is not None and saved_envs != live_envs:
        raise ValueError(f"{what}: the file's buffer holds the transitions of {saved_envs} envs, the model steps "
                         f"{live_envs}: give the model as many envs as it was saved with")
    if state["capacity"] != capacity:
        raise ValueError(f"{what}: the file's buffer holds {state['capacity']} rows, the model's {capacity}: build the "
                         "model with the buffer size it was saved with")
    live = vars(buffer)
    for name, value in state["attributes"].items():
        current = live.get(name)
        if name not in live:
            raise ValueError(f"{what}: the file's buffer has {name!r}, which this version's {type(buffer).__name__} has not")
        if isinstance(value, np.ndarray) and isinstance(current, np.ndarray) and current.ndim > 0 and current.shape[0] == capacity:
            if current.shape[1:] != value.shape[1:] or current.dtype != value.dtype:
                raise ValueError(f"{what}: the file stores {name} as {value.shape[1:]} {value.dtype}, the model as "
                                 f"{current.shape[1:]} {current.dtype} (another observation space or number of envs)")
            current[: len(value)] = value
        elif name not in progress and isinstance(current, (int, float, str, tuple, np.number, spaces.Space)):
            if not current == value:
                raise ValueError(f"{what}: the file's buffer was saved with {name}={value!r}, the model's has "
                                 f"{current!r}: load it into a model built with the same settings")
        else:
            live[name] = value
