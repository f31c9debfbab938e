#!/usr/bin/env bash
# The pick study of docs/results.md (issue 6; record in docs/notebook/): PopSAN vs MLP on franka_pick, 3 seeds each, then
# the evaluations of evaluate_study.sh (energy per T on every seed, latency, curves).
#
# Usage: bash docs/results/pick_seeds/study.sh [RUNS_DIR] [train.py flags...]
#   default flags: --preset paper (512 envs, 40 M steps per run, the settings of the seed-0
#   pick runs in docs/notebook/). On this 2-core CPU a run takes 1.5-3 h alone (a run stopped
#   with Ctrl-C resumes where it stopped when this script is run again).
# Re-running it resumes every run from its last checkpoint (a finished one stops after compiling).
set -euo pipefail
cd "$(dirname "$0")/../../.."
RUNS=${1:-runs/pick_study}
shift || true
FLAGS=("$@")
[ ${#FLAGS[@]} -eq 0 ] && FLAGS=(--preset paper)
PY=.venv/bin/python
train() {  # actor seed
  local dir="$RUNS/$1-s$2"
  if [ -e "$dir/checkpoints/index.json" ]; then
    $PY train.py --resume "$dir" --no-progress
  else
    $PY train.py --env franka_pick "${FLAGS[@]}" --actor "$1" --seed "$2" --name "$1-s$2" \
      --runs-dir "$RUNS" --no-progress
  fi
}
for seed in 0 1 2; do
  train popsan "$seed"
  train mlp "$seed"
done
source docs/results/evaluate_study.sh
evaluate_study "$RUNS" "$RUNS/pick_curves.png"
