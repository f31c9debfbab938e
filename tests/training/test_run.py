"""New run or resume: every bad command line fails with one clear line before anything is
written, and an interrupted run says what it left behind."""

from __future__ import annotations

import importlib.util
import json
import re

import pytest

from popsan_jax.cli import given_flags, run_choices, train_parser
from popsan_jax.errors import UserError
from popsan_jax.training import run
from popsan_jax.training.checkpoint_index import checkpoint_dir, index_path
from popsan_jax.training.loop import train


def start(argv: list[str]) -> None:
    """train.py's work for ``argv`` (without its signal handling and printing)."""
    args = train_parser().parse_args(argv)
    config, run_dir = run.prepare_run("cpu", *given_flags(args), **run_choices(args))
    train(config, run_dir, resume=bool(args.resume), progress=False)


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--actor", "lstm"], "unknown actor 'lstm'"),
        (["--env", "franka_fly"], "unknown env 'franka_fly'"),
        (
            ["--batch-size", "30", "--num-minibatches", "3", "--num-envs", "64"],
            "must be divisible by num_envs = 64",
        ),
        (["--resume", "{tmp}/missing"], "run directory .*missing does not exist"),
        (["--resume", "{tmp}", "--num-envs", "8"], "cannot change num_envs when resuming"),
        (["--resume", "{tmp}", "--timesteps", "2"], "cannot change timesteps when resuming"),
        (["--preset", "tiny"], "unknown preset 'tiny'"),
        (["--init-from", "{tmp}/missing"], "run directory .*missing does not exist"),
        (["--init-checkpoint", "newest"], "init_checkpoint must be 'best', 'last' or an env-step"),
        (["--sop-cost", "-1"], "sop_cost and sop_budget must be >= 0"),
        (["--actor", "mlp", "--sop-cost", "1"], "the 'mlp' actor has none"),
        (["--wandb"], "--wandb needs the wandb package"),
    ],
)
def test_bad_command_lines_fail_in_one_line_and_write_nothing(argv, match, tmp_path):
    if "--wandb" in argv and importlib.util.find_spec("wandb") is not None:
        pytest.skip("wandb is installed here")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    runs = tmp_path / "runs"
    smoke = [] if "--preset" in argv or "--resume" in argv else ["--preset", "smoke"]
    with pytest.raises(UserError) as err:
        start(["--runs-dir", str(runs), *smoke, *argv])
    assert "\n" not in str(err.value)
    assert re.search(match, str(err.value)), str(err.value)
    assert not runs.exists()


def test_new_run_names_its_directory_and_refuses_an_existing_one(tmp_path):
    config, run_dir = run.prepare_run(
        "cpu", {"env": "franka_reach"}, preset="smoke", runs_dir=tmp_path, name="r"
    )
    assert run_dir == tmp_path / "r" and config.env == "franka_reach" and config.num_envs == 32
    _, default = run.prepare_run("cpu", {"actor": "mlp"}, runs_dir=tmp_path)
    assert re.fullmatch(r"franka_pick-mlp-\d{8}-\d{6}", default.name)
    run_dir.mkdir()
    with pytest.raises(UserError, match="exists; use --resume or a new --name"):
        run.prepare_run("cpu", {}, preset="smoke", runs_dir=tmp_path, name="r")


def test_resume_takes_the_saved_config_and_only_more_steps(tmp_path):
    saved, run_dir = run.prepare_run("cpu", {"seed": 3}, preset="smoke", runs_dir=tmp_path)
    run_dir.mkdir()
    saved.to_json(run_dir / "config.json")
    # No checkpoint yet (killed before the first): resumable, training restarts it from step 0.
    assert run.prepare_run("cpu", {}, resume=run_dir) == (saved, run_dir)
    with pytest.raises(UserError, match="no checkpoint in"):
        run.prepare_run("cpu", {}, resume=tmp_path)  # no config either: not a run
    checkpoint_dir(run_dir).mkdir()
    entry = {"step": 1, "eval_index": 0, "success_rate": 0.0, "dir": "step_1"}
    index = {"checkpoints": [entry], "last": 1, "best": 1}
    index_path(run_dir).write_text(json.dumps(index))
    config, same = run.prepare_run("cpu", {"total_env_steps": 10**6}, resume=run_dir)
    assert same == run_dir and config == saved.replace(total_env_steps=10**6)
    with pytest.raises(UserError, match="cannot change preset/env overrides"):
        run.prepare_run("cpu", {}, preset="smoke", resume=run_dir)
    with pytest.raises(UserError, match="cannot change preset/env overrides"):
        run.prepare_run("cpu", {}, env_overrides={"episode_length": 9}, resume=run_dir)


def test_interrupted_message_says_whether_a_checkpoint_is_kept(tmp_path):
    assert run.interrupted_message(None) == "interrupted"
    assert run.interrupted_message(tmp_path) == "interrupted before anything was written"
    (tmp_path / "config.json").write_text("{}")
    assert run.interrupted_message(tmp_path) == (
        "interrupted before the first checkpoint; train it again from step 0 with: "
        f"python train.py --resume {tmp_path}"
    )
    checkpoint_dir(tmp_path).mkdir()
    entry = {"step": 1, "eval_index": 0, "success_rate": 0.0, "dir": "step_1"}
    index = {"checkpoints": [entry], "last": 1, "best": 1}
    index_path(tmp_path).write_text(json.dumps(index))
    assert run.interrupted_message(tmp_path) == (
        "interrupted; the last checkpoint is kept; resume with: "
        f"python train.py --resume {tmp_path}"
    )
