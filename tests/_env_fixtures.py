"""Session-scoped envs and compiled functions shared by the env tests (MJX compiles are slow)."""

from __future__ import annotations

import jax
import pytest

import envs

BATCH = 4


class Compiled:
    """An env with its jitted, vmapped reset and step for a batch of ``BATCH``."""

    def __init__(self, name: str):
        self.env = envs.get_environment(name)
        self.reset = jax.jit(jax.vmap(self.env.reset))
        self.step = jax.jit(jax.vmap(self.env.step))

    def keys(self, seed: int = 0) -> jax.Array:
        return jax.random.split(jax.random.PRNGKey(seed), BATCH)


@pytest.fixture(scope="session")
def pick() -> Compiled:
    return Compiled("franka_pick")


@pytest.fixture(scope="session")
def reach() -> Compiled:
    return Compiled("franka_reach")
