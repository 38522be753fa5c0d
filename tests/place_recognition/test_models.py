"""AutoPlace networks (SE / SE+TE presets) and checkpoints."""

from __future__ import annotations

import math

import pytest
import torch
from pr_synthetic import TINY  # the tiny AutoPlace model shared by the model tests

from radarslam.config import build_config
from radarslam.errors import CheckpointError, ConfigError
from radarslam.place_recognition.checkpoint import load_model, read_checkpoint, save_checkpoint
from radarslam.place_recognition.models import (
    PRESETS,
    ModelConfig,
    build_model,
    expected_parameter_count,
    load_model_config,
    multiply_adds_per_frame,
    parameter_count,
)


def _occupancy(shape, seed=0, p=0.1):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(shape, generator=g) < p).float()


def test_presets_load_with_documented_dimensions():
    dims = {p: load_model_config(p).output_dim() for p in PRESETS}
    assert dims == {
        "paper_se": 9216,
        "paper_se_te": 4096,
        "compact_se": 2304,
        "compact_se_te": 256,
    }
    assert load_model_config("paper_se").frame_feature_dim() == 256 * 6 * 6


def test_parameter_counts_match_formula_and_paper():
    counts = {}
    for name in PRESETS:
        cfg = load_model_config(name)
        with torch.device("meta"):  # the 220 M-parameter TE is never allocated
            model = build_model(cfg)
        counts[name] = parameter_count(model)
        assert counts[name] == expected_parameter_count(cfg), name
    assert counts["paper_se"] == 2_325_568  # "about 2.33 M" (autoplace.md §3.1)
    lstm = counts["paper_se_te"] - counts["paper_se"]
    assert lstm == 4 * (9216 * 4096 + 4096 * 4096 + 2 * 4096) == 218_136_576  # "about 218 M"
    assert counts["compact_se"] == 145_936
    assert counts["compact_se_te"] == 2_769_424
    assert counts["paper_se_te"] / counts["compact_se_te"] > 75


def test_compact_preset_needs_far_fewer_multiply_adds():
    paper = multiply_adds_per_frame(load_model_config("paper_se_te"))
    compact = multiply_adds_per_frame(load_model_config("compact_se_te"))
    assert paper == 6_922_743_808  # 6.70 G in the convolutions + 0.22 G per LSTM step
    assert compact == 434_621_440
    assert paper / compact > 15


def test_paper_te_shape_on_meta_device():
    cfg = load_model_config("paper_se_te")
    with torch.device("meta"):
        model = build_model(cfg)
        out = model(torch.zeros(2, 3, 1, 200, 200))
    assert tuple(out.shape) == (2, 4096)


def test_paper_se_forward_one_frame_is_unit_9216():
    torch.manual_seed(0)
    model = build_model(load_model_config("paper_se")).eval()
    with torch.no_grad():
        out = model(_occupancy((1, 1, 1, 200, 200)))
    assert out.shape == (1, 9216)
    assert torch.linalg.norm(out, dim=1).item() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("name", ["compact_se", "compact_se_te"])
def test_compact_forward_shape_and_norm(name):
    torch.manual_seed(0)
    cfg = load_model_config(name)
    model = build_model(cfg).eval()
    with torch.no_grad():
        out = model(_occupancy((2, cfg.seq_len, 1, 200, 200), seed=1))
    assert out.shape == (2, cfg.output_dim())
    assert torch.allclose(torch.linalg.norm(out, dim=1), torch.ones(2), atol=1e-5)
    assert not torch.allclose(out[0], out[1])


def test_unique_frame_forward_equals_sequence_forward():
    torch.manual_seed(0)
    model = build_model(TINY).eval()
    frames = _occupancy((5, 1, 32, 32), seed=2)
    seq_index = torch.tensor([[0, 1, 2], [1, 2, 3], [2, 3, 4], [4, 4, 4]])
    with torch.no_grad():
        a = model(frames, seq_index)
        b = model(frames[seq_index])
    assert torch.allclose(a, b, atol=1e-6)
    # the TE depends on the order of the frames (an LSTM, not a set function)
    with torch.no_grad():
        c = model(frames[seq_index.flip(1)])
    assert not torch.allclose(b[:3], c[:3], atol=1e-4)


def test_se_uses_the_current_frame_only():
    cfg = TINY.model_copy(update={"use_temporal": False, "seq_len": 1, "descriptor_dim": None})
    torch.manual_seed(0)
    model = build_model(ModelConfig.model_validate(cfg.model_dump())).eval()
    x = _occupancy((3, 3, 1, 32, 32), seed=3)
    with torch.no_grad():
        assert torch.allclose(model(x), model(x[:, -1:]))


def test_imagenet_normalisation_replicates_one_channel():
    torch.manual_seed(0)
    one = build_model(TINY).eval()
    three = build_model(TINY.model_copy(update={"in_channels": 3})).eval()
    three.load_state_dict(one.state_dict())
    x = _occupancy((2, 3, 1, 32, 32), seed=4)
    with torch.no_grad():
        assert torch.allclose(one(x), three(x.expand(-1, -1, 3, -1, -1)), atol=1e-6)
    # the mean/std are applied: an all-zero frame is not an all-zero network input
    with torch.no_grad():
        feats = one.encode_frames(torch.zeros(1, 1, 32, 32))
    assert torch.isfinite(feats).all() and feats.abs().sum() > 0


@pytest.mark.parametrize("temporal", [True, False])
def test_frame_codes_then_aggregate_codes_equal_aggregate(temporal):
    """The inference split (per-frame LSTM input projection, then the recurrence written out)
    gives the nn.LSTM descriptor; and a sequence's codes do not depend on its other frames."""
    cfg = TINY
    if not temporal:
        cfg = TINY.model_copy(update={"use_temporal": False, "seq_len": 1, "descriptor_dim": None})
    torch.manual_seed(0)
    model = build_model(ModelConfig.model_validate(cfg.model_dump())).eval()
    for p in model.parameters():  # trained weights are not small: exercise the gates' range
        p.data.mul_(3.0)
    frames = _occupancy((4 * cfg.seq_len, 1, 32, 32), seed=5)
    with torch.no_grad():
        feats = model.encode_frames(frames).view(4, cfg.seq_len, -1)
        codes = model.frame_codes(feats.flatten(0, 1)).view(4, cfg.seq_len, -1)
        got = model.aggregate_codes(codes)
        want = model.aggregate(feats)
        assert torch.allclose(got, want, atol=1e-5)
        assert not torch.allclose(got[0], got[1])
        single = model.frame_codes(feats[2, -1:])
    assert torch.allclose(single[0], codes[2, -1], atol=1e-5)
    assert codes.shape[-1] == (4 * cfg.descriptor_dim if temporal else feats.shape[-1])


def test_bad_inputs_raise_one_line_errors():
    model = build_model(TINY)
    with pytest.raises(ValueError, match="needs 3"):
        model(torch.zeros(1, 2, 1, 32, 32))
    with pytest.raises(ValueError, match=r"frames must be \(N, 1, 32, 32\)"):
        model(torch.zeros(1, 3, 1, 40, 40))


@pytest.mark.parametrize(
    ("update", "message"),
    [
        ({"use_temporal": False}, "seq_len=3"),
        ({"descriptor_dim": None}, "needs descriptor_dim"),
        ({"image_size_px": 8, "widths": [4, 8, 8]}, "too small"),
        ({"in_channels": 2}, "in_channels 1"),
        ({"use_temporal": False, "seq_len": 1, "descriptor_dim": 5}, "does not match"),
        ({"widths": [4, 0]}, "positive"),
        ({"dropout": 0.1}, "unknown key 'dropout'"),
    ],
)
def test_invalid_model_configs_are_config_errors(update, message):
    with pytest.raises(ConfigError, match=message):
        build_config(ModelConfig, {**TINY.model_dump(), **update}, "model.yaml")


def test_unknown_preset_is_config_error():
    with pytest.raises(ConfigError, match="unknown model preset 'nope'"):
        load_model_config("nope")


# ---------------------------------------------------------------------------------------------
# checkpoints


def test_checkpoint_round_trip_float32_and_float16(tmp_path):
    torch.manual_seed(0)
    model = build_model(TINY).eval()
    x = _occupancy((2, 3, 1, 32, 32), seed=5)
    with torch.no_grad():
        ref = model(x)
    save_checkpoint(tmp_path / "a.pt", model, TINY, meta={"val_recall": {"1": 0.5}})
    save_checkpoint(tmp_path / "h.pt", model, TINY, half=True)
    loaded, cfg, meta = load_model(tmp_path / "a.pt", expect=TINY)
    assert cfg == TINY and meta["val_recall"] == {"1": 0.5} and meta["stored_dtype"] == "float32"
    with torch.no_grad():
        assert torch.equal(loaded(x), ref)
    half, _, hmeta = load_model(tmp_path / "h.pt")
    assert hmeta["stored_dtype"] == "float16"
    assert all(p.dtype == torch.float32 for p in half.parameters())
    with torch.no_grad():
        assert torch.allclose(half(x), ref, atol=2e-3)
    assert (tmp_path / "h.pt").stat().st_size < 0.7 * (tmp_path / "a.pt").stat().st_size
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())


def test_corrupt_checkpoints_are_checkpoint_errors(tmp_path):
    model = build_model(TINY)
    path = save_checkpoint(tmp_path / "m.pt", model, TINY)
    blob = path.read_bytes()

    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CheckpointError, match=r"truncated\.pt: not a readable checkpoint"):
        load_model(truncated)

    # flip bytes inside the stored weights: the zip stays readable, the digest catches it
    state = read_checkpoint(path)
    weights = state["state_dict"]["encoder.0.weight"]
    needle = weights.numpy().tobytes()[:64]
    at = blob.find(needle)
    assert at > 0
    flipped = bytearray(blob)
    flipped[at + 8 : at + 16] = bytes(b ^ 0xFF for b in flipped[at + 8 : at + 16])
    bad = tmp_path / "flipped.pt"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match=r"flipped\.pt: .*corrupt"):
        load_model(bad)

    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match=r"garbage\.pt"):
        load_model(garbage)

    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(CheckpointError, match="not a radarslam AutoPlace checkpoint"):
        load_model(other)

    (tmp_path / "folder.pt").mkdir()
    with pytest.raises(CheckpointError, match=r"folder\.pt: is a folder, not a checkpoint file"):
        read_checkpoint(tmp_path / "folder.pt")
    with pytest.raises(CheckpointError, match=r"missing\.pt: checkpoint file does not exist"):
        load_model(tmp_path / "missing.pt")


def test_mismatched_checkpoints_are_checkpoint_errors(tmp_path):
    path = save_checkpoint(tmp_path / "m.pt", build_model(TINY), TINY)
    wider = TINY.model_copy(update={"widths": [4, 16]})
    with pytest.raises(CheckpointError, match=r"does not match the requested config \(widths"):
        load_model(path, expect=wider)
    # a different preset label alone is not a mismatch
    load_model(path, expect=TINY.model_copy(update={"preset": "renamed"}))

    # weights saved under a config they do not fit (e.g. a hand-edited file)
    forged = tmp_path / "forged.pt"
    save_checkpoint(forged, build_model(wider), TINY)
    with pytest.raises(CheckpointError, match="weights do not fit the stored config"):
        load_model(forged)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda c: c.update(state_dict=None), "'state_dict' is not a mapping of names to tensors"),
        (lambda c: c.update(state_dict="nope"), "'state_dict' is not a mapping"),
        (lambda c: c["state_dict"].update({"encoder.0.weight": "x"}), "'state_dict' is not a"),
        (lambda c: c.update(dtype="float99"), "stored weight dtype 'float99' is not float32"),
    ],
)
def test_a_hand_edited_payload_is_a_checkpoint_error(tmp_path, edit, match):
    path = save_checkpoint(tmp_path / "m.pt", build_model(TINY), TINY)
    payload = torch.load(path, weights_only=True)
    edit(payload)
    torch.save(payload, tmp_path / "edited.pt")
    with pytest.raises(CheckpointError, match=r"edited\.pt: .*" + match):
        load_model(tmp_path / "edited.pt")


def test_weights_that_do_not_fit_are_named_without_a_cut_word(tmp_path):
    wider = TINY.model_copy(update={"widths": [4, 16]})
    forged = save_checkpoint(tmp_path / "forged.pt", build_model(wider), TINY)
    with pytest.raises(CheckpointError) as err:
        load_model(forged)
    detail = str(err.value).split("(", 1)[1]
    assert detail.endswith(")") and (detail.endswith(" ...)") or len(detail) <= 201)


def test_descriptor_dims_are_consistent_with_formula():
    for name in PRESETS:
        cfg = load_model_config(name)
        side = cfg.image_size_px
        for _ in range(len(cfg.widths) + 1):
            side = math.floor(side / 2)
        assert cfg.frame_feature_dim() == cfg.widths[-1] * side * side


def test_non_checkpoint_files_get_a_short_reason(tmp_path):
    import os

    random_bytes = tmp_path / "random.pt"
    random_bytes.write_bytes(os.urandom(2000).replace(b"PK", b"pk"))
    with pytest.raises(CheckpointError) as err:
        load_model(random_bytes)
    assert str(err.value) == f"{random_bytes}: not a radarslam checkpoint (not a torch zip archive)"
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(
        CheckpointError, match=r"empty\.pt: not a readable checkpoint \(empty file\)"
    ):
        load_model(empty)
