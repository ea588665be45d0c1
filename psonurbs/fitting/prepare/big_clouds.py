"""Big clouds: every iterative stage on a subsample, the last rounds on every point.

The swarm, its validation, both polishes (tens of rounds each), the joint refinement
and the choice of a topology all decide a surface of a few hundred unknowns, which a
few tens of thousands of points determine to well below the noise (a least-squares
fit from n points is off by about sigma sqrt(unknowns / n)). So a cloud of more than
``SUBSAMPLE_POINTS`` points is fitted on a random subsample of that size (holding the
swarm's points), and the result is finished on every point (:func:`finished`): every
point's foot point on it (a global search, as the metrics take it), with ``robust`` its
weight by the robust loss on that fit (judged with the local test's neighbourhoods of the
whole cloud; the subsample's own fit weighs its points by the plain scale), and up to
``FINAL_ROUNDS`` rounds of parameter correction on the points kept, with the subsample's
knots, weights and smoothing. The result is the fit
of every point; clouds up to ``SUBSAMPLE_POINTS`` points are fitted on all their points directly.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from psonurbs.fitting.finish.polish import polish
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

from .organise import RESOLUTION
from .outliers import Neighbourhoods
from .robust_weights import biweights

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


def free_state(layout: NetLayout, surface: NurbsSurface) -> NetShape:
    """The shape (free weights, inner knots u and v) of a surface of this layout."""
    weights = np.empty(layout.n_free)
    weights[layout.free_index] = surface.weights.ravel()
    inner = []
    for knots, n, p, closed in ((surface.knots_u, layout.size[0], layout.degrees[0], layout.closed[0]),
                                (surface.knots_v, layout.size[1], layout.degrees[1], layout.closed[1])):
        inner.append(knots[p + 1:p + n] if closed else knots[p + 1:n])
    return NetShape(weights, inner[0], inner[1])


class Finished(NamedTuple):
    surface: NurbsSurface  # the fit of every point
    uv: np.ndarray  # (N, 2) the points' foot points on it (of the points left out, on the subsample's fit)
    point_weights: np.ndarray | None  # (N,) the robust loss's weights on it (0: left out), None without ``robust``
    rounds: int  # rounds of parameter correction on every point (0: kept as it was)


def finished(layout: NetLayout, surface: NurbsSurface, points: np.ndarray, smoothing: float, robust: bool,
             realign: bool, neighbourhoods: Neighbourhoods | None = None) -> Finished:
    """The subsample's surface finished on every point.

    Every point's foot point on it (global search), with ``robust`` its weight by the
    robust loss on it (:func:`psonurbs.fitting.prepare.robust_weights.biweights`, with the whole cloud's
    ``neighbourhoods``; weight 0 is left out), then up to ``FINAL_ROUNDS`` rounds of the
    polish on the points kept, so weighted, at the surface's knots and weights, from those
    foot points as they are (``realign``: the data's edges re-aligned every round, as for
    a refined surface). A surface exact on every point (to ``RESOLUTION``, a shape the net
    represents) is kept as it is.
    """
    uv, dist = closest_parameters(surface, points)
    solver = RegularisedLeastSquares(layout.smoothness_operator(), smoothing, layout.constraint_operator())
    shape = free_state(layout, surface)
    point_weights = biweights(dist, neighbourhoods, lambda of: solver.own_leverage(layout.rows(uv, *shape), None, of)) \
        if robust else None
    keep = np.ones(len(points), bool) if point_weights is None else point_weights > 0
    if np.sqrt(np.mean(dist[keep] ** 2)) <= RESOLUTION:
        return Finished(surface, uv, point_weights, 0)
    result = polish(layout, solver, points[keep], uv[keep], shape, FINAL_ROUNDS,
                    realign=realign, align=False, point_weights=None if point_weights is None else point_weights[keep])
    uv[keep] = result.uv
    return Finished(result.surface, uv, point_weights, result.rounds + 1)


def every_foot_point(surface: NurbsSurface, points: np.ndarray, source: np.ndarray, uv: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Foot-point parameters (M, 2) and distances (M,) on the finished ``surface`` of the
    input points (M, 3): from their distinct point's parameters ``uv[source]`` (``Finished.uv``)
    where they have one (a local search: the polished points' are foot points on it
    already), by a global search for those left out before the fit (``source`` -1, the
    local test's outliers)."""
    out_uv, out_dist = np.empty((len(points), 2)), np.empty(len(points))
    fitted = source >= 0
    out_uv[fitted], out_dist[fitted] = closest_parameters(surface, points[fitted], uv[source[fitted]])
    if not fitted.all():
        out_uv[~fitted], out_dist[~fitted] = closest_parameters(surface, points[~fitted])
    return out_uv, out_dist
