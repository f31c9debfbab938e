"""One tiny pick-like env and run configs for the training and evaluator tests (no MJX).

A free "hand" point moves by ``0.1 * action`` per step towards a random "object" position. Its
``info`` carries the pick keys the evaluator records (``left_tip``, ``right_tip``,
``object_pos``), and its ``pipeline_state.qpos`` is a free joint (position + unit quaternion) of
``mj_model``, so tracking figures and video rendering run on it as on the real pick env.
``success`` latches once the hand is within ``success_radius`` of the object, so an untrained
(random-mean) policy rarely succeeds. It compiles in seconds.
"""

from __future__ import annotations

import types

import flax.struct
import jax
import jax.numpy as jnp
import mujoco
from brax.envs.base import Env, State

from popsan_jax.config import RunConfig

_XML = """
<mujoco>
  <worldbody>
    <light pos="0 0 3"/>
    <geom type="plane" size="2 2 0.1" rgba="0.8 0.8 0.8 1"/>
    <body name="hand" pos="0 0 0.3">
      <freejoint/>
      <geom type="box" size="0.04 0.04 0.04" rgba="0.9 0.2 0.2 1"/>
    </body>
  </worldbody>
</mujoco>
"""
FINGER_OFFSET = jnp.array([0.0, 0.02, 0.0])
_CENTRE = jnp.array([0.0, 0.0, 0.5])


@flax.struct.dataclass
class _Pipeline:
    qpos: jax.Array


class PointPick(Env):
    """obs ``[6]`` = (hand position, object - hand); action ``[3]`` in [-1, 1].

    Hand and object start uniformly in a 1 m cube centred at (0, 0, 0.5).
    """

    goal_z = 0.3

    def __init__(
        self, episode_length: int = 12, ctrl_dt: float = 0.05, success_radius: float = 0.15
    ) -> None:
        self.config = types.SimpleNamespace(episode_length=episode_length, ctrl_dt=ctrl_dt)
        self.success_radius = success_radius
        self.mj_model = mujoco.MjModel.from_xml_string(_XML)

    def _state(self, pos: jax.Array, obj: jax.Array, info: dict | None = None, **fields) -> dict:
        quat = jnp.array([1.0, 0.0, 0.0, 0.0])
        return dict(
            pipeline_state=_Pipeline(qpos=jnp.concatenate([pos, quat])),
            obs=jnp.concatenate([pos, obj - pos]),
            # Keep keys that Brax's training wrappers add to info.
            info={
                **(info or {}),
                "left_tip": pos + FINGER_OFFSET,
                "right_tip": pos - FINGER_OFFSET,
                "object_pos": obj,
            },
            **fields,
        )

    def reset(self, rng: jax.Array) -> State:
        k_pos, k_obj = jax.random.split(rng)
        pos = jax.random.uniform(k_pos, (3,), minval=-0.5, maxval=0.5) + _CENTRE
        obj = jax.random.uniform(k_obj, (3,), minval=-0.5, maxval=0.5) + _CENTRE
        zero = jnp.zeros(())
        metrics = {
            "distance": zero,
            "action_cost": zero,
            "success": zero,
            "reached": zero,
            "hold_time": zero,
        }
        return State(**self._state(pos, obj, reward=zero, done=zero, metrics=metrics))

    def step(self, state: State, action: jax.Array) -> State:
        action = jnp.clip(action, -1.0, 1.0)
        pos = state.pipeline_state.qpos[:3] + 0.1 * action
        obj = state.info["object_pos"]
        distance = jnp.linalg.norm(obj - pos)
        cost = 0.01 * jnp.sum(action**2)
        near = (distance < self.success_radius).astype(jnp.float32)
        success = jnp.maximum(state.metrics["success"], near)
        metrics = {
            "distance": distance,
            "action_cost": cost,
            "success": success,
            "reached": success,
            "hold_time": state.metrics["hold_time"] + near * self.config.ctrl_dt,
        }
        fields = dict(reward=-distance - cost, metrics=metrics)
        return state.replace(**self._state(pos, obj, state.info, **fields))

    @property
    def observation_size(self) -> int:
        return 6

    @property
    def action_size(self) -> int:
        return 3

    @property
    def backend(self) -> str:
        return "none"


def tiny_config(**changes) -> RunConfig:
    """A complete PopSAN run of 640 env steps per iteration (16 envs x 4 x 10), small sizes.

    Defaults: 4 iterations, 2 evals, one hidden layer of 16 at T = 2; pass changes (e.g.
    ``total_env_steps``, ``num_evals``, ``actor_kwargs``) for other shapes.
    """
    base = RunConfig(
        env="point_pick",
        actor="popsan",
        actor_kwargs=dict(hidden_sizes=(16,), encoder_pop_dim=4, decoder_pop_dim=4, timesteps=2),
        critic_hidden_sizes=(16,),
        num_envs=16,
        batch_size=16,
        num_minibatches=4,
        unroll_length=10,
        num_updates_per_batch=2,
        total_env_steps=4 * 640,
        num_evals=2,
        num_eval_envs=8,
        keep_every_n_evals=1,
    )
    return base.replace(**changes)


def tiny_popsan_config(**changes) -> RunConfig:
    """3 iterations x 640 env steps, a PopSAN with hidden 12-8 at T = 2, 3 checkpoints."""
    actor_kwargs = dict(hidden_sizes=(12, 8), encoder_pop_dim=3, decoder_pop_dim=4, timesteps=2)
    return tiny_config(actor_kwargs=actor_kwargs, total_env_steps=3 * 640, num_evals=3).replace(
        **changes
    )
