"""The finish every kept candidate gets: polish -> smoothing by leave-one-out -> polish.

The first polish moves the parameters close to the foot points at the candidate's own
smoothing; there the leave-one-out choice of the smoothing weight is sharp (vanishing
where the net represents the shape, larger where the data are noisy), so it is re-chosen
on the swarm's points, and the surface is polished again at it. The pipeline finishes the
surface it keeps with :func:`finish`, and the validation finishes both candidates it
compares with the same function, so what is judged is what is delivered.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.search.knot_weight_space import SMOOTHING_RANGE
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.nurbs import NurbsSurface

from .polish import polish


@dataclass(frozen=True)
class FitPoints:
    """The points a fit sees: (N, 3), their parameters (N, 2), which of them the swarm saw
    (an index or a slice) and their robust-loss weights (N,; None: unweighted)."""

    points: np.ndarray
    uv: np.ndarray
    seen: np.ndarray | slice
    point_weights: np.ndarray | None = None

    def seen_weights(self) -> np.ndarray | None:
        return None if self.point_weights is None else self.point_weights[self.seen]


@dataclass(frozen=True)
class Finished:
    """A finished surface: its free control points (n, 3), the surface, the solver at the
    chosen smoothing, the points it was finished on (with their corrected parameters) and
    the polish's rounds taken in all."""

    control: np.ndarray
    surface: NurbsSurface
    solver: RegularisedLeastSquares
    fitted: FitPoints
    rounds: int


# the robust loss's points after a polish: reweigh(surface, fitted, again, solver) -> the
# points to go on with, or None when ``again`` (after the last polish) and nothing changed
Reweigh = Callable[[NurbsSurface, FitPoints, bool, RegularisedLeastSquares], "FitPoints | None"]


def loo_smoothing(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
                  shape: NetShape, point_weights: np.ndarray | None = None) -> float:
    """The smoothing weight in the swarm's range (half decades) with the least
    leave-one-out error of ``solver``'s problem at these parameters."""
    rows = layout.rows(uv, *shape)
    grid = 10.0 ** np.arange(SMOOTHING_RANGE[0], SMOOTHING_RANGE[1] + 0.25, 0.5)
    errors = []
    for s in grid:
        try:
            errors.append(solver.with_smoothing(s).leave_one_out_rmse(rows, points, point_weights))
        except np.linalg.LinAlgError:
            errors.append(np.inf)
    return float(grid[int(np.argmin(errors))])


def finish(layout: NetLayout, solver: RegularisedLeastSquares, fit: FitPoints, shape: NetShape, rounds: int,
           reweigh: Reweigh | None = None) -> Finished:
    """Polish at ``solver``'s smoothing (``rounds`` rounds at most), re-choose the smoothing
    by leave-one-out on the points the swarm saw at the corrected parameters, polish again.

    With ``reweigh`` (the robust loss), the points and weights are refreshed on each
    polished surface: between the polishes always, after the second one polished once
    more if the points left out changed."""
    control, surface, uv, steps = polish(layout, solver, fit.points, fit.uv, shape, rounds,
                                         point_weights=fit.point_weights)
    fit = FitPoints(fit.points, uv, fit.seen, fit.point_weights)
    if reweigh is not None:
        fit = reweigh(surface, fit, False, solver)
    solver = solver.with_smoothing(loo_smoothing(layout, solver, fit.points[fit.seen], fit.uv[fit.seen], shape,
                                                 fit.seen_weights()))
    control, surface, uv, more = polish(layout, solver, fit.points, fit.uv, shape, rounds,
                                        point_weights=fit.point_weights)
    steps += more
    fit = FitPoints(fit.points, uv, fit.seen, fit.point_weights)
    again = None if reweigh is None else reweigh(surface, fit, True, solver)
    if again is not None:
        control, surface, uv, more = polish(layout, solver, again.points, again.uv, shape, rounds,
                                            point_weights=again.point_weights)
        steps += more
        fit = FitPoints(again.points, uv, again.seen, again.point_weights)
    return Finished(control, surface, solver, fit, int(steps))
