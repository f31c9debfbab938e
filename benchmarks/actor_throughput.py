"""PopSAN actor throughput against this machine's dense fp32 matmul rate.

Prints, for B = 2048, T = 5, obs 34, actions 9, hidden 256-256 (the defaults):
- PopSAN forward observations/s,
- a training step (forward + backward + Adam) observations/s,
- dense fp32 matmul GFLOP/s measured in the same process,
- the fraction of that rate each figure reaches, counting PopSAN's dense FLOPs:
  forward = 2 * T * sum_l(n_in_l * n_out_l) per observation (encoder->hidden, hidden->hidden,
  hidden->output populations); training = 3x forward (forward, weight grads, input grads; the
  input grad of the first layer is needed because the encoder means/stds are learned).
  Elementwise work (encoder, LIF dynamics, decoder) is not counted. The implementation does the
  first layer's input gradient as one matmul on the T-summed cotangent (exact by linearity with the
  straight-through encoder), so it executes fewer FLOPs than the nominal 3x counted here.
Figures are given for the best and the median wall time of round-robin repeats, and from CPU
time (per CPU-second; the ratios are what matter). On a shared machine the best wall time and the
CPU-time ratios are the closer estimates of uncontended speed.

Usage: python benchmarks/actor_throughput.py [--batch 2048] [--timesteps 5] [--rounds 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp
import optax

from popsan_jax import PopSAN
from popsan_jax.jax_setup import enable_compilation_cache


def _interleaved_times(fns: dict, rounds: int, block: int = 4) -> dict[str, list[float]]:
    """Wall and CPU seconds per call for each zero-arg fn, timed in round-robin blocks.

    Each round runs every fn ``block + 1`` times back to back and keeps the last ``block`` calls:
    round-robin exposes every figure to the same CPU contention (the machine is shared), and the
    dropped first call absorbs the cache pollution of the previous fn (the 2048^3 matmul evicts
    the network's buffers, which slowed an interleaved training step by ~60 %). Keys ``name``
    hold wall times, ``name/cpu`` this process's CPU time (all threads), which other processes'
    load barely changes. Three warm-up calls first because weak types can recompile.
    """
    for fn in fns.values():
        for _ in range(3):
            jax.block_until_ready(fn())
    times: dict[str, list[float]] = {key: [] for name in fns for key in (name, f"{name}/cpu")}
    for _ in range(rounds):
        for name, fn in fns.items():
            jax.block_until_ready(fn())
            for _ in range(block):
                start, start_cpu = time.perf_counter(), time.process_time()
                jax.block_until_ready(fn())
                times[f"{name}/cpu"].append(time.process_time() - start_cpu)
                times[name].append(time.perf_counter() - start)
    return times


def popsan_dense_flops(
    obs_dim: int, action_size: int, hidden: tuple[int, ...], pop: int, timesteps: int
) -> float:
    sizes = [obs_dim * pop, *hidden, action_size * pop]
    return 2.0 * timesteps * sum(a * b for a, b in zip(sizes[:-1], sizes[1:], strict=False))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--timesteps", type=int, default=5)
    parser.add_argument("--obs", type=int, default=34)
    parser.add_argument("--actions", type=int, default=9)
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    enable_compilation_cache()

    model = PopSAN(
        action_size=args.actions, hidden_sizes=tuple(args.hidden), timesteps=args.timesteps
    )
    obs = jnp.clip(jax.random.normal(jax.random.PRNGKey(2), (args.batch, args.obs)), -3, 3)
    target = jax.random.uniform(jax.random.PRNGKey(3), (args.batch, args.actions), minval=-1)
    params = model.init(jax.random.PRNGKey(4), obs)
    optimizer = optax.adam(1e-4)
    opt_state = optimizer.init(params)

    forward = jax.jit(model.apply)

    @jax.jit
    def train_step(params, opt_state, obs, target):
        def loss_fn(p):
            return jnp.mean(jnp.square(model.apply(p, obs) - target))

        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    n = 2048
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    b = jax.random.normal(jax.random.PRNGKey(1), (n, n), jnp.float32)
    matmul = jax.jit(jnp.matmul)
    times = _interleaved_times(
        {
            "matmul": lambda: matmul(a, b),
            "forward": lambda: forward(params, obs),
            "train": lambda: train_step(params, opt_state, obs, target),
        },
        args.rounds,
    )
    flops = popsan_dense_flops(args.obs, args.actions, tuple(args.hidden), 10, args.timesteps)
    print(
        f"machine: {os.cpu_count()} cpus, jax {jax.__version__}, "
        f"load average {os.getloadavg()[0]:.2f} (>{os.cpu_count()} means contended)"
    )
    print(
        f"B={args.batch} T={args.timesteps} obs={args.obs} actions={args.actions} "
        f"hidden={args.hidden}: dense FLOPs/obs forward {flops / 1e6:.3f} M, "
        f"train {3 * flops / 1e6:.3f} M"
    )
    rows = (("wall, best", "", min), ("wall, median", "", statistics.median))
    rows += (("CPU time, median", "/cpu", statistics.median),)
    for stat, suffix, pick in rows:
        gflops = 2.0 * n**3 / pick(times["matmul" + suffix]) / 1e9
        fwd_rate = args.batch / pick(times["forward" + suffix])
        train_rate = args.batch / pick(times["train" + suffix])
        fwd_gf = fwd_rate * flops / 1e9
        train_gf = train_rate * 3 * flops / 1e9
        print(
            f"[{stat} of {len(times['matmul'])}] matmul fp32 {n}^3: {gflops:.1f} GFLOP/s | "
            f"forward {fwd_rate:,.0f} obs/s = {fwd_gf:.1f} GFLOP/s = {fwd_gf / gflops:.0%} | "
            f"train step {train_rate:,.0f} obs/s = {train_gf:.1f} GFLOP/s = "
            f"{train_gf / gflops:.0%}"
        )


if __name__ == "__main__":
    main()
