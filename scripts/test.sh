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
# Two workers (pytest-xdist): most tests wait on nodes in other processes, so two share 2 cores well; each test has
# a ROS domain of its own (tests/conftest.py). `-n 0` after it runs them one at a time.
python -m pytest tests -n 2 --durations=15 "$@"
