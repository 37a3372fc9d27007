"""Montezuma's Revenge: the RAM facts the image goal space records, on real ale-py states, and the scripted oracle
that answers from them."""

import gymnasium as gym
import numpy as np
import pytest

from sb3_hhp import HhP
from sb3_hhp.goals import ImageGoalSpace, make_goal_space
from sb3_hhp.oracles import Label, MontezumaScriptedOracle, NoisyOracle, Query, make_oracle
from sb3_hhp.oracles.montezuma import DOOR_OPENED, KEY_HELD, LOST, NEW_ROOM, NO_KEY
from sb3_hhp.oracles.synthetic import SyntheticOracle

ale_py = pytest.importorskip("ale_py", reason='needs the [atari] extra: pip install "sb3_hhp[atari]"')
gym.register_envs(ale_py)

ACTIONS = {name: index for index, name in enumerate(
    ["NOOP", "FIRE", "UP", "RIGHT", "LEFT", "DOWN", "UPRIGHT", "UPLEFT", "DOWNRIGHT", "DOWNLEFT"])}
#: from the start to the floor: down the middle ladder, onto the rope, onto the right platform, down the right ladder
TO_FLOOR = [("DOWN", 8), ("RIGHT", 8), ("FIRE_RIGHT", 1), ("NOOP", 6), ("FIRE_RIGHT", 1), ("NOOP", 8), ("RIGHT", 1),
            ("DOWN", 9)]
#: from the floor to the key: left, over the skull (seed 0, no sticky actions), up the left ladder, a jump under the key
TO_KEY = [("LEFT", 12), ("FIRE_LEFT", 1), ("LEFT", 16), ("UP", 9), ("LEFT", 3), ("FIRE", 1), ("NOOP", 6)]
FIRE_MOVES = {"FIRE_RIGHT": 11, "FIRE_LEFT": 12}  # RIGHTFIRE, LEFTFIRE


def montezuma() -> gym.Env:
    env = gym.make("ALE/MontezumaRevenge-v5", repeat_action_probability=0.0)
    env.reset(seed=0)
    return env


def walk(env: gym.Env, plan: list) -> float:
    total = 0.0
    for name, steps in plan:
        for _ in range(steps):
            _, reward, *_ = env.step(FIRE_MOVES.get(name, ACTIONS.get(name)))
            total += float(reward)
    return total


def facts(env: gym.Env) -> dict:
    space = ImageGoalSpace()
    return space.facts(space.snapshot(env))


def question(info: dict) -> Query:
    return Query(state=np.zeros(1), goal1=0, goal2=1, goal1_obs=np.zeros(1), goal2_obs=np.zeros(1), info=info)


def ask(oracle: MontezumaScriptedOracle, goal1: dict, goal2: dict) -> Label:
    return oracle.answer(question({"goal1_state": goal1, "goal2_state": goal2}))


def test_ram_facts_at_the_reset_and_along_the_way_to_the_key() -> None:
    """The start (room 1, (77, 235), nothing held, 5 spare lives), the foot of the middle ladder (y 192), the floor
    (y 148), then the key: reward 100, inventory bit 0x02, the key gone from the first room's objects (bit 0x01)."""
    env = montezuma()
    space = ImageGoalSpace()
    snapshot = space.snapshot(env)
    assert isinstance(snapshot, bytes) and len(snapshot) == 8  # what training keeps at each choice
    assert space.facts(snapshot) == {"game": "montezuma_revenge", "room": 1, "x": 77, "y": 235, "inventory": 0,
                                     "room_objects": 15, "first_room_objects": 31, "lives": 5, "death_timer": 0}
    assert space.privileged(env) == space.facts(snapshot)
    walk(env, TO_FLOOR[:1])
    assert (facts(env)["x"], facts(env)["y"]) == (76, 192)  # the ladder's foot, on the conveyor that carries the agent left
    walk(env, TO_FLOOR[1:])
    assert (facts(env)["x"], facts(env)["y"]) == (133, 148)
    assert walk(env, TO_KEY) == 100.0
    held = facts(env)
    assert held["inventory"] & 0x02 and held["first_room_objects"] == 30 and held["room_objects"] == 14
    assert held["lives"] == 5 and held["death_timer"] == 0


def test_a_lost_life_shows_in_the_lives_and_the_death_timer() -> None:
    """Falling off the conveyor: the lives drop on the step of the death, the death timer counts 12 down to 0."""
    env = montezuma()
    seen = []
    for _ in range(40):
        env.step(ACTIONS["DOWN"])
        seen.append((facts(env)["lives"], facts(env)["death_timer"]))
    first = next(index for index, (lives, _) in enumerate(seen) if lives == 4)
    assert seen[first - 1] == (5, 0) and seen[first] == (4, 12)
    assert [timer for _, timer in seen[first:first + 13]] == list(range(12, -1, -1))


@pytest.fixture(scope="module")
def states() -> dict:
    """Facts of concrete states: the start, the middle ladder's foot, the rope, the floor, the key held, dying, the
    left door opened (the key given by setRAM) and the room beyond it."""
    out = {}
    env = montezuma()
    out["start"] = facts(env)
    walk(env, TO_FLOOR[:1])
    out["ladder_foot"] = facts(env)
    walk(env, TO_FLOOR[1:4])
    out["rope"] = facts(env)
    walk(env, TO_FLOOR[4:])
    out["floor"] = facts(env)
    walk(env, TO_KEY)
    out["key"] = facts(env)
    env = montezuma()
    for _ in range(30):
        env.step(ACTIONS["DOWN"])
        if facts(env)["death_timer"]:
            break
    out["dying"] = facts(env)
    env = montezuma()
    env.unwrapped.ale.setRAM(65, 0x02)  # the key, to open the left door without the whole route
    assert walk(env, [("LEFT", 3), ("FIRE_LEFT", 1), ("NOOP", 6), ("LEFT", 6)]) == 300.0
    out["door"] = facts(env)
    walk(env, [("LEFT", 6)])
    out["new_room"] = facts(env)
    return out


def test_the_states_have_the_stages_they_show(states: dict) -> None:
    stage = {name: MontezumaScriptedOracle.score(value)[0] for name, value in states.items()}
    assert stage == {"start": NO_KEY, "ladder_foot": NO_KEY, "rope": NO_KEY, "floor": NO_KEY, "key": KEY_HELD,
                     "dying": LOST, "door": DOOR_OPENED, "new_room": NEW_ROOM}
    assert states["door"]["first_room_objects"] == 23 and states["door"]["inventory"] == 0  # the left door, bit 0x08
    assert states["new_room"]["room"] == 0
    progress = [MontezumaScriptedOracle.score(states[name])[1] for name in ("start", "ladder_foot", "rope", "floor")]
    assert progress == sorted(progress) and progress[0] == 0.0 and progress[-1] > progress[-2] + 50


@pytest.mark.parametrize("better, worse", [
    ("key", "start"), ("key", "floor"), ("ladder_foot", "start"), ("rope", "ladder_foot"), ("floor", "rope"),
    ("start", "dying"), ("floor", "dying"), ("door", "key"), ("new_room", "door"), ("new_room", "key"),
])
def test_the_oracle_prefers_the_state_further_along_the_first_room(states: dict, better: str, worse: str) -> None:
    oracle = MontezumaScriptedOracle()
    assert ask(oracle, states[better], states[worse]) == Label.FIRST
    assert ask(oracle, states[worse], states[better]) == Label.SECOND


def test_equal_answers_within_the_tolerance_and_with_the_key_the_way_back_counts(states: dict) -> None:
    oracle = MontezumaScriptedOracle(equal_tolerance=4.0)
    assert ask(oracle, states["start"], dict(states["start"])) == Label.EQUAL
    assert ask(oracle, states["start"], dict(states["start"], x=74)) == Label.EQUAL  # 3 units off the way: no progress
    assert ask(oracle, states["door"], dict(states["door"], x=60)) == Label.EQUAL  # a door open: the stage decides
    # the key held at the middle ladder's top is further along (back to a door) than the key held where it was taken
    at_top = dict(states["key"], x=77, y=235)
    assert ask(oracle, at_top, states["key"]) == Label.FIRST
    with pytest.raises(ValueError, match="equal_tolerance"):
        MontezumaScriptedOracle(equal_tolerance=-1)


def test_questions_without_the_ram_facts_are_refused_with_what_is_missing(states: dict) -> None:
    oracle = MontezumaScriptedOracle()
    with pytest.raises(ValueError, match=r"query.info\['goal2_state'\].* lacks it"):
        oracle.answer(question({"goal1_state": states["start"]}))
    with pytest.raises(ValueError, match="goal1_state.*montezuma_revenge"):
        ask(oracle, {}, states["start"])  # an image goal space on another env records no facts
    without_timer = {name: value for name, value in states["start"].items() if name != "death_timer"}
    with pytest.raises(ValueError, match="goal2_state"):
        ask(oracle, states["start"], without_timer)


def test_scripted_picks_the_montezuma_oracle_for_an_image_goal_space_bound_to_it() -> None:
    from stable_baselines3.common.atari_wrappers import AtariWrapper

    with pytest.raises(ValueError, match="raw 210x160 screen: wrap it with .*AtariWrapper"):
        ImageGoalSpace().bind(montezuma())  # an Atari env without its frame wrapper
    with pytest.raises(ValueError, match=r"skips 4 frames a step itself and its frame wrapper 4 more, 16 .*frameskip=1"):
        ImageGoalSpace().bind(AtariWrapper(montezuma()))  # ALE's v5 frame skip under AtariWrapper's
    env = AtariWrapper(gym.make("ALE/MontezumaRevenge-v5", frameskip=1, repeat_action_probability=0.0))
    env.reset(seed=0)
    before = env.unwrapped.ale.getEpisodeFrameNumber()
    env.step(0)
    assert env.unwrapped.ale.getEpisodeFrameNumber() - before == 4  # AtariWrapper's frame skip alone
    space = ImageGoalSpace()
    space.bind(env)
    assert space.game == "montezuma_revenge"
    assert make_goal_space(space, env) is space
    assert isinstance(make_oracle("scripted", space, env.observation_space), MontezumaScriptedOracle)
    noisy = make_oracle("noisy-scripted", space, env.observation_space, seed=0, rho=0.2)
    assert isinstance(noisy, NoisyOracle) and isinstance(noisy.oracle, MontezumaScriptedOracle)
    # another oracle's setting (the synthetic oracle's head) is refused, naming what this one takes
    with pytest.raises(ValueError, match=r"'scripted' oracle \(MontezumaScriptedOracle\) takes no 'head'.*equal_tolerance"):
        make_oracle("scripted", space, env.observation_space, head="linear")
    pong = AtariWrapper(gym.make("ALE/Pong-v5", frameskip=1))
    other = ImageGoalSpace()
    other.bind(pong)
    assert other.game == "pong" and other.snapshot(pong) == {} and other.facts(other.snapshot(pong)) == {}
    with pytest.raises(ValueError, match="ALE game 'pong'.*Montezuma.*'synthetic'"):
        make_oracle("scripted", other, pong.observation_space)
    assert make_oracle("synthetic", other, pong.observation_space) is not None
    # sub-goals handed in have no facts of a state they were found in: the scripted oracle is refused before training
    with pytest.raises(ValueError, match=r"MontezumaScriptedOracle answers from the facts.*handed in.*oracle='synthetic'"):
        HhP("CnnPolicy", env, oracle="noisy-scripted", goal_space=space,
            discovery_kwargs=dict(strategy="none", subgoals=[env.reset(seed=0)[0]]))
    # "auto": the scripted oracle where the game has one, the synthetic oracle elsewhere
    assert isinstance(make_oracle("auto", space, env.observation_space), MontezumaScriptedOracle)
    assert isinstance(make_oracle("auto", other, pong.observation_space), SyntheticOracle)


def test_hhp_training_asks_the_montezuma_oracle_with_the_facts_of_both_sub_goals() -> None:
    """Training's questions carry the facts of the states each sub-goal was found in (the goal space takes a snapshot at
    every primitive step on Montezuma), and the scripted oracle answers them."""
    import torch as th
    from stable_baselines3.common.atari_wrappers import AtariWrapper

    from sb3_hhp import HhP

    th.set_num_threads(1)
    env = AtariWrapper(gym.make("ALE/MontezumaRevenge-v5", frameskip=1, repeat_action_probability=0.0))
    model = HhP(
        "CnnPolicy", env, oracle="scripted", query_budget=4, seed=0, learning_starts=50, batch_size=16,
        buffer_size=1_000, query_kwargs=dict(mode="fixed", threshold=0.0), predictor_kwargs=dict(n_masks=4),
        discovery_kwargs=dict(strategy="random", min_visits=1, similarity_threshold=1.0),
        subpolicy_kwargs=dict(learning_starts=10_000, buffer_size=2_000),
    )
    assert model.goal_space.facts_per_step and isinstance(model.oracle, MontezumaScriptedOracle)
    model.learn(600)
    # sub-goals found while questions remained keep their state's snapshot (none is taken once the budget is spent)
    assert sum(goal.snapshot is not None for goal in model.subgoals) >= 2
    answered = [model.store.get_query(query_id) for query_id in model.consumed_query_ids]
    assert answered
    for query in answered:
        for name in ("goal1_state", "goal2_state"):
            assert query.info[name]["game"] == "montezuma_revenge" and query.info[name]["room"] == 1
