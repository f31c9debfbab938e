"""PopSAN spikes measured inside training, and the optional synaptic-operation penalty in the loss.

Why a penalty: the energy target compares SNN and ANN at the smallest ``T`` that still succeeds,
and PopSAN policies trained by PPO alone fire more than that target allows (pick, 30 November:
80-82 % saving at T = 3, docs/results.md "Energy"). Training at T = 2 from scratch or fine-tuning
at T = 2 raised the firing rates instead of lowering them. The penalty charges the quantity the
energy convention counts, synaptic operations per inference (:func:`energy.sops_per_inference`),
above a budget::

    loss = compute_ppo_loss(...) + sop_cost * max(0, SOPs - sop_budget) / 1000

Its gradient reaches the weights, the LIF thresholds' inputs and the encoder's receptive fields
through the same surrogate / straight-through gradients as the policy loss. Below the budget it
adds nothing, so PPO alone decides how to spend the allowed spikes.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.analysis.energy import sops_per_inference
from popsan_jax.config import RunConfig

SpikesFn = Callable[[Any, Any, jax.Array], tuple[jax.Array, ...]]


def make_spikes_fn(config: RunConfig, action_size: int) -> SpikesFn:
    """``spikes(policy_params, normalizer_params, obs [B, O]) -> ([T, B, N_l] per layer)``.

    The observation goes through the same clipped normalisation as the policy's own input.
    Only for the PopSAN actor.
    """
    from popsan_jax.networks import actor_variables, make_actor

    actor = make_actor(config.actor, dict(config.actor_kwargs), action_size)

    def spikes(policy_params: Any, normalizer_params: Any, obs: jax.Array) -> tuple[jax.Array, ...]:
        normed = running_statistics.normalize(obs, normalizer_params, max_abs_value=config.obs_clip)
        return actor.apply(actor_variables(policy_params), normed, return_spikes=True)[1]

    return spikes


def sop_penalty(config: RunConfig, sops: jax.Array) -> jax.Array:
    """``sop_cost * max(0, sops - sop_budget) / 1000`` (scalar)."""
    return config.sop_cost * jax.nn.relu(sops - config.sop_budget) / 1000.0


def make_loss_fn(
    config: RunConfig, networks: ppo_networks.PPONetworks, action_size: int
) -> Callable[..., tuple[jax.Array, dict[str, jax.Array]]]:
    """Brax's ``compute_ppo_loss`` with this config's settings, plus the SOP penalty when
    ``config.sop_cost > 0`` (then the metrics also hold ``sops`` and ``sop_penalty``).

    Signature as Brax's: ``loss(params, normalizer_params, data, key) -> (total, metrics)``;
    ``data.observation`` is ``[S, L, O]``.
    """
    ppo_loss = functools.partial(
        ppo_losses.compute_ppo_loss,
        ppo_network=networks,
        entropy_cost=config.entropy_cost,
        discounting=config.discounting,
        reward_scaling=config.reward_scaling,
        gae_lambda=config.gae_lambda,
        clipping_epsilon=config.clipping_epsilon,
        normalize_advantage=config.normalize_advantage,
        vf_coefficient=config.vf_coefficient,
    )
    if not config.sop_cost:
        return ppo_loss
    spikes_fn = make_spikes_fn(config, action_size)

    def loss(
        params: ppo_losses.PPONetworkParams, normalizer_params: Any, data: Any, key: jax.Array
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        total, metrics = ppo_loss(params, normalizer_params, data, key)
        obs = jnp.reshape(data.observation, (-1, data.observation.shape[-1]))
        sops = sops_per_inference(spikes_fn(params.policy, normalizer_params, obs))
        penalty = sop_penalty(config, sops)
        return total + penalty, {
            **metrics,
            "total_loss": total + penalty,
            "sops": sops,
            "sop_penalty": penalty,
        }

    return loss
