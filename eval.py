"""Evaluate a saved run: report, tracking figure, energy table, latency, video; or compare runs.

    python eval.py runs/<dir> [--best | --step N | --all-checkpoints] [--episodes 1000]
                   [--stochastic] [--seed N]
                   [--timesteps 1,2,3,4,5] [--ann-run runs/<mlp dir>] [--video out.mp4]
                   [--no-energy] [--no-latency] [--no-tracking] [--env-override KEY=VALUE]
    python eval.py --compare runs/a runs/b ... [--out compare.png]

Outputs go into the run directory: ``eval_<which>.json`` (report, energy rows, latency),
``tracking_<which>.png``, ``energy_<which>.md`` and ``.csv``. ``--env-override`` evaluates under
changed env settings (merged over the run's own) and appends them to ``<which>``, e.g.
``eval_last+grasp_radius=0.0.json``, as ``--stochastic`` appends ``+stochastic`` and ``--seed N``
(N > 0) ``+seedN``, so the plain (deterministic, seed 0) evaluation is never overwritten.
``--all-checkpoints`` evaluates every kept checkpoint on the same episodes (success, length,
return; no energy, latency or figures) and writes ``eval_checkpoints.json`` and ``.md`` with the
checkpoint of highest success; its full evaluation is then ``--step N``, and a re-check on other
episodes ``--step N --seed 1`` (it was selected on these).
``--compare`` writes the curves figure and, beside it (``compare.md``), the table of env steps
to the first 50/80/90 % success per run and per actor.
Video rendering needs EGL or OSMesa (CPU machines: ``apt-get install -y libosmesa6``); see
popsan_jax/video.py.
A UserError (missing/corrupt/incompatible checkpoint, bad flag value) prints ``error: <msg>``
and exits 2; argparse rejects unknown flags with exit 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from popsan_jax.cli import add_env_override_flag, overrides_tag
from popsan_jax.errors import UserError

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("run_dir", nargs="?", help="run directory with config.json and checkpoints/")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--best", action="store_true", help="best checkpoint by success rate")
    which.add_argument("--step", type=int, help="checkpoint at this env step (default: last)")
    which.add_argument(
        "--all-checkpoints",
        action="store_true",
        help="rank every kept checkpoint by success on the same episodes",
    )
    p.add_argument("--episodes", type=int, default=1000, help="evaluation episodes (default 1000)")
    p.add_argument("--stochastic", action="store_true", help="sample actions (default: mean)")
    p.add_argument("--seed", type=int, default=0, help="episode seed (not 0: appends +seedN)")
    p.add_argument("--timesteps", default="1,2,3,4,5", help="T values of the energy table")
    p.add_argument("--ann-run", help="MLP run whose hidden sizes define the ANN baseline")
    p.add_argument("--video", metavar="OUT", help="render one episode to this .mp4/.gif")
    p.add_argument("--no-energy", action="store_true", help="skip the energy table")
    p.add_argument("--no-latency", action="store_true", help="skip the latency table")
    p.add_argument("--no-tracking", action="store_true", help="skip the tracking figure")
    add_env_override_flag(p, "evaluate with this env config value (repeatable)")
    p.add_argument("--latency-repeats", type=int, default=100, help=argparse.SUPPRESS)
    p.add_argument(
        "--compare",
        nargs="+",
        metavar="RUN",
        help="plot training curves of runs and tabulate steps to 50/80/90 %% success",
    )
    p.add_argument(
        "--out", help="figure path for --compare: .png, .pdf or .svg (default compare.png)"
    )
    return p


def parse_timesteps(text: str) -> list[int]:
    try:
        values = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise UserError(f"--timesteps must be positive integers like 1,2,3, got {text!r}")
    return values


def compare(runs: list[str], out: str | None) -> None:
    """Curves figure, and the sample-efficiency table printed and written beside it (``.md``)."""
    from popsan_jax.analysis import plots
    from popsan_jax.analysis.sample_efficiency import sample_efficiency_table

    out = Path(out or "compare.png")
    if out.suffix.lower() not in FIGURE_SUFFIXES:
        # The table is written to the figure's path with .md: a .md figure would be overwritten.
        raise UserError(
            f"--out is the figure's path ({', '.join(FIGURE_SUFFIXES)}); got {str(out)!r}"
        )
    curves = [plots.read_run_curves(r) for r in runs]
    path = plots.plot_compare(curves, out)
    table = sample_efficiency_table(curves)
    path.with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"wrote {path} and {path.with_suffix('.md')}")


def evaluate(args: argparse.Namespace, environment: Any = None) -> dict[str, Any]:
    from popsan_jax.jax_setup import import_mjx_quietly

    import_mjx_quietly()  # before brax/MJX modules import it noisily
    import jax

    from popsan_jax.analysis import energy, evaluation, latency, plots
    from popsan_jax.config import RunConfig
    from popsan_jax.jax_setup import enable_compilation_cache
    from popsan_jax.training.checkpoint import load_run

    if args.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {args.episodes}")
    timesteps = parse_timesteps(args.timesteps)
    ann_hidden = None
    if args.ann_run:
        ann_cfg = RunConfig.from_json(Path(args.ann_run) / "config.json")
        if ann_cfg.actor != "mlp":
            raise UserError(f"--ann-run {args.ann_run} is a {ann_cfg.actor!r} run, not an MLP")
        ann_hidden = tuple(ann_cfg.actor_kwargs["hidden_sizes"])
    enable_compilation_cache()
    which = "best" if args.best else (args.step if args.step is not None else "last")
    overrides = dict(args.env_override)
    policy = "+stochastic" if args.stochastic else ""
    seed = f"+seed{args.seed}" if args.seed else ""  # a re-check on other episodes sits beside
    suffix = policy + seed + overrides_tag(overrides)
    run_dir = Path(args.run_dir)
    if args.all_checkpoints:
        return rank_checkpoints(args, run_dir, "checkpoints" + suffix, overrides, environment)
    tag = evaluation.checkpoint_label(which) + suffix
    t0 = time.monotonic()
    loaded = load_run(run_dir, which, environment=environment, env_overrides=overrides)
    print(
        f"loaded {run_dir} ({tag}, env step {loaded.step}); compiling and running "
        f"{args.episodes} episodes",
        flush=True,
    )
    key, k_eval = evaluation.episode_keys(args.seed)
    batch = jax.device_get(
        evaluation.rollouts(loaded, args.episodes, k_eval, not args.stochastic, record=True)
    )
    report = dict(
        run_dir=str(run_dir),
        which=tag,
        env_steps=loaded.step,
        policy="stochastic" if args.stochastic else "deterministic",
        seed=args.seed,
        actor=loaded.config.actor,
        timesteps=evaluation.trained_timesteps(loaded.config),
        env_overrides=overrides,
        **evaluation.summarize(batch),
    )
    print(evaluation.format_report(report))
    shown = evaluation.showcase_index(batch)
    episode = evaluation.episode_arrays(batch, shown)
    outcome = "success" if batch.success[shown] > 0 else "no success"
    if not args.no_tracking:
        path = plots.plot_tracking(
            episode,
            run_dir / f"tracking_{tag}.png",
            goal_z=getattr(loaded.env, "goal_z", None),
            dt=getattr(loaded.env.config, "ctrl_dt", None),
            title=f"{run_dir.name} ({tag}), episode {shown} ({outcome})",
        )
        print(f"wrote {path}")
    if not args.no_energy and loaded.config.actor == "popsan":
        print(f"energy sweep over T = {timesteps} ({args.episodes} episodes each)")
        rows = evaluation.energy_sweep(
            loaded,
            timesteps,
            args.episodes,
            key,
            ann_hidden,
            not args.stochastic,
            batch,
            progress=lambda msg: print(f"  {msg}", flush=True),
        )
        md = energy.energy_markdown(rows, f"Energy per inference, {run_dir.name} ({tag})")
        (run_dir / f"energy_{tag}.md").write_text(md)
        energy.write_energy_csv(rows, run_dir / f"energy_{tag}.csv")
        report["energy"] = rows
        print(md)
    elif not args.no_energy:
        print("energy table skipped: it needs a PopSAN run (this run's actor is an MLP)")
    if not args.no_latency:
        actors = evaluation.latency_actors(loaded, ann_hidden)
        rows = latency.latency_table(
            actors, loaded.env.observation_size, repeats=args.latency_repeats
        )
        report["latency"] = rows
        print(latency.format_latency(rows))
    if args.video:
        from popsan_jax.analysis.video import render_video

        dt = float(getattr(loaded.env.config, "ctrl_dt", 0.02))
        qpos = episode["qpos"]
        path, backend = render_video(
            loaded.env.mj_model,
            qpos,
            args.video,
            fps=1.0 / dt,
            mocap_pos=episode.get("mocap_pos"),
        )
        report["video"] = str(path)
        print(f"wrote {path} (episode {shown}, {outcome}, {len(qpos)} frames, {backend} GL)")
    report["wall_s"] = time.monotonic() - t0
    path = evaluation.write_json(run_dir / f"eval_{tag}.json", report)
    print(f"wrote {path}")
    return report


def rank_checkpoints(
    args: argparse.Namespace,
    run_dir: Path,
    tag: str,
    overrides: dict[str, Any],
    environment: Any,
) -> dict[str, Any]:
    """``--all-checkpoints``: every kept checkpoint over the same episodes; JSON + markdown."""
    from popsan_jax.analysis import checkpoint_sweep, evaluation

    if args.video:
        raise UserError("--video needs one checkpoint: use --step N, not --all-checkpoints")
    t0 = time.monotonic()
    print(f"evaluating every kept checkpoint of {run_dir} on {args.episodes} episodes", flush=True)
    _, k_eval = evaluation.episode_keys(args.seed)  # the episodes of --step N
    result = checkpoint_sweep.evaluate_checkpoints(
        run_dir,
        args.episodes,
        k_eval,
        deterministic=not args.stochastic,
        environment=environment,
        env_overrides=overrides,
        progress=lambda msg: print(f"  {msg}", flush=True),
    )
    md = checkpoint_sweep.checkpoints_markdown(
        result, f"Kept checkpoints of {run_dir.name} ({tag})"
    )
    (run_dir / f"eval_{tag}.md").write_text(md)
    report = dict(
        run_dir=str(run_dir),
        which=tag,
        policy="stochastic" if args.stochastic else "deterministic",
        seed=args.seed,
        env_overrides=overrides,
        **result,
        wall_s=time.monotonic() - t0,
    )
    path = evaluation.write_json(run_dir / f"eval_{tag}.json", report)
    print(md)
    print(f"wrote {path} and {path.with_suffix('.md')}; chosen: --step {result['chosen_step']}")
    return report


def main(argv: list[str] | None = None, environment: Any = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.compare and not args.run_dir:
        parser.error("give a run directory, or --compare RUN [RUN ...]")
    try:
        if args.compare:
            compare(args.compare + ([args.run_dir] if args.run_dir else []), args.out)
        else:
            evaluate(args, environment)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
