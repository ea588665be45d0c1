"""Big clouds: every iterative stage on a subsample, the last rounds on every point.

The swarm, its validation, both polishes (tens of rounds each), the joint refinement
and the choice of a topology all decide a surface of a few hundred unknowns, which a
few tens of thousands of points determine to well below the noise (a least-squares
fit from n points is off by about sigma sqrt(unknowns / n)). So a cloud of more than
``SUBSAMPLE_POINTS`` points is fitted on a random subsample of that size (holding the
swarm's points), and the result is finished on every point (:func:`finished`): every
point's foot point on it (a global search, as the metrics take it), the gross outliers
of that fit left out, and up to ``FINAL_ROUNDS`` rounds of parameter correction on all
the others with the subsample's knots, weights and smoothing. The result is the fit
of every point; clouds up to ``SUBSAMPLE_POINTS`` points are fitted as before.
"""
from __future__ import annotations

import numpy as np

from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

from .organise import RESOLUTION
from .polish import polish
from .robust import inliers
from .solve import RegularisedLeastSquares

SUBSAMPLE_POINTS = 20_000  # a bigger cloud is fitted on this many of its points, then finished on all
FINAL_ROUNDS = 3  # rounds of parameter correction on every point after that (each a solve and foot points)
SAMPLE_SEED = 14  # the subsample is fixed: the same cloud gives the same fit


def big_cloud_sample(n: int, swarm_sample: np.ndarray) -> np.ndarray | None:
    """Sorted indices of the subsample a cloud of n points is fitted on (the swarm's
    sample and others drawn at random, ``SUBSAMPLE_POINTS`` in all or the swarm's sample
    alone if that is bigger), or None if that would be every point."""
    size = max(SUBSAMPLE_POINTS, len(swarm_sample))
    if n <= size:
        return None
    others = np.setdiff1d(np.arange(n), swarm_sample)
    extra = np.random.default_rng(SAMPLE_SEED).choice(others, size - len(swarm_sample), replace=False)
    return np.sort(np.concatenate([swarm_sample, extra]))


def free_state(layout: NetLayout, surface: NurbsSurface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(free weights, inner knots u, inner knots v) of a surface of this layout."""
    weights = np.empty(layout.n_free)
    weights[layout.free_index] = surface.weights.ravel()
    inner = []
    for knots, n, p, closed in ((surface.knots_u, layout.size[0], layout.degrees[0], layout.closed[0]),
                                (surface.knots_v, layout.size[1], layout.degrees[1], layout.closed[1])):
        inner.append(knots[p + 1:p + n] if closed else knots[p + 1:n])
    return weights, inner[0], inner[1]


def finished(layout: NetLayout, surface: NurbsSurface, points: np.ndarray, smoothing: float, robust: bool,
             realign: bool) -> tuple[NurbsSurface, np.ndarray, int]:
    """The subsample's surface finished on every point: (surface, inlier mask, rounds).

    Every point's foot point on it (global search), its gross outliers left out (with
    ``robust``), then up to ``FINAL_ROUNDS`` rounds of the polish on the others at the
    surface's knots and weights, from those foot points as they are (``realign``: the
    data's edges re-aligned every round, as for a refined surface). A surface exact on every point (to ``RESOLUTION``, a
    shape the net represents) is kept as it is.
    """
    uv, dist = closest_parameters(surface, points)
    keep = inliers(dist) if robust else np.ones(len(points), bool)
    if np.sqrt(np.mean(dist[keep] ** 2)) <= RESOLUTION:
        return surface, keep, 0
    solver = RegularisedLeastSquares(layout.smoothness_operator(), smoothing, layout.constraint_operator())
    weights, inner_u, inner_v = free_state(layout, surface)
    result = polish(layout, solver, points[keep], uv[keep], weights, inner_u, inner_v, FINAL_ROUNDS,
                    realign=realign, align=False)
    return result.surface, keep, result.rounds + 1
