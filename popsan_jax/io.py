"""The project's file writes and reads: one atomic JSON write, one JSONL reader.

Atomic: data goes to ``<path>.tmp``, is flushed to disk, then ``os.replace``-d over ``path``, so
a crash leaves either the old file or the new one, never half of one.

The torn-line rule of :func:`read_jsonl`: only the LAST line can be cut short by a killed
writer (records are appended whole, line-buffered). A last line without its newline that is
not valid JSON is that torn write and is skipped; any other line that is not valid JSON is
damage and raises :class:`popsan_jax.errors.CheckpointError`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from popsan_jax.errors import CheckpointError


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


def read_jsonl(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Every record of a JSONL file (blank lines ignored), under the torn-line rule above."""
    path = Path(path)
    text = path.read_text()
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
    return records
