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
# uav_interfaces is built with CMake (>= 3.16) and a C compiler; pip's CMake where the machine has none.
command -v cmake >/dev/null || .venv/bin/python -m pip install -q --no-cache-dir "cmake>=3.16,<4"
command -v cc >/dev/null || { echo "a C/C++ compiler is needed to build src/uav_interfaces (apt install build-essential)" >&2; exit 1; }
# The wheels' exported CMake files name their builder's Python headers: point them at this Python's.
.venv/bin/python scripts/fix_ros_wheel_cmake.py
# colcon must run from the same venv as the ROS wheels so the node scripts get its interpreter; the venv is the ROS
# prefix the interface generators are found in.
. .venv/bin/activate
export AMENT_PREFIX_PATH="$VIRTUAL_ENV" CMAKE_PREFIX_PATH="$VIRTUAL_ENV"
colcon build --base-paths src --cmake-args -DBUILD_TESTING=OFF --event-handlers console_cohesion- summary+ 2>&1 | tail -n 3
colcon list --base-paths src
echo "set-up done: activate with 'source .venv/bin/activate && source install/setup.bash'"
