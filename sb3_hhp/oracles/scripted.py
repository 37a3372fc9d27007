"""Scripted MiniGrid oracle: privileged preferences computed from the grid along an optimal plan.

For any MiniGrid task with keys, doors, boxes and goals (DoorKey of any size, Unlock, KeyCorridor, MultiRoom,
ObstructedMaze, ...) the oracle searches a shortest action sequence from the query's state to success
(stepping on the goal square, or picking up the mission's object), by A* over MiniGrid's own rules (turn,
forward, pick up, drop, toggle a door, with a key of its colour when locked, or a box, which leaves what it
holds), bounded in time per question. Along that optimal plan it
lists the sub-goal keys the agent passes. A sub-goal is better the sooner it comes *as a milestone*
of the plan (facing a key, a door, a ball, a box or the goal, a change of what is carried, the task
solved): the next step a person would name. Sub-goals that are on the plan only in passing ("facing
an empty cell") rank after every milestone; sub-goals off the plan rank last; two sub-goals of the
same rank are EQUAL, and a state with no plan at all gets INCOMPARABLE.
"""

import heapq
import time
from collections.abc import Hashable
from typing import Any, Optional

import numpy as np
from minigrid.core.constants import DIR_TO_VEC, OBJECT_TO_IDX, STATE_TO_IDX

from sb3_hhp.goals.base import SUCCESS_KEY
from sb3_hhp.goals.minigrid import EMPTY, MiniGridGoalSpace
from sb3_hhp.oracles.base import Label, Oracle, Query

_WALKABLE = {OBJECT_TO_IDX[name] for name in ("empty", "floor", "goal")}
_PICKABLE = {OBJECT_TO_IDX[name] for name in ("key", "ball", "box")}
_DOOR, _KEY, _GOAL, _BOX = OBJECT_TO_IDX["door"], OBJECT_TO_IDX["key"], OBJECT_TO_IDX["goal"], OBJECT_TO_IDX["box"]
_OPEN, _CLOSED, _LOCKED = STATE_TO_IDX["open"], STATE_TO_IDX["closed"], STATE_TO_IDX["locked"]
_NO_OBJECT = (EMPTY, 0, 0)


def plan_keys(
    info: dict[str, Any], goal_space: Optional[MiniGridGoalSpace] = None, max_nodes: int = 300_000,
    max_seconds: Optional[float] = None,
) -> Optional[list[Hashable]]:
    """Sub-goal keys after each action of a shortest plan from the state described by ``info``
    (as written by :meth:`MiniGridGoalSpace.privileged`) to success; the last key is ``SUCCESS_KEY``.

    The search follows MiniGrid's rules: turn, forward onto empty, floor, goal or open-door cells, pick up a
    key, ball or box, drop onto an empty cell, open a closed door, unlock a locked door with a key of its colour,
    and open a box, which leaves what it holds in its place (``info["boxes"]``: the contents of each box where
    it lies; a box that was moved opens empty). A search state is the agent's cell, direction and load and the
    cells changed from the start, so a move copies nothing.

    :param max_nodes: most search states visited
    :param max_seconds: most seconds spent searching (None: no limit)
    :return: the keys, ``[]`` when the state is already a success, ``None`` when no plan was found within the limits
    """
    goal_space = goal_space or MiniGridGoalSpace()
    grid0 = np.asarray(info["grid"], dtype=np.uint8)
    width, height = grid0.shape[:2]
    cells = [[tuple(int(v) for v in grid0[x, y]) for y in range(height)] for x in range(width)]
    carrying0 = tuple(info["carrying"]) if info.get("carrying") is not None else _NO_OBJECT
    target = tuple(info["target"]) if info.get("target") is not None else None
    contents = {(int(x), int(y)): (tuple(int(v) for v in held) if held is not None else _NO_OBJECT)
                for x, y, held in info.get("boxes", [])}
    deadline = None if max_seconds is None else time.perf_counter() + max_seconds

    def cell(x: int, y: int, changes: tuple) -> tuple:
        for cx, cy, code in changes:
            if cx == x and cy == y:
                return code
        if 0 <= x < width and 0 <= y < height:
            return cells[x][y]
        return (0, 0, 0)

    def changed(changes: tuple, x: int, y: int, code: tuple) -> tuple:
        kept = tuple(change for change in changes if change[0] != x or change[1] != y)
        return tuple(sorted(kept + (((x, y, code),) if code != cells[x][y] else ())))

    def key_of(x: int, y: int, d: int, carried: tuple, changes: tuple) -> Hashable:
        dx, dy = DIR_TO_VEC[d]
        front = cell(x + dx, y + dy, changes)
        if goal_space.use_color:
            return (int(carried[0]), int(carried[1]), int(front[0]), int(front[1]), int(front[2]))
        return (int(carried[0]), int(front[0]), int(front[2]))

    # A*: a forward move changes the distance to the nearest cell that ends the task by at most one, so that
    # distance never overestimates what is left and the first plan found is a shortest one
    ends = [(cx, cy) for cx in range(width) for cy in range(height)
            if (cells[cx][cy][0] == _GOAL and target is None) or (target is not None and cells[cx][cy][:2] == target)]

    def remaining(x: int, y: int) -> int:
        return min((abs(x - cx) + abs(y - cy) for cx, cy in ends), default=0)

    start = (int(info["agent_pos"][0]), int(info["agent_pos"][1]), int(info["agent_dir"]), carrying0, ())
    parents: dict[tuple, Optional[tuple]] = {start: None}
    depth = {start: 0}
    queue = [(remaining(start[0], start[1]), 0, 0, start)]  # (steps + remaining, -steps, order, state)
    order = popped = 0
    goal_state = None
    while queue and len(parents) < max_nodes:
        popped += 1
        if deadline is not None and popped % 256 == 0 and time.perf_counter() > deadline:
            break
        _, negative_steps, _, state = heapq.heappop(queue)
        if -negative_steps > depth[state]:
            continue  # reached again by a shorter way since this entry was queued
        x, y, d, carried, changes = state
        steps = depth[state] + 1
        dx, dy = DIR_TO_VEC[d]
        fx, fy = x + dx, y + dy
        front = cell(fx, fy, changes)
        successors = [(x, y, (d - 1) % 4, carried, changes, False), (x, y, (d + 1) % 4, carried, changes, False)]
        if front[0] in _WALKABLE or (front[0] == _DOOR and front[2] == _OPEN):
            successors.append((fx, fy, d, carried, changes, front[0] == _GOAL and target is None))
        if carried == _NO_OBJECT and front[0] in _PICKABLE:
            done = target is not None and front[:2] == target
            successors.append((x, y, d, front, changed(changes, fx, fy, _NO_OBJECT), done))
        if carried != _NO_OBJECT and front[0] == EMPTY:
            successors.append((x, y, d, _NO_OBJECT, changed(changes, fx, fy, carried), False))
        if front[0] == _DOOR and (front[2] == _CLOSED or (front[2] == _LOCKED and carried[:2] == (_KEY, front[1]))):
            successors.append((x, y, d, carried, changed(changes, fx, fy, (_DOOR, front[1], _OPEN)), False))
        if front[0] == _BOX:  # opened where it lay at the start: what it held; moved: nothing
            held = contents.get((fx, fy), _NO_OBJECT) if front == cells[fx][fy] else _NO_OBJECT
            successors.append((x, y, d, carried, changed(changes, fx, fy, held), False))
        for *child, done in successors:
            child = tuple(child)
            if done:
                parents[child] = state
                goal_state = child
                break
            if child in parents and depth[child] <= steps:
                continue
            parents[child], depth[child] = state, steps
            order += 1
            heapq.heappush(queue, (steps + remaining(child[0], child[1]), -steps, order, child))
        if goal_state is not None:
            break
    if goal_state is None:
        return None
    path = []
    node: Optional[tuple] = goal_state
    while node is not None:
        path.append(node)
        node = parents[node]
    path.reverse()
    keys: list[Hashable] = [key_of(*node) for node in path[1:-1]]
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
    :param max_seconds: most seconds the plan of one question may take (answers run on the training thread); a
        question with no plan found within it is answered INCOMPARABLE
    """

    def __init__(self, use_color: bool = False, name: str = "scripted", max_seconds: float = 1.0) -> None:
        super().__init__(name)
        if not max_seconds > 0:
            raise ValueError(f"max_seconds must be > 0, got {max_seconds}")
        self.goal_space = MiniGridGoalSpace(use_color=use_color)
        self.max_seconds = float(max_seconds)

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
        keys = plan_keys(state, self.goal_space, max_seconds=self.max_seconds)
        if keys is None:
            return Label.INCOMPARABLE
        carried = state["carrying"][0] if state.get("carrying") is not None else EMPTY
        rank1 = self.rank(keys, _as_key(query.info["goal1_key"]), carried)
        rank2 = self.rank(keys, _as_key(query.info["goal2_key"]), carried)
        if rank1 == rank2:
            return Label.EQUAL
        return Label.FIRST if rank1 < rank2 else Label.SECOND
