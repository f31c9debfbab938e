"""Whole PopSAN forward against a plain NumPy loop of Algorithm 1; gradients; jit/vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _reference import lif_layer, regular_spike_train

from popsan_jax import PopSAN, make_actor
from popsan_jax.config import POPSAN_DEFAULTS

OBS, ACT, B = 6, 3, 16
KW = dict(action_size=ACT, hidden_sizes=(32, 24), encoder_pop_dim=5, decoder_pop_dim=4, timesteps=5)


def numpy_popsan(p: dict, obs: np.ndarray, T: int):
    """Algorithm 1 stepped one time step at a time through every layer, float64.

    Returns (mean, spike trains per layer [T, B, N], min |v - threshold| seen over all LIF steps).
    """
    mu, std = p["encoder"]["mean"], p["encoder"]["std"]
    act = np.exp(-0.5 * (obs[:, :, None] - mu) ** 2 / std**2).reshape(obs.shape[0], -1)
    layers = [p[k] for k in sorted(k for k in p if k.startswith("hidden_"))] + [p["output"]]
    enc_v = np.zeros_like(act)
    cur = [np.zeros((obs.shape[0], lay["bias"].size)) for lay in layers]
    volt = [np.zeros_like(c) for c in cur]
    spk = [np.zeros_like(c) for c in cur]
    trains = [[] for _ in range(len(layers) + 1)]
    margin = np.inf
    for _ in range(T):
        enc_v = enc_v + act
        pre = (enc_v > 0.999).astype(np.float64)
        enc_v = enc_v - pre * 0.999
        trains[0].append(pre)
        for k, lay in enumerate(layers):
            cur[k] = 0.5 * cur[k] + pre @ lay["kernel"] + lay["bias"]
            volt[k] = 0.75 * volt[k] * (1.0 - spk[k]) + cur[k]
            spk[k] = (volt[k] > 0.5).astype(np.float64)
            margin = min(margin, np.abs(volt[k] - 0.5).min())
            trains[k + 1].append(spk[k])
            pre = spk[k]
    rates = np.mean(trains[-1], axis=0).reshape(obs.shape[0], ACT, -1)
    dec = p["decoder"]
    mean = np.tanh(np.sum(rates * dec["weight"], axis=-1) + dec["bias"])
    return mean, [np.stack(t) for t in trains], margin


@pytest.fixture(scope="module")
def setup():
    model = PopSAN(**KW)
    obs = jax.random.normal(jax.random.PRNGKey(0), (B, OBS)) * 1.5
    params = model.init(jax.random.PRNGKey(1), obs)
    # Bigger weights than the init so every layer spikes a fair amount (a stronger comparison).
    params = jax.tree.map(lambda x: x, params)  # a copy of the nested dicts before editing
    for name in ("hidden_0", "hidden_1", "output"):
        params["params"][name]["kernel"] = params["params"][name]["kernel"] * 3.0
    return model, obs, params


def test_forward_matches_numpy_algorithm_1(setup):
    model, obs, params = setup
    mean, spikes = jax.jit(lambda p, o: model.apply(p, o, return_spikes=True))(params, obs)
    p64 = jax.tree.map(lambda x: np.asarray(x, np.float64), params["params"])
    ref_mean, ref_trains, margin = numpy_popsan(p64, np.asarray(obs, np.float64), KW["timesteps"])
    # float32 vs float64 can only flip a spike whose voltage is within rounding of threshold.
    assert margin > 1e-5
    shapes = [(5, B, OBS * 5), (5, B, 32), (5, B, 24), (5, B, ACT * 4)]
    assert [s.shape for s in spikes] == shapes
    for got, ref in zip(spikes, ref_trains, strict=True):
        assert 0.02 < float(ref.mean()) < 0.98  # each layer is active but not saturated
        np.testing.assert_array_equal(np.asarray(got), ref)
    np.testing.assert_allclose(mean, ref_mean, atol=1e-5)
    assert mean.shape == (B, ACT)
    assert bool(jnp.all(jnp.abs(mean) < 1.0))


def test_default_shapes_and_binary_spikes():
    model = PopSAN(action_size=9)
    obs = jnp.clip(jax.random.normal(jax.random.PRNGKey(3), (4, 34)), -3, 3)
    params = model.init(jax.random.PRNGKey(4), obs)
    mean, spikes = model.apply(params, obs, return_spikes=True)
    assert mean.shape == (4, 9)
    assert [s.shape for s in spikes] == [(5, 4, 340), (5, 4, 256), (5, 4, 256), (5, 4, 90)]
    for s in spikes:
        assert set(np.unique(np.asarray(s))) <= {0.0, 1.0}
    np.testing.assert_array_equal(model.apply(params, obs), mean)
    # At the default init every layer fires a little and every parameter gets a gradient.
    assert all(0.01 < float(s.mean()) < 0.5 for s in spikes)
    grads = jax.grad(lambda p: jnp.mean((model.apply(p, obs) - 0.5) ** 2))(params)
    assert all(float(jnp.max(jnp.abs(g))) > 0 for g in jax.tree.leaves(grads))


def test_grad_reaches_every_parameter(setup):
    model, obs, params = setup
    target = jnp.linspace(-0.9, 0.9, B * ACT).reshape(B, ACT)
    loss = lambda p: jnp.mean(jnp.square(model.apply(p, obs) - target))  # noqa: E731
    grads = jax.jit(jax.grad(loss))(params)["params"]
    leaves = jax.tree_util.tree_leaves_with_path(grads)
    assert len(leaves) == 10  # encoder mean/std, 3 x (kernel, bias), decoder weight/bias
    for path, g in leaves:
        assert bool(jnp.all(jnp.isfinite(g))), path
        assert float(jnp.max(jnp.abs(g))) > 0.0, path


def plain_jax_popsan(p: dict, obs: jax.Array, T: int) -> jax.Array:
    """The model composed layer by layer from the unit-tested pieces, with plain autodiff."""
    mu, std = p["encoder"]["mean"], p["encoder"]["std"]
    act = jnp.exp(-0.5 * jnp.square(obs[:, :, None] - mu) / jnp.square(std))
    x = regular_spike_train(act.reshape(obs.shape[0], -1), T)
    for name in ("hidden_0", "hidden_1", "output"):
        x = lif_layer(x @ p[name]["kernel"] + p[name]["bias"])
    rates = jnp.mean(x, axis=0).reshape(obs.shape[0], ACT, -1)
    return jnp.tanh(jnp.sum(rates * p["decoder"]["weight"], -1) + p["decoder"]["bias"])


def test_grads_match_plain_autodiff_composition(setup):
    model, obs, params = setup
    target = jnp.linspace(-0.9, 0.9, B * ACT).reshape(B, ACT)
    got = jax.grad(lambda p: jnp.sum((model.apply(p, obs) - target) ** 2))(params)["params"]
    want = jax.grad(
        lambda p: jnp.sum((plain_jax_popsan(p["params"], obs, KW["timesteps"]) - target) ** 2)
    )(params)["params"]
    for (path, g), w in zip(
        jax.tree_util.tree_leaves_with_path(got), jax.tree.leaves(want), strict=True
    ):
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-6, err_msg=str(path))


def test_jit_vmap_and_no_recompiles(setup):
    model, obs, params = setup
    fwd = jax.jit(model.apply)
    first = fwd(params, obs)
    for k in range(3):  # new values, same shapes and dtypes
        o = jax.random.normal(jax.random.PRNGKey(10 + k), (B, OBS))
        p = jax.tree.map(lambda x, k=k: x * (1.0 + 0.01 * k), params)
        fwd(p, o)
    assert fwd._cache_size() == 1
    np.testing.assert_array_equal(fwd(params, obs), first)
    batched = jax.jit(jax.vmap(model.apply, in_axes=(None, 0)))(params, obs.reshape(4, 4, OBS))
    np.testing.assert_allclose(batched.reshape(B, ACT), first, atol=1e-6)


def test_other_depth_timesteps_and_dtype():
    model = PopSAN(action_size=2, hidden_sizes=(8, 8, 8), timesteps=3, dtype=jnp.bfloat16)
    obs = jnp.ones((2, 4))
    params = model.init(jax.random.PRNGKey(0), obs)
    mean, spikes = model.apply(params, obs, return_spikes=True)
    assert mean.shape == (2, 2) and mean.dtype == jnp.bfloat16
    assert len(spikes) == 5 and all(s.shape[0] == 3 for s in spikes)
    assert params["params"]["hidden_0"]["kernel"].dtype == jnp.float32


def test_decoder_starts_scaled():
    # decoder_init_scale multiplies the decoder's U(-1/sqrt(pop), 1/sqrt(pop)) draw, weights and
    # biases alike; with the same key every other layer is the same draw, so the output spikes
    # are the same and the action mean is tanh of exactly the scaled decoder sum. At 0.01 the full
    # PopSAN's action means start near 0 for every observation rather than at the paper draw's
    # nearly constant offset (|mean| ~0.1-0.2).
    obs = jax.random.normal(jax.random.PRNGKey(1), (64, OBS))
    base_model = PopSAN(**KW)
    base = base_model.init(jax.random.PRNGKey(0), obs)
    small_model = PopSAN(**KW, decoder_init_scale=0.01)
    small = small_model.init(jax.random.PRNGKey(0), obs)
    for name in ("encoder", "hidden_0", "hidden_1", "output"):
        for leaf, base_leaf in zip(
            jax.tree.leaves(small["params"][name]),
            jax.tree.leaves(base["params"][name]),
            strict=True,
        ):
            np.testing.assert_array_equal(leaf, base_leaf)
    dec, base_dec = small["params"]["decoder"], base["params"]["decoder"]
    for part in ("weight", "bias"):
        np.testing.assert_allclose(dec[part], 0.01 * np.asarray(base_dec[part]), rtol=1e-5)
    assert float(np.abs(base_dec["weight"]).max()) > 0.3  # U(+-1/sqrt(4)): the paper's draw
    _, spikes = small_model.apply(small, obs, return_spikes=True)
    rates = np.asarray(spikes[-1]).mean(0).reshape(64, ACT, KW["decoder_pop_dim"])
    expected = np.tanh((rates * np.asarray(dec["weight"])).sum(-1) + np.asarray(dec["bias"]))
    np.testing.assert_allclose(small_model.apply(small, obs), expected, atol=1e-6)
    full = make_actor("popsan", {**POPSAN_DEFAULTS, "decoder_init_scale": 0.01}, ACT)
    means = full.apply(full.init(jax.random.PRNGKey(0), obs), obs)
    assert float(jnp.abs(means).max()) < 0.01
    paper = make_actor("popsan", POPSAN_DEFAULTS, ACT)
    assert float(jnp.abs(paper.apply(paper.init(jax.random.PRNGKey(0), obs), obs)).mean()) > 0.03
