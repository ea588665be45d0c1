"""``psonurbs`` command-line interface.

The commands parse their arguments, call the library and report; no algorithms
live here. Exit codes (also in ``psonurbs fit --help``):

    0    every cloud was fitted (and passed the gate)
    1    internal error (a bug in psonurbs)
    2    unusable input or config (usage errors too)
    3    a fit is above --max-rmse / --max-rmse-rel (or suspect, with --fail-suspect)
    4    a worker process died or was lost while fitting a cloud (killed, out of memory)
    130  interrupted (Ctrl-C)
    143  terminated (SIGTERM)

When several apply, the most severe wins: 143 > 130 > 1 > 4 > 2 > 3 > 0. Every error is
one line on stderr, ``psonurbs: error: ...`` (click's usage errors included).
"""
from __future__ import annotations

import math
import os
import signal
import sys
import traceback
from pathlib import Path

import click

import psonurbs
from psonurbs.config import AUTO_INTEGER, CHOICE, FIELDS, INTEGER, NUMBER, load_config, option_help
from psonurbs.errors import ConfigError, PsonurbsError
from psonurbs.formats.cad import FORMATS, check_formats
from psonurbs.run.batch import preflight, run_batch
from psonurbs.run.cluster import Scheduler, check_available
from psonurbs.run.gate import Gate
from psonurbs.run.inputs import Job, expand_inputs, jobs_from_inputs
from psonurbs.run.summary import (
    EXIT_GATE,
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_TERMINATED,
    WORKER_LOST,
    Row,
    Terminated,
    exit_code,
    raise_terminated,
    write_summary,
)

_CONTROL = {c: f"\\x{c:02x}" for c in [*range(32), 127]}
_CONTROL.update({ord("\n"): "\\n", ord("\r"): "\\r", ord("\t"): "\\t"})


def one_line(text: str) -> str:
    """``text`` safe to print as one line: control characters (a newline in a file name)
    escaped, and the undecodable bytes of a file name (surrogates) shown as ``\\xff``."""
    text = text.translate(_CONTROL)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        text = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    return text


def _error(message: str) -> None:
    click.echo(f"psonurbs: error: {one_line(message)}", err=True)


def _internal_error(error: BaseException | str, trace: str = "") -> None:
    debug = os.environ.get("PSONURBS_DEBUG") == "1"
    if debug:
        if trace:
            click.echo(trace.rstrip("\n"), err=True)
        elif isinstance(error, BaseException):
            traceback.print_exc()
    if isinstance(error, BaseException):
        error = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
    click.echo(f"psonurbs: internal error: {one_line(error)}", err=True)
    if not debug:
        click.echo("psonurbs: this is a bug; set PSONURBS_DEBUG=1 to see the traceback", err=True)


def _finite(ctx, param, value):
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"expected a finite number, got {value}")
    return value


def _stopped(stop: KeyboardInterrupt) -> int:
    """Report a Ctrl-C (130) or a SIGTERM (143) and return its exit code."""
    if isinstance(stop, Terminated):
        click.echo("psonurbs: terminated", err=True)
        return EXIT_TERMINATED
    click.echo("psonurbs: interrupted", err=True)
    return EXIT_INTERRUPTED


def _run(ctx: click.Context, action):
    """``action()``, with its failures turned into the documented exit codes."""
    try:
        return action()
    except PsonurbsError as e:
        _error(str(e))
        ctx.exit(EXIT_INPUT)
    except KeyboardInterrupt as stop:
        ctx.exit(_stopped(stop))
    except Exception as e:
        _internal_error(e)
        ctx.exit(EXIT_INTERNAL)


def _fitter(ctx: click.Context):
    """The fitting function: ``None`` (the real pipeline) unless the caller put one in the
    context object (``cli.main(obj={"fit": ...})``, as the tests do)."""
    return (ctx.obj or {}).get("fit")


# ---- options shared by several commands -------------------------------------------------

def gate_options(what: str):
    """``--max-rmse`` and ``--max-rmse-rel`` (fit, score)."""
    def add(command):
        command = click.option("--max-rmse-rel", type=click.FloatRange(min=0), default=None, callback=_finite,
                               metavar="X", help=f"Gate: exit 3 if {what} rmse divided by the cloud's "
                                                 "bounding-box diagonal is above X.")(command)
        return click.option("--max-rmse", type=click.FloatRange(min=0), default=None, callback=_finite,
                            metavar="X", help=f"Gate: exit 3 if {what} rmse is above X (cloud units).")(command)
    return add


def jobs_option(help_text: str):
    return click.option("--jobs", "-j", type=click.IntRange(min=1), default=1, show_default=True, metavar="N",
                        help=help_text)


quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress bar.")


def auto_or_n(text: str):
    """An option's ``auto`` or integer (checked further by the config's own rules)."""
    return text if text == "auto" else int(text)


def config_options(command):
    """The options that override a config key (``--seed``, ``--topology``, ...): one per key
    of the config's table that names one, in its order, with its help; the value is checked
    by the config's own rules (:meth:`psonurbs.config.FitConfig.with_overrides`)."""
    for f in reversed([f for f in FIELDS.values() if f.option]):
        kind = click.Choice(f.choices) if f.kind == CHOICE else {INTEGER: int, NUMBER: float, AUTO_INTEGER: auto_or_n}[f.kind]
        command = click.option(f.option, type=kind, default=None, help=option_help(f.key))(command)
    return command


class _Commands(click.Group):
    """The command group, reporting click's own errors as the tool does its own: one line
    ``psonurbs: error: ...`` on stderr and exit 2 (a usage error is unusable input), instead
    of click's ``Usage: ...`` block."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.UsageError as e:
            hint = f"; see 'psonurbs {e.ctx.info_name} --help'" if e.ctx is not None and e.ctx.parent else ""
            _error(f"{e.format_message().rstrip('.')}{hint}")
            code = EXIT_INPUT
        except click.ClickException as e:
            _error(e.format_message())
            code = e.exit_code
        except click.exceptions.Abort:  # Ctrl-C or end of input while click prompts or parses
            click.echo("psonurbs: interrupted", err=True)
            code = EXIT_INTERRUPTED
        if not standalone_mode:
            return code
        sys.exit(code if isinstance(code, int) else EXIT_OK)


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(psonurbs.__version__, "--version", prog_name="psonurbs")
def cli() -> None:
    """Fit NURBS surfaces to 3D point clouds by particle swarm optimisation."""


@cli.command("fit")
@click.argument("clouds", nargs=-1, required=True, metavar="CLOUD [CLOUD ...]")
@click.option("--config", "-c", "config_path", metavar="CFG.yaml",
              type=click.Path(path_type=Path),
              help="YAML config (orders, net_size, topology, swarm, ...). "
                   "Without it the defaults are used.")
@click.option("--out", "-o", "out_dir", metavar="DIR", required=True,
              type=click.Path(file_okay=False, path_type=Path),
              help="Directory for the outputs (created if needed).")
@config_options
@jobs_option("Fit clouds in N worker processes (one BLAS thread each); the files are identical "
             "to --jobs 1.")
@click.option("--scheduler", metavar="ADDRESS", default=None,
              help="Fit the clouds on a dask cluster instead: a scheduler address (tcp://host:8786), "
                   "a scheduler file (scheduler.json), or local:N for N local worker processes. "
                   "Needs the dask extra; the files are identical to --jobs 1.")
@click.option("--format", "formats", type=click.Choice(FORMATS), multiple=True,
              help="Also export the exact surface (trimmed to its loops if it has any): 3dm "
                   "(Rhino; needs rhino3dm), iges (IGES 5.3 entity 128, trimmed: 144, STEM.igs), "
                   "obj-nurbs (a 'cstype rat bspline' block in STEM.obj, with trim/hole), step "
                   "(STEP AP214 face, STEM.step; needs cadquery-ocp). Repeatable.")
@gate_options("a fit's")
@click.option("--fail-suspect", is_flag=True,
              help="Gate: exit 3 if a fit fails a self-check (surface or net far outside the "
                   "cloud's box, a fold, surface far from every point).")
@click.option("--fail-unmet", is_flag=True,
              help="Gate: exit 3 if a fit to a tolerance (--tolerance, --tolerance-rel) does not meet it.")
@quiet_option
@click.pass_context
def fit(ctx: click.Context, clouds: tuple[str, ...], config_path: Path | None, out_dir: Path,
        seed: int | None, particles: int | None, iterations: int | None,
        topology: str | None, strategy: str | None, parametrisation: str | None,
        tolerance: float | None, tolerance_rel: float | None, patches: int | str | None, jobs: int,
        scheduler: str | None, formats: tuple[str, ...], max_rmse: float | None, max_rmse_rel: float | None,
        fail_suspect: bool, fail_unmet: bool, quiet: bool) -> None:
    """Fit a NURBS surface to each CLOUD (.ply, .pcd, .xyz, .txt, .pts; .las, .laz, .e57 with the scan extra).

    A CLOUD may be a file, a directory (its cloud files) or a quoted glob
    pattern ('scans/*.ply', 'scans/**/*.xyz'). For a cloud with file stem
    STEM, writes to DIR:

    \b
      STEM.json        the surface (degrees, knots, control net, weights),
                       metrics (rmse, max_error, ...), fit info and config
      STEM.ply, .obj   the tessellated surface as a triangle mesh
      STEM_error.csv   the error curve, one row per swarm iteration
      STEM_tolerance.csv  with a tolerance: the nets the search tried
      STEM.igs, .3dm   with --format iges / 3dm
      STEM.step        with --format step

    and for the run, summary.csv and summary.json: one row per cloud (file,
    points, topology, net, rmse, max_error, relative figures, seconds, status,
    message). A cloud that cannot be used is reported on stderr and in the
    summary, and the others are still fitted. A fit that fails a self-check
    (no ground truth needed) is written, warned about on stderr and marked
    'suspect' in the summary. The same inputs give
    byte-identical outputs (3dm files aside: openNURBS stamps them; and a
    tolerance search's seconds per net).

    Examples:

    \b
      psonurbs fit scan.ply -o results/
      psonurbs fit data_samples/franke_noisy.ply -c data_samples/franke_noisy.yaml -o results/
      psonurbs fit scans/*.ply -c configs/patch.yaml -o results/ --seed 3 -q
      psonurbs fit scans/ -o results/ --jobs 4 --format iges --format obj-nurbs
      psonurbs fit 'survey/*.laz' -o results/ --scheduler tcp://head-node:8786 -q
      psonurbs fit 'scans/**/*.ply' -o results/ --max-rmse-rel 1e-3 -q   # CI gate
      psonurbs fit dome.xyz -o results/ --topology sphere --particles 20 --iterations 100
      psonurbs fit scan.ply -c part.yaml -o results/ --tolerance-rel 3e-4 --fail-unmet

    Exit codes:

    \b
      0    every cloud was fitted (and passed the gate)
      1    internal error (a bug in psonurbs)
      2    unusable input or config (with several clouds: at least one
           could not be used; the others were still fitted)
      3    gate exceeded: a fit's rmse is above --max-rmse or --max-rmse-rel,
           it is suspect with --fail-suspect, or it does not meet its
           tolerance with --fail-unmet (its files are written; the others
           are still fitted)
      4    a worker process died while fitting a cloud (with --jobs N:
           killed, out of memory; with --scheduler: lost twice); the
           others are still fitted
      130  interrupted (Ctrl-C); no half-written files are left
      143  terminated (SIGTERM, e.g. a CI timeout); no half-written files

    When several apply, the most severe wins: 143 > 130 > 1 > 4 > 2 > 3.
    """
    try:
        code = _fit_all(clouds, config_path, out_dir, quiet, jobs, scheduler, formats,
                        Gate(max_rmse, max_rmse_rel, fail_suspect, fail_unmet), _fitter(ctx),
                        dict(seed=seed, particles=particles, iterations=iterations,
                             topology=topology, strategy=strategy, parametrisation=parametrisation,
                             tolerance=tolerance, tolerance_rel=tolerance_rel, patches=patches))
    except KeyboardInterrupt as stop:
        code = _stopped(stop)
    except Exception as e:  # a bug outside a cloud's fit
        _internal_error(e)
        code = EXIT_INTERNAL
    ctx.exit(code)


def _fit_all(clouds: tuple[str, ...], config_path: Path | None, out_dir: Path, quiet: bool,
             jobs: int, scheduler: str | None, formats: tuple[str, ...], gate: Gate, fitter,
             overrides: dict) -> int:
    try:
        config = load_config(config_path).with_overrides(**overrides)
        formats = check_formats(formats)
        preflight(config, str(config_path) if config_path else "the default config with the command-line options")
        cluster = _cluster(scheduler, jobs)
    except ConfigError as e:
        _error(str(e))
        return EXIT_INPUT
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        _error(f"{out_dir}: cannot create the output directory ({e.strerror or e})")
        return EXIT_INPUT
    work = jobs_from_inputs(expand_inputs(clouds), config)
    try:
        rows = _run_and_report(work, out_dir, formats, jobs, gate, quiet, fitter, cluster)
    except ConfigError as e:  # the scheduler cannot be reached, or its workers lack psonurbs
        _error(str(e))
        return EXIT_INPUT
    code = exit_code(rows)
    try:
        write_summary(out_dir, rows, gate)
    except OSError as e:
        _error(f"{out_dir}: cannot write the run summary ({e.strerror or e})")
        code = code if code == EXIT_INTERNAL else EXIT_INPUT
    return code


def _cluster(scheduler: str | None, jobs: int) -> Scheduler | None:
    """The parsed ``--scheduler`` (ConfigError: malformed, combined with --jobs, no dask)."""
    if scheduler is None:
        return None
    if jobs > 1:
        raise ConfigError("--scheduler and --jobs do not go together: the cluster's workers do the work")
    parsed = Scheduler.parse(scheduler)
    check_available()
    return parsed


def _progress_enabled(quiet: bool) -> bool:
    return not quiet and sys.stderr.isatty()


def _run_and_report(work: list[Job], out_dir: Path, formats: tuple[str, ...], jobs: int,
                    gate: Gate, quiet: bool, fitter=None, scheduler: Scheduler | None = None) -> list[Row]:
    """Run the batch with the progress bars; report each cloud as it finishes."""
    from tqdm import tqdm

    from psonurbs import progress

    show = _progress_enabled(quiet)
    several = len(work) > 1
    clouds_bar = tqdm(total=len(work), desc="clouds", unit="cloud", file=sys.stderr,
                      disable=not (show and several), leave=False, dynamic_ncols=True)
    swarm_bar = None
    if len(work) == 1 and scheduler is None:
        swarm_bar = tqdm(total=work[0].config.swarm.iterations, desc=work[0].path.name, unit="it",
                         file=sys.stderr, disable=not show, leave=False, dynamic_ncols=True)

    def on_iteration(iteration: int, best: float, mean: float) -> None:
        if swarm_bar is not None:
            if swarm_bar.total is None or swarm_bar.n < swarm_bar.total:
                swarm_bar.update(1)
            swarm_bar.set_postfix_str(f"best {best:.3g}", refresh=False)

    def on_stage(text: str, iterations: int | None) -> None:  # a net of a search, a region of an object
        swarm_bar.set_description_str(f"{work[0].path.name}: {text}", refresh=False)
        swarm_bar.set_postfix_str("", refresh=False)
        swarm_bar.bar_format = None if iterations and iterations > 1 else "{desc} [{elapsed}]"  # no swarm: the time
        swarm_bar.reset()
        swarm_bar.total = iterations  # (reset(total=None) would keep the last stage's total)

    def on_row(row: Row) -> None:
        if swarm_bar is not None:
            swarm_bar.close()
        with tqdm.external_write_mode(file=sys.stderr):
            _report(row)
        clouds_bar.update(1)

    try:
        with progress.reporting(on_stage if swarm_bar is not None and show else None):
            return run_batch(work, out_dir, formats=formats, workers=jobs, gate=gate,
                             on_row=on_row, on_iteration=on_iteration, fit=fitter, scheduler=scheduler)
    finally:
        if swarm_bar is not None:
            swarm_bar.close()
        clouds_bar.close()


def _report(row: Row) -> None:
    if row.status in ("bad-input", WORKER_LOST):
        _error(row.message)
        return
    if row.status == "internal-error":
        _internal_error(f"{row.file}: {row.message}", row.detail)
        return
    name = one_line(Path(row.file).name)
    line = (f"{name}: {row.points} points, net {row.net} ({row.topology}), "
            f"rmse {row.rmse:.2e}, max {row.max_error:.2e}, {row.seconds:.1f} s")
    click.echo("; ".join([line, *row.notes]))
    for warning in row.warnings:
        click.echo(f"psonurbs: warning: {one_line(row.file)}: suspect fit: {warning}", err=True)
    if row.unmet:
        click.echo(f"psonurbs: warning: {one_line(row.file)}: {row.unmet}", err=True)
    if row.status == "gate-exceeded":
        gate_reason = row.message.split("; ")[0]
        click.echo(f"psonurbs: gate exceeded: {one_line(row.file)}: {gate_reason}", err=True)


@cli.command("score")
@click.argument("surface_path", metavar="SURFACE.json", type=click.Path(path_type=Path))
@click.argument("cloud", metavar="CLOUD", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")
@gate_options("the")
@click.pass_context
def score_command(ctx: click.Context, surface_path: Path, cloud: Path, as_json: bool,
                  max_rmse: float | None, max_rmse_rel: float | None) -> None:
    """Distances from CLOUD to the surface saved in SURFACE.json.

    SURFACE.json is a fit's STEM.json (or a bare surface object). Prints the
    rmse, max, mean and percentiles of the point-to-surface distances (to the
    trimmed face when the surface has trim loops), in the cloud's units and
    relative to its bounding-box diagonal.

    \b
      psonurbs score results/scan.json new_scan.ply
      psonurbs score results/scan.json new_scan.ply --json --max-rmse-rel 1e-3

    Exit codes: 0 ok, 1 internal error, 2 unusable surface or cloud, 3 above
    --max-rmse / --max-rmse-rel, 130 interrupted, 143 terminated.
    """
    from psonurbs.formats.clouds import read_cloud
    from psonurbs.run.scoring import load_faces, score

    def measure():
        return score(load_faces(surface_path)[0], read_cloud(cloud))

    figures = _run(ctx, measure)
    reason = Gate(max_rmse, max_rmse_rel).check(figures)
    if as_json:
        import json

        click.echo(json.dumps({"surface": str(surface_path), "cloud": str(cloud), **figures}))
    else:
        rows = [("points", str(figures["points"]), "")]
        for key, label in [("rmse", "rmse"), ("max_error", "max"), ("mean_error", "mean"),
                           *[(k, k) for k in figures if k.startswith("p") and k[1:].isdigit()]]:
            rel = figures[f"{key}_relative"]
            rows.append((label, f"{figures[key]:.6g}", "" if rel is None else f"{rel:.3e}"))
        rows.append(("bbox diagonal", f"{figures['bbox_diagonal']:.6g}", ""))
        click.echo(f"{surface_path} vs {cloud}")
        click.echo(f"  {'':<14}{'value':>14}  {'/ diagonal':>11}")
        for label, value, rel in rows:
            click.echo(f"  {label:<14}{value:>14}  {rel:>11}")
    if reason:
        click.echo(f"psonurbs: gate exceeded: {cloud}: {reason}", err=True)
        ctx.exit(EXIT_GATE)
    ctx.exit(EXIT_OK)


@cli.command("plot")
@click.argument("result", metavar="RESULT_DIR/STEM.json", type=click.Path(path_type=Path))
@click.option("--cloud", type=click.Path(path_type=Path), default=None,
              help="The fitted cloud (default: the JSON's 'cloud' file name, beside the "
                   "JSON or in the current directory; without it, surface and net only).")
@click.option("--out", "-o", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Directory for the PNGs (default: beside the JSON).")
@click.pass_context
def plot_command(ctx: click.Context, result: Path, cloud: Path | None, out_dir: Path | None) -> None:
    """Draw a fit: PNG pictures beside its JSON (needs matplotlib; no display).

    \b
      STEM_curve.png     error curve: best and mean RMSE per iteration, log scale
      STEM_views.png     cloud, fitted (trimmed) surface and control net, four views
      STEM_distance.png  the points coloured by their distance to the surface
      STEM_domain.png    the parameter domain: foot points, knot lines, trim loops
      STEM_basis.png     the basis functions of both knot vectors
      STEM_tolerance.png with a tolerance: error against control points of
                         the nets the search tried

    Exit codes: 0 ok, 1 internal error, 2 unusable input or matplotlib missing,
    130 interrupted, 143 terminated.
    """
    from psonurbs.run.plots import plot_result

    written, notes = _run(ctx, lambda: plot_result(result, out_dir, cloud))
    for note in notes:
        click.echo(f"psonurbs: note: {note}", err=True)
    for path in written:
        click.echo(str(path))
    ctx.exit(EXIT_OK)


@cli.command("demo")
@click.argument("out_dir", metavar="OUT", type=click.Path(file_okay=False, path_type=Path))
@jobs_option("Worker processes.")
@quiet_option
@click.pass_context
def demo_command(ctx: click.Context, out_dir: Path, jobs: int, quiet: bool) -> None:
    """Write two sample clouds with their configs to OUT/clouds and fit them to OUT/results.

    A first run without data of your own: a Gaussian bump (open patch) and a
    quarter cylinder (exact only with rational weights), small swarms, a few
    seconds. Then look at a fit with `psonurbs plot OUT/results/bump.json`.

    Exit codes: as `psonurbs fit`.
    """
    from psonurbs.config import load_config
    from psonurbs.run.demo import write_samples

    try:
        samples = write_samples(out_dir / "clouds")
        work = [Job(cloud, load_config(config)) for cloud, config in samples]
        results = out_dir / "results"
        click.echo(f"wrote {len(samples)} sample clouds and their configs to {out_dir / 'clouds'}")
        rows = _run_and_report(work, results, (), jobs, Gate(), quiet, _fitter(ctx))
        write_summary(results, rows)
    except KeyboardInterrupt as stop:
        ctx.exit(_stopped(stop))
    except (OSError, PsonurbsError) as e:
        _error(str(e))
        ctx.exit(EXIT_INPUT)
    code = exit_code(rows)
    if code == EXIT_OK:
        click.echo(f"results and summary.csv in {results}; next:")
        cloud, config = samples[0]
        click.echo(f"  psonurbs fit {cloud} -c {config} -o {results} --format iges")
        click.echo(f"  psonurbs score {results / 'bump.json'} {cloud}")
        click.echo(f"  psonurbs plot {results / 'bump.json'} --cloud {cloud}")
    ctx.exit(code)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point (``psonurbs``). SIGTERM stops it like Ctrl-C."""
    signal.signal(signal.SIGTERM, raise_terminated)
    cli.main(args=argv, prog_name="psonurbs")


if __name__ == "__main__":
    main()
