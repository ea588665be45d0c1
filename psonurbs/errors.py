"""Exceptions that carry a message meant for the user."""

import stat
from pathlib import Path


class PsonurbsError(Exception):
    """Base class: the message is a complete sentence for the user."""


class InputError(PsonurbsError):
    """A point cloud that cannot be fitted (missing, unreadable, degenerate)."""


class ConfigError(PsonurbsError):
    """A configuration that is malformed or impossible; the message names the key."""


_NOT_REGULAR = ((stat.S_ISFIFO, "a named pipe"), (stat.S_ISCHR, "a character device"),
                (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def existing_file(path, kind: str, error: type[PsonurbsError], missing: str = "no such file",
                  max_bytes: int | None = None) -> Path:
    """``path`` as a Path, or ``error`` naming it when it is not a regular file to read.

    ``kind`` says what the file should have been ("a point cloud file"). Refused: a missing
    path, a directory, anything that is not a regular file (a named pipe would block the
    read for ever, ``/dev/zero`` never ends; a symlink is judged by its target), and with
    ``max_bytes`` a file larger than that.
    """
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: {missing}") from None
    except OSError as e:  # a symlink loop, a name too long, a component that is a file
        raise error(f"{path}: cannot read file ({e.strerror or e})") from None
    if stat.S_ISDIR(info.st_mode):
        raise error(f"{path}: is a directory, not {kind}")
    if not stat.S_ISREG(info.st_mode):
        what = next((name for test, name in _NOT_REGULAR if test(info.st_mode)), "not a regular file")
        raise error(f"{path}: is {what}, not {kind} (only regular files are read)")
    if max_bytes is not None and info.st_size > max_bytes:
        raise error(f"{path}: file is too large ({info.st_size / 2**20:.0f} MiB; at most "
                    f"{max_bytes / 2**20:.0f} MiB for {kind})")
    return path
