"""Argument types shared by the entry points (train.py, eval.py). No side effects on import."""

from __future__ import annotations

import argparse
import json
import re


def env_override(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` -> ``(key, value)``; VALUE is parsed as JSON when it is JSON, else a string."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


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
