"""A tiny point-mass env and configs for the training-loop tests (compiles in seconds).

The env is a ``brax.envs.base.Env``: a point in the plane moves by ``0.1 * action`` per step
towards a random target. ``success`` latches once the point is within 0.1 of the target, so an
untrained (random-mean) policy rarely succeeds and a trained one almost always does.
"""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

from popsan_jax.config import RunConfig


class PointMass(Env):
    """obs ``[4]`` = (position, target - position); action ``[2]`` in [-1, 1]."""

    def __init__(self, episode_length: int = 30) -> None:
        self.config = types.SimpleNamespace(episode_length=episode_length, ctrl_dt=0.1)

    def reset(self, rng: jax.Array) -> State:
        k_pos, k_target = jax.random.split(rng)
        pos = jax.random.uniform(k_pos, (2,), minval=-1.0, maxval=1.0)
        target = jax.random.uniform(k_target, (2,), minval=-1.0, maxval=1.0)
        zero = jnp.zeros(())
        return State(
            pipeline_state=None,
            obs=jnp.concatenate([pos, target - pos]),
            reward=zero,
            done=zero,
            metrics={"distance": zero, "action_cost": zero, "success": zero},
            info={"pos": pos, "target_pos": target},
        )

    def step(self, state: State, action: jax.Array) -> State:
        action = jnp.clip(action, -1.0, 1.0)
        pos = jnp.clip(state.info["pos"] + 0.1 * action, -1.5, 1.5)
        target = state.info["target_pos"]
        distance = jnp.linalg.norm(target - pos)
        cost = 0.01 * jnp.sum(action**2)
        success = jnp.maximum(state.metrics["success"], (distance < 0.1).astype(jnp.float32))
        return state.replace(
            obs=jnp.concatenate([pos, target - pos]),
            reward=-distance - cost,
            metrics={"distance": distance, "action_cost": cost, "success": success},
            info={**state.info, "pos": pos},
        )

    @property
    def observation_size(self) -> int:
        return 4

    @property
    def action_size(self) -> int:
        return 2

    @property
    def backend(self) -> str:
        return "none"


def tiny_config(**changes) -> RunConfig:
    """A complete run of 4 iterations x 640 steps with a small PopSAN, 2 evals."""
    base = RunConfig(
        env="point_mass",
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
