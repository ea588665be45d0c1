"""What happened to each cloud of a run: statuses, exit codes, the summary files.

Statuses and the exit code they lead to (:func:`exit_code`): ``ok`` (0), ``suspect``
(0: fitted, files written, but a self-check failed; with ``--fail-suspect`` the gate turns
it into ``gate-exceeded``), ``gate-exceeded`` (3), ``bad-input`` (2), ``worker-lost`` (4: the
process fitting the cloud died, e.g. killed for memory; :func:`worker_lost_row`),
``internal-error`` (1); interrupted runs exit with 130 (Ctrl-C) or 143 (SIGTERM). When
several apply the most severe wins: 143 > 130 > 1 > 4 > 2 > 3 > 0. :func:`write_summary` writes ``summary.csv`` and
``summary.json`` atomically, one row per cloud in the order given.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

from psonurbs.run.gate import Gate

__all__ = [
    "Row", "exit_code", "write_summary", "render_summary_csv", "render_summary_json",
    "SUMMARY_COLUMNS", "SUMMARY_NAMES", "OK", "SUSPECT", "GATE", "BAD_INPUT", "INTERNAL", "WORKER_LOST",
    "STATUSES", "EXIT_OK", "EXIT_INTERNAL", "EXIT_INPUT", "EXIT_GATE", "EXIT_WORKER_LOST", "EXIT_INTERRUPTED",
    "EXIT_TERMINATED", "Terminated", "raise_terminated", "worker_lost_row",
]

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_GATE = 3
EXIT_WORKER_LOST = 4  # the process fitting a cloud died (killed, out of memory): not the input's fault
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # 128 + SIGTERM, as a shell reports a process ended by it


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a CI runner cancelling): stopped and cleaned up
    exactly like Ctrl-C, reported with its own exit code."""


def raise_terminated(signum, frame) -> None:
    """SIGTERM handler for the main process (workers keep the default and are ended)."""
    raise Terminated()


OK, SUSPECT, GATE, BAD_INPUT, INTERNAL = "ok", "suspect", "gate-exceeded", "bad-input", "internal-error"
WORKER_LOST = "worker-lost"
STATUSES = (OK, SUSPECT, GATE, BAD_INPUT, WORKER_LOST, INTERNAL)
_STATUS_EXIT = {OK: EXIT_OK, SUSPECT: EXIT_OK, GATE: EXIT_GATE, BAD_INPUT: EXIT_INPUT,
                WORKER_LOST: EXIT_WORKER_LOST, INTERNAL: EXIT_INTERNAL}
# a lost worker is worse than an unusable file (the cloud may be fine and was not fitted:
# the machine needs attention) and not as bad as a bug (a retry with more memory may pass)
_SEVERITY = [EXIT_OK, EXIT_GATE, EXIT_INPUT, EXIT_WORKER_LOST, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_TERMINATED]

SUMMARY_COLUMNS = ["file", "points", "topology", "net", "rmse", "max_error", "rmse_relative",
                   "max_error_relative", "seconds", "status", "message"]
SUMMARY_NAMES = ("summary.csv", "summary.json")


@dataclass
class Row:
    """One line of the summary: what happened to one cloud."""

    file: str
    points: int | None = None
    topology: str | None = None
    net: str | None = None  # "NUxNV"
    rmse: float | None = None
    max_error: float | None = None
    rmse_relative: float | None = None
    max_error_relative: float | None = None
    seconds: float | None = None
    status: str = OK
    message: str = ""
    notes: list[str] = field(default_factory=list)  # the fit's notes (in message too)
    warnings: list[str] = field(default_factory=list)  # the fit's failed self-checks (in notes too)
    unmet: str = ""  # a fit to a tolerance that does not meet it: why (in notes too)
    detail: str = ""  # traceback of an internal error; never written

    def summary(self) -> dict:
        """The summary columns; a non-finite number becomes None (JSON null)."""
        d = asdict(self)
        return {k: (None if isinstance(d[k], float) and not math.isfinite(d[k]) else d[k])
                for k in SUMMARY_COLUMNS}


def worker_lost_row(file: str, how: str) -> Row:
    """The row of a cloud whose worker died before it answered, for any back end that runs
    fits in other processes (``how``: 'was killed by SIGKILL', 'was lost twice')."""
    hint = ("SIGKILL is what the kernel's out-of-memory killer sends; " if "SIGKILL" in how else "")
    return Row(file, status=WORKER_LOST,
               message=f"{file}: the worker process fitting it {how}; not fitted ({hint}the fit may need more "
                       "memory than was free: retry it with fewer --jobs, a smaller net_size or tessellation, or on a machine "
                       "with more memory)")


def exit_code(rows: Iterable[Row]) -> int:
    """The most severe status: internal error 1 > worker lost 4 > bad input 2 > gate exceeded 3 > ok 0."""
    codes = [_STATUS_EXIT[r.status] for r in rows]
    return max(codes, key=_SEVERITY.index, default=EXIT_OK)


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return printable(str(value))


def printable(text: str) -> str:
    """``text`` encodable as UTF-8: the undecodable bytes of a file name (surrogates) as ``\\xff``."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def render_summary_csv(rows: Sequence[Row]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(SUMMARY_COLUMNS)
    for row in rows:
        d = row.summary()
        if d["seconds"] is not None:
            d["seconds"] = round(d["seconds"], 3)
        writer.writerow([_cell(d[c]) for c in SUMMARY_COLUMNS])
    return buffer.getvalue()


def render_summary_json(rows: Sequence[Row], gate: Gate = Gate()) -> str:
    import psonurbs

    clouds = []
    for row in rows:
        d = row.summary()
        if d["seconds"] is not None:
            d["seconds"] = round(d["seconds"], 3)
        clouds.append(d)
    counts = {s: sum(r.status == s for r in rows) for s in STATUSES}
    document = {"psonurbs_version": psonurbs.__version__, "exit_code": exit_code(rows),
                "counts": counts, "gate": gate.as_dict(), "clouds": clouds}
    return json.dumps(document, indent=2, allow_nan=False) + "\n"


def write_summary(out_dir: str | os.PathLike, rows: Sequence[Row], gate: Gate = Gate()) -> dict[str, Path]:
    """``summary.csv`` and ``summary.json`` (one row per cloud), each written atomically."""
    from psonurbs.formats.outputs import atomic_write

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return {
        "csv": atomic_write(out_dir / "summary.csv", render_summary_csv(rows)),
        "json": atomic_write(out_dir / "summary.json", render_summary_json(rows, gate)),
    }
