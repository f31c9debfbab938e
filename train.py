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

Several processes (hosts or GPUs; jax.distributed): start one per host or GPU with
``--coordinator HOST:PORT --num-processes N --process-id I``, or under SLURM (srun) / Open MPI
with none of them. num_envs and batch sizes are global; process 0 writes the run. If another
process dies, the rest print one line and exit 3; the last checkpoint is kept.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from popsan_jax.cli import (
    cluster_flags,
    given_flags,
    raise_if_stop_requested,
    run_choices,
    stop_on_signals,
    train_parser,
)
from popsan_jax.errors import UserError


def main(argv: list[str] | None = None) -> int:
    args = train_parser(__doc__).parse_args(argv)
    print("popsan-jax: starting (importing JAX, MJX)...", file=sys.stderr, flush=True)
    run_dir: Path | None = None
    cluster = None
    with stop_on_signals():
        try:
            # Imported after the flags are parsed: JAX and MJX take seconds to import.
            from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

            import_mjx_quietly()  # before brax/MJX modules import it noisily
            import jax

            from popsan_jax import distributed
            from popsan_jax.training import run
            from popsan_jax.training.stages import train_run

            cluster = distributed.resolve_cluster(**cluster_flags(args))
            if cluster is not None:  # before anything creates a JAX backend
                distributed.initialize(cluster)
            enable_compilation_cache()
            config, run_dir = run.prepare_run_everywhere(
                jax.default_backend(), *given_flags(args), **run_choices(args)
            )
            result = train_run(
                config,
                run_dir,
                resume=bool(args.resume),
                progress=not args.no_progress,
                on_iteration=raise_if_stop_requested,
            )
        except UserError as e:
            return _stop(cluster, 2, f"error: {e}")
        except KeyboardInterrupt:
            # Imported here: an interrupt can come before the library was imported.
            from popsan_jax.training.run import interrupted_message

            return _stop(cluster, 130, f"\n{interrupted_message(run_dir)}")
        except Exception as e:
            if cluster is None or not distributed.peer_failure(e):
                raise
            return _stop(cluster, 3, f"error: {distributed.peer_lost_message(run_dir)}")
    line = run.done_message(result, run_dir, jax.process_index(), jax.process_count())
    print(line, file=sys.stderr)
    return 0


def _stop(cluster: object, code: int, message: str) -> int:
    """Print ``message``; under jax.distributed leave at once (os._exit): JAX's exit handler
    waits at a barrier for every process, and a dead or stopped one never comes."""
    print(message, file=sys.stderr, flush=True)
    if cluster is not None:
        sys.stdout.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
