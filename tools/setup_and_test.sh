#!/usr/bin/env bash
# The README's test command: set up, lint, type-check the library, then the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
. .venv/bin/activate
ruff check .
ruff format --check .
mypy  # settings and the allow-list in pyproject.toml
python -m pytest -q
