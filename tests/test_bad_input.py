"""Every user mistake of issue 22, item 6 (and the video path of item 7) is one line
``error: ...`` with exit 2 from train.py or eval.py, with nothing written: wrong types in a
run's files, bad flags and env overrides, filesystem faults (a file or /proc as --runs-dir,
read-only mounts, a full disk). Toy-env runs (tests/_run_fixtures.py), no MJX compile."""

from __future__ import annotations

import errno
import json
import os
import shutil

import pytest
from _run_fixtures import (
    STEPS,
    copy_run,
    load_script,
    one_error,
    remount_read_only,
    tmpfs,
    toy_env_everywhere,
)

from popsan_jax.analysis import report
from popsan_jax.training import checkpoint_index, loop

train_cli = load_script("train")
eval_cli = load_script("eval")
FAST = ["--episodes", "2", "--no-energy", "--no-latency", "--no-tracking"]
needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")


def _no_training(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("train.py went on to train")

    monkeypatch.setattr(loop, "build_trainer", refuse)


def _main(cli, argv) -> int:
    try:
        return cli.main(argv)
    except SystemExit as e:  # argparse
        return e.code


# ---- wrong types in config.json -----------------------------------------------------------
CONFIG_EDITS = [
    ({"num_envs": "abc"}, "num_envs must be an integer"),
    ({"actor_lr": "fast"}, "actor_lr must be a finite number"),
    ({"actor_kwargs": {"hidden_sizes": "abc"}}, "hidden_sizes must be a non-empty list"),
    ({"critic_hidden_sizes": 64}, "critic_hidden_sizes must be a non-empty list"),
    ({"actor_kwargs": [1]}, "actor_kwargs must be a JSON object"),
    ({"env_overrides": [1]}, "env_overrides must be a JSON object"),
    ({"actor_kwargs": {"timesteps": 0}}, "timesteps T must be an integer >= 1"),
    ({"actor_kwargs": {"encoder_pop_dim": 0}}, "encoder_pop_dim must be an integer >= 1"),
    ({"env_revision": "abc"}, "env_revision must be an integer"),
    ({"seed": 10**23}, "seed must be in [0, 2**32 - 1]"),
]


@pytest.mark.parametrize("edit, match", CONFIG_EDITS)
def test_config_json_wrong_types_on_resume_and_eval(
    edit, match, finished_toy_run, tmp_path, capsys, monkeypatch
):
    run = copy_run(finished_toy_run, tmp_path / "run")
    config = json.loads((run / "config.json").read_text())
    for key, value in edit.items():
        if key == "actor_kwargs" and isinstance(value, dict):
            config[key].update(value)
        else:
            config[key] = value
    (run / "config.json").write_text(json.dumps(config))
    before = (run / "metrics.jsonl").read_text()
    toy_env_everywhere(monkeypatch)
    _no_training(monkeypatch)
    assert _main(train_cli, ["--resume", str(run)]) == 2
    one_error(capsys.readouterr().err, match)
    assert _main(eval_cli, [str(run), *FAST]) == 2
    one_error(capsys.readouterr().err, match)
    assert (run / "metrics.jsonl").read_text() == before and not list(run.glob("eval_*"))


def test_config_json_random_bytes(finished_toy_run, tmp_path, capsys, monkeypatch):
    run = copy_run(finished_toy_run, tmp_path / "run")
    (run / "config.json").write_bytes(bytes(range(128, 256)) * 4)
    _no_training(monkeypatch)
    assert _main(train_cli, ["--resume", str(run)]) == 2
    one_error(capsys.readouterr().err, "cannot read run config")
    assert _main(eval_cli, [str(run), *FAST]) == 2
    one_error(capsys.readouterr().err, "cannot read run config")


# ---- metrics.jsonl ------------------------------------------------------------------------
@pytest.mark.parametrize(
    "line, match", [("5", "must be a JSON object"), ('{"kind": "train"}', "'env_steps' must")]
)
def test_metrics_line_off_its_schema(line, match, finished_toy_run, tmp_path, capsys, monkeypatch):
    run = copy_run(finished_toy_run, tmp_path / "run")
    lines = (run / "metrics.jsonl").read_text().splitlines()
    lines.insert(1, line)
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    _no_training(monkeypatch)
    argv = ["--resume", str(run), "--total-env-steps", str(3 * STEPS)]
    assert _main(train_cli, argv) == 2
    assert "metrics.jsonl:2" in one_error(capsys.readouterr().err, match)
    assert json.loads((run / "config.json").read_text())["total_env_steps"] == 2 * STEPS
    out = tmp_path / "cmp.png"
    assert _main(eval_cli, ["--compare", str(run), "--out", str(out)]) == 2
    one_error(capsys.readouterr().err, match)
    assert not out.exists()


# ---- flags --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "argv, match",
    [
        (["--timesteps", "0"], "timesteps T must be an integer >= 1"),
        (["--timesteps", "-3"], "timesteps T must be an integer >= 1"),
        (["--encoder-pop-dim", "0"], "encoder_pop_dim must be an integer >= 1"),
        (["--seed", "1e23"], "invalid int value: '1e23'"),
        (["--seed", str(10**23)], "seed must be in [0, 2**32 - 1]"),
        (["--env-override", 'reward_scales={"dist":"abc"}'], "'reward_scales.dist'"),
        (["--env-override", "sim_dt=0"], "sim_dt must be > 0"),
        (["--env-override", "target_low=abc"], "bad value 'abc' for 'target_low'"),
    ],
)
def test_bad_flags_are_one_line_and_write_nothing(argv, match, tmp_path, capsys):
    runs = tmp_path / "runs"
    base = ["--env", "franka_reach", "--preset", "smoke", "--runs-dir", str(runs)]
    assert _main(train_cli, [*base, *argv]) == 2
    one_error(capsys.readouterr().err, match)
    assert not runs.exists()


# ---- filesystem faults --------------------------------------------------------------------
def test_runs_dir_that_is_a_file_or_under_proc(tmp_path, capsys, monkeypatch):
    _no_training(monkeypatch)
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert _main(train_cli, ["--preset", "smoke", "--runs-dir", str(afile)]) == 2
    one_error(capsys.readouterr().err, "is a file, not a directory")
    assert _main(train_cli, ["--preset", "smoke", "--runs-dir", "/proc/popsan-runs"]) == 2
    one_error(capsys.readouterr().err, "kernel filesystem")
    assert afile.read_text() == "x"


@needs_root
def test_read_only_runs_dir_run_dir_and_eval(finished_toy_run, tmp_path, capsys, monkeypatch):
    with tmpfs(tmp_path / "ro", size="16m") as mnt:
        run = copy_run(finished_toy_run, mnt / "run")
        remount_read_only(mnt)
        _no_training(monkeypatch)
        assert _main(train_cli, ["--preset", "smoke", "--runs-dir", str(mnt / "runs")]) == 2
        one_error(capsys.readouterr().err, "not writable (Read-only file system)")
        assert _main(train_cli, ["--resume", str(run)]) == 2
        one_error(capsys.readouterr().err, "not writable (Read-only file system)")
        loads = []
        monkeypatch.setattr(report, "load_run", lambda *a, **k: loads.append(a))
        assert _main(eval_cli, [str(run), *FAST]) == 2
        one_error(capsys.readouterr().err, "not writable (Read-only file system)")
        assert not loads  # refused before any work


@needs_root
def test_disk_full_during_training_names_the_last_good_checkpoint(
    finished_toy_run, tmp_path, capsys, monkeypatch
):
    with tmpfs(tmp_path / "full", size="4m") as mnt:
        run = copy_run(finished_toy_run, mnt / "run")
        filler = mnt / "filler"
        fd = os.open(filler, os.O_WRONLY | os.O_CREAT)  # fill the disk, then free 64 KB
        try:
            while True:
                os.write(fd, os.urandom(65536))
        except OSError as e:
            assert e.errno == errno.ENOSPC
        finally:
            os.close(fd)
        os.truncate(filler, filler.stat().st_size - 65536)
        toy_env_everywhere(monkeypatch)
        argv = ["--resume", str(run), "--total-env-steps", str(4 * STEPS), "--no-progress"]
        assert _main(train_cli, argv) == 2
        line = one_error(capsys.readouterr().err)
        assert "No space left on device" in line, line
        assert f"the last good checkpoint is step {2 * STEPS}" in line, line
        filler.unlink()
        assert checkpoint_index.read_index(run)["last"] == 2 * STEPS
        assert not list((run / "checkpoints").glob("*tmp*"))  # no half-written checkpoint
        assert _main(train_cli, argv) == 0  # resumes once there is space
        assert checkpoint_index.read_index(run)["last"] == 4 * STEPS


def test_compare_out_unwritable(finished_toy_run, capsys):
    argv = ["--compare", str(finished_toy_run), "--out", "/proc/popsan/cmp.png"]
    assert _main(eval_cli, argv) == 2
    one_error(capsys.readouterr().err, "kernel filesystem")


def test_video_to_an_unwritable_path_blames_the_path(
    finished_toy_run, tmp_path, capsys, monkeypatch
):
    run = copy_run(finished_toy_run, tmp_path / "run")
    toy_env_everywhere(monkeypatch)
    # refused up front, before the evaluation's minutes of work
    assert _main(eval_cli, [str(run), *FAST, "--video", "/proc/popsan/v.mp4"]) == 2
    line = one_error(capsys.readouterr().err, "--video folder /proc/popsan")
    assert "GL" not in line and "OSMesa" not in line, line
    # a failure only the renderer meets (its folder becomes a file meanwhile) is a path error,
    # and the finished evaluation's report is written first
    out = tmp_path / "gone" / "v.mp4"
    out.parent.mkdir()
    real = report.render_video

    def vanish(model, qpos, path, **kw):
        shutil.rmtree(out.parent)
        out.parent.write_text("now a file")
        return real(model, qpos, path, backends=("osmesa",), **kw)

    monkeypatch.setattr(report, "render_video", vanish)
    assert _main(eval_cli, [str(run), *FAST, "--video", str(out)]) == 2
    line = one_error(capsys.readouterr().err)
    assert "GL" not in line and "OSMesa" not in line, line
    saved = json.loads((run / "eval_last.json").read_text())
    assert "video_error" in saved and saved["env_steps"] == 2 * STEPS
