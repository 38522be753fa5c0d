import pytest

from radarslam.config import StrictModel, apply_overrides, dump_config, load_config
from radarslam.errors import ConfigError


class Inner(StrictModel):
    voxel_size_m: float = 1.0
    iterations: int = 10


class Outer(StrictModel):
    name: str = "x"
    inner: Inner = Inner()


def test_defaults_yaml_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: demo\ninner:\n  iterations: 5\n")
    cfg = load_config(Outer, path, ["inner.voxel_size_m=0.5"])
    assert cfg.name == "demo" and cfg.inner.iterations == 5 and cfg.inner.voxel_size_m == 0.5
    assert "voxel_size_m: 0.5" in dump_config(cfg)


def test_misspelled_key_fails_loudly(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("inner:\n  iteratons: 5\n")
    with pytest.raises(ConfigError, match=r"c.yaml: unknown key 'inner.iteratons'"):
        load_config(Outer, path)


def test_wrong_type_names_key_and_value():
    with pytest.raises(ConfigError, match=r"'inner.iterations'.*'many'"):
        load_config(Outer, None, ["inner.iterations=many"])


def test_bad_yaml_and_missing_file(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config(Outer, path)
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Outer, tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="not of the form"):
        apply_overrides({}, ["novalue"])
    with pytest.raises(ConfigError, match="is not a section"):
        apply_overrides({"name": "x"}, ["name.sub=1"])
