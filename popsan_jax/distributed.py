"""Training over several processes with ``jax.distributed`` (one per host or per GPU).

Data parallel as Brax does it: ``num_envs`` and the batch sizes are global; every process steps
its own rows of envs, gradients and the observation normaliser are averaged over all devices of
all processes (the iteration's ``pmean``/``psum`` span them once ``jax.distributed`` is
initialised), and process 0 alone resolves the config, owns the run directory (lock, config,
metrics, checkpoints) and evaluates. Every process draws the same keys from the same seed and
splits them over all global devices, so 2 processes x 1 device step the same envs with the same
keys as 1 process x 2 devices.

Process 0 shares what it alone computes (config, run directory, an error) through the
coordination service's key-value store, ``jax._src.distributed.global_state.client`` (a private
API; Orbax uses it the same way), and state through a collective
(``multihost_utils.broadcast_one_to_all``).

Where a process stands in the cluster comes from train.py's flags (``--coordinator HOST:PORT
--num-processes N --process-id I``) or, without them, from the environment
(:func:`resolve_cluster`). :func:`initialize` must run before anything creates a JAX backend.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import re
from collections.abc import Callable, Mapping
from typing import Any

import jax
import numpy as np
from jax._src import distributed as jax_distributed  # the coordination client (private API)
from jax.experimental import multihost_utils

from popsan_jax.errors import UserError

HEARTBEAT_TIMEOUT_S = 100  # jax.distributed's own default
WAIT_S = 3600  # how long processes wait for process 0 at a barrier (evaluation, checkpoint)
_ADDRESS = re.compile(r"\[?[A-Za-z0-9_.:-]+\]?:\d{1,5}")
_barriers = itertools.count()
_shares = itertools.count()


class PeerLostError(UserError):
    """Another process of the run stopped or became unreachable."""


@dataclasses.dataclass(frozen=True)
class Cluster:
    """How this process joins the run; None fields are left to JAX's cluster detection."""

    source: str  # "flags", "SLURM", "Open MPI", "JAX_COORDINATOR_ADDRESS"
    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    heartbeat_timeout: int = HEARTBEAT_TIMEOUT_S


def _env_int(environ: Mapping[str, str], name: str) -> int | None:
    value = environ.get(name, "").strip()
    if not value:
        return None
    try:
        return int(value)
    except ValueError:
        raise UserError(f"{name}={value!r} in the environment is not an integer") from None


def resolve_cluster(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    heartbeat_timeout: int | None = None,
    environ: Mapping[str, str] | None = None,
) -> Cluster | None:
    """This process's place in a multi-process run, or None for a single process.

    The flags win; all three go together. Without them: SLURM (``SLURM_NTASKS`` > 1, launched
    with ``srun``), Open MPI (``OMPI_COMM_WORLD_SIZE`` > 1) and ``JAX_COORDINATOR_ADDRESS`` (with
    ``JAX_NUM_PROCESSES``/``JAX_PROCESS_ID`` where set) leave the rest to JAX's own cluster
    detection. Bad values raise UserError (one line).
    """
    environ = os.environ if environ is None else environ
    heartbeat = HEARTBEAT_TIMEOUT_S if heartbeat_timeout is None else heartbeat_timeout
    if heartbeat < 1:
        raise UserError(f"--heartbeat-timeout must be >= 1 s, got {heartbeat}")
    flags = {"--coordinator": coordinator, "--num-processes": num_processes}
    flags["--process-id"] = process_id
    if any(v is not None for v in flags.values()):
        missing = [k for k, v in flags.items() if v is None]
        if missing:
            raise UserError(
                f"--coordinator, --num-processes and --process-id go together; missing "
                f"{', '.join(missing)}"
            )
        return _checked(Cluster("flags", coordinator, num_processes, process_id, heartbeat))
    if (_env_int(environ, "SLURM_NTASKS") or 1) > 1:
        return Cluster("SLURM", heartbeat_timeout=heartbeat)
    if (_env_int(environ, "OMPI_COMM_WORLD_SIZE") or 1) > 1:
        return Cluster("Open MPI", heartbeat_timeout=heartbeat)
    if environ.get("JAX_COORDINATOR_ADDRESS"):
        n, i = _env_int(environ, "JAX_NUM_PROCESSES"), _env_int(environ, "JAX_PROCESS_ID")
        address = environ["JAX_COORDINATOR_ADDRESS"]
        cluster = Cluster("JAX_COORDINATOR_ADDRESS", address, n, i, heartbeat)
        return _checked(cluster) if None not in (n, i) else cluster
    return None


def _checked(c: Cluster) -> Cluster:
    if not _ADDRESS.fullmatch(c.coordinator or ""):
        raise UserError(f"--coordinator must be HOST:PORT, got {c.coordinator!r}")
    if c.num_processes < 1 or not 0 <= c.process_id < c.num_processes:
        raise UserError(
            f"--process-id must be in 0..{c.num_processes - 1} (--num-processes "
            f"{c.num_processes}), got {c.process_id}"
        )
    return c


def initialize(cluster: Cluster) -> None:
    """``jax.distributed.initialize`` for ``cluster``; before anything creates a JAX backend.

    When the coordination service finds a process dead or silent for ``heartbeat_timeout`` s,
    JAX's client ends the others with its own fatal log (exit 134): jaxlib 0.7.0's client takes
    a callback for it, but cannot hand its status to Python (std::bad_cast). A collective with a
    dead peer fails sooner, in seconds, and train.py turns that into one line and exit 3.
    """
    jax.distributed.initialize(
        coordinator_address=cluster.coordinator,
        num_processes=cluster.num_processes,
        process_id=cluster.process_id,
        heartbeat_timeout_seconds=cluster.heartbeat_timeout,
    )


def is_main() -> bool:
    """Whether this process owns the run directory, evaluates and logs (process 0)."""
    return jax.process_index() == 0


def local_rows(count: int) -> np.ndarray:
    """Indices of this process's rows when ``count`` rows are split over all global devices in
    ``jax.devices()`` order (pmap's axis order); ``count`` divides by the device count."""
    per = count // jax.device_count()
    index = {d.id: i for i, d in enumerate(jax.devices())}
    return np.concatenate([np.arange(per) + index[d.id] * per for d in jax.local_devices()])


def local_slice(keys: jax.Array) -> jax.Array:
    """``keys [N, ...]`` -> ``[local devices, N / global devices, ...]``: this process's rows."""
    rows = local_rows(keys.shape[0])
    return keys[rows].reshape((jax.local_device_count(), -1) + keys.shape[1:])


def device_keys(key: jax.Array) -> jax.Array:
    """``[local devices, 2]``: this process's rows of ``key`` split over all global devices."""
    return local_slice(jax.random.split(key, jax.device_count()))[:, 0]


def processes_note() -> str:
    """`` over N processes`` under jax.distributed, else ''."""
    return f" over {jax.process_count()} processes" if jax.process_count() > 1 else ""


def _client() -> Any:
    return jax_distributed.global_state.client


def share_from_main(name: str, compute: Callable[[], Any]) -> Any:
    """``compute()`` on process 0, its JSON-able result on every process.

    An error raised on process 0 is raised on every other process as a UserError with the same
    line (or, not being a UserError, naming it), so all of them stop instead of waiting.
    """
    if jax.process_count() == 1:
        return compute()
    # numbered like the barriers: every process shares in the same order, and a name may recur
    # (each evaluation; both stages of a run with a warm-up)
    key = f"popsan_jax/{name}/{next(_shares)}"
    if not is_main():
        message = json.loads(_client().blocking_key_value_get(key, WAIT_S * 1000))
        if "error" in message:
            raise UserError(message["error"])
        return message["value"]
    try:
        value = compute()
    except Exception as e:
        text = str(e) if isinstance(e, UserError) else f"process 0 stopped: {type(e).__name__}: {e}"
        _client().key_value_set(key, json.dumps({"error": text}))
        raise
    _client().key_value_set(key, json.dumps({"value": value}))
    return value


def share_value_from_main(name: str, value: Any) -> Any:
    """Process 0's ``value`` (JSON-able) on every process; the others' ``value`` is ignored."""
    return share_from_main(name, lambda: value)


def barrier(name: str, timeout_s: float = WAIT_S) -> None:
    """Every process waits here until all arrive (the coordination service; no collective)."""
    if jax.process_count() > 1:
        _client().wait_at_barrier(f"popsan_jax/{name}/{next(_barriers)}", int(timeout_s * 1000))


def broadcast_from_main(tree: Any) -> Any:
    """Process 0's ``tree`` on every process, as NumPy arrays (a psum over all devices)."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    return multihost_utils.broadcast_one_to_all(tree)


def peer_lost_message(run_dir: Any) -> str:
    """The one line a process prints when a collective or barrier failed under it."""
    kept = f"the last checkpoint in {run_dir} is kept" if run_dir else "nothing was written"
    return (
        f"process {jax.process_index()} of {jax.process_count()}: another process stopped or "
        f"became unreachable (a collective or barrier failed); {kept}"
    )


def peer_failure(e: BaseException) -> bool:
    """Whether ``e`` is how a collective, barrier or key-value read fails when a peer is gone."""
    return isinstance(e, jax.errors.JaxRuntimeError)
