"""Population decoder (paper eq. 4): per-action weighted sum of its population's firing rates."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


def torch_linear_init(fan_in: int) -> nn.initializers.Initializer:
    """``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``, the reference PyTorch Linear/Conv1d init.

    Used for weights and biases alike: spiking activity at initialisation depends on the scale of
    the input currents, so we keep the reference implementation's scale rather than Flax's.
    """
    bound = 1.0 / float(fan_in) ** 0.5

    def init(key: jax.Array, shape: tuple[int, ...], dtype=jnp.float32) -> jax.Array:
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


class PopulationDecoder(nn.Module):
    """Output spikes ``[T, B, action_size * pop_dim]`` -> action mean ``[B, action_size]``.

    ``rate = count / T``; ``mean_a = tanh(sum_j w[a, j] * rate[a, j] + b[a])``. ``w`` and ``b``
    start at ``init_scale`` times their :func:`torch_linear_init` draw.
    """

    action_size: int
    pop_dim: int = 10
    init_scale: float = 1.0
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, spikes: jax.Array) -> jax.Array:
        draw = torch_linear_init(self.pop_dim)

        def init(key: jax.Array, shape: tuple[int, ...], dtype=jnp.float32) -> jax.Array:
            return self.init_scale * draw(key, shape, dtype)

        weight = self.param("weight", init, (self.action_size, self.pop_dim))
        bias = self.param("bias", init, (self.action_size,))
        rates = jnp.mean(spikes, axis=0)
        rates = rates.reshape(*rates.shape[:-1], self.action_size, self.pop_dim)
        logits = jnp.sum(rates * weight.astype(self.dtype), axis=-1) + bias.astype(self.dtype)
        return jnp.tanh(logits)
