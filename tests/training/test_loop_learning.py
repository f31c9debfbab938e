"""Learning tests (CI runs them): ``python train.py`` on franka_reach, PopSAN and MLP actors.

Each run goes through the real CLI (flags -> RunConfig -> jitted PPO -> eval -> checkpoints) and
must end with a ``reached`` rate (the fingertips within 2 cm at some step: the latched rule these
thresholds were measured with, issue 4) far above the untrained policy's (the step-0
evaluation). The reach task is made easier through env overrides (1 s episodes, a smaller target
box, success = within 2 cm for the last 0.2 s) so that a couple of CPU minutes suffice.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from popsan_jax.training import checkpoint_index
from popsan_jax.training.run_log import read_metrics

ROOT = Path(__file__).resolve().parents[2]

# Measured on the 2-core CPU (see module docstring); both actors share every PPO setting.
REACH_FLAGS = [
    "--env", "franka_reach",
    "--env-override", "episode_length=50",
    "--env-override", "hold_seconds=0.2",
    "--env-override", "target_low=[0.45, -0.1, 0.25]",
    "--env-override", "target_high=[0.6, 0.1, 0.4]",
    "--num-envs", "128", "--batch-size", "128", "--num-minibatches", "4",
    "--unroll-length", "10", "--num-updates-per-batch", "8",
    "--critic-lr", "1e-3", "--entropy-cost", "1e-3",
    "--init-log-std", "-1.0", "--critic-hidden-sizes", "128,128", "--hidden-sizes", "128,128",
    "--num-evals", "2", "--num-eval-envs", "128", "--no-progress",
]  # fmt: skip
CASES = {
    # actor: (actor lr, lr schedule, total env steps, minimum final success rate).
    # Measured (128 eval episodes): popsan at 200 k steps 0.70 / 0.99 / 1.00 for seeds 0 / 1 / 2
    # (untrained 0.02 / 0.00 / 0.05; 150 k steps gave 0.25-0.70, too close to the threshold);
    # mlp 0.0 untrained -> 0.30 at 230 k -> 0.78 at 300 k steps (seed 0).
    "popsan": (1e-3, "cosine", 200_000, 0.3),
    "mlp": (3e-4, "constant", 300_000, 0.3),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Both actors' runs, started side by side: each process spends much of its time in one-
    threaded XLA compiles, so on two cores the pair takes little longer than one run.
    Returns ``{actor: (returncode, stderr, run_dir)}``."""
    root = tmp_path_factory.mktemp("learning")
    procs = {}
    for actor, (lr, schedule, total, _) in CASES.items():
        argv = [*REACH_FLAGS, "--actor", actor, "--actor-lr", str(lr), "--lr-schedule", schedule]
        argv += ["--total-env-steps", str(total), "--runs-dir", str(root), "--name", actor]
        with open(root / f"{actor}.stderr", "w") as log:  # the child keeps its own copy
            procs[actor] = subprocess.Popen(
                [sys.executable, "train.py", *argv], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=log
            )
    try:
        codes = {actor: p.wait(timeout=3000) for actor, p in procs.items()}
    finally:
        for p in procs.values():
            p.kill()
    return {
        actor: (codes[actor], (root / f"{actor}.stderr").read_text(), root / actor)
        for actor in CASES
    }


@pytest.mark.slow
@pytest.mark.parametrize("actor", sorted(CASES))
def test_reach_success_far_above_untrained(actor, runs):
    _, _, total, threshold = CASES[actor]
    code, stderr, run_dir = runs[actor]
    assert code == 0, stderr[-2000:]
    config = json.loads((run_dir / "config.json").read_text())
    assert config["actor"] == actor and config["env_overrides"]["episode_length"] == 50
    evals = read_metrics(run_dir, "eval")
    untrained, final = evals[0], evals[-1]
    assert untrained["env_steps"] == 0 and final["env_steps"] >= total
    assert untrained["reached_rate"] <= 0.1 and untrained["success_rate"] <= 0.1, untrained
    assert final["reached_rate"] >= threshold, evals
    assert final["success_rate"] <= final["reached_rate"], evals  # a hold implies a reach
    # the mean fingertip-target distance over an episode at least halves
    assert final["reward/dist"] < 0.5 * untrained["reward/dist"], evals
    assert checkpoint_index.read_index(run_dir)["last"] == final["env_steps"]
