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
