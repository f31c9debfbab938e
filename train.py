"""Train a PopSAN (or MLP) actor with PPO on an MJX Franka task.

    python train.py --env franka_pick                 # backend-dependent defaults
    python train.py --env franka_reach --preset smoke # a complete tiny run in about a minute
    python train.py --preset paper                    # the headline run (sized for a GPU)
    python train.py --resume runs/franka_pick-popsan-20261123-160000
    python train.py --preset paper --init-from runs/a --timesteps 3 --sop-cost 1 --sop-budget 3e4

Flags override the preset, which overrides the backend defaults (popsan_jax/config.py).
A run writes runs/<env>-<actor>-<timestamp or --name>/ (config.json, metrics.jsonl, tb/,
checkpoints/). Bad input prints one line ``error: ...`` and exits 2; Ctrl-C, SIGINT (even if
ignored) and SIGTERM stop the run, keep its last checkpoint and exit 130.
"""

from __future__ import annotations

import sys
from pathlib import Path

from popsan_jax.cli import given_flags, run_choices, stop_on_signals, train_parser
from popsan_jax.errors import UserError


def main(argv: list[str] | None = None) -> int:
    args = train_parser(__doc__).parse_args(argv)
    print("popsan-jax: starting (importing JAX, MJX)...", file=sys.stderr, flush=True)
    run_dir: Path | None = None
    with stop_on_signals():
        try:
            # Imported after the flags are parsed: JAX and MJX take seconds to import.
            from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

            import_mjx_quietly()  # before brax/MJX modules import it noisily
            import jax

            from popsan_jax.training import run
            from popsan_jax.training.loop import train

            enable_compilation_cache()
            config, run_dir = run.prepare_run(
                jax.default_backend(), *given_flags(args), **run_choices(args)
            )
            result = train(config, run_dir, resume=bool(args.resume), progress=not args.no_progress)
        except UserError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            # Imported here: an interrupt can come before the library was imported.
            from popsan_jax.training.run import interrupted_message

            print(f"\n{interrupted_message(run_dir)}", file=sys.stderr)
            return 130
    if result.finished:  # resumed a run that had already reached its total
        steps = int(result.state.env_steps)
        print(
            f"done: {run_dir} already finished at {steps} env steps; to train further: "
            f"python train.py --resume {run_dir} --total-env-steps N (N > {steps})",
            file=sys.stderr,
        )
        return 0
    final = result.last_eval or {}
    print(
        f"done: {int(result.state.env_steps)} env steps, success rate "
        f"{final.get('success_rate', float('nan')):.3f} -> {run_dir}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
