from pathlib import Path

import numpy as np
import pytest
from pr_synthetic import synthetic_frames

from radarslam.errors import ConfigError, DataError
from radarslam.place_recognition.config import EvalConfig, RerankConfig
from radarslam.place_recognition.dataset import PreparedData, load_prepared, make_split
from radarslam.place_recognition.evaluate import (
    Ranking,
    apply_rcshr,
    baseline_ranking_fn,
    descriptor_ranking,
    descriptor_ranking_fn,
    evaluate_method,
    evaluate_ranking,
    evaluate_turned,
    tune_rcshr,
    write_results,
)


def synthetic_data(seed=0):
    pos, t, names = synthetic_frames()
    from radarslam.place_recognition.config import SplitConfig

    s = make_split(pos, t, names, SplitConfig(split_day=5))
    rng = np.random.default_rng(seed)
    n = len(pos)
    return PreparedData(
        root=Path("mem"),
        images=np.zeros((n, 4, 4), np.uint8),
        positions_xy=pos,
        yaw_rad=np.zeros(n),
        timestamps_us=t,
        scene_names=names,
        sample_tokens=np.array([f"t{i}" for i in range(n)]),
        rcs=[rng.random(50).astype(np.float32) for _ in range(n)],
        sequences=s.sequences,
        splits=s.splits,
    )


def test_oracle_and_random_descriptors():
    data = synthetic_data()
    cfg = EvalConfig()
    # descriptors = true positions: the nearest DB frame is always a positive
    oracle = descriptor_ranking_fn(data, lambda f: data.positions_xy[f], cfg)
    res = evaluate_method(data, "oracle", oracle, cfg, "test")
    assert res[0].recall == {1: 1.0, 5: 1.0, 10: 1.0} and res[0].num_queries == 6
    # every accepted top-1 is right; the loosest threshold still rejects the largest score
    assert len(res[0].curve.precision) >= 1 and np.all(res[0].curve.precision == 1.0)
    assert 0 < res[0].max_f1 < 1
    # constant descriptors: ties resolve in DB order (frame 2 first), a positive for s3 queries
    # at x <= 3.5 (within 9 m of (1, 0)) only
    const = descriptor_ranking_fn(data, lambda f: np.zeros((len(f), 3)), cfg)
    r = evaluate_method(data, "const", const, cfg, "test")[0]
    q = data.splits["test"]
    expected = np.mean(np.hypot(data.positions_xy[q, 0] - 1.0, 8.5) <= 9.0)
    assert r.recall[1] == pytest.approx(expected)


def test_turned_search_counts_only_positives_driven_the_other_way():
    data = synthetic_data()
    cfg = EvalConfig()
    oracle = descriptor_ranking_fn(data, lambda f: data.positions_xy[f], cfg)
    # every DB frame driven the same way as the queries: nothing for the turned search
    assert evaluate_turned(data, "oracle", oracle, cfg, "test") is None
    db = data.splits["database"]
    data.yaw_rad[db[data.positions_xy[db, 0] >= 2.0]] = np.pi  # the far DB frames reversed
    res = evaluate_turned(data, "oracle", oracle, cfg, "test")
    queries = [q for q in data.splits["test"] if len(data.reversed_positives(q, 45.0))]
    assert res.name == "oracle turned" and res.num_queries == len(queries) == 6
    # the oracle's nearest DB frame is driven the other way for the queries from x = 2 m on
    ranking = oracle(np.array(queries), 10)
    want = np.mean(data.yaw_rad[ranking.db_frames[:, 0]] != 0)
    assert 0 < want < 1 and res.recall[1] == pytest.approx(want) and res.recall[10] == 1.0
    # a plain and a turned ranking function sharing one database cache describe the DB once
    calls = []

    def describe(frames):
        calls.append(len(frames))
        return data.positions_xy[frames]

    shared: dict = {}
    plain = descriptor_ranking_fn(data, describe, cfg, db_cache=shared)
    turned = descriptor_ranking_fn(data, describe, cfg, lambda f: -data.positions_xy[f], shared)
    plain(np.array(queries), 3)
    turned(np.array(queries), 3)
    assert calls == [len(db), len(queries)]


def test_rcshr_ranking_and_tuning():
    data = synthetic_data()
    db = data.splits["database"]
    q = data.splits["val"]
    rng = np.random.default_rng(1)
    ranking = descriptor_ranking(data, rng.normal(size=(len(db), 8)), rng.normal(size=(len(q), 8)),
                                 q, k=6)  # fmt: skip
    same = apply_rcshr(data, ranking, RerankConfig(alpha=0.0))
    np.testing.assert_array_equal(same.db_frames, ranking.db_frames)
    np.testing.assert_allclose(same.scores, ranking.scores)
    # give the query's RCS to DB frame 32 (far away): with alpha = 1 it ranks first
    data.rcs[32] = data.rcs[q[0]].copy()
    rr = apply_rcshr(data, ranking, RerankConfig(alpha=1.0))
    assert rr.db_frames[0, 0] == 32 and rr.scores[0, 0] == pytest.approx(0.0, abs=1e-9)
    tuned = tune_rcshr(data, ranking, [RerankConfig(alpha=a) for a in (0.0, 1.0)])
    assert tuned.best_recall_at_1 >= tuned.baseline_recall_at_1
    assert len(tuned.trials) == 2


def test_results_files_and_errors(tmp_path):
    data = synthetic_data()
    cfg = EvalConfig()
    fn = descriptor_ranking_fn(data, lambda f: data.positions_xy[f] / 10.0, cfg)
    results = evaluate_method(data, "oracle", fn, cfg, "test", rerank_cfg=RerankConfig(),
                              tune_on_val=True)  # fmt: skip
    assert [r.name for r in results] == ["oracle", "oracle+RCSHR"]
    paths = write_results(results, tmp_path, "t")
    assert "| oracle+RCSHR | test | 6 |" in paths["md"].read_text()
    assert paths["png"].stat().st_size > 1000
    with pytest.raises(DataError, match="unknown split"):
        evaluate_method(data, "x", fn, cfg, "nope")
    bad = Ranking(np.array([38]), np.zeros((1, 0), np.int64), np.zeros((1, 0)))
    with pytest.raises(DataError):
        evaluate_ranking(data, bad, cfg, "bad")
    with pytest.raises(ConfigError, match="baseline"):
        baseline_ranking_fn(data, "netvlad", cfg)


def test_baselines_on_prepared_mini(mini_prepared):
    data = load_prepared(mini_prepared)
    cfg = EvalConfig()
    for name in ("scancontext", "m2dp"):
        label, fn = baseline_ranking_fn(data, name, cfg)
        r = evaluate_method(data, label, fn, cfg, "test")[0]
        assert 0.0 <= r.recall[1] <= r.recall[5] <= 1.0
        again = evaluate_method(data, label, fn, cfg, "test")[0]
        assert again.recall == r.recall  # deterministic


def test_only_held_out_splits_are_evaluated():
    data = synthetic_data()
    cfg = EvalConfig()
    fn = descriptor_ranking_fn(data, lambda f: data.positions_xy[f], cfg)
    for split in ("database", "train"):
        with pytest.raises(ConfigError, match=f"split '{split}' cannot be evaluated"):
            evaluate_method(data, "oracle", fn, cfg, split)
        with pytest.raises(ConfigError, match=f"split '{split}' cannot be evaluated"):
            evaluate_turned(data, "oracle", fn, cfg, split)
    assert evaluate_method(data, "oracle", fn, cfg, "val")[0].split == "val"
