"""The control net of a topology: its free control points and how they fill the full net.

The solver works with *free* control points only. A closed direction has ``n``
distinct rows and a full net of ``n + degree`` rows whose last ``degree`` rows repeat
the first (periodic B-splines); a sphere also collapses each pole row (the first and
the last along v) to one point. Both are an index map ``full -> free``, so the
continuity at a seam and the collapse at a pole hold by construction, whatever the
swarm or the solver does.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from .basis import design_matrix, inner_knot_count, make_knots, tensor_basis
from .nurbs import NurbsSurface
from .solve import Rows


@dataclass(frozen=True)
class NetLayout:
    size: tuple[int, int]  # distinct control points along u and v (the config's net_size)
    degrees: tuple[int, int]
    closed: tuple[bool, bool] = (False, False)
    poles: bool = False  # collapse the first and last row along v to single points

    @property
    def full_shape(self) -> tuple[int, int]:
        return tuple(n + p if c else n for n, p, c in zip(self.size, self.degrees, self.closed))

    @property
    def inner_counts(self) -> tuple[int, int]:
        return tuple(inner_knot_count(n, p, c) for n, p, c in zip(self.size, self.degrees, self.closed))

    def distinct_index(self) -> np.ndarray:
        """(full_u, full_v) array: index of each full-net point in the distinct grid."""
        fu, fv = self.full_shape
        nu, nv = self.size
        i, j = np.meshgrid(np.arange(fu) % nu, np.arange(fv) % nv, indexing="ij")
        return i * nv + j

    @cached_property
    def free_index(self) -> np.ndarray:
        """(full_u * full_v,) map from the full net (row-major) to free control points."""
        nu, nv = self.size
        distinct = np.arange(nu * nv).reshape(nu, nv)
        if self.poles:
            distinct[:, 0] = 0
            distinct[:, -1] = nu * nv - 1
        _, free = np.unique(distinct.ravel(), return_inverse=True)
        return free[self.distinct_index().ravel()]

    @cached_property
    def n_free(self) -> int:
        return int(self.free_index.max()) + 1

    def knots(self, inner_u: np.ndarray | None = None, inner_v: np.ndarray | None = None):
        return (make_knots(self.size[0], self.degrees[0], self.closed[0], inner_u),
                make_knots(self.size[1], self.degrees[1], self.closed[1], inner_v))

    def rows(self, uv: np.ndarray, free_weights: np.ndarray,
             inner_u: np.ndarray | None = None, inner_v: np.ndarray | None = None) -> Rows:
        """Rational basis rows at the parameters ``uv``, on the free control points."""
        ku, kv = self.knots(inner_u, inner_v)
        tensor = tensor_basis(design_matrix(uv[:, 0], ku, self.degrees[0]),
                              design_matrix(uv[:, 1], kv, self.degrees[1]))
        return Rows.from_csr(tensor, self.free_index).rational(free_weights)

    def smoothness_operator(self) -> sp.csr_array:
        """Discrete thin-plate energy of the distinct net, ``|L P|^2``, on free points.

        Second differences along u and v and the mixed difference (weight sqrt 2),
        periodic in a closed direction. A net that is affine in (i, j) costs nothing.
        At a sphere's poles the second difference also runs across the pole, from a
        meridian to the opposite one (``P[i, 1] - 2 pole + P[i + nu/2, 1]``): without it
        nothing keeps the ring around a pole flat and the surface ends in a cone.
        """
        nu, nv = self.size
        d2u, d2v = (difference(n, 2, c) for n, c in zip(self.size, self.closed))
        d1u, d1v = (difference(n, 1, c) for n, c in zip(self.size, self.closed))
        iu, iv = sp.identity(nu), sp.identity(nv)
        parts = [sp.kron(d2u, iv), sp.kron(iu, d2v), np.sqrt(2.0) * sp.kron(d1u, d1v)]
        if self.poles:
            parts.append(self._across_poles())
        op = sp.vstack(parts)
        distinct_to_free = self.free_index[self._first_full_of_distinct()]
        fold = sp.csr_array((np.ones(nu * nv), (np.arange(nu * nv), distinct_to_free)),
                            shape=(nu * nv, self.n_free))
        return sp.csr_array(op @ fold)

    def _across_poles(self) -> sp.csr_array:
        """Second differences through each pole between opposite meridians (distinct net)."""
        nu, nv = self.size
        i = np.arange(nu)
        opposite = (i + nu // 2) % nu
        rows, cols, vals = [], [], []
        for k, (pole, ring) in enumerate(((0, 1), (nv - 1, nv - 2))):
            for c, w in ((i * nv + ring, 1.0), (np.full(nu, pole), -2.0), (opposite * nv + ring, 1.0)):
                rows.append(k * nu + i), cols.append(c), vals.append(np.full(nu, w))
        rows, cols, vals = (np.concatenate(x) for x in (rows, cols, vals))
        return sp.csr_array((vals, (rows, cols)), shape=(2 * nu, nu * nv))

    def _first_full_of_distinct(self) -> np.ndarray:
        fu, fv = self.full_shape
        nu, nv = self.size
        i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
        return (i * fv + j).ravel()

    def surface(self, free_points: np.ndarray, free_weights: np.ndarray,
                inner_u: np.ndarray | None = None, inner_v: np.ndarray | None = None) -> NurbsSurface:
        """The full NURBS surface from free control points and weights."""
        idx = self.free_index
        fu, fv = self.full_shape
        ku, kv = self.knots(inner_u, inner_v)
        return NurbsSurface(self.degrees[0], self.degrees[1], ku, kv,
                            free_points[idx].reshape(fu, fv, 3), free_weights[idx].reshape(fu, fv),
                            self.closed[0], self.closed[1])


def difference(n: int, order: int, closed: bool) -> sp.csr_array:
    """Finite difference matrix of the given order; cyclic when ``closed``."""
    stencil = {1: [-1.0, 1.0], 2: [1.0, -2.0, 1.0]}[order]
    rows = n if closed else max(n - order, 0)
    r = np.repeat(np.arange(rows), len(stencil))
    c = (np.arange(rows)[:, None] + np.arange(len(stencil))[None, :]).ravel() % n
    return sp.csr_array((np.tile(stencil, rows), (r, c)), shape=(rows, n))
