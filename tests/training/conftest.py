"""Runs shared by the training tests of a session (toy env, no MJX)."""

from __future__ import annotations

import pytest
from _toy_env import PointPick, tiny_config

from popsan_jax.training.loop import train

STEPS = 640  # env steps per iteration of tiny_config()


@pytest.fixture(scope="session")
def source_and_penalised(tmp_path_factory):
    """A plain 2-iteration run, then a run warm-started from it with a heavy SOP penalty."""
    root = tmp_path_factory.mktemp("runs")
    source = tiny_config(total_env_steps=2 * STEPS)
    train(source, root / "source", environment=PointPick(), progress=False)
    penalised = tiny_config(
        total_env_steps=2 * STEPS,
        init_from=str(root / "source"),
        init_checkpoint="last",
        sop_cost=100.0,
        actor_lr=1e-2,
    )
    result = train(penalised, root / "penalised", environment=PointPick(), progress=False)
    return root, source, penalised, result
