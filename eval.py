"""Evaluate a saved run: report, tracking figure, energy table, latency, video; or compare runs.

    python eval.py runs/<dir> [--best | --step N | --all-checkpoints] [--episodes 1000]
                   [--stochastic] [--seed N]
                   [--energy-timesteps 1,2,3,4,5] [--ann-run runs/<mlp dir>] [--video out.mp4]
                   [--no-energy] [--no-latency] [--no-tracking] [--env-override KEY=VALUE]
    python eval.py --compare runs/a runs/b ... [--out compare.png]
    python eval.py runs/<popsan dir> [--best | --step N] --export-nir policy.nir

Outputs go into the run directory: ``eval_<which>.json`` (report, energy rows, latency),
``tracking_<which>.png``, ``energy_<which>.md`` and ``.csv``; ``--stochastic``, ``--seed N``
(N > 0) and ``--env-override`` append ``+stochastic``, ``+seedN`` and the overrides to
``<which>``, so the plain (deterministic, seed 0) evaluation is never overwritten
(popsan_jax/analysis/report.py). ``--all-checkpoints`` evaluates every kept checkpoint on the
same episodes as ``--step N`` and writes ``eval_checkpoints.json``/``.md`` naming the highest;
re-check it on other episodes with ``--step N --seed 1`` (it was selected on these).
``--compare`` writes the curves figure and, beside it (``compare.md``), the table of env steps
to the first 50/80/90 % success per run and per actor.
Video rendering needs EGL or OSMesa (CPU machines: ``apt-get install -y libosmesa6``).
``--export-nir`` writes the PopSAN's spiking core as a NIR graph and a ``.json`` sidecar beside
it (popsan_jax/analysis/nir_export.py; README, "Taking a policy to neuromorphic hardware") and
does nothing else.
A UserError (missing/corrupt/incompatible checkpoint, bad value) prints ``error: <msg>`` and
exits 2; argparse rejects unknown flags with exit 2; Ctrl-C or SIGTERM exit 130.
"""

from __future__ import annotations

import sys

from popsan_jax.cli import eval_parser, raise_if_stop_requested, stop_on_signals
from popsan_jax.errors import UserError


def say(text: str) -> None:
    """Print one progress line; a Ctrl-C that Python dropped (cli.raise_if_stop_requested)
    stops the evaluation here, at its next line, instead of needing a second one."""
    raise_if_stop_requested()
    print(text, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = eval_parser(__doc__)
    args = parser.parse_args(argv)
    if not args.compare and not args.run_dir:
        parser.error("give a run directory, or --compare RUN [RUN ...]")
    with stop_on_signals():
        try:
            # Imported after the flags are parsed: JAX and MJX take seconds to import.
            from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly

            import_mjx_quietly()  # before brax/MJX modules import it noisily
            from popsan_jax.analysis import report

            if args.compare:
                report.compare(
                    args.compare + ([args.run_dir] if args.run_dir else []), args.out, say
                )
            else:
                enable_compilation_cache()
                report.evaluate(args.run_dir, report.EvalOptions.from_flags(args), say=say)
        except UserError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("\ninterrupted", file=sys.stderr)
            return 130
        except OSError as e:  # e.g. the disk filled while a report was written
            print(f"error: cannot write {e.filename or 'an output'}: {e.strerror}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
