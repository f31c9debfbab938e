"""Figures: fingertip/object tracking of one episode (paper Fig. 6) and training-curve comparison
of several runs (paper Figs. 3-5).

matplotlib's Agg backend is selected inside each function (not at import), so importing this
module never touches a display or changes a caller's backend choice before it is needed.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from popsan_jax.errors import CheckpointError, UserError
from popsan_jax.io import read_jsonl
from popsan_jax.schema import check_metrics_record
from popsan_jax.training.checkpoint_index import WARMUP

ACTOR_COLOURS = {"popsan": "tab:red", "mlp": "tab:blue"}
CURVE_KEYS = (
    ("success_rate", "success rate (held at the goal to the end)"),
    ("reached_rate", "reached (PixMC's latch)"),
    ("episode_length", "episode length (steps)"),
    ("episode_reward", "episode reward"),
)


def _pyplot() -> Any:
    # Imported on first use, to select Agg only then (module docstring).
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_tracking(
    info: Mapping[str, np.ndarray],
    path: str | os.PathLike,
    goal_z: float | None = None,
    dt: float | None = None,
    title: str | None = None,
) -> Path:
    """Write the tracking figure of ONE episode as PNG.

    Args:
      info: ``[T, 3]`` arrays of the episode's alive steps. Pick: ``left_tip``, ``right_tip``,
        ``object_pos``; reach: ``tip_mid``, ``target_pos``.
      path: output PNG.
      goal_z: goal height; with ``object_pos`` it adds the object-height-vs-goal panel.
      dt: seconds per control step for the time axis (steps when None).
      title: figure title.
    """
    plt = _pyplot()
    if "object_pos" in info:
        reference, ref_label = np.asarray(info["object_pos"]), "object"
        followers = [
            ("left_tip", "left finger", "tab:blue"),
            ("right_tip", "right finger", "purple"),
        ]
    elif "target_pos" in info:
        reference, ref_label = np.asarray(info["target_pos"]), "target"
        followers = [("tip_mid", "fingertip midpoint", "tab:blue")]
    else:
        raise ValueError(f"no object_pos or target_pos among recorded keys {sorted(info)}")
    steps = reference.shape[0]
    t = np.arange(steps) * (dt or 1.0)
    height_panel = goal_z is not None and "object_pos" in info
    ncols = 4 if height_panel else 3
    fig, axes = plt.subplots(1, ncols, figsize=(4.2 * ncols, 3.6), constrained_layout=True)
    for axis, ax in enumerate(axes[:3]):
        ax.plot(t, reference[:, axis], color="tab:red", lw=2, label=f"{ref_label} position")
        for key, label, colour in followers:
            ax.plot(t, np.asarray(info[key])[:, axis], color=colour, lw=1.2, label=label)
        ax.set_title(f"position tracking {'XYZ'[axis]}")
        ax.set_xlabel("time (s)" if dt else "control step")
        ax.set_ylabel(f"{'XYZ'[axis]} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if height_panel:
        ax = axes[3]
        ax.plot(t, np.full(steps, float(goal_z)), color="tab:green", lw=2, label="goal height")
        ax.plot(t, reference[:, 2], "--", color="tab:red", lw=1.5, label="object height")
        ax.set_title("target height tracking")
        ax.set_xlabel("time (s)" if dt else "control step")
        ax.set_ylabel("Z (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, plt, path)


@dataclass
class RunCurves:
    """Evaluation curves of one run, read from its ``metrics.jsonl`` and ``config.json``."""

    label: str
    actor: str
    env_steps: np.ndarray
    values: dict[str, np.ndarray] = field(default_factory=dict)
    warmup_steps: float = 0.0  # env steps of the run's warm-up stage (training/stages.py)


def read_run_curves(run_dir: str | os.PathLike) -> RunCurves:
    """Read the ``eval`` lines of ``run_dir/metrics.jsonl`` (actor name from ``config.json``).

    For a run with a warm-up stage (``run_dir/warmup/``), ``env_steps`` count the warm-up's too:
    the run's own evaluations sit after the warm-up's last env step, so "env steps to 90 %" is the
    run's whole cost. The warm-up's own evaluations (on the gentler env) are not curve points.
    """
    run_dir = Path(run_dir)
    metrics = run_dir / "metrics.jsonl"
    if not metrics.is_file():
        raise CheckpointError(f"{run_dir} has no metrics.jsonl; is it a run directory?")
    actor, revision = "?", None
    config = run_dir / "config.json"
    if config.is_file():
        try:
            data = json.loads(config.read_text())
        except (OSError, ValueError) as e:  # ValueError: bad JSON, or bytes that are not UTF-8
            raise CheckpointError(f"cannot read {config}: {e}") from e
        if not isinstance(data, dict):
            raise CheckpointError(f"{config} is not a JSON object")
        actor = str(data.get("actor", "?"))
        revision = data.get("env_revision", 1)
    rows = [r for r in read_jsonl(metrics, check_metrics_record) if r.get("kind") == "eval"]
    if not rows:
        raise CheckpointError(f"{metrics} has no eval lines to plot")
    rows.sort(key=lambda r: r["env_steps"])
    values = {
        key: np.asarray([r.get(key, np.nan) for r in rows], dtype=float) for key, _ in CURVE_KEYS
    }
    if revision == 1:
        # Runs of env revision 1 logged PixMC's latch as "success_rate": it is their "reached";
        # their pick-and-hold success was never measured during training.
        values["reached_rate"] = values["success_rate"]
        values["success_rate"] = np.full_like(values["success_rate"], np.nan)
    warmup = _warmup_steps(run_dir)
    steps = warmup + np.asarray([r["env_steps"] for r in rows], dtype=float)
    return RunCurves(run_dir.name, actor, steps, values, warmup_steps=warmup)


def _warmup_steps(run_dir: Path) -> float:
    """The last env step of ``run_dir``'s warm-up stage (0.0 when it has none)."""
    metrics = run_dir / WARMUP / "metrics.jsonl"
    if not metrics.is_file():
        return 0.0
    rows = read_jsonl(metrics, check_metrics_record)
    return float(max((r["env_steps"] for r in rows), default=0))


def plot_compare(runs: Sequence[RunCurves], path: str | os.PathLike) -> Path:
    """Training curves of several runs on shared axes, coloured by actor (PopSAN vs ANN)."""
    if not runs:
        raise ValueError("no runs to compare")
    plt = _pyplot()
    # The legend sits under the panels: inside the success panel it hid the curves at 6 runs.
    legend_cols = min(len(runs), 3)
    legend_in = 0.22 * -(-len(runs) // legend_cols) + 0.15
    fig, axes = plt.subplots(1, len(CURVE_KEYS), figsize=(5 * len(CURVE_KEYS), 3.8 + legend_in))
    styles = ["-", "--", ":", "-."]
    seen: dict[str, int] = {}
    for run in runs:
        k = seen.get(run.actor, 0)
        seen[run.actor] = k + 1
        colour = ACTOR_COLOURS.get(run.actor, f"C{2 + len(seen)}")
        name = {"popsan": "PopSAN (SNN)", "mlp": "MLP (ANN)"}.get(run.actor, run.actor)
        for ax, (key, _) in zip(axes, CURVE_KEYS, strict=True):
            ax.plot(
                run.env_steps,
                run.values[key],
                styles[k % len(styles)],
                color=colour,
                marker="o",
                ms=3,
                label=f"{name}: {run.label}",
            )
            if run.warmup_steps:  # where the run's own stage began
                ax.axvline(run.warmup_steps, color=colour, lw=0.8, alpha=0.5, ls=":")
    from matplotlib.ticker import EngFormatter  # after _pyplot() chose the backend

    for ax, (_, ylabel) in zip(axes, CURVE_KEYS, strict=True):
        ax.set_xlabel("env steps")
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 400k, 20M: raw counts overlap
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    for ax in axes[:2]:
        ax.set_ylim(-0.03, 1.03)  # success and reached rates are fractions
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=legend_cols, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, legend_in / fig.get_figheight(), 1, 1))
    return _save(fig, plt, path)


def _save(fig: Any, plt: Any, path: str | os.PathLike) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    except OSError as e:  # a full disk or a folder taken away meanwhile
        raise UserError(f"cannot write figure {path}: {e.strerror or e}") from e
    finally:
        plt.close(fig)
    return path
