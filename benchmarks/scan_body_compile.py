"""Compile time and peak host memory of a scan over Brax's training-wrapped franka_pick step.

    .venv/bin/python benchmarks/scan_body_compile.py               # both forms, PopSAN policy
    .venv/bin/python benchmarks/scan_body_compile.py --actor mlp

The episode stagger (popsan_jax/training/iteration.py, ``stagger_episodes``) steps the
training-wrapped env with the run's policy inside a ``lax.scan``. Two forms of that scan:

- ``closure``: the body a plain Python function whose policy closes over the (traced) policy
  parameters, the form the stagger and the normaliser priming had until 6 December 2026;
- ``jitted``: the body ``jax.jit``-ed, the parameters passed in the carry (the form now used).

Each form is compiled in a fresh process (no persistent cache, so each pays its whole compile)
and the peak RSS of that process is printed beside the compile time; the ratio is printed last.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
from brax.envs.wrappers import training as brax_training
from brax.training.agents.ppo import networks as ppo_networks
from train_throughput import cpu_name, matmul_gflops

from popsan_jax.jax_setup import import_mjx_quietly
from popsan_jax.recipes import resolve_config
from popsan_jax.training.iteration import init_training_state, param_policy, stagger_episodes
from popsan_jax.training.setup import build_networks, make_env, make_optimizer

FORMS = ("closure", "jitted")


def measure(form: str, actor: str, num_envs: int, steps: int) -> dict[str, float]:
    """Lower, compile and run one form in this process; peak RSS is this process's own."""
    config = resolve_config(overrides=dict(env="franka_pick", actor=actor, num_envs=num_envs))
    env = make_env(config)
    length = int(env.config.episode_length)
    wrapped = brax_training.wrap(env, episode_length=length, action_repeat=1)
    nets = build_networks(config, env.observation_size, env.action_size)
    state = init_training_state(
        config, nets, make_optimizer(config), env.observation_size, jax.random.PRNGKey(0)
    )
    params = (state.normalizer_params, state.params.policy)
    make_policy = ppo_networks.make_inference_fn(nets)
    env_state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(1), num_envs))

    if form == "jitted":

        def fn(s, p, key):
            return stagger_episodes(wrapped, s, param_policy(make_policy), p, key, steps + 1)

    else:

        def fn(s, p, key):
            policy = make_policy(p)

            def body(carry, _):
                st, k = carry
                k, k_act = jax.random.split(k)
                return (wrapped.step(st, policy(st.obs, k_act)[0]), k), None

            return jax.lax.scan(body, (s, key), jnp.arange(steps))[0][0]

    args = (env_state, params, jax.random.PRNGKey(2))
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    jax.block_until_ready(compiled(*args).obs)
    t3 = time.perf_counter()
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # KiB on Linux
    return dict(lower_s=t1 - t0, compile_s=t2 - t1, run_s=t3 - t2, peak_rss_gb=peak_gb)


def main() -> None:
    import_mjx_quietly()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--actor", default="popsan", choices=("popsan", "mlp"))
    p.add_argument("--envs", type=int, default=64, help="parallel envs (compile cost is flat)")
    p.add_argument("--steps", type=int, default=249, help="scan length (the stagger's L - 1)")
    p.add_argument("--form", choices=FORMS, help=argparse.SUPPRESS)  # the child's own run
    args = p.parse_args()
    if args.form:
        print(json.dumps(measure(args.form, args.actor, args.envs, args.steps)))
        return
    print(f"CPU: {cpu_name()}; fp32 matmul {matmul_gflops():.0f} GFLOP/s (2048^3)")
    results = {}
    for form in FORMS:
        argv = [sys.executable, __file__, "--form", form, "--actor", args.actor]
        argv += ["--envs", str(args.envs), "--steps", str(args.steps)]
        out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
        results[form] = r = json.loads(out.strip().splitlines()[-1])
        print(
            f"{form:8s} {args.actor} {args.envs} envs, {args.steps} steps: lower "
            f"{r['lower_s']:.1f} s, compile {r['compile_s']:.1f} s, run {r['run_s']:.1f} s, "
            f"peak RSS {r['peak_rss_gb']:.1f} GB",
            flush=True,
        )
    old, new = results["closure"], results["jitted"]
    print(
        f"jitted / closure: compile {new['compile_s'] / old['compile_s']:.2f}x, "
        f"peak RSS {new['peak_rss_gb'] / old['peak_rss_gb']:.2f}x"
    )


if __name__ == "__main__":
    main()
