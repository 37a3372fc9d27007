"""The oracle protocol: given a state and two sub-goals, answer FIRST, SECOND, EQUAL or INCOMPARABLE.

Every oracle (scripted, synthetic, noisy, several experts, a person at a web page or a terminal)
implements :class:`Oracle`. Queries go in with :meth:`Oracle.submit`; answers come back, possibly
later and possibly never, through :meth:`Oracle.collect`. Training never blocks on an oracle.
"""

import enum
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np


class Label(enum.IntEnum):
    """An answer to "which sub-goal is better in this state?" (section 4.1.1)."""

    FIRST = 0  # g1 preferred, one-hot [1, 0, 0]
    SECOND = 1  # g2 preferred, one-hot [0, 1, 0]
    EQUAL = 2  # equally good, trained with the target (0.5, 0.5) (DESIGN.md gap 2)
    INCOMPARABLE = 3  # "can't tell": stored, never trained on

    @classmethod
    def parse(cls, value: Any) -> "Label":
        """Read a label from an int, a name (case-insensitive) or a Label; raise ValueError otherwise."""
        if isinstance(value, Label):
            return value
        if isinstance(value, str):
            name = value.strip().upper().replace("'", "").replace(" ", "_")
            aliases = {"CANT_TELL": "INCOMPARABLE", "CAN_NOT_TELL": "INCOMPARABLE", "CANNOT_TELL": "INCOMPARABLE"}
            name = aliases.get(name, name)
            if name in cls.__members__:
                return cls[name]
        elif isinstance(value, (int, np.integer)) and not isinstance(value, bool) and int(value) in (0, 1, 2, 3):
            return cls(int(value))
        raise ValueError(
            f"Unknown preference label {value!r}: use one of FIRST, SECOND, EQUAL, INCOMPARABLE (or 0, 1, 2, 3)"
        )


@dataclass
class Query:
    """One question to an oracle: in ``state``, is sub-goal ``goal1`` or ``goal2`` better?

    :param state: the observation the networks see (as stored in the replay buffers)
    :param goal1: id of the first sub-goal (the meta-controller's choice g)
    :param goal2: id of the second sub-goal (the meta-controller's second choice g2)
    :param goal1_obs: the observation that represents ``goal1`` for the networks
    :param goal2_obs: the observation that represents ``goal2`` for the networks
    :param state_image: RGB image (H, W, 3) uint8 of the state, for people (optional)
    :param goal1_image: RGB image of ``goal1`` for people (optional)
    :param goal2_image: RGB image of ``goal2`` for people (optional)
    :param info: privileged data for scripted oracles (e.g. the goal keys); never shown to people
    :param query_id: unique id; derived from the content when not given, so a re-run asks the same id
    :param asked_at: UNIX time the question was asked
    """

    state: np.ndarray
    goal1: int
    goal2: int
    goal1_obs: np.ndarray
    goal2_obs: np.ndarray
    state_image: Optional[np.ndarray] = None
    goal1_image: Optional[np.ndarray] = None
    goal2_image: Optional[np.ndarray] = None
    info: dict = field(default_factory=dict)
    query_id: str = ""
    asked_at: float = field(default_factory=time.time)

    def __post_init__(self) -> None:
        if not self.query_id:
            self.query_id = uuid.uuid4().hex


@dataclass
class Answer:
    """An oracle's answer to the query ``query_id``."""

    query_id: str
    label: Label
    annotator: str
    answered_at: float = field(default_factory=time.time)


class Oracle(ABC):
    """Answers preference queries. Subclasses implement :meth:`answer` (synchronous oracles) or
    override :meth:`submit` and :meth:`collect` (asynchronous ones, such as a person at a web page).

    :param name: the annotator name recorded with every answer
    """

    def __init__(self, name: str = "oracle") -> None:
        if not isinstance(name, str) or not name:
            raise ValueError(f"An oracle needs a non-empty name, got {name!r}")
        self.name = name
        self._ready: list[Answer] = []

    @abstractmethod
    def answer(self, query: Query) -> Label:
        """Answer one query at once."""

    def submit(self, queries: Sequence[Query]) -> None:
        """Hand queries to the oracle. A synchronous oracle answers them immediately."""
        for query in queries:
            self._ready.append(Answer(query.query_id, Label.parse(self.answer(query)), self.name))

    def collect(self) -> list[Answer]:
        """Answers that arrived since the last call (never blocks)."""
        ready, self._ready = self._ready, []
        return ready

    def pending(self) -> int:
        """Number of submitted queries still waiting for an answer."""
        return 0

    def close(self) -> None:
        """Release resources (servers, threads)."""
