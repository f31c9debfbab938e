"""The checkpoint manifest of a run directory, the digests it records, and the one-line errors
that name the last good checkpoint.

Layout under ``runs/<name>/checkpoints/``::

    step_000000123456/   one checkpoint (written by :mod:`popsan_jax.training.checkpoint`)
    index.json           the manifest: every kept checkpoint, plus "last" and "best"

The manifest is written to a temporary file and ``os.replace``-d, and only lists finished
checkpoints, so a crash leaves the previous manifest and everything it names intact. Each entry
carries a SHA-256 digest over its checkpoint's files, checked before a restore.

Nothing here imports JAX.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

from popsan_jax.errors import CheckpointError
from popsan_jax.io import write_json
from popsan_jax.schema import check_index
from popsan_jax.training.run_dir import contained

INDEX = "index.json"
CONFIG = "config.json"
WARMUP = "warmup"  # a run's warm-up stage: a run directory inside it (training/stages.py)


def checkpoint_dir(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / "checkpoints"


def index_path(run_dir: str | os.PathLike) -> Path:
    """The run's checkpoint manifest; whether the file exists tells a run that has written a
    checkpoint (or tried to) from one killed before its first."""
    return checkpoint_dir(run_dir) / INDEX


def read_index(run_dir: str | os.PathLike) -> dict[str, Any]:
    """The manifest ``{"checkpoints": [{"step", "eval_index", "success_rate", "dir", "digest"}],
    "last", "best"}``; raises CheckpointError when missing, unreadable or off its schema."""
    path = index_path(run_dir)
    if not Path(run_dir).is_dir():
        raise CheckpointError(f"run directory {run_dir} does not exist")
    try:
        index = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise CheckpointError(f"no checkpoint in {run_dir} (missing {path})") from e
    except (OSError, ValueError) as e:  # ValueError: bad JSON, or bytes that are not UTF-8
        raise CheckpointError(f"corrupt checkpoint index {path}: {e}") from e
    return check_index(index, path)  # popsan_jax/schema.py


def has_checkpoint(run_dir: str | os.PathLike) -> bool:
    """Whether ``run_dir`` has a readable manifest listing a checkpoint."""
    try:
        read_index(run_dir)
    except CheckpointError:
        return False
    return True


def write_index(run_dir: str | os.PathLike, index: dict[str, Any]) -> None:
    write_json(index_path(run_dir), index)


def find_entry(index: dict[str, Any], which: str | int) -> dict[str, Any]:
    """The manifest entry of ``which`` (``"last"``, ``"best"`` or an env-step count)."""
    if which in ("last", "best"):
        step = index[which]
    elif isinstance(which, int):
        step = which
    else:
        raise CheckpointError(f"unknown checkpoint {which!r}; use 'last', 'best' or a step")
    for e in index["checkpoints"]:
        if e["step"] == step:
            return e
    steps = ", ".join(str(e["step"]) for e in index["checkpoints"])
    raise CheckpointError(f"no checkpoint at step {step}; available: {steps}")


def checkpoint_digest(path: str | os.PathLike) -> str:
    """``sha256:<hex>`` over every file under ``path`` (relative names and contents, in sorted
    order); links are not followed, and a link or special file is an error."""
    root = Path(path)
    h = hashlib.sha256()
    files = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in dirnames + filenames:
            p = Path(dirpath, name)
            if p.is_symlink():
                raise CheckpointError(f"checkpoint {root} contains a link {p}; refused")
        files.extend(Path(dirpath, name) for name in filenames)
    for p in sorted(files, key=lambda q: q.relative_to(root).as_posix()):
        rel = p.relative_to(root).as_posix().encode()
        h.update(len(rel).to_bytes(8, "little") + rel)
        with open(p, "rb") as f:
            h.update(os.fstat(f.fileno()).st_size.to_bytes(8, "little"))
            for block in iter(lambda f=f: f.read(1 << 20), b""):
                h.update(block)
    return "sha256:" + h.hexdigest()


def _intact_others(run_dir: Path, index: dict[str, Any], step: int) -> list[int]:
    """Steps of the other listed checkpoints whose digest matches (unverifiable ones too)."""
    good = []
    for e in index["checkpoints"]:
        if e["step"] == step:
            continue
        try:
            path = contained(checkpoint_dir(run_dir), e["dir"])
            if "digest" not in e or checkpoint_digest(path) == e["digest"]:
                good.append(e["step"])
        except (OSError, CheckpointError):
            continue
    return good


def verify_checkpoint(
    run_dir: str | os.PathLike, index: dict[str, Any], entry: dict[str, Any]
) -> bool:
    """Check ``entry``'s files against its manifest digest; False when it has none (a manifest
    written before digests: unverified). A mismatch raises one CheckpointError line naming the
    checkpoint and the intact alternatives."""
    if "digest" not in entry:
        return False
    path = contained(checkpoint_dir(run_dir), entry["dir"])
    try:
        actual = checkpoint_digest(path)
    except OSError as e:
        actual = f"unreadable ({e.strerror or e})"
    if actual == entry["digest"]:
        return True
    others = _intact_others(Path(run_dir), index, entry["step"])
    if others:
        best = " or --best" if index["best"] in others else ""
        hint = "intact: " + ", ".join(f"--step {s}" for s in others) + best
    else:
        hint = "no other checkpoint is intact"
    raise CheckpointError(
        f"checkpoint {path} is damaged: its files do not match the digest in {INDEX}; {hint}"
    )


def last_good(index: dict[str, Any]) -> str:
    """Where a failed write leaves the run: ``the last good checkpoint is step N``."""
    last = index.get("last")
    if last is None:
        return "no checkpoint was written yet"
    return f"the last good checkpoint is step {last}"


def write_error(run_dir: str | os.PathLike, e: BaseException) -> CheckpointError:
    """One line for a failed write into ``run_dir`` (disk full, read-only...), naming the last
    good checkpoint to resume from."""
    try:
        index = read_index(run_dir)
    except CheckpointError:
        index = {}
    return CheckpointError(
        f"cannot write to {run_dir}: {first_line(e)}; {last_good(index)}; free the space or "
        f"fix the permissions, then: python train.py --resume {run_dir}"
    )


def first_line(e: BaseException) -> str:
    """The OS's wording of the error under ``e`` (Orbax and tensorstore wrap it), else its first
    line."""
    cause: BaseException | None = e
    while cause is not None:
        if isinstance(cause, OSError) and cause.strerror:
            return cause.strerror
        cause = cause.__cause__ or cause.__context__
    code = re.search(r"os_error_code='?(\d+)", str(e))  # tensorstore's wording of an OSError
    if code:
        return os.strerror(int(code.group(1)))
    text = str(e).strip().splitlines()
    return (text[0] if text else type(e).__name__)[:300]
