"""A plain NumPy interpreter of an exported PopSAN: the NIR graph plus its JSON sidecar.

Written from the NIR spec's CubaLIF equations and the sidecar's stated discretisation, not from
the JAX model (it imports nothing of popsan_jax). Everything is float32. ``convention`` selects
how a simulator discretises CubaLIF, so the tests and docs can measure what the other
conventions would do to the policy:

- ``"exact"``: the stated one (forward Euler, the voltage uses the new current, immediate reset
  to v_reset). Norse's ``from_nir`` and lava-dl's CUBA neuron follow it.
- ``"lagged"``: the voltage integrates the previous step's current (a one-step lag).
- ``"subtractive"``: a spike subtracts v_threshold instead of resetting to v_reset.
- ``"lagged_subtractive"``: both (NIR's reference simulator, Spyx).
- ``"exponential"``: decays ``exp(-dt/tau)`` instead of ``1 - dt/tau`` with the same input
  gains (Rockpool's time-constant convention).
"""

from __future__ import annotations

import numpy as np

F32 = np.float32
CONVENTIONS = ("exact", "lagged", "subtractive", "lagged_subtractive", "exponential")


def chain(graph) -> list[str]:
    """Node names from ``input`` to ``output`` (the exported graph is a chain)."""
    nxt = dict(graph.edges)
    assert len(nxt) == len(graph.edges), "not a chain"
    order = ["input"]
    while order[-1] != "output":
        order.append(nxt[order[-1]])
    return order


def normalise(obs: np.ndarray, side: dict) -> np.ndarray:
    n = side["normalizer"]
    x = (obs.astype(F32) - np.asarray(n["mean"], F32)) / np.asarray(n["std"], F32)
    return np.clip(x, F32(-n["clip"]), F32(n["clip"]))


def encode(x: np.ndarray, side: dict) -> np.ndarray:
    """Normalised obs ``[B, O]`` -> encoder spikes ``[T, B, O * pop]``."""
    e = side["encoder"]
    mean, std = np.asarray(e["mean"], F32), np.asarray(e["std"], F32)
    activity = np.exp(F32(-0.5) * np.square(x[..., None] - mean) / np.square(std))
    activity = activity.reshape(x.shape[0], -1)
    threshold = F32(e["threshold"])
    v = np.zeros_like(activity)
    spikes = []
    for _ in range(side["timesteps"]):
        v = v + activity
        s = (v > threshold).astype(F32)
        v = v - s * threshold
        spikes.append(s)
    return np.stack(spikes)


def affine(node, x: np.ndarray) -> np.ndarray:
    """``W x + b`` for a batch ``x [B, in]`` in float32. The inputs are 0/1 spikes, so this sums
    float32 weights; NumPy's BLAS may sum them in another order than XLA (an ulp apart)."""
    return x @ node.weight.astype(F32).T + node.bias.astype(F32)


def lif_factors(node, dt: float, convention: str) -> tuple[np.ndarray, ...]:
    """``(current decay, current gain, voltage decay, voltage gain)`` as float32 arrays."""
    tau_syn, tau_mem = node.tau_syn.astype(F32), node.tau_mem.astype(F32)
    k_syn, k_mem = F32(dt) / tau_syn, F32(dt) / tau_mem
    if convention == "exponential":
        a_syn, a_mem = np.exp(-k_syn), np.exp(-k_mem)
    else:
        a_syn, a_mem = F32(1) - k_syn, F32(1) - k_mem
    return a_syn, k_syn * node.w_in.astype(F32), a_mem, k_mem * node.r.astype(F32)


def decode(side: dict, out_spikes: np.ndarray) -> np.ndarray:
    """Output-population spikes ``[T, B, A * pop]`` -> actions ``[B, A]``: the sidecar's decoder."""
    d = side["decoder"]
    steps, batch = out_spikes.shape[0], out_spikes.shape[1]
    rates = out_spikes.sum(axis=0, dtype=F32) / F32(steps)
    rates = rates.reshape(batch, side["action_size"], d["pop_dim"])
    weight, bias = np.asarray(d["weight"], F32), np.asarray(d["bias"], F32)
    return np.tanh(np.sum(rates * weight, axis=-1) + bias)


def run(
    graph,
    side: dict,
    obs: np.ndarray,
    convention: str = "exact",
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Raw observations ``[B, O]`` -> ``(actions [B, A], spikes)``.

    ``spikes`` maps ``"input"`` (encoder) and every CubaLIF node name to ``[T, B, N]``.
    """
    assert convention in CONVENTIONS, convention
    dt, steps = float(side["dt"]), int(side["timesteps"])
    order = chain(graph)
    enc = encode(normalise(obs, side), side)
    batch = obs.shape[0]
    state, factors = {}, {}
    for name in order:
        node = graph.nodes[name]
        if type(node).__name__ == "CubaLIF":
            n = node.v_threshold.shape[0]
            state[name] = [np.zeros((batch, n), F32), np.zeros((batch, n), F32)]  # I, v
            factors[name] = lif_factors(node, dt, convention)
    spikes = {"input": enc, **{name: [] for name in state}}
    for t in range(steps):
        x = enc[t]
        for name in order[1:-1]:
            node = graph.nodes[name]
            kind = type(node).__name__
            if kind == "Affine":
                x = affine(node, x)
            elif kind == "CubaLIF":
                a_syn, g_syn, a_mem, g_mem = factors[name]
                i_old, v = state[name]
                i_new = a_syn * i_old + g_syn * x
                drive = i_old if convention.startswith("lagged") else i_new
                v = a_mem * v + g_mem * (node.v_leak.astype(F32) + drive)
                z = v > node.v_threshold.astype(F32)
                if convention.endswith("subtractive"):
                    v = np.where(z, v - node.v_threshold.astype(F32), v)
                else:
                    v = np.where(z, node.v_reset.astype(F32), v)
                state[name] = [i_new, v]
                x = z.astype(F32)
                spikes[name].append(x)
            else:
                raise ValueError(f"unexpected node {name}: {kind}")
    spikes = {k: np.stack(v) if isinstance(v, list) else v for k, v in spikes.items()}
    return decode(side, spikes[order[-2]]), spikes
