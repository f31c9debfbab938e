#!/usr/bin/env bash
# The evaluation half of a study (sourced by reach/study.sh and pick_seeds/study.sh): 1000-episode
# evaluations of the 6 runs <actor>-s<seed> under RUNS, the energy table with success per T
# (T = 1..5, latency and tracking for seed 0; T = 1..3 for seeds 1 and 2, each against its own
# seed's ANN run), and the training curves.
# Usage: evaluate_study RUNS CURVES_PNG   (PY must name the Python interpreter)
evaluate_study() {
  local runs=$1 curves=$2 seed actor
  for seed in 0 1 2; do
    for actor in popsan mlp; do
      $PY eval.py "$runs/$actor-s$seed" --episodes 1000 --no-energy --no-latency --no-tracking
    done
  done
  $PY eval.py "$runs/popsan-s0" --episodes 1000 --ann-run "$runs/mlp-s0"
  for seed in 1 2; do
    $PY eval.py "$runs/popsan-s$seed" --episodes 1000 --ann-run "$runs/mlp-s$seed" \
      --timesteps 1,2,3 --no-latency --no-tracking
  done
  $PY eval.py --compare "$runs"/popsan-s* "$runs"/mlp-s* --out "$curves"
}
