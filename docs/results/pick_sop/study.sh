#!/usr/bin/env bash
# The energy step of the pick study (docs/notebook/2026-11-pick-and-reach.md, "Fine-tuning at T = 2 under a spike
# budget"): each seed's T = 5 PopSAN (best checkpoint) trained on at T = 2 for 4 M env steps with
# a synaptic-operation penalty above 30 k SOPs per inference and actor lr 1e-4; then every kept
# checkpoint is evaluated over the same 1000 episodes at T = 2 (eval.py --all-checkpoints; the
# runs of 30 November did this with one eval.py --step N per checkpoint, which gives the same
# figures), the best of those gets the energy table
# (T = 1, 2, 3, against its seed's ANN) and a re-check on 1000 other episodes (--seed 1).
#
# Usage: bash docs/results/pick_sop/study.sh [STUDY_RUNS] [OUT_RUNS]
#   STUDY_RUNS holds popsan-s{0,1,2} and mlp-s{0,1,2} (docs/results/pick_seeds/study.sh; default runs/pick_study),
#   OUT_RUNS gets t2-s{0,1,2} (default runs/pick_sop). About 30 min per seed on this 2-core CPU;
#   a run stopped with Ctrl-C resumes when the script is run again.
set -euo pipefail
cd "$(dirname "$0")/../../.."
STUDY=${1:-runs/pick_study}
RUNS=${2:-runs/pick_sop}
PY=.venv/bin/python
for seed in 0 1 2; do
  dir="$RUNS/t2-s$seed"
  if [ -e "$dir/checkpoints/index.json" ]; then
    $PY train.py --resume "$dir" --no-progress
  else
    $PY train.py --preset paper --init-from "$STUDY/popsan-s$seed" --timesteps 2 \
      --sop-cost 0.01 --sop-budget 30000 --actor-lr 1e-4 --seed "$seed" \
      --total-env-steps 4000000 --num-evals 16 --name "t2-s$seed" --runs-dir "$RUNS" --no-progress
  fi
  $PY eval.py "$dir" --all-checkpoints --episodes 1000  # writes eval_checkpoints.json/.md
  chosen=$($PY -c "import json,sys; print(json.load(open(sys.argv[1]))['chosen_step'])" \
    "$dir/eval_checkpoints.json")
  $PY eval.py "$dir" --step "$chosen" --episodes 1000 --timesteps 1,2,3 \
    --ann-run "$STUDY/mlp-s$seed" --no-tracking
  $PY eval.py "$dir" --step "$chosen" --episodes 1000 --seed 1 --no-energy --no-latency \
    --no-tracking
done
