"""What the tests share: an independent reference evaluator, sample surfaces and clouds,
and a stand-in for the fitter that the CLI tests pass in as a parameter.

The reference evaluator uses scipy alone (``BSpline`` basis functions, the explicit
double sum over the net), never psonurbs' own basis, so it can judge our evaluation,
our exports and the files other readers see.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.interpolate import BSpline

from psonurbs.cli.main import cli
from psonurbs.errors import InputError
from psonurbs.geometry.basis import clamped_knots, periodic_knots
from psonurbs.geometry.nurbs import NurbsSurface

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "data_samples"


# ---- the reference evaluator ----------------------------------------------------------

def reference_basis(x, knots, degree, derivative=0) -> np.ndarray:
    """All basis functions (columns) at x, from scipy's BSpline with unit coefficients."""
    n = len(knots) - degree - 1
    spline = BSpline(np.asarray(knots, float), np.eye(n), degree)
    if derivative:
        spline = spline.derivative(derivative)
    return spline(np.asarray(x, float))


def reference_evaluate(knots_u, knots_v, degree_u, degree_v, control_points, weights, u, v,
                       derivative=(0, 0)) -> np.ndarray:
    """S(u, v), or S_u / S_v with ``derivative`` (1, 0) / (0, 1), by the explicit double sum
    over the net: S = A / W, A = sum w_ij N_i N_j P_ij, W = sum w_ij N_i N_j, and the
    quotient rule S_u = (A_u - W_u S) / W. Shape (N, 3)."""
    cp, w = np.asarray(control_points, float), np.asarray(weights, float)
    nu, nv = (reference_basis(u, knots_u, degree_u), reference_basis(v, knots_v, degree_v))
    a = np.einsum("ri,rj,ij,ijk->rk", nu, nv, w, cp)
    den = np.einsum("ri,rj,ij->r", nu, nv, w)
    s = a / den[:, None]
    if derivative == (0, 0):
        return s
    du, dv = derivative
    nu_d = reference_basis(u, knots_u, degree_u, du) if du else nu
    nv_d = reference_basis(v, knots_v, degree_v, dv) if dv else nv
    a_d = np.einsum("ri,rj,ij,ijk->rk", nu_d, nv_d, w, cp)
    den_d = np.einsum("ri,rj,ij->r", nu_d, nv_d, w)
    return (a_d - den_d[:, None] * s) / den[:, None]


def reference_points(surface: NurbsSurface, u, v, derivative=(0, 0)) -> np.ndarray:
    """:func:`reference_evaluate` on a surface's own arrays."""
    return reference_evaluate(surface.knots_u, surface.knots_v, surface.degree_u, surface.degree_v,
                              surface.control_points, surface.weights, u, v, derivative)


# ---- sample surfaces ------------------------------------------------------------------

def open_surface(polynomial: bool = False) -> NurbsSurface:
    """A rational bicubic x biquadratic patch, 6 x 5, far from the origin and not unit size."""
    rng = np.random.default_rng(3)
    nu, nv, p, q = 6, 5, 3, 2
    u, v = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    cp = np.stack([u, v, 0.3 * np.sin(3 * u) * v + 0.05 * rng.standard_normal(u.shape)], -1)
    cp = 250.0 * cp + np.array([1000.0, -40.0, 7.0])
    weights = np.ones((nu, nv)) if polynomial else rng.uniform(0.4, 2.5, (nu, nv))
    return NurbsSurface(p, q, clamped_knots(nu, p, np.array([0.3, 0.45])),
                        clamped_knots(nv, q, np.array([0.2, 0.7])), cp, weights)


def closed_u_surface() -> NurbsSurface:
    """A rational tube: periodic in u (the last `degree` rows repeat the first), clamped in v."""
    rng = np.random.default_rng(5)
    n, p, q, nv = 6, 2, 2, 4
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(angle), np.sin(angle)], -1) * rng.uniform(0.8, 1.2, (n, 1))
    rows = np.concatenate([ring, ring[:p]])  # n + p rows, the last p repeat the first
    height = np.linspace(0, 2, nv)
    cp = np.concatenate([np.repeat(rows[:, None, :], nv, 1),
                         np.broadcast_to(height[None, :, None], (n + p, nv, 1))], -1)
    w_distinct = rng.uniform(0.6, 1.6, (n, nv))
    weights = np.concatenate([w_distinct, w_distinct[:p]])
    ku = periodic_knots(n, p, np.array([0.15, 0.3, 0.55, 0.7, 0.9]))
    return NurbsSurface(p, q, ku, clamped_knots(nv, q), cp, weights, closed_u=True)


def random_surface(seed, pu=3, pv=2, nu=6, nv=5, rational=True, domain_u=(0.0, 1.0)) -> NurbsSurface:
    """A random clamped patch with random inner knots (and weights)."""
    rng = np.random.default_rng(seed)
    iu = np.sort(rng.uniform(0.1, 0.9, nu - pu - 1))
    iv = np.sort(rng.uniform(0.1, 0.9, nv - pv - 1))
    a, b = domain_u
    tu = a + (b - a) * clamped_knots(nu, pu, iu)
    tv = clamped_knots(nv, pv, iv)
    cp = rng.normal(size=(nu, nv, 3))
    w = rng.uniform(0.3, 3.0, size=(nu, nv)) if rational else np.ones((nu, nv))
    return NurbsSurface(pu, pv, tu, tv, cp, w)


# ---- sample clouds --------------------------------------------------------------------

def franke_z(x, y):
    """Franke's test function on [0, 1]^2."""
    return (0.75 * np.exp(-((9 * x - 2) ** 2 + (9 * y - 2) ** 2) / 4)
            + 0.75 * np.exp(-(9 * x + 1) ** 2 / 49 - (9 * y + 1) / 10)
            + 0.5 * np.exp(-((9 * x - 7) ** 2 + (9 * y - 3) ** 2) / 4)
            - 0.2 * np.exp(-(9 * x - 4) ** 2 - (9 * y - 7) ** 2))


def franke(n=300, seed=4, noise=0.01) -> np.ndarray:
    """n points of Franke's function, uniform over the square, Gaussian noise in z."""
    rng = np.random.default_rng(seed)
    x, y = rng.random((2, n))
    return np.column_stack([x, y, franke_z(x, y) + noise * rng.normal(size=n)])


GOOD = np.array([[x, y, x * y] for x in range(4) for y in range(4)], dtype=float)


def can(n: int, seed: int = 0, radius: float = 0.5, height: float = 1.2, noise: float = 5e-4) -> np.ndarray:
    """A closed can: a cylinder's wall and two flat discs, sampled area-uniformly (N, 3)."""
    rng = np.random.default_rng(seed)
    wall, disc = 2 * np.pi * radius * height, np.pi * radius ** 2
    counts = rng.multinomial(n, np.array([wall, disc, disc]) / (wall + 2 * disc))
    t = 2 * np.pi * rng.random(counts[0])
    parts = [np.column_stack([radius * np.cos(t), radius * np.sin(t), height * rng.random(counts[0])])]
    for count, z in zip(counts[1:], (0.0, height)):
        r, a = radius * np.sqrt(rng.random(count)), 2 * np.pi * rng.random(count)
        parts.append(np.column_stack([r * np.cos(a), r * np.sin(a), np.full(count, z)]))
    p = np.concatenate(parts)
    return p + noise * np.linalg.norm(np.ptp(p, axis=0)) * rng.standard_normal(p.shape)


def ply_bytes(points) -> bytes:
    """A binary little-endian PLY of the points (double x, y, z)."""
    points = np.ascontiguousarray(points, dtype="<f8").reshape(-1, 3)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
            "property double x\nproperty double y\nproperty double z\nend_header\n")
    return head.encode() + points.tobytes()


# ---- the command line, and a stand-in for the fitter -----------------------------------

def run(*args, fit: Callable | None = None):
    """``psonurbs ARGS`` in this process; ``fit`` replaces the fitter (see :class:`FakeFit`)."""
    try:
        runner = CliRunner(mix_stderr=False)  # click < 8.2
    except TypeError:
        runner = CliRunner()  # click >= 8.2 keeps stderr apart
    return runner.invoke(cli, [str(a) for a in args], catch_exceptions=False,
                         obj=None if fit is None else {"fit": fit})


class FakeSurface:
    def to_dict(self):
        return {"degree_u": 1, "degree_v": 1, "knots_u": [0.0, 0.0, 1.0, 1.0],
                "knots_v": [0.0, 0.0, 1.0, 1.0],
                "control_points": [[[0.0, 0.0, 0.0], [0.0, 3.0, 0.0]],
                                   [[3.0, 0.0, 0.0], [3.0, 3.0, 9.0]]],
                "weights": [[1.0, 1.0], [1.0, 1.0]], "closed_u": False, "closed_v": False}

    def tessellate(self, n_u, n_v):
        u, v = np.meshgrid(np.linspace(0, 3, n_u), np.linspace(0, 3, n_v), indexing="ij")
        verts = np.stack([u.ravel(), v.ravel(), (u * v).ravel()], -1)
        i, j = np.meshgrid(np.arange(n_u - 1), np.arange(n_v - 1), indexing="ij")
        a = (i * n_v + j).ravel()
        return verts, np.concatenate([np.stack([a, a + n_v, a + 1], 1),
                                      np.stack([a + 1, a + n_v, a + n_v + 1], 1)])


@dataclass
class FakeResult:
    surface: FakeSurface = field(default_factory=FakeSurface)
    topology: str = "open"
    metrics: dict = field(default_factory=lambda: {"rmse": 1.234e-4, "max_error": 4.567e-4,
                                                   "n_points": 16})
    curve_header: list = field(default_factory=lambda: ["iteration", "best_rmse", "mean_rmse"])
    curve: np.ndarray = field(default_factory=lambda: np.array([[0, 0.2, 0.3], [1, 0.1, 0.25]]))
    info: dict = field(default_factory=lambda: {"strategy": "hybrid", "evaluations": 80})
    notes: list = field(default_factory=lambda: ["16 points for 4 control points"])
    warnings: list = field(default_factory=list)


@dataclass
class FakeFit:
    """A fitter that records its calls and returns ``behaviour()`` (a :class:`FakeResult`
    unless a test sets another), so that the CLI's own work (reading, reporting, the output
    contract) is tested apart from the numerics. Clouds under 10 points are refused."""

    calls: list = field(default_factory=list)
    behaviour: Callable = FakeResult

    def __call__(self, points, config, on_iteration=None):
        self.calls.append((len(points), config))
        if len(points) < 10:
            raise InputError(f"{len(points)} points are too few for orders {config.orders}")
        for it, best in enumerate([0.2, 0.1]):
            on_iteration(it, best, best + 0.1)
        return self.behaviour()

    def run(self, *args):
        """``psonurbs ARGS`` with this fake as the fitter."""
        return run(*args, fit=self)


@pytest.fixture
def fake_fit() -> FakeFit:
    return FakeFit()
