#!/usr/bin/env bash
# One-command set-up on a fresh Linux machine (Python >= 3.11): a virtual environment with
# the pinned ROS 2 Jazzy wheels, PyTorch (CPU), pybullet and the test tools, then a colcon
# build of src/. Re-running it is safe and fast.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -c 'import sys; assert sys.version_info >= (3, 11), "Python >= 3.11 is required"'
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --no-cache-dir --upgrade pip
.venv/bin/python -m pip install -q --no-cache-dir -r requirements.txt
# colcon must run from the same venv as the ROS wheels so the node scripts get its interpreter.
. .venv/bin/activate
colcon build --base-paths src --event-handlers console_cohesion- summary+ 2>&1 | tail -n 3
colcon list --base-paths src
echo "set-up done: activate with 'source .venv/bin/activate && source install/setup.bash'"
