#!/usr/bin/env bash
# The whole test suite: lint/format check, then unit and integration tests (installed nodes).
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
. install/setup.bash
ruff check src tests benchmarks
ruff format --check src tests benchmarks
python -m pytest tests "$@"
