#!/usr/bin/env bash
# Regenerates docs/RESULTS.md's material: trains D3QN-SAM and D3QN-CNN (3 seeds each, 30 000 steps,
# in-process trainer = the ROS trainer's core run synchronously, bit-reproducible) with the paper's
# 90 degree camera (recorded in the weights files, so evaluate flies them with it), evaluates every
# run exploit-only through the ROS nodes in basic/complex/turbulent and held-out random layouts,
# and draws the curves and attention figures. About 1 h 15 min on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
. install/setup.bash
export PYTHONPATH=src/uav_sim:src/uav_policy:src/uav_trainer:${PYTHONPATH:-} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
SEEDS=${SEEDS:-"0 1 2"}
for seed in $SEEDS; do
  for model in sam cnn; do
    d=runs/paper_${model}_seed${seed}
    [ -f "$d/DONE" ] || { python -m uav_trainer.inprocess --model $model --steps 30000 --seed $seed --hfov-deg 90 --run-dir "$d"; touch "$d/DONE"; }
  done
done
sam=(); cnn=()
for seed in $SEEDS; do sam+=("sam=runs/paper_sam_seed${seed}/policy_sam.safetensors"); cnn+=("cnn=runs/paper_cnn_seed${seed}/policy_cnn.safetensors"); done
install/uav_trainer/lib/uav_trainer/evaluate --model sam --model cnn --weights "${sam[@]}" "${cnn[@]}" \
  --worlds basic complex turbulent --steps 1000 --out docs/results/paper_worlds
install/uav_trainer/lib/uav_trainer/evaluate --model sam --model cnn --weights "${sam[@]}" "${cnn[@]}" \
  --worlds random:101 random:102 random:103 --steps 1000 --out docs/results/heldout_worlds
install/uav_trainer/lib/uav_trainer/plot_curves runs/paper_*_seed* --out docs/figures/training_curves.png
# The attention figures show the packaged SAM (its ten networks as one policy, their attention averaged).
install/uav_policy/lib/uav_policy/attention_figures --model sam --worlds basic turbulent --steps 150 --out docs/figures
