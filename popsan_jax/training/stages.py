"""A run with a warm-up stage: first ``warmup_env_steps`` on a gentler variant of the env, then
the run's own stage, started from the warm-up's last checkpoint.

Layout of such a run ``RUN``::

    RUN/config.json      the run's config as given (its warmup_* fields included); written first
    RUN/warmup/          a complete run directory of the warm-up stage (its own config.json,
                         metrics.jsonl, checkpoints/): env_overrides + warmup_env_overrides,
                         warmup_actor_lr, warmup_num_evals, warmup_clip_per_network,
                         warmup_env_steps (or fewer: warmup_end_at_success ends it at an
                         evaluation that reaches it)
    RUN/metrics.jsonl, RUN/checkpoints/   the run's own stage (env steps counted from 0)

Everything that reads a finished run (eval.py, load_run) reads ``RUN``: its final checkpoint is
the policy after both stages. ``train.py --resume RUN`` resumes whichever stage was running.
Why franka_pick warms up: docs/design.md, "A gentle grasp first".
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax

import envs
from popsan_jax import distributed
from popsan_jax.config import RunConfig
from popsan_jax.training.checkpoint_index import CONFIG, WARMUP
from popsan_jax.training.loop import TrainResult, train
from popsan_jax.training.run_log import METRICS


def warmup_config(config: RunConfig) -> RunConfig:
    """The config of ``config``'s warm-up stage (a run without a warm-up of its own)."""
    # the user's overrides win, key by key
    env_overrides = envs.merge_overrides(config.warmup_env_overrides, config.env_overrides)
    return config.replace(
        env_overrides=env_overrides,
        total_env_steps=config.warmup_env_steps,
        actor_lr=config.warmup_actor_lr,
        num_evals=config.warmup_num_evals,
        warmup_env_steps=0,
        warmup_env_overrides={},
        end_at_success=config.warmup_end_at_success,
        warmup_end_at_success=0.0,
        clip_per_network=config.warmup_clip_per_network,
        warmup_clip_per_network=False,
        critic_warmup_env_steps=0,  # the warm-up stage starts from scratch
        freeze_normalizer=False,
    )


def train_run(
    config: RunConfig, run_dir: str | Path, *, resume: bool = False, **kwargs: Any
) -> TrainResult:
    """Train ``config`` into ``run_dir``: its warm-up stage first when it has one (resumed if
    ``resume`` and it was begun), then its own stage. ``kwargs`` go to :func:`train`."""
    run_dir = Path(run_dir)
    config.validate(jax.device_count())  # before the run directory is made (sizes are global)
    if not config.warmup_env_steps:
        return train(config, run_dir, resume=resume, **kwargs)

    def begin() -> dict[str, bool]:
        """Process 0: write the run's config (so an interrupted warm-up can be resumed) and say
        which stages were begun."""
        if not resume:
            run_dir.mkdir(parents=True, exist_ok=False)
            config.to_json(run_dir / CONFIG)
        return {
            "warmup": resume and (run_dir / WARMUP / CONFIG).is_file(),
            "own": resume and (run_dir / METRICS).is_file(),
        }

    begun = distributed.share_from_main("stages", begin)
    if not begun["own"]:  # a finished warm-up, resumed, returns at once (before compiling)
        train(warmup_config(config), run_dir / WARMUP, resume=begun["warmup"], **kwargs)
    return train(config, run_dir, resume=begun["own"], **kwargs)
