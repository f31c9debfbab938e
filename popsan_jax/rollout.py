"""Jitted evaluation rollouts: whole episodes, vmapped over envs, no auto-reset.

One piece of code serves the trainer's periodic evaluation and ``eval.py``. Every env runs for
exactly ``episode_length`` control steps inside one ``lax.scan``; everything after an episode's
first ``done`` is masked out (with ``jnp.where``, so NaNs of a terminated env never leak into the
statistics). Episodes therefore end at their first ``done`` or at the time limit.

Shapes: ``N`` episodes (= parallel envs), ``T`` control steps, ``O`` observation size,
``A`` action size. Time is axis 0 of every recorded array.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

PolicyFn = Callable[[jax.Array, jax.Array], jax.Array]
"""``policy(obs [N, O], key) -> action [N, A]``."""

PolicyFactory = Callable[[Any], PolicyFn]
"""``factory(params) -> policy``: lets one compiled runner serve changing parameters."""

_RECORDED_INFO_KEYS = ("left_tip", "right_tip", "object_pos", "tip_mid", "target_pos")
EPISODE_END_METRICS = ("success", "reached", "hold_time")
"""Metrics whose value at an episode's last step is the episode's (the envs keep them so);
every other metric is averaged over the episode's steps."""


@flax.struct.dataclass
class EpisodeBatch:
    """Per-episode statistics of ``N`` episodes, plus the recorded trajectories if asked for.

    Attributes:
      success: ``[N]`` the env's ``success`` at the episode's last step (0 or 1): for the Panda
        tasks, held at the goal for the episode's last seconds without terminating early.
      reached: ``[N]`` the env's ``reached`` at the last step: the latched "got there once" flag.
      hold_time: ``[N]`` the env's ``hold_time`` at the last step: seconds spent at the goal.
      length: ``[N]`` control steps until the first ``done`` or the time limit.
      ret: ``[N]`` undiscounted sum of rewards.
      terms: reward term name -> ``[N]`` mean of the unscaled term over the episode's steps.
      obs: ``[T, N, O]`` raw (un-normalised) observation fed to the policy at each step, or None.
      action: ``[T, N, A]`` action taken at each step, or None.
      alive: ``[T, N]`` 1.0 while the episode runs (the step counts), else 0.0; or None.
      info: key -> ``[T, N, ...]`` recorded ``state.info`` entries (fingertips, object, target).
      qpos: ``[T, N, nq]`` generalised positions, enough to re-render the episode; or None.
      mocap_pos: ``[T, N, nmocap, 3]`` mocap body positions (e.g. the reach target), or None.
    """

    success: jax.Array
    reached: jax.Array
    hold_time: jax.Array
    length: jax.Array
    ret: jax.Array
    terms: dict[str, jax.Array]
    obs: jax.Array | None = None
    action: jax.Array | None = None
    alive: jax.Array | None = None
    info: dict[str, jax.Array] | None = None
    qpos: jax.Array | None = None
    mocap_pos: jax.Array | None = None


def make_episode_runner(
    env: Any,
    policy_factory: PolicyFactory,
    num_episodes: int,
    episode_length: int | None = None,
    record: bool = False,
    info_keys: Sequence[str] = _RECORDED_INFO_KEYS,
) -> Callable[[Any, jax.Array], EpisodeBatch]:
    """Build ``runner(params, key) -> EpisodeBatch``, jitted once for fixed shapes.

    Args:
      env: an unwrapped env (``reset``/``step``/``config.episode_length``), not vmapped.
      policy_factory: ``factory(params) -> policy(obs [N, O], key) -> action [N, A]``.
      num_episodes: N, the number of episodes run in parallel.
      episode_length: T; defaults to ``env.config.episode_length``.
      record: also return per-step obs, actions, alive mask, info entries and qpos.
      info_keys: ``state.info`` entries to record when present.
    """
    steps = int(episode_length or env.config.episode_length)
    reset = jax.vmap(env.reset)
    step = jax.vmap(env.step)

    def run(params: Any, key: jax.Array) -> EpisodeBatch:
        policy = policy_factory(params)
        key, reset_key = jax.random.split(key)
        state = reset(jax.random.split(reset_key, num_episodes))
        missing = [k for k in EPISODE_END_METRICS if k not in state.metrics]
        if missing:
            raise ValueError(f"the env's metrics lack the episode metrics {missing}")
        term_names = sorted(k for k in state.metrics if k not in EPISODE_END_METRICS)
        zeros = jnp.zeros((num_episodes,), jnp.float32)
        carry = dict(
            state=state,
            key=key,
            alive=jnp.ones((num_episodes,), jnp.float32),
            ret=zeros,
            length=zeros,
            end={k: zeros for k in EPISODE_END_METRICS},
            terms={k: zeros for k in term_names},
        )

        def body(c: dict, _: None) -> tuple[dict, dict | None]:
            key, act_key = jax.random.split(c["key"])
            s = c["state"]
            action = policy(s.obs, act_key)
            nxt = step(s, action)
            alive = c["alive"]
            live = alive > 0

            def add(total: jax.Array, value: jax.Array) -> jax.Array:
                return jnp.where(live, total + value.astype(jnp.float32), total)

            new = dict(
                state=nxt,
                key=key,
                alive=jnp.where(live & (nxt.done == 0), 1.0, 0.0).astype(jnp.float32),
                ret=add(c["ret"], nxt.reward),
                length=add(c["length"], jnp.ones_like(alive)),
                end={
                    k: jnp.where(live, nxt.metrics[k].astype(jnp.float32), c["end"][k])
                    for k in EPISODE_END_METRICS
                },
                terms={k: add(c["terms"][k], nxt.metrics[k]) for k in term_names},
            )
            if not record:
                return new, None
            frame = dict(
                obs=s.obs,
                action=action,
                alive=alive,
                info={k: s.info[k] for k in info_keys if k in s.info},
                qpos=getattr(s.pipeline_state, "qpos", None),
                mocap_pos=getattr(s.pipeline_state, "mocap_pos", None),
            )
            return new, frame

        final, frames = jax.lax.scan(body, carry, None, length=steps)
        length = final["length"]
        terms = {k: v / jnp.maximum(length, 1.0) for k, v in final["terms"].items()}
        batch = EpisodeBatch(**final["end"], length=length, ret=final["ret"], terms=terms)
        if record:
            batch = batch.replace(**frames)
        return batch

    return jax.jit(run)


def run_episodes(
    env: Any,
    policy_fn: PolicyFn,
    key: jax.Array,
    num_episodes: int,
    episode_length: int | None = None,
    record: bool = False,
) -> EpisodeBatch:
    """Run ``num_episodes`` episodes once with a fixed policy (see :func:`make_episode_runner`).

    For repeated evaluation with changing parameters, build the runner once instead: this
    convenience compiles anew for each new ``policy_fn``.
    """
    runner = make_episode_runner(
        env, lambda _: policy_fn, num_episodes, episode_length=episode_length, record=record
    )
    return runner(None, key)
