"""Benchmarks of sb3_hhp: the sweep runner (``python -m benchmarks.run``), its report and speed measurements."""
