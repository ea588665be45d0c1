"""What given inner knots make of a cloud through the whole pipeline.

    python benchmarks/knot_oracle.py CLOUD --config CONFIG --knots-u 0.2 0.32 0.38 0.5 0.6 0.72 0.78 0.9 --out DIR
    python benchmarks/knot_oracle.py CLOUD --config CONFIG --knots-v ... --out DIR --gt CASE.gt.npz --scorer SCORE_PY
    python benchmarks/knot_oracle.py CLOUD --config CONFIG --random 12 --out DIR --gt CASE.gt.npz

The swarm's fitness judges a knot vector at the first parameters, its validation after
ten rounds of parameter correction; the fit the user gets has had the whole polish and
the refinement with it. This runs the pipeline as the classical fit (one particle, one
iteration) with its uniform inner knots replaced by the given ones (one direction or
both; a direction not given stays uniform), so that they go through the polishes, the
refinement and the trim as uniform knots do, and writes the fit's files to DIR as
``psonurbs fit`` does. With ``--gt`` the scorer (``benchmarks/score.py``, or
``--scorer``) measures the fit against the truth and its line is printed.

``--random N`` fits the uniform knots and N mildly uneven vectors in both directions
(inner spans drawn from a Dirichlet distribution of concentration ``--concentration``,
20 by default: spans within about a fifth of uniform; fixed seed ``--seed``), each to
DIR/K, and prints a table of their rmse and truth_rms (``--gt`` needed) and whether the
finished fit's rmse ranks the vectors as their truth does (Spearman): could a search
that judges knots by the fit they end in find the truer ones? README (The swarm: what it
buys and what it costs) has what hand-placed and random knots did on the steps.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from run_cases import outside_score

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


def fit_with(cloud: Path, config: Path, out: Path, inner_u, inner_v) -> None:
    """The classical fit of the cloud with these inner knots (None: uniform), into ``out``."""
    from psonurbs.cli.main import main as command_line

    restore = with_inner_knots(inner_u, inner_v)
    try:
        command_line(["fit", str(cloud), "--config", str(config), "--particles", "1",
                      "--iterations", "1", "--out", str(out), "--quiet"])
    except SystemExit as stop:  # the command line's own exit: an error, or knots that do not fit the net
        if stop.code not in (None, 0):
            raise
    finally:
        restore()


def inner_counts(config: Path) -> tuple[int, int]:
    """Inner knots along u and v of an open net of the config."""
    from psonurbs.config import load_config

    loaded = load_config(config)
    return tuple(int(n) - int(k) for n, k in zip(loaded.net_size, loaded.orders))


def random_search(args) -> int:
    """The uniform knots and ``args.random`` mildly uneven vectors, scored; a table."""
    from scipy.stats import spearmanr

    if args.gt is None:
        raise SystemExit("--random needs --gt (the vectors are compared by their truth error)")
    counts = inner_counts(args.config)
    rng = np.random.default_rng(args.seed)
    rows = []
    print("| vector | inner u | inner v | rmse | truth_rms |")
    print("|---|---|---|---|---|")
    for k in range(args.random + 1):
        inner = [None if k == 0 else np.cumsum(rng.dirichlet(np.full(c + 1, args.concentration)))[:-1].tolist()
                 for c in counts]
        out = args.out / str(k)
        fit_with(args.cloud, args.config, out, *inner)
        figures = outside_score(args.scorer)(args.cloud, out, args.gt)
        shown = ["uniform" if knots is None else " ".join(f"{t:.3f}" for t in knots) for knots in inner]
        rows.append((figures["rmse"], figures["truth_rms"]))
        print(f"| {k} | {shown[0]} | {shown[1]} | {figures['rmse']:.3g} | {figures['truth_rms']:.3g} |", flush=True)
    rmse, truth = np.array(rows).T
    print(f"\nSpearman (rmse, truth_rms) {spearmanr(rmse, truth).correlation:.2f}; truth_rms over the uniform "
          f"knots': least rmse's {truth[np.argmin(rmse)] / truth[0]:.2f}, best {truth.min() / truth[0]:.2f}, "
          f"worst {truth.max() / truth[0]:.2f}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cloud", type=Path)
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--knots-u", type=float, nargs="+")
    ap.add_argument("--knots-v", type=float, nargs="+")
    ap.add_argument("--random", type=int, metavar="N", help="the uniform and N random mildly uneven vectors, scored")
    ap.add_argument("--concentration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--gt", type=Path, help="the case's ground truth (CASE.gt.npz): score the fit against it")
    ap.add_argument("--scorer", type=Path, default=BENCH / "score.py", metavar="SCORE_PY")
    args = ap.parse_args(argv)
    if args.random is not None:
        return random_search(args)
    fit_with(args.cloud, args.config, args.out, args.knots_u, args.knots_v)
    if args.gt is not None:
        print(json.dumps(outside_score(args.scorer)(args.cloud, args.out, args.gt)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
