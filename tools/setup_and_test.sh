#!/usr/bin/env bash
# The README's test command: set up, lint, then the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tools/setup.sh
. .venv/bin/activate
ruff check .
ruff format --check .
python -m pytest -q
