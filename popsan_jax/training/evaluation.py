"""The evaluation between training iterations: deterministic-policy episodes on the unwrapped
env (:mod:`popsan_jax.rollout`), summed up as one ``eval`` record of ``metrics.jsonl``.

(The evaluation of a finished run, with confidence intervals and energy, is
:mod:`popsan_jax.analysis.evaluation`.)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import numpy as np
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.rollout import EpisodeBatch, make_episode_runner
from popsan_jax.training.iteration import TrainingState


def make_evaluate_fn(
    env: Any, networks: ppo_networks.PPONetworks, num_envs: int, episode_length: int
) -> Callable[[TrainingState, jax.Array], dict[str, float]]:
    """``evaluate(state, key) -> eval record``: ``num_envs`` episodes of the deterministic
    policy (the actor mean) on the unwrapped ``env``."""
    make_policy = ppo_networks.make_inference_fn(networks)
    runner = make_episode_runner(
        env,
        lambda p: lambda obs, k: make_policy(p, deterministic=True)(obs, k)[0],
        num_envs,
        episode_length=episode_length,
    )

    device = jax.local_devices()[0]

    def evaluate(state: TrainingState, key: jax.Array) -> dict[str, float]:
        t0 = time.monotonic()
        # Committed to one device whatever the caller holds (the initial state's host arrays
        # or a pmapped state's first copy): the runner compiles once per run, not twice (an
        # MJX rollout compile is the costliest part of a run's start).
        inputs = jax.device_put(((state.normalizer_params, state.params.policy), key), device)
        batch = jax.device_get(runner(*inputs))
        return eval_record(batch, time.monotonic() - t0)

    return evaluate


def eval_record(batch: EpisodeBatch, eval_s: float) -> dict[str, float]:
    """The means over ``batch`` (host arrays) that an ``eval`` record logs, and the env steps
    per second of the ``eval_s`` seconds it took."""
    return {
        "success_rate": float(np.mean(batch.success)),
        "reached_rate": float(np.mean(batch.reached)),
        "hold_time": float(np.mean(batch.hold_time)),
        "episode_reward": float(np.mean(batch.ret)),
        "episode_length": float(np.mean(batch.length)),
        **{f"reward/{k}": float(np.mean(v)) for k, v in batch.terms.items()},
        "steps_per_s": float(np.sum(batch.length)) / max(eval_s, 1e-9),
    }
