"""Parameter correction: move each point's (u, v) to its closest point on the surface.

The foot point of x on S minimises |S(u, v) - x|^2. From a start (the nearest vertex
of a dense tessellation, or the previous parameters) Gauss-Newton steps

    [S_u S_v]^T [S_u S_v] d = -[S_u S_v]^T (S - x)

are taken for all points at once; a step is kept only where it brings the point closer,
and parameters are clamped to [0, 1] (open) or wrapped (closed).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .nurbs import NurbsSurface


def keep_in_domain(uv: np.ndarray, closed: tuple[bool, bool]) -> np.ndarray:
    out = uv.copy()
    for k in (0, 1):
        out[:, k] = np.mod(out[:, k], 1.0) if closed[k] else np.clip(out[:, k], 0.0, 1.0)
    return out


def nearest_on_grid(surface: NurbsSurface, points: np.ndarray, resolution: int) -> np.ndarray:
    """Parameters of the nearest vertex of a resolution x resolution tessellation."""
    us, vs = surface.parameter_grid(resolution, resolution)
    grid = surface.evaluate_grid(us, vs).reshape(-1, 3)
    _, k = cKDTree(grid).query(points)
    return np.stack([us[k // resolution], vs[k % resolution]], axis=1)


def closest_parameters(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray | None = None,
                       iterations: int = 10, resolution: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Foot-point parameters and distances of ``points`` on ``surface``.

    With ``uv`` None the search starts from a tessellation (global); otherwise from ``uv``.
    """
    closed = (surface.closed_u, surface.closed_v)
    if uv is None:
        res = resolution or int(np.clip(8 * max(surface.shape), 64, 256))
        uv = nearest_on_grid(surface, points, res)
    uv = keep_in_domain(uv, closed)
    s = surface.evaluate(uv[:, 0], uv[:, 1])
    dist2 = np.sum((s - points) ** 2, axis=1)
    for _ in range(iterations):
        s, su, sv = surface.derivatives(uv[:, 0], uv[:, 1])
        r = s - points
        a, b, c = np.sum(su * su, 1), np.sum(su * sv, 1), np.sum(sv * sv, 1)
        gu, gv = np.sum(su * r, 1), np.sum(sv * r, 1)
        damp = 1e-12 * (a + c) + 1e-300
        det = (a + damp) * (c + damp) - b * b
        det = np.where(np.abs(det) > 1e-300, det, 1e-300)
        du = -((c + damp) * gu - b * gv) / det
        dv = -((a + damp) * gv - b * gu) / det
        step = np.stack([du, dv], axis=1)
        moved = np.zeros(len(points), bool)
        for scale in (1.0, 0.5, 0.25):  # a step that overshoots is retried shorter
            todo = np.flatnonzero(~moved)
            trial = keep_in_domain(uv[todo] + scale * step[todo], closed)
            trial_d2 = np.sum((surface.evaluate(trial[:, 0], trial[:, 1]) - points[todo]) ** 2, axis=1)
            better = trial_d2 < dist2[todo]
            uv[todo[better]], dist2[todo[better]] = trial[better], trial_d2[better]
            moved[todo[better]] = True
            if moved.all():
                break
        if not moved.any():
            break
    return uv, np.sqrt(dist2)


def edge_line(along: np.ndarray, across: np.ndarray, upper: bool, bins: int = 8) -> np.ndarray:
    """A straight line ``across = a + b * along`` through the data's edge, evaluated at
    every point: the least-squares line through the lowest (or highest) ``across``
    value in each of ``bins`` slices of ``along``."""
    slices = np.minimum((along * bins).astype(int), bins - 1)
    order = np.lexsort((-across if upper else across, slices))
    first = order[np.r_[True, slices[order][1:] != slices[order][:-1]]]
    if len(first) < 2:
        return np.full(len(along), across[first].mean())
    b, a = np.polyfit(along[first], across[first], 1)
    return a + b * along


def align_to_domain(uv: np.ndarray, closed: tuple[bool, bool]) -> np.ndarray:
    """Map the data's extent in each open direction back onto [0, 1].

    Parameter correction lets the data drift off the domain's edges, and a projection
    on a slightly tilted plane shears them; the surface then extrapolates past the
    data and overshoots the true boundary. For an open direction, each parameter is
    rescaled between two straight lines fitted to the data's lower and upper edges
    (as functions of the other parameter), so the data span the domain again.
    """
    out = uv.copy()
    for k in (0, 1):
        if closed[k]:
            continue
        across, along = out[:, k], out[:, 1 - k]
        if closed[1 - k]:
            lo, hi = np.full(len(across), across.min()), np.full(len(across), across.max())
        else:
            lo, hi = edge_line(along, across, False), edge_line(along, across, True)
        width = hi - lo
        ok = width > 1e-9
        out[:, k] = np.clip(np.where(ok, (across - lo) / np.where(ok, width, 1.0), across), 0.0, 1.0)
    return out


def polish(layout, solver, points: np.ndarray, uv: np.ndarray,
           weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray, iterations: int, realign: bool = False):
    """Alternate the least-squares solve with parameter correction while the error falls.

    Returns the best control points (free), their surface, its foot-point parameters
    and the rounds taken.
    """
    rmse, best, best_uv, best_control = np.inf, None, uv, None
    uv = align_to_domain(uv, layout.closed)
    for it in range(iterations + 1):
        control = solver.solve(layout.rows(uv, weights, inner_u, inner_v), points)
        surface = layout.surface(control, weights, inner_u, inner_v)
        new_uv, dist = closest_parameters(surface, points, uv)
        new_rmse = float(np.sqrt(np.mean(dist ** 2)))
        if new_rmse >= rmse * (1.0 - 1e-4):
            break
        rmse, best, best_uv, best_control = new_rmse, surface, new_uv, control
        uv = align_to_domain(new_uv, layout.closed) if realign else new_uv
    return best_control, best, best_uv, it
