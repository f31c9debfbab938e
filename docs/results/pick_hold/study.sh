#!/usr/bin/env bash
# The pick-and-hold study of docs/results.md (issue 18): PopSAN vs MLP on franka_pick (env
# revision 3 since 3 December; the revision-2 run of 1 December used this script too) with the
# README's own command, seeds 0-2, then the evaluations of
# evaluate_study.sh (1000 episodes of each final checkpoint, energy with success per T, latency,
# tracking figure, curves), a re-check on fresh episodes and the wider-object-range robustness.
#
# Usage: bash docs/results/pick_hold/study.sh [RUNS_DIR] [SEEDS]
#   No training flags: each run is `python train.py --env franka_pick [--actor mlp] --seed K`
#   (the CPU recipe in popsan_jax/config.py). A run stopped with Ctrl-C resumes when this
#   script is run again.
set -euo pipefail
cd "$(dirname "$0")/../../.."
RUNS=${1:-runs/pick_hold3}
SEEDS=${2:-0 1 2}
PY=.venv/bin/python
# Training range: x 0.4-0.6 m, y -0.2-0.2 m; robustness range: 5 cm wider on every side.
WIDE=(--env-override 'object_x_range=[0.35,0.65]' --env-override 'object_y_range=[-0.25,0.25]')
train() {  # actor seed
  local dir="$RUNS/$1-s$2"
  if [ -e "$dir/checkpoints/index.json" ]; then
    $PY train.py --resume "$dir" --no-progress
  else
    $PY train.py --env franka_pick --actor "$1" --seed "$2" --name "$1-s$2" \
      --runs-dir "$RUNS" --no-progress
  fi
}
for seed in $SEEDS; do
  train popsan "$seed"
  train mlp "$seed"
done
for seed in $SEEDS; do
  for actor in popsan mlp; do
    $PY eval.py "$RUNS/$actor-s$seed" --episodes 1000 --no-energy --no-latency --no-tracking
    $PY eval.py "$RUNS/$actor-s$seed" --episodes 1000 --seed 1 --no-energy --no-latency \
      --no-tracking
    $PY eval.py "$RUNS/$actor-s$seed" --episodes 1000 "${WIDE[@]}" --no-energy --no-latency \
      --no-tracking
  done
done
$PY eval.py "$RUNS/popsan-s0" --episodes 1000 --ann-run "$RUNS/mlp-s0"
$PY eval.py --compare "$RUNS"/popsan-s* "$RUNS"/mlp-s* --out "$RUNS/pick_hold_curves.png"
