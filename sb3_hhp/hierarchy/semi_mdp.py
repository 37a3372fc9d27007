"""HhP's semi-MDP as a gymnasium env: each action is a sub-goal, run by its learner until ``terminal(s, g)``.

:class:`HierarchicalEnv` wraps one env, its goal space and a set of sub-goal learners (a trained HhP model's, or
given), so that any SB3 algorithm can be a meta-controller over those skills::

    from stable_baselines3 import DQN
    from sb3_hhp.hierarchy import HierarchicalEnv

    env = HierarchicalEnv.from_model(model, "MiniGrid-DoorKey-5x5-v0")  # the learners frozen
    DQN("MlpPolicy", env).learn(20_000)

An action runs through the same :class:`~sb3_hhp.hierarchy.options.OptionRunner` as HhP's own training loop (one
``terminal(s, g)``, one place that runs an option), with learning switched off: the learners act, nothing is stored.
The reward of an action is the extrinsic reward summed over its primitive steps (undiscounted); ``info`` carries
``primitive_steps``, for a meta-learner that discounts by them, and ``subgoal_reached``.
"""

from typing import Any, Optional, Union

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.base import GoalSpace
from sb3_hhp.hierarchy.options import OptionRunner, Subgoal, SubgoalSet


class HierarchicalEnv(gym.Env):
    """A ``Discrete(K)`` env over K sub-goals: an action runs that sub-goal's learner until it is reached, gives up
    after ``max_subgoal_steps`` primitive steps, or the episode ends.

    :param env: the primitive env (an env id or a gym env; a raw MiniGrid or Fetch env is given the observation its
        goal space reads, :func:`~sb3_hhp.goals.wrap_env`)
    :param goal_space: the goal space the sub-goals' keys belong to
    :param subgoals: the sub-goals (:class:`~sb3_hhp.hierarchy.options.Subgoal` or a
        :class:`~sb3_hhp.hierarchy.options.SubgoalSet`), in the order of the actions
    :param learners: the sub-goal learners, one per sub-goal, indexed as ``subgoals`` (an HhP model's
        ``subpolicies``): anything with ``act(goals, obs, deterministic)``
    :param max_subgoal_steps: primitive steps after which a sub-goal gives up (>= 1)
    :param deterministic: the learners act greedily (default: as they act at the end of training, epsilon-greedy
        with their own final epsilon, which on MiniGrid keeps a greedy learner from looping)
    """

    metadata = {"render_modes": []}

    def __init__(self, env: Union[gym.Env, str], goal_space: GoalSpace, subgoals: Union[SubgoalSet, list[Subgoal]],
                 learners: Any, max_subgoal_steps: int = 50, deterministic: bool = False) -> None:
        super().__init__()
        if isinstance(env, str):
            env = gym.make(env)
        if not isinstance(env, gym.Env):
            raise ValueError(f"HierarchicalEnv wraps one gymnasium env (or an env id), got {type(env).__name__}")
        goals = subgoals if isinstance(subgoals, SubgoalSet) else SubgoalSet(list(subgoals))
        if len(goals) == 0:
            raise ValueError("HierarchicalEnv needs at least one sub-goal: its actions are the sub-goals")
        if len(learners) < len(goals):
            raise ValueError(f"HierarchicalEnv got {len(goals)} sub-goals but learners for only {len(learners)}")
        primitive = wrap_env(env)
        self.runner = OptionRunner(DummyVecEnv([lambda: primitive]), goal_space, goals, learners, rnd=None,
                                   max_subgoal_steps=max_subgoal_steps, learn=False, deterministic=deterministic)
        self.runner.record_privileged = False
        self.observation_space = primitive.observation_space
        self.action_space = spaces.Discrete(len(goals))
        self._needs_reset = True

    @classmethod
    def from_model(cls, model: Any, env: Union[gym.Env, str], deterministic: bool = False) -> "HierarchicalEnv":
        """The semi-MDP over a trained :class:`~sb3_hhp.hhp.hhp.HhP` model's sub-goals and learners (as they are now: sub-goals
        it finds later are not added), on ``env``, a fresh env of the same task."""
        return cls(env, model.goal_space, list(model.subgoals), model.subpolicies,
                   max_subgoal_steps=model.max_subgoal_steps, deterministic=deterministic)

    @property
    def subgoals(self) -> SubgoalSet:
        return self.runner.subgoals

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self.runner.venv.seed(seed)
        obs = self.runner.reset()
        self._needs_reset = False
        return np.array(obs[0], copy=True), {}

    def step(self, action: Union[int, np.integer, np.ndarray]) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Run sub-goal ``action`` until ``terminal(s, g)``; the extrinsic reward summed over its primitive steps."""
        if self._needs_reset:
            raise RuntimeError("HierarchicalEnv.step before reset (or after the episode ended): call reset() first")
        goal = int(np.asarray(action).item())
        if not self.action_space.contains(goal):
            raise ValueError(f"Sub-goal {goal} does not exist: the actions are 0 to {self.action_space.n - 1}")
        self.runner.start(np.array([0]), np.array([goal]))
        while True:
            ended, _ = self.runner.step()
            if ended:
                break
        option = ended[0]
        self._needs_reset = option.terminated or option.truncated
        info = dict(option.info)
        info.pop("terminal_observation", None)
        return np.array(option.next_obs, copy=True), option.extrinsic_return, option.terminated, option.truncated, info

    def close(self) -> None:
        self.runner.venv.close()
