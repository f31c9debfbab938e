"""Actor inference latency per control step: jitted, after warm-up, median of many runs.

One "inference" is one call of the actor on a ``[B, O]`` batch of (already normalised)
observations, i.e. one control step for B robots; for PopSAN it includes all T SNN timesteps.
Times include JAX's dispatch, which dominates at batch 1 on a CPU.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


def median_seconds(
    fn: Callable[..., Any], *args: Any, repeats: int = 100, warmup: int = 3
) -> dict[str, float]:
    """Run ``fn(*args)`` ``warmup`` times, then time ``repeats`` calls (each blocked until ready).

    Returns ``{"median_s", "p10_s", "p90_s"}``.
    """
    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    for _ in range(max(1, warmup)):
        jax.block_until_ready(fn(*args))
    times = np.empty(repeats)
    for i in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times[i] = time.perf_counter() - start
    return {
        "median_s": float(np.median(times)),
        "p10_s": float(np.percentile(times, 10)),
        "p90_s": float(np.percentile(times, 90)),
    }


def actor_latency(
    module: nn.Module,
    variables: Any,
    observation_size: int,
    batch_sizes: Sequence[int] = (1, 2048),
    repeats: int = 100,
    seed: int = 0,
) -> dict[int, dict[str, float]]:
    """Latency of ``module.apply(variables, obs [B, O])`` for each batch size B."""
    apply = jax.jit(module.apply)
    results = {}
    for b in batch_sizes:
        # Normalised observations lie roughly in N(0, 1) clipped to the encoder's range.
        obs = jnp.clip(
            jax.random.normal(jax.random.PRNGKey(seed), (int(b), observation_size)), -3, 3
        )
        # Bigger batches are slower per call; fewer repeats keep the whole table within seconds.
        n = max(10, repeats // 4) if b > 256 else repeats
        results[int(b)] = median_seconds(apply, variables, obs, repeats=n)
    return results


def latency_table(
    actors: Mapping[str, tuple[nn.Module, Any]],
    observation_size: int,
    batch_sizes: Sequence[int] = (1, 2048),
    repeats: int = 100,
) -> list[dict[str, Any]]:
    """Rows ``{"actor", "batch", "median_ms", "p10_ms", "p90_ms", "per_obs_us"}`` per actor and
    batch size; ``actors`` maps a label to ``(module, variables)``."""
    rows = []
    for label, (module, variables) in actors.items():
        for b, t in actor_latency(
            module, variables, observation_size, batch_sizes, repeats
        ).items():
            rows.append(
                dict(
                    actor=label,
                    batch=b,
                    median_ms=1e3 * t["median_s"],
                    p10_ms=1e3 * t["p10_s"],
                    p90_ms=1e3 * t["p90_s"],
                    per_obs_us=1e6 * t["median_s"] / b,
                )
            )
    return rows


def format_latency(rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table of :func:`latency_table` rows."""
    lines = [
        "| actor | batch | median (ms) | p10-p90 (ms) | per observation (us) |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['actor']} | {r['batch']} | {r['median_ms']:.3f} | "
            f"{r['p10_ms']:.3f}-{r['p90_ms']:.3f} | {r['per_obs_us']:.2f} |"
        )
    return "\n".join(lines)
