"""Shared Franka Panda logic: model loading, config handling, action semantics, the base env.

The robot (``assets/panda.xml``) has 9 actuated joints: 7 arm joints and 2 finger slides, each
driven by a position servo whose target is ``data.ctrl``. The action (9 values, clipped to
[-1, 1] here) moves those targets, as in PixMC's FrankaPick::

    target += speed_scale * ctrl_dt * action * action_scale   # speed_scale 1 (arm), 0.1 (fingers)
    target  = clip(target, joint_lower, joint_upper)   # finger targets: [finger_target_low, upper]

``action_scale`` is PixMC's 7.5 by default (0.15 rad per 50 Hz step at full action; franka_reach).
franka_pick uses 2.0, because PixMC's scale leaves no room for exploration noise in a grasp (see
its module docstring).

Everything an episode needs to carry across steps (servo targets, success counters, the reach
target) lives inside the ``mjx.Data`` (``ctrl``, ``userdata``, ``mocap_pos``), not in
``State.info``: Brax's ``AutoResetWrapper`` restores only ``pipeline_state`` and ``obs`` when an
episode ends, so per-episode state kept in ``info`` would leak into the next episode.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import mujoco
import numpy as np
from brax.envs.base import Env
from mujoco import mjx

from envs.errors import EnvConfigError

ASSETS_DIR = Path(__file__).resolve().parent / "assets"

ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("finger_joint1", "finger_joint2")
JOINTS = ARM_JOINTS + FINGER_JOINTS
# Home pose (DESIGN.md): hand ~0.55 m in front of the base, ~0.62 m up, pointing down; fingers open.
HOME_QPOS = np.array([0.0, 0.0, 0.0, -np.pi / 2, 0.0, np.pi / 2, -np.pi / 4, 0.04, 0.04])
ACTION_SCALE = 7.5  # PixMC's
SPEED_SCALE = np.array([1.0] * 7 + [0.1] * 2)
# Lowest finger servo target (m): 2 cm past the closed limit, so a finger that meets the cube, or
# its own closed stop, still squeezes with up to kp * 0.02 = 20 N (the force range). Clamped at the
# limit (0.0, revisions <= 2) a finger pressed to its stop holds with no servo force at all, and
# policies learnt exactly that grasp: one finger at each stop, the cube wedged between them, and
# it slipped out within seconds (docs/design.md, "The grasp that squeezes").
FINGER_TARGET_LOW = -0.02
# The override that restores the finger targets of revisions <= 2 (both Panda envs' revision 3).
CLAMPED_FINGERS: dict[str, Any] = dict(finger_target_low=0.0)
NUM_ACTUATORS = 9


def base_config(**fields: Any) -> ml_collections.ConfigDict:
    """Physics/control fields shared by the Panda envs, updated with the env-specific ``fields``
    (which may replace a shared default, e.g. ``action_scale``)."""
    values: dict[str, Any] = dict(
        ctrl_dt=0.02,
        sim_dt=0.02,
        iterations=4,
        ls_iterations=6,
        init_joint_noise=0.125,
        action_scale=ACTION_SCALE,
        finger_target_low=FINGER_TARGET_LOW,
    )
    values.update(fields)
    return ml_collections.ConfigDict(values)


def merge_overrides(*layers: Mapping[str, Any]) -> dict[str, Any]:
    """Config overrides of several sources in one dict, later layers winning key by key; a dict
    value (``reward_scales``, the configs' only nested level) is merged one level deep, so a layer
    that sets one scale keeps the scales that earlier layers set."""
    merged: dict[str, Any] = {}
    for layer in layers:
        for key, value in layer.items():
            if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
                value = {**merged[key], **value}
            merged[key] = dict(value) if isinstance(value, Mapping) else value
    return merged


def apply_overrides(
    config: ml_collections.ConfigDict, overrides: Mapping[str, Any], env_name: str
) -> ml_collections.ConfigDict:
    """Return a locked copy of ``config`` with ``overrides`` applied; unknown keys are errors.

    Nested dicts (``reward_scales``) are merged key by key, so ``reward_scales={"lift": 2.0}``
    changes one scale and keeps the others.
    """
    config = ml_collections.ConfigDict(config.to_dict())
    for key, value in overrides.items():
        if key not in config:
            raise EnvConfigError(
                f"unknown config key {key!r} for env {env_name!r}; known: {sorted(config.keys())}"
            )
        current = config[key]
        if isinstance(current, ml_collections.ConfigDict):
            if not isinstance(value, Mapping):
                raise EnvConfigError(f"config key {key!r} of env {env_name!r} takes a mapping")
            for sub, sub_value in value.items():
                if sub not in current:
                    raise EnvConfigError(
                        f"unknown key {key}.{sub!r} for env {env_name!r}; "
                        f"known: {sorted(current.keys())}"
                    )
                current[sub] = _coerce(current[sub], sub_value, f"{key}.{sub}", env_name)
        else:
            config[key] = _coerce(current, value, key, env_name)
    for key in ("ctrl_dt", "sim_dt"):
        if not config[key] > 0:
            raise EnvConfigError(f"{key} must be > 0, got {config[key]}")
    n_sub = config.ctrl_dt / config.sim_dt
    if abs(n_sub - round(n_sub)) > 1e-6 or round(n_sub) < 1:
        raise EnvConfigError(
            f"ctrl_dt ({config.ctrl_dt}) must be a positive multiple of sim_dt ({config.sim_dt})"
        )
    for key in ("iterations", "ls_iterations"):
        if config[key] < 1:
            raise EnvConfigError(f"{key} must be >= 1, got {config[key]}")
    if config.init_joint_noise < 0:
        raise EnvConfigError(f"init_joint_noise must be >= 0, got {config.init_joint_noise}")
    if not -0.04 <= config.finger_target_low <= 0.0:
        raise EnvConfigError(
            f"finger_target_low must be in [-0.04, 0] m, got {config.finger_target_low}"
        )
    if not config.action_scale > 0:
        raise EnvConfigError(f"action_scale must be > 0, got {config.action_scale}")
    if config.episode_length < 1:
        raise EnvConfigError(f"episode_length must be >= 1, got {config.episode_length}")
    config.lock()
    return config


def _coerce(current: Any, value: Any, key: str, env_name: str) -> Any:
    """``value`` as the type of the default ``current``: a number stays a finite number (an int
    field takes integers only), a string a string, a tuple a tuple of the same length, element
    by element (``pad_solimp``, ``target_low``). Anything else is an EnvConfigError."""

    def bad(why: str) -> EnvConfigError:
        return EnvConfigError(f"bad value {value!r} for {key!r} of {env_name!r}: {why}")

    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise bad("expected true or false")
        return value
    if isinstance(current, int | float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("expected a number")
        if not np.isfinite(value):
            raise bad("expected a finite number")
        if isinstance(current, int):
            if value != int(value):
                raise bad("expected an integer")
            return int(value)
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise bad("expected a string")
        return value
    if isinstance(current, tuple | list):
        if not isinstance(value, tuple | list) or len(value) != len(current):
            raise bad(f"expected a list of {len(current)} like {list(current)}")
        return type(current)(
            _coerce(c, v, f"{key}[{i}]", env_name)
            for i, (c, v) in enumerate(zip(current, value, strict=True))
        )
    raise bad(f"cannot override a {type(current).__name__}")


def load_model(scene: str, config: ml_collections.ConfigDict) -> mujoco.MjModel:
    """Compile ``assets/<scene>`` and apply the config's solver settings."""
    model = mujoco.MjModel.from_xml_path(str(ASSETS_DIR / scene))
    model.opt.timestep = config.sim_dt
    model.opt.iterations = config.iterations
    model.opt.ls_iterations = config.ls_iterations
    return model


def _f32(x: jax.Array) -> jax.Array:
    """Strongly typed float32, so reset and step states have identical avals (no recompiles)."""
    return jnp.asarray(x, dtype=jnp.float32).astype(jnp.float32)


class PandaEnv(Env):
    """Base class: owns the model, the action semantics and the NaN guard. Subclasses define
    ``reset`` and ``step``."""

    scene: str = ""
    # The env's revision and, per earlier revision, the config overrides that restore it
    # (envs.legacy_overrides merges them for run configs saved by an earlier version).
    revision: int = 1
    legacy_overrides: dict[int, dict[str, Any]] = {}

    def __init__(self, config: ml_collections.ConfigDict):
        self._config = config
        self._mj_model = load_model(self.scene, config)
        self._tune_model(self._mj_model)
        # This process's own device: MJX defaults to jax.devices()[0], which under jax.distributed
        # belongs to process 0.
        device = jax.local_devices()[0]
        self._mjx_model = mjx.put_model(self._mj_model, device=device)
        self._n_substeps = int(round(config.ctrl_dt / config.sim_dt))
        m = self._mj_model
        jnt = [m.joint(name) for name in JOINTS]
        self._qpos_adr = np.array([j.qposadr[0] for j in jnt])
        self._qvel_adr = np.array([j.dofadr[0] for j in jnt])
        self._lower = np.array([j.range[0] for j in jnt], dtype=np.float32)
        self._upper = np.array([j.range[1] for j in jnt], dtype=np.float32)
        # Servo targets: the joint limits, except that finger targets reach finger_target_low.
        self._ctrl_lower = self._lower.copy()
        self._ctrl_lower[7:] = config.finger_target_low
        self._step_scale = (SPEED_SCALE * config.ctrl_dt * config.action_scale).astype(np.float32)
        self._left_tip = m.site("left_tip").id
        self._right_tip = m.site("right_tip").id
        self._template = mjx.make_data(self._mjx_model, device=device)

    # ----- Brax Env interface -------------------------------------------------------------
    @property
    def config(self) -> ml_collections.ConfigDict:
        return self._config

    @property
    def mj_model(self) -> mujoco.MjModel:
        return self._mj_model

    @property
    def mjx_model(self) -> mjx.Model:
        return self._mjx_model

    @property
    def dt(self) -> float:
        return float(self._config.ctrl_dt)

    @property
    def action_size(self) -> int:
        return NUM_ACTUATORS

    @property
    def backend(self) -> str:
        return "mjx"

    # ----- shared pieces ------------------------------------------------------------------
    def _tune_model(self, model: mujoco.MjModel) -> None:
        """Apply env-specific config to the compiled model before it goes to MJX (no-op here)."""

    @property
    def action_step(self) -> np.ndarray:
        """Servo-target change per unit action per control step ``[9]`` (rad; m for fingers)."""
        return self._step_scale.copy()

    def joint_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper limits ``[9]`` of the 9 actuated joints."""
        return self._lower.copy(), self._upper.copy()

    def target_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds ``[9]`` of the servo targets: the joint limits, but finger
        targets go down to ``finger_target_low``."""
        return self._ctrl_lower.copy(), self._upper.copy()

    def _initial_data(self, q: jax.Array, **fields: jax.Array) -> mjx.Data:
        """A forward-computed ``mjx.Data`` with the 9 joints at ``q`` ``[9]`` (zero velocity),
        the servo targets at ``q`` and other Data ``fields`` (e.g. the object's qpos) replaced."""
        qpos = fields.pop("qpos", self._template.qpos).at[self._qpos_adr].set(q)
        data = self._template.replace(qpos=qpos, ctrl=q, **fields)
        return mjx.forward(self._mjx_model, data)

    def _reward(self, terms: Mapping[str, jax.Array]) -> jax.Array:
        """Scaled sum of the unscaled reward terms (``config.reward_scales``)."""
        scales = self._config.reward_scales
        return _f32(sum(scales[k] * terms[k] for k in scales))

    def _random_arm_qpos(self, rng: jax.Array) -> jax.Array:
        """Home pose with U(+-init_joint_noise) on the 7 arm joints, fingers open: ``[9]``."""
        noise = jax.random.uniform(
            rng, (7,), minval=-self._config.init_joint_noise, maxval=self._config.init_joint_noise
        )
        q = jnp.asarray(HOME_QPOS, jnp.float32).at[:7].add(noise)
        return jnp.clip(q, self._lower, self._upper)

    def _physics_step(self, data: mjx.Data, action: jax.Array) -> tuple[mjx.Data, jax.Array]:
        """Clip the action, move the servo targets, run the substeps. Returns (data, action)."""
        action = jnp.clip(action, -1.0, 1.0)
        ctrl = jnp.clip(data.ctrl + self._step_scale * action, self._ctrl_lower, self._upper)
        data = data.replace(ctrl=ctrl)
        # A loop, not a Python for: the substeps then trace and compile once, not once each
        # (franka_pick's two substeps more than doubled its compile; docs/benchmarks.md).
        data = jax.lax.fori_loop(
            0, self._n_substeps, lambda _, d: mjx.step(self._mjx_model, d), data
        )
        # mjx.step leaves body/site positions at the state BEFORE integration (one 20 ms control
        # step old here); refresh them so tips, object and joints in obs/reward agree.
        data = mjx.kinematics(self._mjx_model, data)
        return data, action

    def _joint_obs(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """Joint positions scaled to [-1, 1] in their limits ``[9]``; velocities x 0.1 ``[9]``."""
        q = data.qpos[self._qpos_adr]
        qd = data.qvel[self._qvel_adr]
        scaled = 2.0 * (q - self._lower) / (self._upper - self._lower) - 1.0
        return scaled, 0.1 * qd

    def _tips(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """Left and right fingertip pad centres ``[3]`` each."""
        return data.site_xpos[self._left_tip], data.site_xpos[self._right_tip]

    @staticmethod
    def _non_finite(data: mjx.Data) -> jax.Array:
        """True when the physics state has blown up (NaN/inf or absurd velocity)."""
        finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
        return ~finite | jnp.any(jnp.abs(data.qvel) > 1e3)

    @staticmethod
    def _sanitize(x: jax.Array) -> jax.Array:
        return jnp.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def hold_update(userdata: jax.Array, at_goal: jax.Array, reach_steps: int) -> jax.Array:
    """Advance ``userdata = [consecutive steps at the goal, reached (0/1), steps at the goal in
    all]`` ``[3]`` by one control step; "at the goal" is the task's own test (pick: the cube
    held inside the goal band). ``reached`` latches after ``reach_steps`` consecutive steps.
    Floats, so the Data keeps one dtype."""
    count = jnp.where(at_goal, userdata[0] + 1.0, 0.0)
    reached = jnp.maximum(userdata[1], (count >= reach_steps).astype(jnp.float32))
    total = userdata[2] + at_goal.astype(jnp.float32)
    return jnp.stack([count, reached, total]).astype(jnp.float32)


def episode_metrics(
    userdata: jax.Array, done: jax.Array, hold_steps: int, ctrl_dt: float
) -> dict[str, jax.Array]:
    """The episode metrics from the :func:`hold_update` counters: ``success`` (at the goal for
    the last ``hold_steps`` steps and not terminated: ``done`` is this step's termination),
    ``reached`` (the latch) and ``hold_time`` (seconds at the goal so far)."""
    success = (userdata[0] >= hold_steps) & (done == 0)
    return as_f32_dict(dict(success=success, reached=userdata[1], hold_time=userdata[2] * ctrl_dt))


def as_f32_dict(d: Mapping[str, jax.Array]) -> dict[str, jax.Array]:
    """Float32 scalars for metrics (Brax's wrappers average them)."""
    return {k: _f32(v) for k, v in d.items()}
