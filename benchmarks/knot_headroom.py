#!/usr/bin/env python3
"""How much any knot vector could still buy a cloud, against what the swarm's bought.

    python benchmarks/knot_headroom.py [--only NAME ...] [--scorer SCORE_PY] [--out DIR] [--seed N]

For each cloud with a localised feature (``feature_clouds.py``'s and the public
``step_bump``), three fits by ``psonurbs fit`` at the cloud's own net, scored against the
true surface as ``run_cases.py`` scores them:

- ``classical``: one particle, one iteration (uniform knots, unit weights), truth error T;
- ``noise-free``: the same, on the same sample with the noise left off, truth error T0:
  what uniform knots cost at this net (approximation and parametrisation), the only
  part of T another knot vector can remove;
- ``swarm``: the cloud's own config.

A least-squares fit's truth error is about sqrt(T0^2 + Tn^2), Tn the noise that the
net's unknowns carry into it (about sigma sqrt(unknowns / N), whatever the knots), so
``floor`` = Tn / T = sqrt(1 - (T0 / T)^2) is the least swarm / classical ratio any knots
could reach on the noisy cloud (0 on a noise-free one: there all of T is the knots').

``warp u`` and ``warp v``: how unevenly the classical fit has spread its control rows
over the cloud. Parameter correction moves the points, and with them the rows of the
net, towards where the surface bends: the rows' spacing in the true surface's own
parameters (every cloud here is a height field z(x, y) over the unit square, so x and
y), over the spacing of the knot vector's Greville abscissae (the rows' places on a
surface of uniform speed), largest over smallest, the end rows left out. 1 is no warp;
on a cliff across u the classical fit's u rows crowd into the cliff as knots crowded
there would, and that is the part a knot vector no longer adds.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from cases import CASES, write
from feature_clouds import feature_cases
from run_cases import cell, fit_and_score, outside_score
from score import score

LOCALISED = ["step_bump", "step_diagonal", "cliff_noisy", "twin_ridges", "narrow_bump", "terrace_graded",
             "ridge_curve"]


def greville(knots: np.ndarray, degree: int) -> np.ndarray:
    """The Greville abscissae (n,) of a clamped knot vector: each basis function's mean
    knot, where its control point would sit on a surface of uniform speed."""
    n = len(knots) - degree - 1
    return np.array([knots[i + 1:i + degree + 1].mean() for i in range(n)])


def warp(surface: dict) -> tuple[float | None, float | None]:
    """Largest over smallest of the control rows' spacing in (x, y) relative to their
    Greville spacing, per direction (u rows, v rows), the end rows left out (None where
    no inner gap is left or one has closed)."""
    net = np.asarray(surface["control_points"], float)[..., :2]  # (nu, nv, 2)
    spreads = []
    for axis, (knots, degree) in enumerate(((surface["knots_u"], surface["degree_u"]),
                                            (surface["knots_v"], surface["degree_v"]))):
        rows = net.mean(axis=1 - axis)  # (n, 2): each row's mean place
        gaps = np.linalg.norm(np.diff(rows, axis=0), axis=1)[1:-1]
        density = gaps / np.diff(greville(np.asarray(knots, float), degree))[1:-1]
        spreads.append(float(density.max() / density.min()) if len(density) and density.min() > 0 else None)
    return spreads[0], spreads[1]


def truths(case, cases_dir: Path, results: Path, seed: int, scorer) -> dict | str:
    """truth_rms of the classical and the swarm's fit of ``case`` and of the classical fit
    of its noise-free twin (a noise-free cloud is its own); a line saying which fit
    failed, if one did."""
    runs = [("classical", case, "classical"), ("swarm", case, "swarm")]
    write(case, cases_dir, seed)
    if case.noise:
        clean = dataclasses.replace(case, name=f"{case.name}_noise_free", noise=0.0)
        write(clean, cases_dir, seed)
        runs.append(("noise-free", clean, "classical"))
    truth = {}
    for key, each, variant in runs:
        r = fit_and_score(each.name, variant, cases_dir, results, scorer=scorer)
        if "error" in r:
            return f"failed ({key}): {r['error']}"
        truth[key] = r["truth_rms"]
    truth.setdefault("noise-free", truth["classical"])
    return truth


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", help=f"these clouds (default: {' '.join(LOCALISED)})")
    ap.add_argument("--scorer", type=Path, metavar="SCORE_PY",
                    help="score with this script instead of benchmarks/score.py (as run_cases.py --scorer)")
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--seed", type=int, default=0, help="the clouds' draw (0: the usual ones)")
    args = ap.parse_args(argv)
    scorer = score if args.scorer is None else outside_score(args.scorer)
    known = {**feature_cases(), "step_bump": CASES["step_bump"]}
    names = args.only or LOCALISED
    unknown = [n for n in names if n not in known]
    if unknown:
        print(f"knot_headroom.py: unknown cloud {unknown[0]!r} (one of {', '.join(known)})", file=sys.stderr)
        return 2
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-headroom-"))
    cases_dir, results = root / "cases", root / "results"
    cases_dir.mkdir(parents=True, exist_ok=True)
    header = ["cloud", "noise", "classical truth", "noise-free truth", "floor", "swarm truth", "swarm / classical",
              "warp u", "warp v"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name in names:
        case = known[name]
        truth = truths(case, cases_dir, results, args.seed, scorer)
        if isinstance(truth, str):
            print(f"| {name} | {truth} |" + " |" * (len(header) - 2), flush=True)
            continue
        fitted = json.loads((results / "classical" / name / f"{name}.json").read_text())
        spread_u, spread_v = warp(fitted["surface"])
        t, t0 = truth["classical"], truth["noise-free"]
        floor = f"{np.sqrt(max(0.0, 1.0 - (t0 / t) ** 2)):.2f}" if t > 0 else "-"
        row = [name, cell(case.noise), cell(t), cell(t0), floor, cell(truth["swarm"]),
               f"{truth['swarm'] / t:.2f}" if t > 0 else "-", cell(spread_u), cell(spread_v)]
        print("| " + " | ".join(row) + " |", flush=True)
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
