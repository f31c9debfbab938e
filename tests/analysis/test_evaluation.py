"""Evaluator round trip on a tiny trained run: reload, evaluate, count spikes, energy rows."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import tiny_popsan_config
from brax.training.acme import running_statistics
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.analysis import evaluation
from popsan_jax.networks import actor_variables, make_actor
from popsan_jax.rollout import EpisodeBatch, run_episodes
from popsan_jax.training.setup import build_networks

EPISODES = 16


def test_wilson_interval_hand_values():
    z2 = 1.959963984540054**2
    lo, hi = evaluation.wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(z2 / (10 + z2))  # 0.2775
    lo, hi = evaluation.wilson_interval(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(10 / (10 + z2))
    lo, hi = evaluation.wilson_interval(5, 10)  # textbook: 0.2366 - 0.7634
    assert (lo, hi) == pytest.approx((0.236593, 0.763407), abs=1e-5)
    with pytest.raises(ValueError):
        evaluation.wilson_interval(0, 0)


def test_summarize_hand_built_batch():
    batch = EpisodeBatch(
        success=np.array([1.0, 0.0, 1.0, 1.0]),
        reached=np.array([1.0, 1.0, 1.0, 1.0]),
        hold_time=np.array([2.0, 0.5, 3.0, 2.5]),
        length=np.array([10.0, 20.0, 30.0, 40.0]),
        ret=np.array([1.0, 2.0, 3.0, 6.0]),
        terms={"distance": np.array([0.1, 0.2, 0.3, 0.4])},
    )
    s = evaluation.summarize(batch)
    assert s["episodes"] == 4 and s["success_rate"] == 0.75
    assert s["success_ci95"] == pytest.approx(list(evaluation.wilson_interval(3, 4)))
    assert s["reached_rate"] == 1.0 and s["hold_time"] == pytest.approx(2.0)
    assert s["reached_ci95"] == pytest.approx(list(evaluation.wilson_interval(4, 4)))
    assert s["episode_length"] == 25.0 and s["episode_return"] == 3.0
    assert s["reward/distance"] == pytest.approx(0.25)


def test_reloaded_policy_acts_like_saved_params(trained, loaded):
    _, env, result = trained
    state = result.state
    assert loaded.step == int(state.env_steps) and loaded.entry["step"] == loaded.step
    # Independent rebuild from the in-memory config and the params the trainer ended with.
    nets = build_networks(tiny_popsan_config(), env.observation_size, env.action_size)
    saved = ppo_networks.make_inference_fn(nets)(
        (state.normalizer_params, state.params.policy), deterministic=True
    )
    obs = jax.random.normal(jax.random.PRNGKey(1), (32, env.observation_size))
    key = jax.random.PRNGKey(0)
    expected = np.asarray(saved(obs, key)[0])
    np.testing.assert_array_equal(np.asarray(loaded.make_policy()(obs, key)), expected)
    # The evaluator's rollouts equal a rollout with the saved params' policy.
    mine = evaluation.rollouts(loaded, EPISODES, key)
    ref = run_episodes(env, lambda o, k: saved(o, k)[0], key, EPISODES)
    np.testing.assert_array_equal(np.asarray(mine.ret), np.asarray(ref.ret))
    np.testing.assert_array_equal(np.asarray(mine.success), np.asarray(ref.success))


def test_spike_counts_match_direct_numpy_count(loaded, recorded):
    obs = evaluation.alive_observations(recorded)
    assert obs.shape == (int(np.sum(recorded.length)), loaded.env.observation_size)
    for t in (1, 2):
        ops, sizes = evaluation.measure_snn_ops(loaded, obs, t, chunk=50)  # several chunks
        assert sizes == (6 * 3, 12, 8, 3 * 4)
        actor = make_actor("popsan", {**loaded.config.actor_kwargs, "timesteps": t}, 3)
        x = running_statistics.normalize(
            jnp.asarray(obs), loaded.normalizer_params, max_abs_value=loaded.config.obs_clip
        )
        mean, spikes = actor.apply(actor_variables(loaded.policy_params), x, return_spikes=True)
        # The spikes are those of the policy the rollouts ran (same normalisation and params).
        policy = evaluation.networks_at_timesteps(loaded, t).policy_network
        logits = policy.apply(loaded.normalizer_params, loaded.policy_params, jnp.asarray(obs))
        np.testing.assert_allclose(np.asarray(logits[:, :3]), np.asarray(mean), atol=1e-6)
        enc, h0, h1, out = (np.asarray(s, dtype=np.float64) for s in spikes)
        m = obs.shape[0]
        assert ops.dense_first_layer_macs == 18 * 12 * t and ops.decoder_macs == 12
        assert ops.encoder_macs == 18
        # ACs: encoder spikes reach 12 neurons, hidden_0 spikes 8, hidden_1 spikes 12 outputs.
        expected = (enc.sum() * 12 + h0.sum() * 8 + h1.sum() * 12) / m
        assert ops.sops == pytest.approx(expected, rel=1e-6)
        assert ops.first_layer_sops == pytest.approx(enc.sum() * 12 / m, rel=1e-6)
        rates = [s.mean() for s in (enc, h0, h1, out)]
        np.testing.assert_allclose(ops.firing_rates, rates, rtol=1e-6)
        assert ops.timesteps == t


def test_rebuilt_timesteps_share_params(loaded):
    obs = jax.random.normal(jax.random.PRNGKey(2), (8, loaded.env.observation_size))
    nets_1 = evaluation.networks_at_timesteps(loaded, 1)
    assert evaluation.networks_at_timesteps(loaded, 2) is loaded.networks
    # Same params tree fits both T; the means differ because the spike trains do.
    p1 = nets_1.policy_network.apply(loaded.normalizer_params, loaded.policy_params, obs)
    p2 = loaded.networks.policy_network.apply(loaded.normalizer_params, loaded.policy_params, obs)
    assert p1.shape == p2.shape and not np.allclose(np.asarray(p1), np.asarray(p2))


def test_energy_sweep_rows(loaded, recorded):
    rows = evaluation.energy_sweep(
        loaded, [1, 2], EPISODES, jax.random.PRNGKey(4), None, True, recorded
    )
    assert [r["timesteps"] for r in rows] == [1, 2]
    assert [r["trained_timesteps"] for r in rows] == [False, True]
    # ANN baseline: MLP 6 -> 12 -> 8 -> 3.
    assert all(r["ann_macs"] == 6 * 12 + 12 * 8 + 8 * 3 for r in rows)
    for r in rows:
        # Encoder receptive fields (6 obs x 3) + decoder (3 actions x 4), whatever T is.
        assert r["snn_macs"] == 18 + 12
        assert r["snn_energy_pj"] == pytest.approx(4.6 * r["snn_macs"] + 0.9 * r["snn_acs"])
        assert r["saving_pct"] == pytest.approx(100 * (1 - r["snn_energy_pj"] / r["ann_energy_pj"]))
    assert rows[1]["success_rate"] == pytest.approx(float(np.mean(recorded.success)))


def test_latency_actors_for_an_mlp_run(loaded):
    config = tiny_popsan_config(actor="mlp", actor_kwargs=dict(hidden_sizes=(8,)))
    mlp = make_actor("mlp", config.actor_kwargs, 3)
    params = mlp.init(jax.random.PRNGKey(0), jnp.zeros((1, 6)))["params"]
    run = SimpleNamespace(
        config=config, env=loaded.env, policy_params={"params": {"actor": params}}
    )
    actors = evaluation.latency_actors(run, None)
    assert list(actors) == ["PopSAN T=5", "MLP (ANN)"]
    popsan, _ = actors["PopSAN T=5"]
    assert tuple(popsan.hidden_sizes) == (8,)
    # The run's own trained actor keeps its params.
    assert actors["MLP (ANN)"][1]["params"] is params
