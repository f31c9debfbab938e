"""Spike counts and synaptic operations per inference against hand counts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _tiny_spikes import tiny_spikes

from popsan_jax.snn import ops


def test_layer_names():
    assert ops.spiking_layer_names(2) == ["encoder", "hidden_0", "hidden_1", "output"]


def test_spike_totals_hand_counted():
    totals = np.asarray(ops.spike_totals(tiny_spikes()))
    np.testing.assert_array_equal(totals, [7, 6, 4, 4])
    # Weighting out observation 1 keeps observation 0's counts only.
    w = jnp.asarray([1.0, 0.0])
    np.testing.assert_array_equal(np.asarray(ops.spike_totals(tiny_spikes(), w)), [3, 3, 1, 2])


def test_sops_per_inference_is_the_hand_count_and_differentiable():
    # Fan-outs read from the next layers' widths (3, 2, 2): encoder 7 x 3 + hidden1 6 x 2 +
    # hidden2 4 x 2 = 41 over 2 inferences = 20.5.
    assert float(ops.sops_per_inference(tiny_spikes())) == pytest.approx(20.5)
    # d SOPs / d spike = fan-out / B: encoder 3 / 2, hidden1 2 / 2, hidden2 2 / 2, output 0.
    grads = jax.grad(ops.sops_per_inference)(tiny_spikes())
    for g, expected in zip(grads, (1.5, 1.0, 1.0, 0.0), strict=True):
        np.testing.assert_allclose(g, np.full(g.shape, expected))
