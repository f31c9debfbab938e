"""The PPO loop end to end on a tiny point-mass env: run directory, resume, NaN stop, SIGKILL,
two devices. The MJX learning tests are in test_train_learning.py."""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import PointPick, tiny_config
from brax.envs.wrappers import training as brax_training
from tensorboardX import SummaryWriter
from tensorboardX.proto import event_pb2

from popsan_jax.errors import NonFiniteError
from popsan_jax.networks import actor_variables, make_actor
from popsan_jax.rollout import make_episode_runner
from popsan_jax.training import checkpoint, checkpoint_index, evaluation, iteration
from popsan_jax.training.loop import train
from popsan_jax.training.run_log import read_metrics
from popsan_jax.training.setup import build_networks, make_optimizer

ROOT = Path(__file__).resolve().parents[2]
STEPS = 640  # env steps per iteration of tiny_config()
# Hang guards for child processes, not timings: a loaded 2-core box can take minutes to compile.
HANG_GUARD_S = 600


def _equal_trees(a, b) -> bool:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(np.array_equal(x, y) for x, y in zip(la, lb, strict=True))


def _adam_counts(opt_state) -> list[int]:
    return sorted({int(x) for x in jax.tree.leaves(opt_state) if jnp.issubdtype(x, jnp.integer)})


@pytest.fixture(scope="module")
def two_iteration_run(tmp_path_factory):
    """2 iterations, an eval + checkpoint after each (num_evals=2)."""
    run_dir = tmp_path_factory.mktemp("runs") / "tiny"
    config = tiny_config(total_env_steps=2 * STEPS)
    result = train(config, run_dir, environment=PointPick(), progress=False)
    return config, run_dir, result


def test_run_directory_contents(two_iteration_run):
    config, run_dir, result = two_iteration_run
    assert json.loads((run_dir / "config.json").read_text()) == json.loads(
        json.dumps(config.to_dict())
    )
    train = read_metrics(run_dir, "train")
    evals = read_metrics(run_dir, "eval")
    assert [r["env_steps"] for r in train] == [STEPS, 2 * STEPS]
    assert [r["env_steps"] for r in evals] == [0, STEPS, 2 * STEPS]  # 0: untrained baseline
    for r in train:
        for k in (
            "loss/total",
            "loss/policy",
            "loss/value",
            "loss/entropy",
            "entropy",
            "steps_per_s",
            "wall_s",
            "firing_rate/encoder",
            "firing_rate/hidden_0",
            "firing_rate/output",
        ):
            assert np.isfinite(r[k]), k
        assert 0.0 <= r["firing_rate/encoder"] <= 1.0
        # total = policy + value + entropy terms, as compute_ppo_loss defines it
        np.testing.assert_allclose(
            r["loss/total"], r["loss/policy"] + r["loss/value"] + r["loss/entropy"], rtol=1e-4
        )
    for r in evals:
        assert 0.0 <= r["success_rate"] <= 1.0
        assert r["episode_length"] == PointPick().config.episode_length  # never terminates early
        assert {"reward/distance", "reward/action_cost", "episode_reward", "steps_per_s"} <= set(r)
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))
    index = checkpoint_index.read_index(run_dir)
    assert index["last"] == 2 * STEPS
    assert int(result.state.env_steps) == 2 * STEPS
    # 2 iterations x 2 epochs x 4 minibatches of Adam steps
    assert _adam_counts(result.state.opt_state) == [16]


def test_evaluation_compiles_once_per_run(tmp_path, monkeypatch):
    """The step-0 evaluation gets the initial state (host arrays), later ones a pmapped
    state's first copy (committed device arrays): the runner must see one signature, since
    on franka_pick a second MJX rollout compile mid-run would repeat a costly compile."""
    runners = []

    def recording(*args, **kwargs):
        runners.append(make_episode_runner(*args, **kwargs))
        return runners[-1]

    monkeypatch.setattr(evaluation, "make_episode_runner", recording)
    train(
        tiny_config(total_env_steps=2 * STEPS),
        tmp_path / "run",
        environment=PointPick(),
        progress=False,
    )
    evals = [r for r in read_metrics(tmp_path / "run") if r["kind"] == "eval"]
    assert [r["env_steps"] for r in evals] == [0, STEPS, 2 * STEPS]
    assert len(runners) == 1 and runners[0]._cache_size() == 1


def test_load_run_rebuilds_the_saved_policy(two_iteration_run):
    config, run_dir, result = two_iteration_run
    loaded = checkpoint.load_run(run_dir, "last", environment=PointPick())
    assert loaded.step == 2 * STEPS and loaded.config == config
    assert _equal_trees(loaded.policy_params, result.state.params.policy)
    assert _equal_trees(loaded.value_params, result.state.params.value)
    obs = jax.random.normal(jax.random.PRNGKey(3), (5, PointPick().observation_size))
    action = loaded.make_policy()(obs, jax.random.PRNGKey(0))
    # deterministic action == the actor's mean on the clipped, normalised observation
    norm = loaded.normalizer_params
    x = jnp.clip((obs - norm.mean) / norm.std, -config.obs_clip, config.obs_clip)
    actor = make_actor("popsan", config.actor_kwargs, PointPick().action_size)
    mean = actor.apply(actor_variables(loaded.policy_params), x)
    np.testing.assert_allclose(action, mean, rtol=1e-5, atol=1e-6)
    noisy = loaded.make_policy(deterministic=False)(obs, jax.random.PRNGKey(0))
    assert not np.allclose(noisy, action)


def test_resume_restores_state_and_continues_step_count(two_iteration_run, tmp_path):
    config, run_dir, result = two_iteration_run
    resumed_dir = tmp_path / "resumed"
    shutil.copytree(run_dir, resumed_dir)
    template = iteration.init_training_state(
        config, *_nets_and_opt(config), PointPick().observation_size, jax.random.PRNGKey(9)
    )
    restored, key, _ = checkpoint.restore_checkpoint(resumed_dir, template, "last")
    assert _equal_trees(restored.params, result.state.params)
    assert _equal_trees(restored.opt_state, result.state.opt_state)
    assert _equal_trees(restored.normalizer_params, result.state.normalizer_params)
    np.testing.assert_array_equal(key, result.key)
    # As if the run had logged one more iteration, and half a line, before it was killed: the
    # resumed run redoes that step, so those records must not stay behind as duplicates.
    with open(resumed_dir / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"kind": "train", "env_steps": 3 * STEPS, "stale": True}) + "\n")
        f.write('{"kind": "train", "env_st')
    with SummaryWriter(str(resumed_dir / "tb"), filename_suffix=".killed") as tb:
        tb.add_scalar("train/entropy", 123.0, 3 * STEPS)
    more = config.replace(total_env_steps=4 * STEPS)
    out = train(more, resumed_dir, resume=True, environment=PointPick(), progress=False)
    records = read_metrics(resumed_dir, "train")
    assert [r["env_steps"] for r in records] == [STEPS, 2 * STEPS, 3 * STEPS, 4 * STEPS]
    assert not any(r.get("stale") for r in records)
    entropy = _tensorboard_points(resumed_dir / "tb", "train/entropy")
    assert [s for s, _ in entropy] == [STEPS, 2 * STEPS, 3 * STEPS, 4 * STEPS]
    assert 123.0 not in [v for _, v in entropy]
    # the optimiser state continued: 4 iterations' worth of Adam steps, not 2
    assert _adam_counts(out.state.opt_state) == [32]
    assert checkpoint_index.read_index(resumed_dir)["last"] == 4 * STEPS


def test_stagger_spreads_episode_phases():
    """Env e of a fresh batch takes n_e steps of the policy, n_e spread over [0, L): checked on
    the episode counter Brax's wrapper keeps, and on how far each hand can have moved."""
    length, n = 12, 64
    wrapped = brax_training.wrap(PointPick(episode_length=length), episode_length=length)
    start = wrapped.reset(jax.random.split(jax.random.PRNGKey(0), n))

    def policy(reach, obs, key):
        return reach * jax.random.uniform(key, (obs.shape[0], 3), minval=-1.0, maxval=1.0), {}

    stagger = iteration.stagger_episodes
    out = jax.jit(lambda s, k: stagger(wrapped, s, policy, jnp.float32(1.0), k, length))(
        start, jax.random.PRNGKey(1)
    )
    steps = np.asarray(out.info["steps"]).astype(int)
    assert steps.min() >= 0 and steps.max() <= length - 1
    assert len(set(steps.tolist())) >= length - 2  # 64 draws over 12 phases, not all at 0
    assert not np.any(out.done) and not np.any(out.info["truncation"])
    moved = np.linalg.norm(np.asarray(out.obs[:, :3] - start.obs[:, :3]), axis=1)
    np.testing.assert_array_equal(moved[steps == 0], 0.0)
    assert np.all(moved[steps > 0] > 0)
    assert np.all(moved <= 0.1 * np.sqrt(3) * steps + 1e-6)  # |action| <= 1 per axis, 0.1 m/step
    np.testing.assert_array_equal(out.info["object_pos"], start.info["object_pos"])


def _tensorboard_points(tb_dir, tag: str) -> list[tuple[int, float]]:
    """(step, value) points of ``tag`` as TensorBoard shows them: events files in write order,
    where a SessionLog START at step S hides the points written before it at steps >= S."""
    points: list[tuple[int, float]] = []
    for path in sorted(tb_dir.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime_ns):
        data = path.read_bytes()
        pos = 0
        while pos < len(data):  # TFRecord: u64 length, u32 crc, payload, u32 crc
            (length,) = struct.unpack("<Q", data[pos : pos + 8])
            event = event_pb2.Event.FromString(data[pos + 12 : pos + 12 + length])
            pos += 12 + length + 4
            if event.session_log.status == event_pb2.SessionLog.START:
                points = [(s, v) for s, v in points if s < event.step]
            for value in event.summary.value:
                if value.tag == tag:
                    points.append((event.step, value.simple_value))
    return points


def _nets_and_opt(config):
    env = PointPick()
    return (
        build_networks(config, env.observation_size, env.action_size),
        make_optimizer(config),
    )


class NaNReward(PointPick):
    """Every reward is NaN, so the first loss after resuming is NaN."""

    def step(self, state, action):
        out = super().step(state, action)
        return out.replace(reward=out.reward * jnp.nan)


def test_nan_stops_with_step_and_keeps_last_good_checkpoint(two_iteration_run, tmp_path):
    config, run_dir, result = two_iteration_run
    nan_dir = tmp_path / "nan"
    shutil.copytree(run_dir, nan_dir)
    more = config.replace(total_env_steps=4 * STEPS)
    with pytest.raises(NonFiniteError, match=f"at env step {3 * STEPS}"):
        train(more, nan_dir, resume=True, environment=NaNReward(), progress=False)
    assert checkpoint_index.read_index(nan_dir)["last"] == 2 * STEPS
    loaded = checkpoint.load_run(nan_dir, environment=PointPick())
    assert _equal_trees(loaded.policy_params, result.state.params.policy)


_CHILD = """
import sys
sys.path.insert(0, {tests!r})
from popsan_jax.jax_setup import enable_compilation_cache
enable_compilation_cache()
from _toy_env import PointPick, tiny_config
from tensorboardX import SummaryWriter
from tensorboardX.proto import event_pb2
from popsan_jax.training.loop import train
config = tiny_config(num_envs={num_envs}, batch_size={num_envs}, total_env_steps={total},
                     num_evals={evals})
train(config, {run_dir!r}, environment=PointPick(), progress=False,
          on_iteration=lambda s, m: print("step", s, flush=True))
print("finished", flush=True)
"""


def _child(run_dir: Path, total: int, evals: int, num_envs: int = 16, devices: int = 1):
    env = dict(os.environ)
    if devices > 1:
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    code = _CHILD.format(
        tests=str(ROOT / "tests"), run_dir=str(run_dir), total=total, evals=evals, num_envs=num_envs
    )
    return subprocess.Popen(
        [sys.executable, "-c", code],
        env=env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.slow
def test_sigkill_mid_run_leaves_a_loadable_last_checkpoint(tmp_path):
    run_dir = tmp_path / "killed"
    # 200 iterations with a checkpoint after each: the kill lands while training/saving.
    proc = _child(run_dir, total=200 * STEPS, evals=200)
    index_path = run_dir / "checkpoints" / "index.json"
    deadline = time.monotonic() + HANG_GUARD_S
    while time.monotonic() < deadline and proc.poll() is None:
        if index_path.exists() and json.loads(index_path.read_text())["last"] >= 3 * STEPS:
            break
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()[1][-2000:]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    loaded = checkpoint.load_run(run_dir, environment=PointPick())
    last = checkpoint_index.read_index(run_dir)["last"]
    assert loaded.step == last >= 3 * STEPS
    out = train(
        tiny_config(total_env_steps=last + STEPS, num_evals=200),
        run_dir,
        resume=True,
        environment=PointPick(),
        progress=False,
    )
    assert int(out.state.env_steps) == last + STEPS


@pytest.mark.slow
def test_two_devices_shard_envs(tmp_path):
    run_dir = tmp_path / "two"
    proc = _child(run_dir, total=2 * STEPS, evals=1, devices=2)
    out, err = proc.communicate(timeout=HANG_GUARD_S)
    assert proc.returncode == 0, err[-3000:]
    assert "2 cpu device(s)" in err
    assert out.split()[-1] == "finished"
    assert [r["env_steps"] for r in read_metrics(run_dir, "train")] == [STEPS, 2 * STEPS]
    assert checkpoint.load_run(run_dir, environment=PointPick()).step == 2 * STEPS


def test_auto_reset_start_states_are_redrawn_each_iteration():
    wrapped = brax_training.wrap(PointPick(episode_length=3), episode_length=3, action_repeat=1)
    state = wrapped.reset(jax.random.split(jax.random.PRNGKey(0), 8))
    before = np.asarray(state.info["first_obs"])
    refreshed = iteration.refresh_reset_states(wrapped, state, jax.random.PRNGKey(1))
    after = np.asarray(refreshed.info["first_obs"])
    # The new start states are exactly fresh resets with the split key, all different from before.
    expected = wrapped.reset(jax.random.split(jax.random.PRNGKey(1), 8)).obs
    np.testing.assert_array_equal(after, np.asarray(expected))
    assert np.all(np.any(after != before, axis=1))
    # The running episodes are untouched, and an episode that ends restarts from a new state.
    np.testing.assert_array_equal(np.asarray(refreshed.obs), np.asarray(state.obs))
    step = jax.jit(wrapped.step)
    s = refreshed
    for _ in range(3):
        s = step(s, jnp.zeros((8, 3)))
    np.testing.assert_array_equal(np.asarray(s.obs), after)


def test_priming_seeds_a_fresh_run_only(two_iteration_run, tmp_path):
    """prime_normalizer_episodes=2 adds 2 episodes x 16 envs of observations to a fresh run's
    normaliser (env steps not counted); a run warm-started from another does not prime."""
    _, source_dir, source = two_iteration_run
    config = tiny_config(total_env_steps=STEPS, num_evals=1)
    counts = {}
    for name, changes in {
        "plain": {},
        "primed": {"prime_normalizer_episodes": 2},
        "warm": {
            "prime_normalizer_episodes": 2,
            "init_from": str(source_dir),
            "init_checkpoint": "last",
        },
    }.items():
        out = train(
            config.replace(**changes), tmp_path / name, environment=PointPick(), progress=False
        )
        assert int(out.state.env_steps) == STEPS
        counts[name] = int(out.state.normalizer_params.count)
    assert counts["plain"] == STEPS
    assert counts["primed"] == STEPS + 2 * 12 * 16
    assert counts["warm"] == int(source.state.normalizer_params.count) + STEPS
