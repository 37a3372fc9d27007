"""HhP's grouped arguments: one ``*_kwargs`` dict per component, each over its defaults, validated once.

:class:`~sb3_hhp.hhp.hhp.HhP` takes what the paper names at the top level (the oracle, the budget, beta of eq. 3, alpha of
eq. 6, the goal space, ``max_subgoal_steps``), the meta-controller's SB3 DQN arguments (``learning_rate``,
``buffer_size``, ...), and one dict per component: ``query_kwargs`` (who is asked and when), ``predictor_kwargs``,
``discovery_kwargs`` (CSD), ``subgoal_learner_kwargs`` (how the sub-goal learners learn; their SB3 arguments are
``subpolicy_kwargs``), ``rnd_kwargs`` and ``meta_kwargs`` (the meta-controller beyond SB3's DQN). A key a dict does
not accept is refused with the keys it does.
"""

import inspect
from typing import Any, Optional

import numpy as np

from sb3_hhp.hierarchy.learners import PAPER_SUBPOLICY_KWARGS
from sb3_hhp.preferences.predictor import PreferencePredictor

#: ``query_kwargs``: the query selection (:class:`~sb3_hhp.preferences.query.QuerySelector`): the paper's t_qry
#: (``threshold``), the pacing ``mode`` ("adaptive", "fixed" or "paced"), the ``horizon`` in primitive steps over
#: which the adaptive mode paces the budget (None: the ``total_timesteps`` of each ``learn`` call), how the second
#: sub-goal of a question is chosen (``second``: "meta", the paper's, or "unasked"), what a confidence measures
#: (``reading``: "score", eq. 4 as the paper, or "pair": the spread of the question's answer), whether the state of every
#: choice is rendered for the questions' images (``record_images``; None: when a person answers and the goal space
#: does not draw a question's state from its facts), and the arguments of the oracle built from a name
QUERY_DEFAULTS: dict[str, Any] = dict(threshold=0.26, mode="adaptive", horizon=None, quantile_window=2_000,
                                      second="meta", reading="score", record_images=None, oracle_kwargs={})
#: ``predictor_kwargs``: the preference predictor's (:class:`~sb3_hhp.preferences.predictor.PreferencePredictor`):
#: MC-dropout masks and dropout probability of eq. 4, its head and spread (design decisions: the predictor head), and
#: what it reads (``input``: "observation", "features" of the goal space, or "auto": features where there are some)
PREDICTOR_DEFAULTS: dict[str, Any] = dict(hidden_dim=256, dropout=0.1, n_masks=500, head="linear", spread="std",
                                          input="auto")
#: every key ``predictor_kwargs`` may hold (HhP sets ``buffer_size``, ``device`` and ``seed`` unless given)
PREDICTOR_KEYS = (frozenset(inspect.signature(PreferencePredictor.__init__).parameters) - {"self", "observation_space"}
                  | {"input"})
#: ``discovery_kwargs``: CSD's (:class:`~sb3_hhp.discovery.csd.SubgoalDiscovery`): the ``strategy`` ("csd",
#: "random", the paper's ablation, or "none": only the sub-goals handed in), the ``subgoals`` handed in
#: (observations of the env, seeding or replacing discovery), the lowest percentile of novelty progress, the visits a
#: key needs, the similarity gate b_similarity, whether the state just before a success is a candidate too, and which
#: states the percentile ranks
DISCOVERY_DEFAULTS: dict[str, Any] = dict(strategy="csd", subgoals=None, percentile=5.0, min_visits=2,
                                          similarity_threshold=0.5, before_success=False, percentile_of="visited")
#: ``subgoal_learner_kwargs``: how the sub-goal learners learn, beside their SB3 arguments (``subpolicy_kwargs``): the
#: ``kind`` of the learners (discrete actions: "stacked", a network each, updated in one call, or "heads", one trunk and
#: a head each; continuous actions: "goal_conditioned", one model for every place, trained with hindsight; None:
#: "stacked" or "goal_conditioned"); own steps over which a learner's epsilon decays, and the run's steps since it was
#: added over which it decays too (None: own steps only); whether every transition also trains the other sub-goals'
#: learners; whether they update on every primitive step (None: True for discrete actions); most learners updated in one
#: round; the learning rounds of one step of the envs in one call; the cells around the agent they read; the one-hot
#: encoding of each channel; the coarse overview of the observation (these three may be "auto": :data:`LEARNER_INPUTS`);
#: the range their TD targets are clipped to
SUBGOAL_LEARNER_DEFAULTS: dict[str, Any] = dict(kind=None, exploration_steps=5_000, exploration_run_steps=None,
                                                share_experience=True, train_shared=None, max_updates=8,
                                                grouped_rounds=False, view=None, carry_relabel=0.0, one_hot=None,
                                                overview=None, target_range=None)
#: the ``subgoal_learner_kwargs`` that may be "auto": what the learners read, derived from the env by the goal space
#: (:meth:`~sb3_hhp.goals.base.GoalSpace.learner_input`; MiniGrid: the view and the overview by the grid's size, the
#: indicators by the objects its grids hold)
LEARNER_INPUTS = ("view", "overview", "one_hot")
#: ``meta_kwargs``: the meta-controller beyond SB3's DQN arguments: N_opt updates after each episode (``n_opt``), the
#: target network's ``target_update_interval`` (in sub-goal choices) and ``tau``, ``exploration_initial_eps``,
#: ``max_grad_norm``, ``stats_window_size`` (SB3's), the head's initial ``capacity`` (it doubles when full), what it
#: reads (``input``, as the predictor's), how the preference bonus is centred (``center_bonus``), whether the bonus is
#: added to its Q-values exactly (``exact_bonus``), how the task's own goal is paid (``success_bonus``), whether it
#: chooses only choosable sub-goals (``mask_subgoals``), whether ``predict`` breaks cycles (``break_cycles``) and what
#: ``gamma`` discounts (``discount``): each sub-goal choice ("choice", the paper's DQN over choices) or each primitive
#: step ("steps": an option's return is sum_i gamma^i r_i and its bootstrap gamma^k after its k steps, the semi-MDP's);
#: ``steps_per_update``: at most one update per this many primitive steps of all envs (None: N_opt after every
#: episode, however short, Algorithm 1; design decisions: the meta-controller's update rate); ``choices_per_update``: at
#: least one update per this many sub-goal choices stored (None: N_opt per episode alone; long episodes of many choices
#: then get more updates)
META_DEFAULTS: dict[str, Any] = dict(n_opt=4, target_update_interval=500, tau=1.0, exploration_initial_eps=1.0,
                                     max_grad_norm=10.0, stats_window_size=100, capacity=16, input="auto",
                                     center_bonus="max", exact_bonus=False, success_bonus="predicted",
                                     mask_subgoals=True, break_cycles=True, discount="choice",
                                     steps_per_update=None, choices_per_update=None)
#: each ``*_kwargs`` argument grouped over defaults: its defaults and the keys it accepts (None: the defaults' keys)
GROUPED_ARGUMENTS: dict[str, tuple[dict[str, Any], Optional[frozenset]]] = {
    "query_kwargs": (QUERY_DEFAULTS, None),
    "predictor_kwargs": (PREDICTOR_DEFAULTS, PREDICTOR_KEYS),
    "discovery_kwargs": (DISCOVERY_DEFAULTS, None),
    "subgoal_learner_kwargs": (SUBGOAL_LEARNER_DEFAULTS, None),
    "meta_kwargs": (META_DEFAULTS, None),
}
#: the choices some keys are limited to
CHOICES: dict[tuple[str, str], tuple] = {
    ("discovery_kwargs", "strategy"): ("csd", "random", "none"),
    ("subgoal_learner_kwargs", "kind"): (None, "stacked", "heads", "goal_conditioned"),
    ("predictor_kwargs", "input"): ("auto", "features", "observation"),
    ("meta_kwargs", "input"): ("auto", "features", "observation"),
    ("meta_kwargs", "center_bonus"): (True, False, "mean", "max"),
    ("meta_kwargs", "exact_bonus"): (True, False),
    ("meta_kwargs", "success_bonus"): ("predicted", "best"),
    ("meta_kwargs", "discount"): ("choice", "steps"),
}


def grouped(name: str, given: Optional[dict[str, Any]]) -> dict[str, Any]:
    """The ``*_kwargs`` argument ``name``: its defaults updated with ``given``, checked."""
    defaults, keys = GROUPED_ARGUMENTS[name]
    if given is not None and not isinstance(given, dict):
        raise ValueError(f"{name} must be a dict, got {type(given).__name__}")
    known = keys if keys is not None else frozenset(defaults)
    unknown = sorted(set(given or {}) - known)
    if unknown:
        raise ValueError(f"{name} has no key {unknown[0]!r}; its keys are {', '.join(sorted(known))}")
    values = {**defaults, **(given or {})}
    for (group, key), choices in CHOICES.items():
        value = values[key] if group == name else None
        if group == name and not any(value is choice or (type(value) is type(choice) and value == choice)
                                     for choice in choices):
            raise ValueError(f"{name}['{key}'] must be one of {', '.join(map(repr, choices))}, got {value!r}")
    return values


def check_grouped(query: dict[str, Any], predictor: dict[str, Any], discovery: dict[str, Any],
                  learner: dict[str, Any], meta: dict[str, Any]) -> None:
    """The grouped values a later component would only refuse once the model is set up."""
    if not (isinstance(query["threshold"], (int, float, np.number)) and query["threshold"] >= 0):
        raise ValueError(f"query_kwargs['threshold'] (t_qry) must be >= 0, got {query['threshold']!r}")
    if query["horizon"] is not None and query["horizon"] < 1:
        raise ValueError(f"query_kwargs['horizon'] must be >= 1 primitive steps (or None), got {query['horizon']}")
    if not isinstance(query["oracle_kwargs"], dict):
        raise ValueError(f"query_kwargs['oracle_kwargs'] must be a dict, got {query['oracle_kwargs']!r}")
    if not 0.0 <= predictor["dropout"] < 1.0:
        raise ValueError(f"predictor_kwargs['dropout'] must be in [0, 1), got {predictor['dropout']}")
    if discovery["strategy"] == "none" and not discovery["subgoals"]:
        raise ValueError("discovery_kwargs: strategy='none' needs sub-goals handed in: discovery_kwargs=dict("
                         "strategy='none', subgoals=[obs, ...])")
    if not 0.0 <= learner["carry_relabel"] <= 1.0:
        raise ValueError(f"subgoal_learner_kwargs['carry_relabel'] must be in [0, 1], got {learner['carry_relabel']!r}")
    if learner["train_shared"] and not learner["share_experience"]:
        raise ValueError("subgoal_learner_kwargs: train_shared=True trains sub-goals on shared experience: it needs "
                         "share_experience=True")
    if meta["n_opt"] < 1:
        raise ValueError(f"meta_kwargs['n_opt'] must be >= 1, got {meta['n_opt']}")
    for name in ("steps_per_update", "choices_per_update"):
        every = meta[name]
        if every is not None and (isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1):
            raise ValueError(f"meta_kwargs['{name}'] must be an integer >= 1 (or None), got {every!r}")
    if meta["capacity"] < 1:
        raise ValueError(f"meta_kwargs['capacity'] must be >= 1, got {meta['capacity']}")


#: the paper's settings (section 5.1) over the class defaults, which are those measured to learn MiniGrid here:
#: the paper's sub-goal learner, an uncentred preference bonus, the networks on observations, sub-goals learning only
#: while they act, 200 questions
PAPER_KWARGS: dict[str, Any] = dict(
    query_budget=200, max_subgoal_steps=50, subpolicy_kwargs=PAPER_SUBPOLICY_KWARGS,
    predictor_kwargs=dict(input="observation"),
    meta_kwargs=dict(center_bonus=False, input="observation"),
    subgoal_learner_kwargs=dict(kind="stacked", train_shared=False, max_updates=None),
)
