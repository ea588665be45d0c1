"""Parameter correction: move each point's (u, v) to its closest point on the surface.

The foot point of x on S minimises f(u, v) = |S(u, v) - x|^2 / 2 over the domain. From a
start (the nearest vertex of a dense tessellation, or the previous parameters) Newton
steps H d = -g are taken for all points at once, with

    g = [S_u.r, S_v.r],   H = [[S_u.S_u + r.S_uu, S_u.S_v + r.S_uv], [., S_v.S_v + r.S_vv]],

r = S - x (Gauss-Newton's H without the r terms where the full H is not positive
definite). A parameter on an open edge whose descent leads off the domain is held on
the edge and the step taken in the other one alone (an active set), and a step is
halved until it brings the point closer. Closed directions wrap.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.geometry.nurbs import NurbsSurface

LINE_SEARCH_HALVINGS = 8
PARAMETER_TOLERANCE = 1e-10  # of the unit domain: far below any distance a fit can resolve


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
        res = resolution or int(np.clip(32 * max(surface.shape), 128, 512))
        uv = nearest_on_grid(surface, points, res)
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


def align_to_domain(uv: np.ndarray, layout) -> np.ndarray:
    """Map the data's extent in each bounded direction (``layout.bounded``: one with
    edges, not closed and not ending in poles) back onto [0, 1].

    Parameter correction lets the data drift off the domain's edges, and a projection
    on a slightly tilted plane shears them; the surface then extrapolates past the
    data and overshoots the true boundary. For an open direction, each parameter is
    rescaled between two straight lines fitted to the data's lower and upper edges
    (as functions of the other parameter), so the data span the domain again.
    """
    out = uv.copy()
    for k in (0, 1):
        if not layout.bounded[k]:
            continue
        across, along = out[:, k], out[:, 1 - k]
        if layout.closed[1 - k]:
            lo, hi = np.full(len(across), across.min()), np.full(len(across), across.max())
        else:
            lo, hi = edge_line(along, across, False), edge_line(along, across, True)
        width = hi - lo
        ok = width > 1e-9
        out[:, k] = np.clip(np.where(ok, (across - lo) / np.where(ok, width, 1.0), across), 0.0, 1.0)
    return out


class AndersonMixing:
    """Anderson acceleration of a fixed-point iteration x <- G(x) (Walker & Ni 2011).

    With the residuals f_k = G(x_k) - x_k of the last ``depth`` rounds, the next iterate
    is G(x_k) - dG c, where c = argmin |f_k - dF c| over the differences dF, dG of
    successive residuals and images: the secant model's fixed point. Parameter
    correction alone converges linearly, with a rate near 1 on dense data; mixed, it
    needs a few times fewer rounds. Closed directions are differenced modulo 1, so the
    result is unwrapped: the caller maps it back into the domain.
    """

    def __init__(self, closed: tuple[bool, bool], depth: int = 5):
        self.closed, self.depth = np.asarray(closed), depth
        self.images: list[np.ndarray] = []
        self.residuals: list[np.ndarray] = []

    def reset(self) -> None:
        self.images, self.residuals = [], []

    @property
    def mixing(self) -> bool:
        return len(self.residuals) > 1

    def next(self, x: np.ndarray, image: np.ndarray) -> np.ndarray:
        f = image - x
        f[:, self.closed] = (f[:, self.closed] + 0.5) % 1.0 - 0.5
        g = x + f  # the image, unwrapped next to x
        self.images, self.residuals = (self.images + [g])[-self.depth - 1:], (self.residuals + [f])[-self.depth - 1:]
        if not self.mixing:
            return g
        d_f = np.stack([(b - a).ravel() for a, b in zip(self.residuals, self.residuals[1:])], axis=1)
        d_g = np.stack([(b - a).ravel() for a, b in zip(self.images, self.images[1:])], axis=1)
        c = np.linalg.lstsq(d_f, f.ravel(), rcond=None)[0]
        return g - (d_g @ c).reshape(g.shape)


def polish(layout, solver, points: np.ndarray, uv: np.ndarray,
           weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray, iterations: int, realign: bool = False):
    """Alternate the least-squares solve with parameter correction while the error falls,
    the parameters Anderson-mixed (restarted plainly from the best when a mixed round
    does not lower the error).

    Returns the best control points (free), their surface, its foot-point parameters
    and the rounds taken.
    """
    rmse, best, best_uv, best_control = np.inf, None, uv, None
    uv = align_to_domain(uv, layout)
    mixer = AndersonMixing(layout.closed)
    for it in range(iterations + 1):
        control = solver.solve(layout.rows(uv, weights, inner_u, inner_v), points)
        surface = layout.surface(control, weights, inner_u, inner_v)
        new_uv, dist = closest_parameters(surface, points, uv)
        new_rmse = float(np.sqrt(np.mean(dist ** 2)))
        if new_rmse >= rmse * (1.0 - 1e-4):
            if not mixer.mixing:
                break
            mixer.reset()
            uv = best_image
            continue
        rmse, best, best_uv, best_control = new_rmse, surface, new_uv, control
        best_image = align_to_domain(new_uv, layout) if realign else new_uv
        uv = keep_in_domain(mixer.next(uv, best_image), layout.closed)
    return best_control, best, best_uv, it
