"""The fitter: organise -> parametrise -> swarm -> polish, for one cloud.

``strategy: hybrid`` (default): the swarm searches what is non-linear (the inner knots
of both directions and the weights); inside its fitness the control points come from
the regularised least-squares solve, and a particle is judged by the K-fold
cross-validated RMSE on points its solve did not see, so the swarm cannot win by
tuning knots to noise. ``strategy: full`` is the paper's own search space (Eq. 10,
:mod:`psonurbs.paper`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from .net import NetLayout
from .nurbs import NurbsSurface
from .organise import Cloud, organise, subsample
from .parametrise import Parametrisation, parametrise_open
from .polish import closest_parameters
from .pso import Polytope, minimise
from .solve import RegularisedLeastSquares

CURVE_HEADER = ["iteration", "best_rmse", "mean_rmse"]


@dataclass
class FitResult:
    surface: NurbsSurface  # in the cloud's own coordinates
    topology: str
    metrics: dict
    curve: np.ndarray  # (iterations, 3): iteration, best and mean RMSE (cloud units)
    info: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    curve_header: list[str] = field(default_factory=lambda: list(CURVE_HEADER))


def ordered_knots_polytope(count: int, gap: float) -> Polytope:
    """``gap <= t_1``, ``t_k + gap <= t_{k+1}``, ``t_c <= 1 - gap`` as ``A t <= b``."""
    a = np.zeros((count + 1, count))
    b = np.full(count + 1, -gap)
    for k in range(count + 1):
        if k > 0:
            a[k, k - 1] = 1.0
        if k < count:
            a[k, k] = -1.0
    b[count] = 1.0 - gap
    return Polytope(a, b)


def random_knots(count: int, gap: float, rng: np.random.Generator) -> np.ndarray:
    """Random inner knots with every gap (ends included) at least ``gap``."""
    spacing = gap + (1.0 - (count + 1) * gap) * rng.dirichlet(np.ones(count + 1))
    return np.cumsum(spacing)[:-1]


class KnotWeightSearch:
    """The hybrid encoding: a particle is (inner knots u, inner knots v, log-weights).

    Control points are never in the particle: for given knots and weights they are
    the least-squares solution, which the fitness computes.
    """

    def __init__(self, layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                 uv: np.ndarray, n_folds: int, min_gap: float, weight_bounds: tuple[float, float],
                 rng: np.random.Generator):
        self.layout, self.solver = layout, solver
        self.points, self.uv = points, uv
        self.counts = layout.inner_counts
        self.gaps = tuple(min_gap / (c + 1) for c in self.counts)
        self.log_bounds = np.log(weight_bounds)
        self.n_folds = n_folds
        self.folds = rng.permutation(len(points)) % n_folds if n_folds > 1 else None

    @property
    def dimension(self) -> int:
        return self.counts[0] + self.counts[1] + self.layout.n_free

    def split(self, x: np.ndarray):
        cu, cv = self.counts
        return x[:cu], x[cu:cu + cv], np.exp(x[cu + cv:])

    def feasible(self) -> Polytope:
        cu, cv = self.counts
        parts = []
        for count, gap, offset in ((cu, self.gaps[0], 0), (cv, self.gaps[1], cu)):
            p = ordered_knots_polytope(count, gap)
            a = np.zeros((len(p.b), self.dimension))
            a[:, offset:offset + count] = p.A
            parts.append(Polytope(a, p.b))
        lo = np.concatenate([np.full(cu + cv, -np.inf), np.full(self.layout.n_free, self.log_bounds[0])])
        hi = np.concatenate([np.full(cu + cv, np.inf), np.full(self.layout.n_free, self.log_bounds[1])])
        box = Polytope.box(lo, hi)
        finite = np.isfinite(box.b)
        parts.append(Polytope(box.A[finite], box.b[finite]))
        return Polytope.stack(*parts)

    def classical(self) -> np.ndarray:
        """Uniform knots and unit weights: the classical least-squares fit."""
        cu, cv = self.counts
        return np.concatenate([np.arange(1, cu + 1) / (cu + 1), np.arange(1, cv + 1) / (cv + 1),
                               np.zeros(self.layout.n_free)])

    def initial_swarm(self, n_particles: int, rng: np.random.Generator) -> np.ndarray:
        """The classical fit, then particles spread from it towards random knots and weights."""
        start = self.classical()
        swarm = [start]
        cu, cv = self.counts
        for k in range(1, n_particles):
            mix = k / max(n_particles - 1, 1)  # from near the classical fit to anywhere
            target = np.concatenate([random_knots(cu, self.gaps[0], rng), random_knots(cv, self.gaps[1], rng),
                                     rng.uniform(*self.log_bounds, self.layout.n_free)])
            swarm.append(start + mix * rng.random() * (target - start))
        return np.array(swarm)

    def fitness(self, positions: np.ndarray) -> np.ndarray:
        return np.array([self.error(x) for x in positions])

    def error(self, x: np.ndarray) -> float:
        inner_u, inner_v, weights = self.split(x)
        rows = self.layout.rows(self.uv, weights, inner_u, inner_v)
        try:
            if self.folds is None:
                control = self.solver.solve(rows, self.points)
                return float(np.sqrt(np.mean(np.sum((rows @ control - self.points) ** 2, axis=1))))
            return self.solver.cross_validated_rmse(rows, self.points, self.folds, self.n_folds)
        except np.linalg.LinAlgError:
            return np.inf


def layout_for(config) -> NetLayout:
    if config.topology != "open":
        raise NotImplementedError(f"topology {config.topology!r} is not available yet")
    return NetLayout(tuple(config.net_size), tuple(config.degrees))


def parametrise(points: np.ndarray, topology: str) -> Parametrisation:
    return parametrise_open(points)


def polish(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
           weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray, iterations: int):
    """Alternate the least-squares solve with parameter correction while the error falls."""
    rmse, best = np.inf, None
    for it in range(iterations + 1):
        control = solver.solve(layout.rows(uv, weights, inner_u, inner_v), points)
        surface = layout.surface(control, weights, inner_u, inner_v)
        new_uv, dist = closest_parameters(surface, points, uv)
        new_rmse = float(np.sqrt(np.mean(dist ** 2)))
        if new_rmse >= rmse * (1.0 - 1e-4):
            break
        rmse, best, uv = new_rmse, surface, new_uv
    return best, uv, it


def choose_orientation(search_for: Callable[[Parametrisation], KnotWeightSearch],
                       par: Parametrisation, config) -> Parametrisation:
    """When the two directions differ (orders or net size), try both roles of (u, v)."""
    if config.orders[0] == config.orders[1] and config.net_size[0] == config.net_size[1]:
        return par
    candidates = [par, par.swapped()]
    errors = [(lambda s: s.error(s.classical()))(search_for(c)) for c in candidates]
    return candidates[int(np.argmin(errors))]


def fit_points(points: np.ndarray, config, on_iteration: Callable[[int, float, float], None] | None = None
               ) -> FitResult:
    """Fit one cloud (N, 3) in its own units; see the module docstring."""
    points = np.asarray(points, float)
    with threadpool_limits(limits=1):
        cloud = organise(points, tuple(config.orders), config.remove_outliers)
        diag = cloud.frame.diagonal
        layout = layout_for(config)
        rng = np.random.default_rng(config.swarm.seed)
        solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing)
        par = parametrise(cloud.points, config.topology)
        sample = subsample(len(cloud), config.swarm_points, rng)
        n_folds = int(round(1.0 / config.holdout)) if config.holdout > 0 else 1
        n_folds = min(n_folds, len(sample))

        def search_for(p: Parametrisation) -> KnotWeightSearch:
            return KnotWeightSearch(layout, solver, cloud.points[sample], p.uv[sample], n_folds,
                                    config.min_knot_gap, tuple(config.weight_bounds),
                                    np.random.default_rng(config.swarm.seed))

        par = choose_orientation(search_for, par, config)
        search = search_for(par)
        progress = None if on_iteration is None else (lambda i, b, m: on_iteration(i, b * diag, m * diag))
        swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                         config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                         rng, progress)
        inner_u, inner_v, weights = search.split(swarm.best_position)
        surface, _, polish_steps = polish(layout, solver, cloud.points, par.uv, weights, inner_u, inner_v,
                                          config.polish_iterations)
        world = NurbsSurface(surface.degree_u, surface.degree_v, surface.knots_u, surface.knots_v,
                             cloud.frame.to_world(surface.control_points), surface.weights,
                             surface.closed_u, surface.closed_v)
        _, dist = closest_parameters(surface, cloud.frame.to_local(points))
    dist = dist * diag
    input_diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    metrics = {
        "rmse": float(np.sqrt(np.mean(dist ** 2))),
        "max_error": float(dist.max()),
        "rmse_relative": float(np.sqrt(np.mean(dist ** 2)) / input_diag),
        "max_error_relative": float(dist.max() / input_diag),
        "bbox_diagonal": input_diag,
        "points": int(len(points)),
        "control_points": int(layout.n_free),
        "swarm_cv_rmse": float(swarm.best_value * diag),
        "classical_cv_rmse": float(search.error(search.classical()) * diag),
    }
    iterations = np.arange(1, len(swarm.best_history) + 1)
    curve = np.column_stack([iterations, swarm.best_history * diag, swarm.mean_history * diag])
    notes = []
    if len(cloud) < layout.n_free:
        notes.append(f"under-determined: {len(cloud)} points for {layout.n_free} control points, "
                     "the smoothness term decides between them")
    if cloud.duplicates:
        notes.append(f"{cloud.duplicates} duplicate points ignored")
    info = {
        "strategy": "hybrid",
        "parametrisation": par.info,
        "swarm": {"points": int(len(sample)), "folds": int(n_folds), "evaluations": int(swarm.evaluations)},
        "polish_iterations": int(polish_steps),
    }
    return FitResult(world, config.topology, metrics, curve, info, notes)
