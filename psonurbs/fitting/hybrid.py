"""The hybrid encoding of the swarm: knots and weights in the particle, control points solved.

A particle is (inner knots along u, inner knots along v, log-weights of the free
control points). For given knots and weights the surface is linear in its control
points, so they are never searched: the fitness solves for them by regularised least
squares and returns the leave-one-out RMSE (or the plain RMSE), weighted by the robust
loss's point weights when there are any (:mod:`psonurbs.fitting.robust`).
"""
from __future__ import annotations

import numpy as np

from psonurbs.geometry.basis import random_inner_knots
from psonurbs.geometry.net import NetLayout

from .pso import Polytope
from .solve import RegularisedLeastSquares, weighted_rms

SMOOTHING_RANGE = (-10.0, -1.0)  # log10 of the relative smoothing weight the swarm may choose


class KnotWeightSearch:
    """The hybrid encoding: a particle is (inner knots u, inner knots v, log-weights,
    log10 smoothing).

    Control points are never in the particle: for given knots, weights and smoothing
    they are the least-squares solution, which the fitness computes. Judged by the
    leave-one-out error, the smoothing weight is chosen by cross-validation: large
    where data are noisy or thin, vanishing where the net can represent the shape.
    """

    def __init__(self, layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                 uv: np.ndarray, cross_validation: bool, min_gap: float, weight_bounds: tuple[float, float],
                 point_weights: np.ndarray | None = None):
        self.layout, self.solver = layout, solver
        self.points, self.uv = points, uv
        self.point_weights = point_weights  # (N,) the robust loss's, shared by all particles
        self.counts = layout.inner_counts
        self.gaps = tuple(min_gap / (c + 1) for c in self.counts)
        self.log_bounds = np.log(weight_bounds)
        self.cross_validation = cross_validation

    @property
    def dimension(self) -> int:
        return self.counts[0] + self.counts[1] + self.layout.n_free + 1

    def split(self, x: np.ndarray):
        """(inner knots u, inner knots v, weights, smoothing) of a particle."""
        cu, cv = self.counts
        return x[:cu], x[cu:cu + cv], np.exp(x[cu + cv:-1]), 10.0 ** x[-1]

    def feasible(self) -> Polytope:
        cu, cv = self.counts
        n = self.layout.n_free
        lo = np.concatenate([np.full(cu + cv, -np.inf), np.full(n, self.log_bounds[0]), [SMOOTHING_RANGE[0]]])
        hi = np.concatenate([np.full(cu + cv, np.inf), np.full(n, self.log_bounds[1]), [SMOOTHING_RANGE[1]]])
        return Polytope.stack(Polytope.ordered(cu, self.gaps[0]).embed(self.dimension, 0),
                              Polytope.ordered(cv, self.gaps[1]).embed(self.dimension, cu),
                              Polytope.box(lo, hi))

    def classical(self) -> np.ndarray:
        """Uniform knots, unit weights and the configured smoothing: the classical fit."""
        cu, cv = self.counts
        smoothing = np.clip(np.log10(max(self.solver.smoothing, 1e-300)), *SMOOTHING_RANGE)
        return np.concatenate([np.arange(1, cu + 1) / (cu + 1), np.arange(1, cv + 1) / (cv + 1),
                               np.zeros(self.layout.n_free), [smoothing]])

    def initial_swarm(self, n_particles: int, rng: np.random.Generator) -> np.ndarray:
        """The classical fit, then particles spread from it towards random positions."""
        start = self.classical()
        swarm = [start]
        cu, cv = self.counts
        for k in range(1, n_particles):
            mix = k / max(n_particles - 1, 1)  # from near the classical fit to anywhere
            target = np.concatenate([random_inner_knots(cu, self.gaps[0], rng),
                                     random_inner_knots(cv, self.gaps[1], rng),
                                     rng.uniform(*self.log_bounds, self.layout.n_free),
                                     [rng.uniform(*SMOOTHING_RANGE)]])
            swarm.append(start + mix * rng.random() * (target - start))
        return np.array(swarm)

    def fitness(self, positions: np.ndarray) -> np.ndarray:
        return np.array([self.error(x) for x in positions])

    def error(self, x: np.ndarray) -> float:
        inner_u, inner_v, weights, smoothing = self.split(x)
        rows = self.layout.rows(self.uv, weights, inner_u, inner_v)
        solver = self.solver.with_smoothing(smoothing)
        try:
            if self.cross_validation:
                return solver.leave_one_out_rmse(rows, self.points, self.point_weights)
            control = solver.solve(rows, self.points, self.point_weights)
            return weighted_rms(np.sum((rows @ control - self.points) ** 2, axis=1), self.point_weights)
        except np.linalg.LinAlgError:
            return np.inf
