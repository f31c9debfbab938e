"""Checkpoints of a run directory (Orbax save and restore), and :func:`load_run` for replay /
evaluation.

(The manifest ``index.json``, its digests and the write errors that name the last good
checkpoint: :mod:`popsan_jax.training.checkpoint_index`. Warm-starting a new run from another
run's checkpoint is a training rule: :mod:`popsan_jax.training.warm_start`.)

A checkpoint is ``checkpoints/step_000000123456/``, an Orbax PyTree checkpoint
``{"state": TrainingState, "key": rng key}``. Atomicity: Orbax writes into a temporary directory
and renames it when complete, and the manifest lists only finished checkpoints, so a crash at
any point leaves the previous manifest and everything it names intact. Pruning keeps every
``keep_every_n_evals``-th evaluation, the last, and the best by success rate; directories are
deleted only after the manifest that drops them is in place.

A checkpoint restores into a template built from the saved ``config.json``, so shapes, the
optimiser structure and the normaliser are checked against the config; any mismatch or damage
raises :class:`popsan_jax.errors.CheckpointError`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import gc
import logging
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from brax.training import types as brax_types
from brax.training.agents.ppo import networks as ppo_networks

import envs
from popsan_jax.config import RunConfig
from popsan_jax.errors import CheckpointError, ConfigError
from popsan_jax.training.checkpoint_index import (
    CONFIG,
    checkpoint_digest,
    checkpoint_dir,
    find_entry,
    first_line,
    index_path,
    last_good,
    read_index,
    verify_checkpoint,
    write_index,
)
from popsan_jax.training.iteration import init_training_state
from popsan_jax.training.run_dir import checkpoint_name, contained, deferred_signals
from popsan_jax.training.setup import build_networks, make_env, make_optimizer


def _checkpointer() -> ocp.Checkpointer:
    """An Orbax checkpointer that acts for this process alone. Under jax.distributed only
    process 0 saves and restores; Orbax's default cross-process barriers would wait for
    processes that never call it (orbax #211)."""
    me = jax.process_index()
    options = ocp.options.MultiprocessingOptions(primary_host=me, active_processes={me})
    return ocp.Checkpointer(ocp.StandardCheckpointHandler(), multiprocessing_options=options)


@flax.struct.dataclass
class _HostUInt64:
    """Brax's ``UInt64`` (the normaliser's count) with the same fields but NumPy leaves: Brax's
    own turns them back into jax arrays whenever it is built (``__post_init__``)."""

    hi: Any
    lo: Any


def _host_tree(tree: Any) -> Any:
    """``tree`` with NumPy leaves: under jax.distributed Orbax refuses to save a jax.Array that
    lives on one process ("host local jax.Array in multi-host setting")."""

    def host(x: Any) -> Any:
        if isinstance(x, brax_types.UInt64):
            return _HostUInt64(hi=np.asarray(x.hi), lo=np.asarray(x.lo))
        return np.asarray(x)

    return jax.tree.map(host, tree, is_leaf=lambda x: isinstance(x, brax_types.UInt64))


def _check_finite(tree: Any, path: Path) -> None:
    for leaf_path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.floating) and not np.all(np.isfinite(leaf)):
            name = jax.tree_util.keystr(leaf_path)
            raise CheckpointError(f"checkpoint {path} holds non-finite values in {name}; refused")


def save_checkpoint(
    run_dir: str | os.PathLike,
    state: Any,
    key: jax.Array,
    eval_index: int,
    success_rate: float,
    keep_every_n_evals: int,
) -> Path:
    """Write ``state`` (un-replicated TrainingState) and the host rng ``key``; update the manifest
    and prune. Returns the checkpoint directory.

    SIGINT/SIGTERM wait until the checkpoint and its manifest are complete
    (:func:`~popsan_jax.training.run_dir.deferred_signals`) and the write is synchronous, so no
    Orbax thread outlives an interrupted or failed write. A failed write (disk full, read-only)
    removes Orbax's unfinished directory and raises one CheckpointError line naming the last
    good checkpoint; an altered manifest is refused, never replaced.
    """
    run_dir = Path(run_dir).absolute()  # Orbax rejects relative paths
    root = checkpoint_dir(run_dir)
    step = int(state.env_steps)
    name = checkpoint_name(step)
    try:
        index = read_index(run_dir)
    except CheckpointError:
        if index_path(run_dir).exists():
            raise
        index = {"checkpoints": [], "last": None, "best": None}
    with deferred_signals(), _quiet_orbax():
        try:
            root.mkdir(parents=True, exist_ok=True)
            _check_free_space(root, (state, key))
            with _checkpointer() as ckptr:
                # force: a directory left by a crash between the Orbax write and the manifest
                # update is not listed anywhere and may be overwritten.
                ckptr.save(root / name, _host_tree({"state": state, "key": key}), force=True)
            entries = [e for e in index["checkpoints"] if e["step"] != step]
            entries.append(
                dict(
                    step=step,
                    eval_index=eval_index,
                    success_rate=float(success_rate),
                    dir=name,
                    digest=checkpoint_digest(root / name),
                )
            )
            best = max(entries, key=lambda e: (e["success_rate"], e["step"]))
            kept = [
                e
                for e in entries
                if e["step"] in (step, best["step"]) or e["eval_index"] % keep_every_n_evals == 0
            ]
            write_index(run_dir, {"checkpoints": kept, "last": step, "best": best["step"]})
        except Exception as e:  # ENOSPC, EROFS...: Orbax wraps them in many types
            for tmp in root.glob(f"{name}.orbax-checkpoint-tmp*"):
                shutil.rmtree(tmp, ignore_errors=True)
            raise CheckpointError(
                f"cannot write checkpoint {root / name}: {first_line(e)}; {last_good(index)}"
            ) from e
        for e in entries:
            if e not in kept:
                try:
                    doomed = contained(root, e["dir"], "pruned checkpoint")
                except CheckpointError:
                    continue  # never delete outside checkpoints/; the entry is dropped anyway
                shutil.rmtree(doomed, ignore_errors=True)
    return root / name


@contextlib.contextmanager
def _quiet_orbax() -> Iterator[None]:
    """No third-party tracebacks from a failed write: Orbax logs each failing thread's report
    (absl) and asyncio reports never-retrieved futures; the CheckpointError says it in one line."""
    loggers = [logging.getLogger(n) for n in ("absl", "asyncio", "orbax")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        gc.collect()  # failed futures report when collected: now, while silenced
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def _check_free_space(root: Path, tree: Any) -> None:
    """ENOSPC before Orbax starts, where the size is known: the arrays twice, plus 1 MiB."""
    need = sum(int(np.asarray(x).nbytes) for x in jax.tree.leaves(tree)) * 2 + (1 << 20)
    free = shutil.disk_usage(root).free
    if free < need:
        raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({free} bytes free)")


def restore_checkpoint(
    run_dir: str | os.PathLike, template: Any, which: str | int = "last"
) -> tuple[Any, jax.Array, dict[str, Any]]:
    """Restore ``(state, key, manifest entry)`` into the structure of ``template`` (a fresh
    TrainingState from the same config)."""
    index = read_index(run_dir)
    entry = find_entry(index, which)
    path = contained(checkpoint_dir(run_dir), entry.get("dir"))
    verify_checkpoint(run_dir, index, entry)  # old manifests without digests load unverified
    target = {"state": template, "key": jax.random.PRNGKey(0)}
    abstract = jax.tree.map(lambda x: ocp.utils.to_shape_dtype_struct(jnp.asarray(x)), target)
    try:
        with deferred_signals(), _checkpointer() as ckptr:
            restored = ckptr.restore(path.absolute(), abstract)
    except Exception as e:  # Orbax raises many types for damaged or mismatched data
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise CheckpointError(f"cannot restore checkpoint {path}: {msg[:300]}") from e
    _check_finite(restored, path)
    return restored["state"], restored["key"], entry


@dataclasses.dataclass
class LoadedRun:
    """A checkpoint rebuilt from its run directory alone.

    ``networks`` are the PPONetworks rebuilt from ``config``; ``env`` is the unwrapped env.
    """

    config: RunConfig
    step: int
    normalizer_params: Any
    policy_params: Any
    value_params: Any
    networks: ppo_networks.PPONetworks
    env: Any
    entry: dict[str, Any]

    def make_policy(
        self, deterministic: bool = True
    ) -> Callable[[jax.Array, jax.Array], jax.Array]:
        """``policy(obs [N, O], key) -> action [N, A]`` (the actor mean when deterministic)."""
        inference = ppo_networks.make_inference_fn(self.networks)(
            (self.normalizer_params, self.policy_params), deterministic=deterministic
        )
        return lambda obs, key: inference(obs, key)[0]


def load_run(
    run_dir: str | os.PathLike,
    which: str | int = "last",
    environment: Any = None,
    env_overrides: dict[str, Any] | None = None,
) -> LoadedRun:
    """Load a checkpoint (``"last"``, ``"best"`` or an env-step count) from a run directory.

    ``environment`` replaces the env named in the config (for custom envs); ``env_overrides``
    are merged over the config's own (evaluating under changed env settings; an unknown key
    raises ConfigError). Missing, corrupt or incompatible data raises CheckpointError.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"run directory {run_dir} does not exist")
    try:
        config = RunConfig.from_json(run_dir / CONFIG)
    except ConfigError as e:
        raise CheckpointError(f"run {run_dir} has an unusable config: {e}") from e
    if env_overrides:
        if environment is not None:
            raise ConfigError("env overrides apply to the run's own env, not a custom one")
        merged = envs.merge_overrides(config.env_overrides, env_overrides)
        config = config.replace(env_overrides=merged)
        environment = make_env(config)  # an unknown key is the caller's ConfigError
    try:
        env = environment if environment is not None else make_env(config)
        networks = build_networks(config, env.observation_size, env.action_size)
    except ConfigError as e:
        raise CheckpointError(f"run {run_dir} has an unusable config: {e}") from e
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"run {run_dir}: config does not build networks: {e}") from e
    template = init_training_state(
        config,
        networks,
        make_optimizer(config),
        env.observation_size,
        jax.random.PRNGKey(0),
    )
    state, _, entry = restore_checkpoint(run_dir, template, which)
    return LoadedRun(
        config=config,
        step=int(state.env_steps),
        normalizer_params=state.normalizer_params,
        policy_params=state.params.policy,
        value_params=state.params.value,
        networks=networks,
        env=env,
        entry=entry,
    )
