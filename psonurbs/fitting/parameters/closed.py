"""First parameters of the closed topologies: angles around a fitted axis.

    cylinder  u: angle around the axis, v: height along it; for a bent tube (an
              elbow, a handle: a torus's tube over part of its circle) u: angle around
              the tube, v: angle along the bend
    sphere    u: longitude, v: latitude from pole (0) to pole (1)
    torus     u: angle around the axis, v: angle around the tube

Every seam (u = 0 = 1) is put in the middle of the widest gap of the data's angles.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from psonurbs.fitting.prepare.organise import local_normals

from .parametrisation import Parametrisation, plane_basis


def fit_circle(q: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle through 2D points (Kasa: linear in centre and r^2 - |c|^2)."""
    a = np.column_stack([2.0 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(a, np.sum(q * q, axis=1), rcond=None)
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


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


def spread(points: np.ndarray) -> float:
    """The points' (N, 3) RMS distance from their centroid (a scale, never 0)."""
    return max(float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))), 1e-300)


def direction(polar: float, azimuth: float) -> np.ndarray:
    """The unit vector (3,) at these spherical angles."""
    return np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])


def turn_fraction(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Angle of (x, y) as a fraction of a full turn, in [0, 1)."""
    return np.mod(np.arctan2(y, x) / (2.0 * np.pi), 1.0)


STRAY_SHARE = 0.005  # share of a cloud that may be strays when its extent is judged (gaps, poles)
PROLATE = 1.25  # a cloud this much longer than wide has its poles at its ends
TUBE_GAP = 0.25  # a bent tube's data go round its section and leave this share of its arc's circle empty
TUBE_FIT = 0.1  # ... and lie within this share of its radius of it (RMS)
BENT_SHARE = 0.5  # a bent tube's model must halve the straight one's distance to be taken
TORUS_SAMPLE = 2000  # points a torus is fitted to (a regular thinning of more)
TORUS_STEPS = 60  # evaluations of its distances, at most, from each start


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


def cylinder_axis(points: np.ndarray) -> np.ndarray:
    """The direction most orthogonal to the local normals (normals of a cylinder are radial)."""
    normals = local_normals(points[:: max(1, len(points) // 4000)])
    _, vecs = np.linalg.eigh(normals.T @ normals)
    return vecs[:, 0]


def parametrise_cylinder(points: np.ndarray) -> Parametrisation:
    """A tube's parameters: those of a bent one (:func:`parametrise_bent_tube`) where it
    lies at most ``BENT_SHARE`` as far from the points (N, 3) as the straight one
    (:func:`parametrise_straight_tube`, RMS), else the straight one's: a torus has two
    more parameters and reaches any straight tube as its radius A grows."""
    straight = parametrise_straight_tube(points)
    bent = parametrise_bent_tube(points)
    return bent if bent.info["model_rms"] < BENT_SHARE * straight.info["model_rms"] else straight


def parametrise_straight_tube(points: np.ndarray) -> Parametrisation:
    """u: angle around the axis (seam in the widest gap), v: height along the axis;
    ``model_rms``: the points' RMS distance from the circular cylinder."""
    frame = frame_around(cylinder_axis(points))
    local = (points - points.mean(axis=0)) @ frame.T
    centre, radius = fit_circle(local[:, :2])
    u, gap = seam_at_gap(turn_fraction(local[:, 0] - centre[0], local[:, 1] - centre[1]))
    h = local[:, 2]
    v = (h - h.min()) / max(np.ptp(h), 1e-300)
    rms = float(np.sqrt(np.mean((np.hypot(*(local[:, :2] - centre).T) - radius) ** 2)))
    return Parametrisation(np.column_stack([u, v]), {
        "method": "cylinder", "axis": [float(c) for c in frame[2]], "radius": radius,
        "angular_gap": gap, "model_rms": rms})


def normal_lines_axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The line (a point on it, unit direction) that the points' normal lines meet most
    nearly: every normal of a surface of revolution meets its axis. A line with
    direction a and moment m meets the normal line through p_i along n_i when
    a . (p_i x n_i) + m . n_i = 0; (a, m) is the least singular vector of those rows
    (N, 6), the points centred and scaled to unit spread first. None when that line lies
    at infinity (a ~ 0: parallel normals, a plane)."""
    sample = points[:: max(1, len(points) // 4000)]
    normals = local_normals(sample)
    centroid, scale = sample.mean(axis=0), spread(sample)
    q = (sample - centroid) / scale
    rows = np.hstack([np.cross(q, normals), normals])
    a, m = np.linalg.svd(rows, full_matrices=False)[2][-1].reshape(2, 3)
    length = float(np.linalg.norm(a))
    if not length > 1e-6:
        return None
    a, m = a / length, m / length
    return centroid + scale * np.cross(a, m), a


def torus_distances(x: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Signed distances (N,) of the points (N, 3) from the torus x = (centre (3), the
    axis's polar and azimuthal angles, A, B): |(rho - A, z)| - B, with z the height along
    the axis and rho the distance from it."""
    axis = direction(x[3], x[4])
    d = points - x[:3]
    z = d @ axis
    rho = np.linalg.norm(d - np.outer(z, axis), axis=1)
    return np.hypot(rho - x[5], z) - x[6]


def fitted_torus(points: np.ndarray, starts: list[tuple[np.ndarray, np.ndarray]]
                 ) -> tuple[np.ndarray, np.ndarray, float, float, float] | None:
    """The torus nearest the points (N, 3) in the least-squares sense, from each start
    (a point on the axis, its direction): there, in the half-plane of rho and z, the
    section's circle (least squares: centre (A, z_0), radius B), then the geometric
    distances (:func:`torus_distances`) minimised over all seven parameters (Levenberg-
    Marquardt-like, on at most ``TORUS_SAMPLE`` points). (centre, axis, A, B, rms) of
    the best, or None when no start gives a tube (0 < B < A)."""
    sample = points[:: max(1, len(points) // TORUS_SAMPLE)]
    scale = spread(sample)
    best = None
    for origin, axis in starts:
        frame = frame_around(axis)
        local = (sample - origin) @ frame.T
        (major, height), minor = fit_circle(np.column_stack([np.hypot(local[:, 0], local[:, 1]), local[:, 2]]))
        if not 0.0 < minor < major:
            continue
        a = frame[2]
        start = np.r_[origin + height * a, np.arccos(np.clip(a[2], -1.0, 1.0)), np.arctan2(a[1], a[0]), major, minor]
        found = least_squares(torus_distances, start, args=(sample,), max_nfev=TORUS_STEPS,
                              x_scale=np.r_[scale, scale, scale, 1.0, 1.0, scale, scale])
        rms = float(np.sqrt(np.mean(found.fun ** 2)))
        if best is None or rms < best[-1]:
            best = (found.x[:3], direction(*found.x[3:5]), float(found.x[5]), float(abs(found.x[6])), rms)
    return best


def parametrise_bent_tube(points: np.ndarray) -> Parametrisation:
    """A tube bent along a circular arc (an elbow, a handle), the torus's tube over part
    of its circle (:func:`fitted_torus`, started from the line its normals meet,
    :func:`normal_lines_axis`, and from the normal of the points' thinnest principal
    plane). u: angle around the tube (seam in its widest gap), v: angle along the arc,
    over the arc the data cover (0 .. 1); ``model_rms``: the points' RMS distance from
    the torus. Data that do not go round the section (a gap wider than ``TUBE_GAP``
    there: a vase's profile, a bowl), whose arc closes (no gap along it that wide: a
    torus), whose section reaches the axis (B >= A) or that lie farther from the torus
    than ``TUBE_FIT`` of its tube's radius (RMS: a folded sheet) are no bent tube (an
    infinite RMS)."""
    centroid = points.mean(axis=0)
    thinnest = np.linalg.svd(points - centroid, full_matrices=False)[2][2]
    starts = [start for start in (normal_lines_axis(points), (centroid, thinnest)) if start is not None]
    torus = fitted_torus(points, starts)
    if torus is None:
        return Parametrisation(np.zeros((len(points), 2)), {"method": "bent tube", "model_rms": np.inf})
    centre, axis, major, minor, _ = torus
    frame = frame_around(axis)
    local = (points - centre) @ frame.T
    rho = np.hypot(local[:, 0], local[:, 1])
    along = turn_fraction(local[:, 0], local[:, 1])
    gap, middle = largest_gap(along)
    along = np.mod(along - middle, 1.0)  # the data's arc now runs from past 0 to short of 1
    low, high = along.min(), along.max()
    v = (along - low) / max(high - low, 1e-300)
    u, tube_gap = seam_at_gap(turn_fraction(rho - major, local[:, 2]))
    rms = float(np.sqrt(np.mean((np.hypot(rho - major, local[:, 2]) - minor) ** 2)))
    tube = gap > TUBE_GAP and tube_gap <= TUBE_GAP and minor < major and rms < TUBE_FIT * minor
    return Parametrisation(np.column_stack([u, v]), {
        "method": "bent tube", "axis": [float(c) for c in axis], "centre": [float(c) for c in centre],
        "major_radius": major, "radius": minor, "angular_gap": tube_gap, "arc": float(1.0 - gap),
        "model_rms": rms if tube else np.inf})


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
