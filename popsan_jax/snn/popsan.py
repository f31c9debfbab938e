"""PopSAN actor: population encoder -> K LIF layers -> LIF output populations -> decoder.

Algorithm 1 steps every layer once per time step, T times, from the zero state. The encoder and
the first synaptic layer depend on no LIF state, so their T steps are computed up front in one
matmul (``encode_and_project``); the LIF layers then run in one ``lax.scan`` over T whose body
steps layer 1, 2, ..., output in order. The scan is fully unrolled so XLA sees the whole T-step
graph (per-step matmuls and fused elementwise neuron updates) instead of a loop
(docs/design.md, "The encoder unroll").
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from popsan_jax.snn.decoder import PopulationDecoder, torch_linear_init
from popsan_jax.snn.encoder import PopulationEncoder, encode_and_project
from popsan_jax.snn.lif import DEFAULT_LIF, LIFParams, LIFState, lif_step, lif_zero_state
from popsan_jax.snn.ops import spiking_layer_names

Synapse = tuple[jax.Array, jax.Array]  # (kernel [N_in, N_out], bias [N_out])


class SynapseParams(nn.Module):
    """Declares one layer's ``kernel [fan_in, features]`` and ``bias [features]``."""

    features: int
    fan_in: int

    @nn.compact
    def __call__(self) -> Synapse:
        init = torch_linear_init(self.fan_in)
        kernel = self.param("kernel", init, (self.fan_in, self.features))
        return kernel, self.param("bias", init, (self.features,))


def run_lif_stack(
    first_currents: jax.Array, synapses: Sequence[Synapse], lif: LIFParams = DEFAULT_LIF
) -> tuple[jax.Array, ...]:
    """Unroll the LIF layers over T (Algorithm 1's inner loop).

    Args:
      first_currents: first LIF layer's synaptic input for every step, ``[T, B, N_1]``.
      synapses: (kernel, bias) feeding LIF layers 2..L, in order.
      lif: LIF constants.

    Returns:
      Spikes of every LIF layer, each ``[T, B, N_l]``.
    """
    batch = first_currents.shape[1:-1]
    sizes = [first_currents.shape[-1]] + [bias.shape[-1] for _, bias in synapses]
    init = [lif_zero_state((*batch, n), first_currents.dtype) for n in sizes]

    def body(states: list[LIFState], current: jax.Array) -> tuple[list[LIFState], list[jax.Array]]:
        spike, state = lif_step(current, states[0], lif)
        new_states, spikes = [state], [spike]
        for (kernel, bias), state in zip(synapses, states[1:], strict=True):
            spike, state = lif_step(spike @ kernel + bias, state, lif)
            new_states.append(state)
            spikes.append(spike)
        return new_states, spikes

    _, spikes = jax.lax.scan(body, init, first_currents, unroll=True)
    return tuple(spikes)


class PopSAN(nn.Module):
    """Population-coded spiking actor network.

    ``apply(params, obs [B, obs_dim])`` -> action mean ``[B, action_size]`` in (-1, 1).
    ``apply(params, obs, return_spikes=True)`` -> ``(mean, spikes)`` where ``spikes`` is a tuple
    of 0/1 arrays ``[T, B, N]``: encoder (``N = obs_dim * encoder_pop_dim``), each hidden LIF layer,
    then the output populations (``N = action_size * decoder_pop_dim``).

    Params tree (``params["params"]``): ``encoder/{mean, std}`` ``[obs_dim, encoder_pop_dim]``;
    ``hidden_k/{kernel [N_in, N_out], bias}`` for k = 0..K-1; ``output/{kernel, bias}``;
    ``decoder/{weight [action_size, decoder_pop_dim], bias [action_size]}``. Params are float32;
    computation runs in ``dtype``. ``decoder_init_scale`` scales the decoder's initial draw (its
    weights and biases), so that a small one starts the policy's mean near 0.
    """

    action_size: int
    hidden_sizes: Sequence[int] = (256, 256)
    encoder_pop_dim: int = 10
    decoder_pop_dim: int = 10
    timesteps: int = 5
    decoder_init_scale: float = 1.0
    mean_range: tuple[float, float] = (-3.0, 3.0)
    std_init: float = 0.15**0.5
    dtype: jnp.dtype = jnp.float32
    lif: LIFParams = DEFAULT_LIF

    @nn.compact
    def __call__(
        self, obs: jax.Array, return_spikes: bool = False
    ) -> jax.Array | tuple[jax.Array, tuple[jax.Array, ...]]:
        activity = PopulationEncoder(
            pop_dim=self.encoder_pop_dim,
            timesteps=self.timesteps,
            mean_range=tuple(self.mean_range),
            std_init=self.std_init,
            dtype=self.dtype,
            name="encoder",
        ).activity(obs)
        sizes = [activity.shape[-1], *self.hidden_sizes, self.action_size * self.decoder_pop_dim]
        names = spiking_layer_names(len(self.hidden_sizes))[1:]
        synapses = [
            jax.tree.map(lambda x: x.astype(self.dtype), SynapseParams(n_out, n_in, name=name)())
            for n_in, n_out, name in zip(sizes[:-1], sizes[1:], names, strict=True)
        ]
        first_currents, encoder_spikes = encode_and_project(activity, *synapses[0], self.timesteps)
        lif_spikes = run_lif_stack(first_currents, synapses[1:], self.lif)
        mean = PopulationDecoder(
            self.action_size,
            self.decoder_pop_dim,
            init_scale=self.decoder_init_scale,
            dtype=self.dtype,
            name="decoder",
        )(lif_spikes[-1])
        if return_spikes:
            return mean, (encoder_spikes, *lif_spikes)
        return mean
