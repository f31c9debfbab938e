"""Warm start: a new run begins from another run's networks and observation normaliser.

The optimiser starts fresh and env steps count from 0. PopSAN's ``timesteps`` may differ
between the two runs (its parameters do not depend on ``T``), so a policy trained at one ``T``
can be fine-tuned at another.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.training.checkpoint import load_run


def warm_start(state: Any, config: RunConfig, optimizer: Any, environment: Any = None) -> Any:
    """``state`` (a fresh TrainingState of ``config``) with the policy, critic and observation
    normaliser of ``config.init_from``'s ``config.init_checkpoint`` and a fresh optimiser.

    The networks must match except PopSAN's ``timesteps`` (its parameters do not depend on
    ``T``), so a policy trained at one ``T`` can be fine-tuned at another. A mismatch raises
    ConfigError; a missing or damaged source raises CheckpointError.
    """
    which = config.init_checkpoint
    source = load_run(config.init_from, int(which) if which.isdigit() else which, environment)
    theirs, ours = source.config, config
    for name in ("env", "actor", "critic_hidden_sizes"):
        if getattr(theirs, name) != getattr(ours, name):
            raise ConfigError(
                f"cannot start from {config.init_from}: its {name} {getattr(theirs, name)!r} "
                f"differs from this run's {getattr(ours, name)!r}"
            )
    keys = set(theirs.actor_kwargs) | set(ours.actor_kwargs)
    for name in sorted(keys - {"timesteps"}):
        if theirs.actor_kwargs.get(name) != ours.actor_kwargs.get(name):
            raise ConfigError(
                f"cannot start from {config.init_from}: its actor {name} "
                f"{theirs.actor_kwargs.get(name)!r} differs from this run's "
                f"{ours.actor_kwargs.get(name)!r} (only timesteps may differ)"
            )
    params = state.params.replace(policy=source.policy_params, value=source.value_params)
    shapes = [jax.tree.map(jnp.shape, p) for p in (state.params, params)]
    if shapes[0] != shapes[1]:
        raise ConfigError(f"cannot start from {config.init_from}: its network shapes differ")
    return state.replace(
        params=params,
        opt_state=optimizer.init(params),
        normalizer_params=source.normalizer_params,
    )
