"""Evaluation rollouts against a plain Python loop on a tiny env with known dynamics."""

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State

from popsan_jax.rollout import make_episode_runner, run_episodes


class _Config:
    episode_length = 6


class CounterEnv(Env):
    """x starts at the env's index-dependent value, moves by the action; done when x >= 3.

    reward = x after the step; metric "dist" = |x|; the episode metrics, as the Panda envs keep
    them: ``success`` = 2 <= x < 3 at this step (not terminated), ``reached`` latches once x >= 2,
    ``hold_time`` counts the steps with x >= 2. A NaN is injected into x after termination to
    check that masking keeps it out.
    """

    config = _Config()

    def reset(self, rng: jax.Array) -> State:
        x0 = jax.random.randint(rng, (), 0, 3).astype(jnp.float32)
        zero = jnp.zeros(())
        return State(
            pipeline_state=None,
            obs=jnp.array([x0]),
            reward=zero,
            done=zero,
            metrics={"dist": zero, "success": zero, "reached": zero, "hold_time": zero},
            info={"target_pos": jnp.zeros(3)},
        )

    def step(self, state: State, action: jax.Array) -> State:
        x = state.obs[0]
        x = jnp.where(state.done > 0, jnp.nan, x + action[0])
        there = (x >= 2).astype(jnp.float32)
        return state.replace(
            obs=jnp.array([x]),
            reward=x,
            done=(x >= 3).astype(jnp.float32),
            metrics={
                "dist": jnp.abs(x),
                "success": there * (x < 3),
                "reached": jnp.maximum(state.metrics["reached"], there),
                "hold_time": state.metrics["hold_time"] + there,
            },
        )

    @property
    def observation_size(self) -> int:
        return 1

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "none"


def _reference(x0: float, step: float, limit: int) -> tuple[float, ...]:
    """Plain Python episode: (success, length, return, mean dist, reached, hold_time)."""
    x, ret, length, success, dist, reached, hold = x0, 0.0, 0, 0.0, 0.0, 0.0, 0.0
    for _ in range(limit):
        x += step
        ret += x
        dist += abs(x)
        length += 1
        success = float(2 <= x < 3)  # the value at the episode's last step counts
        reached = max(reached, float(x >= 2))
        hold += float(x >= 2)
        if x >= 3:
            break
    return success, length, ret, dist / length, reached, hold


def test_episode_statistics_match_python_loop():
    env = CounterEnv()
    key = jax.random.PRNGKey(0)
    n = 16
    batch = run_episodes(env, lambda obs, k: jnp.full((obs.shape[0], 1), 0.3), key, n)
    x0 = np.asarray(jax.vmap(env.reset)(jax.random.split(jax.random.split(key)[1], n)).obs[:, 0])
    assert set(x0.tolist()) == {0.0, 1.0, 2.0}  # the seed covers every start
    for i in range(n):
        success, length, ret, dist, reached, hold = _reference(
            float(x0[i]), 0.3, env.config.episode_length
        )
        assert batch.success[i] == success
        assert batch.reached[i] == reached and batch.hold_time[i] == hold
        assert batch.length[i] == length
        np.testing.assert_allclose(batch.ret[i], ret, rtol=1e-6)
        np.testing.assert_allclose(batch.terms["dist"][i], dist, rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(batch.ret)))
    # The seed has episodes that end at the time limit holding (success) and ones that end by
    # terminating after reaching (reached, no success).
    assert set(np.asarray(batch.success).tolist()) == {0.0, 1.0}
    assert np.any((np.asarray(batch.reached) == 1) & (np.asarray(batch.success) == 0))


def test_record_masks_and_runner_reuses_compilation():
    env = CounterEnv()
    runner = make_episode_runner(
        env, lambda p: lambda obs, k: jnp.full((obs.shape[0], 1), p), 4, record=True
    )
    batch = runner(jnp.float32(1.0), jax.random.PRNGKey(1))
    assert batch.obs.shape == (6, 4, 1) and batch.action.shape == (6, 4, 1)
    assert batch.info["target_pos"].shape == (6, 4, 3)
    # alive counts exactly the episode's steps, and the first recorded obs is the reset obs.
    np.testing.assert_array_equal(np.asarray(batch.alive).sum(0), np.asarray(batch.length))
    for i in range(4):
        x0 = float(batch.obs[0, i, 0])
        assert batch.length[i] == _reference(x0, 1.0, 6)[1]
    runner(jnp.float32(0.5), jax.random.PRNGKey(2))
    assert runner._cache_size() == 1
