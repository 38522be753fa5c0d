import itertools

import numpy as np
import pytest
import torch

from radarslam.errors import CheckpointError, DataError
from radarslam.nuscenes.reader import NuScenesRadar
from radarslam.place_recognition.config import PlaceRecognizerConfig
from radarslam.place_recognition.recognizer import (
    PlaceCandidate,
    PlaceRecognizer,
    iter_scene_sequences,
)


class RandomProjection(torch.nn.Module):
    """(B, L, C, H, W) -> (B, 32): a fixed random projection of the last frame's image, pooled
    4x4 so that nearby places stay close; L2-normalised."""

    def __init__(self, seed=0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.register_buffer("w", torch.randn(50 * 50, 32, generator=g))

    def forward(self, x):
        img = x[:, -1, 0]
        pooled = torch.nn.functional.avg_pool2d(img[:, None], 4)[:, 0].flatten(1)
        return torch.nn.functional.normalize(pooled @ self.w, dim=1)


@pytest.fixture(scope="module")
def clouds(mini_dataroot):
    rec = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=2))
    reader = NuScenesRadar(mini_dataroot, "v1.0-mini")
    return list(iter_scene_sequences(rec, reader, "scene-0002"))


def test_add_query_purity_and_persistence(clouds, tmp_path):
    rec = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=2))
    assert rec.query(clouds[0][1]) == []  # empty database
    for token, seq in clouds[:4]:
        assert len(seq) <= 2
        rec.add(seq, key=token)
    assert len(rec) == 4
    token, seq = clouds[2]
    before = rec._index.matrix.copy()
    res = rec.query(seq, k=3)
    assert len(rec) == 4 and np.array_equal(rec._index.matrix, before)  # query never inserts
    assert all(isinstance(c, PlaceCandidate) for c in res)
    assert res[0].key == token and res[0].descriptor_distance < 1e-5 and res[0].rank == 0
    assert [c.rank for c in res] == [0, 1, 2]
    assert all(a.score <= b.score for a, b in itertools.pairwise(res))
    assert rec.query(seq, k=3) == res  # repeatable
    assert token not in [c.key for c in rec.query(seq, k=3, exclude={token})]
    with pytest.raises(DataError, match="already"):
        rec.add(seq, key=token)
    path = rec.save(tmp_path / "db.npz")
    loaded = PlaceRecognizer.load(path, model=RandomProjection())
    assert loaded.keys == rec.keys and loaded.query(seq, k=3) == res
    # an unseen frame: candidates exist but none matches exactly
    nxt = rec.query(clouds[4][1], k=10)
    assert len(nxt) == 4 and nxt[0].descriptor_distance > 1e-3


def test_rerank_and_bad_inputs(clouds, tmp_path):
    cfg = PlaceRecognizerConfig(seq_len=2, rerank={"enabled": False})
    rec = PlaceRecognizer(model=RandomProjection(), config=cfg)
    for token, seq in clouds[:3]:
        rec.add(seq, key=token)
    res = rec.query(clouds[1][1], k=2)
    assert all(c.score == c.descriptor_distance for c in res)
    with pytest.raises(DataError, match="AccumulatedCloud"):
        rec.add(np.zeros((200, 200)), key="x")
    import dataclasses

    ego_cloud = dataclasses.replace(clouds[0][1][-1], ref_channel=None)
    with pytest.raises(DataError, match="ego"):
        rec.query(ego_cloud)
    with pytest.raises(CheckpointError, match="not found"):
        PlaceRecognizer(checkpoint=tmp_path / "missing.pt")
    with pytest.raises(DataError, match="not a place database"):
        (tmp_path / "junk.npz").write_bytes(b"junk")
        PlaceRecognizer.load(tmp_path / "junk.npz", model=RandomProjection())


def test_temporal_padding(clouds):
    rec = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=3))
    d1, rcs = rec.describe(clouds[0][1][-1])  # a single cloud is padded to 3 frames
    d2, _ = rec.describe([clouds[0][1][-1]] * 3)
    np.testing.assert_allclose(d1, d2)
    assert rcs.min() == 0.0 and rcs.max() == 1.0


def test_frame_feature_cache_matches_full_model(clouds):
    """With a split model (encode_frames + frame_codes + aggregate_codes), cached per-frame
    codes give the descriptor of the model's forward on the whole sequence."""
    from radarslam.place_recognition.models import build_model, load_model_config

    torch.manual_seed(0)
    cfg = load_model_config("compact_se_te").model_copy(update={"seq_len": 2})
    model = build_model(cfg).eval()
    rec = PlaceRecognizer(model=model, config=PlaceRecognizerConfig())
    assert rec.seq_len == 2
    seq = clouds[3][1]
    d_first, _ = rec.describe(seq)
    assert len(rec._feature_cache) == 2
    d_cached, _ = rec.describe(seq)  # both frames from the cache
    frames = [rec._frame(c) for c in seq]
    x = torch.from_numpy(np.stack([rec._image(f) for f in frames])[None])
    with torch.no_grad():
        full = model(x).numpy()[0]
    np.testing.assert_allclose(d_first, full, atol=1e-5)
    np.testing.assert_array_equal(d_first, d_cached)


# ---- bad databases, checkpoints and devices ---------------------------------------------------
def _saved_db(tmp_path, clouds, name="db.npz"):
    rec = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=2))
    for token, seq in clouds[:3]:
        rec.add(seq, key=token)
    return rec.save(tmp_path / name)


def _rewrite(src, dst, meta_update=None, drop=(), **arrays):
    import json

    with np.load(src) as z:
        data = {k: z[k] for k in z.files}
    if meta_update is not None:
        meta = json.loads(str(data["meta_json"]))
        meta = meta_update(meta)
        data["meta_json"] = np.array(json.dumps(meta))
    data.update(arrays)
    for k in drop:
        data.pop(k)
    np.savez(dst, **data)
    return dst


def test_bad_databases_are_one_line_data_errors(clouds, tmp_path):
    good = _saved_db(tmp_path, clouds)
    with np.load(good) as z:
        desc, offsets = z["descriptors"], z["offsets"]
    blob = good.read_bytes()
    cases = {
        "trunc.npz": (None, r"trunc\.npz: not a place database \(damaged or truncated"),
        "empty.npz": (None, r"empty\.npz: not a place database \(empty file\)"),
        "list.npz": ({"meta": lambda m: [m]}, r"list\.npz: metadata must be a JSON object"),
        "nocfg.npz": (
            {"meta": lambda m: {k: v for k, v in m.items() if k != "config"}},
            r"nocfg\.npz: metadata lacks \['config'\]",
        ),
        "norcs.npz": ({"drop": ("rcs01",)}, r"norcs\.npz: missing array\(s\) \['rcs01'\]"),
        "offsets.npz": (
            {"offsets": np.concatenate([offsets[:-1], [offsets[-1] + 5]])},
            r"offsets\.npz: offsets must .* end at the number of RCS values",
        ),
        "decreasing.npz": (
            {"offsets": np.array([0, offsets[2], offsets[1], offsets[3]])},
            r"decreasing\.npz: offsets must start at 0, never decrease",
        ),
        "nan.npz": (
            {"descriptors": np.where(np.arange(desc.size).reshape(desc.shape) == 3, np.nan, desc)},
            r"nan\.npz: descriptors contain NaN",
        ),
        "fewdesc.npz": ({"descriptors": desc[:2]}, r"fewdesc\.npz: 3 keys, 2 descriptors"),
        "dbsm.npz": (
            {"rcs01": np.linspace(-10.0, 30.0, offsets[-1]).astype(np.float32)},
            r"dbsm\.npz: rcs01 must lie in \[0, 1\] \(normalised RCS\), got values in \[-10, 30\]",
        ),
    }
    for name, (spec, message) in cases.items():
        path = tmp_path / name
        if name == "trunc.npz":
            path.write_bytes(blob[: len(blob) // 2])
        elif name == "empty.npz":
            path.write_bytes(b"")
        else:
            spec = dict(spec)
            meta = spec.pop("meta", None)
            drop = spec.pop("drop", ())
            _rewrite(good, path, meta, drop, **spec)
        with pytest.raises(DataError, match=message):
            PlaceRecognizer.load(path, model=RandomProjection())
    # a directory is not a database file to write
    rec = PlaceRecognizer.load(good, model=RandomProjection())
    from radarslam.errors import ConfigError

    with pytest.raises(ConfigError, match="output file is an existing directory"):
        rec.save(tmp_path)


@pytest.fixture(scope="module")
def two_checkpoints(tmp_path_factory):
    """Two compact SE+TE checkpoints (seq_len 2) with the same architecture, other weights."""
    from radarslam.place_recognition.checkpoint import save_checkpoint
    from radarslam.place_recognition.models import build_model, load_model_config

    cfg = load_model_config("compact_se_te").model_copy(update={"seq_len": 2})
    out = tmp_path_factory.mktemp("ckpts")
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        paths.append(save_checkpoint(out / f"ck{seed}.pt", build_model(cfg), cfg))
    return paths, cfg.output_dim()


def test_database_records_its_checkpoint(two_checkpoints, tmp_path, monkeypatch):
    import json
    import shutil

    (a, b), dim = two_checkpoints
    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(a, work / "a.pt")
    monkeypatch.chdir(work)
    rec = PlaceRecognizer(checkpoint="a.pt")  # a relative path, as typed on a command line
    rng = np.random.default_rng(0)
    for i in range(3):
        rec.add_descriptor(rng.normal(size=dim), rng.random(20), key=f"k{i}")
    db = rec.save(tmp_path / "db.npz")
    with np.load(db) as z:
        meta = json.loads(str(z["meta_json"]))
    assert meta["checkpoint"] == str((work / "a.pt").resolve())
    assert len(meta["checkpoint_digest"]) == 64
    monkeypatch.chdir(tmp_path)
    assert PlaceRecognizer.load(db).keys == ["k0", "k1", "k2"]  # from any working directory
    # another checkpoint of the same architecture: descriptors are not comparable
    with pytest.raises(CheckpointError, match=r"db\.npz: built with checkpoint .*a\.pt .*ck1\.pt"):
        PlaceRecognizer.load(db, checkpoint=b)
    # a database written before digests were recorded still loads with any checkpoint
    old = _rewrite(db, tmp_path / "old.npz",
                   lambda m: {k: v for k, v in m.items() if k != "checkpoint_digest"})  # fmt: skip
    assert len(PlaceRecognizer.load(old, checkpoint=b)) == 3
    # the recorded checkpoint is gone
    (work / "a.pt").unlink()
    with pytest.raises(CheckpointError, match=r"db\.npz: recorded checkpoint .*a\.pt not found"):
        PlaceRecognizer.load(db)


def test_database_of_another_dimension_is_refused_up_front(clouds, two_checkpoints, tmp_path):
    (a, _), dim = two_checkpoints
    db = _saved_db(tmp_path, clouds)  # 32-D descriptors of the random projection
    with pytest.raises(CheckpointError, match=rf"db\.npz: holds 32-D .*ck0\.pt makes {dim}-D"):
        PlaceRecognizer.load(db, checkpoint=a)


def test_device_is_validated_before_loading(tmp_path):
    from radarslam.config import load_config
    from radarslam.errors import ConfigError

    with pytest.raises(ConfigError, match="device must be auto, cpu, cuda or cuda:N, got 'gpu'"):
        load_config(PlaceRecognizerConfig, None, ["device=gpu"])
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="'cuda' requested but CUDA is not available"):
            PlaceRecognizer(checkpoint=tmp_path / "never_read.pt",
                            config=PlaceRecognizerConfig(device="cuda"))  # fmt: skip
    rec = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(device="auto"))
    assert rec.device.type in ("cpu", "cuda")


# ---- input checks of the database API ---------------------------------------------------------
def _small_db(clouds, n=4, **cfg):
    rec = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=2, **cfg))
    for token, seq in clouds[:n]:
        rec.add(seq, key=token)
    return rec


def test_feature_cache_never_returns_features_of_changed_points(clouds):
    """The per-frame cache is keyed by a fingerprint of the points: a cloud changed in place, or
    another cloud under the same token with as many points, is encoded again; the same content
    (a new cloud object over the same points, as the SLAM pipeline makes) is a cache hit."""
    import dataclasses

    from radarslam.place_recognition.models import build_model, load_model_config

    torch.manual_seed(0)
    cfg = load_model_config("compact_se_te").model_copy(update={"seq_len": 2})
    model = build_model(cfg).eval()
    rec = PlaceRecognizer(model=model, config=PlaceRecognizerConfig())
    fresh = PlaceRecognizer(model=model, config=PlaceRecognizerConfig())
    encoded = []
    encode = rec._encode
    rec._encode = lambda images: encoded.append(len(images)) or encode(images)
    old, cloud = (dataclasses.replace(c, points=c.points.copy()) for c in clouds[3][1])
    d0, _ = rec.describe([old, cloud])
    assert len(encoded) == 2
    same = dataclasses.replace(cloud, points=cloud.points)  # new object, same content
    np.testing.assert_array_equal(rec.describe([old, same])[0], d0)
    assert len(encoded) == 2, "same content: both frames from the cache"
    cloud.points["x"] += 30.0  # changed in place after it was described
    d1, _ = rec.describe([old, cloud])
    assert len(encoded) == 3 and not np.array_equal(d1, d0)
    np.testing.assert_array_equal(d1, fresh.describe([old, cloud])[0])
    moved = cloud.points.copy()
    moved["y"] -= 12.0  # same token, timestamp and point count, other points
    other = dataclasses.replace(cloud, points=moved)
    d2, _ = rec.describe([old, other])
    np.testing.assert_array_equal(d2, fresh.describe([old, other])[0])
    assert not np.array_equal(d2, d1)


def test_exclude_takes_one_key_or_a_collection(clouds):
    from radarslam.io.loops import NodeKey

    rec = _small_db(clouds)
    seq = clouds[1][1]
    best = rec.query(seq, k=1)[0].key
    assert isinstance(best, str)
    for one in (best, [best], {best}, (best,)):  # a str is one key, not its characters
        assert best not in [c.key for c in rec.query(seq, k=4, exclude=one)]
    desc, rcs = rec.describe(seq)
    tup = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=2))
    tup.add_descriptor(desc, rcs, ("scene-1", 3))
    tup.add_descriptor(desc + 1.0, rcs, "scene-1")
    tup.add_descriptor(desc + 2.0, rcs, NodeKey("scene-1", 3))
    keys = lambda ex: [c.key for c in tup.query_descriptor(desc, rcs, k=3, exclude=ex)]  # noqa: E731
    assert keys(("scene-1", 3)) == ["scene-1", NodeKey("scene-1", 3)]  # a tuple key: one key
    assert keys(NodeKey("scene-1", 3)) == [("scene-1", 3), "scene-1"]
    assert keys(("scene-1", "x")) == [("scene-1", 3), NodeKey("scene-1", 3)]  # not a key: keys
    with pytest.raises(DataError, match=r"exclude: key \[1\] is not hashable"):
        tup.query_descriptor(desc, rcs, exclude=[[1]])


def test_rcs_values_must_be_normalised(clouds, tmp_path):
    import dataclasses

    rec = _small_db(clouds)
    desc, rcs = rec.describe(clouds[1][1])
    assert rcs.min() >= 0.0 and rcs.max() <= 1.0  # what describe makes always passes
    before = rec.query_descriptor(desc, rcs, k=3)
    cases = [
        (rcs * 40.0 - 10.0, r"rcs01 must lie in \[0, 1\] \(normalised RCS\), got .* \[-10, 30\]"),
        (np.full_like(rcs, np.nan), "rcs01 contains NaN or infinity"),
        (rcs[None], r"rcs01 must be a 1-D number array .*got shape \(1, \d+\)"),
        (None, r"rcs01 must be a 1-D number array .*got shape \(\)"),
    ]  # fmt: skip
    for bad, message in cases:
        with pytest.raises(DataError, match=message):
            rec.query_descriptor(desc, bad)
        with pytest.raises(DataError, match=message):
            rec.add_descriptor(desc, bad, "bad")
    assert len(rec) == 4 and len(rec._index) == 4 and "bad" not in rec.keys
    assert rec.query_descriptor(desc, rcs, k=3) == before
    # a key frame without points: empty RCS values are legal, to query and to add
    cloud = clouds[1][1][-1]
    empty = dataclasses.replace(cloud, points=cloud.points[:0], sample_token="")
    d_empty, r_empty = rec.describe(empty)
    assert r_empty.shape == (0,)
    assert len(rec.query_descriptor(d_empty, r_empty, k=2)) == 2
    rec.add(empty, key="empty")
    loaded = PlaceRecognizer.load(rec.save(tmp_path / "db.npz"), model=RandomProjection())
    assert loaded.keys == rec.keys
    # the caller's array is copied: changing it later changes nothing stored
    mine = rcs.copy()
    rec.add_descriptor(desc, mine, "mine")
    mine[:] = 5.0
    again = PlaceRecognizer.load(rec.save(tmp_path / "db2.npz"), model=RandomProjection())
    np.testing.assert_array_equal(again._rcs[-1], rcs)


def test_k_descriptor_and_key_checks(clouds, tmp_path):
    from radarslam.io.loops import NodeKey

    rec = _small_db(clouds)
    desc, rcs = rec.describe(clouds[1][1])
    for k in (2.5, "3", True, 0, -1, None):
        with pytest.raises(DataError, match=rf"k must be an integer >= 1, got {k!r}"):
            rec.query_descriptor(desc, rcs, k=k)
    assert len(rec.query_descriptor(desc, rcs, k=np.int64(2))) == 2
    with pytest.raises(
        DataError, match=r"expected one descriptor of 32 values, got shape \(2, 32\)"
    ):
        rec.query_descriptor(np.stack([desc, desc]), rcs)
    with pytest.raises(DataError, match="expected one descriptor of 32 values, got 10"):
        rec.add_descriptor(desc[:10], rcs, "short")
    assert len(rec.query_descriptor(desc[None], rcs, k=1)) == 1  # (1, D) is one descriptor
    # an empty database checks the descriptor too
    empty = PlaceRecognizer(model=RandomProjection(), config=PlaceRecognizerConfig(seq_len=2))
    assert empty.query_descriptor(desc, rcs) == []
    with pytest.raises(DataError, match="descriptor contains NaN"):
        empty.query_descriptor(np.full_like(desc, np.nan), rcs)
    with pytest.raises(DataError, match=r"got shape \(2, 32\)"):
        empty.query_descriptor(np.stack([desc, desc]), rcs)
    with pytest.raises(DataError, match=r"k must be an integer >= 1, got 2\.5"):
        empty.query_descriptor(desc, rcs, k=2.5)
    # keys: hashable, and what save() writes must come back equal
    cases = [
        (["a"], r"place key \['a'\] is not hashable \(list\)"),
        (np.int64(5), r"place key np\.int64\(5\) \(int64\) cannot be saved"),
        (float("nan"), r"place key nan \(float\) cannot be saved"),
        (("a", ("b",)), r"place key \('a', \('b',\)\) \(tuple\) cannot be saved"),
    ]
    for key, message in cases:
        with pytest.raises(DataError, match=message):
            rec.add_descriptor(desc, rcs, key)
    assert len(rec) == 4 and len(rec._index) == 4
    for key in (5, 2.5, None, ("scene", 1)):
        rec.add_descriptor(desc, rcs, key)
    loaded = PlaceRecognizer.load(rec.save(tmp_path / "db.npz"), model=RandomProjection())
    assert loaded.keys == rec.keys
    # in-memory keys such as the SLAM pipeline's NodeKey: added, but save names them
    rec.add_descriptor(desc, rcs, NodeKey("scene-1", 3))
    with pytest.raises(DataError, match=r"db3\.npz: place key NodeKey\(.*\) cannot be saved"):
        rec.save(tmp_path / "db3.npz")
    assert not (tmp_path / "db3.npz").exists()
