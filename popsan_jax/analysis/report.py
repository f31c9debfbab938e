"""What eval.py does: evaluate one checkpoint (report, tracking figure, energy table, latency,
video), rank every kept checkpoint, compare the training curves of several runs, or export a
PopSAN checkpoint to NIR (:mod:`popsan_jax.analysis.nir_export`).

Outputs go into the run directory: ``eval_<tag>.json`` (report, energy rows, latency),
``tracking_<tag>.png``, ``energy_<tag>.md``/``.csv``; the ranking writes
``eval_checkpoints<suffix>.json``/``.md``. ``<tag>`` is the checkpoint (``last``, ``best``,
``step_<N>``) plus ``+stochastic``, ``+seed<N>`` (N > 0) and the env overrides, so the plain
(deterministic, seed 0) evaluation is never overwritten. Progress and tables go to ``say``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax

from popsan_jax.analysis import checkpoint_sweep, energy, evaluation, latency, nir_export, plots
from popsan_jax.analysis.sample_efficiency import sample_efficiency_table
from popsan_jax.analysis.video import render_video
from popsan_jax.cli import overrides_tag
from popsan_jax.config import RunConfig
from popsan_jax.errors import UserError
from popsan_jax.io import check_output_file, check_writable, write_json
from popsan_jax.training.checkpoint import load_run

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")
Say = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


@dataclasses.dataclass(frozen=True)
class EvalOptions:
    """One evaluation's choices (eval.py's flags).

    ``which``: ``"last"``, ``"best"`` or an env-step count; ``all_checkpoints`` ranks every
    kept checkpoint instead. ``energy_timesteps``: the PopSAN T values of the energy table.
    ``ann_run``: an MLP run whose hidden sizes define the ANN baseline. ``export_nir``: write
    the checkpoint as a NIR graph (this ``.nir`` path) and its ``.json`` sidecar, nothing else.
    """

    which: str | int = "last"
    all_checkpoints: bool = False
    episodes: int = 1000
    stochastic: bool = False
    seed: int = 0
    energy_timesteps: tuple[int, ...] = (1, 2, 3, 4, 5)
    ann_run: str | None = None
    video: str | None = None
    energy: bool = True
    latency: bool = True
    tracking: bool = True
    env_overrides: dict[str, Any] = dataclasses.field(default_factory=dict)
    latency_repeats: int = 100
    export_nir: str | None = None

    @classmethod
    def from_flags(cls, args: argparse.Namespace) -> EvalOptions:
        """The options of eval.py's parsed flags (:func:`popsan_jax.cli.eval_parser`)."""
        return cls(
            which="best" if args.best else (args.step if args.step is not None else "last"),
            all_checkpoints=args.all_checkpoints,
            episodes=args.episodes,
            stochastic=args.stochastic,
            seed=args.seed,
            energy_timesteps=tuple(args.energy_timesteps),
            ann_run=args.ann_run,
            video=args.video,
            energy=not args.no_energy,
            latency=not args.no_latency,
            tracking=not args.no_tracking,
            env_overrides=dict(args.env_override),
            latency_repeats=args.latency_repeats,
            export_nir=args.export_nir,
        )

    @property
    def suffix(self) -> str:
        """``+stochastic``, ``+seed<N>`` and the env overrides, in that order ('' for none)."""
        policy = "+stochastic" if self.stochastic else ""
        seed = f"+seed{self.seed}" if self.seed else ""  # a re-check on other episodes
        return policy + seed + overrides_tag(self.env_overrides)


def ann_hidden_sizes(ann_run: str | None) -> tuple[int, ...] | None:
    """Hidden sizes of the MLP run ``ann_run`` (None: none given); a PopSAN run is refused."""
    if not ann_run:
        return None
    config = RunConfig.from_json(Path(ann_run) / "config.json")
    if config.actor != "mlp":
        raise UserError(f"--ann-run {ann_run} is a {config.actor!r} run, not an MLP")
    return tuple(config.actor_kwargs["hidden_sizes"])


def evaluate(
    run_dir: str | Path, options: EvalOptions, environment: Any = None, say: Say = _quiet
) -> dict[str, Any]:
    """Evaluate one checkpoint of ``run_dir`` (or rank them all); returns the written report.

    With ``options.export_nir`` it only exports the checkpoint to NIR and returns the two paths.
    """
    if options.export_nir:
        return export_nir(run_dir, options, say)
    if options.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {options.episodes}")
    ann_hidden = ann_hidden_sizes(options.ann_run)
    run_dir = Path(run_dir)
    if run_dir.is_dir():  # the reports go into it: found read-only now, not after the work
        check_writable(run_dir, "run directory")
    if options.video:
        check_output_file(options.video, "--video")
    if options.all_checkpoints:
        return rank_checkpoints(run_dir, options, environment, say)
    tag = evaluation.checkpoint_label(options.which) + options.suffix
    overrides = dict(options.env_overrides)
    t0 = time.monotonic()
    loaded = load_run(run_dir, options.which, environment=environment, env_overrides=overrides)
    say(
        f"loaded {run_dir} ({tag}, env step {loaded.step}); compiling and running "
        f"{options.episodes} episodes"
    )
    key, k_eval = evaluation.episode_keys(options.seed)
    deterministic = not options.stochastic
    batch = jax.device_get(
        evaluation.rollouts(loaded, options.episodes, k_eval, deterministic, record=True)
    )
    report = dict(
        run_dir=str(run_dir),
        which=tag,
        env_steps=loaded.step,
        policy="stochastic" if options.stochastic else "deterministic",
        seed=options.seed,
        actor=loaded.config.actor,
        timesteps=evaluation.trained_timesteps(loaded.config),
        env_overrides=overrides,
        **evaluation.summarize(batch),
    )
    say(evaluation.format_report(report))
    shown = evaluation.showcase_index(batch)
    episode = evaluation.episode_arrays(batch, shown)
    outcome = "success" if batch.success[shown] > 0 else "no success"
    if options.tracking:
        path = plots.plot_tracking(
            episode,
            run_dir / f"tracking_{tag}.png",
            goal_z=getattr(loaded.env, "goal_z", None),
            dt=getattr(loaded.env.config, "ctrl_dt", None),
            title=f"{run_dir.name} ({tag}), episode {shown} ({outcome})",
        )
        say(f"wrote {path}")
    if options.energy and loaded.config.actor == "popsan":
        timesteps = list(options.energy_timesteps)
        say(f"energy sweep over T = {timesteps} ({options.episodes} episodes each)")
        rows = evaluation.energy_sweep(
            loaded,
            timesteps,
            options.episodes,
            key,
            ann_hidden,
            deterministic,
            batch,
            progress=lambda msg: say(f"  {msg}"),
        )
        md = energy.energy_markdown(rows, f"Energy per inference, {run_dir.name} ({tag})")
        (run_dir / f"energy_{tag}.md").write_text(md)
        energy.write_energy_csv(rows, run_dir / f"energy_{tag}.csv")
        report["energy"] = rows
        say(md)
    elif options.energy:
        say("energy table skipped: it needs a PopSAN run (this run's actor is an MLP)")
    if options.latency:
        actors = evaluation.latency_actors(loaded, ann_hidden)
        rows = latency.latency_table(
            actors, loaded.env.observation_size, repeats=options.latency_repeats
        )
        report["latency"] = rows
        say(latency.format_latency(rows))
    if options.video:
        dt = float(getattr(loaded.env.config, "ctrl_dt", 0.02))
        qpos = episode["qpos"]
        try:
            path, backend = render_video(
                loaded.env.mj_model,
                qpos,
                options.video,
                fps=1.0 / dt,
                mocap_pos=episode.get("mocap_pos"),
            )
        except UserError as e:  # the finished evaluation's report is written all the same
            report.update(video_error=str(e), wall_s=time.monotonic() - t0)
            say(f"wrote {write_json(run_dir / f'eval_{tag}.json', report)}")
            raise
        report["video"] = str(path)
        say(f"wrote {path} (episode {shown}, {outcome}, {len(qpos)} frames, {backend} GL)")
    report["wall_s"] = time.monotonic() - t0
    path = write_json(run_dir / f"eval_{tag}.json", report)
    say(f"wrote {path}")
    return report


def export_nir(run_dir: str | Path, options: EvalOptions, say: Say = _quiet) -> dict[str, str]:
    """``--export-nir PATH``: the chosen checkpoint as a NIR graph + sidecar (README, NIR).

    An MLP run, an unloadable checkpoint or a path not ending in ``.nir`` raise UserError.
    """
    if options.all_checkpoints:
        raise UserError(
            "--export-nir exports one checkpoint: give --best or --step N, not --all-checkpoints"
        )
    graph, side = nir_export.export_run_nir(run_dir, options.export_nir, options.which)
    say(f"wrote {graph} and {side}")
    return dict(nir=str(graph), sidecar=str(side))


def rank_checkpoints(
    run_dir: Path, options: EvalOptions, environment: Any = None, say: Say = _quiet
) -> dict[str, Any]:
    """Every kept checkpoint over the episodes of ``--step N``; JSON + markdown."""
    if options.video:
        raise UserError("--video needs one checkpoint: use --step N, not --all-checkpoints")
    tag = "checkpoints" + options.suffix
    overrides = dict(options.env_overrides)
    t0 = time.monotonic()
    say(f"evaluating every kept checkpoint of {run_dir} on {options.episodes} episodes")
    _, k_eval = evaluation.episode_keys(options.seed)  # the episodes of --step N
    result = checkpoint_sweep.evaluate_checkpoints(
        run_dir,
        options.episodes,
        k_eval,
        deterministic=not options.stochastic,
        environment=environment,
        env_overrides=overrides,
        progress=lambda msg: say(f"  {msg}"),
    )
    md = checkpoint_sweep.checkpoints_markdown(
        result, f"Kept checkpoints of {run_dir.name} ({tag})"
    )
    (run_dir / f"eval_{tag}.md").write_text(md)
    report = dict(
        run_dir=str(run_dir),
        which=tag,
        policy="stochastic" if options.stochastic else "deterministic",
        seed=options.seed,
        env_overrides=overrides,
        **result,
        wall_s=time.monotonic() - t0,
    )
    path = write_json(run_dir / f"eval_{tag}.json", report)
    say(md)
    say(f"wrote {path} and {path.with_suffix('.md')}; chosen: --step {result['chosen_step']}")
    return report


def compare(runs: Sequence[str | Path], out: str | Path | None, say: Say = _quiet) -> str:
    """Curves figure, and the sample-efficiency table written beside it (``.md``); returns it."""
    out = Path(out or "compare.png")
    if out.suffix.lower() not in FIGURE_SUFFIXES:
        # The table is written to the figure's path with .md: a .md figure would be overwritten.
        raise UserError(
            f"--out is the figure's path ({', '.join(FIGURE_SUFFIXES)}); got {str(out)!r}"
        )
    check_output_file(out, "--out")  # before the runs are read
    check_output_file(out.with_suffix(".md"), "--out table")
    curves = [plots.read_run_curves(r) for r in runs]
    path = plots.plot_compare(curves, out)
    table = sample_efficiency_table(curves)
    path.with_suffix(".md").write_text(table + "\n")
    say(table)
    say(f"wrote {path} and {path.with_suffix('.md')}")
    return table
