"""One LIF layer traced by hand (Algorithm 1: decays 0.5 / 0.75, threshold 0.5, hard reset)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _reference import lif_layer

from popsan_jax import LIFParams
from popsan_jax.snn.lif import lif_step, lif_zero_state

# Two neurons, four steps of synaptic input (W o_prev + b already applied).
INPUTS = np.array([[0.3, 0.6], [0.3, -0.2], [0.3, 0.0], [0.0, 0.4]], np.float32)
# Traced by hand:
# n0: c = .3, .45, .525, .2625; v = .3, .225+.45=.675, 0 (reset)+.525, 0 (reset)+.2625
# n1: c = .6, .1, .05, .425;    v = .6, 0 (reset)+.1, .075+.05=.125, .09375+.425=.51875
CURRENT = np.array([[0.3, 0.6], [0.45, 0.1], [0.525, 0.05], [0.2625, 0.425]])
VOLTAGE = np.array([[0.3, 0.6], [0.675, 0.1], [0.525, 0.125], [0.2625, 0.51875]])
SPIKES = np.array([[0, 1], [1, 0], [1, 0], [0, 1]], np.float32)


def test_step_by_step_matches_hand_trace():
    state = lif_zero_state((1, 2))
    for t in range(4):
        out, state = lif_step(jnp.asarray(INPUTS[t])[None], state)
        np.testing.assert_allclose(state.current[0], CURRENT[t], rtol=1e-6)
        np.testing.assert_allclose(state.voltage[0], VOLTAGE[t], rtol=1e-6)
        np.testing.assert_array_equal(out[0], SPIKES[t])
        np.testing.assert_array_equal(state.spike[0], SPIKES[t])


def test_layer_scan_matches_hand_trace():
    spikes = lif_layer(jnp.asarray(INPUTS)[:, None, :])
    assert spikes.shape == (4, 1, 2)
    np.testing.assert_array_equal(spikes[:, 0], SPIKES)


def test_surrogate_gradient_through_reset_by_hand():
    # x = [0.3, 0.3]: v1 = 0.3 (in window, o1 = 0), v2 = 0.675 (in window).
    # dv2/dx1 = 0.75 (1 - o1) dv1/dx1 - 0.75 v1 do1/dx1 + 0.5 = 0.75 - 0.225 + 0.5 = 1.025
    # dv2/dx2 = 1, so d o2 / dx = [1.025, 1]; d o1 / dx = [1, 0].
    x = jnp.array([[[0.3]], [[0.3]]])
    g2 = jax.grad(lambda x: lif_layer(x)[1, 0, 0])(x)
    np.testing.assert_allclose(g2[:, 0, 0], [1.025, 1.0], rtol=1e-6)
    g1 = jax.grad(lambda x: lif_layer(x)[0, 0, 0])(x)
    np.testing.assert_allclose(g1[:, 0, 0], [1.0, 0.0])
    # Outside the window (v1 = 1.2 or -0.1) the gradient of o1 is exactly zero.
    for v in (1.2, -0.1):
        g = jax.grad(lambda x: lif_layer(x)[0, 0, 0])(jnp.full((1, 1, 1), v))
        assert float(g[0, 0, 0]) == 0.0


def test_params_are_frozen_and_change_the_dynamics():
    params = LIFParams()
    assert dataclasses.astuple(params) == (0.5, 0.75, 0.5, 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.threshold = 1.0  # type: ignore[misc]
    # Threshold 0.7: n0 v = .3, .675 (no spike), .75*.675 + .525 = 1.03125 (spike).
    spikes = lif_layer(jnp.asarray(INPUTS)[:, None, :1], LIFParams(threshold=0.7))
    np.testing.assert_array_equal(spikes[:3, 0, 0], [0, 0, 1])
