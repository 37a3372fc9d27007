"""Several experts (section 5.2.7, Table 4): each run, or each query, is answered by one of them."""

from collections.abc import Sequence
from typing import Optional

import numpy as np

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query

ASSIGNMENTS = ("query", "run")


class MultiExpertOracle(Oracle):
    """Answer queries with several experts who do not communicate (so they need not agree).

    With ``assignment="query"`` every query goes to one expert drawn uniformly at random; with
    ``assignment="run"`` one expert, drawn at construction, answers the whole run (the paper's setting:
    "each run is randomly assigned to an expert"). Every :class:`~sb3_hhp.oracles.base.Answer` carries
    the annotator name of the expert who gave it, so experts need distinct names.

    Experts may be synchronous or asynchronous: queries are submitted to the chosen expert and
    :meth:`~sb3_hhp.oracles.base.Oracle.collect` gathers what every expert has answered.

    :param oracles: the experts (at least one, with distinct names)
    :param assignment: ``"query"`` (one random expert per query) or ``"run"`` (one expert for the run)
    :param seed: seed of the random generator that assigns experts
    """

    def __init__(self, oracles: Sequence[Oracle], assignment: str = "query", seed: Optional[int] = None) -> None:
        oracles = list(oracles)
        if len(oracles) == 0:
            raise ValueError("MultiExpertOracle needs at least one expert oracle, got an empty list")
        for i, oracle in enumerate(oracles):
            if not isinstance(oracle, Oracle):
                raise ValueError(f"Expert {i} is not an Oracle but a {type(oracle).__name__}")
        names = [oracle.name for oracle in oracles]
        if len(set(names)) != len(names):
            raise ValueError(f"Experts need distinct names so that each answer says who gave it, got {names}")
        if assignment not in ASSIGNMENTS:
            raise ValueError(f"assignment must be one of {ASSIGNMENTS}, got {assignment!r}")
        super().__init__("experts(" + ",".join(names) + ")")
        self.oracles = oracles
        self.assignment = assignment
        self.rng = np.random.default_rng(seed)
        # the expert of the whole run (assignment="run"); None when each query draws its own
        self.run_expert: Optional[int] = int(self.rng.integers(len(oracles))) if assignment == "run" else None
        # query_id -> index of the expert it was given to
        self.assigned: dict[str, int] = {}
        self.last_annotator: Optional[str] = None

    def choose_expert(self, query: Query) -> int:
        """Index of the expert who answers ``query`` (recorded in ``assigned``)."""
        if self.run_expert is not None:
            index = self.run_expert
        else:
            index = int(self.rng.integers(len(self.oracles)))
        self.assigned[query.query_id] = index
        return index

    def answer(self, query: Query) -> Label:
        """Answer at once with the chosen expert; its name is left in ``last_annotator``."""
        expert = self.oracles[self.choose_expert(query)]
        self.last_annotator = expert.name
        return Label.parse(expert.answer(query))

    def submit(self, queries: Sequence[Query]) -> None:
        batches: dict[int, list[Query]] = {}
        for query in queries:
            batches.setdefault(self.choose_expert(query), []).append(query)
        for index, batch in batches.items():
            self.oracles[index].submit(batch)

    def collect(self) -> list[Answer]:
        answers = super().collect()
        for oracle in self.oracles:
            answers.extend(oracle.collect())
        return answers

    def pending(self) -> int:
        return sum(oracle.pending() for oracle in self.oracles)

    def close(self) -> None:
        for oracle in self.oracles:
            oracle.close()
