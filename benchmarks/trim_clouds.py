#!/usr/bin/env python3
"""Trim loops on clouds of other footprints than the public plate_holes: ragged edges,
slots, an annulus, sparse small holes, a torn non-height-field sheet, an L with graded
density. Each is fitted by ``psonurbs fit`` (trim: auto) and scored by
``benchmarks/score.py`` against its truth (which exists only where the data are).

    python benchmarks/trim_clouds.py                       # every cloud
    python benchmarks/trim_clouds.py --clouds wave_star --seed 3

``loops`` is what the JSON holds against ``expected`` (the outer boundary and the holes of
the true footprint; ``-`` when the footprint fills the square); rmse and truth_rms are in
units of the noise sigma where the cloud has noise.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from cases import CASES, Case, inside, scattered, write
from run_cases import cell, fit_and_score

SWARM = {"particles": 20, "iterations": 100, "inertia": 0.7, "c1": 1.5, "c2": 1.5, "seed": 7}


def star(u, v):
    """A ragged outline: a radius with five random-looking harmonics around (0.5, 0.5)."""
    a = np.arctan2(v - 0.5, u - 0.5)
    r = 0.36 + 0.05 * np.sin(5 * a + 0.3) + 0.03 * np.sin(11 * a + 1.1) + 0.015 * np.sin(23 * a + 2.0)
    return np.hypot(u - 0.5, v - 0.5) < r


def star_slot(u, v):
    slot = (np.abs(u - 0.55) < 0.12) & (np.abs(v - 0.45) < 0.035)
    return star(u, v) & ~slot


def annulus(u, v):
    r = np.hypot(u - 0.5, v - 0.5)
    return (r < 0.47) & (r > 0.2)


def three_small_holes(u, v):
    holes = ((u - 0.25) ** 2 + (v - 0.3) ** 2 < 0.06 ** 2) | ((u - 0.7) ** 2 + (v - 0.35) ** 2 < 0.05 ** 2) \
        | ((u - 0.5) ** 2 + (v - 0.72) ** 2 < 0.07 ** 2)
    return ~holes


def torn(u, v):
    """The whole square but for a torn edge at v = 1 (a sinusoid of uneven depth)."""
    return v < 0.8 + 0.08 * np.sin(9 * u) * np.cos(4 * u + 0.5)


def l_shape(u, v):
    return (u < 0.45) | (v < 0.4)


def graded_inside(region, n):
    """n samples inside region, denser towards u = 1 (u = sqrt(uniform))."""
    def sample(rng):
        u, v = np.sqrt(rng.random(8 * n)), rng.random(8 * n)
        keep = region(u, v)
        return u[keep][:n], v[keep][:n]
    return sample


def clouds() -> dict[str, tuple[Case, int | None]]:
    """name -> (case, loops expected: outer + holes; None where the data fill the square)."""
    base = {"wave": CASES["wave_graded"].shape, "franke": CASES["franke_noisy"].shape,
            "plate": CASES["plate_holes"].shape, "curl": CASES["curl_sheet"].shape}
    mk = [
        ("wave_star_slot", base["wave"], inside(star_slot, 4000), 0.001, star_slot, 2),
        ("franke_annulus", base["franke"], inside(annulus, 3000), 0.002, annulus, 2),
        ("plate_sparse_holes", base["plate"], inside(three_small_holes, 1500), 0.0005, three_small_holes, 4),
        ("curl_torn", base["curl"], inside(torn, 3000), 0.001, torn, 1),
        ("wave_l_graded", base["wave"], graded_inside(l_shape, 4000), 0.0, l_shape, 1),
        ("franke_full", base["franke"], scattered(3000), 0.002, None, None),
    ]
    template = CASES["plate_holes"]
    return {name: (replace(template, name=name, shape=shape, sampler=sampler, noise=noise, footprint=fp,
                           net=(10, 10), note=name, swarm=SWARM), loops)
            for name, shape, sampler, noise, fp, loops in mk}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    table = clouds()
    ap.add_argument("--clouds", nargs="*", default=list(table), choices=list(table), metavar="CLOUD")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-trim-"))
    cases_dir = root / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    columns = ["points", "loops", "expected", "overhang", "rmse/σ", "truth_rms/σ", "truth_max", "cover_max",
               "mesh_vs_nurbs", "seconds"]
    print("| cloud | " + " | ".join(columns) + " |")
    print("|" + "---|" * (len(columns) + 1))
    for name in args.clouds:
        case, expected = table[name]
        write(case, cases_dir, args.seed)
        r = fit_and_score(name, "swarm", cases_dir, root / "results")
        if "error" in r:
            print(f"| {name} | failed: {r['error']} |" + " |" * (len(columns) - 1), flush=True)
            continue
        doc = json.loads((root / "results" / "swarm" / name / f"{name}.json").read_text())
        sigma = case.noise or None
        row = [len(case.points(args.seed)), len(doc["surface"].get("trim", [])) or "-",
               expected or "-", cell(r.get("overhang")),
               cell(r["rmse"] / sigma) if sigma else cell(r.get("rmse")),
               cell(r["truth_rms"] / sigma) if sigma else cell(r.get("truth_rms")),
               cell(r.get("truth_max")), cell(r.get("cover_max")), cell(r.get("mesh_vs_nurbs")),
               f"{r['seconds']:.1f}"]
        print(f"| {name} | " + " | ".join(str(c) for c in row) + " |", flush=True)
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
