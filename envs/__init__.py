"""MJX Franka Panda environments built on the project's own Panda model (``envs/assets``).

``get_environment(name, **config_overrides)`` returns a ``brax.envs.base.Env`` that works with
``brax.envs.wrappers.training.wrap(env, episode_length=env.config.episode_length)``.
"""

from __future__ import annotations

from typing import Any

from brax.envs.base import Env

from envs.errors import EnvConfigError
from envs.franka_pick import FrankaPick
from envs.franka_reach import FrankaReach
from envs.panda import merge_overrides

_ENVS = {"franka_pick": FrankaPick, "franka_reach": FrankaReach}


def list_environments() -> list[str]:
    """Names accepted by :func:`get_environment`."""
    return sorted(_ENVS)


def get_environment(name: str, **config_overrides: Any) -> Env:
    """Build env ``name``; ``config_overrides`` replace keys of its ``default_config()``.

    Unknown names or override keys raise :class:`envs.errors.EnvConfigError`.
    """
    if name not in _ENVS:
        raise EnvConfigError(f"unknown env {name!r}; available: {', '.join(list_environments())}")
    return _ENVS[name](**config_overrides)


def legacy_overrides(name: str, revision: int) -> dict[str, Any]:
    """Config overrides that make env ``name`` behave as its ``revision`` did (a run config saved
    by an earlier version names the revision it was trained with); ``{}`` for the current one."""
    if name not in _ENVS:
        raise EnvConfigError(f"unknown env {name!r}; available: {', '.join(list_environments())}")
    env_cls = _ENVS[name]
    current = env_cls.revision
    if not 1 <= revision <= current:
        raise EnvConfigError(f"env {name!r} has revisions 1..{current}, not {revision}")
    # newest first, so that older values win
    layers = [env_cls.legacy_overrides.get(r, {}) for r in range(current - 1, revision - 1, -1)]
    return merge_overrides(*layers)


__all__ = [
    "EnvConfigError",
    "FrankaPick",
    "FrankaReach",
    "get_environment",
    "legacy_overrides",
    "merge_overrides",
    "list_environments",
]
