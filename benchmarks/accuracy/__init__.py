"""Accuracy: registration error against known motion (held-out real CTs, clinical geometry, capture range,
damaged inputs)."""
