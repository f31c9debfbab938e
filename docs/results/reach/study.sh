#!/usr/bin/env bash
# The reach study of docs/results.md (record: docs/notebook/2026-11-pick-and-reach.md): PopSAN vs MLP on franka_reach, 3 seeds each, then the
# evaluations of evaluate_study.sh.
# Usage: bash docs/results/reach/study.sh [RUNS_DIR] [HIDDEN]
#   HIDDEN: both actors' hidden sizes, default 256,256 (the paper's PopSAN); the whole study took
#   25 minutes on the 2-core CPU on 2026-11-25 (docs/notebook/). 128,128 is the smaller variant.
set -euo pipefail
cd "$(dirname "$0")/../../.."
RUNS=${1:-runs/reach_study}
HIDDEN=${2:-256,256}
PY=.venv/bin/python
COMMON=(--env franka_reach
  --env-override episode_length=50
  --env-override "target_low=[0.45, -0.1, 0.25]"
  --env-override "target_high=[0.6, 0.1, 0.4]"
  --num-envs 128 --batch-size 128 --num-minibatches 4 --unroll-length 10
  --num-updates-per-batch 8 --critic-lr 1e-3 --entropy-cost 1e-3 --init-log-std -1.0
  --critic-hidden-sizes 128,128 --hidden-sizes "$HIDDEN"
  --total-env-steps 400000 --num-evals 10 --num-eval-envs 128 --no-progress
  --runs-dir "$RUNS")
train() {  # actor seed extra-flags...
  local actor=$1 seed=$2; shift 2
  [ -e "$RUNS/$actor-s$seed/checkpoints/index.json" ] && return 0
  $PY train.py "${COMMON[@]}" --actor "$actor" --seed "$seed" --name "$actor-s$seed" "$@"
}
for seed in 0 1 2; do
  train popsan "$seed" --actor-lr 1e-3 --lr-schedule cosine &
  train mlp "$seed" --actor-lr 3e-4 --lr-schedule constant
  wait
done
source docs/results/evaluate_study.sh
evaluate_study "$RUNS" "$RUNS/reach_curves.png"
