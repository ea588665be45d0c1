"""The fitter: organise -> parametrise -> swarm -> polish, for one cloud.

``strategy: hybrid`` (default): the swarm searches what is non-linear (the inner knots
of both directions and the weights); inside its fitness the control points come from
the regularised least-squares solve, and a particle is judged by its leave-one-out
RMSE (each point against the solve that did not see it), so the swarm cannot win by
tuning knots to noise. ``strategy: full`` is the paper's own search space (Eq. 10,
:mod:`psonurbs.paper`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from .basis import random_inner_knots
from .net import NetLayout
from .nurbs import NurbsSurface
from .organise import Cloud, organise, subsample
from .parametrise import Parametrisation, parametrise_open
from .polish import closest_parameters
from .paper import FullSearch
from .pso import Polytope, SwarmResult, minimise
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


class KnotWeightSearch:
    """The hybrid encoding: a particle is (inner knots u, inner knots v, log-weights).

    Control points are never in the particle: for given knots and weights they are
    the least-squares solution, which the fitness computes.
    """

    def __init__(self, layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                 uv: np.ndarray, cross_validation: bool, min_gap: float, weight_bounds: tuple[float, float]):
        self.layout, self.solver = layout, solver
        self.points, self.uv = points, uv
        self.counts = layout.inner_counts
        self.gaps = tuple(min_gap / (c + 1) for c in self.counts)
        self.log_bounds = np.log(weight_bounds)
        self.cross_validation = cross_validation

    @property
    def dimension(self) -> int:
        return self.counts[0] + self.counts[1] + self.layout.n_free

    def split(self, x: np.ndarray):
        cu, cv = self.counts
        return x[:cu], x[cu:cu + cv], np.exp(x[cu + cv:])

    def feasible(self) -> Polytope:
        cu, cv = self.counts
        lo = np.concatenate([np.full(cu + cv, -np.inf), np.full(self.layout.n_free, self.log_bounds[0])])
        hi = np.concatenate([np.full(cu + cv, np.inf), np.full(self.layout.n_free, self.log_bounds[1])])
        return Polytope.stack(Polytope.ordered(cu, self.gaps[0]).embed(self.dimension, 0),
                              Polytope.ordered(cv, self.gaps[1]).embed(self.dimension, cu),
                              Polytope.box(lo, hi))

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
            target = np.concatenate([random_inner_knots(cu, self.gaps[0], rng), random_inner_knots(cv, self.gaps[1], rng),
                                     rng.uniform(*self.log_bounds, self.layout.n_free)])
            swarm.append(start + mix * rng.random() * (target - start))
        return np.array(swarm)

    def fitness(self, positions: np.ndarray) -> np.ndarray:
        return np.array([self.error(x) for x in positions])

    def error(self, x: np.ndarray) -> float:
        inner_u, inner_v, weights = self.split(x)
        rows = self.layout.rows(self.uv, weights, inner_u, inner_v)
        try:
            if self.cross_validation:
                return self.solver.leave_one_out_rmse(rows, self.points)
            control = self.solver.solve(rows, self.points)
            return float(np.sqrt(np.mean(np.sum((rows @ control - self.points) ** 2, axis=1))))
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


def run_hybrid(cloud: Cloud, layout: NetLayout, par: Parametrisation, config, rng: np.random.Generator,
               progress) -> tuple[NurbsSurface, SwarmResult, dict]:
    """Swarm over knots and weights (least-squares control points), then the polish."""
    solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing)
    sample = subsample(len(cloud), config.swarm_points, rng)

    def search_for(p: Parametrisation) -> KnotWeightSearch:
        return KnotWeightSearch(layout, solver, cloud.points[sample], p.uv[sample], config.cross_validation,
                                config.min_knot_gap, tuple(config.weight_bounds))

    par = choose_orientation(search_for, par, config)
    search = search_for(par)
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    inner_u, inner_v, weights = search.split(swarm.best_position)
    surface, _, steps = polish(layout, solver, cloud.points, par.uv, weights, inner_u, inner_v,
                               config.polish_iterations)
    info = {"strategy": "hybrid", "parametrisation": par.info,
            "swarm": {"points": int(len(sample)), "cross_validation": bool(config.cross_validation), "evaluations": int(swarm.evaluations),
                      "classical_error": float(search.error(search.classical()))},
            "polish_iterations": int(steps)}
    return surface, swarm, info


def run_full(cloud: Cloud, layout: NetLayout, par: Parametrisation, config, rng: np.random.Generator,
             progress) -> tuple[NurbsSurface, SwarmResult, dict]:
    """The paper's search space: the swarm's best surface is the result, unpolished."""
    search = FullSearch(layout, cloud.points, par.uv, config.min_knot_gap, tuple(config.weight_bounds))
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    info = {"strategy": "full", "parametrisation": par.info,
            "swarm": {"points": len(cloud), "dimension": int(search.dimension),
                      "evaluations": int(swarm.evaluations)}}
    return search.surface(swarm.best_position), swarm, info


def fit_points(points: np.ndarray, config, on_iteration: Callable[[int, float, float], None] | None = None
               ) -> FitResult:
    """Fit one cloud (N, 3) given in its own units; see the module docstring.

    ``on_iteration(i, best, mean)`` is called after each swarm iteration (cloud units).
    """
    points = np.asarray(points, float)
    with threadpool_limits(limits=1):
        cloud = organise(points, tuple(config.orders), config.remove_outliers)
        diag = cloud.frame.diagonal
        layout = layout_for(config)
        rng = np.random.default_rng(config.swarm.seed)
        par = parametrise(cloud.points, config.topology)
        progress = None if on_iteration is None else (lambda i, b, m: on_iteration(i, b * diag, m * diag))
        run = run_full if config.strategy == "full" else run_hybrid
        surface, swarm, info = run(cloud, layout, par, config, rng, progress)
        _, dist = closest_parameters(surface, cloud.frame.to_local(points))
    world = NurbsSurface(surface.degree_u, surface.degree_v, surface.knots_u, surface.knots_v,
                         cloud.frame.to_world(surface.control_points), surface.weights,
                         surface.closed_u, surface.closed_v)
    dist = dist * diag
    input_diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    rmse = float(np.sqrt(np.mean(dist ** 2)))
    metrics = {
        "rmse": rmse,
        "max_error": float(dist.max()),
        "rmse_relative": rmse / input_diag,
        "max_error_relative": float(dist.max()) / input_diag,
        "bbox_diagonal": input_diag,
        "points": int(len(points)),
        "control_points": int(layout.n_free),
        "swarm_best_error": float(swarm.best_value * diag),
    }
    if "classical_error" in info["swarm"]:
        info["swarm"]["classical_error"] *= diag
    iterations = np.arange(1, len(swarm.best_history) + 1)
    curve = np.column_stack([iterations, swarm.best_history * diag, swarm.mean_history * diag])
    notes = []
    if len(cloud) < layout.n_free:
        notes.append(f"under-determined: {len(cloud)} points for {layout.n_free} control points, "
                     "the smoothness term decides between them")
    if cloud.duplicates:
        notes.append(f"{cloud.duplicates} duplicate points ignored")
    return FitResult(world, config.topology, metrics, curve, info, notes)
