"""Config errors name where the bad value came from: the YAML file or the override."""

import pytest
from pydantic import Field, model_validator

from radarslam.config import StrictModel, load_config, read_yaml
from radarslam.errors import ConfigError


class Inner(StrictModel):
    voxel_size_m: float = Field(1.0, gt=0)
    iterations: int = 10


class Outer(StrictModel):
    name: str = "x"
    inner: Inner = Inner()


@pytest.fixture
def yaml_file(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: demo\ninner:\n  iterations: 5\n")
    return path


def test_binary_yaml_is_a_config_error(tmp_path):
    path = tmp_path / "bin.yaml"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match=r"bin\.yaml: not a UTF-8 text file"):
        read_yaml(path)
    with pytest.raises(ConfigError, match=r"bin\.yaml: not a UTF-8 text file"):
        load_config(Outer, path)


def test_bad_override_value_names_the_override_not_the_file(yaml_file):
    with pytest.raises(ConfigError) as err:
        load_config(Outer, yaml_file, ["inner.voxel_size_m=-1"])
    msg = str(err.value)
    assert msg.startswith("override 'inner.voxel_size_m=-1': 'inner.voxel_size_m'"), msg
    assert "greater than 0 (got -1)" in msg and "c.yaml" not in msg


def test_unknown_override_key_names_the_override(yaml_file):
    with pytest.raises(ConfigError) as err:
        load_config(Outer, yaml_file, ["lr_rate=0.1"])
    assert str(err.value) == "override 'lr_rate=0.1': unknown key 'lr_rate'"


def test_file_errors_still_name_the_file(yaml_file):
    yaml_file.write_text("inner:\n  voxel_size_m: -2\n")
    with pytest.raises(ConfigError) as err:
        load_config(Outer, yaml_file, ["inner.iterations=3"])
    assert str(err.value).startswith(f"{yaml_file}: 'inner.voxel_size_m'")
    # the later override of the same key wins, and is the one named
    with pytest.raises(ConfigError, match=r"^override 'inner.voxel_size_m=-3'"):
        load_config(Outer, yaml_file, ["inner.voxel_size_m=1", "inner.voxel_size_m=-3"])


class Range(StrictModel):
    lo: float = 0.0
    hi: float = 1.0

    @model_validator(mode="after")
    def _ordered(self):
        if self.lo >= self.hi:
            raise ValueError("lo must be < hi")
        return self


class WithRange(StrictModel):
    range: Range = Range()


def test_section_errors_do_not_dump_the_section(yaml_file):
    with pytest.raises(ConfigError) as err:
        load_config(Outer, yaml_file, ["inner=5"])
    assert str(err.value).startswith("override 'inner=5': 'inner':")
    # a section-level check: the file and the override that changed the section are named,
    # the section's values are not dumped
    yaml_file.write_text("range:\n  hi: 2.0\n")
    with pytest.raises(ConfigError) as err:
        load_config(WithRange, yaml_file, ["range.lo=5"])
    assert str(err.value) == (
        f"{yaml_file} with override 'range.lo=5': 'range': Value error, lo must be < hi"
    )
    with pytest.raises(ConfigError) as err:
        load_config(WithRange, yaml_file, ["range.lo=5", "range.hi=1"])
    assert "{" not in str(err.value)
