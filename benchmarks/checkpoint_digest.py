"""What the checkpoint digest (SHA-256 over a checkpoint's files,
popsan_jax/training/checkpoint_index.py) costs against the Orbax save and restore it guards.

Restores a committed pick checkpoint (default docs/reference/readme-popsan-s0's last), then,
for ``--rounds`` rounds: saves it into a temporary run (Orbax write + digest + manifest), hashes
the new checkpoint alone, and restores it (digest check + Orbax read + finiteness check). Prints
the checkpoint's size and the median and best seconds of each part. CPU model from /proc/cpuinfo.

Usage: python benchmarks/checkpoint_digest.py [--run docs/reference/readme-popsan-s0] [--rounds 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from popsan_jax.jax_setup import import_mjx_quietly


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--run", default="docs/reference/readme-popsan-s0")
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args()
    import_mjx_quietly()
    import jax

    from popsan_jax.config import RunConfig
    from popsan_jax.training import checkpoint, checkpoint_index
    from popsan_jax.training.iteration import init_training_state
    from popsan_jax.training.setup import build_networks, make_env, make_optimizer

    run = Path(args.run)
    config = RunConfig.from_json(run / "config.json")
    env = make_env(config)
    networks = build_networks(config, env.observation_size, env.action_size)
    template = init_training_state(
        config, networks, make_optimizer(config), env.observation_size, jax.random.PRNGKey(0)
    )
    state, key, entry = checkpoint.restore_checkpoint(run, template, "last")
    times: dict[str, list[float]] = {
        "save (Orbax + digest + index)": [],
        "digest alone": [],
        "restore (digest + Orbax + finite)": [],
        "restore unverified": [],
    }
    size = 0
    with tempfile.TemporaryDirectory(prefix="popsan_digest_") as tmp:
        for r in range(args.rounds):
            out = Path(tmp) / f"r{r}"
            t0 = time.perf_counter()
            path = checkpoint.save_checkpoint(out, state, key, 1, 0.5, 1)
            times["save (Orbax + digest + index)"].append(time.perf_counter() - t0)
            size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
            t0 = time.perf_counter()
            checkpoint_index.checkpoint_digest(path)
            times["digest alone"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            checkpoint.restore_checkpoint(out, template, "last")
            times["restore (digest + Orbax + finite)"].append(time.perf_counter() - t0)
            index_path = checkpoint_index.checkpoint_dir(out) / checkpoint_index.INDEX
            index = index_path.read_text()
            data = json.loads(index)
            for e in data["checkpoints"]:
                e.pop("digest")
            index_path.write_text(json.dumps(data))
            t0 = time.perf_counter()
            checkpoint.restore_checkpoint(out, template, "last")
            times["restore unverified"].append(time.perf_counter() - t0)
    print(
        f"{run} step {entry['step']}: checkpoint {size / 1e6:.2f} MB, {args.rounds} rounds, "
        f"{_cpu()}, {time.strftime('%Y-%m-%d')}"
    )
    for name, ts in times.items():
        print(
            f"  {name:36s} median {statistics.median(ts) * 1e3:8.1f} ms"
            f"  best {min(ts) * 1e3:8.1f} ms"
        )


if __name__ == "__main__":
    main()
