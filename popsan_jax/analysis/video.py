"""Offscreen video of a recorded episode with MuJoCo's classic renderer (EGL, else OSMesa).

MuJoCo picks its GL backend from ``MUJOCO_GL`` once, when ``mujoco`` is first imported, and a
process that already imported it (the evaluator, via the envs) cannot switch. Frames are therefore
rendered in a fresh Python subprocess per backend attempt, with ``MUJOCO_GL`` and
``PYOPENGL_PLATFORM`` set before its import: EGL first (GPU machines), then OSMesa (CPU machines;
Debian/Ubuntu: ``apt-get install -y libosmesa6``); a ``MUJOCO_GL`` already set by the user is
tried first. A crashing GL driver only kills that subprocess. If no backend works,
:class:`popsan_jax.errors.UserError` says so in one line; an output path that cannot be written
is its own one-line error, checked before any backend is tried and again after they all fail
(a worker that cannot write its file fails on every backend, which is no GL fault).

The model travels as a MuJoCo binary (``mj_saveModel``) and the trajectory as ``.npy``; each frame
sets ``qpos``, runs ``mj_forward`` and renders. imageio-ffmpeg supplies the ffmpeg binary.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from popsan_jax.errors import UserError
from popsan_jax.io import check_output_file

GL_BACKENDS = ("egl", "osmesa")
INSTALL_HINT = "for CPU rendering install OSMesa: apt-get install -y libosmesa6"
_WORKER = (
    "import sys; from popsan_jax.analysis.video import _render_worker; "
    "_render_worker(*sys.argv[1:])"
)


def render_video(
    mj_model: Any,
    qpos: np.ndarray,
    out_path: str | os.PathLike,
    fps: float = 50.0,
    width: int = 640,
    height: int = 480,
    backends: tuple[str, ...] = GL_BACKENDS,
    timeout_s: float = 600.0,
    mocap_pos: np.ndarray | None = None,
) -> tuple[Path, str]:
    """Render ``qpos [T, nq]`` of ``mj_model`` to ``out_path`` (mp4/gif by extension).

    ``mocap_pos [T, nmocap, 3]`` places mocap bodies (e.g. the reach target) in each frame.

    Returns ``(path, backend used)``. Raises UserError when no GL backend can render.
    """
    qpos = np.asarray(qpos, dtype=np.float64)
    if qpos.ndim != 2 or qpos.shape[1] != mj_model.nq or qpos.shape[0] == 0:
        raise ValueError(f"qpos must be [T, {mj_model.nq}] with T > 0, got {qpos.shape}")
    out_path = check_output_file(Path(out_path).resolve(), "--video")
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"cannot create the --video folder {out_path.parent}: {e.strerror}") from e
    failures = []
    # A backend the user chose explicitly (e.g. MUJOCO_GL=glfw with a display) goes first.
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    backends = tuple(dict.fromkeys(((chosen,) if chosen else ()) + tuple(backends)))
    with tempfile.TemporaryDirectory(prefix="popsan_video_") as tmp:
        model_file, qpos_file = Path(tmp, "model.mjb"), Path(tmp, "qpos.npy")
        mujoco.mj_saveModel(mj_model, str(model_file), None)
        np.save(qpos_file, qpos)
        mocap_file = Path(tmp, "mocap.npy")
        if mocap_pos is not None:
            np.save(mocap_file, np.asarray(mocap_pos, dtype=np.float64))
        for backend in backends:
            env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
            args = [str(model_file), str(qpos_file), str(out_path), str(fps), str(width)]
            args_tail = [str(mocap_file)] if mocap_pos is not None else []
            try:
                proc = subprocess.run(
                    [sys.executable, "-c", _WORKER, *args, str(height), *args_tail],
                    env=env,
                    capture_output=True,
                    text=True,
                    timeout=timeout_s,
                )
            except subprocess.TimeoutExpired:
                failures.append(f"{backend}: no video after {timeout_s:.0f} s")
                continue
            if proc.returncode == 0 and out_path.is_file() and out_path.stat().st_size > 0:
                return out_path, backend
            lines = (proc.stderr or proc.stdout or f"exit {proc.returncode}").strip().splitlines()
            failures.append(f"{backend}: {lines[-1] if lines else proc.returncode}")
    check_output_file(out_path, "--video")  # the path, not GL, when it went away meanwhile
    raise UserError(
        f"cannot render video, no GL backend works ({'; '.join(failures)}); {INSTALL_HINT}"
    )


def _render_worker(
    model_file: str,
    qpos_file: str,
    out_path: str,
    fps: str,
    width: str,
    height: str,
    mocap_file: str | None = None,
) -> None:
    """Subprocess body: MUJOCO_GL is already set in this process's environment."""
    import imageio  # only the render subprocess writes video files

    model = mujoco.MjModel.from_binary_path(model_file)
    # The offscreen buffer must be at least the frame size.
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, int(width))
    model.vis.global_.offheight = max(model.vis.global_.offheight, int(height))
    data = mujoco.MjData(model)
    qpos = np.load(qpos_file)
    mocap = np.load(mocap_file) if mocap_file else None
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = (0.45, 0.0, 0.25)
    camera.distance, camera.azimuth, camera.elevation = 1.6, 150.0, -25.0
    with mujoco.Renderer(model, int(height), int(width)) as renderer:
        with imageio.get_writer(out_path, fps=float(fps)) as writer:
            for t, q in enumerate(qpos):
                data.qpos[:] = q
                if mocap is not None:
                    data.mocap_pos[:] = mocap[t]
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera=camera)
                writer.append_data(renderer.render())
