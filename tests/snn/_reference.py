"""Reference implementations the spiking tests check the library against.

Plain compositions of the library's own steps, written the obvious way: one LIF layer scanned
over T, and regular spike trains with eq. 6's straight-through gradient as a custom VJP. The
library fuses these (``encode_and_project``, ``run_lif_stack``) for speed; the tests compare.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from popsan_jax.snn.encoder import PopulationEncoder, encoder_spike_steps
from popsan_jax.snn.lif import DEFAULT_LIF, LIFParams, LIFState, lif_step, lif_zero_state


def lif_layer(synaptic_input: jax.Array, params: LIFParams = DEFAULT_LIF) -> jax.Array:
    """One LIF layer over T from the zero state: ``[T, B, N]`` input -> ``[T, B, N]`` spikes."""

    def body(state: LIFState, x: jax.Array) -> tuple[LIFState, jax.Array]:
        spike, state = lif_step(x, state, params)
        return state, spike

    init = lif_zero_state(synaptic_input.shape[1:], synaptic_input.dtype)
    _, spikes = jax.lax.scan(body, init, synaptic_input, unroll=True)
    return spikes


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def regular_spike_train(activity: jax.Array, timesteps: int) -> jax.Array:
    """Deterministic spike trains ``[T, *activity.shape]`` from activity in (0, 1]; backward is
    the straight-through estimator (each step's spike has gradient 1 w.r.t. the activity)."""
    return jnp.stack(encoder_spike_steps(activity, timesteps))


def _regular_fwd(activity: jax.Array, timesteps: int) -> tuple[jax.Array, None]:
    return regular_spike_train(activity, timesteps), None


def _regular_bwd(timesteps: int, _: None, g: jax.Array) -> tuple[jax.Array]:
    return (jnp.sum(g, axis=0),)


regular_spike_train.defvjp(_regular_fwd, _regular_bwd)


def init_encoder(encoder: PopulationEncoder, key: jax.Array, obs: jax.Array) -> dict:
    """The encoder's params (it has no ``__call__``: ``activity`` is its method)."""
    return encoder.init(key, obs, method=PopulationEncoder.activity)


def encoder_spike_trains(encoder: PopulationEncoder, params: dict, obs: jax.Array) -> jax.Array:
    """Spike trains ``[T, B, obs_dim * pop_dim]`` of the encoder on ``obs [B, obs_dim]``."""
    activity = encoder.apply(params, obs, method=PopulationEncoder.activity)
    return regular_spike_train(activity, encoder.timesteps)
