"""OdometryConfig: bad values are one-line ConfigErrors naming the key, not numpy errors later."""

import pytest
import yaml

from radarslam.config import StrictModel, apply_overrides, build_config, dump_config
from radarslam.errors import ConfigError
from radarslam.odometry.config import (
    FusionConfig,
    OdometryConfig,
    PointsConfig,
    RegistrationConfig,
)


def _build(*overrides: str) -> OdometryConfig:
    return build_config(OdometryConfig, apply_overrides({}, list(overrides)), "odometry.yaml")


def test_defaults_and_yaml_round_trip():
    cfg = OdometryConfig()
    assert cfg.fusion.process_noise == (0.2, 0.2, 0.02)
    assert cfg.fusion.invalid_doppler_growth == (1.0, 1.0, 0.05)
    again = build_config(OdometryConfig, yaml.safe_load(dump_config(cfg)), "dump")
    assert again == cfg
    assert _build("fusion.process_noise=[1, 2, 0]").fusion.process_noise == (1.0, 2.0, 0.0)


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("fusion.process_noise=[1,2]", r"'fusion\.process_noise': .*expected 3 values"),
        ("fusion.process_noise=[1,2,3,4]", r"'fusion\.process_noise': .*expected 3 values"),
        ("fusion.process_noise=0.2", r"'fusion\.process_noise'"),
        ("fusion.process_noise=[1,-2,3]", r"'fusion\.process_noise\.1': .*greater than or equal"),
        ("fusion.invalid_doppler_growth=[1,2]", r"'fusion\.invalid_doppler_growth': .*3 values"),
        ("fusion.invalid_doppler_growth=[1,2,.nan]", r"invalid_doppler_growth\.2': .*finite"),
        ("fusion.invalid_doppler_growth=[1,a,2]", r"invalid_doppler_growth\.1'"),
        ("points.min_range_m=200", r"'points': .*min_range_m \(200\.0\) must be below max_range_m"),
        ("points.max_range_m=0.5", r"min_range_m \(1\.0\) must be below max_range_m \(0\.5\)"),
        ("points.nope=1", r"unknown key 'points\.nope'"),
        ("points.invalid_states=[999]", r"'points\.invalid_states': .*state 999 is not one the"),
        ("points.dynprop_states=[0,8]", r"'points\.dynprop_states': .*state 8 .* \(0-7\)"),
        ("points.ambig_states=[-1]", r"'points\.ambig_states': .*state -1 .* \(0-4\)"),
    ],
)
def test_bad_values_are_config_errors(override, match):
    with pytest.raises(ConfigError, match=match) as exc:
        _build(override)
    assert "\n" not in str(exc.value) and str(exc.value).startswith("odometry.yaml: ")


def test_models_forbid_unknown_keys():
    for model in (OdometryConfig, PointsConfig, RegistrationConfig, FusionConfig):
        assert issubclass(model, StrictModel) and model.model_config["extra"] == "forbid"
