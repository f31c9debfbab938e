"""franka_pick: grasp a 4 cm, 50 g cube from the floor, lift it to ``goal_z`` and hold it there.

PixMC's FrankaPick semantics on the project's Panda model; the reasons for each departure from
PixMC are in ``docs/design.md`` (action scale, grasp gate, contact settings, episode length).

Observation (34, raw / un-normalised), in this order:

====== ========================================================================
0:9    9 joint positions (7 arm, 2 fingers) scaled to [-1, 1] within their limits
9:18   9 joint velocities x 0.1
18:21  left fingertip pad position (world, m)
21:24  right fingertip pad position
24:27  object (cube centre) position
27:30  left tip-to-object vector (object - left tip)
30:33  right tip-to-object vector (object - right tip)
33     goal_z - object_z
====== ========================================================================

Action (9): joint-target deltas in [-1, 1] (clipped here), see ``envs/panda.py``; ``action_scale``
2.0 (0.04 rad per unit action per 50 Hz step; PixMC's 7.5 moves 0.15 rad).

Reward (PixMC's terms; ``state.metrics`` carries each UNSCALED term; scales in
``config.reward_scales``)::

    dist_left/right = 1 / (0.04 + max(|obj - tip|, 0.02))        scale 0.08 each
    lift            = 0.5 * clip((obj_z - z_rest) / lift_ramp, 0, 1) if held   scale 4.0
                      (lift_ramp = 0: PixMC's 0.5 if obj_z - z_rest > 0.015 and held)
    object_goal     = 1 / (0.04 + |goal_z - obj_z|) if lifted+held scale 1.28
    goal_bonus      = 0.5 if |goal_z - obj_z| <= 0.04 and held     scale 4.0
    climb           = clip((obj_z - z_rest) / (goal_z - z_rest), 0, 1) if held   scale 16.0
    object_speed    = |v_obj| (m/s) if held and in the goal band    scale -6.0
    action          = sum(a^2) of the clipped action               scale -0.01

``held`` (0/1, no scale): both fingertip pads within ``grasp_radius`` (0.04 m) of the cube centre.
``lift_ramp`` (m; default 0.015; 0 for PixMC's step at 1.5 cm) makes ``lift`` a ramp that pays
for every millimetre a held cube rises, up to ``lift_ramp``: PixMC's step gives a policy that
grasps the cube on the table no signal until a random motion carries the held cube 1.5 cm up.
``object_goal`` keeps the 1.5 cm gate (``docs/design.md``, "A ramp for the first centimetre").
The object terms pay only while the cube is held, so no term pays for a thrown or dropped cube.
``object_speed`` (not PixMC's) charges the held cube's motion inside the goal band: the goal is a
height, and with a grasp that squeezes nothing else stops a policy from swinging the held cube
through the band. It is not charged on the way up, where it would cost the same for every metre
climbed, whatever the speed, and stall the lift (``docs/design.md``, "Holding still").
``climb`` (not PixMC's) pays the held cube's height in proportion, from the table to the goal:
``object_goal``'s ``1 / (0.04 + d)`` is nearly flat far below the goal (its slope, unscaled:
0.06 per cm at 4 cm up, 6 per cm at the goal), so with the ramp alone policies learnt to hold
the cube a few centimetres up and stayed there (``docs/design.md``, "A climb term").
``in band``: ``|goal_z - obj_z| <= 0.25 (goal_z - z_rest)`` (PixMC's success tolerance).

Episode metrics (``state.metrics``; their value at an episode's last step is the episode's):

- ``success``: pick-and-hold. 1 at a step when the cube has been held inside the band for the
  last ``hold_seconds`` (2 s = 100 control steps) and the episode has not terminated; so at the
  last step of an episode it means "ran to its end with the cube held at the goal for its last
  2 s". An episode that terminates early is a failure.
- ``reached``: PixMC's latched success, kept for comparison with the paper: 1 from the step the
  cube has been held inside the band for ``reach_steps`` (10) consecutive steps.
- ``hold_time``: seconds so far with the cube held inside the band.

Episodes end (``done``) when the object falls more than 0.04 below its rest height or leaves the
workspace, or the physics state is NaN/inf; the timeout is Brax's ``EpisodeWrapper``
(``episode_length`` 250 steps = 5 s: the scripted grasp reaches the band after about 2.5 s, and
the last 2 s must be a hold). The arm links do not collide (for speed), so PixMC's "arm-link
contact" reset does not apply; the hand and pads cannot pass through the floor.

Scene: the cube rests on a floor-level table (z_rest = 0.02) at x = 0.5 +- 0.1, y = 0 +- 0.2; the
lift distance of PixMC is kept (goal_z = z_rest + 0.4 = 0.42). Initial arm joints: home +-
0.125 rad.

Physics: 50 Hz control with two 10 ms physics substeps (MJX's cost is per physics step), the
implicitfast integrator, 4 explicit contact pairs, Newton with 4 / 6 line-search iterations.
Why a grasp needs both (``docs/design.md``, "The grasp that holds"): MuJoCo's soft constraints
let a contact under a steady load slip at a rate proportional to ``(1 - d) / d`` times its time
constant, and ``refsafe`` keeps that time constant >= 2 substeps. The pad-cube pairs therefore
use ``pad_solimp`` with impedance 0.99 (MuJoCo's default is 0.95), which with 10 ms substeps
keeps a held cube in the fingers for 20 s; at 20 ms substeps so stiff a contact and the finger
servos eject the cube when the lift starts. Revision 3 lets the finger servo targets go 2 cm past
the closed limit (``finger_target_low``), so that every grasp squeezes: with targets clamped at the
limit, policies wedged the cube between one finger at each stop, with no servo force, and lost
it. Revision 4 charges the held cube's speed in the goal band; revision 5 pays the lift as a
ramp and the climb in proportion. ``LEGACY_OVERRIDES`` restore each earlier revision (revision 1:
one 20 ms substep, the default impedance, 200-step episodes) for runs saved before a change.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
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

Z_REST = 0.02  # cube half-size: the cube's centre height when it rests on the floor
MUJOCO_DEFAULT_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)
# What earlier revisions of this env meant, for run configs saved before a change (they name
# the revision they were trained with; the library merges these under the run's overrides).
LEGACY_OVERRIDES: dict[int, dict[str, Any]] = {
    1: dict(sim_dt=0.02, pad_solimp=MUJOCO_DEFAULT_SOLIMP, episode_length=200),
    2: CLAMPED_FINGERS,
    3: dict(reward_scales=dict(object_speed=0.0)),
    4: dict(lift_ramp=0.0, reward_scales=dict(climb=0.0)),
}
REVISION = 5


def default_config() -> ml_collections.ConfigDict:
    """Default franka_pick config (override keys through ``envs.get_environment``)."""
    return base_config(
        action_scale=2.0,
        episode_length=250,
        lift_height=0.4,
        grasp_radius=0.04,
        lift_ramp=0.015,
        hold_seconds=2.0,
        reach_steps=10,
        sim_dt=0.01,
        pad_solimp=(0.9, 0.99, 0.001, 0.5, 2.0),
        object_x_range=(0.4, 0.6),
        object_y_range=(-0.2, 0.2),
        reward_scales=dict(
            dist_left=0.08,
            dist_right=0.08,
            lift=4.0,
            object_goal=1.28,
            goal_bonus=4.0,
            climb=16.0,
            object_speed=-6.0,
            action=-0.01,
        ),
    )


def pick_reward_terms(
    obj: jax.Array,
    left_tip: jax.Array,
    right_tip: jax.Array,
    goal_z: float,
    action: jax.Array,
    grasp_radius: float,
    obj_vel: jax.Array,
    z_rest: float = Z_REST,
    lift_ramp: float = 0.0,
) -> dict[str, jax.Array]:
    """Unscaled reward terms for one env: ``obj``/tips ``[3]``, ``action`` ``[9]``, the cube's
    linear velocity ``obj_vel`` ``[3]`` (m/s). ``lift_ramp`` (m): 0 for PixMC's lift step at
    1.5 cm, else the height over which the lift term ramps from 0 to 0.5.

    The object terms (lift, object_goal, goal_bonus, climb) count only while ``is_held``; ``held``
    itself (0/1) is returned too, for the success counter and the metrics (it has no scale).
    """
    d_left = jnp.linalg.norm(obj - left_tip)
    d_right = jnp.linalg.norm(obj - right_tip)
    held = is_held(d_left, d_right, grasp_radius)
    lifted = held & ((obj[2] - z_rest) > 0.015)
    og_d = jnp.abs(goal_z - obj[2])
    if lift_ramp > 0:
        lift = jnp.where(held, 0.5 * jnp.clip((obj[2] - z_rest) / lift_ramp, 0.0, 1.0), 0.0)
    else:
        lift = jnp.where(lifted, 0.5, 0.0)
    return as_f32_dict(
        dict(
            dist_left=1.0 / (0.04 + jnp.maximum(d_left, 0.02)),
            dist_right=1.0 / (0.04 + jnp.maximum(d_right, 0.02)),
            lift=lift,
            object_goal=jnp.where(lifted, 1.0 / (0.04 + og_d), 0.0),
            goal_bonus=jnp.where(held & (og_d <= 0.04), 0.5, 0.0),
            climb=jnp.where(held, jnp.clip((obj[2] - z_rest) / (goal_z - z_rest), 0.0, 1.0), 0.0),
            object_speed=jnp.where(
                held & (og_d <= goal_band(goal_z, z_rest)), jnp.linalg.norm(obj_vel), 0.0
            ),
            action=jnp.sum(jnp.square(action)),
            held=held.astype(jnp.float32),
        )
    )


def goal_band(goal_z: float, z_rest: float = Z_REST) -> float:
    """Half-width of the goal band (m): PixMC's success tolerance, a quarter of the lift."""
    return 0.25 * (goal_z - z_rest)


def is_held(d_left: jax.Array, d_right: jax.Array, grasp_radius: float) -> jax.Array:
    """Both tip-to-cube distances within ``grasp_radius`` (always True when it is <= 0)."""
    if grasp_radius <= 0:
        return jnp.asarray(True)
    return jnp.maximum(d_left, d_right) <= grasp_radius


class FrankaPick(PandaEnv):
    """Grasp-and-lift with the project's Panda model (see the module docstring)."""

    scene = "pick_scene.xml"
    revision = REVISION
    legacy_overrides = LEGACY_OVERRIDES

    default_config = staticmethod(default_config)

    def __init__(self, **overrides: Any):
        super().__init__(apply_overrides(default_config(), overrides, "franka_pick"))
        m = self.mj_model
        self._obj_qpos = m.joint("box_joint").qposadr[0]
        # A free joint's first three velocities are its body's linear velocity (world frame).
        self._obj_qvel = m.joint("box_joint").dofadr[0]
        self._obj_body = m.body("box").id
        self.z_rest = Z_REST
        self.goal_z = Z_REST + float(self.config.lift_height)
        self._goal_tol = goal_band(self.goal_z, Z_REST)
        self._grasp_radius = float(self.config.grasp_radius)
        self._hold_steps = int(round(self.config.hold_seconds / self.config.ctrl_dt))
        m.site_pos[m.site("goal").id, 2] = self.goal_z  # only drawn, never simulated

    @property
    def observation_size(self) -> int:
        return 34

    @property
    def goal_tolerance(self) -> float:
        """Half-width of the goal band around ``goal_z`` (m)."""
        return self._goal_tol

    def reset(self, rng: jax.Array) -> State:
        rng, k_arm, k_obj = jax.random.split(rng, 3)
        q = self._random_arm_qpos(k_arm)
        lo = jnp.array([self.config.object_x_range[0], self.config.object_y_range[0]])
        hi = jnp.array([self.config.object_x_range[1], self.config.object_y_range[1]])
        xy = jax.random.uniform(k_obj, (2,), minval=lo, maxval=hi)
        upright = jnp.array([1.0, 0.0, 0.0, 0.0])  # unit quaternion: cube axis-aligned
        qpos = self._template.qpos.at[self._obj_qpos : self._obj_qpos + 7].set(
            jnp.concatenate([xy, jnp.array([Z_REST]), upright])
        )
        data = self._initial_data(q, qpos=qpos)
        zeros = jnp.zeros(9)
        terms = self._terms(data, zeros)
        metrics = dict(terms, **episode_metrics(data.userdata, 0.0, self._hold_steps, self.dt))
        obs = self._obs(data)
        info = self._info(data, rng)
        reward = self._reward(terms)
        return State(data, obs, reward, jnp.zeros(()), as_f32_dict(metrics), info)

    def step(self, state: State, action: jax.Array) -> State:
        data, action = self._physics_step(state.pipeline_state, action)
        obj = data.xpos[self._obj_body]
        raw_terms = self._terms(data, action)
        at_goal = jnp.abs(self.goal_z - obj[2]) <= self._goal_tol
        userdata = hold_update(
            data.userdata, at_goal & (raw_terms["held"] > 0), int(self.config.reach_steps)
        )
        data = data.replace(userdata=userdata)

        bad = self._non_finite(data)
        fell = obj[2] < Z_REST - 0.04
        away = jnp.linalg.norm(obj[:2]) > 1.2
        done = bad | fell | away
        terms = jax.tree.map(lambda x: jnp.where(bad, 0.0, x), raw_terms)
        reward = jnp.where(bad, 0.0, self._reward(terms))
        # Keep metrics that wrappers added (Brax's EvalWrapper adds "reward" at reset).
        hold = episode_metrics(userdata, done, self._hold_steps, self.dt)
        metrics = {**state.metrics, **terms, **hold}
        obs = self._sanitize(self._obs(data))
        info = {**state.info, **self._info(data, state.info["rng"])}
        return State(
            data,
            obs,
            reward.astype(jnp.float32),
            done.astype(jnp.float32),
            as_f32_dict(metrics),
            info,
        )

    # ----- pieces -------------------------------------------------------------------------
    def _tune_model(self, model) -> None:
        pads = {model.geom("left_pad").id, model.geom("right_pad").id}
        for i in range(model.npair):
            if {int(model.pair_geom1[i]), int(model.pair_geom2[i])} & pads:
                model.pair_solimp[i] = np.asarray(self.config.pad_solimp, np.float64)

    def _terms(self, data, action: jax.Array) -> dict[str, jax.Array]:
        left, right = self._tips(data)
        return pick_reward_terms(
            data.xpos[self._obj_body],
            left,
            right,
            self.goal_z,
            action,
            self._grasp_radius,
            data.qvel[self._obj_qvel : self._obj_qvel + 3],
            lift_ramp=float(self.config.lift_ramp),
        )

    def _obs(self, data) -> jax.Array:
        q, qd = self._joint_obs(data)
        left, right = self._tips(data)
        obj = data.xpos[self._obj_body]
        goal_gap = jnp.array([self.goal_z]) - obj[2:3]
        return jnp.concatenate([q, qd, left, right, obj, obj - left, obj - right, goal_gap])

    def _info(self, data, rng: jax.Array) -> dict[str, jax.Array]:
        left, right = self._tips(data)
        return dict(rng=rng, left_tip=left, right_tip=right, object_pos=data.xpos[self._obj_body])
