"""Errors a user can act on. Every message names the file (or key) at fault and how to fix it."""


class JaxmapError(Exception):
    """Base of all user-facing errors; the CLI prints these without a traceback."""


class DataError(JaxmapError, ValueError):
    """Input data is missing, truncated or malformed."""


class CapacityError(JaxmapError, RuntimeError):
    """A fixed-capacity structure is full and could not be grown."""
