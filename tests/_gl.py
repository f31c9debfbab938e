"""Whether this machine can render offscreen: the video tests skip without a GL backend."""

from __future__ import annotations

import os
import subprocess
import sys


def gl_available(backend: str = "osmesa") -> bool:
    """Whether ``backend`` can make a MuJoCo GL context (probed in a subprocess)."""
    code = (
        "import mujoco; m = mujoco.MjModel.from_xml_string('<mujoco/>'); "
        "r = mujoco.Renderer(m, 16, 16); r.update_scene(mujoco.MjData(m)); r.render()"
    )
    env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=120)
    return proc.returncode == 0
