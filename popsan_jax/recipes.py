"""Presets and default recipes: what train.py's flags override.

Order (:func:`resolve_config`): the backend's defaults (the CPU recipe, scaled on an
accelerator), then the env's own recipe (franka_pick's warm-up curriculum) and the actor's
(``ACTOR_RECIPES``, small output layers) when no preset is given, then the preset, then explicit
flags. A preset is a whole recipe of its own, so the env's and the actor's recipes do not apply
under one.
"""

from __future__ import annotations

from typing import Any

from popsan_jax.config import ACTORS, MLP_DEFAULTS, POPSAN_DEFAULTS, RunConfig, tuplify
from popsan_jax.errors import ConfigError

# Presets: partial configs applied over the backend defaults; explicit flags override both.
PRESETS: dict[str, dict[str, Any]] = {
    # A complete tiny run (train, eval, checkpoint) in about a minute on a 2-core CPU.
    "smoke": dict(
        num_envs=32,
        batch_size=32,
        num_minibatches=4,
        unroll_length=10,
        num_updates_per_batch=2,
        total_env_steps=3 * 1280,
        num_evals=2,
        num_eval_envs=16,
        keep_every_n_evals=1,
        critic_hidden_sizes=(64, 64),
    ),
    # The headline run on franka_pick: the settings of the committed reference pick runs
    # (docs/reference/, tests check the match; docs/design.md, "The paper preset"). The
    # paper's lrs (1e-5 / 1e-4) were tuned for PixMC's 8 k-step batches.
    "paper": dict(
        env="franka_pick",
        actor="popsan",
        num_envs=512,
        batch_size=256,
        num_minibatches=8,
        unroll_length=10,
        num_updates_per_batch=4,
        total_env_steps=40_000_000,
        actor_lr=3e-4,
        critic_lr=1e-3,
        lr_schedule="constant",
        discounting=0.97,
        gae_lambda=0.95,
        clipping_epsilon=0.2,
        entropy_cost=1e-3,
        num_evals=160,
        num_eval_envs=64,
        keep_every_n_evals=5,
    ),
}


# The default recipe: what `python train.py` runs on a CPU, for both actors. Small minibatches
# (16 of 128 sequences) give twice the gradient steps per sample of 8 of 256 at the same FLOPs;
# the actor lr decays to 0 over the run (cosine), so the final checkpoint is the settled one.
# Evaluations use 256 episodes, so a 90 % figure has a 95 % CI of about +-4 points.
CPU_RECIPE: dict[str, Any] = dict(
    num_envs=512,
    batch_size=128,
    num_minibatches=16,
    unroll_length=10,
    num_updates_per_batch=4,
    actor_lr=1e-3,
    critic_lr=1e-3,
    lr_schedule="cosine",
    entropy_cost=1e-3,
    total_env_steps=6_000_000,
    num_evals=24,
    num_eval_envs=256,
)

# franka_pick's curriculum (docs/design.md, "A gentle grasp first"; docs/results.md): the CPU
# recipe's 6 M steps on the revision-2 task (finger targets clamped at the closed stop, no charge
# on the held cube's speed: envs/franka_pick.py LEGACY_OVERRIDES[2] and [3]) with revision 5's
# shaping (the lift ramp and the climb term, which the env's defaults set), where PPO learns a
# gentle grasp and lift; then 4 M steps on the task itself at actor lr 3e-4. From scratch on the
# task itself the policies learn to swing or lower the squeezed cube and never hold it. A warm-up
# that ends holding the cube low needs about 2 M task steps to leave that plateau, hence 4 M
# (docs/design.md, "A gentle grasp first"). The second stage clips the actor's and the critic's
# gradients each: its critic starts fitted to the warm-up's reward, and under the joint clip its
# large gradients set the actor's step size (docs/design.md, "Guards at the stage change"); the
# warm-up, from scratch, keeps the joint clip.
PICK_RECIPE: dict[str, Any] = dict(
    warmup_env_steps=CPU_RECIPE["total_env_steps"],
    warmup_env_overrides=dict(finger_target_low=0.0, reward_scales=dict(object_speed=0.0)),
    warmup_actor_lr=CPU_RECIPE["actor_lr"],
    warmup_num_evals=CPU_RECIPE["num_evals"],
    total_env_steps=4_000_000,
    actor_lr=3e-4,
    num_evals=16,
    clip_per_network=True,
    warmup_clip_per_network=False,
)
ENV_RECIPES: dict[str, dict[str, Any]] = {"franka_pick": PICK_RECIPE}

# The default recipe's actor kwargs over the actors' own (config.POPSAN_DEFAULTS, MLP_DEFAULTS):
# the MLP's output layer starts at 0.01x its draw, so its first policy is the exploration noise
# around a still arm; PopSAN keeps the paper's decoder draw, which learnt faster than a small
# one (docs/design.md, "The output layers start small"). Presets keep the actors' own draws
# (the paper preset is the paper's network).
ACTOR_RECIPES: dict[str, dict[str, Any]] = {"popsan": {}, "mlp": dict(output_init_scale=0.01)}

# The rule that scales the recipes to an accelerator's thousands of envs.
ACCELERATOR_SCALE = 4
SCALED = ("num_envs", "batch_size", "total_env_steps", "warmup_env_steps")


def scale_recipe(recipe: dict[str, Any], factor: int) -> dict[str, Any]:
    """The recipe with ``factor`` times the envs, minibatch size and env steps (those of
    ``SCALED`` that it sets).

    Minibatch count, epochs, unroll length, learning rates and schedule stay, so the run makes
    the same number of gradient updates in the same order, each on ``factor`` times the
    sequences (a less noisy gradient; the lr is not scaled). Evaluations keep their cadence.
    """
    return {k: v * factor if k in SCALED else v for k, v in recipe.items()}


# Per-backend scale of the recipes: as written on a CPU, 4x (2048 envs) on an accelerator.
BACKEND_SCALE: dict[str, int] = {"cpu": 1, "gpu": ACCELERATOR_SCALE, "tpu": ACCELERATOR_SCALE}


def backend_defaults(backend: str, env: str | None = None) -> dict[str, Any]:
    """The CPU recipe and ``env``'s own recipe, scaled for ``backend`` (unknown: as a CPU)."""
    recipe = {**CPU_RECIPE, **ENV_RECIPES.get(env or "", {})}
    return scale_recipe(recipe, BACKEND_SCALE.get(backend, 1))


def resolve_config(
    preset: str | None = None,
    backend: str = "cpu",
    overrides: dict[str, Any] | None = None,
    actor_overrides: dict[str, Any] | None = None,
) -> RunConfig:
    """Backend defaults (with the env's recipe unless a preset is given) < preset < explicit
    overrides; actor kwargs default by actor name (with ``ACTOR_RECIPES`` unless a preset is
    given).

    ``actor_overrides`` (e.g. ``timesteps``) update the chosen actor's default kwargs; a key
    the actor does not take raises ConfigError.
    """
    if preset is not None and preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    env = given.get("env", RunConfig.env)
    values = backend_defaults(backend, None if preset else env)
    values.update(PRESETS.get(preset or "", {}))
    values.update(given)
    actor = values.get("actor", RunConfig.actor)
    if actor not in ACTORS:
        raise ConfigError(f"unknown actor {actor!r}; choose one of {', '.join(ACTORS)}")
    if "actor_kwargs" not in values:
        values["actor_kwargs"] = dict(POPSAN_DEFAULTS if actor == "popsan" else MLP_DEFAULTS)
        if preset is None:
            values["actor_kwargs"].update(ACTOR_RECIPES[actor])
    extra = {k: v for k, v in (actor_overrides or {}).items() if v is not None}
    bad = sorted(set(extra) - set(values["actor_kwargs"]))
    if bad:
        raise ConfigError(f"actor {actor!r} does not take {', '.join(bad)}")
    values["actor_kwargs"] = tuplify({**values["actor_kwargs"], **extra})
    if "critic_hidden_sizes" in values:
        values["critic_hidden_sizes"] = tuple(values["critic_hidden_sizes"])
    return RunConfig.from_dict(values)
