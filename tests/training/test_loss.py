"""The synaptic-operation penalty and warm starts (``--init-from``) on the tiny point-mass env."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import PointPick, tiny_config
from brax.training.acme import running_statistics

from popsan_jax.analysis.energy import sops_per_inference
from popsan_jax.errors import ConfigError
from popsan_jax.training import checkpoint
from popsan_jax.training import iteration as ppo_update
from popsan_jax.training import loop as ppo
from popsan_jax.training import loss as spike_cost
from popsan_jax.training.run_log import read_metrics

STEPS = 640  # env steps per iteration of tiny_config()


def _policy_and_obs(config, n=256):
    env = PointPick()
    nets = ppo_update.build_networks(config, env.observation_size, env.action_size)
    params = nets.policy_network.init(jax.random.PRNGKey(0))
    obs = 2.0 * jax.random.normal(jax.random.PRNGKey(1), (n, env.observation_size))
    normalizer = running_statistics.init_state(jnp.zeros((env.observation_size,)))
    return params, normalizer, obs


def test_penalty_gradient_lowers_measured_sops_and_is_zero_under_budget():
    config = tiny_config(sop_cost=1.0)
    params, normalizer, obs = _policy_and_obs(config)
    spikes_fn = spike_cost.make_spikes_fn(config, PointPick().action_size)

    def sops(p):
        return sops_per_inference(spikes_fn(p, normalizer, obs))

    before = float(sops(params))
    assert before > 10.0  # the untrained tiny network does fire
    penalty = float(spike_cost.sop_penalty(config, jnp.asarray(before)))
    assert penalty == pytest.approx(before / 1000.0)  # cost 1 per 1000 SOPs, budget 0
    grads = jax.grad(lambda p: spike_cost.sop_penalty(config, sops(p)))(params)
    # Plain gradient descent on the penalty alone: the surrogate gradient must point to fewer
    # measured (exact-step) spikes.
    stepped = jax.tree.map(lambda p, g: p - 50.0 * g, params, grads)
    assert float(sops(stepped)) < 0.8 * before
    roomy = config.replace(sop_budget=before + 1.0)
    assert float(spike_cost.sop_penalty(roomy, jnp.asarray(before))) == 0.0
    zero = jax.grad(lambda p: spike_cost.sop_penalty(roomy, sops(p)))(params)
    assert all(float(jnp.max(jnp.abs(g))) == 0.0 for g in jax.tree.leaves(zero))


@pytest.fixture(scope="module")
def source_and_penalised(tmp_path_factory):
    """A plain 2-iteration run, then a run warm-started from it with a heavy SOP penalty."""
    root = tmp_path_factory.mktemp("runs")
    source = tiny_config(total_env_steps=2 * STEPS)
    ppo.train(source, root / "source", environment=PointPick(), progress=False)
    penalised = tiny_config(
        total_env_steps=2 * STEPS,
        init_from=str(root / "source"),
        init_checkpoint="last",
        sop_cost=100.0,
        actor_lr=1e-2,
    )
    result = ppo.train(penalised, root / "penalised", environment=PointPick(), progress=False)
    return root, source, penalised, result


def test_penalised_run_logs_the_penalty_and_fires_less(source_and_penalised):
    root, _, _, _ = source_and_penalised
    start = read_metrics(root / "source", "train")[-1]["sops"]  # the warm start's policy
    records = read_metrics(root / "penalised", "train")
    assert [r["env_steps"] for r in records] == [STEPS, 2 * STEPS]  # counted from 0
    for r in records:
        parts = r["loss/policy"] + r["loss/value"] + r["loss/entropy"] + r["loss/sop_penalty"]
        np.testing.assert_allclose(r["loss/total"], parts, rtol=1e-4)
        assert r["loss/sop_penalty"] > 0.0
    assert records[-1]["sops"] < 0.7 * start
    assert "loss/sop_penalty" not in read_metrics(root / "source", "train")[-1]


def test_warm_start_copies_networks_normaliser_and_not_the_optimiser(source_and_penalised):
    root, source, _, _ = source_and_penalised
    env = PointPick()
    loaded = checkpoint.load_run(root / "source", "last", environment=env)
    # A different T is allowed: PopSAN's parameters do not depend on it.
    kwargs = {**source.actor_kwargs, "timesteps": 3}
    config = source.replace(init_from=str(root / "source"), init_checkpoint="last")
    config = config.replace(actor_kwargs=kwargs, seed=5)
    nets = ppo_update.build_networks(config, env.observation_size, env.action_size)
    optimizer = ppo_update.make_optimizer(config)
    fresh = ppo_update.init_training_state(
        config, nets, optimizer, env.observation_size, jax.random.PRNGKey(5)
    )
    state = checkpoint.warm_start(fresh, config, optimizer, env)
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
        checkpoint.warm_start(fresh, wider, optimizer, env)
    mlp = config.replace(actor="mlp", actor_kwargs={"hidden_sizes": (16,)})
    with pytest.raises(ConfigError, match="its actor 'popsan' differs"):
        checkpoint.warm_start(fresh, mlp, optimizer, env)
