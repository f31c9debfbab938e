"""Training: env and network setup, the jitted PPO iteration, its loss and diagnostics, the host
loop and its evaluations, new-run-or-resume, checkpoints and their manifest, warm start and the
run log."""
