"""Exceptions that carry a message meant for the user."""

from pathlib import Path


class PsonurbsError(Exception):
    """Base class: the message is a complete sentence for the user."""


class InputError(PsonurbsError):
    """A point cloud that cannot be fitted (missing, unreadable, degenerate)."""


class ConfigError(PsonurbsError):
    """A configuration that is malformed or impossible; the message names the key."""


def existing_file(path, kind: str, error: type[PsonurbsError], missing: str = "no such file") -> Path:
    """``path`` as a Path, or ``error`` naming it when it is missing or a directory.

    ``kind`` says what the file should have been ("a point cloud file").
    """
    path = Path(path)
    if not path.exists():
        raise error(f"{path}: {missing}")
    if path.is_dir():
        raise error(f"{path}: is a directory, not {kind}")
    return path
