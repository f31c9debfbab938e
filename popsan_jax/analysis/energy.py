"""Operation counting from measured spikes and the paper's energy model (after Horowitz, 45 nm).

Convention (DESIGN.md "Energy convention"; paper Sec. "Energy Consumption", eq. for E_model):

* ``E_MAC = 4.6 pJ`` per multiply-accumulate, ``E_AC = 0.9 pJ`` per accumulate (32-bit float).
* ANN actor: every layer is dense MACs, ``sum_k n_k * n_{k+1}`` per inference, output layer
  included.
* PopSAN actor, per inference (one control step, ``T`` SNN timesteps):

  - the encoder layer (Gaussian receptive fields of the real-valued observation) is MACs: one per
    encoder neuron, ``obs * enc_pop``, once per inference (its activation does not depend on
    ``t``). This is the paper's "FLOPs in the initial encoder layer are MAC, whereas all other
    Conv or FC layers are AC".
  - every synaptic layer (encoder populations -> first hidden, hidden -> hidden, last hidden ->
    output populations) is one AC per presynaptic spike and postsynaptic target,
    ``SOPs = sum_layers sum_t spikes * fan_out``, counted from spikes actually measured. The
    encoder's output is binary spikes, so its fan-out is accumulate-only like any other layer.
  - decoder over output firing rates: dense MACs once per inference,
    ``action_size * decoder_pop_dim`` (each action reads only its own population).

  The upper-bound reading ("the first FC layer is dense MACs at every timestep",
  ``n_enc * n_h1 * T``, as a GPU would execute Algorithm 1) is reported alongside as a
  sensitivity column: it is what a dense implementation would cost, and it is far above the
  paper's own table (its T = 1 SNN figure is impossible under that reading).

* Biases are not counted on either side (one add per neuron, under 1 % of the totals here).
* Left out: memory access (weights and membrane state reads/writes often dominate on real
  hardware, spyx#76), the exponential of the receptive fields beyond one MAC per neuron, the LIF
  state updates (decay multiplies, threshold compares), the rate division and any output
  squashing, data movement between layers, and hardware idle power. The figures compare
  arithmetic only.

Shapes: spikes are ``[T, B, N]`` 0/1 arrays, ``T`` SNN timesteps, ``B`` observations,
``N`` neurons in the layer.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

E_MAC_PJ = 4.6
E_AC_PJ = 0.9

CONVENTION_NOTE = (
    "Convention (paper, after Horowitz 45 nm, 32-bit float): E_MAC = 4.6 pJ, E_AC = 0.9 pJ. "
    "ANN: every layer is dense MACs (output layer included). PopSAN: the encoder layer "
    "(Gaussian receptive fields of the real-valued observation, obs x pop neurons) is MACs once "
    "per inference; every synaptic layer, the first one included (its input is encoder spikes), "
    "is one AC per measured presynaptic spike and target (SOPs = sum_layers sum_t spikes x "
    "fan-out); the decoder over output firing rates is dense MACs once per inference. Spikes are "
    "measured on the evaluation rollouts' own observations (alive steps only). Biases are not "
    "counted. Left out: memory access (weight and state reads/writes, which often dominate on "
    "real hardware, spyx#76), LIF state updates and threshold compares, and idle power. "
    "'saving, dense first layer' is the upper-bound sensitivity figure that charges the first "
    "FC layer as dense MACs at every timestep (n_enc x n_h1 x T), as a GPU executes it."
)


@dataclass(frozen=True)
class SNNOps:
    """Operations per inference of a PopSAN, averaged over the measured observations.

    Attributes:
      encoder_macs: receptive-field MACs, one per encoder neuron (``obs * enc_pop``).
      sops: spike-driven ACs of every synaptic layer (first layer included).
      first_layer_sops: the part of ``sops`` from encoder spikes into the first hidden layer.
      dense_first_layer_macs: ``n_enc * n_h1 * T``, the first FC layer charged densely
        (sensitivity figure).
      decoder_macs: decoder MACs over firing rates, ``action_size * decoder_pop_dim``.
      firing_rates: per spiking layer (encoder, hidden..., output), spikes per neuron per
        timestep.
      timesteps: ``T``.
    """

    encoder_macs: float
    sops: float
    first_layer_sops: float
    dense_first_layer_macs: float
    decoder_macs: float
    firing_rates: tuple[float, ...]
    timesteps: int

    @property
    def macs(self) -> float:
        return self.encoder_macs + self.decoder_macs

    @property
    def energy_pj(self) -> float:
        return energy_pj(self.macs, self.sops)

    @property
    def dense_first_energy_pj(self) -> float:
        """Energy if the first FC layer were dense MACs every timestep (upper bound)."""
        return energy_pj(self.macs + self.dense_first_layer_macs, self.sops - self.first_layer_sops)


def energy_pj(macs: float, acs: float) -> float:
    """Energy in pJ of ``macs`` multiply-accumulates and ``acs`` accumulates."""
    return E_MAC_PJ * float(macs) + E_AC_PJ * float(acs)


def saving_percent(snn_pj: float, ann_pj: float) -> float:
    """Energy saved by the SNN relative to the ANN, in % (negative if the SNN costs more)."""
    return 100.0 * (1.0 - snn_pj / ann_pj)


def ann_macs(layer_sizes: Sequence[int]) -> int:
    """Dense MACs of an MLP with ``layer_sizes = (in, hidden..., out)``, biases not counted."""
    sizes = [int(n) for n in layer_sizes]
    if len(sizes) < 2 or min(sizes) < 1:
        raise ValueError(f"need at least two positive layer sizes, got {layer_sizes}")
    return sum(a * b for a, b in zip(sizes[:-1], sizes[1:], strict=False))


def popsan_layer_sizes(
    observation_size: int,
    action_size: int,
    hidden_sizes: Sequence[int],
    encoder_pop_dim: int,
    decoder_pop_dim: int,
) -> tuple[int, ...]:
    """Neurons per spiking layer: ``(obs * enc_pop, hidden..., action * dec_pop)``."""
    return (
        observation_size * encoder_pop_dim,
        *(int(h) for h in hidden_sizes),
        action_size * decoder_pop_dim,
    )


def snn_ops_from_totals(
    totals: Sequence[float],
    num_observations: float,
    layer_sizes: Sequence[int],
    timesteps: int,
    action_size: int,
) -> SNNOps:
    """Turn per-layer spike totals over ``num_observations`` inferences into ops per inference.

    Args:
      totals: ``[L]`` spike counts per spiking layer (encoder, hidden..., output), summed over
        timesteps, neurons and observations (see :func:`popsan_jax.snn.ops.spike_totals`).
      num_observations: how many inferences the totals cover.
      layer_sizes: neurons per spiking layer, as :func:`popsan_layer_sizes`.
      timesteps: ``T``.
      action_size: ``A``; the decoder reads ``layer_sizes[-1] // A`` rates per action.
    """
    sizes = [int(n) for n in layer_sizes]
    counts = np.asarray(totals, dtype=np.float64)
    if counts.shape != (len(sizes),):
        raise ValueError(f"expected {len(sizes)} layer totals, got shape {counts.shape}")
    if num_observations <= 0:
        raise ValueError("no observations to count operations over")
    if sizes[-1] % action_size:
        raise ValueError(f"output layer {sizes[-1]} is not a multiple of action size {action_size}")
    per_inf = counts / float(num_observations)
    # Every spiking layer but the output populations feeds a synaptic layer through ACs; the
    # output populations feed the rate decoder, which is MACs.
    fan_in_sops = [per_inf[k] * sizes[k + 1] for k in range(len(sizes) - 1)]
    rates = tuple(float(per_inf[k] / (sizes[k] * timesteps)) for k in range(len(sizes)))
    return SNNOps(
        encoder_macs=float(sizes[0]),
        sops=float(sum(fan_in_sops)),
        first_layer_sops=float(fan_in_sops[0]),
        dense_first_layer_macs=float(sizes[0] * sizes[1] * timesteps),
        decoder_macs=float(sizes[-1]),
        firing_rates=rates,
        timesteps=int(timesteps),
    )


def energy_row(
    ops: SNNOps,
    ann_mac_count: int,
    success_rate: float,
    ci95: tuple[float, float],
    trained: bool,
    layer_names: Sequence[str],
    reached_rate: float | None = None,
) -> dict[str, float | int | bool | str]:
    """One flat row of the energy table (units: pJ; rates in spikes per neuron per timestep).

    ``success_rate`` is pick-and-hold success; ``reached_rate`` (PixMC's latch) rides along."""
    ann_pj = energy_pj(ann_mac_count, 0)
    row: dict[str, float | int | bool | str] = dict(
        timesteps=ops.timesteps,
        trained_timesteps=trained,
        success_rate=float(success_rate),
        success_ci_low=float(ci95[0]),
        success_ci_high=float(ci95[1]),
        reached_rate=float("nan") if reached_rate is None else float(reached_rate),
        snn_macs=ops.macs,
        snn_acs=ops.sops,
        snn_energy_pj=ops.energy_pj,
        snn_dense_first_energy_pj=ops.dense_first_energy_pj,
        ann_macs=int(ann_mac_count),
        ann_energy_pj=ann_pj,
        saving_pct=saving_percent(ops.energy_pj, ann_pj),
        dense_first_saving_pct=saving_percent(ops.dense_first_energy_pj, ann_pj),
    )
    for name, rate in zip(layer_names, ops.firing_rates, strict=True):
        row[f"firing_rate/{name}"] = rate
    return row


def energy_markdown(rows: Sequence[dict], title: str = "Energy per inference") -> str:
    """The energy table, the firing-rate table and the convention note, as Markdown."""
    lines = [
        f"### {title}",
        "",
        "| T | success rate (95 % CI) | reached | SNN MACs | SNN ACs (SOPs) | SNN energy (nJ) "
        "| ANN MACs | ANN energy (nJ) | saving | saving, dense first layer |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        t = f"{r['timesteps']} (trained)" if r["trained_timesteps"] else f"{r['timesteps']}"
        lines.append(
            f"| {t} | {r['success_rate']:.3f} ({r['success_ci_low']:.3f}-"
            f"{r['success_ci_high']:.3f}) | {r.get('reached_rate', float('nan')):.3f} | "
            f"{r['snn_macs']:,.0f} | {r['snn_acs']:,.0f} | "
            f"{r['snn_energy_pj'] / 1e3:,.2f} | {r['ann_macs']:,} | "
            f"{r['ann_energy_pj'] / 1e3:,.2f} | {r['saving_pct']:.1f} % | "
            f"{r['dense_first_saving_pct']:.1f} % |"
        )
    names = [k.split("/", 1)[1] for k in rows[0] if k.startswith("firing_rate/")] if rows else []
    trained = [r["timesteps"] for r in rows if r["trained_timesteps"]]
    if trained:
        lines += [
            "",
            f"Trained at T = {trained[0]}. Other rows run the SAME parameters at another T "
            "(not retrained); success and spikes come from their own rollouts. Success: the "
            "object held at the goal to the episode's end; reached: PixMC's latch.",
        ]
    lines += ["", "Firing rates (spikes per neuron per timestep, alive steps of the rollouts):", ""]
    lines.append("| T | " + " | ".join(names) + " |")
    lines.append("|---|" + "---:|" * len(names))
    for r in rows:
        rates = " | ".join(f"{r[f'firing_rate/{n}']:.4f}" for n in names)
        lines.append(f"| {r['timesteps']} | {rates} |")
    lines += ["", CONVENTION_NOTE, ""]
    return "\n".join(lines)


def write_energy_csv(rows: Sequence[dict], path: str | os.PathLike) -> Path:
    """Write the rows as CSV (one line per T, energies in pJ); the convention is a comment line."""
    path = Path(path)
    with open(path, "w", newline="") as f:
        f.write(f"# {CONVENTION_NOTE}\n")
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path
