#!/usr/bin/env python3
"""Fit open surfaces that are not in the public benchmark, and score them against their truth.

    python benchmarks/unseen.py                       # every cloud, this build
    python benchmarks/unseen.py --baseline /path/to/other/bin/psonurbs --clouds tub cone220

Clouds a plane does or does not see as a height field, clean and noisy, with uneven
density, sparse edges and a few strays: twisted strips, shells whose sides turn vertical,
a hemisphere, a cone section, a curl with a gap, a saddle and a shallow cap. Each is
written as PLY with a dense mesh of its true surface (the ``.gt.npz`` of
``benchmarks/cases.py``), fitted with ``psonurbs fit`` (a smaller swarm than the
public cases: ``--particles``, ``--iterations``) and scored by ``benchmarks/score.py``.
With ``--baseline EXE`` each cloud is fitted by that other build first (rows ``main`` /
``this``). Figures are relative to the bounding-box diagonal.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from run_cases import cell
from score import score

COLUMNS = ["param", "rmse", "inlier_rmse", "truth_rms", "truth_max", "cover_max", "overhang", "outliers", "suspect"]


def twisted(degrees: float, length: float = 3.0):
    def f(u, v):
        t = np.radians(degrees) * (u - 0.5)
        w = v - 0.5
        return np.stack([length * u, w * np.cos(t), w * np.sin(t)], -1)
    return f


def arc(degrees: float, height: float = 1.5):
    def f(u, v):
        a = np.radians(90.0 - degrees / 2.0 + degrees * u)
        return np.stack([np.cos(a), np.sin(a), height * v], -1)
    return f


def cap(polar_degrees: float):
    """A spherical cap from the pole to a polar angle, the square mapped onto the disc."""
    def f(u, v):
        x, y = 2 * u - 1, 2 * v - 1
        dx, dy = x * np.sqrt(1 - y * y / 2), y * np.sqrt(1 - x * x / 2)
        theta, phi = np.radians(polar_degrees) * np.hypot(dx, dy), np.arctan2(dy, dx)
        return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    return f


def tub(u, v):
    """A round pan: a flat bottom, then a quarter-circle wall that turns vertical at the rim
    (the square mapped onto the disc)."""
    x, y = 2 * u - 1, 2 * v - 1
    dx, dy = x * np.sqrt(1 - y * y / 2), y * np.sqrt(1 - x * x / 2)
    r, phi = np.hypot(dx, dy), np.arctan2(dy, dx)
    wall = np.radians(90.0) * np.clip((r - 0.5) / 0.5, 0.0, 1.0)
    rho = np.minimum(r, 0.5) + 0.3 * np.sin(wall)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), 0.3 * (1.0 - np.cos(wall))], -1)


def cone(u, v):
    a, r = np.radians(220.0) * u, 0.5 + v
    return np.stack([r * np.cos(a), r * np.sin(a), 1.2 * v], -1)


def saddle(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return np.stack([x, y, 0.4 * (x * x - y * y)], -1)


@dataclass(frozen=True)
class Cloud:
    name: str
    surface: Callable
    net: tuple[int, int]
    points: int = 4000
    noise: float = 0.0  # sigma, of the diagonal
    density: str = "uniform"  # uniform | graded (rising along u) | sparse_edges
    strays: float = 0.0  # share of points replaced by uniform junk in the box
    note: str = ""


CLOUDS = [
    Cloud("twist200_graded", twisted(200.0), (12, 4), density="graded", note="strip twisted 200 deg, uneven density"),
    Cloud("twist90_noisy", twisted(90.0), (10, 4), noise=1e-3, note="strip twisted 90 deg, noisy"),
    Cloud("tub", tub, (10, 10), note="a pan whose sides turn vertical, clean"),
    Cloud("tub_noisy_strays", tub, (10, 10), noise=1e-3, strays=0.01, note="the pan, noisy, 1% strays"),
    Cloud("hemisphere_noisy", cap(90.0), (10, 10), noise=1e-3, note="hemisphere, noisy"),
    Cloud("cone220", cone, (10, 5), note="cone section over 220 deg (a height field over its axis plane)"),
    Cloud("arc200_sparse_edges", arc(200.0), (10, 5), noise=1e-3, density="sparse_edges",
          note="cylinder section over 200 deg, sparse edges, noisy"),
    Cloud("arc300_strays", arc(300.0), (12, 5), strays=0.02, note="cylinder section over 300 deg, 2% strays"),
    Cloud("saddle_graded_noisy", saddle, (8, 8), noise=2e-3, density="graded", note="saddle height field"),
    Cloud("cap60_noisy", cap(60.0), (8, 8), noise=1e-3, note="shallow cap (a height field)"),
]


def parameters(cloud: Cloud, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    n = cloud.points
    if cloud.density == "graded":
        return np.sqrt(rng.random(n)), rng.random(n)
    if cloud.density == "sparse_edges":
        u, v = rng.random(4 * n), rng.random(4 * n)
        edge = np.minimum.reduce([u, 1 - u, v, 1 - v])
        keep = rng.random(4 * n) < 0.15 + 0.85 * np.minimum(1.0, 4.0 * edge)
        return u[keep][:n], v[keep][:n]
    return rng.random(n), rng.random(n)


def points(cloud: Cloud, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = cloud.surface(*parameters(cloud, rng))
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    pts = pts + rng.normal(0.0, cloud.noise * diag, pts.shape)
    k = int(round(cloud.strays * len(pts)))
    if k:
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pts[rng.choice(len(pts), k, replace=False)] = lo + rng.random((k, 3)) * (hi - lo)
    return pts[rng.permutation(len(pts))]


def truth_mesh(cloud: Cloud, n: int = 241) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    tris = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return cloud.surface(u.ravel(), v.ravel()), tris.astype(np.int32)


def write(cloud: Cloud, directory: Path) -> tuple[Path, Path, Path]:
    directory.mkdir(parents=True, exist_ok=True)
    ply, yaml, gt = (directory / f"{cloud.name}{ext}" for ext in (".ply", ".yaml", ".gt.npz"))
    pts = np.ascontiguousarray(points(cloud), "<f8")
    ply.write_bytes((f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty double x\n"
                     "property double y\nproperty double z\nend_header\n").encode() + pts.tobytes())
    yaml.write_text(f"# {cloud.note}\norders: [4, 4]\nnet_size: [{cloud.net[0]}, {cloud.net[1]}]\ntopology: open\n")
    verts, tris = truth_mesh(cloud)
    np.savez_compressed(gt, vertices=verts, triangles=tris, noise=cloud.noise, outliers=cloud.strays)
    return ply, yaml, gt


def fit_and_score(cloud: Cloud, files, out: Path, exe: str, swarm: list[str]) -> dict:
    ply, yaml, gt = files
    start = time.perf_counter()
    run = subprocess.run([exe, "fit", str(ply), "-c", str(yaml), "-o", str(out), "-q", *swarm],
                         capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        return {"error": (run.stderr or run.stdout).strip().splitlines()[-1], "seconds": seconds}
    result = score(ply, out, gt)
    doc = json.loads((out / f"{cloud.name}.json").read_text())
    result.update(param=doc["fit"].get("parametrisation", {}).get("method"), outliers=doc["metrics"].get("outliers"),
                  suspect={True: "SUSPECT", False: "no"}.get(doc["metrics"].get("suspect")), seconds=seconds)
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clouds", nargs="*", default=[c.name for c in CLOUDS])
    ap.add_argument("--baseline", metavar="EXE", help="another psonurbs executable to fit every cloud with too")
    ap.add_argument("--particles", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-unseen-"))
    builds = ([("main", args.baseline)] if args.baseline else []) + [("this", "psonurbs")]
    swarm = ["--particles", str(args.particles), "--iterations", str(args.iterations)]
    header = ["cloud", "note", "build", *COLUMNS, "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    by_name = {c.name: c for c in CLOUDS}
    for name in args.clouds:
        cloud = by_name[name]
        files = write(cloud, root / "clouds")
        for build, exe in builds:
            r = fit_and_score(cloud, files, root / "results" / build / name, exe, swarm)
            if "error" in r:
                print(f"| {name} | {cloud.note} | {build} | failed: {r['error']} |" + " |" * (len(header) - 4),
                      flush=True)
                continue
            print("| " + " | ".join([name, cloud.note, build, *(cell(r.get(c)) for c in COLUMNS),
                                     f"{r['seconds']:.1f}"]) + " |", flush=True)
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
