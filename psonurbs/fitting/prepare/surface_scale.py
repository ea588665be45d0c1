"""Local normals at the scale where a cloud is a surface, however thick its noise.

A neighbourhood's normal is the least principal direction of its points (PCA). On a
scan whose noise is a fraction of its spacing a dozen neighbours make a disc and the
normal is the surface's; where the noise is as wide as the spacing (a phone's depth
scan, photogrammetry of a dull surface) a dozen neighbours make a blob and the normal
is random, which reads as a surface seen edge-on, folded or stacked.

The **thickness** of a cloud at k neighbours is the median over its points of

    t_k = sqrt(lambda_min / k) / r_k

(lambda_min the least eigenvalue of the neighbourhood's scatter matrix, r_k its radius):
sigma / r_k for a disc with normal noise sigma, 0.26 for a blob, 0.11 at most on every
benchmark cloud and real scan of the repository's suites at a dozen neighbours. Normal noise shrinks as the
neighbourhood widens, so k doubles from the caller's count until ``t_k <= THIN`` (the
neighbourhood is 6.7 noise sigmas wide: a normal to within a few degrees), up to
``WIDEST_SHARE`` of the cloud (``WIDEST`` points); where none is thin enough the least thick is kept.
Curvature thickens a wide neighbourhood too, which is why the ladder starts at the
caller's count and stops at the first thin scale: a thin cloud is never widened.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

THIN = 0.15  # thickness (sigma over the neighbourhood's radius) up to which its normal is the surface's
WIDEST_SHARE = 0.1  # the widest neighbourhood the ladder tries: this share of the points...
WIDEST = 512  # ...and at most this many (callers pass samples of a few thousand points)
PROBES = 500  # points whose neighbourhoods judge a wider scale


def principal_axes(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each neighbourhood's centroid (N, 3), the eigenvalues (N, 3, ascending) and
    eigenvectors (N, 3, 3; columns) of its scatter matrix (``neighbours`` (N, k) indices)."""
    hood = points[neighbours]
    centre = hood.mean(axis=1, keepdims=True)
    q = hood - centre
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
    return centre[:, 0], values, vectors


def normals_and_variation(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented unit normals (N, 3) and surface variation l_0 / (l_0 + l_1 + l_2) (N,)
    by PCA of each point's neighbourhood (N, k indices into ``points``)."""
    _, values, vectors = principal_axes(points, neighbours)
    return vectors[:, :, 0], values[:, 0] / np.maximum(values.sum(axis=1), 1e-300)


@dataclass(frozen=True)
class SurfaceScale:
    """Each point's neighbourhood at the scale where the cloud is a surface."""

    neighbours: int  # points per neighbourhood, each point's own included
    widened: bool  # wider than asked for: the cloud is thick
    thickness: float  # t_k at that scale (module docstring)
    centres: np.ndarray  # (N, 3) each neighbourhood's centroid
    normals: np.ndarray  # (N, 3) unit, unoriented

    def on_planes(self, points: np.ndarray) -> np.ndarray:
        """``points`` (N, 3) moved along the normals onto their neighbourhoods' planes."""
        return points - np.sum((points - self.centres) * self.normals, axis=1)[:, None] * self.normals


def neighbourhoods(tree: cKDTree, points: np.ndarray, k: int) -> SurfaceScale:
    """The ``k``-point neighbourhoods (the point's own included) of ``points`` (M, 3),
    their normals and the thickness t_k over them (``widened`` False)."""
    lengths, idx = tree.query(points, k=k)
    m = len(points)
    centres, values, vectors = principal_axes(tree.data, idx.reshape(m, -1))
    radius = np.maximum(lengths.reshape(m, -1)[:, -1], 1e-300)
    thickness = float(np.median(np.sqrt(np.maximum(values[:, 0], 0.0) / k) / radius)) if k > 1 else 0.0
    return SurfaceScale(k, False, thickness, centres, vectors[:, :, 0])


def surface_scale(points: np.ndarray, neighbours: int = 12) -> SurfaceScale:
    """The neighbourhoods of ``points`` (N, 3) of ``neighbours`` points each (the point
    itself among them), widened by doubling while the cloud is thicker than ``THIN``
    (module docstring); the wider scales are judged on ``PROBES`` of the points."""
    tree = cKDTree(points)
    k, widest = min(neighbours, len(points)), max(neighbours, min(WIDEST, int(WIDEST_SHARE * len(points))))
    asked = neighbourhoods(tree, points, k)
    if asked.thickness <= THIN:
        return asked
    probes = points[:: max(1, len(points) // PROBES)]
    least, best = asked.thickness, k
    while 2 * k <= widest:
        k *= 2
        thickness = neighbourhoods(tree, probes, k).thickness
        if thickness < least:
            least, best = thickness, k
        if thickness <= THIN:
            break
    if best == asked.neighbours:
        return asked
    wide = neighbourhoods(tree, points, best)
    return SurfaceScale(best, True, wide.thickness, wide.centres, wide.normals)


def local_normals(points: np.ndarray, neighbours: int = 12) -> np.ndarray:
    """Unoriented unit normals (N, 3) by PCA of each point's nearest neighbours, at the
    scale where the cloud is a surface (:func:`surface_scale`)."""
    return surface_scale(points, neighbours).normals
