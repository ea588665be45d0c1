"""What to fit: cloud paths from files, directories and glob patterns, as jobs."""
from __future__ import annotations

import glob
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from psonurbs.formats.clouds import CLOUD_SUFFIXES
from psonurbs.run.summary import BAD_INPUT, Row

__all__ = ["Job", "expand_inputs", "jobs_from_inputs"]


@dataclass(frozen=True)
class Job:
    """One cloud to fit, with its config (a :class:`psonurbs.config.FitConfig`)."""

    path: Path
    config: object
    refused: str = ""  # set: not fitted, reported as a bad-input row with this message


def _is_cloud(path: Path) -> bool:
    return path.suffix.lower() in CLOUD_SUFFIXES


def expand_inputs(args: Iterable[str | os.PathLike]) -> list[Path | Row]:
    """Cloud paths from files, directories and glob patterns, in the order given.

    * an existing directory gives its cloud files (``.ply``, ``.pcd``, ``.xyz``,
      ``.txt``, ``.pts``; not recursive), sorted by name;
    * an argument that does not exist but contains ``*``, ``?`` or ``[`` is a glob
      pattern (``**`` recurses): its cloud files, sorted;
    * anything else is taken as a file (a missing one is reported when read).

    A directory or pattern without clouds gives a ``bad-input`` :class:`Row` in its
    place. A path named twice (directly or through a directory/pattern) is fitted once.
    """
    items: list[Path | Row] = []
    seen: set[Path] = set()

    def add(p: Path) -> None:
        key = Path(os.path.abspath(p))
        if key not in seen:
            seen.add(key)
            items.append(p)

    kinds = ", ".join(CLOUD_SUFFIXES)
    for arg in args:
        text = os.fspath(arg)
        path = Path(text)
        try:
            is_dir, exists = path.is_dir(), path.exists()
        except OSError:  # a name too long, a symlink loop: the reader says so
            add(path)
            continue
        if is_dir:
            found = sorted(p for p in path.iterdir() if p.is_file() and _is_cloud(p))
            if not found:
                items.append(Row(text, status=BAD_INPUT,
                                 message=f"{text}: directory has no point cloud files ({kinds})"))
            for p in found:
                add(p)
        elif not exists and glob.has_magic(text):
            found = sorted(Path(p) for p in glob.glob(text, recursive=True))
            found = [p for p in found if p.is_file() and _is_cloud(p)]
            if not found:
                items.append(Row(text, status=BAD_INPUT,
                                 message=f"{text}: no point cloud files match this pattern"))
            for p in found:
                add(p)
        else:
            add(path)
    return items


def jobs_from_inputs(items: Iterable[Path | Row], config) -> list[Job]:
    """One :class:`Job` per item of :func:`expand_inputs` (refused ones included)."""
    return [Job(Path(item.file), config, refused=item.message) if isinstance(item, Row)
            else Job(item, config) for item in items]
