"""Re-simulate an exported PopSAN in third-party and reference NIR conventions; spike agreement.

    python benchmarks/nir_third_party.py [RUN] [--episodes 8] [--steps 150] [--closed-loop 32]

Exports RUN (default: the committed pick PopSAN) to NIR in a temporary folder, collects
observations from deterministic rollouts of the JAX policy, and compares every spiking layer
of the JAX PopSAN, bit for bit, with:

- Norse (``norse.torch.from_nir(graph, dt=...)``), when torch and norse are installed
  (``pip install -e '.[nir-sim]'``);
- the NumPy interpreter of the tests (``tests/analysis/_nir_reference.py``) in the stated
  convention and in the conventions of other simulators (one-step current lag, subtractive
  reset, both: NIR's reference simulator and Spyx; exponential decays: Rockpool).

Prints per layer the spikes that differ from the JAX PopSAN's, and the largest action
difference (from equal spikes, ~1e-7: XLA's float32 sum and tanh round differently from
NumPy's). The encoder's spikes are computed on the host and fed to every simulator, so
differences start in the first LIF layer. ``--closed-loop N`` then drives N episodes with each
re-simulated policy and compares success and trajectories with the JAX policy's.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests/analysis"))  # the NumPy interpreter lives with the tests

from popsan_jax.jax_setup import enable_compilation_cache, import_mjx_quietly  # noqa: E402

import_mjx_quietly()  # before brax/MJX modules import it noisily

import _nir_reference as ref  # noqa: E402
import jax  # noqa: E402
import nir  # noqa: E402
import numpy as np  # noqa: E402

from popsan_jax.analysis.evaluation import alive_observations  # noqa: E402
from popsan_jax.analysis.nir_export import host_episodes, jax_reference, write_nir  # noqa: E402
from popsan_jax.networks import actor_variables  # noqa: E402
from popsan_jax.rollout import run_episodes  # noqa: E402
from popsan_jax.snn.decoder import PopulationDecoder  # noqa: E402
from popsan_jax.training.checkpoint import load_run  # noqa: E402

DEFAULT_RUN = ROOT / "docs/reference/readme-popsan-s0"


def norse_spikes(graph, side: dict, enc: np.ndarray) -> dict[str, np.ndarray]:
    """Run the graph in Norse on the encoder spikes ``[T, B, N]``; spikes of every CubaLIF."""
    import norse.torch  # optional (.[nir-sim]): imported only when Norse is asked for
    import torch

    model = norse.torch.from_nir(graph, dt=float(side["dt"]))
    seen: dict[str, list] = {name: [] for name in side["layers"]}
    for name, module in model.named_modules():
        if name in seen:
            module.register_forward_hook(
                lambda _m, _i, out, name=name: seen[name].append(out[0].detach().numpy())
            )
    state = None
    with torch.no_grad():
        for t in range(enc.shape[0]):
            _, state = model(torch.from_numpy(np.array(enc[t])), state)
    return {name: np.stack(v) for name, v in seen.items()}


def closed_loop(loaded, graph, side: dict, jax_forward, episodes: int) -> None:
    """Success of the same episodes driven by the JAX policy and by each re-simulation.

    One more row drives the env with the JAX policy's own spikes but its decoder compiled on
    its own: XLA then rounds the decoder's float32 sum differently (~1e-7), which shows how much
    of any trajectory difference comes from float rounding alone.
    """
    env_fns = jax.jit(jax.vmap(loaded.env.reset)), jax.jit(jax.vmap(loaded.env.step))
    steps = int(loaded.env.config.episode_length)
    original = host_episodes(env_fns, lambda o: jax_forward(o)[0], episodes, steps)
    decoder = PopulationDecoder(loaded.env.action_size, side["decoder"]["pop_dim"])
    dec_params = {"params": actor_variables(loaded.policy_params)["params"]["decoder"]}
    decode_alone = jax.jit(lambda s: decoder.apply(dec_params, s))
    policies = [
        ("JAX spikes, decoder compiled alone", lambda o: decode_alone(jax_forward(o)[1][-1]))
    ]
    policies += [
        (f"NumPy, {c}", lambda o, c=c: ref.run(graph, side, o, c)[0]) for c in ref.CONVENTIONS
    ]
    print(
        f"\nclosed loop, {episodes} episodes x {steps} steps "
        "(the env's metrics; franka_pick: success = pick-and-hold, reached = PixMC's latch)"
    )
    print(
        f"{'policy':<44} success  same success  reached  same reached  same episode  "
        "max|da| at step 0"
    )
    print(
        f"{'JAX PopSAN':<44} {original['success'].mean():7.3f}  {'':12}  "
        f"{original['reached'].mean():7.3f}"
    )
    alive = original["alive"]
    for label, policy in policies:
        run = host_episodes(env_fns, policy, episodes, steps)
        same = {k: int(np.sum(run[k] == original[k])) for k in ("success", "reached")}
        equal_obs = np.all(run["obs"] == original["obs"], axis=-1) | ~alive
        traj = int(np.sum(np.all((run["alive"] == alive) & equal_obs, axis=0)))
        da = np.abs(run["action"][0] - original["action"][0]).max()
        print(
            f"{label:<44} {run['success'].mean():7.3f}  {same['success']:>6}/{episodes}     "
            f"{run['reached'].mean():7.3f}  {same['reached']:>6}/{episodes}     "
            f"{traj:>8}/{episodes}  {da:.1e}"
        )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("run", nargs="?", default=str(DEFAULT_RUN))
    p.add_argument("--episodes", type=int, default=8, help="rollouts for the observations")
    p.add_argument("--steps", type=int, default=150, help="steps of those rollouts")
    p.add_argument(
        "--closed-loop",
        type=int,
        default=32,
        metavar="N",
        help="also drive N episodes with each convention's policy (0: skip)",
    )
    args = p.parse_args()
    enable_compilation_cache()
    t0 = time.monotonic()
    loaded = load_run(args.run)
    batch = run_episodes(
        loaded.env, loaded.make_policy(), jax.random.PRNGKey(0), args.episodes, args.steps, True
    )
    obs = alive_observations(jax.device_get(batch))
    jax_forward = jax_reference(loaded)
    mean, spikes = jax_forward(obs)
    with tempfile.TemporaryDirectory() as tmp:
        path, side_path = write_nir(loaded, Path(tmp) / "policy.nir")
        graph, side = nir.read(path), json.loads(side_path.read_text())
    names = ["input", *side["layers"]]
    jax_spikes = dict(zip(names, (np.asarray(s) for s in spikes), strict=True))
    print(f"{args.run}: {obs.shape[0]} observations from real rollouts, T = {side['timesteps']}")
    print("spikes that differ from the JAX PopSAN's, per layer (share of neuron-steps)")
    print(f"{'simulator':<44} " + " ".join(f"{n:>15}" for n in side["layers"]) + "   max|da|")

    def report(label: str, sim: dict[str, np.ndarray], actions: np.ndarray) -> None:
        cells = []
        for n in side["layers"]:
            diff = int(np.sum(sim[n] != jax_spikes[n]))
            cells.append(f"{diff:>7} ({100 * diff / sim[n].size:5.2f}%)")
        print(f"{label:<44} " + " ".join(cells) + f"   {np.abs(actions - mean).max():.2e}")

    for conv in ref.CONVENTIONS:
        actions, sim = ref.run(graph, side, obs, conv)
        report(f"NumPy, {conv}", sim, actions)
    try:
        import norse  # optional (.[nir-sim])
    except ImportError as e:
        print(f"Norse: skipped ({e}; pip install -e '.[nir-sim]')")
    else:
        sim = norse_spikes(graph, side, jax_spikes["input"])
        actions = ref.decode(side, sim[names[-1]])
        report(f"Norse {norse.__version__} from_nir(dt={side['dt']:.6g})", sim, actions)
    if args.closed_loop:
        closed_loop(loaded, graph, side, jax_forward, args.closed_loop)
    print(f"({time.monotonic() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
