"""Handcrafted place-recognition baselines evaluated in the same harness as AutoPlace."""
