"""The preference data types: a :class:`Query` (which of two sub-goals is better in a state?), the
:class:`Label` that answers it and the :class:`Answer` that records who answered and when.

They belong to preference learning, so the predictor, the store and every oracle share them from
here; ``sb3_hhp.oracles`` re-exports them for convenience.
"""

import enum
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

__all__ = ["Answer", "Label", "Query"]


class Label(enum.IntEnum):
    """An answer to "which sub-goal is better in this state?" (section 4.1.1)."""

    FIRST = 0  # g1 preferred, one-hot [1, 0, 0]
    SECOND = 1  # g2 preferred, one-hot [0, 1, 0]
    EQUAL = 2  # equally good, trained with the target (0.5, 0.5)
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
    :param query_id: unique id; a random hex id when not given
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
