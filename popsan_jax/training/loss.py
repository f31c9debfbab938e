"""The training loss: Brax's PPO loss plus the optional synaptic-operation (spike) penalty.

Why a penalty: the energy target compares SNN and ANN at the smallest ``T`` that still succeeds,
and PopSAN policies trained by PPO alone fire more than that target allows (docs/design.md,
"The spike penalty"). The penalty charges the quantity the energy convention counts, synaptic
operations per inference (:func:`popsan_jax.snn.ops.sops_per_inference`), above a budget::

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
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.config import RunConfig
from popsan_jax.snn.ops import sops_per_inference
from popsan_jax.training.setup import make_spikes_fn


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
