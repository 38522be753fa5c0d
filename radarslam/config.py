"""Configuration: pydantic models loaded from YAML, with ``key.sub=value`` overrides.

Every model derives from :class:`StrictModel`, which forbids unknown keys so that a misspelled
YAML key fails loudly instead of being silently ignored.
"""

from __future__ import annotations

import contextlib
import types
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError, PydanticKnownError

from radarslam.errors import ConfigError
from radarslam.io.text import read_text

M = TypeVar("M", bound=BaseModel)

# The YAML presets ship inside the package, so a wheel or a plain `pip install .` finds them.
CONFIG_DIR = Path(__file__).resolve().parent / "configs"


class StrictModel(BaseModel):
    """Base of every settings model: unknown keys are refused, and so are values that would only
    fail deep inside a run:

    * non-finite floats (``inf``, ``nan``) anywhere: ``allow_inf_nan=False``. A float setting
      that means "no limit" is written ``null`` (``None``) instead.
    * a negative ``seed``: numpy's random generators refuse one.

    Lengths and sigmas that feed registration, voxel maps and kernels carry an upper bound of
    their own (``le=1000`` m: the radars see at most ~250 m); beyond it a voxel key overflows or
    a kernel turns to NaN.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_a_number(cls, value: Any, info: ValidationInfo) -> Any:
        # pydantic reads true as 1 for a number: `--set fusion.gate_chi2=true` would be a gate of 1
        if isinstance(value, bool) and info.field_name is not None:
            field = cls.model_fields.get(info.field_name)
            if field is not None and not _accepts_bool(field.annotation):
                raise PydanticCustomError(
                    "bool_for_a_number",
                    "a yes/no value where this setting takes a number or a name",
                )
        return value

    @field_validator("*", mode="after")
    @classmethod
    def _seed_not_negative(cls, value: Any, info: ValidationInfo) -> Any:
        if info.field_name == "seed" and isinstance(value, int) and value < 0:
            raise PydanticKnownError("greater_than_equal", {"ge": 0})
        return value


def _accepts_bool(annotation: Any) -> bool:
    """Whether a field of this type takes a yes/no value (bool, a bool Literal, Any, a union with
    either); a model (a section) is left to its own validation."""
    if annotation is bool or annotation is Any:
        return True
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return True
    origin = get_origin(annotation)
    if origin is Literal:
        return any(isinstance(a, bool) for a in get_args(annotation))
    if origin in (Union, types.UnionType, Annotated):
        return any(_accepts_bool(a) for a in get_args(annotation))
    return False


def _got(value: Any) -> str:
    """`` (got <value>)`` for a scalar or short input; nothing for a whole section."""
    if isinstance(value, dict):
        return ""
    text = repr(value)
    return f" (got {text if len(text) <= 80 else text[:77] + '...'})"


def _override_for(loc: tuple, overrides: list[tuple[list[str], str]]) -> tuple[str | None, bool]:
    """The last override that set ``loc`` or a section holding it; else (None, whether an override
    changed something inside ``loc``, a section-level error)."""
    keys = [str(p) for p in loc]
    for path, text in reversed(overrides):
        if keys[: len(path)] == path:
            return text, False
    inside = [text for path, text in overrides if path[: len(keys)] == keys]
    return (inside[-1], True) if inside else (None, False)


def _format_validation_error(
    source: str, exc: ValidationError, overrides: list[str] | None = None
) -> str:
    """One line: errors grouped by where the value came from, ``source`` (the file) or the
    ``key=value`` override that set it."""
    parsed = []
    for text in overrides or []:
        with contextlib.suppress(ConfigError):
            parsed.append((parse_override(text)[0], text))
    groups: dict[str, list[str]] = {}
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "<root>"
        if err["type"] == "extra_forbidden":
            part = f"unknown key '{loc}'"
        else:
            part = f"'{loc}': {err['msg']}{_got(err.get('input'))}"
        setter, section = _override_for(tuple(err["loc"]), parsed)
        if setter is None:
            where = source
        elif section and source != "config overrides":
            where = f"{source} with override {setter!r}"
        else:
            where = f"override {setter!r}"
        groups.setdefault(where, []).append(part)
    return "; ".join(f"{where}: " + "; ".join(parts) for where, parts in groups.items())


def parse_override(text: str) -> tuple[list[str], Any]:
    """``a.b.c=value`` -> (["a", "b", "c"], value parsed as YAML scalar/list)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} is not of the form key.sub=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"override {text!r} has an empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError:
        value = raw
    return key.split("."), value


def apply_overrides(data: dict, overrides: list[str] | None) -> dict:
    data = dict(data)
    for text in overrides or []:
        keys, value = parse_override(text)
        node = data
        for k in keys[:-1]:
            child = node.get(k)
            if child is None:
                child = {}
            elif not isinstance(child, dict):
                raise ConfigError(f"override {text!r}: '{k}' is not a section")
            node[k] = dict(child)
            node = node[k]
        node[keys[-1]] = value
    return data


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last one)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:  # an unhashable key: construct_mapping says so
                    continue
                if first is not None:
                    raise yaml.constructor.ConstructorError(
                        None,
                        None,
                        f"duplicate key {key!r} (first given on line {first + 1})",
                        key_node.start_mark,
                    )
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path) -> dict:
    """A YAML mapping; :class:`ConfigError` naming the file and line for invalid YAML or a key
    given twice in one mapping."""
    path = Path(path)
    text = read_text(path, "config file", ConfigError)
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader) or {}
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}:{where} invalid YAML ({getattr(exc, 'problem', exc)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data


def _section_default(model: type[BaseModel], key: str, parent: BaseModel | None) -> Any:
    """The value section ``key`` of ``model`` takes when nothing sets it (None: required)."""
    if parent is not None:
        return getattr(parent, key)
    field = model.model_fields[key]
    if field.is_required():
        return None
    return field.get_default(call_default_factory=True)


def complete_sections(model: type[BaseModel], data: dict, parent: BaseModel | None = None) -> dict:
    """``data`` with every partly given section completed from the section's default value.

    A section whose default comes from a factory with its own values (the SLAM preset's
    odometry runs a calibration pass; the odometry's Doppler fit refits a creeping car's
    velocity) would otherwise be rebuilt from its class defaults as soon as one of its keys is
    given: ``--set odometry.doppler.seed=1`` must change the seed and nothing else."""
    out = dict(data)
    for key, value in data.items():
        if key not in model.model_fields or not isinstance(value, dict):
            continue  # unknown keys and non-mappings: validation says what is wrong
        default = _section_default(model, key, parent)
        if isinstance(default, BaseModel):
            given = complete_sections(type(default), value, default)
            out[key] = {name: getattr(default, name) for name in type(default).model_fields}
            out[key].update(given)
    return out


def build_config(
    model: type[M], data: dict, source: str = "config", overrides: list[str] | None = None
) -> M:
    """Validate ``data`` (sections it gives in part keep their other defaults); errors name
    ``source``, or the override (of ``overrides``, already applied to ``data``) that set the
    offending key."""
    try:
        return model.model_validate(complete_sections(model, data))
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(source, exc, overrides)) from None


def load_config(
    model: type[M], path: str | Path | None = None, overrides: list[str] | None = None
) -> M:
    """Load ``model`` from a YAML file (or its defaults when ``path`` is None), then overrides."""
    data = read_yaml(path) if path is not None else {}
    data = apply_overrides(data, overrides)
    source = str(path) if path else "config overrides"
    return build_config(model, data, source=source, overrides=overrides)


def dump_config(cfg: BaseModel) -> str:
    """YAML text of a resolved config (written next to the outputs it made)."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
