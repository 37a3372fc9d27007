"""HierarchicalEnv: the task as a semi-MDP whose actions are sub-goals.

``step(g)`` runs the subpolicy ``pi_g`` on the primitive env, training it online, until
``terminal(s, g)`` (Algorithm 1, lines 14-22): the sub-goal is reached (``done(s, g)``), the episode
ends, or the sub-goal gives up after ``max_subgoal_steps`` primitive steps (DESIGN.md gap 5). Eq. 5's
-1 is for the env's own terminal function (section 5.1: "the original terminal functions provided by the
environments"); a give-up or the env's time limit is a time limit, stored as a timeout (bootstrapped, no
-1): the step count is not in the state, so a -1 there would punish states for when they were reached. It
returns the next state and the extrinsic return R_e collected meanwhile; the meta-controller's reward
(eq. 3) is formed from R_e and the preference bonus when the meta-controller trains.

What an episode leaves behind for the callbacks that run between episodes: ``phi_high`` (the
meta-controller's tuples (s, g) with the privileged facts of s, for queries, Algorithm 1 line 13) and
``phi_low`` (the primitive states visited with their sub-goal keys, for CSD, line 29, and the RND update,
line 35).
"""

from collections import Counter
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any, Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_hhp.curiosity.rnd import RND
from sb3_hhp.goals.base import GoalSpace


@dataclass
class Subgoal:
    """One sub-goal of the set G: its key, the observation networks see, the image people see."""

    key: Hashable
    obs: np.ndarray
    image: Optional[np.ndarray]
    found_at: int
    source: str = "csd"


@dataclass
class EpisodeTrace:
    """What one episode leaves for the between-episode callbacks."""

    high_obs: list = field(default_factory=list)  # s_t at each sub-goal choice
    high_goals: list = field(default_factory=list)  # g chosen
    high_privileged: list = field(default_factory=list)  # privileged facts of s_t (scripted oracles)
    high_images: list = field(default_factory=list)  # rendered s_t (people), when recorded
    high_returns: list = field(default_factory=list)  # R_e of each option
    low_obs: list = field(default_factory=list)  # every primitive next state s_{t+1}
    low_keys: list = field(default_factory=list)  # its sub-goal key
    low_images: list = field(default_factory=list)  # rendered s_{t+1}, only for candidate states
    intrinsic: list = field(default_factory=list)  # r^i of every primitive step


class HierarchicalEnv(gym.Env):
    """The semi-MDP over sub-goals. Its action space is ``Discrete(capacity)``; the first
    ``len(self.subgoals)`` actions are valid and the capacity grows when sub-goals are added.

    :param env: the primitive env (observations must suit ``goal_space``)
    :param goal_space: the domain's goal space
    :param subpolicies: the sub-goal learners (:class:`~sb3_hhp.hierarchy.learners.StackedDQN` or
        :class:`~sb3_hhp.hierarchy.subpolicies.PerGoalLearners`)
    :param rnd: the global curiosity model (None: no curiosity, the "Pref" ablation)
    :param alpha: weight of the intrinsic reward in eq. 6
    :param max_subgoal_steps: primitive steps after which a sub-goal gives up
    :param capacity: initial size of the action space (grows by doubling)
    :param record_images: render s_t at each choice (needed by people and the gallery)
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        env: gym.Env,
        goal_space: GoalSpace,
        subpolicies: Any,
        rnd: Optional[RND],
        alpha: float = 0.5,
        max_subgoal_steps: int = 100,
        capacity: int = 16,
        record_images: bool = False,
    ) -> None:
        if max_subgoal_steps < 1:
            raise ValueError(f"max_subgoal_steps must be >= 1, got {max_subgoal_steps}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        self.env = env
        self.goal_space = goal_space
        self.subpolicies = subpolicies
        self.rnd = rnd
        self.alpha = alpha
        self.max_subgoal_steps = max_subgoal_steps
        self.record_images = record_images
        self.observation_space = env.observation_space
        self.action_space = spaces.Discrete(capacity)
        self.subgoals: list[Subgoal] = []
        self.visits: Counter = Counter()  # how often each sub-goal key was visited, over all training
        self.num_steps = 0  # primitive steps taken
        self.trace = EpisodeTrace()
        self.last_trace = EpisodeTrace()
        self._obs: Optional[np.ndarray] = None

    # ------------------------------------------------------------------ sub-goal set
    @property
    def n_subgoals(self) -> int:
        return len(self.subgoals)

    def add_subgoal(self, key: Hashable, obs: np.ndarray, image: Optional[np.ndarray], source: str = "csd") -> int:
        """Add a sub-goal to G with a freshly initialised subpolicy; grow the action space if needed."""
        self.subgoals.append(Subgoal(key, np.array(obs, copy=True), image, self.num_steps, source))
        self.subpolicies.add(key)
        if self.n_subgoals > self.action_space.n:
            self.action_space = spaces.Discrete(2 * int(self.action_space.n))
        return self.n_subgoals - 1

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:  # the random first episode (line 5) samples primitive actions: same seed, same run
            self.env.action_space.seed(seed)
        self.last_trace, self.trace = self.trace, EpisodeTrace()
        self._obs = obs
        return obs, info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        assert self._obs is not None, "reset() must be called before step()"
        if not self.subgoals:
            return self._explore_randomly()
        goal_id = int(action)
        if not 0 <= goal_id < self.n_subgoals:
            raise ValueError(f"Sub-goal {goal_id} does not exist: there are {self.n_subgoals} sub-goals")
        goal = self.subgoals[goal_id]
        learners = self.subpolicies
        trace = self.trace
        trace.high_obs.append(self._obs)
        trace.high_goals.append(goal_id)
        trace.high_privileged.append(self.goal_space.privileged(self.env))
        if self.record_images:
            trace.high_images.append(self.goal_space.render(self.env))

        obs, extrinsic_return, steps = self._obs, 0.0, 0
        terminated = truncated = achieved = False
        info: dict = {}
        acting = np.array([goal_id])
        while True:  # lines 14-22
            action_t = learners.act(acting, obs[None])[0]  # line 15
            next_obs, reward, terminated, truncated, info = self.env.step(action_t)  # line 16
            steps += 1
            extrinsic_return += float(reward)
            key = self.goal_space.terminal_key(next_obs, float(reward), terminated)
            achieved = self.goal_space.achieved(key, goal.key)
            give_up = steps >= self.max_subgoal_steps
            terminal = achieved or terminated or truncated or give_up  # terminal(s, g), line 22
            intrinsic = float(self.rnd.intrinsic_reward(next_obs[None])[0]) if self.rnd is not None else 0.0  # eq. 7
            # lines 17-20: stored once; each sub-goal's eq. 5 / 6 reward is computed when its batch is drawn
            learners.observe(obs[None], np.asarray([action_t]), next_obs[None], [key], np.array([terminated]),
                             np.array([truncated]), np.array([give_up]), acting, np.array([intrinsic], dtype=np.float32))
            self.visits[key] += 1
            trace.low_obs.append(next_obs)
            trace.low_keys.append(key)
            trace.intrinsic.append(intrinsic)
            obs = next_obs  # line 21
            if terminal:
                break
        learners.record_outcome(goal_id, achieved)
        self.num_steps += steps
        if self.rnd is not None:
            self.rnd.on_steps(steps)
        trace.high_returns.append(extrinsic_return)
        self._obs = obs
        info = dict(info)
        info.update(primitive_steps=steps, subgoal=goal_id, subgoal_reached=achieved)
        if terminated or truncated:
            info["is_success"] = _is_success(info, terminated, extrinsic_return)
        return obs, extrinsic_return, terminated, truncated, info

    def _explore_randomly(self) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Before the first sub-goal exists: one random-action episode whose states seed G (Algorithm 1 line 5)."""
        obs, extrinsic_return, steps = self._obs, 0.0, 0
        terminated = truncated = False
        info: dict = {}
        while not (terminated or truncated):
            obs, reward, terminated, truncated, info = self.env.step(self.env.action_space.sample())
            steps += 1
            extrinsic_return += float(reward)
            key = self.goal_space.terminal_key(obs, float(reward), terminated)
            self.visits[key] += 1
            self.trace.low_obs.append(obs)
            self.trace.low_keys.append(key)
        self.num_steps += steps
        if self.rnd is not None:
            self.rnd.on_steps(steps)
        self._obs = obs
        info = dict(info)
        info.update(primitive_steps=steps, subgoal=-1, subgoal_reached=False, random_episode=True,
                    is_success=_is_success(info, terminated, extrinsic_return))
        return obs, extrinsic_return, terminated, truncated, info

    def close(self) -> None:
        self.env.close()


def _is_success(info: dict, terminated: bool, extrinsic_return: float) -> bool:
    """Whether an episode that just ended solved the task: the env's own ``is_success`` where it reports one
    (the Fetch tasks, which never terminate), else a positive return at a terminal state (MiniGrid)."""
    if "is_success" in info:
        return bool(info["is_success"])
    return bool(terminated and extrinsic_return > 0)
