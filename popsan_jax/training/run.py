"""New run or resume: from the user's choices to ``(config, run_dir)``, checked before anything
is written, and what an interrupted run leaves behind."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from popsan_jax import distributed
from popsan_jax.config import RunConfig
from popsan_jax.errors import CheckpointError, ConfigError
from popsan_jax.recipes import resolve_config
from popsan_jax.training.checkpoint_index import (
    CONFIG,
    WARMUP,
    has_checkpoint,
    index_path,
    read_index,
)
from popsan_jax.training.run_dir import check_name, check_runs_dir

# The fields a resumed run may change: its length, and whether it ends at a success (so a run
# that ended at one can be trained on to its end with --end-at-success 0).
RESUMABLE = {"total_env_steps", "end_at_success"}


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
    missing run or config, or an unreadable manifest, raises CheckpointError; both before
    anything is written. A run with its config but no checkpoint yet (killed before the first)
    is resumable: training restarts it from step 0 (popsan_jax.training.loop).
    """
    run_dir = Path(run_dir)
    bad = sorted(set(given) - RESUMABLE) + sorted(actor_given or {})
    if bad or preset or env_overrides:
        extra = ", ".join(bad) or "preset/env overrides"
        raise ConfigError(
            f"cannot change {extra} when resuming (only --total-env-steps, --end-at-success)"
        )
    if index_path(run_dir).exists() or not (run_dir / CONFIG).is_file():
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
    if name:
        check_name(name)
    check_runs_dir(runs_dir)  # a file, a kernel filesystem or read-only: now, not after compiling
    config = resolve_config(preset, backend, given, actor_given)
    name = name or f"{config.env}-{config.actor}-{time.strftime('%Y%m%d-%H%M%S')}"
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
        if not (Path(run_dir) / CONFIG).is_file():
            return "interrupted before anything was written"
        if has_checkpoint(Path(run_dir) / WARMUP):
            return (
                f"interrupted; the warm-up stage's last checkpoint is kept; resume with: "
                f"python train.py --resume {run_dir}"
            )
        return (
            f"interrupted before the first checkpoint; train it again from step 0 with: "
            f"python train.py --resume {run_dir}"
        )
    return (
        f"interrupted; the last checkpoint is kept; resume with: python train.py --resume {run_dir}"
    )


def done_message(result: Any, run_dir: Path | None, process: int, processes: int) -> str:
    """The last line of a run. Under jax.distributed only process 0 evaluates and writes the
    run, so the others say which process they were and point there."""
    steps = int(result.state.env_steps)
    if process != 0:
        return (
            f"done: process {process} of {processes} ({steps} env steps); process 0 holds the "
            f"results -> {run_dir}"
        )
    if result.finished and result.ended:  # resumed a run that ended at its end_at_success
        return (
            f"done: {run_dir} already ended at {steps} env steps (an evaluation reached its "
            f"end_at_success); to train it on: python train.py --resume {run_dir} "
            "--end-at-success 0"
        )
    if result.finished:  # resumed a run that had already reached its total
        return (
            f"done: {run_dir} already finished at {steps} env steps; to train further: "
            f"python train.py --resume {run_dir} --total-env-steps N (N > {steps})"
        )
    final = result.last_eval or {}
    return (
        f"done: {steps} env steps, success rate "
        f"{final.get('success_rate', float('nan')):.3f} -> {run_dir}"
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


def prepare_run_everywhere(
    backend: str, given: dict[str, Any], actor_given: dict[str, Any] | None = None, **choices: Any
) -> tuple[RunConfig, Path]:
    """:func:`prepare_run` on process 0 and its result on every process (one process: just
    prepare_run's); process 0's UserError stops every process (popsan_jax.distributed)."""

    def on_main() -> dict[str, Any]:
        config, run_dir = prepare_run(backend, given, actor_given, **choices)
        return {"config": json.loads(json.dumps(config.to_dict())), "run_dir": str(run_dir)}

    shared = distributed.share_from_main("run", on_main)
    return RunConfig.from_dict(shared["config"]), Path(shared["run_dir"])
