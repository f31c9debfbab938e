"""PPO training loop: our own host loop around Brax's PPO pieces.

Why not ``brax.training.agents.ppo.train``: it cannot resume the optimiser state
(google/brax#655, performance dips after a restore), it uses one learning rate for actor and
critic (the PopSAN paper used actor 1e-5 / critic 1e-4), and it has no NaN stop or per-update
hook for logging and checkpointing. So this loop REUSES Brax's pieces instead of copying them:
``ppo.losses.compute_ppo_loss`` (GAE + clipped surrogate), ``acting.generate_unroll``,
``acme.running_statistics`` (observation normalisation, clipped to ``obs_clip``),
``gradients.gradient_update_fn``, ``envs.wrappers.training.wrap`` and ``ppo.networks``.

One training iteration (unroll, normaliser update, minibatch epochs) is a single pmapped
function over ``jax.local_devices()`` (:mod:`popsan_jax.training.iteration`), whose
collectives span every process under ``jax.distributed`` (:mod:`popsan_jax.distributed`); the
host loop only logs, evaluates (:mod:`popsan_jax.training.evaluation`), checks for NaN and writes
checkpoints (:mod:`popsan_jax.training.checkpoint`) between iterations.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
from brax.envs.wrappers import training as brax_training
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax import distributed
from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError, NonFiniteError
from popsan_jax.training import checkpoint, checkpoint_index
from popsan_jax.training.diagnostics import make_diagnostics_fn
from popsan_jax.training.evaluation import make_evaluate_fn
from popsan_jax.training.iteration import (
    AXIS,
    TrainingState,
    init_training_state,
    make_iteration_fn,
    param_policy,
    prime_normalizer,
    stagger_episodes,
)
from popsan_jax.training.run_dir import RunLock, check_run_dir
from popsan_jax.training.run_log import RunLogger, SilentLogger, wandb_available
from popsan_jax.training.setup import build_networks, make_env, make_optimizer
from popsan_jax.training.warm_start import warm_source, warm_start


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` hands back: final (un-replicated) state and the last eval record;
    ``finished`` when a resumed run had already reached its ``total_env_steps`` or ended at an
    evaluation that reached ``end_at_success`` (then also ``ended``)."""

    state: TrainingState
    key: jax.Array
    last_eval: dict[str, Any] | None
    run_dir: Path
    finished: bool = False
    ended: bool = False


@dataclasses.dataclass
class Trainer:
    """The compiled-once pieces of a run: env (unwrapped and training-wrapped), networks,
    optimiser and the pmapped ``iteration(state [D], env_state [D], keys [D]) -> (state,
    env_state, metrics)`` (D = local devices; the training state and env state are donated)."""

    config: RunConfig
    env: Any
    wrapped: Any
    networks: ppo_networks.PPONetworks
    optimizer: Any
    iteration: Callable[..., Any]
    episode_length: int
    devices: list[Any]


def build_trainer(config: RunConfig, environment: Any = None) -> Trainer:
    """Validate ``config`` against all devices of all processes (the sizes are global) and
    build the training pieces; the pmapped functions run on this process's local devices."""
    devices = jax.local_devices()
    config.validate(jax.device_count())
    env = environment if environment is not None else make_env(config)
    episode_length = config.episode_length or int(env.config.episode_length)
    wrapped = brax_training.wrap(env, episode_length=episode_length, action_repeat=1)
    networks = build_networks(config, env.observation_size, env.action_size)
    optimizer = make_optimizer(config)
    iteration = jax.pmap(
        make_iteration_fn(
            config,
            wrapped,
            networks,
            optimizer,
            make_diagnostics_fn(config, networks, env.action_size),
        ),
        axis_name=AXIS,
        donate_argnums=(0, 1),
    )
    return Trainer(config, env, wrapped, networks, optimizer, iteration, episode_length, devices)


def _stagger(t: Trainer, make_policy: Callable[..., Any]) -> Callable[..., Any]:
    """pmapped ``(state [D], env_state [D], keys [D]) -> env_state``: stagger_episodes
    with the run's stochastic policy."""

    def stagger(state: TrainingState, env_state: Any, key: jax.Array) -> Any:
        params = (state.normalizer_params, state.params.policy)
        return stagger_episodes(
            t.wrapped, env_state, param_policy(make_policy), params, key, t.episode_length
        )

    return jax.pmap(stagger)


def _prime(t: Trainer, make_policy: Callable[..., Any]) -> Callable[..., Any]:
    """pmapped ``(state [D], env_state [D], keys [D]) -> (state, env_state)``: the normaliser
    seeded by prime_normalizer with the run's untrained stochastic policy."""

    def prime(state: TrainingState, env_state: Any, key: jax.Array) -> tuple[Any, Any]:
        params = (state.normalizer_params, state.params.policy)
        steps = t.config.prime_normalizer_episodes * t.episode_length
        normalizer, env_state = prime_normalizer(
            t.wrapped,
            env_state,
            param_policy(make_policy),
            params,
            state.normalizer_params,
            key,
            steps,
        )
        return state.replace(normalizer_params=normalizer), env_state

    return jax.pmap(prime, axis_name=AXIS)


def _unreplicate(tree: Any) -> Any:
    """The first local device's copy of a pmapped tree (under jax.distributed the arrays span
    every process, and only the local copies can be read)."""
    return jax.tree.map(lambda x: x.addressable_data(0).reshape(x.shape[1:]), tree)


def train(
    config: RunConfig,
    run_dir: str | Path,
    *,
    resume: bool = False,
    environment: Any = None,
    progress: bool = True,
    on_iteration: Callable[[int, dict[str, float]], None] | None = None,
) -> TrainResult:
    """Train ``config`` into ``run_dir`` (created; resumed from its last checkpoint if ``resume``).

    ``environment`` replaces the env named in the config (custom envs, tests). Raises
    ConfigError for impossible sizes, CheckpointError for a bad resume directory and
    NonFiniteError (with the env step) when the loss or parameters stop being finite; the last
    good checkpoint is then left untouched.

    The run's lock (popsan_jax/training/run_dir.py) is held throughout: a second trainer on it
    is refused. A resumed run first writes its config (a new ``total_env_steps`` is kept even
    if it is killed again); a resumed run with no checkpoint yet trains again from step 0; a
    resumed run that is already finished returns at once with ``finished``. A run with
    ``end_at_success`` ends after its first evaluation that reaches it, which also counts as
    finished on resume. A failed write (disk full, read-only) is one CheckpointError line
    naming the last good checkpoint.

    Under jax.distributed every process calls this with the same arguments; process 0 alone
    touches ``run_dir`` (lock, checks, restore, config, metrics, evaluation, checkpoints) and
    its errors stop every process (popsan_jax/distributed.py).
    """
    run_dir = Path(run_dir)
    main = distributed.is_main()
    lock = RunLock(run_dir, note=_note)

    def check() -> None:
        if config.wandb and not wandb_available():  # before anything is written
            raise ConfigError(
                "--wandb needs the wandb package (pip install wandb); it is not installed"
            )
        check_run_dir(run_dir, resume)  # writable, metrics.jsonl on its schema: before compiling

    distributed.share_from_main("checked", check)
    t = build_trainer(config, environment)
    key = jax.random.PRNGKey(config.seed)
    key, key_init = jax.random.split(key)
    state = init_training_state(config, t.networks, t.optimizer, t.env.observation_size, key_init)
    source = warm_source(config, run_dir)

    def start() -> dict[str, Any]:
        """Process 0: lock the run, restore or warm-start its state."""
        nonlocal state, key
        restart = resume and not checkpoint_index.index_path(run_dir).exists()
        if not resume or restart:
            if source is not None:
                state = warm_start(state, config, t.optimizer, source, environment)
            run_dir.mkdir(parents=True, exist_ok=True)
        lock.acquire()
        if restart:
            _note(f"note: {run_dir} has no checkpoint yet; training it again from step 0")
        elif resume:
            state, key, entry = checkpoint.restore_checkpoint(run_dir, state, "last")
            return {
                "eval_index": entry["eval_index"],
                "restart": False,
                "resume": True,
                "ended": _reached_end(config, entry["success_rate"]),
            }
        return {"eval_index": 0, "restart": restart, "resume": False, "ended": False}

    try:
        started = distributed.share_from_main("started", start)
        distributed.barrier("started")  # the broadcast is the first collective
        # NumPy on every process: one set of types (no weak types), so a resumed run compiles
        # the iteration for the same types as a new one.
        state, key = distributed.broadcast_from_main((state, key))
        at_total = int(state.env_steps) >= config.num_iterations * config.env_steps_per_iteration
        if at_total or started["ended"]:
            return TrainResult(
                state=state,
                key=key,
                last_eval=None,
                run_dir=run_dir,
                finished=True,
                ended=not at_total,
            )
        return _train_started(t, config, run_dir, state, key, started, progress, on_iteration)
    except OSError as e:  # ENOSPC, EROFS... writing the config, the metrics or TensorBoard's log
        if not main:
            raise
        raise checkpoint_index.write_error(run_dir, e) from e
    finally:
        lock.release()


def _reached_end(config: RunConfig, success_rate: float) -> bool:
    """Whether an evaluation of ``success_rate`` ends a run of ``config`` (end_at_success)."""
    return bool(config.end_at_success) and success_rate >= config.end_at_success


def _note(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _train_started(
    t: Trainer,
    config: RunConfig,
    run_dir: Path,
    state: TrainingState,
    key: jax.Array,
    started: dict[str, Any],
    progress: bool,
    on_iteration: Callable[[int, dict[str, float]], None] | None,
) -> TrainResult:
    """The body of :func:`train` once every process holds the start state (process 0 holds
    the run's lock)."""
    env, networks, devices = t.env, t.networks, t.devices
    main = distributed.is_main()
    eval_index = started["eval_index"]
    if main:
        config.to_json(run_dir / checkpoint_index.CONFIG)
    start_steps = int(state.env_steps)
    start_iteration = start_steps // config.env_steps_per_iteration
    episode_length = t.episode_length

    make_policy = ppo_networks.make_inference_fn(networks)
    evaluate = make_evaluate_fn(env, networks, config.num_eval_envs, episode_length)
    logger: Any = SilentLogger()
    if main:
        logger = RunLogger(
            run_dir,
            config.num_iterations * config.env_steps_per_iteration,
            initial_steps=start_steps,
            config=config.to_dict(),
            use_wandb=config.wandb,
            progress=progress,
            restart=started["restart"],
        )
    try:
        logger.message(
            f"compiling: {config.actor} actor on {config.env}, {config.num_envs} envs on "
            f"{jax.device_count()} {jax.default_backend()} device(s)"
            f"{distributed.processes_note()}, "
            f"{config.env_steps_per_iteration} env steps/iteration, "
            f"{config.num_iterations} iterations (starting at {start_iteration}) -> {run_dir}"
        )
        source = warm_source(config, run_dir)
        if source is not None and not started["resume"]:
            logger.message(f"initialised from {source[0]} ({source[1]} checkpoint)")
        key, key_env = jax.random.split(key)
        env_keys = distributed.local_slice(jax.random.split(key_env, config.num_envs))
        env_state = jax.pmap(t.wrapped.reset)(env_keys)
        last_eval = None
        if start_steps == 0:  # the untrained policy's baseline starts every learning curve
            key, key_eval = jax.random.split(key)
            if main:
                last_eval = logger.log("eval", 0, evaluate(state, key_eval))
        state_r = jax.device_put_replicated(state, devices)
        del state
        if config.prime_normalizer_episodes and not start_steps and source is None:
            logger.message(
                f"priming the observation normaliser: {config.prime_normalizer_episodes} "
                "episode(s) of the untrained policy (not counted)"
            )
            key, key_prime = jax.random.split(key)
            state_r, env_state = _prime(t, make_policy)(
                state_r, env_state, distributed.device_keys(key_prime)
            )
        if start_steps or source is not None:  # a trained policy: see stagger_episodes
            logger.message("trained policy: spreading the envs over episode phases (not counted)")
            key, key_stagger = jax.random.split(key)
            env_state = _stagger(t, make_policy)(
                state_r, env_state, distributed.device_keys(key_stagger)
            )
        # Compiled ahead, then every process meets: a collective's first call waits only
        # seconds for its peers, less than one process's compile may take.
        iteration = t.iteration.lower(state_r, env_state, distributed.device_keys(key)).compile()
        distributed.barrier("compiled")
        for it in range(start_iteration, config.num_iterations):
            key, key_it = jax.random.split(key)
            t0 = time.monotonic()
            state_r, env_state, metrics = iteration(
                state_r, env_state, distributed.device_keys(key_it)
            )
            metrics = {k: float(v) for k, v in jax.device_get(_unreplicate(metrics)).items()}
            elapsed = time.monotonic() - t0
            steps = int(jax.device_get(_unreplicate(state_r.env_steps)))
            if metrics.pop("finite") < 1.0:
                kept = (
                    f"the last good checkpoint in {run_dir} is kept"
                    if checkpoint_index.has_checkpoint(run_dir)
                    else f"{run_dir} has no checkpoint yet"
                )
                raise NonFiniteError(
                    f"non-finite loss or parameters at env step {steps} (iteration {it + 1}); "
                    f"stopped without saving, {kept}"
                )
            metrics["steps_per_s"] = config.env_steps_per_iteration / max(elapsed, 1e-9)
            logger.log("train", steps, metrics)
            if on_iteration is not None:
                on_iteration(steps, metrics)
            if (it + 1) % config.eval_interval and it + 1 != config.num_iterations:
                continue
            state = _unreplicate(state_r)
            key, key_eval = jax.random.split(key)
            eval_index += 1
            rate = None
            if main:
                last_eval = logger.log("eval", steps, evaluate(state, key_eval))
                rate = last_eval["success_rate"]
                checkpoint.save_checkpoint(
                    run_dir, state, key, eval_index, rate, config.keep_every_n_evals
                )
            # the others wait here for process 0's figure, not in a collective
            rate = distributed.share_value_from_main("evaluated", rate)
            if _reached_end(config, rate) and it + 1 < config.num_iterations:
                logger.message(
                    f"ended at env step {steps}: evaluation success {rate:.3f} reached "
                    f"end_at_success {config.end_at_success:g}"
                )
                break
        final = _unreplicate(state_r)
    finally:
        with contextlib.suppress(OSError):  # a full disk: the error in flight says so
            logger.close()
    return TrainResult(state=final, key=key, last_eval=last_eval, run_dir=run_dir)
