"""Run logging: ``metrics.jsonl``, TensorBoard, optional Weights & Biases, and a progress bar.

One :class:`RunLogger` per run; every record is ``{"kind": "train"|"eval", "env_steps", "wall_s",
...}``. The progress bar writes to stderr (tqdm) so a user always sees env steps, steps/s, ETA and
the latest success rate. Nothing here runs at import time.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

from tensorboardX import SummaryWriter
from tqdm import tqdm

from popsan_jax.errors import ConfigError
from popsan_jax.io import read_jsonl, write_jsonl
from popsan_jax.schema import check_metrics_record

METRICS = "metrics.jsonl"


def wandb_available() -> bool:
    return importlib.util.find_spec("wandb") is not None


def _drop_records_after(run_dir: Path, env_steps: int) -> None:
    """Remove records past the checkpoint a run resumes from: it logs those steps again.

    A run killed between checkpoints has logged iterations its checkpoint does not hold; keeping
    them would put two records at the same step in the curves. A line cut short by the kill goes
    too (``read_metrics`` skips it). Rewritten atomically.
    """
    kept = [r for r in read_metrics(run_dir) if r["env_steps"] <= env_steps]
    write_jsonl(run_dir / METRICS, kept)


class RunLogger:
    """Writes metrics of one run; ``initial_steps`` > 0 when resuming (appends to the files),
    ``restart`` when a run without a checkpoint is trained again (its old records go)."""

    def __init__(
        self,
        run_dir: str | os.PathLike,
        total_env_steps: int,
        initial_steps: int = 0,
        config: dict[str, Any] | None = None,
        use_wandb: bool = False,
        progress: bool = True,
        restart: bool = False,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.start = time.monotonic()
        if initial_steps > 0 or restart:  # restart: trained again from step 0, nothing kept
            _drop_records_after(self.run_dir, initial_steps if initial_steps > 0 else -1)
        self._jsonl = open(self.run_dir / METRICS, "a", buffering=1)
        # purge_step: TensorBoard hides the points an earlier, killed process logged past the
        # checkpoint, as _drop_records_after does for the JSONL.
        purge = initial_steps + 1 if initial_steps > 0 else (0 if restart else None)
        self._tb = SummaryWriter(str(self.run_dir / "tb"), purge_step=purge)
        self._wandb = None
        if use_wandb:
            if not wandb_available():
                raise ConfigError("--wandb needs the wandb package: pip install wandb")
            import wandb  # optional dependency, present only when asked for

            mode = "offline" if not os.environ.get("WANDB_API_KEY") else None
            self._wandb = wandb.init(
                project="popsan-jax",
                name=self.run_dir.name,
                dir=str(self.run_dir),
                config=config,
                mode=mode,
                resume="allow",
            )
        self._bar = None
        if progress:
            self._bar = tqdm(
                total=total_env_steps,
                initial=min(initial_steps, total_env_steps),
                unit="step",
                unit_scale=True,
                dynamic_ncols=True,
                file=sys.stderr,
            )
        self._steps = initial_steps
        self._success: float | None = None
        self._post: dict[str, str] = {}

    def log(self, kind: str, env_steps: int, metrics: dict[str, float]) -> dict[str, Any]:
        """Append one record to every sink and advance the progress bar."""
        record: dict[str, Any] = {
            "kind": kind,
            "env_steps": int(env_steps),
            "wall_s": round(time.monotonic() - self.start, 3),
        }
        record.update({k: _plain(v) for k, v in metrics.items()})
        self._jsonl.write(json.dumps(record) + "\n")
        for name, value in record.items():
            if name not in ("kind", "env_steps") and isinstance(value, int | float):
                tag = name if name in ("wall_s",) else f"{kind}/{name}"
                self._tb.add_scalar(tag, value, int(env_steps))
        if self._wandb is not None:
            self._wandb.log({f"{kind}/{k}": v for k, v in record.items() if k != "kind"})
        if kind == "eval" and "success_rate" in record:
            self._success = record["success_rate"]
        if self._bar is not None:
            self._bar.update(max(0, int(env_steps) - self._steps))
            post = self._post  # eval records keep the last train figures on the bar
            if "steps_per_s" in record and kind == "train":
                post["sps"] = f"{record['steps_per_s']:.0f}"
            if self._success is not None:
                post["success"] = f"{self._success:.2f}"
            if "loss/total" in record:
                post["loss"] = f"{record['loss/total']:.3g}"
            self._bar.set_postfix(post, refresh=True)
        self._steps = max(self._steps, int(env_steps))
        return record

    def message(self, text: str) -> None:
        """A status line that does not break the progress bar."""
        if self._bar is not None:
            self._bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        self._tb.flush()
        self._tb.close()
        self._jsonl.close()
        if self._wandb is not None:
            self._wandb.finish()


class SilentLogger:
    """The logger of every process but 0 under jax.distributed: it writes nothing."""

    def log(self, kind: str, env_steps: int, metrics: dict[str, float]) -> dict[str, Any]:
        return {"kind": kind, "env_steps": int(env_steps), **metrics}

    def message(self, text: str) -> None:
        pass

    def close(self) -> None:
        pass


def _plain(value: Any) -> Any:
    """JSON-safe Python scalars (NaN/inf become strings so the JSONL stays valid JSON)."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        return value
    if math.isfinite(value):
        return value
    return str(value)


def read_metrics(run_dir: str | os.PathLike, kind: str | None = None) -> list[dict[str, Any]]:
    """All records of ``metrics.jsonl`` (optionally of one kind; none when there is no file),
    read under :func:`popsan_jax.io.read_jsonl`'s torn-line rule; a record off its schema
    (popsan_jax/schema.py) is a CheckpointError naming its line."""
    path = Path(run_dir) / METRICS
    if not path.exists():
        return []
    records = read_jsonl(path, check_metrics_record)
    return [r for r in records if kind is None or r.get("kind") == kind]
