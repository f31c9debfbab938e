"""One jitted PPO iteration on the toy env, against what its sizes say it must do: env steps
counted, every collected observation in the normaliser, one Adam step per minibatch per epoch,
the metrics it logs, and the non-finite check."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _toy_env import PointPick, tiny_config
from brax.envs.wrappers import training as brax_training
from brax.training.acme import running_statistics

from popsan_jax.training import iteration
from popsan_jax.training.diagnostics import make_diagnostics_fn
from popsan_jax.training.setup import build_networks, make_optimizer


def _start(config):
    """The toy env's jitted iteration for ``config``, its initial training state and envs."""
    env = PointPick()
    wrapped = brax_training.wrap(env, episode_length=env.config.episode_length)
    nets = build_networks(config, env.observation_size, env.action_size)
    optimizer = make_optimizer(config)
    state = iteration.init_training_state(
        config, nets, optimizer, env.observation_size, jax.random.PRNGKey(0)
    )
    diagnostics = make_diagnostics_fn(config, nets, env.action_size)
    step = jax.jit(
        iteration.make_iteration_fn(config, wrapped, nets, optimizer, diagnostics, axis_name=None)
    )
    env_state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(1), config.num_envs))
    return step, state, env_state


def moved(a, b) -> list[bool]:
    """Per leaf of two pytrees of the same structure: whether it changed."""
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return [not np.array_equal(x, y) for x, y in pairs]


@pytest.fixture(scope="module")
def one_iteration():
    config = tiny_config(sop_cost=0.5)  # 16 envs, 4 minibatches of 16 x 10 steps, 2 epochs
    step, state, env_state = _start(config)
    new_state, new_env_state, metrics = step(state, env_state, jax.random.PRNGKey(2))
    return config, state, new_state, new_env_state, jax.device_get(metrics)


def test_counts_steps_observations_and_updates(one_iteration):
    config, state, new, env_state, _ = one_iteration
    # 4 minibatches x 16 sequences x 10 steps = 640 env steps, all of them new observations.
    assert config.env_steps_per_iteration == 640
    assert int(new.env_steps) == int(state.env_steps) + 640
    assert int(new.normalizer_params.count) == 640  # Brax's UInt64 (hi, lo) converts itself
    # Adam stepped once per minibatch per epoch: 4 x 2.
    counts = {int(x) for x in jax.tree.leaves(new.opt_state) if jnp.issubdtype(x, jnp.integer)}
    assert counts == {8}

    assert all(moved(state.params.value, new.params.value))  # a dense critic: every leaf
    old_policy, new_policy = state.params.policy["params"], new.params.policy["params"]
    assert all(moved(old_policy["log_std"], new_policy["log_std"]))
    assert any(moved(old_policy["actor"], new_policy["actor"]))
    # 4 unrolls of 10 steps in episodes of 12: every env slot has been auto-reset.
    assert env_state.obs.shape == (16, PointPick().observation_size)
    assert int(np.max(np.asarray(env_state.info["steps"]))) < 12


def test_logs_losses_diagnostics_and_finite(one_iteration):
    *_, metrics = one_iteration
    keys = {"loss/total", "loss/policy", "loss/value", "loss/entropy", "kl", "kl_max", "entropy"}
    keys |= {"train/reward_per_step", "loss/sop_penalty", "sops", "finite"}
    keys |= {f"firing_rate/{n}" for n in ("encoder", "hidden_0", "output")}
    assert keys <= set(metrics), sorted(metrics)
    assert metrics["finite"] == 1.0
    assert all(np.isfinite(float(v)) for v in metrics.values())
    assert metrics["loss/sop_penalty"] > 0 and metrics["sops"] > 0
    assert metrics["kl_max"] > metrics["kl"] > 0  # the largest minibatch's KL, and their mean
    assert "kl_stopped" not in metrics  # no KL guard (max_kl 0)
    for name in ("encoder", "hidden_0", "output"):
        assert 0.0 <= metrics[f"firing_rate/{name}"] <= 1.0
    # The toy reward is minus the hand-object distance (and an action cost): negative.
    assert metrics["train/reward_per_step"] < 0


def test_all_finite():
    assert bool(iteration.all_finite({"a": jnp.ones(3), "n": jnp.int32(7)}))
    assert not bool(iteration.all_finite({"a": jnp.array([1.0, jnp.nan])}))
    assert not bool(iteration.all_finite((jnp.ones(2), jnp.array(jnp.inf))))
    assert bool(iteration.all_finite({"only_ints": jnp.arange(3)}))


def test_prime_normalizer_holds_the_statistics_of_a_plain_rollout():
    """One episode of a fixed policy seeds the normaliser with exactly the mean and std of the
    observations a plain Python loop over the same env sees (before each of its L steps), and
    adds nothing else; the envs end the episode where the loop does."""
    length, n = 12, 8
    env = PointPick(episode_length=length)
    wrapped = brax_training.wrap(env, episode_length=length)
    start = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(3), n))

    def policy(gain, obs, key):  # deterministic: half way towards the object, clipped
        return jnp.clip(gain * obs[:, 3:6], -1.0, 1.0), {}

    fresh = running_statistics.init_state(jnp.zeros((env.observation_size,), jnp.float32))
    primed, end = jax.jit(
        lambda s, k, g: iteration.prime_normalizer(wrapped, s, policy, g, fresh, k, length, None)
    )(start, jax.random.PRNGKey(4), jnp.float32(5.0))

    step = jax.jit(wrapped.step)
    state, seen = start, []
    for _ in range(length):
        seen.append(np.asarray(state.obs, np.float64))
        state = step(state, policy(5.0, state.obs, None)[0])
    seen = np.stack(seen)  # [L, E, O]
    assert seen[1:].std() > 0  # the hands moved: the statistics are not those of one frame
    assert int(primed.count) == length * n
    np.testing.assert_allclose(primed.mean, seen.mean(axis=(0, 1)), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(primed.std, seen.std(axis=(0, 1)), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(end.obs, state.obs, rtol=1e-6, atol=1e-7)


def test_env_scans_have_jitted_bodies_that_close_over_nothing_traced():
    """The stagger's and the priming's scans over the wrapped env step: each body one jitted
    call with no closed-over values (no scan consts), the policy's parameters in the carry.
    The plain form compiles several times slower with several times the memory on
    franka_pick (iteration.py, WRAPPED_SCAN_BODY); the closure form is checked to differ."""
    length, n = 12, 8
    env = PointPick(episode_length=length)
    wrapped = brax_training.wrap(env, episode_length=length)
    start = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(3), n))
    fresh = running_statistics.init_state(jnp.zeros((env.observation_size,), jnp.float32))

    def policy(gain, obs, key):
        return jnp.clip(gain * obs[:, 3:6], -1.0, 1.0), {}

    def scan_bodies(fn):
        jaxpr = jax.make_jaxpr(fn)(start, jax.random.PRNGKey(0), jnp.float32(5.0)).jaxpr
        scans = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
        return [(e.params["num_consts"], [q.primitive.name for q in e.params["jaxpr"].eqns])
                for e in scans]  # fmt: skip

    one_jitted_call = [(0, ["jit"])]  # one scan; no consts; its body a single jit call
    stagger = iteration.stagger_episodes
    assert scan_bodies(lambda s, k, g: stagger(wrapped, s, policy, g, k, length)) == one_jitted_call
    prime = iteration.prime_normalizer
    primed = scan_bodies(lambda s, k, g: prime(wrapped, s, policy, g, fresh, k, length, None)[1])
    assert primed == one_jitted_call

    def closure_form(s, k, g):  # what the check is there to refuse
        body = jax.jit(lambda c, _: (wrapped.step(c, policy(g, c.obs, k)[0]), None))
        return jax.lax.scan(body, s, None, length=length)[0]

    ((consts, _),) = scan_bodies(closure_form)
    assert consts > 0


def test_critic_warmup_holds_the_actor_for_whole_iterations():
    """With a critic warm-up of one iteration, the first iteration moves the critic and not
    the actor (not even its log-std); the second moves both."""
    step, state, env_state = _start(tiny_config(critic_warmup_env_steps=640))
    first, env_state, _ = step(state, env_state, jax.random.PRNGKey(2))
    second, _, _ = step(first, env_state, jax.random.PRNGKey(3))

    assert not any(moved(state.params.policy, first.params.policy))
    assert any(moved(state.params.value, first.params.value))
    assert any(moved(first.params.policy, second.params.policy))


def test_frozen_normalizer_keeps_the_started_statistics_and_the_actor_learns():
    """--freeze-normalizer: the started statistics (here from 64 random observations) are what
    the next state carries, bit for bit, while the actor and critic still move (unfrozen, an
    iteration adds its observations: test_counts_steps_observations_and_updates)."""
    config = tiny_config(freeze_normalizer=True, init_from="a-run")  # init_from: validation only
    config.validate(1)
    step, state, env_state = _start(config)
    seen = jax.random.normal(jax.random.PRNGKey(7), (64, PointPick().observation_size)) * 3 + 1
    started = running_statistics.update(state.normalizer_params, seen)
    state = state.replace(normalizer_params=started)
    new, _, _ = step(state, env_state, jax.random.PRNGKey(2))

    assert not any(moved(started, new.normalizer_params))
    assert any(moved(state.params.policy, new.params.policy))
    assert any(moved(state.params.value, new.params.value))
    # the 64 it started with, none of the 640 collected
    assert int(new.normalizer_params.count) == 64


def test_kl_guard_keeps_steps_until_the_first_kl_over_the_bound_then_the_last_good_state():
    """Hand-traced: states are numbers, a step adds 1. KLs 0.1, 0.2 pass (steps kept: 0 -> 1
    -> 2); 0.6 > 0.5 is measured on state 2, so the state goes back to 1, the last measured
    within the bound, and stays there although the next KL, 0.1, passes."""
    guard = (jnp.array(False), (jnp.float32(0), jnp.float32(0)))
    state, trace = (jnp.float32(0), jnp.float32(0)), []
    for kl in (0.1, 0.2, 0.6, 0.1):
        stepped = (state[0] + 1, state[1] + 1)
        state, guard = iteration.kl_guard(jnp.float32(kl), 0.5, guard, state, stepped)
        trace.append((float(state[0]), bool(guard[0])))
    assert trace == [(1.0, False), (2.0, False), (1.0, True), (1.0, True)]
    # A NaN KL counts as over the bound; at the first minibatch that is the iteration's start.
    start = (jnp.float32(3), jnp.float32(3))
    fresh = (jnp.array(False), start)
    state, guard = iteration.kl_guard(jnp.float32(jnp.nan), 0.5, fresh, start, (4.0, 4.0))
    assert float(state[0]) == 3.0 and bool(guard[0])


@pytest.fixture(scope="module")
def guarded_iterations():
    """One iteration (the one_iteration fixture's config and key) with the KL guard at a bound
    no minibatch reaches, and one at a bound every step exceeds."""
    out = {}
    for name, bound in (("loose", 1e9), ("tight", 1e-30)):
        step, state, env_state = _start(tiny_config(sop_cost=0.5, max_kl=bound))
        new, _, metrics = step(state, env_state, jax.random.PRNGKey(2))
        out[name] = (state, new, jax.device_get(metrics))
    return out


def test_kl_guard_never_reached_changes_nothing(one_iteration, guarded_iterations):
    """A bound no minibatch reaches gives the unguarded iteration's state, to float rounding:
    XLA fuses the guarded program differently, which moves a few values by an ulp or so
    (not bit for bit), while one step more or less would move them by about the lr, 3e-4."""
    _, _, unguarded, _, plain_metrics = one_iteration
    _, new, metrics = guarded_iterations["loose"]
    for a, b in ((unguarded.params, new.params), (unguarded.opt_state, new.opt_state)):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-8)
    assert metrics["kl_stopped"] == 0.0
    np.testing.assert_allclose(metrics["kl_max"], plain_metrics["kl_max"], rtol=1e-5)


def test_kl_guard_at_a_bound_every_step_exceeds_keeps_the_iteration_start(guarded_iterations):
    """At a bound the first stepped policy already exceeds, the iteration ends with the
    networks and the optimiser it started with (the normaliser still takes the new data)."""
    state, new, metrics = guarded_iterations["tight"]
    assert not any(moved(state.params, new.params))
    assert not any(moved(state.opt_state, new.opt_state))
    assert int(new.normalizer_params.count) == 640
    assert metrics["kl_stopped"] == 1.0 and metrics["kl_max"] > 0
