"""HhP: hierarchical learning from human preferences and curiosity (Algorithm 1).

The meta-controller is a Double DQN with prioritized replay (this class) acting on a
:class:`~sb3_hhp.hierarchy.env.HierarchicalEnv`: each of its actions is a sub-goal, run by that
sub-goal's subpolicy until ``terminal(s, g)``. ``total_timesteps`` counts primitive env steps.
Between episodes, SB3 callbacks (:mod:`sb3_hhp.callbacks`) ask the oracle about the least
confident choices (lines 24-27), discover sub-goals (line 29) and update the curiosity model (line
35); then ``train`` runs N_opt meta-controller updates (lines 30-34) whose reward is eq. 3.
"""

import hashlib
import inspect
import io
import pathlib
import pickle
import zipfile
from collections import Counter, deque
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
from sb3_hhp.goals import SUCCESS_KEY, GoalSpace, MiniGridGoalSpace, make_goal_space, wrap_env
from sb3_hhp.hhp.policies import CnnPolicy, DQNPolicy, GoalSpaceFeatures, GridCNN, MlpPolicy, MultiInputPolicy
from sb3_hhp.hhp.episodes import BetweenEpisodes
from sb3_hhp.hierarchy.learners import PAPER_SUBPOLICY_KWARGS, SharedHeadsDQN, StackedDQN
from sb3_hhp.hierarchy.options import (
    EpisodeTrace, OptionRunner, Subgoal, SubgoalSet, SubgoalVecEnv, check_vec_env, env_view, option_terminal,
)
from sb3_hhp.hierarchy.subpolicies import PerGoalLearners, SubpolicySet
from sb3_hhp.oracles.base import Oracle
from sb3_hhp.oracles.registry import make_oracle
from sb3_hhp.preferences.predictor import PreferencePredictor
from sb3_hhp.preferences.query import QuerySelector
from sb3_hhp.preferences.rewards import PreferenceReturnNormalizer, meta_reward
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable

SelfHhP = TypeVar("SelfHhP", bound="HhP")

#: the learners of discrete-action sub-goals (``subgoal_learner``)
SUBGOAL_LEARNERS = {"heads": SharedHeadsDQN, "stacked": StackedDQN}
#: the choices of an episode ``predict`` remembers per env with ``break_cycles`` (a loop of choices is a few long)
CHOICE_MEMORY = 64


def observation_digests(batch: np.ndarray) -> list[bytes]:
    """A 16-byte digest (blake2b) of each observation of a batch: how the masks' cache and the deterministic policy's
    memory of visited states tell observations apart without keeping them."""
    return [hashlib.blake2b(obs.tobytes(), digest_size=16).digest() for obs in batch]

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


#: ``query_kwargs``: the query selection (:class:`~sb3_hhp.preferences.query.QuerySelector`): the paper's t_qry
#: (``threshold``, fixed mode), the pacing ``mode`` ("adaptive" or "fixed"), and the ``horizon`` in primitive steps
#: over which the adaptive mode paces the budget (None: the ``total_timesteps`` of each ``learn`` call), and how the
#: second sub-goal of a question is chosen (``second``: "meta", the paper's, or "unasked")
QUERY_DEFAULTS: dict[str, Any] = dict(threshold=0.26, mode="adaptive", horizon=None, quantile_window=2_000,
                                      second="meta")
#: ``predictor_kwargs``: the preference predictor's (:class:`~sb3_hhp.preferences.predictor.PreferencePredictor`);
#: MC-dropout masks and dropout probability of eq. 4, its head and spread (design decisions: the predictor head)
PREDICTOR_DEFAULTS: dict[str, Any] = dict(hidden_dim=256, dropout=0.1, n_masks=500, head="linear", spread="std")
#: every key ``predictor_kwargs`` may hold (HhP sets ``buffer_size``, ``device`` and ``seed`` unless given)
PREDICTOR_KEYS = frozenset(inspect.signature(PreferencePredictor.__init__).parameters) - {"self", "observation_space"}
#: ``discovery_kwargs``: CSD's (:class:`~sb3_hhp.discovery.csd.SubgoalDiscovery`): lowest percentile of novelty
#: progress, visits a key needs, the similarity gate b_similarity, whether the state just before a success is a
#: candidate too, and which states the percentile ranks
DISCOVERY_DEFAULTS: dict[str, Any] = dict(percentile=5.0, min_visits=2, similarity_threshold=0.5, before_success=False,
                                          percentile_of="visited")
#: ``subgoal_learner_kwargs``: how the sub-goal learners learn, beside their SB3 arguments (``subpolicy_kwargs``):
#: own steps over which a subpolicy's epsilon decays, and the run's steps since it was added over which it decays too
#: (None: own steps only); whether every transition also trains the other sub-goals' learners, relabelled with their
#: rewards; whether they take their gradient steps on every primitive step, not only while they act (None: True for
#: discrete actions, False for DDPG sub-goals, a model each); most learners updated in one round
#: (``subgoal_learner="stacked"``; None: all); the learning rounds of one step of the envs in one call; the cells
#: around the agent the learners read (None: the whole observation); the one-hot encoding of each channel the
#: learners read (None: its integer codes); the side of the blocks of the coarse copy of the whole observation they
#: also read (None: none); the range their TD targets are clipped to (None: unclipped)
SUBGOAL_LEARNER_DEFAULTS: dict[str, Any] = dict(exploration_steps=5_000, exploration_run_steps=None,
                                                share_experience=True, train_shared=None,
                                                max_updates=8, grouped_rounds=False, view=None, carry_relabel=0.0,
                                                one_hot=None, overview=None, target_range=None)
#: each ``*_kwargs`` argument grouped over defaults: its defaults and the keys it accepts (None: the defaults' keys)
GROUPED_ARGUMENTS: dict[str, tuple[dict[str, Any], Optional[frozenset]]] = {
    "query_kwargs": (QUERY_DEFAULTS, None),
    "predictor_kwargs": (PREDICTOR_DEFAULTS, PREDICTOR_KEYS),
    "discovery_kwargs": (DISCOVERY_DEFAULTS, None),
    "subgoal_learner_kwargs": (SUBGOAL_LEARNER_DEFAULTS, None),
}
#: constructor arguments of earlier versions and where they went: old name -> (``*_kwargs`` argument, key)
MOVED_ARGUMENTS: dict[str, tuple[str, str]] = {
    "t_qry": ("query_kwargs", "threshold"),
    "query_mode": ("query_kwargs", "mode"),
    "query_horizon": ("query_kwargs", "horizon"),
    "n_masks": ("predictor_kwargs", "n_masks"),
    "dropout": ("predictor_kwargs", "dropout"),
    "predictor_head": ("predictor_kwargs", "head"),
    "confidence_spread": ("predictor_kwargs", "spread"),
    "csd_percentile": ("discovery_kwargs", "percentile"),
    "csd_min_visits": ("discovery_kwargs", "min_visits"),
    "b_similarity": ("discovery_kwargs", "similarity_threshold"),
    "subpolicy_exploration_steps": ("subgoal_learner_kwargs", "exploration_steps"),
    "share_experience": ("subgoal_learner_kwargs", "share_experience"),
    "train_shared": ("subgoal_learner_kwargs", "train_shared"),
    "max_subgoal_updates": ("subgoal_learner_kwargs", "max_updates"),
}


def moved_argument_message(name: str) -> str:
    """What to write instead of ``name``, an argument of an earlier version that a ``*_kwargs`` dict now holds."""
    group, key = MOVED_ARGUMENTS[name]
    return f"{name!r} is now a key of {group}: write {group}=dict({key}=...) (in a YAML entry, {group}: {{{key}: ...}})"


def group_moved_arguments(arguments: dict[str, Any]) -> dict[str, Any]:
    """``arguments`` with every moved argument of an earlier version put under its ``*_kwargs`` key (for models
    and optimisation trials written before the arguments were grouped); the other arguments as they are."""
    grouped = {name: value for name, value in arguments.items() if name not in MOVED_ARGUMENTS}
    for name, value in arguments.items():
        if name in MOVED_ARGUMENTS:
            group, key = MOVED_ARGUMENTS[name]
            grouped[group] = {**(grouped.get(group) or {}), key: value}
    return grouped


def _refuse_moved(moved: dict[str, Any]) -> None:
    for name in moved:
        if name in MOVED_ARGUMENTS:
            raise TypeError(f"HhP got an argument of an earlier version: {moved_argument_message(name)}")
    if moved:
        raise TypeError(f"HhP got unexpected keyword arguments {sorted(moved)}")


def _grouped(name: str, given: Optional[dict[str, Any]]) -> dict[str, Any]:
    """The ``*_kwargs`` argument ``name``: its defaults updated with ``given``; a key it does not accept is refused."""
    defaults, keys = GROUPED_ARGUMENTS[name]
    if given is not None and not isinstance(given, dict):
        raise ValueError(f"{name} must be a dict, got {type(given).__name__}")
    known = keys if keys is not None else frozenset(defaults)
    unknown = sorted(set(given or {}) - known)
    if unknown:
        raise ValueError(f"{name} has no key {unknown[0]!r}; its keys are {', '.join(sorted(known))}")
    return {**defaults, **(given or {})}


def _check_grouped(query: dict[str, Any], predictor: dict[str, Any], learner: dict[str, Any]) -> None:
    """The grouped values a later component would only refuse once the model is set up."""
    if not (isinstance(query["threshold"], (int, float, np.number)) and query["threshold"] >= 0):
        raise ValueError(f"query_kwargs['threshold'] (t_qry) must be >= 0, got {query['threshold']!r}")
    if query["horizon"] is not None and query["horizon"] < 1:
        raise ValueError(f"query_kwargs['horizon'] must be >= 1 primitive steps (or None), got {query['horizon']}")
    if not 0.0 <= predictor["dropout"] < 1.0:
        raise ValueError(f"predictor_kwargs['dropout'] must be in [0, 1), got {predictor['dropout']}")
    if not 0.0 <= learner.get("carry_relabel", 0.0) <= 1.0:
        raise ValueError(f"subgoal_learner_kwargs['carry_relabel'] must be in [0, 1], got {learner['carry_relabel']!r}")
    if learner["train_shared"] and not learner["share_experience"]:
        raise ValueError("subgoal_learner_kwargs: train_shared=True trains sub-goals on shared experience: it needs "
                         "share_experience=True")


#: the paper's settings (section 5.1) over the class defaults, which are those measured to learn MiniGrid here:
#: the paper's sub-goal learner, an uncentred preference bonus, the meta-controller on observations, sub-goals
#: learning only while they act, 200 questions
PAPER_KWARGS: dict[str, Any] = dict(
    query_budget=200, center_bonus=False, meta_input="observation", predictor_input="observation",
    subgoal_learner="stacked", subpolicy_kwargs=PAPER_SUBPOLICY_KWARGS, max_subgoal_steps=50,
    subgoal_learner_kwargs=dict(train_shared=False, max_updates=None),
)


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


def _vec_env(env: Union[GymEnv, str, None], outer_ring: bool = False) -> Optional[VecEnv]:
    """The primitive envs under ``env`` as a VecEnv: an env id or a gym env becomes a DummyVecEnv of one env (with
    the observation its goal space reads, and a Monitor for SB3's episode statistics); a VecEnv is used as it is
    (each env already wrapped, e.g. ``make_vec_env(ENV, n_envs=8, wrapper_class=sb3_hhp.goals.wrap_env)``).
    ``outer_ring``: a MiniGrid env's canvas with its outer ring (models saved before it was left out)."""
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
    wrapped = wrap_env(env, outer_ring=outer_ring)
    return DummyVecEnv([lambda: wrapped if is_wrapped(wrapped, Monitor) else Monitor(wrapped)])


class HhP(BetweenEpisodes, DoubleDQN):
    """Hierarchical learning from human preferences and curiosity.

    :param policy: the meta-controller's policy ("MlpPolicy", "CnnPolicy", "MultiInputPolicy" or a class)
    :param env: the task (a gym env, an env id, or a DummyVecEnv of one env); MiniGrid envs are wrapped
        with :class:`~sb3_hhp.goals.MiniGridEgocentricObs` when needed
    :param oracle: who answers preference queries: an :class:`~sb3_hhp.oracles.Oracle` or a name of
        :data:`~sb3_hhp.oracles.ORACLE_NAMES`
    :param query_budget: total number of questions over training (>= 0)
    :param beta: weight of the extrinsic return in eq. 3, in [0, 1]
    :param alpha: weight of the intrinsic reward in eq. 6 (>= 0)
    :param use_preferences: False gives the paper's "Cur" ablation (no queries, reward = R_e)
    :param use_curiosity: False gives the "Pref" ablation (no RND, alpha = 0)
    :param discovery: "csd", "random" (ablation) or "none" (only the sub-goals handed in)
    :param subgoals: sub-goals handed in by the user: observations of the env (seed or replace discovery)
    :param goal_space: "auto", a registered name or a :class:`~sb3_hhp.goals.GoalSpace`
    :param max_subgoal_steps: primitive steps after which a sub-goal gives up (design decisions: max_subgoal_steps)
    :param subgoal_capacity: initial size of the meta-controller's head (it doubles when full)
    :param subgoal_learner: discrete actions: "stacked" (default: a network of its own per sub-goal, all updated in
        one call; measured to learn DoorKey-8x8 faster; cost and memory grow with the number of sub-goals) or "heads"
        (one network, a shared trunk and one head per sub-goal, one relabelled batch for all; the cost of a step
        barely grows with the number of sub-goals); see the README's Design
    :param center_bonus: centre the preference bonus over the sub-goals of each state: True or "mean" subtracts
        their mean, "max" the best choosable one's score, so that no choice is paid (see the README's Design)
    :param exact_bonus: the meta-controller's Q-value of a choice is its preference bonus (eq. 3's
        ``(1 - beta) * b / sigma``, computed by the predictor when the choice is made or replayed) plus what its
        network learns, the value of what follows; False (default): the network learns both, as in the paper. The
        reward and its fixed point are the same; the network no longer lags behind a bonus it is told (see the
        README's Design)
    :param success_bonus: the preference bonus of choosing the task's own goal ("task solved",
        :data:`~sb3_hhp.goals.SUCCESS_KEY`): "predicted" (default: the predictor's, as any sub-goal's) or "best" (the
        state's best choosable score: the extrinsic reward alone judges that choice, and no question compares it;
        see the design decisions)
    :param mask_subgoals: the meta-controller chooses, in each state, only among the sub-goals that the goal space
        calls choosable there (:meth:`~sb3_hhp.goals.GoalSpace.choosable`: not already achieved; on MiniGrid,
        also a milestone); in acting, exploring and the TD target alike (see the README's Design)
    :param break_cycles: how :meth:`predict` acts where a greedy policy on a deterministic env that comes back to a
        state goes round the same cycle: the meta-controller back in an observation it chose in before in the episode
        takes its best choosable sub-goal not chosen there yet (nor one that just gave up), and (discrete actions) a
        sub-goal learner whose walk comes back to an observation takes its best action not yet taken there; the
        stochastic policy (``deterministic=False``) is that policy with epsilon-random choices and actions, as SB3's
        DQN is epsilon-greedy (see the README's Design). False: plain greedy, and plain epsilon-greedy. Training is
        unaffected (it explores)
    :param predictor_input: what the preference predictor reads: "observation", "features" (the goal space's
        compact description of a state, :meth:`~sb3_hhp.goals.GoalSpace.features`) or "auto" (features when the
        goal space has them; see the README's Design)
    :param meta_input: what the meta-controller reads: "observation" (default), "features" (the goal space's
        description, through :class:`~sb3_hhp.hhp.policies.GoalSpaceFeatures`) or "auto" (features when the goal
        space has them and ``policy_kwargs`` names no features extractor; see the README's Design)
    :param preference_db: path of the SQLite preference store (None: in memory)
    :param record_images: render the state at every sub-goal choice, for the questions' state images (default: when
        a person answers, ``oracle="web"`` or ``"terminal"``, unless the goal space draws a question's state from its
        privileged facts, as MiniGrid's does: ``GoalSpace.draws_from_facts``; a render costs ~20 ms on Fetch)
    :param n_opt: meta-controller gradient steps after each episode (N_opt = 4)
    :param query_kwargs: when to ask (keys and defaults: :data:`QUERY_DEFAULTS`): ``threshold`` (the paper's
        t_qry, fixed mode), ``mode`` ("adaptive" paces the budget over training, design decisions: adaptive
        threshold; "fixed" asks above ``threshold``), ``horizon`` (primitive steps over which the adaptive mode
        paces the budget; default: the ``total_timesteps`` of each ``learn`` call; set it when training in several
        ``learn`` calls), ``second`` ("meta": the meta-controller's second choice, the paper's; "unasked": its best
        choosable sub-goal that no question has named yet, where there is one)
    :param predictor_kwargs: arguments of :class:`~sb3_hhp.preferences.predictor.PreferencePredictor` over
        :data:`PREDICTOR_DEFAULTS`: ``n_masks`` (MC-dropout masks of eq. 4), ``dropout`` (its p), ``head`` and
        ``spread`` (design decisions: the predictor head), ``hidden_dim``, ``learning_rate``, ...
    :param discovery_kwargs: CSD's, over :data:`DISCOVERY_DEFAULTS`: ``similarity_threshold`` (the paper's
        b_similarity, in [0, 1]), ``percentile`` (lowest percentile of novelty progress), ``min_visits`` (visits a
        state's sub-goal key needs before it may become a sub-goal), ``before_success`` (the state visited just
        before a success is a candidate too, like the success itself), ``percentile_of`` ("visited": the percentile
        ranks every state of the episode; "new": only those whose key is not a sub-goal's yet and has the visits)
    :param subgoal_learner_kwargs: how the sub-goal learners learn, over :data:`SUBGOAL_LEARNER_DEFAULTS`:
        ``exploration_steps`` (own steps over which a subpolicy's epsilon decays), ``exploration_run_steps``
        (``subgoal_learner="stacked"`` or ``"heads"`` with ``train_shared``: the primitive steps since a sub-goal was
        added over which its epsilon decays too, the lower rate acting, so a sub-goal seldom chosen stops acting at
        random; None: own steps only), ``share_experience`` (every
        transition also trains, off-policy, the other sub-goals' learners, relabelled with their rewards),
        ``train_shared`` (every sub-goal takes its gradient steps on every primitive step, at its own ``train_freq``,
        not only while it acts; the heads learner always does; None: True for discrete actions, False for DDPG
        sub-goals, a model each, K times the updates), ``max_updates`` (``subgoal_learner="stacked"``: most learners
        updated in one round, the sub-goals the envs pursue now first, then those that waited longest, so that the
        cost of a step stops growing once more sub-goals have been found; None: every sub-goal at each of its
        updates; see the README's Design), ``grouped_rounds`` (the learning rounds due at one step of the envs in
        one call), ``view`` (discrete actions: the learners read only the central ``view`` x ``view`` cells of an
        ``(H, W, C)`` observation, on MiniGrid's egocentric canvas the cells around the agent; ``"inner"``: all but the
        outermost ring, which on MiniGrid's canvas only ever shows the border wall; None: all of it), ``carry_relabel``
        (``subgoal_learner="stacked"``: the share of a sub-goal's batch that, where the sub-goal carries an object,
        becomes steps taken with empty hands as they would have gone carrying it; the goal space's
        :meth:`~sb3_hhp.goals.GoalSpace.carried_counterfactual`, MiniGrid's: turns and steps; 0: none), ``one_hot``
        (discrete actions: the learners read each channel ``c`` of ``(H, W, C)`` uint8 codes as one-hot indicators of
        the codes ``one_hot[c]``, a count n for codes 0 to n - 1 or a list of codes, 0 or ``[]`` leaving it out;
        MiniGrid's canvas: ``[11, 6, 3]``, every object, colour and state; None: the codes as numbers), ``overview``
        (discrete actions, MlpPolicy: the learners also read a coarse copy of the whole observation, blocks of
        ``overview`` x ``overview`` cells each as its most salient cell, the highest code of the first channel: on
        MiniGrid's canvas, in which direction a goal square, key or door beyond the ``view`` lies; odd, >= 3; None: none),
        ``target_range`` (discrete actions: ``(low, high)``, the learners' TD targets clipped to it, as HER clips its
        targets; with ``alpha`` 0 eq. 5 puts every return in ``[-1, 1]``; None: unclipped)
    :param subpolicy_kwargs: arguments of the sub-goal learners, in SB3 DQN's names (discrete actions: over
        :data:`~sb3_hhp.hierarchy.learners.DEFAULT_SUBPOLICY_KWARGS`; ``PAPER_SUBPOLICY_KWARGS`` is the paper's learner;
        ``buffer_size`` is the shared replay's, in primitive transitions) or of each sub-goal's SB3 DDPG (continuous)
    :param rnd_kwargs: arguments of :class:`~sb3_hhp.curiosity.rnd.RND` (memory_size M, refresh_interval T, ...)
    :param oracle_kwargs: arguments of the oracle built from a name

    Other parameters are those of :class:`~sb3_hhp.dqn.DoubleDQN` (the meta-controller); the meta
    replay buffer R_H holds ``buffer_size`` sub-goal choices, and ``target_update_interval`` counts them. An argument
    of an earlier version that a ``*_kwargs`` dict now holds (``t_qry``, ``n_masks``, ``b_similarity``, ...) is
    refused with the key to use (:data:`MOVED_ARGUMENTS`); models saved with them load as they were.
    """

    #: states whose key and reach (:meth:`action_mask`) are kept; the cache is emptied when a batch would overfill it
    present_cache_size = 100_000
    #: models saved before ``success_bonus`` existed load with its default
    success_bonus = "predicted"
    #: a MiniGrid model saved before the canvas's empty outer ring was left out reads the canvas with it (set by load)
    minigrid_outer_ring = False

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
        use_preferences: bool = True,
        use_curiosity: bool = True,
        discovery: str = "csd",
        subgoals: Optional[list[np.ndarray]] = None,
        goal_space: Union[str, GoalSpace] = "auto",
        max_subgoal_steps: int = 50,
        subgoal_capacity: int = 16,
        subgoal_learner: str = "stacked",
        center_bonus: Union[bool, str] = "max",
        exact_bonus: bool = False,
        success_bonus: str = "predicted",
        mask_subgoals: bool = True,
        break_cycles: bool = True,
        predictor_input: str = "auto",
        meta_input: str = "auto",
        preference_db: Optional[str] = None,
        record_images: Optional[bool] = None,
        n_opt: int = 4,
        query_kwargs: Optional[dict[str, Any]] = None,
        predictor_kwargs: Optional[dict[str, Any]] = None,
        discovery_kwargs: Optional[dict[str, Any]] = None,
        subgoal_learner_kwargs: Optional[dict[str, Any]] = None,
        subpolicy_kwargs: Optional[dict[str, Any]] = None,
        rnd_kwargs: Optional[dict[str, Any]] = None,
        oracle_kwargs: Optional[dict[str, Any]] = None,
        learning_rate: Union[float, Schedule] = 1e-3,
        buffer_size: int = 500_000,
        learning_starts: int = 1_000,
        batch_size: int = 128,
        tau: float = 1.0,
        gamma: float = 0.99,
        target_update_interval: int = 500,
        exploration_fraction: float = 0.2,
        exploration_initial_eps: float = 1.0,
        exploration_final_eps: float = 0.05,
        max_grad_norm: float = 10,
        stats_window_size: int = 100,
        tensorboard_log: Optional[str] = None,
        policy_kwargs: Optional[dict[str, Any]] = None,
        verbose: int = 0,
        seed: Optional[int] = None,
        device: Union[th.device, str] = "auto",
        _init_setup_model: bool = True,
        **moved: Any,
    ) -> None:
        _refuse_moved(moved)
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {beta}")
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        if isinstance(query_budget, bool) or not isinstance(query_budget, (int, np.integer)) or query_budget < 0:
            raise ValueError(f"query_budget must be an integer >= 0, got {query_budget!r}")
        if discovery not in ("csd", "random", "none"):
            raise ValueError(f"discovery must be 'csd', 'random' or 'none', got {discovery!r}")
        if discovery == "none" and not subgoals:
            raise ValueError("discovery='none' needs sub-goals handed in with subgoals=[obs, ...]")
        if n_opt < 1:
            raise ValueError(f"n_opt must be >= 1, got {n_opt}")
        if subgoal_learner not in SUBGOAL_LEARNERS:
            raise ValueError(f"subgoal_learner must be one of {sorted(SUBGOAL_LEARNERS)}, got {subgoal_learner!r}")
        if predictor_input not in ("auto", "features", "observation"):
            raise ValueError(f"predictor_input must be 'auto', 'features' or 'observation', got {predictor_input!r}")
        if meta_input not in ("auto", "features", "observation"):
            raise ValueError(f"meta_input must be 'auto', 'features' or 'observation', got {meta_input!r}")
        if center_bonus not in (True, False, "mean", "max"):
            raise ValueError(f"center_bonus must be True / 'mean', 'max' or False, got {center_bonus!r}")
        if not isinstance(exact_bonus, bool):
            raise ValueError(f"exact_bonus must be True or False, got {exact_bonus!r}")
        if success_bonus not in ("predicted", "best"):
            raise ValueError(f"success_bonus must be 'predicted' or 'best', got {success_bonus!r}")
        self.query_kwargs = _grouped("query_kwargs", query_kwargs)
        self.predictor_kwargs = _grouped("predictor_kwargs", predictor_kwargs)
        self.discovery_kwargs = _grouped("discovery_kwargs", discovery_kwargs)
        self.subgoal_learner_kwargs = _grouped("subgoal_learner_kwargs", subgoal_learner_kwargs)
        _check_grouped(self.query_kwargs, self.predictor_kwargs, self.subgoal_learner_kwargs)
        learner = self.subgoal_learner_kwargs
        if learner["train_shared"] is None:  # discrete sub-goal learners train on every step; one DDPG model each does not
            learner["train_shared"] = learner["share_experience"] and (env is None or not _continuous_actions(env))
        self.oracle_spec = oracle
        self.query_budget = int(query_budget)
        self.beta = beta
        self.alpha = alpha
        self.use_preferences = use_preferences
        self.use_curiosity = use_curiosity
        self.discovery_strategy = discovery
        self.initial_subgoals = [np.asarray(goal) for goal in subgoals] if subgoals else []
        self.goal_space_spec = goal_space
        self.max_subgoal_steps = max_subgoal_steps
        self.subgoal_capacity = subgoal_capacity
        self.predictor_input = predictor_input
        self.meta_input = meta_input
        self.rnd_kwargs = dict(rnd_kwargs or {})
        self.subpolicy_kwargs = dict(subpolicy_kwargs or {})
        self.preference_db = preference_db
        self.oracle_kwargs = dict(oracle_kwargs or {})
        self.n_opt = n_opt
        self.center_bonus = center_bonus
        self.exact_bonus = exact_bonus
        self.success_bonus = success_bonus
        self.mask_subgoals = mask_subgoals
        self.break_cycles = bool(break_cycles)
        self.subgoal_learner = subgoal_learner
        self.record_images = record_images
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
            SubgoalVecEnv(self.options, subgoal_capacity) if self.options is not None else None,  # type: ignore[arg-type]
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=(1, "episode"),
            gradient_steps=n_opt,
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
        reads_features = self._reads_features("meta_input", self.meta_input)
        if self.meta_input == "auto" and self.subpolicy_policy == "CnnPolicy":
            reads_features = False  # CnnPolicy asks for a CNN on the observation
        if self.meta_input == "features" and "features_extractor_class" in policy_kwargs:
            raise ValueError("meta_input='features' sets the features extractor: remove features_extractor_class from policy_kwargs")
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

    def _group_saved_arguments(self) -> None:
        """A model saved before the arguments were grouped holds them as attributes (SB3's load sets every saved
        attribute): put them under their ``*_kwargs`` dicts, over the defaults, as they were trained with."""
        old = {name: self.__dict__.pop(name) for name in list(MOVED_ARGUMENTS) if name in self.__dict__}
        if not old:
            return
        old.setdefault("max_subgoal_updates", None)  # saved before that argument existed: every learner updated
        grouped = group_moved_arguments(old)
        for group, (defaults, _) in GROUPED_ARGUMENTS.items():
            setattr(self, group, {**defaults, **(getattr(self, group, None) or {}), **grouped.get(group, {})})

    def _setup_model(self) -> None:
        self._group_saved_arguments()
        # the replay R_H holds sub-goal choices, which end at different times in different envs: one stream
        n_envs, self.n_envs = self.n_envs, 1
        try:
            super()._setup_model()
        finally:
            self.n_envs = n_envs
        device = get_device(self.device)
        obs_space = self.primitive_observation_space
        self.rnd = RND(obs_space, device=device, seed=self.seed, **self.rnd_kwargs) if self.use_curiosity else None
        predictor_kwargs = dict(buffer_size=max(1, self.query_budget), device=device, seed=self.seed)
        predictor_kwargs.update(self.predictor_kwargs)
        self._predictor_reads_features = self._reads_features("predictor_input", self.predictor_input)
        predictor_space = (
            spaces.Box(-np.inf, np.inf, (self.goal_space.features_dim(obs_space),), np.float32)
            if self._predictor_reads_features else obs_space
        )
        self.predictor = PreferencePredictor(predictor_space, **predictor_kwargs)
        query = {key: value for key, value in self.query_kwargs.items() if key != "horizon"}
        self.query_selector = QuerySelector(self.query_budget, **query)
        self.return_normalizer = PreferenceReturnNormalizer(gamma=0.99, rollout_length=64)
        alpha = self.alpha if self.use_curiosity else 0.0
        learner = self.subgoal_learner_kwargs
        if isinstance(self.primitive_action_space, spaces.Discrete):
            self.subpolicies = SUBGOAL_LEARNERS[self.subgoal_learner](
                obs_space, self.primitive_action_space, self.goal_space.achieved, policy=self.subpolicy_policy,
                subpolicy_kwargs=self.subpolicy_kwargs, alpha=alpha, n_envs=self.n_envs, device=device, seed=self.seed,
                action_mask=self.goal_space.action_mask, counterfactual=self.goal_space.carried_counterfactual, **learner,
            )
        else:
            # the options of the learners of discrete actions, each with the value that leaves it unset (models saved
            # before an option have no key)
            for name, unset in (("exploration_run_steps", None), ("carry_relabel", 0.0), ("target_range", None),
                                ("one_hot", None), ("overview", None), ("view", None)):
                if learner.get(name, unset) != unset:
                    raise ValueError(f"subgoal_learner_kwargs['{name}'] applies to the learners of discrete actions; this "
                                     f"env's sub-goal learners are DDPG models that explore over their own steps and read "
                                     f"the whole observation as it is: leave {name} out (leave it out for DDPG sub-goals)")
            self.subpolicies = PerGoalLearners(
                SubpolicySet(obs_space, self.primitive_action_space, policy=self.subpolicy_policy,
                             subpolicy_kwargs=self.subpolicy_kwargs, exploration_steps=learner["exploration_steps"],
                             device=device, seed=self.seed),
                self.goal_space.achieved, alpha=alpha, share_experience=learner["share_experience"],
                train_shared=learner["train_shared"],
            )
        self.discovery = SubgoalDiscovery(
            self.goal_space, strategy="random" if self.discovery_strategy == "random" else "csd", seed=self.seed,
            **self.discovery_kwargs,
        )
        self.store = PreferenceStore(self.preference_db or ":memory:", create=True)
        self.store.set_query_budget(self.query_budget)  # shown on the labeling page as "asked / budget"
        self.subgoal_table = SubgoalTable(self.store)  # the labeling page's gallery, in the store's file
        self.oracle = self._make_oracle()
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
        self._rollout_episodes = 0
        if self.options is not None:
            self._attach(self.options)

    def _attach(self, options: OptionRunner) -> None:
        options.learners, options.rnd, options.subgoals = self.subpolicies, self.rnd, self.subgoal_set
        options.record_images = bool(self.record_images)
        if not self.subgoal_set.goals:
            for goal_obs in self.initial_subgoals:
                self.add_subgoal(self.goal_space.key(goal_obs), goal_obs, None, source="user")
        self._sync_action_space()

    def _make_oracle(self) -> Optional[Oracle]:
        if not self.use_preferences:
            return None
        if isinstance(self.oracle_spec, Oracle):
            return self.oracle_spec
        if self.oracle_spec is None:
            return None
        return make_oracle(
            self.oracle_spec, self.goal_space, self.primitive_observation_space, store=self.store, seed=self.seed,
            **self.oracle_kwargs,
        )

    # ------------------------------------------------------------------ the sub-goal set
    @property
    def subgoals(self) -> list[Subgoal]:
        """The sub-goal set G, in the order of the meta-controller's actions."""
        return self.subgoal_set.goals

    def add_subgoal(self, key: Any, obs: np.ndarray, image: Optional[np.ndarray], source: str = "csd") -> int:
        """Add a sub-goal (and its learner); the meta-controller's head doubles when full (design decisions: growing head)."""
        goal_id = self.subgoal_set.add(key, obs, image, self.num_timesteps, source)
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

    def action_mask(self, observations: Union[np.ndarray, dict[str, np.ndarray]]) -> Optional[np.ndarray]:
        """The sub-goals the meta-controller may choose in each state: the existing ones, and with
        ``mask_subgoals`` only those the goal space calls choosable from the state's key (a state where
        none is keeps every existing sub-goal)."""
        valid = self._valid_actions
        if valid is None or not self.mask_subgoals or isinstance(observations, dict):
            return valid
        batch = self._env_layout(np.asarray(observations)).astype(self.primitive_observation_space.dtype, copy=False)
        goal_keys = [goal.key for goal in self.subgoals]
        rows = np.empty((len(batch), len(valid)), dtype=bool)
        digests = observation_digests(batch)  # 16 bytes, not 6.6 KB (47x47x3)
        unseen = {digest: i for i, digest in enumerate(digests) if digest not in self._present_cache}
        if unseen:  # key and present of a state, reused whenever the same observation recurs; new ones in one batch
            if len(self._present_cache) + len(unseen) > self.present_cache_size:
                self._present_cache.clear()  # and every state of the batch is new again
                unseen = {digest: i for i, digest in enumerate(digests)}
            index = list(unseen.values())
            for digest, i, present in zip(unseen, index, self.goal_space.present_batch(batch[index])):
                self._present_cache[digest] = (self.goal_space.key(batch[i]), present)
        for i, digest in enumerate(digests):
            key, present = self._present_cache[digest]
            row = self._mask_cache.get((key, present))
            if row is None:
                row = valid.copy()
                row[: len(goal_keys)] = [self.goal_space.choosable(key, goal_key, present) for goal_key in goal_keys]
                row = row if row.any() else valid
                self._mask_cache[(key, present)] = row
            rows[i] = row
        return rows

    def predictor_inputs(self, observations: np.ndarray) -> np.ndarray:
        """What the predictor reads for a batch of observations: the goal space's features, or the
        observations themselves (``predictor_input``)."""
        observations = self._env_layout(np.asarray(observations))
        return self.goal_space.features(observations) if self._predictor_reads_features else observations

    def query_inputs(self, query: Any) -> np.ndarray:
        """What the predictor reads of a question: its state and its two sub-goals, stacked."""
        return self.predictor_inputs(np.stack([query.state, query.goal1_obs, query.goal2_obs]))

    def add_preference(self, query: Any, label: Any) -> bool:
        """Feed one answered query to the predictor's buffer R (False: the label teaches nothing, e.g.
        "incomparable")."""
        state, goal1, goal2 = self.query_inputs(query)
        return self.predictor.add(state, goal1, goal2, label)

    @property
    def goal_obs(self) -> np.ndarray:
        return np.stack([goal.obs for goal in self.subgoals])

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """N_opt meta-controller updates for each episode that just ended (Algorithm 1 lines 30-34), once the meta
        buffer holds a batch."""
        if self.replay_buffer is None or self.replay_buffer.size() < batch_size:
            return
        super().train(gradient_steps * max(1, self._rollout_episodes), batch_size)

    # ------------------------------------------------------------------ rewards (eq. 3)
    def _rewards(self, replay_data: Any) -> th.Tensor:
        """r^e = beta * R_e + (1 - beta) * b / sigma(R_p) (eq. 3, Algorithm 1 lines 32-33), with the bonus
        b = p_hat(s, g) recomputed by the current predictor for the sampled choices."""
        extrinsic = replay_data.rewards
        if not self.use_preferences or len(self.predictor) == 0:
            return extrinsic
        goals = replay_data.actions.long().flatten().cpu().numpy()
        states = replay_data.observations.cpu().numpy().astype(self.primitive_observation_space.dtype)
        bonus = self._replay_bonus(np.asarray(replay_data.indices) // self.replay_buffer.n_envs, states, goals)
        bonus_t = th.as_tensor(bonus, dtype=extrinsic.dtype, device=extrinsic.device).reshape(-1, 1)
        return meta_reward(extrinsic, bonus_t, sigma=self.return_normalizer.sigma, beta=self.beta)

    def _replay_bonus(self, rows: np.ndarray, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """:meth:`preference_bonus` of sampled rows of R_H, scored once per row while the predictor and the sub-goal
        set (and the centring) stay the same (a row's bonus depends on nothing else): late in a run, when the budget is spent, the
        meta-controller's updates stop re-scoring the same choices."""
        key = (self.predictor.version, len(self.subgoals), self.center_bonus, self.success_bonus, self.mask_subgoals, id(self.replay_buffer),
               self.replay_buffer.buffer_size)
        if getattr(self, "_bonus_key", None) != key:
            self._bonus_key = key
            self._bonus_cache = np.zeros(self.replay_buffer.buffer_size, dtype=np.float32)
            self._bonus_valid = np.zeros(self.replay_buffer.buffer_size, dtype=bool)
        stale = ~self._bonus_valid[rows]
        if stale.any():
            self._bonus_cache[rows[stale]] = self.preference_bonus(states[stale], goals[stale])
            self._bonus_valid[rows[stale]] = True
        return self._bonus_cache[rows]

    def preference_bonus(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """The preference bonus b = p_hat(s, g) (Algorithm 1 line 12), centred over the sub-goals when
        ``center_bonus``: b(s, g) - mean_g' p_hat(s, g') (True or "mean"), or b(s, g) - max_g' p_hat(s, g') over
        the sub-goals choosable in s and g ("max": never positive). Bradley-Terry (eq. 2) fixes scores only up to a
        per-state constant, so the uncentred level is arbitrary shaping that can pay for dawdling. With
        ``success_bonus="best"`` the task's own goal scores as the best of the other sub-goals choosable in s."""
        if not self.center_bonus and self.success_bonus != "best":
            return self.predictor.score(self.predictor_inputs(states), self.predictor_inputs(self.goal_obs)[goals])
        return self.bonus_matrix(states)[np.arange(len(states)), goals]

    def bonus_matrix(self, states: np.ndarray) -> np.ndarray:
        """:meth:`preference_bonus` of every sub-goal in each state, ``(N, n_sub-goals)``; under "max" centring a
        sub-goal not choosable in s and scored above every choosable one gets 0, as it would if chosen."""
        success = self.success_goal if self.success_bonus == "best" else None
        mask = self.action_mask(states) if self.center_bonus == "max" or success is not None else None
        goal_obs, inputs = self.predictor_inputs(self.goal_obs), self.predictor_inputs(states)
        n_goals, n_states = len(goal_obs), len(inputs)
        scores = self.predictor.score_matrix(inputs, goal_obs)  # (n_states, n_goals)
        choosable = (np.ones_like(scores, dtype=bool) if mask is None
                     else np.broadcast_to(mask, (n_states, mask.shape[-1]))[:, :n_goals])
        if success is not None:  # the best other choosable score (the success's own where it is the only choice)
            others = choosable & (np.arange(n_goals) != success)
            best_other = np.where(others, scores, -np.inf).max(axis=1)
            scores[:, success] = np.where(np.isfinite(best_other), best_other, scores[:, success])
        if not self.center_bonus:
            return scores
        if self.center_bonus == "max":
            best = np.where(choosable, scores, -np.inf).max(axis=1, keepdims=True)
            return np.minimum(scores - np.where(np.isfinite(best), best, scores), 0.0)
        return scores - scores.mean(axis=1, keepdims=True)

    def _q_offset(self, observations: th.Tensor) -> Optional[th.Tensor]:
        """With ``exact_bonus``: eq. 3's bonus term ``(1 - beta) * b(s, g) / sigma`` of every sub-goal, the part of the
        meta-controller's Q-values that the predictor computes (0 for the head's unused rows); else None."""
        if not self.exact_bonus or not self.use_preferences or len(self.predictor) == 0 or not self.subgoals:
            return None
        states = observations.cpu().numpy().astype(self.primitive_observation_space.dtype)
        bonus = np.zeros((len(states), int(self.action_space.n)), dtype=np.float32)
        bonus[:, : len(self.subgoals)] = self.bonus_matrix(states)
        bonus_t = th.as_tensor(bonus, device=observations.device)
        return meta_reward(th.zeros_like(bonus_t), bonus_t, sigma=self.return_normalizer.sigma, beta=self.beta)

    @property
    def success_goal(self) -> Optional[int]:
        """The index of the task's own goal among the sub-goals (:data:`~sb3_hhp.goals.SUCCESS_KEY`), None before
        it is found."""
        keys = self.subgoal_set.keys
        return keys.index(SUCCESS_KEY) if SUCCESS_KEY in keys else None

    # ------------------------------------------------------------------ acting
    def choose_subgoals(self, obs: np.ndarray, learning_starts: int = 0, deterministic: bool = False) -> np.ndarray:
        """The meta-controller's sub-goal for each state of ``obs`` (env layout), in one batched forward: at random
        among the choosable sub-goals before ``learning_starts``, else epsilon-greedy (Algorithm 1 line 11)."""
        if self.num_timesteps < learning_starts and not deterministic:
            return self._random_actions(len(obs), self.action_mask(obs))
        actions, _ = DoubleDQN.predict(self, obs, deterministic=deterministic)
        return np.asarray(actions, dtype=np.int64).reshape(len(obs))

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
        num_collected_steps, num_collected_episodes = 0, 0
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
        self._rollout_episodes = num_collected_episodes
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
            if getattr(self, "_bonus_valid", None) is not None and replay_buffer is self.replay_buffer:
                self._bonus_valid[replay_buffer.pos] = False  # the row's cached bonus belongs to the choice it held
            replay_buffer.add(obs, next_obs, np.array([[option.goal]]),
                              np.array([option.extrinsic_return], dtype=np.float32), np.array([done]), [info])
            self._on_step()
        if self.use_preferences and len(self.predictor) > 0:
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

    def _env_layout(self, obs: np.ndarray) -> np.ndarray:
        """Observations in the env's layout: images that come channel first (an env wrapped in SB3's
        VecTransposeImage, as RL Zoo's evaluation envs are) are turned back to the env's channel-last frames."""
        shape = self.primitive_observation_space.shape
        if len(shape) == 3 and obs.shape[-3:] != shape and obs.shape[-3:] == (shape[2], shape[0], shape[1]):
            return np.moveaxis(obs, -3, -1)
        return obs

    def predict(
        self,
        observation: Union[np.ndarray, dict[str, np.ndarray]],
        state: Optional[tuple[np.ndarray, ...]] = None,
        episode_start: Optional[np.ndarray] = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Optional[tuple[np.ndarray, ...]]]:
        """Primitive actions. ``state`` = (current sub-goal per env, primitive steps spent on it, then what
        ``break_cycles`` remembers: digests of the observations the sub-goal's walk was in and the actions taken there,
        digests of the observations of the episode's last choices and the sub-goals chosen there, the number of
        choices), so SB3's ``evaluate_policy`` works unchanged: a new sub-goal is chosen at an episode start, when the
        current one is reached, or when it gives up after ``max_subgoal_steps`` (a deterministic meta-controller then
        takes its best *other* sub-goal). With ``break_cycles``, the policy back in an observation takes the best
        choice, and the best action, it has not taken there yet, or (``deterministic=False``) with probability epsilon
        a random one."""
        obs = self._env_layout(np.asarray(observation))
        vectorized = obs.shape != self.primitive_observation_space.shape
        batch = obs if vectorized else obs[None]
        n_envs = batch.shape[0]
        if state is None:
            goals, steps = np.full(n_envs, -1, dtype=np.int64), np.zeros(n_envs, dtype=np.int64)
        else:
            goals, steps = np.array(state[0], dtype=np.int64), np.array(state[1], dtype=np.int64)
        walk = int(self.max_subgoal_steps)
        shapes = [(n_envs, walk)] * 2 + [(n_envs, CHOICE_MEMORY)] * 2 + [(n_envs,)]
        if state is not None and len(state) == 7 and all(np.shape(part) == shape for part, shape in zip(state[2:], shapes)):
            memory = [np.array(part, dtype=np.int64) for part in state[2:]]
        else:
            memory = [np.zeros(shape, dtype=np.int64) for shape in shapes]
        visited, taken, chosen_at, chosen_goals, n_chosen = memory
        if episode_start is not None:
            goals[np.asarray(episode_start, dtype=bool)] = -1
            n_chosen[np.asarray(episode_start, dtype=bool)] = 0
        subgoals = self.subgoals
        if not subgoals:
            actions = np.stack([self.primitive_action_space.sample() for _ in range(n_envs)])
            return (actions if vectorized else actions[0]), (goals, steps, *memory)
        remember = self.break_cycles
        here = np.array([int.from_bytes(digest[:8], "little", signed=True) for digest in observation_digests(batch)],
                        dtype=np.int64) if remember else None
        renew = []
        for i in range(n_envs):
            goal = goals[i]
            if goal < 0:
                renew.append(i)
                continue
            achieved, gave_up = option_terminal(self.goal_space, self.goal_space.key(batch[i]), subgoals[goal].key,
                                                int(steps[i]), self.max_subgoal_steps)
            if gave_up or (achieved and steps[i] > 0):
                renew.append(i)
        if renew:
            renew = np.asarray(renew)
            greedy = deterministic or remember  # the rules below, then (stochastic) epsilon-random choices
            chosen, _ = DoubleDQN.predict(self, batch[renew], deterministic=greedy)
            if greedy and len(subgoals) > 1:
                # not chosen again at once: a sub-goal that just gave up (a greedy meta-controller would repeat the same
                # failing choice until the episode ends), and with break_cycles any sub-goal chosen before in this
                # observation in this episode (a greedy policy back in a state goes round the same loop of choices)
                excluded = np.zeros((len(renew), len(subgoals)), dtype=bool)
                failed = (goals[renew] >= 0) & (steps[renew] >= self.max_subgoal_steps)
                excluded[np.flatnonzero(failed), goals[renew][failed]] = True
                if remember:
                    known = np.minimum(n_chosen[renew], CHOICE_MEMORY)
                    same = (chosen_at[renew] == here[renew, None]) & (np.arange(CHOICE_MEMORY) < known[:, None])
                    rows, columns = np.nonzero(same)
                    excluded[rows, chosen_goals[renew][rows, columns]] = True
                chosen = self._other_choices(batch[renew], chosen, excluded)
            if not deterministic and remember:  # each env's choice random with probability epsilon, as DQN explores
                explore = np.random.rand(len(renew)) < self.exploration_rate
                if explore.any():  # among the choosable sub-goals, as choose_subgoals explores (None: the valid ones)
                    chosen[explore] = self._random_actions(int(explore.sum()), self.action_mask(batch[renew][explore]))
            goals[renew] = chosen
            steps[renew] = 0
            visited[renew], taken[renew] = 0, -1  # a new walk
            if remember:
                slot = n_chosen[renew] % CHOICE_MEMORY
                chosen_at[renew, slot], chosen_goals[renew, slot] = here[renew], chosen
                n_chosen[renew] += 1
        if remember and isinstance(self.primitive_action_space, spaces.Discrete):
            # a walk back in an observation passes over the actions it took there before
            at = np.minimum(steps, walk - 1)  # steps < max_subgoal_steps here: a walk that long gave up above
            rows, columns = np.nonzero((visited == here[:, None]) & (np.arange(walk) < at[:, None]))
            avoid = np.zeros((n_envs, int(self.primitive_action_space.n)), dtype=bool)
            avoid[rows, taken[rows, columns]] = True
            actions = self.subpolicies.act(goals, batch, deterministic=deterministic, avoid=avoid)
            visited[np.arange(n_envs), at], taken[np.arange(n_envs), at] = here, actions
        else:
            actions = self.subpolicies.act(goals, batch, deterministic=deterministic)
        steps += 1
        return (actions if vectorized else actions[0]), (goals, steps, *memory)

    def _other_choices(self, batch: np.ndarray, chosen: np.ndarray, excluded: np.ndarray) -> np.ndarray:
        """The greedy meta-controller's choices ``chosen`` in the states ``batch``, where a row of ``excluded`` rules
        sub-goals out, replaced by its best choosable sub-goal not ruled out (kept where every choosable one is)."""
        rows = np.flatnonzero(excluded.any(axis=1))
        if not len(rows):
            return chosen
        with th.no_grad():
            q_values = self._q_values(self.policy.obs_to_tensor(batch[rows])[0]).cpu().numpy()[:, : excluded.shape[1]]
        mask = self.action_mask(batch[rows])
        if mask is not None:  # one row per state, or one row for all (mask_subgoals=False)
            q_values[~np.broadcast_to(mask, (len(rows), mask.shape[-1]))[:, : excluded.shape[1]]] = -np.inf
        q_values[excluded[rows]] = -np.inf
        chosen = np.array(chosen, copy=True)
        left = np.isfinite(q_values).any(axis=1)
        chosen[rows[left]] = q_values[left].argmax(axis=1)
        return chosen

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
        horizon = total_timesteps + (0 if reset_num_timesteps else self.num_timesteps)
        self.query_selector.set_total_timesteps(int(self.query_kwargs["horizon"] or horizon))
        self.resume_preferences()
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def resume_preferences(self) -> int:
        """Feed the predictor every answered label of the store it has not seen yet, and count every
        question already asked against the budget, so a resumed run loses no label and asks nothing twice."""
        self._asked_signatures = self._asked_goal_keys = None  # read again from the store
        added = 0
        for _, query, answer in self.store.answers_since(0):
            if query.query_id in self.consumed_query_ids:
                continue
            self.consumed_query_ids.add(query.query_id)
            added += int(self.add_preference(query, answer.label))
        state = self.query_selector.state_dict()
        asked = self.store.count_asked()
        if asked > state["used"]:
            state["used"] = min(asked, self.query_budget)
            self.query_selector.load_state_dict(state)
        if added:
            self.last_predictor_stats = self.predictor.train()
        return added

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

    def subgoal_records(self) -> list[dict[str, Any]]:
        """One record per sub-goal for the gallery: id, image, when found, success rate, recent choices, mean score."""
        counts = Counter(self.recent_choices)
        records = []
        goal_obs = self.predictor_inputs(self.goal_obs) if self.subgoals else None
        states = np.stack(self._last_trace.high_obs) if self._last_trace.high_obs else None
        states = None if states is None else self.predictor_inputs(states)
        for goal_id, goal in enumerate(self.subgoals):
            mean_score = None
            if states is not None and len(self.predictor) > 0:
                mean_score = float(np.mean(self.predictor.score(states, np.repeat(goal_obs[goal_id : goal_id + 1], len(states), 0))))
            records.append(
                dict(
                    id=goal_id,
                    image=goal.image if goal.image is not None else np.zeros((8, 8, 3), np.uint8),
                    found_at=int(goal.found_at),
                    success_rate=self.subpolicies.success_rate(goal_id) if goal_id < len(self.subpolicies) else None,
                    chosen_recently=int(counts.get(goal_id, 0)),
                    mean_score=mean_score,
                    name=self.goal_space.describe(goal.key),
                )
            )
        return records

    # ------------------------------------------------------------------ save / load
    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "options", "subgoal_set", "_last_trace", "rnd", "predictor", "query_selector", "return_normalizer", "subpolicies", "discovery",
            "store", "subgoal_table", "oracle", "oracle_spec", "pending_queries", "recent_choices", "last_predictor_stats",
            "last_confidences", "consumed_query_ids", "initial_subgoals", "_asked_signatures", "_asked_goal_keys", "_mask_cache", "_present_cache",
            "_bonus_key", "_bonus_cache", "_bonus_valid", "_unscored",
            *(["learn"] if "learn" in vars(self) else []),  # a bound learn (sb3_hhp.train --resume) is no data of the model
        ]

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
            # the MiniGrid canvas the networks read (absent from models saved before its outer ring was left out)
            "minigrid_outer_ring": self.minigrid_outer_ring,
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
                if "predictor_input" not in kwargs and '"predictor_input"' not in archive.read("data").decode("utf-8", "replace"):
                    kwargs["predictor_input"] = "observation"  # saved before the predictor could read features
        except zipfile.BadZipFile as error:
            if _holds(file, b"PK\x03\x04", prefix=True):
                raise ValueError(f"{path} is truncated or damaged: it begins as a saved model (a zip archive) but its end "
                                 f"is missing or unreadable ({error}); use a complete copy") from error
            raise ValueError(f"{path} is not a saved HhP model (not a zip archive): {error}") from error
        model = super().load(file, env=None, device=device, custom_objects=custom_objects,
                             print_system_info=print_system_info, force_reset=force_reset, **kwargs)
        # a MiniGrid model saved before the canvas's outer ring was left out reads the canvas with it: raw envs given
        # to it are wrapped so (set_env)
        model.minigrid_outer_ring = (isinstance(getattr(model, "goal_space", None), MiniGridGoalSpace)
                                     and components.get("minigrid_outer_ring", True))
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
        save_to_pkl(path, {
            "format": REPLAY_FORMAT,
            "meta": buffer_state(meta, meta.buffer_size, meta.buffer_size if meta.full else meta.pos),
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
            super().load_replay_buffer(path, truncate_last_traj)  # SB3's file: R_H only
            self._bonus_key = None
            return
        if not isinstance(data, dict) or data.get("format") != REPLAY_FORMAT:
            raise ValueError(f"{path} is not a replay saved by HhP.save_replay_buffer (nor an SB3 replay buffer)")
        self.subpolicies.load_replay_state(data["subgoal_learners"], truncate_last_traj)
        meta = self.replay_buffer
        load_buffer_state(meta, data["meta"], meta.buffer_size, "the meta-controller's replay R_H")
        meta.device = self.device
        self._bonus_key = None  # the cached preference bonuses belonged to the rows held before

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """Attach (new) envs: an env, an env id or a VecEnv of any number of envs, whose sub-goals are the model's."""
        outer_ring = self.minigrid_outer_ring
        venv = _vec_env(env, outer_ring=outer_ring)
        assert venv is not None
        if venv.observation_space != self.primitive_observation_space:
            hint = ""
            if isinstance(self.goal_space, MiniGridGoalSpace):
                hint = ("; this model reads MiniGrid's canvas with its outer ring (it was saved before that ring was left "
                        "out): wrap its envs with sb3_hhp.goals.wrap_env(env, outer_ring=True), or give a raw env"
                        if outer_ring else "; wrap MiniGrid envs with sb3_hhp.goals.wrap_env")
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
