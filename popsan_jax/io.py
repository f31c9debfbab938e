"""The project's file writes and reads: one atomic JSON write, one JSONL reader, and the checks
that a place can be written before minutes of work are spent on what goes there.

Atomic: data goes to ``<path>.tmp``, is flushed to disk, then ``os.replace``-d over ``path``, so
a crash leaves either the old file or the new one, never half of one.

The torn-line rule of :func:`read_jsonl`: only the LAST line can be cut short by a killed
writer (records are appended whole, line-buffered). A last line without its newline that is
not valid JSON is that torn write and is skipped; any other line that is not valid JSON is
damage and raises :class:`popsan_jax.errors.CheckpointError`, as does a record that its
reader's schema check refuses (popsan_jax/schema.py).

Writability (:func:`check_writable`, :func:`check_output_file`) is probed by creating and
removing a file, the only test that also catches read-only mounts, ACLs and kernel
filesystems; a folder that does not exist yet is judged by its nearest existing parent.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from popsan_jax.errors import CheckpointError, UserError

# Kernel filesystems: creating files there fails late or does something else entirely.
_SYSTEM_ROOTS = (Path("/proc"), Path("/sys"), Path("/dev"))


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (tmp file, fsync, rename)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """``data`` as indented JSON with sorted keys, written atomically."""
    return write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


def write_jsonl(path: str | os.PathLike, records: Iterable[dict[str, Any]]) -> Path:
    """One JSON object per line, written atomically (replaces the file)."""
    return write_text(path, "".join(json.dumps(r) + "\n" for r in records))


def read_jsonl(
    path: str | os.PathLike, check: Callable[[Any, str], Any] | None = None
) -> list[dict[str, Any]]:
    """Every record of a JSONL file (blank lines ignored), under the torn-line rule above;
    ``check(record, "path:line")`` raises for a record off the file's schema."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, ValueError) as e:  # ValueError: bytes that are not UTF-8
        raise CheckpointError(f"cannot read {path}: {e}") from e
    lines = text.split("\n")  # the last item is "" when the file ends with its newline
    records = []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as e:
            if n == len(lines):  # no newline after it: a write cut short
                continue
            raise CheckpointError(f"{path}:{n} is not valid JSON: {e.msg}") from e
        if check is not None:
            check(records[-1], f"{path}:{n}")
    return records


def _nearest_existing(path: Path) -> Path:
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_writable(directory: str | os.PathLike, what: str = "directory") -> None:
    """UserError (one line) unless a file can be created in ``directory``, or, where it does
    not exist yet, in its nearest existing parent. Leaves nothing behind."""
    directory = Path(directory)
    resolved = directory.resolve()
    for root in _SYSTEM_ROOTS:
        if resolved == root or root in resolved.parents:
            raise UserError(f"{what} {directory} is under {root}, a kernel filesystem")
    target = _nearest_existing(directory)
    if not target.is_dir():
        raise UserError(f"{what} {directory}: {target} is a file, not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=target)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise UserError(f"{what} {directory} is not writable ({e.strerror or e})") from None


def check_output_file(path: str | os.PathLike, what: str) -> Path:
    """``path`` if a file can be written there (its folder exists or can be made), else
    UserError naming ``what`` (e.g. ``--video``); nothing is left behind."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{what} {path} is a directory, not a file")
    check_writable(path.parent, f"{what} folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise UserError(f"{what} {path} is not writable")
    return path
