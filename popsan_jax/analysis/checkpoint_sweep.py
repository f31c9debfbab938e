"""Rank every kept checkpoint of a run by one large evaluation on the same episodes.

Training marks its "best" checkpoint by its periodic evaluations (64 episodes by default),
whose 95 % interval near 90 % success is about ±7.5 points: wider than the differences between
late checkpoints. This evaluates each kept checkpoint on the same ``N`` episodes (same initial
states and, for a stochastic policy, the same action keys) as ``eval.py --step N`` does, so
the ranking compares policies rather than episode draws and each row is that evaluation's.

Each checkpoint is run by the same code path as a single evaluation (its parameters closed
over, one compile per checkpoint) rather than one runner with parameters as arguments: that
other program rounds the first actions differently (by about 1e-6) and the contact dynamics
amplify it until trajectories part within 20–50 steps, so its success rates would differ from
``--step N``'s by a few episodes per thousand (docs/notebook/, "Which checkpoint").

The highest success rate was selected on these very episodes, so it is biased upwards (the
winner's curse); re-check the chosen checkpoint on other episodes (``eval.py --seed N``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import jax

from popsan_jax.analysis.evaluation import rollouts, summarize
from popsan_jax.training.checkpoint import load_run
from popsan_jax.training.checkpoint_index import read_index


def evaluate_checkpoints(
    run_dir: str | os.PathLike,
    episodes: int,
    key: jax.Array,
    deterministic: bool = True,
    environment: Any = None,
    env_overrides: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Evaluate each kept checkpoint of ``run_dir`` over the same ``episodes`` episodes.

    ``key`` draws the episodes (``eval.py`` passes the key of ``--step N``). Returns
    ``{"rows": [...], "chosen_step": int}``: one row per checkpoint in step order (``step``,
    ``training_success`` from the run's own evaluation, and :func:`summarize`'s fields), and the
    step with the highest success rate (ties: the later step, as training's "best"). PopSAN
    runs are evaluated at the T they were trained with.
    """
    steps = sorted(e["step"] for e in read_index(run_dir)["checkpoints"])
    env = None
    rows = []
    for step in steps:
        if env is None:  # the first load builds the env (with any overrides); the rest reuse it
            loaded = load_run(run_dir, step, environment=environment, env_overrides=env_overrides)
            env = loaded.env
        else:
            loaded = load_run(run_dir, step, environment=env)
        batch = jax.device_get(rollouts(loaded, episodes, key, deterministic))
        row = dict(step=step, training_success=loaded.entry["success_rate"], **summarize(batch))
        rows.append(row)
        if progress is not None:
            progress(f"step {step}: success {row['success_rate']:.3f}")
    chosen = max(rows, key=lambda r: (r["success_rate"], r["step"]))
    return dict(rows=rows, chosen_step=chosen["step"])


def checkpoints_markdown(result: dict[str, Any], title: str) -> str:
    """The ranking as a markdown table; the chosen checkpoint in bold."""
    lines = [
        f"# {title}",
        "",
        "| env step | training eval | success (95 % CI) | episode length | return |",
        "|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lo, hi = r["success_ci95"]
        success = f"{r['success_rate']:.3f} ({lo:.3f}–{hi:.3f})"
        if r["step"] == result["chosen_step"]:
            success = f"**{success}**"
        lines.append(
            f"| {r['step']:,} | {r['training_success']:.3f} | {success} "
            f"| {r['episode_length']:.1f} | {r['episode_return']:.1f} |"
        )
    n = result["rows"][0]["episodes"]
    lines += [
        "",
        f"{n} episodes per checkpoint, the same episodes for all. The chosen one (bold) was "
        "selected on these episodes: re-check it on others (`eval.py --step N --seed 1`).",
    ]
    return "\n".join(lines) + "\n"
