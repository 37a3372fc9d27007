"""One goal-conditioned learner for every sub-goal of continuous actions (Fetch), trained with hindsight.

A Fetch sub-goal is a place, a continuous goal: one SB3 off-policy model (SAC by default; TD3 or DDPG with
``subpolicy_kwargs=dict(algo="td3")``) reads the state and the place to reach, as the low levels of HAC and HIRO
do (UVFA), so every sub-goal, discovered or not, shares the experience and the cost of a step does not grow with
the number of sub-goals. Its input is SB3's goal-env layout, a dict of ``observation`` (the state without the
positions), ``achieved_goal`` and ``desired_goal`` (the sub-goal's place), read by ``MultiInputPolicy``.

:class:`HindsightReplay` keeps every primitive transition of every env once, with the place the env's learner was
sent to; when a batch is drawn, a share ``future_p`` of the goals is replaced by a place reached later in the same
episode (HER's ``future`` strategy, 4 relabelled goals per real one: 0.8), and the reward is eq. 6: the pseudo-reward
of eq. 5 (``+1`` where ``done(s', g)``, the place within ``distance_threshold``; ``-1`` where the episode terminates
short of it; ``0`` otherwise) plus ``alpha`` times the curiosity reward of the step. A place can be held, so reaching
one does not end the learner's return (design decisions: the Fetch sub-goal learner). A goal may carry flags after
its three coordinates (on the tasks with an object: the gripper at the object, 0 or 1); it is then reached where the
place is and every flag the goal sets is set, and hindsight relabels the flags with the place.
"""

from collections import deque
from collections.abc import Callable, Hashable
from typing import Any, Optional

import numpy as np
import torch as th
import gymnasium as gym
from gymnasium import spaces
from stable_baselines3 import DDPG, SAC, TD3
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.type_aliases import DictReplayBufferSamples

from sb3_hhp.hierarchy.rewards import pseudo_reward, subpolicy_reward
from sb3_hhp.hierarchy.learner_kwargs import check_learners_state

class SpacesEnv(gym.Env):
    """A stand-in env that only carries spaces, so an SB3 model can be built without a real env (the learner steps
    it by hand)."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        self.observation_space = observation_space
        self.action_space = action_space

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):  # pragma: no cover - never stepped
        raise RuntimeError("SpacesEnv only carries spaces; the goal-conditioned learner steps its model by hand")

    def step(self, action):  # pragma: no cover - never stepped
        raise RuntimeError("SpacesEnv only carries spaces; the goal-conditioned learner steps its model by hand")


#: the off-policy algorithms the learner may be
ALGOS = {"sac": SAC, "td3": TD3, "ddpg": DDPG}
#: the learner's SB3 arguments by default: RL Zoo's FetchReach settings (gamma 0.95, lr 1e-3, batch 256,
#: learning_starts 1,000) with the paper's 256 hidden units and fused Adam (its cost: the design decisions)
DEFAULT_KWARGS: dict[str, Any] = dict(algo="sac", learning_rate=1e-3, buffer_size=500_000, learning_starts=1_000,
                                      batch_size=256, gamma=0.95, gradient_steps=1, future_p=0.8,
                                      policy_kwargs=dict(net_arch=[256, 256], optimizer_kwargs=dict(fused=True)))


class HindsightReplay:
    """Primitive transitions of ``n_envs`` envs in a ring of ``buffer_size // n_envs`` steps each, goals relabelled
    with future places of the same episode when a batch is drawn.

    :param obs_dim: length of a flat observation
    :param action_dim: length of an action
    :param buffer_size: transitions kept (all envs)
    :param n_envs: envs stepped together
    :param future_p: share of a batch whose goal becomes a place reached later in the episode
    :param distance_threshold: ``done(s, g)``: within this distance (metres) of the goal
    :param alpha: weight of the curiosity reward (eq. 6)
    :param seed: the sampler's seed
    :param goal_dim: length of a goal: 3 coordinates, then flags (>= 3)
    """

    def __init__(self, obs_dim: int, action_dim: int, buffer_size: int, n_envs: int, future_p: float,
                 distance_threshold: float, alpha: float, seed: Optional[int] = None, goal_dim: int = 3) -> None:
        if not 0.0 <= future_p <= 1.0:
            raise ValueError(f"future_p must be in [0, 1], got {future_p}")
        if goal_dim < 3:
            raise ValueError(f"goal_dim must be >= 3 (x, y, z, then flags), got {goal_dim}")
        self.steps = max(1, buffer_size // n_envs)
        self.n_envs, self.future_p, self.distance_threshold, self.alpha = n_envs, future_p, distance_threshold, alpha
        shape = (self.steps, n_envs)
        self.obs = np.zeros((*shape, obs_dim), np.float32)
        self.next_obs = np.zeros((*shape, obs_dim), np.float32)
        self.actions = np.zeros((*shape, action_dim), np.float32)
        self.achieved = np.zeros((*shape, goal_dim), np.float32)  # the place reached by the step (and its flags)
        self.goals = np.zeros((*shape, goal_dim), np.float32)  # the place the learner was sent to
        self.intrinsic = np.zeros(shape, np.float32)
        self.terminated = np.zeros(shape, bool)
        self.step_id = np.zeros(shape, np.int64)  # the step counter of each row, to find its future
        self.episode_end = np.zeros(shape, np.int64)  # the step of its episode's last row (-1: running)
        self.episode_start = np.zeros(n_envs, np.int64)
        self.count = 0  # steps added (each one row per env)
        self.rng = np.random.default_rng(seed)

    def size(self) -> int:
        return min(self.count, self.steps) * self.n_envs

    def nbytes(self) -> int:
        """Bytes of the replay's arrays (allocated whole at construction: the same for every number of sub-goals)."""
        return sum(array.nbytes for array in self.state().values() if isinstance(array, np.ndarray))

    def add(self, obs: np.ndarray, next_obs: np.ndarray, actions: np.ndarray, achieved: np.ndarray, goals: np.ndarray,
            intrinsic: np.ndarray, terminated: np.ndarray, ended: np.ndarray) -> None:
        """One step of every env; ``ended``: its episode ended with this step (a time limit or a termination)."""
        row = self.count % self.steps
        self.obs[row], self.next_obs[row], self.actions[row] = obs, next_obs, actions
        self.achieved[row], self.goals[row], self.intrinsic[row] = achieved, goals, intrinsic
        self.terminated[row], self.step_id[row], self.episode_end[row] = terminated, self.count, -1
        for env in np.flatnonzero(ended):
            first = max(int(self.episode_start[env]), self.count - self.steps + 1)
            self.episode_end[np.arange(first, self.count + 1) % self.steps, env] = self.count
            self.episode_start[env] = self.count + 1
        self.count += 1

    def relabelled(self, batch_size: int) -> tuple[np.ndarray, ...]:
        """A batch: rows, their goals (a future place with probability ``future_p``), eq. 6 rewards, dones."""
        rows = self.rng.integers(min(self.count, self.steps), size=batch_size)
        envs = self.rng.integers(self.n_envs, size=batch_size)
        goals = self.goals[rows, envs].copy()
        future = self.rng.random(batch_size) < self.future_p
        if future.any():
            start = self.step_id[rows[future], envs[future]]
            end = self.episode_end[rows[future], envs[future]]
            end = np.where(end < 0, self.count - 1, end)  # a running episode: its latest step
            later = start + (self.rng.random(len(start)) * (end - start + 1)).astype(np.int64)
            goals[future] = self.achieved[later % self.steps, envs[future]]
        reached = reached_goals(self.achieved[rows, envs], goals, self.distance_threshold)
        terminated = self.terminated[rows, envs]
        rewards = subpolicy_reward(pseudo_reward(reached, reached | terminated), self.intrinsic[rows, envs],
                                   self.alpha)  # eq. 5, 6
        return rows, envs, goals, np.asarray(rewards, np.float32), terminated

    def state(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in ("obs", "next_obs", "actions", "achieved", "goals", "intrinsic",
                                                       "terminated", "step_id", "episode_end", "episode_start", "count")}

    def load_state(self, state: dict[str, Any]) -> None:
        if state["obs"].shape != self.obs.shape:
            raise ValueError(f"the saved replay holds {state['obs'].shape[:2]} (steps, envs) of transitions, this one "
                             f"{self.obs.shape[:2]}: load it into a model with the same buffer_size and number of envs")
        for name, value in state.items():
            setattr(self, name, value if np.isscalar(value) else np.array(value, copy=True))


def reached_goals(achieved: np.ndarray, goals: np.ndarray, distance_threshold: float) -> np.ndarray:
    """``done(s, g)`` of a batch ``(B, G)``: the place within ``distance_threshold`` and every flag the goal sets
    (entries after the three coordinates) set where it was reached."""
    reached = np.linalg.norm(achieved[:, :3] - goals[:, :3], axis=1) <= distance_threshold
    if goals.shape[1] > 3:
        reached &= np.all(achieved[:, 3:] >= goals[:, 3:], axis=1)
    return reached


class _Sampler:
    """What the SB3 model's ``train`` draws batches from (``replay_buffer.sample``), in its goal-env layout."""

    def __init__(self, learner: "GoalConditionedLearner") -> None:
        self.learner = learner

    def sample(self, batch_size: int, env: Any = None) -> DictReplayBufferSamples:
        learner, replay = self.learner, self.learner.replay
        rows, envs, goals, rewards, dones = replay.relabelled(batch_size)
        device = learner.model.device

        def tensors(flat: np.ndarray) -> dict[str, th.Tensor]:
            return {key: th.as_tensor(value, device=device) for key, value in learner.inputs(flat, goals).items()}

        return DictReplayBufferSamples(
            observations=tensors(replay.obs[rows, envs]),
            actions=th.as_tensor(replay.actions[rows, envs], device=device),
            next_observations=tensors(replay.next_obs[rows, envs]),
            dones=th.as_tensor(dones.astype(np.float32)[:, None], device=device),
            rewards=th.as_tensor(rewards[:, None], device=device),
            discounts=None,
        )


class GoalConditionedLearner:
    """Every sub-goal's learner of continuous actions as one goal-conditioned SB3 model (the interface of
    :class:`~sb3_hhp.hierarchy.learners.StackedDQN`: ``add``, ``act``, ``observe``, ...).

    :param observation_space: the flat primitive observation space
    :param action_space: the primitive (Box) action space
    :param position: the place of a batch of observations ``(B, D) -> (B, G)`` (the goal space's achieved goal: 3
        coordinates, then its flags)
    :param state: the rest of a batch of observations ``(B, D) -> (B, D')`` the model reads beside the places
    :param goal_position: the place of a sub-goal key in a state ``(key, obs (D,)) -> (G,)``
    :param distance_threshold: ``done(s, g)`` in metres
    :param alpha: weight of the intrinsic reward in eq. 6
    :param subpolicy_kwargs: the model's SB3 arguments over :data:`DEFAULT_KWARGS` (``algo``, ``future_p`` and
        ``buffer_size`` are the learner's)
    :param n_envs: envs stepped together
    :param device: torch device
    :param seed: seed of the model and the replay's sampler
    """

    def __init__(self, observation_space: spaces.Box, action_space: spaces.Box, position: Callable, state: Callable,
                 goal_position: Callable[[Hashable, np.ndarray], np.ndarray], distance_threshold: float,
                 alpha: float = 0.5, subpolicy_kwargs: Optional[dict[str, Any]] = None, n_envs: int = 1,
                 device: Any = "auto", seed: Optional[int] = None) -> None:
        if not isinstance(action_space, spaces.Box):
            raise ValueError(f"GoalConditionedLearner needs a Box action space, got {action_space}")
        kwargs = {**DEFAULT_KWARGS, **(subpolicy_kwargs or {})}
        algo = kwargs.pop("algo")
        if algo not in ALGOS:
            raise ValueError(f"subpolicy_kwargs['algo'] must be one of {sorted(ALGOS)}, got {algo!r}")
        self.future_p, self.buffer_size = float(kwargs.pop("future_p")), int(kwargs.pop("buffer_size"))
        self.gradient_steps = int(kwargs.pop("gradient_steps"))
        self.position, self.state, self.goal_position = position, state, goal_position
        self.distance_threshold, self.alpha, self.seed = float(distance_threshold), float(alpha), seed
        sample = np.zeros((1, *observation_space.shape), np.float32)
        state_dim = self.state(sample).shape[1]
        achieved = np.asarray(self.position(sample))
        self.goal_dim = int(achieved.shape[-1]) if achieved.ndim == 2 and achieved.shape[-1] >= 3 else 3
        self._check_places(achieved, 1, "position (the achieved place of a batch of observations)")
        box = lambda n: spaces.Box(-np.inf, np.inf, (n,), np.float32)  # noqa: E731
        self.input_space = spaces.Dict(dict(observation=box(state_dim), achieved_goal=box(self.goal_dim),
                                            desired_goal=box(self.goal_dim)))
        self.model = ALGOS[algo]("MultiInputPolicy", SpacesEnv(self.input_space, action_space), buffer_size=1,
                                 device=device, seed=seed, **kwargs)
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        self.model._current_progress_remaining = 1.0
        self.model.replay_buffer = _Sampler(self)  # type: ignore[assignment]
        self.action_space, self.obs_dim = action_space, int(observation_space.shape[0])
        self.goal_keys: list[Hashable] = []
        self.outcomes: list[deque] = []
        self.num_steps = 0
        self._rng = np.random.default_rng(seed)
        self.set_n_envs(n_envs)

    def __len__(self) -> int:
        return len(self.goal_keys)

    def set_n_envs(self, n_envs: int) -> None:
        """A replay laid out for ``n_envs`` envs (empty: rows of another layout are not carried over)."""
        self.n_envs = int(n_envs)
        self.replay = HindsightReplay(self.obs_dim, int(np.prod(self.action_space.shape)), self.buffer_size,
                                      self.n_envs, self.future_p, self.distance_threshold, self.alpha, self.seed,
                                      goal_dim=self.goal_dim)

    def add(self, goal_key: Hashable) -> int:
        """A new sub-goal: nothing to build, the model already reaches any place."""
        self.goal_keys.append(goal_key)
        self.outcomes.append(deque(maxlen=100))
        return len(self.goal_keys) - 1

    def inputs(self, obs: np.ndarray, goals: np.ndarray) -> dict[str, np.ndarray]:
        """The model's dict input of a batch of flat observations and the places to reach."""
        obs = np.asarray(obs, np.float32)
        return dict(observation=self.state(obs).astype(np.float32), achieved_goal=self.position(obs).astype(np.float32),
                    desired_goal=np.asarray(goals, np.float32))

    def places(self, goals: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """The place each env's sub-goal asks for (the env's own target where it pursues none)."""
        places = np.stack([self.goal_position(self.goal_keys[int(g)] if g >= 0 else None, o) for g, o in zip(goals, obs)])
        return self._check_places(places, len(obs), "goal_position (the place a sub-goal key asks for)")

    def _check_places(self, places: np.ndarray, n: int, what: str) -> np.ndarray:
        """``places`` if it holds ``n`` places of ``goal_dim`` entries, else a ValueError naming the goal space's
        ``what``."""
        places = np.asarray(places)
        if places.shape != (n, self.goal_dim):
            flags = f" and {self.goal_dim - 3} flag(s)" if self.goal_dim > 3 else ""
            raise ValueError(f"the goal-conditioned learner reads places of 3 coordinates (metres){flags}; the goal "
                             f"space's {what} gave shape {places.shape[1:] if places.ndim else ()} for each of {n} "
                             f"observations (expected ({self.goal_dim},)): make it return an (x, y, z) position "
                             f"(then the flags its achieved goal has), as FetchGoalSpace does")
        return places

    def act(self, goals: np.ndarray, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """One action per env towards its sub-goal's place: at random before ``learning_starts`` steps (unless
        ``deterministic``), then the model's (its own exploration: SAC samples, TD3 / DDPG add their noise)."""
        if not deterministic and self.num_steps < self.model.learning_starts:
            low, high = self.action_space.low, self.action_space.high
            return self._rng.uniform(low, high, size=(len(obs), *self.action_space.shape)).astype(np.float32)
        actions, _ = self.model.predict(self.inputs(obs, self.places(goals, obs)), deterministic=deterministic)
        if not deterministic and getattr(self.model, "action_noise", None) is not None:
            actions = np.clip(actions + self.model.action_noise(), self.action_space.low, self.action_space.high)
        return actions

    def observe(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray, keys: list, terminated: np.ndarray,
                truncated: np.ndarray, gave_up: np.ndarray, acting: np.ndarray, intrinsic: np.ndarray) -> None:
        """Every env's step into the replay, once, with the place its learner was sent to; then the model's
        gradient steps (one per step of the envs by default), once ``learning_starts`` steps are stored."""
        goals = self.places(acting, obs)
        scaled = self.model.policy.scale_action(np.asarray(actions, np.float32))
        self.replay.add(obs, next_obs, scaled, self.position(np.asarray(next_obs)), goals, intrinsic, terminated,
                        np.asarray(terminated) | np.asarray(truncated))
        self.num_steps += len(obs)
        self.model.num_timesteps = self.num_steps
        if self.replay.size() >= max(self.model.learning_starts, self.model.batch_size):
            self.model.train(gradient_steps=self.gradient_steps, batch_size=self.model.batch_size)

    def record_outcome(self, goal: int, success: bool) -> None:
        self.outcomes[goal].append(bool(success))

    def success_rate(self, goal: int) -> Optional[float]:
        return float(np.mean(self.outcomes[goal])) if self.outcomes[goal] else None

    def state_dict(self) -> dict[str, Any]:
        model = self.model
        optimizers = [model.actor.optimizer, model.critic.optimizer]
        entropy = getattr(model, "ent_coef_optimizer", None)
        return {"format": "sb3_hhp.GoalConditionedLearner", "goal_keys": list(self.goal_keys),
                "policy": model.policy.state_dict(), "optimizers": [opt.state_dict() for opt in optimizers],
                "log_ent_coef": None if entropy is None else model.log_ent_coef.detach().clone(),
                "entropy_optimizer": None if entropy is None else entropy.state_dict(),
                "num_steps": self.num_steps, "n_updates": model._n_updates,
                "outcomes": [list(outcome) for outcome in self.outcomes]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        check_learners_state(state, "GoalConditionedLearner", "goal_conditioned")
        model = self.model
        model.policy.load_state_dict(state["policy"])
        for opt, saved in zip([model.actor.optimizer, model.critic.optimizer], state["optimizers"]):
            opt.load_state_dict(saved)
        if state["log_ent_coef"] is not None:
            with th.no_grad():
                model.log_ent_coef.copy_(state["log_ent_coef"])
            model.ent_coef_optimizer.load_state_dict(state["entropy_optimizer"])
        self.goal_keys = list(state["goal_keys"])
        self.outcomes = [deque(outcome, maxlen=100) for outcome in state["outcomes"]]
        self.num_steps, model._n_updates = int(state["num_steps"]), int(state["n_updates"])

    def replay_state(self) -> dict[str, Any]:
        return {"format": "sb3_hhp.HindsightReplay", **self.replay.state()}

    def load_replay_state(self, state: Any, truncate_last_traj: bool = True) -> None:
        """The replay of ``replay_state``; ``truncate_last_traj``: the running episodes end there (training goes
        on from fresh episodes, so no future place is drawn from the next one)."""
        if not isinstance(state, dict) or state.get("format") != "sb3_hhp.HindsightReplay":
            raise ValueError("the file holds no replay of a goal-conditioned learner")
        self.replay.load_state({key: value for key, value in state.items() if key != "format"})
        if truncate_last_traj and self.replay.count:
            last = (self.replay.count - 1) % self.replay.steps
            running = self.replay.episode_end == -1
            self.replay.episode_end[running] = self.replay.step_id[last, 0]
            self.replay.episode_start[:] = self.replay.count
