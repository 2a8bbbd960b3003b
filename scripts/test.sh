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
# its own ROS domain, the cases of one test sharing a fixed one run on one worker (tests/conftest.py: loadgroup).
# `-n 0` after it runs them one at a time.
python -m pytest tests -n 2 --dist loadgroup --durations=15 "$@"
