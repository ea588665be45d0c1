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
    source: np.ndarray | None = None  # (input points,) each one's distinct point in ``points`` (-1: left out)

    def __len__(self) -> int:
        return len(self.points)


# Coordinates a fit can represent: every squared distance between points stays a normal
# float (above 1e-300, below 1e300), and the cloud's extent keeps a dozen significant
# digits once its centroid is subtracted.
COORDINATE_LIMIT = 1e150  # |coordinate| at most this, the bounding-box diagonal at least its inverse
MIN_RELATIVE_EXTENT = 1e-12  # the diagonal over the largest |coordinate|, at least


def check_coordinates(points: np.ndarray) -> None:
    """Raise InputError for finite coordinates whose extent or magnitude no fit can represent."""
    magnitude = float(np.max(np.abs(points), initial=0.0))
    if magnitude > COORDINATE_LIMIT:
        raise InputError(f"coordinates reach {magnitude:.3g}, beyond {COORDINATE_LIMIT:g}: squared distances "
                         "between points overflow; rescale the cloud")
    extent = np.ptp(points, axis=0) if len(points) else np.zeros(3)
    largest = float(extent.max())
    if largest == 0.0:
        raise InputError("all points are the same point: no surface is defined by them")
    diagonal = largest * float(np.linalg.norm(extent / largest))  # scaled: no underflow in the squares
    if diagonal < 1.0 / COORDINATE_LIMIT:
        raise InputError(f"the cloud's bounding-box diagonal {diagonal:.3g} is below {1 / COORDINATE_LIMIT:g}: "
                         "squared distances between points underflow; rescale the cloud")
    if diagonal < MIN_RELATIVE_EXTENT * magnitude:
        raise InputError(f"the cloud's bounding-box diagonal {diagonal:.3g} is below {MIN_RELATIVE_EXTENT:g} of "
                         f"its coordinates ({magnitude:.3g}): too few significant digits are left once "
                         "its centroid is subtracted; subtract an offset from the coordinates")


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
    check_coordinates(points)
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
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    keep = np.sort(first)
    position = np.empty(len(first), np.int64)
    position[np.argsort(first)] = np.arange(len(first))  # of each distinct row in keep
    distinct = points[keep]
    frame = principal_frame(distinct)
    return Cloud(frame.to_local(distinct), frame, len(points) - len(keep), source=position[inverse.ravel()])


def subsample(n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of ``min(n, size)`` points drawn without replacement."""
    if n <= size:
        return np.arange(n)
    return np.sort(rng.choice(n, size, replace=False))


def normals_and_variation(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented unit normals (N, 3) and surface variation l_0 / (l_0 + l_1 + l_2) (N,)
    by PCA of each point's neighbourhood (N, k indices into ``points``)."""
    q = points[neighbours] - points[neighbours].mean(axis=1, keepdims=True)
    eigenvalues, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
    return vectors[:, :, 0], eigenvalues[:, 0] / np.maximum(eigenvalues.sum(axis=1), 1e-300)


def local_normals(points: np.ndarray, neighbours: int = 12) -> np.ndarray:
    """Unoriented unit normals by PCA of each point's nearest neighbours."""
    k = min(neighbours, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    return normals_and_variation(points, idx)[0]
