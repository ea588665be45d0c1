"""``psonurbs`` command-line interface.

The commands parse their arguments, call the library and report; no algorithms
live here. Exit codes (also in ``psonurbs fit --help``):

    0    every cloud was fitted
    1    internal error (a bug in psonurbs)
    2    unusable input or config
    130  interrupted (Ctrl-C)
"""
from __future__ import annotations

import os
import sys
import time
import traceback
from pathlib import Path

import click

import psonurbs
from psonurbs.config import STRATEGIES, TOPOLOGIES, load_config
from psonurbs.errors import ConfigError, InputError, PsonurbsError

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_INTERRUPTED = 130


def _error(message: str) -> None:
    click.echo(f"psonurbs: error: {message}", err=True)


def _cloud_error(path: Path, error: Exception) -> None:
    message = str(error)
    prefix = f"{path}: "
    _error(message if message.startswith(prefix) else prefix + message)


def _internal_error(error: BaseException) -> None:
    debug = os.environ.get("PSONURBS_DEBUG") == "1"
    if debug:
        traceback.print_exc()
    detail = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
    click.echo(f"psonurbs: internal error: {detail}", err=True)
    if not debug:
        click.echo("psonurbs: this is a bug; set PSONURBS_DEBUG=1 to see the traceback", err=True)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(psonurbs.__version__, "--version", prog_name="psonurbs")
def cli() -> None:
    """Fit NURBS surfaces to 3D point clouds by particle swarm optimisation."""


@cli.command("fit")
@click.argument("clouds", nargs=-1, required=True, metavar="CLOUD [CLOUD ...]",
                type=click.Path(path_type=Path))
@click.option("--config", "-c", "config_path", metavar="CFG.yaml",
              type=click.Path(path_type=Path),
              help="YAML config (orders, net_size, topology, swarm, ...). "
                   "Without it the defaults are used.")
@click.option("--out", "-o", "out_dir", metavar="DIR", required=True,
              type=click.Path(file_okay=False, path_type=Path),
              help="Directory for the outputs (created if needed).")
@click.option("--seed", type=int, default=None, help="Override swarm.seed.")
@click.option("--particles", type=int, default=None, help="Override swarm.particles.")
@click.option("--iterations", type=int, default=None, help="Override swarm.iterations.")
@click.option("--topology", type=click.Choice(TOPOLOGIES), default=None,
              help="Override topology.")
@click.option("--strategy", type=click.Choice(STRATEGIES), default=None,
              help="Override strategy.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.pass_context
def fit(ctx: click.Context, clouds: tuple[Path, ...], config_path: Path | None, out_dir: Path,
        seed: int | None, particles: int | None, iterations: int | None,
        topology: str | None, strategy: str | None, quiet: bool) -> None:
    """Fit a NURBS surface to each CLOUD (.ply, .pcd, .xyz, .txt, .pts).

    For a cloud with file stem STEM, writes to DIR:

    \b
      STEM.json        the surface (degrees, knots, control net, weights),
                       metrics (rmse, max_error, ...), fit info and config
      STEM.ply, .obj   the tessellated surface as a triangle mesh
      STEM_error.csv   the error curve, one row per swarm iteration

    A cloud that cannot be used is reported on stderr and skipped; the others
    are still fitted. The same inputs give byte-identical outputs.

    Examples:

    \b
      psonurbs fit scan.ply -o results/
      psonurbs fit data_samples/franke_noisy.ply -c data_samples/franke_noisy.yaml -o results/
      psonurbs fit scans/*.ply -c configs/patch.yaml -o results/ --seed 3 -q
      psonurbs fit dome.xyz -o results/ --topology sphere --particles 20 --iterations 100

    Exit codes:

    \b
      0    every cloud was fitted
      1    internal error (a bug in psonurbs)
      2    unusable input or config (with several clouds: at least one
           could not be used; the others were still fitted)
      130  interrupted (Ctrl-C); no half-written files are left
    """
    try:
        code = _fit_all(clouds, config_path, out_dir, quiet,
                        dict(seed=seed, particles=particles, iterations=iterations,
                             topology=topology, strategy=strategy))
    except KeyboardInterrupt:
        click.echo("psonurbs: interrupted", err=True)
        code = EXIT_INTERRUPTED
    ctx.exit(code)


def _fit_all(clouds: tuple[Path, ...], config_path: Path | None, out_dir: Path, quiet: bool,
             overrides: dict) -> int:
    try:
        config = load_config(config_path).with_overrides(**overrides)
    except ConfigError as e:
        _error(str(e))
        return EXIT_INPUT
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        _error(f"{out_dir}: cannot create the output directory ({e.strerror or e})")
        return EXIT_INPUT

    failed = False
    stems: dict[str, Path] = {}
    for path in clouds:
        stem = path.stem
        if stem in stems:
            _error(f"{path}: has the same name as {stems[stem]}; its outputs would overwrite "
                   f"{out_dir / stem}.*, skipped")
            failed = True
            continue
        stems[stem] = path
        try:
            _fit_one(path, config, out_dir, quiet)
        except PsonurbsError as e:  # InputError, ConfigError
            _cloud_error(path, e)
            failed = True
        except KeyboardInterrupt:
            raise
        except Exception as e:  # a bug: report it briefly and stop
            _internal_error(e)
            return EXIT_INTERNAL
    return EXIT_INPUT if failed else EXIT_OK


def _fit_one(path: Path, config, out_dir: Path, quiet: bool) -> None:
    from tqdm import tqdm

    from psonurbs.io import read_cloud, write_fit_outputs

    points = read_cloud(path)
    from psonurbs.fit import fit_points  # imported late: reading needs no numerics

    start = time.perf_counter()
    bar = tqdm(total=config.swarm.iterations, desc=path.name, unit="it", file=sys.stderr,
               disable=quiet or not sys.stderr.isatty(), leave=False, dynamic_ncols=True)

    def on_iteration(iteration: int, best: float, mean: float) -> None:
        if bar.n < bar.total:
            bar.update(1)
        bar.set_postfix_str(f"best {best:.3g}", refresh=False)

    try:
        result = fit_points(points, config, on_iteration=on_iteration)
    finally:
        bar.close()

    surface = result.surface.to_dict()
    document = {
        "psonurbs_version": psonurbs.__version__,
        "cloud": path.name,
        "topology": result.topology,
        "surface": surface,
        "metrics": result.metrics,
        "fit": result.info,
        "notes": list(result.notes),
        "config": config.to_dict(),
    }
    vertices, triangles = result.surface.tessellate(*config.tessellation)
    try:
        write_fit_outputs(out_dir, path.stem, document, vertices, triangles,
                          result.curve_header, result.curve)
    except OSError as e:
        raise InputError(f"cannot write the outputs to {out_dir} ({e.strerror or e})") from None
    seconds = time.perf_counter() - start

    cp = surface.get("control_points", [])
    nu = len(cp)
    nv = len(cp[0]) if nu else 0
    line = (f"{path.name}: {len(points)} points, net {nu}x{nv} ({result.topology}), "
            f"rmse {result.metrics['rmse']:.2e}, max {result.metrics['max_error']:.2e}, "
            f"{seconds:.1f} s")
    click.echo("; ".join([line, *result.notes]))


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point (``psonurbs``)."""
    cli.main(args=argv, prog_name="psonurbs")


if __name__ == "__main__":
    main()
