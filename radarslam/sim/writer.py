"""nuScenes table records, deterministic tokens and the map PNG of a synthetic dataroot."""

from __future__ import annotations

import hashlib
import struct
import zlib
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from radarslam.geometry import rotation_to_quat
from radarslam.io.atomic import write_bytes_atomic

_TZ = timezone(timedelta(hours=-4))  # Boston summer time, as the n008 logs


def make_token(seed: int, *parts) -> str:
    """32-hex token, a pure function of the seed and the record's identity."""
    text = "|".join([str(seed), *[str(p) for p in parts]])
    return hashlib.md5(text.encode()).hexdigest()


def log_start(date: str, seconds_of_day: float) -> tuple[int, str]:
    """(epoch microseconds, nuScenes-like log name) of a drive starting at local time."""
    day = datetime.strptime(date, "%Y-%m-%d").replace(tzinfo=_TZ)
    start = day + timedelta(seconds=float(seconds_of_day))
    name = f"synth-{start.strftime('%Y-%m-%d-%H-%M-%S')}-0400"
    return round(start.timestamp() * 1e6), name


def add_days(date: str, days: int) -> str:
    return (datetime.strptime(date, "%Y-%m-%d") + timedelta(days=int(days))).strftime("%Y-%m-%d")


def yaw_quat(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def pose_record(token: str, timestamp_us: int, xy, yaw: float) -> dict:
    return {
        "token": token,
        "timestamp": int(timestamp_us),
        "rotation": yaw_quat(yaw),
        "translation": [float(xy[0]), float(xy[1]), 0.0],
    }


def calibrated_sensor_record(token: str, sensor_token: str, ego_from_sensor: np.ndarray) -> dict:
    return {
        "token": token,
        "sensor_token": sensor_token,
        "translation": [float(v) for v in ego_from_sensor[:3, 3]],
        "rotation": [float(v) for v in rotation_to_quat(ego_from_sensor[:3, :3])],
        "camera_intrinsic": [],
    }


def static_tables(seed: int, channels: tuple[str, ...]) -> dict[str, list[dict]]:
    """sensor, category, attribute, visibility (the devkit needs them; radar uses sensor only)."""
    sensor = [
        {"token": make_token(seed, "sensor", ch), "channel": ch, "modality": "radar"}
        for ch in channels
    ]
    categories = [
        ("vehicle.car", "Vehicle designed primarily for personal use."),
        ("vehicle.bus.rigid", "Rigid bus."),
        ("vehicle.bicycle", "Human or electric powered 2-wheeled vehicle."),
        ("human.pedestrian.adult", "Adult subcategory."),
        ("movable_object.barrier", "Temporary road barrier."),
        ("static_object.bicycle_rack", "Area or device intended to park or secure bicycles."),
    ]
    category = [
        {"token": make_token(seed, "category", n), "name": n, "description": d}
        for n, d in categories
    ]
    attrs = [
        ("vehicle.moving", "Vehicle is moving."),
        ("vehicle.stopped", "Vehicle, with a driver/rider in/on it, is currently stationary."),
        ("vehicle.parked", "Vehicle is stationary (usually for longer duration) with no driver."),
        ("cycle.with_rider", "There is a rider on the bicycle or motorcycle."),
        ("pedestrian.moving", "The human is moving."),
    ]
    attribute = [
        {"token": make_token(seed, "attribute", n), "name": n, "description": d} for n, d in attrs
    ]
    visibility = [
        {"token": str(i + 1), "level": lvl, "description": f"visibility of whole object is {lvl}"}
        for i, lvl in enumerate(["v0-40", "v40-60", "v60-80", "v80-100"])
    ]
    return {
        "sensor": sensor,
        "category": category,
        "attribute": attribute,
        "visibility": visibility,
    }


def png_gray(img: np.ndarray) -> bytes:
    """Minimal 8-bit grayscale PNG encoder (zlib only; no imaging library needed)."""
    h, w = img.shape
    raw = np.zeros((h, w + 1), np.uint8)
    raw[:, 1:] = img
    comp = zlib.compress(raw.tobytes(), 6)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + tag
            + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", comp) + chunk(b"IEND", b"")


def write_map(dataroot: Path, token: str, img: np.ndarray) -> str:
    rel = f"maps/{token}.png"
    write_bytes_atomic(dataroot / rel, png_gray(img))
    return rel
