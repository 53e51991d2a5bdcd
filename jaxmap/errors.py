"""Errors a user can act on. Every message names the file (or key) at fault and how to fix it."""


class JaxmapError(Exception):
    """Base of all user-facing errors; the CLI prints these without a traceback."""


class DataError(JaxmapError, ValueError):
    """Input data is missing, truncated or malformed."""


class CapacityError(JaxmapError, RuntimeError):
    """A fixed-capacity structure is full and could not be grown."""


class RunDirError(JaxmapError):
    """A run or output directory cannot be used as asked: taken by another process, holding another
    run, not writable, or a file where a directory is needed."""


class CheckpointError(DataError):
    """A checkpoint is damaged (missing, truncated or altered files) or none is usable."""


class NoCheckpointError(CheckpointError):
    """A checkpoint directory holds no checkpoint at all (the run never saved one)."""


class ConfigError(JaxmapError, ValueError):
    """A config file or override is wrong; the message says where and how to fix it."""
