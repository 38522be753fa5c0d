"""Static map: key-frame clouds placed with the optimised poses, moving points removed, voxelised.

A radar point is kept as static when its ego-motion-compensated velocity is small (the radars
measure it directly, so this needs no tracking). Voxels seen fewer than ``min_points_per_voxel``
times are dropped as clutter. The map is written as PLY by :mod:`radarslam.slam.outputs`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from radarslam.config import StrictModel
from radarslam.errors import DataError


class StaticMapConfig(StrictModel):
    voxel_size_m: float = Field(0.5, gt=0, le=1000)
    max_static_speed_mps: float = Field(0.5, ge=0)  # |v_comp| above this is a moving object
    min_points_per_voxel: int = Field(2, ge=1)


#: Largest |voxel index| along an axis: cell indices stay exact in float64 and their differences
#: in int64.
_MAX_CELL = 2.0**52

#: Points kept as they came before they are summed per voxel. A city's key frames carry millions
#: of points (2.5 M on the 32-scene city subset); summed chunk by chunk, the map needs memory
#: for its voxels and one chunk, not for every point and its cell at once.
_CHUNK_POINTS = 1 << 19


@dataclass(frozen=True)
class StaticMap:
    xyz: np.ndarray  # (M, 3) voxel centroids in the world frame
    rcs: np.ndarray  # (M,) mean RCS per voxel (NaN when unknown)
    hits: np.ndarray  # (M,) number of points per voxel

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass(frozen=True)
class _VoxelSums:
    """Per voxel: its integer cell, the sum of its points, how many, and their RCS sum and count."""

    cells: np.ndarray  # (M, 3) int64
    sums: np.ndarray  # (M, 3) float64
    counts: np.ndarray  # (M,) float64 (exact: far below 2**53)
    rcs_sum: np.ndarray  # (M,)
    rcs_n: np.ndarray  # (M,)

    @staticmethod
    def concat(a: _VoxelSums, b: _VoxelSums) -> _VoxelSums:
        return _VoxelSums(
            *(np.concatenate([x, y]) for x, y in zip(a.astuple(), b.astuple(), strict=True))
        )

    def astuple(self) -> tuple[np.ndarray, ...]:
        return (self.cells, self.sums, self.counts, self.rcs_sum, self.rcs_n)

    def reduced(self) -> _VoxelSums:
        """One row per distinct cell, in lexicographic cell order."""
        cells = self.cells
        # One scalar key per voxel: a 1-D unique and bincount instead of np.unique(axis=0) and
        # np.add.at, 6 s -> 0.3 s for the 2.5 M points of a 1,280-key-frame run.
        shifted = cells - cells.min(axis=0)
        span = shifted.max(axis=0) + 1
        if int(span[0]) * int(span[1]) * int(span[2]) < 2**63:
            keys = (shifted[:, 0] * span[1] + shifted[:, 1]) * span[2] + shifted[:, 2]
            _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
            unique_cells = cells[first]
        else:  # the scalar key would overflow int64: unique rows instead (slower, same voxels)
            unique_cells, inverse = np.unique(cells, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        n = len(unique_cells)

        def total(w: np.ndarray) -> np.ndarray:
            return np.bincount(inverse, weights=w, minlength=n)

        return _VoxelSums(
            unique_cells,
            np.column_stack([total(self.sums[:, i]) for i in range(3)]),
            total(self.counts),
            total(self.rcs_sum),
            total(self.rcs_n),
        )


class StaticMapBuilder:
    def __init__(self, config: StaticMapConfig | None = None):
        self.config = config or StaticMapConfig()
        self._xyz: list[np.ndarray] = []  # points not yet summed per voxel (world frame)
        self._rcs: list[np.ndarray] = []
        self._pending = 0
        self._voxels: _VoxelSums | None = None
        self.num_dynamic_removed = 0

    def add(
        self,
        world_from_cloud: np.ndarray,
        points,
        velocity_comp_mps=None,
        rcs=None,
    ) -> None:
        """Add one key frame's cloud: ``points`` (N, 2|3) in the cloud frame, or a structured
        array with x, y, z (and vx_comp, vy_comp, rcs, used when present)."""
        pose = np.asarray(world_from_cloud, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise DataError(f"static map: cloud pose must be a finite 4x4, got {pose.shape}")
        arr = np.asarray(points)
        if arr.dtype.names:
            names = arr.dtype.names
            xyz = np.column_stack(
                [arr["x"], arr["y"], arr["z"] if "z" in names else np.zeros(len(arr))]
            ).astype(np.float64)
            if velocity_comp_mps is None and "vx_comp" in names:
                velocity_comp_mps = np.column_stack([arr["vx_comp"], arr["vy_comp"]])
            if rcs is None and "rcs" in names:
                rcs = arr["rcs"]
        else:
            arr = arr.astype(np.float64)
            if arr.ndim != 2 or arr.shape[1] not in (2, 3):
                raise DataError(f"static map: points must be (N, 2) or (N, 3), got {arr.shape}")
            xyz = arr if arr.shape[1] == 3 else np.column_stack([arr, np.zeros(len(arr))])
        if not len(xyz):  # a key frame while every radar was silent
            return
        keep = np.all(np.isfinite(xyz), axis=1)
        if velocity_comp_mps is not None:
            v = np.asarray(velocity_comp_mps, dtype=np.float64).reshape(len(xyz), -1)
            moving = np.linalg.norm(v, axis=1) > self.config.max_static_speed_mps
            self.num_dynamic_removed += int(np.count_nonzero(moving & keep))
            keep &= ~moving
        r = np.full(len(xyz), np.nan) if rcs is None else np.asarray(rcs, dtype=np.float64)
        self._xyz.append(xyz[keep] @ pose[:3, :3].T + pose[:3, 3])
        self._rcs.append(r[keep])
        self._pending += int(np.count_nonzero(keep))
        if self._pending >= _CHUNK_POINTS:
            self._sum_pending()

    def _sum_pending(self) -> None:
        """Fold the points added since the last call into the per-voxel sums."""
        if not self._xyz:
            return
        xyz = np.concatenate(self._xyz)
        rcs = np.concatenate(self._rcs)
        self._xyz, self._rcs, self._pending = [], [], 0
        if len(xyz) == 0:
            return
        finite = np.isfinite(rcs)
        chunk = _VoxelSums(
            self._cells(xyz),
            xyz,
            np.ones(len(xyz)),
            np.where(finite, rcs, 0.0),
            finite.astype(np.float64),
        ).reduced()
        self._voxels = (
            chunk if self._voxels is None else _VoxelSums.concat(self._voxels, chunk).reduced()
        )

    def _cells(self, xyz: np.ndarray) -> np.ndarray:
        cells_f = np.floor(xyz / self.config.voxel_size_m)
        far = np.abs(cells_f).max(axis=1) > _MAX_CELL
        if far.any():  # float -> int64 would wrap and merge unrelated voxels
            i = int(np.flatnonzero(far)[0])
            raise DataError(
                f"static map: point {xyz[i].tolist()} m is too far from the origin for "
                f"{self.config.voxel_size_m:g} m voxels ({int(far.sum())} such point(s)): "
                "are the poses corrupt?"
            )
        return cells_f.astype(np.int64)

    def build(self) -> StaticMap:
        """The map of every cloud added so far (more may be added and the map built again)."""
        self._sum_pending()
        v = self._voxels
        if v is None:
            return StaticMap(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64))
        keep = v.counts >= self.config.min_points_per_voxel
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_rcs = np.where(v.rcs_n > 0, v.rcs_sum / np.maximum(v.rcs_n, 1), np.nan)
        return StaticMap(
            xyz=v.sums[keep] / v.counts[keep, None],
            rcs=mean_rcs[keep],
            hits=v.counts[keep].astype(np.int64),
        )
