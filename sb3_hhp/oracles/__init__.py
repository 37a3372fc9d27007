"""Oracles that answer preference queries: scripted, synthetic, noisy, several experts, people."""

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query

__all__ = ["Answer", "Label", "Oracle", "Query"]
