"""Figures from synthetic arrays and metrics files: written, non-empty, and read back correctly."""

import json

import matplotlib.image
import numpy as np
import pytest

from popsan_jax.analysis import plots
from popsan_jax.errors import CheckpointError


def _png_ok(path, min_width=400):
    assert path.is_file() and path.stat().st_size > 5_000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = matplotlib.image.imread(path)
    assert image.shape[1] >= min_width
    # Not a blank canvas: some pixels differ from the background.
    assert np.ptp(image[..., :3]) > 0.5


def test_tracking_pick_figure(tmp_path):
    t = np.linspace(0, 1, 50)[:, None]
    obj = np.concatenate([0.5 + 0 * t, 0.1 + 0 * t, 0.02 + 0.3 * t], axis=1)
    info = {"object_pos": obj, "left_tip": obj + 0.02, "right_tip": obj - 0.02}
    out = plots.plot_tracking(info, tmp_path / "sub" / "track.png", goal_z=0.3, dt=0.02)
    _png_ok(out, min_width=1200)  # four panels


def test_tracking_reach_figure_and_bad_keys(tmp_path):
    pos = np.random.default_rng(0).normal(size=(20, 3))
    out = plots.plot_tracking({"tip_mid": pos, "target_pos": pos * 0}, tmp_path / "reach.png")
    _png_ok(out)
    with pytest.raises(ValueError):
        plots.plot_tracking({"left_tip": pos}, tmp_path / "bad.png")


def _fake_run(root, name, actor, evals, revision=2):
    run = root / name
    run.mkdir()
    config = {"actor": actor} if revision is None else {"actor": actor, "env_revision": revision}
    (run / "config.json").write_text(json.dumps(config))
    lines = [{"kind": "train", "env_steps": 10, "wall_s": 1.0, "loss/total": 0.1}]
    for steps, success in evals:
        lines.append(
            {
                "kind": "eval",
                "env_steps": steps,
                "wall_s": 2.0,
                "success_rate": success,
                "reached_rate": min(1.0, 2 * success),
                "episode_length": 100 - success * 50,
                "episode_reward": 10 * success,
            }
        )
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    return run


def test_read_run_curves_keeps_eval_lines_sorted(tmp_path):
    run = _fake_run(tmp_path, "a", "popsan", [(2000, 0.5), (1000, 0.25)])
    curves = plots.read_run_curves(run)
    assert curves.actor == "popsan" and curves.label == "a"
    np.testing.assert_array_equal(curves.env_steps, [1000, 2000])
    np.testing.assert_array_equal(curves.values["success_rate"], [0.25, 0.5])
    np.testing.assert_array_equal(curves.values["reached_rate"], [0.5, 1.0])
    np.testing.assert_array_equal(curves.values["episode_length"], [87.5, 75.0])


def test_revision_1_runs_logged_the_latch_as_success(tmp_path):
    # A run saved before env revisions (no env_revision in config.json) logged PixMC's latch
    # as success_rate: its curves show it as "reached", and its hold success as unmeasured.
    run = _fake_run(tmp_path, "old", "popsan", [(1000, 0.25), (2000, 0.5)], revision=None)
    curves = plots.read_run_curves(run)
    np.testing.assert_array_equal(curves.values["reached_rate"], [0.25, 0.5])
    assert np.all(np.isnan(curves.values["success_rate"]))


def test_compare_figure(tmp_path):
    runs = [
        plots.read_run_curves(_fake_run(tmp_path, "snn", "popsan", [(0, 0.0), (1000, 0.4)])),
        plots.read_run_curves(_fake_run(tmp_path, "ann", "mlp", [(0, 0.1), (1000, 0.9)])),
    ]
    _png_ok(plots.plot_compare(runs, tmp_path / "cmp.png"), min_width=1200)


def test_compare_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no metrics.jsonl"):
        plots.read_run_curves(tmp_path)
    run = _fake_run(tmp_path, "empty", "mlp", [])
    with pytest.raises(CheckpointError, match="no eval lines"):
        plots.read_run_curves(run)
    (run / "metrics.jsonl").write_text("{not json\n")
    with pytest.raises(CheckpointError, match="not valid JSON"):
        plots.read_run_curves(run)
