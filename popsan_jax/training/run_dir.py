"""A run directory that cannot be turned against its user: names, containment, writability,
one writer, and signals held over the writes that must not be cut.

Run directories get shared and downloaded, so what they contain is untrusted input:

- :func:`check_name` accepts only a plain directory name for ``--name`` (no ``/``, ``..``,
  absolute paths or control characters), so a new run is always created inside ``--runs-dir``.
- :func:`contained` resolves a checkpoint directory name read from ``index.json`` inside the
  run's ``checkpoints/``. Only the project's own pattern (:data:`CHECKPOINT_NAME`) is accepted
  and links out are refused, so neither loading nor pruning reaches outside the run.
- :func:`check_runs_dir` and :func:`check_run_dir` find a runs directory that is a file, under a
  kernel filesystem or read-only, and a resumed run that cannot be written or whose
  ``metrics.jsonl`` is off its schema, before minutes of compiling.
- :class:`RunLock` is ``<run>/lock``, JSON with the holder's PID and host, created atomically
  (``os.link`` of a complete temporary file, which fails if the lock exists). A second trainer
  is refused with one line naming the holder: two writers would interleave their metrics and
  overwrite each other's checkpoints. A lock whose PID is dead on this host is stale (a killed
  trainer) and is taken over with a note.
- :func:`deferred_signals` holds SIGINT/SIGTERM while a checkpoint is written and re-raises them
  once it is complete. An interrupt that lands inside Orbax's threads can hang the process or
  bury the one message under third-party tracebacks; a synchronous write of a few seconds that
  then stops cleanly is bounded and leaves a complete checkpoint.

Nothing here imports JAX.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from popsan_jax.errors import CheckpointError, ConfigError, UserError
from popsan_jax.io import check_writable

LOCK = "lock"
# The only checkpoint directory names the project writes (checkpoint.save_checkpoint).
CHECKPOINT_NAME = re.compile(r"step_\d{12}")
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+=,-]*")


def checkpoint_name(step: int) -> str:
    """The directory name of the checkpoint at env step ``step``."""
    return f"step_{int(step):012d}"


def check_name(name: str) -> str:
    """``name`` if it is a plain directory name, else ConfigError (one line)."""
    if not isinstance(name, str) or len(name) > 200 or not _NAME.fullmatch(name):
        raise ConfigError(
            f"--name must be a plain directory name (letters, digits, _ . + = , -; no '/', "
            f"'..' or absolute path), got {name!r}"
        )
    return name


def contained(root: str | os.PathLike, name: Any, what: str = "checkpoint") -> Path:
    """``root / name`` for a checkpoint directory name read from ``index.json``.

    ``name`` must be the project's own pattern (``step_`` + 12 digits) and the path must
    resolve (links followed) directly inside ``root``; otherwise CheckpointError.
    """
    root = Path(root)
    if not isinstance(name, str) or not CHECKPOINT_NAME.fullmatch(name):
        raise CheckpointError(
            f"{what} directory {name!r} in {root / 'index.json'} is not a checkpoint name "
            f"(step_ and 12 digits); the index was altered"
        )
    path = root / name
    real = path.resolve()
    if real.parent != root.resolve():
        raise CheckpointError(f"{what} {path} resolves outside {root} (to {real}); refused")
    return path


def check_runs_dir(runs_dir: str | os.PathLike) -> Path:
    """``runs_dir`` if a run directory can be created in it, else UserError (one line)."""
    runs_dir = Path(runs_dir)
    if runs_dir.exists() and not runs_dir.is_dir():
        raise UserError(f"--runs-dir {runs_dir} is a file, not a directory")
    check_writable(runs_dir, "--runs-dir")
    return runs_dir


def check_run_dir(run_dir: str | os.PathLike, resume: bool) -> None:
    """Before a run writes anything: a new run's parent can take it; a resumed run and its
    ``checkpoints/`` can be written, and its ``metrics.jsonl`` is on its schema."""
    run_dir = Path(run_dir)
    if not resume:
        check_runs_dir(run_dir.parent)
        return
    if not run_dir.is_dir():
        raise CheckpointError(f"run directory {run_dir} does not exist")
    check_writable(run_dir, "run directory")
    if (run_dir / "checkpoints").is_dir():
        check_writable(run_dir / "checkpoints", "checkpoint directory")
    from popsan_jax.training.run_log import read_metrics  # tensorboardX: only when resuming

    read_metrics(run_dir)


# ---- one writer --------------------------------------------------------------------------
class RunLockedError(UserError):
    """Another live process holds the run's lock."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def read_lock(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The lock's ``{"pid", "host", "since"}``, ``{}`` when unreadable, None when absent."""
    try:
        data = json.loads((Path(run_dir) / LOCK).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


class RunLock:
    """``with RunLock(run_dir, note=print):`` holds ``run_dir/lock`` for its body."""

    def __init__(self, run_dir: str | os.PathLike, note: Callable[[str], None] | None = None):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK
        self.note = note or (lambda text: None)
        self.held = False

    def _try_create(self) -> bool:
        record = dict(pid=os.getpid(), host=socket.gethostname(), since=time.time())
        fd, tmp = tempfile.mkstemp(prefix=".lock-", dir=self.run_dir)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(record, f)
            os.link(tmp, self.path)  # atomic, and fails when the lock exists
            return True
        except FileExistsError:
            return False
        finally:
            os.unlink(tmp)

    def acquire(self) -> None:
        for _ in range(3):
            try:
                if self._try_create():
                    self.held = True
                    return
            except OSError as e:
                if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC):
                    raise UserError(f"cannot lock {self.run_dir}: {e.strerror}") from None
                raise
            holder = read_lock(self.run_dir)
            if holder is None:
                continue  # released meanwhile
            pid, host = holder.get("pid"), holder.get("host")
            if isinstance(pid, int) and host == socket.gethostname() and not _pid_alive(pid):
                self.note(f"note: taking over the stale lock of PID {pid} on {host} (not running)")
            elif holder == {}:
                self.note(f"note: replacing the unreadable lock file {self.path}")
            else:
                raise RunLockedError(
                    f"{self.run_dir} is in use by PID {pid} on host {host} (lock {self.path}); "
                    f"stop that process, or delete the lock if it is not running"
                )
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
        raise RunLockedError(f"cannot take the lock {self.path}: another process keeps taking it")

    def release(self) -> None:
        if not self.held:
            return
        self.held = False
        holder = read_lock(self.run_dir) or {}
        if (holder.get("pid"), holder.get("host")) == (os.getpid(), socket.gethostname()):
            with contextlib.suppress(OSError):
                os.unlink(self.path)

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


# ---- signals ------------------------------------------------------------------------------
@contextlib.contextmanager
def deferred_signals(
    signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM),
) -> Iterator[None]:
    """Hold ``signals`` over the body; if one arrived, act on it after the body (the handler
    that was in place runs then; train.py's raises KeyboardInterrupt).

    Only the main thread can set handlers; elsewhere (and for handlers that are not Python
    callables, e.g. SIG_IGN) the body runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = {}
    for sig in signals:
        old = signal.getsignal(sig)
        if old in (signal.SIG_IGN, None):
            continue
        previous[sig] = old
        signal.signal(sig, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
    if received:  # act as the handler that was in place would have
        sig = received[0]
        handler = previous[sig]
        if callable(handler):
            handler(sig, None)  # train.py's: KeyboardInterrupt
        else:
            os.kill(os.getpid(), sig)
