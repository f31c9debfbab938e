"""franka_pick throughput: env steps/s (vmap + jit, warmed up), raw mjx.step, compile time.

    .venv/bin/python benchmarks/env_throughput.py                # 512 and 2048 envs
    .venv/bin/python benchmarks/env_throughput.py --envs 64      # small and quick

Each size is measured for the current env and for revision 1 (the settings before the grasp
fix: one 20 ms substep, MuJoCo's default pad impedance) in the same process, and the ratio is
printed, so the figure survives the 2-3x speed differences between CPU boxes.

Each figure is measured after two warm-up calls (the second call of a jitted function on a reset
state can recompile if dtypes are unstable; here it must not) over a jitted ``lax.scan`` of
``--steps`` steps, so the host is out of the loop. The compile time is printed without the
persistent cache unless ``--cache`` is given.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
from mujoco import mjx
from train_throughput import cpu_name, matmul_gflops

import envs
from popsan_jax.jax_setup import enable_compilation_cache


def _timed(fn, *args) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, out


def bench_env(env, num_envs: int, steps: int, seed: int = 0) -> dict[str, float]:
    """Env steps/s of ``env`` for ``num_envs`` parallel envs (zero-mean random actions)."""
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.vmap(env.step)

    @jax.jit
    def rollout(state, key):
        def body(carry, k):
            action = jax.random.uniform(k, (num_envs, env.action_size), minval=-1, maxval=1)
            return step(carry, action), None

        return jax.lax.scan(body, state, jax.random.split(key, steps))[0]

    keys = jax.random.split(jax.random.PRNGKey(seed), num_envs)
    t_reset, state = _timed(reset, keys)
    t_compile, state = _timed(rollout, state, jax.random.PRNGKey(1))
    _, state = _timed(rollout, state, jax.random.PRNGKey(2))  # second warm-up: no recompile
    t_run, state = _timed(rollout, state, jax.random.PRNGKey(3))
    return dict(
        steps_per_s=num_envs * steps / t_run,
        compile_reset_s=t_reset,
        compile_step_s=t_compile,
        finite=float(jnp.all(jnp.isfinite(state.obs))),
    )


def bench_raw_mjx(env, num_envs: int, steps: int) -> float:
    """Physics steps/s of the bare batched ``mjx.step`` of the same model (no env logic)."""
    model = env.mjx_model
    data = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), num_envs)).pipeline_state

    @jax.jit
    def rollout(d):
        return jax.lax.scan(
            lambda c, _: (jax.vmap(mjx.step, (None, 0))(model, c), None), d, None, length=steps
        )[0]

    _timed(rollout, data)
    _timed(rollout, data)
    t_run, _ = _timed(rollout, data)
    return num_envs * steps / t_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, nargs="+", default=[512, 2048])
    parser.add_argument("--steps", type=int, default=50, help="steps per timed scan")
    parser.add_argument("--env", default="franka_pick")
    parser.add_argument("--no-raw", action="store_true", help="skip the raw mjx.step figure")
    parser.add_argument("--cache", action="store_true", help="use the persistent compile cache")
    parser.add_argument(
        "--no-legacy", action="store_true", help="skip the revision-1 (old settings) figure"
    )
    args = parser.parse_args()
    if args.cache:
        enable_compilation_cache()

    variants = {"current": envs.get_environment(args.env)}
    if not args.no_legacy:
        variants["revision 1"] = envs.get_environment(
            args.env, **envs.legacy_overrides(args.env, 1)
        )
    print(
        f"CPU: {cpu_name()}; matmul fp32 2048^3 {matmul_gflops():.0f} GFLOP/s; "
        f"devices {jax.devices()}"
    )
    for name, env in variants.items():
        print(f"{args.env} {name}: ctrl_dt {env.config.ctrl_dt}, sim_dt {env.config.sim_dt}")
    for n in args.envs:
        rates = {}
        for name, env in variants.items():
            r = bench_env(env, n, args.steps)
            rates[name] = r["steps_per_s"]
            print(
                f"{n:5d} envs, {name:10s}: {r['steps_per_s']:9.0f} env steps/s | compile reset "
                f"{r['compile_reset_s']:.1f} s, step scan {r['compile_step_s']:.1f} s | "
                f"finite {bool(r['finite'])}",
                flush=True,
            )
            if not args.no_raw:
                raw = bench_raw_mjx(env, n, args.steps)
                print(f"{n:5d} envs, {name:10s}: {raw:9.0f} raw mjx.step physics steps/s")
        if len(rates) == 2:
            print(
                f"{n:5d} envs: current / revision 1 = {rates['current'] / rates['revision 1']:.2f}"
            )


if __name__ == "__main__":
    main()
