"""Steps to first reach a success level, and the per-actor summary, on hand-made curves."""

import numpy as np
import pytest

from popsan_jax.analysis.plots import RunCurves
from popsan_jax.analysis.sample_efficiency import first_steps_at, sample_efficiency_table


def _curves(label, actor, points):
    steps, success = zip(*points, strict=True)
    return RunCurves(
        label=label,
        actor=actor,
        env_steps=np.asarray(steps, dtype=float),
        values={"success_rate": np.asarray(success, dtype=float)},
    )


def test_first_steps_at_is_the_first_crossing_not_the_best():
    run = _curves("a", "popsan", [(0, 0.0), (1e6, 0.79), (2e6, 0.8), (3e6, 0.5), (4e6, 0.95)])
    assert first_steps_at(run, 0.8) == 2e6  # exactly at the level counts
    assert first_steps_at(run, 0.5) == 1e6  # the dip to 0.5 at 3 M does not move it
    assert first_steps_at(run, 0.9) == 4e6
    assert first_steps_at(run, 0.99) is None
    nan_run = _curves("n", "mlp", [(0, np.nan), (1e6, np.nan)])
    assert first_steps_at(nan_run, 0.0) is None


def test_table_means_ranges_and_ratio():
    runs = [
        _curves("popsan-s0", "popsan", [(0, 0.0), (1e6, 0.85), (2e6, 0.92)]),
        _curves("popsan-s1", "popsan", [(0, 0.0), (3e6, 0.81), (4e6, 0.9)]),
        _curves("mlp-s0", "mlp", [(0, 0.0), (4e6, 0.8), (6e6, 0.95)]),
        _curves("mlp-s1", "mlp", [(0, 0.0), (8e6, 0.86), (9e6, 0.88)]),
    ]
    lines = sample_efficiency_table(runs, levels=(0.8, 0.9)).splitlines()
    rows = {line.split(" | ")[0].lstrip("| "): line for line in lines if line.startswith("|")}
    assert rows["popsan-s0"] == "| popsan-s0 | popsan | 1.00 M | 2.00 M | 0.920 (2.00 M) |"
    assert "| mlp-s1 | mlp | 8.00 M | — | 0.880 (9.00 M) |" in lines
    popsan_mean, mlp_mean = [line for line in lines if line.startswith("| mean")]
    # PopSAN at 80 %: mean(1, 3) = 2 M, range 1-3; at 90 %: mean(2, 4) = 3 M.
    assert "| PopSAN | 2.00 M (1.00–3.00) | 3.00 M (2.00–4.00) |" in popsan_mean
    # MLP at 80 %: mean(4, 8) = 6 M. At 90 % mlp-s1 never got there by its last evaluation at
    # 9 M, so it needs more than 9 M: the mean (6 + 9) / 2 = 7.5 M is only a lower bound.
    assert "| MLP | 6.00 M (4.00–8.00) | ≥ 7.50 M (6.00–9.00), 1 of 2 reached |" in mlp_mean
    ratio = lines[-1]
    assert ratio.startswith("| PopSAN / MLP") and "**0.33**" in ratio  # 2 M / 6 M
    assert "**≤ 0.40**" in ratio  # 3 M / (more than 7.5 M): an upper bound


def test_ratio_bounds_when_popsan_or_both_are_censored():
    runs = [
        _curves("p", "popsan", [(0, 0.0), (2e6, 0.85), (5e6, 0.88)]),  # 90 %: never, by 5 M
        _curves("m", "mlp", [(0, 0.0), (4e6, 0.95)]),
    ]
    ratio = sample_efficiency_table(runs, levels=(0.8, 0.9, 0.99)).splitlines()[-1]
    cells = [c.strip() for c in ratio.strip("|").split("|")][2:5]
    # 80 %: 2 / 4; 90 %: PopSAN needs > 5 M against 4 M -> at least 1.25; 99 %: both censored.
    assert cells == ["**0.50**", "**≥ 1.25**", "—"]


def test_table_single_actor_has_no_ratio_and_empty_input_is_an_error():
    table = sample_efficiency_table([_curves("x", "popsan", [(0, 0.0), (5e5, 1.0)])])
    assert "PopSAN / MLP" not in table
    assert "| x | popsan | 0.50 M | 0.50 M | 0.50 M | 1.000 (0.50 M) |" in table
    with pytest.raises(ValueError, match="no runs"):
        sample_efficiency_table([])
