"""Population encoder: Gaussian receptive fields and deterministic regular spike trains.

Each observation dimension ``i`` drives ``pop_dim`` neurons with activity
``A = exp(-0.5 (s_i - mu_ij)^2 / sigma_ij^2)`` in (0, 1]. Each neuron integrates its activity and
fires regularly: ``v += A; spike if v > 0.999; v -= spike * 0.999``. The gradient is straight
through, ``d spike_t / d A = 1`` for every step (paper eq. 6), so the learnable means and stds
receive ``sum_t dL/d spike_t * dA/d(mu, sigma)``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

ENCODER_THRESHOLD = 0.999


def encoder_step(activity: jax.Array, voltage: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One regular-spiking step: ``(spikes, new_voltage)``, both shaped like ``activity``."""
    voltage = voltage + activity
    spike = (voltage > ENCODER_THRESHOLD).astype(activity.dtype)
    return spike, voltage - spike * ENCODER_THRESHOLD


def encoder_spike_steps(activity: jax.Array, timesteps: int) -> list[jax.Array]:
    """The T regular-spiking steps from zero voltage, as a list of arrays shaped like ``activity``.

    A Python-unrolled loop (T is small and static) rather than ``lax.scan``: separate per-step
    outputs let XLA compute all T steps in one multi-output fusion and feed per-step matmuls,
    where a stacked scan output made it recompute the Gaussian ``exp`` once per step
    (docs/design.md, "The encoder unroll").
    """
    voltage = jnp.zeros_like(activity)
    spikes = []
    for _ in range(timesteps):
        spike, voltage = encoder_step(activity, voltage)
        spikes.append(spike)
    return spikes


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def encode_and_project(
    activity: jax.Array, kernel: jax.Array, bias: jax.Array, timesteps: int
) -> tuple[jax.Array, jax.Array]:
    """Encoder spike trains and the first synaptic layer's input currents, for all T at once.

    Args:
      activity: ``[B, M]`` encoder activity in (0, 1].
      kernel: ``[M, N]`` first-layer weights; bias: ``[N]``.
      timesteps: T.

    Returns:
      ``(currents [T, B, N], spikes [T, B, M])`` with ``currents[t] = spikes[t] @ kernel + bias``.

    The encoder does not depend on any LIF state, so its T steps and the T first-layer matmuls are
    all known up front. The backward pass uses eq. 6's straight-through gradient: the activity
    cotangent is ``sum_t g_currents[t] @ kernel.T (+ sum_t g_spikes[t])``, which by linearity is one
    matmul on the T-summed cotangent instead of T matmuls (same value up to float rounding).
    """
    return _encode_and_project_fwd(activity, kernel, bias, timesteps)[0]


def _encode_and_project_fwd(
    activity: jax.Array, kernel: jax.Array, bias: jax.Array, timesteps: int
) -> tuple[tuple[jax.Array, jax.Array], tuple[list[jax.Array], jax.Array]]:
    steps = encoder_spike_steps(activity, timesteps)
    currents = jnp.stack([spike @ kernel + bias for spike in steps])
    return (currents, jnp.stack(steps)), (steps, kernel)


def _encode_and_project_bwd(
    timesteps: int,
    residuals: tuple[list[jax.Array], jax.Array],
    cotangents: tuple[jax.Array, jax.Array],
) -> tuple[jax.Array, jax.Array, jax.Array]:
    steps, kernel = residuals
    g_currents, g_spikes = cotangents
    g_sum = jnp.sum(g_currents, axis=0)
    g_activity = g_sum @ kernel.T + jnp.sum(g_spikes, axis=0)
    # T accumulated [M, B] x [B, N] products ran faster here than one [M, T*B] x [T*B, N].
    g_kernel = sum(spike.T @ g for spike, g in zip(steps, g_currents, strict=True))
    return g_activity, g_kernel, jnp.sum(g_sum, axis=0)


encode_and_project.defvjp(_encode_and_project_fwd, _encode_and_project_bwd)


def evenly_spaced_means(mean_range: Sequence[float], pop_dim: int) -> nn.initializers.Initializer:
    """Init for means ``[obs_dim, pop_dim]``: ``pop_dim`` points from low to high, inclusive."""
    low, high = float(mean_range[0]), float(mean_range[1])

    def init(key: jax.Array, shape: tuple[int, int], dtype=jnp.float32) -> jax.Array:
        del key
        row = jnp.linspace(low, high, pop_dim, dtype=dtype) if pop_dim > 1 else jnp.full((1,), low)
        return jnp.broadcast_to(row.astype(dtype), shape)

    return init


class PopulationEncoder(nn.Module):
    """The encoder's learnable receptive fields: observation ``[B, obs_dim]`` -> activity.

    Neuron ``i * pop_dim + j`` encodes observation dimension ``i`` with mean ``mean[i, j]``.
    Its spike trains come from :func:`encode_and_project` together with the first layer's
    input (``PopSAN`` calls ``activity`` only; ``init`` with ``method="activity"``).
    """

    pop_dim: int = 10
    timesteps: int = 5
    mean_range: tuple[float, float] = (-3.0, 3.0)
    std_init: float = 0.15**0.5
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def activity(self, obs: jax.Array) -> jax.Array:
        """Gaussian receptive-field activity ``[B, obs_dim * pop_dim]`` in (0, 1]."""
        obs_dim = obs.shape[-1]
        shape = (obs_dim, self.pop_dim)
        mean = self.param("mean", evenly_spaced_means(self.mean_range, self.pop_dim), shape)
        std = self.param("std", nn.initializers.constant(self.std_init), shape)
        obs = obs.astype(self.dtype)[..., None]
        mean, std = mean.astype(self.dtype), std.astype(self.dtype)
        activity = jnp.exp(-0.5 * jnp.square(obs - mean) / jnp.square(std))
        return activity.reshape(*obs.shape[:-2], obs_dim * self.pop_dim)
