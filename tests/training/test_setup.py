"""The run's building blocks: env errors translated, the one observation preprocessing, the
PopSAN at another T, and the optimiser's actor / critic split."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses

from popsan_jax.config import RunConfig
from popsan_jax.errors import ConfigError
from popsan_jax.training.setup import (
    at_timesteps,
    make_env,
    make_optimizer,
    preprocess_observations,
    trained_timesteps,
)


def test_env_errors_become_config_errors():
    with pytest.raises(ConfigError, match="unknown env 'franka_fly'"):
        make_env(RunConfig(env="franka_fly"))
    with pytest.raises(ConfigError, match="unknown config key 'bogus'"):
        make_env(RunConfig(env="franka_reach", env_overrides={"bogus": 1}))


def test_preprocessing_normalises_and_clips():
    stats = running_statistics.init_state(jnp.zeros((2,)))
    stats = running_statistics.update(stats, jnp.array([[0.0, 10.0], [2.0, 30.0]]))
    # mean (1, 20), std (1, 10): obs (3, 20) -> (2, 0); (100, -1000) clips to (+3, -3).
    out = preprocess_observations(jnp.array([[3.0, 20.0], [100.0, -1000.0]]), stats, 3.0)
    np.testing.assert_allclose(out, [[2.0, 0.0], [3.0, -3.0]], atol=1e-5)


def test_popsan_at_another_timesteps():
    config = RunConfig()
    assert trained_timesteps(config) == 5
    assert at_timesteps(config, None) is config and at_timesteps(config, 5) is config
    other = at_timesteps(config, 2)
    assert other.actor_kwargs == {**config.actor_kwargs, "timesteps": 2}
    assert config.actor_kwargs["timesteps"] == 5  # unchanged
    assert trained_timesteps(RunConfig(actor="mlp", actor_kwargs={"hidden_sizes": (8,)})) is None


def test_optimizer_uses_separate_actor_and_critic_learning_rates():
    # Adam's first step is -lr * sign(grad) (bias-corrected m/sqrt(v) = +-1), so each group's
    # step size reveals its learning rate.
    c = RunConfig(actor_lr=1e-5, critic_lr=1e-4, max_grad_norm=None)
    params = ppo_losses.PPONetworkParams(policy={"w": jnp.ones(3)}, value={"w": jnp.ones(2)})
    grads = ppo_losses.PPONetworkParams(
        policy={"w": jnp.array([0.5, -2.0, 3.0])}, value={"w": jnp.array([-1.0, 4.0])}
    )
    opt = make_optimizer(c)
    updates, _ = opt.update(grads, opt.init(params), params)
    np.testing.assert_allclose(updates.policy["w"], [-1e-5, 1e-5, -1e-5], rtol=1e-3)
    np.testing.assert_allclose(updates.value["w"], [1e-4, -1e-4], rtol=1e-3)
