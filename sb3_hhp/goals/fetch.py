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
one. People see the rendered scene when the env renders (``render_mode="rgb_array"``), else a drawing of the
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


class FetchGoalSpace(GoalSpace):
    """Sub-goal key = the ``cell_size`` cube that holds the achieved position (gripper or object), read off
    a :class:`FetchFlatObs` observation; a sub-goal is reached within ``distance_threshold`` of it.

    :param cell_size: side of a key's cell in metres (> 0)
    :param distance_threshold: ``done(s, g)`` distance in metres (> 0); the paper's and the Fetch tasks' own 0.05
    """

    name = "fetch"

    def __init__(self, cell_size: float = 0.01, distance_threshold: float = 0.05) -> None:
        if not cell_size > 0:
            raise ValueError(f"cell_size must be > 0 metres, got {cell_size}")
        if not distance_threshold > 0:
            raise ValueError(f"distance_threshold must be > 0 metres, got {distance_threshold}")
        self.cell_size = float(cell_size)
        self.distance_threshold = float(distance_threshold)

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

    def key(self, obs: np.ndarray) -> Hashable:
        return tuple(int(v) for v in np.floor(self.achieved_position(obs) / self.cell_size))

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
        task's own goal (:data:`~sb3_hhp.goals.base.SUCCESS_KEY`) or for none (``key`` None)."""
        if key is None or key == SUCCESS_KEY:
            return self.desired_position(obs)
        return self.cell_center(key)

    @staticmethod
    def state_part(obs: np.ndarray) -> np.ndarray:
        """A flat observation without its achieved and desired positions (what a goal-conditioned learner reads
        beside the place it is sent to)."""
        return np.asarray(obs)[..., :-6]

    def cell_center(self, key: Hashable) -> np.ndarray:
        """The centre (metres) of a key's cell."""
        return (np.asarray(key, dtype=np.float64) + 0.5) * self.cell_size

    def distance(self, key: Hashable, other: Hashable) -> float:
        """Distance in metres between the centres of two keys' cells (infinite between a place and
        :data:`~sb3_hhp.goals.base.SUCCESS_KEY`, 0 between two)."""
        if key == SUCCESS_KEY or other == SUCCESS_KEY:
            return 0.0 if key == other else math.inf
        return self.cell_size * math.dist(key, other)  # centres are (key + 0.5) * cell_size: no arrays per step

    def achieved(self, key: Hashable, goal_key: Hashable) -> bool:
        """``done(s, g)``: the achieved position is within ``distance_threshold`` of the sub-goal's."""
        return self.distance(key, goal_key) <= self.distance_threshold + 1e-9

    def similarity(self, key: Hashable, obs: np.ndarray, goal_keys: Sequence[Hashable], goal_obs: np.ndarray) -> np.ndarray:
        """1 / (1 + (d / distance_threshold)^2), d the distance between the places: 1 at the same place, 0.5 at
        the threshold."""
        distances = np.array([self.distance(key, other) for other in goal_keys], dtype=np.float64)
        return 1.0 / (1.0 + (distances / self.distance_threshold) ** 2)

    def query_info(self, state: np.ndarray, goal1_obs: np.ndarray, goal2_obs: np.ndarray) -> dict[str, Any]:
        """What :class:`~sb3_hhp.oracles.fetch.FetchScriptedOracle` reads: the state's target and each
        sub-goal's achieved position (where it was found), in metres."""
        desired = self.desired_position(state)
        # the task's own goal ("task solved", found where a target was reached) is the target of this state
        places = [desired if self.solved(obs) else self.achieved_position(obs) for obs in (goal1_obs, goal2_obs)]
        return {"desired_goal": desired.tolist(), "goal1_achieved": places[0].tolist(), "goal2_achieved": places[1].tolist()}

    def image_of(self, obs: np.ndarray) -> np.ndarray:
        """Two panels, seen from above (x right, y up) and from the side (x right, z up), of the region
        around the table: the achieved position as a filled blue dot, the target as a red ring."""
        panels = []
        for axes in ((0, 1), (0, 2)):
            panel = np.full((PANEL, PANEL, 3), 235, dtype=np.uint8)
            cv2.rectangle(panel, (0, 0), (PANEL - 1, PANEL - 1), (160, 160, 160), 1)
            for position, colour, thickness in (
                (self.desired_position(obs), (220, 40, 40), 1),
                (self.achieved_position(obs), (40, 80, 220), -1),
            ):
                relative = (position[list(axes)] - VIEW_CENTER[list(axes)]) / (2 * VIEW_HALF_WIDTH) + 0.5
                column = int(np.clip(relative[0], 0, 1) * (PANEL - 1))
                row = int(np.clip(1.0 - relative[1], 0, 1) * (PANEL - 1))
                cv2.circle(panel, (column, row), 4, colour, thickness)
            panels.append(panel)
        return np.concatenate(panels, axis=1)

    def describe(self, key: Hashable) -> str:
        if key == SUCCESS_KEY:
            return "task solved"
        x, y, z = (100 * v for v in self.cell_center(key))
        return f"at ({x:.1f}, {y:.1f}, {z:.1f}) cm"
