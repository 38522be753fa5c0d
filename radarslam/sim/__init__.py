"""Synthetic world generator writing the nuScenes radar layout (the embedded default dataset).

``simulate`` is imported lazily so that ``import radarslam.sim`` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from radarslam.sim.generate import SimulationSummary, simulate

__all__ = ["SimulationSummary", "simulate"]


def __getattr__(name: str):
    if name in __all__:
        from radarslam.sim import generate as _mod

        return getattr(_mod, name)
    raise AttributeError(name)
