"""People answering at the labeling web page (``python -m sb3_hhp.label``), through the preference store.

The trainer's :class:`WebOracle` and the labeling servers share one :class:`~sb3_hhp.preferences.store.PreferenceStore` (an
object in the same process, or the same SQLite file from other processes): :meth:`WebOracle.submit`
queues the questions in the store, annotators answer them from their browsers, and
:meth:`WebOracle.collect` reads the answers committed since its previous call. Training never
waits for a person.
"""

from collections.abc import Sequence
from typing import Optional

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query
from sb3_hhp.preferences.store import PreferenceStore

__all__ = ["WebOracle"]


class WebOracle(Oracle):
    """An asynchronous oracle: the queue of questions and the answers live in a :class:`~sb3_hhp.preferences.store.PreferenceStore`.

    :param store: the store the labeling page serves (the caller keeps ownership and closes it)
    :param name: the oracle's name (each answer records the annotator who gave it, not this name)
    :param run_id: recorded with every submitted query, see :meth:`~sb3_hhp.preferences.store.PreferenceStore.count_asked`
    :param start_seq: answers with a sequence number above this are collected; ``None`` starts after
        the newest answer already in the store (a resumed run collects only new answers), ``0``
        collects every answer in the store on the first call
    """

    def __init__(
        self, store: PreferenceStore, name: str = "web", run_id: str = "", start_seq: Optional[int] = None
    ) -> None:
        super().__init__(name)
        if not isinstance(store, PreferenceStore):
            raise ValueError(f"WebOracle needs a PreferenceStore, got {type(store).__name__}")
        if start_seq is not None and start_seq < 0:
            raise ValueError(f"start_seq must be >= 0 or None, got {start_seq}")
        self.store = store
        self.run_id = run_id
        self._seq = store.last_seq() if start_seq is None else int(start_seq)

    def answer(self, query: Query) -> Label:
        """Not available: people answer asynchronously; use :meth:`submit` and :meth:`collect`."""
        raise NotImplementedError("WebOracle is asynchronous: submit() queries and collect() the answers later")

    def submit(self, queries: Sequence[Query]) -> None:
        """Queue the queries in the store, where the labeling page picks them up (already stored ids are kept)."""
        for query in queries:
            self.store.add_query(query, run_id=self.run_id)

    def collect_pairs(self) -> list[tuple[Query, Answer]]:
        """Like :meth:`collect`, with each answer's query (as stored) beside it."""
        triples = self.store.answers_since(self._seq)
        if triples:
            self._seq = triples[-1][0]
        return [(query, answer) for _, query, answer in triples]

    def collect(self) -> list[Answer]:
        """The answers committed to the store since the last call, by any annotator or process (never blocks)."""
        return [answer for _, answer in self.collect_pairs()]

    @property
    def last_seq(self) -> int:
        """The sequence number of the last answer collected (save it to resume collecting after a restart)."""
        return self._seq

    def pending(self) -> int:
        """Number of queries in the store still waiting for an answer."""
        return len(self.store.open_query_ids())
