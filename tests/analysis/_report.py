"""eval.py's flags run through the library, as the report tests use them."""

from __future__ import annotations

import pytest

from popsan_jax.analysis import report
from popsan_jax.cli import eval_parser
from popsan_jax.errors import UserError


def run_eval(argv: list[str], environment=None) -> int:
    """eval.py's flags through the library; 0 on success (a UserError propagates)."""
    args = eval_parser().parse_args(argv)
    if args.compare:
        report.compare(args.compare + ([args.run_dir] if args.run_dir else []), args.out, print)
    else:
        report.evaluate(args.run_dir, report.EvalOptions.from_flags(args), environment, print)
    return 0


def fails(argv: list[str], environment=None) -> str:
    """The one-line message of the UserError that eval.py would print as ``error: ...``."""
    with pytest.raises(UserError) as err:
        run_eval(argv, environment)
    assert "\n" not in str(err.value)
    return f"error: {err.value}"
