import pytest
from pydantic import Field

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


class Tuned(StrictModel):
    """A section whose default is built with other values than its class defaults."""

    inner: Inner = Field(default_factory=lambda: Inner(voxel_size_m=0.25, iterations=3))
    other: Inner = Field(default_factory=Inner)


def test_a_partly_given_section_keeps_its_factory_defaults(tmp_path):
    cfg = load_config(Tuned, None, ["inner.iterations=7"])
    assert (cfg.inner.voxel_size_m, cfg.inner.iterations) == (0.25, 7)
    path = tmp_path / "c.yaml"
    path.write_text("inner:\n  voxel_size_m: 2.0\nother:\n  iterations: 4\n")
    cfg = load_config(Tuned, path)
    assert (cfg.inner.voxel_size_m, cfg.inner.iterations) == (2.0, 3)
    assert (cfg.other.voxel_size_m, cfg.other.iterations) == (1.0, 4)
    with pytest.raises(ConfigError, match=r"unknown key 'inner.iteratons'"):
        load_config(Tuned, None, ["inner.iteratons=5"])


def _flat(d: dict, prefix: str = "") -> dict:
    out: dict = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


@pytest.mark.parametrize(
    "override",
    ["odometry.doppler.speed_scale_error=-0.002", "odometry.doppler.seed=3"],
)
def test_one_slam_odometry_key_changes_that_key_only(override):
    # The SLAM preset's odometry and the odometry's Doppler fit are built by factories with
    # their own values (a calibration pass; a refitted creeping velocity): giving one key of
    # those sections must not rebuild them from their class defaults.
    from radarslam.config import CONFIG_DIR
    from radarslam.slam.config import SlamConfig

    path = CONFIG_DIR / "slam" / "default.yaml"
    plain = _flat(load_config(SlamConfig, path).model_dump())
    changed = _flat(load_config(SlamConfig, path, [override]).model_dump())
    key = override.split("=")[0]
    assert {k for k in plain if plain[k] != changed[k]} == {key}
    bare = load_config(SlamConfig, None, [override])
    assert bare.odometry.fusion.calibration.passes == 2
    assert bare.odometry.doppler.static_velocity == "refit"


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
    (tmp_path / "folder.yaml").mkdir()
    with pytest.raises(ConfigError, match=r"folder\.yaml: is a folder, not a config file"):
        load_config(Outer, tmp_path / "folder.yaml")
    with pytest.raises(ConfigError, match="not of the form"):
        apply_overrides({}, ["novalue"])
    with pytest.raises(ConfigError, match="is not a section"):
        apply_overrides({"name": "x"}, ["name.sub=1"])


# ---- numeric settings: non-finite, out-of-range and negative seeds refused at load -------------
def _all_models():
    from radarslam.eval.evaluate import EvalConfig
    from radarslam.odometry.config import OdometryConfig
    from radarslam.place_recognition.config import PlaceRecognizerConfig
    from radarslam.sim.config import SimConfig
    from radarslam.slam.config import SlamConfig

    return [SlamConfig, OdometryConfig, SimConfig, EvalConfig, PlaceRecognizerConfig]


def test_every_settings_model_refuses_non_finite_floats():
    for model in _all_models():
        assert model.model_config.get("allow_inf_nan") is False, model.__name__


@pytest.mark.parametrize(
    "override",
    [
        "odometry.registration.fixed_sigma_m=inf",
        "odometry.registration.fixed_sigma_m=1e300",
        "odometry.registration.point_sigma_m=inf",
        "odometry.registration.voxel_size_m=.inf",
        "odometry.doppler.noise_floor_mps=inf",
        "odometry.doppler.noise_floor_mps=1e300",
        "odometry.doppler.inlier_threshold_mps=nan",
        "odometry.fusion.process_noise=[0.2, 0.2, .inf]",
        "backend.static_map.voxel_size_m=inf",
        "backend.static_map.voxel_size_m=1e6",
        "backend.loop_verification.voxel_size_m=1e300",
        "odometry.doppler.seed=-1",
    ],
)
def test_bad_numeric_settings_name_the_key(override):
    from radarslam.slam.config import SlamConfig

    key = override.split("=")[0]
    with pytest.raises(ConfigError) as exc:
        load_config(SlamConfig, None, [override])
    msg = str(exc.value)
    assert msg.startswith(f"override {override!r}: '{key}") and "\n" not in msg


def test_bounds_leave_the_shipped_ranges_alone():
    from radarslam.slam.config import SlamConfig

    cfg = load_config(
        SlamConfig,
        None,
        ["odometry.registration.fixed_sigma_m=1000", "backend.static_map.voxel_size_m=1000"],
    )
    assert cfg.odometry.registration.fixed_sigma_m == 1000.0


def test_negative_seed_of_the_simulator_is_refused(tmp_path):
    from radarslam.sim import simulate
    from radarslam.sim.config import load_sim_config

    with pytest.raises(ConfigError, match=r"'seed': Input should be greater than or equal to 0"):
        load_sim_config("tiny", ["seed=-1"])
    with pytest.raises(ConfigError, match=r"simulate arguments: 'seed'"):
        simulate("tiny", tmp_path / "out", seed=-1, progress=False)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("text", "line", "key"),
    [
        ("inner:\n  iterations: 5\n  voxel_size_m: 1\n  iterations: 7\n", 4, "iterations"),
        ("name: a\ninner: {iterations: 1, iterations: 2}\n", 2, "iterations"),
        ("name: a\nname: b\n", 2, "name"),
    ],
)
def test_duplicate_yaml_keys_name_the_file_key_and_line(tmp_path, text, line, key):
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(Outer, path)
    assert str(exc.value).startswith(f"{path}: line {line} ")
    assert f"duplicate key {key!r}" in str(exc.value)


def test_a_yes_no_value_is_refused_for_a_number_or_a_name():
    # pydantic alone reads `true` as 1: a gate of 1, one iteration
    from radarslam.odometry.config import OdometryConfig

    for key in ("fusion.gate_chi2", "registration.max_num_iterations", "fusion.mode"):
        with pytest.raises(ConfigError, match=rf"'{key}': a yes/no value where"):
            load_config(OdometryConfig, None, [f"{key}=true"])
    # where a setting is a yes/no, or may be null, it still is
    cfg = load_config(OdometryConfig, None, ["points.deskew=false", "fusion.max_twist_rate=null"])
    assert cfg.points.deskew is False and cfg.fusion.max_twist_rate is None
