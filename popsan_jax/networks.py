"""ANN baseline actor, critic, and the Brax PPO network factory (actor = popsan | mlp).

Policy params layout (what ``PPONetworks.policy_network.init`` returns)::

    {"params": {"actor": <actor module's params>, "log_std": [action_size]}}

so the actor alone is applied with ``actor_module.apply(actor_variables(policy_params), obs)``,
e.g. ``make_actor("popsan", kwargs).apply(actor_variables(p), obs, return_spikes=True)``.
Value params are ``{"params": <Critic params>}``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from brax.training import distribution, networks, types
from brax.training.agents.ppo.networks import PPONetworks

from popsan_jax.config import ACTORS
from popsan_jax.errors import ConfigError
from popsan_jax.snn.popsan import PopSAN


def dense_stack(
    x: jax.Array,
    hidden_sizes: Sequence[int],
    activation: Callable,
    out_features: int,
    output_init_scale: float = 1.0,
) -> jax.Array:
    """``hidden_k`` Dense + activation layers, then a linear ``output`` layer (inside a compact
    method: the layers belong to the calling module, so its params read ``hidden_k``/``output``).

    Every kernel starts LeCun-normal; the output kernel's standard deviation is multiplied by
    ``output_init_scale`` (its bias starts at 0).
    """
    for k, size in enumerate(hidden_sizes):
        x = activation(nn.Dense(size, name=f"hidden_{k}")(x))
    init = nn.initializers.variance_scaling(output_init_scale**2, "fan_in", "truncated_normal")
    return nn.Dense(out_features, kernel_init=init, name="output")(x)


class MLPActor(nn.Module):
    """ANN baseline: obs ``[B, obs_dim]`` -> tanh action mean ``[B, action_size]``."""

    action_size: int
    hidden_sizes: Sequence[int] = (256, 256)
    activation: Callable[[jax.Array], jax.Array] = nn.elu
    output_init_scale: float = 1.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        mean = dense_stack(
            obs, self.hidden_sizes, self.activation, self.action_size, self.output_init_scale
        )
        return jnp.tanh(mean)


class Critic(nn.Module):
    """ANN value function: obs ``[..., obs_dim]`` -> value ``[...]``."""

    hidden_sizes: Sequence[int] = (256, 256, 256)
    activation: Callable[[jax.Array], jax.Array] = nn.elu

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return jnp.squeeze(dense_stack(obs, self.hidden_sizes, self.activation, 1), axis=-1)


def make_actor(name: str, actor_kwargs: Mapping[str, Any] | None, action_size: int) -> nn.Module:
    """The actor module for ``name`` ("popsan" | "mlp") built with ``actor_kwargs``.

    Unknown names or keyword arguments raise ConfigError. ``actor_kwargs`` may hold JSON-style
    lists (converted to tuples) and must not need ``action_size`` (given separately).
    """
    # JSON configs give lists; module fields should be hashable tuples.
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in (actor_kwargs or {}).items()}
    kwargs.pop("action_size", None)
    try:
        if name == "popsan":
            return PopSAN(action_size=action_size, **kwargs)
        if name == "mlp":
            return MLPActor(action_size=action_size, **kwargs)
    except TypeError as err:
        raise ConfigError(f"bad actor_kwargs for actor {name!r}: {err}") from err
    raise ConfigError(f"unknown actor {name!r}; choose one of: {', '.join(ACTORS)}")


def actor_variables(policy_params: Mapping[str, Any]) -> dict[str, Any]:
    """The actor module's variables inside a policy params tree (see module docstring)."""
    return {"params": policy_params["params"]["actor"]}


class PolicyWithLogStd(nn.Module):
    """Actor mean plus a learned state-independent log-std: obs ``[..., O]`` -> ``[..., 2A]``.

    The actor sees a flat ``[B, O]`` batch (PopSAN puts time on axis 0 of its internals), so any
    leading dims, e.g. PPO's ``[unroll, batch]``, are flattened and restored.
    """

    actor: nn.Module
    action_size: int
    init_log_std: float = -0.5

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        lead = obs.shape[:-1]
        mean = self.actor(obs.reshape(-1, obs.shape[-1])).astype(jnp.float32)
        mean = mean.reshape(*lead, self.action_size)
        log_std = self.param(
            "log_std", nn.initializers.constant(self.init_log_std), (self.action_size,)
        )
        return jnp.concatenate([mean, jnp.broadcast_to(log_std, mean.shape)], axis=-1)


class MeanLogStdNormal(distribution.NormalDistribution):
    """Normal over actions from ``[..., 2A]`` = (mean, log_std); identity postprocessing.

    The actor's mean is already tanh-squashed, so unlike Brax's ``NormalTanhDistribution`` there
    is no second tanh: ``mode == mean`` and ``scale == exp(log_std)``. Brax's public
    ``NormalDistribution`` takes ``(loc, scale)``; this one reads the policy's flat output.
    """

    def __init__(self, event_size: int) -> None:
        super().__init__(event_size)
        self.event_size = event_size

    @property
    def param_size(self) -> int:
        """The policy's output size: mean and log_std."""
        return 2 * self.event_size

    def create_dist(self, parameters: jax.Array) -> Any:
        loc, log_std = jnp.split(parameters, 2, axis=-1)
        return super().create_dist((loc, jnp.exp(log_std)))


def make_ppo_networks(
    observation_size: int,
    action_size: int,
    preprocess_observations_fn: types.PreprocessObservationFn = (
        types.identity_observation_preprocessor
    ),
    actor: str = "popsan",
    actor_kwargs: Mapping[str, Any] | None = None,
    critic_hidden_sizes: Sequence[int] = (256, 256, 256),
    init_log_std: float = -0.5,
) -> PPONetworks:
    """Brax ``PPONetworks`` with a PopSAN or MLP actor and an MLP critic.

    Works unchanged with ``brax.training.agents.ppo.networks.make_inference_fn`` and
    ``brax.training.agents.ppo.losses.compute_ppo_loss``. The policy's apply
    ``(processor_params, policy_params, obs [..., O])`` returns ``[..., 2A]`` (mean, log_std);
    the value's apply returns ``[...]``. ``preprocess_observations_fn(obs, processor_params)`` runs
    before both networks.
    """
    policy_module = PolicyWithLogStd(
        make_actor(actor, actor_kwargs, action_size), action_size, float(init_log_std)
    )
    value_module = Critic(hidden_sizes=tuple(critic_hidden_sizes))
    dummy_obs = jnp.zeros((1, int(observation_size)))

    def policy_apply(processor_params: Any, policy_params: Any, obs: jax.Array) -> jax.Array:
        return policy_module.apply(policy_params, preprocess_observations_fn(obs, processor_params))

    def value_apply(processor_params: Any, value_params: Any, obs: jax.Array) -> jax.Array:
        return value_module.apply(value_params, preprocess_observations_fn(obs, processor_params))

    return PPONetworks(
        policy_network=networks.FeedForwardNetwork(
            init=lambda key: policy_module.init(key, dummy_obs), apply=policy_apply
        ),
        value_network=networks.FeedForwardNetwork(
            init=lambda key: value_module.init(key, dummy_obs), apply=value_apply
        ),
        parametric_action_distribution=MeanLogStdNormal(action_size),
    )
