"""Sample efficiency from training curves: env steps to the first evaluation at a success level.

The issue-6 target compares PopSAN with the ANN on env steps to first reach 80 % success; this
module reads it off the ``eval`` lines (``RunCurves``) of several seeds and summarises per actor
(mean and range over seeds) with the PopSAN / ANN ratio of the means.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from popsan_jax.plots import RunCurves

DEFAULT_LEVELS = (0.5, 0.8, 0.9)
ACTOR_NAMES = {"popsan": "PopSAN", "mlp": "MLP"}


def first_steps_at(curves: RunCurves, level: float) -> float | None:
    """Env steps of the first evaluation whose success rate is >= ``level``; None if none is.

    NaN success rates (an env without a success metric) never count as reaching the level.
    """
    success = curves.values["success_rate"]
    reached = np.flatnonzero(np.nan_to_num(success, nan=-1.0) >= level)
    return float(curves.env_steps[reached[0]]) if reached.size else None


def _steps(value: float | None) -> str:
    return "—" if value is None else f"{value / 1e6:.2f} M"


def _summary(values: list[float | None]) -> tuple[str, float | None]:
    """``"mean (min–max)"`` over the runs that reached the level, and the mean when all did."""
    reached = [v for v in values if v is not None]
    if not reached:
        return f"— (0 of {len(values)})", None
    mean = sum(reached) / len(reached)
    text = _steps(mean)
    if len(reached) > 1:
        text += f" ({min(reached) / 1e6:.2f}–{max(reached) / 1e6:.2f})"
    if len(reached) < len(values):
        return f"{text} ({len(reached)} of {len(values)} reached)", None
    return text, mean


def sample_efficiency_table(
    runs: Sequence[RunCurves], levels: Sequence[float] = DEFAULT_LEVELS
) -> str:
    """Markdown table: per run, per actor (mean and range over runs), and PopSAN / MLP.

    The ratio row is the ratio of the per-actor means; it is left out (—) at a level that some
    run of either actor never reached, since a mean over the runs that did would flatter it.
    """
    if not runs:
        raise ValueError("no runs to compare")
    heads = " | ".join(f"≥ {level:.0%}" for level in levels)
    lines = [
        "env steps to the first training evaluation at or above each success level",
        "",
        f"| run | actor | {heads} | best success (env steps) |",
        "|---|---|" + "---:|" * len(levels) + "---|",
    ]
    firsts = {id(run): [first_steps_at(run, level) for level in levels] for run in runs}
    for run in runs:
        cells = " | ".join(_steps(v) for v in firsts[id(run)])
        success = run.values["success_rate"]
        if np.all(np.isnan(success)):
            best = "—"
        else:
            k = int(np.nanargmax(success))
            best = f"{success[k]:.3f} ({_steps(float(run.env_steps[k]))})"
        lines.append(f"| {run.label} | {run.actor} | {cells} | {best} |")
    means: dict[str, list[float | None]] = {}
    for actor in dict.fromkeys(run.actor for run in runs):
        group = [firsts[id(run)] for run in runs if run.actor == actor]
        summaries = [_summary([g[i] for g in group]) for i in range(len(levels))]
        means[actor] = [mean for _, mean in summaries]
        cells = " | ".join(text for text, _ in summaries)
        name = ACTOR_NAMES.get(actor, actor)
        lines.append(f"| mean (range), {len(group)} run(s) | {name} | {cells} | |")
    if "popsan" in means and "mlp" in means:
        ratios = [
            "—" if p is None or m is None or m == 0 or math.isnan(p / m) else f"**{p / m:.2f}**"
            for p, m in zip(means["popsan"], means["mlp"], strict=True)
        ]
        lines.append(f"| PopSAN / MLP, ratio of means | | {' | '.join(ratios)} | |")
    return "\n".join(lines)
