"""eval.py's work (popsan_jax.analysis.report) on a tiny trained run: the report and its files,
checkpoint choices, the ranking of every checkpoint, errors, comparison, the ANN baseline."""

import gc
import json
import math
import shutil

import pytest
from _report import fails, run_eval
from _toy_env import tiny_popsan_config

from popsan_jax.errors import CheckpointError
from popsan_jax.training.checkpoint import load_run

# A failed Orbax restore (test_errors) leaves un-awaited coroutines that the garbage
# collector reports later as "unraisable"; harmless, and not ours to silence globally.
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")


def test_full_report(trained, capsys):
    run_dir, env, _ = trained
    argv = [str(run_dir), "--episodes", "8", "--timesteps", "1,2", "--latency-repeats", "3"]
    assert run_eval(argv, env) == 0
    out = capsys.readouterr().out
    assert "success rate" in out and "(trained)" in out and "PopSAN T=2" in out
    report = json.loads((run_dir / "eval_last.json").read_text())
    assert report["episodes"] == 8 and report["which"] == "last"
    lo, hi = report["success_ci95"]
    assert lo <= report["success_rate"] <= hi
    assert [r["timesteps"] for r in report["energy"]] == [1, 2]
    assert len(report["latency"]) == 4 and math.isfinite(report["episode_return"])
    assert (run_dir / "tracking_last.png").stat().st_size > 5000
    md = (run_dir / "energy_last.md").read_text()
    assert "spyx#76" in md and "2 (trained)" in md
    csv_lines = (run_dir / "energy_last.csv").read_text().splitlines()
    assert csv_lines[0].startswith("# Convention") and len(csv_lines) == 4


def test_best_and_step(trained):
    run_dir, env, _ = trained
    index = json.loads((run_dir / "checkpoints" / "index.json").read_text())
    first = index["checkpoints"][0]["step"]
    fast = ["--episodes", "4", "--no-energy", "--no-latency", "--no-tracking"]
    assert run_eval([str(run_dir), "--step", str(first), *fast], env) == 0
    assert json.loads((run_dir / f"eval_step_{first}.json").read_text())["env_steps"] == first
    assert run_eval([str(run_dir), "--best", *fast], env) == 0
    best = json.loads((run_dir / "eval_best.json").read_text())
    assert best["env_steps"] == index["best"]
    # A stochastic evaluation goes beside the deterministic one, not over it.
    assert run_eval([str(run_dir), "--best", "--stochastic", *fast], env) == 0
    sampled = json.loads((run_dir / "eval_best+stochastic.json").read_text())
    assert sampled["policy"] == "stochastic" and sampled["which"] == "best+stochastic"
    assert json.loads((run_dir / "eval_best.json").read_text())["policy"] == "deterministic"
    # So does a re-check on other episodes (another --seed); it draws other initial states.
    assert run_eval([str(run_dir), "--best", "--seed", "3", *fast], env) == 0
    other = json.loads((run_dir / "eval_best+seed3.json").read_text())
    plain = json.loads((run_dir / "eval_best.json").read_text())
    assert other["seed"] == 3 and plain["seed"] == 0
    assert other["episode_return"] != plain["episode_return"]


def test_all_checkpoints_match_single_evaluations(trained, capsys):
    """The ranking's rows are exactly the ``--step N`` evaluations of each checkpoint: the same
    episodes (the key of ``--step N``), each checkpoint loaded, its training figure carried."""
    run_dir, env, _ = trained
    index = json.loads((run_dir / "checkpoints" / "index.json").read_text())
    fast = ["--episodes", "8", "--no-energy", "--no-latency", "--no-tracking"]
    assert run_eval([str(run_dir), "--all-checkpoints", "--episodes", "8"], env) == 0
    ranked = json.loads((run_dir / "eval_checkpoints.json").read_text())
    assert [r["step"] for r in ranked["rows"]] == sorted(e["step"] for e in index["checkpoints"])
    assert len(ranked["rows"]) >= 2
    for row in ranked["rows"]:
        entry = next(e for e in index["checkpoints"] if e["step"] == row["step"])
        assert row["training_success"] == entry["success_rate"]
        assert run_eval([str(run_dir), "--step", str(row["step"]), *fast], env) == 0
        single = json.loads((run_dir / f"eval_step_{row['step']}.json").read_text())
        assert row["episodes"] == single["episodes"] == 8
        assert row["success_rate"] == single["success_rate"]
        assert row["episode_length"] == single["episode_length"]
        assert row["episode_return"] == single["episode_return"]
    # Checkpoints differ, so the rows must too (else all rows came from one checkpoint).
    assert len({r["episode_return"] for r in ranked["rows"]}) == len(ranked["rows"])
    top = max(r["success_rate"] for r in ranked["rows"])
    assert ranked["chosen_step"] == max(
        r["step"] for r in ranked["rows"] if r["success_rate"] == top
    )
    md = (run_dir / "eval_checkpoints.md").read_text()
    assert md.count("**") == 2 and f"| {ranked['chosen_step']:,} |" in md
    assert "chosen: --step" in capsys.readouterr().out
    argv = [str(run_dir), "--all-checkpoints", "--video", "x.mp4"]
    assert "--video needs one checkpoint" in fails(argv, env)
    with pytest.raises(SystemExit):  # one of --best / --step / --all-checkpoints
        run_eval([str(run_dir), "--all-checkpoints", "--best"])


def test_errors(trained, tmp_path, capsys):
    run_dir, env, _ = trained
    fast = ["--episodes", "4", "--no-energy", "--no-latency", "--no-tracking"]
    assert fails([str(tmp_path / "missing"), *fast], env).startswith("error: run directory")
    empty = tmp_path / "empty"
    empty.mkdir()
    shutil.copy(run_dir / "config.json", empty / "config.json")
    assert "no checkpoint" in fails([str(empty), *fast], env)
    assert "no checkpoint at step 7" in fails([str(run_dir), "--step", "7", *fast], env)
    # Same checkpoints, config edited to other hidden sizes: restore must refuse.
    other = tmp_path / "other"
    shutil.copytree(run_dir, other)
    cfg = json.loads((other / "config.json").read_text())
    cfg["actor_kwargs"]["hidden_sizes"] = [5, 5]
    (other / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError):
        load_run(other, environment=env)
    assert fails([str(other), *fast], env).startswith("error: cannot restore checkpoint")
    with pytest.raises(SystemExit) as exc:
        run_eval([str(run_dir), "--timesteps", "0,x", *fast], env)
    assert exc.value.code == 2
    # An env override must name a key of the run's own env (here a registered one).
    reach = tmp_path / "reach"
    shutil.copytree(run_dir, reach)
    cfg = json.loads((reach / "config.json").read_text())
    (reach / "config.json").write_text(json.dumps({**cfg, "env": "franka_reach"}))
    err = fails([str(reach), "--env-override", "bogus=1", *fast])
    assert "unknown config key 'bogus' for env 'franka_reach'" in err
    assert not list(reach.glob("eval_last+*"))
    for argv in (["--no-such-flag"], ["--env-override", "no_equals_sign"]):
        with pytest.raises(SystemExit) as exc:
            run_eval([str(run_dir), *argv])
        assert exc.value.code == 2
    gc.collect()  # collect Orbax's leftovers (see pytestmark) while this module runs


def test_compare(trained, tmp_path):
    run_dir, _, _ = trained
    out = tmp_path / "cmp.png"
    assert run_eval(["--compare", str(run_dir), str(run_dir), "--out", str(out)]) == 0
    assert out.stat().st_size > 5000
    table = (tmp_path / "cmp.md").read_text()  # the sample-efficiency table beside the figure
    assert table.startswith("env steps to the first") and table.count(f"| {run_dir.name} |") == 2
    fails(["--compare", str(tmp_path)])
    # The table goes to the figure's path with .md, so a .md figure would be overwritten by it.
    md_out = tmp_path / "table.md"
    fails(["--compare", str(run_dir), "--out", str(md_out)])
    assert not md_out.exists()


def test_ann_run_sets_baseline(trained, tmp_path, capsys):
    run_dir, env, _ = trained
    ann = tmp_path / "mlp_run"
    ann.mkdir()
    tiny_popsan_config(actor="mlp", actor_kwargs=dict(hidden_sizes=(20,))).to_json(
        ann / "config.json"
    )
    fast = ["--episodes", "4", "--timesteps", "2", "--no-latency", "--no-tracking"]
    assert run_eval([str(run_dir), "--ann-run", str(ann), *fast], env) == 0
    (row,) = json.loads((run_dir / "eval_last.json").read_text())["energy"]
    assert row["ann_macs"] == 6 * 20 + 20 * 3
    # A PopSAN run is no ANN baseline.
    assert "not an MLP" in fails([str(run_dir), "--ann-run", str(run_dir), *fast], env)
