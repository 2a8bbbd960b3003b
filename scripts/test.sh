#!/usr/bin/env bash
# The whole test suite: lint/format check, then unit and integration tests (installed nodes).
set -euo pipefail
cd "$(dirname "$0")/.."
set +u  # colcon's setup.bash reads unset variables
. .venv/bin/activate
. install/setup.bash
set -u
ruff check src tests benchmarks scripts
ruff format --check src tests benchmarks scripts
python -m pytest tests --durations=15 "$@"
