"""The run's building blocks: env errors translated, the one observation preprocessing, the
PopSAN at another T, and the optimiser's actor / critic split and critic warm-up."""

from __future__ import annotations

import jax
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


def _adam_steps(grads: list[np.ndarray], lr: float) -> list[np.ndarray]:
    """Plain Adam (optax's defaults: b1 0.9, b2 0.999, eps 1e-8), its updates step by step."""
    m = v = np.zeros_like(grads[0])
    out = []
    for t, g in enumerate(grads, start=1):
        m, v = 0.9 * m + 0.1 * g, 0.999 * v + 0.001 * g * g
        out.append(-lr * (m / (1 - 0.9**t)) / (np.sqrt(v / (1 - 0.999**t)) + 1e-8))
    return out


@pytest.mark.parametrize("per_network", [False, True])
def test_grad_clip_of_the_joint_gradient_or_of_each_network(per_network):
    """200 updates with a critic gradient of norm 50, then 20 of norm 0.5, beside a constant
    actor gradient of norm 0.5 (as a started critic's loss falls). The joint clip (norm 1)
    shrinks the actor's gradient 100-fold while the critic's is large, so Adam's slow second
    moment remembers a small actor gradient and, once the critic's falls, the actor's steps
    grow to several times its learning rate. Clipped per network, the actor's gradient is
    never touched and every step is lr * sign. Against a plain Adam on the clipped gradients."""
    c = RunConfig(actor_lr=1e-3, critic_lr=1e-2, max_grad_norm=1.0, clip_per_network=per_network)
    actor_g = np.array([0.3, -0.4])  # norm 0.5
    critic_g = [np.array([30.0, 40.0])] * 200 + [np.array([0.3, 0.4])] * 20  # norms 50, 0.5
    params = ppo_losses.PPONetworkParams(policy={"w": jnp.ones(2)}, value={"w": jnp.ones(2)})
    opt = make_optimizer(c)
    state = opt.init(params)
    update = jax.jit(lambda g, s: opt.update(g, s, params))
    got_actor, got_critic = [], []
    for cg in critic_g:
        grads = ppo_losses.PPONetworkParams(policy={"w": jnp.asarray(actor_g)}, value={"w": cg})
        updates, state = update(grads, state)
        got_actor.append(np.asarray(updates.policy["w"]))
        got_critic.append(np.asarray(updates.value["w"]))

    def clip(g: np.ndarray, norm: float) -> np.ndarray:
        return g * min(1.0, 1.0 / norm)

    if per_network:
        actor_in = [clip(actor_g, 0.5)] * len(critic_g)
        critic_in = [clip(g, np.linalg.norm(g)) for g in critic_g]
    else:
        joint = [np.hypot(0.5, np.linalg.norm(g)) for g in critic_g]
        actor_in = [clip(actor_g, n) for n in joint]
        critic_in = [clip(g, n) for g, n in zip(critic_g, joint, strict=True)]
    np.testing.assert_allclose(got_actor, _adam_steps(actor_in, 1e-3), rtol=1e-4)
    np.testing.assert_allclose(got_critic, _adam_steps(critic_in, 1e-2), rtol=1e-4)
    last = np.abs(got_actor[-1]) / 1e-3  # the actor's last step, in units of its lr
    if per_network:
        np.testing.assert_allclose(np.abs(np.array(got_actor)) / 1e-3, 1.0, rtol=1e-4)
    else:
        assert np.all(last > 2.5), last


def test_critic_warmup_freezes_the_actor_then_runs_its_schedule_over_the_rest():
    # 640 env steps and 4 x 2 = 8 updates per iteration, 4 iterations = 32 updates; a critic
    # warm-up of 641 env steps rounds up to 2 whole iterations = 16 updates with the actor still.
    c = RunConfig(
        num_envs=16, batch_size=16, num_minibatches=4, unroll_length=10, num_updates_per_batch=2,
        total_env_steps=4 * 640, critic_warmup_env_steps=641, lr_schedule="cosine",
        actor_lr=1e-3, critic_lr=1e-2, max_grad_norm=None,
    )  # fmt: skip
    assert c.critic_warmup_iterations == 2
    # A constant gradient makes each Adam step -lr(t) * sign(grad) exactly (bias-corrected
    # m / sqrt(v) = sign), so the steps trace each group's learning rate update by update.
    params = ppo_losses.PPONetworkParams(policy={"w": jnp.ones(2)}, value={"w": jnp.ones(1)})
    grads = ppo_losses.PPONetworkParams(
        policy={"w": jnp.array([2.0, -0.5])}, value={"w": -jnp.ones(1)}
    )
    opt = make_optimizer(c)
    state = opt.init(params)
    actor, critic = [], []
    for _ in range(32):
        updates, state = opt.update(grads, state, params)
        actor.append(np.asarray(updates.policy["w"]) / -np.sign([2.0, -0.5]))
        critic.append(float(updates.value["w"][0]))

    def cosine(value: float, step: int, steps: int) -> float:
        return value * 0.5 * (1 + np.cos(np.pi * step / steps))

    assert all(np.all(a == 0.0) for a in actor[:16])  # exactly still for 2 iterations
    want_actor = [cosine(1e-3, t, 16) for t in range(16)]  # then the full cosine over 16
    np.testing.assert_allclose([a[0] for a in actor[16:]], want_actor, rtol=1e-4)
    np.testing.assert_allclose([a[1] for a in actor[16:]], want_actor, rtol=1e-4)
    np.testing.assert_allclose(critic, [cosine(1e-2, t, 32) for t in range(32)], rtol=1e-4)


def test_max_kl_must_be_finite_and_not_negative():
    RunConfig(max_kl=0.0).validate()
    RunConfig(max_kl=0.5).validate()
    for bad in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ConfigError, match="max_kl must be a finite number >= 0"):
            RunConfig(max_kl=bad).validate()


def test_critic_warmup_must_leave_the_actor_an_iteration():
    c = RunConfig(num_envs=16, batch_size=16, num_minibatches=4, total_env_steps=4 * 640)
    c.replace(critic_warmup_env_steps=3 * 640).validate()
    for bad in (3 * 640 + 1, 4 * 640, -1):
        with pytest.raises(ConfigError, match="critic_warmup_env_steps must be >= 0 and leave"):
            c.replace(critic_warmup_env_steps=bad).validate()
