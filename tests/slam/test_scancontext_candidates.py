"""Rotation-invariant (ScanContext) loop candidates: retrieval under any heading, pure queries."""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.slam.scancontext_candidates import ScanContextCandidates


def _place(rng, n=400):
    """A cloud of reflectors around the vehicle, denser on two street sides."""
    along = rng.uniform(-70, 70, n)
    side = np.where(rng.uniform(size=n) < 0.5, -1, 1) * rng.uniform(4, 30, n)
    return np.column_stack([along, side])


def _seen_again(xy, rng, yaw_deg, shift_m=(0.6, -0.4), noise_m=0.3, keep=0.8):
    """The same place from a pose ``shift_m`` away, turned by ``yaw_deg``: radar-like noise and
    flicker (only ``keep`` of the points return)."""
    pts = xy[rng.uniform(size=len(xy)) < keep] - np.asarray(shift_m)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pts = pts @ np.array([[c, -s], [s, c]])  # seen by a vehicle turned by yaw_deg
    return pts + rng.normal(0, noise_m, pts.shape)


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, 180.0])
def test_a_place_is_found_whatever_the_heading(yaw_deg):
    rng = np.random.default_rng(4)
    places = [_place(rng) for _ in range(30)]
    db = ScanContextCandidates()
    for k, xy in enumerate(places):
        db.add(("s", k), xy)
    hits = 0
    for k in range(0, 30, 3):
        best = db.query(_seen_again(places[k], rng, yaw_deg), lambda key: True, k=1)
        hits += best[0].key == ("s", k)
        assert 0.0 <= best[0].distance <= 1.0
    assert hits >= 9, hits  # 10 queries


def test_query_is_pure_and_respects_allowed():
    rng = np.random.default_rng(5)
    db = ScanContextCandidates(ring_candidates=5)
    assert db.query(_place(rng), lambda key: True) == []  # empty database
    places = [_place(rng) for _ in range(8)]
    for k, xy in enumerate(places):
        db.add(k, xy)
    n = len(db)
    got = db.query(places[3], lambda key: key != 3, k=3)
    assert len(db) == n, "a query must not insert"
    assert [c.key for c in got if c.key == 3] == []
    assert len(got) == 3 and got[0].distance <= got[1].distance <= got[2].distance
    assert db.query(places[3], lambda key: False) == []
    assert db.query(np.zeros((0, 2)), lambda key: True) == []  # an empty cloud matches nothing


def test_database_grows_past_its_first_allocation():
    rng = np.random.default_rng(6)
    db = ScanContextCandidates()
    places = [_place(rng, 150) for _ in range(70)]
    for k, xy in enumerate(places):
        db.add(k, xy)
    assert len(db) == 70
    assert db.query(places[65], lambda key: True)[0].key == 65
