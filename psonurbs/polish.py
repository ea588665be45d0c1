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
        trial = keep_in_domain(uv + np.stack([du, dv], axis=1), closed)
        trial_d2 = np.sum((surface.evaluate(trial[:, 0], trial[:, 1]) - points) ** 2, axis=1)
        better = trial_d2 < dist2
        if not better.any():
            break
        uv[better], dist2[better] = trial[better], trial_d2[better]
    return uv, np.sqrt(dist2)
