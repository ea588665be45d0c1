#!/usr/bin/env python3
"""Clouds for the robust fit that are not among the public cases, fitted and scored.

    python benchmarks/run_robust.py                       # every cloud, the swarm variant
    python benchmarks/run_robust.py --clouds blob_junk5 --variants classical swarm
    python benchmarks/run_robust.py --write-only --out /tmp/robust   # only the clouds

Each cloud is written with its YAML and its true surface (``NAME.gt.npz``: a dense
triangulation, the noise and the junk share, the format ``benchmarks/score.py``
reads), fitted by the installed ``psonurbs`` and scored like the public cases
(``run_cases.py``); the table adds ``outliers`` (``metrics.outliers``: points left out of
the fit) and the scorer's ``inlier_rmse`` (on the points within 4 noise sigmas of the
truth). Noise and distances are shares of the bounding-box diagonal.

Clean clouds (nothing should be left out): a narrow bump an 8 x 8 net cannot resolve, an
exact half cylinder (a plane projection folds at its sides), a coarse latitude-longitude
grid on a sphere, a terrain sampled along scan lines. Contaminated ones: a tilted saddle
with 5% junk in its bounding box, a sphere cap with 8%, a graded cloud with 5%, a cylinder
with 8%, a compact blob of 5% floating over a surface and a flat piece of another object
(5%) beside it, 10% of the points pushed 5 to 20 sigmas off the surface along its normal.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from run_cases import cell, fit_and_score

TAU = 2.0 * np.pi


def franke(u, v):
    z = (0.75 * np.exp(-((9 * u - 2) ** 2 + (9 * v - 2) ** 2) / 4) + 0.75 * np.exp(-((9 * u + 1) ** 2) / 49 - (9 * v + 1) / 10)
         + 0.5 * np.exp(-((9 * u - 7) ** 2 + (9 * v - 3) ** 2) / 4) - 0.2 * np.exp(-(9 * u - 4) ** 2 - (9 * v - 7) ** 2))
    return np.stack([u, v, z], -1)


def narrow_bump(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return np.stack([x, y, 0.5 * np.exp(-(x * x + y * y) / 0.15 ** 2)], -1)


def half_cylinder(u, v):
    a = np.pi * u
    return np.stack([np.cos(a), np.sin(a), 2.0 * v], -1)


def tilted_saddle(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    p = np.stack([x, y, 0.4 * (x * x - y * y)], -1)
    t = np.radians(40.0)  # about the axis (1, 1, 0) / sqrt 2
    k = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + np.sin(t) * kx + (1 - np.cos(t)) * kx @ kx
    return p @ rot.T


def sphere_cap(u, v):  # u around, v from the pole to 60 degrees
    th, ph = TAU * u, np.radians(60.0) * v
    return np.stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)], -1)


def sphere(u, v):
    th, ph = TAU * u, np.pi * v
    return np.stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), -np.cos(ph)], -1)


def wave(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return np.stack([x, y, 0.3 * np.sin(3 * x) * np.cos(3 * y)], -1)


def cylinder(u, v):
    th = TAU * u
    return np.stack([0.8 * np.cos(th), 0.8 * np.sin(th), 3.0 * v - 1.5], -1)


def terrain(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return np.stack([x, y, 0.15 * np.sin(2 * x + 1) * np.cos(1.5 * y) + 0.1 * x * y], -1)


def uniform(n):
    return lambda rng: (rng.random(n), rng.random(n))


def graded(n):
    return lambda rng: (np.sqrt(rng.random(n)), rng.random(n))


def cap_area_uniform(n):
    def f(rng):  # cos(polar angle) uniform on [cos 60, 1]
        c = 1.0 - rng.random(n) * (1.0 - np.cos(np.radians(60.0)))
        return rng.random(n), np.arccos(c) / np.radians(60.0)
    return f


def lat_long(nu, nv):
    def f(_rng):
        u, v = np.meshgrid(np.arange(nu) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")
        return u.ravel(), v.ravel()
    return f


def scan_lines(lines, per_line):
    def f(rng):  # lines across u, each sampled densely and a little unevenly along v
        u = np.repeat((np.arange(lines) + 0.5) / lines, per_line) + rng.normal(0, 0.001, lines * per_line)
        v = np.tile(np.linspace(0, 1, per_line), lines) + rng.uniform(-0.2, 0.2, lines * per_line) / per_line
        return np.clip(u, 0, 1), np.clip(v, 0, 1)
    return f


@dataclass
class Junk:
    """How a share of the points is replaced: ``box`` uniform in the bounding box, ``blob`` a
    ball, ``piece`` a flat square of another object, ``near`` pushed along the normal."""

    kind: str
    share: float
    where: tuple = ()


@dataclass
class Cloud:
    name: str
    surface: Callable
    sample: Callable
    config: dict
    noise: float = 0.0
    junk: Junk | None = None
    note: str = ""
    extra: dict = field(default_factory=dict)


def open_config(net, orders=(4, 4), topology="open"):
    return {"orders": list(orders), "net_size": list(net), "topology": topology,
            "swarm": {"particles": 40, "iterations": 300, "inertia": 0.7, "c1": 1.5, "c2": 1.5, "seed": 7}}


CLOUDS = {c.name: c for c in [
    Cloud("narrow_bump", narrow_bump, uniform(5000), open_config((8, 8)), 0.001,
          note="a bump 0.15 wide that an 8 x 8 net cannot resolve; clean"),
    Cloud("half_cylinder", half_cylinder, uniform(3000), open_config((6, 4), (3, 3)), 0.0,
          note="an exact half cylinder, a plane projection folds at its sides; clean"),
    Cloud("sphere_grid", sphere, lat_long(32, 24), open_config((10, 8), topology="sphere"), 0.0,
          note="a coarse latitude-longitude grid on a sphere, rings dense at the poles; clean"),
    Cloud("terrain_lines", terrain, scan_lines(50, 120), open_config((10, 10)), 0.0005,
          note="a terrain along 50 scan lines, 120 points each; clean"),
    Cloud("saddle_junk5", tilted_saddle, uniform(4000), open_config((8, 8)), 0.002, Junk("box", 0.05),
          note="a saddle tilted 40 degrees, 5% junk in the bounding box"),
    Cloud("cap_junk8", sphere_cap, cap_area_uniform(4000), open_config((8, 8)), 0.001, Junk("box", 0.08),
          note="a sphere cap (60 degrees), 8% junk in the bounding box"),
    Cloud("graded_junk5", wave, graded(8000), open_config((10, 10)), 0.001, Junk("box", 0.05),
          note="density rising towards one edge, 5% junk in the bounding box"),
    Cloud("cylinder_junk8", cylinder, uniform(4000), open_config((10, 6), topology="cylinder"), 0.001,
          Junk("box", 0.08), note="a closed cylinder, 8% junk in the bounding box"),
    Cloud("blob_junk5", franke, uniform(5000), open_config((12, 12)), 0.001, Junk("blob", 0.05, (0.3, 0.6, 0.15, 0.04)),
          note="5% of the points in a ball (radius 0.04) floating 0.15 over the surface"),
    Cloud("piece_junk5", franke, uniform(5000), open_config((12, 12)), 0.001, Junk("piece", 0.05, (0.75, 0.75, 0.12, 0.12)),
          note="5% of the points on a flat square (side 0.12), a piece of another object 0.12 over the surface"),
    Cloud("near_junk10", franke, uniform(5000), open_config((12, 12)), 0.001, Junk("near", 0.10, (5.0, 20.0)),
          note="10% of the points pushed 5 to 20 sigmas off the surface along its normal"),
]}


def bbox_diag(p):
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def normals(surface, u, v, h=1e-6):
    du = surface(np.clip(u + h, 0, 1), v) - surface(np.clip(u - h, 0, 1), v)
    dv = surface(u, np.clip(v + h, 0, 1)) - surface(u, np.clip(v - h, 0, 1))
    n = np.cross(du, dv)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def make_points(cloud: Cloud, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u, v = cloud.sample(rng)
    pts = cloud.surface(u, v)
    diag = bbox_diag(pts)
    pts = pts + rng.normal(0.0, cloud.noise * diag, pts.shape)
    junk = cloud.junk
    if junk is not None:
        k = int(round(junk.share * len(pts)))
        idx = rng.choice(len(pts), k, replace=False)
        if junk.kind == "box":
            lo, hi = pts.min(0), pts.max(0)
            pts[idx] = lo + rng.random((k, 3)) * (hi - lo)
        elif junk.kind == "blob":  # a ball at height h over the surface point (u0, v0)
            u0, v0, h, r = junk.where
            centre = cloud.surface(np.array([u0]), np.array([v0]))[0] + normals(cloud.surface, np.array([u0]), np.array([v0]))[0] * h * diag
            d = rng.normal(size=(k, 3))
            d *= (r * diag * rng.random(k) ** (1 / 3) / np.linalg.norm(d, axis=1))[:, None]
            pts[idx] = centre + d
        elif junk.kind == "piece":  # a flat square, tilted 30 degrees, at height h over (u0, v0)
            u0, v0, h, side = junk.where
            base = cloud.surface(np.array([u0]), np.array([v0]))[0] + np.array([0.0, 0.0, h * diag])
            a, b = rng.uniform(-0.5, 0.5, (2, k)) * side * diag
            t = np.radians(30.0)
            pts[idx] = base + np.stack([a * np.cos(t), b, a * np.sin(t)], -1) + rng.normal(0, cloud.noise * diag, (k, 3))
        elif junk.kind == "near":
            lo, hi = junk.where
            n = normals(cloud.surface, u[idx], v[idx])
            amount = rng.uniform(lo, hi, k) * cloud.noise * diag * rng.choice([-1.0, 1.0], k)
            pts[idx] = cloud.surface(u[idx], v[idx]) + n * amount[:, None]
    return pts[rng.permutation(len(pts))]


def grid_triangles(nu: int, nv: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(nu - 1), np.arange(nv - 1), indexing="ij")
    a = (i * nv + j).ravel()
    b, c, d = a + nv, a + 1, a + nv + 1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)]).astype(np.int32)


def write_cloud(cloud: Cloud, out: Path, seed: int = 0) -> None:
    pts = make_points(cloud, seed)
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(pts)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n")
    (out / f"{cloud.name}.ply").write_bytes(head.encode() + np.ascontiguousarray(pts, "<f8").tobytes())
    cfg = cloud.config
    lines = [f"# {cloud.note}", f"orders: {cfg['orders']}", f"net_size: {cfg['net_size']}", f"topology: {cfg['topology']}",
             "swarm:"] + [f"  {k}: {v}" for k, v in cfg["swarm"].items()]
    (out / f"{cloud.name}.yaml").write_text("\n".join(lines) + "\n")
    u, v = np.meshgrid(np.linspace(0, 1, 241), np.linspace(0, 1, 241), indexing="ij")
    np.savez_compressed(out / f"{cloud.name}.gt.npz", vertices=cloud.surface(u.ravel(), v.ravel()),
                        triangles=grid_triangles(241, 241), noise=cloud.noise,
                        outliers=cloud.junk.share if cloud.junk else 0.0)


COLUMNS = ["topology", "outliers", "rmse", "inlier_rmse", "truth_rms", "truth_max", "cover_max"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clouds", nargs="*", default=list(CLOUDS), choices=list(CLOUDS))
    ap.add_argument("--variants", nargs="*", default=["swarm"], choices=["swarm", "classical"])
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--write-only", action="store_true", help="write the clouds, fit nothing")
    args = ap.parse_args(argv)
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-robust-"))
    cases = root / "cases"
    cases.mkdir(parents=True, exist_ok=True)
    for name in args.clouds:
        write_cloud(CLOUDS[name], cases)
    if args.write_only:
        print(f"clouds in {cases}")
        return 0
    header = ["cloud", "variant", *COLUMNS, "noise", "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name in args.clouds:
        for variant in args.variants:
            r = fit_and_score(name, variant, cases, root / "results")
            if "error" in r:
                print(f"| {name} | {variant} | failed: {r['error']} |" + " |" * (len(header) - 3), flush=True)
                continue
            doc = json.loads((root / "results" / variant / name / f"{name}.json").read_text())
            r["outliers"] = doc["metrics"].get("outliers")
            row = [name, variant, *(cell(r.get(c)) for c in COLUMNS), cell(r.get("noise")), f"{r['seconds']:.1f}"]
            print("| " + " | ".join(row) + " |", flush=True)
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
