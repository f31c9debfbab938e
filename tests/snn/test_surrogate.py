"""Spike function: exact Heaviside forward, exact rectangular surrogate backward."""

import jax
import jax.numpy as jnp
import numpy as np

from popsan_jax.snn.surrogate import make_spike_fn


def _grad(spike_fn, v, cotangent=1.0):
    out, vjp = jax.vjp(spike_fn, v)
    return out, vjp(jnp.full_like(out, cotangent))[0]


def test_forward_is_strict_heaviside():
    spike = make_spike_fn(0.5, 0.5)
    v = jnp.array([-2.0, 0.0, 0.4999, 0.5, 0.5001, 1.0, 7.0])
    np.testing.assert_array_equal(spike(v), [0, 0, 0, 0, 1, 1, 1])


def test_gradient_is_exactly_the_rectangle():
    spike = make_spike_fn(0.5, 0.5)
    inside = jnp.array([0.0001, 0.2, 0.4999, 0.5, 0.5001, 0.9999])
    outside = jnp.array([-3.0, -0.5, 0.0, 1.0, 1.0001, 4.0])
    _, g_in = _grad(spike, inside, 3.0)
    _, g_out = _grad(spike, outside, 3.0)
    # Cotangent passes unchanged inside |v - 0.5| < 0.5 (amplitude 1), nothing at or beyond it.
    np.testing.assert_array_equal(g_in, np.full(6, 3.0, np.float32))
    np.testing.assert_array_equal(g_out, np.zeros(6, np.float32))


def test_other_threshold_and_window():
    spike = make_spike_fn(1.0, 0.2)
    v = jnp.array([0.79, 0.81, 1.0, 1.01, 1.19, 1.21])
    out, g = _grad(spike, v)
    np.testing.assert_array_equal(out, [0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(g, [0, 1, 1, 1, 1, 0])


def test_same_constants_give_same_function_and_dtype_is_kept():
    assert make_spike_fn(0.5, 0.5) is make_spike_fn(0.5, 0.5)
    out = make_spike_fn(0.5, 0.5)(jnp.array([0.2, 0.7], jnp.bfloat16))
    assert out.dtype == jnp.bfloat16
    np.testing.assert_array_equal(out.astype(jnp.float32), [0.0, 1.0])


def test_grad_under_jit_and_vmap():
    spike = make_spike_fn(0.5, 0.5)
    g = jax.jit(jax.vmap(jax.grad(lambda v: spike(v))))(jnp.array([0.2, 1.2, 0.9]))
    np.testing.assert_array_equal(g, [1.0, 0.0, 1.0])
