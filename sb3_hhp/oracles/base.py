"""The oracle protocol: given a state and two sub-goals, answer FIRST, SECOND, EQUAL or INCOMPARABLE.

Every oracle (scripted, synthetic, noisy, several experts, a person at a web page or a terminal)
implements :class:`Oracle`. Queries go in with :meth:`Oracle.submit`; answers come back, possibly
later and possibly never, through :meth:`Oracle.collect`. Training never blocks on an oracle.
"""

from abc import ABC, abstractmethod
from collections.abc import Sequence

from sb3_hhp.preferences.types import Answer, Label, Query

__all__ = ["Answer", "Label", "Oracle", "Query"]


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
