"""Current-based LIF neurons (PopSAN Algorithm 1): the state and one time step.

Per step, with the previous layer's spikes ``o_prev`` already multiplied by the weights::

    c = current_decay * c + (W o_prev + b)
    v = voltage_decay * v * (1 - o_last) + c      # hard reset through the previous spike
    o = spike(v)                                  # v > threshold, rectangular surrogate

States start at zero; there is no synaptic delay.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from popsan_jax.snn.surrogate import make_spike_fn


@dataclasses.dataclass(frozen=True)
class LIFParams:
    """Fixed LIF constants, kept explicit so an exporter (e.g. NIR) can map them one to one.

    ``current_decay`` and ``voltage_decay`` multiply the state each step (discrete-time decays,
    not time constants); ``window`` is the surrogate-gradient half-width around ``threshold``.
    """

    current_decay: float = 0.5
    voltage_decay: float = 0.75
    threshold: float = 0.5
    window: float = 0.5


DEFAULT_LIF = LIFParams()


class LIFState(NamedTuple):
    """Neuron state, each field ``[B, N]``."""

    current: jax.Array
    voltage: jax.Array
    spike: jax.Array


def lif_zero_state(shape: tuple[int, ...], dtype: jnp.dtype = jnp.float32) -> LIFState:
    """Zero initial state of shape ``[B, N]``."""
    zeros = jnp.zeros(shape, dtype)
    return LIFState(zeros, zeros, zeros)


def lif_step(
    synaptic_input: jax.Array, state: LIFState, params: LIFParams = DEFAULT_LIF
) -> tuple[jax.Array, LIFState]:
    """Advance one time step.

    Args:
      synaptic_input: ``W o_prev + b`` for this step, ``[B, N]``.
      state: the previous ``LIFState``.
      params: LIF constants.

    Returns:
      ``(spikes [B, N], new_state)``.
    """
    spike_fn = make_spike_fn(params.threshold, params.window)
    current = params.current_decay * state.current + synaptic_input
    voltage = params.voltage_decay * state.voltage * (1.0 - state.spike) + current
    spike = spike_fn(voltage)
    return spike, LIFState(current, voltage, spike)
