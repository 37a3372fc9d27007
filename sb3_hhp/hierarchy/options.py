"""The option loop: sub-goals run by their learners on ``n`` primitive envs at once (Algorithm 1, lines 14-22).

:class:`OptionRunner` steps a VecEnv of primitive envs. Each env pursues its own sub-goal ``g``: the sub-goal
learners act for every env in one batched call (line 15), the envs step together (line 16), the curiosity
reward comes for the whole batch (eq. 7), and every primitive transition is stored once in the learners' shared
replay (lines 17-20), whose eq. 5 / 6 rewards are computed per sub-goal when a batch is drawn. An env's option
ends at ``terminal(s, g)`` (line 22): the sub-goal is reached, the episode ends, or the sub-goal gives up after
``max_subgoal_steps`` primitive steps (:func:`option_terminal`, the one test that training and
:meth:`~sb3_hhp.hhp.acting.HierarchicalActing.predict` share). The algorithm (:meth:`~sb3_hhp.hhp.hhp.HhP.collect_rollouts`) drives the runner:
it chooses the next sub-goal of every env whose option ended in one batched forward, stores the choices'
transitions in its replay and does the between-episode work on each finished episode's
:class:`EpisodeTrace`. The sub-goal set G (:class:`SubgoalSet`) is the model's state; the runner reads it.
"""

from collections import Counter
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any, Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper

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
    #: the goal space's snapshot of the state it was found in (goal spaces with ``facts_per_step``; else None)
    snapshot: Any = None


class SubgoalSet:
    """The sub-goal set G with the visit counts of every sub-goal key (CSD reads them)."""

    def __init__(self, goals: Optional[list[Subgoal]] = None, visits: Optional[dict] = None) -> None:
        self.goals: list[Subgoal] = list(goals or [])
        self.visits: Counter = Counter(visits or {})

    def __len__(self) -> int:
        return len(self.goals)

    def __getitem__(self, index: int) -> Subgoal:
        return self.goals[index]

    def __iter__(self):
        return iter(self.goals)

    @property
    def keys(self) -> list[Hashable]:
        return [goal.key for goal in self.goals]

    def add(self, key: Hashable, obs: np.ndarray, image: Optional[np.ndarray], found_at: int, source: str = "csd",
            snapshot: Any = None) -> int:
        self.goals.append(Subgoal(key, np.array(obs, copy=True), image, int(found_at), source, snapshot))
        return len(self.goals) - 1


def option_terminal(goal_space: GoalSpace, key: Hashable, goal_key: Hashable, steps: int,
                    max_subgoal_steps: int) -> tuple[bool, bool]:
    """``terminal(s, g)`` apart from the env's own end (Algorithm 1 line 22), after ``steps`` primitive steps
    of the option: (the sub-goal is reached, it gives up)."""
    return bool(goal_space.achieved(key, goal_key)), steps >= max_subgoal_steps


@dataclass
class EpisodeTrace:
    """What one episode leaves for the between-episode work (queries, discovery, the RND update)."""

    high_obs: list = field(default_factory=list)  # s_t at each sub-goal choice
    high_goals: list = field(default_factory=list)  # g chosen
    high_privileged: list = field(default_factory=list)  # snapshots of s_t's privileged facts (scripted oracles)
    high_images: list = field(default_factory=list)  # rendered s_t (people), when recorded
    high_returns: list = field(default_factory=list)  # R_e of each option
    low_obs: list = field(default_factory=list)  # every primitive next state s_{t+1}
    low_keys: list = field(default_factory=list)  # its sub-goal key
    intrinsic: list = field(default_factory=list)  # r^i of every primitive step
    low_privileged: list = field(default_factory=list)  # snapshots of every primitive step (``facts_per_step``)
    random: bool = False  # the random-action episode that seeds G (Algorithm 1 line 5)

    def low_states(self) -> np.ndarray:
        """``low_obs`` as one array, stacked once for the between-episode steps that read it (discovery, RND)."""
        stacked = self.__dict__.get("_low_states")
        if stacked is None or len(stacked) != len(self.low_obs):
            stacked = self.__dict__["_low_states"] = np.stack(self.low_obs)
        return stacked


@dataclass
class OptionEnd:
    """A sub-goal choice whose option ended: the meta-controller's transition (s, g, R_e, s', done)."""

    env: int
    obs: np.ndarray
    goal: int
    extrinsic_return: float
    next_obs: np.ndarray
    terminated: bool
    truncated: bool
    achieved: bool
    steps: int
    info: dict


@dataclass
class EpisodeEnd:
    """An episode of one env that ended, with what it leaves behind."""

    env: int
    trace: EpisodeTrace
    info: dict


#: VecEnv wrappers the option loop can run under: they change neither observations nor rewards
TRANSPARENT_WRAPPERS = ("VecMonitor", "VecCheckNan")


def check_vec_env(venv: VecEnv) -> VecEnv:
    """``venv`` when HhP can step it: sub-goals are states of the env itself, so a wrapper that changes
    observations or rewards (normalisation, frame stacking) would make them states of something else."""
    env = venv
    while isinstance(env, VecEnvWrapper):
        name = type(env).__name__
        if name == "VecTransposeImage":
            raise ValueError("Pass HhP the env without VecTransposeImage: HhP turns images for its networks itself")
        if name not in TRANSPARENT_WRAPPERS:
            raise ValueError(
                f"HhP cannot train under {name}: a sub-goal is a state of the env itself, which a VecEnv wrapper that "
                "changes observations or rewards would hide. Remove it (RL Zoo: drop normalize / frame_stack / "
                "vec_env_wrapper from the hyperparameters); stack frames inside each env (a gymnasium wrapper) instead"
            )
        env = env.venv
    return venv


def env_view(venv: VecEnv, index: int = 0) -> gym.Env:
    """Env ``index`` of ``venv`` for reading (goal-space detection, privileged facts, rendering): the env itself in
    a DummyVecEnv, else a copy of its current state under the VecEnv's observation space."""
    base = venv
    while isinstance(base, VecEnvWrapper):
        base = base.venv
    if isinstance(base, DummyVecEnv):
        return base.envs[index]
    try:
        copy = base.get_attr("unwrapped", [index])[0]
    except (EOFError, ConnectionError, TypeError, AttributeError) as error:  # the worker could not pickle its env
        raise ValueError(
            f"HhP reads env {index} of the {type(base).__name__} (its goal space, the facts of a question, the frames "
            f"people see) as a copy sent out of the env's process, and that copy failed ({type(error).__name__}: "
            f"{str(error) or 'the worker process ended'}; its traceback is printed above): give the env only picklable "
            "attributes, or use a DummyVecEnv"
        ) from error
    view = gym.Wrapper(copy)
    view.observation_space, view.action_space = venv.observation_space, venv.action_space
    return view


class OptionRunner:
    """Runs the sub-goals chosen for ``venv.num_envs`` primitive envs until each one's ``terminal(s, g)``.

    :param venv: the primitive envs (observations must suit ``goal_space``)
    :param goal_space: the domain's goal space
    :param subgoals: the sub-goal set G (the model's, read here)
    :param learners: the sub-goal learners (:class:`~sb3_hhp.hierarchy.learners.StackedDQN`,
        :class:`~sb3_hhp.hierarchy.heads.SharedHeadsDQN` or
        :class:`~sb3_hhp.hierarchy.goal_conditioned.GoalConditionedLearner`)
    :param rnd: the global curiosity model (None: no curiosity, the "Pref" ablation)
    :param max_subgoal_steps: primitive steps after which a sub-goal gives up
    :param record_images: render s_t at each choice (people and the gallery need it)
    :param learn: store every transition in the learners' replay, curiosity, visits and the episodes' traces (False:
        the learners only act, frozen, as in :class:`~sb3_hhp.hierarchy.semi_mdp.HierarchicalEnv`)
    :param deterministic: the learners act greedily (else epsilon-greedy, or with their action noise)
    """

    def __init__(self, venv: VecEnv, goal_space: GoalSpace, subgoals: SubgoalSet, learners: Any, rnd: Optional[RND],
                 max_subgoal_steps: int = 50, record_images: bool = False, learn: bool = True,
                 deterministic: bool = False) -> None:
        if max_subgoal_steps < 1:
            raise ValueError(f"max_subgoal_steps must be >= 1, got {max_subgoal_steps}")
        #: an option's return R_e is ``sum_i return_discount^i r_i`` over its primitive steps (None: the plain sum, the
        #: paper's); HhP sets its gamma here with ``meta_kwargs["discount"] = "steps"``
        self.return_discount: Optional[float] = None
        self.venv = check_vec_env(venv)
        self.goal_space, self.subgoals, self.learners, self.rnd = goal_space, subgoals, learners, rnd
        self.max_subgoal_steps = max_subgoal_steps
        self.record_images = record_images
        self.learn, self.deterministic = learn, deterministic
        #: set when the envs were stepped or reset by someone else (:class:`PrimitiveVecEnv`): the next ``learn``
        #: starts from fresh episodes rather than from observations that are no longer the envs'
        self.interrupted = False
        #: record the privileged facts of s_t at each choice (questions need them; None is stored while not)
        self.record_privileged = True
        self.num_envs = venv.num_envs
        self.action_space = venv.action_space
        n = self.num_envs
        self.goals = np.full(n, -1, dtype=np.int64)  # each env's sub-goal (-1: none chosen yet)
        self.steps = np.zeros(n, dtype=np.int64)  # primitive steps of the current option
        self.option_returns = np.zeros(n)  # R_e of the current option
        self.episode_returns = np.zeros(n)
        self.choice_obs: list[Optional[np.ndarray]] = [None] * n  # s_t where the option began
        self.traces = [EpisodeTrace() for _ in range(n)]
        self.obs: Optional[np.ndarray] = None
        self.num_steps = 0  # primitive steps taken (all envs)

    def seed(self, seed: Optional[int]) -> None:
        """Seed the envs' next reset (env ``i`` gets ``seed + i``) and the random first episode's actions."""
        if seed is not None:
            self.venv.seed(seed)
            self.action_space.seed(seed)

    def reset(self) -> np.ndarray:
        self.obs = self.venv.reset()
        self.interrupted = False
        self.goals[:] = -1
        self.steps[:] = 0
        self.option_returns[:] = 0.0
        self.episode_returns[:] = 0.0
        self.traces = [EpisodeTrace(random=not self.subgoals) for _ in range(self.num_envs)]
        return self.obs

    def waiting(self) -> np.ndarray:
        """The envs that need a sub-goal (none while G is empty: they explore at random, line 5)."""
        return np.flatnonzero(self.goals < 0) if len(self.subgoals) else np.zeros(0, dtype=np.int64)

    def start(self, envs: np.ndarray, goals: np.ndarray) -> None:
        """Begin sub-goal ``goals[j]`` on env ``envs[j]`` (Algorithm 1 lines 10-13)."""
        assert self.obs is not None, "reset() must be called before start()"
        for env, goal in zip(np.asarray(envs, dtype=np.int64), np.asarray(goals, dtype=np.int64)):
            if not 0 <= goal < len(self.subgoals):
                raise ValueError(f"Sub-goal {goal} does not exist: there are {len(self.subgoals)} sub-goals")
            self.goals[env], self.steps[env], self.option_returns[env] = goal, 0, 0.0
            self.choice_obs[env] = np.array(self.obs[env], copy=True)
            trace = self.traces[env]
            trace.high_obs.append(self.choice_obs[env])
            trace.high_goals.append(int(goal))
            # a SubprocVecEnv's env is copied to be read: only when its facts or its image are kept
            view = env_view(self.venv, int(env)) if self.record_privileged or self.record_images else None
            trace.high_privileged.append(self.goal_space.snapshot(view) if self.record_privileged else None)
            if self.record_images:
                trace.high_images.append(self.goal_space.render(view))

    def step(self) -> tuple[list[OptionEnd], list[EpisodeEnd]]:
        """One primitive step of every env (lines 15-22); the options and episodes that ended in it."""
        assert self.obs is not None, "reset() must be called before step()"
        obs, acting, n = self.obs, self.goals.copy(), self.num_envs
        pursuing = acting >= 0
        deterministic = self.deterministic
        if pursuing.all():
            actions = self.learners.act(acting, obs, deterministic=deterministic)  # line 15, every env in one call
        else:
            actions = np.stack([self.action_space.sample() for _ in range(n)])  # no sub-goal yet: line 5
            if pursuing.any():
                actions[pursuing] = self.learners.act(acting[pursuing], obs[pursuing], deterministic=deterministic)
        next_obs, rewards, dones, infos = self.venv.step(actions)  # line 16
        final_obs = next_obs
        truncated = np.array([bool(info.get("TimeLimit.truncated", False)) for info in infos]) & dones
        terminated = dones & ~truncated
        if dones.any():
            final_obs = np.array(next_obs, copy=True)
            for i in np.flatnonzero(dones):
                final_obs[i] = infos[i]["terminal_observation"]
        goal_space = self.goal_space
        keys = [goal_space.terminal_key(final_obs[i], float(rewards[i]), bool(terminated[i])) for i in range(n)]
        self.steps[pursuing] += 1
        if self.return_discount is None:
            self.option_returns += rewards
        else:  # the option's i-th step (i from 0) weighs return_discount^i; an env without a sub-goal counts as step 0
            self.option_returns += rewards * self.return_discount ** np.maximum(self.steps - 1, 0)
        self.episode_returns += rewards
        achieved = np.zeros(n, dtype=bool)
        gave_up = np.zeros(n, dtype=bool)
        goal_keys = self.subgoals.keys
        for i in np.flatnonzero(pursuing):
            achieved[i], gave_up[i] = option_terminal(goal_space, keys[i], goal_keys[acting[i]], int(self.steps[i]),
                                                      self.max_subgoal_steps)
        if self.learn:
            self._observe(obs, np.asarray(actions), final_obs, keys, terminated, truncated, gave_up, acting)
        self.num_steps += n
        options, episodes = [], []
        for i in np.flatnonzero(pursuing & (achieved | gave_up | dones)):  # line 22
            goal = int(acting[i])
            if self.learn:
                self.learners.record_outcome(goal, bool(achieved[i]))
            info = dict(infos[i], primitive_steps=int(self.steps[i]), subgoal=goal, subgoal_reached=bool(achieved[i]))
            options.append(OptionEnd(int(i), self.choice_obs[i], goal, float(self.option_returns[i]), final_obs[i],
                                     bool(terminated[i]), bool(truncated[i]), bool(achieved[i]), int(self.steps[i]), info))
            self.traces[i].high_returns.append(float(self.option_returns[i]))
            self.goals[i] = -1
        for i in np.flatnonzero(dones):
            info = dict(infos[i])
            info["is_success"] = is_success(info, bool(terminated[i]), float(self.episode_returns[i]))
            episodes.append(EpisodeEnd(int(i), self.traces[i], info))
            self.traces[i] = EpisodeTrace(random=not self.subgoals)
            self.goals[i], self.episode_returns[i] = -1, 0.0
        self.obs = next_obs
        return options, episodes


    def _observe(self, obs: np.ndarray, actions: np.ndarray, final_obs: np.ndarray, keys: list, terminated: np.ndarray,
                 truncated: np.ndarray, gave_up: np.ndarray, acting: np.ndarray) -> None:
        """What a step leaves to learn from: its curiosity reward (eq. 7), the transition in the learners' replay
        (lines 17-20: stored once; each sub-goal's eq. 5 / 6 reward is computed when its batch is drawn), the keys'
        visits (CSD) and the episodes' traces."""
        n = len(keys)
        intrinsic = (self.rnd.intrinsic_reward(final_obs) if self.rnd is not None else np.zeros(n)).astype(np.float32)
        self.learners.observe(obs, actions, final_obs, keys, terminated, truncated, gave_up, acting, intrinsic)
        visits = self.subgoals.visits
        snapshots = self.goal_space.facts_per_step and self.record_privileged  # a question may name any step's state
        for i in range(n):
            visits[keys[i]] += 1
            trace = self.traces[i]
            if snapshots:  # an episode's last state is gone (the env was reset in its step): no facts of it
                ended = terminated[i] or truncated[i]
                trace.low_privileged.append(None if ended else self.goal_space.snapshot(env_view(self.venv, i)))
            trace.low_obs.append(final_obs[i])
            trace.low_keys.append(keys[i])
            trace.intrinsic.append(float(intrinsic[i]))
        if self.rnd is not None:
            self.rnd.on_steps(n)


def is_success(info: dict, terminated: bool, extrinsic_return: float) -> bool:
    """Whether an episode that just ended solved the task: the env's own ``is_success`` where it reports one
    (the Fetch tasks, which never terminate), else a positive return at a terminal state (MiniGrid)."""
    if "is_success" in info:
        return bool(info["is_success"])
    return bool(terminated and extrinsic_return > 0)


class SubgoalVecEnv(VecEnvWrapper):
    """What the meta-controller's SB3 base class holds of HhP's envs: their observations, and one action per env that
    is a sub-goal (``Discrete(capacity)``). HhP steps the primitive envs itself through its :class:`OptionRunner`;
    this view resets them and carries the spaces. Users get :class:`PrimitiveVecEnv` (``model.get_env()``)."""

    def __init__(self, runner: OptionRunner, capacity: int) -> None:
        super().__init__(runner.venv, observation_space=runner.venv.observation_space,
                         action_space=spaces.Discrete(int(capacity)))
        self.runner = runner

    def reset(self) -> np.ndarray:
        return self.runner.reset()

    def seed(self, seed: Optional[int] = None) -> list:
        self.runner.seed(seed)
        return [None if seed is None else seed + i for i in range(self.num_envs)]

    def step_async(self, actions: np.ndarray) -> None:
        raise RuntimeError("HhP's sub-goal choices are run by its option runner (model.options); step the primitive "
                           "envs of model.get_env() with the actions of model.predict, or use HierarchicalEnv")

    def step_wait(self):  # pragma: no cover - step_async refuses first
        raise RuntimeError("HhP's sub-goal choices are run by its option runner (model.options)")


class PrimitiveVecEnv(VecEnvWrapper):
    """The model's primitive envs as SB3 users step them (``model.get_env()``): actions are primitive actions, as
    :meth:`~sb3_hhp.hhp.acting.HierarchicalActing.predict` returns them, so SB3's README loop and ``evaluate_policy(model, model.get_env())``
    work. Stepping or resetting them marks the option runner as interrupted: the next ``learn`` starts from fresh
    episodes instead of training on observations that are no longer the envs'."""

    def __init__(self, runner: OptionRunner) -> None:
        super().__init__(runner.venv)
        self.runner = runner

    def reset(self) -> np.ndarray:
        self.runner.interrupted = True
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        self.runner.interrupted = True
        self.venv.step_async(actions)

    def step_wait(self):
        return self.venv.step_wait()
