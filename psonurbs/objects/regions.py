"""A cloud split into regions that one smooth surface each describes.

Region growing on the points' normals: each point's normal and surface variation
sigma = l_0 / (l_0 + l_1 + l_2) come from the covariance of its ``NEIGHBOURS`` nearest
neighbours (eigenvalues l_0 <= l_1 <= l_2). A region starts at the smoothest point not
yet taken and takes every neighbour whose normal is within ``ANGLE`` of the point it is
reached from; it grows on only through smooth points (sigma below ``ROUGH`` times the
median, or below what a neighbourhood straddling a crease of ``CREASE`` reads,
:func:`folded_variation`, whichever is larger), so it stops at a crease, where the
neighbourhoods straddle two faces and sigma peaks, and goes on round a fillet, a bend
whose radius is more than a neighbourhood's (a can's rounded rim). Points a region never
reached (a crease's band) belong to none.

Regions smaller than ``MIN_SHARE`` of the cloud are given up (their points to none), and
two regions that touch are merged where they meet smoothly: the mean normals of their
points facing each other (each within ``CONTACT`` neighbours of the other region) are
within ``CREASE``. Noise breaks a region's growth without a crease (a rough terrain), and
so does a bend tighter than a neighbourhood (a bottle's rounded corners, 40 degrees
across); a crease (a can's rim, a shaft's step: 85-90 degrees) stays.

A region grown round a fillet can be one no single surface fits (a cup: wall, rounded
foot and base); :func:`split_where_facing` parts it where its normals turn to face the
direction they span least, for the caller to try when a region's fit misses its tolerance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from psonurbs.fitting.prepare.organise import normals_and_variation

NEIGHBOURS = 16
ANGLE = np.radians(12.0)
ROUGH = 4.0
MIN_SHARE = 0.03
CONTACT = 32
CREASE = np.radians(45.0)  # a turn this large across a band is a crease (the four-sided map's corner)
FACING = np.radians(45.0)  # a split's side: normals this close to the direction they span least
LINKS = 8  # neighbours that join a split side's points into pieces


@dataclass(frozen=True)
class Regions:
    """labels (N,): each point's region 0 .. count - 1, or -1 (a crease's band, or a
    region too small); normals (N, 3) unoriented; spacing: the points' median distance to
    their nearest neighbour."""

    labels: np.ndarray
    normals: np.ndarray
    spacing: float

    @property
    def count(self) -> int:
        return int(self.labels.max()) + 1 if len(self.labels) and self.labels.max() >= 0 else 0

    def members(self, region: int) -> np.ndarray:
        return np.flatnonzero(self.labels == region)


def folded_variation(turn: float) -> float:
    """The surface variation of a uniform disc folded along a diameter, its halves
    turned ``turn`` apart: covariance eigenvalues 1/4, cos^2(t/2) / 4 and
    sin^2(t/2) (1/4 - 16 / (9 pi^2)) (the halves' offsets |y| sin(t/2) about their mean),
    sigma = the least over their sum. A neighbourhood straddling a crease of that turn
    reads about this much at the crease; one on a bend of radius r, about
    (rho / r)^2 / 32 for a neighbourhood of radius rho."""
    half = turn / 2.0
    least = np.sin(half) ** 2 * (0.25 - 16.0 / (9.0 * np.pi ** 2))
    return float(least / (0.25 + 0.25 * np.cos(half) ** 2 + least))


def grown(normals: np.ndarray, variation: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Labels (N,) of the regions grown from the smoothest points (-1: reached by none)."""
    smooth = variation < max(ROUGH * np.median(variation), folded_variation(CREASE))
    labels = np.full(len(normals), -1)
    cos = np.cos(ANGLE)
    region = 0
    for seed in np.argsort(variation, kind="stable"):
        if labels[seed] >= 0 or not smooth[seed]:
            continue
        labels[seed] = region
        stack = [seed]
        while stack:
            i = stack.pop()
            for j in neighbours[i, 1:]:
                if labels[j] < 0 and abs(normals[i] @ normals[j]) > cos:
                    labels[j] = region
                    if smooth[j]:
                        stack.append(j)
        region += 1
    return labels


def merged_smooth_joins(labels: np.ndarray, normals: np.ndarray, contacts: np.ndarray) -> np.ndarray:
    """Labels with every two touching regions whose facing points' mean normals are
    within ``CREASE`` merged (union-find), renumbered by size, largest first."""
    parent = list(range(int(labels.max()) + 1))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    own = labels[:, None]
    other = labels[contacts]
    touching = (other >= 0) & (other != own) & (own >= 0)
    pairs = np.unique(np.column_stack([np.repeat(labels, contacts.shape[1])[touching.ravel()],
                                       other[touching]]), axis=0)
    for a, b in pairs:
        if a > b:
            continue
        facing_a = np.flatnonzero((labels == a) & np.any(other == b, axis=1))
        facing_b = np.flatnonzero((labels == b) & np.any(other == a, axis=1))
        mean_a, mean_b = (_mean_axis(normals[f]) for f in (facing_a, facing_b))
        if abs(mean_a @ mean_b) > np.cos(CREASE):
            parent[root(int(a))] = root(int(b))
    roots = np.array([root(r) for r in range(len(parent))])
    return _by_size(np.where(labels >= 0, roots[np.maximum(labels, 0)], -1))


def _mean_axis(normals: np.ndarray) -> np.ndarray:
    """The mean of unoriented unit vectors (M, 3): the principal axis of their scatter."""
    return np.linalg.eigh(normals.T @ normals)[1][:, -1]


def _by_size(labels: np.ndarray) -> np.ndarray:
    """Labels renumbered 0, 1, ... by decreasing size (-1 kept)."""
    kept = labels >= 0
    if not kept.any():
        return labels
    values, counts = np.unique(labels[kept], return_counts=True)
    order = values[np.argsort(-counts, kind="stable")]
    rename = np.full(int(labels.max()) + 1, -1)
    rename[order] = np.arange(len(order))
    return np.where(kept, rename[np.maximum(labels, 0)], -1)


def split_where_facing(points: np.ndarray, normals: np.ndarray, least: int) -> np.ndarray:
    """Labels (M,) of a region's parts, for a region that one surface does not fit: its
    points whose normal lies within ``FACING`` of the direction a the normals span least
    (a: the least eigenvector of sum n n^T over the region), against the rest, each side's
    connected pieces (``LINKS`` nearest neighbours on the same side) a part; pieces
    smaller than ``least`` points go to none (-1). A cup's base faces its axis, its wall
    does not; a bottle's shoulder faces it, its body does not. A region of one smooth
    surface that turns less than ``FACING`` towards its least direction (a plane, a
    cylinder's wall, a shallow cap) does not split: every label is 0."""
    axis = np.linalg.eigh(normals.T @ normals)[1][:, 0]
    facing = np.abs(normals @ axis) > np.cos(FACING)
    k = min(LINKS, len(points))
    neighbours = cKDTree(points).query(points, k)[1]
    same = facing[neighbours] == facing[:, None]
    rows = np.repeat(np.arange(len(points)), k)[same.ravel()]
    graph = coo_matrix((np.ones(len(rows)), (rows, neighbours.ravel()[same.ravel()])), shape=(len(points),) * 2)
    pieces = connected_components(graph, directed=False)[1]
    sizes = np.bincount(pieces)
    labels = _by_size(np.where(sizes[pieces] >= least, pieces, -1))
    return labels if labels.max() > 0 else np.zeros(len(points), int)


def segment(points: np.ndarray, most: int | None = None) -> Regions:
    """The regions of a cloud (N, 3); with ``most``, its largest ``most`` regions only."""
    tree = cKDTree(points)
    distances, neighbours = tree.query(points, max(NEIGHBOURS, CONTACT))
    normals, variation = normals_and_variation(points, neighbours[:, :NEIGHBOURS])
    labels = _by_size(grown(normals, variation, neighbours[:, :NEIGHBOURS]))
    small = np.bincount(labels[labels >= 0]) < MIN_SHARE * len(points)
    labels = np.where((labels >= 0) & ~small[np.maximum(labels, 0)], labels, -1)
    if labels.max() > 0:
        labels = merged_smooth_joins(_by_size(labels), normals, neighbours[:, 1:CONTACT])
    if most is not None:
        labels = np.where(labels < most, labels, -1)
    return Regions(labels, normals, float(np.median(distances[:, 1])))
