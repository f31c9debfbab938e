"""The per-iteration diagnostics logged with the training metrics: the policy's entropy and, for
a PopSAN actor, each spiking layer's firing rate and the synaptic operations per inference."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.config import RunConfig
from popsan_jax.snn.ops import sops_per_inference, spiking_layer_names
from popsan_jax.training.iteration import TrainingState
from popsan_jax.training.setup import make_spikes_fn


def make_diagnostics_fn(
    config: RunConfig, networks: ppo_networks.PPONetworks, action_size: int
) -> Callable[[TrainingState, jax.Array], dict[str, jax.Array]]:
    """``fn(state, obs [B, O]) -> {entropy, firing_rate/<layer>, sops}`` on a sample of the
    batch (``sops``: synaptic operations per inference, the energy convention's count)."""
    spikes_fn = make_spikes_fn(config, action_size) if config.actor == "popsan" else None

    def diagnostics(state: TrainingState, obs: jax.Array) -> dict[str, jax.Array]:
        logits = networks.policy_network.apply(state.normalizer_params, state.params.policy, obs)
        entropy = networks.parametric_action_distribution.entropy(logits, jax.random.PRNGKey(0))
        out = {"entropy": jnp.mean(entropy)}
        if spikes_fn is not None:
            spikes = spikes_fn(state.params.policy, state.normalizer_params, obs)
            names = spiking_layer_names(len(spikes) - 2)
            out.update(
                {f"firing_rate/{n}": jnp.mean(s) for n, s in zip(names, spikes, strict=True)}
            )
            out["sops"] = sops_per_inference(spikes)
        return out

    return diagnostics
