"""How does a franka_pick policy fail? Its episodes split by outcome, with the grasp at the end.

    .venv/bin/python benchmarks/pick_failure_modes.py docs/reference/readme-popsan-s0
    .venv/bin/python benchmarks/pick_failure_modes.py RUN --episodes 1000 \
        --override finger_target_low=-0.02

Deterministic episodes of the run's final checkpoint (``--which``), in the run's own env revision
unless ``--override`` changes env settings (values parsed as Python literals). Each episode is:

- ``success``: held at the goal for the last 2 s (the env's pick-and-hold success);
- ``lost``: reached the goal (PixMC's latch) but did not hold to the end;
- ``never``: never reached the goal.

For each group: the cube's final height, whether the pads still hold it, the finger joints at the
end (scaled to [-1, 1]: +1 open stop, -1 closed stop), the share of finger pairs at opposite
stops (the wedge grasp of docs/design.md, "The grasp that squeezes"), arm joints near a limit,
and the hand's drift over the last 2 s.
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
import numpy as np
from grasp_hold import parse_variant

from popsan_jax.analysis.evaluation import episode_keys, rollouts
from popsan_jax.errors import UserError
from popsan_jax.training.checkpoint import load_run

# Observation slices (envs/franka_pick.py's layout).
Q, LEFT, RIGHT, OBJ, TO_LEFT, TO_RIGHT = (
    slice(0, 9),
    slice(18, 21),
    slice(21, 24),
    slice(24, 27),
    slice(27, 30),
    slice(30, 33),
)


def group_figures(obs: np.ndarray, mask: np.ndarray, grasp_radius: float) -> dict[str, float]:
    """Figures of the episodes in ``mask`` ``[N]`` from the recorded observations ``[T, N, 34]``."""
    last, hold_start = obs[-1, mask], obs[-100, mask]
    reach = np.maximum(
        np.linalg.norm(last[:, TO_LEFT], axis=-1), np.linalg.norm(last[:, TO_RIGHT], axis=-1)
    )
    fingers = last[:, Q][:, 7:9]
    wedge = np.abs(fingers[:, 0] - fingers[:, 1]) > 1.8  # one finger at each stop
    mid_end = 0.5 * (last[:, LEFT] + last[:, RIGHT])
    mid_start = 0.5 * (hold_start[:, LEFT] + hold_start[:, RIGHT])
    return dict(
        episodes=int(mask.sum()),
        final_object_z=float(last[:, OBJ][:, 2].mean()),
        held_at_end=float((reach <= grasp_radius).mean()),
        left_finger=float(fingers[:, 0].mean()),
        right_finger=float(fingers[:, 1].mean()),
        wedge_grasp=float(wedge.mean()),
        arm_joint_near_limit=float((np.abs(last[:, Q][:, :7]) > 0.95).any(axis=1).mean()),
        hand_drift_last_2s_m=float(np.linalg.norm((mid_end - mid_start)[:, :2], axis=-1).mean()),
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=256)
    p.add_argument("--which", default="last")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--override", default="", help='env overrides, e.g. "finger_target_low=0.0"')
    args = p.parse_args()
    try:
        loaded = load_run(args.run_dir, args.which, env_overrides=parse_variant(args.override))
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    batch = rollouts(loaded, args.episodes, episode_keys(args.seed)[1], record=True)
    batch = jax.tree.map(np.asarray, batch)
    seconds = time.perf_counter() - t0
    success, reached = batch.success > 0, batch.reached > 0
    groups = dict(success=success, lost=reached & ~success, never=~reached)
    radius = float(loaded.env.config.grasp_radius)
    print(
        f"{args.run_dir} @ {loaded.step} env steps, {args.episodes} episodes (seed {args.seed}), "
        f"env revision {loaded.config.env_revision}, overrides {args.override or 'none'}, "
        f"finger_target_low {loaded.env.config.finger_target_low}; {seconds:.0f} s"
    )
    names = list(group_figures(batch.obs, success | ~success, radius))
    print(f"{'group':8s} " + " ".join(f"{n:>20s}" for n in names))
    for name, mask in groups.items():
        if mask.any():
            figures = group_figures(batch.obs, mask, radius)
            print(f"{name:8s} " + " ".join(f"{figures[n]:20.3f}" for n in names))
    return 0


if __name__ == "__main__":
    sys.exit(main())
