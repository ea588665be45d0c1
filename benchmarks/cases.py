#!/usr/bin/env python3
"""The benchmark cases: point clouds with a known true surface, a config, and ground truth.

    python benchmarks/cases.py --list                     # the public cases and what each tests
    python benchmarks/cases.py --list --suite features    # another suite's
    python benchmarks/cases.py OUT                        # every public case
    python benchmarks/cases.py OUT --only franke_noisy torus [--seed 0]
    python benchmarks/cases.py OUT --suite robust         # every case of another suite

Every case belongs to one suite (``SUITES``; ``CASES`` is the public one):

    public    the fifteen public cases: the paper's two experiments, height fields,
              closed surfaces, noise, outliers, shapes no plane sees as a height field,
              a footprint with holes
    robust    junk of other kinds (in the box, a floating blob, a piece of another
              object, points pushed off along the normal) and hard clean clouds
    unseen    open surfaces outside the public set (twisted strips, shells whose sides
              turn vertical, caps, cones), with a smaller swarm
    features  localised features where knot placement decides the fit, and smooth
              shapes where the swarm must not make the fit worse
    trims     footprints with ragged edges, slots, an annulus, small holes, a torn edge
    edges     data that end, thin out or carry junk near an edge: the surface should end
              where they do

For each CASE it writes OUT/CASE.ply (binary PLY, double x y z), OUT/CASE.yaml (the
config to fit it with) and OUT/CASE.gt.npz (``vertices``, ``triangles``: the true
surface as a 241 x 241 triangulation, only where the data are for a case with a
footprint; ``noise``: the Gaussian sigma, ``outliers``: the share of junk points, both
relative to the bounding-box diagonal), which ``benchmarks/score.py --gt`` reads. Only
numpy is needed. Seed 0 gives the public clouds (those in ``data_samples/`` among them);
other seeds give clouds nobody has tuned for.

A cloud is made in this order, from one generator seeded with ``--seed``: the (u, v)
samples, the points on the true surface, Gaussian noise (when there is any), the junk
points, and a shuffle (except for the organised grids).
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
Region = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (u, v) -> (N,) bool


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


def graded(n: int, ratio: float) -> Sampler:
    """Density rising linearly along u to ``ratio`` times its value at u = 0 (inverse of the cumulative)."""
    def sample(rng):
        share = rng.random(n)
        return (np.sqrt(1.0 + (ratio * ratio - 1.0) * share) - 1.0) / (ratio - 1.0), rng.random(n)
    return sample


def equal_area_cone(n: int, r0: float, r1: float) -> Sampler:
    """Uniform over a cone's area, its radius r0 at v = 0 and r1 at v = 1: v by the inverse of its cumulative area."""
    def sample(rng):
        u, share = rng.random(n), rng.random(n)
        if r1 == r0:
            return u, share
        return u, (np.sqrt(r0 * r0 + (r1 * r1 - r0 * r0) * share) - r0) / (r1 - r0)
    return sample


def equal_area_band(n: int, degrees: float) -> Sampler:
    """Uniform over the area of a sphere's band from latitude -degrees (v = 0) to +degrees (v = 1)."""
    def sample(rng):
        top = np.sin(np.radians(degrees))
        latitude = np.arcsin(rng.uniform(-top, top, n))
        return rng.random(n), 0.5 + latitude / (2.0 * np.radians(degrees))
    return sample


def equal_area_sphere(n: int) -> Sampler:
    """Uniform over a sphere's area: latitude by the inverse of its cumulative area."""
    def sample(rng):
        u = rng.random(n)
        return u, np.arccos(1.0 - 2.0 * rng.random(n)) / np.pi
    return sample


def equal_area_cap(n: int, degrees: float) -> Sampler:
    """Uniform over the area of a cap from the pole (v = 0) to a polar angle (v = 1)."""
    def sample(rng):
        cosine = 1.0 - rng.random(n) * (1.0 - np.cos(np.radians(degrees)))
        return rng.random(n), np.arccos(cosine) / np.radians(degrees)
    return sample


def latitude_longitude(nu: int, nv: int) -> Sampler:
    """nu meridians by nv parallels at the centres of their bands (rings crowd at the poles)."""
    def sample(rng):
        u, v = np.meshgrid(np.arange(nu) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")
        return u.ravel(), v.ravel()
    return sample


def scan_lines(lines: int, per_line: int) -> Sampler:
    """Lines across u, each sampled densely and a little unevenly along v."""
    def sample(rng):
        n = lines * per_line
        u = np.repeat((np.arange(lines) + 0.5) / lines, per_line) + rng.normal(0, 0.001, n)
        v = np.tile(np.linspace(0, 1, per_line), lines) + rng.uniform(-0.2, 0.2, n) / per_line
        return np.clip(u, 0, 1), np.clip(v, 0, 1)
    return sample


def sparse_edges(n: int) -> Sampler:
    """Uniform inside, thinning to 15% of the density at the square's edges."""
    def sample(rng):
        u, v = rng.random(4 * n), rng.random(4 * n)
        edge = np.minimum.reduce([u, 1 - u, v, 1 - v])
        keep = rng.random(4 * n) < 0.15 + 0.85 * np.minimum(1.0, 4.0 * edge)
        return u[keep][:n], v[keep][:n]
    return sample


def inside(region: Region, n: int, draws: Sampler | None = None) -> Sampler:
    """The first n samples of ``draws`` (default: 4n uniform ones) inside ``region(u, v)``."""
    draws = draws or scattered(4 * n)

    def sample(rng):
        u, v = draws(rng)
        keep = region(u, v)
        return u[keep][:n], v[keep][:n]
    return sample


# ---- the true surfaces ------------------------------------------------------------------------

def xyz(x, y, z) -> np.ndarray:
    return np.stack([np.broadcast_to(x, np.shape(z)), np.broadcast_to(y, np.shape(z)), z], axis=-1)


def height(z: Callable) -> Shape:
    """The height field z(u, v) over the unit square."""
    return lambda u, v: xyz(u, v, z(u, v))


def franke_height(u, v):
    """Franke's bivariate test function (1979) over the unit square."""
    x, y = 9 * u, 9 * v
    return (0.75 * np.exp(-((x - 2) ** 2 + (y - 2) ** 2) / 4) + 0.75 * np.exp(-((x + 1) ** 2) / 49 - (y + 1) / 10)
            + 0.5 * np.exp(-((x - 7) ** 2 + (y - 3) ** 2) / 4) - 0.2 * np.exp(-(x - 4) ** 2 - (y - 7) ** 2))


franke = height(franke_height)


def centred(z: Callable) -> Shape:
    """The height field z(x, y) over [-1, 1]^2, x = 2u - 1, y = 2v - 1."""
    def shape(u, v):
        x, y = 2 * u - 1, 2 * v - 1
        return xyz(x, y, z(x, y))
    return shape


gaussian_bump = centred(lambda x, y: 0.6 * np.exp(-2.0 * (x ** 2 + y ** 2)))
wave = centred(lambda x, y: 0.3 * np.sin(3 * x) * np.cos(3 * y))
plate = centred(lambda x, y: 0.15 * x * x - 0.1 * y * y + 0.05 * x * y)
saddle = centred(lambda x, y: 0.4 * (x * x - y * y))
narrow_bump_8x8 = centred(lambda x, y: 0.5 * np.exp(-(x * x + y * y) / 0.15 ** 2))
terrain = centred(lambda x, y: 0.15 * np.sin(2 * x + 1) * np.cos(1.5 * y) + 0.1 * x * y)


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


def sphere_cap(u, v):
    """u around, v from the pole to 60 degrees."""
    around, polar = TAU * u, np.radians(60.0) * v
    return xyz(np.sin(polar) * np.cos(around), np.sin(polar) * np.sin(around), np.cos(polar))


def tube(u, v):
    angle = TAU * u
    return xyz(0.8 * np.cos(angle), 0.8 * np.sin(angle), 3.0 * v - 1.5)


def half_cylinder(u, v):
    angle = np.pi * u
    return xyz(np.cos(angle), np.sin(angle), 2.0 * v)


def torus(u, v):
    big, small = 1.0, 0.35
    around, tube_angle = TAU * u, TAU * v
    ring = big + small * np.cos(tube_angle)
    return xyz(ring * np.cos(around), ring * np.sin(around), small * np.sin(tube_angle))


def elbow(u, v):
    """A pipe elbow: a tube of radius 0.3 bent along 120 degrees of a circle of radius 1;
    u around the tube, v along the bend."""
    around, along = TAU * u, np.radians(120.0) * v
    ring = 1.0 + 0.3 * np.cos(around)
    return xyz(ring * np.cos(along), ring * np.sin(along), 0.3 * np.sin(around))


def s_bend(u, v):
    """A tube of radius 0.15 swept along the S curve (2 t, 0.5 sin(2 pi t), 0), t in 0 .. 1
    (no arc: two bends the other way round); u around the tube, v along it (the curve's
    parameter, not its arc length)."""
    t, around = v, TAU * u
    centre = xyz(2.0 * t, 0.5 * np.sin(TAU * t), 0.0 * t)
    tangent = xyz(2.0 + 0.0 * t, np.pi * np.cos(TAU * t), 0.0 * t)
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
    normal = np.stack([-tangent[..., 1], tangent[..., 0], 0.0 * t], -1)
    return centre + 0.15 * (np.cos(around)[..., None] * normal + np.sin(around)[..., None] * xyz(0.0 * t, 0.0 * t, 1.0 + 0.0 * t))


def curl(u, v):
    """250 degrees of a cylinder: no plane sees it as a height field."""
    angle = np.radians(-35.0) + np.radians(250.0) * u
    return xyz(np.cos(angle), np.sin(angle), 1.5 * v)


def twisted_ribbon(u, v):
    """Three units long, one wide, twisted by 150 degrees about its long axis."""
    across, twist = v - 0.5, np.radians(150.0) * u
    return xyz(3.0 * u, across * np.cos(twist), across * np.sin(twist))


def twisted(degrees: float, length: float = 3.0) -> Shape:
    """A strip one unit wide, twisted by ``degrees`` about its long axis, symmetric about its middle."""
    def shape(u, v):
        twist, across = np.radians(degrees) * (u - 0.5), v - 0.5
        return xyz(length * u, across * np.cos(twist), across * np.sin(twist))
    return shape


def arc(degrees: float, height_: float = 1.5) -> Shape:
    """A cylinder section of ``degrees`` of arc, symmetric about the y axis."""
    def shape(u, v):
        angle = np.radians(90.0 - degrees / 2.0 + degrees * u)
        return xyz(np.cos(angle), np.sin(angle), height_ * v)
    return shape


def disc(u, v) -> tuple[np.ndarray, np.ndarray]:
    """The square mapped onto the unit disc: radius and angle."""
    x, y = 2 * u - 1, 2 * v - 1
    dx, dy = x * np.sqrt(1 - y * y / 2), y * np.sqrt(1 - x * x / 2)
    return np.hypot(dx, dy), np.arctan2(dy, dx)


def cap(polar_degrees: float) -> Shape:
    """A spherical cap from the pole to a polar angle (the square mapped onto the disc)."""
    def shape(u, v):
        r, around = disc(u, v)
        polar = np.radians(polar_degrees) * r
        return xyz(np.sin(polar) * np.cos(around), np.sin(polar) * np.sin(around), np.cos(polar))
    return shape


def tub(u, v):
    """A round pan: a flat bottom, then a quarter-circle wall that turns vertical at the rim."""
    r, around = disc(u, v)
    wall = np.radians(90.0) * np.clip((r - 0.5) / 0.5, 0.0, 1.0)
    rho = np.minimum(r, 0.5) + 0.3 * np.sin(wall)
    return xyz(rho * np.cos(around), rho * np.sin(around), 0.3 * (1.0 - np.cos(wall)))


def cone(u, v):
    angle, r = np.radians(220.0) * u, 0.5 + v
    return xyz(r * np.cos(angle), r * np.sin(angle), 1.2 * v)


def cone_sector(degrees: float, r0: float, r1: float, height_: float) -> Shape:
    """A cone sector of ``degrees`` around the z axis, its radius r0 at z = 0 to r1 at z = height_."""
    def shape(u, v):
        angle, r = np.radians(degrees) * u, r0 + (r1 - r0) * v
        return xyz(r * np.cos(angle), r * np.sin(angle), height_ * v)
    return shape


def sphere_band(longitude: float, latitude: float) -> Shape:
    """The unit sphere's band over ``longitude`` degrees (u, centred on +x) and latitudes within +-``latitude``."""
    def shape(u, v):
        lon, lat = np.radians(longitude) * (u - 0.5), np.radians(latitude) * (2.0 * v - 1.0)
        return xyz(np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat))
    return shape


def helicoid(u, v):
    """1.5 turns of a helicoid strip, radius 0.3 to 1.0 along v, rising 0.3 a turn: it overlaps itself seen from any plane."""
    angle, r = 1.5 * TAU * u, 0.3 + 0.7 * v
    return xyz(r * np.cos(angle), r * np.sin(angle), 0.3 * angle / TAU)


def s_fold(u, v):
    """A sheet whose cross-section (along u) is an S of two 230-degree arcs of radius 0.5 that turn opposite
    ways, tangent where they meet, extruded 1.5 along y: each arc's tangent turns past every direction,
    so no plane sees the sheet as a height field."""
    sweep, radius = np.radians(230.0), 0.5
    s = 2.0 * sweep * u
    first = s < sweep
    angle = np.where(first, s - sweep, np.pi - (s - sweep))  # about (-r, 0) anticlockwise, then (r, 0) clockwise
    centre = np.where(first, -radius, radius)
    return xyz(centre + radius * np.cos(angle), 1.5 * v, radius * np.sin(angle))


def vase(u, v):
    angle, r = TAU * u, 0.6 + 0.25 * np.sin(2.5 * v + 0.4)
    return xyz(r * np.cos(angle), r * np.sin(angle), 2.0 * v)


def tilted_saddle(u, v):
    """The saddle turned by 40 degrees about the axis (1, 1, 0) / sqrt 2 (Rodrigues)."""
    k = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    angle = np.radians(40.0)
    rotation = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
    return saddle(u, v) @ rotation.T


def step_and_ridge(u, v):
    """A steep step across u = 0.65 and a narrow ridge along v = 0.3."""
    return xyz(u, v, 0.3 * np.tanh(14 * (u - 0.65)) + 0.15 * np.exp(-((v - 0.3) / 0.07) ** 2))


def normals(shape: Shape, u: np.ndarray, v: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Unit normals (N, 3) of a shape by central differences in (u, v)."""
    du = shape(np.clip(u + h, 0, 1), v) - shape(np.clip(u - h, 0, 1), v)
    dv = shape(u, np.clip(v + h, 0, 1)) - shape(u, np.clip(v - h, 0, 1))
    n = np.cross(du, dv)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# ---- footprints: where a case has data ------------------------------------------------------

def plate_footprint(u, v):
    """Where the plate has data: an ellipse without two round holes."""
    ellipse = ((u - 0.5) / 0.48) ** 2 + ((v - 0.5) / 0.36) ** 2 < 1.0
    holes = ((u - 0.32) ** 2 + (v - 0.5) ** 2 < 0.09 ** 2) | ((u - 0.68) ** 2 + (v - 0.55) ** 2 < 0.06 ** 2)
    return ellipse & ~holes


def star(u, v):
    """A ragged outline: a radius with three harmonics around (0.5, 0.5)."""
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


# ---- junk: points replaced by something else -----------------------------------------------

@dataclass(frozen=True)
class Junk:
    """A share of the points replaced: ``box`` uniform in the bounding box; ``blob`` a ball
    (where = u0, v0, height, radius: over the surface point (u0, v0)); ``piece`` a flat square
    of another object tilted 30 degrees (where = u0, v0, height, side); ``near`` pushed along
    the normal by 5 to 20 noise sigmas (where = least, most). Lengths are shares of the diagonal."""

    kind: str
    share: float
    where: tuple = ()

    def replace(self, points, u, v, shape: Shape, noise: float, diagonal: float,
                rng: np.random.Generator) -> None:
        """Replace the junk's share of ``points`` (N, 3, sampled at (u, v)) in place;
        ``diagonal``: the clean cloud's."""
        k = int(round(self.share * len(points)))
        chosen = rng.choice(len(points), k, replace=False)
        if self.kind == "box":
            low, high = points.min(0), points.max(0)
            points[chosen] = low + rng.random((k, 3)) * (high - low)
        elif self.kind == "blob":
            u0, v0, lift, radius = (np.array([x]) for x in self.where)
            centre = shape(u0, v0)[0] + normals(shape, u0, v0)[0] * lift * diagonal
            offsets = rng.normal(size=(k, 3))
            offsets *= (radius * diagonal * rng.random(k) ** (1 / 3) / np.linalg.norm(offsets, axis=1))[:, None]
            points[chosen] = centre + offsets
        elif self.kind == "piece":
            u0, v0, lift, side = self.where
            base = shape(np.array([u0]), np.array([v0]))[0] + np.array([0.0, 0.0, lift * diagonal])
            a, b = rng.uniform(-0.5, 0.5, (2, k)) * side * diagonal
            tilt = np.radians(30.0)
            points[chosen] = (base + np.stack([a * np.cos(tilt), b, a * np.sin(tilt)], -1)
                              + rng.normal(0, noise * diagonal, (k, 3)))
        elif self.kind == "near":
            least, most = self.where
            amount = rng.uniform(least, most, k) * noise * diagonal * rng.choice([-1.0, 1.0], k)
            points[chosen] = shape(u[chosen], v[chosen]) + normals(shape, u[chosen], v[chosen]) * amount[:, None]
        else:
            raise ValueError(f"unknown junk {self.kind!r}")


# ---- the cases --------------------------------------------------------------------------------

SWARM = {"particles": 40, "iterations": 300, "inertia": 0.7, "c1": 1.5, "c2": 1.5, "seed": 7}


@dataclass(frozen=True)
class Case:
    name: str
    suite: str
    shape: Shape
    sampler: Sampler
    orders: tuple[int, int]
    net: tuple[int, int]
    topology: str
    note: str
    noise: float = 0.0  # Gaussian sigma over the bounding-box diagonal
    junk: Junk | None = None  # points replaced by junk
    organised: bool = False  # kept in scan order
    footprint: Region | None = None  # where the truth is (None: the whole square)
    loops: int | None = None  # trim loops the footprint calls for (outer + holes; None: untrimmed)
    swarm: dict = field(default_factory=lambda: dict(SWARM))

    @property
    def outliers(self) -> float:
        return self.junk.share if self.junk else 0.0

    def points(self, seed: int = 0) -> np.ndarray:
        rng = np.random.default_rng(seed)
        u, v = self.sampler(rng)
        points = self.shape(u, v)
        diagonal = np.linalg.norm(points.max(0) - points.min(0))
        if self.noise:
            points = points + rng.normal(0.0, self.noise * diagonal, points.shape)
        if self.junk:
            self.junk.replace(points, u, v, self.shape, self.noise, diagonal, rng)
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


def public_cases() -> list[Case]:
    def case(*args, **kw):
        return Case(args[0], "public", *args[1:], **kw)
    return [
        case("seed_patch16", gaussian_bump, organised(4, 4), (3, 3), (5, 5), "open",
             "the seed paper's first experiment: D=16, k=l=3, m=n=4", organised=True),
        case("seed_sphere169", sphere(), organised(13, 13, closed_u=True), (3, 3), (5, 5), "sphere",
             "the seed paper's sphere: D=169 (13x13), k=l=3, m=n=4", organised=True),
        case("franke_grid", franke, organised(33, 33), (4, 4), (12, 12), "open",
             "Franke's test function on an organised 33x33 grid", organised=True),
        case("franke_noisy", franke, scattered(5000), (4, 4), (12, 12), "open",
             "5,000 scattered, shuffled points, noise 0.2% of the diagonal", noise=0.002),
        case("wave_graded", wave, denser_towards_u1(8000), (4, 4), (10, 10), "open",
             "non-uniform density, shuffled"),
        case("quarter_cylinder", quarter_cylinder, scattered(2000), (3, 2), (3, 2), "open",
             "exactly representable only with rational weights (middle row w = sqrt(2)/2)"),
        case("cylinder", tube, scattered(4000), (4, 4), (10, 6), "cylinder", "closed in u", noise=0.001),
        case("sphere_noisy", sphere((1.0, -1.0, 0.5), 2.0), equal_area_sphere(6000), (4, 4), (10, 8), "sphere",
             "off-centre sphere, area-uniform samples", noise=0.002),
        case("torus", torus, scattered(8000), (4, 4), (14, 8), "torus", "closed in both directions (genus 1)"),
        case("franke_outliers", franke, scattered(5000), (4, 4), (12, 12), "open", "3% gross outliers",
             noise=0.001, junk=Junk("box", 0.03)),
        case("curl_sheet", curl, scattered(4000), (4, 4), (10, 6), "open",
             "open cylinder section over 250 degrees: not a height field over any plane", noise=0.001),
        case("twisted_ribbon", twisted_ribbon, scattered(3000), (4, 4), (10, 4), "open",
             "ribbon twisted 150 degrees about its long axis: not a height field over any plane"),
        case("step_bump", step_and_ridge, scattered(4000), (4, 4), (10, 10), "open",
             "a steep step and a narrow ridge: knot placement decides the fit at this net size"),
        case("franke_outliers10", franke, scattered(5000), (4, 4), (12, 12), "open", "10% gross outliers",
             noise=0.001, junk=Junk("box", 0.10)),
        case("plate_holes", plate, inside(plate_footprint, 5000), (4, 4), (8, 8), "open",
             "data on an elliptic region with two holes: the surface should end where the data end",
             noise=0.0005, footprint=plate_footprint),
    ]


def robust_cases() -> list[Case]:
    def case(name, shape, sampler, net, noise, note, junk=None, orders=(4, 4), topology="open"):
        return Case(name, "robust", shape, sampler, orders, net, topology, note, noise=noise, junk=junk)
    return [
        case("narrow_bump_8x8", narrow_bump_8x8, scattered(5000), (8, 8), 0.001,
             "a bump 0.15 wide that an 8 x 8 net cannot resolve; clean"),
        case("half_cylinder", half_cylinder, scattered(3000), (6, 4), 0.0,
             "an exact half cylinder, a plane projection folds at its sides; clean", orders=(3, 3)),
        case("sphere_grid", sphere(), latitude_longitude(32, 24), (10, 8), 0.0,
             "a coarse latitude-longitude grid on a sphere, rings dense at the poles; clean", topology="sphere"),
        case("terrain_lines", terrain, scan_lines(50, 120), (10, 10), 0.0005,
             "a terrain along 50 scan lines, 120 points each; clean"),
        case("saddle_junk5", tilted_saddle, scattered(4000), (8, 8), 0.002,
             "a saddle tilted 40 degrees, 5% junk in the bounding box", Junk("box", 0.05)),
        case("cap_junk8", sphere_cap, equal_area_cap(4000, 60.0), (8, 8), 0.001,
             "a sphere cap (60 degrees), 8% junk in the bounding box", Junk("box", 0.08)),
        case("graded_junk5", wave, denser_towards_u1(8000), (10, 10), 0.001,
             "density rising towards one edge, 5% junk in the bounding box", Junk("box", 0.05)),
        case("cylinder_junk8", tube, scattered(4000), (10, 6), 0.001,
             "a closed cylinder, 8% junk in the bounding box", Junk("box", 0.08), topology="cylinder"),
        case("blob_junk5", franke, scattered(5000), (12, 12), 0.001,
             "5% of the points in a ball (radius 0.04) floating 0.15 over the surface",
             Junk("blob", 0.05, (0.3, 0.6, 0.15, 0.04))),
        case("piece_junk5", franke, scattered(5000), (12, 12), 0.001,
             "5% of the points on a flat square (side 0.12), a piece of another object 0.12 over the surface",
             Junk("piece", 0.05, (0.75, 0.75, 0.12, 0.12))),
        case("near_junk10", franke, scattered(5000), (12, 12), 0.001,
             "10% of the points pushed 5 to 20 sigmas off the surface along its normal",
             Junk("near", 0.10, (5.0, 20.0))),
    ]


def unseen_cases() -> list[Case]:
    swarm = {**SWARM, "particles": 20, "iterations": 60}

    def case(name, shape, net, note, sampler=None, noise=0.0, strays=0.0):
        return Case(name, "unseen", shape, sampler or scattered(4000), (4, 4), net, "open", note, noise=noise,
                    junk=Junk("box", strays) if strays else None, swarm=swarm)
    return [
        case("twist200_graded", twisted(200.0), (12, 4), "strip twisted 200 deg, uneven density",
             denser_towards_u1(4000)),
        case("twist90_noisy", twisted(90.0), (10, 4), "strip twisted 90 deg, noisy", noise=1e-3),
        case("tub", tub, (10, 10), "a pan whose sides turn vertical, clean"),
        case("tub_noisy_strays", tub, (10, 10), "the pan, noisy, 1% strays", noise=1e-3, strays=0.01),
        case("hemisphere_noisy", cap(90.0), (10, 10), "hemisphere, noisy", noise=1e-3),
        case("cone220", cone, (10, 5), "cone section over 220 deg (a height field over its axis plane)"),
        case("arc200_sparse_edges", arc(200.0), (10, 5), "cylinder section over 200 deg, sparse edges, noisy",
             sparse_edges(4000), noise=1e-3),
        case("arc300_strays", arc(300.0), (12, 5), "cylinder section over 300 deg, 2% strays", strays=0.02),
        case("saddle_graded_noisy", saddle, (8, 8), "saddle height field", denser_towards_u1(4000), noise=2e-3),
        case("cap60_noisy", cap(60.0), (8, 8), "shallow cap (a height field)", noise=1e-3),
    ]


def feature_cases() -> list[Case]:
    def case(name, shape, sampler, net, note, noise=0.0, topology="open"):
        return Case(name, "features", shape, sampler, (4, 4), net, topology, note, noise=noise)
    return [
        # localised features: a knot vector must put its knots where they are
        case("step_diagonal", height(lambda u, v: 0.3 * np.tanh(12 * (u + v - 1.1))), scattered(4000), (10, 10),
             "a steep step along the diagonal u + v = 1.1"),
        case("cliff_noisy", height(lambda u, v: 0.25 * np.tanh(20 * (u - 0.4))), scattered(4000), (10, 10),
             "a cliff across u = 0.4, noise 0.1%", noise=0.001),
        case("twin_ridges", height(lambda u, v: 0.12 * np.exp(-((v - 0.25) / 0.05) ** 2)
                                   + 0.08 * np.exp(-((v - 0.7) / 0.04) ** 2) + 0.1 * u),
             scattered(4000), (10, 10), "two narrow ridges along u"),
        case("narrow_bump", height(lambda u, v: 0.2 * np.exp(-((u - 0.3) ** 2 + (v - 0.6) ** 2) / (2 * 0.06 ** 2))
                                   + 0.05 * u - 0.03 * v), scattered(3000), (10, 10),
             "a narrow bump on a gentle slope"),
        case("terrace_graded", height(lambda u, v: 0.15 * np.tanh(18 * (u - 0.35)) + 0.12 * np.tanh(18 * (u - 0.75))),
             denser_towards_u1(4000), (12, 8), "two steps, density rising towards u = 1"),
        case("ridge_curve", height(lambda u, v: 0.15 * np.exp(-((v - 0.5 - 0.15 * np.sin(5 * u)) / 0.06) ** 2)),
             scattered(5000), (12, 12), "a narrow ridge along a curve, noise", noise=0.0005),
        # smooth shapes: the swarm must not make them worse
        case("saddle_noisy", saddle, scattered(3000), (8, 8), "a saddle, noise 0.3%", noise=0.003),
        case("vase", vase, scattered(4000), (10, 6), "a vase (radius varying with height), closed in u",
             noise=0.001, topology="cylinder"),
        case("elbow", elbow, scattered(4000), (8, 6), "a pipe elbow: a tube bent along 120 degrees, closed in u",
             noise=0.001, topology="cylinder"),
        case("s_bend", s_bend, scattered(4000), (8, 10), "a tube swept along an S curve (no arc), closed in u",
             noise=0.001, topology="cylinder"),
        case("sphere_sparse", sphere((0.3, -0.2, 0.1), 1.2), equal_area_sphere(900), (8, 6),
             "900 points on a sphere, noise", noise=0.002, topology="sphere"),
        case("terrain_noisy", height(lambda u, v: 0.1 * np.sin(7 * u + 1) * np.cos(5 * v) + 0.05 * np.sin(13 * v)),
             scattered(6000), (12, 12), "terrain-like waves, noise 0.2%", noise=0.002),
    ]


def trim_cases() -> list[Case]:
    """Footprints other than plate_holes', fitted with ``trim: auto`` (the default) and a
    smaller swarm; ``loops`` is what the footprint calls for."""
    swarm = {**SWARM, "particles": 20, "iterations": 100}

    def case(name, shape, sampler, noise, footprint, loops):
        return Case(name, "trims", shape, sampler, (4, 4), (10, 10), "open", name, noise=noise,
                    footprint=footprint, loops=loops, swarm=swarm)
    return [
        case("wave_star_slot", wave, inside(star_slot, 4000), 0.001, star_slot, 2),
        case("franke_annulus", franke, inside(annulus, 3000), 0.002, annulus, 2),
        case("plate_sparse_holes", plate, inside(three_small_holes, 1500), 0.0005, three_small_holes, 4),
        case("curl_torn", curl, inside(torn, 3000), 0.001, torn, 1),
        case("wave_l_graded", wave, inside(l_shape, 4000, denser_towards_u1(8 * 4000)), 0.0, l_shape, 1),
        case("franke_full", franke, scattered(3000), 0.002, None, None),
    ]


def edge_cases() -> list[Case]:
    """Clouds whose data end, thin out or carry junk near an edge: where the data end, the
    surface should end, neither short of it nor past it."""
    def case(name, shape, sampler, orders, net, note, noise=0.0, junk=None):
        return Case(name, "edges", shape, sampler, orders, net, "open", note, noise=noise, junk=junk)
    return [
        case("step_bump14", step_and_ridge, scattered(4000), (4, 4), (14, 14),
             "the public step and ridge on a finer net: edges of a height field with steep features"),
        case("graded_helicoid", helicoid, graded(4000, 20.0), (4, 4), (12, 6),
             "1.5 turns of a helicoid, density rising 20-fold along the turns: the sparse end must not overrun",
             noise=0.0005),
        case("s_fold", s_fold, scattered(4000), (4, 4), (12, 6),
             "a sheet folded like an S (two 230-degree arcs), no height field: its edges curl back", noise=0.001),
        case("tilted_saddle_junk5", tilted_saddle, scattered(4000), (4, 4), (8, 8),
             "the robust saddle tilted 40 degrees with 5% junk in the box: junk must not stretch the edges",
             noise=0.002, junk=Junk("box", 0.05)),
        case("franke_junk4", franke, scattered(5000), (4, 4), (12, 12),
             "Franke with 4% junk in the box: junk must not stretch the edges", noise=0.001, junk=Junk("box", 0.04)),
        case("cone_sector270", cone_sector(270.0, 0.5, 1.0, 1.0), equal_area_cone(3000, 0.5, 1.0), (3, 2), (7, 2),
             "a cone sector over 270 degrees, area-uniform: exactly rational quadratic (three 90-degree arcs) "
             "by linear"),
        case("sphere_band288", sphere_band(288.0, 35.0), equal_area_band(4000, 35.0), (4, 4), (10, 6),
             "a sphere's band, 288 degrees of longitude by latitudes -35 to 35: edges on a doubly curved surface",
             noise=0.001),
        case("wave_sparse_end", wave, graded(4000, 20.0), (4, 4), (10, 10),
             "the public wave, density falling 20-fold towards u = 0: the sparse end must still be covered"),
    ]


def thick_cases() -> list[Case]:
    """Clouds whose noise is about as wide as their sampling step sqrt(area / points) or wider (a
    phone's depth scan, photogrammetry of a dull surface): a dozen neighbours make a blob,
    not a disc, and the rim's noisy points hold the net where no data are."""
    def case(name, shape, note, noise):
        return Case(name, "thick", shape, scattered(4000), (4, 4), (8, 8), "open", note, noise=noise)
    return [
        case("cap60_thick", cap(60.0), "a 60-degree cap (a height field), noise 1.1 sampling steps", 0.012),
        case("cap60_thicker", cap(60.0), "the cap, noise 2.1 sampling steps", 0.024),
        case("hemisphere_thick", cap(90.0), "a hemisphere, its rim vertical, noise 0.9 sampling steps", 0.012),
        case("franke_thick", franke, "Franke's surface, noise 1e-2 of the diagonal", 0.01),
        case("saddle_thick", saddle, "a saddle, noise 1e-2 of the diagonal", 0.01),
        case("tub_thick", tub, "the pan whose sides turn vertical, noise 1.2e-2 of the diagonal", 0.012),
    ]


SUITES: dict[str, dict[str, Case]] = {
    name: {case.name: case for case in make()}
    for name, make in (("public", public_cases), ("robust", robust_cases), ("unseen", unseen_cases),
                       ("features", feature_cases), ("trims", trim_cases), ("edges", edge_cases),
                       ("thick", thick_cases))}
CASES = SUITES["public"]


def ply(points: np.ndarray) -> bytes:
    """A cloud as binary little-endian PLY, double x y z and nothing else (the product's
    mesh writer adds a comment and faces)."""
    points = np.ascontiguousarray(points, "<f8")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property double x\nproperty double y\nproperty double z\nend_header\n")
    return header.encode() + points.tobytes()


@dataclass(frozen=True)
class CaseFiles:
    cloud: Path
    config: Path
    truth: Path


def write(case: Case, out: Path, seed: int = 0) -> CaseFiles:
    files = CaseFiles(out / f"{case.name}.ply", out / f"{case.name}.yaml", out / f"{case.name}.gt.npz")
    files.cloud.write_bytes(ply(case.points(seed)))
    files.config.write_text(case.yaml())
    vertices, triangles = case.truth()
    np.savez_compressed(files.truth, vertices=vertices, triangles=triangles, noise=case.noise,
                        outliers=case.outliers)
    return files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", nargs="?", type=Path, help="directory to write the cases to")
    ap.add_argument("--suite", default="public", choices=list(SUITES), help="the case set (default: public)")
    ap.add_argument("--only", nargs="+", metavar="CASE", help="these cases only")
    ap.add_argument("--seed", type=int, default=0, help="0: the public clouds; others: fresh draws")
    ap.add_argument("--list", action="store_true", help="list the cases")
    args = ap.parse_args(argv)
    cases = SUITES[args.suite]
    if args.list or args.out is None:
        for case in cases.values():
            print(f"{case.name:20s} {case.note}")
        return 0
    unknown = [name for name in args.only or [] if name not in cases]
    if unknown:
        print(f"cases.py: unknown case {unknown[0]!r} (see --list)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.only or list(cases):
        write(cases[name], args.out, args.seed)
        print(f"wrote {args.out / name}.{{ply,yaml,gt.npz}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
