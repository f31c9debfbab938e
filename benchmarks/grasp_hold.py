"""Does a grasped cube stay held? The scripted pick (envs/scripted.py) on random franka_pick
episodes, held inside the goal band at 1, 2, 3, 4, 10 and 20 s after the lift starts.

    .venv/bin/python benchmarks/grasp_hold.py                       # current vs revision 1
    .venv/bin/python benchmarks/grasp_hold.py --episodes 64 --variant sim_dt=0.02

"Held inside the goal band": both pads within ``grasp_radius`` of the cube centre and the cube
within the band around ``goal_z``. Also printed: the episode-end ``success`` (held for the last
2 s of the default-length episode) and ``reached`` (PixMC's latch) of the same episodes, and the
wall time of the rollout. Each ``--variant`` is a comma-separated list of env overrides (values
parsed as Python literals), e.g. ``--variant "sim_dt=0.02,pad_solimp=(0.9,0.95,0.001,0.5,2)"``.
"""

from __future__ import annotations

import argparse
import ast
import time

import jax
import numpy as np

import envs
from envs.scripted import CLOSE_END, run_scripted_pick

MARKS_S = (1, 2, 3, 4, 10, 20)


def parse_variant(text: str) -> dict:
    """``"a=1,b=(1,2)"`` -> ``{"a": 1, "b": (1, 2)}`` (commas inside brackets are kept)."""
    out, depth, part = {}, 0, ""
    for ch in text + ",":
        depth += ch in "([{"
        depth -= ch in ")]}"
        if ch == "," and depth == 0:
            if part.strip():
                key, value = part.split("=", 1)
                out[key.strip()] = ast.literal_eval(value.strip())
            part = ""
        else:
            part += ch
    return out


def measure(overrides: dict, episodes: int, seed: int = 0) -> dict:
    """Held-in-band fractions at ``MARKS_S`` after the lift starts, end-of-episode success."""
    env = envs.get_environment("franka_pick", **overrides)
    steps = max(CLOSE_END + int(round(max(MARKS_S) / env.dt)), env.config.episode_length)
    t0 = time.perf_counter()
    _, trace, _ = run_scripted_pick(env, jax.random.PRNGKey(seed), episodes, steps=steps)
    held = np.asarray(trace["in_band_held"])
    wall = time.perf_counter() - t0
    end = env.config.episode_length - 1
    return dict(
        held={s: float(held[CLOSE_END + int(round(s / env.dt)) - 1].mean()) for s in MARKS_S},
        success=float(np.asarray(trace["success"])[end].mean()),
        reached=float(np.asarray(trace["reached"])[end].mean()),
        wall_s=wall,
        sim_dt=env.config.sim_dt,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variant", action="append", help="env overrides (repeatable)")
    args = parser.parse_args()
    variants = {"current": {}, "revision 1": envs.legacy_overrides("franka_pick", 1)}
    for text in args.variant or []:
        variants[text] = parse_variant(text)
    print(f"{args.episodes} episodes; held inside the goal band, s after the lift starts:")
    for name, overrides in variants.items():
        r = measure(overrides, args.episodes, args.seed)
        marks = " ".join(f"{s:2d}s {100 * v:5.1f}%" for s, v in r["held"].items())
        print(
            f"{name:28s} {marks} | end: success {100 * r['success']:5.1f}% reached "
            f"{100 * r['reached']:5.1f}% | sim_dt {r['sim_dt']} | {r['wall_s']:.0f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
