"""franka_pick: reset/step, obs layout, reward terms, pick-and-hold success, NaN, wrappers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _env_fixtures import BATCH, pick  # noqa: F401  (session fixture)
from brax.envs.wrappers import training

import envs
from envs.errors import EnvConfigError
from envs.franka_pick import Z_REST, is_held, pick_reward_terms
from envs.panda import HOME_QPOS, episode_metrics, hold_update


def _avals(tree):
    return jax.tree.map(lambda x: (x.shape, str(x.dtype), jax.core.get_aval(x).weak_type), tree)


@pytest.fixture(scope="module")
def stepped(pick):  # noqa: F811
    state = pick.reset(pick.keys())
    return state, pick.step(state, jnp.zeros((BATCH, 9)))


def test_reset_and_step_shapes_finite_and_stable_avals(pick, stepped):  # noqa: F811
    state, nxt = stepped
    assert pick.env.observation_size == 34 and pick.env.action_size == 9
    assert state.obs.shape == (BATCH, 34) and nxt.obs.shape == (BATCH, 34)
    assert np.all(np.isfinite(nxt.obs)) and np.all(np.isfinite(nxt.reward))
    # Identical avals => the jitted step of a reset state and of a stepped state is one compile.
    assert _avals(state) == _avals(nxt)
    for name in [
        "dist_left",
        "dist_right",
        "lift",
        "object_goal",
        "goal_bonus",
        "climb",
        "action",
        "success",
        "reached",
        "hold_time",
        "held",
        "object_speed",
    ]:
        assert nxt.metrics[name].shape == (BATCH,) and nxt.metrics[name].dtype == jnp.float32


def test_observation_layout(pick, stepped):  # noqa: F811
    _, s = stepped
    obs, info = np.asarray(s.obs), s.info
    np.testing.assert_allclose(obs[:, 18:21], info["left_tip"], atol=1e-6)
    np.testing.assert_allclose(obs[:, 21:24], info["right_tip"], atol=1e-6)
    np.testing.assert_allclose(obs[:, 24:27], info["object_pos"], atol=1e-6)
    np.testing.assert_allclose(obs[:, 27:30], info["object_pos"] - info["left_tip"], atol=1e-6)
    np.testing.assert_allclose(obs[:, 33], pick.env.goal_z - info["object_pos"][:, 2], atol=1e-6)
    lo, hi = pick.env.joint_limits()
    q = np.asarray(s.pipeline_state.qpos[:, :9])
    np.testing.assert_allclose(obs[:, :9], 2 * (q - lo) / (hi - lo) - 1, atol=1e-5)
    np.testing.assert_allclose(
        obs[:, 9:18], 0.1 * np.asarray(s.pipeline_state.qvel[:, :9]), atol=1e-6
    )


def test_randomisation_ranges(pick):  # noqa: F811
    states = [pick.reset(pick.keys(seed)) for seed in range(8)]
    obj = np.concatenate([np.asarray(s.info["object_pos"]) for s in states])
    q = np.concatenate([np.asarray(s.pipeline_state.qpos[:, :7]) for s in states])
    assert np.all((obj[:, 0] >= 0.4) & (obj[:, 0] <= 0.6))
    assert np.all((obj[:, 1] >= -0.2) & (obj[:, 1] <= 0.2))
    np.testing.assert_allclose(obj[:, 2], Z_REST, atol=1e-6)
    assert np.all(np.abs(q - HOME_QPOS[:7]) <= 0.125 + 1e-6)
    # Actually random: spread over most of the range, not a constant.
    assert np.ptp(obj[:, 0]) > 0.1 and np.ptp(obj[:, 1]) > 0.2 and np.ptp(q[:, 3]) > 0.1


def test_reward_terms_hand_computed():
    goal_z = 0.42
    left = jnp.array([0.5, 0.03, 0.02])
    right = jnp.array([0.5, -0.01, 0.02])

    def terms(obj_z, radius, tips=(left, right), action=None, vel=(0.3, 0.0, -0.4), ramp=0.0):
        obj = jnp.array([0.5, 0.0, obj_z])
        action = jnp.zeros(9) if action is None else action
        return pick_reward_terms(obj, *tips, goal_z, action, radius, jnp.array(vel), lift_ramp=ramp)

    # PixMC's ungated terms (grasp_radius 0). On the floor: left tip 3 cm away, right tip 1 cm
    # (clamped to 2 cm); not lifted.
    t = terms(0.02, 0.0, action=jnp.full(9, 0.5))
    assert float(t["dist_left"]) == pytest.approx(1 / (0.04 + 0.03), rel=1e-5)
    assert float(t["dist_right"]) == pytest.approx(1 / (0.04 + 0.02), rel=1e-5)
    assert float(t["lift"]) == 0.0 and float(t["object_goal"]) == 0.0
    assert float(t["goal_bonus"]) == 0.0 and float(t["action"]) == pytest.approx(9 * 0.25)
    # Lifted to 3 cm below the goal: lift, object_goal = 1/(0.04+0.03) and the bonus.
    t = terms(0.39, 0.0)
    assert float(t["held"]) == 1.0  # ungated: every cube counts as held
    assert float(t["lift"]) == 0.5 and float(t["goal_bonus"]) == 0.5
    assert float(t["object_goal"]) == pytest.approx(1 / 0.07, rel=1e-4)
    assert float(t["object_speed"]) == pytest.approx(0.5, rel=1e-5)  # |(0.3, 0, -0.4)| m/s
    # Charged only inside the goal band (0.42 +- 0.1 m): not on the floor, not on the way up.
    assert float(terms(0.02, 0.0)["object_speed"]) == 0.0
    assert float(terms(0.31, 0.0)["object_speed"]) == 0.0
    assert float(terms(0.33, 0.0)["object_speed"]) == pytest.approx(0.5, rel=1e-5)
    assert float(terms(0.53, 0.0)["object_speed"]) == 0.0
    # Barely above the 1.5 cm lift threshold vs barely below it.
    assert float(terms(0.036, 0.0)["lift"]) == 0.5 and float(terms(0.034, 0.0)["lift"]) == 0.0
    # A 1.5 cm ramp instead: 0 at rest (and below it), 0.5 * 6 / 15 at 6 mm, 0.5 from 1.5 cm up;
    # object_goal keeps its 1.5 cm gate.
    ramp = [float(terms(z, 0.0, ramp=0.015)["lift"]) for z in (0.015, 0.02, 0.026, 0.036, 0.3)]
    assert ramp == pytest.approx([0.0, 0.0, 0.2, 0.5, 0.5], abs=1e-6)
    assert float(terms(0.026, 0.0, ramp=0.015)["object_goal"]) == 0.0
    # climb: the held cube's share of the 0.4 m from the table (z 0.02) to the goal (0.42), in
    # proportion and with no gate: 0 at rest and below it, 0.1 at 6 cm, 0.925 at 0.39, 1 above.
    climb = [float(terms(z, 0.0)["climb"]) for z in (0.01, 0.02, 0.06, 0.39, 0.42, 0.5)]
    assert climb == pytest.approx([0.0, 0.0, 0.1, 0.925, 1.0, 1.0], abs=1e-6)

    # Grasp-gated (0.04 m): the same lifted cube far from the tips (a toss) earns no object term.
    t = terms(0.39, 0.04)
    assert float(t["lift"]) == float(t["object_goal"]) == float(t["goal_bonus"]) == 0.0
    assert float(t["climb"]) == 0.0
    assert float(t["object_speed"]) == 0.0  # a flying cube is not charged either
    assert float(t["held"]) == 0.0
    assert float(t["dist_left"]) == pytest.approx(1 / (0.04 + np.hypot(0.03, 0.37)), rel=1e-5)
    # Between the pads (1.8 cm each side) it earns all three.
    pads = (jnp.array([0.5, 0.018, 0.39]), jnp.array([0.5, -0.018, 0.39]))
    t = terms(0.39, 0.04, tips=pads)
    assert float(t["held"]) == 1.0 and float(t["climb"]) == pytest.approx(0.925, abs=1e-6)
    assert float(t["lift"]) == 0.5 and float(t["goal_bonus"]) == 0.5
    assert float(t["object_goal"]) == pytest.approx(1 / 0.07, rel=1e-4)
    assert float(t["dist_left"]) == pytest.approx(1 / (0.04 + 0.02), rel=1e-5)
    # One pad 4.1 cm away: not held; 3.9 cm: held.
    for gap, held in [(0.041, False), (0.039, True)]:
        one_off = (jnp.array([0.5, gap, 0.39]), pads[1])
        assert bool(is_held(jnp.float32(gap), jnp.float32(0.018), 0.04)) == held
        assert float(terms(0.39, 0.04, tips=one_off)["lift"]) == (0.5 if held else 0.0)
    # The ramp is grasp-gated too: a cube 6 mm up with the pads 10 cm above it earns nothing.
    high_pads = (jnp.array([0.5, 0.018, 0.126]), jnp.array([0.5, -0.018, 0.126]))
    assert float(terms(0.026, 0.04, tips=high_pads, ramp=0.015)["lift"]) == 0.0
    low_pads = (jnp.array([0.5, 0.018, 0.026]), jnp.array([0.5, -0.018, 0.026]))
    assert float(terms(0.026, 0.04, tips=low_pads, ramp=0.015)["lift"]) == pytest.approx(0.2)


def test_hold_counters_match_a_python_reference():
    rng = np.random.default_rng(0)
    at_goal = rng.random((64, 6)) < 0.85
    ud = jnp.zeros((6, 3))
    ref = [[0, 0, 0] for _ in range(6)]  # consecutive, reached, total
    step = jax.vmap(lambda u, g: hold_update(u, g, 10))
    for t in range(64):
        ud = step(ud, jnp.array(at_goal[t]))
        for i in range(6):
            ref[i][0] = ref[i][0] + 1 if at_goal[t, i] else 0
            ref[i][1] = 1 if ref[i][0] >= 10 or ref[i][1] else 0
            ref[i][2] += int(at_goal[t, i])
        np.testing.assert_array_equal(ud, ref)
    assert 0 < np.mean([r[1] for r in ref]) < 1  # the sequence exercises both outcomes


def test_episode_metrics_need_the_last_hold_and_no_termination():
    dt = 0.02
    # 100 consecutive steps at the goal: success; 99: not; terminated this step: not.
    for count, done, success in [(100, 0.0, 1.0), (99, 0.0, 0.0), (250, 1.0, 0.0)]:
        m = episode_metrics(jnp.array([count, 1.0, 120.0]), jnp.float32(done), 100, dt)
        assert float(m["success"]) == success
        assert float(m["reached"]) == 1.0
        assert float(m["hold_time"]) == pytest.approx(120 * dt)


def _with_object(state, z, userdata=None):
    """Teleport each env's cube to height ``z`` and optionally set the hold counters ``[3]``."""
    data = state.pipeline_state
    qpos = data.qpos.at[:, 11].set(z)
    ud = data.userdata if userdata is None else jnp.tile(jnp.asarray(userdata), (BATCH, 1))
    return state.replace(pipeline_state=data.replace(qpos=qpos, userdata=ud))


def test_reward_and_hold_counters_through_steps(pick):  # noqa: F811
    env = pick.env
    state = pick.reset(pick.keys(3))
    # Teleport the cube to the goal while the open hand is far away (what a toss looks like):
    # not held, so nothing counts, the object terms stay 0 and there is no success, although
    # the counters said 150 steps held in the band (a drop after a hold). ``reached`` stays.
    state = _with_object(state, env.goal_z, userdata=[150.0, 1.0, 150.0])
    nxt = pick.step(state, jnp.zeros((BATCH, 9)))
    np.testing.assert_array_equal(nxt.metrics["held"], 0.0)
    np.testing.assert_array_equal(nxt.pipeline_state.userdata[:, 0], 0.0)
    np.testing.assert_array_equal(nxt.metrics["success"], 0.0)
    np.testing.assert_array_equal(nxt.metrics["reached"], 1.0)
    np.testing.assert_allclose(nxt.metrics["hold_time"], 150 * env.dt, rtol=1e-6)
    for term in ("lift", "object_goal", "goal_bonus", "climb", "object_speed"):
        np.testing.assert_array_equal(nxt.metrics[term], 0.0)
    assert np.all(np.asarray(nxt.info["object_pos"])[:, 2] > env.goal_z - 0.05)
    # The step's reward is the scaled sum of its unscaled terms.
    scales = env.config.reward_scales
    expected = sum(scales[k] * np.asarray(nxt.metrics[k]) for k in scales)
    np.testing.assert_allclose(nxt.reward, expected, rtol=1e-5)
    assert np.all(np.asarray(nxt.reward) > 0)  # the dist terms
    # Out of the workspace: the episode terminates, and a terminated episode never succeeds
    # (the gate itself: test_episode_metrics_need_the_last_hold_and_no_termination).
    away = _with_object(nxt, Z_REST, userdata=[150.0, 1.0, 150.0])
    data = away.pipeline_state
    away = away.replace(pipeline_state=data.replace(qpos=data.qpos.at[:, 9].set(1.5)))
    gone = pick.step(away, jnp.zeros((BATCH, 9)))
    np.testing.assert_array_equal(gone.done, 1.0)  # the cube left the workspace
    np.testing.assert_array_equal(gone.metrics["success"], 0.0)


def test_action_is_clipped_and_moves_servo_targets(pick, stepped):  # noqa: F811
    state, _ = stepped
    action = jnp.tile(jnp.array([5.0, -5.0, 0.3, 0, 0, 0, 0, -7.0, 2.0]), (BATCH, 1))
    nxt = pick.step(state, action)
    delta = np.asarray(nxt.pipeline_state.ctrl - state.pipeline_state.ctrl)
    # dt 0.02 x action_scale 2.0 = 0.04 rad per unit action (arm), x 0.1 for the fingers;
    # fingers start open at their 0.04 upper limit, so +2 stays clamped there.
    np.testing.assert_allclose(delta[:, :3], [[0.04, -0.04, 0.012]] * BATCH, atol=1e-6)
    np.testing.assert_allclose(delta[:, 7:], [[-0.004, 0.0]] * BATCH, atol=1e-6)
    assert float(nxt.metrics["action"][0]) == pytest.approx(1 + 1 + 0.09 + 1 + 1, rel=1e-5)


def test_closed_fingers_squeeze_at_their_stop(pick, stepped):  # noqa: F811
    # Finger targets go 2 cm past the closed stop: 15 steps of -0.004 m from 0.04 reach -0.02,
    # and further closing stays there. With nothing between them the fingers rest on their
    # stop (MuJoCo's joint limit is soft: a few mm past it under load), and each servo pushes
    # kp * (target - q) - kv * qdot = 1000 * (-0.02 - q) N into it: about 17 N, the squeeze a
    # grasped cube feels however the fingers meet it (with targets clamped at the stop: ~0 N).
    state, _ = stepped
    close = jnp.tile(jnp.array([0.0] * 7 + [-1.0, -1.0]), (BATCH, 1))
    for _ in range(40):
        state = pick.step(state, close)
    data = state.pipeline_state
    q, qd = np.asarray(data.qpos[:, 7:9]), np.asarray(data.qvel[:, 7:9])
    np.testing.assert_allclose(data.ctrl[:, 7:], -0.02, atol=1e-6)
    assert np.all((q > -0.006) & (q < 0.001)), q  # resting on the stop
    servo = np.clip(1000.0 * (-0.02 - q) - 20.0 * qd, -20.0, 20.0)
    np.testing.assert_allclose(data.actuator_force[:, 7:], servo, atol=0.05)
    assert np.all(np.asarray(data.actuator_force[:, 7:]) < -14.0)
    lo, hi = pick.env.target_limits()
    np.testing.assert_allclose(lo, np.r_[pick.env.joint_limits()[0][:7], -0.02, -0.02])
    np.testing.assert_allclose(hi, pick.env.joint_limits()[1])


def test_revision_2_clamps_finger_targets_at_the_stop():
    # Runs saved on revision 2 rebuild its clamp: a finger at its stop has no servo force.
    for name in ("franka_pick", "franka_reach"):
        legacy = envs.legacy_overrides(name, 2)
        assert legacy["finger_target_low"] == 0.0
        old = envs.get_environment(name, **legacy)
        np.testing.assert_allclose(old.target_limits()[0], old.joint_limits()[0])
    with pytest.raises(EnvConfigError, match="finger_target_low must be in"):
        envs.get_environment("franka_pick", finger_target_low=-0.05)


def test_action_scale_config_sets_the_servo_step():
    # franka_pick's 2.0 at dt 0.02: 0.04 rad (arm) and 0.004 m (fingers, speed 0.1) per unit
    # action; PixMC's 7.5 (franka_reach's default): 0.15 and 0.015. The stepped test above
    # checks that the physics step moves the targets by exactly this vector.
    np.testing.assert_allclose(
        envs.get_environment("franka_pick").action_step, [0.04] * 7 + [0.004] * 2, rtol=1e-6
    )
    pixmc = envs.get_environment("franka_pick", action_scale=7.5)
    np.testing.assert_allclose(pixmc.action_step, [0.15] * 7 + [0.015] * 2, rtol=1e-6)
    reach = envs.get_environment("franka_reach")
    np.testing.assert_allclose(reach.action_step, pixmc.action_step, rtol=1e-6)
    with pytest.raises(EnvConfigError, match="action_scale must be > 0"):
        envs.get_environment("franka_reach", action_scale=0.0)


def test_nan_ends_only_that_env(pick, stepped):  # noqa: F811
    state, _ = stepped
    data = state.pipeline_state
    bad = state.replace(pipeline_state=data.replace(qvel=data.qvel.at[0, 0].set(jnp.nan)))
    nxt = pick.step(bad, jnp.zeros((BATCH, 9)))
    np.testing.assert_array_equal(nxt.done, [1.0, 0.0, 0.0, 0.0])
    assert np.all(np.isfinite(nxt.obs)) and np.all(np.isfinite(nxt.reward))
    assert np.all(np.isfinite(np.asarray(nxt.pipeline_state.qpos[1:])))


def test_brax_wrappers_auto_reset(pick):  # noqa: F811
    env = pick.env
    # EvalWrapper on top, as Brax's evaluator uses it: it adds a "reward" metric at reset,
    # which the env's step must carry through.
    wrapped = training.EvalWrapper(training.wrap(env, episode_length=3, action_repeat=1))
    reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
    state = reset(pick.keys(5))
    first_obs = np.asarray(state.obs)
    # Latch success by hand in env 1: it must be cleared by the auto-reset.
    data = state.pipeline_state
    state = state.replace(pipeline_state=data.replace(userdata=data.userdata.at[1, 1].set(1.0)))
    action = jnp.ones((BATCH, 9))
    for i in range(3):
        state = step(state, action)
        assert np.all(np.asarray(state.done) == (1.0 if i == 2 else 0.0))
    assert np.all(np.asarray(state.info["truncation"]) == 1.0)
    # After the timeout the envs restart from their first state (obs, servo targets, counters).
    np.testing.assert_allclose(state.obs, first_obs, atol=1e-6)
    np.testing.assert_array_equal(state.pipeline_state.userdata, 0.0)
    state = step(state, action)
    assert np.all(np.asarray(state.info["steps"]) == 1) and np.all(np.asarray(state.done) == 0)
    # The evaluator's per-episode sums stopped after the first episode: 3 steps each.
    np.testing.assert_array_equal(state.info["eval_metrics"].episode_steps, 3)
    assert "success" in state.info["eval_metrics"].episode_metrics


def test_registry_errors_and_overrides():
    assert envs.list_environments() == ["franka_pick", "franka_reach"]
    with pytest.raises(EnvConfigError, match="franka_pick, franka_reach"):
        envs.get_environment("franka_push")
    with pytest.raises(EnvConfigError, match="unknown config key 'episode_len'"):
        envs.get_environment("franka_pick", episode_len=10)
    with pytest.raises(EnvConfigError, match="reward_scales"):
        envs.get_environment("franka_pick", reward_scales={"bogus": 1.0})
    env = envs.get_environment("franka_pick", episode_length=50, reward_scales={"lift": 2.0})
    assert env.config.episode_length == 50 and env.config.reward_scales.lift == 2.0
    assert env.config.reward_scales.goal_bonus == 4.0
    assert env.mj_model.camera("front").id >= 0 and env.goal_z == pytest.approx(0.42)
