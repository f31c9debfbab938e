"""Offscreen video: frames written for a moving body; a clear error when no GL backend works."""

import imageio
import mujoco
import numpy as np
import pytest
from _gl import gl_available
from _toy_env import PointPick

from popsan_jax.analysis.video import GL_BACKENDS, render_video
from popsan_jax.errors import UserError

HAVE_GL = any(gl_available(b) for b in GL_BACKENDS)
# subprocess forks the (multithreaded) JAX process only to exec a fresh Python at once.
pytestmark = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")


@pytest.mark.skipif(not HAVE_GL, reason="neither EGL nor OSMesa works (apt-get install libosmesa6)")
def test_video_frames_follow_qpos(tmp_path):
    model = PointPick().mj_model
    qpos = np.tile(model.qpos0, (12, 1))
    qpos[:, 0] = np.linspace(-0.3, 0.3, 12)  # the box slides along x
    path, backend = render_video(model, qpos, tmp_path / "v.mp4", fps=10, width=160, height=128)
    assert backend in GL_BACKENDS and path.stat().st_size > 1000
    frames = [np.asarray(f, dtype=float) for f in imageio.get_reader(path)]
    assert len(frames) == 12 and frames[0].shape == (128, 160, 3)
    assert frames[0].std() > 5  # not a blank image
    assert np.abs(frames[0] - frames[-1]).mean() > 0.5  # the body moved


def test_no_gl_backend_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.delenv("MUJOCO_GL", raising=False)  # else the user's choice is tried first
    model = PointPick().mj_model
    qpos = np.tile(model.qpos0, (2, 1))
    with pytest.raises(UserError, match="no GL backend works.*libosmesa6") as exc:
        render_video(model, qpos, tmp_path / "v.mp4", backends=("no-such-gl",))
    assert "\n" not in str(exc.value)
    with pytest.raises(ValueError):
        render_video(model, qpos[:, :3], tmp_path / "v.mp4")


@pytest.mark.skipif(not HAVE_GL, reason="neither EGL nor OSMesa works (apt-get install libosmesa6)")
def test_video_places_mocap_bodies(tmp_path):
    # No joints at all: only the mocap target can move, so any change between frames is its doing.
    model = mujoco.MjModel.from_xml_string(
        """<mujoco><worldbody><light pos="0 0 3"/>
        <geom type="plane" size="2 2 0.1" rgba="0.8 0.8 0.8 1"/>
        <body name="target" mocap="true" pos="0 0 0.3">
          <geom type="sphere" size="0.06" rgba="0.1 0.9 0.1 1" contype="0" conaffinity="0"/>
        </body></worldbody></mujoco>"""
    )
    qpos = np.zeros((6, 0))
    still, _ = render_video(model, qpos, tmp_path / "still.mp4", fps=10, width=160, height=128)
    mocap = np.zeros((6, 1, 3))
    mocap[:, 0, 0] = np.linspace(-0.3, 0.3, 6)
    mocap[:, 0, 2] = 0.3
    moving, _ = render_video(
        model, qpos, tmp_path / "moving.mp4", fps=10, width=160, height=128, mocap_pos=mocap
    )
    still_frames = [np.asarray(f, dtype=float) for f in imageio.get_reader(still)]
    frames = [np.asarray(f, dtype=float) for f in imageio.get_reader(moving)]
    assert len(frames) == 6
    assert np.abs(still_frames[0] - still_frames[-1]).mean() < 0.5  # nothing moves without mocap
    assert np.abs(frames[0] - frames[-1]).mean() > 0.5  # the target moved
