"""The loss's synaptic-operation penalty on the tiny point-mass env: its gradient lowers the
measured SOPs, it is zero under budget, and a penalised run logs it and fires less."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import PointPick, tiny_config
from brax.training.acme import running_statistics

from popsan_jax.snn.ops import sops_per_inference
from popsan_jax.training import loss
from popsan_jax.training.run_log import read_metrics
from popsan_jax.training.setup import build_networks, make_spikes_fn

STEPS = 640  # env steps per iteration of tiny_config()


def _policy_and_obs(config, n=256):
    env = PointPick()
    nets = build_networks(config, env.observation_size, env.action_size)
    params = nets.policy_network.init(jax.random.PRNGKey(0))
    obs = 2.0 * jax.random.normal(jax.random.PRNGKey(1), (n, env.observation_size))
    normalizer = running_statistics.init_state(jnp.zeros((env.observation_size,)))
    return params, normalizer, obs


def test_penalty_gradient_lowers_measured_sops_and_is_zero_under_budget():
    config = tiny_config(sop_cost=1.0)
    params, normalizer, obs = _policy_and_obs(config)
    spikes_fn = make_spikes_fn(config, PointPick().action_size)

    def sops(p):
        return sops_per_inference(spikes_fn(p, normalizer, obs))

    before = float(sops(params))
    assert before > 10.0  # the untrained tiny network does fire
    penalty = float(loss.sop_penalty(config, jnp.asarray(before)))
    assert penalty == pytest.approx(before / 1000.0)  # cost 1 per 1000 SOPs, budget 0
    grads = jax.grad(lambda p: loss.sop_penalty(config, sops(p)))(params)
    # Plain gradient descent on the penalty alone: the surrogate gradient must point to fewer
    # measured (exact-step) spikes.
    stepped = jax.tree.map(lambda p, g: p - 50.0 * g, params, grads)
    assert float(sops(stepped)) < 0.8 * before
    roomy = config.replace(sop_budget=before + 1.0)
    assert float(loss.sop_penalty(roomy, jnp.asarray(before))) == 0.0
    zero = jax.grad(lambda p: loss.sop_penalty(roomy, sops(p)))(params)
    assert all(float(jnp.max(jnp.abs(g))) == 0.0 for g in jax.tree.leaves(zero))


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
