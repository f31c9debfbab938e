"""The entry points' flags (train.py, eval.py), derived from the library's own definitions.

train.py's config flags are the :class:`~popsan_jax.config.RunConfig` fields declared with a
help text (``config._flag``): name, type and help come from the field, so nothing is restated
here. The PopSAN shape flags are the keys of ``POPSAN_DEFAULTS``. No side effects on import;
nothing here imports JAX, so ``--help`` and flag errors are instant.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import re
import signal
import sys
import types
import typing
from collections.abc import Callable, Iterator
from typing import Any

from popsan_jax.config import FLAG_HELP, POPSAN_DEFAULTS, RunConfig
from popsan_jax.recipes import PRESETS

ACTOR_FLAG_HELP = {
    "hidden_sizes": "actor hidden sizes, e.g. 256,256",
    "timesteps": "PopSAN timesteps T",
    "encoder_pop_dim": "PopSAN encoder population per observation dimension",
    "decoder_pop_dim": "PopSAN output population per action dimension",
    "decoder_init_scale": "PopSAN decoder's initial weights, times the paper's draw",
}
assert set(ACTOR_FLAG_HELP) == set(POPSAN_DEFAULTS), "one help line per PopSAN shape key"


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line ``error: ...`` with exit 2, as UserErrors are."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def env_override(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` -> ``(key, value)``; VALUE is parsed as JSON when it is JSON, else a string."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def sizes(text: str) -> tuple[int, ...]:
    """``256,256`` (or ``256 256``) -> ``(256, 256)``, every size positive."""
    try:
        values = tuple(int(s) for s in text.replace(",", " ").split())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected sizes like 256,256, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive sizes like 256,256, got {text!r}")
    return values


def add_env_override_flag(parser: argparse.ArgumentParser, help_text: str) -> None:
    """The repeatable ``--env-override KEY=VALUE`` flag (``args.env_override``: list of pairs)."""
    parser.add_argument(
        "--env-override",
        type=env_override,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=help_text,
    )


def overrides_tag(overrides: dict[str, object]) -> str:
    """File-name suffix naming env overrides, e.g. ``+grasp_radius=0.0`` ('' when none)."""
    text = "".join(f"+{k}={json.dumps(v, separators=(',', ':'))}" for k, v in overrides.items())
    return re.sub(r"[^A-Za-z0-9_.=+,-]", "", text)


def boolean(text: str) -> bool:
    """``true`` / ``false`` (also ``1`` / ``0``, ``yes`` / ``no``) -> bool."""
    value = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}
    try:
        return value[text.strip().lower()]
    except KeyError:
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}") from None


def _flag_type(annotation: Any) -> Callable[[str], Any]:
    """The argparse type of a RunConfig field: ``X | None`` is X, tuples of ints are sizes,
    bools read true / false (``bool('false')`` would be True)."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        annotation = args[0]
    if typing.get_origin(annotation) is tuple:
        return sizes
    if annotation is bool:
        return boolean
    return annotation


def config_flags() -> dict[str, tuple[Callable[[str], Any], str]]:
    """``{field: (argparse type, help)}`` for every RunConfig field that is a flag."""
    hints = typing.get_type_hints(RunConfig)
    return {
        f.name: (_flag_type(hints[f.name]), f.metadata[FLAG_HELP])
        for f in dataclasses.fields(RunConfig)
        if FLAG_HELP in f.metadata
    }


def train_parser(description: str | None = None) -> argparse.ArgumentParser:
    """train.py's flags; config flags default to None ("not given", so presets show through)."""
    p = OneLineParser(description=description, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--preset", help=" | ".join(PRESETS))
    p.add_argument("--name", help="run directory name (default <env>-<actor>-<timestamp>)")
    p.add_argument("--runs-dir", default="runs", help="parent of run directories")
    p.add_argument("--resume", metavar="RUN_DIR", help="continue a run from its last checkpoint")
    add_env_override_flag(p, "env config override (repeatable)")
    p.add_argument("--wandb", action="store_true", default=None, help="also log to W&B")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    multi = p.add_argument_group(
        "several processes (jax.distributed; default: SLURM, Open MPI or JAX's cluster detection)"
    )
    multi.add_argument("--coordinator", metavar="HOST:PORT", help="process 0's address")
    multi.add_argument("--num-processes", type=int, metavar="N", help="processes in the run")
    multi.add_argument("--process-id", type=int, metavar="I", help="this process, 0..N-1")
    multi.add_argument(
        "--heartbeat-timeout",
        type=int,
        metavar="S",
        help="seconds after which a silent process is declared dead (default 100)",
    )
    flags = {**config_flags(), **{k: (_actor_type(k), h) for k, h in ACTOR_FLAG_HELP.items()}}
    for name, (kind, text) in flags.items():
        p.add_argument("--" + name.replace("_", "-"), type=kind, help=text)
    return p


def _actor_type(name: str) -> Callable[[str], Any]:
    return sizes if isinstance(POPSAN_DEFAULTS[name], tuple) else type(POPSAN_DEFAULTS[name])


def given_flags(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(config fields, actor kwargs)`` the user gave on train.py's command line."""
    given = {k: getattr(args, k) for k in config_flags() if getattr(args, k) is not None}
    actor = {k: getattr(args, k) for k in ACTOR_FLAG_HELP if getattr(args, k) is not None}
    return given, actor


def run_choices(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword arguments of ``training.run.prepare_run`` from train.py's parsed flags."""
    return dict(
        preset=args.preset,
        env_overrides=dict(args.env_override),
        wandb=bool(args.wandb),
        resume=args.resume,
        runs_dir=args.runs_dir,
        name=args.name,
    )


def cluster_flags(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword arguments of ``distributed.resolve_cluster`` from train.py's parsed flags."""
    return dict(
        coordinator=args.coordinator,
        num_processes=args.num_processes,
        process_id=args.process_id,
        heartbeat_timeout=args.heartbeat_timeout,
    )


def timesteps_list(text: str) -> tuple[int, ...]:
    """``1,2,3`` -> ``(1, 2, 3)``, every T positive."""
    try:
        values = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers like 1,2,3, got {text!r}")
    return values


def eval_parser(description: str | None = None) -> argparse.ArgumentParser:
    """eval.py's flags (see :class:`popsan_jax.analysis.report.EvalOptions`)."""
    p = OneLineParser(description=description, formatter_class=argparse.RawTextHelpFormatter)
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
    p.add_argument(
        "--energy-timesteps",
        "--timesteps",
        dest="energy_timesteps",
        type=timesteps_list,
        default=(1, 2, 3, 4, 5),
        metavar="T,T,...",
        help="PopSAN T values of the energy table (default 1,2,3,4,5)",
    )
    p.add_argument("--ann-run", help="MLP run whose hidden sizes define the ANN baseline")
    p.add_argument("--video", metavar="OUT", help="render one episode to this .mp4/.gif")
    p.add_argument(
        "--export-nir",
        metavar="PATH",
        help="write the PopSAN as a NIR graph (PATH, .nir) and its sidecar (.json); nothing else",
    )
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


_stop = types.SimpleNamespace(requested=False)


def _interrupt(signum: int, frame: Any) -> None:
    _stop.requested = True
    raise KeyboardInterrupt


def raise_if_stop_requested(*_: Any) -> None:
    """Raise KeyboardInterrupt if a signal asked :func:`stop_on_signals` to stop.

    A signal's KeyboardInterrupt is raised wherever Python code runs at that moment; inside a
    garbage-collector callback (JAX registers one, and a compile collects often) Python reports
    it to ``sys.unraisablehook`` and drops it, and the run would go on (stop_on_signals keeps
    that report quiet). Called after every training iteration
    (train.py's ``on_iteration``), this raises it again there.
    """
    if _stop.requested:
        raise KeyboardInterrupt


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """SIGINT and SIGTERM raise KeyboardInterrupt inside, as Ctrl-C does; handlers restored after.

    A job started with ``&`` by a non-interactive shell has SIGINT ignored, and schedulers stop
    jobs with SIGTERM: both should end a run as Ctrl-C does (last checkpoint kept). A stop that
    was dropped on its way is raised again by :func:`raise_if_stop_requested`.
    """
    _stop.requested = False
    previous = signal.signal(signal.SIGINT, _interrupt)
    previous_term = signal.signal(signal.SIGTERM, _interrupt)
    previous_hook = sys.unraisablehook

    def unraisable(report: Any) -> None:
        if not isinstance(report.exc_value, KeyboardInterrupt):  # that one is raised again
            previous_hook(report)

    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)
        sys.unraisablehook = previous_hook
        _stop.requested = False  # a stop belongs to this block: none is raised after it
