"""Fitting many clouds: each job read, fitted and rendered, the files written by this process.

``psonurbs fit`` is a thin layer over :func:`run_batch`:

* :func:`psonurbs.run.inputs.expand_inputs` turns files, directories (their cloud files,
  sorted) and glob patterns into a list of cloud paths; an argument that names nothing
  usable becomes an error row instead.
* :func:`run_batch` fits each :class:`~psonurbs.run.inputs.Job` (a path and its config),
  in this process (``workers=1``), in a pool of worker processes
  (:mod:`psonurbs.run.workers`) or on a dask cluster (:mod:`psonurbs.run.cluster`, the
  clouds read here). A worker only computes: it returns the rendered outputs
  and the parent writes them (atomically, all-or-nothing per cloud,
  :func:`psonurbs.formats.outputs.write_fit_outputs`), so a worker can be stopped at any
  moment without leaving a partial file, and ``workers=N`` writes byte-identical files
  to ``workers=1``.
* A cloud that fails becomes a :class:`~psonurbs.run.summary.Row` with its status and
  message; the others go on. :class:`~psonurbs.run.gate.Gate` marks a fit whose RMSE is
  above a bound (its files are still written).
"""
from __future__ import annotations

import os
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from numpy.linalg import LinAlgError

from psonurbs.errors import PsonurbsError
from psonurbs.formats.clouds import Cloud, load_cloud
from psonurbs.run.cluster import Scheduler
from psonurbs.run.gate import Gate
from psonurbs.run.heap import keep_freed_memory
from psonurbs.run.inputs import Job
from psonurbs.run.summary import BAD_INPUT, GATE, INTERNAL, SUMMARY_NAMES, SUSPECT, Row, printable, worker_lost_row
from psonurbs.run.workers import pool_run

__all__ = ["FitOutcome", "fit_cloud", "fit_job", "preflight", "read_job", "run_batch"]


def preflight(config, source: str | None = None) -> None:
    """Refuse (ConfigError, its message prefixed with ``source``) a config whose arrays
    would be too large whatever the cloud."""
    from psonurbs.errors import ConfigError
    from psonurbs.fitting.budget import check_budget

    try:
        check_budget(config)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}" if source else str(e)) from None


@dataclass
class FitOutcome:
    """What a worker sends back: the row, and the rendered outputs to write."""

    row: Row
    stem: str
    outputs: dict | None = None  # keyword arguments of write_fit_outputs (minus out_dir, stem)
    metrics: dict | None = None


def fit_job(job: Job, formats: Sequence[str] = (),
            on_iteration: Callable[[int, float, float], None] | None = None,
            fit: Callable | None = None) -> FitOutcome:
    """Read, fit and render one cloud; never raises except on KeyboardInterrupt.

    ``fit(points, config, on_iteration=...)`` is the fitter (default
    :func:`psonurbs.fitting.pipeline.fit_points`; tests pass a stand-in). A
    :class:`~psonurbs.errors.PsonurbsError` gives a ``bad-input`` row, any other
    exception an ``internal-error`` row (with the traceback in ``row.detail``).
    """
    start = time.perf_counter()
    cloud = read_job(job)
    if isinstance(cloud, FitOutcome):
        return cloud
    outcome = fit_cloud(job, cloud, formats, on_iteration, fit)
    outcome.row.seconds = time.perf_counter() - start
    return outcome


def read_job(job: Job) -> Cloud | FitOutcome:
    """The job's cloud as read, or the outcome of a cloud that cannot be read or fitted
    (its row): unreadable, coordinates not representable, or more than the config's
    memory budget allows (:mod:`psonurbs.fitting.budget`)."""
    from psonurbs.fitting.budget import check_budget, max_points
    from psonurbs.fitting.prepare.organise import check_coordinates

    start = time.perf_counter()
    try:
        cloud = load_cloud(job.path, max_points(job.config))
        check_coordinates(cloud.points)  # refused before any fitter sees them
        check_budget(job.config, len(cloud.points))
        return cloud
    except KeyboardInterrupt:
        raise
    except Exception as e:
        return FitOutcome(_failed(Row(str(job.path)), job.path, e, time.perf_counter() - start), job.path.stem)


def fit_cloud(job: Job, cloud: Cloud, formats: Sequence[str] = (),
              on_iteration: Callable[[int, float, float], None] | None = None,
              fit: Callable | None = None) -> FitOutcome:
    """Fit and render a cloud already read (the part a worker or a cluster runs); never
    raises except on KeyboardInterrupt. ``row.seconds`` is the time taken here."""
    import psonurbs
    from psonurbs.formats.cad import render_exports

    path = job.path
    row = Row(str(path), points=int(len(cloud.points)))
    start = time.perf_counter()
    try:
        if fit is None:
            from psonurbs.fitting.pipeline import fit_points as fit  # imported late: reading needs no numerics
        if job.config.patches != 1:
            from psonurbs.objects.whole import ObjectFit, fit_object

            result = fit_object(cloud.points, job.config, on_iteration, fit)
            if isinstance(result, ObjectFit):  # several faces (one region: one surface, below)
                return _object_outcome(job, cloud, result, formats, row, start)
        else:
            result = fit(cloud.points, job.config, on_iteration=on_iteration)
        trim = getattr(result, "trim", None)
        notes = [*cloud.notes, *result.notes]
        surface = result.surface.to_dict()
        if trim is not None:
            surface["trim"] = trim.to_list()
        document = {
            "psonurbs_version": psonurbs.__version__,
            "cloud": path.name,
            "topology": result.topology,
            "surface": surface,
            "metrics": result.metrics,
            "fit": result.info,
            "notes": notes,
            "config": job.config.to_dict(),
        }
        vertices, triangles = _mesh(result.surface, trim, job.config.tessellation)
        obj_extra, extra_files = ("", {})
        searched = result.info.get("tolerance")
        if searched is not None:
            extra_files["_tolerance.csv"] = _tolerance_csv(searched)
        if formats:
            from psonurbs.geometry.nurbs import NurbsSurface
            from psonurbs.geometry.trim import Trim

            exact = NurbsSurface.from_dict(surface)  # what the JSON says, to the last digit
            obj_extra, exports = render_exports(exact, formats, _export_name(path.stem), len(vertices),
                                                Trim.from_list(surface.get("trim")))
            extra_files.update(exports)
        metrics = result.metrics
        row.topology = result.topology
        net = job.config.net_size if searched is None else searched["net_size"]
        row.net = "x".join(str(n) for n in net)  # distinct control points
        if searched is not None and not searched["met"]:
            from psonurbs.fitting.search.tolerance import tolerance_sentence

            row.unmet = tolerance_sentence(searched)
        _row_figures(row, metrics)
        row.notes = notes
        row.warnings = list(result.warnings)
        if trim is not None and "3dm" in formats:
            from psonurbs.formats.cad import TRIM_3DM_NOTE

            notes.append(TRIM_3DM_NOTE.replace("STEM", path.stem))
        outputs = dict(document=document, vertices=vertices, triangles=triangles,
                       curve_header=list(result.curve_header), curve_rows=result.curve,
                       obj_extra=obj_extra, extra_files=extra_files)
        row.seconds = time.perf_counter() - start
        return FitOutcome(row, path.stem, outputs, dict(metrics))
    except KeyboardInterrupt:
        raise
    except Exception as e:
        return FitOutcome(_failed(row, path, e, time.perf_counter() - start), path.stem)


def _object_outcome(job: Job, cloud: Cloud, whole, formats: Sequence[str], row: Row, start: float) -> FitOutcome:
    """The outputs of an object fitted as several faces (:mod:`psonurbs.objects.whole`):
    JSON ``surfaces`` (each like ``surface``, with its trims, topology and metrics), one
    mesh of every face, the faces' error curves, STEP and IGES of the sewn shell."""
    import psonurbs

    surfaces = []
    for face in whole.faces:
        entry = face.surface.to_dict()
        if face.trim is not None:
            entry["trim"] = face.trim.to_list()
        surfaces.append({**entry, "topology": face.topology, "metrics": face.metrics,
                         "notes": face.info.get("notes", [])})
    notes = [*cloud.notes, *whole.notes]
    document = {
        "psonurbs_version": psonurbs.__version__,
        "cloud": job.path.name,
        "topology": "object",
        "surfaces": surfaces,
        "metrics": whole.metrics,
        "fit": {"object": {"shell": whole.shell, "faces": [face.info.get("region_fit", {}) for face in whole.faces]}},
        "notes": notes,
        "config": job.config.to_dict(),
    }
    meshes = [_mesh(face.surface, face.trim, job.config.tessellation) for face in whole.faces]
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])
    vertices = np.concatenate([v for v, _ in meshes])
    triangles = np.concatenate([t + o for (_, t), o in zip(meshes, offsets)])
    extra_files, shape = {}, whole.shape
    for fmt in formats:
        if fmt in ("step", "iges") and shape is None:  # not joined: the faces side by side
            from psonurbs.formats.step import compound_of

            shape = compound_of([(face.surface, face.trim) for face in whole.faces])
        if fmt == "step":
            from psonurbs.formats.step import render_step_shape

            extra_files[".step"] = render_step_shape(shape, _export_name(job.path.stem))
        elif fmt == "iges":
            from psonurbs.formats.step import render_iges_shape

            extra_files[".igs"] = render_iges_shape(shape)
        else:
            notes.append(f"{fmt} holds one surface: not written for an object of {len(whole.faces)} faces "
                         "(its faces are in the STEP and IGES files)")
    metrics = whole.metrics
    row.topology = "object"
    row.net = f"{len(whole.faces)} faces"
    tolerance = metrics.get("tolerance")
    if tolerance is not None and not tolerance["met"]:
        measured = {"p99": metrics["p99"], "max": metrics["max_error"], "rms": metrics["rmse"]}[tolerance["measure"]]
        row.unmet = (f"tolerance {tolerance['value']:.1e} ({tolerance['measure']}) not met: "
                     f"{measured:.1e} with {len(whole.faces)} faces")
    _row_figures(row, metrics)
    row.notes = notes
    row.warnings = list(whole.warnings)
    outputs = dict(document=document, vertices=vertices, triangles=triangles,
                   curve_header=list(whole.curve_header), curve_rows=whole.curve,
                   obj_extra="", extra_files=extra_files)
    row.seconds = time.perf_counter() - start
    return FitOutcome(row, job.path.stem, outputs, dict(metrics))


def _failed(row: Row, path: Path, error: Exception, seconds: float) -> Row:
    """``row`` for a cloud that failed: ``bad-input`` for a PsonurbsError (the message
    starting with the path), ``internal-error`` with the traceback for anything else."""
    if isinstance(error, PsonurbsError):
        message = str(error)
        prefix = f"{path}: "
        row.status, row.message = BAD_INPUT, message if message.startswith(prefix) else prefix + message
    elif isinstance(error, LinAlgError):  # a net these points and this smoothing leave undecided
        row.status = BAD_INPUT
        row.message = (f"{path}: the least-squares system of the fit is singular ({error}): the points cannot decide "
                       "this net; use a smaller net_size or a smoothing above 0")
    else:  # a bug: reported in the row, the batch goes on
        row.status = INTERNAL
        row.message = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
        row.detail = traceback.format_exc()
    row.seconds = seconds
    return row


TOLERANCE_COLUMNS = ["net_u", "net_v", "control_points", "achieved", "met", "seconds", "swarm"]
SWARM_KINDS = ("uniform", "swarm", "rational")  # fit.tolerance.searched's knots: the CSV's swarm column 0, 1, 2


def _tolerance_csv(searched: dict) -> str:
    """STEM_tolerance.csv: one row per net the search fitted (``fit.tolerance.searched``),
    achieved in cloud units, met as 1 or 0, control points nu x nv, swarm 1 where the
    swarm placed the knots, 2 where it chose the weights too (0: uniform knots, the
    classical fit)."""
    from psonurbs.formats.outputs import render_csv

    rows = [[*step["net_size"], step["net_size"][0] * step["net_size"][1], step["achieved"], step["achieved"] <= searched["value"],
             step["seconds"], SWARM_KINDS.index(step["knots"])] for step in searched["searched"]]
    return render_csv(TOLERANCE_COLUMNS, np.array(rows, float).reshape(-1, len(TOLERANCE_COLUMNS)))


def _export_name(stem: str) -> str:
    """The surface's name inside CAD files: the stem, on one line, encodable as UTF-8."""
    return "".join(c if c.isprintable() else "_" for c in printable(stem)) or "surface"


def _mesh(surface, trim, tessellation: tuple[int, int]):
    """The surface's triangle mesh (vertices, triangles), clipped to the trim if any."""
    if trim is None:
        return surface.tessellate(*tessellation)
    from psonurbs.geometry.trim import trimmed_mesh

    vertices, triangles, _ = trimmed_mesh(surface, trim, *tessellation)
    return vertices, triangles


def _row_figures(row: Row, metrics: dict) -> None:
    """The summary row's rmse, max_error and their relative forms, from a fit's metrics."""
    for key in ("rmse", "max_error", "rmse_relative", "max_error_relative"):
        setattr(row, key, _number(metrics.get(key)))


def _number(x) -> float | None:
    return None if x is None else float(x)


def _finish(outcome: FitOutcome, out_dir: Path, gate: Gate) -> Row:
    """In the parent: write a successful fit's files, apply the gate; returns the row."""
    from psonurbs.formats.outputs import write_fit_outputs

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
    reason = gate.check(outcome.metrics, row.warnings, row.unmet) if outcome.metrics else ""
    if reason:
        row.status = GATE
    elif row.warnings:
        row.status = SUSPECT
    row.message = "; ".join([m for m in [reason, *row.notes] if m])
    return row


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
              on_iteration: Callable[[int, float, float], None] | None = None,
              fit: Callable | None = None, scheduler: Scheduler | None = None) -> list[Row]:
    """Fit every job; returns one row per job, in the order of ``jobs``.

    ``on_row(row)`` is called in this process as each cloud finishes (in completion
    order). ``fit`` is the fitter (see :func:`fit_job`; with workers or a cluster, it must
    be importable by name). ``on_iteration`` is passed to the fit when it runs in this
    process (``workers == 1``, no scheduler). With a ``scheduler``
    (:class:`~psonurbs.run.cluster.Scheduler`) the fits run on a dask cluster instead of
    ``workers`` processes (:mod:`psonurbs.run.cluster`); this process still reads the
    clouds and writes every file. KeyboardInterrupt propagates after the pool is stopped
    (the futures cancelled); the outputs of the clouds already finished are complete, the
    others are not written.
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
    if scheduler is not None:
        for k, row in pending_reports.items():
            done(k, row)
        _run_on_cluster(jobs, todo, scheduler, formats, fit, lambda k, row: done(k, row),
                        lambda outcome: _finish(outcome, out_dir, gate))
        return rows  # type: ignore[return-value]
    if workers <= 1 or len(todo) <= 1:
        keep_freed_memory()  # this process fits
        for k in range(len(jobs)):
            if k in pending_reports:
                done(k, pending_reports[k])
                continue
            outcome = fit_job(jobs[k], formats, on_iteration, fit)
            done(k, _finish(outcome, out_dir, gate))
        return rows  # type: ignore[return-value]

    for k, row in pending_reports.items():
        done(k, row)

    def failed(k: int, error: str, trace: str) -> None:
        done(k, Row(str(jobs[k].path), status=INTERNAL, detail=trace, message=f"worker process failed: {error}"))

    pool_run(fit_job, {k: (jobs[k], tuple(formats), None, fit) for k in todo}, min(workers, len(todo)),
             lambda k, outcome: done(k, _finish(outcome, out_dir, gate)), failed,
             lambda k, how: done(k, worker_lost_row(str(jobs[k].path), how)))
    return rows  # type: ignore[return-value]


def _run_on_cluster(jobs: Sequence[Job], todo: Sequence[int], scheduler: Scheduler, formats: Sequence[str],
                    fit: Callable | None, done: Callable[[int, Row], None],
                    finish: Callable[[FitOutcome], Row]) -> None:
    """Read each cloud here as the cluster has room, fit it there, write it here."""
    from psonurbs.run.cluster import cluster_run, stop_if_cancelled

    read_seconds: dict[int, float] = {}

    def prepare(k: int) -> tuple | None:
        start = time.perf_counter()
        cloud = read_job(jobs[k])
        if isinstance(cloud, FitOutcome):  # unreadable: its row, no task
            done(k, cloud.row)
            return None
        read_seconds[k] = time.perf_counter() - start
        return (jobs[k], cloud, tuple(formats), stop_if_cancelled, fit)

    def result(k: int, outcome: FitOutcome) -> None:
        outcome.row.seconds = (outcome.row.seconds or 0.0) + read_seconds.pop(k, 0.0)
        done(k, finish(outcome))

    def lost(k: int, how: str) -> None:
        done(k, worker_lost_row(str(jobs[k].path), how))

    def failed(k: int, message: str, trace: str) -> None:
        done(k, Row(str(jobs[k].path), status=INTERNAL, message=message, detail=trace))

    cluster_run(fit_cloud, todo, prepare, scheduler, result, lost, failed)
