"""A scripted grasp-and-lift controller for franka_pick: proof that the task is solvable.

It reads the true state (``mjx.Data``), not the observation, and drives the same 9-dim action
the policy uses. Phases by control step ``t`` (50 Hz): move the grasp site 10 cm above the cube,
descend onto it, close the fingers, lift to ``goal_z``. Cartesian targets become joint targets
through one damped-least-squares step per control step on the grasp site's position and a
"pointing down" orientation error, with the Jacobian from ``jax.jacfwd`` of ``mjx.kinematics``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco import mjx

from envs.franka_pick import FrankaPick
from envs.panda import HOME_QPOS

APPROACH_END, DESCEND_END, CLOSE_END = 55, 80, 95  # control steps; the lift starts at CLOSE_END
HOVER = 0.10  # m above the cube during the approach
MAX_STEP = 0.015  # m of Cartesian target motion per control step
DAMPING = 1e-3


def make_scripted_pick_policy(env: FrankaPick):
    """Return ``policy(data: mjx.Data) -> action [9]`` for ONE env (vmap it for a batch)."""
    model = env.mjx_model
    grasp = env.mj_model.site("grasp").id
    qadr = jnp.asarray(env._qpos_adr[:7])
    obj_body = env._obj_body
    step_scale = jnp.asarray(env.action_step)
    template = env._template

    def site_pose(q_arm):
        data = mjx.kinematics(model, template.replace(qpos=template.qpos.at[qadr].set(q_arm)))
        return data.site_xpos[grasp], data.site_xmat[grasp]

    _, home_rot = site_pose(jnp.asarray(HOME_QPOS[:7], jnp.float32))

    def pose_error_fn(q_arm):
        pos, rot = site_pose(q_arm)
        # Small-angle rotation vector from the current to the home ("pointing down") orientation.
        rot_err = 0.5 * jnp.sum(jnp.cross(rot.T, home_rot.T), axis=0)
        return jnp.concatenate([pos, rot_err])

    def policy(data: mjx.Data) -> jax.Array:
        t = jnp.round(data.time / env.config.ctrl_dt)
        obj = data.xpos[obj_body]
        hover = obj + jnp.array([0.0, 0.0, HOVER])
        # Lift straight up from the commanded xy: following the held cube's xy would chase it.
        lift = jnp.concatenate([pose_error_fn(data.ctrl[:7])[:2], jnp.array([env.goal_z])])
        # Grasp at the cube's rest height, not its measured height: chasing a cube that the
        # pads press down would drive the hand into the floor.
        grasp_at = jnp.concatenate([obj[:2], jnp.array([env.z_rest])])
        target = jnp.where(t < APPROACH_END, hover, jnp.where(t < CLOSE_END, grasp_at, lift))
        fingers = jnp.where(t < DESCEND_END, 0.04, 0.0)

        # Plan on the servo targets, not the measured joints: the measured pose lags the
        # command, and re-planning from it every step would fight the servos.
        q_cmd = data.ctrl[:7]
        current = pose_error_fn(q_cmd)
        jac = jax.jacfwd(pose_error_fn)(q_cmd)  # [6, 7]
        dpos = target - current[:3]
        dpos = dpos * jnp.minimum(1.0, MAX_STEP / (jnp.linalg.norm(dpos) + 1e-9))
        err = jnp.concatenate([dpos, -current[3:]])
        dq = jac.T @ jnp.linalg.solve(jac @ jac.T + DAMPING * jnp.eye(6), err)
        desired = jnp.concatenate([q_cmd + dq, jnp.full((2,), fingers)])
        return jnp.clip((desired - data.ctrl) / step_scale, -1.0, 1.0)

    return policy


def run_scripted_pick(env: FrankaPick, rng: jax.Array, num_episodes: int, steps: int | None = None):
    """Run the scripted controller on ``num_episodes`` randomised episodes in one vmapped scan.

    Returns ``(success [N], trace, final_state)``: ``success`` at the last step, ``trace`` a dict
    of per-step ``[T, N]`` arrays (``object_z``, ``held``, ``in_band_held``: held inside the goal
    band, ``success``, ``reached``). Episodes are not auto-reset.
    """
    steps = int(steps or env.config.episode_length)
    policy = jax.vmap(make_scripted_pick_policy(env))
    step = jax.vmap(env.step)

    @jax.jit
    def rollout(rng):
        state = jax.vmap(env.reset)(jax.random.split(rng, num_episodes))

        def body(state, _):
            state = step(state, policy(state.pipeline_state))
            obj_z = state.info["object_pos"][:, 2]
            in_band = jnp.abs(env.goal_z - obj_z) <= env.goal_tolerance
            trace = dict(
                object_z=obj_z,
                held=state.metrics["held"],
                in_band_held=(in_band & (state.metrics["held"] > 0)).astype(jnp.float32),
                success=state.metrics["success"],
                reached=state.metrics["reached"],
                object_speed=state.metrics["object_speed"],
            )
            return state, trace

        state, trace = jax.lax.scan(body, state, None, length=steps)
        return state.metrics["success"], trace, state

    return rollout(rng)


__all__ = ["make_scripted_pick_policy", "run_scripted_pick"]
