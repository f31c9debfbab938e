"""What a run is built from: its env, its networks and optimiser, and the one observation
preprocessing in front of every network.

Everything here is a function of the :class:`~popsan_jax.config.RunConfig` alone, so the trainer,
checkpoint reloading, the spike penalty and the evaluation all build the same pieces.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import optax
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks

import envs
from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.networks import actor_variables, make_actor, make_ppo_networks

SpikesFn = Callable[[Any, Any, jax.Array], tuple[jax.Array, ...]]


def make_env(config: RunConfig) -> Any:
    """The unwrapped env named by the config, as of the env revision the run was made with
    (``envs.legacy_overrides``, under the run's own overrides); envs' own errors become
    ConfigError."""
    try:
        legacy = envs.legacy_overrides(config.env, config.env_revision)
        overrides = envs.merge_overrides(legacy, config.env_overrides)
        return envs.get_environment(config.env, **overrides)
    except envs.EnvConfigError as e:
        raise ConfigError(str(e)) from e


def preprocess_observations(obs: jax.Array, normalizer_params: Any, obs_clip: float) -> jax.Array:
    """The observation every network sees: running mean/std normalised, clipped to ±obs_clip
    (the clip matches the encoder's receptive-field range)."""
    return running_statistics.normalize(obs, normalizer_params, max_abs_value=obs_clip)


def trained_timesteps(config: RunConfig) -> int | None:
    """T the PopSAN was trained with (None for an ANN run)."""
    return int(config.actor_kwargs["timesteps"]) if config.actor == "popsan" else None


def at_timesteps(config: RunConfig, timesteps: int | None) -> RunConfig:
    """``config`` with its PopSAN run at ``timesteps`` (None = as trained). The PopSAN's
    parameters do not depend on T, so the same parameters serve every T."""
    if timesteps is None or timesteps == trained_timesteps(config):
        return config
    return config.replace(actor_kwargs={**config.actor_kwargs, "timesteps": int(timesteps)})


def build_networks(
    config: RunConfig, observation_size: int, action_size: int
) -> ppo_networks.PPONetworks:
    """The run's PPO networks, with :func:`preprocess_observations` in front of both."""
    preprocess = functools.partial(preprocess_observations, obs_clip=config.obs_clip)
    return make_ppo_networks(
        observation_size,
        action_size,
        preprocess_observations_fn=preprocess,
        actor=config.actor,
        actor_kwargs=dict(config.actor_kwargs),
        critic_hidden_sizes=tuple(config.critic_hidden_sizes),
        init_log_std=config.init_log_std,
    )


def make_spikes_fn(config: RunConfig, action_size: int) -> SpikesFn:
    """``spikes(policy_params, normalizer_params, obs [B, O]) -> ([T, B, N_l] per layer)``.

    The observation goes through the policy's own preprocessing. Only for the PopSAN actor.
    """
    actor = make_actor(config.actor, dict(config.actor_kwargs), action_size)

    def spikes(policy_params: Any, normalizer_params: Any, obs: jax.Array) -> tuple[jax.Array, ...]:
        normed = preprocess_observations(obs, normalizer_params, config.obs_clip)
        return actor.apply(actor_variables(policy_params), normed, return_spikes=True)[1]

    return spikes


def make_optimizer(config: RunConfig) -> optax.GradientTransformation:
    """Adam with separate actor / critic learning rates (the PopSAN paper's 1e-5 / 1e-4 split),
    optional cosine decay over the whole run, and optional grad-norm clipping: of the joint
    gradient, or (``clip_per_network``) of the actor's and the critic's each.

    With a critic warm-up the actor's rate is 0 for its first updates and its schedule (the
    cosine decay included) runs over the remaining ones."""
    per_iteration = config.num_updates_per_batch * config.num_minibatches
    total_updates = config.num_iterations * per_iteration
    frozen = config.critic_warmup_iterations * per_iteration

    def lr(value: float, skip: int = 0) -> optax.ScalarOrSchedule:
        rate: optax.ScalarOrSchedule = value
        if config.lr_schedule == "cosine":
            rate = optax.cosine_decay_schedule(value, decay_steps=total_updates - skip)
        if not skip:
            return rate
        after = rate if callable(rate) else optax.constant_schedule(rate)
        return optax.join_schedules([optax.constant_schedule(0.0), after], [skip])

    def labels(params: ppo_losses.PPONetworkParams) -> ppo_losses.PPONetworkParams:
        return ppo_losses.PPONetworkParams(
            policy=jax.tree.map(lambda _: "actor", params.policy),
            value=jax.tree.map(lambda _: "critic", params.value),
        )

    def adam(rate: optax.ScalarOrSchedule) -> optax.GradientTransformation:
        if config.clip_per_network and config.max_grad_norm is not None:
            # inside multi_transform, the norm is of this network's gradients alone
            return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(rate))
        return optax.adam(rate)

    split = optax.multi_transform(
        {"actor": adam(lr(config.actor_lr, frozen)), "critic": adam(lr(config.critic_lr))},
        labels,
    )
    if config.max_grad_norm is None or config.clip_per_network:
        return split
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), split)
