"""Training over two processes with jax.distributed on localhost (issue 21), and how a process
finds its place in a cluster (flags, SLURM, Open MPI, JAX's variables)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from popsan_jax.distributed import Cluster, resolve_cluster
from popsan_jax.errors import UserError
from popsan_jax.training import checkpoint_index

ROOT = Path(__file__).resolve().parents[2]
WORKER = Path(__file__).with_name("_dist_worker.py")
# Hang guards, not timings: the toy env's processes start, compile and finish in well under a
# minute on an idle 2-core box.
HANG_GUARD_S = 600
# The smoke preset with tiny networks: 3 iterations, a checkpoint after each. The config names
# franka_reach; _dist_worker.py trains the toy env in its place (no MJX compile).
TINY = [
    "--env", "franka_reach", "--preset", "smoke", "--actor", "mlp", "--hidden-sizes", "16,16",
    "--critic-hidden-sizes", "16,16", "--num-eval-envs", "4", "--no-progress",
]  # fmt: skip


# ---- where a process stands --------------------------------------------------------------
def test_flags_win_and_go_together():
    env = {"SLURM_NTASKS": "4"}
    assert resolve_cluster("10.0.0.1:1234", 2, 1, None, env) == Cluster(
        "flags", "10.0.0.1:1234", 2, 1
    )
    with pytest.raises(UserError, match="go together; missing --num-processes, --process-id"):
        resolve_cluster("10.0.0.1:1234", None, None, None, {})
    with pytest.raises(UserError, match=r"--process-id must be in 0..1 \(--num-processes 2\)"):
        resolve_cluster("h:1", 2, 2, None, {})
    with pytest.raises(UserError, match="HOST:PORT"):
        resolve_cluster("nohost", 2, 0, None, {})
    with pytest.raises(UserError, match="--heartbeat-timeout must be >= 1"):
        resolve_cluster(None, None, None, 0, {})


def test_cluster_from_the_environment():
    assert resolve_cluster(environ={}) is None
    assert resolve_cluster(environ={"SLURM_NTASKS": "1", "OMPI_COMM_WORLD_SIZE": "1"}) is None
    assert resolve_cluster(environ={"SLURM_NTASKS": "8"}) == Cluster("SLURM")
    assert resolve_cluster(environ={"OMPI_COMM_WORLD_SIZE": "2"}).source == "Open MPI"
    jax_vars = {"JAX_COORDINATOR_ADDRESS": "h:99", "JAX_NUM_PROCESSES": "3", "JAX_PROCESS_ID": "2"}
    assert resolve_cluster(heartbeat_timeout=7, environ=jax_vars) == Cluster(
        "JAX_COORDINATOR_ADDRESS", "h:99", 3, 2, 7
    )
    # the address alone: JAX's own detection supplies the rest
    assert resolve_cluster(environ={"JAX_COORDINATOR_ADDRESS": "h:99"}).num_processes is None
    with pytest.raises(UserError, match="SLURM_NTASKS='x' in the environment is not an integer"):
        resolve_cluster(environ={"SLURM_NTASKS": "x"})


# ---- two processes on localhost ----------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(devices: int = 1) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "OMPI_", "JAX_"))}
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    return env


def _start(argv: list[str], log: Path, devices: int = 1) -> subprocess.Popen:
    """``python argv`` from the repository root, stderr to ``log``."""
    with open(log, "w") as err:  # the child keeps its own copy
        return subprocess.Popen(
            [sys.executable, *argv],
            cwd=ROOT,
            env=_env(devices),
            stdout=subprocess.DEVNULL,
            stderr=err,
        )


def _launch(command: list[str], port: int, log: Path, extra: list[str]) -> list[subprocess.Popen]:
    cluster = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", "2"]
    return [
        _start([*command, *extra, *cluster, "--process-id", str(i)], log.with_suffix(f".p{i}.log"))
        for i in range(2)
    ]


def _wait(procs: list[subprocess.Popen], timeout: float) -> list[int]:
    deadline = time.monotonic() + timeout
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(timeout=max(1.0, deadline - time.monotonic())))
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            pytest.fail(f"a process was still running after {timeout} s")
    return codes


def _states(paths: list[Path]) -> list[list[np.ndarray]]:
    loaded = [np.load(p) for p in paths]
    return [[f[k] for k in sorted(f.files, key=lambda k: int(k.split("_")[1]))] for f in loaded]


@pytest.mark.slow
def test_two_processes_lose_one_resume_and_match_one_process(tmp_path):
    runs = tmp_path / "runs"
    run_dir, ref_dir = runs / "run", runs / "ref"
    # 1. a fresh 2-process run through train.py; process 1 dies (SIGKILL) once the first
    # checkpoint after step 0 is written
    port = _free_port()
    cluster = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", "2"]
    flags = [*TINY, "--runs-dir", str(runs), "--name", "run", *cluster]
    procs = [
        _start([str(WORKER), "cli", *flags, "--process-id", "0"], tmp_path / "a.p0.log"),
        _start(
            [str(WORKER), "cli", "--die-after-first-checkpoint", *flags, "--process-id", "1"],
            tmp_path / "a.p1.log",
        ),
    ]
    code1 = _wait(procs[1:], timeout=HANG_GUARD_S)[0]
    assert code1 == -signal.SIGKILL, (tmp_path / "a.p1.log").read_text()[-3000:]
    t0 = time.monotonic()
    code = _wait(procs[:1], timeout=120)[0]
    err = (tmp_path / "a.p0.log").read_text()
    assert code == 3, err[-3000:]
    assert "error: process 0 of 2: another process stopped or became unreachable" in err
    assert f"the last checkpoint in {run_dir} is kept" in err
    print(f"process 0 stopped {time.monotonic() - t0:.1f} s after the kill")
    assert not (run_dir / "lock").exists()
    index = checkpoint_index.read_index(run_dir)
    assert int(index["last"]) == 1280  # the first iteration's checkpoint, not a later one
    assert all(checkpoint_index.verify_checkpoint(run_dir, index, e) for e in index["checkpoints"])
    shutil.copytree(run_dir, ref_dir)

    # 2. the 2-process resume to the end, and 1 process x 2 devices from the same checkpoint,
    # side by side
    out_two, out_one = tmp_path / "two", tmp_path / "one"
    out_two.mkdir()
    out_one.mkdir()
    resume = ["--no-progress", "--resume"]
    procs = _launch(
        [str(WORKER), "state", str(out_two)], _free_port(), tmp_path / "b", [*resume, str(run_dir)]
    )
    one_log = tmp_path / "c.log"
    one = _start([str(WORKER), "state", str(out_one), *resume, str(ref_dir)], one_log, devices=2)
    codes = _wait([*procs, one], timeout=HANG_GUARD_S)
    assert codes[:2] == [0, 0], (tmp_path / "b.p0.log").read_text()[-3000:]
    assert codes[2] == 0, one_log.read_text()[-3000:]

    # Bit-equal: every device runs the same HLO on the same env rows and keys in both layouts,
    # and the only cross-device reductions are 2-term psums, whose sum does not depend on order.
    two0, two1, ref = _states(
        [out_two / "state_p0.npz", out_two / "state_p1.npz", out_one / "state_p0.npz"]
    )
    assert len(two0) == len(ref) > 10
    for a, b, c in zip(two0, two1, ref, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    assert int(checkpoint_index.read_index(run_dir)["last"]) == 3 * 1280
