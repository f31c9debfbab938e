"""Sample efficiency from training curves: env steps to the first evaluation at a success level.

The issue-6 target compares PopSAN with the ANN on env steps to first reach 80 % success; this
module reads it off the ``eval`` lines (``RunCurves``) of several seeds and summarises per actor
(mean and range over seeds) with the PopSAN / ANN ratio of the means.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from popsan_jax.analysis.plots import RunCurves

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


def _summary(values: list[float | None], lasts: list[float]) -> tuple[str, float, bool]:
    """``"mean (min–max)"`` over the runs, the mean, and whether it is exact.

    A run that never reached the level is censored: it needs more steps than its last evaluation,
    so with its last step counted the mean becomes a lower bound (``"≥ …"``, exact = False).
    """
    filled = [v if v is not None else last for v, last in zip(values, lasts, strict=True)]
    mean = sum(filled) / len(filled)
    text = _steps(mean)
    if len(filled) > 1:
        text += f" ({min(filled) / 1e6:.2f}–{max(filled) / 1e6:.2f})"
    reached = sum(v is not None for v in values)
    if reached == len(values):
        return text, mean, True
    return f"≥ {text}, {reached} of {len(values)} reached", mean, False


def _ratio(popsan: tuple[float, bool], mlp: tuple[float, bool]) -> str:
    """PopSAN / MLP mean; a bound when one side is a lower bound, — when both are."""
    (p, p_exact), (m, m_exact) = popsan, mlp
    if m <= 0 or not (p_exact or m_exact):
        return "—"
    prefix = "" if p_exact and m_exact else ("≤ " if p_exact else "≥ ")
    return f"**{prefix}{p / m:.2f}**"


def sample_efficiency_table(
    runs: Sequence[RunCurves], levels: Sequence[float] = DEFAULT_LEVELS
) -> str:
    """Markdown table: per run, per actor (mean and range over runs), and PopSAN / MLP.

    A run that never reached a level counts with its last evaluated step, which makes its actor's
    mean a lower bound; the ratio of the means is then an upper (MLP censored) or lower (PopSAN
    censored) bound, and is left out (—) when both are censored.
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
    means: dict[str, list[tuple[float, bool]]] = {}
    for actor in dict.fromkeys(run.actor for run in runs):
        group = [run for run in runs if run.actor == actor]
        lasts = [float(run.env_steps[-1]) for run in group]
        summaries = [
            _summary([firsts[id(run)][i] for run in group], lasts) for i in range(len(levels))
        ]
        means[actor] = [(mean, exact) for _, mean, exact in summaries]
        cells = " | ".join(text for text, _, _ in summaries)
        name = ACTOR_NAMES.get(actor, actor)
        lines.append(f"| mean (range), {len(group)} run(s) | {name} | {cells} | |")
    if "popsan" in means and "mlp" in means:
        ratios = [_ratio(p, m) for p, m in zip(means["popsan"], means["mlp"], strict=True)]
        lines.append(f"| PopSAN / MLP, ratio of means | | {' | '.join(ratios)} | |")
    return "\n".join(lines)
