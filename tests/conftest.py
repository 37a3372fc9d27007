"""Test-session settings, read before any test module imports torch.

The CPU kernels are pinned to their AVX2 code paths (MKL's conditional numerical reproducibility, torch's own
vectorised kernels, oneDNN), so that a test that trains (``test_learning.py``) takes the same floating-point path on
every x86 machine with AVX2, whatever its processor would pick by default: on this project's AMD EPYC machines MKL's
default path and its AVX2 path gave the README's first command mean returns of 0.863 and 0.965 (same code, seed and
machine), and a run amplifies such last-bit differences. A value already set in the environment is kept. Subprocesses
the tests start inherit these settings.
"""

import os

PINNED_KERNELS = {"MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}

for name, value in PINNED_KERNELS.items():
    os.environ.setdefault(name, value)
