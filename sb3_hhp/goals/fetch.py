"""Goal space for the gymnasium-robotics Fetch tasks (Reach, Push, PickAndPlace, Slide).

A Fetch observation is a dict: ``observation`` (the robot and object state), ``achieved_goal`` (the
gripper's position for Reach, the object's for the others, in metres) and ``desired_goal`` (the episode's
target). :class:`FetchFlatObs` flattens it into one float32 vector ``[observation, achieved_goal,
desired_goal]`` that every network of HhP reads.

A sub-goal is a place for the achieved position. Its key is the ``cell_size`` cube (1 cm by default) that
holds ``achieved_goal``, so that keys recur and visits can be counted (CSD's "visited several times"). The
table does not move between episodes, so a place found in one episode is a place to go in the next
(design decisions: a sub-goal recurs), while the desired goal changes; the meta-controller sees the desired goal in the
observation and learns which place to go to. ``done(s, g)`` is the paper's (section 5.1): the achieved
position is within ``distance_threshold`` (0.05 m) of the sub-goal's, measured between cell centres. The
discovery gate's similarity falls with that distance d: 1 / (1 + (d / distance_threshold)^2), 1 at the same
place and 0.5 at the threshold, so with ``b_similarity = 0.5`` no new sub-goal lies within reach of an old
one. Places become sub-goals only within the task's region (:func:`task_region`, widened by ``distance_threshold``):
where its targets lie and its achieved position starts, not a block on the floor (design decisions: the task's region). On the tasks with an object (Push, PickAndPlace, Slide) the key also says whether the gripper is at the object
(within ``distance_threshold`` of it, ``gripper=True``): the object cannot move before the gripper reaches it, and
that first step of every episode is then a sub-goal of its own, "the object at its place with the gripper at it",
found where the gripper first comes to the object (design decisions: the gripper at the object). A sub-goal with the
gripper at the object is reached where the object is within reach of its place and the gripper at the object; one
without, wherever the gripper is. People see the rendered scene when the env renders (``render_mode="rgb_array"``), else a drawing of the
achieved position and the target seen from above and from the side. The envs' own camera shows the whole robot,
the table top a third of the frame wide; :data:`TABLE_CAMERA` looks down at the table top, where the object (a black
cube) and the target (a red sphere) come out about twice as large across::

    gym.make("FetchPush-v4", render_mode="rgb_array", default_camera_config=TABLE_CAMERA)
"""

import math
from collections.abc import Hashable, Sequence
from typing import Any, Optional

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace

#: the region drawn by :meth:`FetchGoalSpace.image_of` (metres): the table top in front of the robot
VIEW_CENTER = np.array([1.30, 0.75, 0.60])
VIEW_HALF_WIDTH = 0.40
#: pixels per side of each of the two panels of the drawing
PANEL = 64
#: a camera on the table top for the scenes people see (``default_camera_config`` of the Fetch envs; distance in
#: metres, angles in degrees): the whole table top seen from above, the robot behind it
TABLE_CAMERA = {"distance": 1.5, "azimuth": 160.0, "elevation": -50.0, "lookat": np.array([1.30, 0.75, 0.42])}
#: the parts of a Fetch observation, in the order :class:`FetchFlatObs` concatenates them
FIELDS = ("observation", "achieved_goal", "desired_goal")
#: how far above the table a target "in the air" may lie (metres; gymnasium-robotics draws it in [0, 0.45))
AIR_HEIGHT = 0.45


def find_fetch(env: gym.Env) -> Optional[gym.Env]:
    """The gymnasium-robotics Fetch env underneath ``env`` (None when it is not a Fetch task)."""
    base = getattr(env, "unwrapped", env)
    return base if type(base).__module__.startswith("gymnasium_robotics.envs.fetch") else None


class FetchFlatObs(gym.ObservationWrapper):
    """Observation: ``[observation, achieved_goal, desired_goal]`` as one float32 vector, the layout
    :class:`FetchGoalSpace` reads (the last six entries are the achieved and the desired position)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        space = env.observation_space
        if find_fetch(env) is None or not isinstance(space, spaces.Dict) or set(space.spaces) != set(FIELDS):
            raise ValueError(
                f"FetchFlatObs needs a gymnasium-robotics Fetch env with its dict observation, got {env} "
                f"observing {space}"
            )
        size = sum(int(np.prod(space[name].shape)) for name in FIELDS)
        self.observation_space = spaces.Box(-np.inf, np.inf, (size,), np.float32)

    def observation(self, observation: dict[str, Any]) -> np.ndarray:
        return np.concatenate([np.ravel(observation[name]) for name in FIELDS]).astype(np.float32)


def task_region(env: gym.Env) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The box (low and high corners, metres) that holds every target the Fetch env under ``env`` can draw and every
    place its achieved position starts from (the gripper's start on Reach, the object's start region on the others),
    read off the env's own sampling settings; None where the env does not have them."""
    base = find_fetch(env)
    try:
        center = np.asarray(base.initial_gripper_xpos, dtype=np.float64)[:3]
        spread = float(base.target_range)
        offset = np.broadcast_to(np.asarray(base.target_offset, dtype=np.float64), (3,))
        has_object = bool(base.has_object)
        height = float(base.height_offset) if has_object else 0.0
        object_range = float(base.obj_range) if has_object else 0.0
        in_the_air = bool(base.target_in_the_air)
    except (AttributeError, TypeError, ValueError):
        return None
    low, high = center + offset - spread, center + offset + spread
    if not has_object:  # Reach: targets in a cube around the gripper's start, which it holds
        return np.minimum(low, center), np.maximum(high, center)
    # the object's targets lie on the table top (and up to AIR_HEIGHT above it); it starts on the table near the gripper
    low[2], high[2] = height, height + (AIR_HEIGHT if in_the_air else 0.0)
    start_low = np.array([center[0] - object_range, center[1] - object_range, height])
    start_high = np.array([center[0] + object_range, center[1] + object_range, height])
    return np.minimum(low, start_low), np.maximum(high, start_high)


def _gripper_at(key: Hashable) -> int:
    """The flag "the gripper at the object" of a place's key (0 for a key without it: Reach's, or an older one)."""
    return int(key[3]) if len(key) > 3 else 0


class FetchGoalSpace(GoalSpace):
    """Sub-goal key = the ``cell_size`` cube that holds the achieved position (gripper or object), read off
    a :class:`FetchFlatObs` observation; a sub-goal is reached within ``distance_threshold`` of it.

    :param cell_size: side of a key's cell in metres (> 0)
    :param distance_threshold: ``done(s, g)`` distance in metres (> 0); the paper's and the Fetch tasks' own 0.05
    :param gripper: on a task with an object, the key's fourth entry: 1 where the gripper is within
        ``distance_threshold`` of the object, else 0 (no effect on Reach, whose achieved position is the gripper's)
    """

    name = "fetch"
    #: whether keys carry the "gripper at the object" flag: set by :meth:`bind` on a task with an object; a goal space
    #: pickled before the flag existed reads these class values, and keeps its 3-entry keys when bound again
    with_gripper: bool = False
    gripper: bool = False
    #: where places may become sub-goals (low and high corners, metres): the task's region (:func:`task_region`) widened
    #: by ``distance_threshold``, set by :meth:`bind`; None: everywhere
    region: Optional[tuple[np.ndarray, np.ndarray]] = None

    def __init__(self, cell_size: float = 0.01, distance_threshold: float = 0.05, gripper: bool = True) -> None:
        if not cell_size > 0:
            raise ValueError(f"cell_size must be > 0 metres, got {cell_size}")
        if not distance_threshold > 0:
            raise ValueError(f"distance_threshold must be > 0 metres, got {distance_threshold}")
        self.cell_size = float(cell_size)
        self.distance_threshold = float(distance_threshold)
        self.gripper = bool(gripper)

    def bind(self, env: gym.Env) -> None:
        """Keys carry the gripper's flag where the task has an object (its observation then starts with the gripper's
        position and the object's); sub-goals are found within the task's region, widened by ``distance_threshold``."""
        self.with_gripper = self.gripper and bool(getattr(find_fetch(env), "has_object", False))
        region = task_region(env)
        self.region = None if region is None else (region[0] - self.distance_threshold, region[1] + self.distance_threshold)

    def discoverable(self, key: Hashable) -> bool:
        """A place may become a sub-goal within the task's region (:attr:`region`): where the task's targets lie and its
        object (or the gripper, on Reach) starts. The object pushed off the table, or the gripper far from the table,
        is new to curiosity but no step towards any target. The task solved always may."""
        if key == SUCCESS_KEY or self.region is None:
            return True
        center = self.cell_center(key)
        return bool(np.all(center >= self.region[0]) and np.all(center <= self.region[1]))

    @classmethod
    def supports(cls, env: gym.Env) -> bool:
        base, space = find_fetch(env), env.observation_space
        if base is None or not isinstance(space, spaces.Box) or len(space.shape) != 1:
            return False
        base_space = base.observation_space
        if not isinstance(base_space, spaces.Dict) or "observation" not in base_space.spaces:
            return False
        return space.shape[0] == int(np.prod(base_space["observation"].shape)) + 6

    @staticmethod
    def achieved_position(obs: np.ndarray) -> np.ndarray:
        """The achieved position (metres) of a flat observation, or of a batch ``(B, D)``."""
        return np.asarray(obs, dtype=np.float64)[..., -6:-3]

    @staticmethod
    def desired_position(obs: np.ndarray) -> np.ndarray:
        """The episode's target position (metres) of a flat observation, or of a batch ``(B, D)``."""
        return np.asarray(obs, dtype=np.float64)[..., -3:]

    def gripper_at_object(self, obs: np.ndarray) -> np.ndarray:
        """Whether the gripper is within ``distance_threshold`` of the object (the first two positions of a Fetch
        observation with an object), for an observation or a batch; False without the flag."""
        obs = np.asarray(obs, dtype=np.float64)
        if not self.with_gripper:
            return np.zeros(obs.shape[:-1], bool)
        return np.linalg.norm(obs[..., 0:3] - obs[..., 3:6], axis=-1) <= self.distance_threshold

    def achieved_goal(self, obs: np.ndarray) -> np.ndarray:
        """What the goal-conditioned learner reaches, of a batch ``(B, D)``: the achieved position, then the gripper's
        flag where keys carry it (``(B, 3)`` or ``(B, 4)``)."""
        position = self.achieved_position(obs)
        if not self.with_gripper:
            return position
        return np.concatenate([position, self.gripper_at_object(obs)[..., None].astype(np.float64)], axis=-1)

    def key(self, obs: np.ndarray) -> Hashable:
        cell = tuple(int(v) for v in np.floor(self.achieved_position(obs) / self.cell_size))
        return cell + (int(self.gripper_at_object(obs)),) if self.with_gripper else cell

    def solved(self, obs: np.ndarray) -> np.ndarray:
        """Whether the achieved position is within ``distance_threshold`` of the target (the env's ``is_success``),
        for an observation or a batch."""
        distance = np.linalg.norm(self.achieved_position(obs) - self.desired_position(obs), axis=-1)
        return distance <= self.distance_threshold

    def terminal_key(self, obs: np.ndarray, reward: float, terminated: bool) -> Hashable:
        """:data:`~sb3_hhp.goals.base.SUCCESS_KEY` where the task is solved (a Fetch episode never terminates: it is solved where the
        achieved position is at the target), else the place's key."""
        return SUCCESS_KEY if bool(self.solved(obs)) else self.key(obs)

    def choosable(self, key: Hashable, goal_key: Hashable, present: Optional[frozenset] = None) -> bool:
        """Every place but the one reached; the task's target always (success is judged at the episode's last step:
        where it is reached it is held)."""
        return goal_key == SUCCESS_KEY or not self.achieved(key, goal_key)

    def goal_position(self, key: Optional[Hashable], obs: np.ndarray) -> np.ndarray:
        """The place (metres) a sub-goal asks for in state ``obs``: its cell's centre; the state's target for the
        task's own goal (:data:`~sb3_hhp.goals.base.SUCCESS_KEY`) or for none (``key`` None). Where keys carry the
        gripper's flag, the flag follows (the task's own goal asks for none)."""
        if key is None or key == SUCCESS_KEY:
            place, flag = self.desired_position(obs), 0
        else:
            place, flag = self.cell_center(key), _gripper_at(key)
        return np.append(place, float(flag)) if self.with_gripper else place

    @staticmethod
    def state_part(obs: np.ndarray) -> np.ndarray:
        """A flat observation without its achieved and desired positions (what a goal-conditioned learner reads
        beside the place it is sent to)."""
        return np.asarray(obs)[..., :-6]

    def cell_center(self, key: Hashable) -> np.ndarray:
        """The centre (metres) of a key's cell."""
        return (np.asarray(key[:3], dtype=np.float64) + 0.5) * self.cell_size

    def distance(self, key: Hashable, other: Hashable) -> float:
        """Distance in metres between the centres of two keys' cells (infinite between a place and
        :data:`~sb3_hhp.goals.base.SUCCESS_KEY`, 0 between two); the gripper's flags are not a distance."""
        if key == SUCCESS_KEY or other == SUCCESS_KEY:
            return 0.0 if key == other else math.inf
        return self.cell_size * math.dist(key[:3], other[:3])  # centres are (key + 0.5) * cell_size: no arrays per step

    def achieved(self, key: Hashable, goal_key: Hashable) -> bool:
        """``done(s, g)``: the achieved position is within ``distance_threshold`` of the sub-goal's, and the gripper
        at the object where the sub-goal has it there."""
        if self.distance(key, goal_key) > self.distance_threshold + 1e-9:
            return False
        return goal_key == SUCCESS_KEY or _gripper_at(key) >= _gripper_at(goal_key)

    def similarity(self, key: Hashable, obs: np.ndarray, goal_keys: Sequence[Hashable], goal_obs: np.ndarray) -> np.ndarray:
        """1 / (1 + (d / distance_threshold)^2), d the distance between the places: 1 at the same place, 0.5 at
        the threshold; 0 between keys whose gripper's flags differ (the gripper reaching the object is new)."""
        distances = np.array([self.distance(key, other) for other in goal_keys], dtype=np.float64)
        similarity = 1.0 / (1.0 + (distances / self.distance_threshold) ** 2)
        if key != SUCCESS_KEY:
            flags = [other != SUCCESS_KEY and _gripper_at(other) != _gripper_at(key) for other in goal_keys]
            similarity[np.array(flags, dtype=bool)] = 0.0
        return similarity

    def query_info(self, state: np.ndarray, goal1_obs: np.ndarray, goal2_obs: np.ndarray) -> dict[str, Any]:
        """What :class:`~sb3_hhp.oracles.fetch.FetchScriptedOracle` reads: the state's target and each
        sub-goal's achieved position (where it was found), in metres."""
        desired = self.desired_position(state)
        # the task's own goal ("task solved", found where a target was reached) is the target of this state
        places = [desired if self.solved(obs) else self.achieved_position(obs) for obs in (goal1_obs, goal2_obs)]
        info = {"desired_goal": desired.tolist(), "goal1_achieved": places[0].tolist(), "goal2_achieved": places[1].tolist()}
        if self.with_gripper:  # whether each sub-goal has the gripper at the object (the task solved: none asked)
            for name, obs in (("goal1", goal1_obs), ("goal2", goal2_obs)):
                info[f"{name}_gripper_at_object"] = bool(self.gripper_at_object(obs)) and not bool(self.solved(obs))
        return info

    def image_of(self, obs: np.ndarray) -> np.ndarray:
        """Two panels, seen from above (x right, y up) and from the side (x right, z up), of the region
        around the table: the achieved position as a filled blue dot, the target as a red ring, and on a task with
        an object the gripper as a small black dot."""
        marks = [(self.desired_position(obs), (220, 40, 40), 4, 1), (self.achieved_position(obs), (40, 80, 220), 4, -1)]
        if self.with_gripper:
            marks.append((np.asarray(obs, dtype=np.float64)[0:3], (20, 20, 20), 2, -1))
        panels = []
        for axes in ((0, 1), (0, 2)):
            panel = np.full((PANEL, PANEL, 3), 235, dtype=np.uint8)
            cv2.rectangle(panel, (0, 0), (PANEL - 1, PANEL - 1), (160, 160, 160), 1)
            for position, colour, radius, thickness in marks:
                relative = (position[list(axes)] - VIEW_CENTER[list(axes)]) / (2 * VIEW_HALF_WIDTH) + 0.5
                column = int(np.clip(relative[0], 0, 1) * (PANEL - 1))
                row = int(np.clip(1.0 - relative[1], 0, 1) * (PANEL - 1))
                cv2.circle(panel, (column, row), radius, colour, thickness)
            panels.append(panel)
        return np.concatenate(panels, axis=1)

    def describe(self, key: Hashable) -> str:
        if key == SUCCESS_KEY:
            return "task solved"
        x, y, z = (100 * v for v in self.cell_center(key))
        place = f"at ({x:.1f}, {y:.1f}, {z:.1f}) cm"
        if len(key) > 3:
            return place + (", the gripper at it" if _gripper_at(key) else ", the gripper away")
        return place
