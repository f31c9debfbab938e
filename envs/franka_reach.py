"""franka_reach: bring the fingertip midpoint to a random target point (an easy, fast task).

Same robot, action semantics (9 joint-target deltas in [-1, 1]) and physics settings as
franka_pick (50 Hz control, one physics substep), but no cube: the only contact pair is the hand
with the floor. It exists so that learning can be proven in a few CPU minutes.

Observation (27, raw), in this order:

====== ===================================================================
0:9    9 joint positions scaled to [-1, 1] within their limits
9:18   9 joint velocities x 0.1
18:21  fingertip midpoint (world, m)
21:24  target position
24:27  target - fingertip midpoint
====== ===================================================================

Reward (``state.metrics`` carries each UNSCALED term)::

    dist    = |target - tip_mid|                  scale -2.0
    at_target = 1 if dist <= 0.02                 scale  1.0
    action  = sum(a^2) of the clipped action      scale -0.01

Episode metrics, as franka_pick's (their value at an episode's last step is the episode's):
``success`` = the midpoint has been within 2 cm of the target for the last ``hold_seconds``
(1 s = 50 steps) and the episode has not terminated; ``reached`` = latched once within 2 cm;
``hold_time`` = seconds within 2 cm. Targets are uniform in x 0.35-0.65, y -0.25-0.25,
z 0.15-0.5 m; initial arm joints are home +- 0.125 rad. episode_length 100 (2 s at 50 Hz): the
arm can cross the workspace in well under a second at the action's full speed.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
from brax.envs.base import State

from envs.panda import (
    CLAMPED_FINGERS,
    PandaEnv,
    apply_overrides,
    as_f32_dict,
    base_config,
    episode_metrics,
    hold_update,
)

SUCCESS_RADIUS = 0.02
# 2: success = held at the target for the last hold_seconds (1: latched reach);
# 3: finger servo targets reach past the closed limit (envs/panda.py, FINGER_TARGET_LOW);
# 4, 5: as 3 (franka_pick's revisions 4 and 5 changed its reward only).
REVISION = 5


def default_config() -> ml_collections.ConfigDict:
    """Default franka_reach config (override keys through ``envs.get_environment``)."""
    return base_config(
        episode_length=100,
        hold_seconds=1.0,
        target_low=(0.35, -0.25, 0.15),
        target_high=(0.65, 0.25, 0.5),
        reward_scales=dict(dist=-2.0, at_target=1.0, action=-0.01),
    )


def reach_reward_terms(
    tip_mid: jax.Array, target: jax.Array, action: jax.Array
) -> dict[str, jax.Array]:
    """Unscaled reach terms for one env: ``tip_mid``/``target`` ``[3]``, ``action`` ``[9]``."""
    dist = jnp.linalg.norm(target - tip_mid)
    return as_f32_dict(
        dict(
            dist=dist,
            at_target=jnp.where(dist <= SUCCESS_RADIUS, 1.0, 0.0),
            action=jnp.sum(jnp.square(action)),
        )
    )


class FrankaReach(PandaEnv):
    """Reach a random point with the fingertip midpoint (see the module docstring)."""

    scene = "reach_scene.xml"
    revision = REVISION
    # Revision 1 had revision 2's physics (only the metrics changed).
    legacy_overrides: dict[int, dict[str, Any]] = {1: {}, 2: CLAMPED_FINGERS, 3: {}}

    default_config = staticmethod(default_config)

    def __init__(self, **overrides: Any):
        super().__init__(apply_overrides(default_config(), overrides, "franka_reach"))
        self._hold_steps = int(round(self.config.hold_seconds / self.config.ctrl_dt))

    @property
    def observation_size(self) -> int:
        return 27

    def reset(self, rng: jax.Array) -> State:
        rng, k_arm, k_target = jax.random.split(rng, 3)
        q = self._random_arm_qpos(k_arm)
        target = jax.random.uniform(
            k_target,
            (3,),
            minval=jnp.array(self.config.target_low),
            maxval=jnp.array(self.config.target_high),
        )
        # The target lives in the mocap body, so Brax's auto-reset restores it with the data.
        data = self._initial_data(q, mocap_pos=target[None].astype(jnp.float32))
        terms = self._terms(data, jnp.zeros(9))
        metrics = dict(terms, **episode_metrics(data.userdata, 0.0, self._hold_steps, self.dt))
        return State(
            data,
            self._obs(data),
            self._reward(terms),
            jnp.zeros(()),
            as_f32_dict(metrics),
            self._info(data, rng),
        )

    def step(self, state: State, action: jax.Array) -> State:
        data, action = self._physics_step(state.pipeline_state, action)
        terms = self._terms(data, action)
        userdata = hold_update(data.userdata, terms["at_target"] > 0, 1)
        data = data.replace(userdata=userdata)
        bad = self._non_finite(data)
        terms = jax.tree.map(lambda x: jnp.where(bad, 0.0, x), terms)
        reward = jnp.where(bad, 0.0, self._reward(terms))
        # Keep metrics that wrappers added (Brax's EvalWrapper adds "reward" at reset).
        hold = episode_metrics(userdata, bad, self._hold_steps, self.dt)
        metrics = {**state.metrics, **terms, **hold}
        return State(
            data,
            self._sanitize(self._obs(data)),
            reward.astype(jnp.float32),
            bad.astype(jnp.float32),
            as_f32_dict(metrics),
            {**state.info, **self._info(data, state.info["rng"])},
        )

    # ----- pieces -------------------------------------------------------------------------
    def _tip_mid(self, data) -> jax.Array:
        left, right = self._tips(data)
        return 0.5 * (left + right)

    def _terms(self, data, action: jax.Array) -> dict[str, jax.Array]:
        return reach_reward_terms(self._tip_mid(data), data.mocap_pos[0], action)

    def _obs(self, data) -> jax.Array:
        q, qd = self._joint_obs(data)
        tip, target = self._tip_mid(data), data.mocap_pos[0]
        return jnp.concatenate([q, qd, tip, target, target - tip])

    def _info(self, data, rng: jax.Array) -> dict[str, jax.Array]:
        left, right = self._tips(data)
        return dict(
            rng=rng,
            left_tip=left,
            right_tip=right,
            tip_mid=0.5 * (left + right),
            target_pos=data.mocap_pos[0],
        )
