#!/usr/bin/env bash
# Regenerates the investigation experiments in docs/RESULTS.md (run scripts/reproduce_results.sh
# first: it trains the paper-protocol runs runs/paper_*). Trains D3QN-SAM and D3QN-CNN with a new
# procedural layout every episode (3 seeds each), at the default 90 degree camera and at 120
# degrees, then evaluates through the ROS nodes with the paper's fixed start pose and with random
# start headings (5 x 1000 steps per weight file), and two SAM-only experiments; then a second
# round at 120 degrees (longer training, weight averaging, learning-rate annealing, a turn
# penalty), a third (five and ten seeds with the turn penalty; SAM with the flatten readout) with
# turning share and area covered, and a fourth (twenty seeds; choosing, packaging and measuring the
# shipped weights, and the attention figures); then re-measures every ROS table without ROS
# (scripts/crosscheck_eval.py); a fifth round (a new start heading every training episode), the
# main job on its defaults, a sixth round (a time limit on training episodes) and a seventh
# (the same trained longer, and a confirmation on fresh seeds), an eighth (an 84 x 84 input) and a
# ninth (half or a fifth of the training episodes start at a random place and heading), a tenth
# (a larger SAM), an eleventh (n-step returns), a twelfth (prioritized replay), a thirteenth
# (slower exploration, then with CNN), a fourteenth (the same on fresh seeds) and a fifteenth (round
# 6's setting on fresh seeds, flown alone and as ensembles of three), a sixteenth (every fourth or
# eighth training episode in Basic), a seventeenth (layouts with 2-3 m partitions), an eighteenth
# (round 16 on fresh seeds, both models), a nineteenth (choosing one seed of each group on validation
# layouts), a twentieth (ten stacked depth frames), a twenty-first (a two-layer trunk: 16 x 16 SAM
# nodes, and a CNN with the same trunk), a twenty-second (twice the updates per step), a twenty-third
# (the same with every fourth training episode in Basic), a twenty-fourth (a 150 degree camera with a
# smaller reward window), a twenty-fifth (the same on ten more SAM seeds, and a CNN arm), a
# twenty-sixth (random-shift augmentation of the sampled states), a twenty-seventh (each run's last
# three checkpoints flown as one policy), a twenty-eighth (five and ten snapshots per run), a
# twenty-ninth (round 25's runs retrained with ten snapshots), a thirtieth (those runs flown two
# seeds to a policy), a thirty-first (those runs flown as round 27 flew round 25's), a thirty-second
# (round 28's recipe on twenty fresh seeds; the odds that a set of twenty meets the bar), a thirty-third
# (those ten-snapshot ensembles on each action's lowest Q-value), a thirty-fourth (two seeds to a
# policy on other pairs; how much of each set's crash rate is one failure repeated), a thirty-fifth
# (round 29's recipe with every fourth training episode in Basic), a thirty-sixth (the same on twenty
# fresh seeds, and both draws pooled), a thirty-seventh (the CNN arm of that recipe), a thirty-eighth (that
# recipe as the main job over ROS, `train --recipe ensemble`), a thirty-ninth (the same with the weights
# pushed after every update), a fortieth (both on three more seeds), a forty-first (in-process, acting on
# the network pushed every 50 updates, as policy_node beside the ROS trainer), a forty-second (the main job
# on fresh seeds 6-11), a forty-third (the main job on seeds 0-5 again: seed or run?) and a forty-fourth (the main
# job learning in lockstep against round 35's in-process runs and the packaged SAM); then it packages round 35-37's
# best runs as policy_node's default weights, measures them through the ROS nodes and draws the attention
# figures with them. About 72 h on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
set +u; . install/setup.bash; set -u
export PYTHONPATH=src/uav_sim:src/uav_policy:src/uav_trainer:${PYTHONPATH:-} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
SEEDS=${SEEDS:-"0 1 2"}
EVAL=install/uav_trainer/lib/uav_trainer/evaluate
VARIED=(--start-yaw-jitter-deg 180 --repeats 5)
train() {  # tag model seed [inprocess args]; the paper's 90 degree camera unless the args say --hfov-deg
  local tag=$1 model=$2 seed=$3 d=runs/$1_$2_seed$3
  shift 3
  [ -f "$d/DONE" ] || {
    python -m uav_trainer.inprocess --threads 1 --model "$model" --steps 30000 --seed "$seed" --layout-per-episode \
      --hfov-deg 90 --run-dir "$d" "$@" > "$d.log" 2>&1
    touch "$d/DONE"
  }
}
train_ten() {  # tag model [inprocess args]: ten seeds from FIRST (default 0), two at a time
  local tag=$1 model=$2 first=${FIRST:-0} s k
  shift 2
  for s in $(seq "$first" 2 $((first + 8))); do
    for k in "$s" $((s + 1)); do train "$tag" "$model" "$k" "$@" & done
    wait
  done
}
camera_args() {  # sets CAM: the 120 degree camera (or HFOV degrees, with the reward window WINDOW when set)
  CAM=(--sim-arg hfov_deg:=${HFOV:-120}.0)
  [ -n "${WINDOW:-}" ] && CAM+=(--sim-arg reward_window_fraction:=$WINDOW)
  return 0
}
eval_120() {  # folder crash-log(0|1) [evaluate args]: the random-start and the fixed-start tables, 120 degree
  # camera (or HFOV degrees, with the reward window WINDOW when set)
  local out=$1 log=() cam
  [ "$2" = 1 ] && log=(--crash-log)
  camera_args
  cam=("${CAM[@]}")
  shift 2
  $EVAL --inprocess "$@" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" "${cam[@]}" \
    "${log[@]}" --out "$out/varied_start"
  $EVAL --inprocess "$@" --worlds basic complex turbulent --steps 1000 "${cam[@]}" --out "$out/fixed_start"
}
weights() {  # tag -> sam=... cnn=... for every seed
  for m in sam cnn; do for s in $SEEDS; do echo "$m=runs/$1_${m}_seed$s/policy_$m.safetensors"; done; done
}
for seed in $SEEDS; do
  for model in sam cnn; do
    train layouts "$model" "$seed" &
    train fov120 "$model" "$seed" --hfov-deg 120 &
    wait
  done
done
# Two SAM-only experiments (seeds 0 and 1): the side-clearance penalty, and validation selection
# (the same training as runs/layouts_*, which it leaves bit-for-bit unchanged).
train clear sam 0 --clearance-m 1.0 &
train clear sam 1 --clearance-m 1.0 &
wait
train val sam 0 --validate-every 1000 &
train val sam 1 --validate-every 1000 &
wait
# Layout-per-episode training, 90 degrees: the paper's fixed start and random start headings.
mapfile -t W < <(weights layouts)
$EVAL --model sam --model cnn --weights "${W[@]}" --worlds basic complex turbulent random:101 random:102 random:103 \
  --steps 1000 --out docs/results/layout_training
$EVAL --model sam --model cnn --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --out docs/results/varied_start/layouts_training
# Basic-only (paper-protocol) training under random start headings.
mapfile -t W < <(weights paper)
$EVAL --model sam --model cnn --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --out docs/results/varied_start/paper_training
# The 120 degree camera: trained and flown at 120 degrees.
mapfile -t W < <(weights fov120)
$EVAL --model sam --model cnn --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out docs/results/fov120/fixed_start
$EVAL --model sam --model cnn --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --sim-arg hfov_deg:=120.0 --out docs/results/fov120/varied_start
$EVAL --model sam --weights runs/clear_sam_seed{0,1}/policy_sam.safetensors --worlds complex --steps 1000 "${VARIED[@]}" \
  --out docs/results/clearance
$EVAL --model sam --weights runs/val_sam_seed{0,1}/policy_sam_best.safetensors --worlds complex --steps 1000 "${VARIED[@]}" \
  --out docs/results/validation_selection
# Round 2, SAM at 120 degrees (layouts): longer training (80 000 steps), a moving average of the
# weights, learning-rate annealing, and a turn penalty (SAM and CNN). Trained two at a time.
train long sam 0 --hfov-deg 120 --steps 80000 --ema-decay 0.999 &
train long sam 1 --hfov-deg 120 --steps 80000 --ema-decay 0.999 &
wait
train long sam 2 --hfov-deg 120 --steps 80000 --ema-decay 0.999 &
train ema sam 0 --hfov-deg 120 --ema-decay 0.999 &
wait
train ema sam 1 --hfov-deg 120 --ema-decay 0.999 &
train anneal sam 0 --hfov-deg 120 --ema-decay 0.999 --lr-anneal &
wait
train anneal sam 1 --hfov-deg 120 --ema-decay 0.999 --lr-anneal &
train turn sam 0 --hfov-deg 120 --turn-penalty 1.0 &
wait
for pair in "sam 1" "sam 2" "cnn 0" "cnn 1"; do
  read -r m s <<< "$pair"
  train turn "$m" "$s" --hfov-deg 120 --turn-penalty 1.0 &
  if [ "$pair" = "sam 2" ] || [ "$pair" = "cnn 1" ]; then wait; fi
done
# Round 3, 120 degrees with the turn penalty: SAM with the flatten readout (an extension), and
# seeds 3 and 4 of the max-readout SAM and of the CNN (five seeds each).
for pair in "flatten 0" "flatten 1" "flatten 2" "flatten 3" "flatten 4" "cnn 2" "cnn 3" "cnn 4" "sam 3" "sam 4"; do
  read -r m s <<< "$pair"
  case $m in
    flatten) train turnflat sam "$s" --hfov-deg 120 --turn-penalty 1.0 --sam-readout flatten & ;;
    *) train turn "$m" "$s" --hfov-deg 120 --turn-penalty 1.0 & ;;
  esac
  case $pair in "flatten 1" | "flatten 3" | "cnn 2" | "cnn 4" | "sam 4") wait ;; esac
done
# and SAM with the turn penalty and learning-rate annealing, five seeds; then seeds 5-9 of SAM
# and CNN with the turn penalty (ten seeds each).
for s in 0 1 2 3 4; do
  train turnanneal sam "$s" --hfov-deg 120 --turn-penalty 1.0 --lr-anneal &
  case $s in 1 | 3 | 4) wait ;; esac
done
for s in 5 6 7 8 9; do
  train turn sam "$s" --hfov-deg 120 --turn-penalty 1.0 &
  train turn cnn "$s" --hfov-deg 120 --turn-penalty 1.0 &
  wait
done
# How the policies fly (turning share, area covered) beside the crashes: in-process (--inprocess
# gives the same rows as the ROS nodes; tested), random start headings.
B=(--inprocess --worlds basic complex turbulent --steps 1000 "${VARIED[@]}")
B120=("${B[@]}" --sim-arg hfov_deg:=120.0)
mapfile -t W < <(weights paper)
$EVAL "${B[@]}" --model sam --model cnn --weights "${W[@]}" --out docs/results/behaviour/paper_training
mapfile -t W < <(weights fov120)
$EVAL "${B120[@]}" --model sam --model cnn --weights "${W[@]}" --out docs/results/behaviour/fov120
$EVAL "${B120[@]}" --model sam --weights runs/long_sam_seed{0,1,2}/policy_sam.safetensors --out docs/results/behaviour/long_training
$EVAL "${B120[@]}" --model sam --weights runs/turn_sam_seed{0,1,2,3,4}/policy_sam.safetensors --out docs/results/behaviour/turn_penalty_sam
$EVAL "${B120[@]}" --model cnn --weights runs/turn_cnn_seed{0,1,2,3,4}/policy_cnn.safetensors --out docs/results/behaviour/turn_penalty_cnn
$EVAL "${B120[@]}" --model sam --weights runs/turnflat_sam_seed{0,1,2,3,4}/policy_sam.safetensors \
  --out docs/results/behaviour/turn_penalty_sam_flatten
$EVAL "${B120[@]}" --model sam --weights runs/turnanneal_sam_seed{0,1,2,3,4}/policy_sam.safetensors \
  --out docs/results/behaviour/turn_penalty_lr_anneal_sam
T=()
for m in sam cnn; do for s in 0 1 2 3 4 5 6 7 8 9; do T+=("$m=runs/turn_${m}_seed$s/policy_$m.safetensors"); done; done
$EVAL "${B120[@]}" --model sam --model cnn --weights "${T[@]}" --out docs/results/behaviour/turn_penalty_10_seeds
C120=(--inprocess --worlds complex --steps 1000 "${VARIED[@]}" --sim-arg hfov_deg:=120.0 --model sam)
$EVAL "${C120[@]}" --weights runs/ema_sam_seed{0,1}/policy_sam_ema.safetensors --out docs/results/behaviour/weight_average
$EVAL "${C120[@]}" --weights runs/anneal_sam_seed{0,1}/policy_sam.safetensors --out docs/results/behaviour/lr_anneal
$EVAL "${C120[@]}" --weights runs/anneal_sam_seed{0,1}/policy_sam_ema.safetensors --out docs/results/behaviour/lr_anneal_ema
# Round 4: seeds 10-19 of SAM and CNN with the turn penalty (twenty seeds each).
for s in 10 11 12 13 14 15 16 17 18 19; do
  train turn sam "$s" --hfov-deg 120 --turn-penalty 1.0 &
  train turn cnn "$s" --hfov-deg 120 --turn-penalty 1.0 &
  wait
done
T=()
for m in sam cnn; do for s in $(seq 0 19); do T+=("$m=runs/turn_${m}_seed$s/policy_$m.safetensors"); done; done
$EVAL "${B120[@]}" --model sam --model cnn --weights "${T[@]}" --out docs/results/behaviour/turn_penalty_20_seeds
$EVAL --inprocess --model sam --model cnn --weights "${T[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out docs/results/behaviour/turn_penalty_20_seeds_fixed_start
for t in turn_penalty_20_seeds turn_penalty_20_seeds_fixed_start; do
  python scripts/compare_models.py docs/results/behaviour/$t/results.csv > docs/results/behaviour/$t/comparison.md
done
# Choosing the weights shipped in round 4 among seeds 0-9 (docs/RESULTS.md, "Shipped weights"): the fewest
# crashes over the paper's fixed start (below) and turn_penalty_10_seeds picked SAM seed 4 and CNN
# seed 8; the validation layouts (below) picked seed 3 for both and were not used. Then package
# them with their camera (into runs/shipped_round4 since round 35's ensembles are packaged, at the end)
# and measure those files through the ROS nodes as policy_node flew them by default then.
T=()
for m in sam cnn; do for s in $(seq 0 9); do T+=("$m=runs/turn_${m}_seed$s/policy_$m.safetensors"); done; done
$EVAL --inprocess --model sam --model cnn --weights "${T[@]}" --worlds random:200 random:201 random:202 random:203 random:204 \
  --steps 1000 --start-yaw-jitter-deg 180 --repeats 2 --sim-arg hfov_deg:=120.0 --out docs/results/shipping/validation_layouts
$EVAL --inprocess --model sam --model cnn --weights "${T[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out docs/results/shipping/fixed_start
python scripts/package_weights.py runs/turn_sam_seed4/policy_sam.safetensors --model sam --camera-hfov-deg 120 --out runs/shipped_round4/sam
python scripts/package_weights.py runs/turn_cnn_seed8/policy_cnn.safetensors --model cnn --camera-hfov-deg 120 --out runs/shipped_round4/cnn
S4=(sam=runs/shipped_round4/sam/sam_00.safetensors cnn=runs/shipped_round4/cnn/cnn_00.safetensors)
$EVAL --model sam --model cnn --weights "${S4[@]}" --worlds basic complex turbulent --steps 1000 --out docs/results/shipped_round4/fixed_start
$EVAL --model sam --model cnn --weights "${S4[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --out docs/results/shipped_round4/varied_start
# Every ROS measurement again without ROS: the rows must agree.
X=scripts/crosscheck_eval.py
python $X docs/results/layout_training/results.csv
python $X docs/results/varied_start/layouts_training/results.csv "${VARIED[@]}"
python $X docs/results/varied_start/paper_training/results.csv "${VARIED[@]}"
python $X docs/results/fov120/fixed_start/results.csv --hfov-deg 120
python $X docs/results/fov120/varied_start/results.csv "${VARIED[@]}" --hfov-deg 120
python $X docs/results/clearance/results.csv "${VARIED[@]}"
python $X docs/results/validation_selection/results.csv "${VARIED[@]}"
python $X docs/results/shipped_round4/fixed_start/results.csv --hfov-deg 120
python $X docs/results/shipped_round4/varied_start/results.csv "${VARIED[@]}" --hfov-deg 120
# Round 5: a new start heading every training episode (--redraw-heading), SAM seeds 0-9, against
# round 4, where every layout starts at the seed's first heading draw. Then the main job (ROS)
# on its defaults of then (--recipe shipped, now --recipe single), seeds 0-2; evaluated in-process (equal to the ROS rows, tested).
train_ten redraw sam --hfov-deg 120 --turn-penalty 1.0 --redraw-heading
R=(runs/redraw_sam_seed{0..9}/policy_sam.safetensors)
R5=docs/results/round5_redraw_heading
$EVAL --inprocess --model sam --weights "${R[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --sim-arg hfov_deg:=120.0 --out $R5/varied_start
$EVAL --inprocess --model sam --weights "${R[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out $R5/fixed_start
python scripts/compare_models.py $R5/varied_start/results.csv docs/results/behaviour/turn_penalty_20_seeds/results.csv \
  --by run --a redraw_sam --b turn_sam > $R5/varied_start/comparison.md
python scripts/compare_models.py $R5/fixed_start/results.csv \
  docs/results/behaviour/turn_penalty_20_seeds_fixed_start/results.csv --by run --a redraw_sam --b turn_sam \
  > $R5/fixed_start/comparison.md
# Round 5's CNN arm: CNN seeds 0-9 with --redraw-heading, against round 4's twenty CNN seeds.
train_ten redraw cnn --hfov-deg 120 --turn-penalty 1.0 --redraw-heading
R=(runs/redraw_cnn_seed{0..9}/policy_cnn.safetensors)
$EVAL --inprocess --model cnn --weights "${R[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --sim-arg hfov_deg:=120.0 --out $R5/cnn/varied_start
$EVAL --inprocess --model cnn --weights "${R[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out $R5/cnn/fixed_start
python scripts/compare_models.py $R5/cnn/varied_start/results.csv docs/results/behaviour/turn_penalty_20_seeds/results.csv \
  --by run --a redraw_cnn --b turn_cnn > $R5/cnn/varied_start/comparison.md
python scripts/compare_models.py $R5/cnn/fixed_start/results.csv \
  docs/results/behaviour/turn_penalty_20_seeds_fixed_start/results.csv --by run --a redraw_cnn --b turn_cnn \
  > $R5/cnn/fixed_start/comparison.md
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R5/$p/results.csv $R5/cnn/$p/results.csv --by run --a redraw_sam --b redraw_cnn \
    > $R5/cnn/$p/sam_against_cnn.md
done
for s in 0 1 2; do
  install/uav_trainer/lib/uav_trainer/train --learning concurrent --recipe single --model sam --seed $s --run-dir runs/main_sam_seed$s
done
M=(runs/main_sam_seed{0,1,2}/policy_sam.safetensors)
$EVAL --inprocess --model sam --weights "${M[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --out docs/results/main_job/varied_start
$EVAL --inprocess --model sam --weights "${M[@]}" --worlds basic complex turbulent --steps 1000 \
  --out docs/results/main_job/fixed_start
# The same main job with a new start heading for every layout (as round 5), seed 0.
install/uav_trainer/lib/uav_trainer/train --learning concurrent --recipe single --model sam --run-dir runs/main_redraw_sam_seed0 --sim-arg redraw_start_heading:=true
$EVAL --inprocess --model sam --weights runs/main_redraw_sam_seed0/policy_sam.safetensors --worlds basic complex turbulent \
  --steps 1000 "${VARIED[@]}" --out docs/results/main_job_redraw/varied_start
$EVAL --inprocess --model sam --weights runs/main_redraw_sam_seed0/policy_sam.safetensors --worlds basic complex turbulent \
  --steps 1000 --out docs/results/main_job_redraw/fixed_start
# Round 6: round 4's setting with a 300-step time limit on training episodes (--max-episode-steps
# 300): SAM seeds 0-19, CNN seeds 0-9; compared with each other and with round 4.
for s in 0 2 4 6 8 10 12 14 16 18; do
  train tl300 sam "$s" --hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300 &
  train tl300 sam $((s + 1)) --hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300 &
  wait
done
for s in 0 2 4 6 8; do
  train tl300 cnn "$s" --hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300 &
  train tl300 cnn $((s + 1)) --hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300 &
  wait
done
T6=()
for s in $(seq 0 19); do T6+=("sam=runs/tl300_sam_seed$s/policy_sam.safetensors"); done
for s in $(seq 0 9); do T6+=("cnn=runs/tl300_cnn_seed$s/policy_cnn.safetensors"); done
R6=docs/results/round6_time_limit
$EVAL --inprocess --model sam --model cnn --weights "${T6[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --sim-arg hfov_deg:=120.0 --out $R6/varied_start
$EVAL --inprocess --model sam --model cnn --weights "${T6[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out $R6/fixed_start
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R6/$p/results.csv > $R6/$p/comparison.md
done
python scripts/compare_models.py $R6/varied_start/results.csv docs/results/behaviour/turn_penalty_20_seeds/results.csv \
  --by run --a tl300_sam --b turn_sam > $R6/varied_start/comparison_round4.md
python scripts/compare_models.py $R6/fixed_start/results.csv \
  docs/results/behaviour/turn_penalty_20_seeds_fixed_start/results.csv --by run --a tl300_sam --b turn_sam \
  > $R6/fixed_start/comparison_round4.md
install/uav_trainer/lib/uav_trainer/train --learning concurrent --recipe single --model sam --run-dir runs/main_tl300_sam_seed0 --sim-arg max_episode_steps:=300
$EVAL --inprocess --model sam --weights runs/main_tl300_sam_seed0/policy_sam.safetensors --worlds basic complex turbulent \
  --steps 1000 "${VARIED[@]}" --out docs/results/main_job_time_limit/varied_start
$EVAL --inprocess --model sam --weights runs/main_tl300_sam_seed0/policy_sam.safetensors --worlds basic complex turbulent \
  --steps 1000 --out docs/results/main_job_time_limit/fixed_start
# Round 6's SAM crashes with random starts, one row each (the same flights as the table above).
T6S=()
for s in $(seq 0 19); do T6S+=("runs/tl300_sam_seed$s/policy_sam.safetensors"); done
for w in basic complex; do
  $EVAL --inprocess --model sam --weights "${T6S[@]}" --worlds $w --steps 1000 "${VARIED[@]}" --sim-arg hfov_deg:=120.0 \
    --crash-log --out runs/r6_crashlog_$w
  mkdir -p $R6/crash_log && cp runs/r6_crashlog_$w/crashes.csv $R6/crash_log/sam_${w}_varied_start.csv
done

# Round 7: round 6's setting trained to 60 000 steps (SAM seeds 0-9), with weight snapshots at
# 30 000 (round 6's final weights: checked), 40 000 and 50 000; then a confirmation of the
# 40 000-step budget on fresh seeds: SAM seeds 10-19 trained to 40 000 (snapshot at 30 000).
for s in 0 2 4 6 8; do
  for k in "$s" $((s + 1)); do
    train tl300long sam "$k" --hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300 --steps 60000 \
      --save-weights-at 30000 40000 50000 &
  done
  wait
done
for s in 10 12 14 16 18; do
  for k in "$s" $((s + 1)); do
    train tl300at40k sam "$k" --hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300 --steps 40000 \
      --save-weights-at 30000 &
  done
  wait
done
for s in $(seq 0 19); do
  d=runs/tl300long_sam_seed$s
  [ "$s" -lt 10 ] || d=runs/tl300at40k_sam_seed$s
  cmp $d/policy_sam_step30000.safetensors runs/tl300_sam_seed$s/policy_sam.safetensors
done
R7=docs/results/round7_longer_training
for step in 40000 50000 60000; do
  W=()
  for s in $(seq 0 9); do
    f=runs/tl300long_sam_seed$s/policy_sam.safetensors
    [ "$step" = 60000 ] || f=runs/tl300long_sam_seed$s/policy_sam_step$step.safetensors
    W+=("$f")
  done
  $EVAL --inprocess --model sam --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
    --sim-arg hfov_deg:=120.0 --out $R7/step$step/varied_start
  $EVAL --inprocess --model sam --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 \
    --sim-arg hfov_deg:=120.0 --out $R7/step$step/fixed_start
done
W=()
for s in $(seq 10 19); do W+=("runs/tl300at40k_sam_seed$s/policy_sam.safetensors"); done
$EVAL --inprocess --model sam --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" \
  --sim-arg hfov_deg:=120.0 --out $R7/confirm_step40000_seeds10_19/varied_start
$EVAL --inprocess --model sam --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=120.0 --out $R7/confirm_step40000_seeds10_19/fixed_start
for p in varied_start fixed_start; do
  for step in 40000 50000 60000; do
    a=tl300long_sam_step$step
    [ "$step" = 60000 ] && a=tl300long_sam
    python scripts/compare_models.py $R7/step$step/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
      --by run --paired --a $a --b tl300_sam
    echo
  done > $R7/sam_against_30000_$p.md
  python scripts/compare_models.py $R7/confirm_step40000_seeds10_19/$p/results.csv \
    docs/results/round6_time_limit/$p/results.csv --by run --paired --a tl300at40k_sam --b tl300_sam \
    > $R7/confirm_step40000_seeds10_19/$p/against_30000.md
done

# Round 8: round 6's setting with an 84 x 84 network input and camera (--input-size 84: SAM sees
# 10 x 10 nodes instead of 8 x 8), SAM and CNN seeds 0-9; compared with each other and with round
# 6 (unpaired: other networks).
ROUND6=(--hfov-deg 120 --turn-penalty 1.0 --max-episode-steps 300)
round_both() {  # tag folder crash-log(0|1) suffix [inprocess args]: SAM and CNN seeds 0-9 in round 6's
  # setting plus the args, both tables, SAM against CNN (comparison.md) and each model against
  # round 6 (unpaired: {sam,cnn}_<suffix>.md)
  local tag=$1 out=$2 log=$3 suffix=$4 m s p w=()
  shift 4
  for m in sam cnn; do train_ten "$tag" "$m" "${ROUND6[@]}" "$@"; done
  for m in sam cnn; do
    for s in $(seq 0 9); do w+=("$m=runs/${tag}_${m}_seed$s/policy_$m.safetensors"); done
  done
  eval_120 "$out" "$log" --model sam --model cnn --weights "${w[@]}"
  for p in varied_start fixed_start; do
    python scripts/compare_models.py "$out/$p/results.csv" > "$out/$p/comparison.md"
    for m in sam cnn; do
      python scripts/compare_models.py "$out/$p/results.csv" docs/results/round6_time_limit/$p/results.csv \
        --by run --a "${tag}_$m" --b "tl300_$m" > "$out/$p/${m}_$suffix.md"
    done
  done
}
round_both in84 docs/results/round8_input84 0 against_64 --input-size 84

# Round 9: round 6's setting with half the training episodes starting at a random free place and
# heading (--random-start-fraction 0.5), SAM and CNN seeds 0-9; compared with each other and with
# round 6 (unpaired, against all of round 6's seeds), with a crash log of the random-start flights.
R9=docs/results/round9_random_starts
round_both rs50 $R9 1 against_round6 --random-start-fraction 0.5

model_ten() {  # tag model folder [inprocess args]: ten seeds from FIRST (default 0) of one model in
  # round 6's setting plus the args, trained and evaluated (both tables, with a crash log)
  local tag=$1 model=$2 out=$3 first=${FIRST:-0} s w=()
  shift 3
  train_ten "$tag" "$model" "${ROUND6[@]}" "$@"
  for s in $(seq "$first" $((first + 9))); do w+=("runs/${tag}_${model}_seed$s/policy_$model.safetensors"); done
  eval_120 "$out" 1 --model "$model" --weights "${w[@]}"
}
against_round6_cnn() {  # tag folder: per protocol, SAM (folder) against round 6's CNN
  local p
  for p in varied_start fixed_start; do
    python scripts/compare_models.py "$2"/$p/results.csv docs/results/round6_time_limit/$p/results.csv --by run \
      --a "$1_sam" --b tl300_cnn > "$2"/$p/against_round6_cnn.md
  done
}
sam_ten() {  # tag folder [inprocess args]: model_ten for SAM, each table against round 6's SAM and
  # CNN (unpaired: against_round6{,_cnn}.md)
  local tag=$1 out=$2 p
  shift 2
  model_ten "$tag" sam "$out" "$@"
  for p in varied_start fixed_start; do
    python scripts/compare_models.py "$out/$p/results.csv" docs/results/round6_time_limit/$p/results.csv \
      --by run --a "${tag}_sam" --b tl300_sam > "$out/$p/against_round6.md"
  done
  against_round6_cnn "$tag" "$out"
}

# Round 9, second part: a fifth of the training episodes from a random place (SAM seeds 0-9);
# compared with round 6 and with round 9's half.
sam_ten rs20 $R9/sam_fifth --random-start-fraction 0.2
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R9/sam_fifth/$p/results.csv $R9/$p/results.csv \
    --by run --a rs20_sam --b rs50_sam > $R9/sam_fifth/$p/against_half.md
done

# Round 10: a larger SAM (node features 96, two relational blocks, MLP 192: 191 605 parameters
# against 53 173) in round 6's setting, seeds 0-9; against round 6's SAM and CNN.
sam_ten big docs/results/round10_larger_sam --d-model 96 --relational-blocks 2 --mlp-hidden 192

# Round 11: n-step returns (--n-step 3: an extension, the paper learns from one step) in round 6's
# setting, SAM seeds 0-9 against round 6's SAM and CNN; then CNN seeds 0-9 (tables in cnn/) against
# round 6's CNN and against the 3-step SAM.
R11=docs/results/round11_n_step
sam_ten nstep3 $R11 --n-step 3
model_ten nstep3 cnn $R11/cnn --n-step 3
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R11/cnn/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
    --by run --a nstep3_cnn --b tl300_cnn > $R11/cnn/$p/against_round6.md
  python scripts/compare_models.py $R11/cnn/$p/results.csv $R11/$p/results.csv \
    --by run --a nstep3_cnn --b nstep3_sam > $R11/cnn/$p/against_sam.md
done

# Round 12: prioritized replay (--priority-alpha 0.6, importance-weight exponent 0.4 rising to 1:
# an extension, the paper samples uniformly) in round 6's setting, SAM seeds 0-9 against round 6's
# SAM and CNN.
sam_ten per06 docs/results/round12_prioritized --priority-alpha 0.6

# Round 13: slower exploration (epsilon 1 -> 0.05 over 20 000 steps instead of 10 000) in round 6's
# setting, SAM seeds 0-9 against round 6's SAM and CNN.
sam_ten eps20k docs/results/round13_slow_exploration --epsilon-decay-steps 20000

# Round 14: round 13's setting on fresh SAM seeds 10-19 (is round 13's fixed-start figure in Complex
# luck?); seeds 10-19 alone and pooled with round 13's 0-9, against round 6's SAM and CNN.
R14=docs/results/round14_slow_exploration_seeds10_19
for s in 10 12 14 16 18; do
  for k in "$s" $((s + 1)); do train eps20k sam "$k" "${ROUND6[@]}" --epsilon-decay-steps 20000 & done
  wait
done
W=()
for s in $(seq 10 19); do W+=("runs/eps20k_sam_seed$s/policy_sam.safetensors"); done
eval_120 $R14 1 --model sam --weights "${W[@]}"
for p in varied_start fixed_start; do
  for m in sam cnn; do
    f=against_round6
    [ "$m" = sam ] || f=against_round6_cnn
    python scripts/compare_models.py $R14/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
      --by run --a eps20k_sam --b "tl300_$m" > "$R14/$p/$f.md"
    python scripts/compare_models.py $R14/$p/results.csv docs/results/round13_slow_exploration/$p/results.csv \
      docs/results/round6_time_limit/$p/results.csv --by run --a eps20k_sam --b "tl300_$m" > "$R14/$p/pooled_$f.md"
  done
done

# Round 13's CNN arm: CNN seeds 0-9 with the slower exploration; against round 6's CNN, and SAM's
# twenty seeds of rounds 13 and 14 against it.
R13=docs/results/round13_slow_exploration
model_ten eps20k cnn $R13/cnn --epsilon-decay-steps 20000
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R13/cnn/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
    --by run --a eps20k_cnn --b tl300_cnn > $R13/cnn/$p/against_round6.md
  python scripts/compare_models.py $R13/cnn/$p/results.csv $R13/$p/results.csv $R14/$p/results.csv \
    --by run --a eps20k_sam --b eps20k_cnn > $R13/cnn/$p/sam_against_cnn.md
done

# Round 15: round 6's setting on fresh SAM seeds 20-31, flown one by one and as four ensembles of
# three consecutive seeds (evaluate --ensemble 3: the mean of their Q-values); the ensembles against
# their own members (paired) and all single seeds; the fresh seeds against round 6's (renamed so
# that the two sets of tl300_sam runs can be told apart); round 6's SAM pooled over 32 seeds.
R15=docs/results/round15_ensembles
for s in 20 22 24 26 28 30; do
  for k in "$s" $((s + 1)); do train tl300 sam "$k" "${ROUND6[@]}" & done
  wait
done
W=()
for s in $(seq 20 31); do W+=("runs/tl300_sam_seed$s/policy_sam.safetensors"); done
eval_120 $R15/single 1 --model sam --weights "${W[@]}"
eval_120 $R15/ensemble3 1 --model sam --ensemble 3 --weights "${W[@]}"
R6=docs/results/round6_time_limit
for p in varied_start fixed_start; do
  E=$R15/ensemble3/$p
  python scripts/compare_models.py $E/results.csv $R15/single/$p/results.csv --by run --a tl300_sam_ens3 --b tl300_sam \
    > $E/against_single.md
  python scripts/compare_models.py $E/results.csv $R15/single/$p/results.csv --by run --paired --a tl300_sam_ens3 \
    --b tl300_sam > $E/against_members.md
  python scripts/compare_models.py $E/results.csv $R15/single/$p/results.csv $R6/$p/results.csv --by run \
    --a tl300_sam_ens3 --b tl300_sam > $E/against_32_single.md
  sed 's/tl300_sam_seed/fresh_sam_seed/' $R15/single/$p/results.csv > /tmp/fresh_$p.csv
  python scripts/compare_models.py /tmp/fresh_$p.csv $R6/$p/results.csv --by run --a fresh_sam --b tl300_sam \
    | sed "s|/tmp/fresh_$p.csv|$R15/single/$p/results.csv (runs renamed fresh_sam)|" > $R15/single/$p/against_round6.md
done
$EVAL --inprocess --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" --sim-arg hfov_deg:=120.0 \
  --from-csv $R6/varied_start/results.csv $R15/single/varied_start/results.csv --out $R15/round6_32_seeds/varied_start
$EVAL --inprocess --worlds basic complex turbulent --steps 1000 --sim-arg hfov_deg:=120.0 \
  --from-csv $R6/fixed_start/results.csv $R15/single/fixed_start/results.csv --out $R15/round6_32_seeds/fixed_start
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R15/round6_32_seeds/$p/results.csv > $R15/round6_32_seeds/$p/comparison.md
done
# Round 15's reproducibility check: round 6's seed 0 trained again and flown; compare its rows with
# runs/tl300_sam_seed0's in docs/results/round6_time_limit/*/results.csv (equal only on round 6's machine).
train recheck sam 0 "${ROUND6[@]}"
eval_120 runs/recheck_eval 0 --model sam --weights runs/recheck_sam_seed0/policy_sam.safetensors

# Round 16: round 6's setting with every fourth training episode in Basic, the paper's training room
# (--world basic --world-every 4), SAM seeds 0-9; then every eighth (every8/); then the CNN arm of every
# fourth (cnn/). SAM against round 6's SAM and CNN and against round 6's setting pooled over 32 SAM
# seeds (round 15); every eighth against every fourth; the CNN against round 6's CNN and SAM against it.
R16=docs/results/round16_basic_mix
sam_ten r16basic4 $R16 --world basic --world-every 4
sam_ten r16basic8 $R16/every8 --world basic --world-every 8
model_ten r16basic4 cnn $R16/cnn --world basic --world-every 4
two_arms() {  # tag folder: per protocol, SAM (folder) against round 6's 32 SAM seeds, the CNN (folder/cnn)
  # against round 6's CNN, and SAM against the CNN
  local tag=$1 out=$2 p
  for p in varied_start fixed_start; do
    python scripts/compare_models.py $out/$p/results.csv $R15/round6_32_seeds/$p/results.csv --by run \
      --a ${tag}_sam --b tl300_sam > $out/$p/against_round6_32_seeds.md
    python scripts/compare_models.py $out/cnn/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
      --by run --a ${tag}_cnn --b tl300_cnn > $out/cnn/$p/against_round6.md
    python scripts/compare_models.py $out/$p/results.csv $out/cnn/$p/results.csv --by run \
      --a ${tag}_sam --b ${tag}_cnn > $out/cnn/$p/sam_against_cnn.md
  done
}
two_arms r16basic4 $R16
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R16/every8/$p/results.csv $R15/round6_32_seeds/$p/results.csv --by run \
    --a r16basic8_sam --b tl300_sam > $R16/every8/$p/against_round6_32_seeds.md
  python scripts/compare_models.py $R16/every8/$p/results.csv $R16/$p/results.csv --by run \
    --a r16basic8_sam --b r16basic4_sam > $R16/every8/$p/against_every4.md
done

# Round 17: round 6's setting on layouts where half of the boxes are 2-3 m partitions
# (--layout-partitions; Basic stays held out), SAM and CNN seeds 0-9; SAM against round 6's 32 SAM seeds,
# the CNN against round 6's CNN, and SAM against the CNN.
R17=docs/results/round17_partitions
sam_ten r17part $R17 --layout-partitions
model_ten r17part cnn $R17/cnn --layout-partitions
two_arms r17part $R17

# Round 18: round 16's recipe (every fourth training episode in Basic) on fresh seeds 10-19, SAM and CNN;
# pooled with round 16's seeds 0-9 (twenty per model): tables of both models (pooled_20_seeds/), SAM
# against CNN, SAM against round 6's 32 SAM seeds, CNN against round 6's CNN.
R18=docs/results/round18_basic_mix_seeds10_19
FIRST=10 model_ten r16basic4 sam $R18 --world basic --world-every 4
FIRST=10 model_ten r16basic4 cnn $R18/cnn --world basic --world-every 4
for p in varied_start fixed_start; do
  proto=()
  [ $p = varied_start ] && proto=("${VARIED[@]}")
  $EVAL --inprocess --worlds basic complex turbulent --steps 1000 "${proto[@]}" --sim-arg hfov_deg:=120.0 \
    --from-csv $R16/$p/results.csv $R18/$p/results.csv $R16/cnn/$p/results.csv $R18/cnn/$p/results.csv \
    --out $R18/pooled_20_seeds/$p
  python scripts/compare_models.py $R18/pooled_20_seeds/$p/results.csv --by run --a r16basic4_sam --b r16basic4_cnn \
    > $R18/pooled_20_seeds/$p/sam_against_cnn.md
  python scripts/compare_models.py $R18/pooled_20_seeds/$p/results.csv $R15/round6_32_seeds/$p/results.csv --by run \
    --a r16basic4_sam --b tl300_sam > $R18/pooled_20_seeds/$p/sam_against_round6_32_seeds.md
  python scripts/compare_models.py $R18/pooled_20_seeds/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
    --by run --a r16basic4_cnn --b tl300_cnn > $R18/pooled_20_seeds/$p/cnn_against_round6.md
done

# Round 19: choosing one training seed of each group on validation layouts that neither training nor the
# test worlds use (random:300..309 and random_partitions:300..309, 1000 steps each from a random heading),
# for round 16/18's twenty seeds per model (groups of four) and round 17's ten (groups of two); the chosen
# seeds' test tables (rows of the earlier evaluations), SAM against CNN on the chosen seeds and on the
# validation layouts themselves.
R19=docs/results/round19_validation_choice
VAL=()
for s in $(seq 300 309); do VAL+=("random:$s" "random_partitions:$s"); done
choose_on_validation() {  # tag last-seed group-size folder test-folders...
  local tag=$1 last=$2 group=$3 out=$4 m p W tests=() proto
  shift 4
  for m in sam cnn; do
    W=()
    for s in $(seq 0 "$last"); do W+=("runs/${tag}_${m}_seed$s/policy_$m.safetensors"); done
    [ -f runs/r19val_${tag}_$m/results.csv ] || $EVAL --inprocess --model $m --weights "${W[@]}" --worlds "${VAL[@]}" \
      --steps 1000 --start-yaw-jitter-deg 180 --sim-arg hfov_deg:=120.0 --out runs/r19val_${tag}_$m > runs/r19val_${tag}_$m.log &
  done
  wait
  $EVAL --inprocess --worlds "${VAL[@]}" --steps 1000 --start-yaw-jitter-deg 180 --sim-arg hfov_deg:=120.0 \
    --from-csv runs/r19val_${tag}_{sam,cnn}/results.csv --out $out/validation
  python scripts/compare_models.py $out/validation/results.csv --pool-worlds validation --by run \
    --a ${tag}_sam --b ${tag}_cnn > $out/validation/sam_against_cnn.md
  for p in "$@"; do tests+=("$p/varied_start/results.csv" "$p/fixed_start/results.csv"); done
  python scripts/select_runs.py $out/validation/results.csv --group "$group" --test "${tests[@]}" --out $out/chosen \
    > $out/selection.md
  for p in varied_start fixed_start; do
    proto=()
    [ $p = varied_start ] && proto=("${VARIED[@]}")
    $EVAL --inprocess --worlds basic complex turbulent --steps 1000 "${proto[@]}" --sim-arg hfov_deg:=120.0 \
      --from-csv $out/chosen/$p/results.csv --out $out/chosen/$p
    python scripts/compare_models.py $out/chosen/$p/results.csv --by run --a ${tag}_sam --b ${tag}_cnn \
      > $out/chosen/$p/sam_against_cnn.md
  done
}
choose_on_validation r16basic4 19 4 $R19 $R18/pooled_20_seeds
choose_on_validation r17part 9 2 $R19/round17_partitions $R17 $R17/cnn

# Round 20: round 6's setting with ten stacked depth frames instead of the paper's five (--frames 10), SAM
# and CNN seeds 0-9; SAM against round 6's 32 SAM seeds, the CNN against round 6's CNN, SAM against the CNN.
R20=docs/results/round20_frames10
model_ten r20frames10 sam $R20 --frames 10
model_ten r20frames10 cnn $R20/cnn --frames 10
two_arms r20frames10 $R20
# Round 19's choice on validation layouts for round 20's runs as well (groups of two).
choose_on_validation r20frames10 9 2 $R19/round20_frames10 $R20 $R20/cnn

# Round 21: round 6's setting with a two-layer conv trunk (--conv-channels 16 32), SAM and CNN seeds
# 0-9: SAM sees 16 x 16 nodes (each 4 x 4 px, 7.5 degrees of the 120 degree camera) instead of 8 x 8;
# SAM against round 6's 32 SAM seeds and round 6's CNN, the CNN against round 6's CNN, SAM against
# the CNN.
R21=docs/results/round21_nodes16
model_ten r21nodes16 sam $R21 --conv-channels 16 32
model_ten r21nodes16 cnn $R21/cnn --conv-channels 16 32
two_arms r21nodes16 $R21
against_round6_cnn r21nodes16 $R21

# Round 22: round 6's setting with twice the updates per environment step (--replay-ratio 0.5; the
# default 0.25 gives about 7 250 updates in 30 000 steps), SAM and CNN seeds 0-9; SAM against round 6's
# 32 SAM seeds and round 6's CNN, the CNN against round 6's CNN, SAM against the CNN.
R22=docs/results/round22_replay_ratio
model_ten r22rr05 sam $R22 --replay-ratio 0.5
model_ten r22rr05 cnn $R22/cnn --replay-ratio 0.5
two_arms r22rr05 $R22
against_round6_cnn r22rr05 $R22
# Round 22's SAM on ten more seeds (10-19), pooled with seeds 0-9 (sam_20_seeds/): against round 6's 32
# SAM seeds, round 6's CNN and round 22's CNN.
FIRST=10 model_ten r22rr05 sam $R22/sam_seeds10_19 --replay-ratio 0.5
pool_two() {  # folder-a folder-b out [evaluate args]: two tables (both protocols, random starts with a crash log)
  # joined into out (camera as eval_120's: HFOV, WINDOW)
  local p proto
  camera_args
  mkdir -p $3/varied_start
  { cat $1/varied_start/crashes.csv; tail -n +2 $2/varied_start/crashes.csv; } > $3/varied_start/crashes.csv
  for p in varied_start fixed_start; do
    proto=()
    [ $p = varied_start ] && proto=("${VARIED[@]}")
    $EVAL --inprocess --worlds basic complex turbulent --steps 1000 "${proto[@]}" "${CAM[@]}" \
      "${@:4}" --from-csv $1/$p/results.csv $2/$p/results.csv --out $3/$p
  done
}
sam_twenty() {  # tag folder cnn-folder cnn-tag: SAM seeds 0-9 (folder) and 10-19 (folder/sam_seeds10_19) pooled
  # in folder/sam_20_seeds with their crash log, against round 6's 32 SAM seeds, round 6's CNN and a CNN
  # (camera as eval_120's: HFOV, WINDOW)
  local tag=$1 out=$2 p
  pool_two $out $out/sam_seeds10_19 $out/sam_20_seeds
  for p in varied_start fixed_start; do
    python scripts/compare_models.py $out/sam_20_seeds/$p/results.csv $R15/round6_32_seeds/$p/results.csv --by run \
      --a ${tag}_sam --b tl300_sam > $out/sam_20_seeds/$p/against_round6_32_seeds.md
    python scripts/compare_models.py $out/sam_20_seeds/$p/results.csv $3/$p/results.csv --by run \
      --a ${tag}_sam --b $4 > $out/sam_20_seeds/$p/against_cnn.md
  done
  against_round6_cnn "$tag" $out/sam_20_seeds
}
sam_twenty r22rr05 $R22 $R22/cnn r22rr05_cnn

# Round 23: round 22's twice the updates (--replay-ratio 0.5) with round 16's every fourth training
# episode in Basic (--world basic --world-every 4), SAM seeds 0-19 (no CNN arm: neither change moved
# the CNN), pooled as round 22's: against round 6's 32 SAM seeds, round 6's CNN and round 22's CNN
# (against_cnn.md); against its two parents, round 22's and round 18's twenty SAM seeds, and round
# 18's twenty CNN seeds.
R23=docs/results/round23_basic_mix_rr05
R23ARGS=(--replay-ratio 0.5 --world basic --world-every 4)
model_ten r23mix05 sam $R23 "${R23ARGS[@]}"
FIRST=10 model_ten r23mix05 sam $R23/sam_seeds10_19 "${R23ARGS[@]}"
sam_twenty r23mix05 $R23 $R22/cnn r22rr05_cnn
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R23/sam_20_seeds/$p/results.csv $R22/sam_20_seeds/$p/results.csv --by run \
    --a r23mix05_sam --b r22rr05_sam > $R23/sam_20_seeds/$p/against_round22.md
  for m in sam cnn; do
    python scripts/compare_models.py $R23/sam_20_seeds/$p/results.csv $R18/pooled_20_seeds/$p/results.csv --by run \
      --a r23mix05_sam --b r16basic4_$m > $R23/sam_20_seeds/$p/against_round18_$m.md
  done
done

# Round 24: round 22's setting with a 150 degree camera (trained and flown at 150) and a reward window of
# 5 x 5 px (--reward-window-fraction 0.078, about the 120 degree camera's angle; the paper's 0.2 would
# see the floor 1.43 m ahead and punish every step), SAM seeds 0-9: against round 22's twenty SAM seeds
# and its CNN (both 120 degrees).
R24=docs/results/round24_fov150
HFOV=150 WINDOW=0.078 model_ten r24fov150 sam $R24 --replay-ratio 0.5 --hfov-deg 150 --reward-window-fraction 0.078
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R24/$p/results.csv $R22/sam_20_seeds/$p/results.csv --by run \
    --a r24fov150_sam --b r22rr05_sam > $R24/$p/against_round22.md
  python scripts/compare_models.py $R24/$p/results.csv $R22/cnn/$p/results.csv --by run \
    --a r24fov150_sam --b r22rr05_cnn > $R24/$p/against_round22_cnn.md
done

# Round 25: round 24 on SAM seeds 10-19 (sam_seeds10_19/) and a CNN arm, seeds 0-9 (cnn/) and 10-19
# (cnn/seeds10_19/), same camera and window. Each model's twenty seeds pooled (sam_20_seeds/,
# cnn_20_seeds/); SAM against round 6's 32 SAM seeds, round 6's CNN, its CNN (against_cnn.md, and
# seeds_at_bar.md: the seeds at or under the paper's 0 / 1 / 1), round 22's twenty SAM seeds and round
# 22's CNN; the CNN against round 6's and round 22's CNN.
R24ARGS=(--replay-ratio 0.5 --hfov-deg 150 --reward-window-fraction 0.078)
export HFOV=150 WINDOW=0.078
FIRST=10 model_ten r24fov150 sam $R24/sam_seeds10_19 "${R24ARGS[@]}"
model_ten r24fov150 cnn $R24/cnn "${R24ARGS[@]}"
FIRST=10 model_ten r24fov150 cnn $R24/cnn/seeds10_19 "${R24ARGS[@]}"
pool_two $R24/cnn $R24/cnn/seeds10_19 $R24/cnn_20_seeds
sam_twenty r24fov150 $R24 $R24/cnn_20_seeds r24fov150_cnn
unset HFOV WINDOW
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R24/sam_20_seeds/$p/results.csv $R24/cnn_20_seeds/$p/results.csv --by run \
    --a r24fov150_sam --b r24fov150_cnn --bar paper > $R24/sam_20_seeds/$p/seeds_at_bar.md
  python scripts/compare_models.py $R24/sam_20_seeds/$p/results.csv $R22/sam_20_seeds/$p/results.csv --by run \
    --a r24fov150_sam --b r22rr05_sam > $R24/sam_20_seeds/$p/against_round22.md
  for d in sam_20_seeds:sam cnn_20_seeds:cnn; do  # folder:model
    python scripts/compare_models.py $R24/${d%:*}/$p/results.csv $R22/cnn/$p/results.csv --by run \
      --a r24fov150_${d#*:} --b r22rr05_cnn > $R24/${d%:*}/$p/against_round22_cnn.md
  done
  python scripts/compare_models.py $R24/cnn_20_seeds/$p/results.csv docs/results/round6_time_limit/$p/results.csv \
    --by run --a r24fov150_cnn --b tl300_cnn > $R24/cnn_20_seeds/$p/against_round6.md
done

# Round 26: round 22's setting with random-shift augmentation (--augment-shift 4: each sampled state and
# next state moves by up to 4 px before an update, edges repeated, as DrQ), SAM seeds 0-19 pooled as round
# 22's (sam_20_seeds/): against round 6's 32 SAM seeds, round 6's CNN and round 22's CNN (against_cnn.md,
# and seeds_at_bar.md), and against round 22's twenty SAM seeds (the same recipe without the shifts).
R26=docs/results/round26_shift
R26ARGS=(--replay-ratio 0.5 --augment-shift 4)
model_ten r26shift4 sam $R26 "${R26ARGS[@]}"
FIRST=10 model_ten r26shift4 sam $R26/sam_seeds10_19 "${R26ARGS[@]}"
sam_twenty r26shift4 $R26 $R22/cnn r22rr05_cnn
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R26/sam_20_seeds/$p/results.csv $R22/cnn/$p/results.csv --by run \
    --a r26shift4_sam --b r22rr05_cnn --bar paper > $R26/sam_20_seeds/$p/seeds_at_bar.md
  python scripts/compare_models.py $R26/sam_20_seeds/$p/results.csv $R22/sam_20_seeds/$p/results.csv --by run \
    --a r26shift4_sam --b r22rr05_sam > $R26/sam_20_seeds/$p/against_round22.md
done

# Round 27: no training. The last three checkpoints of the runs of rounds 22, 25, 26, 16/18 and 23 (26 999,
# 28 999 and 30 000 steps; 24 997, 28 997, 30 000 in rounds 16/18), exported as weights
# (scripts/export_checkpoint.py) and flown as one policy each, the mean of their Q-values (evaluate
# --ensemble 3): against each run's own final network (paired), SAM against CNN trained the same way;
# the single snapshots at 26 999 and 28 999 steps of rounds 26 and 25's SAM as a control.
R27=docs/results/round27_snapshots
snap_eval() {  # tag model first last folder: the last three checkpoints of each seed's run as one policy
  local w=() s out f
  for s in $(seq "$3" "$4"); do
    out=$(python scripts/export_checkpoint.py runs/$1_$2_seed$s/checkpoints/ckpt-*)  # one "FILE: ..." line each
    while read -r f; do w+=("${f%%: *}"); done <<< "$out"
  done
  eval_120 "$5" 1 --model "$2" --ensemble 3 --weights "${w[@]}"
}
snap_eval r22rr05 sam 0 19 $R27/round22_sam
snap_eval r22rr05 cnn 0 9 $R27/round22_cnn
snap_eval r26shift4 sam 0 19 $R27/round26_sam
HFOV=150 WINDOW=0.078 snap_eval r24fov150 sam 0 19 $R27/round25_sam
HFOV=150 WINDOW=0.078 snap_eval r24fov150 cnn 0 19 $R27/round25_cnn
snap_eval r16basic4 sam 0 19 $R27/round18_sam  # rounds 16 and 18: checkpoints at 24 997, 28 997, 30 000 steps
snap_eval r16basic4 cnn 0 19 $R27/round18_cnn
snap_eval r23mix05 sam 0 19 $R27/round23_sam
for n in 26999 28999; do  # the control: SAM's earlier snapshots flown alone
  W=() V=()
  for s in $(seq 0 19); do
    W+=("runs/r26shift4_sam_seed$s/policy_sam_step$n.safetensors")
    V+=("runs/r24fov150_sam_seed$s/policy_sam_step$n.safetensors")
  done
  eval_120 $R27/round26_sam_step$n 1 --model sam --weights "${W[@]}"
  HFOV=150 WINDOW=0.078 eval_120 $R27/round25_sam_step$n 1 --model sam --weights "${V[@]}"
done
for p in varied_start fixed_start; do
  for r in round22_sam:r22rr05_sam:$R22/sam_20_seeds round22_cnn:r22rr05_cnn:$R22/cnn \
    round26_sam:r26shift4_sam:$R26/sam_20_seeds round25_sam:r24fov150_sam:$R24/sam_20_seeds \
    round25_cnn:r24fov150_cnn:$R24/cnn_20_seeds round18_sam:r16basic4_sam:$R18/pooled_20_seeds \
    round18_cnn:r16basic4_cnn:$R18/pooled_20_seeds round23_sam:r23mix05_sam:$R23/sam_20_seeds; do  # folder:run:its final networks' tables
    IFS=: read -r f run final <<< "$r"
    python scripts/compare_models.py $R27/$f/$p/results.csv $final/$p/results.csv --by run --paired \
      --a ${run}_snap3 --b $run > $R27/$f/$p/against_final.md
  done
  for r in round22_sam:r22rr05_sam:round22_cnn:r22rr05_cnn round26_sam:r26shift4_sam:round22_cnn:r22rr05_cnn \
    round25_sam:r24fov150_sam:round25_cnn:r24fov150_cnn round18_sam:r16basic4_sam:round18_cnn:r16basic4_cnn; do
    # SAM folder:run:CNN folder:run
    IFS=: read -r f run cf crun <<< "$r"
    python scripts/compare_models.py $R27/$f/$p/results.csv $R27/$cf/$p/results.csv --by run \
      --a ${run}_snap3 --b ${crun}_snap3 --bar paper > $R27/$f/$p/against_cnn.md
  done
  for n in 26999 28999; do
    for r in round26_sam:r26shift4_sam round25_sam:r24fov150_sam; do  # folder:run
      python scripts/compare_models.py $R27/${r%:*}/$p/results.csv $R27/${r%:*}_step$n/$p/results.csv --by run \
        --paired --a ${r#*:}_snap3 --b ${r#*:}_step$n > $R27/${r%:*}/$p/against_step$n.md
    done
  done
done
# The SAM sets pooled, snapshot ensembles against the final networks, paired: rounds 22, 25 and 26 (60
# seeds), and with rounds 18 and 23 (100). Seeds renumbered: round 22's as they are, round 25's + 100,
# 26's + 200, 18's + 300, 23's + 400.
pool_sam() {  # protocol folder:tag:offset ...: the tables' SAM rows as one table, on stdout
  local p=$1 r f t o
  shift
  head -1 "${1%%:*}/$p/results.csv"
  for r in "$@"; do
    IFS=: read -r f t o <<< "$r"
    grep "/${t}_sam_seed" "$f/$p/results.csv" | perl -pe "s/${t}_sam_seed(\d+)/'pool_sam_seed'.(\$1+$o)/ge"
  done
}
for p in varied_start fixed_start; do
  for n in 60 100; do
    mkdir -p $R27/sam_${n}_seeds/$p
    S=("$R27/round22_sam:r22rr05:0" "$R27/round25_sam:r24fov150:100" "$R27/round26_sam:r26shift4:200")
    F=("$R22/sam_20_seeds:r22rr05:0" "$R24/sam_20_seeds:r24fov150:100" "$R26/sam_20_seeds:r26shift4:200")
    if [ $n = 100 ]; then
      S+=("$R27/round18_sam:r16basic4:300" "$R27/round23_sam:r23mix05:400")
      F+=("$R18/pooled_20_seeds:r16basic4:300" "$R23/sam_20_seeds:r23mix05:400")
    fi
    pool_sam $p "${S[@]}" > $R27/sam_${n}_seeds/$p/snap3.csv
    pool_sam $p "${F[@]}" > $R27/sam_${n}_seeds/$p/final.csv
    python scripts/compare_models.py $R27/sam_${n}_seeds/$p/snap3.csv $R27/sam_${n}_seeds/$p/final.csv --by run \
      --paired --a pool_sam_snap3 --b pool_sam > $R27/sam_${n}_seeds/$p/against_final.md
  done
done

# Round 28: round 22's twenty SAM runs trained again with a weights snapshot every 1000 steps from
# 21 000 (the final networks and the 26 999 / 28 999-step ones come out byte-identical to round 22's
# and round 27's), flown as ensembles of the last five (26 000-30 000) and the last ten (21 000-30 000)
# networks; against round 27's three (26 999, 28 999, 30 000) and the final networks alone, paired by
# seed. Each table measured in two halves (seeds 0-9, 10-19: two at a time on 2 cores) and joined.
R28=docs/results/round28_more_snapshots
SNAPS=(21000 22000 23000 24000 25000 26000 26999 27000 28000 28999 29000)
for s in $(seq 0 2 18); do
  for k in "$s" $((s + 1)); do
    train r28snap sam "$k" "${ROUND6[@]}" --replay-ratio 0.5 --save-weights-at "${SNAPS[@]}" &
  done
  wait
done
for s in $(seq 0 19); do  # the same training as round 22's, bit for bit
  cmp runs/r28snap_sam_seed$s/policy_sam.safetensors runs/r22rr05_sam_seed$s/policy_sam.safetensors
done
snap_group() {  # tag K seed...: the last K snapshots of each seed's run (K = 5: 26 000 on; 10: 21 000 on;
  # STEPS, when set, names the snapshots flown before the final network instead; MODEL: sam unless set)
  local tag=$1 s n m=${MODEL:-sam} steps=${STEPS:-$(seq $((31000 - 1000 * $2)) 1000 29000)}
  shift 2
  for s in "$@"; do
    for n in $steps; do echo "runs/${tag}_${m}_seed$s/policy_${m}_step$n.safetensors"; done
    echo "runs/${tag}_${m}_seed$s/policy_$m.safetensors"
  done
}
snap_halves() {  # tag K folder N: seeds 0-19's (FIRST to FIRST + 19's; or the twenty seeds ORDER lists, in
  # that order) last K snapshots (of MODEL's runs: sam unless set) flown N networks to a policy (N = K: one
  # seed's; 2K: two neighbours in the order together, seeds 2j and 2j+1 by default; camera as eval_120's; on
  # their mean Q, or by the ensemble rule RULE when set), measured in two halves (the first ten seeds, the
  # last ten) and joined into folder/{varied,fixed}_start
  local tag=$1 k=$2 out=$3 n=$4 f=${FIRST:-0} h p V W
  local order=(${ORDER:-$(seq "$f" $((f + 19)))})
  [ ${#order[@]} = 20 ] || { echo "snap_halves: ORDER lists ${#order[@]} seeds, not 20" >&2; return 1; }
  local a=seeds${order[0]}_${order[9]} b=seeds${order[10]}_${order[19]}
  for h in "${order[*]:0:10}" "${order[*]:10:10}"; do
    mapfile -t W < <(snap_group "$tag" "$k" $h)
    eval_120 "$out/seeds${h%% *}_${h##* }" 1 --model "${MODEL:-sam}" --ensemble "$n" ${RULE:+--ensemble-rule "$RULE"} --weights "${W[@]}"
  done
  camera_args
  for p in varied_start fixed_start; do
    V=(); [ $p = varied_start ] && V=("${VARIED[@]}")
    $EVAL --from-csv $out/{$a,$b}/$p/results.csv "${V[@]}" "${CAM[@]}" --inprocess --ensemble "$n" \
      ${RULE:+--ensemble-rule "$RULE"} --out $out/$p
  done
  { cat $out/$a/varied_start/crashes.csv; tail -n +2 $out/$b/varied_start/crashes.csv; } > $out/varied_start/crashes.csv
  rm -r "$out/$a" "$out/$b"
}
snap_ensembles() {  # tag K folder snap3-folder:tag final-folder:tag cnn-folder:tag: each seed's last K snapshots
  # as one policy (snap_halves), against the same runs' last three checkpoints and final networks
  # (paired by seed unless PAIRED is set empty), and against a CNN
  local tag=$1 k=$2 out=$3 paired=${PAIRED---paired} p
  snap_halves "$tag" "$k" "$out" "$k"
  for p in varied_start fixed_start; do
    python scripts/compare_models.py $out/$p/results.csv ${4%:*}/$p/results.csv --by run $paired \
      --a ${tag}_sam_snap$k --b ${4#*:} > $out/$p/against_snap3.md
    python scripts/compare_models.py $out/$p/results.csv ${5%:*}/$p/results.csv --by run $paired \
      --a ${tag}_sam_snap$k --b ${5#*:} > $out/$p/against_final.md
    python scripts/compare_models.py $out/$p/results.csv ${6%:*}/$p/results.csv --by run \
      --a ${tag}_sam_snap$k --b ${6#*:} --bar paper > $out/$p/against_cnn.md
  done
}
for k in 5 10; do
  snap_ensembles r28snap $k $R28/snap$k $R27/round22_sam:r22rr05_sam_snap3 $R22/sam_20_seeds:r22rr05_sam \
    $R27/round22_cnn:r22rr05_cnn_snap3
done

# Round 29: round 25's twenty SAM runs (150 degree camera, 5 x 5 px reward window) trained again with
# round 28's snapshots, flown as ensembles of the last ten networks (21 000-30 000); against round 27's
# three checkpoints of round 25's runs, round 25's final networks and round 25's CNN (three
# checkpoints), unpaired: unlike round 28's, these runs did not come out identical to the earlier ones
# (their final networks fly other rows than round 25's, which were trained on another machine: the code
# at both commits trains byte-identical weights on one machine; RESULTS, round 29).
R29=docs/results/round29_fov150_snapshots
for s in $(seq 0 2 18); do
  for k in "$s" $((s + 1)); do
    train r29snap150 sam "$k" "${ROUND6[@]}" "${R24ARGS[@]}" --save-weights-at "${SNAPS[@]}" &
  done
  wait
done
export HFOV=150 WINDOW=0.078
mapfile -t W < <(for s in $(seq 0 19); do echo "runs/r29snap150_sam_seed$s/policy_sam.safetensors"; done)
camera_args
$EVAL --inprocess --model sam --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 "${CAM[@]}" \
  --out $R29/final/fixed_start  # the final networks alone: other rows than round 25's
PAIRED= snap_ensembles r29snap150 10 $R29/snap10 $R27/round25_sam:r24fov150_sam_snap3 $R24/sam_20_seeds:r24fov150_sam \
  $R27/round25_cnn:r24fov150_cnn_snap3

# Round 30: round 29's runs flown two seeds to a policy: seeds 2j and 2j+1, ten snapshots each (20
# networks, ten policies); against the same seeds' ten-snapshot ensembles (paired: a pair against the
# mean of its two seeds) and round 25's CNN (three checkpoints).
R30=docs/results/round30_seed_pairs
snap_halves r29snap150 10 $R30 20
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R30/$p/results.csv $R29/snap10/$p/results.csv --by run --paired \
    --a r29snap150_sam_snap10_ens2 --b r29snap150_sam_snap10 > $R30/$p/against_snap10.md
  python scripts/compare_models.py $R30/$p/results.csv $R27/round25_cnn/$p/results.csv --by run \
    --a r29snap150_sam_snap10_ens2 --b r24fov150_cnn_snap3 --bar paper > $R30/$p/against_cnn.md
done

# Round 31: round 29's runs flown as round 27 flew round 25's (26 999, 28 999 and 30 000 steps as one
# policy): a second draw of the set that met the paper's bar from the fixed start; against round 25's
# (unpaired), the same runs' ten snapshots (paired) and round 25's CNN; then both draws pooled (40 seeds).
R31=docs/results/round31_snap3_second_draw
STEPS="26999 28999" snap_halves r29snap150 3 $R31 3
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R31/$p/results.csv $R27/round25_sam/$p/results.csv --by run \
    --a r29snap150_sam_snap3 --b r24fov150_sam_snap3 > $R31/$p/against_round25.md
  python scripts/compare_models.py $R31/$p/results.csv $R29/snap10/$p/results.csv --by run --paired \
    --a r29snap150_sam_snap3 --b r29snap150_sam_snap10 > $R31/$p/against_snap10.md
  python scripts/compare_models.py $R31/$p/results.csv $R27/round25_cnn/$p/results.csv --by run \
    --a r29snap150_sam_snap3 --b r24fov150_cnn_snap3 --bar paper > $R31/$p/against_cnn.md
done
pooled_forty() {  # folder N cnn-folder:label folder:tag:offset ...: for each protocol, the SAM rows of the
  # folders' tables (ensembles of N) as one table in folder/pooled_40_seeds (pool_sam, evaluate --from-csv), against the CNN
  local out=$1/pooled_40_seeds n=$2 cnn=$3 p V
  shift 3
  for p in varied_start fixed_start; do
    V=(); [ $p = varied_start ] && V=("${VARIED[@]}")
    mkdir -p $out/$p
    pool_sam $p "$@" > $out/$p/pool.csv
    $EVAL --from-csv $out/$p/pool.csv "${V[@]}" "${CAM[@]}" --inprocess --ensemble "$n" --out $out/$p
    rm $out/$p/pool.csv
    python scripts/compare_models.py $out/$p/results.csv ${cnn%:*}/$p/results.csv --by run \
      --a pool_sam_snap$n --b ${cnn#*:} --bar paper > $out/$p/against_cnn.md
  done
}
pooled_forty $R31 3 $R27/round25_cnn:r24fov150_cnn_snap3 "$R27/round25_sam:r24fov150:0" "$R31:r29snap150:100"
unset HFOV WINDOW

# Round 32: round 28's recipe (round 22's command, 120 degree camera) on twenty fresh SAM seeds (20-39),
# with round 28's snapshots, flown as ensembles of the last ten networks: a second draw of the set that
# met the paper's bar with random starts; against round 28's (unpaired) and round 22's CNN (three
# checkpoints), then both draws pooled (40 seeds). Then the odds that a set of twenty seeds of each
# recipe meets the bar (scripts/bar_odds.py: sets drawn from a recipe's seeds, both protocols at once).
R32=docs/results/round32_snap10_second_draw
for f in 20 30; do
  FIRST=$f train_ten r32snap sam "${ROUND6[@]}" --replay-ratio 0.5 --save-weights-at "${SNAPS[@]}"
done
FIRST=20 snap_halves r32snap 10 $R32 10
camera_args
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R32/$p/results.csv $R28/snap10/$p/results.csv --by run \
    --a r32snap_sam_snap10 --b r28snap_sam_snap10 > $R32/$p/against_round28.md
  python scripts/compare_models.py $R32/$p/results.csv $R27/round22_cnn/$p/results.csv --by run \
    --a r32snap_sam_snap10 --b r22rr05_cnn_snap3 --bar paper > $R32/$p/against_cnn.md
done
pooled_forty $R32 10 $R27/round22_cnn:r22rr05_cnn_snap3 "$R28/snap10:r28snap:0" "$R32:r32snap:0"
mkdir -p $R32/odds
odds() {  # out.md folder [bar_odds args]: twenty-seed sets drawn from folder/{fixed,varied}_start, into out.md
  local out=$1 dir=$2
  shift 2
  python scripts/bar_odds.py $dir/{fixed_start,varied_start}/results.csv --labels fixed random --set-size 20 "$@" > "$out"
}
odds $R32/odds/round25_sam_snap3.md $R27/round25_sam
odds $R32/odds/round29_sam_snap3.md $R31
odds $R32/odds/fov150_sam_snap3_40_seeds.md $R31/pooled_40_seeds
odds $R32/odds/round18_sam_snap3.md $R27/round18_sam
odds $R32/odds/round28_sam_snap10.md $R28/snap10
odds $R32/odds/round32_sam_snap10.md $R32
odds $R32/odds/fov120_sam_snap10_40_seeds.md $R32/pooled_40_seeds
odds $R32/odds/round25_cnn_snap3.md $R27/round25_cnn --model cnn

# Round 33: the same ten-snapshot ensembles (round 32's runs, 120 degrees, seeds 20-39; round 29's runs,
# 150 degrees, seeds 0-19) flown on each action's lowest Q-value over the ten networks (evaluate
# --ensemble-rule min, a pessimistic rule) instead of their mean; paired by seed against the mean rule
# (rounds 32 and 29: the same networks) and against the CNN; odds of twenty-seed sets.
R33=docs/results/round33_ensemble_min
FIRST=20 RULE=min snap_halves r32snap 10 $R33/fov120 10
export HFOV=150 WINDOW=0.078
RULE=min snap_halves r29snap150 10 $R33/fov150 10
unset HFOV WINDOW
for p in varied_start fixed_start; do
  for f in fov120:$R32:$R27/round22_cnn fov150:$R29/snap10:$R27/round25_cnn; do
    IFS=: read -r cam mean cnn <<< "$f"
    python scripts/compare_models.py $R33/$cam/$p/results.csv $mean/$p/results.csv --by file --paired \
      --a min --b mean --bar paper > $R33/$cam/$p/against_mean.md
    python scripts/compare_models.py $R33/$cam/$p/results.csv $cnn/$p/results.csv --by model --a sam --b cnn \
      --bar paper > $R33/$cam/$p/against_cnn.md
  done
done
for cam in fov120 fov150; do
  odds $R33/$cam/odds.md $R33/$cam
done
odds $R33/fov150/odds_round29_mean.md $R29/snap10  # the same runs on the mean (round 32's odds tables have round 32's)

# Round 34: two seeds to a policy again (round 30's method: ten snapshots of each, 20 networks), on other
# pairs: round 32's runs (120 degrees) as (20, 21) ... (38, 39), and round 29's runs (150 degrees) paired the
# other way, (1, 2) ... (17, 18), (19, 0); each against its seeds' ten-snapshot ensembles (paired: a pair
# against the mean of its two seeds) and the CNN; the 150 degree pairs also against round 30's (other pairs
# of the same runs, so unpaired).
R34=docs/results/round34_seed_pairs_again
FIRST=20 snap_halves r32snap 10 $R34/fov120 20
export HFOV=150 WINDOW=0.078
ORDER="$(seq -s ' ' 1 19) 0" snap_halves r29snap150 10 $R34/fov150 20
unset HFOV WINDOW
for p in varied_start fixed_start; do
  for f in fov120:$R32:r32snap:$R27/round22_cnn fov150:$R29/snap10:r29snap150:$R27/round25_cnn; do
    IFS=: read -r cam single tag cnn <<< "$f"
    python scripts/compare_models.py $R34/$cam/$p/results.csv $single/$p/results.csv --by run --paired \
      --a ${tag}_sam_snap10_ens2 --b ${tag}_sam_snap10 --bar paper > $R34/$cam/$p/against_snap10.md
    python scripts/compare_models.py $R34/$cam/$p/results.csv $cnn/$p/results.csv --by model --a sam --b cnn \
      --bar paper > $R34/$cam/$p/against_cnn.md
  done
  python scripts/compare_models.py $R34/fov150/$p/results.csv $R30/$p/results.csv --by file --a round34 \
    --b round30 --bar paper > $R34/fov150/$p/against_round30.md
done
# How much of each ensemble set's crash rate is one failure counted again (crashes beyond the first at a
# site; scripts/repeat_failures.py), every SAM set of rounds 27-34 flown on the mean Q, and the CNN's.
mkdir -p $R34/repeats
for p in fixed_start varied_start; do
  python scripts/repeat_failures.py $R27/round{22,25,18,26,23}_sam/$p/results.csv $R28/snap10/$p/results.csv \
    $R29/snap10/$p/results.csv $R31/$p/results.csv $R32/$p/results.csv $R30/$p/results.csv $R34/fov1{20,50}/$p/results.csv \
    --labels r27_round22 r27_round25 r27_round18 r27_round26 r27_round23 r28_snap10 r29_snap10 r31_snap3 r32_snap10 \
    r30_pairs r34_pairs_fov120 r34_pairs_fov150 > $R34/repeats/sam_$p.md
  python scripts/repeat_failures.py $R27/round{22,25,18}_cnn/$p/results.csv --model cnn \
    --labels r27_round22 r27_round25 r27_round18 > $R34/repeats/cnn_$p.md
done
python scripts/repeat_failures.py $R22/sam_20_seeds/fixed_start/results.csv $R24/sam_20_seeds/fixed_start/results.csv \
  $R33/fov1{20,50}/fixed_start/results.csv --labels round22_final round25_final r33_min_fov120 r33_min_fov150 \
  > $R34/repeats/sam_fixed_start_final_and_min.md  # single networks, and the lowest-Q rule, for comparison

# Round 35: round 29's recipe (150 degree camera, 5 x 5 px reward window, replay ratio 0.5, ten snapshots)
# with round 16's Basic episodes (every fourth training episode flies Basic: --world basic --world-every 4),
# SAM seeds 0-19; each seed's last ten networks as one policy, against round 29's (unpaired: other
# training), round 25's CNN (three checkpoints), and how much of each crash rate is one failure repeated.
R35=docs/results/round35_fov150_basic_episodes
train_basic150() {  # model first: round 35's command on twenty seeds from first, two at a time (train_ten twice)
  local f
  for f in "$2" $(($2 + 10)); do
    FIRST=$f train_ten r35basic150 "$1" "${ROUND6[@]}" "${R24ARGS[@]}" --world basic --world-every 4 --save-weights-at "${SNAPS[@]}"
  done
}
train_basic150 sam 0
export HFOV=150 WINDOW=0.078
snap_halves r35basic150 10 $R35 10
unset HFOV WINDOW
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R35/$p/results.csv $R29/snap10/$p/results.csv --by file --a round35 \
    --b round29 --bar paper > $R35/$p/against_round29.md
  python scripts/compare_models.py $R35/$p/results.csv $R27/round25_cnn/$p/results.csv --by model --a sam --b cnn \
    --bar paper > $R35/$p/against_cnn.md
  python scripts/repeat_failures.py $R35/$p/results.csv $R29/snap10/$p/results.csv --labels round35 round29 \
    > $R35/$p/repeats.md
done
python scripts/crash_map.py --crashes $R35/varied_start/crashes.csv --out $R35/varied_start/crash_map.png

# Round 36: round 35's command on twenty fresh SAM seeds (20-39), flown the same way: a second draw of the
# first set that met the paper's bar under both protocols; against round 35 (unpaired: other seeds) and
# round 25's CNN, repeats and crash map; then both draws pooled (40 seeds, the tables' rows as they are)
# against the CNN, and the odds that twenty seeds of this recipe meet the bar (each draw and the pool).
R36=docs/results/round36_basic_episodes_second_draw
train_basic150 sam 20
export HFOV=150 WINDOW=0.078
FIRST=20 snap_halves r35basic150 10 $R36 10
camera_args
unset HFOV WINDOW
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R36/$p/results.csv $R35/$p/results.csv --by file --a round36 \
    --b round35 --bar paper > $R36/$p/against_round35.md
  python scripts/compare_models.py $R36/$p/results.csv $R27/round25_cnn/$p/results.csv --by model --a sam --b cnn \
    --bar paper > $R36/$p/against_cnn.md
  python scripts/repeat_failures.py $R36/$p/results.csv $R35/$p/results.csv --labels round36 round35 > $R36/$p/repeats.md
done
python scripts/crash_map.py --crashes $R36/varied_start/crashes.csv --out $R36/varied_start/crash_map.png
for p in varied_start fixed_start; do
  V=(); [ $p = varied_start ] && V=("${VARIED[@]}")
  mkdir -p $R36/pooled_40_seeds/$p
  { cat $R35/$p/results.csv; tail -n +2 $R36/$p/results.csv; } > $R36/pooled_40_seeds/$p/pool.csv
  $EVAL --from-csv $R36/pooled_40_seeds/$p/pool.csv "${V[@]}" "${CAM[@]}" --inprocess --ensemble 10 --out $R36/pooled_40_seeds/$p
  rm $R36/pooled_40_seeds/$p/pool.csv
  python scripts/compare_models.py $R36/pooled_40_seeds/$p/results.csv $R27/round25_cnn/$p/results.csv --by model \
    --a sam --b cnn --bar paper > $R36/pooled_40_seeds/$p/against_cnn.md
done
mkdir -p $R36/odds
odds $R36/odds/round35.md $R35
odds $R36/odds/round36.md $R36
odds $R36/odds/pooled_40_seeds.md $R36/pooled_40_seeds

# Round 37: round 35's command for the CNN on seeds 0-19, flown the same way (each seed's last ten networks as
# one policy, 150 degree camera, both protocols): "CNN measured the same way"; against the 40 pooled SAM seeds
# of rounds 35 and 36, against round 35's SAM seeds 0-19 alone, against round 27's CNN (round 25's recipe);
# repeats, crash map, and the odds that twenty CNN seeds of this recipe meet the paper's bar.
R37=docs/results/round37_cnn_basic_episodes
train_basic150 cnn 0
HFOV=150 WINDOW=0.078 MODEL=cnn snap_halves r35basic150 10 $R37 10
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R36/pooled_40_seeds/$p/results.csv $R37/$p/results.csv --by model --a sam --b cnn \
    --bar paper > $R37/$p/against_sam_40.md
  python scripts/compare_models.py $R35/$p/results.csv $R37/$p/results.csv --by model --a sam --b cnn \
    --bar paper > $R37/$p/against_sam_round35.md
  python scripts/compare_models.py $R37/$p/results.csv $R27/round25_cnn/$p/results.csv --by file --a round37_cnn \
    --b round27_cnn --bar paper > $R37/$p/against_round27_cnn.md
  python scripts/repeat_failures.py $R37/$p/results.csv $R27/round25_cnn/$p/results.csv --model cnn \
    --labels round37 round27 > $R37/$p/repeats.md
done
python scripts/crash_map.py --crashes $R37/varied_start/crashes.csv --out $R37/varied_start/crash_map.png
mkdir -p $R37/odds
odds $R37/odds/cnn.md $R37 --model cnn

# Round 38: the main job's ensemble recipe (`train --recipe ensemble`: round 35's recipe over ROS, three node
# processes, lockstep capped at 30 steps/s), SAM seeds 0-2, 30 000 steps each; each run's ten files (nine
# snapshots and the final weights) flown as one policy as rounds 35-37; against the forty in-process SAM seeds
# of rounds 35 and 36 (ROS training is not bit-identical to in-process, so the same seeds are not the same runs).
R38=docs/results/round38_main_job_ensemble
ros_ensemble() {  # tag folder "seeds" [train args]: `train --recipe ensemble` on those SAM seeds into
  # runs/<tag>_sam_seed<s>, each run's ten files flown as one policy (150 degree camera, both protocols) into folder
  local tag=$1 out=$2 seeds=$3 s W
  shift 3
  for s in $seeds; do
    install/uav_trainer/lib/uav_trainer/train --learning concurrent --recipe ensemble --model sam --seed $s --run-dir runs/${tag}_sam_seed$s --no-resume "$@"
  done
  mapfile -t W < <(snap_group "$tag" 10 $seeds)
  HFOV=150 WINDOW=0.078 eval_120 "$out" 1 --model sam --ensemble 10 --weights "${W[@]}"
}
ros_ensemble r38ros $R38 "0 1 2"
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R38/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a round38_ros \
    --b inprocess_40 --bar paper > $R38/$p/against_inprocess_40.md
done
python scripts/repeat_failures.py $R38/fixed_start/results.csv $R36/pooled_40_seeds/fixed_start/results.csv \
  --labels round38_ros inprocess_40 > $R38/fixed_start/repeats.md

# Round 39 (pilot): round 38's three runs with the weights pushed to the policy after every update
# (push_interval_updates:=1, so the policy acts on the newest weights, as in-process), flown the same way; against
# round 38 (paired by seed), the forty in-process seeds, and the fixed-start repeats of all three.
R39=docs/results/round39_push_every_update
ros_ensemble r39push1 $R39 "0 1 2" --trainer-arg push_interval_updates:=1
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R39/$p/results.csv $R38/$p/results.csv --by file --paired --a push_every_update \
    --b push_every_50 --bar paper > $R39/$p/against_round38.md
  python scripts/compare_models.py $R39/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a push_every_update \
    --b inprocess_40 --bar paper > $R39/$p/against_inprocess_40.md
done
python scripts/repeat_failures.py $R39/fixed_start/results.csv $R38/fixed_start/results.csv \
  $R36/pooled_40_seeds/fixed_start/results.csv --labels push_every_update push_every_50 inprocess_40 > $R39/fixed_start/repeats.md

# Round 40: rounds 38 and 39 on SAM seeds 3-5 (design fixed before any flight: $R40/design.md; here the arms
# ran interleaved by seed, one run at a time), each arm joined with its seeds 0-2 and the arms compared paired
# by seed; each arm against the forty in-process seeds, and the fixed-start repeats of both.
R40=docs/results/round40_push_interval_six_seeds
ros_ensemble r40push50 runs/r40push50eval "3 4 5"
ros_ensemble r40push1 runs/r40push1eval "3 4 5" --trainer-arg push_interval_updates:=1
HFOV=150 WINDOW=0.078 pool_two $R38 runs/r40push50eval $R40/push_every_50 --ensemble 10
HFOV=150 WINDOW=0.078 pool_two $R39 runs/r40push1eval $R40/push_every_update --ensemble 10
for arm in push_every_50 push_every_update; do
  for p in varied_start fixed_start; do
    python scripts/compare_models.py $R40/$arm/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a $arm \
      --b inprocess_40 --bar paper > $R40/$arm/$p/against_inprocess_40.md
  done
done
for p in varied_start fixed_start; do
  python scripts/compare_models.py $R40/push_every_update/$p/results.csv $R40/push_every_50/$p/results.csv --by file --paired \
    --a push_every_update --b push_every_50 --bar paper > $R40/against_push_every_50_$p.md
done
python scripts/repeat_failures.py $R40/push_every_update/fixed_start/results.csv $R40/push_every_50/fixed_start/results.csv \
  $R36/pooled_40_seeds/fixed_start/results.csv --labels push_every_update push_every_50 inprocess_40 > $R40/fixed_start_repeats.md

# Round 41: round 35's in-process command with --act-on-pushes 50 (the agent acts on a copy of the network taken
# every 50 updates, as policy_node acts on trainer_node's pushes), SAM seeds 0-9 (design fixed before any flight:
# $R41/design.md); each run's ten files as one policy, both protocols, in two halves joined; against round 35
# (paired by seed), the forty in-process seeds and the twelve ROS runs of rounds 38-40 (pooled; both with the
# count of policies without a fixed-start Complex crash), and the fixed-start repeats.
R41=docs/results/round41_act_on_pushes
train_ten r41pushed sam "${ROUND6[@]}" "${R24ARGS[@]}" --world basic --world-every 4 --save-weights-at "${SNAPS[@]}" \
  --act-on-pushes 50
for h in "0 1 2 3 4" "5 6 7 8 9"; do
  mapfile -t W < <(snap_group r41pushed 10 $h)
  HFOV=150 WINDOW=0.078 eval_120 "runs/r41eval/${h%% *}" 1 --model sam --ensemble 10 --weights "${W[@]}"
done
for p in varied_start fixed_start; do
  V=(); [ $p = varied_start ] && V=("${VARIED[@]}")
  $EVAL --from-csv runs/r41eval/{0,5}/$p/results.csv "${V[@]}" --sim-arg hfov_deg:=150.0 \
    --sim-arg reward_window_fraction:=0.078 --inprocess --ensemble 10 --out $R41/$p
  mkdir -p $R41/ros_12/$p
  { cat $R40/push_every_50/$p/results.csv; tail -n +2 $R40/push_every_update/$p/results.csv; } > $R41/ros_12/$p/results.csv
  python scripts/compare_models.py $R41/$p/results.csv $R35/$p/results.csv --by file --paired --a act_on_pushes \
    --b round35 --bar paper > $R41/$p/against_round35.md
  python scripts/compare_models.py $R41/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a act_on_pushes \
    --b inprocess_40 --bar complex=0 > $R41/$p/against_inprocess_40.md
  python scripts/compare_models.py $R41/$p/results.csv $R41/ros_12/$p/results.csv --by file --a act_on_pushes \
    --b ros_12 --bar complex=0 > $R41/$p/against_ros_12.md
done
{ cat runs/r41eval/0/varied_start/crashes.csv; tail -n +2 runs/r41eval/5/varied_start/crashes.csv; } > $R41/varied_start/crashes.csv
python scripts/repeat_failures.py $R41/fixed_start/results.csv $R41/ros_12/fixed_start/results.csv \
  $R36/pooled_40_seeds/fixed_start/results.csv --labels act_on_pushes ros_12 inprocess_40 > $R41/fixed_start_repeats.md

# Round 42: the main job (`train --recipe ensemble`, push every 50 updates) on fresh SAM seeds 6-11, one run at a
# time (design fixed before any run: $R42/design.md); each run's ten files flown as one policy on its own (both
# protocols, as rounds 38-41) and the six joined; against the forty in-process seeds, the eighteen ROS runs of
# rounds 38-40 and this pooled (`ros_18/`), rounds 38-40's twelve, and the fixed-start repeats.
ros_per_seed() {  # tag folder "seeds": `train --recipe ensemble` on those SAM seeds one at a time into
  # runs/<tag>_sam_seed<s>, each run's ten files flown as one policy on its own into folder/s<s> (150 degree camera,
  # both protocols, random starts with a crash log)
  local tag=$1 out=$2 s W
  for s in $3; do
    install/uav_trainer/lib/uav_trainer/train --learning concurrent --recipe ensemble --model sam --seed $s --run-dir runs/${tag}_sam_seed$s --no-resume
    mapfile -t W < <(snap_group "$tag" 10 $s)
    HFOV=150 WINDOW=0.078 eval_120 "$out/s$s" 1 --model sam --ensemble 10 --weights "${W[@]}"
  done
}
join_150() {  # out protocol csv...: tables of ten-file ensembles (150 degree camera) joined into out/<protocol>
  local out=$1 p=$2 V=()
  shift 2
  [ "$p" = varied_start ] && V=("${VARIED[@]}")
  $EVAL --from-csv "$@" "${V[@]}" --sim-arg hfov_deg:=150.0 --sim-arg reward_window_fraction:=0.078 --inprocess \
    --ensemble 10 --out "$out/$p"
}
join_crash_logs() {  # out folder "seeds": the random-start crash logs of folder/s<s> in one file, out/varied_start
  local first=1 s
  for s in $3; do
    if [ $first = 1 ]; then cat "$2/s$s/varied_start/crashes.csv"; first=0; else tail -n +2 "$2/s$s/varied_start/crashes.csv"; fi
  done > "$1/varied_start/crashes.csv"
}
R42=docs/results/round42_main_job_fresh_seeds
ros_per_seed r42ros runs/r42eval "6 7 8 9 10 11"
for p in varied_start fixed_start; do
  join_150 $R42 $p runs/r42eval/s{6,7,8,9,10,11}/$p/results.csv
  join_150 $R42/ros_18 $p $R41/ros_12/$p/results.csv $R42/$p/results.csv
  python scripts/compare_models.py $R42/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a fresh_seeds \
    --b inprocess_40 --bar complex=0 > $R42/$p/against_inprocess_40.md
  python scripts/compare_models.py $R42/$p/results.csv $R41/ros_12/$p/results.csv --by file --a fresh_seeds \
    --b ros_12 --bar complex=0 > $R42/$p/against_ros_12.md
  python scripts/compare_models.py $R42/ros_18/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a ros_18 \
    --b inprocess_40 --bar complex=0 > $R42/ros_18/$p/against_inprocess_40.md
  python scripts/compare_models.py $R42/ros_18/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a ros_18 \
    --b inprocess_40 --bar paper > $R42/ros_18/$p/bar_paper.md
  python scripts/compare_models.py $R42/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a fresh_seeds \
    --b inprocess_40 --bar paper > $R42/$p/bar_paper.md
done
join_crash_logs $R42 runs/r42eval "6 7 8 9 10 11"
python scripts/repeat_failures.py $R42/fixed_start/results.csv $R41/ros_12/fixed_start/results.csv \
  $R36/pooled_40_seeds/fixed_start/results.csv --labels fresh_seeds ros_12 inprocess_40 > $R42/fixed_start_repeats.md

# Round 43: the main job (push every 50 updates) on SAM seeds 0-5 again, one run at a time (design fixed before any
# run was flown: $R43/design.md), flown per seed as round 42 and joined; a seed effect over the three runs of each
# seed (rounds 38/40's push 50, 39/40's push 1, this) by scripts/seed_effect.py; against round 38/40's push 50
# paired by seed; the 24 ROS runs pooled (rounds 38-40, 42, this) against the forty in-process seeds; repeats.
R43=docs/results/round43_same_seeds_again
ros_per_seed r43ros runs/r43eval "0 1 2 3 4 5"
for p in varied_start fixed_start; do
  join_150 $R43 $p runs/r43eval/s{0,1,2,3,4,5}/$p/results.csv
  join_150 $R43/ros_24 $p $R42/ros_18/$p/results.csv $R43/$p/results.csv
  A=$R40/push_every_50/$p/results.csv B=$R40/push_every_update/$p/results.csv
  python scripts/seed_effect.py $A $B $R43/$p/results.csv --labels push50 push1 push50_again > $R43/$p/seed_effect.md
  python scripts/seed_effect.py $A $R43/$p/results.csv --labels push50 push50_again > $R43/$p/seed_effect_push50.md
  python scripts/compare_models.py $R43/$p/results.csv $A --by file --paired --a push50_again --b push50 \
    --bar paper > $R43/$p/against_push50.md
  for b in complex=0:against paper:bar_paper; do
    python scripts/compare_models.py $R43/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file --a again \
      --b inprocess_40 --bar ${b%%:*} > $R43/$p/${b#*:}_inprocess_40.md
    python scripts/compare_models.py $R43/ros_24/$p/results.csv $R36/pooled_40_seeds/$p/results.csv --by file \
      --a ros_24 --b inprocess_40 --bar ${b%%:*} > $R43/ros_24/$p/${b#*:}_inprocess_40.md
  done
done
join_crash_logs $R43 runs/r43eval "0 1 2 3 4 5"
python scripts/repeat_failures.py $R43/fixed_start/results.csv $R40/push_every_50/fixed_start/results.csv \
  $R40/push_every_update/fixed_start/results.csv $R42/fixed_start/results.csv $R36/pooled_40_seeds/fixed_start/results.csv \
  --labels again push50 push1 fresh_seeds inprocess_40 > $R43/fixed_start_repeats.md

# Round 44: the main job learning in lockstep (train's default since this round: trainer_node learns after
# each step and releases the next frame to policy_node) against round 35's in-process command, SAM seed 0,
# trained side by side: episodes and all ten weights files compared bit for bit; its ten files flown as round
# 35 flew its runs (and from the fixed start through the ROS nodes too), row for row against round 35's seed 0;
# and `train --seed 20` on the embedded defaults against the packaged SAM (round 36's seed 20), `--model cnn
# --seed 13` against the packaged CNN (round 37's seed 13).
R44=docs/results/round44_lockstep_learning
install/uav_trainer/lib/uav_trainer/train --model sam --seed 0 --no-resume --run-dir runs/r44_ros_sam_seed0 > runs/r44_ros_sam_seed0.log 2>&1 &
python -m uav_trainer.inprocess --threads 1 --model sam --steps 30000 --seed 0 --layout-per-episode "${ROUND6[@]}" "${R24ARGS[@]}" \
  --world basic --world-every 4 --save-weights-at "${SNAPS[@]}" --run-dir runs/r44_inproc_sam_seed0 > runs/r44_inproc_sam_seed0.log 2>&1 &
wait
python scripts/same_run.py runs/r44_ros_sam_seed0 runs/r44_inproc_sam_seed0 > $R44/same_seed0_ros_vs_inprocess.txt
mapfile -t W < <(snap_group r44_ros 10 0)
HFOV=150 WINDOW=0.078 eval_120 $R44/seed0 1 --model sam --ensemble 10 --weights "${W[@]}"
$EVAL --model sam --ensemble 10 --weights "${W[@]}" --worlds basic complex turbulent --steps 1000 \
  --sim-arg hfov_deg:=150.0 --sim-arg reward_window_fraction:=0.078 --out $R44/seed0/fixed_start_ros
for p in varied_start fixed_start fixed_start_ros; do
  python scripts/same_run.py runs/r44_ros_sam_seed0 runs/r35basic150_sam_seed0 --tables $R44/seed0/$p/results.csv \
    $R35/${p%_ros}/results.csv > $R44/same_seed0_vs_round35_$p.txt
done
install/uav_trainer/lib/uav_trainer/train --model sam --seed 20 --no-resume --run-dir runs/r44_ros_sam_seed20 > runs/r44_ros_sam_seed20.log 2>&1
python scripts/same_run.py runs/r44_ros_sam_seed20 --packaged sam > $R44/same_seed20_vs_packaged.txt
install/uav_trainer/lib/uav_trainer/train --model cnn --seed 13 --no-resume --run-dir runs/r44_ros_cnn_seed13 > runs/r44_ros_cnn_seed13.log 2>&1
python scripts/same_run.py runs/r44_ros_cnn_seed13 --packaged cnn > $R44/same_cnn_seed13_vs_packaged.txt

# Round 45: round 44's CNN stall looked for again. train --model cnn --seed 13 alone (compared with the packaged
# CNN once more), then short CNN runs idle, beside busy loops and beside the whole test suite, on a domain the
# tests never use (230) and on round 44's (64, inside the tests' 1-100); and a py-spy profile of a SAM lockstep
# run (docs/results/round45_cnn_lockstep_timing/sam_lockstep_profile.md says how; py-spy is not installed here).
R45=docs/results/round45_cnn_lockstep_timing
R45_ROWS="Each row: the rows of the run's metrics.csv after the first one with updates (steady state): 5 s rows for \
the two full runs (30 000 steps, the embedded defaults), 2 s rows for the short ones (\`--trainer-arg \
learning_starts:=500 --trainer-arg log_interval_s:=2.0\`). Busy loops: \`python -c 'while True: pass'\`. All runs \
with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST. Commands: the round 45 block of \`scripts/reproduce_experiments.sh\`."
ROS_DOMAIN_ID=230 install/uav_trainer/lib/uav_trainer/train --model cnn --seed 13 --no-resume --run-dir runs/r45_ros_cnn_seed13 \
  > runs/r45_ros_cnn_seed13.log 2>&1
python scripts/same_run.py runs/r45_ros_cnn_seed13 --packaged cnn > $R45/same_cnn_seed13_vs_packaged.txt
cnn_short() {  # NAME DOMAIN STEPS BUSY_LOOPS
  local busy=() i
  for ((i = 0; i < $4; i++)); do python -c 'while True: pass' & busy+=($!); done
  ROS_DOMAIN_ID=$2 install/uav_trainer/lib/uav_trainer/train --model cnn --steps $3 --seed 13 --no-resume \
    --run-dir runs/shm/$1 --trainer-arg learning_starts:=500 --trainer-arg log_interval_s:=2.0 > runs/shm/$1.out 2>&1
  if ((${#busy[@]})); then kill "${busy[@]}"; fi
}
mkdir -p runs/shm
cnn_short idle_default 77 2500 0
cnn_short load1_default 77 2500 1
cnn_short load3_default 77 2500 3
for dom in 230 64; do
  bash scripts/test.sh -q > runs/shm/suite_d$dom.out 2>&1 &
  cnn_short suite_default_d$dom $dom 12000 0
  wait
done
{
  echo "# D3QN-CNN lockstep \`train\` step rates (seed 13, learning in lockstep; progress rows once learning runs)"
  echo
  echo "$R45_ROWS"
  echo
  python scripts/step_rates.py runs/r44_ros_cnn_seed13 runs/r45_ros_cnn_seed13 runs/shm/{idle,load1,load3}_default \
    runs/shm/suite_default_d{230,64} --labels \
    "round 44: full run, domain 64, part of it beside a clean-clone CI run (the suite's tests use domains 1-100)" \
    "round 45: full run, domain 230, machine otherwise idle" "2 500 steps, domain 77, idle" \
    "2 500 steps, domain 77, one busy-loop process beside it" "2 500 steps, domain 77, three busy-loop processes beside it" \
    "12 000 steps, domain 230, beside the full test suite (scripts/test.sh)" \
    "12 000 steps, domain 64, beside the full test suite (scripts/test.sh)"
} > $R45/step_rates.md

# Shipping round 35's recipe (docs/RESULTS.md, "Shipped weights"): of the forty SAM runs (rounds 35 and 36)
# and the twenty CNN runs (round 37), the one with the fewest crashes over both protocols, ties by reward
# (scripts/pick_shipped.py: SAM seed 20, CNN seed 13); its ten files packaged as policy_node's default,
# measured through the ROS nodes as policy_node flies them by default, and re-measured without ROS.
python scripts/pick_shipped.py $R35/{fixed,varied}_start/results.csv $R36/{fixed,varied}_start/results.csv --model sam \
  > docs/results/shipped/choice_sam.md
python scripts/pick_shipped.py $R37/{fixed,varied}_start/results.csv --model cnn > docs/results/shipped/choice_cnn.md
for m in sam cnn; do
  mapfile -t W < <(sed -n 's/^weights: //p' docs/results/shipped/choice_$m.md | tr ' ' '\n')
  python scripts/package_weights.py "${W[@]}" --model $m
done
colcon build --base-paths src > /dev/null
$EVAL --model sam --model cnn --worlds basic complex turbulent --steps 1000 --out docs/results/shipped/fixed_start
$EVAL --model sam --model cnn --worlds basic complex turbulent --steps 1000 "${VARIED[@]}" --out docs/results/shipped/varied_start
python $X docs/results/shipped/fixed_start/results.csv --hfov-deg 150
python $X docs/results/shipped/varied_start/results.csv "${VARIED[@]}" --hfov-deg 150
install/uav_policy/lib/uav_policy/attention_figures --model sam --worlds basic turbulent --steps 150 --out docs/figures

# Round 46: round 35's recipe on held-out layouts (generalisation). SAM seeds 0-3 (round 35's runs) and CNN
# seeds 0-3 (round 37's), each run's ten files as one policy, and the packaged files (SAM seed 20, CNN seed 13),
# 1000 steps from a random heading on each of random:400..409 (unseen layouts of the generator training draws
# from) and random_partitions:400..409 (long partitions, a family training never flew); a table per family,
# and SAM against CNN with each policy's ten layouts pooled. After the shipping block: it flies the packaged files.
R46=docs/results/round46_heldout_layouts
WL=(); WP=()
for k in $(seq 400 409); do WL+=("random:$k"); WP+=("random_partitions:$k"); done
R46ARGS=(--inprocess --ensemble 10 --steps 1000 --start-yaw-jitter-deg 180 --seed 0 --sim-arg hfov_deg:=150.0
  --sim-arg reward_window_fraction:=0.078)
for m in sam cnn; do
  mapfile -t W < <(MODEL=$m snap_group r35basic150 10 0 1 2 3)
  [ -f runs/r46held_$m/results.csv ] || $EVAL "${R46ARGS[@]}" --crash-log --model $m --weights "${W[@]}" \
    --worlds "${WL[@]}" "${WP[@]}" --out runs/r46held_$m > runs/r46held_$m.log &
  [ -f runs/r46held_packaged_$m/results.csv ] || $EVAL "${R46ARGS[@]}" --crash-log --model $m \
    --weights src/uav_policy/weights/$m/${m}_0{0..9}.safetensors --worlds "${WL[@]}" "${WP[@]}" \
    --out runs/r46held_packaged_$m > runs/r46held_packaged_$m.log &
  wait
done
r46_table() {  # out family-name csv...: the family's rows of the csv files as one table
  local out=$1 fam=$2 f
  shift 2
  mkdir -p "$out"
  head -n 1 "$1" > "$out/rows.csv"
  for f in "$@"; do grep -E "^[a-z]+,$fam:" "$f" >> "$out/rows.csv" || true; done
}
for fam in random random_partitions; do
  if [ $fam = random ]; then W=("${WL[@]}"); else W=("${WP[@]}"); fi
  r46_table $R46/$fam $fam runs/r46held_{sam,cnn}/results.csv
  $EVAL --from-csv $R46/$fam/rows.csv --worlds "${W[@]}" "${R46ARGS[@]}" --out $R46/$fam
  rm $R46/$fam/rows.csv
  python scripts/compare_models.py $R46/$fam/results.csv --by model --a sam --b cnn --pool-worlds "${fam}_400_409" \
    > $R46/$fam/sam_against_cnn.md
  r46_table $R46/packaged/$fam $fam runs/r46held_packaged_{sam,cnn}/results.csv
  $EVAL --from-csv $R46/packaged/$fam/rows.csv --worlds "${W[@]}" "${R46ARGS[@]}" --out $R46/packaged/$fam
  rm $R46/packaged/$fam/rows.csv
done
