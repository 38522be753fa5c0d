"""The ablation runner: the paper's variants trained and evaluated in one call, two-stage TE."""

from __future__ import annotations

import pytest
import yaml
from pr_synthetic import TINY, corridor_data

from radarslam.errors import CheckpointError
from radarslam.place_recognition.ablation import VARIANTS, run_ablation, table_ii_rows
from radarslam.place_recognition.checkpoint import read_checkpoint
from radarslam.place_recognition.config import EvalConfig

# CPU convolution backward is bitwise deterministic only on one thread
pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def presets(tmp_path_factory):
    d = tmp_path_factory.mktemp("presets")
    se = TINY.model_copy(update={"seq_len": 1, "use_temporal": False, "descriptor_dim": None})
    paths = {}
    for slug, cfg in (("se", se), ("se_te", TINY)):
        paths[slug] = d / f"model_tiny_{slug}.yaml"
        paths[slug].write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    train = d / "train_tiny.yaml"
    train.write_text(yaml.safe_dump(dict(epochs=2, select_after_epoch=0, patience=0, seed=1234,
                                         threads=1, device="cpu")))  # fmt: skip
    return {k: str(v) for k, v in paths.items()}, str(train)


def test_two_stage_ablation_starts_te_from_the_se_variant(presets, tmp_path):
    models, train = presets
    data = corridor_data()  # stands in for both caches (same splits)
    runs = run_ablation(data, data, tmp_path, size="tiny", model_presets=models,
                        train_preset=train, eval_cfg=EvalConfig(), variants=VARIANTS[:2],
                        progress=False, te_init_from_se=True)  # fmt: skip
    se_run, te_run = runs
    assert se_run.trained and te_run.trained
    assert se_run.checkpoint == tmp_path / "tiny_se" / "best.pt"
    stored = read_checkpoint(te_run.checkpoint)["train_config"]
    assert stored["init_encoder_from"] == str(se_run.checkpoint)
    assert read_checkpoint(se_run.checkpoint)["train_config"]["init_encoder_from"] is None
    rows = table_ii_rows(runs)
    assert [r["method"] for r in rows] == ["SE", "SE+TE", "SE+RCSHR", "SE+TE+RCSHR"]
    # the corridor is learnable: both trained variants find most test places
    assert all(r["R@1"] > 50 for r in rows)


def test_two_stage_needs_the_se_variant_first(presets, tmp_path):
    models, train = presets
    data = corridor_data()
    with pytest.raises(CheckpointError, match="two-stage training needs the tiny se checkpoint"):
        run_ablation(data, data, tmp_path, size="tiny", model_presets=models, train_preset=train,
                     variants=VARIANTS[1:2], progress=False, te_init_from_se=True)  # fmt: skip
