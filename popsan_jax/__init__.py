"""PopSAN-JAX: population-coded spiking actor networks trained with PPO on MJX tasks.

The public names below load lazily (PEP 562), so ``import popsan_jax.errors`` or
``popsan_jax.jax_setup`` does not pull in Flax/Brax (Brax's import loads mujoco, which prints
"Failed to import warp" on machines without NVIDIA Warp).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "PopSAN": "popsan_jax.snn.popsan",
    "LIFParams": "popsan_jax.snn.lif",
    "Critic": "popsan_jax.networks",
    "MLPActor": "popsan_jax.networks",
    "actor_variables": "popsan_jax.networks",
    "make_actor": "popsan_jax.networks",
    "make_ppo_networks": "popsan_jax.networks",
}

__all__ = [
    "Critic",
    "LIFParams",
    "MLPActor",
    "PopSAN",
    "actor_variables",
    "make_actor",
    "make_ppo_networks",
]

if TYPE_CHECKING:
    from popsan_jax.networks import (
        Critic,
        MLPActor,
        actor_variables,
        make_actor,
        make_ppo_networks,
    )
    from popsan_jax.snn.lif import LIFParams
    from popsan_jax.snn.popsan import PopSAN


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'popsan_jax' has no attribute {name!r}")
