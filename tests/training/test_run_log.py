"""The run log: JSONL records, JSON-safe values, resuming drops what the checkpoint lacks."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from popsan_jax.errors import ConfigError
from popsan_jax.training.run_log import RunLogger, read_metrics


def test_records_are_plain_json_with_kind_steps_and_wall_time(tmp_path):
    log = RunLogger(tmp_path, total_env_steps=100, progress=False)
    log.log("train", 10, {"loss/total": np.float32(0.5), "kl": float("nan")})
    log.log("eval", 10, {"success_rate": 0.25})
    log.close()
    lines = (tmp_path / "metrics.jsonl").read_text().splitlines()
    first, second = (json.loads(line) for line in lines)
    assert first["kind"] == "train" and first["env_steps"] == 10 and first["wall_s"] >= 0
    assert first["loss/total"] == 0.5 and first["kl"] == "nan"  # NaN kept as valid JSON
    assert second == {**second, "kind": "eval", "success_rate": 0.25}
    assert [r["env_steps"] for r in read_metrics(tmp_path, "eval")] == [10]
    assert len(read_metrics(tmp_path)) == 2
    assert read_metrics(tmp_path / "nowhere") == []
    assert (tmp_path / "tb").is_dir()


def test_resume_drops_records_past_the_checkpoint_and_a_torn_line(tmp_path):
    log = RunLogger(tmp_path, total_env_steps=100, progress=False)
    for steps in (10, 20, 30):
        log.log("train", steps, {"x": steps})
    log.close()
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"kind": "train", "env_steps": 40, "x"')  # killed mid-line
    log = RunLogger(tmp_path, total_env_steps=100, initial_steps=20, progress=False)
    assert [r["env_steps"] for r in read_metrics(tmp_path)] == [10, 20]
    log.log("train", 30, {"x": 31})
    log.close()
    assert [(r["env_steps"], r["x"]) for r in read_metrics(tmp_path)] == [
        (10, 10),
        (20, 20),
        (30, 31),
    ]


@pytest.mark.skipif(importlib.util.find_spec("wandb") is not None, reason="wandb is installed")
def test_wandb_without_the_package_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="needs the wandb package"):
        RunLogger(tmp_path, total_env_steps=10, use_wandb=True, progress=False)
