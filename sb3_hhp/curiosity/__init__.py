"""Curiosity: Random Network Distillation (eq. 7), the memory Omega and novelty progress (eq. 8)."""
