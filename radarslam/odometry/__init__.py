"""Radar odometry front end: Doppler ego-motion + kiss-icp scan-to-map registration, fused.

See docs/odometry.md. Names are resolved lazily so that importing the CLI stays light.
"""

from __future__ import annotations

_EXPORTS = {
    "DopplerConfig": "radarslam.odometry.doppler",
    "DopplerEstimator": "radarslam.odometry.doppler",
    "EgoMotionFit": "radarslam.odometry.doppler",
    "SensorVelocityFit": "radarslam.odometry.doppler",
    "fit_sensor_velocity": "radarslam.odometry.doppler",
    "OdometryConfig": "radarslam.odometry.config",
    "OdometryResult": "radarslam.odometry.pipeline",
    "RadarOdometry": "radarslam.odometry.pipeline",
    "OdometryTrajectory": "radarslam.odometry.run",
    "run_odometry": "radarslam.odometry.run",
    "write_outputs": "radarslam.odometry.run",
    "PlainKissIcpOdometry": "radarslam.odometry.baselines",
    "make_odometry": "radarslam.odometry.baselines",
    "load_kernels": "radarslam.odometry.registration",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'radarslam.odometry' has no attribute {name!r}")
