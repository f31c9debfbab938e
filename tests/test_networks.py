"""Brax PPO factory: shapes, mode == actor mean, log-std, inference fn, compute_ppo_loss."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training import types
from brax.training.agents.ppo import losses
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax import Critic, MLPActor, actor_variables, make_actor, make_ppo_networks
from popsan_jax.config import MLP_DEFAULTS
from popsan_jax.errors import ConfigError
from popsan_jax.recipes import ACTOR_RECIPES

OBS, ACT = 7, 3
SMALL = {
    "popsan": dict(hidden_sizes=(16, 16), encoder_pop_dim=4, decoder_pop_dim=4, timesteps=3),
    "mlp": dict(hidden_sizes=(16, 16)),
}


def _scale_preprocess(obs, processor_params):
    return obs * processor_params


def _build(actor):
    nets = make_ppo_networks(
        OBS,
        ACT,
        _scale_preprocess,
        actor=actor,
        actor_kwargs=SMALL[actor],
        critic_hidden_sizes=(16, 16),
        init_log_std=-0.5,
    )
    policy = nets.policy_network.init(jax.random.PRNGKey(0))
    value = nets.value_network.init(jax.random.PRNGKey(1))
    return nets, policy, value


@pytest.fixture(scope="module", params=["popsan", "mlp"])
def built(request):
    return (request.param, *_build(request.param))


def test_policy_output_mode_and_scale(built):
    name, nets, policy, value = built
    obs = jax.random.normal(jax.random.PRNGKey(2), (5, OBS))
    logits = nets.policy_network.apply(2.0, policy, obs)
    assert logits.shape == (5, 2 * ACT)
    actor_mean = make_actor(name, SMALL[name], ACT).apply(actor_variables(policy), obs * 2.0)
    dist = nets.parametric_action_distribution
    np.testing.assert_allclose(dist.mode(logits), actor_mean, atol=1e-6)  # no second tanh
    np.testing.assert_allclose(logits[:, ACT:], -0.5)
    np.testing.assert_allclose(dist.create_dist(logits).scale, np.exp(-0.5), rtol=1e-6)
    assert dist.param_size == 2 * ACT
    np.testing.assert_allclose(policy["params"]["log_std"], -0.5)
    # Leading dims (PPO's [unroll, batch]) are kept.
    assert nets.policy_network.apply(1.0, policy, obs.reshape(5, 1, OBS)).shape == (5, 1, 2 * ACT)
    assert nets.value_network.apply(1.0, value, obs.reshape(5, 1, OBS)).shape == (5, 1)


def test_inference_fn_deterministic_and_stochastic(built):
    name, nets, policy, _ = built
    obs = jax.random.normal(jax.random.PRNGKey(3), (4, OBS))
    make_policy = ppo_networks.make_inference_fn(nets)
    mean = make_actor(name, SMALL[name], ACT).apply(actor_variables(policy), obs)
    action, _ = make_policy((1.0, policy), deterministic=True)(obs, jax.random.PRNGKey(0))
    np.testing.assert_allclose(action, mean, atol=1e-6)
    action, extras = make_policy((1.0, policy))(obs, jax.random.PRNGKey(5))
    sigma = np.exp(-0.5)
    z = (np.asarray(action) - np.asarray(mean)) / sigma
    expected = np.sum(-0.5 * z**2 - np.log(sigma) - 0.5 * np.log(2 * np.pi), axis=-1)
    np.testing.assert_allclose(extras["log_prob"], expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(extras["raw_action"], action)


def test_compute_ppo_loss_gives_finite_nonzero_grads(built):
    name, nets, policy, value = built
    batch, unroll = 4, 3
    keys = jax.random.split(jax.random.PRNGKey(7), 4)
    obs = jax.random.normal(keys[0], (batch, unroll, OBS))
    raw = jax.random.normal(keys[1], (batch, unroll, ACT)) * 0.5
    data = types.Transition(
        observation=obs,
        action=raw,
        reward=jax.random.normal(keys[2], (batch, unroll)),
        discount=jnp.ones((batch, unroll)),
        next_observation=jax.random.normal(keys[3], (batch, unroll, OBS)),
        extras={
            "state_extras": {"truncation": jnp.zeros((batch, unroll))},
            "policy_extras": {
                "raw_action": raw,
                "log_prob": jnp.full((batch, unroll), -3.0),
                "distribution_params": jnp.zeros((batch, unroll, 2 * ACT)),
            },
        },
    )
    params = losses.PPONetworkParams(policy=policy, value=value)

    def loss_fn(p):
        return losses.compute_ppo_loss(p, 1.0, data, jax.random.PRNGKey(0), nets)

    (loss, metrics), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(params)
    assert np.isfinite(float(loss))
    np.testing.assert_allclose(metrics["policy_dist_mean_std"], np.exp(-0.5), rtol=1e-6)
    for part in (grads.policy, grads.value):
        for path, g in jax.tree_util.tree_leaves_with_path(part):
            assert bool(jnp.all(jnp.isfinite(g))), path
    assert float(jnp.abs(grads.policy["params"]["log_std"]).sum()) > 0
    actor_grads = jax.tree.leaves(grads.policy["params"]["actor"])
    assert all(float(jnp.abs(g).sum()) > 0 for g in actor_grads)


def test_unknown_actor_and_bad_kwargs():
    with pytest.raises(ConfigError, match="popsan, mlp"):
        make_ppo_networks(OBS, ACT, actor="lstm")
    with pytest.raises(ConfigError, match="popsan"):
        make_actor("popsan", {"hidden": 3}, ACT)


def test_json_style_list_kwargs_are_accepted():
    actor = make_actor("popsan", {"hidden_sizes": [8, 4], "mean_range": [-2.0, 2.0]}, ACT)
    assert actor.hidden_sizes == (8, 4) and actor.mean_range == (-2.0, 2.0)
    params = actor.init(jax.random.PRNGKey(0), jnp.zeros((1, OBS)))
    np.testing.assert_allclose(params["params"]["encoder"]["mean"][0, [0, -1]], [-2.0, 2.0])
    assert params["params"]["hidden_1"]["kernel"].shape == (8, 4)


def test_mlp_output_layer_starts_scaled():
    # output_init_scale multiplies the output kernel's LeCun-normal draw (std 1/sqrt(fan_in));
    # the hidden layers and the zero bias are untouched, so with the same key the kernel is
    # exactly that multiple of the default one. The default recipe's MLP (recipes.ACTOR_RECIPES)
    # starts 100x smaller: its action means start near 0 for every observation.
    obs = jax.random.normal(jax.random.PRNGKey(1), (64, OBS))
    base = MLPActor(ACT, hidden_sizes=(256,)).init(jax.random.PRNGKey(0), obs)["params"]
    small = MLPActor(ACT, hidden_sizes=(256,), output_init_scale=0.01)
    params = small.init(jax.random.PRNGKey(0), obs)["params"]
    np.testing.assert_array_equal(params["hidden_0"]["kernel"], base["hidden_0"]["kernel"])
    kernel = np.asarray(params["output"]["kernel"])
    np.testing.assert_allclose(kernel, 0.01 * np.asarray(base["output"]["kernel"]), rtol=1e-5)
    assert abs(np.std(base["output"]["kernel"]) * 16.0 - 1.0) < 0.1  # 1/sqrt(256)
    assert not np.any(params["output"]["bias"])
    default = make_actor("mlp", {**MLP_DEFAULTS, **ACTOR_RECIPES["mlp"]}, ACT)
    means = default.apply(default.init(jax.random.PRNGKey(0), obs), obs)
    assert float(jnp.abs(means).max()) < 0.05


def test_modules_directly():
    obs = jnp.ones((2, OBS))
    actor = MLPActor(ACT, hidden_sizes=(8,))
    mean = actor.apply(actor.init(jax.random.PRNGKey(0), obs), obs * 50.0)
    assert mean.shape == (2, ACT) and bool(jnp.all(jnp.abs(mean) <= 1.0))
    critic = Critic(hidden_sizes=(8, 8))
    assert critic.apply(critic.init(jax.random.PRNGKey(0), obs), obs).shape == (2,)
