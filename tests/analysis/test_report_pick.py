"""eval.py's work end to end on the real franka_pick env (MJX): an untrained checkpoint written
with the trainer's own checkpoint code, then report, tracking figure, energy table and video.

One MJX rollout compile (~30 s on 2 cores), hence slow.
"""

import json

import jax
import pytest
from _gl import gl_available
from _report import run_eval

from popsan_jax.analysis.video import GL_BACKENDS
from popsan_jax.recipes import resolve_config
from popsan_jax.training import checkpoint, checkpoint_index
from popsan_jax.training.iteration import init_training_state
from popsan_jax.training.setup import build_networks, make_env, make_optimizer


@pytest.fixture(scope="module")
def pick_run(tmp_path_factory):
    config = resolve_config("smoke", overrides=dict(episode_length=25))
    env = make_env(config)
    run_dir = tmp_path_factory.mktemp("pick").resolve() / "franka_pick-popsan-untrained"
    run_dir.mkdir()
    config.to_json(run_dir / checkpoint_index.CONFIG)
    nets = build_networks(config, env.observation_size, env.action_size)
    state = init_training_state(
        config, nets, make_optimizer(config), env.observation_size, jax.random.PRNGKey(0)
    )
    checkpoint.save_checkpoint(run_dir, state, jax.random.PRNGKey(1), 1, 0.0, 1)
    return run_dir, env


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
# Orbax coroutines left by test_report.py's failed restores may be collected during this test.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_report_on_franka_pick(pick_run, capsys):
    run_dir, env = pick_run
    video = run_dir / "episode.mp4"
    argv = [str(run_dir), "--episodes", "8", "--timesteps", "5", "--latency-repeats", "3"]
    if any(gl_available(b) for b in GL_BACKENDS):
        argv += ["--video", str(video)]
    assert run_eval(argv, env) == 0
    out = capsys.readouterr().out
    report = json.loads((run_dir / "eval_last.json").read_text())
    assert report["episodes"] == 8 and report["actor"] == "popsan" and report["timesteps"] == 5
    assert 1 <= report["episode_length"] <= 25
    assert {"reward/dist_left", "reward/lift"} <= set(report)
    (row,) = report["energy"]
    # Paper-sized PopSAN on the 34-dim pick obs: 340 encoder receptive fields + 9 x 10 decoder
    # MACs; the first FC layer charged densely would be 340 * 256 * T = 5.
    assert row["snn_macs"] == 340 + 90
    assert row["ann_macs"] == 34 * 256 + 256 * 256 + 256 * 9
    assert row["trained_timesteps"] and 0 <= row["firing_rate/hidden_0"] <= 1
    assert (run_dir / "tracking_last.png").stat().st_size > 5000
    assert "5 (trained)" in (run_dir / "energy_last.md").read_text()
    if "--video" in argv:
        assert video.stat().st_size > 1000 and "wrote" in out

    # Under an env override: a 10 m grasp radius counts every step as held (the untrained
    # policy holds nothing at the default 4 cm), written beside the plain report, not over it.
    fast = ["--episodes", "4", "--no-energy", "--no-latency", "--no-tracking"]
    assert run_eval([str(run_dir), *fast, "--env-override", "grasp_radius=10"]) == 0
    wide = json.loads((run_dir / "eval_last+grasp_radius=10.json").read_text())
    assert wide["reward/held"] == 1.0 and wide["env_overrides"] == {"grasp_radius": 10}
    plain = json.loads((run_dir / "eval_last.json").read_text())
    assert plain["episodes"] == 8 and plain["reward/held"] < 0.5 and plain["env_overrides"] == {}
