"""The robust loss: iteratively reweighted least squares with Tukey's biweight.

The local test (:mod:`psonurbs.fitting.prepare.outliers`) removes the junk that lies far from the
surface its neighbours describe. What it cannot see (a flat piece of another object,
junk a few sigmas off the surface) must not pull the fit either, so every solve weighs
point i by

    w_i = (1 - (d_i / (CUTOFF_SIGMAS sigma))^2)^2   (0 beyond),
    sigma = max(1.4826 median(d), RESOLUTION)

with d_i its distance from the current fit (1.4826 median |r| estimates the standard
deviation of a zero-mean normal residual r whatever the junk, as long as it is under
half the points; the floor keeps an exact fit, whose distances are evaluation noise,
from weighing anything down). Points of weight 0 are *left out* (``metrics.outliers``
counts them with the local outliers); partial weights only make a point count less.

Where the fit itself is wrong (a bump the net cannot resolve, a fold of the
parametrisation), a whole neighbourhood lies far from it: those points are not junk,
and leaving them out would hide the error. So a point on the main piece of surface
(:class:`psonurbs.fitting.prepare.outliers.Neighbourhoods`) is judged against the larger of
sigma and the median distance of its neighbours there, ``scale_i = max(sigma, m_i)``:
it is left out only when it is far from the fit *and* from where its neighbours are.
Junk its neighbours disagree with, and separate pieces (another object), keep sigma.
A point the local test vouched for (on the main piece, within a few sigmas of the
surface its neighbours describe and within the neighbourhood of one of them), or a lone
one as near it and as near them (the corner of a sparse edge, which the local test will
not vouch for), is never left out: where the fit folds, tears or cannot reach between
it and its neighbours, the loss lowers its say to at most ``VOUCHED_FLOOR / (d_i / c_i)``
beyond the cut-off c_i, so that its pull w_i d_i stays below the floor's at the cut-off
however far it is (a constant floor let one junk point 150 sigmas beyond an edge bend the fit by a sigma).
A point the local test doubts (not spared) is left out, however near the fit, where it
alone would hold its part of the net. At full weight it decides the share h of its own
fitted value (:meth:`RegularisedLeastSquares.own_leverage`), and the fit without it knows
the surface there only to ``sqrt(h / (1 - h))`` of a point's noise; from
``h / (1 - h) = CUTOFF_SIGMAS^2`` on (``UNCONFIRMED_LEVERAGE``, h = 0.990) that is the
cut-off itself, no distance from the others' fit can tell the point from junk, and a
weight does not lower its say (a stray over a domain's empty corner pins the corner's
control points at any weight above 0, and a free corner curled near it takes it in).
A redescending weight lets no point pull without bound, so refitting with the new
weights (IRLS) converges to a fit that junk cannot hold. The cut-off is wide: a normal
point lies 10 sigmas off with chance 1.5e-23, and a smooth fit's own approximation
error stays within 8 on the benchmark clouds; the biweight gives it 0.99 of the weight
at 1 sigma and 0.56 at 5.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

from .organise import RESOLUTION
from .outliers import Neighbourhoods
from .tukey import biweight

CUTOFF_SIGMAS = 10.0
VOUCHED_FLOOR = 0.01  # the least weight of a point its neighbours vouch for
ROUNDS = 8  # reweighted refits of the classical fit, at most
WEIGHT_TOLERANCE = 1e-3  # the weights stand still: no weight moved more than this
UNCONFIRMED_LEVERAGE = CUTOFF_SIGMAS ** 2 / (1.0 + CUTOFF_SIGMAS ** 2)  # beyond, the others' fit cannot judge a point


def residual_scale(distances: np.ndarray) -> float:
    """sigma: ``max(1.4826 median(d), RESOLUTION)``."""
    return max(1.4826 * float(np.median(distances)), RESOLUTION)


def biweights(distances: np.ndarray, neighbourhoods: Neighbourhoods | None = None,
              leverage: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Tukey's biweight of every distance (N,), cut off at ``CUTOFF_SIGMAS`` times its scale
    (sigma, or ``max(sigma, m_i)`` on the main piece with ``neighbourhoods``, the points
    they vouch for kept at ``VOUCHED_FLOOR`` at least, the others 0 where their own
    leverage, ``leverage(index)`` (M,) of the points at ``index`` (M,), exceeds
    ``UNCONFIRMED_LEVERAGE``)."""
    scale = residual_scale(distances)
    if neighbourhoods is not None:
        scale = np.where(neighbourhoods.on_main_piece, np.maximum(scale, neighbourhoods.median(distances)), scale)
    ratio = distances / (CUTOFF_SIGMAS * scale)
    weights = biweight(ratio)
    if neighbourhoods is not None:
        floor = VOUCHED_FLOOR / np.maximum(ratio, 1.0)  # its pull w d never above the floor's at the cut-off
        weights = np.where(neighbourhoods.spared, np.maximum(weights, floor), weights)
        doubted = np.flatnonzero(~neighbourhoods.spared & (weights > 0)) if leverage is not None else []
        if len(doubted):
            weights[doubted[leverage(doubted) > UNCONFIRMED_LEVERAGE]] = 0.0
    return weights


def classical_weights(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                      uv: np.ndarray, neighbourhoods: Neighbourhoods | None = None) -> np.ndarray:
    """Point weights (N,) of the classical fit (uniform knots, unit weights) at the initial
    parameters, reweighted until they stand still, from the trusted points (the others
    start left out, with a weight to earn).

    A point is judged by its leave-one-out residual (against the fit that did not see
    it; a left-out point's is its residual): junk where data are thin (an edge, a corner)
    pulls the least-squares surface onto itself, not the fit without it.
    """
    rows = layout.rows(uv, np.ones(layout.n_free))
    w = trusted_points(neighbourhoods, len(points)).astype(float)
    for _ in range(ROUNDS):
        new = biweights(np.linalg.norm(solver.leave_one_out(rows, points, w)[1], axis=1), neighbourhoods,
                        lambda of, now=w: solver.own_leverage(rows, now, of))
        done = np.max(np.abs(new - w)) <= WEIGHT_TOLERANCE
        w = new
        if done:
            break
    return w


def refreshed_weights(surface: NurbsSurface, points: np.ndarray, keep: np.ndarray, uv_kept: np.ndarray,
                      neighbourhoods: Neighbourhoods | None = None,
                      leverage_at: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The weights (N,) on a better fit, and the foot-point parameters (N, 2) on it (the
    points kept so far start from their own, the left-out ones from a global search);
    ``leverage_at(uv, index)`` (M,) the own leverage of the points at ``index`` on the fit
    at the parameters ``uv`` (N, 2)."""
    start = np.empty((len(points), 2))
    start[keep] = uv_kept
    if not keep.all():
        start[~keep] = closest_parameters(surface, points[~keep])[0]
    uv, dist = closest_parameters(surface, points, start)
    return biweights(dist, neighbourhoods, None if leverage_at is None else lambda of: leverage_at(uv, of)), uv


def loss_summary(weights: np.ndarray) -> dict:
    """For the JSON: how many points the final solve left out (weight 0), how many it
    counted less than half, and the mean weight of those it kept."""
    kept = weights[weights > 0]
    return {"left_out": int(np.sum(weights == 0)), "down_weighted": int(np.sum(kept < 0.5)),
            "mean_weight": float(kept.mean()) if len(kept) else 0.0, "cutoff_sigmas": CUTOFF_SIGMAS}


def trusted_points(neighbourhoods: Neighbourhoods | None, n: int) -> np.ndarray:
    """(N,) the points that may steer the parametrisation and start the first fit: those the
    local test vouches for (all, when it judged nothing, or vouched for under half: a cloud
    whose noise hides its structure at the scale of the neighbourhoods)."""
    if neighbourhoods is None or not neighbourhoods.vouches_for_most:
        return np.ones(n, bool)
    return neighbourhoods.vouched


def doubted_points(neighbourhoods: Neighbourhoods | None, source: np.ndarray) -> np.ndarray | None:
    """(N,) bool over the input points, each the kept point ``source[i]`` (-1: a local
    outlier): the points the robust stage doubts, local outliers and the points joined to
    the main piece of surface from beyond every neighbour's reach there
    (:attr:`Neighbourhoods.beyond_reach`: junk past an edge). A point among the data a few
    sigmas off (not spared by the loss) still says where the data lie, and a separate
    piece (a part of the scan apart from the rest) is not doubted for being apart. None:
    nothing was judged; only the local outliers when the local test vouched for under
    half (as in :func:`trusted_points`)."""
    if neighbourhoods is None:
        return None
    beyond = neighbourhoods.beyond_reach
    if beyond is None or not neighbourhoods.vouches_for_most:
        return source < 0
    return (source < 0) | beyond[np.maximum(source, 0)]


@dataclass(frozen=True)
class Verdict:
    """The robust stage's word on each input point for the footprint, (N,) bool each (None:
    nothing judged): what marks no data, and what marks the data however far the fit."""

    doubted: np.ndarray | None  # :func:`doubted_points`
    spared: np.ndarray | None = None  # :func:`spared_points`
    outlying: np.ndarray | None = None  # the local outliers (among the doubted)

    @staticmethod
    def of(neighbourhoods: Neighbourhoods | None, source: np.ndarray) -> "Verdict":
        """The verdict on the input points, each the kept point ``source[i]`` (-1: a local outlier)."""
        return Verdict(doubted_points(neighbourhoods, source), spared_points(neighbourhoods, source),
                       None if neighbourhoods is None else source < 0)

    def rejudged(self, distances: np.ndarray, band: float) -> "Verdict":
        """The verdict less the local outliers that a fit passes within ``band`` of
        (``distances`` (N,) to it): judged against their k nearest neighbours, the last
        points of a sheet's sparse end read as outliers of another turn of the sheet
        nearer than their own neighbours; the fit, which never saw them, passes through them.
        The verdict itself where none is."""
        if self.outlying is None or self.doubted is None:
            return self
        on = self.outlying & (distances <= band)
        return replace(self, doubted=self.doubted & ~on, outlying=self.outlying & ~on) if on.any() else self


def spared_points(neighbourhoods: Neighbourhoods | None, source: np.ndarray) -> np.ndarray | None:
    """(N,) bool over the input points, each the kept point ``source[i]`` (-1: a local
    outlier): the points the robust loss never leaves out (:attr:`Neighbourhoods.spared`:
    vouched for, or a sparse edge's lone corner as near its neighbours' surface). None:
    nothing was judged, or the test vouched for under half (as in :func:`trusted_points`)."""
    if neighbourhoods is None or not neighbourhoods.vouches_for_most:
        return None
    return (source >= 0) & neighbourhoods.spared[np.maximum(source, 0)]


def parameters_for_all(points: np.ndarray, trusted: np.ndarray, uv_trusted: np.ndarray) -> np.ndarray:
    """(N, 2) parameters of all points from those of the trusted ones: each other point takes
    its nearest trusted point's (a start; the first fit leaves it out until it earns a weight)."""
    if trusted.all():
        return uv_trusted
    uv = np.empty((len(points), 2))
    uv[trusted] = uv_trusted
    uv[~trusted] = uv_trusted[cKDTree(points[trusted]).query(points[~trusted])[1]]
    return uv


def kept_sample(sample: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The sample's kept points, as indices into the kept points."""
    return (np.cumsum(keep) - 1)[sample[keep[sample]]]
