import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.eval.loops import (
    LoopEvalConfig,
    SessionGroundTruth,
    evaluate_loops,
    gt_revisit_queries,
)
from radarslam.geometry import invert, se2_to_matrix
from radarslam.io.loops import LoopCandidate, NodeKey
from radarslam.slam.synthetic_graph import multilap_circuit


def _loop(s, j, i, ts, rel, accepted=True):
    return LoopCandidate(
        NodeKey(s, j),
        NodeKey(s, i),
        int(ts[j]),
        int(ts[i]),
        0.1,
        accepted,
        "ok" if accepted else "fitness",
        rel,
    )


def test_hand_computed_straight_line_revisit():
    # out and back along x: frames 0..10 go out, 11..20 come back (1 s apart)
    x = np.concatenate([np.arange(11.0), np.arange(9.0, -1.0, -1.0)])
    poses = np.column_stack([x, np.zeros_like(x), np.where(np.arange(21) <= 10, 0.0, np.pi)])
    ts = np.arange(21, dtype=np.int64) * 1_000_000
    gt = {"s": SessionGroundTruth(ts, poses)}
    cfg = LoopEvalConfig(revisit_radius_m=0.5, exclude_recent_s=3.0)
    # frame 11 (x=9) is 2 s after frame 10 (x=10), 3 s after 9 (x=9): frames >= 12 revisit
    # frame 11 revisits frame 9 (x=9, t=9 s; 2 s ago: excluded). frames 12..20 revisit.
    assert gt_revisit_queries(gt, cfg) == {NodeKey("s", k) for k in range(12, 21)}
    truth = se2_to_matrix(0.0, 0.0, np.pi)  # frame 15 (x=5, heading pi) seen from frame 5
    loops = [
        _loop("s", 15, 5, ts, truth),
        _loop("s", 16, 4, ts, se2_to_matrix(3.0, 0.0, np.pi)),  # 3 m off: wrong
        _loop("s", 17, 3, ts, truth, accepted=False),
    ]
    m = evaluate_loops(loops, gt, cfg)
    assert (m.num_candidates, m.num_accepted, m.num_correct) == (3, 2, 1)
    assert m.precision == 0.5
    assert m.num_revisit_queries == 9 and m.num_recalled_queries == 1
    assert m.recall == pytest.approx(1 / 9)
    assert m.judgements[1].translation_error_m == pytest.approx(3.0)


def test_multilap_true_and_false_loops():
    sg = multilap_circuit(num_laps=3, poses_per_lap=100, seed=2, false_loop_fraction=0.25)
    ts = np.arange(len(sg.gt), dtype=np.int64) * 100_000  # 10 Hz: one lap = 10 s
    gt = {"run": SessionGroundTruth(ts, sg.gt)}
    loops = [_loop("run", lp.j, lp.i, ts, lp.i_from_j) for lp in sg.loops]
    m = evaluate_loops(loops, gt, LoopEvalConfig(revisit_radius_m=1.0, exclude_recent_s=5.0))
    n_true = sum(lp.true for lp in sg.loops)
    assert m.num_correct == n_true
    assert m.precision == pytest.approx(n_true / len(sg.loops))
    # laps 2 and 3 revisit lap 1 (200 queries); each true loop recalls one of them
    assert m.num_revisit_queries == 200
    assert m.recall == pytest.approx(n_true / 200)


def test_second_session_revisits_the_first_and_errors():
    a = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    ts_a = np.arange(10, dtype=np.int64) * 1_000_000
    ts_b = ts_a + 100_000_000
    shifted = a + np.array([0.2, 0.0, 0.0])
    gt = {"b": SessionGroundTruth(ts_b, shifted), "a": SessionGroundTruth(ts_a, a)}
    cfg = LoopEvalConfig(revisit_radius_m=0.5, exclude_recent_s=0.0)
    assert gt_revisit_queries(gt, cfg) == {NodeKey("b", k) for k in range(10)}
    # processed the other way round, a revisits b
    assert gt_revisit_queries(gt, cfg, ["b", "a"]) == {NodeKey("a", k) for k in range(10)}
    bad = LoopCandidate(NodeKey("b", 1), NodeKey("a", 1), 123, int(ts_a[1]), 0.1, True, "ok")
    with pytest.raises(DataError, match="not in the ground truth"):
        evaluate_loops([bad], gt, cfg)
    loop = LoopCandidate(NodeKey("b", 1), NodeKey("c", 1), int(ts_b[1]), 0, 0.1, True, "ok")
    with pytest.raises(DataError, match="no ground truth for session 'c'"):
        evaluate_loops([loop], gt, cfg)
    rel = invert(se2_to_matrix(1.0, 0, 0)) @ se2_to_matrix(1.2, 0, 0)
    ok = LoopCandidate(
        NodeKey("b", 1), NodeKey("a", 1), int(ts_b[1]), int(ts_a[1]), 0.1, True, "ok", rel
    )
    m = evaluate_loops([ok], gt, cfg)
    assert m.precision == 1.0 and m.recall == pytest.approx(0.1)


def test_a_session_that_continues_a_drive_is_one_pass_with_it():
    """A drive cut into two sessions, standing still across the cut: the second session's first
    key frames are where the first one ended seconds ago, the recent past of the same pass, not
    a revisit; once they are ``exclude_recent_s`` older they are."""
    xy = np.zeros((10, 3))  # a car at a red light, both sessions at x = 0
    ts_a = np.arange(10, dtype=np.int64) * 1_000_000
    ts_b = ts_a + 10_000_000
    gt = {"a": SessionGroundTruth(ts_a, xy), "b": SessionGroundTruth(ts_b, xy)}
    cfg = LoopEvalConfig(revisit_radius_m=1.0, exclude_recent_s=15.0)
    # two sessions: every key frame of b revisits a
    assert gt_revisit_queries(gt, cfg, ["a", "b"]) == {NodeKey("b", k) for k in range(10)}
    # one pass: only key frames more than 15 s after the pass's first frames revisit them
    one = gt_revisit_queries(gt, cfg, ["a", "b"], continues={"b": "a"})
    assert one == {NodeKey("b", k) for k in range(6, 10)}
    # the pass reaches back through a chain of sessions
    ts_c = ts_b + 10_000_000
    gt["c"] = SessionGroundTruth(ts_c, xy)
    chain = gt_revisit_queries(gt, cfg, ["a", "b", "c"], continues={"b": "a", "c": "b"})
    assert NodeKey("c", 0) in chain and NodeKey("b", 5) not in chain
    with pytest.raises(DataError, match="loops back"):
        gt_revisit_queries(gt, cfg, ["a", "b"], continues={"b": "a", "a": "b"})
