"""The paper's own search space (Eq. 10): everything in the particle.

A particle holds the free control points, the log-weights, the inner knots of both
directions and the (u, v) of every point; the fitness is the RMSE of
``S(u_r, v_r) - x_r``. Nothing is solved by linear algebra, so this is slow to
converge and only sensible for small clouds; it is kept to reproduce the paper
(correct basis functions included) and as a yardstick for the hybrid strategy.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from psonurbs.geometry.basis import random_inner_knots
from psonurbs.geometry.net import NetLayout, NetShape

from .swarm import Polytope


class PaperParticle(NamedTuple):
    """What a particle of the paper's search space stands for."""

    control: np.ndarray  # (n_free, 3)
    shape: NetShape  # weights and inner knots
    uv: np.ndarray  # (N, 2) every point's parameters


class PaperSpace:
    def __init__(self, layout: NetLayout, points: np.ndarray, uv: np.ndarray,
                 min_gap: float, weight_bounds: tuple[float, float]):
        self.layout, self.points, self.uv0 = layout, points, uv
        self.n_free = layout.n_free
        self.counts = layout.inner_counts
        self.gaps = tuple(min_gap / (c + 1) for c in self.counts)
        self.log_bounds = np.log(weight_bounds)
        lo, hi = points.min(axis=0), points.max(axis=0)
        margin = 0.5 * (hi - lo).max()
        self.box = (lo - margin, hi + margin)

    @property
    def sizes(self) -> list[int]:
        return [3 * self.n_free, self.n_free, self.counts[0], self.counts[1], 2 * len(self.points)]

    @property
    def dimension(self) -> int:
        return sum(self.sizes)

    def split(self, x: np.ndarray) -> PaperParticle:
        parts = np.split(x, np.cumsum(self.sizes)[:-1])
        return PaperParticle(parts[0].reshape(-1, 3), NetShape(np.exp(parts[1]), parts[2], parts[3]),
                            parts[4].reshape(-1, 2))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Box bounds per coordinate (knots are bounded by their ordering instead)."""
        n, (cu, cv), m = self.n_free, self.counts, len(self.points)
        lower = np.concatenate([np.tile(self.box[0], n), np.full(n, self.log_bounds[0]),
                                np.full(cu + cv, -np.inf), np.zeros(2 * m)])
        upper = np.concatenate([np.tile(self.box[1], n), np.full(n, self.log_bounds[1]),
                                np.full(cu + cv, np.inf), np.ones(2 * m)])
        return lower, upper

    def feasible(self) -> Polytope:
        (cu, cv), offset = self.counts, 4 * self.n_free
        return Polytope.stack(Polytope.box(*self.bounds()),
                              Polytope.ordered(cu, self.gaps[0]).embed(self.dimension, offset),
                              Polytope.ordered(cv, self.gaps[1]).embed(self.dimension, offset + cu))

    def plane_net(self) -> np.ndarray:
        """The affine map (u, v) -> x fitted to the points, sampled at the net's nodes."""
        design = np.column_stack([np.ones(len(self.uv0)), self.uv0])
        coef, *_ = np.linalg.lstsq(design, self.points, rcond=None)
        nu, nv = self.layout.size
        s, t = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
        net = coef[0] + s.reshape(-1, 1) * coef[1] + t.reshape(-1, 1) * coef[2]
        free = np.zeros((self.n_free, 3))
        free[self.layout.free_index[self._distinct_positions()]] = net
        return free

    def _distinct_positions(self) -> np.ndarray:
        nu, nv = self.layout.size
        fv = self.layout.full_shape[1]
        i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
        return (i * fv + j).ravel()

    def initial_swarm(self, n_particles: int, rng: np.random.Generator) -> np.ndarray:
        """Particle 0: the plane through the cloud with uniform knots, unit weights and
        the projected parameters; the others scattered around it."""
        cu, cv = self.counts
        start = np.concatenate([self.plane_net().ravel(), np.zeros(self.n_free),
                                np.arange(1, cu + 1) / (cu + 1), np.arange(1, cv + 1) / (cv + 1),
                                self.uv0.ravel()])
        start = np.clip(start, *self.bounds())  # the plane may leave the box (a closed surface's cloud)
        scale = 0.1 * (self.box[1] - self.box[0]).max()
        swarm = [start]
        for _ in range(1, n_particles):
            target = np.concatenate([
                self.plane_net().ravel() + rng.normal(0.0, scale, 3 * self.n_free),
                rng.uniform(*self.log_bounds, self.n_free) * 0.25,
                random_inner_knots(cu, self.gaps[0], rng), random_inner_knots(cv, self.gaps[1], rng),
                np.clip(self.uv0 + rng.normal(0.0, 0.05, self.uv0.shape), 0.0, 1.0).ravel()])
            target = np.clip(target, *self.bounds())
            swarm.append(start + rng.random() * (target - start))
        return np.array(swarm)

    def surface(self, x: np.ndarray):
        control, shape, _ = self.split(x)
        return self.layout.surface(control, *shape)

    def fitness(self, positions: np.ndarray) -> np.ndarray:
        return np.array([self.error(x) for x in positions])

    def error(self, x: np.ndarray) -> float:
        control, shape, uv = self.split(x)
        rows = self.layout.rows(uv, *shape)
        return float(np.sqrt(np.mean(np.sum((rows @ control - self.points) ** 2, axis=1))))
