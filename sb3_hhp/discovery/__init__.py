"""Sub-goal discovery: curiosity-driven (CSD, eq. 8) and the random ablation."""
