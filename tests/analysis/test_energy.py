"""Operation counting and energy arithmetic against hand-worked values."""

import csv

import jax.numpy as jnp
import numpy as np
import pytest
from _tiny_spikes import SIZES, tiny_spikes

from popsan_jax.analysis import energy
from popsan_jax.snn.ops import spike_totals


def count_snn_ops(spikes, layer_sizes, action_size, weight=None) -> energy.SNNOps:
    """Reference: ops per inference from one batch of measured spikes ``[T, B, N_l]`` per layer
    (what eval's chunked measurement adds up)."""
    timesteps, batch = spikes[0].shape[:2]
    totals = np.asarray(spike_totals(spikes, weight))
    n = float(batch if weight is None else np.sum(np.asarray(weight)))
    return energy.snn_ops_from_totals(totals, n, layer_sizes, timesteps, action_size)


def test_layer_sizes_and_ann_macs():
    assert energy.popsan_layer_sizes(34, 9, (256, 256), 10, 10) == (340, 256, 256, 90)
    # 34*256 + 256*256 + 256*9, output layer included, no biases.
    assert energy.ann_macs((34, 256, 256, 9)) == 8704 + 65536 + 2304
    with pytest.raises(ValueError):
        energy.ann_macs((34,))


def test_tiny_network_ops_hand_worked():
    ops = count_snn_ops(tiny_spikes(), SIZES, action_size=1)
    # Encoder receptive fields: one MAC per encoder neuron = 4; decoder: 1 action x 2 rates.
    assert ops.encoder_macs == 4 and ops.decoder_macs == 2 and ops.macs == 6
    # SOPs per inference (2 inferences): encoder 7 spikes x fan-out 3 = 21, hidden1 6 x 2 = 12,
    # hidden2 4 x 2 = 8 -> 41 / 2 = 20.5; the output populations feed the decoder, not ACs.
    assert ops.sops == pytest.approx(20.5)
    assert ops.first_layer_sops == pytest.approx(10.5)
    # Dense first layer (sensitivity): 4 * 3 * T=2 = 24 MACs per inference.
    assert ops.dense_first_layer_macs == 24
    # Firing rates: spikes / (neurons * T * B).
    np.testing.assert_allclose(ops.firing_rates, [7 / 16, 6 / 12, 4 / 8, 4 / 8])
    # Energy: 6 MACs * 4.6 + 20.5 ACs * 0.9 = 27.6 + 18.45 = 46.05 pJ.
    assert ops.energy_pj == pytest.approx(46.05)
    # Dense first layer: (6 + 24) * 4.6 + (20.5 - 10.5) * 0.9 = 138 + 9 = 147 pJ.
    assert ops.dense_first_energy_pj == pytest.approx(147.0)


def test_masked_observation_is_not_counted():
    ops = count_snn_ops(tiny_spikes(), SIZES, 1, weight=jnp.asarray([0.0, 1.0]))
    # Only observation 1: encoder 4 spikes x 3 + hidden1 3 x 2 + hidden2 3 x 2 = 24 SOPs.
    assert ops.sops == pytest.approx(24.0)
    assert ops.first_layer_sops == pytest.approx(4 * 3)


def test_energy_arithmetic_paper_sized_network():
    ann_pj = energy.energy_pj(energy.ann_macs((34, 256, 256, 9)), 0)
    assert ann_pj == pytest.approx(76544 * 4.6)  # 352,102.4 pJ
    # PopSAN 34x10 -> 256 -> 256 -> 9x10 at T = 5, encoder rate 0.05, hidden rates 0.1, 0.2:
    # SOPs = 0.05*340*5*256 + 0.1*256*5*256 + 0.2*256*5*90 = 21760 + 32768 + 23040 = 77568
    # MACs = 340 + 90 = 430 -> 1,978 pJ + 69,811.2 pJ = 71,789.2 pJ.
    sizes = (340, 256, 256, 90)
    totals = [0.05 * 340 * 5, 0.1 * 256 * 5, 0.2 * 256 * 5, 0.0]
    ops = energy.snn_ops_from_totals(totals, 1, sizes, timesteps=5, action_size=9)
    assert ops.sops == pytest.approx(77568)
    assert ops.energy_pj == pytest.approx(71789.2)
    assert energy.saving_percent(ops.energy_pj, ann_pj) == pytest.approx(
        100 * (1 - 71789.2 / 352102.4)
    )
    # Dense first layer: MACs 430 + 435200, ACs 77568 - 21760 = 55808.
    assert ops.dense_first_energy_pj == pytest.approx(435630 * 4.6 + 55808 * 0.9)
    assert energy.saving_percent(25.0, 100.0) == pytest.approx(75.0)


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        energy.snn_ops_from_totals([1.0, 2.0], 1, SIZES, 2, 1)
    with pytest.raises(ValueError):
        energy.snn_ops_from_totals([1.0] * 4, 0, SIZES, 2, 1)
    with pytest.raises(ValueError):
        energy.snn_ops_from_totals([1.0] * 4, 1, (4, 3, 2, 3), 2, 2)


def test_energy_row_markdown_and_csv(tmp_path):
    sizes = (4, 3, 2, 2)
    ops = energy.snn_ops_from_totals([8.0, 6.0, 4.0, 2.0], 2, sizes, timesteps=2, action_size=1)
    names = ["encoder", "hidden_0", "hidden_1", "output"]
    # ANN 2 -> 3 -> 2 -> 1: 6 + 6 + 2 = 14 MACs = 64.4 pJ.
    row = energy.energy_row(
        ops, 14, 0.5, (0.2, 0.8), trained=True, layer_names=names, reached_rate=0.75
    )
    # SNN: MACs 4 + 2 = 6, SOPs (8*3 + 6*2 + 4*2)/2 = 22 -> 27.6 + 19.8 = 47.4 pJ.
    assert row["snn_energy_pj"] == pytest.approx(47.4)
    assert row["ann_energy_pj"] == pytest.approx(64.4)
    assert row["saving_pct"] == pytest.approx(100 * (1 - 47.4 / 64.4))
    # Dense first layer: (6 + 24) * 4.6 + (22 - 12) * 0.9 = 147 pJ: the SNN costs more.
    assert row["dense_first_saving_pct"] == pytest.approx(100 * (1 - 147.0 / 64.4))
    assert row["firing_rate/encoder"] == pytest.approx(8 / (4 * 2 * 2))
    md = energy.energy_markdown([row], "tiny")
    row_md = (
        "| 2 (trained) | 0.500 (0.200-0.800) | 0.750 | 6 | 22 | 0.05 | 14 | 0.06 | 26.4 % "
        "| -128.3 % |"
    )
    assert row_md in md
    assert (
        "Trained at T = 2" in md
        and "spyx#76" in md
        and "| 2 | 0.5000 | 0.5000 | 0.5000 | 0.2500 |" in md
    )
    path = energy.write_energy_csv([row], tmp_path / "e.csv")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# Convention")
    (parsed,) = list(csv.DictReader(lines[1:]))
    assert float(parsed["snn_energy_pj"]) == pytest.approx(47.4)
    assert parsed["trained_timesteps"] == "True"
