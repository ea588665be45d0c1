"""Gross outliers: points lying many robust standard deviations off the fitted surface.

A scan carries junk (flying pixels, stray returns, a piece of a neighbouring object)
that least squares would follow. With d the points' foot-point distances to a fit, the
residual scale is

    sigma = max(1.4826 median(d), RESOLUTION)

(1.4826 median |r| estimates the standard deviation of a zero-mean normal residual r
whatever the junk, as long as it is under half the points), and a point is an inlier
while ``d <= OUTLIER_SIGMAS * sigma``. Ten sigmas never reject normal noise (the chance
is about 1e-23) and leave a smooth fit's own approximation error alone (it stays
within 8 sigmas on the benchmark clouds, whose residuals are that error alone), while
junk in the bounding box lies hundreds of sigmas off. The floor keeps an exact fit,
whose distances are evaluation noise, from rejecting anything. Rejected points are
left out of the fit, not out of the reported metrics.
"""
from __future__ import annotations

import numpy as np

from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

from .organise import RESOLUTION
from .solve import RegularisedLeastSquares

OUTLIER_SIGMAS = 10.0
ROUNDS = 5  # refits without the rejected points until the inlier set stands still


def inliers(distances: np.ndarray) -> np.ndarray:
    """Mask of the points within ``OUTLIER_SIGMAS`` robust standard deviations."""
    sigma = max(1.4826 * float(np.median(distances)), RESOLUTION)
    return distances <= OUTLIER_SIGMAS * sigma


def classical_inliers(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                      uv: np.ndarray) -> np.ndarray:
    """Inliers of the classical fit (uniform knots, unit weights, least squares) at the
    initial parameters, refitted without the points it rejects until the set repeats.

    A kept point is judged by its leave-one-out residual (against the fit that did not
    see it), a rejected one by its residual: junk where data are thin (an edge, a
    corner) pulls the least-squares surface onto itself, not the fit without it.
    """
    weights = np.ones(layout.n_free)
    rows = layout.rows(uv, weights)
    keep = np.ones(len(points), bool)
    for _ in range(ROUNDS):
        control, loo = solver.leave_one_out(rows.take(keep), points[keep])
        dist = np.linalg.norm(rows @ control - points, axis=1)
        dist[keep] = np.linalg.norm(loo, axis=1)
        new = inliers(dist)
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


def refreshed_inliers(surface: NurbsSurface, points: np.ndarray, keep: np.ndarray,
                      uv_kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inliers of a better fit, and their foot-point parameters on it (the points
    kept so far start from their own, the others from a global search)."""
    start = np.empty((len(points), 2))
    start[keep] = uv_kept
    if not keep.all():
        start[~keep] = closest_parameters(surface, points[~keep])[0]
    uv, dist = closest_parameters(surface, points, start)
    new = inliers(dist)
    return new, uv[new]


def kept_sample(sample: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The sample's kept points, as indices into the kept points."""
    return (np.cumsum(keep) - 1)[sample[keep[sample]]]
