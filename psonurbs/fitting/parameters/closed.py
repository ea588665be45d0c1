"""First parameters of the closed topologies: angles around a fitted axis.

    cylinder  a tube: see :mod:`psonurbs.fitting.parameters.tubes`
    sphere    u: longitude, v: latitude from pole (0) to pole (1)
    torus     u: angle around the axis, v: angle around the tube

Every seam (u = 0 = 1) is put in the middle of the widest gap of the data's angles.
"""
from __future__ import annotations

import numpy as np

from .parametrisation import Parametrisation, plane_basis


def fit_circle(q: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle through 2D points (Kasa: linear in centre and r^2 - |c|^2)."""
    a = np.column_stack([2.0 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(a, np.sum(q * q, axis=1), rcond=None)
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


def circle_fits(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares circles through M sets of K 2D points (M, K, 2) at once: centres
    (M, 2), radii (M,). :func:`fit_circle`'s equations (Kasa), by their normal equations."""
    a = np.concatenate([2.0 * q, np.ones(q.shape[:2] + (1,))], axis=2)
    normal = np.einsum("mki,mkj->mij", a, a)
    normal += 1e-12 * np.eye(3) * (np.trace(normal, axis1=1, axis2=2)[:, None, None] + 1e-300)
    x = np.linalg.solve(normal, np.einsum("mki,mk->mi", a, np.sum(q * q, axis=2))[..., None])[..., 0]
    return x[:, :2], np.sqrt(np.maximum(x[:, 2] + np.sum(x[:, :2] ** 2, axis=1), 0.0))


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (algebraic fit, linear in centre and r^2 - |c|^2)."""
    a = np.column_stack([2.0 * points, np.ones(len(points))])
    sol, *_ = np.linalg.lstsq(a, np.sum(points * points, axis=1), rcond=None)
    centre = sol[:3]
    return centre, float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))


def frame_around(axis: np.ndarray) -> np.ndarray:
    """Rows e1, e2, axis: a right-handed orthonormal frame with the given third axis."""
    axis = axis / np.linalg.norm(axis)
    e1, e2 = plane_basis(axis)
    if np.dot(np.cross(e1, e2), axis) < 0:
        e2 = -e2
    return np.stack([e1, e2, axis])


def turn_fraction(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Angle of (x, y) as a fraction of a full turn, in [0, 1)."""
    return np.mod(np.arctan2(y, x) / (2.0 * np.pi), 1.0)


STRAY_SHARE = 0.005  # share of a cloud that may be strays when its extent is judged (gaps, poles)
PROLATE = 1.25  # a cloud this much longer than wide has its poles at its ends
def largest_gap(turns: np.ndarray, strays: float = STRAY_SHARE) -> tuple[float, float]:
    """(size, middle) of the widest arc of angles (given in turns) with at most a share
    ``strays`` of the points inside: the widest empty arc, a few stray points (a scan's
    background, a flying pixel) notwithstanding."""
    s = np.sort(turns)
    m = min(int(strays * len(s)) + 1, len(s))
    gaps = np.r_[s, s[:m] + 1.0][m:m + len(s)] - s
    k = int(np.argmax(gaps))
    return float(gaps[k]), float(np.mod(s[k] + gaps[k] / 2.0, 1.0))


def seam_at_gap(turns: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotate angles so that the seam (0 = 1) sits in the middle of the widest gap."""
    gap, middle = largest_gap(turns)
    return np.mod(turns - middle, 1.0), gap


def sphere_axis(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Pole axis: along the mean direction for a cap, else the cloud's axis of symmetry:
    the longest PCA axis of a clearly prolate cloud (spreads s_0 >= s_1 >= s_2 with
    s_0 / s_1 above both ``PROLATE`` and s_1 / s_2: a capsule, an egg, a bottle), else the
    thinnest (a lentil's; a near-round ball's, where no axis stands out)."""
    d = points - centre
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    mean = d.mean(axis=0)
    if np.linalg.norm(mean) > 0.3:
        return mean / np.linalg.norm(mean)
    _, s, vt = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    return vt[0] if s[0] > s[1] * max(PROLATE, s[1] / max(s[2], 1e-300)) else vt[2]


def parametrise_sphere(points: np.ndarray) -> Parametrisation:
    """u: longitude (seam in the widest gap), v: latitude from pole (0) to pole (1)."""
    centre, radius = fit_sphere(points)
    frame = frame_around(sphere_axis(points, centre))
    local = (points - centre) @ frame.T
    u, gap = seam_at_gap(turn_fraction(local[:, 0], local[:, 1]))
    r = np.maximum(np.linalg.norm(local, axis=1), 1e-300)
    v = np.arccos(np.clip(-local[:, 2] / r, -1.0, 1.0)) / np.pi
    return Parametrisation(np.column_stack([u, v]), {
        "method": "sphere", "centre": [float(c) for c in centre], "radius": radius,
        "axis": [float(c) for c in frame[2]], "angular_gap": gap,
        "latitude_range": [float(q) for q in np.quantile(v, [STRAY_SHARE, 1.0 - STRAY_SHARE])]})


def parametrise_torus(points: np.ndarray) -> Parametrisation:
    """u: angle around the axis, v: angle around the tube (both seams in their widest gap)."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    frame = frame_around(vt[2])
    local = (points - centroid) @ frame.T
    rho = np.hypot(local[:, 0], local[:, 1])
    major = float(np.median(rho))
    u, gap_u = seam_at_gap(turn_fraction(local[:, 0], local[:, 1]))
    v, gap_v = seam_at_gap(turn_fraction(rho - major, local[:, 2]))
    return Parametrisation(np.column_stack([u, v]), {
        "method": "torus", "axis": [float(c) for c in frame[2]], "major_radius": major,
        "angular_gaps": [gap_u, gap_v]})
