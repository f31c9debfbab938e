"""Warm start: a new run begins from another run's networks and observation normaliser: its
warm-up stage's (popsan_jax/training/stages.py) or ``init_from``'s.

The optimiser starts fresh and env steps count from 0. PopSAN's ``timesteps`` may differ
between the two runs (its parameters do not depend on ``T``), so a policy trained at one ``T``
can be fine-tuned at another.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.training.checkpoint import load_run
from popsan_jax.training.checkpoint_index import WARMUP


def warm_source(config: RunConfig, run_dir: str | Path) -> tuple[str, str] | None:
    """``(run directory, checkpoint)`` that a new run of ``config`` in ``run_dir`` starts from:
    its warm-up stage's last checkpoint, else ``init_from``'s, else None (from scratch)."""
    if config.warmup_env_steps:
        return str(Path(run_dir) / WARMUP), "last"
    if config.init_from:
        return config.init_from, config.init_checkpoint
    return None


# Actor kwargs a warm start may change: neither changes the parameters or what loaded ones do.
FREE_ACTOR_KWARGS = frozenset({"timesteps", "output_init_scale", "decoder_init_scale"})


def check_same_networks(theirs: RunConfig, ours: RunConfig, where: str) -> None:
    """ConfigError unless a run of config ``ours`` can start from one of ``theirs`` (found at
    ``where``): the same env, actor and critic, and the same actor kwargs except those in
    ``FREE_ACTOR_KWARGS`` (a kwarg one config lacks counts as different, unless free)."""
    for name in ("env", "actor", "critic_hidden_sizes"):
        if getattr(theirs, name) != getattr(ours, name):
            raise ConfigError(
                f"cannot start from {where}: its {name} {getattr(theirs, name)!r} "
                f"differs from this run's {getattr(ours, name)!r}"
            )
    keys = set(theirs.actor_kwargs) | set(ours.actor_kwargs)
    for name in sorted(keys - FREE_ACTOR_KWARGS):
        if theirs.actor_kwargs.get(name) != ours.actor_kwargs.get(name):
            raise ConfigError(
                f"cannot start from {where}: its actor {name} "
                f"{theirs.actor_kwargs.get(name)!r} differs from this run's "
                f"{ours.actor_kwargs.get(name)!r} (only {', '.join(sorted(FREE_ACTOR_KWARGS))} "
                "may differ)"
            )


def warm_start(
    state: Any, config: RunConfig, optimizer: Any, source: tuple[str, str], environment: Any = None
) -> Any:
    """``state`` (a fresh TrainingState of ``config``) with the policy, critic and observation
    normaliser of ``source`` (``(run directory, checkpoint)``, see :func:`warm_source`) and a
    fresh optimiser.

    The networks must match except in ``FREE_ACTOR_KWARGS``: PopSAN's ``timesteps`` (its
    parameters do not depend on ``T``), so a policy trained at one ``T`` can be fine-tuned at
    another, and the MLP's ``output_init_scale`` and PopSAN's ``decoder_init_scale`` (they only
    scale the initial draw, which the loaded parameters replace). A mismatch raises
    ConfigError; a missing or damaged source raises CheckpointError.
    """
    where, which = source
    loaded = load_run(where, int(which) if which.isdigit() else which, environment)
    check_same_networks(loaded.config, config, where)
    params = state.params.replace(policy=loaded.policy_params, value=loaded.value_params)
    shapes = [jax.tree.map(jnp.shape, p) for p in (state.params, params)]
    if shapes[0] != shapes[1]:
        raise ConfigError(f"cannot start from {where}: its network shapes differ")
    return state.replace(
        params=params,
        opt_state=optimizer.init(params),
        normalizer_params=loaded.normalizer_params,
    )
