"""Training throughput of 2 processes x 1 CPU device (jax.distributed, gloo collectives) against
1 process x 2 devices (pmap), same config, measured in this script; prints the ratio.

    python benchmarks/distributed_throughput.py                 # franka_reach, 256 envs
    python benchmarks/distributed_throughput.py --env franka_pick --iterations 3

Each layout runs as fresh subprocesses (``--worker``) that build the trainer, compile, run
``--warmup`` iterations and time ``--iterations`` more; process 0 reports env steps/s.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from train_throughput import cpu_name

ROOT = Path(__file__).resolve().parent.parent


def worker(args: argparse.Namespace) -> None:
    """One process: distributed when --coordinator is given; prints steps/s on process 0."""
    # Imported here: jax.distributed.initialize must run before JAX creates its backend.
    import jax

    from popsan_jax import distributed
    from popsan_jax.jax_setup import enable_compilation_cache
    from popsan_jax.recipes import resolve_config
    from popsan_jax.training.iteration import init_training_state
    from popsan_jax.training.loop import build_trainer

    if args.coordinator:
        distributed.initialize(distributed.Cluster("flags", args.coordinator, 2, args.process_id))
    enable_compilation_cache()
    fields = dict(env=args.env, actor=args.actor, num_envs=args.num_envs, batch_size=args.num_envs)
    config = resolve_config(None, "cpu", fields)
    t = build_trainer(config)
    key = jax.random.PRNGKey(0)
    state = init_training_state(config, t.networks, t.optimizer, t.env.observation_size, key)
    env_keys = distributed.local_slice(jax.random.split(key, config.num_envs))
    env_state = jax.pmap(t.wrapped.reset)(env_keys)
    state = jax.device_put_replicated(jax.device_get(state), t.devices)
    keys = distributed.device_keys(key)
    iteration = t.iteration.lower(state, env_state, keys).compile()
    distributed.barrier("compiled")
    for i in range(args.warmup + args.iterations):
        if i == args.warmup:
            jax.block_until_ready(state)
            t0 = time.monotonic()
        state, env_state, metrics = iteration(state, env_state, distributed.device_keys(key))
        jax.block_until_ready(metrics)
    rate = args.iterations * config.env_steps_per_iteration / (time.monotonic() - t0)
    if distributed.is_main():
        print(f"RATE {rate:.1f}", flush=True)


def _run(args: argparse.Namespace, processes: int) -> float:
    base = [sys.executable, __file__, "--worker", "--env", args.env, "--actor", args.actor]
    base += ["--num-envs", str(args.num_envs), "--iterations", str(args.iterations)]
    base += ["--warmup", str(args.warmup)]
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={3 - processes}")
    if processes == 1:
        commands = [base]
    else:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        commands = [
            base + ["--coordinator", f"127.0.0.1:{port}", "--process-id", str(i)] for i in (0, 1)
        ]
    procs = [
        subprocess.Popen(c, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True) for c in commands
    ]
    outs = [p.communicate()[0] for p in procs]
    if any(p.returncode for p in procs):
        raise SystemExit(f"error: a worker failed: {[p.returncode for p in procs]}")
    return float(next(line for line in outs[0].splitlines() if line.startswith("RATE")).split()[1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--env", default="franka_reach")
    p.add_argument("--actor", default="mlp")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--coordinator", help=argparse.SUPPRESS)
    p.add_argument("--process-id", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker(args)
        return
    print(f"{args.env}, {args.actor}, {args.num_envs} envs; {cpu_name()}, {os.cpu_count()} cores")
    one = _run(args, 1)
    print(f"1 process x 2 devices: {one:,.0f} env steps/s", flush=True)
    two = _run(args, 2)
    print(f"2 processes x 1 device: {two:,.0f} env steps/s", flush=True)
    print(f"ratio (2x1 / 1x2) = {two / one:.2f}; overhead {1 - two / one:.0%}")


if __name__ == "__main__":
    main()
