"""The envs package's own error type (envs imports nothing of popsan_jax)."""


class EnvConfigError(ValueError):
    """An unknown env name or config key, or an impossible env setting; one clear line.

    ``popsan_jax`` translates it into its ``ConfigError`` where it builds envs.
    """
