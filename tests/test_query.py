"""Query selection (Algorithm 1, line 26): threshold, second choice g2, budget, adaptive pacing."""

import math

import numpy as np
import pytest

from sb3_hhp.preferences.query import QuerySelector


def test_only_tuples_above_the_threshold_are_asked():
    selector = QuerySelector(budget=10, threshold=0.26)
    confidences = np.array([0.1, 0.3, 0.26, 0.5, 0.25])
    q_values = np.tile([1.0, 2.0, 3.0], (5, 1))
    asked = selector.select(confidences, np.zeros(5, dtype=int), q_values)
    assert [i for i, _ in asked] == [1, 3]  # c > t_qry, strictly
    assert selector.used == 2 and selector.remaining == 8


def test_second_goal_is_the_meta_controllers_second_choice():
    selector = QuerySelector(budget=10, threshold=0.0)
    q_values = np.array(
        [
            [5.0, 1.0, 3.0, 2.0],  # g = 0 is the argmax: g2 = 2, the runner-up
            [5.0, 1.0, 3.0, 2.0],  # g = 1 was exploratory: g2 = 0, the argmax
            [-np.inf, 1.0, -np.inf, 0.5],  # invalid sub-goals never come back: g2 = 3
            [-np.inf, 4.0, -np.inf, -np.inf],  # no other valid sub-goal: skipped
            [np.nan, 2.0, 7.0, 7.0],  # NaN is invalid; a tie goes to the lower id
        ]
    )
    goals = np.array([0, 1, 1, 1, 1])
    asked = selector.select(np.ones(5), goals, q_values)
    assert asked == [(0, 2), (1, 0), (2, 3), (4, 2)]
    assert selector.used == 4  # the skipped tuple costs nothing


def test_seconds_are_the_sub_goals_select_compares_with():
    """``seconds`` (what a "pair" reading measures the spread of the answer on) names the g2 that ``select`` asks
    with, -1 where a tuple has none."""
    q_values = np.array([[5.0, 1.0, 3.0, 2.0], [5.0, 1.0, 3.0, 2.0], [-np.inf, 4.0, -np.inf, -np.inf]])
    goals = np.array([0, 1, 1])
    exclude = np.zeros(q_values.shape, dtype=bool)
    exclude[0, 2] = True  # asked before: the next best
    selector = QuerySelector(budget=10, threshold=0.0, reading="pair")
    seconds = selector.seconds(goals, q_values, exclude=exclude)
    assert seconds.tolist() == [3, 0, -1]
    asked = selector.select(np.ones(3), goals, q_values, exclude=exclude)
    assert asked == [(0, 3), (1, 0)]


def test_an_unknown_reading_is_refused():
    with pytest.raises(ValueError, match="reading must be one of"):
        QuerySelector(budget=10, reading="answer")


def test_budget_zero_asks_nothing():
    for mode in ("fixed", "adaptive"):
        selector = QuerySelector(budget=0, threshold=0.0, mode=mode, total_timesteps=10)
        assert selector.select(np.ones(4), np.zeros(4, dtype=int), np.ones((4, 3)), num_timesteps=10) == []
        assert selector.used == 0 and selector.remaining == 0


def test_budget_is_never_exceeded_and_the_least_confident_are_kept():
    rng = np.random.default_rng(0)
    selector = QuerySelector(budget=40, threshold=0.3)
    total = 0
    for _ in range(200):
        n, n_goals = int(rng.integers(0, 12)), int(rng.integers(1, 6))
        confidences = rng.uniform(0.0, 1.0, size=n)
        goals = rng.integers(0, n_goals, size=n)
        q_values = rng.normal(size=(n, n_goals))
        q_values[rng.uniform(size=(n, n_goals)) < 0.3] = -np.inf
        remaining_before = selector.remaining
        asked = selector.select(confidences, goals, q_values)
        total += len(asked)
        assert len(asked) <= remaining_before
        assert selector.used == total <= 40 and selector.remaining == 40 - total

        indices = [i for i, _ in asked]
        assert indices == sorted(set(indices))
        for i, g2 in asked:
            assert confidences[i] > 0.3
            others = np.delete(q_values[i], goals[i])
            assert g2 != goals[i] and np.isfinite(q_values[i, g2]) and q_values[i, g2] == others.max()
        # every askable tuple above the threshold left out is at most as unsure as every tuple asked
        askable = [
            i
            for i in range(n)
            if confidences[i] > 0.3 and np.isfinite(np.delete(q_values[i], goals[i])).any() and i not in indices
        ]
        if askable and asked:
            assert len(asked) == remaining_before
            assert confidences[askable].max() <= confidences[indices].min()
    assert selector.used == 40  # enough qualifying tuples to spend it all


def test_capped_selection_keeps_the_highest_confidences():
    selector = QuerySelector(budget=2, threshold=0.1)
    confidences = np.array([0.5, 0.9, 0.2, 0.7])
    asked = selector.select(confidences, np.zeros(4, dtype=int), np.tile([0.0, 1.0], (4, 1)))
    assert asked == [(1, 1), (3, 1)]
    assert selector.select(confidences, np.zeros(4, dtype=int), np.tile([0.0, 1.0], (4, 1))) == []


@pytest.mark.parametrize("drift", [False, True])
def test_adaptive_mode_paces_the_budget(drift):
    rng = np.random.default_rng(1)
    episodes, steps_per_episode, budget = 100, 500, 60
    # a window of a few episodes' tuples, so that the quantile can follow drifting confidences
    window = 200 if drift else 2_000
    selector = QuerySelector(budget, mode="adaptive", total_timesteps=episodes * steps_per_episode, quantile_window=window)
    thresholds = []
    for episode in range(1, episodes + 1):
        n = int(rng.integers(5, 25))
        confidences = rng.uniform(0.0, 1.0, size=n)
        if drift:  # the predictor grows surer as it learns: confidences shrink tenfold over training
            confidences *= 1.0 - 0.9 * episode / episodes
        num_timesteps = episode * steps_per_episode
        selector.select(confidences, rng.integers(0, 4, size=n), rng.normal(size=(n, 4)), num_timesteps)
        allowance = math.floor(budget * episode / episodes)
        assert selector.used <= allowance  # never ahead of the pace
        assert allowance - selector.used <= (6 if drift else 3)  # and never far behind
        thresholds.append(selector.current_threshold)
        if episode == episodes // 2:
            assert abs(selector.used - budget / 2) <= 4
    assert selector.used == budget  # the last call spends what the pacing left over
    finite = [t for t in thresholds if np.isfinite(t)]
    assert len(finite) > 10
    if drift:  # the threshold follows the confidences down
        assert np.mean(finite[-10:]) < np.mean(finite[:10])


def test_adaptive_threshold_is_the_window_quantile():
    # quota 2 of 4 askable tuples: the threshold is the 1 - 2/4 quantile of the window (4 old + 4 new values)
    selector = QuerySelector(budget=100, mode="adaptive", total_timesteps=100, quantile_window=8)
    q_values = np.tile([0.0, 1.0], (4, 1))
    goals = np.zeros(4, dtype=int)
    assert selector.select(np.array([0.1, 0.2, 0.3, 0.4]), goals, q_values, num_timesteps=0) == []
    assert selector.current_threshold == math.inf  # allowance 0
    new = np.array([0.05, 0.35, 0.15, 0.25])
    asked = selector.select(new, goals, q_values, num_timesteps=2)
    window = np.array([0.1, 0.2, 0.3, 0.4, 0.05, 0.35, 0.15, 0.25])
    assert selector.current_threshold == pytest.approx(np.quantile(window, 0.5))
    assert asked == [(1, 1), (3, 1)]  # 0.35 and 0.25 are above the median 0.225
    assert selector.used == 2


@pytest.mark.parametrize("mode", ["adaptive", "paced"])
def test_a_call_with_no_quota_is_idle_and_counted_without_confidences(mode):
    # budget 10 over 1,000 steps: the allowance grows by one every 100 steps
    selector = QuerySelector(budget=10, mode=mode, total_timesteps=1_000, threshold=0.0)
    q_values = np.tile([0.0, 1.0], (2, 1))
    assert selector.idle(50) and selector.current_threshold == math.inf  # allowance 0
    assert not selector.idle(100)  # allowance 1: a question may be asked, the confidences are needed
    assert selector.select(np.array([0.9, 0.1]), np.zeros(2, dtype=int), q_values, num_timesteps=100) == [(0, 1)]
    assert selector.idle(150)  # caught up with the allowance
    assert selector.state_dict()["n_calls"] == 3  # idle calls count towards the steps between calls
    assert len(selector._window) == 2  # only the calls that could ask pooled their confidences
    assert not QuerySelector(budget=10, threshold=0.5).idle(0)  # the fixed mode asks whenever c > t_qry


def test_paced_mode_asks_only_above_t_qry_and_within_the_pace():
    # the same window and quota as above: the adaptive threshold is the median 0.225; t_qry 0.3 lies above it
    q_values = np.tile([0.0, 1.0], (4, 1))
    goals = np.zeros(4, dtype=int)
    new = np.array([0.05, 0.35, 0.15, 0.25])
    selectors = {mode: QuerySelector(budget=100, threshold=0.3, mode=mode, total_timesteps=100, quantile_window=8)
                 for mode in ("adaptive", "paced")}
    asked = {}
    for mode, selector in selectors.items():
        selector.select(np.array([0.1, 0.2, 0.3, 0.4]), goals, q_values, num_timesteps=0)
        asked[mode] = selector.select(new, goals, q_values, num_timesteps=2)
    assert asked["adaptive"] == [(1, 1), (3, 1)]
    assert asked["paced"] == [(1, 1)]  # 0.25 lies below t_qry: not asked, however much of the quota is left
    assert selectors["paced"].current_threshold == pytest.approx(0.3) and selectors["paced"].used == 1
    # a sure predictor asks nothing, even at the last call, which the adaptive mode spends in full
    for mode, selector in selectors.items():
        asked[mode] = selector.select(np.array([0.1, 0.2, 0.3, 0.29]), goals, q_values, num_timesteps=99)
    assert len(asked["adaptive"]) == 4 and asked["paced"] == []
    # and where unsure, no more than the paced allowance: 3 questions by step 3 of 100
    paced = QuerySelector(budget=100, threshold=0.3, mode="paced", total_timesteps=100, quantile_window=8)
    assert len(paced.select(np.full(4, 0.9), goals, q_values, num_timesteps=3)) == 3


@pytest.mark.parametrize("mode", ["adaptive", "paced"])
def test_adaptive_mode_needs_total_timesteps(mode):
    selector = QuerySelector(budget=10, mode=mode)
    with pytest.raises(ValueError, match="total_timesteps"):
        selector.select(np.ones(2), np.zeros(2, dtype=int), np.ones((2, 2)), num_timesteps=5)
    selector.set_total_timesteps(10)
    assert len(selector.select(np.ones(2), np.zeros(2, dtype=int), np.ones((2, 2)), num_timesteps=5)) == 2
    with pytest.raises(ValueError, match="total_timesteps"):
        selector.set_total_timesteps(0)


def test_state_dict_round_trip():
    rng = np.random.default_rng(0)
    first = QuerySelector(budget=30, mode="adaptive", total_timesteps=1000, quantile_window=50)
    second = QuerySelector(budget=30, mode="adaptive", quantile_window=50)
    for t in range(1, 6):
        first.select(rng.uniform(size=10), rng.integers(0, 3, 10), rng.normal(size=(10, 3)), num_timesteps=100 * t)
    second.load_state_dict(first.state_dict())
    assert (second.used, second.current_threshold, second.total_timesteps) == (
        first.used,
        first.current_threshold,
        first.total_timesteps,
    )
    inputs = (rng.uniform(size=10), rng.integers(0, 3, 10), rng.normal(size=(10, 3)))
    assert first.select(*inputs, num_timesteps=700) == second.select(*inputs, num_timesteps=700)
    assert first.current_threshold == second.current_threshold


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(budget=-1), "query_budget must be an integer >= 0, got -1"),
        (dict(budget=1.5), "query_budget"),
        (dict(budget=5, threshold=-0.1), "threshold"),
        (dict(budget=5, mode="greedy"), "mode"),
        (dict(budget=5, quantile_window=0), "quantile_window"),
        (dict(budget=5, mode="adaptive", total_timesteps=0), "total_timesteps"),
    ],
)
def test_bad_arguments_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        QuerySelector(**kwargs)


@pytest.mark.parametrize(
    "confidences, goals, q_values, message",
    [
        (np.ones((2, 1)), np.zeros(2, dtype=int), np.ones((2, 3)), "confidences"),
        (np.ones(2), np.zeros(3, dtype=int), np.ones((2, 3)), "goals"),
        (np.ones(2), np.zeros(2, dtype=int), np.ones((3, 3)), "q_values"),
        (np.ones(2), np.array([0, 3]), np.ones((2, 3)), r"\[0, 3\)"),
        (np.ones(2), np.array([0.0, 1.0]), np.ones((2, 3)), "integer"),
        (np.array([np.nan, 1.0]), np.zeros(2, dtype=int), np.ones((2, 3)), "NaN"),
    ],
)
def test_inconsistent_shapes_raise(confidences, goals, q_values, message):
    with pytest.raises(ValueError, match=message):
        QuerySelector(budget=5).select(confidences, goals, q_values)


def test_excluded_pairs_are_never_asked_and_the_next_best_second_choice_is_shown() -> None:
    """``exclude`` marks (tuple, g2) pairs already asked: g2 becomes the best sub-goal not excluded, and a tuple whose
    every other sub-goal is excluded is not asked; ``refund`` gives back questions counted but not asked."""
    selector = QuerySelector(budget=10, threshold=0.0, mode="fixed")
    q_values = np.array([[0.0, 3.0, 2.0, 1.0], [0.0, 3.0, 2.0, 1.0]])
    exclude = np.zeros((2, 4), dtype=bool)
    exclude[0, 1] = True  # tuple 0's best second choice was asked
    exclude[1, [0, 2, 3]] = True  # tuple 1 (g = 1) has nothing left to ask
    selected = selector.select(np.array([0.5, 0.5]), np.array([0, 1]), q_values, exclude=exclude)
    assert selected == [(0, 2)]
    assert selector.used == 1
    selector.refund(1)
    assert selector.used == 0
    with pytest.raises(ValueError, match="refund"):
        selector.refund(1)
    with pytest.raises(ValueError, match="exclude"):
        selector.select(np.array([0.5]), np.array([0]), q_values[:1], exclude=exclude)


def test_unasked_second_goal_is_the_best_sub_goal_no_question_named() -> None:
    """``second="unasked"``: g2 is the meta-controller's best valid, not excluded sub-goal other than g among those no
    question has named yet; a tuple without one gets the meta-controller's second choice, as with ``"meta"``."""
    q_values = np.array(
        [
            [5.0, 1.0, 3.0, 2.0],  # g = 0; unasked 1 and 3: g2 = 3 (the better of them), not the runner-up 2
            [5.0, 1.0, 3.0, -np.inf],  # g = 0; 3 is not choosable: g2 = 1
            [5.0, 1.0, 3.0, 2.0],  # g = 1 (itself unasked, never its own g2), 3 excluded: g2 = 0, the runner-up
        ]
    )
    unasked = np.array([False, True, False, True])
    exclude = np.zeros((3, 4), dtype=bool)
    exclude[2, 3] = True
    goals = np.array([0, 0, 1])
    unasked_selector = QuerySelector(budget=10, threshold=0.0, second="unasked")
    assert unasked_selector.select(np.ones(3), goals, q_values, exclude=exclude, unasked=unasked) == [
        (0, 3), (1, 1), (2, 0)]
    meta = QuerySelector(budget=10, threshold=0.0)
    assert meta.select(np.ones(3), goals, q_values, exclude=exclude, unasked=unasked) == [(0, 2), (1, 2), (2, 0)]
    # without the flags "unasked" is the paper's rule
    assert QuerySelector(budget=10, threshold=0.0, second="unasked").select(
        np.ones(3), goals, q_values, exclude=exclude) == [(0, 2), (1, 2), (2, 0)]
    with pytest.raises(ValueError, match="second must be one of"):
        QuerySelector(budget=10, second="random")
    with pytest.raises(ValueError, match="unasked must have shape"):
        unasked_selector.select(np.ones(3), goals, q_values, unasked=np.ones(3, dtype=bool))
