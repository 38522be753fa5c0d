import copy
import warnings

import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.eval.metrics import (
    align_se2,
    align_sim2,
    ate,
    ate_clock_offsets,
    drift,
    pairs_for_delta,
    rpe,
    se2_between,
    turn_scale,
    turn_scale_of_steps,
)
from radarslam.geometry import se2_to_matrix


def _circle(n=200, radius=30.0):
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([radius * np.cos(th), radius * np.sin(th), th + np.pi / 2])


def _poses(xy_yaw):
    return np.stack([se2_to_matrix(*p) for p in xy_yaw])


def _noisy(ref, seed=0, sigma=(0.3, 0.3, 0.01)):
    rng = np.random.default_rng(seed)
    return ref + rng.normal(scale=sigma, size=ref.shape)


def test_align_se2_recovers_a_rigid_transform():
    ref = _circle()
    rot = 0.7
    c, s = np.cos(rot), np.sin(rot)
    est_xy = (ref[:, :2] - [5.0, -2.0]) @ np.array([[c, -s], [s, c]])  # est = R^T (ref - t)
    al = align_se2(est_xy, ref[:, :2])
    assert al.yaw_rad == pytest.approx(rot, abs=1e-12)
    np.testing.assert_allclose(
        al.rotation @ est_xy.T + al.translation[:, None], ref[:, :2].T, atol=1e-9
    )


def test_align_sim2_recovers_a_similarity_and_reads_a_short_estimate_as_scale_above_one():
    ref = _circle()
    rot, scale = -0.3, 1.002  # the estimate is 0.2 % short of the reference
    c, s = np.cos(rot), np.sin(rot)
    est_xy = (ref[:, :2] - [4.0, 9.0]) @ np.array([[c, -s], [s, c]]) / scale
    al = align_sim2(est_xy, ref[:, :2])
    assert al.scale == pytest.approx(scale, abs=1e-12)
    assert al.yaw_rad == pytest.approx(rot, abs=1e-12)
    np.testing.assert_allclose(
        al.apply(np.column_stack([est_xy, ref[:, 2]]))[:, :2], ref[:, :2], atol=1e-9
    )
    np.testing.assert_allclose(al.matrix[:2, :2], scale * al.rotation)
    est = np.column_stack([est_xy, ref[:, 2] - rot])
    assert ate(est, ref, align="sim2").rmse_m == pytest.approx(0.0, abs=1e-9)
    # without the scale the 0.2 % shows: 0.06 m on a circle of radius 30 m
    assert ate(est, ref, align="se2").rmse_m == pytest.approx(30 * 0.002 / scale, rel=1e-6)
    assert align_se2(est_xy, ref[:, :2]).scale == 1.0
    # positions that do not spread leave the scale at 1 (only the translation is observable)
    assert align_sim2(np.zeros((5, 2)), ref[:5, :2]).scale == 1.0


def test_ate_hand_computed():
    ref = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    est = ref + np.array([[0, 1, 0], [0, 1, 0], [0, 1, 0], [0, -3, 0]])
    r = ate(est, ref, align="none")
    np.testing.assert_allclose(r.errors_m, [1, 1, 1, 3])
    assert r.rmse_m == pytest.approx(np.sqrt(12 / 4))
    assert r.mean_m == 1.5 and r.median_m == 1.0 and r.max_m == 3.0
    # first-pose alignment removes the constant +1 offset: errors 0, 0, 0, 4
    r = ate(est, ref, align="first")
    np.testing.assert_allclose(r.errors_m, [0, 0, 0, 4], atol=1e-12)
    # se2 alignment of a pure translation offset is exact
    r = ate(ref + np.array([10.0, -4.0, 0.0]), ref, align="se2")
    assert r.rmse_m == pytest.approx(0.0, abs=1e-12)


def test_rpe_hand_computed():
    ref = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    est = ref.copy()
    est[2:, 2] = np.deg2rad(10)  # a 10 deg heading error appears between frames 1 and 2
    r = rpe(est, ref, delta=1, unit="frames")
    np.testing.assert_allclose(r.rot_errors_deg, [0, 10, 0], atol=1e-9)
    # positions are right, so the step after the heading jump appears rotated by 10 deg
    np.testing.assert_allclose(r.trans_errors_m, [0, 0, 2 * np.sin(np.deg2rad(5))], atol=1e-12)
    # estimate twice as fast: each 1-frame step is 1 m too long
    r = rpe(ref * [2, 1, 1], ref, delta=1, unit="frames")
    np.testing.assert_allclose(r.trans_errors_m, [1, 1, 1])
    ts = np.array([0, 500_000, 1_000_000, 1_499_900])
    np.testing.assert_array_equal(pairs_for_delta(ref, ts, 1.0, "s"), [[0, 2], [1, 3]])
    np.testing.assert_array_equal(pairs_for_delta(ref, None, 2.0, "m"), [[0, 2], [1, 3]])


def test_drift_hand_computed():
    n = 201
    ref = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    est = ref * [1.01, 1, 1]  # 1 % scale error -> 1 % drift
    d = drift(est, ref, segment_lengths_m=(100,))
    assert d.translation_pct == pytest.approx(1.0)
    assert d.rotation_deg_per_100m == pytest.approx(0.0)
    assert d.num_segments == 101
    # constant yaw rate error of 0.01 deg per metre -> 1 deg / 100 m
    est = ref.copy()
    est[:, 2] = np.deg2rad(0.01 * np.arange(n))
    d = drift(est, ref, segment_lengths_m=(50, 100))
    assert d.rotation_deg_per_100m == pytest.approx(1.0)
    assert d.per_length[50.0][2] == 151
    assert np.isnan(drift(est, ref, segment_lengths_m=(500,)).translation_pct)


def test_ate_and_rpe_match_evo_on_planar_trajectory():
    import evo.main_ape as main_ape
    import evo.main_rpe as main_rpe
    from evo.core import metrics, trajectory
    from evo.core.units import Unit

    ref = _circle(300)
    est = _noisy(ref, seed=1)
    # rotate+shift the estimate so alignment matters
    est_poses = np.stack([se2_to_matrix(7.0, -3.0, 0.4) @ p for p in _poses(est)])
    ref_poses = _poses(ref)
    t = np.arange(len(ref)) * 0.1
    ref_t = trajectory.PoseTrajectory3D(poses_se3=list(ref_poses), timestamps=t)
    est_t = trajectory.PoseTrajectory3D(poses_se3=list(est_poses), timestamps=t)

    # rigid, and with a scale on an estimate made 0.5 % short
    short_t = trajectory.PoseTrajectory3D(poses_se3=list(est_poses), timestamps=t)
    short_t.scale(0.995)
    for traj, align in ((est_t, "se2"), (short_t, "sim2")):
        res = main_ape.ape(
            ref_t,
            copy.deepcopy(traj),
            metrics.PoseRelation.translation_part,
            align=True,
            correct_scale=align == "sim2",
        )
        ours = ate(np.stack(traj.poses_se3), ref_poses, align=align)
        assert ours.rmse_m == pytest.approx(res.stats["rmse"], abs=1e-6)
        assert ours.max_m == pytest.approx(res.stats["max"], abs=1e-6)
        np.testing.assert_allclose(ours.errors_m, res.np_arrays["error_array"], atol=1e-6)
    assert ours.alignment.scale == pytest.approx(1 / 0.995, rel=2e-3)
    res = main_ape.ape(ref_t, copy.deepcopy(est_t), metrics.PoseRelation.translation_part)
    assert ate(est_poses, ref_poses, align="none").rmse_m == pytest.approx(
        res.stats["rmse"], abs=1e-6
    )

    for delta in (1, 10):
        ours = rpe(est_poses, ref_poses, delta=delta, unit="frames")
        for rel, value in (
            (metrics.PoseRelation.translation_part, ours.trans_rmse_m),
            (metrics.PoseRelation.rotation_angle_deg, ours.rot_rmse_deg),
        ):
            res = main_rpe.rpe(
                copy.deepcopy(ref_t),  # evo reduces both trajectories in place
                copy.deepcopy(est_t),
                rel,
                delta=delta,
                delta_unit=Unit.frames,
                all_pairs=True,
            )
            assert value == pytest.approx(res.stats["rmse"], abs=1e-6)


def test_se2_between_inverts_compose():
    a, b = np.array([1.0, 2.0, 0.3]), np.array([-4.0, 0.5, 2.9])
    d = se2_between(a, b)
    np.testing.assert_allclose(se2_to_matrix(*a) @ se2_to_matrix(*d), se2_to_matrix(*b), atol=1e-12)


def test_bad_inputs_are_data_errors():
    ref = _circle(10)
    with pytest.raises(DataError, match="estimate has 9 poses but reference has 10"):
        ate(ref[:9], ref)
    with pytest.raises(DataError, match="expected"):
        ate(np.zeros((3, 2)), ref[:3])
    with pytest.raises(DataError, match="unknown alignment"):
        ate(ref, ref, align="sim3")
    with pytest.raises(DataError, match="needs timestamps"):
        rpe(ref, ref, delta=1.0, unit="s")
    with pytest.raises(DataError, match="delta must be > 0"):
        rpe(ref, ref, delta=0, unit="m")
    bad = ref.copy()
    bad[3, 0] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        ate(bad, ref)


def _est_gt(n=60):
    ts = 1_533_152_744_702_540 + np.arange(n, dtype=np.int64) * 100_000
    ref = np.column_stack(
        [1000 + 2.0 * np.arange(n), 500 + 0.05 * np.arange(n) ** 2, 0.02 * np.arange(n)]
    )
    return ts, _poses(_noisy(ref, sigma=(0.1, 0.1, 0.001))), _poses(ref)


@pytest.mark.parametrize(
    ("stamps", "match"),
    [
        (
            lambda ts: ts / 1e6,
            r"timestamp 0 is 1533152744\.70254; "
            r"timestamps_us must be finite integer microseconds \(seconds given",
        ),
        (lambda ts: ts + 0.7, r"timestamp 0 is 1533152744702540\.8; timestamps_us must be"),
        (lambda ts: np.full(len(ts), np.nan), "timestamp 0 is nan; timestamps_us must be finite"),
        (lambda ts: ["x"] * len(ts), "timestamps_us must be integer microseconds, got <U1 .* 'x'"),
        (lambda ts: np.ones(len(ts), dtype=bool), "timestamps_us must be integer .*, got bool"),
        (lambda ts: ts[::-1], r"timestamp 1 \(\d+ us\) is earlier than the previous one"),
        (lambda ts: ts + 2**62, r"timestamp \d+ \(\d+ us\) is out of range"),
    ],
)
def test_rpe_in_seconds_rejects_timestamps_that_are_not_integer_microseconds(stamps, match):
    ts, est, gt = _est_gt()
    assert rpe(est, gt, ts, 1.0, "s").count == 50
    assert rpe(est, gt, ts.astype(float), 1.0, "s").count == 50  # integral floats are fine
    with pytest.raises(DataError, match="RPE: " + match):
        rpe(est, gt, stamps(ts), 1.0, "s")


def test_rpe_delta_must_be_a_number_and_huge_delta_gives_no_pair():
    ts, est, gt = _est_gt()
    with pytest.raises(DataError, match="RPE: delta must be a number, got str '1'"):
        rpe(est, gt, ts, "1", "s")
    assert rpe(est, gt, ts, 1e300, "s").count == 0


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda p: p @ np.diag([3.0, 3.0, 3.0, 1.0]), r"estimate: pose 0 has a non-orthonormal"),
        (lambda p: p @ np.diag([1.0, -1.0, 1.0, 1.0]), r"estimate: pose 0 has a reflection"),
        (
            lambda p: np.where(np.arange(len(p))[:, None, None] == 3, np.nan, p),
            "estimate: pose 3 has non-finite entries",
        ),
    ],
)
def test_metrics_reject_non_rigid_poses(damage, match):
    ts, est, gt = _est_gt()
    for fn in (lambda e: ate(e, gt), lambda e: rpe(e, gt, ts), lambda e: drift(e, gt, 20.0)):
        with pytest.raises(DataError, match=match):
            fn(damage(est))
    assert ate(est.astype(np.float32), gt).rmse_m == pytest.approx(ate(est, gt).rmse_m, abs=1e-4)


def test_drift_arguments():
    _, est, gt = _est_gt()
    assert drift(est, gt, 50.0) == drift(est, gt, (50.0,))  # a bare length is one length
    assert drift(est, gt, (50.0,), step_frames=np.int64(2)).num_segments > 0
    for step in (1.5, True, "2"):
        with pytest.raises(DataError, match=f"step_frames must be an integer >= 1, got .*{step!r}"):
            drift(est, gt, (50.0,), step_frames=step)
    with pytest.raises(DataError, match="step_frames must be >= 1, got 0"):
        drift(est, gt, (50.0,), step_frames=0)
    with pytest.raises(DataError, match="segment lengths must be numbers in metres, got 'abc'"):
        drift(est, gt, "abc")


def _printed(poses, decimals):
    """Poses as a file printed with ``decimals`` digits gives them back (rotation blocks no
    longer exactly orthonormal)."""
    return np.round(poses, decimals)


def test_rounded_rotation_blocks_are_accepted_like_evo_with_one_warning():
    import evo.main_ape as main_ape
    from evo.core import metrics as evo_metrics
    from evo.core import trajectory

    ref = _circle(300)
    ref_poses = _poses(ref)
    est_poses = _printed(
        np.stack([se2_to_matrix(7.0, -3.0, 0.4) @ p for p in _poses(_noisy(ref))]), 3
    )
    orth = np.abs(np.einsum("nij,nkj->nik", est_poses[:, :3, :3], est_poses[:, :3, :3]) - np.eye(3))
    assert 1e-3 < orth.max() <= 0.01  # what the old 1e-3 tolerance refused
    with pytest.warns(UserWarning, match=r"estimate: \d+ of 300 pose\(s\) have a rotation block"):
        ours = ate(est_poses, ref_poses, align="se2")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("default")  # Python's own: each text once per place
        ate(est_poses, ref_poses, align="first")
        rpe(est_poses, ref_poses, delta=1, unit="frames")
        drift(est_poses, ref_poses)
    assert len(rec) == 1, [str(w.message) for w in rec]
    t = np.arange(len(ref)) * 0.1
    res = main_ape.ape(
        trajectory.PoseTrajectory3D(poses_se3=list(ref_poses), timestamps=t),
        trajectory.PoseTrajectory3D(poses_se3=list(est_poses), timestamps=t),
        evo_metrics.PoseRelation.translation_part,
        align=True,
        correct_scale=False,
    )
    assert ours.rmse_m == pytest.approx(res.stats["rmse"], abs=1e-6)


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda r: r * 1.05, r"pose 5 has a non-orthonormal rotation block .*tolerance 0\.01"),
        (lambda r: r @ np.diag([1.0, 1.0, -1.0]), "pose 5 has a reflection"),
    ],
)
def test_rotation_blocks_beyond_rounding_are_refused(damage, match):
    ref = _poses(_circle(20))
    bad = ref.copy()
    bad[5, :3, :3] = damage(bad[5, :3, :3])
    with pytest.raises(DataError, match=match):
        ate(bad, ref)


def test_ate_split_along_and_across_the_reference_heading():
    ref = _circle(n=120)
    rng = np.random.default_rng(3)
    along, across = rng.normal(0.2, 0.05, len(ref)), rng.normal(-0.1, 0.02, len(ref))
    c, s = np.cos(ref[:, 2]), np.sin(ref[:, 2])
    est = ref.copy()
    est[:, 0] += c * along - s * across
    est[:, 1] += s * along + c * across
    res = ate(est, ref, align="none")
    np.testing.assert_allclose(res.along_errors_m, along, atol=1e-12)
    np.testing.assert_allclose(res.cross_errors_m, across, atol=1e-12)
    assert res.along_rmse_m**2 + res.cross_rmse_m**2 == pytest.approx(res.rmse_m**2)
    # on a trajectory with one heading, alignment takes out the constant part of either
    straight = np.column_stack([np.arange(50.0), np.zeros(50), np.zeros(50)])
    ahead = straight + np.array([0.3, 0.0, 0.0])
    assert ate(ahead, straight).along_rmse_m < 1e-9
    assert ate(ahead, straight, align="none").along_rmse_m == pytest.approx(0.3)


def _braking(t_s):
    """x(t) of a car braking from 8 m/s at 1 m/s^2, then standing, heading turning slowly."""
    v0, a = 8.0, 1.0
    x = np.where(t_s < v0 / a, v0 * t_s - 0.5 * a * t_s**2, v0**2 / (2 * a))
    return np.column_stack([x, 0.004 * x**2, 0.01 * x])


def test_clock_offset_of_an_estimate_stamped_early_is_found():
    t_us = 1_700_000_000_000_000 + np.arange(0, 12_000_000, 75_000, dtype=np.int64)
    t_s = (t_us - t_us[0]) * 1e-6
    ref = _braking(t_s)
    est = _braking(t_s + 0.035)  # the car 35 ms after each stamp
    res = ate_clock_offsets(est, t_us, ref, t_us, max_offset_s=0.1, step_s=0.005)
    assert res.best_offset_s == pytest.approx(0.035)
    assert res.best_rmse_m < 2e-3  # the reference interpolated linearly between 75 ms poses
    assert res.rmse_at_zero_m > 0.05
    assert len(res.offsets_s) == 41 and res.offsets_s[20] == 0.0
    # the poses whose shifted time the reference does not cover are left out at every shift
    assert res.count == len(t_us) - 4
    late = ate_clock_offsets(_braking(t_s - 0.06), t_us, ref, t_us)
    assert late.best_offset_s == pytest.approx(-0.06)


def test_clock_offsets_arguments():
    t = np.arange(3, dtype=np.int64) * 100_000
    ref = _braking(t * 1e-6)
    assert ate_clock_offsets(ref, t, ref, t, max_offset_s=0.15) is None  # nothing left to compare
    with pytest.raises(DataError, match="step_s > 0"):
        ate_clock_offsets(ref, t, ref, t, step_s=0.0)
    with pytest.raises(DataError, match="reference: timestamp"):
        ate_clock_offsets(ref, t, ref, t * 1e-6)
    with pytest.raises(DataError, match="strictly increasing"):
        ate_clock_offsets(ref, t, ref, t[::-1])


def _turning_drive(n=400):
    """A drive along a straight, a 90 deg left turn, a straight and a 60 deg right turn."""
    rate = np.zeros(n)
    rate[50:150] = np.pi / 2 / 100
    rate[250:330] = -np.pi / 3 / 80
    yaw = np.concatenate([[0.0], np.cumsum(rate[:-1])])
    xy = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]), axis=0)
    return np.column_stack([xy, yaw])


def test_turn_scale_reads_a_turn_rate_scale_error_and_ignores_a_heading_offset():
    ref = _turning_drive()
    est = ref.copy()
    est[:, 2] = 0.3 + 1.007 * ref[:, 2]  # turns 0.7 % too far, from a heading 0.3 rad off
    res = turn_scale(est, ref)
    assert res.scale == pytest.approx(1.007, abs=1e-12)
    assert res.turned_deg == pytest.approx(150.0, abs=1e-9)
    assert res.num_steps == len(ref) - 1
    noisy = est.copy()
    noisy[:, 2] += np.random.default_rng(3).normal(0, 0.002, len(ref))
    assert turn_scale(noisy, ref).scale == pytest.approx(1.007, abs=0.003)
    # turns too little on a drive of the other handedness too
    mirrored = ref * [1, -1, -1]
    est_m = mirrored.copy()
    est_m[:, 2] = 0.99 * mirrored[:, 2]
    assert turn_scale(est_m, mirrored).scale == pytest.approx(0.99, abs=1e-12)


def test_turn_scale_is_nan_on_a_straight_drive_and_pools_steps_by_their_turn():
    ref = _turning_drive()
    straight = ref[:50]
    res = turn_scale(straight + np.array([0, 0, 0.01]), straight)
    assert np.isnan(res.scale) and res.turned_deg == 0.0
    assert np.isnan(turn_scale(ref, ref, min_turn_deg=151.0).scale)
    assert turn_scale(ref, ref, min_turn_deg=149.0).scale == 1.0
    far = ref.copy()
    far[:, 2] = 1.01 * ref[:, 2]
    a, b = turn_scale(far, ref), turn_scale(ref, ref)
    pooled = turn_scale_of_steps(
        np.concatenate([a.steps[0], b.steps[0]]), np.concatenate([a.steps[1], b.steps[1]])
    )
    assert pooled.scale == pytest.approx(1.005, abs=1e-12)  # two drives with the same turns
    with pytest.raises(DataError, match="truth steps against"):
        turn_scale_of_steps(np.zeros(3), np.zeros(2))
    with pytest.raises(DataError, match="minimum turn"):
        turn_scale_of_steps(np.zeros(3), np.zeros(3), min_turn_deg=-1.0)
