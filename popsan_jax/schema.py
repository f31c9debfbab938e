"""Schemas of a run's own files: ``config.json``, ``checkpoints/index.json``, ``metrics.jsonl``.

Run directories are shared and downloaded, so their files are input like any other. Each check
here raises one line naming the file and the field before anything acts on the value:
:class:`ConfigError` for the config, :class:`CheckpointError` for the index and the metrics.
The config's field types come from :class:`popsan_jax.config.RunConfig`'s annotations (passed
in, so that this module imports nothing of the project but its errors); its ranges beyond these
are ``RunConfig.validate``'s. No JAX here.
"""

from __future__ import annotations

import math
import re
import types
import typing
from typing import Any

from popsan_jax.errors import CheckpointError, ConfigError

MAX_SEED = 2**32 - 1  # jax.random.PRNGKey takes a uint32 seed
# Actor kwargs: name -> kind ("sizes" = a non-empty list of integers >= 1). Every kwarg of
# either actor (popsan_jax.config.POPSAN_DEFAULTS, MLP_DEFAULTS) is listed; each count >= 1,
# each positive number > 0.
ACTOR_KWARGS = {
    "hidden_sizes": "sizes",
    "timesteps": "count",
    "encoder_pop_dim": "count",
    "decoder_pop_dim": "count",
    "output_init_scale": "positive",
    "decoder_init_scale": "positive",
}
_WANTED = {
    "int": "an integer",
    "float": "a finite number",
    "str": "a string",
    "bool": "true or false",
    "dict": "a JSON object",
    "sizes": "a non-empty list of positive integers like [256, 256]",
    "count": "an integer >= 1",
    "positive": "a finite number > 0",
}


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _ok(kind: str, value: Any) -> bool:
    if kind == "int":
        return is_int(value)
    if kind == "float":
        return is_number(value)
    if kind == "str":
        return isinstance(value, str)
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "dict":
        return isinstance(value, dict)
    if kind == "sizes":
        return (
            isinstance(value, list | tuple)
            and len(value) > 0
            and all(is_int(v) and v >= 1 for v in value)
        )
    if kind == "count":
        return is_int(value) and value >= 1
    if kind == "positive":
        return is_number(value) and value > 0
    raise AssertionError(f"unknown kind {kind}")


def annotation_kind(annotation: Any) -> tuple[str, bool]:
    """``(kind, None allowed)`` of a RunConfig field annotation (``int``, ``float | None``,
    ``tuple[int, ...]``, ``dict[str, Any]``...)."""
    nullable = False
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        nullable, annotation = len(args) < len(typing.get_args(annotation)), args[0]
    origin = typing.get_origin(annotation) or annotation
    kind = {int: "int", float: "float", str: "str", bool: "bool", dict: "dict", tuple: "sizes"}
    return kind[origin], nullable


def check_config(data: dict[str, Any], hints: dict[str, Any], where: str = "") -> None:
    """Types of a RunConfig dict (read from ``config.json`` or built from flags) against the
    field annotations ``hints``, and the ranges no later code can survive: every actor kwarg
    (T >= 1, populations >= 1), ``env_revision >= 1``, a seed in uint32. ``where`` prefixes the
    messages (e.g. ``"runs/a/config.json: "``)."""

    def check(name: str, value: Any, kind: str) -> None:
        if not _ok(kind, value):
            raise ConfigError(f"{where}{name} must be {_WANTED[kind]}, got {value!r}"[:300])

    for name, value in data.items():
        if name not in hints:
            continue  # unknown keys are RunConfig.from_dict's message
        kind, nullable = annotation_kind(hints[name])
        if not (nullable and value is None):
            check(name, value, kind)
    for name, value in data.get("actor_kwargs", {}).items():
        if name not in ACTOR_KWARGS:
            raise ConfigError(
                f"{where}actor_kwargs has unknown key {name!r}; known: {sorted(ACTOR_KWARGS)}"
            )
        label = "timesteps T" if name == "timesteps" else f"actor_kwargs.{name}"
        check(label, value, ACTOR_KWARGS[name])
    if data.get("env_revision", 1) < 1:
        raise ConfigError(f"{where}env_revision must be >= 1, got {data['env_revision']}")
    if not 0 <= data.get("seed", 0) <= MAX_SEED:
        raise ConfigError(f"{where}seed must be in [0, 2**32 - 1], got {data['seed']}")


# ---- checkpoints/index.json --------------------------------------------------------------
DIGEST = re.compile(r"sha256:[0-9a-f]{64}")


def check_index(index: Any, path: Any) -> dict[str, Any]:
    """``index`` if it is a manifest ``{"checkpoints": [entry, ...], "last", "best"}`` with
    entries ``{"step", "eval_index", "success_rate", "dir"[, "digest"]}``; CheckpointError names
    the first bad field. (Whether ``dir`` stays inside ``checkpoints/`` is checked where it is
    used: popsan_jax.training.run_dir.contained.)"""

    def bad(what: str) -> CheckpointError:
        return CheckpointError(f"corrupt checkpoint index {path}: {what}"[:400])

    if not isinstance(index, dict):
        raise bad("not a JSON object")
    entries = index.get("checkpoints")
    if not isinstance(entries, list):
        raise bad(f"'checkpoints' must be a list, got {entries!r}")
    if not entries or index.get("last") is None:
        raise bad("no checkpoints listed")
    steps = set()
    for n, e in enumerate(entries):
        if not isinstance(e, dict):
            raise bad(f"checkpoint {n} is not an object")
        for name in ("step", "eval_index"):
            if not is_int(e.get(name)) or e[name] < 0:
                raise bad(f"checkpoint {n}: {name} must be an integer >= 0, got {e.get(name)!r}")
        if not is_number(e.get("success_rate")):
            raise bad(
                f"checkpoint {n}: success_rate must be a number, got {e.get('success_rate')!r}"
            )
        if not isinstance(e.get("dir"), str):
            raise bad(f"checkpoint {n}: dir must be a string, got {e.get('dir')!r}")
        if "digest" in e and not (isinstance(e["digest"], str) and DIGEST.fullmatch(e["digest"])):
            raise bad(f"checkpoint {n}: digest must be 'sha256:' and 64 hex digits")
        steps.add(e["step"])
    for name in ("last", "best"):
        if not is_int(index.get(name)) or index[name] not in steps:
            raise bad(f"{name!r} ({index.get(name)!r}) is not a listed checkpoint step")
    return index


# ---- metrics.jsonl -----------------------------------------------------------------------
def check_metrics_record(record: Any, where: str) -> dict[str, Any]:
    """``record`` if it is ``{"kind": str, "env_steps": int >= 0, ...}`` with a numeric
    ``success_rate`` where it has one (``"nan"``/``"inf"`` as run_log writes them), else
    CheckpointError (``where`` is ``path:line``)."""
    if not isinstance(record, dict):
        raise CheckpointError(
            f"{where}: a metrics record must be a JSON object, got {record!r}"[:300]
        )
    if not isinstance(record.get("kind"), str):
        raise CheckpointError(f"{where}: metrics record without a 'kind' string")
    steps = record.get("env_steps")
    if not is_int(steps) or steps < 0:
        raise CheckpointError(f"{where}: 'env_steps' must be an integer >= 0, got {steps!r}")
    rate = record.get("success_rate", 0.0)
    if not (is_number(rate) or rate in ("nan", "inf", "-inf")):
        raise CheckpointError(f"{where}: 'success_rate' must be a number, got {rate!r}"[:300])
    return record
