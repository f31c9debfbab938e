"""Train a PopSAN (or MLP) actor with PPO on an MJX Franka task.

    python train.py --env franka_pick                 # backend-dependent defaults
    python train.py --env franka_reach --preset smoke # a complete tiny run in about a minute
    python train.py --preset paper                    # the headline run (sized for a GPU)
    python train.py --resume runs/franka_pick-popsan-20261123-160000
    python train.py --preset paper --init-from runs/a --timesteps 3 --sop-cost 1 --sop-budget 3e4

Flags override the preset, which overrides the backend defaults (popsan_jax/config.py).
A run writes runs/<env>-<actor>-<timestamp or --name>/ (config.json, metrics.jsonl, tb/,
checkpoints/). Bad input prints one line ``error: ...`` and exits 2.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

from popsan_jax.cli import add_env_override_flag


def _sizes(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(s) for s in text.replace(",", " ").split())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected sizes like 256,256, got {text!r}") from None
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"expected positive sizes like 256,256, got {text!r}")
    return sizes


# flag -> RunConfig field (None default = "not given", so presets show through).
CONFIG_FLAGS: dict[str, tuple[type, str]] = {
    "env": (str, "task name: franka_pick | franka_reach"),
    "actor": (str, "policy network: popsan | mlp"),
    "seed": (int, "random seed"),
    "num_envs": (int, "parallel training envs"),
    "total_env_steps": (int, "training env steps"),
    "episode_length": (int, "episode length in control steps (default: the env's)"),
    "unroll_length": (int, "steps per unroll"),
    "batch_size": (int, "sequences per minibatch"),
    "num_minibatches": (int, "minibatches per epoch"),
    "num_updates_per_batch": (int, "epochs over each batch"),
    "actor_lr": (float, "actor learning rate"),
    "critic_lr": (float, "critic learning rate"),
    "lr_schedule": (str, "constant | cosine"),
    "max_grad_norm": (float, "global gradient-norm clip"),
    "entropy_cost": (float, "entropy bonus coefficient"),
    "discounting": (float, "discount gamma"),
    "gae_lambda": (float, "GAE lambda"),
    "clipping_epsilon": (float, "PPO clip"),
    "reward_scaling": (float, "reward multiplier"),
    "obs_clip": (float, "clip of the normalised observations"),
    "init_log_std": (float, "initial exploration log-std"),
    "critic_hidden_sizes": (_sizes, "critic hidden sizes, e.g. 256,256,256"),
    "sop_cost": (float, "PopSAN loss penalty per 1000 synaptic ops per inference over budget"),
    "sop_budget": (float, "synaptic ops per inference the penalty allows for free"),
    "init_from": (str, "start from this run's networks and normaliser (fresh optimiser)"),
    "init_checkpoint": (str, "which checkpoint of --init-from: best | last | env-step count"),
    "num_evals": (int, "evaluations (and checkpoints) over the run"),
    "num_eval_envs": (int, "episodes per evaluation"),
    "keep_every_n_evals": (int, "keep every N-th checkpoint besides the last and the best"),
}
ACTOR_FLAGS: dict[str, tuple[type, str]] = {
    "hidden_sizes": (_sizes, "actor hidden sizes, e.g. 256,256"),
    "timesteps": (int, "PopSAN timesteps T"),
    "encoder_pop_dim": (int, "PopSAN encoder population per observation dimension"),
    "decoder_pop_dim": (int, "PopSAN output population per action dimension"),
}
RESUMABLE = {"total_env_steps"}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--preset", help="smoke | paper")
    p.add_argument("--name", help="run directory name (default <env>-<actor>-<timestamp>)")
    p.add_argument("--runs-dir", default="runs", help="parent of run directories")
    p.add_argument("--resume", metavar="RUN_DIR", help="continue a run from its last checkpoint")
    add_env_override_flag(p, "env config override (repeatable)")
    p.add_argument("--wandb", action="store_true", default=None, help="also log to W&B")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    for name, (kind, text) in {**CONFIG_FLAGS, **ACTOR_FLAGS}.items():
        p.add_argument("--" + name.replace("_", "-"), type=kind, help=text)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    # A job started with `&` by a non-interactive shell has SIGINT ignored, and schedulers stop
    # jobs with SIGTERM: both should end the run as Ctrl-C does (message, last checkpoint kept).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    previous_term = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        return _main(argv)
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)


def _main(argv: list[str] | None) -> int:
    args = parse_args(argv)
    print("popsan-jax: starting (importing JAX, MJX)...", file=sys.stderr, flush=True)
    from popsan_jax.errors import ConfigError, UserError
    from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

    run_dir = None
    try:
        import_mjx_quietly()  # before brax/ppo import it noisily
        import jax

        from popsan_jax import config as cfg
        from popsan_jax.training import loop as ppo

        enable_compilation_cache()
        given = {k: getattr(args, k) for k in CONFIG_FLAGS if getattr(args, k) is not None}
        actor_given = {k: getattr(args, k) for k in ACTOR_FLAGS if getattr(args, k) is not None}
        if args.resume:
            from popsan_jax.errors import CheckpointError
            from popsan_jax.training.checkpoint import CONFIG, read_index

            run_dir = Path(args.resume)
            bad = sorted(set(given) - RESUMABLE) + sorted(actor_given)
            if bad or args.preset or args.env_override:
                extra = ", ".join(bad) or "preset/env overrides"
                raise ConfigError(f"cannot change {extra} when resuming (only --total-env-steps)")
            read_index(run_dir)  # fails early with a clear CheckpointError
            try:
                config = cfg.RunConfig.from_json(run_dir / CONFIG)
            except ConfigError as e:
                raise CheckpointError(str(e)) from e
            config = config.replace(**given, **({"wandb": True} if args.wandb else {}))
        else:
            if args.env_override:
                given["env_overrides"] = dict(args.env_override)
            if args.wandb:
                given["wandb"] = True
            config = cfg.resolve_config(args.preset, jax.default_backend(), given, actor_given)
            name = args.name or f"{config.env}-{config.actor}-{time.strftime('%Y%m%d-%H%M%S')}"
            run_dir = Path(args.runs_dir) / name
            if run_dir.exists():
                raise ConfigError(f"run directory {run_dir} exists; use --resume or a new --name")
        result = ppo.train(config, run_dir, resume=bool(args.resume), progress=not args.no_progress)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\n{_interrupted_message(run_dir)}", file=sys.stderr)
        return 130
    final = result.last_eval or {}
    print(
        f"done: {int(result.state.env_steps)} env steps, success rate "
        f"{final.get('success_rate', float('nan')):.3f} -> {run_dir}",
        file=sys.stderr,
    )
    return 0


def _interrupted_message(run_dir: Path | None) -> str:
    """What an interrupted run left behind: a checkpoint to resume from, or none yet."""
    if run_dir is None:
        return "interrupted"
    from popsan_jax.errors import CheckpointError
    from popsan_jax.training.checkpoint import read_index

    try:
        read_index(run_dir)
    except CheckpointError:
        return f"interrupted before the first checkpoint; {run_dir} has nothing to resume"
    return (
        f"interrupted; the last checkpoint is kept; resume with: python train.py --resume {run_dir}"
    )


if __name__ == "__main__":
    sys.exit(main())
