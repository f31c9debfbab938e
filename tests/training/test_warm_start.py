"""Warm start (``--init-from``): networks and normaliser copied, a fresh optimiser, another T
allowed, other network shapes refused."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import PointPick

from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.recipes import resolve_config
from popsan_jax.training.checkpoint import load_run
from popsan_jax.training.iteration import init_training_state
from popsan_jax.training.setup import build_networks, make_optimizer
from popsan_jax.training.warm_start import check_same_networks, warm_source, warm_start


def test_warm_start_copies_networks_normaliser_and_not_the_optimiser(source_and_penalised):
    root, source, _, _ = source_and_penalised
    env = PointPick()
    loaded = load_run(root / "source", "last", environment=env)
    # A different T is allowed: PopSAN's parameters do not depend on it.
    kwargs = {**source.actor_kwargs, "timesteps": 3}
    config = source.replace(init_from=str(root / "source"), init_checkpoint="last")
    config = config.replace(actor_kwargs=kwargs, seed=5)
    nets = build_networks(config, env.observation_size, env.action_size)
    optimizer = make_optimizer(config)
    fresh = init_training_state(
        config, nets, optimizer, env.observation_size, jax.random.PRNGKey(5)
    )
    source = warm_source(config, root / "new")
    assert source == (str(root / "source"), "last")
    state = warm_start(fresh, config, optimizer, source, env)
    for got, want in [
        (state.params.policy, loaded.policy_params),
        (state.params.value, loaded.value_params),
        (state.normalizer_params, loaded.normalizer_params),
    ]:
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_array_equal(a, b)
    counts = {int(x) for x in jax.tree.leaves(state.opt_state) if jnp.issubdtype(x, jnp.integer)}
    assert counts == {0} and int(state.env_steps) == 0
    wider = config.replace(actor_kwargs={**kwargs, "hidden_sizes": (32,)})
    with pytest.raises(ConfigError, match="actor hidden_sizes"):
        warm_start(fresh, wider, optimizer, source, env)
    mlp = config.replace(actor="mlp", actor_kwargs={"hidden_sizes": (16,)})
    with pytest.raises(ConfigError, match="its actor 'popsan' differs"):
        warm_start(fresh, mlp, optimizer, source, env)


def test_an_mlp_run_from_before_output_init_scale_can_be_started_from():
    # Runs made before the MLP's output_init_scale have no such key; the command now records
    # 0.01. Only the initial draw depends on it, so --init-from such a run is allowed, while a
    # real difference in the network (here the hidden sizes) is still refused.
    old = RunConfig().replace(actor="mlp", actor_kwargs={"hidden_sizes": (256, 256)})
    new = resolve_config(None, "cpu", {"actor": "mlp"})
    assert new.actor_kwargs["output_init_scale"] == 0.01
    check_same_networks(old, new, "runs/old")
    narrower = new.replace(actor_kwargs={**new.actor_kwargs, "hidden_sizes": (64,)})
    with pytest.raises(
        ConfigError,
        match="actor hidden_sizes .*only decoder_init_scale, output_init_scale, timesteps",
    ):
        check_same_networks(old, narrower, "runs/old")


def test_warm_source_prefers_the_runs_own_warm_up(tmp_path):
    # A run with a warm-up stage starts its own stage from the warm-up's last checkpoint, even
    # when it has init_from (which the warm-up stage itself starts from).
    plain = RunConfig()
    assert warm_source(plain, tmp_path) is None
    given = plain.replace(init_from="runs/a", init_checkpoint="best")
    assert warm_source(given, tmp_path) == ("runs/a", "best")
    staged = given.replace(warmup_env_steps=1000)
    assert warm_source(staged, tmp_path / "r") == (str(tmp_path / "r" / "warmup"), "last")
