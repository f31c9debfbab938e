"""Evaluation of a saved run: rollouts -> report with a 95 % Wilson CI, energy sweep over T.

Everything starts from :class:`popsan_jax.training.checkpoint.LoadedRun`, i.e. from the run
directory alone. The PopSAN's parameters do not depend on T, so the energy sweep rebuilds the
networks from the saved config with another ``timesteps`` and reuses the same parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.training.agents.ppo import networks as ppo_networks

from popsan_jax.analysis import energy
from popsan_jax.config import POPSAN_DEFAULTS
from popsan_jax.networks import actor_variables, make_actor
from popsan_jax.rollout import EpisodeBatch, run_episodes
from popsan_jax.snn.ops import spike_totals, spiking_layer_names
from popsan_jax.training.setup import (
    at_timesteps,
    build_networks,
    make_spikes_fn,
    trained_timesteps,
)

Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def wilson_interval(successes: float, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion ``successes / n``."""
    if n <= 0:
        raise ValueError("need at least one trial")
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def summarize(batch: EpisodeBatch) -> dict[str, Any]:
    """Success rate (the env's ``success`` at the episode's end: pick-and-hold) and the
    ``reached`` rate (PixMC's latch), each with its 95 % Wilson CI; mean hold time, length and
    return; per-term means."""
    success = np.asarray(batch.success, dtype=np.float64)
    reached = np.asarray(batch.reached, dtype=np.float64)
    n = int(success.shape[0])
    out: dict[str, Any] = dict(
        episodes=n,
        success_rate=float(success.mean()),
        success_ci95=list(wilson_interval(float(success.sum()), n)),
        reached_rate=float(reached.mean()),
        reached_ci95=list(wilson_interval(float(reached.sum()), n)),
        hold_time=float(np.mean(batch.hold_time)),
        episode_length=float(np.mean(batch.length)),
        episode_return=float(np.mean(batch.ret)),
    )
    out.update({f"reward/{k}": float(np.mean(v)) for k, v in sorted(batch.terms.items())})
    return out


def networks_at_timesteps(loaded: Any, timesteps: int | None) -> ppo_networks.PPONetworks:
    """The run's networks, with the PopSAN rebuilt at ``timesteps`` (None = as trained)."""
    config = at_timesteps(loaded.config, timesteps)
    if config is loaded.config:
        return loaded.networks
    return build_networks(config, loaded.env.observation_size, loaded.env.action_size)


def episode_keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """``(key, episodes_key)`` of an evaluation with ``seed``: the second draws the episodes
    (initial states, and actions when stochastic), the first is left for the energy sweep.
    Every evaluation of a seed draws the same episodes, so runs and checkpoints compare."""
    return tuple(jax.random.split(jax.random.PRNGKey(seed)))


def rollouts(
    loaded: Any,
    episodes: int,
    key: jax.Array,
    deterministic: bool = True,
    timesteps: int | None = None,
    record: bool = False,
) -> EpisodeBatch:
    """Run ``episodes`` evaluation episodes of the loaded policy (PopSAN at ``timesteps``)."""
    networks = networks_at_timesteps(loaded, timesteps)
    inference = ppo_networks.make_inference_fn(networks)(
        (loaded.normalizer_params, loaded.policy_params), deterministic=deterministic
    )
    return run_episodes(
        loaded.env,
        lambda obs, k: inference(obs, k)[0],
        key,
        episodes,
        episode_length=loaded.config.episode_length,
        record=record,
    )


def alive_observations(batch: EpisodeBatch) -> np.ndarray:
    """``[M, O]`` raw observations of every alive step of a recorded batch."""
    if batch.obs is None or batch.alive is None:
        raise ValueError("the batch was not recorded (run with record=True)")
    obs, alive = np.asarray(batch.obs), np.asarray(batch.alive) > 0
    return obs[alive]


def measure_snn_ops(
    loaded: Any, observations: np.ndarray, timesteps: int, chunk: int = 2048
) -> tuple[energy.SNNOps, tuple[int, ...]]:
    """Run the PopSAN at ``timesteps`` on raw ``observations [M, O]`` (preprocessed as the
    policy's input); count operations.

    Returns the ops per inference and the spiking layer sizes.
    """
    config = at_timesteps(loaded.config, timesteps)
    kwargs = config.actor_kwargs
    spikes_fn = make_spikes_fn(config, loaded.env.action_size)
    sizes = energy.popsan_layer_sizes(
        loaded.env.observation_size,
        loaded.env.action_size,
        kwargs["hidden_sizes"],
        kwargs["encoder_pop_dim"],
        kwargs["decoder_pop_dim"],
    )

    @jax.jit
    def totals(obs: jax.Array, weight: jax.Array) -> jax.Array:
        spikes = spikes_fn(loaded.policy_params, loaded.normalizer_params, obs)
        return spike_totals(spikes, weight)

    m = observations.shape[0]
    if m == 0:
        raise ValueError("no alive observations to measure spikes on")
    chunk = min(chunk, m)
    acc = np.zeros(len(sizes))
    for start in range(0, m, chunk):
        part = observations[start : start + chunk]
        weight = np.zeros(chunk, np.float32)
        weight[: part.shape[0]] = 1.0
        padded = np.zeros((chunk, observations.shape[1]), np.float32)
        padded[: part.shape[0]] = part
        acc += np.asarray(totals(jnp.asarray(padded), jnp.asarray(weight)), dtype=np.float64)
    ops = energy.snn_ops_from_totals(acc, m, sizes, timesteps, loaded.env.action_size)
    return ops, sizes


def energy_sweep(
    loaded: Any,
    timesteps_list: Sequence[int],
    episodes: int,
    key: jax.Array,
    ann_hidden_sizes: Sequence[int] | None = None,
    deterministic: bool = True,
    trained_batch: EpisodeBatch | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Energy table rows for each T: rollouts at T, spikes measured on those rollouts' obs.

    ``trained_batch`` (a recorded batch at the trained T) is reused instead of re-running it.
    The ANN baseline is an MLP ``obs -> ann_hidden_sizes -> action`` (default: the PopSAN's
    hidden sizes). ``progress(message)`` is called before each T (compiles take a while).
    """
    trained_t = trained_timesteps(loaded.config)
    if trained_t is None:
        raise ValueError("the energy table needs a PopSAN run")
    hidden = tuple(loaded.config.actor_kwargs["hidden_sizes"])
    ann_sizes = (loaded.env.observation_size, *(ann_hidden_sizes or hidden), loaded.env.action_size)
    ann_count = energy.ann_macs(ann_sizes)
    rows = []
    for t in timesteps_list:
        key, sub = jax.random.split(key)
        reuse = t == trained_t and trained_batch is not None and trained_batch.obs is not None
        if progress is not None:
            what = "reusing the report's rollouts" if reuse else f"running {episodes} episodes"
            progress(f"T = {t}: {what}, counting spikes")
        if reuse:
            batch = trained_batch
        else:
            batch = rollouts(loaded, episodes, sub, deterministic, timesteps=t, record=True)
        stats = summarize(batch)
        ops, _ = measure_snn_ops(loaded, alive_observations(batch), t)
        rows.append(
            energy.energy_row(
                ops,
                ann_count,
                stats["success_rate"],
                tuple(stats["success_ci95"]),
                reached_rate=stats["reached_rate"],
                trained=t == trained_t,
                layer_names=spiking_layer_names(len(hidden)),
            )
        )
    return rows


def format_report(report: dict[str, Any]) -> str:
    """Plain-text table of a :func:`summarize` report (plus run/which header if present)."""
    lo, hi = report["success_ci95"]
    rlo, rhi = report["reached_ci95"]
    lines = [
        f"run: {report.get('run_dir', '?')}  checkpoint: {report.get('which', '?')} "
        f"(env step {report.get('env_steps', '?')})  policy: {report.get('policy', '?')}",
        f"{'episodes':<22}{report['episodes']}",
        f"{'success rate':<22}{report['success_rate']:.3f}  (95 % CI {lo:.3f}-{hi:.3f}, Wilson)"
        "  held at the goal to the end",
        f"{'reached rate':<22}{report['reached_rate']:.3f}  (95 % CI {rlo:.3f}-{rhi:.3f})"
        "  PixMC's latch, for the paper",
        f"{'mean hold time (s)':<22}{report['hold_time']:.2f}",
        f"{'mean episode length':<22}{report['episode_length']:.1f}",
        f"{'mean return':<22}{report['episode_return']:.3f}",
    ]
    lines += [f"  {k:<20}{v:.4f}" for k, v in report.items() if k.startswith("reward/")]
    return "\n".join(lines)


def showcase_index(batch: EpisodeBatch) -> int:
    """Index of the episode to plot or render: the first successful one, else episode 0."""
    success = np.asarray(batch.success) > 0
    return int(np.argmax(success)) if success.any() else 0


def episode_arrays(batch: EpisodeBatch, index: int = 0) -> dict[str, np.ndarray]:
    """Recorded ``info`` arrays ``[T_i, ...]``, ``qpos`` and ``mocap_pos`` (when recorded) of one
    episode, cut to its alive steps."""
    if batch.alive is None or batch.info is None or batch.qpos is None:
        raise ValueError("the batch was not recorded (run with record=True)")
    alive = np.asarray(batch.alive)[:, index] > 0
    out = {k: np.asarray(v)[alive, index] for k, v in batch.info.items()}
    out["qpos"] = np.asarray(batch.qpos)[alive, index]
    if batch.mocap_pos is not None:
        out["mocap_pos"] = np.asarray(batch.mocap_pos)[alive, index]
    return out


def checkpoint_label(which: str | int) -> str:
    """File-name tag of a checkpoint choice: ``last``, ``best`` or ``step_<N>``."""
    return which if isinstance(which, str) else f"step_{int(which)}"


def latency_actors(loaded: Any, ann_hidden_sizes: Sequence[int] | None) -> dict[str, tuple]:
    """``{label: (module, variables)}`` for the PopSAN and the ANN actor compared for latency.

    The evaluated run's own actor keeps its trained params; the other one is freshly
    initialised (timing does not depend on the weights' values).
    """
    cfg, env = loaded.config, loaded.env
    own = make_actor(cfg.actor, cfg.actor_kwargs, env.action_size)
    hidden = tuple(cfg.actor_kwargs["hidden_sizes"])
    if cfg.actor == "popsan":
        other_name, other_kwargs = "mlp", dict(hidden_sizes=tuple(ann_hidden_sizes or hidden))
    else:
        other_name, other_kwargs = "popsan", {**POPSAN_DEFAULTS, "hidden_sizes": hidden}
    other = make_actor(other_name, other_kwargs, env.action_size)
    dummy = jnp.zeros((1, env.observation_size))
    actors = {
        cfg.actor: (own, actor_variables(loaded.policy_params)),
        other_name: (other, other.init(jax.random.PRNGKey(0), dummy)),
    }

    def label(name: str, module: Any) -> str:
        return f"PopSAN T={module.timesteps}" if name == "popsan" else "MLP (ANN)"

    ordered = sorted(actors.items(), key=lambda kv: kv[0] != "popsan")
    return {label(name, mv[0]): mv for name, mv in ordered}
