"""One process of test_distributed.py's runs, on the toy env of ``tests/_toy_env.py``.

    python _dist_worker.py cli [--die-after-first-checkpoint] [train.py flags...]
    python _dist_worker.py state OUT [train.py flags...]

``cli`` runs train.py itself (its flags, exit codes and one-line errors); with
``--die-after-first-checkpoint`` the process SIGKILLs itself once the first checkpoint after
step 0 is written and process 0 has shared that evaluation's figure, so the loss of a peer
always falls at the same point of the run. ``state`` follows train.py's path (cluster,
initialize, shared config, loop.train) and saves this process's final state to
``OUT/state_p<process index>.npz``.

The config names an MJX env, and train.py's own flag checks run on it; the toy env replaces it
where the trainer and the checkpoint loader build the env. What is under test (process layout,
collectives, barriers, checkpoints, a peer's loss) does not depend on the env, and the toy env
compiles in seconds where an MJX program takes minutes per process.
"""

import os
import runpy
import signal
import sys
from pathlib import Path

import numpy as np

from popsan_jax.cli import cluster_flags, given_flags, run_choices, train_parser
from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

import_mjx_quietly()

import jax  # noqa: E402

from popsan_jax import distributed  # noqa: E402
from popsan_jax.training import checkpoint, loop, run  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))  # for _toy_env


def toy_env(config):
    # Imported on first use: _toy_env builds arrays at import, which would create the JAX
    # backend before jax.distributed.initialize.
    from _toy_env import PointPick

    return PointPick()


def die_after_first_checkpoint() -> None:
    share = distributed.share_value_from_main

    def share_then_die(name, *args, **kwargs):
        value = share(name, *args, **kwargs)
        if name == "evaluated":  # process 0 wrote the checkpoint before it shared its figure
            os.kill(os.getpid(), signal.SIGKILL)
        return value

    distributed.share_value_from_main = share_then_die


def save_final_state(out: Path, argv: list[str]) -> None:
    args = train_parser().parse_args(argv)
    cluster = distributed.resolve_cluster(**cluster_flags(args))
    if cluster is not None:
        distributed.initialize(cluster)
    enable_compilation_cache()
    config, run_dir = run.prepare_run_everywhere(
        jax.default_backend(), *given_flags(args), **run_choices(args)
    )
    result = loop.train(config, run_dir, resume=bool(args.resume), progress=False)
    leaves = jax.tree.leaves(jax.device_get((result.state, result.key)))
    np.savez(out / f"state_p{jax.process_index()}.npz", *[np.asarray(x) for x in leaves])


if __name__ == "__main__":
    loop.make_env = checkpoint.make_env = toy_env
    mode, argv = sys.argv[1], sys.argv[2:]
    if mode == "cli":
        if argv[:1] == ["--die-after-first-checkpoint"]:
            die_after_first_checkpoint()
            argv = argv[1:]
        sys.argv = [str(ROOT / "train.py"), *argv]
        runpy.run_path(str(ROOT / "train.py"), run_name="__main__")
    else:
        save_final_state(Path(argv[0]), argv[1:])
