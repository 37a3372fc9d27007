"""Oracles that answer preference queries: scripted, synthetic, noisy, several experts, people."""

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query
from sb3_hhp.oracles.experts import MultiExpertOracle
from sb3_hhp.oracles.fetch import FetchScriptedOracle
from sb3_hhp.oracles.montezuma import MontezumaScriptedOracle
from sb3_hhp.oracles.noisy import NoisyOracle
from sb3_hhp.oracles.registry import ORACLE_NAMES, make_oracle
from sb3_hhp.oracles.scripted import MiniGridScriptedOracle
from sb3_hhp.oracles.synthetic import SyntheticOracle
from sb3_hhp.oracles.terminal import TerminalOracle

__all__ = [
    "ORACLE_NAMES",
    "Answer",
    "FetchScriptedOracle",
    "Label",
    "MiniGridScriptedOracle",
    "MontezumaScriptedOracle",
    "MultiExpertOracle",
    "NoisyOracle",
    "Oracle",
    "Query",
    "SyntheticOracle",
    "TerminalOracle",
    "make_oracle",
]
