"""A scripted (privileged) oracle for the first room of ALE Montezuma's Revenge, answering from the console's RAM.

A person who knows the first room prefers, of two sub-goals: one where the agent is in another room to one where
it is not; one where a door of the first room is open; one where the agent holds the key; without the key, the one
further along the way to it (down the middle ladder, over the rope, down the right ladder, across the floor past the
skull, up the left ladder, to the key); with it, the one further along the way back to a door. A sub-goal whose state
shows the agent dying is worse than any other.

The facts are those :class:`~sb3_hhp.goals.image.ImageGoalSpace` records on Montezuma's Revenge
(:data:`~sb3_hhp.goals.image.MONTEZUMA_RAM`). Verified with ale-py 0.12.1 on ``ALE/MontezumaRevenge-v5`` (frame skip
4, ``repeat_action_probability=0``, seed 0) by stepping scripted actions and reading ``env.unwrapped.ale.getRAM()``:

- at the reset: ``ram[3] = 1`` (the first room), ``(ram[42], ram[43]) = (77, 235)``, the agent on the top of the
  middle ladder, ``ram[65] = 0``, ``ram[58] = 5`` while ``info["lives"]`` is 6 (the RAM counts the spare lives),
  ``ram[66] = 15``, ``ram[67] = 31``;
- ``DOWN``: y falls 4 a step on the ladder, 235 to 192 at its foot (y grows upwards; the floor is y = 148); x is the
  screen column (the rope at 109, the right ladder at 133, the left one at 21);
- a scripted route down the middle ladder, over the rope, down the right ladder, across the floor (jumping the skull)
  and up the left ladder, then a jump at (9, 192): reward 100, ``ram[65]`` 0 -> 2 (the key, bit 0x02), ``ram[66]``
  15 -> 14 and ``ram[67]`` 31 -> 30 (bit 0x01: the key has left the room);
- the same route back with the key, up the middle ladder and right along the top floor: reward 300 at x = 130,
  ``ram[65]`` 2 -> 0 (the key used), ``ram[66]`` 14 -> 10 and ``ram[67]`` 30 -> 26 (bit 0x04: the right door); walking
  on, ``ram[3]`` 1 -> 2 at the screen's edge, where ``ram[66]`` becomes 3 while ``ram[67]`` stays 26: ``ram[66]`` holds
  the objects of the room the agent is in, ``ram[67]`` those of the first room;
- the left door, the key given by ``ale.setRAM(65, 2)`` at the reset: reward 300 at x = 24, ``ram[67]`` 31 -> 23 (bit
  0x08), then ``ram[3]`` 1 -> 0;
- touching the skull, or falling off the conveyor: ``ram[58]`` drops by one on the step the agent dies while
  ``ram[55]`` jumps from 0 to 12 and counts down one a step to 0, when the agent reappears at the start; the skull's
  touch also clears bit 0x02 of ``ram[66]`` and ``ram[67]`` (the skull is gone). Over 20,000 random steps (180 lives
  lost) ``ram[55]`` was above 0 only in the 12 steps after a life was lost, or on the last life (``ram[58] = 0``),
  whose death ends the game.

Lives are recorded but not compared: under SB3's ``AtariWrapper`` each life is an episode, so a sub-goal found on a
later life has fewer lives without having cost one; the death animation (``ram[55] > 0``) is what marks a sub-goal
where a life was lost.
"""

import math
from collections.abc import Sequence
from typing import Any, Optional

from sb3_hhp.goals.image import MONTEZUMA
from sb3_hhp.oracles.base import Label, Oracle, Query

#: the facts of each sub-goal the oracle reads (of :func:`~sb3_hhp.goals.image.montezuma_facts`)
REQUIRED_FACTS = ("room", "x", "y", "inventory", "first_room_objects", "death_timer")
#: the question's ``info`` entries that hold them: the facts of the state where each sub-goal was found
REQUIRED_KEYS = ("goal1_state", "goal2_state")
FIRST_ROOM = 1
#: ``inventory`` bit of the key picked up in the first room
KEY_BIT = 0x02
#: ``first_room_objects`` bits of the right and the left door, cleared once opened
DOOR_BITS = 0x04 | 0x08
#: the way from the start to the key in RAM coordinates (x, y): the middle ladder's top and foot, the conveyor's right
#: end, the rope, the right platform, the right ladder's foot, the floor to the left ladder's foot, its top, under the key
ROUTE_TO_KEY = ((77, 235), (77, 192), (92, 192), (109, 203), (130, 192), (133, 192), (133, 148), (21, 148), (21, 192),
                (9, 192))
#: from the middle ladder's top to the left door and to the right door
TO_DOORS = (((77, 235), (24, 235)), ((77, 235), (130, 235)))
#: the way back from the key to either door
ROUTE_TO_DOORS = tuple(ROUTE_TO_KEY[::-1] + branch[1:] for branch in TO_DOORS)
#: a state further than this (RAM units) from every segment of a way is off it: no further along than its start
MAX_OFF_ROUTE = 20.0
#: the stages, worst first: a life lost, no key, the key held, a door opened, another room
LOST, NO_KEY, KEY_HELD, DOOR_OPENED, NEW_ROOM = range(5)


def along(x: float, y: float, paths: Sequence[Sequence[tuple[int, int]]]) -> float:
    """How far (RAM units of path length) the point (x, y) lies along the nearest of ``paths`` (polylines), measured
    at its projection on the nearest segment; 0 when it is more than :data:`MAX_OFF_ROUTE` from every segment."""
    best_distance, best_progress = math.inf, 0.0
    for path in paths:
        walked = 0.0
        for (x0, y0), (x1, y1) in zip(path[:-1], path[1:]):
            length = math.hypot(x1 - x0, y1 - y0)
            t = min(max(((x - x0) * (x1 - x0) + (y - y0) * (y1 - y0)) / (length * length), 0.0), 1.0)
            distance = math.hypot(x - (x0 + t * (x1 - x0)), y - (y0 + t * (y1 - y0)))
            if distance < best_distance:
                best_distance, best_progress = distance, walked + t * length
            walked += length
    return best_progress if best_distance <= MAX_OFF_ROUTE else 0.0



class MontezumaScriptedOracle(Oracle):
    """Prefer the sub-goal further along the first room of Montezuma's Revenge (the module says how).

    Each query's ``info`` must hold ``"goal1_state"`` and ``"goal2_state"``: the facts
    (:func:`~sb3_hhp.goals.image.montezuma_facts`) of the state where each sub-goal was found. Sub-goals are ranked by
    :meth:`score`; at the same stage without a door open, positions along the way within ``equal_tolerance`` of each
    other give ``EQUAL``, as do two sub-goals in other rooms or with a door open. HhP's questions hold the facts of their
    own state (``info["state"]``, from :meth:`~sb3_hhp.goals.image.ImageGoalSpace.snapshot` at the choice) but not yet
    those of the states where the sub-goals were found: until they do, this oracle answers questions whose ``info``
    was given them.

    :param name: annotator name recorded with every answer
    :param equal_tolerance: difference of progress along the way (RAM units, >= 0) under which both sub-goals are
        equally good; 4 is one step of walking or climbing at the frame skip of 4
    """

    #: it reads the facts of the states where the sub-goals were found (sub-goals handed in have none)
    needs_found_facts = True

    def __init__(self, name: str = "scripted", equal_tolerance: float = 4.0) -> None:
        if not equal_tolerance >= 0:
            raise ValueError(f"equal_tolerance must be >= 0 RAM units, got {equal_tolerance}")
        super().__init__(name)
        self.equal_tolerance = float(equal_tolerance)

    @staticmethod
    def score(facts: dict[str, Any]) -> tuple[int, float]:
        """(stage, progress) of a state's facts: the stage from :data:`LOST` (dying) to :data:`NEW_ROOM`, and how far
        along the way to the key (no key) or back to a door (the key held) the agent stands, in RAM units."""
        if facts["death_timer"] > 0:
            return LOST, 0.0
        if facts["room"] != FIRST_ROOM:
            return NEW_ROOM, 0.0
        if ~facts["first_room_objects"] & DOOR_BITS:
            return DOOR_OPENED, 0.0
        if facts["inventory"] & KEY_BIT:
            return KEY_HELD, along(facts["x"], facts["y"], ROUTE_TO_DOORS)
        return NO_KEY, along(facts["x"], facts["y"], (ROUTE_TO_KEY,))

    @staticmethod
    def _facts(query: Query, entry: str) -> dict[str, Any]:
        facts: Optional[Any] = query.info.get(entry)
        if not isinstance(facts, dict) or facts.get("game") != MONTEZUMA or any(name not in facts for name in REQUIRED_FACTS):
            found = f"has {facts!r}" if entry in query.info else "lacks it"
            raise ValueError(
                f"MontezumaScriptedOracle needs query.info['{entry}']: the RAM facts {list(REQUIRED_FACTS)} of the state "
                f"where the sub-goal was found, as ImageGoalSpace.facts gives them on ALE Montezuma's Revenge (game "
                f"{MONTEZUMA!r}); query {query.query_id} {found}"
            )
        return facts

    def answer(self, query: Query) -> Label:
        (stage1, progress1), (stage2, progress2) = (self.score(self._facts(query, entry)) for entry in REQUIRED_KEYS)
        if stage1 != stage2:
            return Label.FIRST if stage1 > stage2 else Label.SECOND
        if abs(progress1 - progress2) <= self.equal_tolerance:
            return Label.EQUAL
        return Label.FIRST if progress1 > progress2 else Label.SECOND
