"""The Panda MJCF against Franka's published facts (classic MuJoCo: no MJX compile needed)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from envs.panda import ASSETS_DIR, HOME_QPOS, JOINTS

# Franka's Craig-convention DH table (a, d, alpha) for joints 1-7 and the flange (DESIGN.md).
DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -np.pi / 2),
    (0.0, 0.316, np.pi / 2),
    (0.0825, 0.0, np.pi / 2),
    (-0.0825, 0.384, -np.pi / 2),
    (0.0, 0.0, np.pi / 2),
    (0.088, 0.0, np.pi / 2),
]
FLANGE_D = 0.107
LIMITS = [
    (-2.8973, 2.8973),
    (-1.7628, 1.7628),
    (-2.8973, 2.8973),
    (-3.0718, -0.0698),
    (-2.8973, 2.8973),
    (-0.0175, 3.7525),
    (-2.8973, 2.8973),
]
LINK_MASSES = [4.97, 0.65, 3.23, 3.59, 1.23, 1.67, 0.74]


def dh_flange(q: np.ndarray) -> np.ndarray:
    """Flange pose (4x4) from the modified-DH table, computed independently of the MJCF."""

    def craig(a, d, alpha, theta):
        ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
        return np.array(
            [
                [ct, -st, 0, a],
                [st * ca, ct * ca, -sa, -sa * d],
                [st * sa, ct * sa, ca, ca * d],
                [0, 0, 0, 1],
            ]
        )

    t = np.eye(4)
    for (a, d, alpha), theta in zip(DH, q, strict=True):
        t = t @ craig(a, d, alpha, theta)
    return t @ craig(0.0, FLANGE_D, 0.0, 0.0)


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(ASSETS_DIR / "pick_scene.xml"))


def _forward(model, q):
    data = mujoco.MjData(model)
    data.qpos[:7] = q
    mujoco.mj_kinematics(model, data)
    return data


def test_home_pose_matches_dh_and_published_position(model):
    data = _forward(model, HOME_QPOS[:7])
    expected = dh_flange(HOME_QPOS[:7])
    np.testing.assert_allclose(data.site("flange").xpos, expected[:3, 3], atol=1e-6)
    # DESIGN.md: hand origin about 0.55 m in front of the base and 0.62 m up, pointing down.
    hand = data.body("hand")
    assert abs(hand.xpos[0] - 0.55) < 0.01 and abs(hand.xpos[2] - 0.62) < 0.01
    assert abs(hand.xpos[1]) < 1e-6
    np.testing.assert_allclose(hand.xmat.reshape(3, 3)[:, 2], [0, 0, -1], atol=1e-6)


def test_random_poses_match_dh(model):
    rng = np.random.default_rng(0)
    lo, hi = np.array(LIMITS).T
    for _ in range(20):
        q = rng.uniform(lo, hi)
        data = _forward(model, q)
        expected = dh_flange(q)
        np.testing.assert_allclose(data.site("flange").xpos, expected[:3, 3], atol=1e-6)
        flange_rot = data.body("link7").xmat.reshape(3, 3)
        np.testing.assert_allclose(flange_rot, expected[:3, :3], atol=1e-6)
        # The hand is the flange rotated by -pi/4 about its z axis.
        rz = np.array(
            [
                [np.cos(-np.pi / 4), -np.sin(-np.pi / 4), 0],
                [np.sin(-np.pi / 4), np.cos(-np.pi / 4), 0],
                [0, 0, 1],
            ]
        )
        np.testing.assert_allclose(
            data.body("hand").xmat.reshape(3, 3), expected[:3, :3] @ rz, atol=1e-6
        )


def test_limits_masses_and_fingers(model):
    for name, (lo, hi) in zip(JOINTS[:7], LIMITS, strict=True):
        np.testing.assert_allclose(model.joint(name).range, [lo, hi], atol=1e-6)
        assert model.joint(name).armature[0] == pytest.approx(0.1)
    for name in JOINTS[7:]:
        np.testing.assert_allclose(model.joint(name).range, [0.0, 0.04])
    for i, mass in enumerate(LINK_MASSES, start=1):
        assert model.body(f"link{i}").mass[0] == pytest.approx(mass, abs=0.01)
    assert model.body("hand").mass[0] == pytest.approx(0.73)
    # The only contacts are the explicit pairs; no geom collides by contype/conaffinity.
    assert np.all(model.geom_contype == 0) and np.all(model.geom_conaffinity == 0)
    assert model.npair == 4


def test_holds_home_pose_under_gravity(model):
    """Position servos hold the home pose for 3 s (no drift, no blow-up) at the env's 50 Hz."""
    data = mujoco.MjData(model)
    data.qpos[:9] = HOME_QPOS
    data.qpos[9:16] = [0.5, 0.0, 0.02, 1, 0, 0, 0]
    data.ctrl[:] = HOME_QPOS
    for _ in range(150):
        mujoco.mj_step(model, data)
    assert np.all(np.isfinite(data.qpos))
    np.testing.assert_allclose(data.qpos[:9], HOME_QPOS, atol=2e-3)
    assert np.max(np.abs(data.qvel[:9])) < 1e-2
    # The cube rests on the floor (its centre at its half-size, within the contact softness).
    assert abs(data.qpos[11] - 0.02) < 2e-3


def test_joint_limits_hold_when_commanded_beyond(model):
    data = mujoco.MjData(model)
    data.qpos[:9] = HOME_QPOS
    data.qpos[9:16] = [0.5, 0.0, 0.02, 1, 0, 0, 0]
    data.ctrl[:] = 10.0  # ctrlrange clamps the servo targets to the joint ranges
    for _ in range(150):
        mujoco.mj_step(model, data)
    hi = np.array([r[1] for r in LIMITS] + [0.04, 0.04])
    assert np.all(data.qpos[:9] <= hi + 0.01)
