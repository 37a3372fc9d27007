"""HhP: hierarchical learning from human preferences and curiosity (Algorithm 1), shaped as SB3's ``dqn.py``.

:class:`HhP` is the meta-controller, a Double DQN with prioritized replay over the sub-goals: ``__init__`` stores
the settings, ``_setup_model`` builds the components, ``collect_rollouts`` runs the option loop
(:class:`~sb3_hhp.hierarchy.options.OptionRunner`) and the work between episodes
(:class:`~sb3_hhp.hhp.episodes.BetweenEpisodes`: questions, CSD, RND), ``train`` runs N_opt updates whose reward is
eq. 3 (:class:`~sb3_hhp.hhp.bonus.PreferenceBonus`), ``predict`` acts (:class:`~sb3_hhp.hhp.acting.HierarchicalActing`),
and save / load keep every component in one zip. ``total_timesteps`` counts primitive env steps.
"""

import io
import pathlib
import pickle
import zipfile
from collections import deque
from typing import Any, ClassVar, Optional, TypeVar, Union

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, ConvertCallback, ProgressBarCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, RolloutReturn, Schedule, TrainFreq
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl
from stable_baselines3.common.utils import get_device, polyak_update
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.preprocessing import maybe_transpose
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecTransposeImage

from sb3_hhp.curiosity.rnd import RND
from sb3_hhp.discovery.csd import SubgoalDiscovery
from sb3_hhp.dqn.buffers import buffer_state, load_buffer_state
from sb3_hhp.dqn.dqn import DoubleDQN
from sb3_hhp.goals import GoalSpace, MiniGridGoalSpace, make_goal_space, wrap_env
from sb3_hhp.hhp.arguments import LEARNER_INPUTS, check_grouped, grouped
from sb3_hhp.hhp.acting import HierarchicalActing
from sb3_hhp.hhp.bonus import PreferenceBonus
from sb3_hhp.hhp.policies import CnnPolicy, DQNPolicy, GoalSpaceFeatures, GridCNN, MlpPolicy, MultiInputPolicy
from sb3_hhp.hhp.episodes import BetweenEpisodes
from sb3_hhp.hierarchy.heads import SharedHeadsDQN
from sb3_hhp.hierarchy.learners import StackedDQN
from sb3_hhp.hierarchy.options import (
    EpisodeTrace, OptionRunner, PrimitiveVecEnv, Subgoal, SubgoalSet, SubgoalVecEnv, check_vec_env, env_view,
)
from sb3_hhp.hierarchy.goal_conditioned import GoalConditionedLearner
from sb3_hhp.oracles.base import Oracle
from sb3_hhp.oracles.registry import make_oracle
from sb3_hhp.preferences.predictor import PreferencePredictor
from sb3_hhp.preferences.query import QuerySelector
from sb3_hhp.preferences.rewards import PreferenceReturnNormalizer
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable

SelfHhP = TypeVar("SelfHhP", bound="HhP")

#: the learners of discrete-action sub-goals (``subgoal_learner``)
SUBGOAL_LEARNERS = {"heads": SharedHeadsDQN, "stacked": StackedDQN}
#: the zip member of a saved model that holds the components beyond the meta-controller
COMPONENTS_FILE = "hhp_components.pt"  # not .pth: SB3 loads every .pth member as weights only
REPLAY_FORMAT = "sb3_hhp.HhP.replay"  # the file of HhP.save_replay_buffer


def _continuous_actions(env: Union[GymEnv, str]) -> bool:
    """Whether ``env`` (a gym env, a VecEnv or an env id) has a continuous (Box) action space."""
    if isinstance(env, str):
        try:
            space = gym.spec(env).make().action_space
        except gym.error.Error:
            return False  # the unknown id is reported with its fix when the env is built
    else:
        space = env.action_space
    return isinstance(space, spaces.Box)


def _holds(file: Any, data: bytes, prefix: bool = False) -> bool:
    """Whether a model file (a path or a binary file object) begins with, or contains, ``data``."""
    try:
        if hasattr(file, "read"):
            position = file.tell()
            file.seek(0)
            content = file.read()
            file.seek(position)
        else:
            content = pathlib.Path(file).read_bytes()
    except (OSError, ValueError):
        return False
    return content.startswith(data) if prefix else data in content


def _vec_env(env: Union[GymEnv, str, None]) -> Optional[VecEnv]:
    """The primitive envs under ``env`` as a VecEnv: an env id or a gym env becomes a DummyVecEnv of one env (with
    the observation its goal space reads, and a Monitor for SB3's episode statistics); a VecEnv is used as it is
    (each env already wrapped, e.g. ``make_vec_env(ENV, n_envs=8, wrapper_class=sb3_hhp.goals.wrap_env)``)."""
    if env is None:
        return None
    if isinstance(env, str):
        try:
            env = gym.make(env)
        except gym.error.Error as error:
            raise ValueError(f"Unknown env id {env!r}: {error}") from error
    if isinstance(env, VecTransposeImage):  # SB3's own layout change (RL Zoo adds it for images): HhP turns images itself
        env = env.venv
    if isinstance(env, VecEnv):
        return check_vec_env(env)
    if not isinstance(env, gym.Env):
        raise ValueError(f"HhP needs a gymnasium env, an env id or a VecEnv, got {type(env).__name__}")
    wrapped = wrap_env(env)
    return DummyVecEnv([lambda: wrapped if is_wrapped(wrapped, Monitor) else Monitor(wrapped)])


class _Grouped:
    """An attribute of the model that is one key of one of its ``*_kwargs`` dicts (read and set through it)."""

    def __init__(self, group: str, key: str) -> None:
        self.group, self.key = group, key

    def __get__(self, model: Any, owner: Any = None) -> Any:
        return self if model is None else getattr(model, self.group)[self.key]

    def __set__(self, model: Any, value: Any) -> None:
        getattr(model, self.group)[self.key] = value


class HhP(HierarchicalActing, PreferenceBonus, BetweenEpisodes, DoubleDQN):
    """Hierarchical learning from human preferences and curiosity (Algorithm 1).

    The meta-controller (this class, a Double DQN with prioritized replay) chooses a sub-goal for each env; the
    sub-goal learners run it until ``terminal(s, g)`` (:class:`~sb3_hhp.hierarchy.options.OptionRunner`); between
    episodes the oracle is asked about the least confident choices, CSD adds sub-goals and RND is updated
    (:class:`~sb3_hhp.hhp.episodes.BetweenEpisodes`); then N_opt meta-controller updates whose reward is eq. 3.
    ``total_timesteps`` counts primitive env steps, :meth:`~sb3_hhp.hhp.acting.HierarchicalActing.predict` returns primitive actions, and
    :meth:`~sb3_hhp.hhp.hhp.HhP.get_env` is the VecEnv of primitive envs, as SB3 users expect. The same semi-MDP is offered to any SB3
    algorithm by :class:`~sb3_hhp.hierarchy.semi_mdp.HierarchicalEnv`.

    :param policy: the meta-controller's policy ("MlpPolicy", "CnnPolicy", "MultiInputPolicy" or a class)
    :param env: the task: a gym env or an env id (wrapped with :func:`~sb3_hhp.goals.wrap_env` and a Monitor), or a
        VecEnv of any number of envs, each already wrapped
    :param oracle: who answers preference queries: an :class:`~sb3_hhp.oracles.base.Oracle`, a name of
        :data:`~sb3_hhp.oracles.registry.ORACLE_NAMES` (built with ``query_kwargs["oracle_kwargs"]``), or None
    :param query_budget: total number of questions over training (>= 0); 0 with no preference file gives the paper's
        "Cur" ablation (no labels, so the meta-controller's reward is R_e alone)
    :param beta: weight of the extrinsic return in eq. 3, in [0, 1]
    :param alpha: weight of the intrinsic reward in eq. 6 (>= 0)
    :param use_curiosity: False gives the paper's "Pref" ablation (no RND at all: no intrinsic reward, and CSD ranks
        no novelty progress)
    :param goal_space: "auto", a registered name or a :class:`~sb3_hhp.goals.base.GoalSpace`
    :param max_subgoal_steps: primitive steps after which a sub-goal gives up (``terminal(s, g)``, design decisions)
    :param preference_db: path of the SQLite preference store (None: in memory); the labeling page reads it
    :param query_kwargs: who is asked and when, over :data:`~sb3_hhp.hhp.arguments.QUERY_DEFAULTS`
    :param predictor_kwargs: the preference predictor's, over :data:`~sb3_hhp.hhp.arguments.PREDICTOR_DEFAULTS`
        (any argument of :class:`~sb3_hhp.preferences.predictor.PreferencePredictor`, and ``input``)
    :param discovery_kwargs: CSD's, over :data:`~sb3_hhp.hhp.arguments.DISCOVERY_DEFAULTS` (``strategy``, the
        ``subgoals`` handed in, the similarity gate b_similarity, ...)
    :param subgoal_learner_kwargs: how the sub-goal learners learn, over
        :data:`~sb3_hhp.hhp.arguments.SUBGOAL_LEARNER_DEFAULTS`
    :param subpolicy_kwargs: the sub-goal learners' SB3 arguments (discrete actions: DQN's names, over
        :data:`~sb3_hhp.hierarchy.learner_kwargs.DEFAULT_SUBPOLICY_KWARGS`; ``buffer_size`` is the shared replay's, in
        primitive transitions; continuous actions: the goal-conditioned SB3 model's, SAC by default)
    :param rnd_kwargs: arguments of :class:`~sb3_hhp.curiosity.rnd.RND` (memory_size M, refresh_interval T, ...)
    :param meta_kwargs: the meta-controller beyond SB3's DQN arguments, over
        :data:`~sb3_hhp.hhp.arguments.META_DEFAULTS` (``n_opt``, the target network's interval in choices, the
        preference bonus's centring, masks, cycle breaking, ``discount`` per choice or per primitive step, ...)
    :param learning_rate: the meta-controller's (SB3's DQN); so are ``batch_size``, ``gamma``, the exploration
        schedule (over primitive steps), ``policy_kwargs``, ``tensorboard_log``, ``verbose``, ``seed`` and ``device``
    :param buffer_size: the meta replay R_H, in sub-goal choices
    :param learning_starts: primitive steps of random sub-goal choices before the meta-controller chooses
    :param batch_size: the meta-controller's batch
    :param gamma: the meta-controller's discount, per choice
    :param exploration_fraction: the fraction of training over which its epsilon falls
    :param exploration_final_eps: its epsilon at the end of that fraction
    :param policy_kwargs: the meta-controller's policy's arguments
    :param tensorboard_log: SB3's
    :param verbose: SB3's
    :param seed: SB3's
    :param device: SB3's
    :param _init_setup_model: SB3's
    """

    center_bonus = _Grouped("meta_kwargs", "center_bonus")
    exact_bonus = _Grouped("meta_kwargs", "exact_bonus")
    success_bonus = _Grouped("meta_kwargs", "success_bonus")
    mask_subgoals = _Grouped("meta_kwargs", "mask_subgoals")
    break_cycles = _Grouped("meta_kwargs", "break_cycles")
    meta_discount = _Grouped("meta_kwargs", "discount")
    meta_input = _Grouped("meta_kwargs", "input")
    predictor_input = _Grouped("predictor_kwargs", "input")
    discovery_strategy = _Grouped("discovery_kwargs", "strategy")
    subgoal_learner = _Grouped("subgoal_learner_kwargs", "kind")

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }

    def __init__(
        self,
        policy: Union[str, type[DQNPolicy]],
        env: Union[GymEnv, str, None],
        oracle: Union[str, Oracle, None] = "scripted",
        query_budget: int = 100,
        beta: float = 0.7,
        alpha: float = 0.5,
        use_curiosity: bool = True,
        goal_space: Union[str, GoalSpace] = "auto",
        max_subgoal_steps: int = 50,
        preference_db: Optional[str] = None,
        query_kwargs: Optional[dict[str, Any]] = None,
        predictor_kwargs: Optional[dict[str, Any]] = None,
        discovery_kwargs: Optional[dict[str, Any]] = None,
        subgoal_learner_kwargs: Optional[dict[str, Any]] = None,
        subpolicy_kwargs: Optional[dict[str, Any]] = None,
        rnd_kwargs: Optional[dict[str, Any]] = None,
        meta_kwargs: Optional[dict[str, Any]] = None,
        learning_rate: Union[float, Schedule] = 1e-3,
        buffer_size: int = 500_000,
        learning_starts: int = 1_000,
        batch_size: int = 128,
        gamma: float = 0.99,
        exploration_fraction: float = 0.2,
        exploration_final_eps: float = 0.05,
        policy_kwargs: Optional[dict[str, Any]] = None,
        tensorboard_log: Optional[str] = None,
        verbose: int = 0,
        seed: Optional[int] = None,
        device: Union[th.device, str] = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {beta}")
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        if isinstance(query_budget, bool) or not isinstance(query_budget, (int, np.integer)) or query_budget < 0:
            raise ValueError(f"query_budget must be an integer >= 0, got {query_budget!r}")
        self.query_kwargs = grouped("query_kwargs", query_kwargs)
        self.predictor_kwargs = grouped("predictor_kwargs", predictor_kwargs)
        self.discovery_kwargs = grouped("discovery_kwargs", discovery_kwargs)
        self.subgoal_learner_kwargs = grouped("subgoal_learner_kwargs", subgoal_learner_kwargs)
        self.meta_kwargs = grouped("meta_kwargs", meta_kwargs)
        check_grouped(self.query_kwargs, self.predictor_kwargs, self.discovery_kwargs, self.subgoal_learner_kwargs,
                      self.meta_kwargs)
        learner, meta = self.subgoal_learner_kwargs, self.meta_kwargs
        continuous = env is not None and _continuous_actions(env)  # an env id is built to be read: once
        if learner["kind"] is None and env is not None:
            learner["kind"] = "goal_conditioned" if continuous else "stacked"
        # discrete sub-goal learners train on every step (the goal-conditioned learner updates at every step anyway)
        if learner["train_shared"] is None:
            learner["train_shared"] = learner["share_experience"] and not continuous
        subgoals = self.discovery_kwargs.pop("subgoals")
        self.initial_subgoals = [np.asarray(goal) for goal in subgoals] if subgoals else []
        self.oracle_spec = oracle
        self.query_budget = int(query_budget)
        self.beta = beta
        self.alpha = alpha
        self.use_curiosity = use_curiosity
        self.goal_space_spec = goal_space
        self.max_subgoal_steps = max_subgoal_steps
        self.rnd_kwargs = dict(rnd_kwargs or {})
        self.subpolicy_kwargs = dict(subpolicy_kwargs or {})
        self.preference_db = preference_db
        self.subpolicy_policy = policy if isinstance(policy, str) else "MlpPolicy"

        venv = _vec_env(env)
        self.subgoal_set = SubgoalSet()
        self.options: Optional[OptionRunner] = None
        if venv is not None:
            probe = env_view(venv)
            self.goal_space = make_goal_space(goal_space, probe)
            self.primitive_observation_space = venv.observation_space
            self.primitive_action_space = venv.action_space
            self.options = OptionRunner(venv, self.goal_space, self.subgoal_set, learners=None, rnd=None,
                                        max_subgoal_steps=max_subgoal_steps)
            policy_kwargs = self._meta_policy_kwargs(policy_kwargs)
            if policy == "CnnPolicy":
                policy_kwargs = self._cnn_policy_kwargs(policy_kwargs)
        super().__init__(
            policy,
            SubgoalVecEnv(self.options, meta["capacity"]) if self.options is not None else None,  # type: ignore[arg-type]
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=meta["tau"],
            gamma=gamma,
            train_freq=(1, "episode"),
            gradient_steps=meta["n_opt"],
            target_update_interval=meta["target_update_interval"],
            exploration_fraction=exploration_fraction,
            exploration_initial_eps=meta["exploration_initial_eps"],
            exploration_final_eps=exploration_final_eps,
            max_grad_norm=meta["max_grad_norm"],
            stats_window_size=meta["stats_window_size"],
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ construction
    def _reads_features(self, option: str, value: str) -> bool:
        """Whether ``option`` ("predictor_input" / "meta_input") set to ``value`` means reading the goal space's
        features: "features" needs them (a clear error otherwise), "auto" takes them when they exist."""
        if value == "observation":
            return False
        has_features = self.goal_space.features_dim(self.primitive_observation_space) is not None
        if value == "features" and not has_features:
            raise ValueError(
                f"{option}='features' needs a goal space with features; {type(self.goal_space).__name__} has none: "
                f"use {option}='observation' (or 'auto')"
            )
        return has_features

    def _meta_policy_kwargs(self, policy_kwargs: Optional[dict[str, Any]]) -> dict[str, Any]:
        """``policy_kwargs`` with the goal space's features as the meta-controller's features extractor when
        ``meta_input`` asks for them (and no extractor is named)."""
        policy_kwargs = dict(policy_kwargs or {})
        reads_features = self._reads_features("meta_kwargs['input']", self.meta_input)
        if self.meta_input == "auto" and self.subpolicy_policy == "CnnPolicy":
            reads_features = False  # CnnPolicy asks for a CNN on the observation
        if self.meta_input == "features" and "features_extractor_class" in policy_kwargs:
            raise ValueError("meta_kwargs['input']='features' sets the features extractor: remove features_extractor_class "
                             "from policy_kwargs")
        if reads_features and "features_extractor_class" not in policy_kwargs:
            policy_kwargs.update(features_extractor_class=GoalSpaceFeatures, features_extractor_kwargs=dict(goal_space=self.goal_space))
        return policy_kwargs

    def _cnn_policy_kwargs(self, policy_kwargs: dict[str, Any]) -> dict[str, Any]:
        """``CnnPolicy`` on a symbolic grid (MiniGrid) reads it with :class:`~sb3_hhp.hhp.policies.GridCNN`, for the
        meta-controller and the sub-goal learners alike; on a space no CNN can read, a clear error."""
        space = self.primitive_observation_space
        if is_image_space(space, check_channels=False):
            return policy_kwargs
        if len(space.shape) == 3 and space.shape[0] >= 4 and space.shape[1] >= 4 and space.dtype == np.uint8:
            sub = dict(self.subpolicy_kwargs.get("policy_kwargs") or {})
            sub.setdefault("features_extractor_class", GridCNN)
            self.subpolicy_kwargs["policy_kwargs"] = sub
            policy_kwargs.setdefault("features_extractor_class", GridCNN)
            return policy_kwargs
        raise ValueError(
            f"CnnPolicy reads images or symbolic grids (H, W, C) of uint8, and this env's observations are "
            f"{space}: use HhP('MlpPolicy', env)"
        )

    def _learner_inputs(self, obs_space: spaces.Space) -> dict[str, Any]:
        """``subgoal_learner_kwargs`` with each ``"auto"`` of ``view``, ``overview`` and ``one_hot`` replaced by what the
        goal space derives from the env (:meth:`~sb3_hhp.goals.base.GoalSpace.learner_input`)."""
        learner = dict(self.subgoal_learner_kwargs)
        auto = [name for name in LEARNER_INPUTS if isinstance(learner[name], str) and learner[name] == "auto"]
        if auto:
            derived = self.goal_space.learner_input(obs_space)
            if derived is None:
                raise ValueError(f"subgoal_learner_kwargs {', '.join(auto)} 'auto' are derived from the env by its goal "
                                 f"space, and {type(self.goal_space).__name__} derives none: give them (or None)")
            learner.update({name: derived[name] for name in auto})
        return learner

    def _setup_model(self) -> None:
        # the replay R_H holds sub-goal choices, which end at different times in different envs: one stream
        n_envs, self.n_envs = self.n_envs, 1
        try:
            super()._setup_model()
        finally:
            self.n_envs = n_envs
        #: the primitive steps of the choice in each row of R_H (``meta_kwargs["discount"] == "steps"`` discounts by them)
        self._choice_steps = np.ones(self.replay_buffer.buffer_size, dtype=np.int32)
        device = get_device(self.device)
        obs_space = self.primitive_observation_space
        self.rnd = RND(obs_space, device=device, seed=self.seed, **self.rnd_kwargs) if self.use_curiosity else None
        predictor_kwargs = dict(buffer_size=max(1, self.query_budget), device=device, seed=self.seed)
        predictor_kwargs.update(self.predictor_settings)
        self._predictor_reads_features = self._reads_features("predictor_kwargs['input']", self.predictor_input)
        predictor_space = (
            spaces.Box(-np.inf, np.inf, (self.goal_space.features_dim(obs_space),), np.float32)
            if self._predictor_reads_features else obs_space
        )
        self.predictor = PreferencePredictor(predictor_space, **predictor_kwargs)
        query = {key: value for key, value in self.query_kwargs.items()
                 if key not in ("horizon", "record_images", "oracle_kwargs")}
        self.query_selector = QuerySelector(self.query_budget, **query)
        self.return_normalizer = PreferenceReturnNormalizer(gamma=0.99, rollout_length=64)
        alpha = self.alpha if self.use_curiosity else 0.0
        learner = self._learner_inputs(obs_space)
        discrete = isinstance(self.primitive_action_space, spaces.Discrete)
        if discrete != (self.subgoal_learner in SUBGOAL_LEARNERS):
            raise ValueError(f"subgoal_learner_kwargs kind {self.subgoal_learner!r} does not suit "
                             f"{self.primitive_action_space}: discrete actions take 'stacked' or 'heads', continuous "
                             "ones 'goal_conditioned'")
        if discrete:
            self.subpolicies = SUBGOAL_LEARNERS[self.subgoal_learner](
                obs_space, self.primitive_action_space, self.goal_space.achieved, policy=self.subpolicy_policy,
                subpolicy_kwargs=self.subpolicy_kwargs, alpha=alpha, n_envs=self.n_envs, device=device, seed=self.seed,
                action_mask=self.goal_space.action_mask, counterfactual=self.goal_space.carried_counterfactual,
                input_codes=self.goal_space.learner_codes(),
                **{key: value for key, value in learner.items() if key != "kind"},
            )
        else:
            # the options of the learners of discrete actions, each with the value that leaves it unset
            for name, unset in (("exploration_run_steps", None), ("carry_relabel", 0.0), ("target_range", None),
                                ("one_hot", None), ("overview", None), ("view", None)):
                if learner[name] != unset:
                    raise ValueError(f"subgoal_learner_kwargs['{name}'] applies to the learners of discrete actions; this "
                                     f"env's sub-goal learners are continuous-action models that read the whole "
                                     f"observation as it is: leave {name} out")
            space = self.goal_space
            if not hasattr(space, "goal_position"):
                raise ValueError(f"subgoal_learner_kwargs kind 'goal_conditioned' needs a goal space whose sub-goals are "
                                 f"places (goal_position, state_part: FetchGoalSpace); {type(space).__name__} has none")
            self.subpolicies = GoalConditionedLearner(
                obs_space, self.primitive_action_space, getattr(space, "achieved_goal", space.achieved_position),
                space.state_part, space.goal_position,
                space.distance_threshold, alpha=alpha, subpolicy_kwargs=self.subpolicy_kwargs, n_envs=self.n_envs,
                device=device, seed=self.seed)
        self.discovery = SubgoalDiscovery(
            self.goal_space, strategy="random" if self.discovery_strategy == "random" else "csd", seed=self.seed,
            **{key: value for key, value in self.discovery_kwargs.items() if key != "strategy"},
        )
        self.store = PreferenceStore(self._store_path(), create=True)
        self.store.set_query_budget(self.query_budget)  # shown on the labeling page as "asked / budget"
        self.subgoal_table = SubgoalTable(self.store)  # the labeling page's gallery, in the store's file
        self.oracle = self._make_oracle()
        answering = getattr(self.oracle, "oracle", self.oracle)  # a noisy oracle's own
        if self.initial_subgoals and getattr(answering, "needs_found_facts", False):
            raise ValueError(f"{type(answering).__name__} answers from the facts of the state each sub-goal was found in, "
                             "and sub-goals handed in (discovery_kwargs['subgoals']) have none: let discovery find "
                             "them, or ask another oracle (oracle='synthetic', 'web' or 'terminal')")
        self.record_images = self.query_kwargs["record_images"]
        if self.record_images is None:  # states shown to people, unless a question's state is drawn from its facts
            self.record_images = (self.oracle_spec in ("web", "terminal")
                                  and not getattr(self.goal_space, "draws_from_facts", False))
        if not hasattr(self, "consumed_query_ids"):
            self.consumed_query_ids: set[str] = set()
        self.pending_queries: dict[str, Any] = {}
        self._mask_cache: dict[Any, np.ndarray] = {}  # (state key, present) -> choosable sub-goals, emptied when G changes
        self._present_cache: dict[bytes, tuple] = {}  # observation digest -> (key, present)
        self.recent_choices: deque = deque(maxlen=1_000)
        self._unscored: list = []  # choices stored in R_H whose preference bonus is not yet in sigma(R_p)
        self.last_predictor_stats: dict[str, float] = {}
        self.last_confidences: np.ndarray = np.zeros(0)
        self._last_trace = EpisodeTrace()
        self._rollout_episodes, self._rollout_steps, self._rollout_choices = 0, 0, 0
        if not hasattr(self, "_update_allowance"):
            self._update_allowance = 0.0  # meta-controller updates the steps so far allow (meta_kwargs steps_per_update)
        if not hasattr(self, "_choice_allowance"):
            self._choice_allowance = 0.0  # updates the choices so far ask for (meta_kwargs choices_per_update)
        if self.options is not None:
            self._attach(self.options)

    def _attach(self, options: OptionRunner) -> None:
        options.learners, options.rnd, options.subgoals = self.subpolicies, self.rnd, self.subgoal_set
        options.record_images = bool(self.record_images)
        options.return_discount = self.gamma if self.meta_discount == "steps" else None
        if not self.subgoal_set.goals:
            shape = self.primitive_observation_space.shape
            for index, goal_obs in enumerate(self.initial_subgoals):
                if goal_obs.shape != shape:
                    raise ValueError(f"discovery_kwargs['subgoals'][{index}] has shape {goal_obs.shape}; a sub-goal is an "
                                     f"observation of the env, shape {shape} (pass what env.reset() returns, wrapped as "
                                     "HhP wraps it: sb3_hhp.goals.wrap_env)")
                self.add_subgoal(self.goal_space.key(goal_obs), goal_obs, None, source="user")
        self._sync_action_space()

    def _make_oracle(self) -> Optional[Oracle]:
        if isinstance(self.oracle_spec, Oracle):
            return self.oracle_spec
        if self.oracle_spec is None:
            return None
        return make_oracle(
            self.oracle_spec, self.goal_space, self.primitive_observation_space, store=self.store, seed=self.seed,
            **self.query_kwargs["oracle_kwargs"],
        )

    # ------------------------------------------------------------------ the sub-goal set
    @property
    def subgoals(self) -> list[Subgoal]:
        """The sub-goal set G, in the order of the meta-controller's actions."""
        return self.subgoal_set.goals

    def add_subgoal(self, key: Any, obs: np.ndarray, image: Optional[np.ndarray], source: str = "csd",
                    snapshot: Any = None) -> int:
        """Add a sub-goal (and its learner); the meta-controller's head doubles when full (design decisions: growing head).
        ``snapshot``: the goal space's snapshot of the state it was found in (questions give its facts to oracles)."""
        goal_id = self.subgoal_set.add(key, obs, image, self.num_timesteps, source, snapshot)
        self.subpolicies.add(key)
        self._sync_action_space()
        return goal_id

    def _sync_action_space(self) -> None:
        """Match the meta-controller's head and valid-action mask to the sub-goal set."""
        n_goals = len(self.subgoals)
        capacity = int(self.action_space.n)
        while capacity < n_goals:
            capacity *= 2
        if capacity > self.action_space.n:
            self.resize_action_space(capacity)
        if self.env is not None and self.env.action_space != self.action_space:
            self.env.action_space = self.action_space
            if isinstance(self.env, VecTransposeImage):
                self.env.venv.action_space = self.action_space
        mask = np.arange(self.action_space.n) < n_goals
        self.valid_actions = mask if n_goals > 0 else None
        self._mask_cache = {}

    def _discounts(self, replay_data: Any) -> Union[float, th.Tensor]:
        """``gamma`` per choice, or (``meta_kwargs["discount"] == "steps"``) ``gamma^k`` for a choice whose option took
        k primitive steps: the semi-MDP's bootstrap, under which an option that ends sooner is not paid for it."""
        if self.meta_discount == "choice":
            return super()._discounts(replay_data)
        rows = np.asarray(replay_data.indices) // self.replay_buffer.n_envs
        discounts = np.power(self.gamma, self._choice_steps[rows], dtype=np.float64).astype(np.float32)
        return th.as_tensor(discounts, device=replay_data.rewards.device).reshape(-1, 1)

    @property
    def predictor_settings(self) -> dict[str, Any]:
        """The keys of ``predictor_kwargs`` that :class:`~sb3_hhp.preferences.predictor.PreferencePredictor` takes
        (all but ``input``, what HhP gives it to read)."""
        return {key: value for key, value in self.predictor_kwargs.items() if key != "input"}

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """N_opt meta-controller updates for each episode that just ended (Algorithm 1 lines 30-34), once the meta
        buffer holds a batch. With ``meta_kwargs["steps_per_update"]`` = K, no more than the rollout's primitive steps
        over K: short episodes (a solved task's, or every life lost on Atari) then do not each cost N_opt updates.
        What a rollout does not use of its steps' allowance is kept for the next, up to its own N_opt per episode.
        With ``meta_kwargs["choices_per_update"]`` = C, at least one update per C choices stored (long episodes of many
        choices then get more than N_opt), the fraction kept for the next rollout."""
        if self.replay_buffer is None or self.replay_buffer.size() < batch_size:
            return
        due = gradient_steps * max(1, self._rollout_episodes)
        per_choice = self.meta_kwargs.get("choices_per_update")  # (absent from a model saved before the option)
        if per_choice is not None:
            self._choice_allowance += self._rollout_choices / per_choice
            by_choices = int(self._choice_allowance)
            self._choice_allowance -= by_choices
            due = max(due, by_choices)
        every = self.meta_kwargs["steps_per_update"]
        if every is not None:
            self._update_allowance = min(self._update_allowance + self._rollout_steps / every, float(due))
            due = int(self._update_allowance)
            self._update_allowance -= due
        if due > 0:
            super().train(due, batch_size)

    # ------------------------------------------------------------------ rollouts
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: ReplayBuffer,
        action_noise: Any = None,
        learning_starts: int = 0,
        log_interval: Optional[int] = None,
    ) -> RolloutReturn:
        """Run the option loop on every env (Algorithm 1 lines 9-23) until an episode ends, then the work between
        episodes (lines 24-29, 35) for each one that ended. ``num_timesteps`` counts primitive steps of all envs;
        callbacks are called once per step of the envs, as SB3's own algorithms do."""
        options = self.options
        assert options is not None and options.obs is not None
        self.policy.set_training_mode(False)
        num_collected_steps, num_collected_episodes, num_collected_choices = 0, 0, 0
        callback.on_rollout_start()
        while num_collected_episodes == 0:
            waiting = options.waiting()
            if len(waiting):  # line 11, every env whose option ended in one forward
                goals = self.choose_subgoals(options.obs[waiting], learning_starts)
                options.start(waiting, goals)
                self.recent_choices.extend(int(goal) for goal in goals)
            ended, episodes = options.step()
            self.num_timesteps += options.num_envs
            num_collected_steps += 1
            if ended:
                self._store_choices(replay_buffer, ended)
                num_collected_choices += len(ended)
            callback.update_locals(locals())
            if not callback.on_step():
                self._score_ended_choices()
                return RolloutReturn(num_collected_steps * options.num_envs, num_collected_episodes, continue_training=False)
            self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
            if episodes:
                self._score_ended_choices()
            for episode in episodes:
                num_collected_episodes += 1
                self._episode_num += 1
                self._update_info_buffer([episode.info], np.array([True]))
                self._last_trace = episode.trace
                self.after_episode(episode.trace)  # lines 24-29, 35
                if log_interval is not None and self._episode_num % log_interval == 0:
                    self.dump_logs()
        self._score_ended_choices()
        self._rollout_episodes, self._rollout_steps = num_collected_episodes, num_collected_steps * options.num_envs
        self._rollout_choices = num_collected_choices
        callback.on_rollout_end()
        return RolloutReturn(num_collected_steps * options.num_envs, num_collected_episodes, True)

    def _store_choices(self, replay_buffer: ReplayBuffer, ended: list) -> None:
        """The sub-goal choices that ended in a step, into R_H one by one (line 23): (s, g, R_e, s', terminated), a
        time limit as a timeout; their preference bonuses, scored in one batch, update sigma(R_p) (line 12)."""
        for option in ended:
            obs = maybe_transpose(option.obs[None], self.observation_space)
            next_obs = maybe_transpose(option.next_obs[None], self.observation_space)
            done = option.terminated or option.truncated
            info = {"TimeLimit.truncated": option.truncated and not option.terminated}
            if replay_buffer is self.replay_buffer:
                if getattr(self, "_bonus_valid", None) is not None:
                    self._bonus_valid[replay_buffer.pos] = False  # the row's cached bonus belonged to the choice it held
                self._choice_steps[replay_buffer.pos] = option.steps  # >= 1: an option ends after a step at least
            replay_buffer.add(obs, next_obs, np.array([[option.goal]]),
                              np.array([option.extrinsic_return], dtype=np.float32), np.array([done]), [info])
            self._on_step()
        if len(self.predictor) > 0:
            self._unscored.extend(ended)

    def _score_ended_choices(self) -> None:
        """The preference bonuses of the choices stored since the last call, scored in one batch and folded into
        sigma(R_p) in the order the choices ended (line 12). Called before the predictor or the sub-goal set can
        change (before the work between episodes) and when a rollout ends, so every bonus is the one the predictor
        gave when its choice ended, at one forward per episode rather than one per step."""
        ended, self._unscored = self._unscored, []
        if ended:
            states = np.stack([option.obs for option in ended])
            self.return_normalizer.update(self.preference_bonus(states, np.array([option.goal for option in ended])))

    def _on_step(self) -> None:
        """After each sub-goal choice stored: the target network every ``target_update_interval`` choices, and
        the exploration rate (SB3's DQN divides the interval by the number of envs; choices are counted here)."""
        self._n_calls += 1
        if self._n_calls % max(self.target_update_interval, 1) == 0:
            polyak_update(self.q_net.parameters(), self.q_net_target.parameters(), self.tau)
            polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
        self.exploration_rate = self.exploration_schedule(self._current_progress_remaining)
        self.logger.record("rollout/exploration_rate", self.exploration_rate)

    # ------------------------------------------------------------------ learning
    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        if isinstance(callback, list):
            callback = CallbackList(callback)
        if not isinstance(callback, BaseCallback):
            callback = ConvertCallback(callback)
        if progress_bar:
            callback = CallbackList([callback, ProgressBarCallback()])
        callback.init_callback(self)
        return callback

    def learn(
        self: SelfHhP,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "HhP",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfHhP:
        """Train for ``total_timesteps`` primitive env steps (Algorithm 1)."""
        if self.options is None:
            raise ValueError("This model has no env: pass one with HhP.load(path, env=env) or model.set_env(env)")
        if self.options.interrupted:  # the envs were stepped through get_env(): fresh episodes, not stale observations
            self._last_obs = None
        horizon = total_timesteps + (0 if reset_num_timesteps else self.num_timesteps)
        self.query_selector.set_total_timesteps(int(self.query_kwargs["horizon"] or horizon))
        self.resume_preferences()
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def get_env(self) -> Optional[VecEnv]:
        """The primitive envs, as a VecEnv whose actions are what :meth:`~sb3_hhp.hhp.acting.HierarchicalActing.predict` returns (SB3's README loop and
        ``evaluate_policy(model, model.get_env())`` work); None without an env."""
        if self.options is None:
            return None
        if getattr(self, "_primitive_env", None) is None or self._primitive_env.runner is not self.options:
            self._primitive_env = PrimitiveVecEnv(self.options)
        return self._primitive_env

    def dump_logs(self) -> None:
        """SB3's rollout logs plus HhP's: queries, sub-goals, predictor, confidence, curiosity, sub-goal success."""
        self.logger.record("hhp/queries_used", self.query_selector.used)
        self.logger.record("hhp/queries_left", self.query_selector.remaining)
        self.logger.record("hhp/queries_distinct", len(self.asked_signatures))
        self.logger.record("hhp/num_subgoals", len(self.subgoals))
        self.logger.record("hhp/preference_labels", len(self.predictor))
        for name, value in self.last_predictor_stats.items():
            self.logger.record(f"hhp/predictor_{name}", value)
        if len(self.last_confidences):
            self.logger.record("hhp/mean_confidence", float(np.mean(self.last_confidences)))
        self.logger.record("hhp/query_threshold", self.query_selector.current_threshold)
        if self._last_trace.intrinsic:
            self.logger.record("hhp/mean_intrinsic_reward", float(np.mean(self._last_trace.intrinsic)))
        self.logger.record("hhp/sigma_preference_return", self.return_normalizer.sigma)
        for goal_id in range(len(self.subpolicies)):
            rate = self.subpolicies.success_rate(goal_id)
            if rate is not None:
                self.logger.record(f"subgoals/success_rate_{goal_id}", rate)
        super().dump_logs()

    # ------------------------------------------------------------------ save / load
    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "options", "subgoal_set", "_last_trace", "rnd", "predictor", "query_selector", "return_normalizer", "subpolicies", "discovery",
            "store", "subgoal_table", "oracle", "oracle_spec", "pending_queries", "recent_choices", "last_predictor_stats",
            "last_confidences", "consumed_query_ids", "initial_subgoals", "_asked_signatures", "_asked_goal_keys", "_mask_cache", "_present_cache",
            "_bonus_key", "_bonus_cache", "_bonus_valid", "_choice_steps", "_unscored", "_primitive_env",
            *(["learn"] if "learn" in vars(self) else []),  # a bound learn (sb3_hhp.train --resume) is no data of the model
        ]

    def _store_path(self) -> str:
        """Where the preference store is: ``preference_db``, or ``":memory:"``. A file whose folder does not exist is
        refused with what to pass instead: a model loaded from a moved run folder names the store it was saved with."""
        if not self.preference_db:
            return ":memory:"
        folder = pathlib.Path(self.preference_db).parent
        if not folder.is_dir():
            raise ValueError(
                f"The preference store {str(self.preference_db)!r} cannot be opened: its folder {str(folder)!r} does not "
                "exist. A model loaded from a moved run folder names the store it was saved with: load it with the "
                "store where it is now, HhP.load(path, preference_db='RUN/preferences.sqlite'), or with "
                "preference_db=None for an empty store in memory")
        return str(self.preference_db)

    def components_state(self) -> dict[str, Any]:
        """Everything beyond the meta-controller: subpolicies, predictor (with the preference data), RND and
        Omega, the sub-goal set with its images, the query count and budget."""
        from dataclasses import asdict

        return {
            "format": "sb3_hhp.HhP",
            "subgoals": [asdict(goal) for goal in self.subgoals],
            "visits": dict(self.subgoal_set.visits),
            "subpolicies": self.subpolicies.state_dict(),
            "predictor": self.predictor.state_dict(),
            "rnd": self.rnd.state_dict() if self.rnd is not None else None,
            "query_selector": self.query_selector.state_dict(),
            "return_normalizer": self.return_normalizer.state_dict(),
            "consumed_query_ids": sorted(self.consumed_query_ids),
            "recent_choices": list(self.recent_choices),
            "oracle": self.oracle_spec if isinstance(self.oracle_spec, str) or self.oracle_spec is None else "none",
        }

    def load_components_state(self, state: dict[str, Any]) -> None:
        if not isinstance(state, dict) or state.get("format") != "sb3_hhp.HhP":
            raise ValueError("This file holds no HhP components: it was not saved by sb3_hhp.HhP.save")
        self.subpolicies.load_state_dict(state["subpolicies"])
        self.subgoal_set.goals[:] = [Subgoal(**goal) for goal in state["subgoals"]]
        self.subgoal_set.visits.clear()
        self.subgoal_set.visits.update(state["visits"])
        self.predictor.load_state_dict(state["predictor"])
        if self.rnd is not None and state["rnd"] is not None:
            self.rnd.load_state_dict(state["rnd"])
        self.query_selector.load_state_dict(state["query_selector"])
        self.return_normalizer.load_state_dict(state["return_normalizer"])
        self.consumed_query_ids = set(state["consumed_query_ids"])
        self.recent_choices = deque(state.get("recent_choices", []), maxlen=self.recent_choices.maxlen)  # absent in older saves
        self._sync_action_space()

    def save(self, path: Any, exclude: Optional[list[str]] = None, include: Optional[list[str]] = None) -> None:
        """SB3's save (meta-controller) plus one more zip member with every other component."""
        super().save(path, exclude=exclude, include=include)
        if isinstance(path, (str,)) or hasattr(path, "__fspath__"):
            path = pathlib.Path(path)
            if path.suffix == "":
                path = path.with_suffix(".zip")
        buffer = io.BytesIO()
        th.save(self.components_state(), buffer)
        with zipfile.ZipFile(path, mode="a") as archive:
            archive.writestr(COMPONENTS_FILE, buffer.getvalue())

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfHhP],
        path: Any,
        env: Optional[GymEnv] = None,
        device: Union[th.device, str] = "auto",
        custom_objects: Optional[dict[str, Any]] = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfHhP:
        """Load a saved HhP (everything :meth:`save` wrote); give ``env`` to go on training."""
        file = pathlib.Path(path) if isinstance(path, str) or hasattr(path, "__fspath__") else path
        if isinstance(file, pathlib.Path) and not file.exists() and file.with_suffix(".zip").exists():
            file = file.with_suffix(".zip")
        try:
            with zipfile.ZipFile(file) as archive:
                if COMPONENTS_FILE not in archive.namelist():
                    if _holds(file, COMPONENTS_FILE.encode()):  # the member's header is there, the archive's end is not
                        raise ValueError(f"{path} is truncated: it holds the start of an HhP model's {COMPONENTS_FILE} "
                                         "but not the end of the file (an interrupted copy or save?); use a complete copy")
                    raise ValueError(f"{path} is not an HhP model: it has no {COMPONENTS_FILE} (was it saved by HhP.save?)")
                try:
                    components = th.load(io.BytesIO(archive.read(COMPONENTS_FILE)), map_location="cpu", weights_only=False)
                except (pickle.UnpicklingError, EOFError, RuntimeError) as error:
                    raise ValueError(
                        f"{path} is a damaged HhP model: its {COMPONENTS_FILE} cannot be read ({error}); save it again with HhP.save"
                    ) from error
                # the oracle: the caller's (HhP.load(path, oracle="web")), else the one the model was saved with
                kwargs["oracle_spec"] = kwargs.pop("oracle") if "oracle" in kwargs else components.get("oracle", "scripted")
        except zipfile.BadZipFile as error:
            if _holds(file, b"PK\x03\x04", prefix=True):
                raise ValueError(f"{path} is truncated or damaged: it begins as a saved model (a zip archive) but its end "
                                 f"is missing or unreadable ({error}); use a complete copy") from error
            raise ValueError(f"{path} is not a saved HhP model (not a zip archive): {error}") from error
        # settings that are keys of a *_kwargs dict (HhP.load(path, break_cycles=False)) go into their dict
        grouped_settings = {name: kwargs.pop(name) for name in list(kwargs) if isinstance(vars(cls).get(name), _Grouped)}
        model = super().load(file, env=None, device=device, custom_objects=custom_objects,
                             print_system_info=print_system_info, force_reset=force_reset, **kwargs)
        for name, value in grouped_settings.items():
            setattr(model, name, value)
        model.load_components_state(components)
        if env is not None:
            model.set_env(env, force_reset=force_reset)
        return model

    def save_replay_buffer(self, path: Union[str, pathlib.Path, io.BufferedIOBase]) -> None:
        """Save the meta-controller's replay R_H and the sub-goal learners' replay in one pickle file (SB3's saves
        R_H alone): with :meth:`save`, what training needs to go on where it stopped (RL Zoo's ``--save-replay-buffer``,
        ``sb3_hhp.train --checkpoint-freq``). Only the rows in use are written."""
        assert self.replay_buffer is not None, "The replay buffer is not defined"
        meta = self.replay_buffer
        rows = meta.buffer_size if meta.full else meta.pos
        save_to_pkl(path, {
            "format": REPLAY_FORMAT,
            "meta": buffer_state(meta, meta.buffer_size, rows),
            "choice_steps": self._choice_steps[:rows].copy(),
            "subgoal_learners": self.subpolicies.replay_state(),
        }, self.verbose)

    def load_replay_buffer(self, path: Union[str, pathlib.Path, io.BufferedIOBase], truncate_last_traj: bool = True) -> None:
        """Load what :meth:`save_replay_buffer` saved into this model's replays (built with the same settings and
        sub-goals: load the model saved with it first). A file of SB3's ``save_replay_buffer`` (R_H alone) is
        taken as R_H, the sub-goal learners' replay left as it is. ``truncate_last_traj``: training goes on from
        fresh episodes, so the newest transition of each env in the sub-goal learners' replay is taken as cut by a
        time limit (no n-step return runs on into the next episode)."""
        try:
            data = load_from_pkl(path, self.verbose)
        except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, ValueError) as error:
            raise ValueError(f"{path} cannot be read as a saved replay ({type(error).__name__}: {error}): a damaged or "
                             "truncated file? Save it again with HhP.save_replay_buffer") from error
        if isinstance(data, ReplayBuffer):
            super().load_replay_buffer(path, truncate_last_traj)  # SB3's file: R_H only, its choices' steps unknown (1)
            self._bonus_key = None
            self._choice_steps[:] = 1
            return
        if not isinstance(data, dict) or data.get("format") != REPLAY_FORMAT:
            raise ValueError(f"{path} is not a replay saved by HhP.save_replay_buffer (nor an SB3 replay buffer)")
        self.subpolicies.load_replay_state(data["subgoal_learners"], truncate_last_traj)
        meta = self.replay_buffer
        load_buffer_state(meta, data["meta"], meta.buffer_size, "the meta-controller's replay R_H")
        steps = np.asarray(data.get("choice_steps", ()), dtype=np.int32)
        self._choice_steps[:] = 1
        self._choice_steps[:len(steps)] = steps
        meta.device = self.device
        self._bonus_key = None  # the cached preference bonuses belonged to the rows held before

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """Attach (new) envs: an env, an env id or a VecEnv of any number of envs, whose sub-goals are the model's."""
        venv = _vec_env(env)
        assert venv is not None
        if venv.observation_space != self.primitive_observation_space:
            hint = "; wrap MiniGrid envs with sb3_hhp.goals.wrap_env" if isinstance(self.goal_space, MiniGridGoalSpace) else ""
            raise ValueError(
                f"The env's observation space {venv.observation_space} differs from the model's "
                f"{self.primitive_observation_space}{hint}"
            )
        self.options = OptionRunner(venv, self.goal_space, self.subgoal_set, self.subpolicies, self.rnd,
                                    max_subgoal_steps=self.max_subgoal_steps)
        if venv.num_envs != getattr(self.subpolicies, "n_envs", venv.num_envs):
            self.subpolicies.set_n_envs(venv.num_envs)
        self._attach(self.options)
        view = SubgoalVecEnv(self.options, int(self.action_space.n))
        n_envs, self.n_envs = self.n_envs, venv.num_envs  # SB3 refuses a different number of envs; HhP takes any
        try:
            super().set_env(view, force_reset=force_reset)
        except Exception:
            self.n_envs = n_envs
            raise
