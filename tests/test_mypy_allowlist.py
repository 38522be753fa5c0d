"""The mypy allow-list in pyproject.toml names modules that exist.

A module that was renamed, split or deleted must leave the list rather than linger in it: an
entry that matches nothing would let a new module of that name skip type checking unnoticed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # the standard library's from Python 3.11

ROOT = Path(__file__).resolve().parents[1]


def _allow_list() -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    modules: list[str] = []
    for override in config.get("overrides", []):
        if override.get("ignore_errors"):
            names = override["module"]
            modules += [names] if isinstance(names, str) else names
    return modules


def _exists(module: str) -> bool:
    path = ROOT.joinpath(*module.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def test_allow_list_names_existing_modules() -> None:
    modules = _allow_list()
    assert modules, "no [[tool.mypy.overrides]] block with ignore_errors found"
    missing = [m for m in modules if not _exists(m)]
    assert not missing, f"allow-listed for mypy but not in the package: {missing}"


def test_allow_list_has_no_wildcards_or_duplicates() -> None:
    modules = _allow_list()
    assert not [m for m in modules if "*" in m], "list modules one by one"
    assert len(modules) == len(set(modules))
