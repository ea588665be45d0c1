"""Exceptions that carry a message meant for the user."""


class PsonurbsError(Exception):
    """Base class: the message is a complete sentence for the user."""


class InputError(PsonurbsError):
    """A point cloud that cannot be fitted (missing, unreadable, degenerate)."""


class ConfigError(PsonurbsError):
    """A configuration that is malformed or impossible; the message names the key."""
