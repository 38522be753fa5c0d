"""Evaluation: trajectory metrics, loop-closure precision/recall, plots, ``radarslam eval``."""
