"""Imperfect preferences (section 5.2.1, Table 1): another oracle's answer, wrong with probability rho."""

from collections.abc import Sequence
from typing import Optional

import numpy as np

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query


class NoisyOracle(Oracle):
    """Wrap ``oracle`` so that each of its answers is replaced by a non-optimal one with probability ``rho``
    (the paper's varrho in {0.05, 0.1, 0.2}).

    A wrong answer is the opposite preference: ``FIRST`` becomes ``SECOND`` and ``SECOND`` becomes
    ``FIRST``; when the truth is ``EQUAL``, the wrong answer prefers one of the two sub-goals, chosen
    uniformly at random. ``INCOMPARABLE`` ("can't tell") is never corrupted: it carries no preference to
    get wrong, and it is never trained on anyway.

    Works for synchronous and asynchronous inner oracles alike: :meth:`~sb3_hhp.oracles.base.Oracle.submit`, :meth:`~sb3_hhp.oracles.base.Oracle.collect`,
    :meth:`~sb3_hhp.oracles.base.Oracle.pending` and :meth:`~sb3_hhp.oracles.base.Oracle.close` are passed through, and answers are corrupted as they come out.

    :param oracle: the oracle whose answers are corrupted
    :param rho: probability in [0, 1] that an answer is wrong
    :param seed: seed of the random generator that decides which answers are wrong
    :param name: annotator name recorded with every answer; by default each answer keeps the inner
        annotator's name wrapped as ``"noisy(<name>)"`` (so the expert behind a
        :class:`~sb3_hhp.oracles.experts.MultiExpertOracle` stays known)
    """

    def __init__(self, oracle: Oracle, rho: float, seed: Optional[int] = None, name: Optional[str] = None) -> None:
        if not isinstance(oracle, Oracle):
            raise ValueError(f"NoisyOracle wraps an Oracle, got {type(oracle).__name__}")
        if not 0.0 <= float(rho) <= 1.0:
            raise ValueError(f"rho must be a probability in [0, 1], got {rho}")
        super().__init__(name if name is not None else f"noisy({oracle.name})")
        self.oracle = oracle
        self.rho = float(rho)
        self._fixed_name = name is not None
        self.rng = np.random.default_rng(seed)
        # counters, e.g. for the logger: answers that went through, and how many were made wrong
        self.n_answers = 0
        self.n_corrupted = 0

    def corrupt(self, label: Label) -> Label:
        """Return ``label`` unchanged with probability 1 - rho, else a wrong answer (see the class docstring)."""
        label = Label.parse(label)
        # draw every time (even for INCOMPARABLE), so the stream of decisions depends only on the seed
        wrong = self.rng.random() < self.rho
        side = self.rng.random() < 0.5
        self.n_answers += 1
        if not wrong or label == Label.INCOMPARABLE:
            return label
        self.n_corrupted += 1
        if label == Label.FIRST:
            return Label.SECOND
        if label == Label.SECOND:
            return Label.FIRST
        return Label.FIRST if side else Label.SECOND  # EQUAL: prefer one of the two at random

    def _annotator(self, inner: str) -> str:
        return self.name if self._fixed_name else f"noisy({inner})"

    def answer(self, query: Query) -> Label:
        return self.corrupt(self.oracle.answer(query))

    def submit(self, queries: Sequence[Query]) -> None:
        self.oracle.submit(queries)

    def collect(self) -> list[Answer]:
        answers = super().collect()  # nothing is queued here, but keep the protocol's bookkeeping
        for inner in self.oracle.collect():
            label = self.corrupt(inner.label)
            answers.append(Answer(inner.query_id, label, self._annotator(inner.annotator), inner.answered_at))
        return answers

    def pending(self) -> int:
        return self.oracle.pending()

    def close(self) -> None:
        self.oracle.close()
