"""New run or resume: from the user's choices to ``(config, run_dir)``, checked before anything
is written, and what an interrupted run leaves behind."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

from popsan_jax.config import RunConfig, resolve_config
from popsan_jax.errors import CheckpointError, ConfigError
from popsan_jax.training.checkpoint import CONFIG, read_index

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+=,-]*")


def check_name(name: str) -> str:
    """``name`` if it is a plain directory name, else ConfigError (one line)."""
    if not isinstance(name, str) or len(name) > 200 or not _NAME.fullmatch(name):
        raise ConfigError(
            f"--name must be a plain directory name (letters, digits, _ . + = , -; no '/', "
            f"'..' or absolute path), got {name!r}"
        )
    return name


RESUMABLE = {"total_env_steps"}  # the only field a resumed run may change


def resume_config(
    run_dir: str | Path,
    given: dict[str, Any],
    actor_given: dict[str, Any] | None = None,
    preset: str | None = None,
    env_overrides: dict[str, Any] | None = None,
    wandb: bool = False,
) -> RunConfig:
    """The saved config of ``run_dir`` with ``given`` (only RESUMABLE fields) applied.

    Any other change (a field, an actor kwarg, a preset, env overrides) raises ConfigError; a
    missing run, checkpoint or config raises CheckpointError; both before anything is written.
    """
    run_dir = Path(run_dir)
    bad = sorted(set(given) - RESUMABLE) + sorted(actor_given or {})
    if bad or preset or env_overrides:
        extra = ", ".join(bad) or "preset/env overrides"
        raise ConfigError(f"cannot change {extra} when resuming (only --total-env-steps)")
    read_index(run_dir)  # fails early with a clear CheckpointError
    try:
        config = RunConfig.from_json(run_dir / CONFIG)
    except ConfigError as e:
        raise CheckpointError(str(e)) from e
    return config.replace(**given, **({"wandb": True} if wandb else {}))


def new_run(
    preset: str | None,
    backend: str,
    given: dict[str, Any],
    actor_given: dict[str, Any],
    runs_dir: str | Path,
    name: str | None = None,
) -> tuple[RunConfig, Path]:
    """The resolved config of a new run and its (not yet existing) directory.

    ``name`` defaults to ``<env>-<actor>-<timestamp>``; an existing directory raises ConfigError.
    """
    config = resolve_config(preset, backend, given, actor_given)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    name = check_name(name) if name else f"{config.env}-{config.actor}-{stamp}"
    run_dir = Path(runs_dir) / name
    if run_dir.exists():
        raise ConfigError(f"run directory {run_dir} exists; use --resume or a new --name")
    return config, run_dir


def interrupted_message(run_dir: Path | None) -> str:
    """What an interrupted run left behind: a checkpoint to resume from, or none yet."""
    if run_dir is None:
        return "interrupted"
    try:
        read_index(run_dir)
    except CheckpointError:
        return f"interrupted before the first checkpoint; {run_dir} has nothing to resume"
    return (
        f"interrupted; the last checkpoint is kept; resume with: python train.py --resume {run_dir}"
    )


def prepare_run(
    backend: str,
    given: dict[str, Any],
    actor_given: dict[str, Any] | None = None,
    *,
    preset: str | None = None,
    env_overrides: dict[str, Any] | None = None,
    wandb: bool = False,
    resume: str | Path | None = None,
    runs_dir: str | Path = "runs",
    name: str | None = None,
) -> tuple[RunConfig, Path]:
    """``(config, run_dir)`` of train.py's command line: the resumed run's saved config
    (:func:`resume_config`) or a new run's resolved one (:func:`new_run`). Writes nothing."""
    if resume:
        config = resume_config(resume, given, actor_given, preset, env_overrides, wandb)
        return config, Path(resume)
    given = dict(given)
    if env_overrides:
        given["env_overrides"] = dict(env_overrides)
    if wandb:
        given["wandb"] = True
    return new_run(preset, backend, given, actor_given or {}, runs_dir, name)
