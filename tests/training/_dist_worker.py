"""One process of a multi-process (or the single-process reference) training run for
test_distributed.py: train.py's path (cluster, initialize, shared config, loop.train), then this
process's final state saved to ``OUT/state_p<process index>.npz``.

    python _dist_worker.py OUT [train.py flags...]
"""

import sys
from pathlib import Path

import numpy as np

from popsan_jax.cli import cluster_flags, given_flags, run_choices, train_parser
from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

import_mjx_quietly()

import jax  # noqa: E402

from popsan_jax import distributed  # noqa: E402
from popsan_jax.training import run  # noqa: E402
from popsan_jax.training.loop import train  # noqa: E402

out, argv = Path(sys.argv[1]), sys.argv[2:]
args = train_parser().parse_args(argv)
cluster = distributed.resolve_cluster(**cluster_flags(args))
if cluster is not None:
    distributed.initialize(cluster)
enable_compilation_cache()
config, run_dir = run.prepare_run_everywhere(
    jax.default_backend(), *given_flags(args), **run_choices(args)
)
result = train(config, run_dir, resume=bool(args.resume), progress=False)
leaves = jax.tree.leaves(jax.device_get((result.state, result.key)))
np.savez(out / f"state_p{jax.process_index()}.npz", *[np.asarray(x) for x in leaves])
