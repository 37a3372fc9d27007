"""MiniGrid goal space: the egocentric observation, sub-goal keys after real actions, images, and the
scripted oracle's plan and preferences (sb3_hhp.goals.minigrid, sb3_hhp.oracles.scripted)."""

import pickle
from types import SimpleNamespace

import gymnasium as gym
from gymnasium import spaces
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import pytest
from minigrid.core.actions import Actions
from minigrid.core.constants import COLOR_TO_IDX, COLORS, DIR_TO_VEC, OBJECT_TO_IDX, STATE_TO_IDX
from minigrid.core.world_object import Ball, Key, Wall

from sb3_hhp.goals import SUCCESS_KEY, MiniGridEgocentricObs, MiniGridGoalSpace, make_goal_space, wrap_env
from sb3_hhp.goals.minigrid import blockers, encode_grid, grid_codes
from sb3_hhp.hierarchy.encoders import GridInput
from sb3_hhp.label.app import layout_goal_space
from sb3_hhp.goals.minigrid import (BLOCKS, GOAL_OUT_OF_REACH, MAX_COUNTED_DOORS, N_OBJECTS, N_STATES, NO_GOAL_SQUARE,
                                    OPEN_DOORS, RELATIVE, SAME_COLOR, TARGET)
from sb3_hhp.oracles import Label, MiniGridScriptedOracle, Query, scripted
from sb3_hhp.oracles.registry import make_oracle
from sb3_hhp.oracles.scripted import plan_keys, plan_steps

EMPTY = OBJECT_TO_IDX["empty"]
WALL = OBJECT_TO_IDX["wall"]
KEY = OBJECT_TO_IDX["key"]
DOOR = OBJECT_TO_IDX["door"]
GOAL = OBJECT_TO_IDX["goal"]
OPEN, CLOSED, LOCKED = STATE_TO_IDX["open"], STATE_TO_IDX["closed"], STATE_TO_IDX["locked"]

# the situations of a DoorKey plan, as (carried, front, front state) keys
FACING_KEY = (EMPTY, KEY, 0)
CARRYING_KEY = (KEY, EMPTY, 0)
FACING_LOCKED_DOOR = (EMPTY, DOOR, LOCKED)
CARRYING_KEY_FACING_LOCKED_DOOR = (KEY, DOOR, LOCKED)
CARRYING_KEY_FACING_OPEN_DOOR = (KEY, DOOR, OPEN)
CARRYING_KEY_FACING_GOAL = (KEY, GOAL, 0)


def _cell(grid, x: int, y: int) -> np.ndarray:
    """MiniGrid's encoding of one cell (empty and out-of-grid cells as Grid.encode writes them)."""
    if not (0 <= x < grid.width and 0 <= y < grid.height):
        return np.zeros(3, np.uint8)
    obj = grid.get(x, y)
    return np.array([EMPTY, 0, 0], np.uint8) if obj is None else np.asarray(obj.encode(), np.uint8)


def _find(base, type_name: str) -> tuple[int, int]:
    for x in range(base.width):
        for y in range(base.height):
            obj = base.grid.get(x, y)
            if obj is not None and obj.type == type_name:
                return x, y
    raise AssertionError(f"no {type_name} in the grid")


def _place(base, pos: tuple[int, int], direction: int) -> None:
    base.agent_pos = (int(pos[0]), int(pos[1]))
    base.agent_dir = int(direction)


@pytest.fixture
def doorkey5():
    env = MiniGridEgocentricObs(gym.make("MiniGrid-DoorKey-5x5-v0"))
    env.reset(seed=3)
    yield env
    env.close()


def test_wrap_env_and_goal_space_auto() -> None:
    raw = gym.make("MiniGrid-DoorKey-5x5-v0")
    wrapped = wrap_env(raw)
    assert isinstance(wrapped, MiniGridEgocentricObs)
    # 5x5 grid -> a (2 * 5 - 3)-square egocentric canvas of (object, colour, state)
    assert wrapped.observation_space.shape == (7, 7, 3)
    assert wrap_env(wrapped) is wrapped  # already wrapped: left alone
    assert isinstance(make_goal_space("auto", wrapped), MiniGridGoalSpace)
    obs, _ = wrapped.reset(seed=0)
    assert wrapped.observation_space.contains(obs)


def test_minigrids_own_observation_is_skipped_only_where_nothing_reads_it() -> None:
    from minigrid.wrappers import ImgObsWrapper
    from stable_baselines3.common.monitor import Monitor

    fast = MiniGridEgocentricObs(Monitor(gym.make("MiniGrid-DoorKey-8x8-v0")))
    # a wrapper in between that reads MiniGrid's image keeps MiniGrid's own observation
    reader = MiniGridEgocentricObs(ImgObsWrapper(gym.make("MiniGrid-DoorKey-8x8-v0")))
    assert "gen_obs" in vars(fast.unwrapped) and "gen_obs" not in vars(reader.unwrapped)
    image, _ = reader.env.reset(seed=3)
    assert image.any()  # ImgObsWrapper still sees the real 7x7 view
    # the egocentric observation is the same whether MiniGrid built its own or not
    obs_fast, _ = fast.reset(seed=3)
    obs_reader, _ = reader.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(200):
        np.testing.assert_array_equal(obs_fast, obs_reader)
        action = int(rng.integers(fast.action_space.n))
        obs_fast, reward_fast, term_fast, trunc_fast, _ = fast.step(action)
        obs_reader, reward_reader, term_reader, trunc_reader, _ = reader.step(action)
        assert (reward_fast, term_fast, trunc_fast) == (reward_reader, term_reader, trunc_reader)
        if term_fast or trunc_fast:
            obs_fast, _ = fast.reset(seed=4)
            obs_reader, _ = reader.reset(seed=4)
    assert fast.unwrapped.gen_obs()["image"].shape == fast.unwrapped.observation_space["image"].shape


@pytest.mark.parametrize("env_id", ["MiniGrid-DoorKey-8x8-v0", "MiniGrid-KeyCorridorS3R1-v0", "MiniGrid-MultiRoom-N2-S4-v0"])
def test_the_canvas_leaves_out_only_its_always_empty_outer_ring(env_id: str) -> None:
    """The egocentric canvas of side 2 * max(W, H) - 3 is the 2 * max(W, H) - 1 canvas (from which the agent sees the
    whole grid wherever it stands, built here from the full grid) without its outer ring, which stays empty on every
    step of random play."""
    cropped = MiniGridEgocentricObs(gym.make(env_id))
    base = cropped.unwrapped
    side = 2 * max(base.width, base.height) - 1
    assert cropped.observation_space.shape == (side - 2, side - 2, 3)
    obs, _ = cropped.reset(seed=1)
    rng = np.random.default_rng(1)
    for _ in range(300):
        full = encode_grid(base.grid)
        ax, ay = (int(v) for v in base.agent_pos)
        full[ax, ay] = base.carrying.encode() if base.carrying is not None else (1, 0, 0)
        ring = np.zeros((side, side, 3), np.uint8)
        ring[side // 2 - ax : side // 2 - ax + base.width, side // 2 - ay : side // 2 - ay + base.height] = full
        ring = np.rot90(ring, (3 - int(base.agent_dir)) % 4, axes=(0, 1))
        assert not ring[[0, -1]].any() and not ring[:, [0, -1]].any()  # the ring is empty
        np.testing.assert_array_equal(obs, ring[1:-1, 1:-1])
        assert cropped.observation_space.contains(obs)
        obs, _, terminated, truncated, _ = cropped.step(int(rng.integers(cropped.action_space.n)))
        if terminated or truncated:
            obs, _ = cropped.reset()


@pytest.mark.parametrize("env_id, walled", [("MiniGrid-DoorKey-8x8-v0", True), ("MiniGrid-KeyCorridorS3R1-v0", True),
                                            ("MiniGrid-FourRooms-v0", True), ("MiniGrid-ObstructedMaze-1Q-v1", True),
                                            ("MiniGrid-MultiRoom-N6-v0", False)])
def test_the_canvas_ring_only_shows_the_border_wall_so_the_inner_view_loses_nothing(env_id: str, walled: bool) -> None:
    """On a grid with a border wall, the outermost ring of the canvas holds only that wall or nothing, and the whole
    canvas is a function of the cells inside that ring (no two states seen in random play share those cells and
    differ in the ring): the sub-goal learners' ``view="inner"`` reads everything the canvas tells. MultiRoom's grid
    has no border wall: there the ring shows only the grid's edge cells, walls or the void between rooms."""
    env = MiniGridEgocentricObs(gym.make(env_id))
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(3)
    rings: dict[bytes, bytes] = {}
    allowed = {(0, 0, 0), tuple(Wall().encode())} | (set() if walled else {(OBJECT_TO_IDX["empty"], 0, 0)})
    for step in range(600):
        ring = np.concatenate([obs[0], obs[-1], obs[:, 0], obs[:, -1]])
        assert set(map(tuple, ring.tolist())) <= allowed
        if walled:
            assert rings.setdefault(obs[1:-1, 1:-1].tobytes(), ring.tobytes()) == ring.tobytes()
        obs, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            obs, _ = env.reset(seed=step)
    assert len(rings) > 50 or not walled


@pytest.mark.parametrize("env_id", ["MiniGrid-DoorKey-8x8-v0", "MiniGrid-KeyCorridorS3R3-v0", "MiniGrid-ObstructedMaze-1Q-v1"])
def test_the_grid_encoding_is_minigrids_own(env_id: str) -> None:
    from sb3_hhp.goals.minigrid import encode_grid

    env = gym.make(env_id)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    seen_states = set()
    for _ in range(400):  # random play opens, unlocks and picks up: doors' and boxes' encodings change
        grid = env.unwrapped.grid
        encoded = encode_grid(grid)
        np.testing.assert_array_equal(encoded, grid.encode())
        assert encoded.dtype == np.uint8 and encoded.shape == (grid.width, grid.height, 3)
        seen_states.update(np.unique(encoded[..., 2]).tolist())
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            env.reset()
    assert len(seen_states) >= 2  # the state channel varied (doors of more than one state)


@pytest.mark.parametrize("direction", [0, 1, 2, 3])
def test_egocentric_obs_agent_at_centre_facing_up(doorkey5: MiniGridEgocentricObs, direction: int) -> None:
    base = doorkey5.unwrapped
    _place(base, base.agent_pos, direction)
    obs = doorkey5.observation(None)
    c = obs.shape[0] // 2
    ax, ay = (int(v) for v in base.agent_pos)
    # the agent's own cell holds what it carries: nothing
    np.testing.assert_array_equal(obs[c, c], [EMPTY, 0, 0])
    # "up" in the canvas (y - 1) is the env's front cell, whatever the agent's direction
    fx, fy = (int(v) for v in base.front_pos)
    np.testing.assert_array_equal(obs[c, c - 1], _cell(base.grid, fx, fy))
    # and the rest of the neighbourhood is rotated with it: left, right and behind
    for canvas_offset, turn in (((-1, 0), -1), ((1, 0), 1), ((0, 1), 2)):
        dx, dy = DIR_TO_VEC[(direction + turn) % 4]
        expected = _cell(base.grid, ax + dx, ay + dy)
        np.testing.assert_array_equal(obs[c + canvas_offset[0], c + canvas_offset[1]], expected)
    # every grid cell appears exactly once: the canvas holds as many walls as the grid
    n_walls = sum(_cell(base.grid, x, y)[0] == WALL for x in range(base.width) for y in range(base.height))
    assert int((obs[..., 0] == WALL).sum()) == n_walls


def test_egocentric_obs_shows_the_carried_object_in_the_agent_cell(doorkey5: MiniGridEgocentricObs) -> None:
    base = doorkey5.unwrapped
    base.carrying = Ball("blue")
    obs = doorkey5.observation(None)
    c = obs.shape[0] // 2
    np.testing.assert_array_equal(obs[c, c], Ball("blue").encode())
    assert MiniGridGoalSpace().key(obs)[0] == OBJECT_TO_IDX["ball"]
    assert MiniGridGoalSpace(use_color=True).key(obs)[:2] == tuple(int(v) for v in Ball("blue").encode()[:2])


def test_keys_along_a_scripted_doorkey_episode(doorkey5: MiniGridEgocentricObs) -> None:
    """Turn to the key, pick it up, open the door, reach the goal: each key read off the observation."""
    goal_space = MiniGridGoalSpace()
    base = doorkey5.unwrapped
    actions = base.actions
    kx, ky = _find(base, "key")
    dx_, dy_ = _find(base, "door")
    gx, gy = _find(base, "goal")

    # stand beside the key (above or below it, inside the left room), facing away; turn to face it
    below_free = base.grid.get(kx, ky + 1) is None and (kx, ky + 1) != (dx_, dy_)
    stand, facing = ((kx, ky + 1), 3) if below_free else ((kx, ky - 1), 1)
    _place(base, stand, (facing + 2) % 4)
    obs = doorkey5.observation(None)
    assert goal_space.key(obs)[0] == EMPTY and goal_space.key(obs) != FACING_KEY
    obs, *_ = doorkey5.step(actions.left)
    obs, *_ = doorkey5.step(actions.left)
    assert base.agent_dir == facing
    assert goal_space.key(obs) == FACING_KEY
    assert goal_space.describe(FACING_KEY) == "carrying nothing, facing key"

    obs, *_ = doorkey5.step(actions.pickup)
    assert base.carrying is not None and base.carrying.type == "key"
    assert goal_space.key(obs) == CARRYING_KEY

    # stand in front of the locked door (west of it, where the agent's room is), facing it
    _place(base, (dx_ - 1, dy_), 0)
    obs = doorkey5.observation(None)
    assert goal_space.key(obs) == CARRYING_KEY_FACING_LOCKED_DOOR
    assert goal_space.describe(CARRYING_KEY_FACING_LOCKED_DOOR) == "carrying key, facing locked door"
    obs, *_ = doorkey5.step(actions.toggle)
    assert base.grid.get(dx_, dy_).is_open
    assert goal_space.key(obs) == CARRYING_KEY_FACING_OPEN_DOOR

    # face the goal from the cell above it and step on it
    _place(base, (gx, gy - 1), 1)
    obs = doorkey5.observation(None)
    assert goal_space.key(obs) == CARRYING_KEY_FACING_GOAL
    obs, reward, terminated, _, _ = doorkey5.step(actions.forward)
    assert terminated and reward > 0
    key = goal_space.terminal_key(obs, float(reward), terminated)
    assert key == SUCCESS_KEY
    assert goal_space.achieved(key, SUCCESS_KEY) and not goal_space.achieved(key, CARRYING_KEY_FACING_GOAL)
    # without the reward, the same observation is an ordinary key
    assert goal_space.terminal_key(obs, 0.0, False) == goal_space.key(obs) != SUCCESS_KEY


def test_image_of_draws_the_egocentric_observation(doorkey5: MiniGridEgocentricObs) -> None:
    goal_space = MiniGridGoalSpace(tile_size=8)
    base = doorkey5.unwrapped
    kx, ky = _find(base, "key")
    below_free = base.grid.get(kx, ky + 1) is None
    _place(base, *(((kx, ky + 1), 3) if below_free else ((kx, ky - 1), 1)))
    obs = doorkey5.observation(None)
    image = goal_space.image_of(obs)
    size = obs.shape[0] * 8
    assert image.shape == (size, size, 3) and image.dtype == np.uint8
    c = obs.shape[0] // 2

    def tile(x: int, y: int) -> np.ndarray:
        return image[y * 8 : (y + 1) * 8, x * 8 : (x + 1) * 8].reshape(-1, 3)

    red, yellow = np.asarray(COLORS["red"]), np.asarray(COLORS["yellow"])
    assert (tile(c, c) == red).all(axis=1).any()  # the agent, in the centre
    assert (tile(c, c - 1) == yellow).all(axis=1).any()  # the (yellow) key in front of it
    assert not (tile(c, c + 1) == yellow).all(axis=1).any()
    # a different situation draws a different image
    _place(base, base.agent_pos, (base.agent_dir + 2) % 4)
    assert not np.array_equal(goal_space.image_of(doorkey5.observation(None)), image)


def test_render_gives_the_rgb_frame_of_the_env(doorkey5: MiniGridEgocentricObs) -> None:
    frame = MiniGridGoalSpace(tile_size=8).render(doorkey5)
    assert frame.shape == (5 * 8, 5 * 8, 3) and frame.dtype == np.uint8


# ---------------------------------------------------------------------------- scripted oracle


def _query(state_info: dict, key1: tuple, key2: tuple) -> Query:
    zeros = np.zeros((3, 3, 3), np.uint8)
    return Query(
        state=zeros, goal1=0, goal2=1, goal1_obs=zeros, goal2_obs=zeros,
        info={"state": state_info, "goal1_key": list(key1), "goal2_key": list(key2)},
    )


@pytest.mark.parametrize("env_id", ["MiniGrid-DoorKey-8x8-v0", "MiniGrid-DoorKey-16x16-v0"])
@pytest.mark.parametrize("seed", [0, 1])
def test_plan_milestones_in_order(env_id: str, seed: int) -> None:
    env = wrap_env(gym.make(env_id))
    env.reset(seed=seed)
    goal_space = MiniGridGoalSpace()
    keys = plan_keys(goal_space.privileged(env), goal_space)
    assert keys is not None and keys[-1] == SUCCESS_KEY
    milestones = [FACING_KEY, CARRYING_KEY_FACING_LOCKED_DOOR, CARRYING_KEY_FACING_OPEN_DOOR, CARRYING_KEY_FACING_GOAL]
    positions = [keys.index(key) for key in milestones]
    assert positions == sorted(positions) and len(set(positions)) == 4
    assert positions[-1] == len(keys) - 2  # facing the goal, then one step onto it
    assert SUCCESS_KEY not in keys[:-1]
    # the plan is a shortest one: the agent never faces the locked door without the key
    assert FACING_LOCKED_DOOR not in keys
    env.close()


@pytest.mark.parametrize("env_id", ["MiniGrid-DoorKey-8x8-v0", "MiniGrid-DoorKey-16x16-v0"])
def test_scripted_oracle_preferences(env_id: str) -> None:
    env = wrap_env(gym.make(env_id))
    env.reset(seed=0)
    goal_space = MiniGridGoalSpace()
    oracle = MiniGridScriptedOracle()
    start = goal_space.privileged(env)
    # at the start: the key before the locked door, in either order of the question
    assert oracle.answer(_query(start, FACING_KEY, FACING_LOCKED_DOOR)) == Label.FIRST
    assert oracle.answer(_query(start, FACING_LOCKED_DOOR, FACING_KEY)) == Label.SECOND
    # two sub-goals off the plan: equal
    off_plan_1, off_plan_2 = (EMPTY, OBJECT_TO_IDX["ball"], 0), (OBJECT_TO_IDX["box"], WALL, 0)
    assert oracle.answer(_query(start, off_plan_1, off_plan_2)) == Label.EQUAL

    # once the key is carried: "carrying the key, facing the locked door" beats "facing the key"
    base = env.unwrapped
    kx, ky = _find(base, "key")
    base.carrying = base.grid.get(kx, ky)
    base.grid.set(kx, ky, None)
    carrying = goal_space.privileged(env)
    assert carrying["carrying"][0] == KEY
    assert oracle.answer(_query(carrying, CARRYING_KEY_FACING_LOCKED_DOOR, FACING_KEY)) == Label.FIRST
    assert oracle.answer(_query(carrying, FACING_KEY, CARRYING_KEY_FACING_LOCKED_DOOR)) == Label.SECOND
    # the asynchronous protocol gives the same answer, under the oracle's name
    query = _query(carrying, CARRYING_KEY_FACING_LOCKED_DOOR, FACING_KEY)
    oracle.submit([query])
    (answer,) = oracle.collect()
    assert (answer.query_id, answer.label, answer.annotator) == (query.query_id, Label.FIRST, "scripted")
    env.close()


def test_the_locked_door_walked_past_is_no_milestone() -> None:
    """DoorKey-8x8 seed 9: a shortest plan turns past the locked door, empty-handed, on its way to the key. The
    oracle still names the key first; facing the key, the door just opened and the goal are where the plan acts."""
    env = wrap_env(gym.make("MiniGrid-DoorKey-8x8-v0"))
    env.reset(seed=9)
    goal_space = MiniGridGoalSpace()
    start = goal_space.privileged(env)
    steps = plan_steps(start, goal_space)
    keys = [key for key, _ in steps]
    assert plan_keys(start, goal_space) == keys
    assert keys.index(FACING_LOCKED_DOOR) < keys.index(FACING_KEY)  # the layout this test is about
    acted = dict(reversed(steps))  # each key's first occurrence
    assert not acted[FACING_LOCKED_DOOR]
    assert acted[FACING_KEY] and acted[CARRYING_KEY] and acted[CARRYING_KEY_FACING_LOCKED_DOOR]
    assert acted[CARRYING_KEY_FACING_OPEN_DOOR] and acted[CARRYING_KEY_FACING_GOAL]
    oracle = MiniGridScriptedOracle()
    assert oracle.answer(_query(start, FACING_KEY, FACING_LOCKED_DOOR)) == Label.FIRST
    assert oracle.answer(_query(start, FACING_LOCKED_DOOR, FACING_KEY)) == Label.SECOND
    # walked past, the door still ranks before what the plan never meets
    assert oracle.answer(_query(start, FACING_LOCKED_DOOR, (EMPTY, OBJECT_TO_IDX["ball"], 0))) == Label.FIRST
    env.close()


def test_scripted_oracle_needs_privileged_info() -> None:
    zeros = np.zeros((3, 3, 3), np.uint8)
    query = Query(state=zeros, goal1=0, goal2=1, goal1_obs=zeros, goal2_obs=zeros, info={})
    with pytest.raises(ValueError, match="Query.info"):
        MiniGridScriptedOracle().answer(query)


def test_plan_of_a_state_that_needs_the_key_in_hand() -> None:
    """A hand-built 5x5 DoorKey: the plan from beside the key is pick up -> door -> goal, with no detour."""
    env = wrap_env(gym.make("MiniGrid-DoorKey-5x5-v0"))
    env.reset(seed=3)
    base = env.unwrapped
    kx, ky = _find(base, "key")
    base.grid.set(kx, ky, None)
    base.carrying = Key("yellow")
    keys = plan_keys(MiniGridGoalSpace().privileged(env))
    assert keys is not None and keys[-1] == SUCCESS_KEY
    assert all(key[0] == KEY for key in keys[:-1])  # never drops the key on a shortest plan
    assert keys.index(CARRYING_KEY_FACING_LOCKED_DOOR) < keys.index(CARRYING_KEY_FACING_OPEN_DOOR)
    env.close()


def test_choosable_subgoals_are_one_skill_away() -> None:
    """The meta-controller's mask: a sub-goal already achieved is not choosable; with the same carried object
    only objects one interacts with; a change of what is carried only as a pick-up of the object in front (then
    facing the emptied cell) or a drop of what is carried, whatever is in front (then facing the dropped object);
    success always (without what the state holds)."""
    space = MiniGridGoalSpace()
    key_, wall, empty, door, goal = (OBJECT_TO_IDX[name] for name in ("key", "wall", "empty", "door", "goal"))
    facing_key = (empty, key_, 0)
    assert not space.choosable(facing_key, facing_key)
    assert space.choosable(facing_key, (key_, empty, 0))  # picking the key up
    assert not space.choosable(facing_key, (key_, wall, 0))  # picking it up, then turning to a wall
    assert not space.choosable(facing_key, (key_, door, 2))  # picking it up, then walking to the locked door
    assert not space.choosable(facing_key, (empty, wall, 0))
    assert not space.choosable(facing_key, (empty, empty, 0))
    assert space.choosable(facing_key, (empty, door, 2))
    assert space.choosable(facing_key, (empty, goal, 0))
    assert space.choosable(facing_key, SUCCESS_KEY)
    facing_wall = (empty, wall, 0)
    assert not space.choosable(facing_wall, (key_, empty, 0))  # walking to the key and picking it up: two skills
    assert space.choosable(facing_wall, facing_key)
    assert not space.choosable((empty, door, 2), (key_, empty, 0))  # a door cannot be picked up
    assert not space.choosable((empty, goal, 0), (key_, empty, 0))
    carrying = (key_, wall, 0)
    assert not space.choosable(carrying, (key_, empty, 0))  # already carrying it: just a turn
    assert space.choosable(carrying, (key_, door, 2))  # walking to the locked door with the key
    assert space.choosable((key_, door, 2), (key_, door, 0))  # opening it
    assert space.choosable(carrying, (empty, key_, 0))  # a wall in front: turning to a free cell, dropping it
    assert space.choosable((key_, door, 0), (empty, key_, 0))  # the door just opened: dropping the key there
    assert not space.choosable((key_, door, 0), (empty, door, 0))  # dropping it, then facing the door: two skills
    assert space.choosable((key_, empty, 0), (empty, key_, 0))  # dropping it: the key lies in front
    assert not space.choosable((key_, empty, 0), (empty, empty, 0))  # dropping it, then turning away
    assert not space.choosable(carrying, (empty, empty, 0))
    assert not space.choosable(carrying, (empty, door, 2))
    assert not space.choosable(SUCCESS_KEY, SUCCESS_KEY)
    assert space.choosable(SUCCESS_KEY, facing_key)
    colored = MiniGridGoalSpace(use_color=True)  # (carried, its colour, front, its colour, state)
    assert colored.choosable((empty, 0, key_, 4, 0), (key_, 4, empty, 0, 0))
    assert not colored.choosable((empty, 0, key_, 4, 0), (key_, 1, empty, 0, 0))  # the key in front is yellow, not green
    assert not colored.choosable((empty, 0, key_, 4, 0), (key_, 4, door, 4, 2))
    assert colored.choosable((key_, 4, empty, 0, 0), (empty, 0, key_, 4, 0))
    assert not colored.choosable((key_, 4, empty, 0, 0), (empty, 0, key_, 1, 0))  # it drops the key it carries


def test_opening_the_box_in_front_is_a_choice_of_what_it_holds() -> None:
    """ObstructedMaze hides its keys in boxes, and an observation shows no box's contents: in front of a box,
    "facing a key" is a choice (the toggle leaves the key in the box's place) though no key lies within reach, and
    the toggle does reach it; facing a box is no such choice elsewhere, and a box opens into what can be picked
    up, never a door."""
    key_, box, ball, door, empty = (OBJECT_TO_IDX[name] for name in ("key", "box", "ball", "door", "empty"))
    env = wrap_env(gym.make("MiniGrid-ObstructedMaze-1Q-v1"))
    space = make_goal_space(MiniGridGoalSpace(keep_doors_open=True), env)  # colours ignored, so keys read short
    env.reset(seed=0)
    base = env.unwrapped
    bx, by = _find(base, "box")
    assert base.grid.get(bx, by).contains.type == "key"
    direction, (dx, dy) = next((d, DIR_TO_VEC[d]) for d in range(4)
                               if base.grid.get(bx - DIR_TO_VEC[d][0], by - DIR_TO_VEC[d][1]) is None)
    _place(base, (bx - dx, by - dy), direction)
    obs = env.observation(None)
    facing_box, facing_key = space.key(obs), (empty, key_, 0)
    present = space.present(obs)
    assert facing_box == (empty, box, 0)
    assert (key_, 0) not in present  # both keys are in boxes
    assert space.choosable(facing_box, facing_key, present)
    assert space.choosable(facing_box, (empty, ball, 0), present)  # what a box holds is not seen
    assert not space.choosable(facing_box, (empty, door, STATE_TO_IDX["open"]), present)  # a door is no content
    assert not space.choosable((empty, ball, 0), facing_key, present)  # only the box in front opens into one
    assert space.choosable((key_, box, 0), (key_, key_, 0), present)  # a box opens whatever the agent carries
    obs, *_ = env.step(Actions.toggle)
    assert space.key(obs) == facing_key
    env.close()


def test_walks_are_choosable_only_to_objects_within_reach() -> None:
    """With what the state holds (``present``), a walk is a choice only to an object the agent can reach without
    opening anything: not "facing the locked door" while the key lies in the only way to it, nor once the door is
    open, nor "facing the key" once it is carried; "task solved" only once the goal square is within reach;
    toggling the door in front stays a choice. ``present`` leaves out the agent's cell."""
    space = MiniGridGoalSpace()
    key_, door, empty, goal = (OBJECT_TO_IDX[name] for name in ("key", "door", "empty", "goal"))
    locked, opened = STATE_TO_IDX["locked"], STATE_TO_IDX["open"]
    env = wrap_env(gym.make("MiniGrid-DoorKey-5x5-v0"))
    obs, _ = env.reset(seed=0)
    # this layout: the key lies in the one cell next to the locked door, the goal behind the door
    assert space.present(obs) == {(key_, 0), GOAL_OUT_OF_REACH}
    start = space.key(obs)
    assert space.choosable(start, (empty, key_, 0), space.present(obs))
    assert not space.choosable(start, SUCCESS_KEY, space.present(obs))
    assert space.choosable(start, SUCCESS_KEY)  # without present: always
    base = env.unwrapped
    (kx, ky), = [(x, y) for x in range(base.width) for y in range(base.height) if base.grid.get(x, y) is not None
                 and base.grid.get(x, y).type == "key"]
    base.carrying = base.grid.get(kx, ky)
    base.grid.set(kx, ky, None)
    carrying = (key_, empty, 0)
    present = space.present(env.observation(None))
    assert present == {(door, locked), GOAL_OUT_OF_REACH}  # the carried key is in the agent's cell: not "present"
    assert space.choosable(carrying, (key_, door, locked), present)
    assert not space.choosable(carrying, SUCCESS_KEY, present)
    door_cell = next(base.grid.get(x, y) for x in range(base.width) for y in range(base.height)
                     if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "door")
    door_cell.is_locked, door_cell.is_open = False, True
    present = space.present(env.observation(None))
    assert present == {(door, opened), (goal, 0)}
    assert not space.choosable(carrying, (key_, door, locked), present)
    assert not space.choosable((key_, door, opened), (key_, door, locked), present)  # no toggle locks a door
    # closing the door in front is no choice: an open-close loop would succeed at every choice
    assert not space.choosable((key_, door, opened), (key_, door, STATE_TO_IDX["closed"]), present)
    assert space.choosable((key_, door, STATE_TO_IDX["closed"]), (key_, door, opened), present)  # opening it is
    # walking to another closed door within reach stays a choice
    assert space.choosable((key_, door, opened), (key_, door, STATE_TO_IDX["closed"]), present | {(door, STATE_TO_IDX["closed"])})
    assert space.choosable(carrying, (key_, door, locked))  # without present: the key-only rule
    assert space.choosable(carrying, (key_, door, opened), present)
    assert space.choosable(carrying, (key_, goal, 0), present)
    assert space.choosable(carrying, SUCCESS_KEY, present)
    assert not space.choosable((empty, empty, 0), (empty, key_, 0), present)  # no key on the floor
    with_locked_door = frozenset({(door, locked), GOAL_OUT_OF_REACH})
    assert space.choosable((key_, door, locked), (key_, door, opened), with_locked_door)  # a toggle of the door in front
    assert not space.choosable((key_, empty, 0), (key_, door, opened), with_locked_door)  # walking to an open door: none
    colored = MiniGridGoalSpace(use_color=True)
    assert colored.present(obs) == {(key_, 4, 0), GOAL_OUT_OF_REACH}
    assert not colored.choosable((empty, 0, empty, 0, 0), (empty, 0, key_, 1, 0), colored.present(obs))  # no green key: the key is yellow
    assert colored.choosable((empty, 0, empty, 0, 0), (empty, 0, key_, 4, 0), colored.present(obs))


def test_within_reach_is_a_flood_fill_through_passable_cells() -> None:
    """On a hand-made egocentric grid: walls and a locked door stop the fill, an open door and the goal square
    let it through, an object next to a reached cell counts (the agent faces it from there), one behind a wall
    does not, and a grid with no goal square never reports one out of reach."""
    space = MiniGridGoalSpace()
    wall, key_, ball, door, goal = (OBJECT_TO_IDX[name] for name in ("wall", "key", "ball", "door", "goal"))
    empty = OBJECT_TO_IDX["empty"]
    locked, opened = STATE_TO_IDX["locked"], STATE_TO_IDX["open"]
    seen = []  # each state below, with the set it must give
    space.present = lambda obs: seen.append((obs.copy(), MiniGridGoalSpace.present(space, obs))) or seen[-1][1]
    obs = np.zeros((7, 7, 3), dtype=np.uint8)  # the agent at (3, 3)
    obs[1:6, 1:6, 0] = empty
    obs[:, 0, 0] = obs[:, 6, 0] = obs[0, :, 0] = obs[6, :, 0] = wall
    obs[1:6, 2, 0] = wall  # a wall across row y = 2, with a door at x = 3
    obs[3, 2] = (door, 0, locked)
    obs[1, 1] = (goal, 0, 0)  # behind the wall
    obs[5, 5] = (key_, 0, 0)  # in the agent's room, in a corner
    assert space.present(obs) == {(key_, 0), (door, locked), GOAL_OUT_OF_REACH}
    obs[3, 2] = (door, 0, opened)
    assert space.present(obs) == {(key_, 0), (door, opened), (goal, 0)}
    obs[4, 1] = (ball, 0, 0)  # reached through the open door: next to (3, 1) and (5, 1)
    assert (ball, 0) in space.present(obs)
    obs[3, 2] = (wall, 0, 0)
    assert space.present(obs) == {(key_, 0), GOAL_OUT_OF_REACH}
    obs[1, 1] = (empty, 0, 0)
    present = space.present(obs)
    assert present == {(key_, 0), NO_GOAL_SQUARE}  # no goal square: nothing is out of reach, the task ends with a pick-up
    # so "task solved" is one skill away only with empty hands in front of an object to pick up
    assert not space.choosable((empty, empty, 0), SUCCESS_KEY, present)
    assert space.choosable((empty, ball, 0), SUCCESS_KEY, present)
    assert space.choosable((empty, key_, 0), SUCCESS_KEY, present)
    assert not space.choosable((key_, ball, 0), SUCCESS_KEY, present)  # the key must be put down first
    assert not space.choosable((empty, door, opened), SUCCESS_KEY, present)
    # the states in one batch (a meta-controller's update masks a batch of closing states): each its own set, the
    # regions of one grid never joined to another's (the open door's state, next to the locked door's, in either order)
    states, sets = np.stack([obs for obs, _ in seen]), [within for _, within in seen]
    assert len(states) == len(set(sets)) == 5
    assert space.present_batch(states) == sets
    assert space.present_batch(states[::-1]) == sets[::-1]
    assert space.choosable((empty, empty, 0), SUCCESS_KEY)  # without present: always


def test_features_are_one_hots_of_carried_front_and_the_objects_present() -> None:
    """The predictor's description of a state: carried object, object in front, its state, then the (object,
    state) pairs present anywhere; two layouts of the same situation get the same description."""
    space = MiniGridGoalSpace()
    n_obj, n_state = len(OBJECT_TO_IDX), len(STATE_TO_IDX)
    obs = np.zeros((5, 5, 3), dtype=np.uint8)
    obs[..., 0] = OBJECT_TO_IDX["empty"]
    obs[2, 2] = (OBJECT_TO_IDX["key"], 4, 0)  # carrying a key
    obs[2, 1] = (OBJECT_TO_IDX["door"], 4, STATE_TO_IDX["locked"])  # facing a locked door
    obs[0, 4] = (OBJECT_TO_IDX["goal"], 1, 0)
    features = space.features(obs)
    assert features.shape == (1, 2 * n_obj + n_state + n_obj * n_state) and features.dtype == np.float32
    expected = np.zeros(features.shape[1], dtype=np.float32)
    expected[OBJECT_TO_IDX["key"]] = 1
    expected[n_obj + OBJECT_TO_IDX["door"]] = 1
    expected[2 * n_obj + STATE_TO_IDX["locked"]] = 1
    present = 2 * n_obj + n_state
    for name, state in (("empty", 0), ("key", 0), ("door", STATE_TO_IDX["locked"]), ("goal", 0)):
        expected[present + OBJECT_TO_IDX[name] * n_state + state] = 1
    np.testing.assert_array_equal(features[0], expected)
    moved = obs.copy()
    moved[0, 4], moved[4, 0] = obs[4, 0], obs[0, 4]  # the goal elsewhere: same description
    np.testing.assert_array_equal(space.features(np.stack([obs, moved])), np.repeat(features, 2, axis=0))
    assert MiniGridGoalSpace(use_color=True).features(obs).shape[1] == features.shape[1] + 2 * len(COLORS)


def test_plans_open_boxes_for_what_they_hold_and_stop_at_their_time_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    """ObstructedMaze: the key to the locked door lies in a box, and a ball blocks the door. The time limit is
    checked on a clock of the test's own (a millisecond a reading), so the machine's load cannot move it."""
    env = gym.make("MiniGrid-ObstructedMaze-1Q-v1")
    env.reset(seed=0)
    goal_space = MiniGridGoalSpace()
    facts = goal_space.privileged(env)
    base = env.unwrapped
    boxes = [(x, y) for x in range(base.width) for y in range(base.height)
             if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "box"]
    # the boxes' contents, which their encodings do not show
    assert sorted((x, y) for x, y, _ in facts["boxes"]) == sorted(boxes)
    assert all(held[0] == OBJECT_TO_IDX["key"] for _, _, held in facts["boxes"])
    keys = plan_keys(facts, goal_space)
    assert keys is not None and keys[-1] == SUCCESS_KEY
    box, key, ball = OBJECT_TO_IDX["box"], OBJECT_TO_IDX["key"], OBJECT_TO_IDX["ball"]
    facing_box = keys.index((EMPTY, box, 0))
    assert keys[facing_box + 1] == (EMPTY, key, 0)  # the box opened: its key lies in front
    assert keys.index((key, OBJECT_TO_IDX["door"], STATE_TO_IDX["locked"])) > facing_box
    assert (ball, EMPTY, 0) in keys  # the ball that blocked the door carried away
    # without the boxes' contents opening one leaves nothing: no plan, and the search stops at its time limit
    readings = []

    def clock() -> float:
        readings.append(None)
        return 0.001 * len(readings)

    monkeypatch.setattr(scripted, "time", SimpleNamespace(perf_counter=clock))
    assert plan_keys({**facts, "boxes": []}, goal_space, max_seconds=0.1) is None
    # one reading to set the deadline, then one every 256 states until one is past it (the 102nd, at 0.102 s):
    # stopped by the clock, neither sooner (running out of states) nor later
    assert len(readings) == 102
    with pytest.raises(ValueError, match="max_seconds"):
        MiniGridScriptedOracle(max_seconds=0)


def _random_walk_states(env_id: str, seed: int, n_states: int, every: int, use_color: bool = False) -> list[dict]:
    env = wrap_env(gym.make(env_id))
    env.reset(seed=seed)
    goal_space, rng, states = MiniGridGoalSpace(use_color=use_color), np.random.default_rng(seed), []
    for step in range(n_states * every):
        if step % every == 0:
            states.append(goal_space.privileged(env))
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            break
    env.close()
    return states


@pytest.mark.parametrize("env_id, seed", [("MiniGrid-DoorKey-6x6-v0", 0), ("MiniGrid-DoorKey-6x6-v0", 1),
                                          ("MiniGrid-ObstructedMaze-1Dl-v0", 0), ("MiniGrid-KeyCorridorS3R1-v0", 2)])
def test_the_search_heuristic_keeps_plans_shortest(env_id: str, seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The A* heuristic (moves through the cells the agent could ever stand on, a turn when the cell ahead is not
    nearer, a drop when the hands are full) never overestimates: plans are as short as a search without it (the
    distances all 0: breadth-first in effect). The weighted search's plans are valid and at most ``weight`` times
    as long."""
    from sb3_hhp.oracles import scripted

    goal_space = MiniGridGoalSpace(use_color=True)
    states = _random_walk_states(env_id, seed, n_states=4, every=7, use_color=True)
    guided = [plan_keys(state, goal_space) for state in states]
    weighted = [plan_keys(state, goal_space, weight=3.0) for state in states]
    monkeypatch.setattr(scripted, "_distances", lambda cells, ends: [[0] * len(cells[0]) for _ in cells])
    blind = [plan_keys(state, goal_space, max_nodes=2_000_000) for state in states]
    assert all(keys is not None for keys in guided + blind + weighted)
    assert [len(keys) for keys in guided] == [len(keys) for keys in blind]
    assert all(keys[-1] == SUCCESS_KEY and len(guided_keys) <= len(keys) <= 3 * len(guided_keys)
               for keys, guided_keys in zip(weighted, guided))
    with pytest.raises(ValueError, match="weight must be >= 1"):
        plan_keys(states[0], goal_space, weight=0.5)


def test_the_heuristic_counts_moves_around_walls() -> None:
    """Forward moves to the nearest end over every cell but walls and lava: doors and objects are passable."""
    from sb3_hhp.oracles.scripted import _distances

    wall, empty, door, ball = (OBJECT_TO_IDX[name] + 0 for name in ("wall", "empty", "door", "ball"))
    rows = ["#####",
            "#..E#",
            "#D###",
            "#.b.#",
            "#####"]
    codes = {"#": (wall, 0, 0), ".": (empty, 0, 0), "E": (empty, 0, 0), "D": (door, 0, 2), "b": (ball, 0, 0)}
    cells = [[codes[rows[y][x]] for y in range(5)] for x in range(5)]  # cells[x][y], as MiniGrid's grids
    distance = _distances(cells, [(3, 1)])
    assert distance[3][1] == 0 and distance[1][1] == 2
    assert distance[1][2] == 3 and distance[1][3] == 4  # through the (locked) door
    assert distance[3][3] == 6  # past the ball, which may be carried away; not through the walls (2 straight)


def test_the_oracle_falls_back_to_a_weighted_search(monkeypatch: pytest.MonkeyPatch) -> None:
    """A quarter of the time for a shortest plan; when none comes, the rest for one at most ``fallback_weight``
    times as long; "can't tell" when neither finds one."""
    from sb3_hhp.oracles import scripted

    env = wrap_env(gym.make("MiniGrid-DoorKey-5x5-v0"))
    env.reset(seed=0)
    state = MiniGridGoalSpace().privileged(env)
    calls = []

    def plan(info, goal_space, max_seconds=None, weight=1.0, **kwargs):
        calls.append((weight, max_seconds))
        return None if weight == 1.0 else [(SUCCESS_KEY, False)]

    oracle = MiniGridScriptedOracle(max_seconds=2.0, fallback_weight=3.0)
    monkeypatch.setattr(scripted, "plan_steps", plan)
    assert oracle.plan(state) == [(SUCCESS_KEY, False)] and oracle.last_plan_weight == 3.0
    assert calls == [(1.0, 0.5), (3.0, 1.5)]
    monkeypatch.setattr(scripted, "plan_steps", lambda *args, **kwargs: None)
    assert oracle.answer(_query(state, FACING_KEY, FACING_LOCKED_DOOR)) == Label.INCOMPARABLE
    monkeypatch.undo()
    assert oracle.plan(state) is not None and oracle.last_plan_weight == 1.0
    with pytest.raises(ValueError, match="fallback_weight"):
        MiniGridScriptedOracle(fallback_weight=0.5)
    env.close()


def test_a_carried_box_keeps_what_it_holds() -> None:
    """ObstructedMaze with the box that holds the door's key in the agent's hands (as a random walk leaves it):
    the plan drops the box, opens it and takes the key; without knowing what the carried box holds, no plan."""
    env = gym.make("MiniGrid-ObstructedMaze-1Q-v1")
    env.reset(seed=0)
    base = env.unwrapped
    locked = [obj for obj in base.grid.grid if obj is not None and obj.type == "door" and obj.is_locked]
    [(bx, by)] = [(x, y) for x in range(base.width) for y in range(base.height)
                  if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "box"
                  and base.grid.get(x, y).contains.color == locked[0].color]
    base.carrying = base.grid.get(bx, by)
    base.grid.set(bx, by, None)
    goal_space = MiniGridGoalSpace()
    facts = goal_space.privileged(env)
    assert facts["carrying_holds"][:2] == [KEY, COLOR_TO_IDX[locked[0].color]]
    keys = plan_keys(facts, goal_space)
    box = OBJECT_TO_IDX["box"]
    assert keys is not None and keys[-1] == SUCCESS_KEY
    assert keys.index((EMPTY, box, 0)) < keys.index((EMPTY, KEY, 0))  # put down, then opened
    assert keys.index((EMPTY, KEY, 0)) < keys.index((KEY, OBJECT_TO_IDX["door"], STATE_TO_IDX["locked"]))
    assert plan_keys({**facts, "carrying_holds": None}, goal_space, max_seconds=0.2) is None
    env.close()


def test_snapshots_are_compact_and_give_the_privileged_facts() -> None:
    """Training keeps a snapshot of every sub-goal choice while questions remain: the grid as a uint8 array, turned
    into the JSON facts of privileged() only for the choices a question is asked about."""
    import json
    import tracemalloc

    from sb3_hhp.goals.base import GoalSpace

    env = gym.make("MiniGrid-ObstructedMaze-1Q-v1")
    env.reset(seed=0)
    goal_space = MiniGridGoalSpace()
    snapshot = goal_space.snapshot(env)
    assert snapshot["grid"].dtype == np.uint8 and snapshot["grid"].shape == (env.unwrapped.width, env.unwrapped.height, 3)
    facts = goal_space.facts(snapshot)
    assert facts == goal_space.privileged(env) and facts["boxes"]
    assert json.loads(json.dumps(facts)) == facts  # JSON values, as questions store them
    assert isinstance(snapshot["grid"], np.ndarray)  # facts() left the snapshot as it was
    big = gym.make("MiniGrid-DoorKey-16x16-v0")
    big.reset(seed=0)
    tracemalloc.start()
    kept = [goal_space.snapshot(big) for _ in range(100)]
    per_snapshot = tracemalloc.get_traced_memory()[0] / len(kept)
    tracemalloc.stop()
    assert per_snapshot < 3_000  # the nested lists of privileged() take ~24 KB here

    class OwnFacts(GoalSpace):  # a goal space written before snapshots: its privileged facts are still recorded
        def supports(self, env: gym.Env) -> bool:
            return True

        def key(self, obs: np.ndarray) -> tuple:
            return ()

        def privileged(self, env: gym.Env) -> dict:
            return {"agent_pos": [1, 2]}

    own = OwnFacts()
    assert own.facts(own.snapshot(env)) == {"agent_pos": [1, 2]}


def test_keep_doors_open_masks_the_toggle_that_would_close_the_door_in_front() -> None:
    """With ``keep_doors_open`` the learners never close a door: ``toggle`` is masked where the cell in front is an
    open door, and only there; without it there is no mask."""
    door, empty = OBJECT_TO_IDX["door"], OBJECT_TO_IDX["empty"]
    obs = np.zeros((3, 7, 7, 3), dtype=np.uint8)
    obs[..., 0] = empty
    obs[0, 3, 2] = (door, 1, STATE_TO_IDX["open"])  # in front of the agent at (3, 3), facing up
    obs[1, 3, 2] = (door, 1, STATE_TO_IDX["closed"])
    obs[2, 3, 4] = (door, 1, STATE_TO_IDX["open"])  # behind it
    assert MiniGridGoalSpace().action_mask(obs) is None
    mask = MiniGridGoalSpace(keep_doors_open=True).action_mask(obs)
    assert mask.shape == (3, 7) and mask.dtype == bool
    toggle = int(Actions.toggle)
    assert mask[:, toggle].tolist() == [False, True, True]
    assert np.delete(mask, toggle, axis=1).all()
    assert MiniGridGoalSpace(keep_doors_open=True).action_mask(obs[0]).shape == (7,)  # one state
    # the goal space named for doors of several colours (ObstructedMaze) keeps them open and tells their colours apart
    env = wrap_env(gym.make("MiniGrid-ObstructedMaze-1Q-v1"))
    named = make_goal_space("minigrid_color_open_doors", env)
    assert named.use_color and named.keep_doors_open
    np.testing.assert_array_equal(named.action_mask(obs), mask)
    other = obs.copy()
    other[0, 3, 2, 1] = 3  # the same open door in front, another colour
    assert named.key(obs[0]) != named.key(other[0])
    # minigrid_open_doors reads colours only where the task's grids hold keys of several colours, and then as they
    # relate to the carried object's: with empty hands the door's colour does not matter, with a key in hand it does
    colored = make_goal_space("minigrid_open_doors", env)
    assert colored.relative_color and colored.key(obs[0]) == colored.key(other[0])
    obs[0, 3, 3] = other[0, 3, 3] = (KEY, 1, 0)  # a green key in hand: the door in front green, or purple
    assert colored.key(obs[0]) != colored.key(other[0])
    env.close()
    doorkey = wrap_env(gym.make("MiniGrid-DoorKey-8x8-v0"))
    plain = make_goal_space("minigrid_open_doors", doorkey)
    assert not plain.use_color and plain.keep_doors_open
    assert plain.key(obs[0]) == plain.key(other[0])
    doorkey.close()


def _doors(base) -> list:
    return [base.grid.get(x, y) for x in range(base.width) for y in range(base.height)
            if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "door"]


def test_count_open_doors_tells_opening_a_door_from_turning_to_an_open_one() -> None:
    """With ``count_open_doors``, a key facing an open door holds how many doors are open: the toggle of the
    closed door in front reaches (nothing, door, open, n + 1), turning to a door opened before reaches (..., n).
    The mask offers each only where it is one skill away, the features count the open doors, and the scripted
    oracle's plan names the keys the goal space reads."""
    space = MiniGridGoalSpace(keep_doors_open=True, count_open_doors=True)
    env = wrap_env(gym.make("MiniGrid-KeyCorridorS3R3-v0"))
    env.reset(seed=5)
    base = env.unwrapped
    closed = [door for door in _doors(base) if not door.is_open and not door.is_locked]
    assert len(closed) >= 2
    first, second = closed[0], closed[1]
    first.is_open = True  # one door opened before
    # the agent in front of the second, closed, door
    (dx, dy), = [(x, y) for x in range(base.width) for y in range(base.height) if base.grid.get(x, y) is second]
    for direction, (vx, vy) in enumerate(DIR_TO_VEC):
        cx, cy = dx - int(vx), dy - int(vy)
        if base.grid.get(cx, cy) is None:
            _place(base, (cx, cy), direction)
            break
    obs = env.observation(None)
    closed_key = space.key(obs)
    assert closed_key == (EMPTY, DOOR, STATE_TO_IDX["closed"])  # no count where the door in front is not open
    present = space.present(obs)
    assert (OPEN_DOORS, 1) in present
    assert space.choosable(closed_key, (EMPTY, DOOR, OPEN, 2), present)  # open the door in front
    assert not space.choosable(closed_key, (EMPTY, DOOR, OPEN, 3), present)  # two doors more: not one skill
    reachable = (DOOR, OPEN) in present
    assert space.choosable(closed_key, (EMPTY, DOOR, OPEN, 1), present) == reachable  # walk to the one open before
    features = space.features(obs)
    obs, *_ = env.step(int(Actions.toggle))
    assert space.key(obs) == (EMPTY, DOOR, OPEN, 2)
    assert (OPEN_DOORS, 2) in space.present(obs)
    assert not space.choosable(space.key(obs), (EMPTY, DOOR, OPEN, 3), space.present(obs))  # toggling would close it
    assert not np.array_equal(space.features(obs), features)
    counted = space.features(np.stack([obs, obs]))[:, 2 * len(OBJECT_TO_IDX) + len(STATE_TO_IDX):][:, :MAX_COUNTED_DOORS]
    assert counted.argmax(axis=1).tolist() == [2, 2] and counted.sum() == 2
    assert MiniGridGoalSpace().key(obs) == (EMPTY, DOOR, OPEN)  # without the option: the three numbers
    assert "2 open" in space.describe(space.key(obs))
    # the oracle's plan counts the doors it opens on its way, from the doors open at the start
    env.reset(seed=5)
    keys = plan_keys(space.privileged(env), space)
    opened = [key[-1] for key in keys if key != SUCCESS_KEY and key[1:3] == (DOOR, OPEN)]
    assert opened and all(len(key) == 4 for key in keys if key != SUCCESS_KEY and key[1:3] == (DOOR, OPEN))
    assert sorted(opened) == opened and opened[0] == 1
    unlocked = [door for door in _doors(env.unwrapped) if not door.is_locked]
    for door in unlocked:
        door.is_open = True  # every door but the locked one open before the plan: it opens only the locked one
    shifted = [key[-1] for key in plan_keys(space.privileged(env), space) if key != SUCCESS_KEY and key[1:3] == (DOOR, OPEN)]
    assert set(shifted) <= {len(unlocked), len(unlocked) + 1} and len(unlocked) + 1 in shifted
    env.close()
    # the goal space named for it, and the scripted oracle made for it, count too
    named_env = wrap_env(gym.make("MiniGrid-KeyCorridorS3R3-v0"))
    named = make_goal_space("minigrid_count_doors", named_env)
    assert named.count_open_doors and named.keep_doors_open
    assert make_oracle("scripted", named, named_env.observation_space).goal_space.count_open_doors


def _blocking_ball(base) -> tuple[tuple[int, int], int]:
    """The cell in front of a ball that lies between a door and a free cell (ObstructedMaze's blocking balls), on the
    side away from the door, and the direction that faces the ball from there."""
    for x in range(base.width):
        for y in range(base.height):
            if not isinstance(base.grid.get(x, y), Ball):
                continue
            for direction, (vx, vy) in enumerate(DIR_TO_VEC):
                door = base.grid.get(x + int(vx), y + int(vy))
                if door is not None and door.type == "door" and base.grid.get(x - int(vx), y - int(vy)) is None:
                    return (x - int(vx), y - int(vy)), direction
    raise AssertionError("no ball blocks a door")


def _unmarked_obstructed_maze() -> gym.Env:
    """ObstructedMaze-1Q without the mission's ball marked (:data:`TARGET`, tested on its own below), so that a blocking
    ball can be made the object to pick up."""
    return MiniGridEgocentricObs(gym.make("MiniGrid-ObstructedMaze-1Q-v1"), mark_target=False)


def test_mark_blockers_tells_a_ball_in_the_way_from_one_moved_aside() -> None:
    """With ``mark_blockers``, a key that faces a ball in front of a door gives it the state BLOCKS: put back where it
    was, the ball still blocks; dropped beside the agent after a turn, it does not. :meth:`present` marks such objects
    as the keys do, the features and the description tell them apart, and the scripted oracle's plan names the same
    keys as the goal space reads in the env."""
    space = make_goal_space("minigrid_open_doors_blockers", _unmarked_obstructed_maze())
    assert space.mark_blockers and space.keep_doors_open
    plain = MiniGridGoalSpace(keep_doors_open=True)
    env = _unmarked_obstructed_maze()
    env.reset(seed=1)
    base = env.unwrapped
    ball = OBJECT_TO_IDX["ball"]
    cell, direction = _blocking_ball(base)
    _place(base, cell, direction)
    obs = env.observation(None)
    assert space.key(obs) == (EMPTY, ball, BLOCKS) and plain.key(obs) == (EMPTY, ball, 0)
    assert (ball, BLOCKS) in space.present(obs) and (ball, BLOCKS) not in plain.present(obs)
    assert "blocks the way" in space.describe(space.key(obs))
    obs, *_ = env.step(int(Actions.pickup))
    assert space.key(obs) == (ball, EMPTY, 0)
    put_back, *_ = env.step(int(Actions.drop))
    assert space.key(put_back) == (EMPTY, ball, BLOCKS)
    env.step(int(Actions.pickup))
    env.step(int(Actions.left))
    aside, *_ = env.step(int(Actions.drop))
    assert space.key(aside) == (EMPTY, ball, 0) == plain.key(aside)
    assert "blocks" not in space.describe(space.key(aside))
    assert (ball, 0) in space.present(aside)
    blocked = space.features(np.stack([put_back, aside]))
    assert blocked.shape[1] == plain.features(aside).shape[1] + 2
    assert not np.array_equal(blocked[0], blocked[1])
    # the oracle: with the agent turned away from the ball, the plan to pick it up turns to it first
    for state, expected in ((put_back, BLOCKS), (aside, 0)):
        env.reset(seed=1)
        cell, direction = _blocking_ball(base)
        target = base.grid.get(cell[0] + int(DIR_TO_VEC[direction][0]), cell[1] + int(DIR_TO_VEC[direction][1]))
        if expected == 0:  # moved aside as above
            base.grid.set(*(np.asarray(cell) + DIR_TO_VEC[direction]), None)
            beside = np.asarray(cell) + DIR_TO_VEC[(direction - 1) % 4]
            base.grid.set(*beside, target)
            direction = (direction - 1) % 4
        base.obj = target
        _place(base, cell, (direction + 1) % 4)
        keys = plan_keys(space.privileged(env), space)
        assert keys == [(EMPTY, ball, expected), SUCCESS_KEY]
        obs, *_ = env.step(int(Actions.left))
        assert space.key(obs) == keys[0]
        assert all(len(key) < 3 or key[2] != BLOCKS for key in plan_keys(plain.privileged(env), plain))
    assert make_oracle("scripted", space, env.observation_space).goal_space.mark_blockers
    env.close()


def test_count_blockers_counts_the_objects_in_the_way_in_the_features() -> None:
    """``count_blockers``: the features end their flags with a one-hot of how many objects block the way (0, 1, 2 or
    more), here ObstructedMaze-1Q's two balls in front of its locked doors, then one, then none; keys are unchanged."""
    space = make_goal_space("minigrid_open_doors_blockers_counted", _unmarked_obstructed_maze())
    assert space.count_blockers and space.mark_blockers and space.keep_doors_open
    marked = MiniGridGoalSpace(keep_doors_open=True, mark_blockers=True)
    env = _unmarked_obstructed_maze()
    env.reset(seed=1)
    base = env.unwrapped
    balls = [(x, y) for x in range(base.width) for y in range(base.height)
             if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "ball" and base.grid.get(x, y) is not base.obj]
    assert len(balls) == 2
    states = [env.observation(None)]
    for cell in balls:
        base.grid.set(*cell, None)
        states.append(env.observation(None))
    features = space.features(np.stack(states))
    assert features.shape[1] == marked.features(states[0]).shape[1] + 3
    n_flags = features.shape[1] - N_OBJECTS * N_STATES  # the counts' one-hot is the flags' last part
    counts = features[:, n_flags - 3: n_flags]
    np.testing.assert_array_equal(counts, np.eye(3)[[2, 1, 0]])
    np.testing.assert_array_equal(np.delete(features, np.arange(n_flags - 3, n_flags), axis=1), marked.features(np.stack(states)))
    assert [space.key(state) for state in states] == [marked.key(state) for state in states]
    env.close()


# ---------------------------------------------------------------------- steps as they would have gone carrying the key



def _facing(base, obj) -> tuple[tuple[int, int], int]:
    """A free cell beside the object ``obj`` on the grid and the direction that faces it from there."""
    x, y = (int(v) for v in obj.cur_pos)
    for direction, (vx, vy) in enumerate(DIR_TO_VEC):
        cell = (x - int(vx), y - int(vy))
        if 0 <= cell[0] < base.width and 0 <= cell[1] < base.height and base.grid.get(*cell) is None:
            return cell, direction
    raise AssertionError("no free cell beside the object")


def test_mark_target_tells_the_missions_ball_from_the_balls_moved_off_the_doors() -> None:
    """ObstructedMaze-1Q draws green balls in front of its doors and the red ball the mission names: the observation
    gives the red one the state TARGET (where a task draws one object of its kind, KeyCorridor, or names none, DoorKey,
    nothing is marked); the keys, the features and the description tell it from a green ball; "task solved" is a choice
    facing it and not facing a green ball; the scripted oracle's plan names the key the env's observation gives."""
    assert grid_codes(gym.make("MiniGrid-ObstructedMaze-1Q-v1").unwrapped).target_twin
    for env_id in ("MiniGrid-KeyCorridorS4R3-v0", "MiniGrid-DoorKey-8x8-v0"):
        other = wrap_env(gym.make(env_id))
        assert not other.mark_target and not grid_codes(other.unwrapped).target_twin
        assert (other.reset(seed=0)[0][..., 2] != TARGET).all()
        assert not make_goal_space("minigrid_open_doors", other).mark_target
    env = wrap_env(gym.make("MiniGrid-ObstructedMaze-1Q-v1"))
    space = make_goal_space("minigrid_open_doors", env)
    assert env.mark_target and space.mark_target and TARGET in space.state_codes
    unmarked = MiniGridGoalSpace(use_color="relative", keep_doors_open=True, mark_blockers=True, count_blockers=True,
                                 mark_target=False)
    obs, _ = env.reset(seed=1)
    base, ball = env.unwrapped, OBJECT_TO_IDX["ball"]
    assert np.count_nonzero((obs[..., 0] == ball) & (obs[..., 2] == TARGET)) == 1
    assert np.count_nonzero(obs[..., 0] == ball) == 3  # and the two green balls, unmarked
    _place(base, *_facing(base, base.obj))
    red = env.observation(None)
    cell, direction = _blocking_ball(base)
    _place(base, cell, direction)
    green = env.observation(None)
    assert space.key(red) == (EMPTY, RELATIVE, ball, 0, TARGET) and space.key(green) == (EMPTY, RELATIVE, ball, 0, BLOCKS)
    assert space.describe(space.key(red)) == "carrying nothing, facing the mission's ball"
    assert (ball, 0, TARGET) in space.present(red) and unmarked.key(red) == (EMPTY, RELATIVE, ball, 0, 0)
    assert space.choosable(space.key(red), SUCCESS_KEY, space.present(red))
    assert not space.choosable(space.key(green), SUCCESS_KEY, space.present(green))
    assert unmarked.choosable(unmarked.key(green), SUCCESS_KEY, unmarked.present(green))  # the green ball, unmarked
    features = space.features(np.stack([red, green]))
    assert features.shape[1] == unmarked.features(red).shape[1] + 1 + N_OBJECTS  # one more state, in front and present
    front_state = slice(2 * N_OBJECTS, 2 * N_OBJECTS + N_STATES + 1)
    assert features[0, front_state].argmax() == N_STATES and features[1, front_state].argmax() != N_STATES
    # the sub-goal learners read the mark as one more indicator of the state channel
    assert TARGET in space.learner_input(env.observation_space)["one_hot"][2]
    # the cells "facing the mission's ball" concerns: the red ball alone
    mask = space.concerned_cells(space.privileged(env), space.key(red))
    assert mask.sum() == 1 and tuple(np.argwhere(mask)[0]) == tuple(int(v) for v in base.obj.cur_pos)
    # the oracle: turned away from the red ball, the plan turns to it and picks it up, under the env's own key
    oracle = make_oracle("scripted", space, env.observation_space)
    assert oracle.goal_space.mark_target
    cell, direction = _facing(base, base.obj)
    _place(base, cell, (direction + 1) % 4)
    keys = plan_keys(space.privileged(env), oracle.goal_space)
    assert keys == [(EMPTY, RELATIVE, ball, 0, TARGET), SUCCESS_KEY]
    assert plan_keys(space.privileged(env), unmarked) == [(EMPTY, RELATIVE, ball, 0, 0), SUCCESS_KEY]
    obs, *_ = env.step(int(Actions.left))
    assert space.key(obs) == keys[0]
    with pytest.raises(ValueError, match="mark_target"):
        MiniGridGoalSpace(mark_target="yes")
    with pytest.raises(ValueError, match="mark_target"):
        MiniGridEgocentricObs(gym.make("MiniGrid-ObstructedMaze-1Q-v1"), mark_target="yes")
    # a goal space pickled before the option (a model saved then) reads no mark, as it did
    older = MiniGridGoalSpace(use_color="relative")
    del older.mark_target, older.target_from_env
    assert not older.mark_target and older.key(red) == (EMPTY, RELATIVE, ball, 0, 0)
    assert (ball, 0, 0) in older.present(red)
    assert older.features(red).shape == MiniGridGoalSpace(use_color="relative", mark_target=False).features(red).shape
    env.close()

def _steps_both_ways(seed: int, n: int = 60) -> tuple[list, list]:
    """Random turns and steps on DoorKey-8x8 (seed ``seed``) twice from the same start: with empty hands, and with the
    key taken off its cell into the agent's hands. Each: (obs, action, next_obs) triples."""
    ways = []
    for carrying in (False, True):
        env = MiniGridEgocentricObs(gym.make("MiniGrid-DoorKey-8x8-v0"))
        env.reset(seed=seed)
        base = env.unwrapped
        if carrying:
            x, y = _find(base, "key")
            base.carrying = base.grid.get(x, y)
            base.grid.set(x, y, None)
        obs, rng, steps = env.observation(None), np.random.default_rng(seed), []
        for _ in range(n):
            action = int(rng.choice([Actions.left, Actions.right, Actions.forward, Actions.forward]))
            next_obs, *_ = env.step(action)
            steps.append((obs, action, next_obs))
            obs = next_obs
        ways.append(steps)
    return ways[0], ways[1]


def test_steps_taken_empty_handed_become_the_steps_taken_carrying_the_key() -> None:
    """The counterfactual of a turn or a step is exactly what the env shows when the agent carries the key, except a
    step into the key (the key on the floor blocks it), after which the two walks part."""
    space = MiniGridGoalSpace()
    compared = 0
    for seed in range(6):
        empty, carrying = _steps_both_ways(seed)
        obs, actions, next_obs = (np.array([step[i] for step in empty]) for i in range(3))
        usable, obs2, next_obs2, keys = space.carried_counterfactual(CARRYING_KEY_FACING_GOAL, obs, actions, next_obs)
        for i, ((_, _, real_next), (real_obs, _, carried_next)) in enumerate(zip(empty, carrying)):
            if not np.array_equal(real_next, next_obs[i]):
                break
            if not usable[i]:  # the only step left out of a walk: into the key on the floor
                assert actions[i] == Actions.forward and obs[i][obs.shape[1] // 2, obs.shape[1] // 2 - 1, 0] == KEY
                break
            np.testing.assert_array_equal(obs2[i], real_obs)
            np.testing.assert_array_equal(next_obs2[i], carried_next)
            compared += 1
        assert [space.key(o) for o in next_obs2[usable]] == keys
        assert all(key[0] == KEY for key in keys)
    assert compared >= 100


def test_the_carried_counterfactual_leaves_out_what_carrying_would_change(doorkey5) -> None:
    space = MiniGridGoalSpace()
    obs = doorkey5.observation(None)
    batch = np.stack([obs] * 7)
    actions = np.array([Actions.left, Actions.right, Actions.forward, Actions.done, Actions.pickup, Actions.drop,
                        Actions.toggle])
    usable, *_ = space.carried_counterfactual(CARRYING_KEY_FACING_LOCKED_DOOR, batch, actions, batch)
    assert usable.tolist() == [True] * 4 + [False] * 3  # a pick-up, a drop or a toggle would go otherwise
    assert space.carried_counterfactual(FACING_LOCKED_DOOR, batch, actions, batch) is None  # empty hands: no change
    assert space.carried_counterfactual(SUCCESS_KEY, batch, actions, batch) is None
    holding = batch.copy()
    center = obs.shape[0] // 2
    holding[:, center, center] = (KEY, 0, 0)  # already carrying something
    assert not space.carried_counterfactual(CARRYING_KEY_FACING_LOCKED_DOOR, holding, actions, holding)[0].any()
    two_keys = batch.copy()
    two_keys[:, 0, 0] = two_keys[:, np.nonzero(obs[..., 0] == KEY)[0][0], np.nonzero(obs[..., 0] == KEY)[1][0]]
    assert not space.carried_counterfactual(CARRYING_KEY_FACING_LOCKED_DOOR, two_keys, actions, two_keys)[0].any()
    np.testing.assert_array_equal(batch[0], obs)  # the caller's arrays are left as they were


@pytest.mark.parametrize("env_id, types, states, key_colors", [
    ("MiniGrid-DoorKey-8x8-v0", ["wall", "door", "key", "goal"], ["closed", "locked"], 1),
    ("MiniGrid-MultiRoom-N4-S5-v0", ["wall", "door", "goal"], ["closed"], 0),  # its doors are never locked
    ("MiniGrid-ObstructedMaze-1Dlh-v0", ["wall", "door", "key", "ball", "box"], ["closed", "locked"], 1),
    ("MiniGrid-ObstructedMaze-1Q-v1", ["wall", "door", "key", "ball", "box"], ["closed", "locked"], 2),
    ("MiniGrid-Empty-5x5-v0", ["wall", "goal"], [], 0),
])
def test_grid_codes_are_what_the_tasks_grids_hold(env_id: str, types: list, states: list, key_colors: int) -> None:
    """The object types on a task's grids (ObstructedMaze-1Dlh's key only inside its box), the states other than "open"
    its doors can take and the most colours of keys in one layout, read from a copy: the env's own layout and random
    state are left as they were. With use_color "auto" the goal space reads colours where keys have several."""
    base = gym.make(env_id).unwrapped
    base.reset(seed=3)
    random_state, cells = base.np_random.bit_generator.state, list(base.grid.grid)
    found = grid_codes(base)
    assert found.types == sorted(OBJECT_TO_IDX[name] for name in types)
    assert found.states == sorted(STATE_TO_IDX[name] for name in states) and found.key_colors == key_colors
    assert base.np_random.bit_generator.state == random_state and base.grid.grid == cells
    space = MiniGridGoalSpace(use_color="auto")
    assert space.use_color is False  # until bound
    space.bind(base)
    assert space.use_color is space.relative_color is (key_colors > 1)
    assert space.color_option == ("relative" if key_colors > 1 else False)


@pytest.mark.parametrize("env_id, blocked", [
    ("MiniGrid-BlockedUnlockPickup-v0", True),  # a ball in front of the locked door in every layout
    ("MiniGrid-ObstructedMaze-1Q-v1", True),
    ("MiniGrid-ObstructedMaze-1Dlhb-v0", True),
    ("MiniGrid-ObstructedMaze-1Dl-v0", False),  # no ball at its door
    ("MiniGrid-DoorKey-8x8-v0", False),  # a key or ball drawn at random sometimes stands in a passage: not every layout
    ("MiniGrid-KeyCorridorS4R3-v0", False),
    ("MiniGrid-UnlockPickup-v0", False),
])
def test_mark_blockers_auto_where_the_task_puts_an_object_in_the_way(env_id: str, blocked: bool) -> None:
    """``mark_blockers="auto"`` marks objects in the way where the task's every layout drawn has one (a ball in front
    of a door), not where one drawn at random sometimes blocks a passage; the scripted oracle keys alike."""
    base = gym.make(env_id).unwrapped
    assert grid_codes(base).blocked is blocked

    def in_the_way(seed: int) -> bool:  # an object blocks the way in the layout of seed, from the agent's start
        base.reset(seed=seed)
        return bool(blockers(encode_grid(base.grid)[None, ..., 0], [tuple(base.agent_pos)]).any())

    layouts = [in_the_way(seed) for seed in range(20)]
    assert all(layouts) if blocked else not all(layouts)
    space = MiniGridGoalSpace(keep_doors_open=True, mark_blockers="auto", count_blockers="auto")
    assert space.mark_blockers is space.count_blockers is False  # until bound
    env = wrap_env(gym.make(env_id))
    space = make_goal_space("minigrid_open_doors", env)  # the minigrid entry's
    assert space.mark_blockers is space.count_blockers is blocked and space.keep_doors_open
    unmarked = make_goal_space("minigrid_open_doors_unmarked", env)
    assert not unmarked.mark_blockers and not unmarked.count_blockers and unmarked.keep_doors_open
    assert make_oracle("scripted", space, env.observation_space).goal_space.mark_blockers is blocked
    env.close()
    for option in ("mark_blockers", "count_blockers"):
        with pytest.raises(ValueError, match=f"{option} must be True, False or 'auto'"):
            MiniGridGoalSpace(**{option: "yes"})


@pytest.mark.parametrize("env_id, view, overview", [
    ("MiniGrid-DoorKey-8x8-v0", "inner", None),  # 11 x 11 inner cells: all of them
    ("MiniGrid-DoorKey-16x16-v0", 15, 5),  # 27 x 27: the 15 x 15 around the agent and blocks of the whole canvas
])
def test_learner_input_is_derived_from_the_bound_env(env_id: str, view, overview) -> None:
    env = wrap_env(gym.make(env_id))
    space = make_goal_space("minigrid", env)  # binds it
    derived = space.learner_input(env.observation_space)
    assert derived == dict(view=view, overview=overview, one_hot=[[2, 4, 5, 8], [], [1, 2]])
    with pytest.raises(ValueError, match="bind the goal space"):
        MiniGridGoalSpace().learner_input(env.observation_space)
    with pytest.raises(ValueError, match="use_color must be True, False, 'relative'"):
        MiniGridGoalSpace(use_color="yes")


def _holding(carried: tuple, front: tuple, size: int = 7) -> np.ndarray:
    """An egocentric observation: empty cells in walls, the agent carrying ``carried``, ``front`` in front of it."""
    obs = np.zeros((size, size, 3), dtype=np.uint8)
    obs[1:-1, 1:-1] = (EMPTY, 0, 0)
    obs[0, :], obs[-1, :], obs[:, 0], obs[:, -1] = (WALL, 5, 0), (WALL, 5, 0), (WALL, 5, 0), (WALL, 5, 0)
    center = size // 2
    obs[center, center], obs[center, center - 1] = carried, front
    return obs


def test_relative_colours_name_a_key_and_the_door_it_opens_whatever_their_colour() -> None:
    """With use_color "relative" a key holds whether the object in front has the carried object's colour, not which
    colour either has: ObstructedMaze draws its doors' colours anew in every layout, so "carrying the key, facing the
    door it opens" is one sub-goal in every layout, and another than facing a door the key does not open. present,
    features, choosable, describe and the scripted oracle read colours the same way."""
    space = MiniGridGoalSpace(use_color="relative")
    assert space.use_color and space.relative_color and space.color_option == "relative"
    red, green, purple, grey = (COLOR_TO_IDX[name] for name in ("red", "green", "purple", "grey"))
    ball, box = OBJECT_TO_IDX["ball"], OBJECT_TO_IDX["box"]
    opens = _holding((KEY, green, 0), (DOOR, green, LOCKED))
    opens_too = _holding((KEY, purple, 0), (DOOR, purple, LOCKED))  # another layout's colours
    other_door = _holding((KEY, green, 0), (DOOR, purple, LOCKED))
    assert space.key(opens) == space.key(opens_too) == (KEY, RELATIVE, DOOR, SAME_COLOR, LOCKED)
    assert space.key(other_door) == (KEY, RELATIVE, DOOR, 0, LOCKED)
    absolute = MiniGridGoalSpace(use_color=True)
    assert len({absolute.key(obs) for obs in (opens, opens_too, other_door)}) == 3
    # empty hands: no colour to relate to; walls, empty cells and goal squares relate to none (a grey key, a red one)
    assert space.key(_holding((EMPTY, 0, 0), (DOOR, green, LOCKED))) == (EMPTY, RELATIVE, DOOR, 0, LOCKED)
    assert space.key(_holding((KEY, grey, 0), (WALL, grey, 0)))[3] == 0
    assert space.key(_holding((KEY, red, 0), (EMPTY, red, 0)))[3] == 0
    assert space.describe(space.key(opens)) == "carrying key, facing locked door of its colour"
    assert space.describe(space.key(other_door)) == "carrying key, facing locked door"
    # present: the door the key opens, as the key names it; features: the relation, the same in both layouts
    door_of_the_key = (DOOR, SAME_COLOR, LOCKED)
    beside = _holding((KEY, green, 0), (EMPTY, 0, 0))
    beside[1, 2] = (DOOR, green, LOCKED)  # a door within reach, of the key's colour
    assert door_of_the_key in space.present(beside)
    carrying_key = space.key(beside)
    assert carrying_key == (KEY, RELATIVE, EMPTY, 0, 0)
    assert space.choosable(carrying_key, (KEY, RELATIVE, DOOR, SAME_COLOR, LOCKED), space.present(beside))
    beside[1, 2] = (DOOR, purple, LOCKED)
    assert door_of_the_key not in space.present(beside) and (DOOR, 0, LOCKED) in space.present(beside)
    assert not space.choosable(carrying_key, (KEY, RELATIVE, DOOR, SAME_COLOR, LOCKED), space.present(beside))
    np.testing.assert_array_equal(space.features(opens), space.features(opens_too))
    assert not np.array_equal(space.features(opens), space.features(other_door))
    assert space.features(opens).shape[1] == MiniGridGoalSpace().features(opens).shape[1] + 2
    np.testing.assert_array_equal(opens[3, 3], (KEY, green, 0))  # the observation is left as it was
    # a pick-up and a drop move one object between the hands and the cell in front: its colour relation changes
    facing_ball, holding_ball = (EMPTY, RELATIVE, ball, 0, 0), (ball, RELATIVE, EMPTY, 0, 0)
    assert space.choosable(facing_ball, holding_ball) and space.choosable(holding_ball, facing_ball)
    assert not space.choosable(facing_ball, (KEY, RELATIVE, EMPTY, 0, 0))  # the ball in front is not a key
    assert not space.choosable(holding_ball, (EMPTY, RELATIVE, box, 0, 0))  # it drops the ball it carries
    # the sub-goal learners read the relation too, where the door the key opens is (one_hot "auto" lists it)
    codes = space.learner_codes()
    assert codes is not None and MiniGridGoalSpace(use_color=True).learner_codes() is None
    read = GridInput(spaces.Box(0, 10, opens.shape, np.uint8), one_hot=[list(range(11)), [SAME_COLOR], [0, 1, 2]],
                     codes=codes)
    np.testing.assert_array_equal(read.encode(opens), read.encode(opens_too))
    assert not np.array_equal(read.encode(opens), read.encode(other_door))
    assert read.encode(opens)[3, 2].sum() == 3 and read.encode(other_door)[3, 2].sum() == 2  # door, same colour, locked
    # the scripted oracle keys its plans the same way (make_oracle passes the goal space's colour options)
    assert make_oracle("scripted", space, spaces.Box(0, 10, opens.shape, np.uint8)).goal_space.relative_color


def test_colours_relate_a_key_and_a_door_only_unless_any_pair_is_asked_for() -> None:
    """Relative colours relate the carried key to a door of its colour (the one relation MiniGrid's steps read), not a
    ball to a ball, a key to a ball or a box to a box; ``color_relation="any"`` relates every two objects with colours.
    Keys, present, features and what the learners read agree; the scripted oracle is made with the same relation."""
    green, purple = COLOR_TO_IDX["green"], COLOR_TO_IDX["purple"]
    ball, box = OBJECT_TO_IDX["ball"], OBJECT_TO_IDX["box"]
    opens, any_pair = MiniGridGoalSpace(use_color="relative"), MiniGridGoalSpace(use_color="relative", color_relation="any")
    assert opens.color_relation == "opens" and any_pair.color_relation == "any"
    pairs = {  # (carried, in front): whether "opens" relates their colour
        ((KEY, green, 0), (DOOR, green, LOCKED)): True,
        ((KEY, green, 0), (DOOR, green, CLOSED)): True,
        ((ball, green, 0), (ball, green, 0)): False,
        ((KEY, green, 0), (ball, green, 0)): False,
        ((ball, green, 0), (DOOR, green, LOCKED)): False,
        ((box, green, 0), (box, green, 0)): False,
        ((ball, green, 0), (KEY, green, 0)): False,
    }
    for (carried, front), related in pairs.items():
        obs = _holding(carried, front)
        assert opens.key(obs)[3] == (SAME_COLOR if related else 0), (carried, front)
        assert any_pair.key(obs)[3] == SAME_COLOR, (carried, front)  # every pair here has one colour
        assert opens.relate_colors(obs)[3, 2, 1] == (SAME_COLOR if related else 0)
        assert ((front[0], SAME_COLOR, front[2]) in opens.present(obs)) is related
        if not related:  # the colour in front then changes nothing the goal space reads
            recoloured = _holding(carried, (front[0], purple, front[2]))
            assert opens.key(recoloured) == opens.key(obs)
            np.testing.assert_array_equal(opens.features(recoloured), opens.features(obs))
    # a ball of another colour than the carried one: unrelated either way
    assert any_pair.key(_holding((ball, green, 0), (ball, purple, 0)))[3] == 0
    with pytest.raises(ValueError, match="color_relation must be 'opens'"):
        MiniGridGoalSpace(use_color="relative", color_relation="keys")
    # a goal space pickled before the option (a model saved then) relates any pair, as it did
    saved = pickle.loads(pickle.dumps(opens))
    del saved.__dict__["color_relation"]
    assert saved.key(_holding((ball, green, 0), (ball, green, 0)))[3] == SAME_COLOR
    observation_space = spaces.Box(0, 10, (7, 7, 3), np.uint8)
    for space in (opens, any_pair):
        assert make_oracle("scripted", space, observation_space).goal_space.color_relation == space.color_relation


def test_relative_colours_give_obstructedmaze_the_few_situations_of_its_plans() -> None:
    """On ObstructedMaze-1Q (the doors' colours drawn per layout) the scripted oracle's plans pass through fewer keys
    with colours related than named, and every plan walks to the door with the key that opens it."""
    env = wrap_env(gym.make("MiniGrid-ObstructedMaze-1Q-v1"))
    space = make_goal_space("minigrid_open_doors", env)
    assert space.relative_color
    related_oracle = make_oracle("scripted", space, env.observation_space, max_seconds=60.0)  # under load too
    named_oracle = MiniGridScriptedOracle(use_color=True, max_seconds=60.0)
    related, named = set(), set()
    for seed in (0, 2, 4, 5):
        env.reset(seed=seed)
        state = space.privileged(env)
        plan = [key for key, _ in related_oracle.plan(state)]
        assert (KEY, RELATIVE, DOOR, SAME_COLOR, LOCKED) in plan and (KEY, RELATIVE, DOOR, 0, LOCKED) not in plan
        assert plan[-1] == SUCCESS_KEY
        related.update(plan)
        named.update(key for key, _ in named_oracle.plan(state))
    assert len(related) < len(named)
    # a question's drawing marks the door the key in hand opens (the labeling page reads the relation off the key)
    grid = np.asarray(state["grid"])
    locked = np.argwhere((grid[..., 0] == DOOR) & (grid[..., 2] == LOCKED))
    assert len(locked) == 2
    colour = int(grid[tuple(locked[0])][1])
    state = dict(state, carrying=[KEY, colour, 0])
    drawer = layout_goal_space({"state": state, "goal1_key": [KEY, RELATIVE, DOOR, SAME_COLOR, LOCKED]})
    assert drawer.relative_color
    marked = drawer.concerned_cells(state, (KEY, RELATIVE, DOOR, SAME_COLOR, LOCKED))
    assert marked[tuple(locked[0])] and not marked[tuple(locked[1])]
    env.close()


def test_mark_target_auto_on_an_env_that_cannot_be_copied_reads_its_first_layout() -> None:
    """``mark_target="auto"`` reads a few layouts from a copy of the env; an env that cannot be copied (it holds a lock)
    is still wrapped, and decides from its first layout: ObstructedMaze-1Q's red ball is marked, DoorKey's nothing."""
    import threading

    for env_id, marked in (("MiniGrid-ObstructedMaze-1Q-v1", True), ("MiniGrid-DoorKey-5x5-v0", False)):
        raw = gym.make(env_id)
        raw.unwrapped.lock = threading.Lock()
        env = MiniGridEgocentricObs(raw)
        assert env.mark_target is None
        obs, _ = env.reset(seed=1)
        assert env.mark_target is marked and bool((obs[..., 2] == TARGET).any()) is marked
