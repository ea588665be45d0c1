"""The swarm's search space (``strategy: hybrid``): knots, weights and smoothing in the
particle, control points solved.

A particle is (inner knots along u, inner knots along v, log-weights of the free
control points, log10 of the smoothing). For given knots and weights the surface is linear in its control
points, so they are never searched: the fitness solves for them by regularised least
squares and returns the leave-one-out RMSE (or the plain RMSE), weighted by the robust
loss's point weights when there are any (:mod:`psonurbs.fitting.prepare.robust_weights`).

The swarm's fitness evaluates all particles of an iteration together
(:mod:`psonurbs.fitting.leastsq.stacked`: by numpy, or its compiled twin with numba);
:meth:`KnotWeightSpace.error` is the same number for one particle through the single solver (scipy design matrices, dense
Cholesky), used by the topology choice and the validation.
"""
from __future__ import annotations

from functools import cached_property
from typing import NamedTuple

import numpy as np

from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares, weighted_rms
from psonurbs.fitting.leastsq.stacked import StackedLeastSquares
from psonurbs.geometry import compiled
from psonurbs.geometry.basis import random_inner_knots, uniform_inner_knots
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.stacked_rows import CellLayout, StackedRows, stacked_rows

from .swarm import Polytope

SMOOTHING_RANGE = (-10.0, -1.0)  # log10 of the relative smoothing weight the swarm may choose
GROUP_BYTES = 2 ** 21  # particles are evaluated in groups whose rows take about this much (cache)


class Decoded(NamedTuple):
    """What a particle stands for: the net's shape (weights, inner knots) and the smoothing."""

    shape: NetShape
    smoothing: float


class KnotWeightSpace:
    """The knot and weight search space: a particle is (inner knots u, inner knots v,
    log-weights, log10 smoothing).

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
        self.point_weights = point_weights  # (N,) the robust loss's, or None
        self.counts = layout.inner_counts
        self.gaps = tuple(min_gap / (c + 1) for c in self.counts)
        self.log_bounds = np.log(weight_bounds)
        self.cross_validation = cross_validation

    @property
    def dimension(self) -> int:
        return self.counts[0] + self.counts[1] + self.layout.n_free + 1

    def split(self, x: np.ndarray) -> Decoded:
        """The net's shape (weights, inner knots u and v) and the smoothing of a particle (D,)."""
        cu, cv = self.counts
        return Decoded(NetShape(np.exp(x[cu + cv:-1]), x[:cu], x[cu:cu + cv]), 10.0 ** x[-1])

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
        return np.concatenate([uniform_inner_knots(cu), uniform_inner_knots(cv), np.zeros(self.layout.n_free),
                               [smoothing]])

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

    @cached_property
    def stacked(self) -> StackedLeastSquares:
        return StackedLeastSquares(self.solver, CellLayout(self.layout))

    @property
    def group_size(self) -> int:
        """Particles evaluated together: their rows take about ``GROUP_BYTES``."""
        return max(1, GROUP_BYTES // (8 * len(self.points) * int(np.prod(np.add(self.layout.degrees, 1)))))

    def stacked_shapes(self, positions: np.ndarray) -> NetShape:
        """The shapes of the particles (P, D) stacked: weights (P, n_free), inner knots
        (P, inner u), (P, inner v)."""
        cu, cv = self.counts
        return NetShape(np.exp(positions[:, cu + cv:-1]), positions[:, :cu], positions[:, cu:cu + cv])

    def rows(self, positions: np.ndarray) -> StackedRows:
        """The rows of the particles (P, D) at the search's points, all together."""
        return stacked_rows(self.stacked.cells, self.uv, *self.stacked_shapes(positions))

    def fitness(self, positions: np.ndarray) -> np.ndarray:
        """The error of every particle (P,), all evaluated together; inf for a particle
        whose normal matrix is not numerically positive definite. Compiled where numba is
        there (:mod:`psonurbs.geometry.compiled`), else numpy: the same numbers."""
        return self.compiled_fitness(positions) if compiled.ENABLED else self.numpy_fitness(positions)

    def compiled_fitness(self, positions: np.ndarray) -> np.ndarray:
        """:meth:`fitness` by the compiled kernel, particle by particle."""
        positions = np.atleast_2d(positions)
        return self.stacked.compiled_errors(self.uv, *self.stacked_shapes(positions), self.points,
                                            10.0 ** positions[:, -1], self.cross_validation, self.point_weights)

    def numpy_fitness(self, positions: np.ndarray) -> np.ndarray:
        """:meth:`fitness` by numpy (the reference), the particles in groups of stacked rows."""
        positions = np.atleast_2d(positions)
        group = self.group_size
        if len(positions) > group:
            return np.concatenate([self.numpy_fitness(positions[k:k + group])
                                   for k in range(0, len(positions), group)])
        try:
            return self.stacked.errors(self.rows(positions), self.points, 10.0 ** positions[:, -1],
                                       self.cross_validation, self.point_weights)
        except np.linalg.LinAlgError:
            if len(positions) == 1:
                return np.array([np.inf])
            return np.concatenate([self.numpy_fitness(x) for x in positions])

    def error(self, x: np.ndarray) -> float:
        shape, smoothing = self.split(x)
        rows = self.layout.rows(self.uv, *shape)
        solver = self.solver.with_smoothing(smoothing)
        try:
            if self.cross_validation:
                return solver.leave_one_out_rmse(rows, self.points, self.point_weights)
            control = solver.solve(rows, self.points, self.point_weights)
            return weighted_rms(np.sum((rows @ control - self.points) ** 2, axis=1), self.point_weights)
        except np.linalg.LinAlgError:
            return np.inf
