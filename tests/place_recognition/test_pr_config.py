import pytest

from radarslam.config import CONFIG_DIR, build_config, load_config
from radarslam.errors import ConfigError
from radarslam.place_recognition.config import (
    EvalConfig,
    PlaceRecognizerConfig,
    PrepareConfig,
    RerankConfig,
    SplitConfig,
)

PRESETS = CONFIG_DIR / "place_recognition"


@pytest.mark.parametrize("path", sorted(PRESETS.glob("data_*.yaml")), ids=lambda p: p.name)
def test_data_presets_load(path):
    cfg = load_config(PrepareConfig, path)
    assert cfg.split.pos_radius_m == 9.0 and cfg.split.neg_radius_m == 18.0
    assert cfg.accumulation.nsweeps == 7 and cfg.image.size_px == 200


def test_eval_and_recognizer_presets():
    ev = load_config(EvalConfig, PRESETS / "eval_default.yaml")
    assert ev == EvalConfig()
    rec = load_config(PlaceRecognizerConfig, PRESETS / "recognizer_default.yaml")
    assert rec.rerank == RerankConfig()


def test_config_validation():
    with pytest.raises(ConfigError, match="neg_radius_m"):
        build_config(SplitConfig, {"neg_radius_m": 5.0})
    with pytest.raises(ConfigError, match="edge_exclusion"):
        build_config(SplitConfig, {"seq_len": 4, "edge_exclusion": 2})
    with pytest.raises(ConfigError, match="unknown key"):
        build_config(PrepareConfig, {"imgae": {}})
    with pytest.raises(ConfigError, match="bin"):
        build_config(RerankConfig, {"bin_min": 0.9, "bin_width": 0.2})
    with pytest.raises(ConfigError, match="name"):
        build_config(PrepareConfig, {"name": "a/b"})
