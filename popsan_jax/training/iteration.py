"""The jitted pieces of one PPO training iteration, built from Brax's own parts.

See :mod:`popsan_jax.training.loop` for why we drive Brax's pieces with our own loop. Shapes:
``E`` envs on this device, ``U`` unrolls per iteration, ``L`` unroll length, ``S = U * E``
sequences, ``M`` minibatches.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax
from brax.training import acting, gradients
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.config import RunConfig
from popsan_jax.training import loss

AXIS = "devices"


@flax.struct.dataclass
class TrainingState:
    """Everything a resumed run needs besides the rng key (kept by the host loop).

    ``env_steps`` is an int32 scalar: 2**31 steps is far beyond any planned run.
    """

    params: ppo_losses.PPONetworkParams
    opt_state: Any
    normalizer_params: running_statistics.RunningStatisticsState
    env_steps: jax.Array


def init_training_state(
    config: RunConfig,
    networks: ppo_networks.PPONetworks,
    optimizer: optax.GradientTransformation,
    observation_size: int,
    key: jax.Array,
) -> TrainingState:
    key_policy, key_value = jax.random.split(key)
    params = ppo_losses.PPONetworkParams(
        policy=networks.policy_network.init(key_policy),
        value=networks.value_network.init(key_value),
    )
    normalizer = running_statistics.init_state(jnp.zeros((observation_size,), jnp.float32))
    return TrainingState(
        params=params,
        opt_state=optimizer.init(params),
        normalizer_params=normalizer,
        env_steps=jnp.zeros((), jnp.int32),
    )


def all_finite(tree: Any) -> jax.Array:
    leaves = [
        jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree) if jnp.issubdtype(x, jnp.inexact)
    ]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


def refresh_reset_states(env: Any, env_state: Any, key: jax.Array) -> Any:
    """Redraw the states that Brax's ``AutoResetWrapper`` restarts finished episodes from.

    That wrapper restores ``info["first_pipeline_state"]``/``info["first_obs"]``, drawn once at
    the first reset, so without this every episode of an env slot would start from the same
    cube / target position and the policy would see only ``num_envs`` distinct tasks. One
    batched reset per iteration (not per step) keeps it cheap.

    Args:
      env: the training-wrapped env (vmapped, auto-reset).
      env_state: its batched state, ``E`` envs on this device.
      key: rng for the new start states.
    """
    fresh = env.reset(jax.random.split(key, env_state.obs.shape[0]))
    info = {
        **env_state.info,
        "first_pipeline_state": fresh.pipeline_state,
        "first_obs": fresh.obs,
    }
    return env_state.replace(info=info)


# WRAPPED_SCAN_BODY: on XLA:CPU a ``lax.scan`` whose body steps Brax's training-wrapped env
# compiles several times slower, with several times the host memory, at any batch size or scan
# length, unless the body is itself ``jax.jit``-ed (as Brax's ``acting.generate_unroll`` does)
# and closes over no traced value: the policy's parameters and anything else traced ride in
# the carry. Hence the explicit ``params`` of the policies below (docs/design.md, "A jitted
# scan body"; benchmarks/scan_body_compile.py measures both forms).
ParamPolicy = Callable[[Any, jax.Array, jax.Array], tuple[jax.Array, Any]]


def param_policy(make_policy: Callable[[Any], Callable[..., Any]]) -> ParamPolicy:
    """``policy(params, obs, key)`` from Brax's ``make_policy(params)(obs, key)``, for the
    scans below that take their parameters explicitly (WRAPPED_SCAN_BODY)."""
    return lambda params, obs, key: make_policy(params)(obs, key)


def stagger_episodes(
    env: Any,
    env_state: Any,
    policy: ParamPolicy,
    params: Any,
    key: jax.Array,
    episode_length: int,
) -> Any:
    """Step env ``e`` of a freshly reset batch ``n_e`` times (``n_e`` uniform in [0, L)), no SGD.

    A fresh reset starts all ``E`` envs at step 0 of their episodes, so each of the next ``L /
    unroll_length`` iterations would learn from a single phase of the episode (all reaching,
    then all grasping, ...). A policy far into training may not survive that (docs/design.md,
    "Staggering on resume"). Costs ``(L - 1) * E`` uncounted env steps of ``policy``
    (stochastic).

    Args:
      env: the training-wrapped (vmapped, auto-reset) env.
      env_state: its batched state, ``E`` envs on this device, all at episode step 0.
      policy: ``policy(params, obs [E, O], key) -> (action [E, A], extras)``.
      params: the policy's parameters (a pytree; see WRAPPED_SCAN_BODY).
      key: rng for the step counts and the actions.
      episode_length: ``L``, control steps per episode.
    """
    key_counts, key_steps = jax.random.split(key)
    counts = jax.random.randint(key_counts, (env_state.obs.shape[0],), 0, episode_length)

    @jax.jit  # see WRAPPED_SCAN_BODY
    def body(carry, t):
        state, k, params, counts = carry
        k, k_act = jax.random.split(k)
        stepped = env.step(state, policy(params, state.obs, k_act)[0])
        keep = t < counts  # [E]: env e takes steps 0 .. n_e - 1 and then stands still

        def pick(new: jax.Array, old: jax.Array) -> jax.Array:
            return jnp.where(keep.reshape(keep.shape + (1,) * (new.ndim - 1)), new, old)

        return (jax.tree.map(pick, stepped, state), k, params, counts), None

    carry = (env_state, key_steps, params, counts)
    (env_state, *_), _ = jax.lax.scan(body, carry, jnp.arange(episode_length - 1))
    return env_state


def prime_normalizer(
    env: Any,
    env_state: Any,
    policy: ParamPolicy,
    params: Any,
    normalizer_params: running_statistics.RunningStatisticsState,
    key: jax.Array,
    num_steps: int,
    axis_name: str | None = AXIS,
) -> tuple[running_statistics.RunningStatisticsState, Any]:
    """Seed the observation normaliser with ``num_steps`` steps of ``policy``, no SGD.

    A fresh normaliser is the identity (mean 0, std 1), so the first unroll's behaviour policy
    acts on raw observations while its update sees normalised ones: the two policies differ,
    and for the MLP the first update's KL is 4-8 instead of PopSAN's 0.04 (docs/design.md,
    "Priming the normaliser"). Stepping the untrained policy for an episode first and adding
    what it saw makes the behaviour policy of iteration 1 act on normalised observations.
    Costs ``num_steps * E`` uncounted env steps.

    Args:
      env: the training-wrapped (vmapped, auto-reset) env.
      env_state: its batched state, ``E`` envs on this device.
      policy: ``policy(params, obs [E, O], key) -> (action [E, A], extras)``, the untrained
        one.
      params: its parameters (a pytree; see WRAPPED_SCAN_BODY).
      normalizer_params: the fresh normaliser state.
      key: rng for the actions.
      num_steps: control steps to take (a whole number of episodes brings every env back to
        the start of one).
      axis_name: pmap axis to pool the statistics over (None: this device alone).

    Returns:
      ``(normalizer_params, env_state)``, the statistics of all ``num_steps * E`` observations
      ``[num_steps, E, O]`` added.
    """

    @jax.jit  # see WRAPPED_SCAN_BODY
    def body(carry, _):
        state, k, params = carry
        k, k_act = jax.random.split(k)
        return (env.step(state, policy(params, state.obs, k_act)[0]), k, params), state.obs

    (env_state, *_), obs = jax.lax.scan(body, (env_state, key, params), None, length=num_steps)
    normalizer_params = running_statistics.update(normalizer_params, obs, pmap_axis_name=axis_name)
    return normalizer_params, env_state


Guard = tuple[jax.Array, tuple[Any, Any]]  # (stopped, good (params, opt_state))


def kl_guard(
    kl: jax.Array, max_kl: float, guard: Guard, before: tuple[Any, Any], stepped: tuple[Any, Any]
) -> tuple[tuple[Any, Any], Guard]:
    """One minibatch of the KL guard (``config.max_kl``).

    A warm start's first updates, driven by a critic fitted to another reward, can move the
    policy by a KL of 1 or more in one iteration and undo it (docs/design.md, "Guards at the
    stage change"). The guard keeps an iteration's SGD within ``max_kl`` of the policy that
    collected its data, as far as the minibatches measure it.

    Args:
      kl: scalar, the minibatch's mean KL from the behaviour policy to ``before``'s policy
        (Brax's ``kl_mean``, measured before the step).
      max_kl: the bound.
      guard: ``(stopped, good)``: whether this iteration's SGD has stopped, and the last
        ``(params, opt_state)`` measured within ``max_kl`` (the iteration's start at first).
      before: ``(params, opt_state)`` before this minibatch's step; ``stepped``: after it.

    Returns:
      ``((params, opt_state), guard)``: while every KL so far is ``<= max_kl`` the step is
      kept and ``before`` becomes ``good``; at the first that is not (NaN included) the state
      goes back to ``good`` and stays there for the rest of the iteration.
    """
    stopped, good = guard
    fine = jnp.logical_and(jnp.logical_not(stopped), kl <= max_kl)

    def pick(if_fine: Any, otherwise: Any) -> Any:
        return jax.tree.map(lambda a, b: jnp.where(fine, a, b), if_fine, otherwise)

    return pick(stepped, good), (jnp.logical_not(fine), pick(before, good))


def make_iteration_fn(
    config: RunConfig,
    env: Any,
    networks: ppo_networks.PPONetworks,
    optimizer: optax.GradientTransformation,
    diagnostics_fn: Callable[[TrainingState, jax.Array], dict[str, jax.Array]],
    axis_name: str | None = AXIS,
) -> Callable[[TrainingState, Any, jax.Array], tuple[TrainingState, Any, dict[str, jax.Array]]]:
    """One full iteration (unroll, normaliser update, epochs of minibatch SGD) for one device.

    The loss is :func:`popsan_jax.training.loss.make_loss_fn`'s: Brax's PPO loss, plus the SOP
    penalty when ``config.sop_cost > 0``.

    ``env`` is the training-wrapped (vmapped, auto-reset) env; ``diagnostics_fn(state, obs [B,
    O]) -> metrics`` adds entropy / firing rates. Under pmap, gradients and normaliser statistics
    are averaged over ``axis_name``. Returns per-iteration mean metrics plus ``kl_max`` (the
    largest minibatch KL), ``finite`` (1.0 when loss and parameters are all finite) and, with
    ``config.max_kl`` (:func:`kl_guard`), ``kl_stopped`` (1.0 when the guard stopped its SGD).
    """
    make_policy = ppo_networks.make_inference_fn(networks)
    loss_fn = loss.make_loss_fn(config, networks, env.action_size)
    update = gradients.gradient_update_fn(loss_fn, optimizer, axis_name, has_aux=True)
    minibatches = config.num_minibatches

    def minibatch_step(carry, data, normalizer_params):
        opt_state, params, key, guard = carry
        key, key_loss = jax.random.split(key)
        (_, metrics), new_params, new_opt_state = update(
            params, normalizer_params, data, key_loss, optimizer_state=opt_state
        )
        if guard is not None:  # config.max_kl > 0
            kl = metrics["kl_mean"]
            if axis_name is not None:  # every device takes the same decision
                kl = jax.lax.pmean(kl, axis_name)
            (new_params, new_opt_state), guard = kl_guard(
                kl, config.max_kl, guard, (params, opt_state), (new_params, new_opt_state)
            )
        return (new_opt_state, new_params, key, guard), metrics

    def epoch(carry, _, data, normalizer_params):
        opt_state, params, key, guard = carry
        key, key_perm, key_grad = jax.random.split(key, 3)

        def shuffle(x: jax.Array) -> jax.Array:
            x = jax.random.permutation(key_perm, x)
            return jnp.reshape(x, (minibatches, -1) + x.shape[1:])

        (opt_state, params, _, guard), metrics = jax.lax.scan(
            functools.partial(minibatch_step, normalizer_params=normalizer_params),
            (opt_state, params, key_grad, guard),
            jax.tree.map(shuffle, data),
        )
        return (opt_state, params, key, guard), metrics

    def iteration(state: TrainingState, env_state: Any, key: jax.Array):
        key_sgd, key_unroll, key_reset = jax.random.split(key, 3)
        policy = make_policy((state.normalizer_params, state.params.policy))
        env_state = refresh_reset_states(env, env_state, key_reset)

        def unroll(carry, _):
            env_state, k = carry
            k, k_next = jax.random.split(k)
            env_state, data = acting.generate_unroll(
                env, env_state, policy, k, config.unroll_length, extra_fields=("truncation",)
            )
            return (env_state, k_next), data

        (env_state, _), data = jax.lax.scan(
            unroll, (env_state, key_unroll), (), length=config.unrolls_per_iteration
        )
        # [U, L, E, ...] -> [U * E, L, ...]: one sequence per row, as compute_ppo_loss expects.
        data = jax.tree.map(lambda x: jnp.swapaxes(x, 1, 2), data)
        data = jax.tree.map(lambda x: jnp.reshape(x, (-1,) + x.shape[2:]), data)
        normalizer = state.normalizer_params
        if not config.freeze_normalizer:
            normalizer = running_statistics.update(
                normalizer, data.observation, pmap_axis_name=axis_name
            )
        guard = None
        if config.max_kl:
            guard = (jnp.array(False), (state.params, state.opt_state))
        (opt_state, params, _, guard), metrics = jax.lax.scan(
            functools.partial(epoch, data=data, normalizer_params=normalizer),
            (state.opt_state, state.params, key_sgd, guard),
            (),
            length=config.num_updates_per_batch,
        )
        steps = config.env_steps_per_iteration
        new_state = TrainingState(
            params=params,
            opt_state=opt_state,
            normalizer_params=normalizer,
            env_steps=state.env_steps + jnp.int32(steps),
        )
        out = {
            "loss/total": metrics["total_loss"],
            "loss/policy": metrics["policy_loss"],
            "loss/value": metrics["v_loss"],
            "loss/entropy": metrics["entropy_loss"],
            "kl": metrics["kl_mean"],
        }
        if config.sop_cost:  # the penalised SOPs of the minibatches, before each update
            out["loss/sop_penalty"] = metrics["sop_penalty"]
        out = {k: jnp.mean(v) for k, v in out.items()}
        out["kl_max"] = jnp.max(metrics["kl_mean"])  # the largest minibatch's, before its step
        if guard is not None:  # 1.0 when the KL guard stopped this iteration's SGD
            out["kl_stopped"] = guard[0].astype(jnp.float32)
        out["train/reward_per_step"] = jnp.mean(data.reward)
        obs_sample = data.observation[: min(256, data.observation.shape[0]), 0]
        out.update(diagnostics_fn(new_state, obs_sample))
        finite = all_finite((out["loss/total"], params, normalizer.mean, normalizer.std))
        out["finite"] = finite.astype(jnp.float32)
        if axis_name is not None:
            out = jax.lax.pmean(out, axis_name)
        return new_state, env_state, out

    return iteration
