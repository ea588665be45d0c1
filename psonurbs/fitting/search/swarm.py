"""Particle swarm optimisation over a convex feasible set (the paper's Eq. 1-2).

Each particle has a position x and a velocity v. One iteration is

    v <- w v + c1 R1 (g - x) + c2 R2 (p - x)        (Eq. 1)
    x <- x + s v                                    (Eq. 2)

with inertia w, the swarm's best position g, the particle's own best p, R1 and R2
uniform on [0, 1] per coordinate, and s in [0, 1] the largest step that keeps x
feasible (the paper's Algorithm 1 scales an infeasible move back). The feasible set
is a convex polytope ``A x <= b``: box bounds and ordered knots with a minimum gap are
both of this form, so the largest feasible step has a closed form.

The fitness takes the whole swarm at once, ``(P, D) -> (P,)``, so it can batch the work.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class Polytope:
    """The feasible set ``{x : A x <= b}``."""

    A: np.ndarray  # (m, D)
    b: np.ndarray  # (m,)

    @classmethod
    def box(cls, lower: np.ndarray, upper: np.ndarray) -> "Polytope":
        """``lower <= x <= upper``; infinite bounds are left out."""
        eye = np.eye(len(lower))
        a = np.vstack([eye, -eye])
        b = np.concatenate([upper, -np.asarray(lower)])
        keep = np.isfinite(b)
        return cls(a[keep], b[keep])

    @classmethod
    def ordered(cls, count: int, gap: float) -> "Polytope":
        """Increasing values in (0, 1) with gaps of at least ``gap`` (inner knots)::

            gap <= t_1,   t_k + gap <= t_{k+1},   t_c <= 1 - gap
        """
        a = np.zeros((count + 1, count))
        b = np.full(count + 1, -gap)
        for k in range(count + 1):
            if k > 0:
                a[k, k - 1] = 1.0
            if k < count:
                a[k, k] = -1.0
        b[count] = 1.0 - gap
        return cls(a, b)

    def embed(self, dimension: int, offset: int) -> "Polytope":
        """The same constraints on coordinates offset.. of a larger vector."""
        a = np.zeros((len(self.b), dimension))
        a[:, offset:offset + self.A.shape[1]] = self.A
        return Polytope(a, self.b)

    @classmethod
    def stack(cls, *parts: "Polytope") -> "Polytope":
        return cls(np.vstack([p.A for p in parts]), np.concatenate([p.b for p in parts]))

    def contains(self, x: np.ndarray, tol: float = 1e-12) -> np.ndarray:
        return np.all(np.atleast_2d(x) @ self.A.T <= self.b + tol, axis=1)

    def max_step(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Largest s in [0, 1] with x + s v feasible, per row of x (x feasible)."""
        slack = np.maximum(self.b - x @ self.A.T, 0.0)  # (P, m)
        rate = v @ self.A.T
        with np.errstate(divide="ignore", invalid="ignore"):
            limit = np.where(rate > 0, slack / rate, np.inf)
        return np.clip(limit.min(axis=1, initial=np.inf), 0.0, 1.0)


@dataclass
class SwarmResult:
    best_position: np.ndarray
    best_value: float
    best_history: np.ndarray  # (iterations,) swarm best after each iteration
    mean_history: np.ndarray  # (iterations,) mean fitness of the swarm at each iteration
    evaluations: int


def minimise(fitness: Callable[[np.ndarray], np.ndarray], initial: np.ndarray, feasible: Polytope,
             iterations: int, inertia: float, c1: float, c2: float, rng: np.random.Generator,
             on_iteration: Callable[[int, float, float], None] | None = None) -> SwarmResult:
    """Minimise ``fitness`` with a particle swarm started at the rows of ``initial``.

    The swarm is evaluated once per iteration (the first on the initial positions);
    non-finite fitness values count as infinitely bad.
    """
    x = np.array(initial, float)
    if not np.all(feasible.contains(x, tol=1e-9)):
        raise ValueError("initial particles must be feasible")
    n = len(x)
    v = 0.1 * (x[rng.permutation(n)] - x)  # small random initial velocities, feasible directions
    own_best, own_value = x.copy(), np.full(n, np.inf)
    best, best_value = x[0].copy(), np.inf
    best_hist, mean_hist = np.empty(iterations), np.empty(iterations)
    for it in range(iterations):
        if it > 0:
            r1, r2 = rng.random(x.shape), rng.random(x.shape)
            v = inertia * v + c1 * r1 * (best - x) + c2 * r2 * (own_best - x)
            v *= feasible.max_step(x, v)[:, None]
            x = x + v
        f = np.asarray(fitness(x), float)
        f = np.where(np.isfinite(f), f, np.inf)
        improved = f < own_value
        own_best[improved], own_value[improved] = x[improved], f[improved]
        k = int(np.argmin(own_value))
        if own_value[k] < best_value:
            best, best_value = own_best[k].copy(), float(own_value[k])
        finite = f[np.isfinite(f)]
        best_hist[it] = best_value
        mean_hist[it] = finite.mean() if len(finite) else np.inf
        if on_iteration is not None:
            on_iteration(it + 1, best_value, mean_hist[it])
    return SwarmResult(best, best_value, best_hist, mean_hist, n * iterations)
