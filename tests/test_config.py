"""RunConfig: derived sizes, presets and backend defaults, checks, JSON, the committed runs.

Everything here is cheap: no env is compiled.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import envs
from popsan_jax.cli import given_flags, run_choices, train_parser
from popsan_jax.config import CURRENT_ENV_REVISION, POPSAN_DEFAULTS, RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.recipes import ACTOR_RECIPES, PICK_RECIPE, PRESETS, resolve_config
from popsan_jax.training.run import prepare_run
from popsan_jax.training.setup import make_env
from popsan_jax.training.stages import warmup_config

ROOT = Path(__file__).resolve().parent.parent
# franka_pick's second stage before 6 December (since then PICK_RECIPE's 4 M steps, 16 evals).
SECOND_STAGE_2M = dict(total_env_steps=2_000_000, num_evals=8)


def before_clip(**flags) -> RunConfig:
    """The README's command ``train.py --env franka_pick`` with ``flags`` as it was before its
    second stage clipped per network (8 December): the same command with the joint clip."""
    command = resolve_config(None, "cpu", dict(env="franka_pick", **flags))
    assert command.clip_per_network and not command.warmup_clip_per_network
    return command.replace(clip_per_network=False)


def earlier_command(**flags) -> RunConfig:
    """:func:`before_clip` as configs recorded it before PopSAN's ``decoder_init_scale``
    existed: without the key, which builds the same 1.0."""
    command = before_clip(**flags)
    assert command.actor_kwargs.get("decoder_init_scale", 1.0) == 1.0
    kwargs = {k: v for k, v in command.actor_kwargs.items() if k != "decoder_init_scale"}
    return command.replace(actor_kwargs=kwargs)


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
    assert cpu.num_envs == 512 and cpu.actor == "popsan"
    assert cpu.actor_kwargs == POPSAN_DEFAULTS
    gpu = resolve_config(None, "gpu")
    assert gpu.num_envs >= 2048
    smoke = resolve_config("smoke", "gpu")
    assert smoke.num_envs == PRESETS["smoke"]["num_envs"]
    flagged = resolve_config("smoke", "cpu", {"num_envs": 64, "seed": None}, {"timesteps": 3})
    assert flagged.num_envs == 64 and flagged.seed == 0
    assert flagged.actor_kwargs["timesteps"] == 3
    assert flagged.actor_kwargs["hidden_sizes"] == (256, 256)
    mlp = resolve_config(None, "cpu", {"actor": "mlp"}, {"hidden_sizes": (32, 32)})
    assert mlp.actor_kwargs == {"hidden_sizes": (32, 32), "output_init_scale": 0.01}


def test_presets_keep_the_actors_own_draws():
    # The default recipe starts the MLP's output layer at 0.01x its draw (ACTOR_RECIPES) and
    # keeps PopSAN's; a preset is a whole recipe of its own and builds the actors as their
    # modules' defaults do (the paper preset is the paper's network), unless flags say otherwise.
    assert ACTOR_RECIPES == {"popsan": {}, "mlp": {"output_init_scale": 0.01}}
    assert resolve_config(None, "cpu", dict(actor="mlp")).actor_kwargs["output_init_scale"] == 0.01
    assert resolve_config(None, "cpu").actor_kwargs["decoder_init_scale"] == 1.0
    for preset in PRESETS:
        mlp = resolve_config(preset, "cpu", dict(actor="mlp"))
        assert mlp.actor_kwargs == {"hidden_sizes": (256, 256), "output_init_scale": 1.0}
        assert resolve_config(preset, "cpu").actor_kwargs == POPSAN_DEFAULTS
    for actor, key in (("popsan", "decoder_init_scale"), ("mlp", "output_init_scale")):
        flagged = resolve_config("paper", "cpu", dict(actor=actor), {key: 0.1})
        assert flagged.actor_kwargs[key] == 0.1


def test_accelerator_defaults_scale_the_cpu_recipe():
    # The GPU run makes the CPU recipe's gradient updates (same count per run, same minibatches
    # and epochs per iteration), each on 4x the sequences, and evaluates at the same fractions.
    cpu, gpu = resolve_config(None, "cpu"), resolve_config(None, "gpu")
    assert gpu.num_envs == 4 * cpu.num_envs == 2048
    assert gpu.num_iterations == cpu.num_iterations
    updates = [c.num_iterations * c.num_minibatches * c.num_updates_per_batch for c in (cpu, gpu)]
    assert updates[0] == updates[1]
    assert (
        gpu.batch_size == 4 * cpu.batch_size
        and gpu.unrolls_per_iteration == cpu.unrolls_per_iteration
    )
    assert gpu.eval_interval == cpu.eval_interval
    same = ("actor_lr", "critic_lr", "lr_schedule", "entropy_cost", "num_eval_envs")
    assert all(getattr(cpu, k) == getattr(gpu, k) for k in same)


def test_every_preset_and_backend_default_is_valid():
    for backend in ("cpu", "gpu"):
        for preset in (None, *PRESETS):
            resolve_config(preset, backend).validate(1)


def test_paper_preset_is_the_committed_pick_run_that_learned():
    # `--preset paper` must reproduce docs/reference/pick-popsan-s0 (95.5 % success): the
    # same RunConfig, its env override (action_scale 2.0) being franka_pick's default now.
    run_dir = ROOT / "docs/reference/pick-popsan-s0"
    committed = RunConfig.from_json(run_dir / "config.json")
    overrides = dict(committed.env_overrides)
    env_defaults = envs.FrankaPick.default_config()
    assert all(env_defaults[k] == v for k, v in overrides.items()), overrides
    for backend in ("cpu", "gpu"):
        paper = resolve_config("paper", backend, dict(seed=committed.seed))
        # The same PPO and network settings; it now trains on the current env revision, and
        # records the decoder's init scale that a config without the key builds with.
        assert committed.env_revision == 1
        kwargs = {**committed.actor_kwargs, "decoder_init_scale": 1.0}
        current = committed.replace(
            env_overrides={}, env_revision=CURRENT_ENV_REVISION, actor_kwargs=kwargs
        )
        assert paper == current, backend


def test_readme_command_is_the_committed_pick_hold_chain():
    # `python train.py --env franka_pick` on a CPU (docs/results.md) must be the committed
    # revision-4 seed-0 chain: its warm-up is the revision-2 run of the README's earlier command
    # (docs/reference/pick-hold-popsan-s0; revision 2 spelt out as overrides), its own stage the
    # 2 M-step fine-tune from that run's last checkpoint (docs/reference/pick-hold-popsan-ft-s0),
    # the warm-up taking the place of init_from; revision 5 adds only the lift ramp and the climb
    # term, and since 6 December the second stage is 4 M steps long (SECOND_STAGE_2M undoes it).
    # `--seed K` and `--actor mlp` change only those fields.
    command = earlier_command()
    fine_tune = RunConfig.from_json(ROOT / "docs/reference/pick-hold-popsan-ft-s0/config.json")
    assert fine_tune.init_from == "docs/reference/pick-hold-popsan-s0"
    assert fine_tune.init_checkpoint == "last"  # what the warm-up hands on (warm_source)
    assert fine_tune.env_revision == 4
    warm = {k: getattr(command, k) for k in PICK_RECIPE if k.startswith("warmup_")}
    as_fine_tune = fine_tune.replace(init_from=None, init_checkpoint="best", **warm)
    assert command.replace(**SECOND_STAGE_2M) == as_fine_tune.replace(
        env_revision=CURRENT_ENV_REVISION
    )
    revision_2 = RunConfig.from_json(ROOT / "docs/reference/pick-hold-popsan-s0/config.json")
    assert revision_2.env_revision == 2
    as_revision_2 = warmup_config(command).replace(env_overrides={}, env_revision=2)
    assert as_revision_2 == revision_2
    mlp = earlier_command(actor="mlp", seed=2)
    assert mlp.replace(actor="popsan", seed=0, actor_kwargs=command.actor_kwargs) == command


def test_readme_command_is_the_committed_4m_stage_runs():
    # docs/results.md, "The README's command since 6 December": each run is the README's command
    # for its actor and seed, either whole or as its warm-up (RUN/warmup) followed by the 4 M-step
    # stage started from that warm-up, which is the command's own stage with init_from set.
    whole = [("stage4m/popsan-s0", "popsan", 0), ("stage4m/popsan-s2", "popsan", 2)]
    whole += [("stage4m/mlp-s1", "mlp", 1), ("stage4m/mlp-s2", "mlp", 2)]
    split = [("stage4m/mlp-s0", "stage4m/mlp-s0/warmup", "runs/mlpinit-s0/warmup", "mlp", 0)]
    split += [
        ("readme5/popsan-s1-4m", "readme5/popsan-s1/warmup", "runs/popsan-s1/warmup", "popsan", 1)
    ]
    results = ROOT / "docs/results"
    for path, actor, seed in whole:
        command = earlier_command(actor=actor, seed=seed)
        assert RunConfig.from_json(results / path / "config.json") == command
        warm_up = RunConfig.from_json(results / path / "warmup/config.json")
        assert warm_up == warmup_config(command)
    for path, warm_path, source, actor, seed in split:
        command = earlier_command(actor=actor, seed=seed)
        stage = command.replace(init_from=source, init_checkpoint="last", warmup_env_steps=0)
        assert RunConfig.from_json(results / path / "config.json") == stage
        warm_up = RunConfig.from_json(results / warm_path / "config.json")
        assert warm_up == warmup_config(command)
    assert command.total_env_steps == 4_000_000 and command.num_evals == 16


def test_readme_command_today_is_the_committed_epyc_run_and_its_t2_fine_tune():
    # docs/results.md, "The README's command on an AMD EPYC": the plain command as it reads now
    # (seed 0, the decoder key recorded), and the documented T = 2 fine-tune started from it.
    results = ROOT / "docs/results/stage4m"
    command = before_clip()
    assert RunConfig.from_json(results / "popsan-s0-epyc/config.json") == command
    warm_up = RunConfig.from_json(results / "popsan-s0-epyc/warmup/config.json")
    assert warm_up == warmup_config(command)
    # Its configs differ from the 6 December run's only by the key that run predates.
    assert command == earlier_command().replace(actor_kwargs=command.actor_kwargs)
    # The reference checkpoints of the README's command (docs/reference/README.md): that run,
    # and the same command with --actor mlp.
    mlp = before_clip(actor="mlp")
    for name, config in (("readme-popsan-s0", command), ("readme-mlp-s0", mlp)):
        reference = ROOT / "docs/reference" / name
        assert RunConfig.from_json(reference / "config.json") == config
        assert RunConfig.from_json(reference / "warmup/config.json") == warmup_config(config)
    # The fine-tune as docs/results.md writes it, parsed as train.py parses it.
    text = (ROOT / "docs/results.md").read_text()
    start = text.index("train.py --env franka_pick --warmup-env-steps 0 --name t2-s0")
    line = text[start : text.index(".venv/bin/python eval.py", start)].replace("\\\n", " ")
    args = train_parser().parse_args(line.split()[1:])
    assert args.name == "t2-s0" and args.init_from == "runs/popsan-s0"
    assert args.clip_per_network is False  # the run it starts from had the joint clip
    fine_tune = resolve_config(None, "cpu", *given_flags(args))
    assert RunConfig.from_json(results / "popsan-t2-s0/config.json") == fine_tune
    assert fine_tune.actor_kwargs["timesteps"] == 2 and fine_tune.warmup_env_steps == 0


def test_readme_command_is_the_committed_per_network_clip_stages():
    # docs/results.md, "The per-network clip on all six README stages": each of the six runs is
    # the README's command for its actor and seed as a warm-up followed by the stage started
    # from it. The warm-up is the one the command trained before 8 December (unchanged by the
    # per-network clip, which is the second stage's only), committed beside the earlier stage.
    results = ROOT / "docs/results"
    warm_ups = {
        ("popsan", 0): "../reference/readme-popsan-s0/warmup",
        ("popsan", 1): "readme5/popsan-s1/warmup",
        ("popsan", 2): "stage4m/popsan-s2/warmup",
        ("mlp", 0): "../reference/readme-mlp-s0/warmup",
        ("mlp", 1): "stage4m/mlp-s1/warmup",
        ("mlp", 2): "stage4m/mlp-s2/warmup",
    }
    sources = {("popsan", 0): "runs/popsan-s0/warmup"}
    for (actor, seed), warm_path in warm_ups.items():
        command = resolve_config(None, "cpu", dict(env="franka_pick", actor=actor, seed=seed))
        assert warmup_config(command) == warmup_config(before_clip(actor=actor, seed=seed))
        source = sources.get((actor, seed), f"runs/readme-{actor}-s{seed}/warmup")
        stage = command.replace(init_from=source, init_checkpoint="last", warmup_env_steps=0)
        committed = RunConfig.from_json(results / f"guards/clip-{actor}-s{seed}/config.json")
        assert committed == stage, (actor, seed)
        # as recorded then: with PopSAN's decoder key, or from before it existed
        recorded = (before_clip(actor=actor, seed=seed), earlier_command(actor=actor, seed=seed))
        warm_up = RunConfig.from_json(results / warm_path / "config.json")
        assert warm_up in [warmup_config(c) for c in recorded], (actor, seed)


def test_readme_command_is_the_committed_climb_runs():
    # The three-seed headline (docs/results.md, "Revision 5") was trained on revision 4 with the
    # ramp and the climb term as overrides: the same run config as the README's command, and in
    # both stages the same env (revision 5 made those overrides the defaults).
    for seed in (0, 1, 2):
        path = ROOT / f"docs/results/climb/popsan-climb-s{seed}/config.json"
        committed = RunConfig.from_json(path)
        command = earlier_command(seed=seed).replace(**SECOND_STAGE_2M)
        if seed == 1:  # rerun on 5 December with the plain command of revision 5
            assert committed == command
        else:
            assert committed.env_revision == 4
            ramp_climb = {"lift_ramp": 0.015, "reward_scales": {"climb": 16.0}}
            assert committed.env_overrides == ramp_climb
            assert command == committed.replace(env_overrides={}, env_revision=CURRENT_ENV_REVISION)
        for stage in (lambda c: c, warmup_config):
            assert make_env(stage(committed)).config == make_env(stage(command)).config


def test_pick_warm_up_is_the_revision_2_task():
    # The warm-up's overrides mean exactly what env revision 2 meant (clamped finger targets,
    # no charge on the held cube's speed), as the env itself defines its old revisions, except
    # that it keeps revision 5's shaping (the lift ramp and the climb term).
    revision_5_shaping_undone = envs.legacy_overrides("franka_pick", 4)
    warm = envs.merge_overrides(PICK_RECIPE["warmup_env_overrides"], revision_5_shaping_undone)
    assert warm == envs.legacy_overrides("franka_pick", 2)
    cpu, gpu = resolve_config(None, "cpu"), resolve_config(None, "gpu")
    assert cpu.warmup_env_steps == 6_000_000 and cpu.total_env_steps == 4_000_000
    assert gpu.warmup_env_steps == 4 * cpu.warmup_env_steps
    # Another env and the presets (whole recipes of their own) have no warm-up.
    assert resolve_config(None, "cpu", dict(env="franka_reach")).warmup_env_steps == 0
    assert all(resolve_config(p, "cpu").warmup_env_steps == 0 for p in PRESETS)


def test_documented_t2_fine_tune_is_the_committed_run():
    # docs/results.md's fine-tune command (T = 2 under a spike budget, the energy result) must
    # resolve to the committed t2-s0 config, whose checkpoint is committed beside it.
    committed = RunConfig.from_json(ROOT / "docs/reference/pick-popsan-t2-sop-s0/config.json")
    flags = dict(
        init_from="runs/pick_scale/popsan-s0",
        sop_cost=0.01,
        sop_budget=30000.0,
        actor_lr=1e-4,
        seed=0,
        total_env_steps=4_000_000,
        num_evals=16,
    )
    current = committed.replace(  # trained on revision 1, before the key (1.0: built the same)
        env_revision=CURRENT_ENV_REVISION,
        actor_kwargs={**committed.actor_kwargs, "decoder_init_scale": 1.0},
    )
    for backend in ("cpu", "gpu"):
        assert resolve_config("paper", backend, flags, {"timesteps": 2}) == current, backend


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
    with pytest.raises(ConfigError, match=r"by the 3 devices \(all devices of all processes\)"):
        RunConfig(num_envs=64, batch_size=64, num_minibatches=1).validate(3)
    with pytest.raises(ConfigError, match="unroll_length must be >= 1"):
        RunConfig(unroll_length=0).validate()
    with pytest.raises(ConfigError, match="unknown preset"):
        resolve_config("huge")
    # Per-network clipping clips by max_grad_norm: without a norm it would clip nothing.
    with pytest.raises(ConfigError, match="clip_per_network clips by max_grad_norm, which is None"):
        RunConfig(clip_per_network=True, max_grad_norm=None).validate()
    RunConfig(clip_per_network=False, max_grad_norm=None).validate()
    with pytest.raises(ConfigError, match=r"max_grad_norm must be > 0 \(None: no clip\), got 0.0"):
        RunConfig(max_grad_norm=0.0).validate()
    for name in ("end_at_success", "warmup_end_at_success"):
        with pytest.raises(ConfigError, match=rf"{name} must be in \[0, 1\], got 1.5"):
            RunConfig(**{name: 1.5}).validate()
    # A frozen normaliser needs statistics to keep: a warm start or a warm-up stage, whose own
    # stage (from scratch) then updates its normaliser as usual.
    with pytest.raises(ConfigError, match="freeze_normalizer needs a started normaliser"):
        RunConfig(freeze_normalizer=True).validate()
    chained = resolve_config(None, "cpu", dict(freeze_normalizer=True))
    chained.validate()
    assert not warmup_config(chained).freeze_normalizer
    warmup_config(chained).validate()


@pytest.mark.parametrize("stage, warm_up", [(True, False), (False, True), (True, True)])
def test_each_stage_has_its_own_clip(stage, warm_up):
    chained = RunConfig(
        warmup_env_steps=1000, clip_per_network=stage, warmup_clip_per_network=warm_up
    )
    chained.validate()
    assert warmup_config(chained).clip_per_network is warm_up
    assert not warmup_config(chained).warmup_clip_per_network
    with pytest.raises(ConfigError, match="clip_per_network clips by max_grad_norm"):
        chained.replace(max_grad_norm=None).validate()


def test_json_round_trip_keeps_tuples(tmp_path):
    c = resolve_config("smoke", "cpu", {"env_overrides": {"episode_length": 50}}, {"timesteps": 2})
    c.to_json(tmp_path / "config.json")
    back = RunConfig.from_json(tmp_path / "config.json")
    assert back == c
    assert isinstance(back.actor_kwargs["hidden_sizes"], tuple)
    (tmp_path / "bad.json").write_text(json.dumps({"num_envs": 4, "warp_speed": 9}))
    with pytest.raises(ConfigError, match="unknown config keys: warp_speed"):
        RunConfig.from_json(tmp_path / "bad.json")


def test_config_without_env_revision_rebuilds_the_env_it_was_trained_with(tmp_path):
    # A config.json written before env revisions existed is revision 1: its pick env must come
    # back with the physics it was trained with (one 20 ms substep, MuJoCo's default pad
    # impedance, 200-step episodes), and its own overrides still win.
    fresh = resolve_config(overrides=dict(env="franka_pick"))
    assert fresh.env_revision == CURRENT_ENV_REVISION == 5
    data = fresh.to_dict()
    del data["env_revision"]
    data["env_overrides"] = {"grasp_radius": 0.05}
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))
    old = RunConfig.from_json(path)
    assert old.env_revision == 1
    legacy = envs.legacy_overrides("franka_pick", 1)
    assert legacy["sim_dt"] == 0.02 and legacy["episode_length"] == 200
    assert legacy["finger_target_low"] == 0.0  # later revisions' changes are undone too
    # revisions 3 and 4 each restore a scale: merged, not the newer replacing the older
    assert legacy["reward_scales"] == {"object_speed": 0.0, "climb": 0.0}
    assert legacy["lift_ramp"] == 0.0
    env = make_env(old)
    assert env.config.sim_dt == 0.02 and env.config.episode_length == 200
    assert tuple(env.config.pad_solimp) == (0.9, 0.95, 0.001, 0.5, 2.0)
    assert env.config.grasp_radius == 0.05
    assert env.config.reward_scales.object_speed == 0.0 and env.config.reward_scales.climb == 0.0
    assert env.config.reward_scales.lift == 4.0 and env.config.lift_ramp == 0.0
    current = make_env(fresh)
    assert current.config.sim_dt == 0.01 and current.config.episode_length == 250
    assert current.config.lift_ramp == 0.015 and current.config.reward_scales.climb == 16.0
    assert envs.legacy_overrides("franka_pick", 5) == {}
    with pytest.raises(envs.EnvConfigError, match="revisions 1..5"):
        envs.legacy_overrides("franka_pick", 6)


def test_current_env_revision_is_every_env_s_revision():
    assert envs.FrankaPick.revision == envs.FrankaReach.revision == CURRENT_ENV_REVISION


def test_documented_mlp_fine_tune_is_the_committed_three_seeds(tmp_path, monkeypatch):
    # docs/results.md's one-command MLP recipe ("One command, three seeds"), parsed as train.py
    # parses it, must resolve to the three committed configs; `--seed K` changes only the seed.
    monkeypatch.chdir(ROOT)  # --init-from names the committed reference run relative to it
    for seed in (0, 1, 2):
        name = f"mlp-critwu5-lr1e4-s{seed}"
        argv = ["--env", "franka_pick", "--actor", "mlp", "--name", name, "--seed", str(seed)]
        argv += ["--warmup-env-steps", "0", "--init-from", "docs/reference/pick-mlp-s0"]
        argv += ["--init-checkpoint", "last", "--critic-warmup-env-steps", "491520"]
        argv += ["--total-env-steps", "2500000", "--actor-lr", "1e-4", "--num-evals", "10"]
        argv += ["--clip-per-network", "false"]
        args = train_parser().parse_args([*argv, "--runs-dir", str(tmp_path)])
        config, run_dir = prepare_run("cpu", *given_flags(args), **run_choices(args))
        committed = RunConfig.from_json(ROOT / f"docs/results/climb/{name}/config.json")
        # The runs predate the MLP's output_init_scale, which a started run's loaded weights
        # make moot (warm_start.FREE_ACTOR_KWARGS); the command now records the default.
        assert config.actor_kwargs == {**committed.actor_kwargs, "output_init_scale": 0.01}
        # ... and the recipe's per-network clip (8 December), which the command states off.
        assert args.clip_per_network is False
        assert config.replace(actor_kwargs=committed.actor_kwargs) == committed
        assert run_dir == tmp_path / name
        assert committed.critic_warmup_env_steps == 491520 and committed.seed == seed
