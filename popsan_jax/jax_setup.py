"""Process-level JAX settings shared by the entry points and the tests.

Nothing here runs at import time; callers opt in explicitly.
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import jax

_REPO_ROOT = Path(__file__).resolve().parent.parent


def enable_compilation_cache(cache_dir: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache (one directory per checkout).

    MJX step compiles take 15-45 s on a 2-core CPU; the cache roughly halves warm-up in a
    second process. ``POPSAN_JAX_CACHE`` overrides the default ``<repo>/.jax_cache``.
    """
    path = Path(cache_dir or os.environ.get("POPSAN_JAX_CACHE") or _REPO_ROOT / ".jax_cache")
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def import_mjx_quietly() -> None:
    """Import ``mujoco.mjx`` once with its stdout captured.

    mujoco 3.17's MJX prints "Failed to import warp" on stdout whenever the optional Warp (GPU)
    backend is absent, which is always the case on CPU; users read it as an error.
    """
    with contextlib.redirect_stdout(io.StringIO()):
        import mujoco.mjx  # noqa: F401  (imported here: the point is to capture its print)
