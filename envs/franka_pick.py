"""franka_pick: grasp a 4 cm cube from the floor and lift it to ``goal_z`` (PixMC FrankaPick).

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

Action (9): joint-target deltas in [-1, 1] (clipped here), see ``envs/panda.py``, with
``action_scale`` 2.0 instead of PixMC's 7.5: 0.04 rad per unit action per 50 Hz step
(Playground's PandaPickCube also moves its targets 0.04 rad per step) instead of 0.15 rad.
Why: a Gaussian policy explores by adding noise to every action, and at 0.15 rad per step
N(0, 0.1^2) noise on the scripted grasp's actions already breaks it (success 95 % -> 2 %),
while at 0.04 rad it still succeeds 87 % of the time (``docs/results/grasp_noise.py``).
Trained with PixMC's scale, neither actor carried the cube up in 16-22 M steps; with 2.0 both
held it within 1.2-2.5 M steps and passed 90 % success (seed 0, docs/results.md).
``action_scale=7.5`` restores PixMC's semantics.

Reward (PixMC's terms; ``state.metrics`` carries each UNSCALED term, ``held`` (0/1, not
scaled into the reward) and ``success``)::

    dist_left/right = 1 / (0.04 + max(|obj - tip|, 0.02))        scale 0.08 each
    lift            = 0.5 if obj_z - z_rest > 0.015 and held       scale 4.0
    object_goal     = 1 / (0.04 + |goal_z - obj_z|) if lifted+held scale 1.28
    goal_bonus      = 0.5 if |goal_z - obj_z| <= 0.04 and held     scale 4.0
    action          = sum(a^2) of the clipped action               scale -0.01

``held`` means both fingertip pads are within ``grasp_radius`` (0.04 m) of the cube centre; in a
grasp they sit 0.016-0.022 m from it (scripted grasp, 99th percentile). ``success`` latches
(stays 1 for the rest of the episode) once ``|goal_z - obj_z| <= 0.25 (goal_z - z_rest)`` and
``held`` have both been true for 10 consecutive control steps.

Why the grasp gate (PixMC has none): with PixMC's ungated terms, policies trained here learned to
TOSS the cube through the goal height. At 50 Hz with soft contacts a squeezed cube can be
launched, the airborne cube earns ``object_goal`` (up to 32 per step near the goal), and a toss
whose apex is 10 cm above the goal stays within the success band for ~14 steps, so it even
"succeeds". Measured on the 2-hour seed-0 runs (256 episodes each): 75 % (MLP) and 42 % (PopSAN)
of episodes ended early with the cube thrown out of the workspace, although 99 % lifted it.
``grasp_radius=0`` restores PixMC's ungated reward and success.
Episodes end (``done``) when the object falls more than 0.04 below its rest height or leaves the
workspace, or the physics state is NaN/inf; the timeout is Brax's ``EpisodeWrapper``
(``episode_length``). The arm links do not collide in this model (for speed), so PixMC's
"arm-link contact" reset does not apply; the hand+pads cannot pass through the floor.

Scene: the cube rests on a floor-level table (z_rest = 0.02) at x = 0.5 +- 0.1, y = 0 +- 0.2;
the lift distance of PixMC is kept (goal_z = z_rest + 0.4 = 0.42). Initial arm joints are the
home pose +- 0.125 rad.

Control rate and physics (chosen for MJX speed on CPU, measured in benchmarks/env_throughput.py):
ctrl_dt = sim_dt = 0.02 s, i.e. 50 Hz control with ONE physics substep per env step (Playground's
PandaPickCube uses 4 substeps of 5 ms). MJX's cost is per physics step, so one substep is what
reaches >= 11k env steps/s at 512 envs on 2 CPU cores. It stays stable because the integrator is
implicitfast (servo and joint damping handled implicitly), every joint has armature 0.1, the
servos are damped near critically and gravity-compensated (see assets/panda.xml), the contact set
is 4 explicit pairs, and the solver runs Newton with 4 iterations / 6 line-search iterations.
MJX's ``max_contact_points`` caps the TOTAL number of contacts (not per pair): 12 leaves room for
the cube-floor box (4) plus both box pads; with 4 the pads got no contacts at all. The grasp
holds at 50 Hz with box pads (pair friction 1.5) squeezing a 50 g cube at <= 20 N per finger; the
scripted grasp (``envs/scripted.py``) checks it: 97 % success on 64 random episodes (at PixMC's
action scale). The contact stays soft at 50 Hz, so a held cube creeps slowly; ~10-15 % slip
out 1.5-2 s after reaching the goal (success has latched by then). Elliptic cones (impratio
10) and a stiffer pad solimp made the grasp fail outright in MJX here.
episode_length 200 steps = 4 s (PixMC: 500 steps at 60 Hz = 8.3 s); the scripted
grasp-and-lift reaches success after about 2.5 s, leaving room for a learned policy.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
from brax.envs.base import State

from envs.panda import PandaEnv, apply_overrides, as_f32_dict, base_config

Z_REST = 0.02  # cube half-size: the cube's centre height when it rests on the floor
SUCCESS_STEPS = 10


def default_config() -> ml_collections.ConfigDict:
    """Default franka_pick config (override keys through ``envs.get_environment``)."""
    return base_config(
        action_scale=2.0,
        episode_length=200,
        lift_height=0.4,
        grasp_radius=0.04,
        object_x_range=(0.4, 0.6),
        object_y_range=(-0.2, 0.2),
        reward_scales=dict(
            dist_left=0.08,
            dist_right=0.08,
            lift=4.0,
            object_goal=1.28,
            goal_bonus=4.0,
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
    z_rest: float = Z_REST,
) -> dict[str, jax.Array]:
    """Unscaled reward terms for one env: ``obj``/tips ``[3]``, ``action`` ``[9]``.

    The object terms (lift, object_goal, goal_bonus) count only while ``is_held``; ``held``
    itself (0/1) is returned too, for the success counter and the metrics (it has no scale).
    """
    d_left = jnp.linalg.norm(obj - left_tip)
    d_right = jnp.linalg.norm(obj - right_tip)
    held = is_held(d_left, d_right, grasp_radius)
    lifted = held & ((obj[2] - z_rest) > 0.015)
    og_d = jnp.abs(goal_z - obj[2])
    return as_f32_dict(
        dict(
            dist_left=1.0 / (0.04 + jnp.maximum(d_left, 0.02)),
            dist_right=1.0 / (0.04 + jnp.maximum(d_right, 0.02)),
            lift=jnp.where(lifted, 0.5, 0.0),
            object_goal=jnp.where(lifted, 1.0 / (0.04 + og_d), 0.0),
            goal_bonus=jnp.where(held & (og_d <= 0.04), 0.5, 0.0),
            action=jnp.sum(jnp.square(action)),
            held=held.astype(jnp.float32),
        )
    )


def is_held(d_left: jax.Array, d_right: jax.Array, grasp_radius: float) -> jax.Array:
    """Both tip-to-cube distances within ``grasp_radius`` (always True when it is <= 0)."""
    if grasp_radius <= 0:
        return jnp.asarray(True)
    return jnp.maximum(d_left, d_right) <= grasp_radius


def success_update(
    count: jax.Array, success: jax.Array, at_goal: jax.Array, held: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Consecutive steps at the goal while held, and the latched success flag (0/1 floats)."""
    count = jnp.where(at_goal & held, count + 1.0, 0.0)
    return count, jnp.maximum(success, (count >= SUCCESS_STEPS).astype(jnp.float32))


class FrankaPick(PandaEnv):
    """Grasp-and-lift with the project's Panda model (see the module docstring)."""

    scene = "pick_scene.xml"

    default_config = staticmethod(default_config)

    def __init__(self, **overrides: Any):
        super().__init__(apply_overrides(default_config(), overrides, "franka_pick"))
        m = self.mj_model
        self._obj_qpos = m.joint("box_joint").qposadr[0]
        self._obj_body = m.body("box").id
        self.z_rest = Z_REST
        self.goal_z = Z_REST + float(self.config.lift_height)
        self._goal_tol = 0.25 * (self.goal_z - Z_REST)
        self._grasp_radius = float(self.config.grasp_radius)
        m.site_pos[m.site("goal").id, 2] = self.goal_z  # only drawn, never simulated

    @property
    def observation_size(self) -> int:
        return 34

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
        metrics = dict(terms, success=jnp.zeros(()))
        obs = self._obs(data)
        info = self._info(data, rng)
        reward = self._reward(terms)
        return State(data, obs, reward, jnp.zeros(()), as_f32_dict(metrics), info)

    def step(self, state: State, action: jax.Array) -> State:
        data, action = self._physics_step(state.pipeline_state, action)
        obj = data.xpos[self._obj_body]
        raw_terms = self._terms(data, action)
        at_goal = jnp.abs(self.goal_z - obj[2]) <= self._goal_tol
        # userdata = [consecutive steps near the goal while held, latched success]
        count, success = success_update(
            data.userdata[0], data.userdata[1], at_goal, raw_terms["held"] > 0
        )
        data = data.replace(userdata=jnp.stack([count, success]).astype(jnp.float32))

        bad = self._non_finite(data)
        fell = obj[2] < Z_REST - 0.04
        away = jnp.linalg.norm(obj[:2]) > 1.2
        done = bad | fell | away
        terms = jax.tree.map(lambda x: jnp.where(bad, 0.0, x), raw_terms)
        reward = jnp.where(bad, 0.0, self._reward(terms))
        # Keep metrics that wrappers added (Brax's EvalWrapper adds "reward" at reset).
        metrics = {**state.metrics, **terms, "success": success}
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
    def _terms(self, data, action: jax.Array) -> dict[str, jax.Array]:
        left, right = self._tips(data)
        return pick_reward_terms(
            data.xpos[self._obj_body], left, right, self.goal_z, action, self._grasp_radius
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
