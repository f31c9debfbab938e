"""The run configuration: one frozen dataclass, derived sizes and up-front checks.

A :class:`RunConfig` fully describes a training run; it is saved as ``config.json`` in the run
directory and is all that :func:`popsan_jax.training.checkpoint.load_run` needs to rebuild the
env and the networks. No CLI parsing here; the presets and default recipes that train.py's
flags override are in :mod:`popsan_jax.recipes`.

Batch vocabulary (Brax's): each training iteration collects ``batch_size * num_minibatches``
sequences of ``unroll_length`` steps from ``num_envs`` parallel envs, i.e.
``batch_size * num_minibatches / num_envs`` consecutive unrolls per env, then runs
``num_updates_per_batch`` epochs of ``num_minibatches`` minibatches of ``batch_size`` sequences.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import typing
from pathlib import Path
from typing import Any

from popsan_jax.errors import ConfigError
from popsan_jax.io import write_json
from popsan_jax.schema import check_config

ACTORS = ("popsan", "mlp")
# franka_pick/franka_reach revision 2: the grasp that holds; 3: finger targets past the closed
# stop; 4: franka_pick charges the held cube's speed in the goal band; 5: franka_pick pays the
# lift as a ramp and the climb to the goal in proportion (envs/franka_pick.py)
CURRENT_ENV_REVISION = 5
LR_SCHEDULES = ("constant", "cosine")

# The actors' own defaults: the paper's PopSAN (pop 10 in and out, hidden 256-256, T = 5, its
# decoder drawn as PyTorch's Linear) and a 256-256 MLP with LeCun-normal layers. The default
# recipe starts the MLP's output layer smaller (recipes.ACTOR_RECIPES); a config without an
# init scale builds with 1.0, as these do.
POPSAN_DEFAULTS: dict[str, Any] = dict(
    hidden_sizes=(256, 256),
    encoder_pop_dim=10,
    decoder_pop_dim=10,
    timesteps=5,
    decoder_init_scale=1.0,
)
MLP_DEFAULTS: dict[str, Any] = dict(hidden_sizes=(256, 256), output_init_scale=1.0)
FLAG_HELP = "help"  # the dataclass field metadata key that makes a RunConfig field a flag


def _flag(default: Any, help_text: str) -> Any:
    """A RunConfig field that train.py exposes as ``--<name>`` with this help."""
    return dataclasses.field(default=default, metadata={FLAG_HELP: help_text})


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run (saved as ``config.json``).

    ``actor_kwargs`` are passed to the actor module (PopSAN: hidden_sizes, encoder_pop_dim,
    decoder_pop_dim, timesteps, decoder_init_scale; MLP: hidden_sizes, output_init_scale).
    ``episode_length`` None means the env's own.
    Fields declared with ``_flag`` are train.py's flags (``popsan_jax.cli`` derives them: name,
    type and help from here).
    """

    env: str = _flag("franka_pick", "task name: franka_pick | franka_reach")
    env_overrides: dict[str, Any] = dataclasses.field(default_factory=dict)
    # The env revision the run was made with (envs.<Env>.revision). A config.json without it
    # predates revisions and is revision 1; its env is rebuilt with envs.legacy_overrides.
    env_revision: int = CURRENT_ENV_REVISION
    actor: str = _flag("popsan", "policy network: popsan | mlp")
    actor_kwargs: dict[str, Any] = dataclasses.field(default_factory=lambda: dict(POPSAN_DEFAULTS))
    critic_hidden_sizes: tuple[int, ...] = _flag(
        (256, 256, 256), "critic hidden sizes, e.g. 256,256,256"
    )
    init_log_std: float = _flag(-0.5, "initial exploration log-std")
    obs_clip: float = _flag(3.0, "clip of the normalised observations")
    # Episodes of the untrained policy whose observations seed the normaliser before a fresh
    # run's first update (popsan_jax/training/iteration.py, prime_normalizer); not counted.
    prime_normalizer_episodes: int = _flag(
        0, "untrained-policy episodes that seed the obs normaliser before training (not counted)"
    )
    seed: int = _flag(0, "random seed")
    # Sizes.
    num_envs: int = _flag(256, "parallel training envs")
    total_env_steps: int = _flag(3_000_000, "training env steps")
    episode_length: int | None = _flag(None, "episode length in control steps (default: the env's)")
    unroll_length: int = _flag(10, "steps per unroll")
    batch_size: int = _flag(256, "sequences per minibatch")
    num_minibatches: int = _flag(8, "minibatches per epoch")
    num_updates_per_batch: int = _flag(4, "epochs over each batch")
    # Optimiser.
    actor_lr: float = _flag(3e-4, "actor learning rate")
    critic_lr: float = _flag(1e-3, "critic learning rate")
    lr_schedule: str = _flag("constant", "constant | cosine")
    max_grad_norm: float | None = _flag(1.0, "global gradient-norm clip")
    # Clip the actor's and the critic's gradients by max_grad_norm each, not by their joint
    # norm: a critic that starts far from this reward (a warm start) has gradients that set the
    # joint clip, so the actor's step size then follows the critic's loss (docs/design.md,
    # "Guards at the stage change").
    clip_per_network: bool = _flag(
        False, "clip the actor's and the critic's gradients each by max_grad_norm: true | false"
    )
    # KL guard (popsan_jax/training/iteration.py): an iteration's SGD stops at its first
    # minibatch whose policy, before its step, is further than max_kl (mean KL per action
    # distribution) from the policy that collected the data, and keeps the last parameters
    # that were measured within it. 0: off.
    max_kl: float = _flag(
        0.0, "stop an iteration's SGD at the first minibatch whose KL exceeds this (0: off)"
    )
    # PPO loss.
    entropy_cost: float = _flag(1e-3, "entropy bonus coefficient")
    discounting: float = _flag(0.97, "discount gamma")
    gae_lambda: float = _flag(0.95, "GAE lambda")
    clipping_epsilon: float = _flag(0.2, "PPO clip")
    reward_scaling: float = _flag(1.0, "reward multiplier")
    normalize_advantage: bool = True
    vf_coefficient: float = 0.5
    # Synaptic-operation penalty (PopSAN only, popsan_jax/training/loss.py): the loss gains
    # sop_cost per 1000 SOPs per inference above sop_budget. 0 = PPO's loss alone.
    sop_cost: float = _flag(
        0.0, "PopSAN loss penalty per 1000 synaptic ops per inference over budget"
    )
    sop_budget: float = _flag(0.0, "synaptic ops per inference the penalty allows for free")
    # Warm start: policy, critic and observation normaliser from another run's checkpoint
    # ("best", "last" or an env-step count); fresh optimiser, steps counted from 0.
    init_from: str | None = _flag(
        None, "start from this run's networks and normaliser (fresh optimiser)"
    )
    init_checkpoint: str = _flag(
        "best", "which checkpoint of --init-from: best | last | env-step count"
    )
    # Critic warm-up: a started critic (init_from, or the warm-up stage's) learnt another
    # reward, and PPO's first updates on its advantages can undo the policy it starts from.
    # The actor's learning rate is 0 for the first critic_warmup_env_steps (whole iterations)
    # while the critic learns this reward; actor_lr's schedule then runs over the rest.
    critic_warmup_env_steps: int = _flag(
        0, "env steps at the start in which only the critic learns (actor lr 0)"
    )
    # A frozen normaliser keeps the observation statistics the run started from (init_from's,
    # or the warm-up stage's for the run's own stage). A PopSAN's encoder maps a shifted
    # normalised input to other spikes, so a moving normaliser moves its policy without any
    # actor update (docs/design.md, "A frozen normaliser").
    freeze_normalizer: bool = _flag(
        False, "keep the started observation normaliser fixed: true | false (needs a warm start)"
    )
    # Warm-up stage (popsan_jax/training/stages.py): first warmup_env_steps on the env with
    # warmup_env_overrides (a gentler variant of the task) at warmup_actor_lr, in RUN/warmup/;
    # then this config's own stage starts from its last checkpoint (fresh optimiser).
    warmup_env_steps: int = _flag(0, "env steps of a warm-up stage before the run's own (0: none)")
    warmup_env_overrides: dict[str, Any] = dataclasses.field(default_factory=dict)
    warmup_actor_lr: float = _flag(1e-3, "actor learning rate of the warm-up stage")
    warmup_num_evals: int = _flag(24, "evaluations (and checkpoints) of the warm-up stage")
    # The warm-up stage's clip_per_network: a warm-up starts from scratch, with no critic
    # fitted to another reward, which is what the per-network clip is against.
    warmup_clip_per_network: bool = _flag(
        False, "the warm-up stage's clip_per_network: true | false"
    )
    # Ending early (popsan_jax/training/loop.py): a run ends after its first training
    # evaluation whose success rate reaches end_at_success (0: never); its last checkpoint is
    # that evaluation's. warmup_end_at_success is the warm-up stage's: the run's own stage then
    # starts as soon as the warm-up policy holds the cube (docs/design.md, "Ending the warm-up").
    end_at_success: float = _flag(
        0.0, "end the run at its first evaluation with at least this success rate (0: never)"
    )
    warmup_end_at_success: float = _flag(
        0.0, "end the warm-up stage at its first evaluation with at least this success (0: never)"
    )
    # Evaluation, checkpoints, logging.
    num_evals: int = _flag(10, "evaluations (and checkpoints) over the run")
    num_eval_envs: int = _flag(64, "episodes per evaluation")
    keep_every_n_evals: int = _flag(5, "keep every N-th checkpoint besides the last and the best")
    wandb: bool = False

    # ---- derived sizes -------------------------------------------------------------------
    @property
    def sequences_per_iteration(self) -> int:
        return self.batch_size * self.num_minibatches

    @property
    def unrolls_per_iteration(self) -> int:
        """Consecutive unrolls of every env per iteration."""
        return self.sequences_per_iteration // self.num_envs

    @property
    def env_steps_per_iteration(self) -> int:
        return self.sequences_per_iteration * self.unroll_length

    @property
    def num_iterations(self) -> int:
        return max(1, math.ceil(self.total_env_steps / self.env_steps_per_iteration))

    @property
    def critic_warmup_iterations(self) -> int:
        """Iterations at the start in which the actor does not learn."""
        return math.ceil(self.critic_warmup_env_steps / self.env_steps_per_iteration)

    @property
    def eval_interval(self) -> int:
        """Iterations between evaluations (the last iteration is always evaluated)."""
        return max(1, self.num_iterations // max(1, self.num_evals))

    def validate(self, device_count: int = 1) -> None:
        """Raise :class:`ConfigError` (one line) for an impossible configuration on
        ``device_count`` devices (all devices of all processes: the sizes are global)."""
        if self.actor not in ACTORS:
            raise ConfigError(f"unknown actor {self.actor!r}; choose one of {', '.join(ACTORS)}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ConfigError(
                f"unknown lr schedule {self.lr_schedule!r}; choose one of {LR_SCHEDULES}"
            )
        positive = dict(
            num_envs=self.num_envs,
            total_env_steps=self.total_env_steps,
            unroll_length=self.unroll_length,
            batch_size=self.batch_size,
            num_minibatches=self.num_minibatches,
            num_updates_per_batch=self.num_updates_per_batch,
            num_eval_envs=self.num_eval_envs,
            keep_every_n_evals=self.keep_every_n_evals,
            num_evals=self.num_evals,
        )
        for name, value in positive.items():
            if value < 1:
                raise ConfigError(f"{name} must be >= 1, got {value}")
        if self.prime_normalizer_episodes < 0:
            raise ConfigError(
                f"prime_normalizer_episodes must be >= 0, got {self.prime_normalizer_episodes}"
            )
        if self.warmup_env_steps < 0:
            raise ConfigError(f"warmup_env_steps must be >= 0, got {self.warmup_env_steps}")
        if self.warmup_env_steps and (self.warmup_num_evals < 1 or not self.warmup_actor_lr > 0):
            raise ConfigError("a warm-up needs warmup_num_evals >= 1 and warmup_actor_lr > 0")
        if self.max_grad_norm is not None and not self.max_grad_norm > 0:
            raise ConfigError(
                f"max_grad_norm must be > 0 (None: no clip), got {self.max_grad_norm}"
            )
        if (self.clip_per_network or self.warmup_clip_per_network) and self.max_grad_norm is None:
            raise ConfigError("clip_per_network clips by max_grad_norm, which is None (no clip)")
        if not (self.max_kl >= 0 and math.isfinite(self.max_kl)):
            raise ConfigError(f"max_kl must be a finite number >= 0 (0: off), got {self.max_kl}")
        for name in ("end_at_success", "warmup_end_at_success"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.critic_warmup_env_steps < 0 or self.critic_warmup_iterations >= self.num_iterations:
            raise ConfigError(
                f"critic_warmup_env_steps must be >= 0 and leave the actor at least one "
                f"iteration: got {self.critic_warmup_env_steps} of {self.total_env_steps} "
                f"env steps ({self.env_steps_per_iteration} per iteration)"
            )
        if self.freeze_normalizer and not (self.init_from or self.warmup_env_steps):
            raise ConfigError(
                "freeze_normalizer needs a started normaliser: --init-from or a warm-up stage"
            )
        if self.episode_length is not None and self.episode_length < 1:
            raise ConfigError(f"episode_length must be >= 1, got {self.episode_length}")
        for name in ("actor_lr", "critic_lr", "obs_clip"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.sop_cost < 0 or self.sop_budget < 0:
            raise ConfigError("sop_cost and sop_budget must be >= 0")
        if self.sop_cost and self.actor != "popsan":
            raise ConfigError(f"sop_cost charges spikes; the {self.actor!r} actor has none")
        if not (self.init_checkpoint in ("best", "last") or self.init_checkpoint.isdigit()):
            raise ConfigError(
                f"init_checkpoint must be 'best', 'last' or an env-step count, "
                f"got {self.init_checkpoint!r}"
            )
        if not 0 < self.discounting <= 1 or not 0 <= self.gae_lambda <= 1:
            raise ConfigError("discounting must be in (0, 1] and gae_lambda in [0, 1]")
        if self.sequences_per_iteration % self.num_envs:
            raise ConfigError(
                f"batch_size * num_minibatches = {self.batch_size} * {self.num_minibatches} = "
                f"{self.sequences_per_iteration} must be divisible by num_envs = {self.num_envs}"
            )
        if self.num_envs % device_count:
            raise ConfigError(
                f"num_envs = {self.num_envs} must be divisible by the {device_count} devices "
                f"(all devices of all processes)"
            )
        if self.batch_size % device_count:
            raise ConfigError(
                f"batch_size = {self.batch_size} must be divisible by the {device_count} devices "
                f"(all devices of all processes)"
            )

    # ---- JSON ----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self, path: str | os.PathLike) -> None:
        """Write atomically, so a crash never leaves half a config."""
        write_json(path, self.to_dict())

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "") -> RunConfig:
        """The config of ``data``; unknown keys and wrong types (popsan_jax/schema.py) raise
        ConfigError, its message prefixed with ``where`` (the file read)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"{where}unknown config keys: {', '.join(unknown)}")
        check_config(data, typing.get_type_hints(cls), where)
        data = dict(data)
        if "critic_hidden_sizes" in data:
            data["critic_hidden_sizes"] = tuple(data["critic_hidden_sizes"])
        if "actor_kwargs" in data:
            data["actor_kwargs"] = tuplify(data["actor_kwargs"])
        return cls(**data)

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> RunConfig:
        """Read ``config.json``; a missing or unreadable file raises ConfigError."""
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:  # ValueError: bad JSON, or bytes that are not UTF-8
            raise ConfigError(f"cannot read run config {path}: {e}") from e
        if not isinstance(data, dict):
            raise ConfigError(f"run config {path} is not a JSON object")
        data.setdefault("env_revision", 1)  # written before env revisions existed
        return cls.from_dict(data, f"{path}: ")

    def replace(self, **changes: Any) -> RunConfig:
        return dataclasses.replace(self, **changes)


def tuplify(kwargs: dict[str, Any]) -> dict[str, Any]:
    # JSON turns tuples into lists; flax module fields want hashable tuples.
    return {k: tuple(v) if isinstance(v, list) else v for k, v in kwargs.items()}
