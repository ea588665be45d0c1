"""Parameter correction: least squares alternated with moving each point's (u, v) to its
foot point (:mod:`psonurbs.geometry.projection`), Anderson-accelerated, with the data's
edges kept on the domain's.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from psonurbs.fitting.leastsq.regularised import weighted_rms
from psonurbs.fitting.leastsq.stacked import least_squares_at
from psonurbs.geometry.net import NetShape
from psonurbs.geometry.projection import closest_parameters, keep_in_domain

from .footprint import ALPHA
from .straight_edges import straight_line


def edge_line(along: np.ndarray, across: np.ndarray, upper: bool, scatter: float) -> np.ndarray:
    """The data's lower (or ``upper``) edge ``across`` as a function of ``along``, at every
    point: its straight line (:func:`straight_line`) or, if it is not straight, the data's
    extreme, ``across`` constant. Put on a line, a disc's parameters are squeezed onto the
    square: a small net folds over its own plane there, and no face can be extended
    past such an edge."""
    line = straight_line(along, across, upper, scatter)
    if line is None:
        return np.full(len(along), across.max() if upper else across.min())
    a, b, _ = line
    return a + b * along


def align_to_domain(uv: np.ndarray, layout, support: bool = True) -> np.ndarray:
    """Map the data's extent in each bounded direction (``layout.bounded``: one with
    edges, not closed and not ending in poles) back onto [0, 1].

    Parameter correction lets the data drift off the domain's edges, and a projection
    on a slightly tilted plane shears them; the surface then extrapolates past the
    data and overshoots the true boundary. For an open direction, each parameter is
    rescaled between two straight lines along the data's lower and upper edges (as
    functions of the other parameter, :func:`edge_line`), so the data span the domain
    again; the few points past a straight edge's line are put on it.

    The sampling scatter of an edge is ``ALPHA`` spacings (the alpha shape's scale of a
    sampling gap, :mod:`psonurbs.fitting.finish.footprint`), the spacing s = sqrt(A / N) of N
    points over the area A of their bounding box. Past an edge that is not straight
    the points reach farther, and putting them on a line through its extremes would
    squeeze a whole cap of the data onto the domain's edge: a bent parametrisation, in
    which even a surface the net represents exactly in its plain parameters
    (plate_holes' quadric over an ellipse) is no longer represented. Such an edge is
    the data's extreme instead (the map stays affine), and the trim cuts the surface
    back to the data. With ``support`` False every edge is a line: the re-alignment at every round of parameter correction (``realign``) keeps
    putting the foot points that run past an edge back on it.
    """
    out = uv.copy()
    box = np.ptp(out, axis=0)
    scatter = ALPHA * float(np.sqrt(max(box[0] * box[1], 0.0) / max(len(out), 1))) if support else np.inf
    for k in (0, 1):
        if not layout.bounded[k]:
            continue
        across, along = out[:, k], out[:, 1 - k]
        if layout.closed[1 - k]:
            lo, hi = np.full(len(across), across.min()), np.full(len(across), across.max())
        else:
            lo, hi = edge_line(along, across, False, scatter), edge_line(along, across, True, scatter)
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

    With a ``relaxation`` beta the step is x_k + beta f_k - (dX + beta dF) c (dX the
    differences of the iterates): beta 1 is the plain mix above, the polish's. Beta 2
    converges faster where the polish runs to its cap on real scans, but can throw a
    polished surface far from the truth (the steep cliff of tests/test_fit.py with knots
    leaving wide end spans).
    """

    def __init__(self, closed: tuple[bool, bool], depth: int = 5, relaxation: float = 1.0):
        self.closed, self.depth, self.relaxation = np.asarray(closed), depth, relaxation
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
        over = self.relaxation - 1.0  # x + beta f = g + over f, dX + beta dF = dG + over dF (exact at beta 1)
        if not self.mixing:
            return g + over * f
        d_f = np.stack([(b - a).ravel() for a, b in zip(self.residuals, self.residuals[1:])], axis=1)
        d_g = np.stack([(b - a).ravel() for a, b in zip(self.images, self.images[1:])], axis=1)
        c = np.linalg.lstsq(d_f, f.ravel(), rcond=None)[0]
        return g + over * f - ((d_g + over * d_f) @ c).reshape(g.shape)


class Polished(NamedTuple):
    control: np.ndarray  # (n_free, 3) the best round's free control points
    surface: object  # their NurbsSurface
    uv: np.ndarray  # (N, 2) the points' foot-point parameters on it
    rounds: int  # rounds taken after the first solve


def polish(layout, solver, points: np.ndarray, uv: np.ndarray, shape: NetShape, iterations: int,
           realign: bool = False, align: bool = True, point_weights: np.ndarray | None = None) -> Polished:
    """Alternate the least-squares solve (at the net's ``shape``: weights and knots) with
    parameter correction of the points (N, 3) at uv (N, 2) while the error falls,
    the parameters Anderson-mixed (restarted plainly from the best when a mixed round
    does not lower the error). ``point_weights`` (N,) weigh the solve and the error.

    The data's extent is first aligned onto the domain (``align``), with ``realign`` at
    every round. The pipeline aligns before each of its polishes, foot points of the
    previous one included (undoing that one's drift of the edges; without it bunny_front's
    fit is the same to 0.5%); the few finishing rounds on a big cloud's every
    point do not.
    Returns the best control points (free), their surface, its foot-point parameters
    and the rounds taken.
    """
    rmse, best, best_uv, best_control = np.inf, None, uv, None
    uv = best_image = align_to_domain(uv, layout) if align or realign else uv
    mixer, fit = AndersonMixing(layout.closed), least_squares_at(layout, solver)
    for it in range(iterations + 1):
        control = fit(uv, shape, points, point_weights)
        surface = layout.surface(control, *shape)
        new_uv, dist = closest_parameters(surface, points, uv)
        new_rmse = weighted_rms(dist ** 2, point_weights)
        if new_rmse >= rmse * (1.0 - 1e-4):
            if not mixer.mixing:
                break
            mixer.reset()
            uv = best_image
            continue
        rmse, best, best_uv, best_control = new_rmse, surface, new_uv, control
        best_image = align_to_domain(new_uv, layout, support=False) if realign else new_uv
        uv = keep_in_domain(mixer.next(uv, best_image), layout.closed)
    return Polished(best_control, best, best_uv, it)
