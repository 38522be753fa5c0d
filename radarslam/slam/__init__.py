"""SLAM back end: pose graph (GTSAM), loop verification, map and outputs."""
