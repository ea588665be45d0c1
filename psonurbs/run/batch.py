"""Fitting many clouds: input expansion, a worker pool, the regression gate, the summary.

``psonurbs fit`` is a thin layer over :func:`run_batch`:

* :func:`expand_inputs` turns files, directories (their cloud files, sorted) and glob
  patterns into a list of cloud paths; an argument that names nothing usable becomes
  an error row instead.
* :func:`run_batch` fits each :class:`Job` (a path and its config), in this process
  (``workers=1``) or in a pool of ``workers`` processes started with the ``spawn``
  method, each limited to one BLAS/OpenMP thread. A worker only computes: it returns
  the rendered outputs and the parent writes them (atomically, all-or-nothing per
  cloud, :func:`psonurbs.io.write_fit_outputs`), so a worker can be stopped at any
  moment without leaving a partial file, and ``workers=N`` writes byte-identical
  files to ``workers=1``.
* A cloud that fails becomes a :class:`Row` with its status and message; the others
  go on. :class:`Gate` marks a fit whose RMSE is above a bound (its files are still
  written).
* :func:`write_summary` writes ``summary.csv`` and ``summary.json`` atomically.

Statuses and the exit code they lead to (:func:`exit_code`): ``ok`` (0),
``gate-exceeded`` (3), ``bad-input`` (2), ``internal-error`` (1); interrupted runs
exit with 130. When several apply the most severe wins: 130 > 1 > 2 > 3 > 0.
"""
from __future__ import annotations

import csv
import glob
import io
import json
import math
import os
import signal
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

from psonurbs.errors import PsonurbsError

__all__ = [
    "Job",
    "Row",
    "Gate",
    "FitOutcome",
    "expand_inputs",
    "jobs_from_inputs",
    "fit_job",
    "run_batch",
    "exit_code",
    "write_summary",
    "render_summary_csv",
    "render_summary_json",
    "SUMMARY_COLUMNS",
    "EXIT_OK",
    "EXIT_INTERNAL",
    "EXIT_INPUT",
    "EXIT_GATE",
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "Terminated",
    "raise_terminated",
]

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_GATE = 3
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # 128 + SIGTERM, as a shell reports a process ended by it


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a CI runner cancelling): stopped and cleaned up
    exactly like Ctrl-C, reported with its own exit code."""


def raise_terminated(signum, frame) -> None:
    """SIGTERM handler for the main process (workers keep the default and are ended)."""
    raise Terminated()


OK, GATE, BAD_INPUT, INTERNAL = "ok", "gate-exceeded", "bad-input", "internal-error"
_STATUS_EXIT = {OK: EXIT_OK, GATE: EXIT_GATE, BAD_INPUT: EXIT_INPUT, INTERNAL: EXIT_INTERNAL}
_SEVERITY = [EXIT_OK, EXIT_GATE, EXIT_INPUT, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_TERMINATED]

SUMMARY_COLUMNS = ["file", "points", "topology", "net", "rmse", "max_error", "rmse_relative",
                   "max_error_relative", "seconds", "status", "message"]
SUMMARY_NAMES = ("summary.csv", "summary.json")


@dataclass(frozen=True)
class Job:
    """One cloud to fit, with its config (a :class:`psonurbs.config.FitConfig`)."""

    path: Path
    config: object
    refused: str = ""  # set: not fitted, reported as a bad-input row with this message


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
    detail: str = ""  # traceback of an internal error; never written

    def summary(self) -> dict:
        """The summary columns; a non-finite number becomes None (JSON null)."""
        d = asdict(self)
        return {k: (None if isinstance(d[k], float) and not math.isfinite(d[k]) else d[k])
                for k in SUMMARY_COLUMNS}


@dataclass(frozen=True)
class Gate:
    """Regression bounds: RMSE in cloud units, and relative to the bounding-box diagonal."""

    max_rmse: float | None = None
    max_rmse_rel: float | None = None

    def check(self, metrics: dict) -> str:
        """'' when the fit passes, else the reason (for the row's message)."""
        reasons = []
        rmse, rel = metrics.get("rmse", math.nan), metrics.get("rmse_relative", math.nan)
        if self.max_rmse is not None and not rmse <= self.max_rmse:
            reasons.append(f"rmse {rmse:.3e} > --max-rmse {self.max_rmse:g}")
        if self.max_rmse_rel is not None and not rel <= self.max_rmse_rel:
            reasons.append(f"relative rmse {rel:.3e} > --max-rmse-rel {self.max_rmse_rel:g}")
        return "; ".join(reasons)

    def as_dict(self) -> dict:
        return {"max_rmse": self.max_rmse, "max_rmse_rel": self.max_rmse_rel}


# ---- inputs --------------------------------------------------------------------

def _is_cloud(path: Path) -> bool:
    from psonurbs.formats.clouds import CLOUD_SUFFIXES

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
    from psonurbs.formats.clouds import CLOUD_SUFFIXES

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
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and _is_cloud(p))
            if not found:
                items.append(Row(text, status=BAD_INPUT,
                                 message=f"{text}: directory has no point cloud files ({kinds})"))
            for p in found:
                add(p)
        elif not path.exists() and glob.has_magic(text):
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


# ---- one cloud -----------------------------------------------------------------

@dataclass
class FitOutcome:
    """What a worker sends back: the row, and the rendered outputs to write."""

    row: Row
    stem: str
    outputs: dict | None = None  # keyword arguments of write_fit_outputs (minus out_dir, stem)
    metrics: dict | None = None


def fit_job(job: Job, formats: Sequence[str] = (),
            on_iteration: Callable[[int, float, float], None] | None = None) -> FitOutcome:
    """Read, fit and render one cloud; never raises except on KeyboardInterrupt.

    A :class:`~psonurbs.errors.PsonurbsError` gives a ``bad-input`` row, any other
    exception an ``internal-error`` row (with the traceback in ``row.detail``).
    """
    import psonurbs
    from psonurbs.formats.cad import render_exports
    from psonurbs.formats.clouds import read_cloud

    path = job.path
    row = Row(str(path))
    start = time.perf_counter()
    try:
        points = read_cloud(path)
        row.points = int(len(points))
        from psonurbs.fitting.pipeline import fit_points  # imported late: reading needs no numerics

        result = fit_points(points, job.config, on_iteration=on_iteration)
        surface = result.surface.to_dict()
        document = {
            "psonurbs_version": psonurbs.__version__,
            "cloud": path.name,
            "topology": result.topology,
            "surface": surface,
            "metrics": result.metrics,
            "fit": result.info,
            "notes": list(result.notes),
            "config": job.config.to_dict(),
        }
        vertices, triangles = result.surface.tessellate(*job.config.tessellation)
        obj_extra, extra_files = ("", {})
        if formats:
            from psonurbs.geometry.nurbs import NurbsSurface

            exact = NurbsSurface.from_dict(surface)
            obj_extra, extra_files = render_exports(exact, formats, path.stem, len(vertices))
        metrics = result.metrics
        row.topology = result.topology
        row.net = "x".join(str(n) for n in job.config.net_size)  # distinct control points
        row.rmse = _number(metrics.get("rmse"))
        row.max_error = _number(metrics.get("max_error"))
        row.rmse_relative = _number(metrics.get("rmse_relative"))
        row.max_error_relative = _number(metrics.get("max_error_relative"))
        row.notes = list(result.notes)
        outputs = dict(document=document, vertices=vertices, triangles=triangles,
                       curve_header=list(result.curve_header), curve_rows=result.curve,
                       obj_extra=obj_extra, extra_files=extra_files)
        row.seconds = time.perf_counter() - start
        return FitOutcome(row, path.stem, outputs, dict(metrics))
    except KeyboardInterrupt:
        raise
    except PsonurbsError as e:
        message = str(e)
        prefix = f"{path}: "
        row.status, row.message = BAD_INPUT, message if message.startswith(prefix) else prefix + message
    except Exception as e:  # a bug: reported in the row, the batch goes on
        row.status = INTERNAL
        row.message = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        row.detail = traceback.format_exc()
    row.seconds = time.perf_counter() - start
    return FitOutcome(row, path.stem)


def _number(x) -> float | None:
    return None if x is None else float(x)


def _finish(outcome: FitOutcome, out_dir: Path, gate: Gate) -> Row:
    """In the parent: write a successful fit's files, apply the gate; returns the row."""
    from psonurbs.formats.clouds import write_fit_outputs

    row = outcome.row
    if outcome.outputs is None:
        return row
    try:
        write_fit_outputs(out_dir, outcome.stem, **outcome.outputs)
    except OSError as e:
        row.status = BAD_INPUT
        row.message = f"{row.file}: cannot write the outputs to {out_dir} ({e.strerror or e})"
        return row
    except KeyboardInterrupt:
        raise
    except Exception as e:  # e.g. NaN in the document: a bug
        row.status = INTERNAL
        row.message = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        row.detail = traceback.format_exc()
        return row
    reason = gate.check(outcome.metrics) if outcome.metrics else ""
    if reason:
        row.status = GATE
    row.message = "; ".join([m for m in [reason, *row.notes] if m])
    return row


# ---- the pool ------------------------------------------------------------------

_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                     "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def _worker_init() -> None:
    """Each worker: Ctrl-C is the parent's business; one BLAS/OpenMP thread."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for name in _THREAD_VARIABLES:
        os.environ[name] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    except Exception:  # pragma: no cover - threadpoolctl is a dependency
        pass


def _duplicate_rows(jobs: Sequence[Job], out_dir: Path) -> dict[int, Row]:
    """Rows for jobs that would overwrite another's outputs or the summary."""
    stems: dict[str, Path] = {}
    bad: dict[int, Row] = {}
    for k, job in enumerate(jobs):
        stem = job.path.stem
        if job.refused:
            bad[k] = Row(str(job.path), status=BAD_INPUT, message=job.refused)
        elif f"{stem}.json" in SUMMARY_NAMES or f"{stem}.csv" in SUMMARY_NAMES:
            bad[k] = Row(str(job.path), status=BAD_INPUT,
                         message=f"{job.path}: its outputs would overwrite the run summary "
                                 f"{out_dir / stem}.json; rename the file, skipped")
        elif stem in stems:
            bad[k] = Row(str(job.path), status=BAD_INPUT,
                         message=f"{job.path}: has the same name as {stems[stem]}; its outputs "
                                 f"would overwrite {out_dir / stem}.*, skipped")
        else:
            stems[stem] = job.path
    return bad


def run_batch(jobs: Sequence[Job], out_dir: str | os.PathLike, *, formats: Sequence[str] = (),
              workers: int = 1, gate: Gate = Gate(),
              on_row: Callable[[Row], None] | None = None,
              on_iteration: Callable[[int, float, float], None] | None = None) -> list[Row]:
    """Fit every job; returns one row per job, in the order of ``jobs``.

    ``on_row(row)`` is called in this process as each cloud finishes (in completion
    order). ``on_iteration`` is passed to the fit when it runs in this process
    (``workers == 1``). KeyboardInterrupt propagates after the pool is stopped; the
    outputs of the clouds already finished are complete, the others are not written.
    """
    out_dir = Path(out_dir)
    rows: list[Row | None] = [None] * len(jobs)
    for k, row in _duplicate_rows(jobs, out_dir).items():
        rows[k] = row
    todo = [k for k in range(len(jobs)) if rows[k] is None]

    def done(k: int, row: Row) -> None:
        rows[k] = row
        if on_row is not None:
            on_row(row)

    # the refusals are reported where they stand in the input order (workers == 1) or first
    pending_reports = {k: rows[k] for k in range(len(jobs)) if rows[k] is not None}
    if workers <= 1 or len(todo) <= 1:
        for k in range(len(jobs)):
            if k in pending_reports:
                done(k, pending_reports[k])
                continue
            outcome = fit_job(jobs[k], formats, on_iteration)
            done(k, _finish(outcome, out_dir, gate))
        return rows  # type: ignore[return-value]

    for k, row in pending_reports.items():
        done(k, row)
    _pool_run(jobs, todo, out_dir, formats, min(workers, len(todo)), gate, done)
    return rows  # type: ignore[return-value]


def _pool_run(jobs, todo, out_dir, formats, workers, gate, done) -> None:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    context = multiprocessing.get_context("spawn")
    # Workers start with SIGINT ignored (a disposition that survives exec), so a Ctrl-C
    # reaches only this process, which then stops the pool.
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_worker_init)
    try:
        try:
            futures = {executor.submit(fit_job, jobs[k], tuple(formats)): k for k in todo}
        finally:
            signal.signal(signal.SIGINT, previous)
        remaining = set(futures)
        while remaining:
            finished, remaining = wait(remaining, return_when=FIRST_COMPLETED)
            for future in sorted(finished, key=lambda f: futures[f]):
                k = futures[future]
                try:
                    outcome = future.result()
                except Exception as e:  # the worker process died
                    row = Row(str(jobs[k].path), status=INTERNAL,
                              message=f"worker process failed: {type(e).__name__}: {e}",
                              detail=traceback.format_exc())
                    done(k, row)
                    continue
                done(k, _finish(outcome, out_dir, gate))
    except BaseException:
        _stop_pool(executor)
        raise
    executor.shutdown(wait=True)


def _stop_pool(executor) -> None:
    """Cancel what has not started and end the worker processes this run started."""
    processes = list(getattr(executor, "_processes", {}).values())
    executor.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=5)


# ---- the exit code and the summary ---------------------------------------------

def exit_code(rows: Iterable[Row]) -> int:
    """The most severe status: internal error 1 > bad input 2 > gate exceeded 3 > ok 0."""
    codes = [_STATUS_EXIT[r.status] for r in rows]
    return max(codes, key=_SEVERITY.index, default=EXIT_OK)


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


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
    counts = {s: sum(r.status == s for r in rows) for s in (OK, GATE, BAD_INPUT, INTERNAL)}
    document = {"psonurbs_version": psonurbs.__version__, "exit_code": exit_code(rows),
                "counts": counts, "gate": gate.as_dict(), "clouds": clouds}
    return json.dumps(document, indent=2, allow_nan=False) + "\n"


def write_summary(out_dir: str | os.PathLike, rows: Sequence[Row], gate: Gate = Gate()) -> dict[str, Path]:
    """``summary.csv`` and ``summary.json`` (one row per cloud), each written atomically."""
    from psonurbs.formats.clouds import atomic_write

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return {
        "csv": atomic_write(out_dir / "summary.csv", render_summary_csv(rows)),
        "json": atomic_write(out_dir / "summary.json", render_summary_json(rows, gate)),
    }
