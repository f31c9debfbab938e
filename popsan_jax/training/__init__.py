"""Training: env and network setup, the jitted PPO iteration and its loss, the host loop,
new-run-or-resume, checkpoints, warm start and the run log."""
