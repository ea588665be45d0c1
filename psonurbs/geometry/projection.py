"""Foot points: the closest point of a NURBS surface to each of many points.

The foot point of x on S minimises f(u, v) = |S(u, v) - x|^2 / 2 over the domain. From a
start (the nearest vertex of a dense tessellation, or the previous parameters) Newton
steps H d = -g are taken for all points at once, with

    g = [S_u.r, S_v.r],   H = [[S_u.S_u + r.S_uu, S_u.S_v + r.S_uv], [., S_v.S_v + r.S_vv]],

r = S - x (Gauss-Newton's H without the r terms where the full H is not positive
definite). A parameter on an open edge whose descent leads off the domain is held on
the edge and the step taken in the other one alone (an active set), and a step is
halved until it brings the point closer. Closed directions wrap.

Two implementations of the same search: :func:`newton_foot_points` (numpy, every point's
arrays at once: the reference) and its compiled twin in :mod:`.foot_kernel` (point by
point, no derivative arrays; the same numbers), used where :data:`COMPILED`.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.geometry import compiled, foot_kernel
from psonurbs.geometry.nurbs import NurbsSurface

from .compiled import chunks

LINE_SEARCH_HALVINGS = 8
PARAMETER_TOLERANCE = 1e-10  # of the unit domain: far below any distance a fit can resolve
FOOT_POINT_CHUNK = 1 << 15  # points searched together: some 30 MB of derivatives and trial arrays
THREAD_POINTS = 2048  # fewest points a thread of the compiled search takes (a thread's start costs ~50 us)
COMPILED = compiled.ENABLED  # the search's one switch: the compiled twin, or the numpy reference


def keep_in_domain(uv: np.ndarray, closed: tuple[bool, bool]) -> np.ndarray:
    out = uv.copy()
    for k in (0, 1):
        out[:, k] = np.mod(out[:, k], 1.0) if closed[k] else np.clip(out[:, k], 0.0, 1.0)
    return out


class GridStart:
    """Starts for a global search: the parameters of the nearest vertex of a resolution x
    resolution tessellation (a KD-tree over it, built once per surface and used for
    every chunk of points)."""

    def __init__(self, surface: NurbsSurface, resolution: int):
        self.us, self.vs = surface.parameter_grid(resolution, resolution)
        self.resolution = resolution
        self.tree = cKDTree(surface.evaluate_grid(self.us, self.vs).reshape(-1, 3))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        _, k = self.tree.query(points)
        return np.stack([self.us[k // self.resolution], self.vs[k % self.resolution]], axis=1)


def closest_parameters(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray | None = None,
                       iterations: int = 10, resolution: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Foot-point parameters (N, 2) and distances (N,) of ``points`` on ``surface``.

    With ``uv`` None the search starts from a tessellation (global); otherwise from ``uv``.
    The points are taken ``FOOT_POINT_CHUNK`` at a time (each point's search is its own).
    """
    closed = (surface.closed_u, surface.closed_v)
    start = None
    if uv is None:
        start = GridStart(surface, resolution or int(np.clip(32 * max(surface.shape), 128, 512)))
    search = compiled_foot_points if COMPILED else newton_foot_points
    out_uv, out_dist = np.empty((len(points), 2)), np.empty(len(points))
    for part in chunks(len(points), FOOT_POINT_CHUNK):
        first = start(points[part]) if start is not None else uv[part]
        out_uv[part], out_dist[part] = search(surface, points[part], first, closed, iterations)
    return out_uv, out_dist


def compiled_foot_points(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, closed: tuple[bool, bool],
                         iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`newton_foot_points` by the compiled kernel :func:`.foot_kernel.foot_points`."""
    out_uv, out_dist = np.empty((len(points), 2)), np.empty(len(points))
    weighted_net = (surface.control_points * surface.weights[..., None]).reshape(-1, 3)
    weights = np.ascontiguousarray(surface.weights.reshape(-1))
    points, uv = np.ascontiguousarray(points, float), np.ascontiguousarray(uv, float)
    inverse_u = foot_kernel.inverse_gaps(surface.knots_u, int(surface.degree_u))
    inverse_v = foot_kernel.inverse_gaps(surface.knots_v, int(surface.degree_v))

    def search(part: slice) -> None:
        foot_kernel.foot_points(surface.knots_u, surface.knots_v, inverse_u, inverse_v,
                                int(surface.degree_u), int(surface.degree_v),
                                int(surface.shape[1]), weighted_net, weights, bool(closed[0]), bool(closed[1]),
                                points[part], uv[part], int(iterations), LINE_SEARCH_HALVINGS, PARAMETER_TOLERANCE,
                                out_uv[part], out_dist[part])

    compiled.over_parts(len(points), search, THREAD_POINTS)
    return out_uv, out_dist


def newton_foot_points(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, closed: tuple[bool, bool],
                       iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounded Newton steps with halving from ``uv`` until every point stops moving."""
    uv = keep_in_domain(uv, closed)
    dist2 = np.sum((surface.evaluate(uv[:, 0], uv[:, 1]) - points) ** 2, axis=1)
    active = np.arange(len(points))
    for _ in range(iterations):
        step = foot_point_step(surface, points[active], uv[active], closed)
        moved = np.zeros(len(active), bool)
        for halving in range(LINE_SEARCH_HALVINGS):
            todo = np.flatnonzero(~moved)
            trial = keep_in_domain(uv[active[todo]] + 0.5 ** halving * step[todo], closed)
            trial_d2 = np.sum((surface.evaluate(trial[:, 0], trial[:, 1]) - points[active[todo]]) ** 2, axis=1)
            better = trial_d2 < dist2[active[todo]]
            uv[active[todo[better]]], dist2[active[todo[better]]] = trial[better], trial_d2[better]
            moved[todo[better]] = True
            if moved.all():
                break
        # a point is done once it stops moving or its step falls below PARAMETER_TOLERANCE
        active = active[moved & (np.abs(step).max(axis=1) > PARAMETER_TOLERANCE)]
        if len(active) == 0:
            break
    return uv, np.sqrt(dist2)


def foot_point_step(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray,
                    closed: tuple[bool, bool]) -> np.ndarray:
    """One bounded Newton step (du, dv) per point towards its foot point."""
    s, su, sv, suu, suv, svv = surface.derivatives(uv[:, 0], uv[:, 1], second=True)
    r = s - points
    g = np.stack([np.sum(su * r, 1), np.sum(sv * r, 1)], axis=1)
    gauss = np.stack([np.sum(su * su, 1), np.sum(su * sv, 1), np.sum(sv * sv, 1)], axis=1)
    newton = gauss + np.stack([np.sum(r * suu, 1), np.sum(r * suv, 1), np.sum(r * svv, 1)], axis=1)
    convex = (newton[:, 0] > 0) & (newton[:, 0] * newton[:, 2] - newton[:, 1] ** 2 > 0)
    h = np.where(convex[:, None], newton, gauss)
    h[:, [0, 2]] += 1e-12 * (h[:, [0]] + h[:, [2]]) + 1e-300
    # an open edge holds a parameter whose descent -g leaves the domain
    held = np.zeros_like(g, bool)
    for k in (0, 1):
        if not closed[k]:
            held[:, k] = ((uv[:, k] <= 0.0) & (g[:, k] > 0)) | ((uv[:, k] >= 1.0) & (g[:, k] < 0))
    step = np.zeros_like(g)
    both = ~held[:, 0] & ~held[:, 1]
    det = h[both, 0] * h[both, 2] - h[both, 1] ** 2
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    step[both, 0] = -(h[both, 2] * g[both, 0] - h[both, 1] * g[both, 1]) / det
    step[both, 1] = -(h[both, 0] * g[both, 1] - h[both, 1] * g[both, 0]) / det
    only_u, only_v = ~held[:, 0] & held[:, 1], held[:, 0] & ~held[:, 1]
    step[only_u, 0] = -g[only_u, 0] / h[only_u, 0]
    step[only_v, 1] = -g[only_v, 1] / h[only_v, 2]
    return step
