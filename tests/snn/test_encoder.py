"""Population encoder against the closed form of regular spiking and eq. 6's gradient."""

import jax
import jax.numpy as jnp
import numpy as np
from _reference import encoder_spike_trains, init_encoder, regular_spike_train

from popsan_jax.snn.encoder import PopulationEncoder, encode_and_project

T = 5


def _closed_form_trains(activity: np.ndarray, timesteps: int) -> np.ndarray:
    """Spike at step t iff floor(t A / 0.999) increases: at most one spike per step as A <= 1."""
    a = activity.astype(np.float64)
    counts = np.stack([np.floor(t * a / 0.999) for t in range(timesteps + 1)])
    return np.diff(counts, axis=0)


def _away_from_boundaries(activity: np.ndarray, timesteps: int) -> np.ndarray:
    """Mask of activities whose running sums t A / 0.999 are not within 1e-4 of an integer."""
    ratios = np.stack([t * activity.astype(np.float64) / 0.999 for t in range(1, timesteps + 1)])
    return np.all(np.abs(ratios - np.round(ratios)) > 1e-4, axis=0)


def test_spike_trains_match_closed_form():
    activity = np.random.default_rng(0).uniform(0.0, 1.0, size=(64, 30)).astype(np.float32)
    activity[0, :4] = [1.0, 0.999, 0.5, 0.2]
    trains = np.asarray(regular_spike_train(jnp.asarray(activity), T))
    assert trains.shape == (T, 64, 30)
    assert set(np.unique(trains)) <= {0.0, 1.0}
    ok = _away_from_boundaries(activity, T)
    assert ok.mean() > 0.95
    np.testing.assert_array_equal(trains[:, ok], _closed_form_trains(activity, T)[:, ok])
    # Hand-checked rows: A=1 fires every step; A=0.999 first reaches but does not exceed 0.999;
    # A=0.5 fires at t=2 and t=4 (v = 1.0, then 1.001); A=0.2 first exceeds 0.999 at t=5.
    np.testing.assert_array_equal(trains[:, 0, 0], [1, 1, 1, 1, 1])
    np.testing.assert_array_equal(trains[:, 0, 1], [0, 1, 1, 1, 1])
    np.testing.assert_array_equal(trains[:, 0, 2], [0, 1, 0, 1, 0])
    np.testing.assert_array_equal(trains[:, 0, 3], [0, 0, 0, 0, 1])


def test_encoder_init_and_counts_from_gaussian_receptive_fields():
    obs = jnp.array([[-3.0, 0.4, 2.2], [1.0, -0.7, 3.0]])
    enc = PopulationEncoder(pop_dim=7, timesteps=T)
    params = init_encoder(enc, jax.random.PRNGKey(0), obs)
    mean, std = params["params"]["mean"], params["params"]["std"]
    np.testing.assert_allclose(mean, np.tile(np.linspace(-3, 3, 7), (3, 1)), atol=1e-6)
    np.testing.assert_allclose(std, np.full((3, 7), 0.15**0.5), rtol=1e-6)
    spikes = np.asarray(encoder_spike_trains(enc, params, obs))
    assert spikes.shape == (T, 2, 21)
    activity = np.exp(-0.5 * (np.asarray(obs)[..., None] - np.linspace(-3, 3, 7)) ** 2 / 0.15)
    activity = activity.reshape(2, 21)
    ok = _away_from_boundaries(activity, T)
    np.testing.assert_array_equal(spikes[:, ok], _closed_form_trains(activity, T)[:, ok])
    # A neuron centred on its input (A = 1) fires every step.
    np.testing.assert_array_equal(spikes[:, 0, 0], np.ones(T))


def test_straight_through_gradient_to_activity_means_and_stds():
    weights = jnp.arange(1.0, T + 1.0)[:, None, None]  # distinct per-step cotangents
    activity = jnp.array([[0.1, 0.6, 0.95]])
    g = jax.grad(lambda a: jnp.sum(weights * regular_spike_train(a, T)))(activity)
    np.testing.assert_allclose(g, np.full((1, 3), 15.0))  # d spike_t / dA = 1 for every t

    obs = jnp.array([[0.3, -1.1]])
    enc = PopulationEncoder(pop_dim=4, timesteps=T)
    params = init_encoder(enc, jax.random.PRNGKey(0), obs)
    grads = jax.grad(lambda p: jnp.sum(encoder_spike_trains(enc, p, obs)))(params)["params"]
    mu = np.asarray(params["params"]["mean"], np.float64)
    var = 0.15
    s = np.asarray(obs, np.float64)[0][:, None]
    a = np.exp(-0.5 * (s - mu) ** 2 / var)
    np.testing.assert_allclose(grads["mean"], T * a * (s - mu) / var, rtol=1e-4, atol=1e-6)
    dstd = T * a * (s - mu) ** 2 / var**1.5
    np.testing.assert_allclose(grads["std"], dstd, rtol=1e-4, atol=1e-6)


def test_encode_and_project_matches_autodiff_of_the_plain_composition():
    key = jax.random.PRNGKey(5)
    activity = jax.random.uniform(key, (6, 12), minval=0.01, maxval=1.0)
    kernel = jax.random.normal(jax.random.fold_in(key, 1), (12, 7))
    bias = jax.random.normal(jax.random.fold_in(key, 2), (7,))
    cot_c = jax.random.normal(jax.random.fold_in(key, 3), (T, 6, 7))
    cot_s = jax.random.normal(jax.random.fold_in(key, 4), (T, 6, 12))

    def plain(a, w, b):
        spikes = regular_spike_train(a, T)
        return jnp.einsum("tbm,mn->tbn", spikes, w) + b, spikes

    def loss(fn):
        return lambda a, w, b: jnp.sum(fn(a, w, b)[0] * cot_c) + jnp.sum(fn(a, w, b)[1] * cot_s)

    fused = lambda a, w, b: encode_and_project(a, w, b, T)  # noqa: E731
    currents, spikes = fused(activity, kernel, bias)
    ref_currents, ref_spikes = plain(activity, kernel, bias)
    np.testing.assert_array_equal(spikes, ref_spikes)
    np.testing.assert_allclose(currents, ref_currents, rtol=1e-6, atol=1e-6)
    got = jax.grad(loss(fused), argnums=(0, 1, 2))(activity, kernel, bias)
    want = jax.grad(loss(plain), argnums=(0, 1, 2))(activity, kernel, bias)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5)
