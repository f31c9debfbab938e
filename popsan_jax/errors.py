"""User-facing errors.

Entry points (train.py, eval.py) catch :class:`UserError`, print its message as one line prefixed
with ``error:`` and exit with status 2. Library code raises it for anything a user can fix: an
unknown name, an impossible config, a missing or corrupt checkpoint, NaNs.
"""


class UserError(Exception):
    """A mistake in the user's input or state, reported as one clear line."""


class ConfigError(UserError):
    """An impossible or inconsistent configuration."""


class CheckpointError(UserError):
    """A missing, corrupt or incompatible checkpoint or run directory."""


class NonFiniteError(UserError):
    """NaN or inf appeared in the loss or the parameters."""
