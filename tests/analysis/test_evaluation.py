"""Evaluator round trip on a tiny trained run: reload, evaluate, count spikes, CLI outputs."""

import gc
import importlib.util
import json
import math
import shutil
import time
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import PointPick, tiny_popsan_config
from brax.training.acme import running_statistics
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.analysis import evaluation, latency
from popsan_jax.errors import CheckpointError
from popsan_jax.networks import actor_variables, make_actor
from popsan_jax.rollout import EpisodeBatch, run_episodes
from popsan_jax.training import iteration as ppo_update
from popsan_jax.training import loop as ppo
from popsan_jax.training.checkpoint import load_run

# eval.py is a script at the repo root, not a package module: load it by path.
_spec = importlib.util.spec_from_file_location(
    "eval_cli", Path(__file__).resolve().parents[2] / "eval.py"
)
eval_cli = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(eval_cli)

EPISODES = 16
# A failed Orbax restore (test_cli_errors) leaves un-awaited coroutines that the garbage
# collector reports later as "unraisable"; harmless, and not ours to silence globally.
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """One tiny PopSAN run shared by every test here: (run_dir, env, TrainResult)."""
    env = PointPick()
    run_dir = tmp_path_factory.mktemp("eval") / "popsan_run"
    result = ppo.train(tiny_popsan_config(), run_dir, environment=env, progress=False)
    return run_dir, env, result


@pytest.fixture(scope="session")
def loaded(trained):
    run_dir, env, _ = trained
    return load_run(run_dir, environment=env)


@pytest.fixture(scope="session")
def recorded(loaded):
    return jax.device_get(evaluation.rollouts(loaded, EPISODES, jax.random.PRNGKey(3), record=True))


def test_wilson_interval_hand_values():
    z2 = 1.959963984540054**2
    lo, hi = evaluation.wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(z2 / (10 + z2))  # 0.2775
    lo, hi = evaluation.wilson_interval(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(10 / (10 + z2))
    lo, hi = evaluation.wilson_interval(5, 10)  # textbook: 0.2366 - 0.7634
    assert (lo, hi) == pytest.approx((0.236593, 0.763407), abs=1e-5)
    with pytest.raises(ValueError):
        evaluation.wilson_interval(0, 0)


def test_summarize_hand_built_batch():
    batch = EpisodeBatch(
        success=np.array([1.0, 0.0, 1.0, 1.0]),
        length=np.array([10.0, 20.0, 30.0, 40.0]),
        ret=np.array([1.0, 2.0, 3.0, 6.0]),
        terms={"distance": np.array([0.1, 0.2, 0.3, 0.4])},
    )
    s = evaluation.summarize(batch)
    assert s["episodes"] == 4 and s["success_rate"] == 0.75
    assert s["success_ci95"] == pytest.approx(list(evaluation.wilson_interval(3, 4)))
    assert s["episode_length"] == 25.0 and s["episode_return"] == 3.0
    assert s["reward/distance"] == pytest.approx(0.25)


def test_reloaded_policy_acts_like_saved_params(trained, loaded):
    _, env, result = trained
    state = result.state
    assert loaded.step == int(state.env_steps) and loaded.entry["step"] == loaded.step
    # Independent rebuild from the in-memory config and the params the trainer ended with.
    nets = ppo_update.build_networks(tiny_popsan_config(), env.observation_size, env.action_size)
    saved = ppo_networks.make_inference_fn(nets)(
        (state.normalizer_params, state.params.policy), deterministic=True
    )
    obs = jax.random.normal(jax.random.PRNGKey(1), (32, env.observation_size))
    key = jax.random.PRNGKey(0)
    expected = np.asarray(saved(obs, key)[0])
    np.testing.assert_array_equal(np.asarray(loaded.make_policy()(obs, key)), expected)
    # The evaluator's rollouts equal a rollout with the saved params' policy.
    mine = evaluation.rollouts(loaded, EPISODES, key)
    ref = run_episodes(env, lambda o, k: saved(o, k)[0], key, EPISODES)
    np.testing.assert_array_equal(np.asarray(mine.ret), np.asarray(ref.ret))
    np.testing.assert_array_equal(np.asarray(mine.success), np.asarray(ref.success))


def test_spike_counts_match_direct_numpy_count(loaded, recorded):
    obs = evaluation.alive_observations(recorded)
    assert obs.shape == (int(np.sum(recorded.length)), loaded.env.observation_size)
    for t in (1, 2):
        ops, sizes = evaluation.measure_snn_ops(loaded, obs, t, chunk=50)  # several chunks
        assert sizes == (6 * 3, 12, 8, 3 * 4)
        actor = make_actor("popsan", {**loaded.config.actor_kwargs, "timesteps": t}, 3)
        x = running_statistics.normalize(
            jnp.asarray(obs), loaded.normalizer_params, max_abs_value=loaded.config.obs_clip
        )
        mean, spikes = actor.apply(actor_variables(loaded.policy_params), x, return_spikes=True)
        # The spikes are those of the policy the rollouts ran (same normalisation and params).
        policy = evaluation.networks_at_timesteps(loaded, t).policy_network
        logits = policy.apply(loaded.normalizer_params, loaded.policy_params, jnp.asarray(obs))
        np.testing.assert_allclose(np.asarray(logits[:, :3]), np.asarray(mean), atol=1e-6)
        enc, h0, h1, out = (np.asarray(s, dtype=np.float64) for s in spikes)
        m = obs.shape[0]
        assert ops.dense_first_layer_macs == 18 * 12 * t and ops.decoder_macs == 12
        assert ops.encoder_macs == 18
        # ACs: encoder spikes reach 12 neurons, hidden_0 spikes 8, hidden_1 spikes 12 outputs.
        expected = (enc.sum() * 12 + h0.sum() * 8 + h1.sum() * 12) / m
        assert ops.sops == pytest.approx(expected, rel=1e-6)
        assert ops.first_layer_sops == pytest.approx(enc.sum() * 12 / m, rel=1e-6)
        rates = [s.mean() for s in (enc, h0, h1, out)]
        np.testing.assert_allclose(ops.firing_rates, rates, rtol=1e-6)
        assert ops.timesteps == t


def test_rebuilt_timesteps_share_params(loaded):
    obs = jax.random.normal(jax.random.PRNGKey(2), (8, loaded.env.observation_size))
    nets_1 = evaluation.networks_at_timesteps(loaded, 1)
    assert evaluation.networks_at_timesteps(loaded, 2) is loaded.networks
    # Same params tree fits both T; the means differ because the spike trains do.
    p1 = nets_1.policy_network.apply(loaded.normalizer_params, loaded.policy_params, obs)
    p2 = loaded.networks.policy_network.apply(loaded.normalizer_params, loaded.policy_params, obs)
    assert p1.shape == p2.shape and not np.allclose(np.asarray(p1), np.asarray(p2))


def test_energy_sweep_rows(loaded, recorded):
    rows = evaluation.energy_sweep(
        loaded, [1, 2], EPISODES, jax.random.PRNGKey(4), None, True, recorded
    )
    assert [r["timesteps"] for r in rows] == [1, 2]
    assert [r["trained_timesteps"] for r in rows] == [False, True]
    # ANN baseline: MLP 6 -> 12 -> 8 -> 3.
    assert all(r["ann_macs"] == 6 * 12 + 12 * 8 + 8 * 3 for r in rows)
    for r in rows:
        # Encoder receptive fields (6 obs x 3) + decoder (3 actions x 4), whatever T is.
        assert r["snn_macs"] == 18 + 12
        assert r["snn_energy_pj"] == pytest.approx(4.6 * r["snn_macs"] + 0.9 * r["snn_acs"])
        assert r["saving_pct"] == pytest.approx(100 * (1 - r["snn_energy_pj"] / r["ann_energy_pj"]))
    assert rows[1]["success_rate"] == pytest.approx(float(np.mean(recorded.success)))


def test_median_seconds_and_latency_rows(loaded):
    timing = latency.median_seconds(lambda: time.sleep(0.002), repeats=5, warmup=1)
    assert 0.002 <= timing["median_s"] < 0.05 and timing["p10_s"] <= timing["p90_s"]
    actors = evaluation.latency_actors(loaded, None)
    assert list(actors) == ["PopSAN T=2", "MLP (ANN)"]
    rows = latency.latency_table(actors, loaded.env.observation_size, (1, 64), repeats=5)
    assert [(r["actor"], r["batch"]) for r in rows] == [
        ("PopSAN T=2", 1),
        ("PopSAN T=2", 64),
        ("MLP (ANN)", 1),
        ("MLP (ANN)", 64),
    ]
    for r in rows:
        assert r["median_ms"] > 0 and r["per_obs_us"] == pytest.approx(
            1e3 * r["median_ms"] / r["batch"]
        )
    assert "| PopSAN T=2 | 64 |" in latency.format_latency(rows)


def test_cli_full_report(trained, capsys):
    run_dir, env, _ = trained
    argv = [str(run_dir), "--episodes", "8", "--timesteps", "1,2", "--latency-repeats", "3"]
    assert eval_cli.main(argv, environment=env) == 0
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


def test_cli_best_and_step(trained):
    run_dir, env, _ = trained
    index = json.loads((run_dir / "checkpoints" / "index.json").read_text())
    first = index["checkpoints"][0]["step"]
    fast = ["--episodes", "4", "--no-energy", "--no-latency", "--no-tracking"]
    assert eval_cli.main([str(run_dir), "--step", str(first), *fast], environment=env) == 0
    assert json.loads((run_dir / f"eval_step_{first}.json").read_text())["env_steps"] == first
    assert eval_cli.main([str(run_dir), "--best", *fast], environment=env) == 0
    best = json.loads((run_dir / "eval_best.json").read_text())
    assert best["env_steps"] == index["best"]
    # A stochastic evaluation goes beside the deterministic one, not over it.
    assert eval_cli.main([str(run_dir), "--best", "--stochastic", *fast], environment=env) == 0
    sampled = json.loads((run_dir / "eval_best+stochastic.json").read_text())
    assert sampled["policy"] == "stochastic" and sampled["which"] == "best+stochastic"
    assert json.loads((run_dir / "eval_best.json").read_text())["policy"] == "deterministic"
    # So does a re-check on other episodes (another --seed); it draws other initial states.
    assert eval_cli.main([str(run_dir), "--best", "--seed", "3", *fast], environment=env) == 0
    other = json.loads((run_dir / "eval_best+seed3.json").read_text())
    plain = json.loads((run_dir / "eval_best.json").read_text())
    assert other["seed"] == 3 and plain["seed"] == 0
    assert other["episode_return"] != plain["episode_return"]


def test_cli_all_checkpoints_match_single_evaluations(trained, capsys):
    """The ranking's rows are exactly the ``--step N`` evaluations of each checkpoint: the same
    episodes (the key of ``--step N``), each checkpoint loaded, its training figure carried."""
    run_dir, env, _ = trained
    index = json.loads((run_dir / "checkpoints" / "index.json").read_text())
    fast = ["--episodes", "8", "--no-energy", "--no-latency", "--no-tracking"]
    assert eval_cli.main([str(run_dir), "--all-checkpoints", "--episodes", "8"], env) == 0
    ranked = json.loads((run_dir / "eval_checkpoints.json").read_text())
    assert [r["step"] for r in ranked["rows"]] == sorted(e["step"] for e in index["checkpoints"])
    assert len(ranked["rows"]) >= 2
    for row in ranked["rows"]:
        entry = next(e for e in index["checkpoints"] if e["step"] == row["step"])
        assert row["training_success"] == entry["success_rate"]
        assert eval_cli.main([str(run_dir), "--step", str(row["step"]), *fast], env) == 0
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
    assert eval_cli.main(argv, env) == 2
    assert "--video needs one checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # one of --best / --step / --all-checkpoints
        eval_cli.main([str(run_dir), "--all-checkpoints", "--best"])


def test_cli_errors(trained, tmp_path, capsys):
    run_dir, env, _ = trained
    fast = ["--episodes", "4", "--no-energy", "--no-latency", "--no-tracking"]
    assert eval_cli.main([str(tmp_path / "missing"), *fast], environment=env) == 2
    assert capsys.readouterr().err.startswith("error: run directory")
    empty = tmp_path / "empty"
    empty.mkdir()
    shutil.copy(run_dir / "config.json", empty / "config.json")
    assert eval_cli.main([str(empty), *fast], environment=env) == 2
    assert "no checkpoint" in capsys.readouterr().err
    assert eval_cli.main([str(run_dir), "--step", "7", *fast], environment=env) == 2
    assert "no checkpoint at step 7" in capsys.readouterr().err
    # Same checkpoints, config edited to other hidden sizes: restore must refuse.
    other = tmp_path / "other"
    shutil.copytree(run_dir, other)
    cfg = json.loads((other / "config.json").read_text())
    cfg["actor_kwargs"]["hidden_sizes"] = [5, 5]
    (other / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError):
        load_run(other, environment=env)
    assert eval_cli.main([str(other), *fast], environment=env) == 2
    err = capsys.readouterr().err
    # Orbax may log its own traceback first (C's area); ours is the one final line.
    assert err.strip().splitlines()[-1].startswith("error: cannot restore checkpoint")
    assert eval_cli.main([str(run_dir), "--timesteps", "0,x", *fast], environment=env) == 2
    # An env override must name a key of the run's own env (here a registered one).
    reach = tmp_path / "reach"
    shutil.copytree(run_dir, reach)
    cfg = json.loads((reach / "config.json").read_text())
    (reach / "config.json").write_text(json.dumps({**cfg, "env": "franka_reach"}))
    assert eval_cli.main([str(reach), "--env-override", "bogus=1", *fast]) == 2
    assert "unknown config key 'bogus' for env 'franka_reach'" in capsys.readouterr().err
    assert not list(reach.glob("eval_last+*"))
    for argv in (["--no-such-flag"], ["--env-override", "no_equals_sign"]):
        with pytest.raises(SystemExit) as exc:
            eval_cli.main([str(run_dir), *argv])
        assert exc.value.code == 2
    gc.collect()  # collect Orbax's leftovers (see pytestmark) while this module runs


def test_cli_compare(trained, tmp_path):
    run_dir, _, _ = trained
    out = tmp_path / "cmp.png"
    assert eval_cli.main(["--compare", str(run_dir), str(run_dir), "--out", str(out)]) == 0
    assert out.stat().st_size > 5000
    table = (tmp_path / "cmp.md").read_text()  # the sample-efficiency table beside the figure
    assert table.startswith("env steps to the first") and table.count(f"| {run_dir.name} |") == 2
    assert eval_cli.main(["--compare", str(tmp_path)]) == 2
    # The table goes to the figure's path with .md, so a .md figure would be overwritten by it.
    md_out = tmp_path / "table.md"
    assert eval_cli.main(["--compare", str(run_dir), "--out", str(md_out)]) == 2
    assert not md_out.exists()


def test_cli_ann_run_sets_baseline(trained, tmp_path, capsys):
    run_dir, env, _ = trained
    ann = tmp_path / "mlp_run"
    ann.mkdir()
    tiny_popsan_config(actor="mlp", actor_kwargs=dict(hidden_sizes=(20,))).to_json(
        ann / "config.json"
    )
    fast = ["--episodes", "4", "--timesteps", "2", "--no-latency", "--no-tracking"]
    assert eval_cli.main([str(run_dir), "--ann-run", str(ann), *fast], environment=env) == 0
    (row,) = json.loads((run_dir / "eval_last.json").read_text())["energy"]
    assert row["ann_macs"] == 6 * 20 + 20 * 3
    # A PopSAN run is no ANN baseline.
    assert eval_cli.main([str(run_dir), "--ann-run", str(run_dir), *fast], environment=env) == 2
    assert "not an MLP" in capsys.readouterr().err


def test_latency_actors_for_an_mlp_run(loaded):
    config = tiny_popsan_config(actor="mlp", actor_kwargs=dict(hidden_sizes=(8,)))
    mlp = make_actor("mlp", config.actor_kwargs, 3)
    params = mlp.init(jax.random.PRNGKey(0), jnp.zeros((1, 6)))["params"]
    run = SimpleNamespace(
        config=config, env=loaded.env, policy_params={"params": {"actor": params}}
    )
    actors = evaluation.latency_actors(run, None)
    assert list(actors) == ["PopSAN T=5", "MLP (ANN)"]
    popsan, _ = actors["PopSAN T=5"]
    assert tuple(popsan.hidden_sizes) == (8,)
    # The run's own trained actor keeps its params.
    assert actors["MLP (ANN)"][1]["params"] is params
