"""Gross outliers judged locally, before anything is fitted: a point is an outlier when it
lies far from the surface its neighbours describe.

For a point x_i and its k nearest neighbours (x_i itself left out), a quadric

    z = b0 + b1 x + b2 y + b3 x^2 + b4 x y + b5 y^2

is fitted to the neighbours in a frame whose z axis is their normal, by iteratively
reweighted least squares with Tukey's biweight (scale: the median absolute residual), the
frame re-estimated from the weighted neighbours: junk among the neighbours gets no weight,
so it tilts neither the frame nor the quadric. A quadric removes the curvature to second
order, so what is left is noise (and, on noise-free data, third-order shape). Point i's
prediction residual ``rho_i = z_i - q(x_i, y_i)`` is studentised by its variance factor,

    t_i = |rho_i| / sqrt(1 + v_i),   v_i = a_i^T (A^T W A)^-1 A^T W^2 A (A^T W A)^-1 a_i

(a_i the quadric's monomials at x_i, A at the neighbours, W their weights), which grows
where x_i lies outside its neighbours' footprint (an edge, a corner). The cloud's noise
scale is ``sigma = 1.4826 median(t)`` (the standard deviation of normal noise, whatever
the junk as long as it is under half the points), and a point is an outlier when

    t_i > OUTLIER_SIGMAS * max(sigma, s_i, MODEL_RESOLUTION * r_i)

with s_i the neighbours' own weighted spread about their quadric (the third-order shape
a quadric cannot follow where a noise-free cloud is sparse or strongly curved: the thin
edge of a graded cloud) and r_i the neighbourhood's radius (the quadric's precision on
exact data). The neighbourhood is k points, not a radius, so the test is the same in
sparse and dense regions.

Junk far from the surface has other junk as its nearest neighbours, scattered points
that describe no surface. So the test runs twice: the first pass judges every point
against all its neighbours and finds the *support*, the points whose neighbourhood is a
surface (thin about its least-squares quadric: residual RMS at most
``max(THICKNESS, THICKNESS_RATIO x median)`` of its radius; scattered points in a ball
are about 0.5) and which lie on it; the second judges every point against its nearest
support points, where junk faces the surface it floats over.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from psonurbs.geometry import compiled
from psonurbs.geometry.compiled import chunks

from . import tukey

NEIGHBOURS = 24  # k: a quadric (6 coefficients) with room for a few junk neighbours
OUTLIER_SIGMAS = 20.0  # gross: beyond heavy-tailed scanner noise (see the module docstring)
SUPPORT_SIGMAS = 7.0  # a support point surely lies on its neighbours' surface (normal: 3e-12 off)
MODEL_RESOLUTION = 1e-3  # relative precision of a local quadric on exact data
THICKNESS = 0.2  # a neighbourhood thicker than this share of its radius is no surface...
THICKNESS_RATIO = 3.0  # ...unless the cloud's typical neighbourhood is as thick (noise ~ spacing)
MIN_POINTS = 20 * NEIGHBOURS  # below, a neighbourhood is over 5% of the cloud: too much for a quadric
TUKEY = 4.685  # biweight tuning constant (95% efficiency under normal noise)
RESOLUTION = 1e-6  # the scale floor, in shares of the diagonal (organise.RESOLUTION)
CHUNK = 8192  # neighbourhoods fitted at once
IRLS_STEPS = 2  # reweighted solves for the plane, then for the quadric
SHARED_NEIGHBOURS = NEIGHBOURS // 4  # two points on one surface share a good part of their neighbours


@dataclass(frozen=True)
class NeighbourhoodFits:
    """What the robust quadrics of the neighbourhoods say about their centres, (N,) each."""

    residual: np.ndarray  # t_i: studentised distance of the centre from its neighbours' quadric
    spread: np.ndarray  # s_i: the neighbours' weighted RMS residual about it
    radius: np.ndarray  # r_i: RMS distance of the neighbours from their centroid, in the plane
    weights: np.ndarray  # (N, k) the neighbours' biweights in the robust fit

    @staticmethod
    def placed(rows: np.ndarray, fits: "NeighbourhoodFits") -> "NeighbourhoodFits":
        """The fits of the points ``rows`` (a permutation of all N), in the points' order."""
        return fits.scattered(rows, fits, np.empty_like)

    def replaced(self, rows: np.ndarray, other: "NeighbourhoodFits") -> "NeighbourhoodFits":
        """These fits with those of ``rows`` taken from ``other`` (fitted for those rows only)."""
        return self.scattered(rows, other, np.copy)

    def scattered(self, rows: np.ndarray, other: "NeighbourhoodFits", start) -> "NeighbourhoodFits":
        """Every field ``start``-ed from this one's (a copy, or an empty array like it), with
        ``other``'s values at ``rows``."""
        out = {}
        for field in fields(self):
            out[field.name] = start(getattr(self, field.name))
            out[field.name][rows] = getattr(other, field.name)
        return NeighbourhoodFits(**out)


@dataclass(frozen=True)
class Neighbourhoods:
    """Each point's neighbours on the same piece of surface (for the robust loss, which
    keeps a point its neighbours agree with, however far from the fit they all are).

    A piece is a connected set of points chained by neighbourhoods that agree: j is
    among i's nearest support points and has a positive weight in i's robust quadric,
    and i likewise in j's.
    Separate pieces (a piece of another object, fragments) are not chained to the main one.
    """

    index: np.ndarray  # (N, k) agreeing neighbours on the main piece, -1 where none
    on_main_piece: np.ndarray  # (N,) bool: on the largest piece
    vouched: np.ndarray  # (N,) bool: on it, within SUPPORT_SIGMAS of its neighbours' quadric and their reach
    lone_consistent: np.ndarray | None = None  # (N,) bool: a lone point (below) as near its neighbours' quadric
    beyond_reach: np.ndarray | None = None  # (N,) bool: joined to the main piece from beyond every neighbour's reach

    @property
    def vouches_for_most(self) -> bool:
        """Whether the test vouched for at least half the points (else the cloud's noise hides
        its structure at the scale of the neighbourhoods, and its vouching says nothing)."""
        return 2 * int(self.vouched.sum()) >= len(self.vouched)

    @property
    def spared(self) -> np.ndarray:
        """(N,) the points the robust loss never leaves out: the vouched ones and the lone
        points as consistent with their neighbours and within their reach (the corner of a
        sparse edge). Only the vouched may steer the parametrisation (junk just beyond an
        edge looks lone too)."""
        return self.vouched if self.lone_consistent is None else self.vouched | self.lone_consistent

    def median(self, values: np.ndarray) -> np.ndarray:
        """(N,) median of the neighbours' values (0 for a point without neighbours)."""
        valid = self.index >= 0
        picked = np.sort(np.where(valid, values[np.maximum(self.index, 0)], np.inf), axis=1)
        count = valid.sum(axis=1)
        rows = np.arange(len(values))
        low, high = picked[rows, np.maximum(count - 1, 0) // 2], picked[rows, np.minimum(count // 2, picked.shape[1] - 1)]
        return np.where(count > 0, 0.5 * (low + high), 0.0)


@dataclass(frozen=True)
class LocalOutliers:
    """The local verdict on a cloud: which points are gross outliers, and the noise scale."""

    outliers: np.ndarray  # (N,) bool
    statistic: np.ndarray  # (N,) t_i over its threshold scale, in robust sigmas
    noise: float  # sigma, in normalised units (shares of the diagonal)
    support: np.ndarray  # (N,) bool: points on a surface their neighbours describe
    neighbours: np.ndarray  # (N, k) each point's nearest support points (itself left out)
    agree: np.ndarray  # (N, k) bool: the neighbour has weight in the point's robust quadric
    order: np.ndarray  # (N,) the points in a spatial order (:func:`spatial_order`)
    reached: np.ndarray  # (N, k) bool: the point lies within that neighbour's neighbourhood (within_reach)

    @property
    def inliers(self) -> np.ndarray:
        return ~self.outliers

    def neighbourhoods(self) -> Neighbourhoods | None:
        """The inliers' :class:`Neighbourhoods`, indexed among the inliers (None if the
        cloud was too small to be judged).

        Pieces are chained through support points only: a point whose neighbourhood is
        no surface (a corner of a floating piece, a point beside junk) reaches across
        gaps to whatever support is nearest, so it joins the piece most of its agreeing
        neighbours are on, but links none; so does a support point no other links to,
        which nothing vouches for.
        """
        if self.neighbours.shape[1] == 0:
            return None
        keep = self.inliers
        new = np.cumsum(keep) - 1
        valid = (self.agree & keep[self.neighbours])[keep]
        index = np.where(valid, new[self.neighbours[keep]], -1)
        support = self.support[keep]
        n = int(keep.sum())
        # links between support points, mutual (a quadric over a neighbourhood half on one
        # piece, half on another can pass through both, but the far piece's own
        # neighbourhoods do not reach back) and sharing SHARED_NEIGHBOURS neighbours (two
        # pieces whose edges come close are not one surface)
        order = new[self.order[keep[self.order]]]
        links = valid & support[:, None] & (shared_neighbours(index, order) >= SHARED_NEIGHBOURS)
        rows = np.repeat(np.arange(n), index.shape[1])[links.ravel()]
        graph = sp.csr_array((np.ones(len(rows)), (rows, index[links])), shape=(n, n))
        _, piece = connected_components(graph.multiply(graph.T), directed=False)
        sizes = np.bincount(piece[support], minlength=piece.max() + 1)
        main = support & (piece == np.argmax(sizes))
        votes = np.sum(valid & main[np.maximum(index, 0)], axis=1)
        joins = 2 * votes > valid.sum(axis=1)
        # a support point linked to none (a piece of one) is no piece of its own: it is
        # judged with the neighbours it agrees with, but nothing vouches for it (a corner
        # of a sparse edge and junk just beyond an edge both look so: their neighbours'
        # denser quadrics do not reach back to them); the loss spares it if it lies as
        # near their quadric as a vouched point, with a bounded say
        lone = support & (sizes[piece] <= 1) & joins
        chained = main
        main = main | (~support & joins)
        consistent = self.statistic[keep] <= SUPPORT_SIGMAS
        # a point no neighbour on the chained piece reaches back to (it lies beyond every
        # such neighbour's own neighbourhood: across a gap, out past an edge) may join the
        # piece, but nothing vouches for it: junk there fits the quadric its neighbours
        # extrapolate, whose uncertainty grows with the distance, as well as an edge point
        reached = chained | np.any(valid & self.reached[keep] & chained[np.maximum(index, 0)], axis=1)
        vouched = main & consistent & reached
        main = main | lone
        on_main = valid & main[np.maximum(index, 0)]
        return Neighbourhoods(np.where(main[:, None] & on_main, index, -1), main, vouched, lone & consistent & reached,
                              main & ~reached)

    def to_dict(self, diagonal: float = 1.0) -> dict:
        """For the JSON: the count, the noise scale (in the units of ``diagonal``, the
        normalised cloud's scale) and the test's settings (0 neighbours: not judged)."""
        return {"outliers": int(self.outliers.sum()), "noise": float(self.noise * diagonal),
                "threshold_sigmas": OUTLIER_SIGMAS, "neighbours": int(self.neighbours.shape[1])}


def shared_neighbours(index: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """(N, k) how many neighbours point i shares with its neighbour ``index[i, s]`` (-1: none, 0).

    With A the (N, N) 0/1 matrix of the neighbourhoods (A[i, j] = 1 for j among i's), the
    count is (A A^T)[i, index[i, s]]: sparse products of CHUNK rows at a time, about
    k^2 terms per point. The points are renumbered in ``order`` (N,) first, when given: in
    a spatial order the product's rows and columns are near each other in memory."""
    if order is not None:
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order))
        out = np.empty(index.shape, np.int64)
        out[order] = shared_neighbours(np.where(index >= 0, rank[np.maximum(index, 0)], -1)[order])
        return out
    n, k = index.shape
    valid = index >= 0
    rows = np.repeat(np.arange(n), k)[valid.ravel()]
    member = sp.csr_array((np.ones(len(rows), np.int8), (rows, index[valid])), shape=(n, n))  # counts <= k < 128
    transposed = member.T.tocsr()
    out = np.zeros((n, k), np.int64)
    for start in range(0, n, CHUNK):
        block = slice(start, min(n, start + CHUNK))
        common = (member[block] @ transposed).tocsr()
        mine = index[block]
        local = np.repeat(np.arange(len(mine)), k)
        counts = np.asarray(common[local, np.maximum(mine, 0).ravel()]).reshape(mine.shape)
        out[block] = np.where(mine >= 0, counts, 0)
    return out


def biweight(residual: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Tukey's biweight (:func:`psonurbs.fitting.prepare.tukey.biweight`) cut off at ``TUKEY scale``."""
    return tukey.biweight(np.abs(residual) / (TUKEY * np.maximum(scale, 1e-300)))


def spatial_order(points: np.ndarray) -> np.ndarray:
    """(N,) the points (N, 3) in the order of a KD-tree's leaves: points near in space are
    near in the order, so passes over neighbourhoods taken in it stay in the cache."""
    return cKDTree(points).indices


class Nearest(NamedTuple):
    index: np.ndarray  # (M, k) the nearest points, nearest first
    tied: np.ndarray  # (M,) bool: two of the k + 1 nearest (itself among them) are equally near


def nearest_among(points: np.ndarray, among: np.ndarray, k: int, rows: np.ndarray | None = None) -> Nearest:
    """The k nearest points of the mask ``among`` to each of the points ``rows`` (M,)
    (default: all), itself left out. Rows in a spatial order are found faster.

    Among equally near points the KD-tree's choice depends on what it holds (and how many
    it is asked for); where none are, the nearest are the same whatever the mask holds
    beyond them."""
    rows = np.arange(len(points)) if rows is None else rows
    if len(rows) == 0:
        return Nearest(np.zeros((0, k), np.int64), np.zeros(0, bool))
    pool = np.flatnonzero(among)
    distance, found = cKDTree(points[pool]).query(points[rows], k=k + 1, workers=compiled.threads())
    distance, found = distance.reshape(len(rows), k + 1), found.reshape(len(rows), k + 1)
    nearest = pool[found]
    own = nearest == rows[:, None]
    keep = np.where(own.any(axis=1)[:, None], ~own, np.arange(k + 1) < k)
    return Nearest(nearest[keep].reshape(len(rows), k), np.any(np.diff(distance, axis=1) == 0, axis=1))


def _frame(p: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted centroid (m, 3) and principal axes (m, 3, 3), the normal first."""
    share = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    centre = np.einsum("mk,mki->mi", share, p)
    q = p - centre[:, None]
    _, axes = np.linalg.eigh(np.matmul(q.transpose(0, 2, 1), q * w[:, :, None]))
    return centre, axes


def _monomials(xy: np.ndarray, quadric: bool) -> np.ndarray:
    """(..., 6) or (..., 3) columns 1, x, y (, x^2, x y, y^2)."""
    x, y = xy[..., 0], xy[..., 1]
    cols = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if quadric else [])
    return np.stack(cols, axis=-1)


def _local(p: np.ndarray, centre: np.ndarray, axes: np.ndarray, points: np.ndarray):
    """Neighbours (m, k, 3) and centres (m, 3) in the frame, in-plane coordinates over the
    neighbourhood's radius; and the radius (m,)."""
    local = np.matmul(p - centre[:, None], axes)
    at = np.einsum("mi,mij->mj", points - centre, axes)
    radius = np.sqrt(np.mean(local[:, :, 1] ** 2 + local[:, :, 2] ** 2, axis=1))
    radius = np.maximum(radius, 1e-300)
    return local[:, :, 1:] / radius[:, None, None], local[:, :, 0], at[:, 1:] / radius[:, None], at[:, 0], radius


def _solve(a: np.ndarray, w: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Weighted least-squares coefficients (m, p), a tiny ridge against empty directions."""
    aw = a * w[:, :, None]
    normal = np.matmul(aw.transpose(0, 2, 1), a)
    normal += 1e-9 * np.eye(a.shape[2]) * (np.trace(normal, axis1=1, axis2=2)[:, None, None] + 1e-300)
    return np.linalg.solve(normal, np.matmul(aw.transpose(0, 2, 1), z[:, :, None]))[:, :, 0]


def _apply(a: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """``A beta`` for every neighbourhood: (m, k, p) by (m, p) -> (m, k)."""
    return np.matmul(a, beta[:, :, None])[:, :, 0]


def _median_abs(r: np.ndarray) -> np.ndarray:
    return np.median(np.abs(r), axis=1, keepdims=True)


def plain_spread(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RMS residual (N,) of the plain least-squares quadric of every point's neighbours, and
    their radius (N,). No robustness: scattered junk must look scattered."""
    n, k = neighbours.shape
    spread, radius = np.empty(n), np.empty(n)

    def chunk(rows: slice) -> None:  # independent chunks, each writing its own rows: in threads
        p = points[neighbours[rows]]
        ones = np.ones(p.shape[:2])
        xy, z, _, _, radius[rows] = _local(p, *_frame(p, ones), points[rows])
        a = _monomials(xy, True)
        e = z - _apply(a, _solve(a, ones, z))
        spread[rows] = np.sqrt(np.sum(e * e, axis=1) / max(k - a.shape[2], 1))

    compiled.each(chunk, chunks(n, CHUNK))
    return spread, radius


def fit_neighbourhoods(points: np.ndarray, centres: np.ndarray, neighbours: np.ndarray,
                       floor: float) -> NeighbourhoodFits:
    """The robust quadric of the neighbours ``points[neighbours[i]]`` (M, k) of each point
    ``points[centres[i]]`` (M,), and what it says about that point (see the module docstring).

    ``floor`` bounds the biweight's scale from below (the cloud's noise): on structured
    data (a grid, scan lines, the rings of a sphere) more than half the neighbours may lie
    exactly on a plane, and a scale from their median residual alone would be zero.
    """
    n, k = neighbours.shape
    out = {name: np.empty(n) for name in ("residual", "spread", "radius")}
    all_weights = np.empty((n, k))

    def chunk(rows: slice) -> None:  # independent chunks, each writing its own rows: in threads
        p, x = points[neighbours[rows]], points[centres[rows]]
        # robust start: the weights of the distances from the coordinate-wise median
        d = np.linalg.norm(p - np.median(p, axis=1)[:, None], axis=2)
        w = biweight(d, 1.4826 * _median_abs(d))
        for quadric in (False, True):  # a plane settles the frame, then the quadric
            xy, z, xy0, z0, radius = _local(p, *_frame(p, w), x)
            a = _monomials(xy, quadric)
            for _ in range(IRLS_STEPS):
                e = z - _apply(a, _solve(a, w, z))
                w = biweight(e, np.maximum(1.4826 * _median_abs(e), floor))
        beta = _solve(a, w, z)
        e = z - _apply(a, beta)
        a0 = _monomials(xy0, True)
        aw = a * w[:, :, None]
        normal = np.matmul(aw.transpose(0, 2, 1), a)
        normal += 1e-9 * np.eye(6) * (np.trace(normal, axis1=1, axis2=2)[:, None, None] + 1e-300)
        g = np.linalg.solve(normal, a0[:, :, None])[:, :, 0]  # (A^T W A)^-1 a_0
        variance = np.sum(_apply(aw, g) ** 2, axis=1)  # |W A (A^T W A)^-1 a_0|^2
        rho = z0 - np.einsum("mp,mp->m", a0, beta)
        out["residual"][rows] = np.abs(rho) / np.sqrt(1.0 + variance)
        out["spread"][rows] = np.sqrt(np.sum(w * e * e, axis=1) / np.maximum(w.sum(axis=1) - 6, 1.0))
        out["radius"][rows] = radius
        all_weights[rows] = w

    compiled.each(chunk, chunks(n, CHUNK))
    return NeighbourhoodFits(weights=all_weights, **out)


def _statistic(fits: NeighbourhoodFits, noise: float) -> np.ndarray:
    return fits.residual / np.maximum(np.maximum(noise, fits.spread), MODEL_RESOLUTION * fits.radius)


def _noise(fits: NeighbourhoodFits, among: np.ndarray) -> float:
    return max(1.4826 * float(np.median(fits.residual[among])), RESOLUTION)


def local_outliers(points: np.ndarray, neighbours: int = NEIGHBOURS) -> LocalOutliers:
    """The local verdict on a cloud (N, 3) in normalised coordinates (diagonal 1).

    A cloud of fewer than ``MIN_POINTS`` points is not judged (nothing is an outlier).
    """
    n = len(points)
    if n < MIN_POINTS:
        return LocalOutliers(np.zeros(n, bool), np.zeros(n), 0.0, np.ones(n, bool),
                             np.zeros((n, 0), np.int64), np.zeros((n, 0), bool), np.arange(n), np.zeros((n, 0), bool))
    k = min(neighbours, n - 1)
    everyone = np.arange(n)
    order = spatial_order(points)  # every pass below takes the points in it (the same answers, faster)
    nearest = np.empty((n, k), np.int64)
    first_found = nearest_among(points, np.ones(n, bool), k, order)
    nearest[order] = first_found.index
    spread, radius = np.empty(n), np.empty(n)
    spread[order], radius[order] = plain_spread(points, nearest[order])
    floor = float(np.median(spread))
    first = NeighbourhoodFits.placed(order, fit_neighbourhoods(points, order, nearest[order], floor))
    thickness = spread / np.maximum(radius, 1e-300)
    thin = thickness <= max(THICKNESS, THICKNESS_RATIO * float(np.median(thickness)))
    support = thin & (_statistic(first, _noise(first, everyone)) <= SUPPORT_SIGMAS)
    # a point whose nearest neighbours are all support has them as its nearest support
    # points, unless the tree chose among equal distances (a cloud on a grid has them
    # everywhere, then every point is searched again; in floating-point data they are absent)
    among_support = nearest.copy()
    again = order if first_found.tied.any() else order[~np.all(support[nearest[order]], axis=1)]
    among_support[again] = nearest_among(points, support, k, again).index
    changed = order[np.any(among_support != nearest, axis=1)[order]]  # the others' fits stand
    second = first.replaced(changed, fit_neighbourhoods(points, changed, among_support[changed], floor))
    noise = _noise(second, support)
    statistic = _statistic(second, noise)
    return LocalOutliers(statistic > OUTLIER_SIGMAS, statistic, noise, support, among_support, second.weights > 0,
                         order, within_reach(points, among_support, order))


def within_reach(points: np.ndarray, index: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(N, k) bool: point i lies within the neighbourhood of its neighbour j = index[i, s],
    no farther from j than j's own farthest neighbour index[j, -1] (i among j's nearest
    but for ties): the neighbourhoods overlap both ways, not only from i across a gap.
    Rows are taken in the spatial ``order`` (N,), in threads."""
    reach = np.linalg.norm(points[index[:, -1]] - points, axis=1)
    out = np.empty(index.shape, bool)

    def chunk(part: slice) -> None:  # independent chunks, each writing its own rows
        rows = order[part]
        near = index[rows]
        out[rows] = np.linalg.norm(points[near] - points[rows, None, :], axis=2) <= reach[near]

    compiled.each(chunk, chunks(len(points), CHUNK))
    return out
