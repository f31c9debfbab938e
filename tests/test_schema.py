"""The schemas of a run's files (issue 22, item 6): config.json through RunConfig.from_dict,
metrics.jsonl records; each bad field is one line naming it (index.json:
tests/training/test_checkpoint_integrity.py)."""

from __future__ import annotations

import json

import pytest

from popsan_jax.config import RunConfig
from popsan_jax.errors import CheckpointError, ConfigError
from popsan_jax.io import read_jsonl

GOOD = RunConfig().to_dict()


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("num_envs", "abc", "num_envs must be an integer"),
        ("num_envs", 32.5, "num_envs must be an integer"),
        ("actor_lr", "fast", "actor_lr must be a finite number"),
        ("actor_lr", float("nan"), "actor_lr must be a finite number"),
        ("episode_length", "x", "episode_length must be an integer"),
        ("critic_hidden_sizes", 64, "critic_hidden_sizes must be a non-empty list"),
        ("critic_hidden_sizes", [64, 0], "critic_hidden_sizes must be a non-empty list"),
        ("actor_kwargs", [1], "actor_kwargs must be a JSON object"),
        ("env_overrides", [1], "env_overrides must be a JSON object"),
        ("normalize_advantage", "yes", "normalize_advantage must be true or false"),
        ("init_from", 3, "init_from must be a string"),
        ("env_revision", 0, "env_revision must be >= 1"),
        ("seed", -1, "seed must be in [0, 2**32 - 1]"),
    ],
)
def test_config_field_types_and_ranges(key, value, match, tmp_path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**GOOD, key: value}))
    with pytest.raises(ConfigError) as err:
        RunConfig.from_json(path)
    assert match in str(err.value) and str(path) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"timesteps": 0}, "timesteps T must be an integer >= 1"),
        ({"encoder_pop_dim": 0}, "actor_kwargs.encoder_pop_dim must be an integer >= 1"),
        ({"decoder_pop_dim": "10"}, "actor_kwargs.decoder_pop_dim must be an integer >= 1"),
        ({"hidden_sizes": "abc"}, "actor_kwargs.hidden_sizes must be a non-empty list"),
        ({"depth": 3}, "actor_kwargs has unknown key 'depth'"),
        ({"output_init_scale": 0}, "actor_kwargs.output_init_scale must be a finite number > 0"),
        ({"output_init_scale": -0.5}, "actor_kwargs.output_init_scale must be a finite number"),
        ({"output_init_scale": "0.01"}, "actor_kwargs.output_init_scale must be a finite number"),
    ],
)
def test_actor_kwargs(kwargs, match):
    with pytest.raises(ConfigError, match=match.replace(".", r"\.")):
        RunConfig.from_dict({**GOOD, "actor_kwargs": {**GOOD["actor_kwargs"], **kwargs}})


def test_good_configs_pass_and_float_fields_take_integers():
    assert RunConfig.from_dict(GOOD) == RunConfig()
    assert RunConfig.from_dict({**GOOD, "actor_lr": 1, "max_grad_norm": None}).actor_lr == 1


@pytest.mark.parametrize(
    "line, match",
    [
        ("5", "must be a JSON object"),
        ('{"kind": "train"}', "'env_steps' must be an integer >= 0"),
        ('{"env_steps": 3}', "without a 'kind'"),
        ('{"kind": "eval", "env_steps": 3, "success_rate": "high"}', "'success_rate' must"),
    ],
)
def test_metrics_records_off_their_schema(line, match, tmp_path):
    from popsan_jax.training.run_log import read_metrics

    good = '{"kind": "eval", "env_steps": 0, "success_rate": "nan"}'
    (tmp_path / "metrics.jsonl").write_text(f"{good}\n{line}\n{good}\n")
    with pytest.raises(CheckpointError, match=f"metrics.jsonl:2: .*{match}"):
        read_metrics(tmp_path)
    assert len(read_jsonl(tmp_path / "metrics.jsonl")) == 3  # no schema: only JSON is checked
