"""Actor latency: the timer against a known sleep, and the table rows of both actors."""

import time

import jax
import jax.numpy as jnp
import pytest

from popsan_jax.analysis import evaluation, latency
from popsan_jax.networks import MLPActor


def test_median_seconds_and_latency_rows(loaded):
    timing = latency.median_seconds(lambda: time.sleep(0.002), repeats=5, warmup=1)
    assert 0.002 <= timing["median_s"] < 0.05 and timing["p10_s"] <= timing["p90_s"]
    actors = evaluation.latency_actors(loaded, None)
    assert list(actors) == ["PopSAN T=2", "MLP (ANN)"]
    rows = latency.latency_table(actors, loaded.env.observation_size, (1, 64), repeats=5)
    assert [(r["actor"], r["batch"]) for r in rows] == [
        ("PopSAN T=2", 1),
        ("PopSAN T=2", 64),
        ("MLP (ANN)", 1),
        ("MLP (ANN)", 64),
    ]
    for r in rows:
        assert r["median_ms"] > 0 and r["per_obs_us"] == pytest.approx(
            1e3 * r["median_ms"] / r["batch"]
        )
    assert "| PopSAN T=2 | 64 |" in latency.format_latency(rows)


def test_actor_latency_per_batch_size_and_format():
    module = MLPActor(action_size=2, hidden_sizes=(4,))
    variables = module.init(jax.random.PRNGKey(0), jnp.zeros((1, 3)))
    timings = latency.actor_latency(module, variables, 3, batch_sizes=(1, 4), repeats=3)
    assert sorted(timings) == [1, 4]
    for t in timings.values():
        assert 0 < t["p10_s"] <= t["median_s"] <= t["p90_s"] < 1.0
    rows = [dict(actor="x", batch=4, median_ms=2.0, p10_ms=1.0, p90_ms=3.0, per_obs_us=500.0)]
    last = latency.format_latency(rows).splitlines()[-1]
    assert last == "| x | 4 | 2.000 | 1.000-3.000 | 500.00 |"
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        latency.median_seconds(lambda: None, repeats=0)
