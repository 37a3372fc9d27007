"""Double DQN (van Hasselt et al., 2016) with prioritized replay (Schaul et al., 2016) on SB3's DQN.

The paper trains both levels of the hierarchy with "DDQN with prioritized experience replay
(alpha = 0.6, beta = 0.4)" (section 5.1). :class:`DoubleDQN` changes only SB3's ``DQN.train`` and
adds the three hooks the hierarchical algorithm needs:

- ``DoubleDQN._rewards``: the reward column used in the TD target (a subclass may recompute
  rewards at sample time, e.g. the meta-reward of eq. 3 from the current preference predictor);
- :attr:`DoubleDQN.valid_actions`: a boolean mask over the discrete actions, honoured by the TD
  target, by greedy action selection and by epsilon-greedy exploration; :meth:`DoubleDQN.action_mask`
  may narrow it state by state;
- :meth:`DoubleDQN.resize_action_space`: grow the discrete action space (a new sub-goal) while
  keeping every learnt Q-value.
"""

from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, ReplayBufferSamples, Schedule
from stable_baselines3.common.utils import get_parameters_by_name
from stable_baselines3.dqn.policies import CnnPolicy, DQNPolicy, MlpPolicy, MultiInputPolicy
from torch.nn import functional as F

from sb3_hhp.dqn.buffers import PrioritizedReplayBuffer, PrioritizedReplayBufferSamples

SelfDoubleDQN = TypeVar("SelfDoubleDQN", bound="DoubleDQN")


def double_q_target(
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    gamma: float | th.Tensor,
    valid_actions: th.Tensor | None = None,
) -> th.Tensor:
    """
    Double Q-learning target ``y = r + gamma * (1 - done) * Q_target(s', argmax_a Q_online(s', a))``.

    The online network chooses the next action and the target network evaluates it (van Hasselt
    et al., 2016). Passing ``next_q_online = next_q_target`` gives the plain DQN target
    ``r + gamma * (1 - done) * max_a Q_target(s', a)``.

    :param next_q_online: Online Q-values of the next states, shape ``(B, A)``.
    :param next_q_target: Target-network Q-values of the next states, shape ``(B, A)``.
    :param rewards: Rewards, shape ``(B, 1)``.
    :param dones: Terminal flags in ``{0, 1}`` (timeouts excluded), shape ``(B, 1)``.
    :param gamma: Discount factor in ``[0, 1]``, a float or a tensor of shape ``(B, 1)``
        (per-sample discounts of n-step returns).
    :param valid_actions: Optional boolean mask of shape ``(A,)`` or ``(B, A)``; invalid actions are
        never chosen by the argmax. At least one action per row must be valid.
    :return: The targets, shape ``(B, 1)``.
    """
    if next_q_online.shape != next_q_target.shape or next_q_online.ndim != 2:
        raise ValueError(
            f"next_q_online and next_q_target must both have shape (B, A), got {tuple(next_q_online.shape)} "
            f"and {tuple(next_q_target.shape)}"
        )
    if valid_actions is not None:
        valid_actions = valid_actions.to(device=next_q_online.device, dtype=th.bool)
        next_q_online = next_q_online.masked_fill(~valid_actions, -th.inf)
    next_actions = next_q_online.argmax(dim=1, keepdim=True)
    next_q = th.gather(next_q_target, dim=1, index=next_actions)
    return rewards.reshape(-1, 1) + gamma * (1 - dones.reshape(-1, 1)) * next_q


def _fixed_extractor(q_net: th.nn.Module) -> bool:
    """Whether an SB3 ``QNetwork``'s features extractor has no parameters (the same function in every copy)."""
    return next(iter(q_net.features_extractor.parameters()), None) is None


class DoubleDQN(DQN):
    """
    Double DQN with proportional prioritized experience replay.

    Same arguments as SB3's :class:`~stable_baselines3.DQN` (see its documentation), plus:

    :param double_q: Select the next action with the online network and evaluate it with the
        target network (Double DQN); ``False`` gives the plain DQN target.
    :param prioritized_replay: Use :class:`~sb3_hhp.dqn.buffers.PrioritizedReplayBuffer` (when no
        ``replay_buffer_class`` is given), weight the per-sample Huber loss by the importance
        weights and update the priorities with the absolute TD errors.
    :param prioritized_replay_alpha: Prioritization exponent in ``[0, 1]``.
    :param prioritized_replay_beta: Importance-sampling exponent in ``[0, 1]``.
    :param prioritized_replay_eps: Constant ``> 0`` added to ``|td error|`` in the priorities.

    ``n_steps`` > 1 gives n-step returns under prioritized replay too (the buffer computes them).

    Hooks for subclasses and the hierarchical algorithm:

    - ``_rewards(replay_data)``: the reward column of the TD target; default ``replay_data.rewards``.
    - ``valid_actions``: ``None`` (every action valid) or a boolean array of shape ``(n_actions,)``;
      invalid actions are excluded from the target's argmax, from ``predict`` (greedy and
      epsilon-greedy) and from the random warm-up actions.
    - ``action_mask(observations)``: the actions allowed in each state, shape ``(B, n_actions)`` (or
      ``(n_actions,)`` for all); default ``valid_actions``. Used by the same three.
    - ``resize_action_space(n_actions)``: grow the discrete action space, keeping old Q-values.
    - ``_q_offset(observations)``: a known part of the Q-values, ``(B, n_actions)``, added to both networks'
      outputs wherever Q-values are read (targets, the loss, ``predict``); default ``None`` (nothing added). It is
      no parameter: the networks learn the rest.

    The importance weighting applies whenever the replay buffer is a ``PrioritizedReplayBuffer``.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }

    def __init__(
        self,
        policy: str | type[DQNPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 32,
        tau: float = 1.0,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 4,
        gradient_steps: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        target_update_interval: int = 10000,
        exploration_fraction: float = 0.1,
        exploration_initial_eps: float = 1.0,
        exploration_final_eps: float = 0.05,
        max_grad_norm: float = 10,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        double_q: bool = True,
        prioritized_replay: bool = True,
        prioritized_replay_alpha: float = 0.6,
        prioritized_replay_beta: float = 0.4,
        prioritized_replay_eps: float = 1e-6,
        _init_setup_model: bool = True,
    ) -> None:
        if not isinstance(double_q, bool):
            raise ValueError(f"double_q must be a bool, got {double_q!r}")
        if not isinstance(prioritized_replay, bool):
            raise ValueError(f"prioritized_replay must be a bool, got {prioritized_replay!r}")
        if not 0.0 <= prioritized_replay_alpha <= 1.0:
            raise ValueError(f"prioritized_replay_alpha must be in [0, 1], got {prioritized_replay_alpha}")
        if not 0.0 <= prioritized_replay_beta <= 1.0:
            raise ValueError(f"prioritized_replay_beta must be in [0, 1], got {prioritized_replay_beta}")
        if not prioritized_replay_eps > 0.0:
            raise ValueError(f"prioritized_replay_eps must be > 0, got {prioritized_replay_eps}")
        if prioritized_replay and replay_buffer_class is None:
            replay_buffer_class = PrioritizedReplayBuffer
            replay_buffer_kwargs = {
                **(replay_buffer_kwargs or {}),
                "alpha": prioritized_replay_alpha,
                "beta": prioritized_replay_beta,
                "epsilon": prioritized_replay_eps,
                "n_steps": n_steps,
                "gamma": gamma,
            }
        self.double_q = double_q
        self.prioritized_replay = prioritized_replay
        self.prioritized_replay_alpha = prioritized_replay_alpha
        self.prioritized_replay_beta = prioritized_replay_beta
        self.prioritized_replay_eps = prioritized_replay_eps
        self._valid_actions: np.ndarray | None = None
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            target_update_interval=target_update_interval,
            exploration_fraction=exploration_fraction,
            exploration_initial_eps=exploration_initial_eps,
            exploration_final_eps=exploration_final_eps,
            max_grad_norm=max_grad_norm,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=_init_setup_model,
        )

    def _setup_model(self) -> None:
        # The prioritized buffer computes n-step returns itself (n_steps is in its kwargs); SB3 would
        # otherwise warn that n_steps is ignored for a custom buffer class.
        n_steps = self.n_steps
        if self.replay_buffer_class is PrioritizedReplayBuffer:
            self.n_steps = 1
        try:
            super()._setup_model()
        finally:
            self.n_steps = n_steps
        if getattr(self.replay_buffer, "off_policy_lower_bound", False) and type(self)._rewards is not DoubleDQN._rewards:
            raise ValueError(
                f"{type(self).__name__} recomputes its rewards when it samples (_rewards), which the stored behaviour "
                "returns of off_policy_lower_bound would not see; leave replay_buffer_kwargs['off_policy_lower_bound'] off"
            )

    # ------------------------------------------------------------------ hooks

    @property
    def valid_actions(self) -> np.ndarray | None:
        """Boolean mask of shape ``(n_actions,)`` over the discrete actions, or ``None`` (all valid)."""
        return self._valid_actions

    @valid_actions.setter
    def valid_actions(self, mask: np.ndarray | None) -> None:
        if mask is None:
            self._valid_actions = None
            return
        mask = np.asarray(mask)
        n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
        if mask.shape != (n_actions,):
            raise ValueError(f"valid_actions must have shape ({n_actions},), got {mask.shape}")
        if mask.dtype != np.bool_:
            raise ValueError(f"valid_actions must be a boolean array, got dtype {mask.dtype}")
        if not mask.any():
            raise ValueError("valid_actions must allow at least one action, got an all-False mask")
        self._valid_actions = mask.copy()

    def _discounts(self, replay_data: ReplayBufferSamples | PrioritizedReplayBufferSamples) -> float | th.Tensor:
        """The bootstrap's discount of each sampled transition: ``gamma^n`` of an n-step return (when no early
        termination), else ``gamma``."""
        return replay_data.discounts if replay_data.discounts is not None else self.gamma

    def _rewards(self, replay_data: ReplayBufferSamples | PrioritizedReplayBufferSamples) -> th.Tensor:
        """
        Reward column used in the TD target, shape ``(B, 1)``.

        Override to recompute rewards when a batch is sampled (e.g. from a reward model that keeps
        learning); the default returns the stored ``replay_data.rewards``.

        :param replay_data: The sampled batch.
        :return: Rewards of shape ``(B, 1)`` on ``self.device``.
        """
        return replay_data.rewards

    def _q_offset(self, observations: th.Tensor) -> th.Tensor | None:
        """
        A known part of the Q-values of a batch of observations, ``(B, n_actions)``, added to the online and the
        target network's outputs wherever they are read; ``None`` (the default): nothing is added.

        :param observations: A batch of observations as the networks read them (a tensor on ``self.device``).
        """
        return None

    def _q_values(self, observations: th.Tensor, network: th.nn.Module | None = None) -> th.Tensor:
        """The Q-values of a batch: ``network`` (default the online network) plus :meth:`_q_offset`."""
        q_values = (self.q_net if network is None else network)(observations)
        offset = self._q_offset(observations)
        return q_values if offset is None else q_values + offset

    def action_mask(self, observations: np.ndarray | dict[str, np.ndarray]) -> np.ndarray | None:
        """
        The actions allowed in each state of a batch: a boolean array ``(B, n_actions)``, one mask
        ``(n_actions,)`` for every state, or ``None`` (all actions). Default: :attr:`valid_actions`.
        Override to rule out actions state by state; each row must allow at least one action.

        :param observations: A batch of observations (NumPy, as stored in the replay buffer).
        """
        return self._valid_actions

    def _valid_actions_tensor(self, observations: np.ndarray | dict[str, np.ndarray] | None = None) -> th.Tensor | None:
        mask = self._valid_actions if observations is None else self.action_mask(observations)
        if mask is None:
            return None
        return th.as_tensor(mask, device=self.device)

    def _random_actions(self, n: int, mask: np.ndarray | None = None) -> np.ndarray:
        """``n`` actions drawn uniformly among the allowed ones (``mask``: ``(n_actions,)`` or one row per
        action; default :attr:`valid_actions`), with the action space's generator."""
        assert isinstance(self.action_space, spaces.Discrete)
        mask = self._valid_actions if mask is None else mask
        start, rng = int(self.action_space.start), self.action_space.np_random
        if mask is None:
            return rng.choice(int(self.action_space.n), size=n) + start
        if mask.ndim == 1:
            return rng.choice(np.flatnonzero(mask), size=n) + start
        return np.array([rng.choice(np.flatnonzero(row)) for row in mask]) + start

    # --------------------------------------------------------------- training

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """``gradient_steps`` Double DQN updates on prioritized batches: the online network picks the next action, the
        target network values it (:func:`double_q_target`), and the batch's priorities become its TD errors."""
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        # Update learning rate according to schedule
        self._update_learning_rate(self.policy.optimizer)
        prioritized = isinstance(self.replay_buffer, PrioritizedReplayBuffer)
        state_masks = type(self).action_mask is not DoubleDQN.action_mask  # else one mask for every state
        valid_actions = self._valid_actions_tensor()

        losses, td_errors_abs, weights_mean = [], [], []
        for _ in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = self._discounts(replay_data)

            with th.no_grad():
                target_q_values = self._target(replay_data.next_observations, self._rewards(replay_data),
                                               replay_data.dones, discounts, state_masks, valid_actions)
                if getattr(replay_data, "behaviour_rewards", None) is not None:
                    # optimality tightening: the behaviour's n-step return is a lower bound
                    target_q_values = th.maximum(target_q_values, self._target(
                        replay_data.behaviour_next_observations, replay_data.behaviour_rewards,
                        replay_data.behaviour_dones, replay_data.behaviour_discounts, state_masks, valid_actions))

            current_q_values = th.gather(self._q_values(replay_data.observations), dim=1, index=replay_data.actions.long())

            # Per-sample Huber loss, weighted by the importance-sampling weights under PER
            elementwise_loss = F.smooth_l1_loss(current_q_values, target_q_values, reduction="none")
            if prioritized:
                loss = (replay_data.weights * elementwise_loss).mean()  # type: ignore[union-attr]
                weights_mean.append(replay_data.weights.mean().item())  # type: ignore[union-attr]
            else:
                loss = elementwise_loss.mean()
            losses.append(loss.item())

            self.policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()

            td_errors = (target_q_values - current_q_values).detach().abs().reshape(-1).cpu().numpy()
            td_errors_abs.append(float(td_errors.mean()))
            if prioritized:
                # p_i = |delta_i| + epsilon
                self.replay_buffer.update_priorities(replay_data.indices, td_errors)  # type: ignore[union-attr]

        self._n_updates += gradient_steps

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", np.mean(losses))
        self.logger.record("train/td_error", np.mean(td_errors_abs))
        if weights_mean:
            self.logger.record("train/is_weight", np.mean(weights_mean))

    def _target(self, next_obs: th.Tensor, rewards: th.Tensor, dones: th.Tensor, discounts: float | th.Tensor,
                state_masks: bool, valid_actions: th.Tensor | None) -> th.Tensor:
        """The double-Q target of returns closed by ``next_obs`` (per-state masks when ``state_masks``)."""
        if state_masks:
            valid_actions = self._valid_actions_tensor(next_obs.cpu().numpy())
        online, target = self.q_net, self.q_net_target
        if self.double_q and _fixed_extractor(online):
            # a features extractor without parameters (a fixed description; the target is a copy of the online
            # network, so the same one): both networks read one extraction
            features = online.extract_features(next_obs, online.features_extractor)
            next_q_target, next_q_online = target.q_net(features), online.q_net(features)
            offset = self._q_offset(next_obs)
            if offset is not None:
                next_q_target, next_q_online = next_q_target + offset, next_q_online + offset
        else:
            next_q_target = self._q_values(next_obs, target)
            next_q_online = self._q_values(next_obs, online) if self.double_q else next_q_target
        return double_q_target(next_q_online, next_q_target, rewards, dones, discounts, valid_actions=valid_actions)

    # ------------------------------------------------------- action selection

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        Epsilon-greedy action selection restricted to ``valid_actions`` (all actions when ``None``).

        :param observation: The input observation (single or vectorized).
        :param state: Unused (no recurrent state), returned as is.
        :param episode_start: Unused.
        :param deterministic: Greedy actions only, no exploration.
        :return: The actions and ``state``.
        """
        vectorized = self.policy.is_vectorized_observation(observation)
        if isinstance(observation, dict):
            batch = observation if vectorized else {key: np.asarray(value)[None] for key, value in observation.items()}
        else:
            batch = observation if vectorized else np.asarray(observation)[None]
        mask = self.action_mask(batch)
        if mask is None and type(self)._q_offset is DoubleDQN._q_offset:
            return super().predict(observation, state, episode_start, deterministic)
        if not deterministic and np.random.rand() < self.exploration_rate:
            if vectorized:
                first = observation[next(iter(observation.keys()))] if isinstance(observation, dict) else observation
                return self._random_actions(first.shape[0], mask), state
            return np.array(self._random_actions(1, mask)[0]), state
        self.policy.set_training_mode(False)
        obs_tensor, vectorized = self.policy.obs_to_tensor(observation)
        with th.no_grad():
            q_values = self._q_values(obs_tensor)
        if mask is not None:
            q_values = q_values.masked_fill(~th.as_tensor(mask, device=q_values.device), -th.inf)
        actions = q_values.argmax(dim=1).cpu().numpy() + int(self.action_space.start)  # type: ignore[attr-defined]
        if not vectorized:
            actions = actions.squeeze(axis=0)
        return actions, state

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: Any = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        # Warm-up actions are uniform over the allowed actions only; afterwards `predict` decides.
        if self.num_timesteps < learning_starts:
            mask = self.action_mask(self._last_obs)
            if mask is not None:
                action = self._random_actions(n_envs, mask)
                return action, action
        return super()._sample_action(learning_starts, action_noise, n_envs)

    # ------------------------------------------------------ growing the space

    def resize_action_space(self, n_actions: int) -> None:
        """
        Grow the discrete action space to ``n_actions`` actions, keeping what was learnt.

        The policy (online and target Q-networks) is rebuilt for the new space; every old weight
        is copied (for the output layer, the first ``old_n`` rows and biases), so the Q-values of
        the old actions are unchanged while the new actions start from a fresh initialisation.
        The optimizer is re-created (its moment estimates are lost). ``valid_actions``, if set,
        marks the new actions valid. The replay buffer is kept.

        :param n_actions: New number of actions, ``>= action_space.n``.
        """
        if not isinstance(self.action_space, spaces.Discrete):
            raise ValueError(f"resize_action_space needs a Discrete action space, got {self.action_space}")
        old_n = int(self.action_space.n)
        if isinstance(n_actions, bool) or not isinstance(n_actions, (int, np.integer)) or n_actions < old_n:
            raise ValueError(f"n_actions must be an int >= the current number of actions ({old_n}), got {n_actions!r}")
        n_actions = int(n_actions)
        if n_actions == old_n:
            return
        new_space = spaces.Discrete(n_actions, start=int(self.action_space.start))
        new_space.seed(int(self.action_space.np_random.integers(2**31 - 1)))

        old_state = self.policy.state_dict()
        new_policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space,
            new_space,
            self.lr_schedule,
            **self.policy_kwargs,
        ).to(self.device)
        new_state = new_policy.state_dict()
        with th.no_grad():
            for name, old_value in old_state.items():
                new_value = new_state[name]
                if new_value.shape == old_value.shape:
                    new_value.copy_(old_value)
                elif new_value.ndim == old_value.ndim and all(n >= o for n, o in zip(new_value.shape, old_value.shape)):
                    new_value[tuple(slice(0, size) for size in old_value.shape)] = old_value
                else:
                    raise RuntimeError(f"cannot copy {name}: old shape {tuple(old_value.shape)}, new {tuple(new_value.shape)}")
        new_policy.load_state_dict(new_state)
        new_policy.set_training_mode(self.policy.training)

        self.policy = new_policy  # type: ignore[assignment]
        self.action_space = new_space
        self._create_aliases()
        self.batch_norm_stats = get_parameters_by_name(self.q_net, ["running_"])
        self.batch_norm_stats_target = get_parameters_by_name(self.q_net_target, ["running_"])
        if self.replay_buffer is not None:
            self.replay_buffer.action_space = new_space
        if self._valid_actions is not None:
            self._valid_actions = np.concatenate([self._valid_actions, np.ones(n_actions - old_n, dtype=bool)])

    def learn(
        self: SelfDoubleDQN,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DoubleDQN",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDoubleDQN:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
