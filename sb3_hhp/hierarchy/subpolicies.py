"""One SB3 ``DDPG`` model per sub-goal, trained online while it acts: the learners of continuous (Box) actions.

Discrete actions use :class:`~sb3_hhp.hierarchy.learners.StackedDQN` (every sub-goal's learner stacked over
one shared replay). Continuous actions (Fetch) give each sub-goal ``g`` its own SB3 ``DDPG`` with its own
buffer: :class:`PerGoalLearners` drives them with the same interface, one primitive step at a time
(Algorithm 1, lines 15-20): act, store the transition with the reward of eq. 6, one gradient step. Its cost
grows with the number of sub-goals.
"""

from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import VecTransposeImage

from sb3_hhp.dqn.buffers import buffer_state, load_buffer_state
from sb3_hhp.hierarchy.learner_kwargs import check_learners_state


class SpacesEnv(gym.Env):
    """A stand-in env that only carries spaces, so SB3 learners can be built without a real env."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):  # pragma: no cover - never stepped
        raise RuntimeError("SpacesEnv only carries spaces; subpolicies are stepped by PerGoalLearners")

    def step(self, action):  # pragma: no cover - never stepped
        raise RuntimeError("SpacesEnv only carries spaces; subpolicies are stepped by PerGoalLearners")


def default_subpolicy_kwargs() -> dict[str, Any]:
    """The paper's defaults (section 5.1) for a sub-goal's DDPG: Adam lr 1e-3, batch 128, buffers of 50K, 256x256
    units, an update every step."""
    return dict(
        learning_rate=1e-3, buffer_size=50_000, learning_starts=500, batch_size=128, gamma=0.99, train_freq=1,
        # fused Adam: one kernel per update instead of one per tensor, ~1 ms less per update on a CPU
        policy_kwargs=dict(net_arch=[256, 256], optimizer_kwargs=dict(fused=True)),
    )


class Subpolicy:
    """One sub-goal's learner, stepped by hand (no ``learn`` loop).

    :param model: the SB3 off-policy model of Box actions (its ``learn`` is never called)
    :param exploration_steps: own steps over which the model's progress (``_current_progress_remaining``) runs out

    The model's own ``train_freq`` (counted in steps) and ``gradient_steps`` say how often it learns
    (1 and 1 in the paper).
    """

    def __init__(self, model: OffPolicyAlgorithm, exploration_steps: int) -> None:
        self.model = model
        self.exploration_steps = exploration_steps
        if model.train_freq.unit.value != "step":
            raise ValueError(f"A subpolicy's train_freq counts its own steps, got the unit {model.train_freq.unit.value!r}")
        self.train_freq = model.train_freq.frequency
        if self.train_freq < 1 or model.gradient_steps < 1:
            raise ValueError(f"A subpolicy needs train_freq >= 1 and gradient_steps >= 1, got {self.train_freq} and "
                             f"{model.gradient_steps}")
        self.num_steps = 0  # own steps (acting for its sub-goal)
        self.num_ticks = 0  # learning ticks (own steps, plus shared steps with train_shared)
        self.successes = 0
        self.attempts = 0
        self.recent: list[bool] = []
        # SB3 builds image learners channel first (VecTransposeImage); PerGoalLearners hands over env observations
        self._transpose = isinstance(model.env, VecTransposeImage)

    def _model_obs(self, batch: np.ndarray) -> np.ndarray:
        """A batch of env observations in the layout the model was built for."""
        return VecTransposeImage.transpose_image(batch) if self._transpose else batch

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """One primitive action for one observation (with the model's action noise unless deterministic)."""
        model = self.model
        action, _ = model.predict(obs, deterministic=True)
        if not deterministic and model.action_noise is not None:
            action = np.clip(action + model.action_noise(), model.action_space.low, model.action_space.high)
        return action

    def store(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: float, done: bool,
              timeout: bool = False, off_policy: bool = False) -> None:
        """Add one transition to this subpolicy's buffer D_g (Algorithm 1 line 19), without training.
        ``timeout``: cut here by a time limit, the episode's or the sub-goal's (bootstrapped, but n-step returns stop).
        ``off_policy``: another subpolicy acted (relabelled experience): a prioritized buffer keeps it a
        one-step transition, outside every n-step return."""
        model = self.model
        buffer_action = model.policy.scale_action(action)
        model.replay_buffer.add(  # type: ignore[union-attr]
            self._model_obs(obs[None]), self._model_obs(next_obs[None]), np.asarray([buffer_action]), np.asarray([reward], np.float32),
            np.asarray([done or timeout]), [{"TimeLimit.truncated": timeout and not done, "off_policy": off_policy}],
        )

    def observe(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: float, done: bool,
                timeout: bool = False) -> None:
        """Store one transition of its own (Algorithm 1 line 19) and take a gradient step (line 20).
        ``timeout``: its try was cut here by a time limit (the sub-goal's or the episode's), see :meth:`store`."""
        model = self.model
        self.store(obs, next_obs, action, reward, done, timeout=timeout)
        self.num_steps += 1
        model.num_timesteps = self.num_steps
        model._current_progress_remaining = max(0.0, 1.0 - self.num_steps / self.exploration_steps)
        self.learn_step()

    def learn_step(self) -> None:
        """One learning tick: ``gradient_steps`` gradient steps every ``train_freq`` ticks once the buffer is
        ready (DDPG's target networks follow by Polyak averaging inside each). A tick is an own step, or with
        ``train_shared`` any primitive step whose transition was stored for this subpolicy."""
        model = self.model
        self.num_ticks += 1
        ready = model.replay_buffer.size() >= max(model.learning_starts, model.batch_size)  # type: ignore[union-attr]
        if ready and self.num_ticks % self.train_freq == 0:
            model.train(gradient_steps=model.gradient_steps, batch_size=model.batch_size)

    def record_outcome(self, success: bool, window: int = 100) -> None:
        self.attempts += 1
        self.successes += int(success)
        self.recent.append(success)
        if len(self.recent) > window:
            del self.recent[0]

    @property
    def success_rate(self) -> Optional[float]:
        return float(np.mean(self.recent)) if self.recent else None


class SubpolicySet:
    """Builds and holds one :class:`Subpolicy`, an SB3 ``DDPG``, per sub-goal.

    :param observation_space: the primitive observation space
    :param action_space: the primitive action space (a Box; discrete actions have
        :class:`~sb3_hhp.hierarchy.learners.StackedDQN`)
    :param policy: SB3 policy name for the subpolicies ("MlpPolicy", "CnnPolicy", ...)
    :param subpolicy_kwargs: SB3 DDPG's keyword arguments for the subpolicy models (over the paper's defaults)
    :param exploration_steps: own steps over which a new subpolicy's progress runs out (SB3's schedules)
    :param logger: the logger given to every subpolicy model (a silent one by default)
    :param device: torch device
    :param seed: base seed; subpolicy ``i`` gets ``seed + i``
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        policy: str = "MlpPolicy",
        subpolicy_kwargs: Optional[dict[str, Any]] = None,
        exploration_steps: int = 5_000,
        logger: Optional[Logger] = None,
        device: str | th.device = "auto",
        seed: Optional[int] = None,
    ) -> None:
        if not isinstance(action_space, spaces.Box):
            raise ValueError(f"SubpolicySet builds DDPG learners of Box actions, got {action_space}: the learners of "
                             "Discrete actions are sb3_hhp.hierarchy.learners.StackedDQN")
        if exploration_steps < 1:
            raise ValueError(f"exploration_steps must be >= 1, got {exploration_steps}")
        self.observation_space = observation_space
        self.action_space = action_space
        self.policy = policy
        self.kwargs = {**default_subpolicy_kwargs(), **(subpolicy_kwargs or {})}
        self.exploration_steps = exploration_steps
        self.logger = logger or Logger(folder=None, output_formats=[])
        self.device = device
        self.seed = seed
        self.policies: list[Subpolicy] = []

    def __len__(self) -> int:
        return len(self.policies)

    def __getitem__(self, index: int) -> Subpolicy:
        return self.policies[index]

    def add(self) -> Subpolicy:
        """A freshly initialised subpolicy for a new sub-goal (section 5.1: random initialisation)."""
        env = SpacesEnv(self.observation_space, self.action_space)
        seed = None if self.seed is None else self.seed + len(self.policies)
        kwargs = dict(self.kwargs)
        kwargs.setdefault("action_noise",
                          NormalActionNoise(np.zeros(self.action_space.shape), 0.1 * np.ones(self.action_space.shape)))
        model = DDPG(self.policy, env, device=self.device, seed=seed, **kwargs)
        model.set_logger(self.logger)
        model._current_progress_remaining = 1.0
        subpolicy = Subpolicy(model, self.exploration_steps)
        self.policies.append(subpolicy)
        return subpolicy

    def state_dict(self) -> list[dict[str, Any]]:
        """Weights, optimiser states and counters of every subpolicy (replay buffers are not saved, as in SB3)."""
        return [
            {
                "policy": sub.model.policy.state_dict(),
                "optimizers": [opt.state_dict() for opt in _optimizers(sub.model)],
                "num_steps": sub.num_steps,
                "num_ticks": sub.num_ticks,
                "n_calls": getattr(sub.model, "_n_calls", 0),
                "successes": sub.successes,
                "attempts": sub.attempts,
                "recent": list(sub.recent),
            }
            for sub in self.policies
        ]

    def load_state_dict(self, states: list[dict[str, Any]]) -> None:
        self.policies = []
        for state in states:
            sub = self.add()
            sub.model.policy.load_state_dict(state["policy"])
            for opt, opt_state in zip(_optimizers(sub.model), state["optimizers"]):
                opt.load_state_dict(opt_state)
            sub.num_steps = state["num_steps"]
            sub.num_ticks = state["num_ticks"]
            sub.model.num_timesteps = sub.num_steps
            sub.model._n_calls = state["n_calls"]
            sub.model._current_progress_remaining = max(0.0, 1.0 - sub.num_steps / self.exploration_steps)
            sub.successes, sub.attempts, sub.recent = state["successes"], state["attempts"], list(state["recent"])


def _optimizers(model: OffPolicyAlgorithm) -> list[th.optim.Optimizer]:
    """The actor's and the critic's optimizer of a DDPG model."""
    return [model.policy.actor.optimizer, model.policy.critic.optimizer]


class PerGoalLearners:
    """:class:`SubpolicySet` behind the interface of :class:`~sb3_hhp.hierarchy.learners.StackedDQN` (one env), for
    the DDPG sub-goals of Box actions.

    :param subpolicies: the subpolicy set
    :param achieved: ``done(s, g)`` from two sub-goal keys
    :param alpha: weight of the intrinsic reward in eq. 6
    :param share_experience: also store every transition in the other sub-goals' buffers with their own rewards
    :param train_shared: with ``share_experience``, every subpolicy counts every primitive step as a learning tick
    """

    def __init__(self, subpolicies: SubpolicySet, achieved: Any, alpha: float = 0.5, share_experience: bool = True,
                 train_shared: bool = False) -> None:
        self.subpolicies = subpolicies
        self.achieved = achieved
        self.alpha = alpha
        self.share_experience = share_experience
        self.train_shared = train_shared
        self.goal_keys: list[Any] = []

    def __len__(self) -> int:
        return len(self.subpolicies)

    def add(self, goal_key: Any) -> int:
        self.goal_keys.append(goal_key)
        self.subpolicies.add()
        return len(self) - 1

    def act(self, goals: np.ndarray, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        return np.stack([self.subpolicies[int(g)].act(o, deterministic=deterministic) for g, o in zip(goals, obs)])

    def observe(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray, keys: list, terminated: np.ndarray,
                truncated: np.ndarray, gave_up: np.ndarray, acting: np.ndarray, intrinsic: np.ndarray) -> None:
        """Each env's step: the acting subpolicy stores it with its eq. 5 / 6 reward and learns; with
        ``share_experience`` every other one stores it relabelled with its own reward (one-step)."""
        from sb3_hhp.hierarchy.rewards import pseudo_reward, subpolicy_reward

        for i, key in enumerate(keys):
            done = np.array([self.achieved(key, goal_key) for goal_key in self.goal_keys], dtype=bool)
            terminal = done | bool(terminated[i])
            rewards = subpolicy_reward(pseudo_reward(done, terminal), float(intrinsic[i]), self.alpha)  # eq. 5, 6
            rewards = np.atleast_1d(rewards)
            active = int(acting[i])
            for goal, sub in enumerate(self.subpolicies.policies):
                if goal == active:
                    cut = (bool(truncated[i]) or bool(gave_up[i])) and not terminal[goal]
                    sub.observe(obs[i], next_obs[i], actions[i], float(rewards[goal]), bool(terminal[goal]), timeout=cut)
                elif self.share_experience:
                    sub.store(obs[i], next_obs[i], actions[i], float(rewards[goal]), bool(terminal[goal]),
                              timeout=bool(truncated[i]), off_policy=True)
                    if self.train_shared:
                        sub.learn_step()

    def record_outcome(self, goal: int, success: bool) -> None:
        self.subpolicies[goal].record_outcome(success)

    def success_rate(self, goal: int) -> Optional[float]:
        return self.subpolicies[goal].success_rate

    def state_dict(self) -> dict[str, Any]:
        return {"format": "sb3_hhp.PerGoalLearners", "goal_keys": list(self.goal_keys), "subpolicies": self.subpolicies.state_dict()}

    def replay_state(self) -> dict[str, Any]:
        """Every subpolicy's SB3 replay buffer, the rows in use, for a file (:meth:`~sb3_hhp.hhp.hhp.HhP.save_replay_buffer`)."""
        buffers = [policy.model.replay_buffer for policy in self.subpolicies.policies]
        return {"format": "sb3_hhp.PerGoalReplays", "goal_keys": list(self.goal_keys),
                "replays": [buffer_state(buffer, buffer.buffer_size, buffer.buffer_size if buffer.full else buffer.pos)
                            for buffer in buffers]}

    def load_replay_state(self, state: Any, truncate_last_traj: bool = True) -> None:
        """Refill every subpolicy's replay buffer from :meth:`replay_state` (the sub-goals must be the file's; their
        one-step transitions need no truncation)."""
        if not isinstance(state, dict) or state.get("format") != "sb3_hhp.PerGoalReplays":
            raise ValueError("the file holds no replay buffers of per-sub-goal learners")
        if list(state["goal_keys"]) != list(self.goal_keys):
            raise ValueError(f"the file's replays belong to a model with {len(state['goal_keys'])} sub-goals, this one "
                             f"has {len(self.goal_keys)} (or others): load the replay saved with this model")
        for goal, (policy, saved) in enumerate(zip(self.subpolicies.policies, state["replays"])):
            buffer = policy.model.replay_buffer
            load_buffer_state(buffer, saved, buffer.buffer_size, f"sub-goal {goal}'s replay buffer")

    def load_state_dict(self, state: Any) -> None:
        check_learners_state(state, "PerGoalLearners", "per_goal")
        self.goal_keys = list(state["goal_keys"])
        self.subpolicies.load_state_dict(state["subpolicies"])
