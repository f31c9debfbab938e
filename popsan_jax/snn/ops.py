"""Operations of a PopSAN counted from its spikes, in the energy convention's terms.

Shapes: spikes are ``[T, B, N]`` 0/1 arrays, ``T`` SNN timesteps, ``B`` observations, ``N``
neurons in the layer. Layers are, in order, the encoder, the hidden LIF layers and the output
populations (:func:`spiking_layer_names`). The energy model itself is
:mod:`popsan_jax.analysis.energy`; the training loss charges :func:`sops_per_inference`.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp


def spiking_layer_names(num_hidden: int) -> list[str]:
    """``["encoder", "hidden_0", ..., "output"]``; all but the first name PopSAN's synapses."""
    return ["encoder", *(f"hidden_{k}" for k in range(num_hidden)), "output"]


def spike_totals(spikes: Sequence[jax.Array], weight: jax.Array | None = None) -> jax.Array:
    """Weighted spike count per layer, summed over timesteps, neurons and observations.

    Args:
      spikes: one ``[T, B, N_l]`` 0/1 array per spiking layer.
      weight: ``[B]`` per-observation weight (1 for alive steps, 0 for padding); None = all 1.

    Returns:
      ``[L]`` float32 totals, jit-friendly (no host transfer).
    """
    totals = []
    for s in spikes:
        per_obs = jnp.sum(s.astype(jnp.float32), axis=(0, 2))
        if weight is not None:
            per_obs = per_obs * weight.astype(jnp.float32)
        totals.append(jnp.sum(per_obs))
    return jnp.stack(totals)


def sops_per_inference(spikes: Sequence[jax.Array]) -> jax.Array:
    """Mean synaptic operations per inference of one batch, differentiable through the spikes.

    The same count as ``popsan_jax.analysis.energy.snn_ops_from_totals``' ``sops`` (every layer
    but the output
    populations drives the next layer, one AC per spike and target), with each layer's fan-out
    read from the next layer's width.

    Args:
      spikes: one ``[T, B, N_l]`` array per spiking layer (encoder, hidden..., output).

    Returns:
      scalar float32: ``sum_l sum_{t, n} spikes_l / B * N_{l+1}``.
    """
    totals = spike_totals(spikes)[:-1]
    fan_out = jnp.asarray([float(s.shape[-1]) for s in spikes[1:]], jnp.float32)
    return jnp.sum(totals * fan_out) / spikes[0].shape[1]
