"""Actor latency: the timer against a known sleep, and the table rows of both actors."""

import time

import pytest

from popsan_jax.analysis import evaluation, latency


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
