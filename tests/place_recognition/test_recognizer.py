import itertools

import numpy as np
import pytest
import torch

from place_recognition.config import PlaceRecognizerConfig
from place_recognition.recognizer import PlaceCandidate, PlaceRecognizer, iter_scene_sequences
from radarslam.errors import CheckpointError, DataError
from radarslam.nuscenes.reader import NuScenesRadar


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
    from place_recognition.models import build_model, load_model_config

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
    from place_recognition.checkpoint import save_checkpoint
    from place_recognition.models import build_model, load_model_config

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
