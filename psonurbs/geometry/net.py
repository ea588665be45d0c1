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
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from psonurbs.geometry.basis import design_matrix, inner_knot_count, make_knots, tensor_basis
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.rows import Rows


class NetShape(NamedTuple):
    """The non-linear part of a net's basis, which travels with it through every solve,
    polish and refinement: the free control points' weights (n_free,) and the inner knots
    along u and v (None: uniform). ``layout.rows(uv, *shape)``, ``layout.surface(control, *shape)``."""

    weights: np.ndarray
    inner_u: np.ndarray | None = None
    inner_v: np.ndarray | None = None


@dataclass(frozen=True)
class NetLayout:
    size: tuple[int, int]  # distinct control points along u and v (the config's net_size)
    degrees: tuple[int, int]
    closed: tuple[bool, bool] = (False, False)
    poles: bool = False  # collapse the first and last row along v to single points
    free_edges: bool = False  # the edges are not held to the data's: other faces will cut the surface

    @property
    def bounded(self) -> tuple[bool, bool]:
        """Directions whose two ends are edges of the surface that end where the data do:
        open and not collapsed to poles, unless the edges are free (an object's face,
        which its neighbours cut)."""
        if self.free_edges:
            return (False, False)
        return (not self.closed[0], not (self.closed[1] or self.poles))

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
        """
        nu, nv = self.size
        d2u, d2v = (difference(n, 2, c) for n, c in zip(self.size, self.closed))
        d1u, d1v = (difference(n, 1, c) for n, c in zip(self.size, self.closed))
        iu, iv = sp.identity(nu), sp.identity(nv)
        parts = [sp.kron(d2u, iv), sp.kron(iu, d2v), np.sqrt(2.0) * sp.kron(d1u, d1v)]
        return sp.csr_array(sp.vstack(parts) @ self._distinct_to_free())

    def constraint_operator(self) -> sp.csr_array | None:
        """Linear conditions ``C P = 0`` on the free points, or None: at a sphere's poles,
        a tangent plane (:meth:`pole_tangent_planes`)."""
        if not self.poles:
            return None
        return sp.csr_array(self.pole_tangent_planes() @ self._distinct_to_free())

    def _distinct_to_free(self) -> sp.csr_array:
        """0/1 matrix taking the free points to the distinct net (nu * nv rows)."""
        nu, nv = self.size
        distinct_to_free = self.free_index[self._first_full_of_distinct()]
        return sp.csr_array((np.ones(nu * nv), (np.arange(nu * nv), distinct_to_free)), shape=(nu * nv, self.n_free))

    def pole_tangent_planes(self) -> sp.csr_array:
        """Rows on the distinct net that vanish exactly when each pole's first ring is the
        pole plus an affine image of a circle, ``P[i, 1] = pole + a cos(2 pi i / nu) + b sin(2 pi i / nu)``.

        Then every direction leaving the pole lies in the plane of a and b: the surface
        has a tangent plane at the pole (G1) instead of a cone or a nipple. The rows are
        ``Q (P[:, 1] - pole)`` with Q the projector off span(cos, sin) (Q 1 = 1).
        """
        nu, nv = self.size
        angle = 2.0 * np.pi * np.arange(nu) / nu
        circle = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        q = np.eye(nu) - circle @ np.linalg.pinv(circle)
        blocks = []
        for pole, ring in ((0, 1), (nv - 1, nv - 2)):
            block = np.zeros((nu, nu * nv))
            block[:, np.arange(nu) * nv + ring] = q
            block[:, pole] -= q.sum(axis=1)
            blocks.append(block)
        return sp.csr_array(np.vstack(blocks))

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
