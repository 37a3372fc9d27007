"""Preference learning: predictor (eq. 1, 2, 4), query selection, durable store, meta-rewards (eq. 3)."""
