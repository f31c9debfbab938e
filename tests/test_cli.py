"""The entry points' flags (derived from RunConfig), signal handling, and the entry points
themselves run as a user runs them: bad input is one ``error:`` line and exit status 2."""

from __future__ import annotations

import argparse
import gc
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from _run_fixtures import load_script

from popsan_jax import cli
from popsan_jax.config import RunConfig
from popsan_jax.training import run

ROOT = Path(__file__).resolve().parent.parent
eval_cli = load_script("eval")

# train.py's config flags before they were derived from RunConfig (the hand-written table),
# and the warm-up, priming, critic warm-up, frozen-normaliser and guard flags since.
HAND_TABLE = """env actor seed num_envs total_env_steps episode_length unroll_length batch_size
num_minibatches num_updates_per_batch actor_lr critic_lr lr_schedule max_grad_norm entropy_cost
discounting gae_lambda clipping_epsilon reward_scaling obs_clip init_log_std critic_hidden_sizes
sop_cost sop_budget init_from init_checkpoint num_evals num_eval_envs keep_every_n_evals
warmup_env_steps warmup_actor_lr warmup_num_evals prime_normalizer_episodes
critic_warmup_env_steps freeze_normalizer end_at_success warmup_end_at_success clip_per_network
max_kl warmup_clip_per_network""".split()


def test_config_flags_are_the_run_config_fields_with_their_types():
    flags = cli.config_flags()
    assert sorted(flags) == sorted(HAND_TABLE)
    assert all(help_text for _, help_text in flags.values())
    args = cli.train_parser().parse_args(
        "--critic-hidden-sizes 64,32 --episode-length 50 --max-grad-norm 0.5 --init-from r "
        "--actor-lr 1e-4 --timesteps 2 --hidden-sizes 8,8".split()
    )
    given, actor = cli.given_flags(args)
    assert given == dict(
        critic_hidden_sizes=(64, 32), episode_length=50, max_grad_norm=0.5, init_from="r",
        actor_lr=1e-4,
    )  # fmt: skip
    assert actor == {"timesteps": 2, "hidden_sizes": (8, 8)}
    # Every given value builds a valid RunConfig field of the same type.
    config = RunConfig(**given)
    assert config.critic_hidden_sizes == (64, 32) and config.episode_length == 50
    assert cli.given_flags(cli.train_parser().parse_args([])) == ({}, {})
    # A bool field reads its words (argparse's bool('false') would be True).
    for word, value in (("false", False), ("true", True), ("No", False), ("1", True)):
        args = cli.train_parser().parse_args(["--freeze-normalizer", word])
        assert cli.given_flags(args)[0] == {"freeze_normalizer": value}


@pytest.mark.parametrize(
    "argv", [["--num-envs", "many"], ["--hidden-sizes", "0,4"], ["--freeze-normalizer", "maybe"]]
)
def test_train_flag_type_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.train_parser().parse_args(argv)
    assert exc.value.code == 2


def test_eval_flags():
    args = cli.eval_parser().parse_args(["run", "--timesteps", "1,3", "--best"])
    assert args.energy_timesteps == (1, 3) and args.best and args.run_dir == "run"
    assert cli.eval_parser().parse_args(["run"]).energy_timesteps == (1, 2, 3, 4, 5)
    for argv in (
        ["run", "--energy-timesteps", "0,x"],
        ["run", "--no-such-flag"],
        ["run", "--env-override", "no_equals_sign"],
        ["run", "--all-checkpoints", "--best"],  # one of --best / --step / --all-checkpoints
    ):
        with pytest.raises(SystemExit) as exc:
            cli.eval_parser().parse_args(argv)
        assert exc.value.code == 2


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_sigint_even_if_ignored_and_sigterm_stop_like_ctrl_c(signum):
    ignored = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a `cmd &` job of a script gets
    try:
        with pytest.raises(KeyboardInterrupt):
            with cli.stop_on_signals():
                signal.raise_signal(signum)  # to this thread: os.kill may reach another one
                time.sleep(5)  # the handler raises before this returns
                raise AssertionError("the signal did not stop the run")
        # the handlers found are restored
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    finally:
        signal.signal(signal.SIGINT, ignored)


def test_a_stop_dropped_in_a_gc_callback_is_raised_at_the_next_iteration(monkeypatch):
    """Python drops an exception raised inside a garbage-collector callback (JAX registers
    one): a SIGINT handled there would be lost. train.py's per-iteration hook and eval.py's
    progress lines raise it again."""
    fired = []

    def once(action):  # a gc callback that acts at the start of one collection, then never
        def callback(phase, info):
            if phase == "start" and not fired.count(action):
                fired.append(action)
                action()

        return callback

    def interrupt():
        # raise_signal reaches this thread before it returns; os.kill(getpid()) can land on
        # one of JAX's threads and reach this one only after the callback has ended
        signal.raise_signal(signal.SIGINT)
        for _ in range(10_000):  # the handler runs at a bytecode boundary: in here
            pass

    reported = []
    monkeypatch.setattr(sys, "unraisablehook", lambda report: reported.append(report))
    callbacks = [once(interrupt), once(lambda: 1 / 0)]  # others are reported as before
    with cli.stop_on_signals():
        # armed only inside: an automatic collection can start at any allocation
        gc.callbacks.append(callbacks[0])
        try:
            gc.collect()  # its KeyboardInterrupt is raised in the callback and dropped
            assert fired == [interrupt]  # the signal was sent, and this line still runs
            with pytest.raises(KeyboardInterrupt):
                cli.raise_if_stop_requested()
            with pytest.raises(KeyboardInterrupt):  # eval.py stops at its next progress line
                eval_cli.say("energy sweep")
            gc.callbacks.append(callbacks[1])
            gc.collect()
        finally:
            for callback in callbacks:
                if callback in gc.callbacks:
                    gc.callbacks.remove(callback)
    assert [type(r.exc_value) for r in reported] == [ZeroDivisionError]  # no traceback printed
    cli.raise_if_stop_requested()  # the stop ended with its block
    with cli.stop_on_signals():
        cli.raise_if_stop_requested()  # a new run starts without a stop


def test_env_override_argument_and_file_tag():
    env_override, overrides_tag = cli.env_override, cli.overrides_tag
    assert env_override("grasp_radius=0.0") == ("grasp_radius", 0.0)
    assert env_override("object_x_range=[0.45, 0.55]") == ("object_x_range", [0.45, 0.55])
    assert env_override("name=plain text") == ("name", "plain text")
    for bad in ("no_equals", "=1"):
        with pytest.raises(argparse.ArgumentTypeError, match="KEY=VALUE"):
            env_override(bad)
    assert overrides_tag({}) == ""
    tag = overrides_tag({"grasp_radius": 0.0, "object_x_range": [0.45, 0.55], "a/b": "x y"})
    assert tag == "+grasp_radius=0.0+object_x_range=0.45,0.55+ab=xy"


@pytest.mark.parametrize(
    "argv, match",
    [
        (["train.py", "--preset", "tiny"], "error: unknown preset 'tiny'"),
        (["eval.py", "{tmp}/missing", "--no-latency"], "error: run directory .*missing"),
        (["eval.py", "--compare", "{tmp}"], "error: .* has no metrics.jsonl"),
    ],
)
def test_entry_points_exit_2_with_one_error_line(argv, match, tmp_path):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    runs = tmp_path / "runs"
    extra = ["--runs-dir", str(runs)] if argv[0] == "train.py" else []
    proc = subprocess.run(
        [sys.executable, *argv, *extra], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 2, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert re.search(match, last), last
    assert not runs.exists()


def test_done_line_of_each_process():
    """Only process 0 evaluates: the others name themselves and point there, not at NaN."""
    state = SimpleNamespace(env_steps=1280)
    main = SimpleNamespace(state=state, finished=False, last_eval={"success_rate": 0.25})
    other = SimpleNamespace(state=state, finished=False, last_eval=None)
    run_dir = Path("runs/r")
    assert (
        run.done_message(main, run_dir, 0, 2)
        == "done: 1280 env steps, success rate 0.250 -> runs/r"
    )
    for result in (other, SimpleNamespace(state=state, finished=True, ended=False, last_eval=None)):
        line = run.done_message(result, run_dir, 1, 2)
        assert (
            line == "done: process 1 of 2 (1280 env steps); process 0 holds the results -> runs/r"
        )
    assert "already finished at 1280" in run.done_message(
        SimpleNamespace(state=state, finished=True, ended=False, last_eval=None), run_dir, 0, 1
    )
    ended = SimpleNamespace(state=state, finished=True, ended=True, last_eval=None)
    assert run.done_message(ended, run_dir, 0, 1) == (
        "done: runs/r already ended at 1280 env steps (an evaluation reached its "
        "end_at_success); to train it on: python train.py --resume runs/r --end-at-success 0"
    )


@pytest.mark.slow
def test_train_py_stops_on_an_ignored_sigint_with_exit_130(tmp_path):
    """A `cmd &` job of a script starts with SIGINT ignored; train.py still stops on it."""
    proc = subprocess.Popen(
        [sys.executable, "train.py", "--env", "franka_reach", "--preset", "smoke"]
        + ["--runs-dir", str(tmp_path), "--name", "r", "--no-progress"],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        for line in proc.stderr:
            if line.startswith("compiling:"):
                break
        proc.send_signal(signal.SIGINT)
        rest = proc.stderr.read()
        assert proc.wait(timeout=300) == 130
    finally:
        proc.kill()
    last = rest.strip().splitlines()[-1]
    assert last == (
        f"interrupted before the first checkpoint; train it again from step 0 with: "
        f"python train.py --resume {tmp_path / 'r'}"
    )
