"""One tiny trained PopSAN run (toy env, no MJX) shared by the analysis tests of a session."""

from __future__ import annotations

import jax
import pytest
from _toy_env import PointPick, tiny_popsan_config

from popsan_jax.analysis import evaluation
from popsan_jax.training.checkpoint import load_run
from popsan_jax.training.loop import train

EPISODES = 16


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """One tiny PopSAN run shared by every test here: (run_dir, env, TrainResult)."""
    env = PointPick()
    run_dir = tmp_path_factory.mktemp("eval") / "popsan_run"
    result = train(tiny_popsan_config(), run_dir, environment=env, progress=False)
    return run_dir, env, result


@pytest.fixture(scope="session")
def loaded(trained):
    run_dir, env, _ = trained
    return load_run(run_dir, environment=env)


@pytest.fixture(scope="session")
def recorded(loaded):
    return jax.device_get(evaluation.rollouts(loaded, EPISODES, jax.random.PRNGKey(3), record=True))
