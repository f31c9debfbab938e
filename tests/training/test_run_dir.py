"""A run directory cannot be turned against its user (issue 22, items 1, 3, 4, 5, 7): contained
checkpoint paths, plain --name, one writer, clean signals, and resume that keeps its promises."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import flax.struct
import jax
import jax.numpy as jnp
import pytest
from _run_fixtures import ROOT, STEPS, copy_run, load_script, toy_env_everywhere
from _toy_env import PointPick, tiny_config

from popsan_jax.errors import CheckpointError, ConfigError, NonFiniteError, UserError
from popsan_jax.training import checkpoint, checkpoint_index
from popsan_jax.training.loop import train
from popsan_jax.training.run_log import read_metrics


def _run_dir_lib():
    from popsan_jax.training import run_dir  # new with issue 22: imported where it is used

    return run_dir


def check_name(name):
    return _run_dir_lib().check_name(name)


def contained(root, name):
    return _run_dir_lib().contained(root, name)


@pytest.mark.parametrize("name", ["../x", "/abs", "a/b", "..", ".", "", "a\nb", "x" * 201])
def test_check_name_refuses_non_plain(name):
    with pytest.raises(ConfigError, match="plain directory name"):
        check_name(name)


@pytest.mark.parametrize("name", ["a/b", "../x", "/tmp/abs-run"])
def test_train_py_refuses_a_name_that_is_not_plain(name, tmp_path, capsys, monkeypatch):
    from popsan_jax.training import loop

    monkeypatch.setattr(loop, "build_trainer", lambda *a: pytest.fail("went on to train"))
    runs = tmp_path / "runs"
    assert (
        load_script("train").main(["--preset", "smoke", "--runs-dir", str(runs), "--name", name])
        == 2
    )
    assert "error: --name must be a plain directory name" in capsys.readouterr().err
    assert not runs.exists() and not (tmp_path / "x").exists()


@pytest.mark.parametrize("name", ["run1", "pick-popsan-s0", "a.b+c=d,e_f"])
def test_check_name_accepts_plain(name):
    assert check_name(name) == name


def test_contained_accepts_own_pattern(tmp_path):
    (tmp_path / "step_000000000100").mkdir()
    assert contained(tmp_path, "step_000000000100") == tmp_path / "step_000000000100"


@pytest.mark.parametrize("name", ["../step_000000000100", "/etc", "step_1", None, 5, "x"])
def test_contained_refuses_other_names(tmp_path, name):
    with pytest.raises(CheckpointError, match="not a checkpoint name"):
        contained(tmp_path, name)


def test_contained_refuses_link_outside(tmp_path):
    root = tmp_path / "checkpoints"
    root.mkdir()
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", root / "step_000000000100")
    with pytest.raises(CheckpointError, match="resolves outside"):
        contained(root, "step_000000000100")


# ---- containment end to end (issue 22, item 1) --------------------------------------------
@flax.struct.dataclass
class _State:
    w: jax.Array
    env_steps: jax.Array


def _saved(run, n: int = 1):
    for i in range(1, n + 1):
        state = _State(w=jnp.full((2,), float(i)), env_steps=jnp.int32(100 * i))
        checkpoint.save_checkpoint(run, state, jax.random.PRNGKey(i), i, 0.1 * i, 1)
    return run


@pytest.mark.parametrize("crafted", ["{victim}", "../../victim", "step_000000000100/../../victim"])
def test_crafted_index_dir_deletes_and_loads_nothing_outside(tmp_path, crafted):
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.txt").write_text("keep me")
    run = _saved(tmp_path / "run")
    index_path = run / "checkpoints" / "index.json"
    index = json.loads(index_path.read_text())
    # An entry that the next save prunes (eval_index 3 is not kept with keep_every_n_evals=2).
    entry = dict(step=50, eval_index=3, success_rate=0.0, dir=crafted.format(victim=victim))
    index["checkpoints"].append(entry)
    index_path.write_text(json.dumps(index))
    state = _State(w=jnp.zeros(2), env_steps=jnp.int32(300))
    with pytest.raises(CheckpointError, match="not a checkpoint name"):
        checkpoint.restore_checkpoint(run, state, 50)
    checkpoint.save_checkpoint(run, state, jax.random.PRNGKey(0), 4, 0.0, 2)
    assert (victim / "precious.txt").read_text() == "keep me"
    assert [e["step"] for e in checkpoint_index.read_index(run)["checkpoints"]] == [100, 300]


# ---- one writer (item 4) -------------------------------------------------------------------
def test_lock_is_held_while_training_and_released(tmp_path):
    seen = []
    run = tmp_path / "r"

    def look(steps, metrics):
        seen.append(json.loads((run / "lock").read_text()))

    train(tiny_config(total_env_steps=STEPS), run, environment=PointPick(), progress=False,
          on_iteration=look)  # fmt: skip
    assert seen and seen[0]["pid"] == os.getpid() and seen[0]["host"] == socket.gethostname()
    assert not (run / "lock").exists()


def test_second_trainer_is_refused_naming_the_holder(finished_toy_run, tmp_path):
    run = copy_run(finished_toy_run, tmp_path / "run")
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = dict(pid=holder.pid, host=socket.gethostname(), since=time.time())
        (run / "lock").write_text(json.dumps(lock))
        before = (run / "metrics.jsonl").read_text()
        more = tiny_config(total_env_steps=3 * STEPS)
        with pytest.raises(UserError, match=f"in use by PID {holder.pid} on host ") as err:
            train(more, run, resume=True, environment=PointPick(), progress=False)
        assert "\n" not in str(err.value)
    finally:
        holder.kill()
        holder.wait()
    assert checkpoint_index.read_index(run)["last"] == 2 * STEPS  # nothing written
    assert (run / "metrics.jsonl").read_text() == before
    assert json.loads((run / "lock").read_text())["pid"] == holder.pid


def test_stale_lock_is_taken_over_with_a_note(finished_toy_run, tmp_path, capsys):
    run = copy_run(finished_toy_run, tmp_path / "run")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    lock = dict(pid=dead.pid, host=socket.gethostname(), since=time.time())
    (run / "lock").write_text(json.dumps(lock))
    more = tiny_config(total_env_steps=3 * STEPS)
    out = train(more, run, resume=True, environment=PointPick(), progress=False)
    assert int(out.state.env_steps) == 3 * STEPS
    assert f"taking over the stale lock of PID {dead.pid}" in capsys.readouterr().err
    assert not (run / "lock").exists()


# ---- signals during a checkpoint write (item 3) -----------------------------------------
_SIGNAL_CHILD = """
import os, sys
sys.path.insert(0, {tests!r})
from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly
import_mjx_quietly()
enable_compilation_cache()
from orbax.checkpoint import StandardCheckpointHandler
from _run_fixtures import load_script
from _toy_env import PointPick
from popsan_jax.training import checkpoint, loop
loop.make_env = checkpoint.make_env = lambda config: PointPick()
original = StandardCheckpointHandler.async_save  # once per checkpoint, sync or async
calls = []
async def save_then_signal(self, *args, **kwargs):
    calls.append(1)
    if len(calls) == 1:  # in the middle of the resumed run's first checkpoint write
        os.kill(os.getpid(), {signum})
    return await original(self, *args, **kwargs)
StandardCheckpointHandler.async_save = save_then_signal
argv = ["--resume", {run!r}, "--total-env-steps", {total!r}, "--no-progress"]
sys.exit(load_script("train").main(argv))
"""


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_checkpoint_write_finishes_it_and_exits_130(
    finished_toy_run, tmp_path, signum
):
    # Resumed to 6 iterations with 2 evaluations: checkpoints after iterations 3 and 6.
    run = copy_run(finished_toy_run, tmp_path / "run")
    total = str(6 * STEPS)
    code = _SIGNAL_CHILD.format(
        tests=str(ROOT / "tests"), signum=int(signum), run=str(run), total=total
    )
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.count("interrupted") == 1, proc.stderr[-3000:]
    assert time.monotonic() - t0 < 200
    index = checkpoint_index.read_index(run)
    assert index["last"] == 3 * STEPS  # the write under way when the signal came is complete
    assert checkpoint.load_run(run, environment=PointPick()).step == 3 * STEPS
    assert not (run / "lock").exists()


def test_deferred_signals_hold_an_interrupt_until_the_write_is_done():
    from popsan_jax.cli import stop_on_signals
    from popsan_jax.training.run_dir import deferred_signals

    done = []
    with stop_on_signals(), pytest.raises(KeyboardInterrupt):
        with deferred_signals():
            signal.raise_signal(signal.SIGTERM)  # to this thread, before it returns
            time.sleep(0.05)
            done.append("write complete")
    assert done == ["write complete"]


# ---- resume (items 5 and 7) --------------------------------------------------------------
train_cli = load_script("train")


def test_resume_persists_total_env_steps_before_training(finished_toy_run, tmp_path, monkeypatch):
    run = copy_run(finished_toy_run, tmp_path / "run")
    toy_env_everywhere(monkeypatch)

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save_checkpoint", killed)  # killed at the first save
    argv = ["--resume", str(run), "--total-env-steps", str(4 * STEPS), "--no-progress"]
    assert train_cli.main(argv) == 130
    assert json.loads((run / "config.json").read_text())["total_env_steps"] == 4 * STEPS


def test_resuming_a_finished_run_says_so(finished_toy_run, tmp_path, monkeypatch, capsys):
    run = copy_run(finished_toy_run, tmp_path / "run")
    toy_env_everywhere(monkeypatch)
    assert train_cli.main(["--resume", str(run), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert f"already finished at {2 * STEPS} env steps" in err, err
    assert "nan" not in err
    assert checkpoint_index.read_index(run)["last"] == 2 * STEPS


def test_run_killed_before_its_first_checkpoint_restarts(
    finished_toy_run, tmp_path, monkeypatch, capsys
):
    run = copy_run(finished_toy_run, tmp_path / "run")
    shutil.rmtree(run / "checkpoints")  # as if killed before the first save
    toy_env_everywhere(monkeypatch)
    assert train_cli.main(["--resume", str(run), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "no checkpoint yet; training it again from step 0" in err
    assert checkpoint_index.read_index(run)["last"] == 2 * STEPS
    evals = [r["env_steps"] for r in read_metrics(run, "eval")]
    assert evals == [0, STEPS, 2 * STEPS]  # the killed attempt's records are gone


class NaNReward(PointPick):
    def step(self, state, action):
        out = super().step(state, action)
        return out.replace(reward=out.reward * jnp.nan)


def test_nan_stop_without_a_checkpoint_says_there_is_none(tmp_path):
    with pytest.raises(NonFiniteError, match="has no checkpoint yet") as exc:
        train(tiny_config(), tmp_path / "r", environment=NaNReward(), progress=False)
    assert "last good checkpoint" not in str(exc.value)
