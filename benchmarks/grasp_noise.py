"""How much exploration noise the franka_pick grasp tolerates, per action scale (issue 6).

    .venv/bin/python benchmarks/grasp_noise.py 7.5       # PixMC's scale
    .venv/bin/python benchmarks/grasp_noise.py 2.0       # franka_pick's default

The scripted grasp-and-lift controller (``envs/scripted.py``) runs 128 randomised 200-step
episodes with N(0, sigma^2) added to each of its 9 actions before the env clips them, as a
Gaussian PPO policy explores. A policy has to get through this noise to discover that lifting a
held cube pays. Prints one line per sigma: success, episodes that terminated (cube out of the
workspace), fraction of steps with the cube held, episodes whose cube rose above 0.30 m.

Run it with nothing else on the machine: each scale compiled in about 4 min on the 2-core,
24 GB CPU box (30 November), and a variant of this rollout that also returned per-step traces
and the final state ran out of the box's 24 GB while compiling.
"""

from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp

import envs
from envs.scripted import make_scripted_pick_policy

N = 128
SIGMAS = (0.0, 0.1, 0.2, 0.4, 0.6, 1.0)


def main() -> None:
    scale = float(sys.argv[1]) if len(sys.argv) > 1 else 2.0
    env = envs.get_environment("franka_pick", action_scale=scale)
    policy = jax.vmap(make_scripted_pick_policy(env))
    step = jax.vmap(env.step)

    @jax.jit
    def rollout(rng, sigma):
        k0, k1 = jax.random.split(rng)
        state = jax.vmap(env.reset)(jax.random.split(k0, N))

        def body(carry, key):
            state, done = carry
            action = policy(state.pipeline_state)
            state = step(state, action + sigma * jax.random.normal(key, action.shape))
            done = jnp.maximum(done, state.done)
            return (state, done), (state.metrics["held"], state.info["object_pos"][:, 2])

        keys = jax.random.split(k1, env.config.episode_length)
        (state, done), (held, z) = jax.lax.scan(body, (state, jnp.zeros(N)), keys)
        return state.metrics["success"], done, held.mean(), z.max(0)

    for sigma in SIGMAS:
        t0 = time.time()
        success, done, held, z_max = rollout(jax.random.PRNGKey(1), sigma)
        print(
            f"scale={scale} sigma={sigma}: success {float(success.mean()):.3f} "
            f"terminated {float(done.mean()):.3f} held {float(held):.3f} "
            f"zmax>0.3 {float((z_max > 0.3).mean()):.3f} ({time.time() - t0:.0f}s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
