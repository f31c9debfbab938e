"""Helpers for the hostile-input tests (issue 22): the entry points loaded by path, train.py and
eval.py on the toy env, a finished toy run to copy, and tmpfs mounts for filesystem faults."""

from __future__ import annotations

import contextlib
import importlib.util
import shutil
import subprocess
from pathlib import Path

import pytest
from _toy_env import PointPick, tiny_config

from popsan_jax.training import checkpoint, loop

ROOT = Path(__file__).resolve().parent.parent
STEPS = 640  # env steps per iteration of tiny_config()


def load_script(name: str):
    """train.py or eval.py as a module (its ``main(argv)``)."""
    spec = importlib.util.spec_from_file_location(f"{name}_cli", ROOT / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def toy_env_everywhere(monkeypatch) -> None:
    """train.py and eval.py build the config's env: make it the toy env (no MJX compile)."""
    monkeypatch.setattr(loop, "make_env", lambda config: PointPick())
    monkeypatch.setattr(checkpoint, "make_env", lambda config: PointPick())


def train_finished(run_dir: Path) -> Path:
    """A toy run trained to its end: 2 iterations, a checkpoint after each."""
    loop.train(
        tiny_config(total_env_steps=2 * STEPS), run_dir, environment=PointPick(), progress=False
    )
    return run_dir


def copy_run(run_dir: Path, dest: Path) -> Path:
    shutil.copytree(run_dir, dest)
    return dest


def error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


def one_error(err: str, match: str | None = None) -> str:
    """The stderr of a refused command: exactly one ``error:`` line, last, no traceback."""
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert "Traceback" not in err, err[-3000:]
    assert len(error_lines(err)) == 1 and lines[-1].startswith("error: "), err[-3000:]
    if match is not None:
        assert match in lines[-1], lines[-1]
    return lines[-1]


@contextlib.contextmanager
def tmpfs(path: Path, size: str = "1m"):
    """A tmpfs mounted at ``path`` (root only); skips the test where mounting is refused."""
    path.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True
    )
    if proc.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def remount_read_only(path: Path) -> None:
    subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True, capture_output=True)
