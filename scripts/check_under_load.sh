#!/usr/bin/env bash
# The suite beside the main job, as users run the two README commands together: N times (default 3), a clean clone
# of this repository's HEAD runs `CI=true bash .ci/run` while `train --model sam` (from this checkout's install) trains
# beside it on a ROS domain the tests never take. Prints each run's verdict and main-suite time; exit 1 if any failed or
# its main suite took over 12 minutes (720 s, the suite's budget). Each run's logs (ci.out, train.out, the nodes') stay
# in its scratch folder; its clone is removed.
#   bash scripts/check_under_load.sh [N]
set -uo pipefail
cd "$(dirname "$0")/.."
runs=${1:-3}
repo=$(pwd)
shared=$(cd .. && pwd)/shared
if [ ! -x install/uav_trainer/lib/uav_trainer/train ]; then
  echo "check_under_load: build first (bash scripts/setup.sh): the main job runs from install/" >&2
  exit 2
fi
failed=0
for i in $(seq 1 "$runs"); do
  work=$(mktemp -d)
  # A run installs a virtual environment in its clone (about 2.6 GB) and trains beside it: refuse to start one that
  # would fill the disk halfway (pip's "No space left on device" reads like a failed suite).
  free_gb=$(( $(df --output=avail -k "$work" | tail -n 1) / 1048576 ))
  if [ "$free_gb" -lt 4 ]; then
    echo "check_under_load: only $free_gb GB free in $(dirname "$work"); a run needs 4 GB (each run removes its own clone)" >&2
    rm -rf "$work"
    exit 2
  fi
  git clone -q "$repo" "$work/main" && ln -s "$shared" "$work/shared"
  # The main job on a domain of its own (the tests take 1-101), its run folders and logs in the scratch folder, trained
  # again from the start each time it ends (30 000 steps can end mid-suite), until the suite is done.
  setsid bash -c 'set +u && source .venv/bin/activate && source install/setup.bash || exit 1
    export ROS_DOMAIN_ID=150 ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
    for k in $(seq 1 100); do
      install/uav_trainer/lib/uav_trainer/train --model sam --run-dir "$0/train_run$k" --log-dir "$0/train_logs$k" \
        --validation-steps 0 || exit 1
    done' "$work" >"$work/train.out" 2>&1 &
  job=$!
  (cd "$work/main" && CI=true bash .ci/run) >"$work/ci.out" 2>&1
  code=$?
  beside="the main job beside it reached"
  if ! kill -0 "$job" 2>/dev/null; then  # it ended before the suite did: the run was not under load
    beside="NOT UNDER LOAD: the main job had exited ($(tail -n 1 "$work/train.out")); it reached"
    failed=1
  fi
  kill -INT -- "-$job" 2>/dev/null  # the loop and the run it is in
  wait "$job" 2>/dev/null
  suite=$(grep -o "main suite took [0-9]* s" "$work/ci.out" || echo "main suite: no time (see $work/ci.out)")
  steps=$(grep -o "progress: [0-9]*/[0-9]* steps" "$work/train.out" 2>/dev/null | tail -n 1)
  secs=$(grep -o "main suite took [0-9]*" "$work/ci.out" 2>/dev/null | grep -o "[0-9]*$" || echo 0)
  if [ "$code" -ne 0 ]; then verdict="FAILED (code $code)"; failed=1
  elif [ "${secs:-0}" -gt 720 ]; then verdict="green but OVER the 720 s budget"; failed=1
  else verdict=green; fi
  rm -rf "$work/main" "$work"/train_run*  # the clone and its checkpoints; the logs stay
  echo "run $i/$runs: $verdict; $suite; $beside ${steps:-no step logged} (logs: $work)"
done
exit $failed
