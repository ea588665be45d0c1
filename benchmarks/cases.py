#!/usr/bin/env python3
"""The benchmark cases: point clouds with a known true surface, a config, and ground truth.

    python benchmarks/cases.py --list                     # the cases and what each tests
    python benchmarks/cases.py OUT                        # every case
    python benchmarks/cases.py OUT --only franke_noisy torus [--seed 0]

For each CASE it writes OUT/CASE.ply (binary PLY, double x y z), OUT/CASE.yaml (the
config to fit it with) and OUT/CASE.gt.npz (``vertices``, ``triangles``: the true
surface as a 241 x 241 triangulation, only where the data are for a case with a
footprint; ``noise``: the Gaussian sigma, ``outliers``: the share of junk points, both
relative to the bounding-box diagonal), which ``benchmarks/score.py --gt`` reads. Only
numpy is needed. Seed 0 gives the public clouds (those in ``data_samples/`` among them);
other seeds give clouds nobody has tuned for.

A cloud is made in this order, from one generator seeded with ``--seed``: the (u, v)
samples, the points on the true surface, Gaussian noise, junk points uniform in the
bounding box, and a shuffle (except for the three organised grids).
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

TAU = 2.0 * np.pi
TRUTH_GRID = 241

Sampler = Callable[[np.random.Generator], "tuple[np.ndarray, np.ndarray]"]
Shape = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (u, v) in [0, 1]^2 -> (N, 3)


# ---- how the parameter square is sampled -----------------------------------------------

def organised(nu: int, nv: int, closed_u: bool = False) -> Sampler:
    """An nu x nv grid in scan order (u slowest); a closed u leaves out u = 1 (it is u = 0)."""
    def sample(rng):
        u, v = np.meshgrid(np.linspace(0, 1, nu, endpoint=not closed_u), np.linspace(0, 1, nv), indexing="ij")
        return u.ravel(), v.ravel()
    return sample


def scattered(n: int) -> Sampler:
    def sample(rng):
        u = rng.random(n)
        return u, rng.random(n)
    return sample


def denser_towards_u1(n: int) -> Sampler:
    """Density growing linearly with u: u = sqrt(uniform)."""
    def sample(rng):
        u = np.sqrt(rng.random(n))
        return u, rng.random(n)
    return sample


def equal_area_sphere(n: int) -> Sampler:
    """Uniform over a sphere's area: latitude by the inverse of its cumulative area."""
    def sample(rng):
        u = rng.random(n)
        return u, np.arccos(1.0 - 2.0 * rng.random(n)) / np.pi
    return sample


def inside(region: Callable, n: int) -> Sampler:
    """The first n of 4n uniform samples that fall inside ``region(u, v)``."""
    def sample(rng):
        u, v = rng.random(4 * n), rng.random(4 * n)
        keep = region(u, v)
        return u[keep][:n], v[keep][:n]
    return sample


# ---- the true surfaces ------------------------------------------------------------------------

def xyz(x, y, z) -> np.ndarray:
    return np.stack([np.broadcast_to(x, np.shape(z)), np.broadcast_to(y, np.shape(z)), z], axis=-1)


def gaussian_bump(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return xyz(x, y, 0.6 * np.exp(-2.0 * (x ** 2 + y ** 2)))


def franke(u, v):
    """Franke's bivariate test function (1979) over the unit square."""
    x, y = 9 * u, 9 * v
    z = (0.75 * np.exp(-((x - 2) ** 2 + (y - 2) ** 2) / 4) + 0.75 * np.exp(-((x + 1) ** 2) / 49 - (y + 1) / 10)
         + 0.5 * np.exp(-((x - 7) ** 2 + (y - 3) ** 2) / 4) - 0.2 * np.exp(-(x - 4) ** 2 - (y - 7) ** 2))
    return xyz(u, v, z)


def wave(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return xyz(x, y, 0.3 * np.sin(3 * x) * np.cos(3 * y))


def quarter_cylinder(u, v):
    """Radius 1, height 2, 90 degrees of arc: a rational quadratic surface exactly."""
    angle = 0.5 * np.pi * u
    return xyz(np.cos(angle), np.sin(angle), 2.0 * v)


def sphere(center=(0.0, 0.0, 0.0), radius=1.0) -> Shape:
    """u: longitude, v: from the south pole (v = 0) to the north pole."""
    def shape(u, v):
        lon, colat = TAU * u, np.pi * v
        return np.asarray(center) + radius * xyz(np.sin(colat) * np.cos(lon), np.sin(colat) * np.sin(lon),
                                                 -np.cos(colat))
    return shape


def tube(u, v):
    angle = TAU * u
    return xyz(0.8 * np.cos(angle), 0.8 * np.sin(angle), 3.0 * v - 1.5)


def torus(u, v):
    big, small = 1.0, 0.35
    around, tube_angle = TAU * u, TAU * v
    ring = big + small * np.cos(tube_angle)
    return xyz(ring * np.cos(around), ring * np.sin(around), small * np.sin(tube_angle))


def curl(u, v):
    """250 degrees of a cylinder: no plane sees it as a height field."""
    angle = np.radians(-35.0) + np.radians(250.0) * u
    return xyz(np.cos(angle), np.sin(angle), 1.5 * v)


def twisted_ribbon(u, v):
    """Three units long, one wide, twisted by 150 degrees about its long axis."""
    across, twist = v - 0.5, np.radians(150.0) * u
    return xyz(3.0 * u, across * np.cos(twist), across * np.sin(twist))


def step_and_ridge(u, v):
    """A steep step across u = 0.65 and a narrow ridge along v = 0.3."""
    return xyz(u, v, 0.3 * np.tanh(14 * (u - 0.65)) + 0.15 * np.exp(-((v - 0.3) / 0.07) ** 2))


def plate(u, v):
    x, y = 2 * u - 1, 2 * v - 1
    return xyz(x, y, 0.15 * x * x - 0.1 * y * y + 0.05 * x * y)


def plate_footprint(u, v):
    """Where the plate has data: an ellipse without two round holes."""
    ellipse = ((u - 0.5) / 0.48) ** 2 + ((v - 0.5) / 0.36) ** 2 < 1.0
    holes = ((u - 0.32) ** 2 + (v - 0.5) ** 2 < 0.09 ** 2) | ((u - 0.68) ** 2 + (v - 0.55) ** 2 < 0.06 ** 2)
    return ellipse & ~holes


# ---- the cases --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    name: str
    shape: Shape
    sampler: Sampler
    orders: tuple[int, int]
    net: tuple[int, int]
    topology: str
    note: str
    noise: float = 0.0  # Gaussian sigma over the bounding-box diagonal
    outliers: float = 0.0  # share of the points replaced by junk
    organised: bool = False  # kept in scan order
    footprint: Callable | None = None  # where the truth is (None: the whole square)
    swarm: dict = field(default_factory=lambda: {"particles": 40, "iterations": 300, "inertia": 0.7,
                                                 "c1": 1.5, "c2": 1.5, "seed": 7})

    def points(self, seed: int = 0) -> np.ndarray:
        rng = np.random.default_rng(seed)
        u, v = self.sampler(rng)
        points = self.shape(u, v)
        diagonal = np.linalg.norm(points.max(0) - points.min(0))
        if self.noise:
            points = points + rng.normal(0.0, self.noise * diagonal, points.shape)
        if self.outliers:
            count = int(round(self.outliers * len(points)))
            junk = rng.choice(len(points), count, replace=False)
            low, high = points.min(0), points.max(0)
            points[junk] = low + rng.random((count, 3)) * (high - low)
        if not self.organised:
            points = points[rng.permutation(len(points))]
        return points

    def truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The true surface as a triangulated TRUTH_GRID x TRUTH_GRID parameter grid
        (restricted to the triangles inside the footprint, if any)."""
        n = TRUTH_GRID
        u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
        vertices = self.shape(u.ravel(), v.ravel())
        i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
        corner = (i * n + j).ravel()
        triangles = np.concatenate([np.stack([corner, corner + n, corner + 1], 1),
                                    np.stack([corner + 1, corner + n, corner + n + 1], 1)])
        if self.footprint is not None:
            covered = self.footprint(u.ravel(), v.ravel())
            triangles = triangles[covered[triangles].all(axis=1)]
            used = np.unique(triangles)
            renumber = np.full(len(vertices), -1)
            renumber[used] = np.arange(len(used))
            vertices, triangles = vertices[used], renumber[triangles]
        return vertices, triangles.astype(np.int32)

    def yaml(self) -> str:
        lines = [f"# {self.note}", f"orders: [{self.orders[0]}, {self.orders[1]}]",
                 f"net_size: [{self.net[0]}, {self.net[1]}]", f"topology: {self.topology}", "swarm:"]
        return "\n".join(lines + [f"  {key}: {value}" for key, value in self.swarm.items()]) + "\n"


CASES = {case.name: case for case in [
    Case("seed_patch16", gaussian_bump, organised(4, 4), (3, 3), (5, 5), "open",
         "the seed paper's first experiment: D=16, k=l=3, m=n=4", organised=True),
    Case("seed_sphere169", sphere(), organised(13, 13, closed_u=True), (3, 3), (5, 5), "sphere",
         "the seed paper's sphere: D=169 (13x13), k=l=3, m=n=4", organised=True),
    Case("franke_grid", franke, organised(33, 33), (4, 4), (12, 12), "open",
         "Franke's test function on an organised 33x33 grid", organised=True),
    Case("franke_noisy", franke, scattered(5000), (4, 4), (12, 12), "open",
         "5,000 scattered, shuffled points, noise 0.2% of the diagonal", noise=0.002),
    Case("wave_graded", wave, denser_towards_u1(8000), (4, 4), (10, 10), "open",
         "non-uniform density, shuffled"),
    Case("quarter_cylinder", quarter_cylinder, scattered(2000), (3, 2), (3, 2), "open",
         "exactly representable only with rational weights (middle row w = sqrt(2)/2)"),
    Case("cylinder", tube, scattered(4000), (4, 4), (10, 6), "cylinder", "closed in u", noise=0.001),
    Case("sphere_noisy", sphere((1.0, -1.0, 0.5), 2.0), equal_area_sphere(6000), (4, 4), (10, 8), "sphere",
         "off-centre sphere, area-uniform samples", noise=0.002),
    Case("torus", torus, scattered(8000), (4, 4), (14, 8), "torus", "closed in both directions (genus 1)"),
    Case("franke_outliers", franke, scattered(5000), (4, 4), (12, 12), "open", "3% gross outliers",
         noise=0.001, outliers=0.03),
    Case("curl_sheet", curl, scattered(4000), (4, 4), (10, 6), "open",
         "open cylinder section over 250 degrees: not a height field over any plane", noise=0.001),
    Case("twisted_ribbon", twisted_ribbon, scattered(3000), (4, 4), (10, 4), "open",
         "ribbon twisted 150 degrees about its long axis: not a height field over any plane"),
    Case("step_bump", step_and_ridge, scattered(4000), (4, 4), (10, 10), "open",
         "a steep step and a narrow ridge: knot placement decides the fit at this net size"),
    Case("franke_outliers10", franke, scattered(5000), (4, 4), (12, 12), "open", "10% gross outliers",
         noise=0.001, outliers=0.10),
    Case("plate_holes", plate, inside(plate_footprint, 5000), (4, 4), (8, 8), "open",
         "data on an elliptic region with two holes: the surface should end where the data end",
         noise=0.0005, footprint=plate_footprint),
]}


def ply(points: np.ndarray) -> bytes:
    points = np.ascontiguousarray(points, "<f8")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property double x\nproperty double y\nproperty double z\nend_header\n")
    return header.encode() + points.tobytes()


def write(case: Case, out: Path, seed: int = 0) -> None:
    (out / f"{case.name}.ply").write_bytes(ply(case.points(seed)))
    (out / f"{case.name}.yaml").write_text(case.yaml())
    vertices, triangles = case.truth()
    np.savez_compressed(out / f"{case.name}.gt.npz", vertices=vertices, triangles=triangles,
                        noise=case.noise, outliers=case.outliers)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", nargs="?", type=Path, help="directory to write the cases to")
    ap.add_argument("--only", nargs="+", metavar="CASE", help="these cases only")
    ap.add_argument("--seed", type=int, default=0, help="0: the public clouds; others: fresh draws")
    ap.add_argument("--list", action="store_true", help="list the cases")
    args = ap.parse_args(argv)
    if args.list or args.out is None:
        for case in CASES.values():
            print(f"{case.name:20s} {case.note}")
        return 0
    unknown = [name for name in args.only or [] if name not in CASES]
    if unknown:
        print(f"cases.py: unknown case {unknown[0]!r} (see --list)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.only or list(CASES):
        write(CASES[name], args.out, args.seed)
        print(f"wrote {args.out / name}.{{ply,yaml,gt.npz}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
