"""The diagnostics' own arithmetic (benchmarks/diagnostics): where the object a sub-goal faces lies at a choice, and
what a walk's idle steps and action gaps add up to."""

from collections import Counter
from types import SimpleNamespace

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX
from minigrid.core.world_object import Door, Key
import numpy as np
import torch as th

from benchmarks.diagnostics.choice_trace import q_readings, target_distance, value_readings, view_reach, walk_readings
from benchmarks.diagnostics.learner_proxy import make_env, split_at, start_distance, tries
from benchmarks.diagnostics.question_coverage import coverage
from sb3_hhp.goals import SUCCESS_KEY, MiniGridGoalSpace, wrap_env
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.preferences.types import Label, Query
from sb3_hhp.subgoal_table import SubgoalTable

EMPTY, KEY, DOOR = OBJECT_TO_IDX["empty"], OBJECT_TO_IDX["key"], OBJECT_TO_IDX["door"]
LOCKED, OPEN = STATE_TO_IDX["locked"], STATE_TO_IDX["open"]


def _cell_of(base, kind) -> tuple[int, int]:
    return next((x, y) for x in range(base.width) for y in range(base.height) if isinstance(base.grid.get(x, y), kind))


def test_target_distance_is_the_larger_axis_to_the_nearest_matching_object() -> None:
    env = wrap_env(gym.make("MiniGrid-DoorKey-16x16-v0"))
    env.reset(seed=3)
    base = env.unwrapped
    door_x, door_y = _cell_of(base, Door)
    key_x, key_y = _cell_of(base, Key)
    agent_x, agent_y = base.agent_pos
    plain = MiniGridGoalSpace()
    assert target_distance(env, plain, (KEY, DOOR, LOCKED)) == max(abs(door_x - agent_x), abs(door_y - agent_y))
    assert target_distance(env, plain, (EMPTY, KEY, 0)) == max(abs(key_x - agent_x), abs(key_y - agent_y))
    # the door's state counts: no open door in a fresh DoorKey layout; nothing to face, and "task solved": no distance
    assert target_distance(env, plain, (KEY, DOOR, OPEN)) is None
    assert target_distance(env, plain, (KEY, EMPTY, 0)) is None
    assert target_distance(env, plain, SUCCESS_KEY) is None
    # with colours, the key's colour must match too
    coloured = MiniGridGoalSpace(use_color=True)
    door_colour = COLOR_TO_IDX[base.grid.get(door_x, door_y).color]
    other = next(index for index in COLOR_TO_IDX.values() if index != door_colour)
    expected = max(abs(door_x - agent_x), abs(door_y - agent_y))
    assert target_distance(env, coloured, (EMPTY, 0, DOOR, door_colour, LOCKED)) == expected
    assert target_distance(env, coloured, (EMPTY, 0, DOOR, other, LOCKED)) is None


def test_view_reach_splits_walks_at_the_learners_view() -> None:
    walk = dict(goal="to the door")
    episodes = [dict(choices=[
        {**walk, "distance": 7, "reached": True},  # the edge of a 15 x 15 view: in it
        {**walk, "distance": 8, "reached": False},
        {**walk, "distance": 9, "reached": True},
        {**walk, "distance": 2, "reached": False},
        dict(goal="task solved", distance=None, reached=True),  # no distance: left out
    ])]
    reach = view_reach(episodes, 15)
    assert reach["view"] == 15
    assert reach["goals"] == {"to the door": dict(in_view=2, in_view_reached=1, out_of_view=2, out_of_view_reached=1)}
    # learners that read every cell: every walk is in view
    everything = view_reach(episodes, None)["goals"]["to the door"]
    assert (everything["in_view"], everything["out_of_view"]) == (4, 0)
    assert view_reach([dict(choices=[dict(goal="task solved", distance=None, reached=True)])], 15) is None


def test_walk_readings_weigh_the_gap_by_steps_and_split_reached_from_failed_walks() -> None:
    episodes = [dict(choices=[dict(goal="to the door", reached=True, steps=4, idle=1, gap=0.10),
                              dict(goal="to the door", reached=False, steps=10, idle=5, gap=0.01),
                              dict(goal="to the door", reached=True, steps=6, idle=0, gap=0.20)]),
                dict(choices=[dict(goal="task solved", reached=False, steps=2, idle=2, gap=0.0),
                              dict(goal="older trace", reached=True)])]  # a choice recorded without the readings
    rows = walk_readings(episodes)
    door = rows["to the door"]
    assert (door["reached_walks"], door["reached_steps"], door["reached_idle"]) == (2, 10, 1)
    assert door["reached_idle_share"] == 0.1
    assert abs(door["reached_gap"] - (0.10 * 4 + 0.20 * 6) / 10) < 1e-12  # by steps, not the walks' plain mean 0.15
    assert (door["failed_walks"], door["failed_idle_share"], door["failed_gap"]) == (1, 0.5, 0.01)
    solved = rows["task solved"]
    assert solved["reached_walks"] == 0 and solved["reached_idle_share"] is None and solved["reached_gap"] is None
    assert "older trace" not in rows


def test_q_readings_are_the_best_q_value_and_its_margin_over_the_second_best() -> None:
    values = {0: [0.2, 0.9, 0.5], 1: [0.3, 0.3, 0.1]}
    learners = SimpleNamespace(q_values=lambda goals, obs: th.tensor([values[int(goals[0])]]))
    model = SimpleNamespace(subpolicies=learners)
    best, gap = q_readings(model, 0, np.zeros(3))
    assert abs(best - 0.9) < 1e-6 and abs(gap - 0.4) < 1e-6
    assert q_readings(model, 1, np.zeros(3))[1] == 0.0  # a tie: no gap
    best, gap = q_readings(SimpleNamespace(subpolicies=object()), 0, np.zeros(3))  # no Q-values (DDPG)
    assert np.isnan(best) and gap == 0.0


def test_value_readings_weigh_walks_by_steps_and_count_the_steps_above_1() -> None:
    episodes = [dict(choices=[dict(steps=4, best=1.2, above_1=3), dict(steps=6, best=0.7, above_1=0)]),
                dict(choices=[dict(steps=0, best=0.0, above_1=0), dict(goal="older trace", steps=5)])]
    values = value_readings(episodes)
    assert values["steps"] == 10 and values["share_above_1"] == 0.3
    assert abs(values["mean_best"] - (1.2 * 4 + 0.7 * 6) / 10) < 1e-12
    assert value_readings([dict(choices=[dict(goal="older trace", steps=5)])]) is None


def test_the_proxy_splits_its_tries_by_where_the_object_starts() -> None:
    env = make_env("MiniGrid-DoorKey-16x16-v0", "door", max_steps=3)
    env.reset(seed=5)
    base = env.unwrapped
    door_x, door_y = _cell_of(base, Door)
    assert start_distance(env, Door) == max(abs(door_x - base.agent_pos[0]), abs(door_y - base.agent_pos[1]))
    results = tries(env, 3, lambda obs, first: 0, seed=5)  # turning left: never reaches the door
    env.reset(seed=5)
    assert results[0][0] == start_distance(env, Door)  # each try's distance is its own layout's
    assert not any(reached for _, reached in results)
    split = split_at([(3, True), (7, False), (8, True), (12, True)], radius=7)
    assert split == dict(tries_within=2, reached_within=0.5, tries_beyond=2, reached_beyond=1.0)
    assert split_at([(9, False)], radius=7) == dict(tries_within=0, reached_within=None, tries_beyond=1,
                                                    reached_beyond=0.0)


def test_question_coverage_counts_each_sub_goals_questions_and_outcomes() -> None:
    """Named: every question asked with the sub-goal in it, answered or not; won / lost / equal from the answers;
    "can't tell" counts as named only."""
    store = PreferenceStore()
    image = np.zeros((8, 8, 3), np.uint8)
    SubgoalTable(store).put([dict(id=goal, image=image, found_at=10 * goal, mean_score=float(goal), name=f"g{goal}")
                             for goal in range(4)])
    obs = np.zeros(3, np.float32)
    for goal1, goal2, label in ((0, 1, Label.FIRST), (1, 0, Label.FIRST), (0, 2, Label.EQUAL), (0, 2, Label.INCOMPARABLE),
                                (2, 1, None)):
        query = Query(state=obs, goal1=goal1, goal2=goal2, goal1_obs=obs, goal2_obs=obs)
        store.add_query(query)
        if label is not None:
            store.add_answer(query.query_id, label, "oracle")
    rows = {row["id"]: row for row in coverage(store)}
    assert [(rows[g]["named"], rows[g]["won"], rows[g]["lost"], rows[g]["equal"]) for g in range(4)] == [
        (4, 1, 1, 1), (3, 1, 1, 0), (3, 0, 0, 1), (0, 0, 0, 0)]
    assert rows[3]["name"] == "g3" and rows[3]["found_at"] == 30 and rows[3]["mean_score"] == 3.0



def test_the_oracles_chooser_takes_the_plans_first_choosable_milestone_not_ruled_out() -> None:
    """oracle_choices.py: in DoorKey's first state the plan's first milestone among the sub-goals is the walk to the
    key; ruled out (as predict rules out a sub-goal that just gave up), the plan names no other sub-goal here, and
    the model's own choice stands (counted as not planned). The predictor's best score is judged among every choice
    predict may make there, the plan's or not."""
    from benchmarks.diagnostics.oracle_choices import oracle_chooser
    from sb3_hhp import HhP
    from sb3_hhp.oracles import make_oracle

    env = wrap_env(gym.make("MiniGrid-DoorKey-5x5-v0"))
    space = MiniGridGoalSpace()
    given, keys, rng = [], [], np.random.default_rng(0)
    for seed in range(40):  # observations of distinct keys, one facing the key
        obs, _ = env.reset(seed=seed)
        for action in rng.integers(0, 3, size=12):
            if space.key(obs) not in keys and space.key(obs) != (EMPTY, EMPTY, 0):
                given.append(obs)
                keys.append(space.key(obs))
            obs, *_ = env.step(int(action))
    assert (EMPTY, KEY, 0) in keys and len(keys) >= 3
    model = HhP("MlpPolicy", gym.make("MiniGrid-DoorKey-5x5-v0"), seed=0,
                buffer_size=500, policy_kwargs=dict(net_arch=[16]), discovery_kwargs=dict(strategy="none", subgoals=given))
    oracle = make_oracle("scripted", model.goal_space, model.primitive_observation_space)
    obs, _ = env.reset(seed=3)
    planned: list = []
    agree = Counter()
    records: list = []
    choose = oracle_chooser(model, oracle, env, planned, agree, records)
    walk_to_key = keys.index((EMPTY, KEY, 0))
    own = np.array([(walk_to_key + 1) % len(keys)])
    excluded = np.zeros((1, len(model.subgoals)), dtype=bool)  # predict's shape
    # the predictor's best score counts among every choice predict may make, off the plan too: here the walk to the
    # locked door, choosable and not on the plan, best scored, departs from the plan
    off_plan = keys.index((EMPTY, DOOR, 2))
    assert model.action_mask(obs[None])[0, off_plan]
    for best, agreed in ((off_plan, 0), (walk_to_key, 1)):
        model.predictor.score_matrix = lambda states, goals, best=best: np.eye(len(keys))[best][None]
        choose(obs[None], own, excluded)
        assert agree["predictor"] == agreed
    assert off_plan in records[0]["choosable"] and records[0]["best"] == (walk_to_key,)
    assert choose(obs[None], own, excluded)[0] == walk_to_key and planned == [True] * 3 and agree["choices"] == 3
    excluded[0, walk_to_key] = True
    assert choose(obs[None], own, excluded)[0] != walk_to_key and planned == [True] * 3 + [False]
    assert agree["choices"] == 3


def test_the_feature_ceiling_counts_per_alike_input_the_most_often_best_sub_goal() -> None:
    """oracle_choices.py: choices whose inputs read alike (same bytes, same choosable sub-goals) can be matched at most
    as often as their most often best sub-goal; a tie on the plan counts for either sub-goal; inputs that differ, or
    whose choosable sub-goals differ, are groups of their own."""
    from benchmarks.diagnostics.oracle_choices import feature_ceiling

    def record(reads: bytes, best: tuple, choosable: tuple = (0, 1, 2), state: str = "s") -> dict:
        return dict(inputs=np.frombuffer(reads, dtype=np.uint8), choosable=choosable, best=best, state=state)

    records = [record(b"a", (0,)), record(b"a", (0,)), record(b"a", (1,), state="t"),  # alike: 2 of 3 at best
               record(b"a", (1,), choosable=(1, 2)),  # other choosable sub-goals: its own group
               record(b"b", (2,)), record(b"b", (1, 2)),  # the tie counts for 2: both matched
               record(b"c", (0,)), record(b"c", (1,))]  # 1 of 2
    result = feature_ceiling(records, describe=lambda goal: f"g{goal}")
    assert (result["choices"], result["groups"], result["ceiling"]) == (8, 4, 2 + 1 + 2 + 1)
    assert [(c["choices"], c["matched"]) for c in result["conflicts"]] == [(3, 2), (2, 1)]
    assert result["conflicts"][0]["states"] == ["s", "t"] and result["conflicts"][0]["plan"] == {"g0": 2, "g1": 1}


def test_departures_count_the_choices_off_the_plan_per_state_plan_and_choice() -> None:
    """oracle_choices.py: a chooser's choice among the plan's best ones (a tie counts for either) is no departure;
    the others are counted per (state, the plan's best, the choice), most frequent first, for each chooser apart."""
    from benchmarks.diagnostics.oracle_choices import departures

    def record(state: str, best: tuple, predictor: int, meta: int) -> dict:
        return dict(state=state, best=best, predictor=predictor, meta=meta)

    records = [record("s", (0,), 1, 0), record("s", (0,), 1, 2), record("s", (0,), 2, 0),
               record("t", (1, 2), 2, 0), record("t", (1,), 0, 1)]
    describe = lambda goal: f"g{goal}"  # noqa: E731
    assert departures(records, "predictor", describe) == [
        dict(state="s", plan="g0", chosen="g1", count=2), dict(state="s", plan="g0", chosen="g2", count=1),
        dict(state="t", plan="g1", chosen="g0", count=1)]
    assert departures(records, "meta", describe) == [
        dict(state="s", plan="g0", chosen="g2", count=1), dict(state="t", plan="g1 / g2", chosen="g0", count=1)]
    assert departures(records, "meta", describe, top=1) == [dict(state="s", plan="g0", chosen="g2", count=1)]


def test_placement_answers_by_plan_rank_and_names_each_rules_pair() -> None:
    """predictor_placement.py: the oracle prefers the sub-goal earlier in its plan and ties teach nothing; ``plan``
    names the plan's choice against another choosable sub-goal, ``top2`` the predictor's two best choosable ones."""
    from benchmarks.diagnostics.predictor_placement import answer, pair_of
    from sb3_hhp.preferences.types import Label

    ranks = np.array([0.0, 2.0, 2.0, np.inf])
    assert (answer(ranks, 0, 1), answer(ranks, 1, 0), answer(ranks, 1, 2)) == (Label.FIRST, Label.SECOND,
                                                                                 Label.INCOMPARABLE)
    record = dict(choosable=(0, 1, 2), best=(0,), ranks=ranks)
    rng = np.random.default_rng(0)
    pairs = {pair_of("plan", record, None, rng) for _ in range(20)}
    assert pairs == {(0, 1), (0, 2)}
    scores = lambda _: np.array([0.1, 0.9, 0.5, 2.0])  # noqa: E731  (sub-goal 3, not choosable, scores best)
    assert pair_of("top2", record, scores, rng) == (1, 2)
    assert all(len(set(pair_of("random", record, None, rng)) & {0, 1, 2}) == 2 for _ in range(10))


def test_placement_teaches_a_fresh_predictor_the_plans_choice() -> None:
    """predictor_placement.py: with the plan always preferring sub-goal 0, a fresh predictor trained after every label
    comes to choose it in unseen states (agreement 1), and its agreement is counted among the choosable sub-goals."""
    from gymnasium import spaces

    from benchmarks.diagnostics.predictor_placement import agreement, placement_curve
    from sb3_hhp.preferences.predictor import PreferencePredictor

    rng = np.random.default_rng(1)
    goals = np.eye(3, dtype=np.float32)
    ranks = np.array([0.0, 1.0, 2.0])

    def records(n: int) -> list[dict]:
        return [dict(inputs=rng.random(3).astype(np.float32), choosable=(0, 1, 2), best=(0,), ranks=ranks)
                for _ in range(n)]

    space = spaces.Box(-np.inf, np.inf, (3,), np.float32)
    make = lambda: PreferencePredictor(space, hidden_dim=16, min_updates=30, buffer_size=30, seed=0)  # noqa: E731
    threads = th.get_num_threads()
    th.set_num_threads(1)  # thirty small trainings: more threads only contend with whatever else runs
    try:
        points = placement_curve(make, goals, records(40), records(20), "random", [1, 30], seed=0)
    finally:
        th.set_num_threads(threads)
    assert [p["labels"] for p in points] == [1, 30] and points[1]["taught"] == 30
    assert points[1]["test"] == 1.0

    class Fixed:  # scores sub-goal 2 best: right only where 0 is not choosable and 2 is best
        @staticmethod
        def score_matrix(states: np.ndarray, _goals: np.ndarray) -> np.ndarray:
            return np.tile([0.0, 1.0, 2.0], (len(states), 1))

    cases = [dict(inputs=np.zeros(3), choosable=(0, 1), best=(1,)), dict(inputs=np.zeros(3), choosable=(0, 2), best=(0,))]
    assert agreement(Fixed(), goals, cases) == 0.5


def test_placement_can_read_a_sub_goal_as_the_change_it_makes() -> None:
    """predictor_placement.py ``--goal-input change``: every sub-goal is read as its features less the state's, the
    same in the scores of every (state, sub-goal) as in a question's pair."""
    from gymnasium import spaces

    from benchmarks.diagnostics.predictor_placement import goal_input, scores_of
    from sb3_hhp.preferences.predictor import PreferencePredictor

    rng = np.random.default_rng(2)
    states, goals = rng.random((4, 3)).astype(np.float32), rng.random((5, 3)).astype(np.float32)
    predictor = PreferencePredictor(spaces.Box(-np.inf, np.inf, (3,), np.float32), hidden_dim=8, seed=0)
    assert np.array_equal(goal_input(goals, states[1], "features"), goals)
    assert np.allclose(goal_input(goals, states[1], "change"), goals - states[1])
    scores = scores_of(predictor, goals, states, "change")
    assert scores.shape == (4, 5)
    assert np.allclose(scores[1], [predictor.score(states[1:2], (goal - states[1])[None])[0] for goal in goals], atol=1e-6)
    assert np.allclose(scores_of(predictor, goals, states), predictor.score_matrix(states, goals))
    assert not np.allclose(scores, predictor.score_matrix(states, goals))


def test_choice_orders_fit_an_order_per_state_key_only_where_asked() -> None:
    """choice_orders.py: where the plan prefers sub-goal 0 in states of one key and 1 in the other's, one order of the
    sub-goals (``goal``) can match at most half the choices and a score table per key (``key``) all of them; every
    pair the ranks order is a triple, random labels keep the preferred sub-goal first and drop ties."""
    from benchmarks.diagnostics.choice_orders import TableOrder, agreement, every_pair, random_labels, state_key

    def record(flag: float, extra: float) -> dict:
        ranks = np.array([0.0, 1.0, 1.0]) if flag else np.array([1.0, 0.0, 1.0])
        return dict(inputs=np.array([flag, extra], dtype=np.float32), choosable=(0, 1, 2), ranks=ranks,
                    best=(0,) if flag else (1,))

    train = [record(flag, extra) for flag in (0.0, 1.0) for extra in (0.0, 1.0, 2.0)]
    test = [record(flag, 3.0) for flag in (0.0, 1.0)]
    triples = every_pair(train)
    assert len(triples) == 12 and all(r["ranks"][a] < r["ranks"][b] for r, a, b in triples)
    goal = TableOrder(3, state_key("goal", 1)).fit(triples)
    key = TableOrder(3, state_key("key", 1)).fit(triples)
    full = TableOrder(3, state_key("full", 1)).fit(triples)
    assert len(goal.keys) == 1 and len(key.keys) == 2 and len(full.keys) == 6
    assert agreement(goal, test) == 0.5 and agreement(key, test) == 1.0
    assert agreement(full, train) == 1.0 and agreement(full, test) == 0.5  # unseen inputs score by the order alone
    labels = random_labels(train, 40, seed=0)
    assert 0 < len(labels) < 40  # pairs (1, 2) or (0, 2) of equal rank are spent
    assert all(r["ranks"][a] < r["ranks"][b] for r, a, b in labels)


def test_fetch_oracle_pairs_along_a_scripted_pick_and_place() -> None:
    """The scripted pick and place solves its episode; along it, the pairs of states before the block moves are
    answered "the later" where the gripper came to the block in between (the goal space keys them apart by the
    gripper's flag) and "equal" elsewhere, never "the earlier"; the pairs where the block came nearer the target are
    answered "the later", none "the earlier". Unbound (keys without the flag) every such pair is "equal"."""
    import pytest

    pytest.importorskip("gymnasium_robotics", reason='needs the [fetch] extra: pip install "sb3_hhp[fetch]"')
    from benchmarks.diagnostics.fetch_oracle import episode, pair_readings
    from sb3_hhp.extras import register_fetch_envs
    from sb3_hhp.goals.fetch import FetchGoalSpace
    from sb3_hhp.oracles.fetch import FetchScriptedOracle

    register_fetch_envs()
    states, solved = episode("FetchPickAndPlace-v4", seed=0)
    assert solved and len(states) == 51
    space, oracle = FetchGoalSpace(), FetchScriptedOracle()
    unbound = pair_readings(states, every=3, moved=0.01, space=space, oracle=oracle)["reach"]
    assert unbound["equal"] > 0 and unbound["later"] == unbound["earlier"] == unbound["gripper_arrives"] == 0
    space.bind(gym.make("FetchPickAndPlace-v4"))
    counts = pair_readings(states, every=3, moved=0.01, space=space, oracle=oracle)
    reach, carry = counts["reach"], counts["carry"]
    assert reach["gripper_arrives"] > 0 and reach["later"] == reach["gripper_arrives_later"] == reach["gripper_arrives"]
    assert reach["equal"] > 0 and reach["earlier"] == 0
    assert reach["later"] + reach["equal"] == unbound["equal"]  # the same pairs, those the gripper's arrival splits
    assert reach["same_key"] <= reach["equal"]  # keyed alike only where the flags agree
    assert carry["later"] > 5 * carry["equal"] and carry["earlier"] == 0


def test_fetch_contact_counts_the_gripper_at_the_object_and_the_object_moved() -> None:
    """A scripted pick and place as the model: on every episode it solved the gripper came to the block and moved it;
    a model that holds still does neither (the block starts away from the gripper) and solves nothing."""
    import pytest

    pytest.importorskip("gymnasium_robotics", reason='needs the [fetch] extra: pip install "sb3_hhp[fetch]"')
    from benchmarks.diagnostics.fetch_contact import contact
    from benchmarks.diagnostics.fetch_oracle import pick_and_place
    from sb3_hhp.extras import register_fetch_envs

    register_fetch_envs()

    class Scripted:
        def __init__(self, controller):
            self.controller = controller

        def predict(self, obs, state=None, episode_start=None, deterministic=False):
            stage = {} if episode_start[0] else state
            return self.controller(obs, stage), stage

    played = contact(Scripted(pick_and_place), "FetchPickAndPlace-v4", [0, 1])
    assert played == {"episodes": 2, "gripper_at_object": 1.0, "object_moved": 1.0, "success": 1.0}
    still = contact(Scripted(lambda obs, stage: np.zeros(4, np.float32)), "FetchPickAndPlace-v4", [0, 1])
    assert still == {"episodes": 2, "gripper_at_object": 0.0, "object_moved": 0.0, "success": 0.0}
