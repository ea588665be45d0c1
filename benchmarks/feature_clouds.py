#!/usr/bin/env python3
"""Clouds outside the public benchmark: localised features where knot placement decides
the fit, and smooth shapes where the swarm should change nothing for the worse.

    python benchmarks/feature_clouds.py [--out DIR] [--only NAME ...] [--variants classical swarm] [--scorer SCORE_PY] [--seed N]

Each cloud has a known surface and is written like a public case (PLY, YAML config,
ground-truth mesh) with ``benchmarks/cases.py``; then it is fitted with ``psonurbs fit``
and scored with ``benchmarks/score.py`` exactly as ``run_cases.py`` does (``classical``: one particle, one iteration; ``swarm``: the config).
``--seed`` draws other clouds of the same shapes (0: the clouds measured so far), so that
a change can be checked on draws nobody has tuned for.
The table ends with the ratio of the swarm's truth_rms to the classical one per cloud.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from cases import TAU, Case, denser_towards_u1, equal_area_sphere, scattered, sphere, write
from run_cases import COLUMNS, cell, fit_and_score, outside_score
from score import score


def height(z):
    """A height field over [0, 1]^2 from z(u, v)."""
    return lambda u, v: np.stack([u, v, z(u, v)], -1)


def feature_cases() -> dict:
    def vase(u, v):
        a, r = TAU * u, 0.6 + 0.25 * np.sin(2.5 * v + 0.4)
        return np.stack([r * np.cos(a), r * np.sin(a), 2.0 * v], -1)

    def saddle(u, v):
        x, y = 2 * u - 1, 2 * v - 1
        return np.stack([x, y, 0.4 * (x * x - y * y)], -1)

    cubic = (4, 4)
    cases = [
        # localised features: a knot vector must put its knots where they are
        Case("step_diagonal", height(lambda u, v: 0.3 * np.tanh(12 * (u + v - 1.1))), scattered(4000), cubic,
             (10, 10), "open", "a steep step along the diagonal u + v = 1.1"),
        Case("cliff_noisy", height(lambda u, v: 0.25 * np.tanh(20 * (u - 0.4))), scattered(4000), cubic,
             (10, 10), "open", "a cliff across u = 0.4, noise 0.1%", noise=0.001),
        Case("twin_ridges", height(lambda u, v: 0.12 * np.exp(-((v - 0.25) / 0.05) ** 2)
                                   + 0.08 * np.exp(-((v - 0.7) / 0.04) ** 2) + 0.1 * u),
             scattered(4000), cubic, (10, 10), "open", "two narrow ridges along u"),
        Case("narrow_bump", height(lambda u, v: 0.2 * np.exp(-((u - 0.3) ** 2 + (v - 0.6) ** 2) / (2 * 0.06 ** 2))
                                   + 0.05 * u - 0.03 * v), scattered(3000), cubic, (10, 10), "open",
             "a narrow bump on a gentle slope"),
        Case("terrace_graded", height(lambda u, v: 0.15 * np.tanh(18 * (u - 0.35)) + 0.12 * np.tanh(18 * (u - 0.75))),
             denser_towards_u1(4000), cubic, (12, 8), "open", "two steps, density rising towards u = 1"),
        Case("ridge_curve", height(lambda u, v: 0.15 * np.exp(-((v - 0.5 - 0.15 * np.sin(5 * u)) / 0.06) ** 2)),
             scattered(5000), cubic, (12, 12), "open", "a narrow ridge along a curve, noise", noise=0.0005),
        # smooth shapes: the swarm must not make them worse
        Case("saddle_noisy", saddle, scattered(3000), cubic, (8, 8), "open", "a saddle, noise 0.3%", noise=0.003),
        Case("vase", vase, scattered(4000), cubic, (10, 6), "cylinder",
             "a vase (radius varying with height), closed in u", noise=0.001),
        Case("sphere_sparse", sphere((0.3, -0.2, 0.1), 1.2), equal_area_sphere(900), cubic, (8, 6), "sphere",
             "900 points on a sphere, noise", noise=0.002),
        Case("terrain_noisy", height(lambda u, v: 0.1 * np.sin(7 * u + 1) * np.cos(5 * v) + 0.05 * np.sin(13 * v)),
             scattered(6000), cubic, (12, 12), "open", "terrain-like waves, noise 0.2%", noise=0.002),
    ]
    return {c.name: c for c in cases}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--variants", nargs="*", default=["classical", "swarm"])
    ap.add_argument("--scorer", type=Path, metavar="SCORE_PY",
                    help="score with this script instead of benchmarks/score.py (as run_cases.py --scorer)")
    ap.add_argument("--seed", type=int, default=0, help="the clouds' draw (0: the usual ones; others: fresh draws)")
    args = ap.parse_args(argv)
    scorer = score if args.scorer is None else outside_score(args.scorer)
    cases = feature_cases()
    names = args.only or list(cases)
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-features-"))
    cases_dir = root / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    header = ["case", "variant", *COLUMNS, "noise", "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    truth = {}
    for name in names:
        write(cases[name], cases_dir, args.seed)
        for variant in args.variants:
            r = fit_and_score(name, variant, cases_dir, root / "results", scorer=scorer)
            if "error" in r:
                print(f"| {name} | {variant} | failed: {r['error']} |" + " |" * (len(header) - 3), flush=True)
                continue
            truth[name, variant] = r.get("truth_rms")
            row = [name, variant, *(cell(r.get(c)) for c in COLUMNS), cell(r.get("noise")), f"{r['seconds']:.1f}"]
            print("| " + " | ".join(row) + " |", flush=True)
    print("\n| case | swarm truth_rms / classical |\n|---|---|")
    for name in names:
        if (name, "classical") in truth and (name, "swarm") in truth:
            print(f"| {name} | {truth[name, 'swarm'] / truth[name, 'classical']:.2f} |")
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
