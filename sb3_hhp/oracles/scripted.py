"""Scripted MiniGrid oracle: privileged preferences computed from the grid along an optimal plan.

For any MiniGrid task with keys, doors, boxes and goals (DoorKey of any size, Unlock, KeyCorridor, MultiRoom,
ObstructedMaze, ...) the oracle searches a shortest action sequence from the query's state to success
(stepping on the goal square, or picking up the mission's object), by A* over MiniGrid's own rules (turn,
forward, pick up, drop, toggle a door, with a key of its colour when locked, or a box, which leaves what it
holds), bounded in time per question (a plan at most a few times as long is taken when the shortest is not found
in a quarter of that time). Along that plan it lists the sub-goal keys the agent passes. A sub-goal is better the
sooner it comes *as a milestone* of the plan: facing a key, a door, a ball, a box or the goal, or a change of what is
carried, where the plan acts (picks up, drops, opens or ends the task just before or just after), or the task
solved: the next step a person would name. Facing an object the plan only walks past (the locked door on the way to
its key) is no milestone there. Sub-goals that are on the plan only in passing ("facing an empty cell") rank after
every milestone; sub-goals off the plan rank last; two sub-goals of the same rank are EQUAL, and a state with no
plan at all gets INCOMPARABLE.
"""

import heapq
import time
from collections.abc import Hashable
from typing import Any, Optional, Union

import numpy as np
from minigrid.core.constants import DIR_TO_VEC, OBJECT_TO_IDX, STATE_TO_IDX

from sb3_hhp.goals.base import SUCCESS_KEY
from sb3_hhp.goals.minigrid import BOX as _BOX, EMPTY, PICKABLE as _PICKABLE, MiniGridGoalSpace, blockers, mark_target
from sb3_hhp.oracles.base import Label, Oracle, Query

_WALKABLE = {OBJECT_TO_IDX[name] for name in ("empty", "floor", "goal")}
_DOOR, _KEY, _GOAL = OBJECT_TO_IDX["door"], OBJECT_TO_IDX["key"], OBJECT_TO_IDX["goal"]
_OPEN, _CLOSED, _LOCKED = STATE_TO_IDX["open"], STATE_TO_IDX["closed"], STATE_TO_IDX["locked"]
_NO_OBJECT = (EMPTY, 0, 0)


def plan_keys(
    info: dict[str, Any], goal_space: Optional[MiniGridGoalSpace] = None, max_nodes: int = 300_000,
    max_seconds: Optional[float] = None, weight: float = 1.0, move_boxes: bool = False,
) -> Optional[list[Hashable]]:
    """Sub-goal keys after each action of a shortest plan from the state described by ``info``
    (as written by :meth:`~sb3_hhp.goals.base.GoalSpace.privileged`) to success; the last key is ``SUCCESS_KEY``.
    :func:`plan_steps` with the keys alone (same arguments)."""
    steps = plan_steps(info, goal_space, max_nodes=max_nodes, max_seconds=max_seconds, weight=weight,
                       move_boxes=move_boxes)
    return None if steps is None else [key for key, _ in steps]


def plan_steps(
    info: dict[str, Any], goal_space: Optional[MiniGridGoalSpace] = None, max_nodes: int = 300_000,
    max_seconds: Optional[float] = None, weight: float = 1.0, move_boxes: bool = False,
) -> Optional[list[tuple[Hashable, bool]]]:
    """The sub-goal key after each action of a shortest plan from the state described by ``info``
    (as written by :meth:`~sb3_hhp.goals.base.GoalSpace.privileged`) to success, each with whether the plan *acts* there: the
    action that led to it or the next one picks up, drops, opens a door or a box, or ends the task, rather than
    turns or walks on. The last key is ``SUCCESS_KEY``.

    The search follows MiniGrid's rules: turn, forward onto empty, floor, goal or open-door cells, pick up a
    key, ball or box, drop onto an empty cell, open a closed door, unlock a locked door with a key of its colour,
    and open a box, which leaves what it holds in its place (``info["boxes"]``: the contents of each box where
    it lies, ``info["carrying_holds"]``: those of the carried box; a box keeps them when carried). A search state
    is the agent's cell, direction and load and the cells changed from the start, so a move copies nothing.

    :param max_nodes: most search states visited
    :param max_seconds: most seconds spent searching (None: no limit)
    :param move_boxes: also search plans that carry a box that is not the task's object somewhere else (a box is
        opened where it lies otherwise: moving one pays only where it blocks the way, and multiplies the states to
        search by the cells it could be left on)
    :param weight: the heuristic's weight (weighted A*): 1 finds a shortest plan; w > 1 finds one at most w times as
        long as the shortest, usually far sooner
    :return: ``(key, acts)`` pairs, ``[]`` when the state is already a success, ``None`` when no plan was found
        within the limits
    """
    if not weight >= 1.0:
        raise ValueError(f"weight must be >= 1, got {weight}")
    goal_space = goal_space or MiniGridGoalSpace()
    target = tuple(info["target"]) if info.get("target") is not None else None
    grid0 = np.asarray(info["grid"], dtype=np.uint8)
    if goal_space.mark_target:  # the keys name the mission's object as the observation marks it
        grid0 = mark_target(grid0.copy(), target)
    width, height = grid0.shape[:2]
    cells = [[tuple(int(v) for v in grid0[x, y]) for y in range(height)] for x in range(width)]
    # a box's code carries what it holds after its own three numbers, so that its contents travel with it
    for x, y, held in info.get("boxes", []):
        cells[int(x)][int(y)] += _held(held)
    carrying0 = tuple(int(v) for v in info["carrying"]) if info.get("carrying") is not None else _NO_OBJECT
    if carrying0[0] == _BOX:
        carrying0 += _held(info.get("carrying_holds"))
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

    objects0 = grid0[..., 0].copy()
    opened0 = sum(code[0] == _DOOR and code[2] == _OPEN for column in cells for code in column)

    def key_of(x: int, y: int, d: int, carried: tuple, changes: tuple) -> Hashable:
        dx, dy = DIR_TO_VEC[d]
        fx, fy = x + dx, y + dy
        # the search opens doors and never closes one: those changed to open are the doors opened since the start
        return goal_space.key_of(carried, cell(fx, fy, changes), lambda: opened0 + sum(
            code[0] == _DOOR and code[2] == _OPEN for _, _, code in changes), lambda: blocks(x, y, fx, fy, changes))

    def blocks(x: int, y: int, fx: int, fy: int, changes: tuple) -> bool:
        """Whether the object on (fx, fy) blocks the way of the agent on (x, y) in the grid as changed."""
        if not (0 <= fx < width and 0 <= fy < height):
            return False
        objects = objects0.copy()
        for cx, cy, code in changes:
            objects[cx, cy] = code[0]
        return bool(blockers(objects[None], [(x, y)])[0, fx, fy])

    # A*: the heuristic counts the forward moves from the agent's cell to the nearest cell that ends the task,
    # through every cell the agent could ever stand on (anything but walls and lava: doors may open, objects may be
    # moved), plus a turn when the cell in front is not one move nearer, plus a drop when the task is to pick up an
    # object and the hands are full. Each is owed by any plan, so it never overestimates what is left and the first
    # plan found is a shortest one; unlike the straight-line distance it knows that rooms are entered by their doors.
    ends = [(cx, cy) for cx in range(width) for cy in range(height)
            if (cells[cx][cy][0] == _GOAL and target is None) or (target is not None and cells[cx][cy][:2] == target)]
    distance = _distances(cells, ends)

    def remaining(state: tuple) -> int:
        x, y, d, carried, _ = state
        left = distance[x][y]
        if left > 0:
            fx, fy = x + int(DIR_TO_VEC[d][0]), y + int(DIR_TO_VEC[d][1])
            ahead = distance[fx][fy] if 0 <= fx < width and 0 <= fy < height else left
            left += ahead != left - 1
        return left + (target is not None and carried != _NO_OBJECT)

    start = (int(info["agent_pos"][0]), int(info["agent_pos"][1]), int(info["agent_dir"]), carrying0, ())
    reached: dict[tuple, tuple[int, Optional[tuple]]] = {start: (0, None)}  # state -> (steps, the state before)
    queue = [(weight * remaining(start), 0, 0, start)]  # (steps + weight * remaining, -steps, order, state)
    order = popped = 0
    goal_state = None
    while queue and len(reached) < max_nodes:
        popped += 1
        if deadline is not None and popped % 256 == 0 and time.perf_counter() > deadline:
            break
        _, negative_steps, _, state = heapq.heappop(queue)
        if -negative_steps > reached[state][0]:
            continue  # reached again by a shorter way since this entry was queued
        x, y, d, carried, changes = state
        steps = 1 - negative_steps
        dx, dy = DIR_TO_VEC[d]
        fx, fy = x + dx, y + dy
        front = cell(fx, fy, changes)
        kind = front[0]
        done = target is not None and front[:2] == target
        successors = [((x, y, (d - 1) % 4, carried, changes), False), ((x, y, (d + 1) % 4, carried, changes), False)]
        if kind in _WALKABLE or (kind == _DOOR and front[2] == _OPEN):
            successors.append(((fx, fy, d, carried, changes), kind == _GOAL and target is None))
        # a box is opened where it lies, and carried only when it is what the task asks for (or with move_boxes)
        if carried == _NO_OBJECT and kind in _PICKABLE and (kind != _BOX or done or move_boxes):
            successors.append(((x, y, d, front, changed(changes, fx, fy, _NO_OBJECT)), done))
        if carried != _NO_OBJECT and kind == EMPTY:
            successors.append(((x, y, d, _NO_OBJECT, changed(changes, fx, fy, carried)), False))
        if kind == _DOOR and (front[2] == _CLOSED or (front[2] == _LOCKED and carried[:2] == (_KEY, front[1]))):
            successors.append(((x, y, d, carried, changed(changes, fx, fy, (_DOOR, front[1], _OPEN))), False))
        if kind == _BOX:  # opened, it leaves what it holds in its place
            successors.append(((x, y, d, carried, changed(changes, fx, fy, front[3:] or _NO_OBJECT)), False))
        for child, done in successors:
            if done:
                reached[child] = (steps, state)
                goal_state = child
                break
            known = reached.get(child)
            if known is not None and known[0] <= steps:
                continue
            reached[child] = (steps, state)
            order += 1
            heapq.heappush(queue, (steps + weight * remaining(child), -steps, order, child))
        if goal_state is not None:
            break
    if goal_state is None:
        return None
    path = []
    node: Optional[tuple] = goal_state
    while node is not None:
        path.append(node)
        node = reached[node][1]
    path.reverse()
    # an action acts when it changes the load or the grid, or ends the task (the last one); a key is acted at when
    # the action that led to it or the next one acts
    acted = [before[3:] != after[3:] for before, after in zip(path[:-2], path[1:-1])] + [True]
    steps: list[tuple[Hashable, bool]] = [(key_of(*node), acted[i] or acted[i + 1])
                                          for i, node in enumerate(path[1:-1])]
    steps.append((SUCCESS_KEY, False))
    return steps


def _held(held: Optional[Any]) -> tuple:
    """The code a box's code is extended by: what it holds (nothing: the empty cell's code)."""
    return tuple(int(v) for v in held) if held is not None else _NO_OBJECT


def _distances(cells: list[list[tuple]], ends: list[tuple[int, int]]) -> list[list[int]]:
    """Forward moves from every cell to the nearest of ``ends`` over the cells that are not walls or lava
    (breadth-first from the ends); 0 where no end can be reached (the search then finds no plan by itself)."""
    width, height = len(cells), len(cells[0])
    blocked = {OBJECT_TO_IDX["wall"], OBJECT_TO_IDX["lava"]}
    distance = [[-1] * height for _ in range(width)]
    frontier = list(ends)
    for x, y in frontier:
        distance[x][y] = 0
    while frontier:
        reached = []
        for x, y in frontier:
            for dx, dy in DIR_TO_VEC:
                nx, ny = x + int(dx), y + int(dy)
                if 0 <= nx < width and 0 <= ny < height and distance[nx][ny] < 0 and cells[nx][ny][0] not in blocked:
                    distance[nx][ny] = distance[x][y] + 1
                    reached.append((nx, ny))
        frontier = reached
    return [[max(value, 0) for value in column] for column in distance]


def _as_key(value: Any) -> Hashable:
    return tuple(value) if isinstance(value, (list, tuple, np.ndarray)) else value


class MiniGridScriptedOracle(Oracle):
    """Privileged MiniGrid oracle (the "expert"): prefers the sub-goal that comes first as a milestone
    of an optimal plan from the query's state (see the module docstring).

    Each query's ``info`` must hold ``state`` (the privileged facts of the state, from
    :meth:`~sb3_hhp.goals.base.GoalSpace.privileged`) and ``goal1_key`` / ``goal2_key``.

    :param use_color: must match the goal space's (its :attr:`~sb3_hhp.goals.minigrid.MiniGridGoalSpace.color_option`)
    :param count_open_doors: must match the goal space's ``count_open_doors``
    :param mark_blockers: must match the goal space's ``mark_blockers``
    :param color_relation: must match the goal space's ``color_relation``
    :param mark_target: must match the goal space's ``mark_target``
    :param name: the annotator name recorded with its answers
    :param max_seconds: most seconds the plan of one question may take (answers run on the training thread): the
        first quarter searches a shortest plan; when none is found by then, the rest searches one at most
        ``fallback_weight`` times as long (weighted A*); a question with no plan found within it is answered
        INCOMPARABLE
    :param fallback_weight: the heuristic's weight of the second search (>= 1)
    """

    def __init__(self, use_color: Union[bool, str] = False, name: str = "scripted", max_seconds: float = 2.0,
                 fallback_weight: float = 3.0, count_open_doors: bool = False, mark_blockers: bool = False,
                 color_relation: str = "opens", mark_target: bool = False) -> None:
        super().__init__(name)
        if not max_seconds > 0:
            raise ValueError(f"max_seconds must be > 0, got {max_seconds}")
        if not fallback_weight >= 1:
            raise ValueError(f"fallback_weight must be >= 1, got {fallback_weight}")
        self.goal_space = MiniGridGoalSpace(use_color=use_color, count_open_doors=count_open_doors,
                                            mark_blockers=mark_blockers, color_relation=color_relation,
                                            mark_target=mark_target)
        self.max_seconds = float(max_seconds)
        self.fallback_weight = float(fallback_weight)
        self.last_plan_weight: Optional[float] = None  # which search found the last plan (1: a shortest one)

    def plan(self, state: dict[str, Any]) -> Optional[list[tuple[Hashable, bool]]]:
        """The sub-goal keys along a plan from ``state``, each with whether the plan acts there (:func:`plan_steps`),
        within ``max_seconds``: a shortest one, else one at most ``fallback_weight`` times as long, else None."""
        self.last_plan_weight = None
        searches = ((1.0, 0.25), (self.fallback_weight, 0.75)) if self.fallback_weight > 1 else ((1.0, 1.0),)
        for weight, share in searches:
            steps = plan_steps(state, self.goal_space, max_seconds=share * self.max_seconds, weight=weight)
            if steps is not None:
                self.last_plan_weight = weight
                return steps
        return None

    def milestone(self, key: Hashable, acts: bool, carried_before: int) -> bool:
        """Whether ``key``, met on a plan that ``acts`` there or not (:func:`plan_steps`), is a step a person would
        name: the task solved, or a change of what is carried or facing an object, where the plan acts (the door just
        opened, the key about to be picked up; not the locked door passed on the way to its key)."""
        return key == SUCCESS_KEY or (acts and self.goal_space.is_milestone(key, carried_before))

    def rank(self, steps: Optional[list[tuple[Hashable, bool]]], goal_key: Hashable, carried_before: int) -> float:
        """Position of ``goal_key`` on the plan ``steps`` (:meth:`plan`): milestones first, keys seen only in passing
        next, off-plan last."""
        if not steps:
            return np.inf
        passing = None
        for step, (key, acts) in enumerate(steps):
            if key == goal_key:
                if self.milestone(key, acts, carried_before):
                    return float(step)
                if passing is None:
                    passing = step
        return np.inf if passing is None else float(len(steps) + passing)

    def answer(self, query: Query) -> Label:
        missing = [name for name in ("state", "goal1_key", "goal2_key") if name not in query.info]
        if missing:
            raise ValueError(f"The scripted MiniGrid oracle needs {missing} in Query.info (use a MiniGrid goal space)")
        state = query.info["state"]
        steps = self.plan(state)
        if steps is None:
            return Label.INCOMPARABLE
        carried = state["carrying"][0] if state.get("carrying") is not None else EMPTY
        rank1 = self.rank(steps, _as_key(query.info["goal1_key"]), carried)
        rank2 = self.rank(steps, _as_key(query.info["goal2_key"]), carried)
        if rank1 == rank2:
            return Label.EQUAL
        return Label.FIRST if rank1 < rank2 else Label.SECOND
