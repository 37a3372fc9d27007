"""Scripted MiniGrid oracle: privileged preferences computed from the grid along an optimal plan.

For any MiniGrid task with keys, doors and goals (DoorKey of any size, Unlock, KeyCorridor, MultiRoom,
...) the oracle searches a shortest action sequence from the query's state to success (stepping on
the goal square, or picking up the mission's object), breadth first over MiniGrid's own rules
(turn, forward, pick up, drop, toggle with a key of the door's colour). Along that optimal plan it
lists the sub-goal keys the agent passes. A sub-goal is better the sooner it comes *as a milestone*
of the plan (facing a key, a door, a ball, a box or the goal, a change of what is carried, the task
solved): the next step a person would name. Sub-goals that are on the plan only in passing ("facing
an empty cell") rank after every milestone; sub-goals off the plan rank last; two sub-goals of the
same rank are EQUAL, and a state with no plan at all gets INCOMPARABLE.
"""

from collections import deque
from collections.abc import Hashable
from typing import Any, Optional

import numpy as np
from minigrid.core.constants import DIR_TO_VEC, OBJECT_TO_IDX, STATE_TO_IDX

from sb3_hhp.goals.base import SUCCESS_KEY
from sb3_hhp.goals.minigrid import EMPTY, MiniGridGoalSpace
from sb3_hhp.oracles.base import Label, Oracle, Query

_WALKABLE = {OBJECT_TO_IDX[name] for name in ("empty", "floor", "goal")}
_PICKABLE = {OBJECT_TO_IDX[name] for name in ("key", "ball", "box")}
_DOOR, _KEY, _GOAL = OBJECT_TO_IDX["door"], OBJECT_TO_IDX["key"], OBJECT_TO_IDX["goal"]
_OPEN, _CLOSED, _LOCKED = STATE_TO_IDX["open"], STATE_TO_IDX["closed"], STATE_TO_IDX["locked"]
_NO_OBJECT = (EMPTY, 0, 0)


def plan_keys(
    info: dict[str, Any], goal_space: Optional[MiniGridGoalSpace] = None, max_nodes: int = 300_000
) -> Optional[list[Hashable]]:
    """Sub-goal keys after each action of a shortest plan from the state described by ``info``
    (as written by :meth:`MiniGridGoalSpace.privileged`) to success; the last key is ``SUCCESS_KEY``.

    :return: the keys, ``[]`` when the state is already a success, ``None`` when no plan exists within ``max_nodes``
    """
    goal_space = goal_space or MiniGridGoalSpace()
    grid0 = np.asarray(info["grid"], dtype=np.uint8)
    width, height = grid0.shape[:2]
    carrying0 = tuple(info["carrying"]) if info.get("carrying") is not None else _NO_OBJECT
    target = tuple(info["target"]) if info.get("target") is not None else None

    def key_of(x: int, y: int, d: int, carried: tuple, grid: np.ndarray) -> Hashable:
        dx, dy = DIR_TO_VEC[d]
        fx, fy = x + dx, y + dy
        front = grid[fx, fy] if 0 <= fx < width and 0 <= fy < height else np.zeros(3, np.uint8)
        if goal_space.use_color:
            return (int(carried[0]), int(carried[1]), int(front[0]), int(front[1]), int(front[2]))
        return (int(carried[0]), int(front[0]), int(front[2]))

    start = (int(info["agent_pos"][0]), int(info["agent_pos"][1]), int(info["agent_dir"]), carrying0, grid0.tobytes())
    parents: dict[tuple, Optional[tuple]] = {start: None}
    queue = deque([start])
    goal_state = None
    while queue and len(parents) < max_nodes:
        state = queue.popleft()
        x, y, d, carried, grid_bytes = state
        grid = np.frombuffer(grid_bytes, dtype=np.uint8).reshape(grid0.shape)
        dx, dy = DIR_TO_VEC[d]
        fx, fy = x + dx, y + dy
        front = tuple(int(v) for v in grid[fx, fy]) if 0 <= fx < width and 0 <= fy < height else (0, 0, 0)
        successors = [(x, y, (d - 1) % 4, carried, grid_bytes, False), (x, y, (d + 1) % 4, carried, grid_bytes, False)]
        if front[0] in _WALKABLE or (front[0] == _DOOR and front[2] == _OPEN):
            successors.append((fx, fy, d, carried, grid_bytes, front[0] == _GOAL and target is None))
        if carried == _NO_OBJECT and front[0] in _PICKABLE:
            new_grid = grid.copy()
            new_grid[fx, fy] = _NO_OBJECT
            done = target is not None and front[:2] == target
            successors.append((x, y, d, front, new_grid.tobytes(), done))
        if carried != _NO_OBJECT and front[0] == EMPTY:
            new_grid = grid.copy()
            new_grid[fx, fy] = carried
            successors.append((x, y, d, _NO_OBJECT, new_grid.tobytes(), False))
        if front[0] == _DOOR and (front[2] == _CLOSED or (front[2] == _LOCKED and carried[:2] == (_KEY, front[1]))):
            new_grid = grid.copy()
            new_grid[fx, fy] = (_DOOR, front[1], _OPEN)
            successors.append((x, y, d, carried, new_grid.tobytes(), False))
        for *child, done in successors:
            child = tuple(child)
            if child in parents:
                continue
            parents[child] = state
            if done:
                goal_state = child
                queue.clear()
                break
            queue.append(child)
    if goal_state is None:
        return None
    path = []
    node: Optional[tuple] = goal_state
    while node is not None:
        path.append(node)
        node = parents[node]
    path.reverse()
    keys: list[Hashable] = []
    for x, y, d, carried, grid_bytes in path[1:-1]:
        keys.append(key_of(x, y, d, carried, np.frombuffer(grid_bytes, dtype=np.uint8).reshape(grid0.shape)))
    keys.append(SUCCESS_KEY)
    return keys


def _as_key(value: Any) -> Hashable:
    return tuple(value) if isinstance(value, (list, tuple, np.ndarray)) else value


class MiniGridScriptedOracle(Oracle):
    """Privileged MiniGrid oracle (the "expert"): prefers the sub-goal that comes first as a milestone
    of an optimal plan from the query's state (see the module docstring).

    Each query's ``info`` must hold ``state`` (the privileged facts of the state, from
    :meth:`MiniGridGoalSpace.privileged`) and ``goal1_key`` / ``goal2_key``.

    :param use_color: must match the goal space's ``use_color``
    :param name: the annotator name recorded with its answers
    """

    def __init__(self, use_color: bool = False, name: str = "scripted") -> None:
        super().__init__(name)
        self.goal_space = MiniGridGoalSpace(use_color=use_color)

    def rank(self, keys: Optional[list[Hashable]], goal_key: Hashable, carried_before: int) -> float:
        """Position of ``goal_key`` on the plan: milestones first, keys seen only in passing next, off-plan last."""
        if not keys:
            return np.inf
        for step, key in enumerate(keys):
            if key == goal_key:
                milestone = self.goal_space.is_milestone(key, carried_before)
                return float(step) if milestone else float(len(keys) + step)
        return np.inf

    def answer(self, query: Query) -> Label:
        missing = [name for name in ("state", "goal1_key", "goal2_key") if name not in query.info]
        if missing:
            raise ValueError(f"The scripted MiniGrid oracle needs {missing} in Query.info (use a MiniGrid goal space)")
        state = query.info["state"]
        keys = plan_keys(state, self.goal_space)
        if keys is None:
            return Label.INCOMPARABLE
        carried = state["carrying"][0] if state.get("carrying") is not None else EMPTY
        rank1 = self.rank(keys, _as_key(query.info["goal1_key"]), carried)
        rank2 = self.rank(keys, _as_key(query.info["goal2_key"]), carried)
        if rank1 == rank2:
            return Label.EQUAL
        return Label.FIRST if rank1 < rank2 else Label.SECOND
