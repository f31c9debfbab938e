"""A run with a warm-up stage (popsan_jax/training/stages.py): layout, resume of an interrupted
warm-up, the run's own stage starting from the warm-up's last checkpoint, the learning curve's
env steps counting both stages, a warm-up ended early by its success (end_at_success), a run
ended at a success trained on to its end by resuming it with end_at_success 0."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from _toy_env import PointPick, tiny_config

from popsan_jax.analysis.plots import read_run_curves
from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.training.checkpoint import load_run
from popsan_jax.training.checkpoint_index import read_index
from popsan_jax.training.loop import train
from popsan_jax.training.run import interrupted_message, resume_config
from popsan_jax.training.run_log import read_metrics
from popsan_jax.training.stages import train_run, warmup_config

STEPS = 640  # env steps per iteration of tiny_config()


def test_warmup_config_merges_overrides_and_drops_its_own_warm_up():
    config = RunConfig(
        env_overrides={"reward_scales": {"lift": 2.0}, "action_scale": 1.0},
        warmup_env_overrides={"reward_scales": {"object_speed": 0.0}, "finger_target_low": 0.0},
        warmup_env_steps=6000,
        warmup_actor_lr=1e-3,
        warmup_num_evals=3,
        total_env_steps=2000,
        actor_lr=3e-4,
        num_evals=8,
        seed=4,
        critic_warmup_env_steps=1000,
    )
    warm = warmup_config(config)
    assert warm.env_overrides == {
        "reward_scales": {"object_speed": 0.0, "lift": 2.0},
        "finger_target_low": 0.0,
        "action_scale": 1.0,
    }
    assert (warm.total_env_steps, warm.actor_lr, warm.num_evals) == (6000, 1e-3, 3)
    assert warm.warmup_env_steps == 0 and warm.warmup_env_overrides == {}
    assert warm.critic_warmup_env_steps == 0  # the critic warm-up is the run's own stage's
    assert warm.seed == 4 and warm.critic_lr == config.critic_lr


def test_interrupted_warm_up_resumes_then_the_run_starts_from_its_last_checkpoint(tmp_path):
    # 2 warm-up iterations (a checkpoint after each), interrupted during the second; resumed,
    # the warm-up ends and the run's own stage (1 iteration) starts from its last checkpoint.
    # The own stage's lrs are ~0, so its final policy must be the warm-up's last one.
    config = tiny_config(
        total_env_steps=STEPS,
        num_evals=1,
        actor_lr=1e-12,
        critic_lr=1e-12,
        warmup_env_steps=2 * STEPS,
        warmup_actor_lr=1e-2,
        warmup_num_evals=2,
    )
    run = tmp_path / "staged"
    calls = []

    def stop_in_second(steps, metrics):
        calls.append(steps)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_run(config, run, environment=PointPick(), progress=False, on_iteration=stop_in_second)
    assert RunConfig.from_json(run / "config.json") == config
    assert RunConfig.from_json(run / "warmup" / "config.json") == warmup_config(config)
    assert not (run / "metrics.jsonl").exists()
    assert "warm-up stage's last checkpoint is kept" in interrupted_message(run)

    result = train_run(config, run, resume=True, environment=PointPick(), progress=False)
    warm_steps = [r["env_steps"] for r in read_metrics(run / "warmup", "train")]
    assert warm_steps == [STEPS, 2 * STEPS]  # the second iteration again, not from step 0
    assert [r["env_steps"] for r in read_metrics(run, "train")] == [STEPS]
    assert int(result.state.env_steps) == STEPS
    warm = load_run(run / "warmup", "last", environment=PointPick())
    final = load_run(run, "last", environment=PointPick())
    for a, b in zip(
        jax.tree.leaves(final.policy_params), jax.tree.leaves(warm.policy_params), strict=True
    ):
        np.testing.assert_allclose(a, b, atol=1e-6)

    curves = read_run_curves(run)
    assert curves.warmup_steps == 2 * STEPS
    assert list(curves.env_steps) == [2 * STEPS, 3 * STEPS]  # own evaluations at 0 and STEPS
    evals = [r["env_steps"] for r in read_metrics(run, "eval")]
    assert evals == [0, STEPS]
    assert json.loads((run / "config.json").read_text())["warmup_env_steps"] == 2 * STEPS

    # Resumed again: both stages are finished; nothing is trained.
    again = train_run(config, run, resume=True, environment=PointPick(), progress=False)
    assert again.finished and len(read_metrics(run / "warmup", "train")) == 2


def test_bad_warm_up_is_refused_before_anything_is_written(tmp_path):
    config = tiny_config(warmup_env_steps=-5)
    with pytest.raises(ConfigError, match="warmup_env_steps must be >= 0"):
        train_run(config, tmp_path / "bad", environment=PointPick(), progress=False)
    assert not (tmp_path / "bad").exists()


def test_warm_up_ends_at_its_first_evaluation_that_reaches_its_success(tmp_path):
    # success_radius 10 m: every episode succeeds from its first step, so the warm-up's first
    # evaluation after an update (1.0) reaches warmup_end_at_success and ends it: one of its four
    # iterations, its last checkpoint that evaluation's. Killed between the stages (the warm-up
    # trained alone), the resumed run must not train the ended warm-up again.
    config = tiny_config(
        total_env_steps=STEPS,
        num_evals=1,
        warmup_env_steps=4 * STEPS,
        warmup_num_evals=4,
        warmup_end_at_success=0.5,
    )
    assert warmup_config(config).end_at_success == 0.5
    assert warmup_config(config).warmup_end_at_success == 0.0
    always = PointPick(success_radius=10.0)
    run = tmp_path / "staged"
    run.mkdir()
    config.to_json(run / "config.json")
    warm = train(warmup_config(config), run / "warmup", environment=always, progress=False)
    assert not warm.finished and int(warm.state.env_steps) == STEPS
    assert [r["env_steps"] for r in read_metrics(run / "warmup", "train")] == [STEPS]
    assert [r["success_rate"] for r in read_metrics(run / "warmup", "eval")] == [1.0, 1.0]
    assert [e["step"] for e in read_index(run / "warmup")["checkpoints"]] == [STEPS]

    result = train_run(config, run, resume=True, environment=always, progress=False)
    assert len(read_metrics(run / "warmup", "train")) == 1  # the ended warm-up stays ended
    assert [r["env_steps"] for r in read_metrics(run, "train")] == [STEPS]
    assert int(result.state.env_steps) == STEPS
    assert read_run_curves(run).warmup_steps == STEPS  # the warm-up's cost is what it ran


def test_a_run_that_never_reaches_end_at_success_runs_to_its_end(tmp_path):
    never = PointPick(success_radius=0.0)  # no distance is below 0
    config = tiny_config(total_env_steps=3 * STEPS, num_evals=3, end_at_success=0.01)
    result = train(config, tmp_path / "run", environment=never, progress=False)
    assert int(result.state.env_steps) == 3 * STEPS
    assert [r["success_rate"] for r in read_metrics(tmp_path / "run", "eval")] == [0.0] * 4


def test_a_run_ended_at_a_success_resumed_with_end_at_success_0_trains_to_its_end(tmp_path):
    always = PointPick(success_radius=10.0)  # every evaluation is 1.0
    run = tmp_path / "run"
    ended = train(
        tiny_config(total_env_steps=3 * STEPS, num_evals=3, end_at_success=0.5),
        run,
        environment=always,
        progress=False,
    )
    assert int(ended.state.env_steps) == STEPS  # ended at its first evaluation after an update
    again = train(resume_config(run, {}), run, resume=True, environment=always, progress=False)
    assert again.finished and again.ended and int(again.state.env_steps) == STEPS  # still ended
    config = resume_config(run, {"end_at_success": 0.0})
    assert config.end_at_success == 0.0
    result = train(config, run, resume=True, environment=always, progress=False)
    assert not result.finished and int(result.state.env_steps) == 3 * STEPS
    assert [r["env_steps"] for r in read_metrics(run, "train")] == [STEPS, 2 * STEPS, 3 * STEPS]
    assert RunConfig.from_json(run / "config.json").end_at_success == 0.0  # kept if killed again
