"""What given inner knots make of a cloud through the whole pipeline.

    python benchmarks/knot_oracle.py CLOUD --config CONFIG --knots-u 0.2 0.32 0.38 0.5 0.6 0.72 0.78 0.9 --out DIR
    python benchmarks/knot_oracle.py CLOUD --config CONFIG --knots-v ... --out DIR --gt CASE.gt.npz --scorer SCORE_PY

The swarm's fitness judges a knot vector at the first parameters, its validation after
ten rounds of parameter correction; the fit the user gets has had the whole polish and
the refinement with it. This runs the pipeline as the classical fit (one particle, one
iteration) with its uniform inner knots replaced by the given ones (one direction or
both; a direction not given stays uniform), so that they go through the polishes, the
refinement and the trim as uniform knots do, and writes the fit's files to DIR as
``psonurbs fit`` does. With ``--gt`` the scorer (``benchmarks/score.py``, or
``--scorer``) measures the fit against the truth and its line is printed. README (The
swarm: what it buys and what it costs) has what hand-placed knots did on the steps.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from psonurbs.fitting import hybrid

BENCH = Path(__file__).resolve().parent


def with_inner_knots(inner_u: list[float] | None, inner_v: list[float] | None):
    """Make the classical start of every search carry these inner knots (restored by the
    returned function)."""
    uniform = hybrid.KnotWeightSearch.classical

    def classical(search: hybrid.KnotWeightSearch) -> np.ndarray:
        x = uniform(search)
        cu, cv = search.counts
        for given, start, count, name in ((inner_u, 0, cu, "u"), (inner_v, cu, cv, "v")):
            if given is None:
                continue
            if len(given) != count or np.any(np.diff(given) <= 0) or min(given) <= 0 or max(given) >= 1:
                raise SystemExit(f"--knots-{name}: {count} increasing values inside (0, 1) for this net")
            x[start:start + count] = given
        return x

    hybrid.KnotWeightSearch.classical = classical
    return lambda: setattr(hybrid.KnotWeightSearch, "classical", uniform)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cloud", type=Path)
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--knots-u", type=float, nargs="+")
    ap.add_argument("--knots-v", type=float, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--gt", type=Path, help="the case's ground truth (CASE.gt.npz): score the fit against it")
    ap.add_argument("--scorer", type=Path, default=BENCH / "score.py", metavar="SCORE_PY")
    args = ap.parse_args(argv)
    from psonurbs.cli.main import main as command_line

    restore = with_inner_knots(args.knots_u, args.knots_v)
    try:
        command_line(["fit", str(args.cloud), "--config", str(args.config), "--particles", "1",
                      "--iterations", "1", "--out", str(args.out), "--quiet"])
    except SystemExit as stop:  # the command line's own exit: an error, or knots that do not fit the net
        if stop.code not in (None, 0):
            raise
    finally:
        restore()
    if args.gt is not None:
        scored = subprocess.run([sys.executable, str(args.scorer), str(args.cloud), str(args.out), "--gt", str(args.gt)],
                                capture_output=True, text=True)
        print(scored.stdout.strip() or scored.stderr.strip())
        return scored.returncode
    return 0


if __name__ == "__main__":
    sys.exit(main())
