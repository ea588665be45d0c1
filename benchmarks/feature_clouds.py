#!/usr/bin/env python3
"""Clouds outside the public benchmark: localised features where knot placement decides
the fit, and smooth shapes where the swarm should change nothing for the worse.

    python benchmarks/feature_clouds.py [--out DIR] [--only NAME ...] [--variants classical swarm]

Each cloud has a known surface and is written like a public case (PLY, YAML config,
ground-truth mesh) with the generator of ``../shared/bench/cases.py``; then it is fitted
with ``psonurbs fit`` and scored with ``../shared/bench/score.py`` exactly as
``run_cases.py`` does (``classical``: one particle, one iteration; ``swarm``: the config).
The table ends with the ratio of the swarm's truth_rms to the classical one per cloud.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from pathlib import Path

import numpy as np
from run_cases import COLUMNS, SHARED, cell, fit_and_score


def load_cases_module():
    spec = importlib.util.spec_from_file_location("bench_cases", SHARED / "cases.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_cases"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def height(z):
    """A height field over [0, 1]^2 from z(u, v)."""
    return lambda u, v: np.stack([u, v, z(u, v)], -1)


def feature_cases(bench) -> dict:
    swarm = bench.seed_swarm()

    def config(net, orders=(4, 4), topology="open"):
        return {"orders": list(orders), "net_size": list(net), "topology": topology, "swarm": swarm}

    def vase(u, v):
        a, r = bench.TAU * u, 0.6 + 0.25 * np.sin(2.5 * v + 0.4)
        return np.stack([r * np.cos(a), r * np.sin(a), 2.0 * v], -1)

    def saddle(u, v):
        x, y = 2 * u - 1, 2 * v - 1
        return np.stack([x, y, 0.4 * (x * x - y * y)], -1)

    cases = [
        # localised features: a knot vector must put its knots where they are
        bench.Case("step_diagonal", height(lambda u, v: 0.3 * np.tanh(12 * (u + v - 1.1))), bench.uniform(4000),
                   config((10, 10)), note="a steep step along the diagonal u + v = 1.1"),
        bench.Case("cliff_noisy", height(lambda u, v: 0.25 * np.tanh(20 * (u - 0.4))), bench.uniform(4000),
                   config((10, 10)), noise=0.001, note="a cliff across u = 0.4, noise 0.1%"),
        bench.Case("twin_ridges", height(lambda u, v: 0.12 * np.exp(-((v - 0.25) / 0.05) ** 2)
                                         + 0.08 * np.exp(-((v - 0.7) / 0.04) ** 2) + 0.1 * u),
                   bench.uniform(4000), config((10, 10)), note="two narrow ridges along u"),
        bench.Case("narrow_bump", height(lambda u, v: 0.2 * np.exp(-((u - 0.3) ** 2 + (v - 0.6) ** 2) / (2 * 0.06 ** 2))
                                         + 0.05 * u - 0.03 * v), bench.uniform(3000), config((10, 10)),
                   note="a narrow bump on a gentle slope"),
        bench.Case("terrace_graded", height(lambda u, v: 0.15 * np.tanh(18 * (u - 0.35)) + 0.12 * np.tanh(18 * (u - 0.75))),
                   bench.graded(4000), config((12, 8)), note="two steps, density rising towards u = 1"),
        bench.Case("ridge_curve", height(lambda u, v: 0.15 * np.exp(-((v - 0.5 - 0.15 * np.sin(5 * u)) / 0.06) ** 2)),
                   bench.uniform(5000), config((12, 12)), noise=0.0005, note="a narrow ridge along a curve, noise"),
        # smooth shapes: the swarm must not make them worse
        bench.Case("saddle_noisy", saddle, bench.uniform(3000), config((8, 8)), noise=0.003, note="a saddle, noise 0.3%"),
        bench.Case("vase", vase, bench.uniform(4000), config((10, 6), topology="cylinder"), noise=0.001,
                   note="a vase (radius varying with height), closed in u"),
        bench.Case("sphere_sparse", bench.sphere((0.3, -0.2, 0.1), 1.2), bench.sphere_area_uniform(900),
                   config((8, 6), topology="sphere"), noise=0.002, note="900 points on a sphere, noise"),
        bench.Case("terrain_noisy", height(lambda u, v: 0.1 * np.sin(7 * u + 1) * np.cos(5 * v) + 0.05 * np.sin(13 * v)),
                   bench.uniform(6000), config((12, 12)), noise=0.002, note="terrain-like waves, noise 0.2%"),
    ]
    return {c.name: c for c in cases}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--variants", nargs="*", default=["classical", "swarm"])
    args = ap.parse_args(argv)
    bench = load_cases_module()
    cases = feature_cases(bench)
    names = args.only or list(cases)
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-features-"))
    cases_dir = root / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    header = ["case", "variant", *COLUMNS, "noise", "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    truth = {}
    for name in names:
        bench.write_case(cases[name], cases_dir)
        for variant in args.variants:
            r = fit_and_score(name, variant, cases_dir, root / "results")
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
