"""Organise a raw cloud: refuse what cannot be fitted, drop duplicates, normalise.

All fitting happens in normalised coordinates ``(x - centroid) / diagonal`` (the cloud
fits in a unit box around the origin), which keeps the least-squares systems well
conditioned for clouds far from the origin (UTM coordinates of a terrain scan, say);
NURBS are affine invariant, so the control net maps back exactly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.errors import InputError

from .outliers import Neighbourhoods

# a distance, in normalised units (shares of the diagonal), at which a point lies on a
# surface: the precision to which fitted surfaces are evaluated and scored
RESOLUTION = 1e-6


@dataclass
class Frame:
    """Centroid, principal axes (rows, by decreasing spread) and bounding-box diagonal."""

    centroid: np.ndarray
    axes: np.ndarray
    diagonal: float

    def to_local(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centroid) / self.diagonal

    def to_world(self, points: np.ndarray) -> np.ndarray:
        return points * self.diagonal + self.centroid


@dataclass
class Cloud:
    """A cloud ready for fitting: distinct points in normalised coordinates."""

    points: np.ndarray  # (N, 3) distinct input points, normalised
    frame: Frame
    duplicates: int  # how many input points repeated an earlier one
    neighbourhoods: Neighbourhoods | None = None  # the local test's, for the robust loss

    def __len__(self) -> int:
        return len(self.points)


def check_fittable(points: np.ndarray, orders: tuple[int, int]) -> None:
    """Raise InputError for a cloud no surface of these orders can be fitted to."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"expected an (N, 3) array of points, got shape {points.shape}")
    if len(points) == 0:
        raise InputError("the cloud has no points")
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise InputError(f"{int(bad.sum())} points have NaN or infinite coordinates")
    distinct = len(np.unique(points, axis=0))
    needed = orders[0] * orders[1]
    if distinct < needed:
        raise InputError(f"{distinct} distinct points are too few for orders {orders[0]} x {orders[1]}: "
                         f"at least {needed} are needed")
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[1] <= 1e-9 * s[0]:
        raise InputError("all points lie on a line: no surface is defined by them")


def principal_frame(points: np.ndarray) -> Frame:
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return Frame(centroid, vt, diagonal)


def organise(points: np.ndarray, orders: tuple[int, int]) -> Cloud:
    """Validate, de-duplicate (keeping input order) and normalise a cloud."""
    points = np.asarray(points, float)
    check_fittable(points, orders)
    _, first = np.unique(points, axis=0, return_index=True)
    keep = np.sort(first)
    distinct = points[keep]
    frame = principal_frame(distinct)
    return Cloud(frame.to_local(distinct), frame, len(points) - len(keep))


def subsample(n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of ``min(n, size)`` points drawn without replacement."""
    if n <= size:
        return np.arange(n)
    return np.sort(rng.choice(n, size, replace=False))


def local_normals(points: np.ndarray, neighbours: int = 12) -> np.ndarray:
    """Unoriented unit normals by PCA of each point's nearest neighbours."""
    k = min(neighbours, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]
