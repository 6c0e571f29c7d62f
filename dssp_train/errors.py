"""User-facing errors: one line that says what is wrong and what to do.

The CLIs catch :class:`DSSPError` and print its message without a traceback.
"""


class DSSPError(Exception):
    """An error caused by the user's input (a path, a dataset, a config)."""


class DatasetError(DSSPError):
    """A dataset on disk is missing something or holds invalid values."""


class ConfigError(DSSPError):
    """A configuration value is invalid or does not fit a checkpoint."""


class CheckpointError(DSSPError):
    """A checkpoint is missing, corrupt, or does not fit its config."""
