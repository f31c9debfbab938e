"""Training throughput (env steps/s) of PopSAN vs the MLP actor at the same env count.

    python benchmarks/train_throughput.py                     # franka_pick, 512 envs
    python benchmarks/train_throughput.py --num-envs 256 --iterations 3
    python benchmarks/train_throughput.py --actors popsan,popsan+sop --timesteps 2

Times whole jitted PPO iterations (unroll + normaliser update + minibatch epochs), after
``--warmup`` iterations that absorb compilation (and the weak-type recompile of a fresh state).
Target (issue 4): PopSAN >= 60 % of the MLP actor's steps/s at 512 envs on a 2-core CPU.

It also prints the ceiling that the same maths allows: the ratio PopSAN would reach if both
actors' dense FLOPs ran at the fp32 matmul rate measured in this process and everything else
(env, critic, PPO bookkeeping) cost what the MLP run shows. FLOPs per env step = one rollout
forward + ``epochs`` x (forward + backward) as executed: PopSAN's first-layer input gradient is one
matmul on the T-summed cotangent (see popsan_jax/snn/encoder.py); the MLP needs no input gradient.

``popsan+sop`` is PopSAN with the synaptic-operation penalty in the loss (``--sop-cost``, budget
0 so it is active on every minibatch); its line gives its cost relative to plain PopSAN.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
from actor_throughput import popsan_dense_flops

from popsan_jax.jax_setup import enable_compilation_cache
from popsan_jax.recipes import resolve_config
from popsan_jax.training.iteration import init_training_state
from popsan_jax.training.loop import build_trainer


def cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def actor_flops_per_env_step(config, obs_dim: int, action_size: int, epochs: int) -> float:
    """Dense FLOPs of the actor per env step of training, as executed (see the docstring)."""
    kw = config.actor_kwargs
    if config.actor == "popsan":
        t, pop = kw["timesteps"], kw["encoder_pop_dim"]
        fwd = popsan_dense_flops(obs_dim, action_size, tuple(kw["hidden_sizes"]), pop, t)
        train = 3 * fwd - 2.0 * (t - 1) * obs_dim * pop * kw["hidden_sizes"][0]
    else:
        sizes = [obs_dim, *kw["hidden_sizes"], action_size]
        fwd = 2.0 * sum(a * b for a, b in zip(sizes[:-1], sizes[1:], strict=False))
        train = 3 * fwd - 2.0 * sizes[0] * sizes[1]
    return fwd + epochs * train


def matmul_gflops(n: int = 2048, repeats: int = 10) -> float:
    """Best-of-``repeats`` fp32 ``n x n`` matmul rate of this process."""
    a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
    matmul = jax.jit(jnp.matmul)
    jax.block_until_ready(matmul(a, a))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(matmul(a, a))
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best / 1e9


def measure(spec: str, args: argparse.Namespace) -> tuple[float, float]:
    """(env steps/s, actor dense FLOPs per env step) for one actor spec (``mlp``, ``popsan``,
    ``popsan+sop``)."""
    actor, _, variant = spec.partition("+")
    if variant not in ("", "sop") or (variant and actor != "popsan"):
        raise SystemExit(f"error: unknown actor spec {spec!r} (mlp, popsan, popsan+sop)")
    penalty = dict(sop_cost=args.sop_cost, sop_budget=0.0) if variant else {}
    config = resolve_config(
        None,
        jax.default_backend(),
        dict(
            env=args.env,
            actor=actor,
            num_envs=args.num_envs,
            batch_size=args.num_envs,
            num_minibatches=args.num_minibatches,
            unroll_length=args.unroll_length,
            num_updates_per_batch=args.epochs,
            **penalty,
        ),
        {"timesteps": args.timesteps} if actor == "popsan" else {},
    )
    t = build_trainer(config)
    key = jax.random.PRNGKey(0)
    state = init_training_state(config, t.networks, t.optimizer, t.env.observation_size, key)
    keys = jax.random.split(key, config.num_envs).reshape(len(t.devices), -1, 2)
    env_state = jax.pmap(t.wrapped.reset)(keys)
    state = jax.device_put_replicated(state, t.devices)
    t0 = time.monotonic()
    for i in range(args.warmup + args.iterations):
        if i == args.warmup:
            jax.block_until_ready(state)
            print(f"  {spec}: compiled + warm-up {time.monotonic() - t0:.1f} s", flush=True)
            t0 = time.monotonic()
        state, env_state, metrics = t.iteration(
            state, env_state, jax.random.split(jax.random.PRNGKey(i), len(t.devices))
        )
    jax.block_until_ready((state, metrics))
    elapsed = time.monotonic() - t0
    flops = actor_flops_per_env_step(config, t.env.observation_size, t.env.action_size, args.epochs)
    return args.iterations * config.env_steps_per_iteration / elapsed, flops


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--env", default="franka_pick")
    p.add_argument("--num-envs", type=int, default=512)
    p.add_argument("--unroll-length", type=int, default=10)
    p.add_argument("--num-minibatches", type=int, default=8)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--actors", default="popsan,mlp", help="comma list of mlp, popsan, popsan+sop")
    p.add_argument("--timesteps", type=int, default=5, help="PopSAN's T")
    p.add_argument("--sop-cost", type=float, default=0.01, help="penalty weight of popsan+sop")
    args = p.parse_args()

    enable_compilation_cache()
    print(
        f"train throughput on {args.env}: {args.num_envs} envs, unroll {args.unroll_length}, "
        f"{args.num_minibatches} minibatches x {args.epochs} epochs; PopSAN T = {args.timesteps}; "
        f"{jax.device_count()} {jax.default_backend()} device(s); "
        f"{cpu_name()}, {os.cpu_count()} cores",
        flush=True,
    )
    rates, flops = {}, {}
    for actor in args.actors.split(","):
        rates[actor], flops[actor] = measure(actor, args)
        print(
            f"{actor:>7}: {rates[actor]:,.0f} env steps/s; actor {flops[actor] / 1e6:.2f} "
            "MFLOP per env step",
            flush=True,
        )
    if {"popsan", "popsan+sop"} <= set(rates):
        print(f"popsan+sop / popsan = {rates['popsan+sop'] / rates['popsan']:.2f}")
    if {"popsan", "mlp"} <= set(rates):
        ratio = rates["popsan"] / rates["mlp"]
        verdict = "meets" if ratio >= 0.6 else "misses"
        print(f"popsan / mlp = {ratio:.2f} ({verdict} the >= 0.60 target)")
        gflops = matmul_gflops()
        t_mlp, t_pop = 1.0 / rates["mlp"], 1.0 / rates["popsan"]
        extra_ideal = (flops["popsan"] - flops["mlp"]) / (gflops * 1e9)
        print(
            f"matmul fp32 2048^3: {gflops:.0f} GFLOP/s; PopSAN's extra actor work runs at "
            f"{extra_ideal / (t_pop - t_mlp):.0%} of it in the loop; ceiling at 100 %: "
            f"popsan / mlp = {t_mlp / (t_mlp + extra_ideal):.2f}"
        )


if __name__ == "__main__":
    main()
