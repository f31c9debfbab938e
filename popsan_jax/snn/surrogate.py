"""Spike function: exact Heaviside forward, rectangular surrogate gradient backward.

PopSAN (paper eq. 5) trains LIF layers with a pseudo-gradient: ``d spike / d v = 1`` inside the
window ``|v - threshold| < window`` and 0 outside. The threshold and window are Python floats
closed over by the ``jax.custom_vjp`` so they are compile-time constants, not traced values.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp


@functools.cache
def make_spike_fn(threshold: float, window: float) -> Callable[[jax.Array], jax.Array]:
    """Return ``spike(v) -> (v > threshold)`` with a rectangular surrogate gradient.

    The same (threshold, window) pair always yields the same function object, so jitted callers
    hash identically and do not retrace.

    Args:
      threshold: firing threshold (strict ``>``, as in the reference implementation).
      window: half-width of the rectangle where the surrogate gradient is 1.

    Returns:
      An elementwise function of any shape; output dtype equals the input dtype and every value is
      exactly 0 or 1.
    """
    threshold = float(threshold)
    window = float(window)

    @jax.custom_vjp
    def spike(v: jax.Array) -> jax.Array:
        return (v > threshold).astype(v.dtype)

    def spike_fwd(v: jax.Array) -> tuple[jax.Array, jax.Array]:
        return spike(v), v

    def spike_bwd(v: jax.Array, g: jax.Array) -> tuple[jax.Array]:
        inside = jnp.abs(v - threshold) < window
        return (jnp.where(inside, g, jnp.zeros_like(g)),)

    spike.defvjp(spike_fwd, spike_bwd)
    return spike
