"""MiniGrid goal space: a sub-goal is a situation that recurs across procedurally generated layouts.

MiniGrid tasks draw a new layout every episode, so an exact match of the full grid never recurs and
a sub-goal taken from one episode would be unreachable in the next (design decisions: a sub-goal recurs). A sub-goal key
is therefore the situation a person would name: *what the agent carries* and *what is in front of
it, with its state* ("facing the key", "carrying the key, facing the locked door", "the door in
front is open", "facing the goal"), plus :data:`~sb3_hhp.goals.base.SUCCESS_KEY` for a solved task.
Keys are compared exactly; networks see the observation where the sub-goal was found and people see
the rendered frame of that state.

The observation is :class:`MiniGridEgocentricObs`: the whole grid, rotated so that the agent sits
in the centre facing up, with the carried object drawn in the agent's cell (MiniGrid's own
convention). Every fact of a key can be read off the observation, so ``predict`` can tell when a
sub-goal is reached without access to the environment.
"""

import contextlib
import copy
import pickle
from collections.abc import Callable, Hashable, Sequence
from itertools import chain
from typing import Any, NamedTuple, Optional, Union

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import OrderEnforcing, PassiveEnvChecker, RecordEpisodeStatistics, TimeLimit
from scipy import ndimage
from stable_baselines3.common.monitor import Monitor
from minigrid.core.constants import COLOR_TO_IDX, IDX_TO_OBJECT, OBJECT_TO_IDX, STATE_TO_IDX
from minigrid.core.grid import Grid
from minigrid.core.world_object import Box, WorldObj
from minigrid.core.actions import Actions
from minigrid.minigrid_env import MiniGridEnv

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace

EMPTY = OBJECT_TO_IDX["empty"]
IDX_TO_STATE = {idx: name for name, idx in STATE_TO_IDX.items()}
#: objects the agent interacts with: facing one of them is a milestone of a plan
INTERACTIVE = {OBJECT_TO_IDX[name] for name in ("key", "ball", "box", "door", "goal")}
#: objects the agent can pick up
PICKABLE = {OBJECT_TO_IDX[name] for name in ("key", "ball", "box")}
#: cells the agent walks through (an open door too; lava ends the episode, so it is not among them)
PASSABLE = {OBJECT_TO_IDX[name] for name in ("empty", "floor", "goal")}
DOOR, GOAL, OPEN, LOCKED = OBJECT_TO_IDX["door"], OBJECT_TO_IDX["goal"], STATE_TO_IDX["open"], STATE_TO_IDX["locked"]
CLOSED = STATE_TO_IDX["closed"]
BOX = OBJECT_TO_IDX["box"]
#: objects whose colour tells them apart (a key opens the door of its colour); walls, floors and goal squares have one
#: colour each
COLORED = PICKABLE | {DOOR}
#: in :meth:`MiniGridGoalSpace.present`: the grid has a goal square, and none is within reach
GOAL_OUT_OF_REACH = "goal out of reach"
#: in :meth:`MiniGridGoalSpace.present`: the grid has no goal square, so the task ends with a pick-up (KeyCorridor,
#: ObstructedMaze, Fetch: the mission's object)
NO_GOAL_SQUARE = "no goal square"
#: in :meth:`MiniGridGoalSpace.present` with ``count_open_doors``: ``(OPEN_DOORS, n)``, n doors of the grid are open
OPEN_DOORS = "open doors"
#: with ``mark_blockers``, the state a key gives a key, ball or box in front that blocks the way (:func:`blockers`;
#: MiniGrid's states of doors are 0-2, objects one picks up have none of their own)
BLOCKS = 3
#: the state :class:`MiniGridEgocentricObs` gives the mission's object (the env's ``obj``: ObstructedMaze's ball,
#: KeyCorridor's, UnlockPickup's box) where its task draws other objects of that kind (:func:`grid_codes`), and so keys
#: of facing it: "facing the mission's ball" is then another sub-goal than facing a ball moved off a door
TARGET = 4
#: with ``count_open_doors``, the features tell 0 .. MAX_COUNTED_DOORS - 1 open doors apart (more count as the last)
MAX_COUNTED_DOORS = 8
#: with ``count_blockers``, the features' count of objects that block the way stops here (its last value: this many
#: less one, or more)
MAX_COUNTED_BLOCKERS = 3
#: with ``use_color`` "relative", what a key holds in place of the carried object's colour: the colour fields then say
#: how the colours relate (the object in front :data:`SAME_COLOR` as the carried one, or not: 0), not which they are
RELATIVE = -1
#: with ``use_color`` "relative": the object in front has the carried object's colour (a key and the door it opens)
SAME_COLOR = 1
MAX_ENCODING = max(max(OBJECT_TO_IDX.values()), 5, TARGET)  # object ids 0..10, colours 0..5, states 0..2 and TARGET
N_OBJECTS, N_COLORS, N_STATES = len(OBJECT_TO_IDX), len(COLOR_TO_IDX), len(STATE_TO_IDX)
#: the frame drawn around the cells a sub-goal concerns (a colour MiniGrid's objects never have)
HIGHLIGHT_RGB = (255, 64, 200)
#: brightness of the rest of the room in a sub-goal drawn in a state's layout
DIM = 0.45


#: layouts :meth:`MiniGridGoalSpace.bind` draws (from a copy of the env, seeds 0, 1, ...) to learn what its grids hold
BOUND_LAYOUTS = 4
#: the sub-goal learners' ``view: auto`` on a canvas whose inner cells are wider than this: the cells around the agent;
#: on a narrower one, every inner cell (docs/design_decisions.rst: the view of the learners)
LEARNER_VIEW = 15
#: the sub-goal learners' ``overview: auto`` where the view leaves cells out: blocks of 5 x 5 cells of the whole canvas
LEARNER_OVERVIEW = 5


class GridCodes(NamedTuple):
    """What the grids of a task hold (:func:`grid_codes`)."""

    #: the object types found on the grid, in its boxes or carried, sorted
    types: list[int]
    #: the states other than "open" its objects can take (a door can be closed, and locked where one was found locked)
    states: list[int]
    #: the most colours of keys one layout held
    key_colors: int
    #: whether an object one picks up blocked the way in every layout as it was drawn (:func:`blockers`, from the
    #: agent's start): the task puts it there (a ball in front of a door), where elsewhere a key or ball drawn at
    #: random sometimes happens to
    blocked: bool = False
    #: whether some layout held another object of the mission object's kind (the env's ``obj``: ObstructedMaze's
    #: balls moved off the doors beside the ball to pick up): :class:`MiniGridEgocentricObs` then marks the mission's
    #: object (:data:`TARGET`)
    target_twin: bool = False


def _objects(base: MiniGridEnv) -> list[WorldObj]:
    """The objects of ``base``'s grid, the carried one and those its boxes hold."""
    objects = [obj for obj in [*base.grid.grid, base.carrying] if obj is not None]
    return objects + [obj.contains for obj in objects if isinstance(obj, Box) and obj.contains is not None]


def _has_target_twin(base: MiniGridEnv, objects: Optional[list[WorldObj]] = None) -> bool:
    """Whether ``base``'s layout holds another object of the kind of the mission's (``obj``)."""
    target = getattr(base, "obj", None)
    return isinstance(target, WorldObj) and any(obj is not target and obj.type == target.type
                                                for obj in (_objects(base) if objects is None else objects))


def mission_object(base: MiniGridEnv) -> Optional[tuple[int, int]]:
    """The (object, colour) codes of the object the env's mission names, where the env keeps it as ``obj``
    (KeyCorridor, ObstructedMaze, UnlockPickup: the object to pick up), else None."""
    target = getattr(base, "obj", None)
    return None if not isinstance(target, WorldObj) else (OBJECT_TO_IDX[target.type], COLOR_TO_IDX[target.color])


def grid_codes(base: MiniGridEnv, layouts: int = BOUND_LAYOUTS) -> GridCodes:
    """What the grids of ``base``'s task hold, over ``layouts`` layouts drawn by a copy of it (``base`` itself is not
    reset)."""
    env = copy.deepcopy(base)
    types, states, key_colors, blocked, twin = set(), set(), 0, True, False
    for seed in range(layouts):
        env.reset(seed=seed)
        grid = encode_grid(env.grid)  # [x, y], as agent_pos
        blocked = blocked and bool(blockers(grid[None, ..., 0], [tuple(env.agent_pos)]).any())
        objects = _objects(env)
        for obj in objects:
            kind, _, state = (int(code) for code in obj.encode())
            types.add(kind)
            if kind == DOOR:
                states.update({CLOSED, state} - {OPEN})
        key_colors = max(key_colors, len({obj.color for obj in objects if obj.type == "key"}))
        twin = twin or _has_target_twin(env, objects)
    return GridCodes(sorted(types), sorted(states), key_colors, blocked, twin)


#: the paper's MultiRoom task, which MiniGrid does not register: 12 rooms of at most 10x10 cells (a 25x25 grid,
#: 240 steps)
#: the id under which sb3_hhp registers the paper's MultiRoom task (12 rooms of up to 10 x 10)
MULTIROOM_N12_S10 = "MiniGrid-MultiRoom-N12-S10-v0"


def register_minigrid_tasks() -> None:
    """Register the paper's MiniGrid tasks that MiniGrid has under no id of their own (:data:`MULTIROOM_N12_S10`);
    ``sb3_hhp.train`` and the benchmark runner call it, a script calls it before ``gym.make``."""
    if MULTIROOM_N12_S10 not in gym.registry:
        gym.register(MULTIROOM_N12_S10, entry_point="minigrid.envs:MultiRoomEnv",
                     kwargs=dict(minNumRooms=12, maxNumRooms=12, maxRoomSize=10))


def find_minigrid(env: gym.Env) -> Optional[MiniGridEnv]:
    """The MiniGrid env underneath ``env`` (None when it is not a MiniGrid task)."""
    base = getattr(env, "unwrapped", env)
    return base if isinstance(base, MiniGridEnv) else None


def _find_wrapper(env: gym.Env, kind: type) -> Optional[gym.Wrapper]:
    """The first wrapper of class ``kind`` in ``env``'s chain of wrappers (None: there is none)."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, kind):
            return env
        env = env.env
    return None


def _beside(mask: np.ndarray) -> np.ndarray:
    """The cells of a batch of grids ``(N, S, S)`` with a True cell among their four neighbours (within each grid)."""
    near = np.zeros_like(mask)
    near[:, 1:] |= mask[:, :-1]
    near[:, :-1] |= mask[:, 1:]
    near[:, :, 1:] |= mask[:, :, :-1]
    near[:, :, :-1] |= mask[:, :, 1:]
    return near


def blockers(objects: np.ndarray, agents: np.ndarray) -> np.ndarray:
    """Which cells of a batch of grids of object codes ``(N, A, B)`` hold an object one picks up that blocks the
    way: with its cell free, the agent (its cell ``agents[i]`` in grid ``i``) could walk to cells it cannot reach now,
    doors counted as passable in any state (they can be opened). ``(N, A, B)`` booleans."""
    objects = np.asarray(objects)
    rows = np.arange(len(objects))
    agents = np.asarray(agents, dtype=np.int64).reshape(len(objects), 2)
    passable = _PASSABLE_TABLE[objects] | (objects == DOOR)
    passable[rows, agents[:, 0], agents[:, 1]] = True
    regions, _ = ndimage.label(passable, structure=_GRID_CROSS)
    beyond = passable & (regions != regions[rows, agents[:, 0], agents[:, 1]][:, None, None])
    return _PICKABLE_TABLE[objects] & _beside(beyond)


def open_doors(obs: np.ndarray) -> Union[int, np.ndarray]:
    """How many doors of the grid an observation (:class:`MiniGridEgocentricObs`) shows open; for a batch of
    observations ``(N, S, S, 3)``, one count each."""
    obs = np.asarray(obs)
    counts = np.count_nonzero((obs[..., 0] == DOOR) & (obs[..., 2] == OPEN), axis=(-2, -1))
    return int(counts) if obs.ndim == 3 else counts


_EMPTY_CELL = (EMPTY, 0, 0)
#: lookups by object id (any byte) of PASSABLE, INTERACTIVE, PICKABLE and COLORED
_PASSABLE_TABLE, _INTERACTIVE_TABLE, _PICKABLE_TABLE, _COLORED_TABLE = (
    np.isin(np.arange(256), list(ids)) for ids in (PASSABLE, INTERACTIVE, PICKABLE, COLORED))
#: 4-connected neighbours within each grid of a batch (N, S, S), never across grids
_GRID_CROSS = np.stack([np.zeros((3, 3), dtype=bool), ndimage.generate_binary_structure(2, 1), np.zeros((3, 3), dtype=bool)])
#: with ``use_color`` "relative", by ``color_relation``: the (carried, cell) object ids (any bytes) whose colours a key
#: relates: "opens", a key and a door, the one relation MiniGrid's steps read (a key opens the door of its colour);
#: "any", any two objects that have colours (keys, balls, boxes, doors)
_RELATED_TABLES = {"opens": np.zeros((256, 256), dtype=bool), "any": _COLORED_TABLE[:, None] & _COLORED_TABLE[None, :]}
_RELATED_TABLES["opens"][OBJECT_TO_IDX["key"], DOOR] = True
#: actions whose outcome does not depend on what the agent carries (MiniGridGoalSpace.carried_counterfactual)
_CARRY_FREE_ACTIONS = np.array([Actions.left, Actions.right, Actions.forward, Actions.done])


def encode_grid(grid: Grid) -> np.ndarray:
    """``grid.encode()`` (every cell visible), the same array: (W, H, 3) uint8 indexed ``[x, y]``, an empty cell
    ``(empty, 0, 0)``. MiniGrid's writes the array cell by cell; this reads the cells in one pass, in a third of the
    time, which counts on every primitive step."""
    cells = chain.from_iterable([_EMPTY_CELL if obj is None else obj.encode() for obj in grid.grid])  # [y * W + x]
    flat = np.fromiter(cells, dtype=np.uint8, count=3 * len(grid.grid))
    return flat.reshape(grid.height, grid.width, 3).transpose(1, 0, 2)


def egocentric_size(width: int, height: int) -> int:
    """The side of the egocentric canvas of a ``width`` x ``height`` grid: ``2 * max(W, H) - 3``. From the centre
    of a ``2 * max(W, H) - 1`` canvas the agent sees the whole grid wherever it stands; MiniGrid's grids are
    walled, so it never stands on their outermost cells and that canvas's outer ring is always empty: it is left
    out (a quarter of the inputs of DoorKey-8x8's 15x15 canvas, which networks' first layers would read for
    nothing)."""
    return max(1, 2 * max(width, height) - 3)


def mark_target(codes: np.ndarray, target: Optional[Sequence[int]]) -> np.ndarray:
    """``codes`` (..., 3) with the state :data:`TARGET` on the cells that hold the object ``target`` ((object,
    colour) codes; None: unchanged), in place."""
    if target is not None:
        codes[(codes[..., 0] == target[0]) & (codes[..., 1] == target[1]), 2] = TARGET
    return codes


def egocentric_grid(base: MiniGridEnv, target: Optional[Sequence[int]] = None) -> np.ndarray:
    """The full grid encoding (W, H, 3) rotated so the agent is at the centre facing up, in a square canvas of side
    :func:`egocentric_size` indexed ``[x, y]``; cells outside the grid are 0 ("unseen"). (On a grid without walls,
    cells beyond the canvas would be cut off.) With ``target`` ((object, colour) codes), the cells that hold that
    object have the state :data:`TARGET` (:func:`mark_target`)."""
    full = mark_target(encode_grid(base.grid), target)  # (W, H, 3), [x, y]
    ax, ay = (int(v) for v in base.agent_pos)
    full[ax, ay] = base.carrying.encode() if base.carrying is not None else _EMPTY_CELL
    size = egocentric_size(base.width, base.height)
    center = size // 2
    canvas = np.zeros((size, size, 3), dtype=np.uint8)
    x0, y0 = center - ax, center - ay  # where the grid's (0, 0) falls on the canvas
    xs, ys = slice(max(0, -x0), min(base.width, size - x0)), slice(max(0, -y0), min(base.height, size - y0))
    canvas[x0 + xs.start : x0 + xs.stop, y0 + ys.start : y0 + ys.stop] = full[xs, ys]
    # agent_dir 0/1/2/3 = right/down/left/up; rotate so that "forward" is -y in the canvas
    return np.ascontiguousarray(np.rot90(canvas, (3 - int(base.agent_dir)) % 4, axes=(0, 1)))


class MiniGridEgocentricObs(gym.ObservationWrapper):
    """Observation: the whole grid, egocentric (agent at the centre facing up), as a uint8 array
    (S, S, 3) of MiniGrid encodings (object, colour, state), ``S = 2 * max(W, H) - 3`` (:func:`egocentric_size`:
    13 on DoorKey-8x8).

    Its upper bound is the largest encoding value (not 255), so SB3 treats it as a vector and
    ``MlpPolicy`` sees the integer codes directly.

    :param env: a MiniGrid env
    :param mark_target: give the object the mission names (:func:`mission_object`) the state :data:`TARGET`;
        ``"auto"``: where the task draws other objects of its kind (:func:`grid_codes`: ObstructedMaze, whose balls moved
        off the doors look like the ball to pick up; docs/design_decisions.rst)
    """

    def __init__(self, env: gym.Env, mark_target: Union[bool, str] = "auto") -> None:
        super().__init__(env)
        base = find_minigrid(env)
        if base is None:
            raise ValueError(f"MiniGridEgocentricObs needs a MiniGrid env, got {env}")
        if not isinstance(mark_target, bool) and mark_target != "auto":
            raise ValueError(f"mark_target must be True, False or 'auto' (where the task draws other objects of the "
                             f"mission object's kind), got {mark_target!r}")
        #: None until the first observation where "auto" could not copy the env (it holds what cannot be copied)
        self.mark_target: Optional[bool] = mark_target if isinstance(mark_target, bool) else None
        if mark_target == "auto":
            with contextlib.suppress(TypeError, copy.Error, pickle.PicklingError):
                self.mark_target = grid_codes(base).target_twin
        size = egocentric_size(base.width, base.height)
        self.observation_space = spaces.Box(0, MAX_ENCODING, (size, size, 3), np.uint8)
        if _reads_no_minigrid_obs(env, base):
            # MiniGrid's own observation (the 7x7 view, built cell by cell) is discarded here: when no wrapper in
            # between reads it, the env returns a blank one instead (a DoorKey-8x8 step then costs a fifth)
            base.gen_obs = _BlankObs(base)

    def observation(self, observation: Any) -> np.ndarray:
        base = self.env.unwrapped
        if self.mark_target is None:  # "auto" on an env that cannot be copied: read from its first layout
            self.mark_target = _has_target_twin(base)
        return egocentric_grid(base, mission_object(base) if self.mark_target else None)


#: wrappers that pass observations through without reading them
_PASS_THROUGH = (TimeLimit, OrderEnforcing, PassiveEnvChecker, RecordEpisodeStatistics, Monitor)


def _reads_no_minigrid_obs(env: gym.Env, base: MiniGridEnv) -> bool:
    """Whether every wrapper between ``env`` and ``base`` passes MiniGrid's observation through unread."""
    while env is not base:
        if not isinstance(env, _PASS_THROUGH):
            return False
        env = env.env
    return True


class _BlankObs:
    """MiniGrid's observation dict with a blank image of the right shape (see :class:`MiniGridEgocentricObs`)."""

    def __init__(self, base: MiniGridEnv) -> None:
        self.base = base
        self.shape = base.observation_space["image"].shape

    def __call__(self) -> dict[str, Any]:
        return {"image": np.zeros(self.shape, dtype=np.uint8), "direction": self.base.agent_dir, "mission": self.base.mission}


class MiniGridGoalSpace(GoalSpace):
    """Sub-goal key = (carried object, object in front, its state), read off a
    :class:`MiniGridEgocentricObs` observation; colours are ignored unless ``use_color``.

    :param use_color: distinguish objects by colour (needed when colours matter, e.g. several keys); ``"relative"``:
        by how their colours relate, not which they are: a key then holds whether the object in front has the
        carried object's colour, for the pairs ``color_relation`` relates (:data:`SAME_COLOR`; a key and the door it
        opens), e.g.
        ``(key, RELATIVE, door, SAME_COLOR, locked)``, and :meth:`present` and :meth:`features` read colours the same
        way; ``"auto"``: relative where the task's grids hold keys of more than one colour (ObstructedMaze, whose
        door colours change with every layout, so that named colours make one sub-goal of each situation per pair of
        colours; docs/design_decisions.rst), read when the goal space is bound to the env (:meth:`bind`; no colours
        until then)
    :param tile_size: pixels per cell of the rendered images shown to people
    :param keep_doors_open: the sub-goal learners never close the door in front (``toggle`` is masked there, in acting
        and in their targets): a key names *a* closed door, not which, so the learner of "facing a closed door"
        would otherwise reach it in one step by closing the door it has just opened (KeyCorridor; design decisions)
    :param count_open_doors: a key that faces an open door also holds how many doors of the grid are open, e.g.
        ``(carried, door, open, 2)``: "open the door in front" is then a sub-goal of its own, which turning to a door
        opened before does not reach (without it, the learner of "facing an open door" asked in front of a closed
        door turns to the open one beside it, and the choice repeats without end; KeyCorridor, design decisions).
        :meth:`present` then also holds ``(OPEN_DOORS, n)``
    :param mark_blockers: a key that faces a key, a ball or a box that blocks the way (with its cell free the agent
        could reach cells it cannot reach now, doors counted as open: :func:`blockers`) gives it the state
        :data:`BLOCKS`, e.g. ``(nothing, ball, BLOCKS)``, as :meth:`present` does such objects within reach: a ball
        in front of a door is then another sub-goal than the ball moved aside (ObstructedMaze, where the learner of
        "facing a ball", asked after the blocking ball was picked up, put it back on its cell, its quickest way;
        docs/design_decisions.rst); ``"auto"``: where the task puts such an object in every layout it draws
        (:func:`grid_codes`: BlockedUnlockPickup, ObstructedMaze's "b" tasks), read when the goal space is bound to
        the env (:meth:`bind`; off until then)
    :param color_relation: with relative colours, which pairs of the carried object and a cell they relate: "opens"
        a key and a door only (the key opens the door of its colour; other pairs of colours change nothing a step
        does, and each would make one more sub-goal of a situation), "any" every two objects with colours
        (docs/design_decisions.rst)
    :param mark_target: read the mission's object as the observation marks it (:data:`TARGET`,
        :class:`MiniGridEgocentricObs`): a key of facing it, e.g. ``(nothing, ball, TARGET)``, is then a sub-goal of its
        own, and "task solved", in a grid without a goal square, is a choice only facing it (ObstructedMaze, where the
        learner of "task solved" picked up the balls moved off the doors; docs/design_decisions.rst); ``"auto"``: as the
        env's :class:`MiniGridEgocentricObs` marks it (where the task draws other objects of its kind), read when the
        goal space is bound to the env (:meth:`bind`; off until then)
    :param count_blockers: the features (what the predictor, and with ``meta_input`` features the meta-controller,
        read) also hold how many objects on the canvas block the way (0, 1, 2 or more; :func:`blockers`): whether the
        key in hand goes to its door or is put down to move a ball first depends on it (ObstructedMaze,
        docs/design_decisions.rst). Keys are unchanged. ``"auto"`` as ``mark_blockers``'s
    """

    name = "minigrid"
    #: what the env's grids hold (:meth:`bind`, :func:`grid_codes`): object types, and states other than "open"
    object_codes: Optional[list[int]] = None
    state_codes: Optional[list[int]] = None
    color_from_env = False  # use_color "auto": set by bind
    blockers_from_env = (False, False)  # mark_blockers, count_blockers "auto": set by bind
    relative_color = False  # use_color "relative" (use_color is then True: the keys have colour fields)
    color_relation = "any"  # what a goal space pickled before the option related
    keep_doors_open = False  # what a goal space pickled before the options reads
    count_open_doors = False
    mark_blockers = False
    count_blockers = False
    mark_target = False
    target_from_env = False  # mark_target "auto": set by bind

    def __init__(self, use_color: Union[bool, str] = False, tile_size: int = 16, keep_doors_open: bool = False,
                 count_open_doors: bool = False, mark_blockers: Union[bool, str] = False,
                 count_blockers: Union[bool, str] = False, color_relation: str = "opens",
                 mark_target: Union[bool, str] = "auto") -> None:
        if tile_size < 1:
            raise ValueError(f"tile_size must be >= 1, got {tile_size}")
        if not isinstance(use_color, bool) and use_color not in ("auto", "relative"):
            raise ValueError(f"use_color must be True, False, 'relative' (how colours relate) or 'auto' (from the env's "
                             f"keys), got {use_color!r}")
        for name, value in (("mark_blockers", mark_blockers), ("count_blockers", count_blockers)):
            if not isinstance(value, bool) and value != "auto":
                raise ValueError(f"{name} must be True, False or 'auto' (where the env's layouts put an object in the "
                                 f"way), got {value!r}")
        if not isinstance(mark_target, bool) and mark_target != "auto":
            raise ValueError(f"mark_target must be True, False or 'auto' (as the env's MiniGridEgocentricObs marks the "
                             f"mission's object), got {mark_target!r}")
        if color_relation not in _RELATED_TABLES:
            raise ValueError(f"color_relation must be 'opens' (a key and the door of its colour) or 'any' (any two "
                             f"objects with colours), got {color_relation!r}")
        self.color_relation = color_relation
        self.color_from_env = use_color == "auto"
        self.use_color = use_color is True or use_color == "relative"
        self.relative_color = use_color == "relative"
        self.tile_size = tile_size
        self.keep_doors_open = bool(keep_doors_open)
        self.count_open_doors = bool(count_open_doors)
        self.blockers_from_env = (mark_blockers == "auto", count_blockers == "auto")
        self.mark_blockers = mark_blockers is True
        self.count_blockers = count_blockers is True
        self.target_from_env = mark_target == "auto"
        self.mark_target = mark_target is True

    def action_mask(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """With ``keep_doors_open``: every MiniGrid action but ``toggle`` in front of an open door (which would close it)."""
        if not self.keep_doors_open:
            return None
        obs = np.asarray(obs)
        center = obs.shape[-3] // 2
        front = obs[..., center, center - 1, :]
        mask = np.ones((*obs.shape[:-3], len(Actions)), dtype=bool)
        mask[..., int(Actions.toggle)] = ~((front[..., 0] == DOOR) & (front[..., 2] == OPEN))
        return mask

    @classmethod
    def supports(cls, env: gym.Env) -> bool:
        space = env.observation_space
        return (
            find_minigrid(env) is not None
            and isinstance(space, spaces.Box)
            and len(space.shape) == 3
            and space.shape[0] == space.shape[1]
            and space.shape[0] % 2 == 1
            and space.shape[2] == 3
        )

    def bind(self, env: gym.Env) -> None:
        """Record which object types and states the env's grids hold (:func:`grid_codes`, from a copy of the env):
        what :meth:`learner_input` gives the sub-goal learners to read as indicators; with ``use_color`` "auto",
        whether colours are read (as they relate: "relative"); with ``mark_blockers`` "auto", whether objects in the
        way are marked (and with ``count_blockers`` "auto", counted); with ``mark_target`` "auto", whether the env's
        observation marks the mission's object (its :class:`MiniGridEgocentricObs`; without one, where it would)."""
        codes = grid_codes(find_minigrid(env))
        if self.target_from_env:
            wrapper = _find_wrapper(env, MiniGridEgocentricObs)
            marks = None if wrapper is None else wrapper.mark_target
            self.mark_target = codes.target_twin if marks is None else marks
        self.object_codes, self.state_codes = codes.types, codes.states + ([TARGET] if self.mark_target else [])
        if self.color_from_env:
            self.use_color = self.relative_color = codes.key_colors > 1
        mark, count = self.blockers_from_env
        if mark:
            self.mark_blockers = codes.blocked
        if count:
            self.count_blockers = codes.blocked

    @property
    def color_option(self) -> Union[bool, str]:
        """The ``use_color`` that makes a goal space with the same keys (the scripted oracle's must match)."""
        return "relative" if self.relative_color else self.use_color

    def relate_colors(self, obs: np.ndarray) -> np.ndarray:
        """With relative colours, a copy of observations ``(..., S, S, 3)`` whose colour channel says how each cell's
        colour relates to the carried object's (what :meth:`present`, :meth:`features` and the sub-goal learners read):
        :data:`SAME_COLOR` where the agent carries an object of that colour and the cell, not the agent's own, holds one
        too that ``color_relation`` relates to it (a door to a key; with "any", keys, balls, boxes and doors to each
        other), else 0. Without them, the observations themselves."""
        if not self.relative_color:
            return obs
        obs = np.array(obs, copy=True)
        center = obs.shape[-3] // 2
        carried = obs[..., center, center, :]
        related = _RELATED_TABLES[self.color_relation][carried[..., None, None, 0], obs[..., 0]]
        same = related & (obs[..., 1] == carried[..., None, None, 1])
        same[..., center, center] = False
        obs[..., 1] = same
        return obs

    def learner_codes(self) -> Optional[Callable[[np.ndarray], np.ndarray]]:
        """With relative colours, :meth:`relate_colors`: the learner of "carrying the key, facing the door of its colour"
        reads which door that is (``one_hot`` "auto" lists :data:`SAME_COLOR` as the colour channel's code)."""
        return self.relate_colors if self.relative_color else None

    def learner_input(self, observation_space: spaces.Space) -> dict[str, Any]:
        """The sub-goal learners' ``view``, ``overview`` and ``one_hot`` (``subgoal_learner_kwargs``) that ``"auto"``
        stands for, derived from the env: the :data:`LEARNER_VIEW` cells around the agent and an overview of the
        whole canvas (:data:`LEARNER_OVERVIEW`) where the canvas's inner cells are wider than the view, else every
        inner cell; the object types and states its grids hold (:meth:`bind`) as indicators, colours left out (with
        relative colours, whether a cell has the carried object's colour: :meth:`learner_codes`)."""
        if self.object_codes is None:
            raise ValueError("subgoal_learner_kwargs 'auto' reads what the env's grids hold: bind the goal space to the "
                             "env first (make_goal_space(goal_space, env) does)")
        wide = observation_space.shape[0] - 2 > LEARNER_VIEW
        return dict(view=LEARNER_VIEW if wide else "inner", overview=LEARNER_OVERVIEW if wide else None,
                    one_hot=[list(self.object_codes), [SAME_COLOR] if self.relative_color else [], list(self.state_codes)])

    def key(self, obs: np.ndarray) -> Hashable:
        obs = np.asarray(obs)
        center = obs.shape[0] // 2
        return self.key_of(obs[center, center], obs[center, center - 1], lambda: open_doors(obs),
                           lambda: bool(blockers(obs[None, ..., 0], [(center, center)])[0, center, center - 1]))

    def key_of(self, carried: Sequence[int], front: Sequence[int], count_open: Callable[[], int],
               blocks: Optional[Callable[[], bool]] = None) -> Hashable:
        """The key of a state from the encodings of the carried object and of the one in front; ``count_open()``
        (how many doors of the grid are open) is called only where ``count_open_doors`` needs it, ``blocks()``
        (whether the object in front blocks the way, :func:`blockers`) where ``mark_blockers`` does. :meth:`~sb3_hhp.goals.base.GoalSpace.key`
        reads them from an observation, the scripted oracle from the grid its search changes."""
        state = int(front[2])
        if state == TARGET and not self.mark_target:  # the observation marks what this goal space does not read
            state = 0
        if self.mark_blockers and front[0] in PICKABLE and blocks is not None and blocks():
            state = BLOCKS
        if self.relative_color:
            same = _RELATED_TABLES[self.color_relation][int(carried[0]), int(front[0])] and carried[1] == front[1]
            key = (int(carried[0]), RELATIVE, int(front[0]), SAME_COLOR if same else 0, state)
        elif self.use_color:
            key = (int(carried[0]), int(carried[1]), int(front[0]), int(front[1]), state)
        else:
            key = (int(carried[0]), int(front[0]), state)
        if self.count_open_doors and front[0] == DOOR and front[2] == OPEN:
            key += (int(count_open()),)
        return key

    def carried_counterfactual(self, goal_key: Hashable, obs: np.ndarray, actions: np.ndarray,
                               next_obs: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray, list]]:
        """Steps taken with empty hands, as they would have gone carrying the object ``goal_key`` carries: that
        object (the only one of its kind, and colour with ``use_color``, in both states) taken off its cell and put
        in the agent's. Usable only where carrying it changes nothing else: the agent's hands empty before and after,
        and a turn, a step or ``done`` (a pick-up, a drop or a toggle would go otherwise), but not a step into the
        object itself (it blocks the way while on the floor). See :meth:`~sb3_hhp.goals.base.GoalSpace.carried_counterfactual`."""
        if goal_key == SUCCESS_KEY or not isinstance(goal_key, tuple) or goal_key[0] in (EMPTY, 0):
            return None  # the task's own goal or empty hands: nothing to carry
        kind, colour = goal_key[0], (goal_key[1] if self.use_color and not self.relative_color else None)
        obs, next_obs = np.array(obs, copy=True), np.array(next_obs, copy=True)
        actions = np.asarray(actions).reshape(len(obs))
        center = obs.shape[-3] // 2

        def the_object(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            match = states[..., 0] == kind
            if colour is not None:
                match &= states[..., 1] == colour
            match = match.reshape(len(states), -1)
            return match.sum(axis=1) == 1, match.argmax(axis=1)

        once, cell = the_object(obs)
        next_once, next_cell = the_object(next_obs)
        empty_handed = (obs[:, center, center, 0] == EMPTY) & (next_obs[:, center, center, 0] == EMPTY)
        into_it = (actions == Actions.forward) & (obs[:, center, center - 1, 0] == kind)
        usable = once & next_once & empty_handed & np.isin(actions, _CARRY_FREE_ACTIONS) & ~into_it
        rows = np.flatnonzero(usable)
        for states, cells in ((obs, cell), (next_obs, next_cell)):
            flat = states.reshape(len(states), -1, states.shape[-1])
            held = flat[rows, cells[rows]].copy()
            flat[rows, cells[rows]] = _EMPTY_CELL
            states[rows, center, center] = held
        return usable, obs, next_obs, [self.key(state) for state in next_obs[rows]]

    def is_milestone(self, key: Hashable, carried_before: Optional[int] = None) -> bool:
        """A key worth pursuing: facing an object one interacts with, the task solved, or a change of what is carried."""
        if key == SUCCESS_KEY:
            return True
        carried, front = key[0], key[2] if self.use_color else key[1]
        return front in INTERACTIVE or (carried_before is not None and carried != carried_before)

    def present(self, obs: np.ndarray) -> frozenset:
        """The objects within reach: those the agent can walk to and face without opening anything on the way
        (through empty cells, floor, open doors and goal squares), each as (object, state), or (object, colour,
        state) with ``use_color``; the agent's cell (the carried object) is left out. When the grid has a goal
        square and none is within reach, the set also holds :data:`GOAL_OUT_OF_REACH`; when it has none,
        :data:`NO_GOAL_SQUARE`."""
        return self.present_batch(np.asarray(obs)[None])[0]

    def present_batch(self, observations: np.ndarray) -> list[frozenset]:
        """:meth:`present` of each observation of a batch ``(N, S, S, 3)``, the regions of all of them labelled
        in one pass (a meta-controller's update masks the choices of a whole batch of closing states)."""
        obs = np.asarray(observations)
        n, center = len(obs), obs.shape[1] // 2
        objects, states = obs[..., 0], obs[..., 2]
        passable = _PASSABLE_TABLE[objects] | ((objects == DOOR) & (states == OPEN))
        passable[:, center, center] = True
        regions, _ = ndimage.label(passable, structure=_GRID_CROSS)
        reached = regions == regions[:, center, center][:, None, None]
        near = reached | _beside(reached)  # and the cells next to a reached one (4-connected), which can be faced
        near[:, center, center] = False
        rows, ys, xs = np.nonzero(near & _INTERACTIVE_TABLE[objects])
        columns = [0, 1, 2] if self.use_color else [0, 2]
        cells = self.relate_colors(obs)[rows, ys, xs][:, columns]
        if not self.mark_target:  # the observation marks what this goal space does not read
            cells[cells[:, -1] == TARGET, -1] = 0
        if self.mark_blockers:  # as the keys name them: objects one picks up that block the way
            cells[blockers(objects, np.full((n, 2), center))[rows, ys, xs], -1] = BLOCKS
        found: list[list[tuple]] = [[] for _ in range(n)]
        for row, *cell in np.unique(np.column_stack([rows, cells]), axis=0).tolist():  # (row, object[, colour], state)
            found[row].append(tuple(cell))
        has_goal = (objects == GOAL).any(axis=(1, 2))
        goal_within = np.zeros(n, dtype=bool)
        goal_within[rows[cells[:, 0] == GOAL]] = True
        doors = open_doors(obs) if self.count_open_doors else None
        within = []
        for i in range(n):
            items = set(found[i])
            if not has_goal[i]:
                items.add(NO_GOAL_SQUARE)
            elif not goal_within[i]:
                items.add(GOAL_OUT_OF_REACH)
            if doors is not None:
                items.add((OPEN_DOORS, int(doors[i])))
            within.append(frozenset(items))
        return within

    def choosable(self, key: Hashable, goal_key: Hashable, present: Optional[frozenset] = None) -> bool:
        """Not achieved in the state, and one skill away from it: with the same carried object, facing an
        object one interacts with (walk there, or open the door in front); with a different one, a pick-up of
        the object in front (the agent then faces the emptied cell) or a drop of what is carried (turning to a
        free cell if need be; it then faces what it dropped): walking to the key and picking it up are two
        choices, not one. A drop is a choice wherever the agent faces: were it one only in front of an empty
        cell, no choice could put the key down once it has opened a door (the agent then faces the door), and
        a task that ends by picking up an object behind that door (KeyCorridor) could not be planned with
        choices. With ``present`` (:meth:`present`), a walk is choosable only to an object within reach in that
        state ("facing the locked door" not once it is open, nothing behind a locked door), opening the door in
        front always (closing it never: no task needs it, and a loop of opening and closing succeeds at every
        choice), opening the box in front always (the agent then faces what it held, a key or a ball: no
        observation shows which before), and "task solved" only while a goal square is within reach or, in a grid with
        no goal square (the task ends with a pick-up), only with empty hands in front of an object one can pick
        up. "Facing a wall / an empty cell" is never worth a choice of its own, and "carrying the key, facing
        the locked door" is not chosen before the key is carried: such choices ask a subpolicy for two skills
        in a row, and both its success rate and the meta-controller's values then mix two tasks."""
        if not super().choosable(key, goal_key):
            return False
        if key == SUCCESS_KEY:
            return True
        front_at = 2 if self.use_color else 1
        carried, front = key[:front_at], key[front_at : 2 * front_at]  # (object[, colour]) carried / in front
        # the same object carried and then in front, or the other way round (relative colours: of its kind)
        moved = (lambda a, b: a[0] == b[0]) if self.relative_color else (lambda a, b: a == b)
        if goal_key == SUCCESS_KEY:
            if present is None:
                return True
            if NO_GOAL_SQUARE in present:  # a pick-up of the object in front (the mission's, where it is marked)
                return carried[0] == EMPTY and front[0] in PICKABLE and (not self.mark_target
                                                                          or key[2 * front_at] == TARGET)
            return GOAL_OUT_OF_REACH not in present  # not while the goal square is behind a locked door
        goal_carried, goal_front = goal_key[:front_at], goal_key[front_at : 2 * front_at]
        if goal_carried == carried:
            if goal_front[0] not in INTERACTIVE:
                return False
            # walk to an object that is in the grid, or toggle the one in front (a door: only its state changes)
            goal_object = goal_key[front_at : 2 * front_at + 1]  # (object[, colour], state)
            # (a toggle opens a locked or closed door; closing one is no choice: no MiniGrid task needs a door
            # closed, and an open-close loop succeeds at every choice)
            toggle = goal_front == front and goal_object[-1] == OPEN and key[2 * front_at] != OPEN
            # a toggle of the box in front leaves what it holds in its place, which no observation shows before
            # (ObstructedMaze's keys): facing a key or a ball is then one skill away
            toggle |= front[0] == BOX and goal_front[0] in PICKABLE and goal_front[0] != BOX
            if present is None:
                return True
            if len(goal_key) > 2 * front_at + 1:  # count_open_doors: how many doors are open once it is reached
                now = next((item[1] for item in present if isinstance(item, tuple) and item[0] == OPEN_DOORS), None)
                if now is not None:  # walk to a door open now, or open the one in front: one door more
                    return (goal_object in present and goal_key[-1] == now) or (toggle and goal_key[-1] == now + 1)
            return goal_object in present or toggle
        if carried[0] == EMPTY:  # a pick-up of the object in front; the agent then faces the emptied cell
            return front[0] in PICKABLE and moved(goal_carried, front) and goal_front[0] == EMPTY
        # a drop (onto the empty cell in front, or after a turn to one); the dropped object then lies in front
        return goal_carried[0] == EMPTY and moved(goal_front, carried)

    def features(self, obs: np.ndarray) -> np.ndarray:
        """What the preference predictor reads: one-hots of the carried object, the object in front and its
        state (and, with ``use_color``, both colours), then which (object, state) pairs are present anywhere
        in the grid (a locked door, an open door, a key on the floor, ...); before those, with ``count_open_doors``,
        a one-hot of how many doors are open, with ``mark_blockers`` one of whether the object in front blocks the way
        (:func:`blockers`), and with ``count_blockers`` one of how many objects block it. Positions are left out, so
        the description recurs across layouts and a hundred labels can teach a ranking of sub-goals that holds in
        every layout."""
        batch = self.relate_colors(np.asarray(obs).reshape(-1, *np.shape(obs)[-3:]).astype(np.int64))
        center, rows = batch.shape[1] // 2, np.arange(len(batch))
        objects = np.clip(batch[..., 0], 0, N_OBJECTS - 1)
        colors = np.clip(batch[..., 1], 0, N_COLORS - 1)
        # MiniGrid's states, and with mark_target one more for the mission's object (TARGET)
        n_states = N_STATES + 1 if self.mark_target else N_STATES
        states = np.where(batch[..., 2] == TARGET, n_states - 1 if self.mark_target else 0,
                          np.clip(batch[..., 2], 0, N_STATES - 1))
        parts = [
            (objects[:, center, center], N_OBJECTS),
            (objects[:, center, center - 1], N_OBJECTS),
            (states[:, center, center - 1], n_states),
        ]
        if self.relative_color:  # whether the object in front has the carried object's colour
            parts.append(((batch[:, center, center - 1, 1] == SAME_COLOR).astype(np.int64), 2))
        elif self.use_color:
            parts += [(colors[:, center, center], N_COLORS), (colors[:, center, center - 1], N_COLORS)]
        if self.count_open_doors:  # how many doors are open, the last value for MAX_COUNTED_DOORS - 1 or more
            parts.append((np.minimum(open_doors(batch), MAX_COUNTED_DOORS - 1), MAX_COUNTED_DOORS))
        if self.mark_blockers or self.count_blockers:
            blocking = blockers(batch[..., 0], np.full((len(batch), 2), center))
            if self.mark_blockers:  # whether the object in front blocks the way
                parts.append((blocking[:, center, center - 1].astype(np.int64), 2))
            if self.count_blockers:  # how many objects block the way, anywhere
                counts = np.count_nonzero(blocking, axis=(1, 2))
                parts.append((np.minimum(counts, MAX_COUNTED_BLOCKERS - 1), MAX_COUNTED_BLOCKERS))
        size = sum(n for _, n in parts) + N_OBJECTS * n_states
        out = np.zeros((len(batch), size), dtype=np.float32)
        offset = 0
        for values, n in parts:
            out[rows, offset + values] = 1.0
            offset += n
        pairs = (objects * n_states + states).reshape(len(batch), -1)
        out[rows[:, None], offset + pairs] = 1.0  # presence of each (object, state) in the grid
        return out

    def privileged(self, env: gym.Env) -> dict[str, Any]:
        return self.facts(self.snapshot(env))

    def snapshot(self, env: gym.Env) -> dict[str, Any]:
        """The privileged facts with the grid's encoding as a uint8 array (W, H, 3): a few hundred bytes where its
        nested lists take ~24 KB on DoorKey-16x16."""
        base = find_minigrid(env)
        if base is None:
            return {}
        target = getattr(base, "obj", None)  # KeyCorridor / ObstructedMaze: the object to pick up
        return {
            "grid": encode_grid(base.grid),
            "agent_pos": [int(v) for v in base.agent_pos],
            "agent_dir": int(base.agent_dir),
            "carrying": list(base.carrying.encode()) if base.carrying is not None else None,
            "target": list(target.encode()[:2]) if target is not None else None,
            # what each box holds (its encoding shows no contents; opening it leaves them in its place)
            "boxes": [[x, y, list(obj.contains.encode()) if obj.contains is not None else None]
                      for x, y, obj in ((i % base.width, i // base.width, obj) for i, obj in enumerate(base.grid.grid))
                      if isinstance(obj, Box)],
            # and what the carried box holds (a box keeps its contents while carried)
            "carrying_holds": (list(base.carrying.contains.encode())
                               if isinstance(base.carrying, Box) and base.carrying.contains is not None else None),
        }

    def facts(self, snapshot: dict[str, Any]) -> dict[str, Any]:
        facts = dict(snapshot)
        if isinstance(facts.get("grid"), np.ndarray):
            facts["grid"] = facts["grid"].tolist()
        return facts

    def render(self, env: gym.Env) -> Optional[np.ndarray]:
        base = find_minigrid(env)
        if base is None:
            return None
        return np.asarray(base.get_frame(highlight=False, tile_size=self.tile_size), dtype=np.uint8)

    def image_of(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """Draw an egocentric observation (agent in the centre, facing up) with MiniGrid's renderer."""
        obs = np.asarray(obs)
        center = obs.shape[0] // 2
        grid, _ = Grid.decode(obs)
        return np.asarray(grid.render(self.tile_size, agent_pos=(center, center), agent_dir=3), dtype=np.uint8)

    def concerned_cells(self, state: dict[str, Any], key: Hashable) -> np.ndarray:
        """Which cells of the state's grid (a boolean (W, H) mask, ``[x, y]``) a sub-goal concerns: the goal
        squares for "task solved"; else the objects of the kind to face (a door in any state: the same door
        is opened or closed) and, when the sub-goal carries something the agent does not carry yet, the
        objects of that kind to pick up. Walls and empty cells are nobody's target: an empty mask.

        :param state: privileged facts of the state (:meth:`~sb3_hhp.goals.base.GoalSpace.privileged`): ``grid``, ``carrying``
        :param key: the sub-goal key
        """
        codes = np.asarray(state["grid"], dtype=np.int64)
        objects, colors = codes[..., 0], codes[..., 1]
        if key == SUCCESS_KEY:
            return objects == GOAL
        carrying_now = state.get("carrying")
        now = EMPTY if not carrying_now else int(carrying_now[0])
        if self.relative_color:  # a colour only where the key names the carried one's and the state carries it
            carried, _, front, same, _ = key[:5]
            carried_color = None
            front_color = int(carrying_now[1]) if same == SAME_COLOR and carried == now != EMPTY else None
        elif self.use_color:
            carried, carried_color, front, front_color, _ = key[:5]
        else:
            (carried, front, _), carried_color, front_color = key[:3], None, None

        def of_kind(kind: int, color: Optional[int]) -> np.ndarray:
            return (objects == kind) & (True if color is None else colors == color)

        if key[4 if self.use_color else 2] == TARGET and state.get("target") is not None:
            front_color = int(state["target"][1])  # the mission's object, not the others of its kind
        mask = of_kind(front, front_color) if front in INTERACTIVE else np.zeros(objects.shape, dtype=bool)
        if carried != EMPTY and carried != now:
            mask |= of_kind(carried, carried_color)
        return mask

    draws_from_facts = True

    def image_in_state(self, state: dict[str, Any], key: Optional[Hashable] = None) -> Optional[np.ndarray]:
        """The state's room drawn by MiniGrid's renderer from its privileged facts (``grid``, ``agent_pos``,
        ``agent_dir``); with ``key``, the cells it concerns (:meth:`concerned_cells`) keep their colours
        inside a :data:`HIGHLIGHT_RGB` frame and the rest of the room is dimmed. None when ``state`` lacks
        those facts."""
        try:
            codes = np.asarray(state["grid"], dtype=np.uint8)
            agent_pos = tuple(int(v) for v in state["agent_pos"])
            agent_dir = int(state["agent_dir"])
        except (KeyError, TypeError, ValueError):
            return None
        if codes.ndim != 3 or codes.shape[2] != 3 or not all(0 <= v < n for v, n in zip(agent_pos, codes.shape[:2])):
            return None
        grid, _ = Grid.decode(codes)
        tile = self.tile_size
        image = np.asarray(grid.render(tile, agent_pos=agent_pos, agent_dir=agent_dir), dtype=np.uint8)
        if key is None:
            return image
        mask = self.concerned_cells(state, key)
        if not mask.any():
            return image
        bright = np.kron(mask.T, np.ones((tile, tile), dtype=bool))  # image rows are y, columns x
        bright[agent_pos[1] * tile : (agent_pos[1] + 1) * tile, agent_pos[0] * tile : (agent_pos[0] + 1) * tile] = True
        image = np.where(bright[..., None], image, (image * DIM).astype(np.uint8))
        width = max(1, tile // 8)
        for x, y in np.argwhere(mask):
            cv2.rectangle(image, (x * tile, y * tile), ((x + 1) * tile - 1, (y + 1) * tile - 1), HIGHLIGHT_RGB, width)
        return image

    def describe(self, key: Hashable) -> str:
        if key == SUCCESS_KEY:
            return "task solved"
        if self.use_color:
            carried, _, front, same, state = key[:5]
        else:
            carried, front, state = key[:3]
        front_name = IDX_TO_OBJECT.get(front, str(front))
        of_its_color = self.relative_color and same == SAME_COLOR
        if front_name == "door":
            front_name = f"{IDX_TO_STATE.get(state, state)} door"
            if len(key) == (6 if self.use_color else 4):  # with count_open_doors
                front_name += f" ({key[-1]} open in all)"
        elif state == BLOCKS:
            front_name += " that blocks the way"
        elif state == TARGET:
            front_name = f"the mission's {front_name}"
        if of_its_color:
            front_name += " of its colour"
        carried_name = "nothing" if carried == EMPTY else IDX_TO_OBJECT.get(carried, str(carried))
        return f"carrying {carried_name}, facing {front_name}"
