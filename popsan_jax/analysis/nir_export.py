"""Export a trained PopSAN's spiking core to NIR (the Neuromorphic Intermediate Representation).

The graph (``policy.nir``, HDF5 through ``nir.write``) holds the part of the policy that runs on a
neuromorphic chip::

    Input (encoder spikes, obs_dim * pop) -> [Affine -> CubaLIF] per synaptic layer -> Output

one ``Affine`` (weight ``(out, in)``, bias) and one ``CubaLIF`` for every hidden layer and for the
output populations. What NIR cannot express goes into a JSON sidecar with the same stem
(``policy.json``): the observation normaliser, the Gaussian receptive fields, the regular-spike
generator, the decoder, T, dt and the discretisation. The file pair alone reproduces the actions.

The mapping is exact. With the stated discretisation (forward Euler with step ``dt``, the voltage
uses the *new* current, an immediate reset to ``v_reset``)::

    I[t] = I[t-1] + dt/tau_syn * (-I[t-1] + w_in * x[t])
    v[t] = u[t-1] + dt/tau_mem * (v_leak - u[t-1] + r * I[t])
    z[t] = v[t] > v_threshold;     u[t] = v_reset if z[t] else v[t]

``tau_syn = dt / (1 - current_decay) = 2 dt``, ``w_in = tau_syn / dt = 2``,
``tau_mem = dt / (1 - voltage_decay) = 4 dt``, ``r = tau_mem / dt = 4``, ``v_leak = v_reset = 0``
give ``I = 0.5 I + x`` and ``v = 0.75 u + I``, i.e. PopSAN's
``c = 0.5 c + (W o + b); v = 0.75 v (1 - o_prev) + c`` (``u`` is 0 after a spike and ``v``
otherwise; the bias is the Affine's, added every step as in the model). The factors
``1 - dt/tau_syn = 0.5``, ``dt/tau_syn * w_in = 1``, ``1 - dt/tau_mem = 0.75`` and
``dt/tau_mem * r = 1`` are exact in binary floating point, so an interpreter that forms them
first (``decay * state + gain * input``) does the same float32 operations as the model.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import nir
import numpy as np

from popsan_jax.errors import UserError
from popsan_jax.networks import actor_variables, make_actor
from popsan_jax.rollout import EPISODE_END_METRICS
from popsan_jax.snn.encoder import ENCODER_THRESHOLD
from popsan_jax.snn.ops import spiking_layer_names
from popsan_jax.training.checkpoint import LoadedRun, load_run
from popsan_jax.training.setup import preprocess_observations

SIDECAR_FORMAT = "popsan-nir-sidecar/1"
# Seconds per SNN step (2**-10 s, about 1 ms). Only the ratios dt / tau enter the dynamics; a
# power of two makes dt / tau, 1 / tau and dt * (1 / tau) exact in any binary floating-point
# simulator, not only in one that forms the ratios as the sidecar states.
DEFAULT_DT = 2.0**-10
DISCRETISATION = (
    "forward Euler with step dt; per step and layer in graph order: "
    "I = (1 - dt/tau_syn) * I + (dt/tau_syn * w_in) * x (x = the Affine's W o + b of this step); "
    "v = (1 - dt/tau_mem) * v + (dt/tau_mem) * (v_leak + r * I), using the new I; "
    "z = v > v_threshold; v = v_reset where z (immediate reset); "
    "zero synaptic delay (layer l+1 sees layer l's spikes of the same step); "
    "all states are zero at the start of every observation (one inference = T steps); "
    "float32 throughout"
)


class NIRExportError(UserError):
    """The run cannot be exported to NIR (not a PopSAN, or a LIF mapping that is not exact)."""


def _layer_names(n_hidden: int) -> list[str]:
    """NIR layer names: the model's synaptic layers, ``output`` renamed ``output_pop`` (NIR's
    ``output`` is the graph's output node). Underscores only: importers turn node names into
    module names (torch rejects dots)."""
    return [*spiking_layer_names(n_hidden)[1:-1], "output_pop"]


def cuba_lif_params(
    current_decay: float, voltage_decay: float, threshold: float, n: int, dt: float
) -> dict[str, np.ndarray]:
    """``nir.CubaLIF`` keyword arguments (per-neuron ``(n,)`` float32 arrays) for PopSAN's LIF.

    Raises NIRExportError if the discrete factors the interpreter forms from them are not exactly
    the model's decays (they are for decays 0.5 and 0.75 and any dt).
    """
    tau_syn = dt / (1.0 - current_decay)
    tau_mem = dt / (1.0 - voltage_decay)
    w_in, r = tau_syn / dt, tau_mem / dt
    a, b = np.float32(tau_syn), np.float32(tau_mem)
    exact = (
        np.float32(1.0) - np.float32(dt) / a == np.float32(current_decay)
        and np.float32(dt) / a * np.float32(w_in) == 1.0
        and np.float32(1.0) - np.float32(dt) / b == np.float32(voltage_decay)
        and np.float32(dt) / b * np.float32(r) == 1.0
    )
    if not exact:
        raise NIRExportError(
            f"LIF decays ({current_decay}, {voltage_decay}) at dt={dt} have no exact float32 "
            "CubaLIF mapping"
        )

    def full(value: float) -> np.ndarray:
        return np.full((n,), value, np.float32)

    return dict(
        tau_syn=full(tau_syn),
        tau_mem=full(tau_mem),
        r=full(r),
        v_leak=full(0.0),
        v_threshold=full(threshold),
        v_reset=full(0.0),
        w_in=full(w_in),
    )


def _popsan_params(loaded: LoadedRun) -> tuple[Any, dict[str, Any]]:
    """``(actor module, params as float32 NumPy arrays)``; NIRExportError for a non-PopSAN run."""
    if loaded.config.actor != "popsan":
        raise NIRExportError(
            f"NIR export needs a PopSAN run; this run's actor is {loaded.config.actor!r}"
        )
    actor = make_actor("popsan", loaded.config.actor_kwargs, loaded.env.action_size)
    params = actor_variables(loaded.policy_params)["params"]
    as_np = {k: {n: np.asarray(v, np.float32) for n, v in p.items()} for k, p in params.items()}
    return actor, as_np


def to_nir(loaded: LoadedRun, dt: float = DEFAULT_DT) -> nir.NIRGraph:
    """The PopSAN's spiking core as a NIR graph (encoder spikes in, output-population spikes out).

    Nodes: ``input``, then per synaptic layer ``fc_<layer>`` (Affine) and ``lif_<layer>``
    (CubaLIF) for ``<layer>`` in ``hidden_0 .. hidden_{K-1}, output_pop``, then ``output``.
    The graph's metadata names dt, T and the discretisation; the rest is in the sidecar.
    """
    actor, params = _popsan_params(loaded)
    lif = actor.lif
    n_in = loaded.env.observation_size * actor.encoder_pop_dim
    nodes: dict[str, nir.NIRNode] = {"input": nir.Input(input_type=np.array([n_in]))}
    edges, prev = [], "input"
    for name, key in zip(_layer_names(len(actor.hidden_sizes)), _param_keys(actor), strict=True):
        kernel, bias = params[key]["kernel"], params[key]["bias"]
        nodes[f"fc_{name}"] = nir.Affine(weight=np.ascontiguousarray(kernel.T), bias=bias.copy())
        nodes[f"lif_{name}"] = nir.CubaLIF(
            **cuba_lif_params(
                lif.current_decay, lif.voltage_decay, lif.threshold, bias.shape[0], dt
            )
        )
        edges += [(prev, f"fc_{name}"), (f"fc_{name}", f"lif_{name}")]
        prev = f"lif_{name}"
    n_out = loaded.env.action_size * actor.decoder_pop_dim
    nodes["output"] = nir.Output(output_type=np.array([n_out]))
    edges.append((prev, "output"))
    metadata = dict(
        producer="popsan_jax",
        sidecar_format=SIDECAR_FORMAT,
        dt=float(dt),
        timesteps=int(actor.timesteps),
        discretisation=DISCRETISATION,
    )
    return nir.NIRGraph(nodes=nodes, edges=edges, metadata=metadata)


def _param_keys(actor: Any) -> list[str]:
    """The params keys of the synaptic layers, in graph order (``hidden_0 .. output``)."""
    return spiking_layer_names(len(actor.hidden_sizes))[1:]


def sidecar(loaded: LoadedRun, dt: float = DEFAULT_DT, graph_name: str = "policy.nir") -> dict:
    """What NIR cannot express, as a JSON-ready dict (float32 values, exact through JSON)."""
    actor, params = _popsan_params(loaded)
    norm = loaded.normalizer_params
    enc, dec = params["encoder"], params["decoder"]
    obs_dim, action_size = loaded.env.observation_size, loaded.env.action_size

    def floats(x: Any) -> list:
        return np.asarray(x, np.float32).astype(np.float64).tolist()

    return dict(
        format=SIDECAR_FORMAT,
        graph=graph_name,
        run=dict(
            env=loaded.config.env,
            env_revision=int(loaded.config.env_revision),
            env_overrides=dict(loaded.config.env_overrides),
            env_steps=int(loaded.step),
            checkpoint=loaded.entry.get("dir"),
        ),
        dtype="float32",
        observation_size=int(obs_dim),
        action_size=int(action_size),
        timesteps=int(actor.timesteps),
        dt=float(dt),
        discretisation=DISCRETISATION,
        layers=[f"lif_{n}" for n in _layer_names(len(actor.hidden_sizes))],
        normalizer=dict(
            formula="x = clip((obs - mean) / std, -clip, clip), float32",
            mean=floats(norm.mean),
            std=floats(norm.std),
            clip=float(loaded.config.obs_clip),
        ),
        encoder=dict(
            formula=(
                "A[i*pop_dim + j] = exp(-0.5 * (x[i] - mean[i][j])**2 / std[i][j]**2); "
                "per step: v += A; spike = v > threshold; v -= spike * threshold; v starts at 0"
            ),
            pop_dim=int(actor.encoder_pop_dim),
            mean=floats(enc["mean"]),
            std=floats(enc["std"]),
            threshold=float(np.float32(ENCODER_THRESHOLD)),
            input_order="graph input neuron i*pop_dim + j: observation dimension i, field j",
        ),
        decoder=dict(
            formula=(
                "rate = (spike count of the graph's output over the T steps) / T; "
                "action[a] = tanh(sum_j weight[a][j] * rate[a*pop_dim + j] + bias[a])"
            ),
            float32_note=(
                "the trained policy's float32 sum and tanh are XLA's; NumPy's round differently "
                "(actions ~1e-7 apart from equal spike counts)"
            ),
            pop_dim=int(actor.decoder_pop_dim),
            weight=floats(dec["weight"]),
            bias=floats(dec["bias"]),
            output_order="graph output neuron a*pop_dim + j: action dimension a, neuron j",
        ),
    )


def write_nir(
    loaded: LoadedRun, path: str | os.PathLike, dt: float = DEFAULT_DT
) -> tuple[Path, Path]:
    """Write the graph to ``path`` (``.nir``) and the sidecar beside it (``.json``, same stem)."""
    path = Path(path)
    if path.suffix != ".nir":
        raise NIRExportError(f"the NIR file's name must end in .nir, got {str(path)!r}")
    graph = to_nir(loaded, dt)
    side = path.with_suffix(".json")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        nir.write(path, graph)
        side.write_text(json.dumps(sidecar(loaded, dt, path.name), indent=1) + "\n")
    except OSError as e:
        raise NIRExportError(f"cannot write {path}: {e}") from e
    return path, side


def export_run_nir(
    run_dir: str | os.PathLike,
    path: str | os.PathLike,
    which: str | int = "last",
    dt: float = DEFAULT_DT,
) -> tuple[Path, Path]:
    """Load ``which`` checkpoint of ``run_dir`` and write ``path`` and its sidecar.

    A missing or unloadable checkpoint raises CheckpointError, an MLP run NIRExportError
    (both UserError).
    """
    return write_nir(load_run(run_dir, which), path, dt)


def jax_reference(loaded: LoadedRun) -> Callable[[np.ndarray], tuple[np.ndarray, tuple]]:
    """The trained JAX PopSAN that an export is checked against, on the host.

    ``forward(obs [B, O]) -> (action mean [B, A], spikes)`` with the policy's preprocessing
    (running-statistics normalisation clipped to ``obs_clip``); ``spikes`` are NumPy arrays
    ``[T, B, N]``: the encoder, then every LIF layer in graph order.
    """
    actor, _ = _popsan_params(loaded)
    variables = actor_variables(loaded.policy_params)

    @jax.jit
    def forward(obs: jax.Array) -> tuple[jax.Array, tuple[jax.Array, ...]]:
        x = preprocess_observations(obs, loaded.normalizer_params, loaded.config.obs_clip)
        return actor.apply(variables, x, return_spikes=True)

    return lambda obs: jax.device_get(forward(jnp.asarray(obs, jnp.float32)))


def host_episodes(
    env_fns: tuple[Callable, Callable],
    policy: Callable[[np.ndarray], np.ndarray],
    num_episodes: int,
    steps: int,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Episodes driven by a host-side policy, e.g. an exported policy re-simulated in NumPy.

    Args:
      env_fns: ``(reset, step)``: the env's jitted, vmapped reset and step.
      policy: ``policy(obs [N, O] float32) -> action [N, A]``, called once per control step.
      num_episodes: N, run in parallel from ``reset(split(PRNGKey(seed), N))``.
      steps: control steps; no auto-reset (an episode ends at its first ``done``).

    Returns:
      ``obs [S, N, O]``, ``action [S, N, A]``, ``alive [S, N]`` (bool: the step counts) and
      ``success``, ``reached``, ``hold_time`` ``[N]``: the env's metrics at each episode's last
      step, as in popsan_jax.rollout (``franka_pick``: ``success`` is pick-and-hold,
      ``reached`` PixMC's latch).
    """
    reset, step = env_fns
    state = reset(jax.random.split(jax.random.PRNGKey(seed), num_episodes))
    alive = np.ones(num_episodes, bool)
    end = {k: np.zeros(num_episodes, np.float32) for k in EPISODE_END_METRICS}
    obs_log, act_log, alive_log = [], [], []
    for _ in range(steps):
        obs = np.asarray(state.obs)
        with np.errstate(all="ignore"):  # a finished episode's state may hold NaNs
            action = np.asarray(policy(obs), np.float32)
        obs_log.append(obs)
        act_log.append(action)
        alive_log.append(alive.copy())
        state = step(state, jnp.asarray(action))
        for k, value in end.items():
            end[k] = np.where(alive, np.asarray(state.metrics[k], np.float32), value)
        alive = alive & (np.asarray(state.done) == 0)
    return dict(
        obs=np.stack(obs_log),
        action=np.stack(act_log),
        alive=np.stack(alive_log),
        **end,
    )
