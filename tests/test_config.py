"""RunConfig, presets, the optimiser split, the checkpoint manifest and train.py's flag errors.

Everything here is cheap: no env is compiled.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import signal
import time
from pathlib import Path

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.agents.ppo import losses as ppo_losses

import envs
from popsan_jax.config import POPSAN_DEFAULTS, PRESETS, RunConfig, resolve_config
from popsan_jax.errors import CheckpointError, ConfigError
from popsan_jax.training import checkpoint
from popsan_jax.training.iteration import make_optimizer

ROOT = Path(__file__).resolve().parent.parent


def load_train_cli():
    """train.py lives at the repo root (not a package); load it by path."""
    spec = importlib.util.spec_from_file_location("train_cli", ROOT / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


train_cli = load_train_cli()


def test_derived_sizes_hand_computed():
    c = RunConfig(
        num_envs=64,
        batch_size=32,
        num_minibatches=8,
        unroll_length=10,
        total_env_steps=100_000,
        num_evals=3,
    )
    assert c.sequences_per_iteration == 256
    assert c.unrolls_per_iteration == 4
    assert c.env_steps_per_iteration == 2560
    assert c.num_iterations == 40  # ceil(100000 / 2560) = ceil(39.06)
    assert c.eval_interval == 13


def test_precedence_backend_then_preset_then_flags():
    cpu = resolve_config(None, "cpu")
    assert cpu.num_envs == 256 and cpu.actor == "popsan"
    assert cpu.actor_kwargs == POPSAN_DEFAULTS
    gpu = resolve_config(None, "gpu")
    assert gpu.num_envs >= 1024
    smoke = resolve_config("smoke", "gpu")
    assert smoke.num_envs == PRESETS["smoke"]["num_envs"]
    flagged = resolve_config("smoke", "cpu", {"num_envs": 64, "seed": None}, {"timesteps": 3})
    assert flagged.num_envs == 64 and flagged.seed == 0
    assert flagged.actor_kwargs["timesteps"] == 3
    assert flagged.actor_kwargs["hidden_sizes"] == (256, 256)
    mlp = resolve_config(None, "cpu", {"actor": "mlp"}, {"hidden_sizes": (32, 32)})
    assert mlp.actor_kwargs == {"hidden_sizes": (32, 32)}


def test_every_preset_and_backend_default_is_valid():
    for backend in ("cpu", "gpu"):
        for preset in (None, *PRESETS):
            resolve_config(preset, backend).validate(1)


def test_paper_preset_is_the_committed_pick_run_that_learned():
    # `--preset paper` must reproduce docs/results/pick_scale/popsan-s0 (95.5 % success): the
    # same RunConfig, its env override (action_scale 2.0) being franka_pick's default now.
    run_dir = ROOT / "docs/results/pick_scale/popsan-s0"
    committed = RunConfig.from_json(run_dir / "config.json")
    overrides = dict(committed.env_overrides)
    env_defaults = envs.default_config("franka_pick")
    assert all(env_defaults[k] == v for k, v in overrides.items()), overrides
    for backend in ("cpu", "gpu"):
        paper = resolve_config("paper", backend, dict(seed=committed.seed))
        assert paper == committed.replace(env_overrides={}), backend


def test_documented_t2_fine_tune_is_the_committed_run():
    # docs/results.md's fine-tune command (T = 2 under a spike budget, the energy result) must
    # resolve to the committed t2-s0 config, whose checkpoint is committed beside it.
    committed = RunConfig.from_json(ROOT / "docs/results/pick_sop/t2-s0/config.json")
    flags = dict(
        init_from="runs/pick_scale/popsan-s0",
        sop_cost=0.01,
        sop_budget=30000.0,
        actor_lr=1e-4,
        seed=0,
        total_env_steps=4_000_000,
        num_evals=16,
    )
    for backend in ("cpu", "gpu"):
        assert resolve_config("paper", backend, flags, {"timesteps": 2}) == committed, backend


@pytest.mark.parametrize(
    "kwargs, actor_kwargs, match",
    [
        ({"actor": "lstm"}, {}, "unknown actor 'lstm'"),
        ({"actor": "mlp"}, {"timesteps": 3}, "does not take timesteps"),
        ({}, {}, None),
    ],
)
def test_resolve_errors(kwargs, actor_kwargs, match):
    if match is None:
        resolve_config(None, "cpu", kwargs, actor_kwargs)
        return
    with pytest.raises(ConfigError, match=match):
        resolve_config(None, "cpu", kwargs, actor_kwargs)


def test_validate_messages():
    with pytest.raises(ConfigError, match=r"100 \* 3 = 300 must be divisible by num_envs = 64"):
        RunConfig(num_envs=64, batch_size=100, num_minibatches=3).validate()
    with pytest.raises(ConfigError, match="divisible by the 3 local devices"):
        RunConfig(num_envs=64, batch_size=64, num_minibatches=1).validate(3)
    with pytest.raises(ConfigError, match="unroll_length must be >= 1"):
        RunConfig(unroll_length=0).validate()
    with pytest.raises(ConfigError, match="unknown preset"):
        resolve_config("huge")


def test_json_round_trip_keeps_tuples(tmp_path):
    c = resolve_config("smoke", "cpu", {"env_overrides": {"episode_length": 50}}, {"timesteps": 2})
    c.to_json(tmp_path / "config.json")
    back = RunConfig.from_json(tmp_path / "config.json")
    assert back == c
    assert isinstance(back.actor_kwargs["hidden_sizes"], tuple)
    (tmp_path / "bad.json").write_text(json.dumps({"num_envs": 4, "warp_speed": 9}))
    with pytest.raises(ConfigError, match="unknown config keys: warp_speed"):
        RunConfig.from_json(tmp_path / "bad.json")


def test_optimizer_uses_separate_actor_and_critic_learning_rates():
    # Adam's first step is -lr * sign(grad) (bias-corrected m/sqrt(v) = +-1), so each group's
    # step size reveals its learning rate.
    c = RunConfig(actor_lr=1e-5, critic_lr=1e-4, max_grad_norm=None)
    params = ppo_losses.PPONetworkParams(policy={"w": jnp.ones(3)}, value={"w": jnp.ones(2)})
    grads = ppo_losses.PPONetworkParams(
        policy={"w": jnp.array([0.5, -2.0, 3.0])}, value={"w": jnp.array([-1.0, 4.0])}
    )
    opt = make_optimizer(c)
    updates, _ = opt.update(grads, opt.init(params), params)
    np.testing.assert_allclose(updates.policy["w"], [-1e-5, 1e-5, -1e-5], rtol=1e-3)
    np.testing.assert_allclose(updates.value["w"], [1e-4, -1e-4], rtol=1e-3)


@flax.struct.dataclass
class _FakeState:
    w: jax.Array
    env_steps: jax.Array


def test_manifest_keeps_every_nth_last_and_best(tmp_path):
    successes = [0.1, 0.9, 0.2, 0.3, 0.1]
    for i, s in enumerate(successes, start=1):
        state = _FakeState(w=jnp.full((2,), float(i)), env_steps=jnp.int32(100 * i))
        checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(i), i, s, 2)
    index = checkpoint.read_index(tmp_path)
    # every 2nd eval (2, 4), the best (eval 2, success 0.9) and the last (eval 5)
    assert [e["step"] for e in index["checkpoints"]] == [200, 400, 500]
    assert index["last"] == 500 and index["best"] == 200
    on_disk = sorted(p.name for p in (tmp_path / "checkpoints").iterdir() if p.is_dir())
    assert on_disk == ["step_000000000200", "step_000000000400", "step_000000000500"]
    template = _FakeState(w=jnp.zeros(2), env_steps=jnp.int32(0))
    state, key, entry = checkpoint.restore_checkpoint(tmp_path, template, "best")
    np.testing.assert_array_equal(state.w, [2.0, 2.0])
    np.testing.assert_array_equal(key, jax.random.PRNGKey(2))
    assert entry["success_rate"] == 0.9
    with pytest.raises(CheckpointError, match="no checkpoint at step 300"):
        checkpoint.restore_checkpoint(tmp_path, template, 300)


def test_missing_and_corrupt_checkpoints_raise_checkpoint_error(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        checkpoint.read_index(tmp_path / "nope")
    with pytest.raises(CheckpointError, match="no checkpoint in"):
        checkpoint.read_index(tmp_path)
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "index.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="corrupt checkpoint index"):
        checkpoint.read_index(tmp_path)
    state = _FakeState(w=jnp.ones(2), env_steps=jnp.int32(7))
    (tmp_path / "checkpoints" / "index.json").unlink()
    path = checkpoint.save_checkpoint(tmp_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    for f in path.rglob("*"):
        if f.is_file() and f.stat().st_size > 0 and "manifest" in f.name:
            f.write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="cannot restore checkpoint"):
        checkpoint.restore_checkpoint(tmp_path, state, "last")
    wrong_shape = _FakeState(w=jnp.ones(3), env_steps=jnp.int32(0))
    shutil_path = tmp_path / "other"
    checkpoint.save_checkpoint(shutil_path, state, jax.random.PRNGKey(0), 1, 0.0, 1)
    with pytest.raises(CheckpointError, match="cannot restore checkpoint"):
        checkpoint.restore_checkpoint(shutil_path, wrong_shape, "last")


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--actor", "lstm"], "error: unknown actor 'lstm'"),
        (["--env", "franka_fly"], "error: unknown env 'franka_fly'"),
        (
            ["--batch-size", "30", "--num-minibatches", "3", "--num-envs", "64"],
            "must be divisible by num_envs = 64",
        ),
        (["--resume", "{tmp}/missing"], "error: run directory .*missing does not exist"),
        (["--resume", "{tmp}", "--num-envs", "8"], "cannot change num_envs when resuming"),
        (["--preset", "tiny"], "error: unknown preset 'tiny'"),
        (["--init-from", "{tmp}/missing"], "error: run directory .*missing does not exist"),
        (["--init-checkpoint", "newest"], "init_checkpoint must be 'best', 'last' or an env-step"),
        (["--sop-cost", "-1"], "sop_cost and sop_budget must be >= 0"),
        (["--actor", "mlp", "--sop-cost", "1"], "the 'mlp' actor has none"),
        (["--wandb"], "error: --wandb needs the wandb package"),
    ],
)
def test_cli_errors_exit_2_with_one_line_and_write_nothing(argv, match, tmp_path, capsys):
    if "--wandb" in argv and importlib.util.find_spec("wandb") is not None:
        pytest.skip("wandb is installed here")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    runs = tmp_path / "runs"
    code = train_cli.main(
        ["--runs-dir", str(runs), "--preset", "smoke", *argv]
        if "--preset" not in argv and "--resume" not in argv
        else ["--runs-dir", str(runs), *argv]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("error: ")
    assert re.search(match, err[-1]), err[-1]
    assert not runs.exists()


@pytest.mark.parametrize(
    "signum, checkpointed",
    [(signal.SIGINT, True), (signal.SIGTERM, True), (signal.SIGTERM, False)],
)
def test_sigint_even_if_ignored_and_sigterm_stop_like_ctrl_c(
    signum, checkpointed, tmp_path, capsys, monkeypatch
):
    from popsan_jax.training import loop as ppo
    from popsan_jax.training.checkpoint import INDEX, checkpoint_dir

    def killed_mid_training(config, run_dir, **_):
        if checkpointed:  # the index of a run with one checkpoint saved
            checkpoint_dir(run_dir).mkdir(parents=True)
            entry = {"step": 1, "eval_index": 0, "success_rate": 0.0, "dir": "step_1"}
            index = {"checkpoints": [entry], "last": 1, "best": 1}
            (checkpoint_dir(run_dir) / INDEX).write_text(json.dumps(index))
        os.kill(os.getpid(), signum)
        time.sleep(5)  # the handler raises before this returns
        raise AssertionError("the signal did not stop the run")

    monkeypatch.setattr(ppo, "train", killed_mid_training)
    ignored = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a `cmd &` job of a script gets
    try:
        code = train_cli.main(["--preset", "smoke", "--runs-dir", str(tmp_path), "--name", "r"])
        # main restores the handlers it found
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, ignored)
    assert code == 130
    last = capsys.readouterr().err.strip().splitlines()[-1]
    if checkpointed:
        assert last.startswith("interrupted; the last checkpoint is kept; resume with:"), last
    else:
        assert (
            last
            == f"interrupted before the first checkpoint; {tmp_path / 'r'} has nothing to resume"
        )


def test_env_override_argument_and_file_tag():
    from popsan_jax.cli import env_override, overrides_tag

    assert env_override("grasp_radius=0.0") == ("grasp_radius", 0.0)
    assert env_override("object_x_range=[0.45, 0.55]") == ("object_x_range", [0.45, 0.55])
    assert env_override("name=plain text") == ("name", "plain text")
    for bad in ("no_equals", "=1"):
        with pytest.raises(argparse.ArgumentTypeError, match="KEY=VALUE"):
            env_override(bad)
    assert overrides_tag({}) == ""
    tag = overrides_tag({"grasp_radius": 0.0, "object_x_range": [0.45, 0.55], "a/b": "x y"})
    assert tag == "+grasp_radius=0.0+object_x_range=0.45,0.55+ab=xy"
