"""The public surface of HhP: predict with the sub-goal in ``state``, primitive-step counting, callbacks,
save/load, errors, the paper's ablations, resuming with a preference database, and a growing
sub-goal set. Tiny settings throughout (5x5 MiniGrid, a few thousand primitive steps)."""

import pathlib
import zipfile
from collections import Counter
from typing import Any, Optional

import gymnasium as gym
from gymnasium import spaces
import minigrid  # noqa: F401  (registers the MiniGrid envs)
from minigrid.core.constants import OBJECT_TO_IDX
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack, VecNormalize

from sb3_hhp import HhP
from sb3_hhp.dqn.dqn import DoubleDQN
from sb3_hhp.goals import MiniGridGoalSpace, wrap_env
from sb3_hhp.hhp.hhp import COMPONENTS_FILE
from sb3_hhp.hierarchy.encoders import OneHotCodes, Overview
from sb3_hhp.hierarchy.learners import StackedDQN
from sb3_hhp.hierarchy.options import EpisodeTrace
from sb3_hhp.oracles import Label
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable

th.set_num_threads(1)

DOORKEY = "MiniGrid-DoorKey-5x5-v0"
EMPTY = "MiniGrid-Empty-5x5-v0"
#: tiny networks and buffers
TINY: dict[str, Any] = dict(
    buffer_size=2_000,
    learning_starts=300,
    batch_size=32,
    max_subgoal_steps=30,
    meta_kwargs=dict(target_update_interval=50),
    policy_kwargs=dict(net_arch=[64]),
    predictor_kwargs=dict(hidden_dim=64, batch_size=32, n_masks=20),
    rnd_kwargs=dict(hidden_dim=64, refresh_interval=500),
    subpolicy_kwargs=dict(learning_starts=50, buffer_size=2_000, batch_size=32, policy_kwargs=dict(net_arch=[64, 64])),
    subgoal_learner_kwargs=dict(exploration_steps=500),
)
#: the ``*_kwargs`` arguments that :func:`tiny` merges key by key
GROUPED = ("query_kwargs", "predictor_kwargs", "subgoal_learner_kwargs", "meta_kwargs", "discovery_kwargs")


def tiny(**kwargs: Any) -> dict[str, Any]:
    """:data:`TINY` updated with ``kwargs``; the grouped ``*_kwargs`` dicts are merged key by key."""
    settings = {**TINY, **kwargs}
    for group in GROUPED:
        if group in kwargs:
            settings[group] = {**TINY.get(group, {}), **kwargs[group]}
    return settings


def make_model(env_id: str = DOORKEY, **kwargs: Any) -> HhP:
    """A tiny model that asks about every tuple (fixed mode, t_qry = 0) within a budget of 10."""
    query_kwargs = {"mode": "fixed", "threshold": 0.0, **kwargs.pop("query_kwargs", {})}
    return HhP("MlpPolicy", gym.make(env_id), **tiny(**{"seed": 0, "query_budget": 10, **kwargs, "query_kwargs": query_kwargs}))


def observations(env_id: str = DOORKEY, seeds: tuple[int, ...] = (0, 1, 2, 3, 4)) -> np.ndarray:
    env = wrap_env(gym.make(env_id))
    return np.stack([env.reset(seed=seed)[0] for seed in seeds])


@pytest.fixture(scope="module")
def trained() -> HhP:
    """2000 primitive steps on DoorKey-5x5 with the scripted oracle asking about every tuple (t_qry = 0)."""
    model = make_model()
    model.learn(2_000)
    return model


class CountingCallback(BaseCallback):
    """Counts its calls and the primitive steps the meta-steps took."""

    def __init__(self) -> None:
        super().__init__()
        self.primitive_steps = 0
        self.starts = 0
        self.ends = 0

    def _on_training_start(self) -> None:
        self.starts += 1

    def _on_step(self) -> bool:
        self.primitive_steps += self.training_env.num_envs
        return True

    def _on_training_end(self) -> None:
        self.ends += 1


# ---------------------------------------------------------------------------- predict


def test_predict_single_and_vectorised(trained: HhP) -> None:
    obs = observations()
    n_goals = len(trained.subgoals)
    assert n_goals >= 2
    action, state = trained.predict(obs[0], deterministic=True)
    assert np.shape(action) == () and trained.primitive_action_space.contains(int(action))
    goals, steps, *_ = state
    assert goals.shape == (1,) and steps.shape == (1,)
    assert 0 <= goals[0] < n_goals and steps[0] == 1
    # the action is the chosen sub-goal's subpolicy acting greedily
    assert int(action) == int(trained.subpolicies.act(goals[:1], obs[0][None], deterministic=True)[0])

    actions, (goals, steps, *_) = trained.predict(obs, deterministic=True)
    assert actions.shape == (len(obs),)
    assert all(trained.primitive_action_space.contains(int(a)) for a in actions)
    assert goals.shape == steps.shape == (len(obs),)
    assert ((goals >= 0) & (goals < n_goals)).all() and (steps == 1).all()
    # stochastic predictions stay in the spaces too
    actions, (goals, _, *_) = trained.predict(obs, deterministic=False)
    assert all(trained.primitive_action_space.contains(int(a)) for a in actions)
    assert trained.valid_actions[goals].all()


@pytest.mark.parametrize("deterministic", [True, False])
@pytest.mark.parametrize("break_cycles", [True, False])
def test_a_walk_that_comes_back_takes_its_best_untried_action(break_cycles: bool, deterministic: bool, monkeypatch) -> None:
    """A greedy learner on a deterministic env that comes back to an observation would go round the same cycle until
    its sub-goal gave up; with ``break_cycles`` it takes there its best action not yet taken there (in this walk). The
    stochastic policy is that policy with epsilon-random actions (epsilon 0 here: the same actions)."""
    env = wrap_env(gym.make(DOORKEY))
    obs, _ = env.reset(seed=0)
    model = make_model(meta_kwargs=dict(break_cycles=break_cycles), discovery_kwargs=dict(strategy="none", subgoals=[obs]))
    q_row = np.array([3.0, 1.0, 2.0, 0.5, 0.4, 0.3, 0.2])  # greedy: turn left, round and round in one cell
    monkeypatch.setattr(model.subpolicies, "q_values",
                        lambda goals, batch: th.as_tensor(np.tile(q_row, (len(goals), 1)), device=model.device))
    monkeypatch.setattr(model.subpolicies, "allowed_actions", lambda batch: None)
    monkeypatch.setattr(model.subpolicies, "exploration_rate", lambda goal: 0.0)
    monkeypatch.setattr("sb3_hhp.hhp.acting.option_terminal", lambda space, key, goal, steps, limit: (False, steps >= limit))
    state, seen, actions = None, [], []
    for t in range(16):
        action, state = model.predict(obs, state=state, episode_start=np.array([t == 0]), deterministic=deterministic)
        assert state[0][0] == 0 and state[1][0] == t + 1  # one walk, never renewed
        before = [a for o, a in zip(seen, actions) if np.array_equal(o, obs)]
        untried = [a for a in np.argsort(-q_row) if a not in before]
        expected = untried[0] if before and break_cycles and untried else 0
        assert int(action) == expected, f"step {t}: took {int(action)}, expected {expected}"
        seen.append(obs)
        actions.append(int(action))
        obs, *_ = env.step(action)
    if break_cycles:  # four turns bring it back: the fifth step tries the next best action
        assert actions[4] == 2 and len(set(actions)) >= 3
    else:
        assert actions == [0] * 16
    # the walk's memory is dropped with the walk: a new episode starts greedy again
    action, state = model.predict(seen[4], state=state, episode_start=np.array([True]), deterministic=True)
    assert int(action) == 0 and state[1][0] == 1
    # back in that observation later in the walk: both policies break the cycle (epsilon 0)
    later = (np.array([0]), np.array([5]), *state[2:])
    assert int(model.predict(seen[4], state=later, deterministic=True)[0]) == (2 if break_cycles else 0)
    assert int(model.predict(seen[4], state=later, deterministic=False)[0]) == (2 if break_cycles else 0)
    # epsilon 1: the stochastic policy's actions are random, whatever it remembers
    monkeypatch.setattr(model.subpolicies, "exploration_rate", lambda goal: 1.0)
    drawn = {int(model.predict(seen[4], state=later, deterministic=False)[0]) for _ in range(60)}
    assert len(drawn) >= 4


@pytest.mark.parametrize("deterministic", [True, False])
@pytest.mark.parametrize("break_cycles", [True, False])
def test_a_meta_controller_back_in_a_state_takes_its_best_untried_choice(trained: HhP, break_cycles: bool,
                                                                         deterministic: bool, monkeypatch) -> None:
    """A greedy meta-controller back in an observation it chose in before in the episode (its sub-goal reached, the
    env back where it was: a loop of choices) would choose the same again; with ``break_cycles`` it takes its best
    choosable sub-goal not chosen there yet in this episode, and the best again once all were tried. The stochastic
    policy is that policy with epsilon-random choices (epsilon 0 here: the same choices; 1: random choosable ones)."""
    monkeypatch.setattr(trained, "break_cycles", break_cycles)
    monkeypatch.setattr(trained, "exploration_rate", 0.0)
    # every existing sub-goal choosable everywhere: the test is of the rule, whatever the goal space would mask
    monkeypatch.setitem(vars(trained), "action_mask", lambda observations: np.asarray(trained.valid_actions))
    monkeypatch.setattr("sb3_hhp.hhp.acting.option_terminal", lambda space, key, goal, steps, limit: (steps > 0, False))
    obs, other = observations()[:1], observations()[1:2]
    with th.no_grad():
        q_values = trained.q_net(trained.policy.obs_to_tensor(obs)[0]).cpu().numpy()[0, : len(trained.subgoals)]
    mask = trained.action_mask(obs)
    choosable = np.ones(len(q_values), dtype=bool) if mask is None else np.broadcast_to(mask, (1, mask.shape[-1]))[0, : len(q_values)]
    order = [int(g) for g in np.argsort(-np.where(choosable, q_values, -np.inf)) if choosable[g]]
    assert len(order) >= 2, "the test needs a state with two choosable sub-goals"
    _, state = trained.predict(obs, episode_start=np.array([True]), deterministic=deterministic)
    choices = [int(state[0][0])]
    assert choices[0] == order[0]
    for _ in range(len(order) + 1):  # each choice reached at once, the env back in the same observation
        _, state = trained.predict(obs, state=state, episode_start=np.array([False]), deterministic=deterministic)
        choices.append(int(state[0][0]))
    if break_cycles:  # every choosable sub-goal once, best first, then the best again
        assert choices == order + [order[0]] * 2
    else:
        assert choices == [order[0]] * (len(order) + 2)
    # another observation keeps its greedy choice; a new episode forgets the choices
    _, fresh = trained.predict(other, deterministic=True)
    assert int(trained.predict(other, state=state, episode_start=np.array([False]), deterministic=True)[1][0][0]) == int(fresh[0][0])
    _, state = trained.predict(obs, state=state, episode_start=np.array([True]), deterministic=True)
    assert int(state[0][0]) == order[0]
    if not deterministic:  # epsilon 1: random choosable sub-goals, whatever it remembers
        monkeypatch.setattr(trained, "exploration_rate", 1.0)
        drawn = [int(trained.predict(obs, state=state, episode_start=np.array([True]), deterministic=False)[1][0][0])
                 for _ in range(60)]
        assert set(drawn) <= set(order) and len(set(drawn)) == len(order)


def test_predict_keeps_the_subgoal_until_episode_start_or_give_up(trained: HhP) -> None:
    goal_space = trained.goal_space
    obs = observations()[:1]
    _, (chosen, _, *_) = trained.predict(obs, deterministic=True)
    key = goal_space.key(obs[0])
    # a sub-goal other than the meta-controller's choice, not reached in this observation
    other = next(i for i, goal in enumerate(trained.subgoals) if i != chosen[0] and goal.key != key)
    state = (np.array([other]), np.array([5]))

    _, (goals, steps, *_) = trained.predict(obs, state=state, episode_start=np.array([False]), deterministic=True)
    assert goals[0] == other and steps[0] == 6
    _, (goals, steps, *_) = trained.predict(obs, state=state, episode_start=np.array([True]), deterministic=True)
    assert goals[0] == chosen[0] and steps[0] == 1
    gave_up = (np.array([other]), np.array([trained.max_subgoal_steps]))
    _, (goals, steps, *_) = trained.predict(obs, state=gave_up, episode_start=np.array([False]), deterministic=True)
    assert goals[0] == chosen[0] and steps[0] == 1
    # the state passed in is not modified in place
    assert state[0][0] == other and state[1][0] == 5
    # a greedy meta-controller does not take again the sub-goal that just gave up: its best other choosable
    # one; where the failed one is the only choosable sub-goal, it is kept
    cases = {"other": 0, "only": 0}
    env, starts = wrap_env(gym.make(DOORKEY)), []
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(300):  # states along a random walk, where what is carried and faced varies
        start, _, terminated, truncated, _ = env.step(env.action_space.sample())
        starts.append(start)
        if terminated or truncated:
            env.reset()
    masked = trained.mask_subgoals
    try:
        for trained.mask_subgoals in (True, False):  # unmasked, every state has another sub-goal to take
            for start in starts[::10]:
                start = start[None]
                _, (first, *_) = trained.predict(start, deterministic=True)
                if goal_space.achieved(goal_space.key(start[0]), trained.subgoals[first[0]].key):
                    continue  # reached where it would give up: reached (unmasked, it may be chosen where it holds)
                failed = (np.array([first[0]]), np.array([trained.max_subgoal_steps]))
                _, (goals, _, *_) = trained.predict(start, state=failed, episode_start=np.array([False]), deterministic=True)
                with th.no_grad():
                    q_values = trained.q_net(trained.policy.obs_to_tensor(start)[0]).cpu().numpy()[0, : len(trained.subgoals)]
                mask = np.broadcast_to(trained.action_mask(start), (1, int(trained.action_space.n)))
                q_values[~mask[0, : len(trained.subgoals)]] = -np.inf  # among the choosable sub-goals
                q_values[first[0]] = -np.inf
                if np.isfinite(q_values).any():
                    cases["other"] += 1
                    assert goals[0] != first[0] and goals[0] == int(np.argmax(q_values))
                else:
                    cases["only"] += 1
                    assert goals[0] == first[0]
    finally:
        trained.mask_subgoals = masked
    assert cases["other"] > 0, cases  # the rule was exercised at least once


def test_evaluate_policy_works_unchanged(trained: HhP) -> None:
    env = wrap_env(gym.make(DOORKEY))
    lengths_seen = []

    def record(locals_: dict, _globals: dict) -> None:
        goals, steps, *_ = locals_["states"]
        assert goals.shape == (1,) and 0 <= goals[0] < len(trained.subgoals) and steps[0] >= 1
        lengths_seen.append(locals_["current_lengths"][0])

    rewards, lengths = evaluate_policy(trained, env, n_eval_episodes=3, return_episode_rewards=True, callback=record)
    assert len(rewards) == len(lengths) == 3
    max_steps = env.unwrapped.max_steps
    assert all(1 <= length <= max_steps for length in lengths)
    assert all(0.0 <= reward < 1.0 for reward in rewards)
    assert sum(lengths) == len(lengths_seen)
    mean, std = evaluate_policy(trained, wrap_env(gym.make(DOORKEY)), n_eval_episodes=3)
    assert np.isfinite(mean) and np.isfinite(std)


# ---------------------------------------------------------------------------- primitive steps


def test_total_timesteps_counts_primitive_steps(trained: HhP) -> None:
    assert trained.num_timesteps >= 2_000
    assert trained.num_timesteps == trained.options.num_steps
    # every primitive step was a subpolicy step or a step of the first, random episode
    subpolicy_steps = int(trained.subpolicies.own_steps.sum())
    assert 0 < subpolicy_steps < trained.num_timesteps
    assert sum(trained.subgoal_set.visits.values()) == trained.num_timesteps
    # far fewer meta-steps (sub-goal choices) than primitive steps
    assert trained.replay_buffer.size() < trained.num_timesteps


def test_learn_with_a_user_callback_and_progress_bar(capsys: pytest.CaptureFixture) -> None:
    model = make_model(EMPTY)
    callback = CountingCallback()
    model.learn(600, callback=callback, progress_bar=True)
    assert model.num_timesteps >= 600
    assert callback.starts == callback.ends == 1
    assert callback.n_calls == model.num_timesteps  # one call per step of the (one) env, as in SB3's algorithms
    assert callback.primitive_steps == model.num_timesteps
    assert callback.num_timesteps == model.num_timesteps
    # a list of callbacks works too, and a plain function (SB3's ConvertCallback)
    second, third = CountingCallback(), CountingCallback()
    model.learn(300, callback=[second, third], reset_num_timesteps=False)
    assert model.num_timesteps >= 900 and second.primitive_steps == model.num_timesteps - callback.primitive_steps
    assert third.n_calls == second.n_calls >= 1
    calls = []
    model.learn(200, callback=lambda _locals, _globals: calls.append(1) or True, reset_num_timesteps=False)
    assert len(calls) >= 1 and model.num_timesteps >= 1_100


def test_max_centred_bonus_subtracts_the_best_choosable_score(trained: HhP, monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``center_bonus="max"`` a sub-goal the mask rules out in the state does not set the level: the bonus is
    b(s, g) - max over the choosable g' (and g itself)."""
    replay = trained.replay_buffer.sample(8)
    goals = replay.actions.long().flatten().cpu().numpy()
    states = replay.observations.cpu().numpy().astype(np.uint8)
    goal_obs = trained.goal_space.features(trained.goal_obs)
    scores = np.stack([trained.predictor.score(trained.goal_space.features(state), goal_obs) for state in states])
    n_goals = len(goal_obs)
    mask = np.ones((len(states), trained.action_space.n), dtype=bool)
    top = scores.argmax(axis=1)
    mask[np.arange(len(states)), top] = top == goals  # rule out each state's best sub-goal unless it was chosen
    monkeypatch.setitem(vars(trained), "action_mask", lambda observations: mask)
    monkeypatch.setattr(trained, "center_bonus", "max")
    best = np.where(mask[:, :n_goals], scores, -np.inf).max(axis=1)
    np.testing.assert_allclose(trained.preference_bonus(states, goals), scores[np.arange(len(goals)), goals] - best, atol=1e-6)
    assert not np.allclose(best, scores.max(axis=1))


def test_with_success_bonus_best_the_task_solved_scores_as_the_best_other_choosable_subgoal(
        trained: HhP, monkeypatch: pytest.MonkeyPatch) -> None:
    """``success_bonus="best"``: the task's own goal gets, in each state, the best score among the other choosable
    sub-goals, so with ``center_bonus="max"`` its bonus is 0 and the other bonuses are taken from that best."""
    replay = trained.replay_buffer.sample(8)
    states = replay.observations.cpu().numpy().astype(np.uint8)
    goal_obs = trained.goal_space.features(trained.goal_obs)
    n_goals = len(goal_obs)
    assert n_goals >= 3
    scores = np.stack([trained.predictor.score(trained.goal_space.features(state), goal_obs) for state in states])
    success = int(scores.mean(axis=0).argmin())  # a sub-goal the predictor dislikes, standing in for "task solved"
    monkeypatch.setattr(HhP, "success_goal", property(lambda self: success))
    mask = np.ones((len(states), trained.action_space.n), dtype=bool)
    mask[:, (success + 1) % n_goals] = False  # one other sub-goal not choosable anywhere
    monkeypatch.setitem(vars(trained), "action_mask", lambda observations: mask)
    others = mask[:, :n_goals] & (np.arange(n_goals) != success)
    best_other = np.where(others, scores, -np.inf).max(axis=1)
    goals = np.arange(len(states)) % n_goals
    goals[:3] = success
    predicted = trained.preference_bonus(states, goals)
    monkeypatch.setattr(trained, "success_bonus", "best")
    monkeypatch.setattr(trained, "center_bonus", "max")
    bonus = trained.preference_bonus(states, goals)
    np.testing.assert_allclose(bonus[:3], 0.0, atol=1e-6)
    chosen = scores[np.arange(len(goals)), goals]
    expected = np.where(goals == success, 0.0, np.minimum(chosen - best_other, 0.0))
    np.testing.assert_allclose(bonus, expected, atol=1e-5)
    assert (goals[3:] != success).any() and (expected[3:] < 0).any()
    assert not np.allclose(predicted[:3], 0.0)  # the predictor alone scores the stand-in otherwise
    monkeypatch.setattr(trained, "center_bonus", False)
    np.testing.assert_allclose(trained.preference_bonus(states, goals)[:3], best_other[:3], rtol=1e-5, atol=1e-6)


def test_with_success_bonus_best_no_question_compares_the_task_solved() -> None:
    """The task's own goal is judged by the extrinsic reward alone: it is in no question (and is in some without)."""
    solved = []
    for success_bonus in ("predicted", "best"):
        model = make_model(EMPTY, query_budget=40, meta_kwargs=dict(success_bonus=success_bonus))
        model.learn(3_000)
        success = model.success_goal
        assert success is not None and model.query_selector.used > 0
        questions = [model.store.get_query(query_id) for query_id in model.store.asked_ids()]
        solved.append(sum(success in (query.goal1, query.goal2) for query in questions))
    assert solved[0] > 0 and solved[1] == 0


def test_the_confidences_are_computed_only_where_the_paced_budget_allows_a_question(monkeypatch) -> None:
    """Adaptive pacing: an episode that ends while the questions are up with the allowance asks nothing, and eq. 4's
    masks are not run for it; one that may ask runs them."""
    counts = []
    for horizon in (10**9, 1_500):  # the budget paced over a billion steps (allowance 0 throughout) or over this run
        model = make_model(EMPTY, query_budget=40, query_kwargs=dict(mode="adaptive", horizon=horizon))
        calls, confidence = [], model.predictor.confidence
        monkeypatch.setattr(model.predictor, "confidence", lambda *a, **k: calls.append(1) or confidence(*a, **k))
        model.learn(1_500)
        counts.append((len(calls), model.query_selector.used, model.query_selector.state_dict()["n_calls"]))
    (idle_calls, idle_used, idle_episodes), (calls, used, _) = counts
    assert idle_calls == idle_used == 0 and idle_episodes > 10  # every episode counted, none computed
    assert calls > 0 and used > 0


def test_with_the_pair_reading_a_question_is_chosen_on_the_spread_of_its_own_answer(monkeypatch) -> None:
    """``query_kwargs["reading"] = "pair"``: the confidences are measured on each tuple's (s, g, g2) with the g2 the
    question would name, so they lie in [0, 0.5], and questions are asked."""
    model = make_model(EMPTY, query_budget=40, query_kwargs=dict(reading="pair", mode="fixed", threshold=0.0))
    measured, confidence = [], model.predictor.confidence

    def spy(states, goals, seconds=None):
        values = confidence(states, goals, seconds)
        measured.append((seconds, values))
        return values

    monkeypatch.setattr(model.predictor, "confidence", spy)
    model.learn(3_000)
    assert model.query_selector.used > 0 and measured
    assert all(seconds is not None for seconds, _ in measured)
    values = np.concatenate([values for _, values in measured])
    assert values.min() >= 0.0 and values.max() <= 0.5 and values.max() > 0.0
    questions = [model.store.get_query(query_id) for query_id in model.store.asked_ids()]
    assert all(query.goal1 != query.goal2 for query in questions)


def test_with_second_unasked_the_selector_reads_which_sub_goals_no_question_named(monkeypatch) -> None:
    """``query_kwargs["second"] = "unasked"``: each selection is told the sub-goals no earlier question named, the
    named keys follow the questions asked (and are read back from the store alike); "meta" passes nothing."""
    model = make_model(EMPTY, query_budget=40, query_kwargs=dict(second="unasked"))
    assert model.query_selector.second == "unasked"
    calls, select = [], model.query_selector.select

    def spy(*args, unasked=None, **kwargs):
        keys = model.subgoal_set.keys
        calls.append((unasked, {keys[i] for i in range(len(keys)) if unasked is not None and not unasked[i]},
                      set(model.asked_goal_keys)))
        return select(*args, unasked=unasked, **kwargs)

    monkeypatch.setattr(model.query_selector, "select", spy)
    model.learn(3_000)
    assert model.query_selector.used > 0 and calls
    for unasked, named_by_flags, named_before in calls:
        assert unasked is not None and named_by_flags == named_before
    questions = [model.store.get_query(query_id) for query_id in model.store.asked_ids()]
    named = {model.subgoals[goal].key for query in questions for goal in (query.goal1, query.goal2)}
    assert model.asked_goal_keys == named and len(named) >= 2
    model._asked_goal_keys = None  # read again from the store
    assert model.asked_goal_keys == named
    meta = make_model(EMPTY, query_budget=40)
    seen = []
    meta_select = meta.query_selector.select
    monkeypatch.setattr(meta.query_selector, "select",
                        lambda *a, unasked=None, **k: seen.append(unasked) or meta_select(*a, **k))
    meta.learn(3_000)
    assert seen and all(flags is None for flags in seen)


def _eq3_bonus_term(model: HhP, states: np.ndarray) -> np.ndarray:
    """(1 - beta) * b(s, g) / sigma (eq. 3's bonus term) of every sub-goal, 0 for the head's unused rows, with b the
    centred bonus as :meth:`HhP.preference_bonus` gives it one sub-goal at a time."""
    n_goals, n_actions = len(model.subgoals), int(model.action_space.n)
    bonus = np.zeros((len(states), n_actions))
    for goal in range(n_goals):
        bonus[:, goal] = model.preference_bonus(states, np.full(len(states), goal))
    return (1 - model.beta) * bonus / model.return_normalizer.sigma


def test_exact_bonus_adds_eq3s_bonus_term_to_both_networks(trained: HhP, monkeypatch: pytest.MonkeyPatch) -> None:
    """``exact_bonus``: the Q-values read from either network are its output plus (1 - beta) * b(s, g) / sigma of
    every sub-goal (the bonus of eq. 3 that the reward of the choice holds); without it, the network's output."""
    replay = trained.replay_buffer.sample(16)
    states = replay.observations.cpu().numpy().astype(np.uint8)
    with th.no_grad():
        plain = trained._q_values(replay.observations)
        np.testing.assert_array_equal(plain.numpy(), trained.q_net(replay.observations).numpy())
        monkeypatch.setattr(trained, "exact_bonus", True)
        expected = _eq3_bonus_term(trained, states)
        assert (expected[:, : len(trained.subgoals)] < -1e-3).any()  # the centred bonus is not all 0
        online = trained._q_values(replay.observations) - trained.q_net(replay.observations)
        target = (trained._q_values(replay.observations, trained.q_net_target)
                  - trained.q_net_target(replay.observations))
    np.testing.assert_allclose(online.numpy(), expected, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(target.numpy(), expected, rtol=1e-4, atol=1e-5)


def test_with_exact_bonus_the_target_adds_the_next_states_bonus_and_the_choice_follows_it(
        trained: HhP, monkeypatch: pytest.MonkeyPatch) -> None:
    """The TD target is r + discount * (Q_target(s', g*) + bonus(s', g*)), g* the online network's best choosable
    sub-goal with the bonus added; with the networks' outputs at 0 the greedy choice is the best choosable bonus."""
    monkeypatch.setattr(trained, "exact_bonus", True)
    replay = trained.replay_buffer.sample(16)
    next_states = replay.next_observations.cpu().numpy().astype(np.uint8)
    rewards = trained._rewards(replay)
    discounts = replay.discounts if replay.discounts is not None else trained.gamma
    with th.no_grad():
        target = trained._target(replay.next_observations, rewards, replay.dones, discounts, True, None).numpy().ravel()
        bonus = _eq3_bonus_term(trained, next_states)
        online = trained.q_net(replay.next_observations).numpy() + bonus
        valued = trained.q_net_target(replay.next_observations).numpy() + bonus
    mask = np.broadcast_to(trained.action_mask(next_states), online.shape)
    best = np.where(mask, online, -np.inf).argmax(axis=1)
    discount = np.broadcast_to(np.asarray(discounts, dtype=np.float64).reshape(-1), (len(best),))
    expected = (rewards.numpy().ravel()
                + (1 - replay.dones.numpy().ravel()) * discount * valued[np.arange(len(best)), best])
    np.testing.assert_allclose(target, expected, rtol=1e-4, atol=1e-5)
    last = trained.q_net.q_net[-1]
    saved = [last.weight.detach().clone(), last.bias.detach().clone()]
    try:
        with th.no_grad():
            last.weight.zero_()
            last.bias.zero_()
        states = replay.observations.cpu().numpy().astype(np.uint8)
        scores = np.where(np.broadcast_to(trained.action_mask(states), (len(states), int(trained.action_space.n))),
                          _eq3_bonus_term(trained, states), -np.inf)
        chosen = trained.choose_subgoals(states, deterministic=True)
        np.testing.assert_allclose(scores[np.arange(len(states)), chosen], scores.max(axis=1), atol=1e-6)
    finally:
        with th.no_grad():
            last.weight.copy_(saved[0])
            last.bias.copy_(saved[1])


def test_with_exact_bonus_a_model_learns_saves_and_loads(tmp_path) -> None:
    """``exact_bonus`` through ``learn`` (the meta-controller's updates read the bonus) and a save: the loaded model
    keeps the option and chooses as the saved one."""
    model = make_model(EMPTY, meta_kwargs=dict(exact_bonus=True))
    model.learn(1_500)
    assert len(model.predictor) > 0 and model._n_updates > 0
    model.save(tmp_path / "exact.zip")
    loaded = HhP.load(tmp_path / "exact.zip", device="cpu")
    assert loaded.exact_bonus is True
    states = observations(EMPTY)
    np.testing.assert_array_equal(loaded.choose_subgoals(states, deterministic=True),
                                  model.choose_subgoals(states, deterministic=True))


def test_the_bonus_of_a_sampled_choice_is_cached_until_the_predictor_or_the_subgoals_change(trained: HhP) -> None:
    """The meta-controller's updates read each stored choice's bonus from a cache: equal to a fresh
    ``preference_bonus``, and scored again once the predictor has trained or a row holds a new choice."""
    replay = trained.replay_buffer.sample(16)
    rows = np.asarray(replay.indices)
    goals = replay.actions.long().flatten().cpu().numpy()
    states = replay.observations.cpu().numpy().astype(np.uint8)
    calls = []
    original = trained.preference_bonus
    trained.preference_bonus = lambda s, g: calls.append(len(s)) or original(s, g)
    trained._bonus_key = None  # an empty cache
    try:
        first = trained._replay_bonus(rows, states, goals)
        np.testing.assert_allclose(first, original(states, goals), rtol=1e-5, atol=1e-6)
        assert sum(calls) == len(rows)
        calls.clear()
        np.testing.assert_array_equal(trained._replay_bonus(rows, states, goals), first)
        assert calls == []  # nothing scored again
        trained.predictor.train()  # new weights: every row is scored again
        trained._replay_bonus(rows, states, goals)
        assert sum(calls) == len(rows)
        calls.clear()
        trained._bonus_valid[rows[0]] = False  # what _store_choices does to a row it overwrites
        trained._replay_bonus(rows, states, goals)
        assert sum(calls) == int((rows == rows[0]).sum())
    finally:
        del trained.preference_bonus


def test_meta_reward_is_eq3_with_the_predictor_bonus(trained: HhP) -> None:
    """r^e = beta * R_e + (1 - beta) * b / sigma(R_p) (eq. 3) on a sampled batch, with b = p_hat(s, g), centred
    over the sub-goals of the state (b - mean_g' p_hat(s, g')) when ``center_bonus``, or shifted by the best choosable
    one (b - max_g' p_hat(s, g'), never positive) with ``center_bonus="max"``."""
    assert len(trained.predictor) > 0
    replay = trained.replay_buffer.sample(16)
    goals = replay.actions.long().flatten().cpu().numpy()
    states = replay.observations.cpu().numpy().astype(np.uint8)
    goal_obs = trained.goal_space.features(trained.goal_obs)  # the predictor reads the goal space's features
    assert trained.predictor_input == "auto" and goal_obs.ndim == 2
    # p_hat(s, g') for every sub-goal g', one state at a time
    scores = np.stack([trained.predictor.score(trained.goal_space.features(state), goal_obs) for state in states])
    chosen = scores[np.arange(len(goals)), goals]
    r_e = replay.rewards.cpu().numpy().flatten()
    beta, sigma = trained.beta, trained.return_normalizer.sigma
    assert sigma > 0
    # "max": minus the best score among the sub-goals choosable in the state (the chosen one counts too)
    choosable = trained.action_mask(states)[:, : len(goal_obs)] | (np.arange(len(goal_obs)) == goals[:, None])
    best = np.where(choosable, scores, -np.inf).max(axis=1)
    assert (chosen - best <= 1e-6).all()
    center = trained.center_bonus
    try:
        for trained.center_bonus, bonus in ((True, chosen - scores.mean(axis=1)), ("max", chosen - best), (False, chosen)):
            expected = beta * r_e + (1 - beta) * bonus / sigma  # eq. 3
            np.testing.assert_allclose(trained._rewards(replay).cpu().numpy().flatten(), expected, rtol=1e-4, atol=1e-5)
            assert not np.allclose(expected, beta * r_e)  # the bonus really enters
    finally:
        trained.center_bonus = center


# ---------------------------------------------------------------------------- save / load


def _assert_same_model(a: HhP, b: HhP, obs: np.ndarray) -> None:
    assert len(a.subgoals) == len(b.subgoals)
    for goal_a, goal_b in zip(a.subgoals, b.subgoals):
        assert goal_a.key == goal_b.key and isinstance(goal_b.key, tuple)
        np.testing.assert_array_equal(goal_a.obs, goal_b.obs)
        if goal_a.image is None:
            assert goal_b.image is None
        else:
            np.testing.assert_array_equal(goal_a.image, goal_b.image)
        assert goal_a.found_at == goal_b.found_at and goal_a.source == goal_b.source
    assert (a.query_selector.used, a.query_selector.budget) == (b.query_selector.used, b.query_selector.budget)
    assert int(a.action_space.n) == int(b.action_space.n)
    np.testing.assert_array_equal(a.valid_actions, b.valid_actions)
    assert len(a.predictor) == len(b.predictor)
    goal_obs = a.goal_obs
    pairs = a.predictor_inputs(np.repeat(obs, len(goal_obs), 0)), a.predictor_inputs(np.tile(goal_obs, (len(obs), 1, 1, 1)))
    np.testing.assert_allclose(a.predictor.score(*pairs), b.predictor.score(*pairs), rtol=1e-6)
    np.testing.assert_allclose(a.rnd.prediction_error(obs), b.rnd.prediction_error(obs), rtol=1e-6)
    assert len(a.rnd.memory) == len(b.rnd.memory)
    for old_a, old_b in zip(a.rnd.memory, b.rnd.memory):
        assert old_a.num_steps == old_b.num_steps
    np.testing.assert_allclose(a.rnd.novelty_progress(obs), b.rnd.novelty_progress(obs), rtol=1e-5, atol=1e-7)
    with th.no_grad():
        q_a = a.q_net(a.policy.obs_to_tensor(obs)[0]).cpu().numpy()
        q_b = b.q_net(b.policy.obs_to_tensor(obs)[0]).cpu().numpy()
    np.testing.assert_allclose(q_a, q_b, rtol=1e-6)


def _rollout_observations(model: HhP, seed: int, n_steps: int = 60) -> np.ndarray:
    env = wrap_env(gym.make(DOORKEY))
    obs, _ = env.reset(seed=seed)
    seen, state, start = [obs], None, np.array([True])
    for _ in range(n_steps - 1):
        action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
        obs, _, terminated, truncated, _ = env.step(action)
        start = np.array([terminated or truncated])
        if start[0]:
            obs, _ = env.reset()
        seen.append(obs)
    return np.stack(seen)


def _predictions(model: HhP, sequence: np.ndarray) -> list:
    out, state = [], None
    for t, obs in enumerate(sequence):
        action, state = model.predict(obs, state=state, episode_start=np.array([t == 0]), deterministic=True)
        out.append((int(action), int(state[0][0]), int(state[1][0])))
    return out


def test_save_load_round_trip(trained: HhP, tmp_path) -> None:
    assert trained.query_selector.used > 0 and len(trained.rnd.memory) > 0  # something to compare
    path = tmp_path / "hhp"
    trained.save(path)
    assert zipfile.is_zipfile(tmp_path / "hhp.zip")
    obs = observations()
    sequence = _rollout_observations(trained, seed=7)
    expected = _predictions(trained, sequence)

    no_env = HhP.load(path)
    assert no_env.get_env() is None
    _assert_same_model(trained, no_env, obs)
    assert _predictions(no_env, sequence) == expected
    with pytest.raises(ValueError, match="env"):
        no_env.learn(100)

    with_env = HhP.load(str(tmp_path / "hhp.zip"), env=gym.make(DOORKEY))
    _assert_same_model(trained, with_env, obs)
    assert _predictions(with_env, sequence) == expected
    assert with_env.num_timesteps == trained.num_timesteps
    assert with_env.subgoal_set.visits == trained.subgoal_set.visits
    assert len(trained.recent_choices) > 0 and list(with_env.recent_choices) == list(trained.recent_choices)
    assert [r["chosen_recently"] for r in no_env.subgoal_records()] == [r["chosen_recently"] for r in trained.subgoal_records()]

    # training goes on from where it stopped
    before = with_env.num_timesteps
    with_env.learn(400, reset_num_timesteps=False)
    assert with_env.num_timesteps >= before + 400
    assert with_env.options.num_steps == with_env.num_timesteps - before
    assert len(with_env.subgoals) >= len(trained.subgoals)
    assert with_env.query_selector.used <= with_env.query_selector.budget
    # and a model loaded without env can be given one
    no_env.set_env(gym.make(DOORKEY))
    no_env.learn(200, reset_num_timesteps=False)
    assert no_env.num_timesteps >= before + 200


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(env="CartPole-v1"), "goal space.*wrap_env"),
        (dict(env=EMPTY, oracle="no-such-oracle"), "Unknown oracle 'no-such-oracle'.*scripted"),
        (dict(env="NoSuchEnv-v0"), "Unknown env id 'NoSuchEnv-v0'"),
        (dict(env=EMPTY, query_budget=-1), "query_budget must be an integer >= 0, got -1"),
        (dict(env=EMPTY, beta=1.5), r"beta must be in \[0, 1\], got 1.5"),
        (dict(env=EMPTY, beta=-0.1), r"beta must be in \[0, 1\], got -0.1"),
        (dict(env=EMPTY, predictor_kwargs=dict(dropout=1.0)), r"dropout'\] must be in \[0, 1\), got 1.0"),
        (dict(env=EMPTY, meta_kwargs=dict(center_bonus="median")),
         r"meta_kwargs\['center_bonus'\] must be one of True, False, 'mean', 'max', got 'median'"),
        (dict(env=EMPTY, meta_kwargs=dict(success_bonus="neutral")),
         r"meta_kwargs\['success_bonus'\] must be one of 'predicted', 'best', got 'neutral'"),
        (dict(env=EMPTY, meta_kwargs=dict(exact_bonus="yes")), r"meta_kwargs\['exact_bonus'\] must be one of True, False"),
        (dict(env=EMPTY, meta_kwargs=dict(n_opt=0)), r"meta_kwargs\['n_opt'\] must be >= 1, got 0"),
        (dict(env=EMPTY, meta_kwargs=dict(steps_per_update=0)),
         r"meta_kwargs\['steps_per_update'\] must be an integer >= 1 \(or None\), got 0"),
        (dict(env=EMPTY, meta_kwargs=dict(tau=0.5, wizard=1)), "meta_kwargs has no key 'wizard'; its keys are"),
        (dict(env=EMPTY, discovery_kwargs=dict(strategy="none")), "strategy='none' needs sub-goals.*subgoals="),
        (dict(env=EMPTY, discovery_kwargs=dict(strategy="everything")), r"discovery_kwargs\['strategy'\] must be one of"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(kind="wide")), r"subgoal_learner_kwargs\['kind'\] must be one of"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(share_experience=False, train_shared=True)),
         "needs share_experience=True"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(view=4)), "view.*odd integer"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(view=9)), "view 9 is larger than the observation's 7 x 7"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(one_hot=[11, 6])), "one_hot.*each of the observation's 3 channels"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(one_hot=[0, [], 0])), "one_hot.*not all empty"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(one_hot=[11, -1, 3])), "one_hot.*n from 0 to 256"),
        (dict(env=EMPTY, subgoal_learner_kwargs=dict(one_hot=[[2, 2], 0, 3])), "one_hot.*distinct codes"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        HhP("MlpPolicy", **kwargs)


def test_learners_with_a_view_read_the_cells_around_the_agent_and_save_and_load(tmp_path) -> None:
    """subgoal_learner_kwargs view=3: the learners' networks read the 3 x 3 cells around the agent of the 7 x 7 canvas
    (27 inputs), the meta-controller and the goal space the whole canvas; a saved model acts as the one it saved."""
    model = make_model(subgoal_learner_kwargs=dict(view=3))
    model.learn(600)
    assert len(model.subgoals) > 0 and model.subpolicies.n_updates.sum() > 0
    first = model.subpolicies.policy(0).q_net.q_net[0]
    assert first.in_features == 3 * 3 * 3
    assert model.subpolicies.replay.observations.shape[-3:] == model.primitive_observation_space.shape == (7, 7, 3)
    model.save(tmp_path / "viewed")
    loaded = HhP.load(tmp_path / "viewed")
    assert loaded.subgoal_learner_kwargs["view"] == 3
    sequence = _rollout_observations(model, seed=3)
    assert _predictions(loaded, sequence) == _predictions(model, sequence)


def test_one_hot_lists_the_codes_each_indicator_marks() -> None:
    """one_hot: a count n marks codes 0 to n - 1, a list the codes it names in its order, 0 or [] leaves a channel out;
    codes not listed read as all zeros; too many combinations of listed codes are refused with what to do."""
    space = spaces.Box(0, 10, (1, 5, 3), np.uint8)
    codes = OneHotCodes(space, [[2, 4, 5, 8], [], 3])
    assert codes.n_indicators == 7
    # a wall, a locked door (yellow), a key carried over an unlisted colour, a goal square, an empty cell
    cells = np.array([[[2, 5, 0], [4, 4, 2], [5, 1, 0], [8, 1, 0], [1, 0, 0]]], dtype=np.uint8)
    expected = np.array([[[1, 0, 0, 0, 1, 0, 0], [0, 1, 0, 0, 0, 0, 1], [0, 0, 1, 0, 1, 0, 0], [0, 0, 0, 1, 1, 0, 0],
                          [0, 0, 0, 0, 1, 0, 0]]], dtype=np.float32)
    encoded = codes.encode(cells)
    assert encoded.dtype == np.float32 and encoded.tolist() == expected.tolist()
    assert codes.encode(np.stack([cells, cells[:, ::-1]])).tolist() == [expected.tolist(), expected[:, ::-1].tolist()]
    with pytest.raises(ValueError, match="one_hot.*uint8"):
        OneHotCodes(spaces.Box(0, 1, (3, 3), np.float32), [2, 2, 2])
    with pytest.raises(ValueError, match="combine 4784128 ways.*list fewer codes"):
        OneHotCodes(space, [255, 255, 72])


def test_one_hot_learners_read_each_code_as_indicators_and_save_and_load(tmp_path) -> None:
    """subgoal_learner_kwargs one_hot=[11, 0, 3] with view=3: each of the 3 x 3 cells around the agent becomes 11 object
    and 3 state indicators (colour left out), 126 inputs; the learners' Q-values are SB3's network of the sub-goal
    (``policy(g)``) applied to cells encoded here by hand; a saved model acts as the one it saved."""
    model = make_model(subgoal_learner_kwargs=dict(view=3, one_hot=[11, 0, 3]))
    model.learn(600)
    assert len(model.subgoals) > 0 and model.subpolicies.n_updates.sum() > 0
    assert model.subpolicies.policy(0).q_net.q_net[0].in_features == 3 * 3 * (11 + 3)
    obs = observations()
    cells = obs[:, 2:5, 2:5]  # the 3 x 3 cells at the centre of the 7 x 7 canvas
    by_hand = np.zeros((*cells.shape[:3], 14), dtype=np.float32)
    for index in np.ndindex(*cells.shape[:3]):
        by_hand[index + (cells[index + (0,)],)] = 1.0  # the object id among the first 11
        by_hand[index + (11 + cells[index + (2,)],)] = 1.0  # the state among the last 3
    assert by_hand[..., :11].sum() == by_hand[..., 11:].sum() == cells.shape[0] * 9  # one of each in every cell
    for goal in range(len(model.subgoals)):
        with th.no_grad():
            expected = model.subpolicies.policy(goal).q_net(th.as_tensor(by_hand, device=model.device))
        got = model.subpolicies.q_values(np.full(len(obs), goal), obs)
        assert th.allclose(got, expected, atol=1e-5)
    model.save(tmp_path / "one_hot")
    loaded = HhP.load(tmp_path / "one_hot")
    assert loaded.subgoal_learner_kwargs["one_hot"] == [11, 0, 3]
    sequence = _rollout_observations(model, seed=3)
    assert _predictions(loaded, sequence) == _predictions(model, sequence)


def test_auto_learner_inputs_are_derived_from_the_env_and_save_and_load(tmp_path) -> None:
    """subgoal_learner_kwargs view, overview, one_hot "auto": on DoorKey-5x5 (a 7 x 7 canvas) the learners read its 5 x 5
    inner cells, no overview, the walls, doors, keys, goal squares, closed and locked doors its grids hold as
    indicators: 150 inputs; a saved model keeps "auto" and acts as the one it saved; a goal space that derives nothing
    refuses "auto", naming the options to give."""
    model = make_model(subgoal_learner_kwargs=dict(view="auto", overview="auto", one_hot="auto"))
    model.learn(600)
    learners = model.subpolicies
    assert learners.view == "inner" and learners._overview is None and learners._one_hot.n_indicators == 4 + 2
    assert learners.policy(0).q_net.q_net[0].in_features == 5 * 5 * 6
    model.save(tmp_path / "auto")
    loaded = HhP.load(tmp_path / "auto")
    assert loaded.subgoal_learner_kwargs["one_hot"] == "auto" and loaded.subpolicies._one_hot.n_indicators == 6
    sequence = _rollout_observations(model, seed=3)
    assert _predictions(loaded, sequence) == _predictions(model, sequence)

    class Underived(MiniGridGoalSpace):
        def learner_input(self, observation_space):
            return None

    with pytest.raises(ValueError, match="view, one_hot 'auto'.*Underived derives none: give them"):
        HhP("MlpPolicy", gym.make(DOORKEY), goal_space=Underived(), subgoal_learner_kwargs=dict(view="auto", one_hot="auto"))


def test_one_hot_learners_with_an_overview_read_the_view_and_the_blocks_and_save_and_load(tmp_path) -> None:
    """subgoal_learner_kwargs view=3, overview=3, one_hot=[11, 0, 3]: the learners read the 3 x 3 cells around the
    agent and the 3 x 3 blocks of the whole 7 x 7 canvas (each its most salient cell), 18 cells of 14 indicators; their
    Q-values are SB3's network of the sub-goal applied to those cells encoded here; a saved model acts as the one it
    saved."""
    model = make_model(subgoal_learner_kwargs=dict(view=3, overview=3, one_hot=[11, 0, 3]))
    model.learn(600)
    learners = model.subpolicies
    assert len(model.subgoals) > 0 and learners.n_updates.sum() > 0
    assert learners.replay.encoded_observations is not None  # the kept places (one per used channel of each cell)
    assert learners.replay.encoded_observations.shape[-1] == 18 * 2
    assert learners.policy(0).q_net.q_net[0].in_features == 18 * 14
    obs = observations()
    cells = np.concatenate([obs[:, 2:5, 2:5].reshape(len(obs), 9, 3), Overview(model.primitive_observation_space, 3)(obs)
                            .reshape(len(obs), 9, 3)], axis=1)
    by_hand = np.zeros((len(obs), 18, 14), dtype=np.float32)
    for index in np.ndindex(*cells.shape[:2]):
        by_hand[index + (cells[index + (0,)],)] = 1.0
        by_hand[index + (11 + cells[index + (2,)],)] = 1.0
    for goal in range(len(model.subgoals)):
        with th.no_grad():
            expected = learners.policy(goal).q_net(th.as_tensor(by_hand.reshape(len(obs), 1, 18, 14), device=model.device))
        assert th.allclose(learners.q_values(np.full(len(obs), goal), obs), expected, atol=1e-5)
    model.save(tmp_path / "overview")
    loaded = HhP.load(tmp_path / "overview")
    assert loaded.subgoal_learner_kwargs["overview"] == 3
    sequence = _rollout_observations(model, seed=3)
    assert _predictions(loaded, sequence) == _predictions(model, sequence)


def test_one_hot_places_kept_by_the_replay_train_as_the_dense_indicators_encoded_at_each_draw(tmp_path, monkeypatch) -> None:
    """With one_hot the shared replay keeps the places of each stored state's set indicators, written when the step is
    stored, and the learners' update reads them as sums of the first layer's columns instead of encoding every drawn
    state densely: the same parameters, to float rounding, as the dense update; not written into the replay's file,
    found again when it is loaded (rows a carried counterfactual changes: ``test_learners.py``)."""
    kwargs = dict(subgoal_learner_kwargs=dict(view=3, one_hot=[11, 0, 3], carry_relabel=0.5, train_shared=True))
    kept = make_model(**kwargs)
    replay = kept.subpolicies.replay
    assert replay.encoded_observations is not None and replay.encoded_observations.shape[-1] == 3 * 3 * 2
    kept.learn(600)
    with monkeypatch.context() as patch:
        patch.setattr(StackedDQN, "_encoded_replay", False)
        encoded_each_draw = make_model(**kwargs)
    assert encoded_each_draw.subpolicies.replay.encoded_observations is None
    encoded_each_draw.learn(600)
    assert kept.subpolicies.n_updates.sum() > 0
    assert kept.subpolicies.n_updates.tolist() == encoded_each_draw.subpolicies.n_updates.tolist()
    # compared in SB3's order, as saved (the kept places' learners keep each first layer as rows)
    th.testing.assert_close(kept.subpolicies.state_dict()["params"], encoded_each_draw.subpolicies.state_dict()["params"],
                            rtol=1e-4, atol=1e-6)
    assert not th.equal(kept.subpolicies.params, kept.subpolicies.target)  # the updates moved the networks
    size, one_hot = replay.size(), kept.subpolicies._one_hot
    for stored, encoded in ((replay.observations, replay.encoded_observations),
                            (replay.next_observations, replay.encoded_next_observations)):
        dense = one_hot.encode(stored[:size, :, 2:5, 2:5]).reshape(size, replay.n_envs, -1)  # the 3 x 3 view
        for row, places in zip(dense.reshape(-1, dense.shape[-1]), encoded[:size].reshape(-1, encoded.shape[-1])):
            set_ = np.flatnonzero(row).tolist()
            assert places.tolist() == set_ + [dense.shape[-1]] * (len(places) - len(set_))
    assert "encoded_observations" not in kept.subpolicies.replay_state()["replay"]["attributes"]
    kept.save(tmp_path / "model")
    kept.save_replay_buffer(tmp_path / "replay")
    loaded = HhP.load(tmp_path / "model")
    loaded.load_replay_buffer(tmp_path / "replay")
    np.testing.assert_array_equal(loaded.subpolicies.replay.encoded_next_observations[:size],
                                  replay.encoded_next_observations[:size])
    # the file holds SB3's order; loading lays the first layers out as rows again, bit for bit, Adam's moments too
    n = len(kept.subpolicies)
    for name in ("params", "target", "exp_avg", "exp_avg_sq"):
        th.testing.assert_close(getattr(loaded.subpolicies, name)[:n], getattr(kept.subpolicies, name)[:n], rtol=0, atol=0)
    obs = kept.subpolicies.replay.observations[:4, 0]
    th.testing.assert_close(loaded.subpolicies.q_values(np.arange(4) % n, obs), kept.subpolicies.q_values(np.arange(4) % n, obs))


def test_exploration_run_steps_reaches_the_learners_and_saves(tmp_path) -> None:
    """subgoal_learner_kwargs exploration_run_steps: the stacked learners' second exploration clock, kept by save/load."""
    model = make_model(subgoal_learner_kwargs=dict(exploration_run_steps=2_000))
    assert model.subpolicies.exploration_run_steps == 2_000
    model.save(tmp_path / "run_clock")
    assert HhP.load(tmp_path / "run_clock").subpolicies.exploration_run_steps == 2_000
    assert make_model().subpolicies.exploration_run_steps is None  # the default: own steps only


def test_a_target_range_reaches_the_learners_and_saves(tmp_path) -> None:
    model = make_model(subgoal_learner_kwargs=dict(target_range=[-1.0, 1.0]))
    assert model.subpolicies.target_range == (-1.0, 1.0)
    model.save(tmp_path / "clipped")
    assert HhP.load(tmp_path / "clipped").subpolicies.target_range == (-1.0, 1.0)
    assert make_model().subpolicies.target_range is None  # the default: unclipped
    with pytest.raises(ValueError, match="target_range.*low < high"):
        make_model(subgoal_learner_kwargs=dict(target_range=[1.0, 1.0]))


def test_carry_relabel_reaches_the_learners_replay_and_saves(tmp_path) -> None:
    """subgoal_learner_kwargs carry_relabel: the stacked learners' replay draws with the goal space's counterfactual;
    the heads learner (one batch for all) and values outside [0, 1] are refused before training."""
    model = make_model(subgoal_learner_kwargs=dict(carry_relabel=0.5))
    replay = model.subpolicies.replay
    assert replay.carry_relabel == 0.5 and replay.counterfactual == model.goal_space.carried_counterfactual
    model.learn(600)
    assert model.subpolicies.n_updates.sum() > 0
    model.save(tmp_path / "relabelled")
    assert HhP.load(tmp_path / "relabelled").subpolicies.replay.carry_relabel == 0.5
    with pytest.raises(ValueError, match="carry_relabel.*stacked"):
        make_model(subgoal_learner_kwargs=dict(carry_relabel=0.5, kind="heads"))
    with pytest.raises(ValueError, match=r"carry_relabel'\] must be in \[0, 1\]"):
        make_model(subgoal_learner_kwargs=dict(carry_relabel=-0.1))


def test_env_forms(trained: HhP) -> None:
    """An env id, a gym env and a DummyVecEnv of one (wrapped) env are accepted; more envs are not."""
    one = DummyVecEnv([lambda: wrap_env(gym.make(EMPTY))])
    for env in (EMPTY, gym.make(EMPTY), one):
        model = HhP("MlpPolicy", env, **tiny(predictor_kwargs=dict(n_masks=2)))
        assert model.primitive_observation_space.shape == (7, 7, 3)
    for wrapper in (VecNormalize, lambda venv: VecFrameStack(venv, 4)):
        with pytest.raises(ValueError, match="cannot train under Vec.*Remove it"):
            HhP("MlpPolicy", wrapper(DummyVecEnv([lambda: wrap_env(gym.make(EMPTY))] * 2)))
    with pytest.raises(ValueError, match="observation space"):
        trained.set_env(gym.make("MiniGrid-DoorKey-8x8-v0"))
    assert trained.options.venv.observation_space.shape == (7, 7, 3)  # left as it was


def test_cartpole_error_names_the_fix() -> None:
    with pytest.raises(ValueError) as info:
        HhP("MlpPolicy", gym.make("CartPole-v1"))
    assert "goal_space=" in str(info.value) and "MiniGrid" in str(info.value)


def test_load_refuses_corrupt_and_foreign_files(tmp_path) -> None:
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ValueError, match="not a saved HhP model"):
        HhP.load(corrupt)
    foreign = tmp_path / "dqn"
    DQN("MlpPolicy", "CartPole-v1", buffer_size=100, learning_starts=10).save(foreign)
    with pytest.raises(ValueError, match="not an HhP model.*HhP.save"):
        HhP.load(foreign)


@pytest.mark.parametrize("cut", [100, 5_000])
def test_load_reports_a_truncated_model_as_truncated(tmp_path, trained: HhP, cut: int) -> None:
    """A model whose file lost its end (an interrupted copy) is reported as truncated, not as a foreign file."""
    path = tmp_path / "whole.zip"
    trained.save(path)
    truncated = tmp_path / "truncated.zip"
    truncated.write_bytes(path.read_bytes()[:-cut])
    with pytest.raises(ValueError, match="truncated.*complete copy"):
        HhP.load(truncated)


def test_load_refuses_a_zip_whose_components_are_garbage(tmp_path, trained: HhP) -> None:
    path = tmp_path / "broken.zip"
    trained.save(path)
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    assert COMPONENTS_FILE in members
    members[COMPONENTS_FILE] = b"\x80\x04 definitely not a torch file"
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    with pytest.raises(ValueError, match="HhP"):
        HhP.load(path)


# ---------------------------------------------------------------------------- ablations


def test_without_a_budget_no_query_is_asked_and_the_reward_is_the_extrinsic_return() -> None:
    """The paper's "Cur" ablation: no question, no label, and eq. 3's reward is R_e alone."""
    model = make_model(EMPTY, query_budget=0)
    model.learn(600)
    assert model.query_selector.used == 0
    assert model.store.count_asked() == 0 and len(model.predictor) == 0
    replay = model.replay_buffer.sample(8)
    th.testing.assert_close(model._rewards(replay), replay.rewards)  # reward = R_e ("Cur")


def test_without_curiosity_no_intrinsic_reward() -> None:
    model = make_model(EMPTY, use_curiosity=False)
    assert model.rnd is None and model.options.rnd is None and model.subpolicies.replay.alpha == 0.0
    model.learn(600)
    intrinsic = model._last_trace.intrinsic + model.options.traces[0].intrinsic
    assert len(intrinsic) > 0 and all(r == 0.0 for r in intrinsic)
    assert model.num_timesteps >= 600


def run_option(model: HhP, goal: int, seed: Optional[int] = None, reset: bool = True) -> tuple[Any, list, EpisodeTrace]:
    """Run sub-goal ``goal`` on env 0 until its option ends: (the option's end, the episodes that ended, the trace
    of its primitive steps)."""
    options = model.options
    if reset:
        options.seed(seed)
        options.reset()
    options.start(np.array([0]), np.array([goal]))
    while True:
        trace = options.traces[0]
        ended, episodes = options.step()
        if ended:
            return ended[0], episodes, trace


def _last_rows(model: HhP, steps: int) -> np.ndarray:
    """Rows of the shared replay holding the last ``steps`` primitive steps (one env)."""
    replay = model.subpolicies.replay
    return (replay.pos - steps + np.arange(steps)) % replay.capacity


def test_shared_experience_is_relabelled_with_each_subgoals_eq5_reward() -> None:
    """Every primitive step is stored once, and relabelled for every sub-goal with its own eq. 5 reward when
    drawn (no curiosity here, so eq. 6 adds nothing): +1 where its key is reached, -1 where the episode
    terminated without reaching it, 0 otherwise."""
    model = make_model(EMPTY, use_curiosity=False)
    model.learn(600)
    goal_space, replay = model.goal_space, model.subpolicies.replay
    assert len(model.subgoals) >= 2
    model.options.seed(3)
    model.options.reset()
    size = replay.size()
    end, _, trace = run_option(model, 0, reset=False)
    steps, terminated = end.steps, end.terminated
    assert replay.size() == min(replay.capacity, size + steps)
    rows = _last_rows(model, steps)
    keys = trace.low_keys[-steps:]
    rewards, terminal, _ = replay.rewards(rows, np.zeros_like(rows), np.ones_like(rows))  # for sub-goal 1
    for offset in range(steps):
        reached = goal_space.achieved(keys[offset], model.subgoals[1].key)
        last = offset == steps - 1
        assert rewards[offset] == pytest.approx(1.0 if reached else (-1.0 if (terminated and last) else 0.0))
        assert bool(terminal[offset]) == (reached or (terminated and last))
    assert (replay.acting[rows, 0] == 0).all()  # sub-goal 0 acted: one-step transitions for sub-goal 1


@pytest.mark.parametrize("train_shared", [False, True])
def test_train_shared_gives_every_subpolicy_its_gradient_steps(train_shared: bool) -> None:
    """Without ``train_shared`` only the acting sub-goal counts a step as a learning tick; with it, every
    sub-goal does, and all due sub-goals update together at the train frequency."""
    kwargs = {**TINY.get("subpolicy_kwargs", {}), "train_freq": 2, "learning_starts": 1, "batch_size": 4}
    model = make_model(EMPTY, use_curiosity=False, subpolicy_kwargs=kwargs,
                       subgoal_learner_kwargs=dict(train_shared=train_shared, kind="stacked"))
    model.learn(600)
    learners = model.subpolicies
    assert len(model.subgoals) >= 2
    model.options.seed(3)
    model.options.reset()
    ticks, updates = learners.ticks.copy(), learners.n_updates.copy()
    steps = run_option(model, 0, reset=False)[0].steps
    for goal_id in range(len(learners)):
        if goal_id == 0 or train_shared:
            assert learners.ticks[goal_id] == ticks[goal_id] + steps
            assert learners.n_updates[goal_id] == updates[goal_id] + (ticks[goal_id] + steps) // 2 - ticks[goal_id] // 2
        else:
            assert (learners.ticks[goal_id], learners.n_updates[goal_id]) == (ticks[goal_id], updates[goal_id])


def test_relabelled_step_at_the_time_limit_is_a_timeout() -> None:
    """Where the episode is cut by its time limit, every sub-goal reads the step as a timeout: its n-step
    returns stop there instead of running on into the next episode, and the step is bootstrapped."""
    model = make_model(EMPTY, use_curiosity=False, subpolicy_kwargs={**TINY.get("subpolicy_kwargs", {}), "n_steps": 8})
    model.learn(600)
    replay = model.subpolicies.replay
    assert len(model.subgoals) >= 2 and replay.n_steps == 8
    model.options.venv.envs[0].unwrapped.max_steps = 2
    achieved, n_goals = model.goal_space.achieved, len(model.subgoals)
    found = None
    for seed in range(20):
        for acting in range(n_goals):
            end, _, trace = run_option(model, acting, seed=seed)
            others = [goal for goal in range(n_goals) if goal != acting
                      and not any(achieved(key, model.subgoals[goal].key) for key in trace.low_keys[-2:])]
            if end.truncated and not end.terminated and end.steps == 2 and others:
                found = others[0]
                break
        if found is not None:
            break
    else:
        pytest.fail("no episode was cut by the time limit")
    rows = _last_rows(model, 2)
    rewards, terminal, cut = replay.rewards(rows, np.zeros(2, dtype=int), np.full(2, found))
    assert cut[1] and not terminal[1] and rewards[1] == pytest.approx(0.0)
    assert not cut[0]


def test_active_subpolicy_stores_a_give_up_as_a_timeout_and_a_failed_episode_end_as_eq5_minus_one() -> None:
    """Eq. 5's -1 is for the env's own terminal function: a try cut by ``max_subgoal_steps`` (or by the
    env's time limit) is a timeout for the acting sub-goal (bootstrapped, pseudo-reward 0), while an
    episode that terminates without reaching the sub-goal is a terminal -1."""
    carrying_a_key = observations(EMPTY)[0].copy()
    center = carrying_a_key.shape[0] // 2
    carrying_a_key[center, center] = (OBJECT_TO_IDX["key"], 0, 0)  # "carrying a key": never reached in an empty room
    model = make_model(EMPTY, use_curiosity=False, max_subgoal_steps=3, discovery_kwargs=dict(strategy="none", subgoals=[carrying_a_key]))
    replay, options = model.subpolicies.replay, model.options
    before = replay.size()
    end, _, _ = run_option(model, 0, seed=0)
    assert not (end.terminated or end.truncated or end.achieved) and end.steps == 3
    assert replay.size() == before + 3
    rows = _last_rows(model, 3)
    rewards, terminal, cut = replay.rewards(rows, np.zeros(3, dtype=int), np.zeros(3, dtype=int))
    assert cut[-1] and not terminal[-1] and rewards[-1] == pytest.approx(0.0)
    assert not cut[-2] and not terminal[-2]
    # the give-up is the acting sub-goal's own time limit: not a cut for a sub-goal that did not act
    assert not replay.rewards(rows[-1:], np.zeros(1, dtype=int), np.ones(1, dtype=int))[2][0]
    # an episode that ends on the goal square without reaching the sub-goal: -1, terminal, not a timeout
    egocentric = options.venv.envs[0].env  # under SB3's Monitor
    base = egocentric.unwrapped
    for _ in range(20):
        options.seed(1)
        options.reset()
        base.agent_pos = (base.width - 3, base.height - 2)  # left of the goal square
        base.agent_dir = 0
        options.obs = egocentric.observation(None)[None]
        model.subpolicies.act = lambda goals, obs, deterministic=False: np.asarray([2])  # forward
        end, _, _ = run_option(model, 0, reset=False)
        if end.terminated:
            break
    assert end.terminated and end.extrinsic_return > 0 and not end.achieved
    rows = _last_rows(model, 1)
    rewards, terminal, cut = replay.rewards(rows, np.zeros(1, dtype=int), np.zeros(1, dtype=int))
    assert rewards[0] == pytest.approx(-1.0) and terminal[0] and not cut[0]


def test_with_curiosity_intrinsic_rewards_are_not_all_zero() -> None:
    model = make_model(EMPTY)
    model.learn(400)
    intrinsic = model._last_trace.intrinsic + model.options.traces[0].intrinsic
    assert len(intrinsic) > 0 and any(r > 0 for r in intrinsic)


def test_random_discovery() -> None:
    model = make_model(DOORKEY, discovery_kwargs=dict(min_visits=1, strategy="random"))
    assert model.discovery.strategy == "random"
    model.learn(1_000)
    sources = Counter(goal.source for goal in model.subgoals)
    assert sources["random"] == len(model.subgoals) >= 2  # the first sub-goal and the random discoveries
    assert sources["csd"] == 0


def test_no_discovery_uses_only_the_subgoals_handed_in() -> None:
    env = wrap_env(gym.make(DOORKEY))
    goal_space = MiniGridGoalSpace()
    given, keys = [], []
    obs, _ = env.reset(seed=0)
    for action in [0, 0, 0, 2, 1]:  # collect three observations with different keys
        if goal_space.key(obs) not in keys:
            given.append(obs)
            keys.append(goal_space.key(obs))
        obs, *_ = env.step(action)
    given, keys = given[:3], keys[:3]
    assert len(set(keys)) == len(given) >= 2
    model = make_model(DOORKEY, discovery_kwargs=dict(strategy="none", subgoals=given))
    assert [goal.key for goal in model.subgoals] == keys
    assert all(goal.source == "user" for goal in model.subgoals)
    model.learn(800)
    assert [goal.key for goal in model.subgoals] == keys
    for goal, obs in zip(model.subgoals, given):
        np.testing.assert_array_equal(goal.obs, obs)
    # a sub-goal that is reached is renewed at once: state (0, 3) in the state of sub-goal 0
    _, (goals, steps, *_) = model.predict(given[0][None], state=(np.array([0]), np.array([3])), deterministic=True)
    assert steps[0] == 1 and model.valid_actions[goals[0]]


def test_meta_controller_chooses_only_choosable_subgoals() -> None:
    """With mask_subgoals (the default) the meta-controller never picks a sub-goal that the goal space rules
    out in the state (already achieved; on MiniGrid, not a milestone), unless none is choosable there: in
    training (warm-up, exploration and greedy choices alike) and in predict."""
    model = make_model(DOORKEY, learning_starts=100, seed=2)  # a run whose sub-goals are often choosable
    assert model.mask_subgoals
    options, space = model.options, model.goal_space
    choices, start = [], options.start

    def checked_start(envs, goals):
        for env, goal in zip(envs, goals):
            key, present = space.key(options.obs[env]), space.present(options.obs[env])
            allowed = [space.choosable(key, subgoal.key, present) for subgoal in model.subgoals]
            choices.append((any(allowed), allowed[int(goal)]))
        return start(envs, goals)

    options.start = checked_start
    model.learn(3_000)
    assert len(model.subgoals) >= 3
    assert sum(any_allowed for any_allowed, _ in choices) > 10
    assert all(chosen for any_allowed, chosen in choices if any_allowed)
    goal_keys = [goal.key for goal in model.subgoals]
    states = observations()
    mask = model.action_mask(states)
    expected = np.array([[space.choosable(space.key(obs), key, space.present(obs)) for key in goal_keys] for obs in states])
    expected[~expected.any(axis=1)] = True  # a state where nothing is choosable keeps every sub-goal
    np.testing.assert_array_equal(mask[:, : len(goal_keys)], expected)
    assert not mask[:, len(goal_keys):].any()
    # a cache of the states' reach smaller than a batch of states partly in it: emptied, then filled again with
    # this batch's states, those it held before included
    assert len(states) > 4
    model.present_cache_size = 4
    model._present_cache.clear()
    np.testing.assert_array_equal(model.action_mask(states[:3]), mask[:3])
    for order in (slice(None), slice(None, None, -1)):
        np.testing.assert_array_equal(model.action_mask(states[order]), mask[order])
    for obs, allowed in zip(states, mask):
        for deterministic in (True, False):
            _, (goals, _, *_) = model.predict(obs, deterministic=deterministic)
            assert allowed[goals[0]]
    unmasked = make_model(DOORKEY, meta_kwargs=dict(mask_subgoals=False))
    unmasked.learn(300)
    assert unmasked.action_mask(states) is unmasked.valid_actions


def test_predictor_reads_goal_space_features_or_observations() -> None:
    """predictor_input: "auto" (features when the goal space has them), "observation", or "features" (an error
    that names the fix when the goal space has none)."""
    states = observations()
    featured = make_model(DOORKEY)
    assert featured.predictor.observation_space.shape == featured.goal_space.features(states).shape[1:]
    np.testing.assert_array_equal(featured.predictor_inputs(states), featured.goal_space.features(states))
    raw = make_model(DOORKEY, predictor_kwargs=dict(input="observation"))
    assert raw.predictor.observation_space == raw.primitive_observation_space
    np.testing.assert_array_equal(raw.predictor_inputs(states), states)

    class NoFeatures(MiniGridGoalSpace):
        def features(self, obs):
            return None

    with pytest.raises(ValueError, match=r"use predictor_kwargs\['input'\]='observation'"):
        make_model(DOORKEY, goal_space=NoFeatures(), predictor_kwargs=dict(input="features"))
    with pytest.raises(ValueError, match=r"predictor_kwargs\['input'\] must be one of"):
        make_model(DOORKEY, predictor_kwargs=dict(input="pixels"))


def test_meta_controller_reads_goal_space_features_or_observations() -> None:
    """meta_input "auto" (the default) or "features": the Q-network reads the goal space's features, so two layouts
    with the same description get the same Q-values; "observation": SB3's flattened observation; a clear error
    where features cannot be had."""
    from stable_baselines3.common.torch_layers import FlattenExtractor

    from sb3_hhp.hhp.policies import GoalSpaceFeatures

    assert isinstance(make_model(DOORKEY, meta_kwargs=dict(input="features")).q_net.features_extractor, GoalSpaceFeatures)
    model = make_model(DOORKEY, meta_kwargs=dict(input="auto"))
    assert isinstance(model.q_net.features_extractor, GoalSpaceFeatures)
    states = observations(seeds=tuple(range(40)))
    features = model.goal_space.features(states)
    with th.no_grad():
        q_values = model.q_net(model.policy.obs_to_tensor(states)[0]).cpu().numpy()
    same = [(i, j) for i in range(len(states)) for j in range(i) if (features[i] == features[j]).all() and (states[i] != states[j]).any()]
    assert same, "no two layouts with the same description among the first states"
    for i, j in same:
        np.testing.assert_allclose(q_values[i], q_values[j])
    assert isinstance(make_model(DOORKEY).q_net.features_extractor, GoalSpaceFeatures)
    assert isinstance(make_model(DOORKEY, meta_kwargs=dict(input="observation")).q_net.features_extractor, FlattenExtractor)

    class NoFeatures(MiniGridGoalSpace):
        def features(self, obs):
            return None

    with pytest.raises(ValueError, match=r"use meta_kwargs\['input'\]='observation'"):
        make_model(DOORKEY, goal_space=NoFeatures(), predictor_kwargs=dict(input="observation"), meta_kwargs=dict(input="features"))
    with pytest.raises(ValueError, match="features_extractor_class"):
        make_model(DOORKEY, policy_kwargs=dict(features_extractor_class=FlattenExtractor), meta_kwargs=dict(input="features"))
    with pytest.raises(ValueError, match=r"meta_kwargs\['input'\] must be one of"):
        make_model(DOORKEY, meta_kwargs=dict(input="pixels"))


# ---------------------------------------------------------------------------- resume


def test_load_from_a_moved_run_folder_names_the_store_to_pass(tmp_path) -> None:
    """A model saved beside its preference store, the folder then moved: loading it as saved is refused with what to
    pass (nothing is created at the old place); loading it with the store's new path reads the labels there."""
    run = tmp_path / "run"
    run.mkdir()
    model = make_model(DOORKEY, preference_db=str(run / "prefs.sqlite"), subgoal_learner_kwargs=dict(kind="heads"))
    model.learn(1_500)
    asked = model.store.count_asked()
    assert asked > 0
    model.save(run / "hhp")
    model.store.close()
    moved = run.rename(tmp_path / "moved")
    with pytest.raises(ValueError, match=r"its folder .*run' does not exist.*preference_db='RUN/preferences.sqlite'"):
        HhP.load(moved / "hhp", env=gym.make(DOORKEY))
    assert not run.exists()
    loaded = HhP.load(moved / "hhp", env=gym.make(DOORKEY), preference_db=str(moved / "prefs.sqlite"))
    assert loaded.store.count_asked() == asked == loaded.query_selector.used
    with pytest.raises(ValueError, match="does not exist"):
        make_model(DOORKEY, preference_db=str(tmp_path / "no such folder" / "prefs.sqlite"))


@pytest.mark.parametrize("budget, first_steps", [(10, 3_000), (2_000, 1_000)])
def test_resume_with_a_preference_database(tmp_path, budget: int, first_steps: int) -> None:
    """Budget 10 is spent before the save (the resumed run must ask nothing more); budget 2000 is not
    (the resumed run asks more, counting what was asked before the save). t_qry = 0: every tuple qualifies, and
    without the sub-goal mask every state has a second choice to ask about."""
    db = str(tmp_path / "prefs.sqlite")
    predictor_kwargs = dict(hidden_dim=64, buffer_size=budget + 100)  # room to see a label added twice
    model = make_model(DOORKEY, preference_db=db, query_budget=budget, predictor_kwargs=predictor_kwargs,
                       subgoal_learner_kwargs=dict(kind="heads"), meta_kwargs=dict(mask_subgoals=False))  # heads: more sub-goals found in these few steps
    model.learn(first_steps)
    used_before = model.query_selector.used
    assert 0 < used_before <= budget
    assert used_before == budget if budget == 10 else used_before < budget
    assert model.store.count_asked() == used_before
    model.save(tmp_path / "hhp")
    model.store.close()

    loaded = HhP.load(tmp_path / "hhp", env=gym.make(DOORKEY), preference_db=db)
    assert loaded.store.count_asked() == used_before == loaded.query_selector.used
    asked_before = loaded.store.asked_ids()
    loaded.learn(1_500, reset_num_timesteps=False)  # several episodes: room for a question not asked before
    selector, store = loaded.query_selector, loaded.store
    assert selector.used <= budget
    assert store.count_asked() == selector.used  # every question asked is counted once, none asked twice
    assert asked_before <= store.asked_ids()
    if budget > used_before:
        assert selector.used > used_before  # the resumed run went on asking
    else:
        assert store.asked_ids() == asked_before
    answers = [answer for _, _, answer in store.answers_since(0)]
    assert len({answer.query_id for answer in answers}) == len(answers) == store.count_asked()
    labelled = sum(answer.label != Label.INCOMPARABLE for answer in answers)
    assert len(loaded.predictor) == labelled  # every answered label is in the predictor, once
    assert loaded.consumed_query_ids == {answer.query_id for answer in answers}
    # no question was asked twice, before or after the resume: (the state as the predictor reads it, the unordered
    # pair of sub-goals) is different for every question in the store
    questions = [store.get_query(query_id) for query_id in store.asked_ids()]
    asked = [(loaded.predictor_inputs(np.asarray(query.state)[None])[0].tobytes(),
              frozenset({loaded.subgoals[query.goal1].key, loaded.subgoals[query.goal2].key})) for query in questions]
    assert len(set(asked)) == len(asked)
    assert all(query.info.get("signature") for query in questions)


def test_stored_questions_show_the_room_drawn_from_facts_without_a_render_per_choice(tmp_path, monkeypatch) -> None:
    """MiniGrid draws a question's state from the choice's privileged facts: a run that keeps its questions renders
    nothing at its sub-goal choices (a render cost more than the rest of a step), and each stored question still
    carries the room as the labeling page draws it."""
    from sb3_hhp.goals.minigrid import MiniGridGoalSpace

    renders = []
    monkeypatch.setattr(MiniGridGoalSpace, "render", lambda self, env: renders.append(1))
    model = make_model(DOORKEY, preference_db=str(tmp_path / "prefs.sqlite"),
                       subgoal_learner_kwargs=dict(kind="heads"), meta_kwargs=dict(mask_subgoals=False))
    assert model.record_images is False
    model.learn(2_000)
    questions = [model.store.get_query(query_id) for query_id in model.store.asked_ids()]
    assert questions and renders == []
    for query in questions:
        drawn = model.goal_space.image_in_state(query.info["state"])
        assert drawn is not None and np.array_equal(query.state_image, drawn)
    # a goal space that cannot draw from facts renders at every choice for a person, not for a script
    monkeypatch.setattr(MiniGridGoalSpace, "draws_from_facts", False)
    assert make_model(DOORKEY, preference_db=str(tmp_path / "other.sqlite")).record_images is False
    assert make_model(DOORKEY, oracle="terminal").record_images is True


def test_the_labeling_pages_gallery_is_written_into_the_preference_file(tmp_path) -> None:
    db = str(tmp_path / "prefs.sqlite")
    model = make_model(DOORKEY, preference_db=db, subgoal_learner_kwargs=dict(kind="heads"))  # heads: more sub-goals in these few steps
    model.gallery_every = 1  # after every episode
    model.learn(600)
    with PreferenceStore(db, create=False) as other:  # as the labeling server reads it
        gallery = SubgoalTable(other).records(with_images=False)
    assert len(gallery) == len(model.subgoals) >= 2  # no sub-goal is found between an episode's end and learn's
    assert [record["id"] for record in gallery] == list(range(len(model.subgoals)))
    assert [record["name"] for record in gallery] == [model.goal_space.describe(goal.key) for goal in model.subgoals]


def test_grouped_settings_survive_a_save_and_reach_their_components(tmp_path) -> None:
    """Each ``*_kwargs`` key reaches its component, and a saved model loads with the same settings."""
    model = HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0"), seed=0, query_budget=5,
                query_kwargs=dict(threshold=0.1, mode="fixed"), predictor_kwargs=dict(n_masks=7, dropout=0.2),
                discovery_kwargs=dict(similarity_threshold=0.3, min_visits=3),
                subgoal_learner_kwargs=dict(max_updates=5, exploration_steps=123),
                meta_kwargs=dict(n_opt=3, target_update_interval=77, capacity=4, break_cycles=False))
    assert (model.query_selector.threshold, model.query_selector.mode) == (0.1, "fixed")
    assert (model.predictor.n_masks, model.predictor.dropout) == (7, 0.2)
    assert (model.discovery.similarity_threshold, model.discovery.min_visits, model.discovery.percentile) == (0.3, 3, 5.0)
    assert (model.subpolicies.max_updates, model.subpolicies.exploration_steps) == (5, 123)
    assert (model.gradient_steps, model.target_update_interval, model.action_space.n, model.break_cycles) == (3, 77, 4, False)
    model.learn(300)
    model.save(tmp_path / "grouped")
    again = HhP.load(tmp_path / "grouped")
    assert (again.predictor.n_masks, again.subpolicies.max_updates, again.query_selector.threshold) == (7, 5, 0.1)
    assert (again.gradient_steps, again.target_update_interval, again.break_cycles) == (3, 77, False)


def test_the_constructor_keeps_to_thirty_named_arguments() -> None:
    """SB3's DQN takes about 25; HhP's other settings are grouped per component (sb3_hhp.hhp.arguments)."""
    import inspect

    names = [name for name in inspect.signature(HhP.__init__).parameters if name != "self"]
    assert len(names) <= 30, names


def test_discovery_percentile_of_reaches_csd() -> None:
    model = HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0"), seed=0, discovery_kwargs={"percentile_of": "new"})
    assert model.discovery.percentile_of == "new"
    assert HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0")).discovery.percentile_of == "visited"
    with pytest.raises(ValueError, match="percentile_of must be 'visited' or 'new'"):
        HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0"), discovery_kwargs={"percentile_of": "states"})


def test_predictor_min_updates_reaches_the_predictor() -> None:
    model = HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0"), seed=0, predictor_kwargs={"min_updates": 30})
    assert model.predictor.min_updates == 30 and HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0")).predictor.min_updates == 0


def test_misspelt_grouped_arguments_are_refused_with_the_keys_there_are() -> None:
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        HhP("MlpPolicy", gym.make(DOORKEY), not_an_argument=1)
    with pytest.raises(ValueError, match="discovery_kwargs has no key 'b_similarity'; its keys are before_success, min_visits"):
        HhP("MlpPolicy", gym.make(DOORKEY), discovery_kwargs=dict(b_similarity=0.2))
    with pytest.raises(ValueError, match="predictor_kwargs has no key 'masks'"):
        HhP("MlpPolicy", gym.make(DOORKEY), predictor_kwargs=dict(masks=3))
    with pytest.raises(ValueError, match="needs share_experience=True"):
        HhP("MlpPolicy", gym.make(DOORKEY), subgoal_learner_kwargs=dict(train_shared=True, share_experience=False))
    with pytest.raises(ValueError, match=r"query_kwargs\['threshold'\] \(t_qry\) must be >= 0"):
        HhP("MlpPolicy", gym.make(DOORKEY), query_kwargs=dict(threshold=-1))


def test_resume_feeds_labels_answered_after_the_save(tmp_path) -> None:
    """Answers that reach the store while the trainer is down (e.g. a person labelling later) are learnt on resume."""
    from sb3_hhp.oracles.base import Query

    db = str(tmp_path / "prefs.sqlite")
    model = make_model(DOORKEY, preference_db=db, predictor_kwargs=dict(hidden_dim=64, buffer_size=100),
                       subgoal_learner_kwargs=dict(kind="heads"))  # heads: more sub-goals found in these few steps
    model.learn(600)
    model.save(tmp_path / "hhp")
    n_labels = len(model.predictor)
    obs = observations()
    late = Query(state=obs[0], goal1=0, goal2=1, goal1_obs=model.subgoals[0].obs, goal2_obs=model.subgoals[1].obs)
    model.store.add_query(late)
    model.store.add_answer(late.query_id, Label.FIRST, "person")
    model.store.close()

    loaded = HhP.load(tmp_path / "hhp", env=gym.make(DOORKEY), preference_db=db)
    loaded.learn(100, reset_num_timesteps=False)
    assert late.query_id in loaded.consumed_query_ids
    assert len(loaded.predictor) >= n_labels + 1
    assert loaded.query_selector.used <= loaded.query_selector.budget


# ---------------------------------------------------------------------------- growing sub-goal set


def test_subgoal_set_grows_past_the_initial_capacity() -> None:
    model = make_model(EMPTY, meta_kwargs=dict(capacity=2))
    obs = observations(EMPTY)
    env = wrap_env(gym.make(EMPTY))
    env.reset(seed=0)
    states = [obs[0]] + [env.step(action)[0] for action in (0, 2, 1)]
    goal_space = model.goal_space
    model.add_subgoal(goal_space.key(states[0]), states[0], None)
    model.add_subgoal(goal_space.key(states[1]), states[1], None)
    assert int(model.action_space.n) == 2 and model.valid_actions.tolist() == [True, True]
    with th.no_grad():
        q_before = model.q_net(model.policy.obs_to_tensor(obs)[0]).cpu().numpy()

    model.add_subgoal(goal_space.key(states[2]), states[2], None)
    assert int(model.action_space.n) == 4
    assert int(model.env.action_space.n) == 4
    assert model.valid_actions.tolist() == [True, True, True, False]
    with th.no_grad():
        q_after = model.q_net(model.policy.obs_to_tensor(obs)[0]).cpu().numpy()
        q_target = model.q_net_target(model.policy.obs_to_tensor(obs)[0]).cpu().numpy()
    np.testing.assert_allclose(q_after[:, :2], q_before, rtol=1e-6)
    np.testing.assert_allclose(q_target[:, :2], q_before, rtol=1e-6)
    assert len(model.subpolicies) == 3
    # the masked slot is never chosen
    _, (goals, _, *_) = model.predict(obs, deterministic=True)
    assert (goals < 3).all()

    model.learn(600)
    assert model.num_timesteps >= 600
    n = len(model.subgoals)
    assert n >= 3 and int(model.action_space.n) >= n
    assert model.valid_actions.tolist() == [i < n for i in range(int(model.action_space.n))]
    chosen = model.replay_buffer.actions[: model.replay_buffer.size()].flatten()
    assert (chosen < n).all()


def test_same_seed_same_run() -> None:
    """Two runs with the same seed find the same sub-goals and ask the same number of questions."""
    runs = []
    for _ in range(2):
        model = make_model(DOORKEY, query_budget=200)
        model.learn(800)
        runs.append((model.num_timesteps, [goal.key for goal in model.subgoals], model.query_selector.used))
    assert runs[0] == runs[1]


def test_meta_learning_starts_within_the_first_episode() -> None:
    """learning_starts (primitive steps) shorter than the first, random episode, whose steps fill no meta
    buffer: the meta-controller must wait for a batch rather than sample an empty buffer."""
    model = make_model(DOORKEY, learning_starts=50)
    model.learn(600)
    assert model.num_timesteps >= 600
    assert model.replay_buffer.size() > 0


def test_cnn_policy_reads_minigrid_grids_with_a_small_cnn() -> None:
    """SB3's NatureCNN refuses MiniGrid's symbolic grids; CnnPolicy gives the meta-controller and the sub-goal
    learners GridCNN instead, and trains end to end."""
    from sb3_hhp.hhp.policies import GridCNN

    model = HhP("CnnPolicy", gym.make(DOORKEY), **{**TINY, "seed": 0, "query_budget": 5})
    assert isinstance(model.q_net.features_extractor, GridCNN)
    model.learn(400)
    assert model.num_timesteps >= 400 and len(model.subgoals) >= 1
    assert isinstance(model.subpolicies.policy(0).q_net.features_extractor, GridCNN)
    obs = observations()
    features = GridCNN(model.primitive_observation_space)(th.as_tensor(obs))
    assert features.shape == (len(obs), 128)


def test_the_facts_questions_carry_are_recorded_only_while_questions_can_be_asked() -> None:
    model = make_model(query_budget=2)
    model.learn(2_000)
    assert model.query_selector.remaining == 0
    assert model.options.record_privileged is False
    model.learn(300, reset_num_timesteps=False)
    assert model._last_trace.high_privileged and all(facts is None for facts in model._last_trace.high_privileged)
    asked = model.query_selector.used
    model.after_episode(model._last_trace)  # an episode without facts asks nothing
    assert model.query_selector.used == asked
    with_budget = make_model(query_budget=1_000)
    with_budget.learn(600)
    assert with_budget.options.record_privileged and all("grid" in facts for facts in with_budget._last_trace.high_privileged)


# ---------------------------------------------------------------------------- discount per primitive step


@pytest.mark.parametrize("every, updates", [(None, [4, 12, 4, 8]), (10, [2, 1, 4])])
def test_steps_per_update_caps_the_meta_controllers_updates(monkeypatch, every: Optional[int], updates: list) -> None:
    """N_opt updates after each episode (Algorithm 1); with meta_kwargs steps_per_update K, no more than a rollout's
    primitive steps over K, what it leaves unused kept for the next rollout up to that rollout's N_opt per episode."""
    model = make_model(EMPTY, batch_size=8, meta_kwargs=dict(n_opt=4, steps_per_update=every))
    calls: list = []
    monkeypatch.setattr(DoubleDQN, "train", lambda self, gradient_steps, batch_size=100: calls.append(gradient_steps))
    monkeypatch.setattr(model.replay_buffer, "size", lambda: 100)
    # (episodes, primitive steps) of four rollouts: allowance 2.5 -> 2 done; 0.5 + 1.2 -> 1; 0.7 + 10 capped at 4 -> 4;
    # 0 + 0.3 -> none
    for episodes, steps in [(1, 25), (3, 12), (1, 100), (2, 3)]:
        model._rollout_episodes, model._rollout_steps = episodes, steps
        model.train(model.gradient_steps, model.batch_size)
    assert calls == updates


def test_choices_per_update_gives_episodes_of_many_choices_more_updates(monkeypatch) -> None:
    """With meta_kwargs choices_per_update C, at least one update per C choices stored in the rollout, the fraction
    kept for the next; N_opt per episode where that is more."""
    model = make_model(EMPTY, batch_size=8, meta_kwargs=dict(n_opt=4, choices_per_update=4))
    calls: list = []
    monkeypatch.setattr(DoubleDQN, "train", lambda self, gradient_steps, batch_size=100: calls.append(gradient_steps))
    monkeypatch.setattr(model.replay_buffer, "size", lambda: 100)
    # (episodes, choices): 10 / 4 = 2.5 -> 2 < 4; 0.5 + 60 / 4 -> 15 > 4; 0.5 + 6 / 4 = 2 < 8
    for episodes, choices in [(1, 10), (1, 60), (2, 6)]:
        model._rollout_episodes, model._rollout_steps, model._rollout_choices = episodes, 10 * choices, choices
        model.train(model.gradient_steps, model.batch_size)
    assert calls == [4, 15, 8]
    with pytest.raises(ValueError, match=r"meta_kwargs\['choices_per_update'\] must be an integer >= 1"):
        make_model(EMPTY, meta_kwargs=dict(choices_per_update=0))
    monkeypatch.undo()
    counted = make_model(EMPTY, batch_size=8, learning_starts=0, meta_kwargs=dict(n_opt=1, choices_per_update=1))
    counted.learn(600)
    assert counted._n_updates >= counted.replay_buffer.size() - 8  # one update per choice once a batch was stored


def test_steps_per_update_bounds_a_runs_meta_updates() -> None:
    """Over a run, the meta-controller's updates stay within its primitive steps over K (after its buffer held a
    batch), where N_opt per episode does more on a room solved in a few steps."""
    counts = []
    for every in (None, 16):
        model = make_model(EMPTY, batch_size=8, learning_starts=0, meta_kwargs=dict(n_opt=4, steps_per_update=every))
        model.learn(1_500)
        counts.append(model._n_updates)
        if every is not None:
            assert 0 < model._n_updates <= 1_500 / every
    assert counts[1] < counts[0]


def test_with_discount_steps_an_option_is_discounted_by_its_primitive_steps(tmp_path) -> None:
    """meta_kwargs discount="steps": R_e = sum_i gamma^i r_i over the option's steps and the bootstrap gamma^k (the
    semi-MDP's); "choice" (the default) keeps the plain sum and gamma per choice."""
    gamma = 0.9
    model = make_model(gamma=gamma, meta_kwargs=dict(discount="steps"))
    model.learn(1_500)
    runner, buffer = model.options, model.replay_buffer
    assert runner.return_discount == gamma and make_model().options.return_discount is None
    # the runner's return: each of an option's rewards weighs gamma^i, i its step in the option
    obs = runner.reset()
    here = model.goal_space.key(obs[0])
    far = next(g for g, key in enumerate(model.subgoal_set.keys) if not model.goal_space.achieved(here, key))
    runner.start(np.array([0]), np.array([far]))
    rewards = iter([0.5, 1.0, 2.0])
    step = runner.venv.step

    def rewarded(actions: np.ndarray) -> Any:
        obs, _, dones, infos = step(actions)
        return obs, np.array([next(rewards, 0.0)], dtype=np.float32), dones, infos

    runner.venv.step = rewarded
    taken = 0
    while taken < 3 and runner.goals[0] >= 0:  # the option's steps, until it ends (its return stays until the next)
        runner.step()
        taken += 1
    assert taken >= 2  # a weight below 1 is tested
    assert runner.option_returns[0] == pytest.approx(sum(gamma**i * r for i, r in enumerate([0.5, 1.0, 2.0][:taken])))
    runner.venv.step = step
    # the bootstrap: gamma^k of the stored choice's k primitive steps
    size = buffer.size()
    steps = model._choice_steps[:size]
    assert steps.min() >= 1 and steps.max() > 1  # options of different lengths were stored
    batch = buffer.sample(64)
    rows = np.asarray(batch.indices) // buffer.n_envs
    np.testing.assert_allclose(model._discounts(batch).cpu().numpy().ravel(), gamma ** steps[rows].astype(np.float64),
                               rtol=1e-6)
    assert make_model(gamma=gamma)._discounts(batch) == gamma  # per choice
    # kept with the replay
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "replay")
    loaded = HhP.load(tmp_path / "model")
    assert loaded.meta_discount == "steps"
    loaded.load_replay_buffer(tmp_path / "replay")
    np.testing.assert_array_equal(loaded._choice_steps[:size], steps)


def test_an_unknown_discount_is_refused() -> None:
    with pytest.raises(ValueError, match="discount.*'choice', 'steps'"):
        make_model(meta_kwargs=dict(discount="primitive"))


def test_per_step_snapshots_are_of_each_steps_own_episode() -> None:
    """A goal space with ``facts_per_step`` gets a snapshot of every step's state, in order; an episode's last state is
    gone when its step returns (the env was reset), so its step has none rather than the next episode's first state."""

    class Stepwise(MiniGridGoalSpace):
        facts_per_step = True

        def snapshot(self, env):
            return {**super().snapshot(env), "step": int(env.unwrapped.step_count)}

    model = HhP("MlpPolicy", gym.make(EMPTY, max_steps=20), goal_space=Stepwise(), **tiny(seed=0, query_budget=10))
    traces = []
    discover = model.discover_subgoals
    model.discover_subgoals = lambda trace: (traces.append(trace), discover(trace))[1]
    model.learn(200)
    assert len(traces) >= 3
    for trace in traces:
        steps = len(trace.low_obs)
        assert len(trace.low_privileged) == steps and trace.low_privileged[-1] is None
        assert [snapshot["step"] for snapshot in trace.low_privileged[:-1]] == list(range(1, steps))
