"""First parameters of a tube, the cylinder topology (closed in u, open in v), from
the simplest model to the most free:

    straight  u: angle around the axis, v: height along it
    bent      a torus's tube over part of its circle (an elbow, a handle): u: angle
              around the tube, v: angle along the bend
    swept     along any curve (an S bend, a hose): u: angle around the centreline in its
              rotation-minimising frame, v: position along it

Seams are put in the middle of the widest gap of the data's angles.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import least_squares
from scipy.sparse import csr_array
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from psonurbs.fitting.prepare.organise import local_normals

from .closed import circle_fits, fit_circle, frame_around, largest_gap, seam_at_gap, turn_fraction
from .parametrisation import Parametrisation, plane_bases

TUBE_GAP = 0.25  # a bent tube's data go round its section and leave this share of its arc's circle empty
TUBE_FIT = 0.1  # ... and lie within this share of its radius of it (RMS)
BENT_SHARE = 0.5  # a bent tube's model must halve the straight one's distance to be taken
TORUS_SAMPLE = 2000  # points a torus is fitted to (a regular thinning of more)
TORUS_STEPS = 60  # evaluations of its distances, at most, from each start
STATIONS = 40  # stations along a swept tube's centreline
SECTION_NEIGHBOURS = 60  # a point's neighbours whose section circle gives a first centre ...
DIRECTION_NEIGHBOURS = 30  # ... in the plane normal to the least direction of these ones' normals
CENTRE_NEIGHBOURS = 12  # the first centres' graph, which orders them along the tube
STATION_POINTS = 8  # a station with fewer points is no station
CURVE_SAMPLES = 2000  # samples of the centreline, 5% past each end
FIRST_FIT = 3.0  # a first centreline this many times TUBE_FIT off the data is refined no further


def spread(points: np.ndarray) -> float:
    """The points' (N, 3) RMS distance from their centroid (a scale, never 0)."""
    return max(float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))), 1e-300)


def direction(polar: float, azimuth: float) -> np.ndarray:
    """The unit vector (3,) at these spherical angles."""
    return np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])


def cylinder_axis(points: np.ndarray) -> np.ndarray:
    """The direction most orthogonal to the local normals (normals of a cylinder are radial)."""
    normals = local_normals(points[:: max(1, len(points) // 4000)])
    _, vecs = np.linalg.eigh(normals.T @ normals)
    return vecs[:, 0]


def parametrise_cylinder(points: np.ndarray) -> Parametrisation:
    """A tube's parameters, from the simplest model to the most free: straight
    (:func:`parametrise_straight_tube`), bent along an arc (:func:`parametrise_bent_tube`),
    swept along any curve (:func:`parametrise_swept_tube`). A freer model is taken where
    it lies at most ``BENT_SHARE`` as far from the points (N, 3) as the best before it
    (RMS): a torus reaches any straight tube as its radius grows, a sweep any torus.
    The sweep is tried only where neither simpler model is a tube within ``TUBE_FIT``
    of its radius."""
    best = parametrise_straight_tube(points)
    bent = parametrise_bent_tube(points)
    if bent.info["model_rms"] < BENT_SHARE * best.info["model_rms"]:
        best = bent
    if not best.info["model_rms"] < TUBE_FIT * best.info["radius"]:
        swept = parametrise_swept_tube(points)
        if swept.info["model_rms"] < BENT_SHARE * best.info["model_rms"]:
            best = swept
    return best


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


def section_centres(points: np.ndarray) -> np.ndarray:
    """A first centre (N, 3) of the tube's section at each point (N, 3): the tube runs
    along the least direction of its neighbours' normals (a tube's normals are normal to
    it); its ``SECTION_NEIGHBOURS`` nearest points, in the plane normal to that, lie on
    the section's circle."""
    normals = local_normals(points)
    _, near = cKDTree(points).query(points, min(SECTION_NEIGHBOURS, len(points)))
    scatter = normals[near[:, :DIRECTION_NEIGHBOURS]]
    along = np.linalg.eigh(np.einsum("nki,nkj->nij", scatter, scatter))[1][:, :, 0]
    e1, e2 = plane_bases(along).transpose(1, 0, 2)
    offsets = points[near] - points[:, None, :]
    centre, _ = circle_fits(np.stack([np.einsum("nki,ni->nk", offsets, e1), np.einsum("nki,ni->nk", offsets, e2)], 2))
    return points + centre[:, :1] * e1 + centre[:, 1:] * e2


def along_centres(centres: np.ndarray) -> np.ndarray | None:
    """Each centre's (N, 3) position along the tube (0 .. 1): its distance along their
    ``CENTRE_NEIGHBOURS``-nearest graph from the farthest centre (the graph's diameter,
    by a double sweep). None when the graph falls apart."""
    k = min(CENTRE_NEIGHBOURS, len(centres) - 1)
    distance, near = cKDTree(centres).query(centres, k + 1)
    rows = np.repeat(np.arange(len(centres)), k)
    graph = csr_array((distance[:, 1:].ravel(), (rows, near[:, 1:].ravel())), shape=(len(centres),) * 2)
    graph = graph.maximum(graph.T)
    first = dijkstra(graph, indices=0)
    if not np.isfinite(first).all():
        return None
    along = dijkstra(graph, indices=int(np.argmax(first)))
    return along / max(float(along.max()), 1e-300)


def smooth_curve(stations: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The centreline through the stations' centres ((S,) positions in 0 .. 1, (S, 3)):
    a smoothing spline per coordinate (its smoothing by generalised cross-validation),
    sampled ``CURVE_SAMPLES`` times from 5% before the first station to 5% past the last.
    None with fewer than 5 stations (too short a tube to follow)."""
    if len(stations) < 5 or np.any(np.diff(stations) <= 0):
        return None
    grid = np.linspace(-0.05, 1.05, CURVE_SAMPLES)
    return grid, np.column_stack([make_smoothing_spline(stations, centres[:, c])(grid) for c in range(3)])


def station_means(along: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean position (S,) and value (S, ...) in each of ``STATIONS`` equal parts of
    0 .. 1 holding at least ``STATION_POINTS`` points."""
    part = np.clip((along * STATIONS).astype(int), 0, STATIONS - 1)
    kept = [k for k in range(STATIONS) if np.sum(part == k) >= STATION_POINTS]
    return (np.array([along[part == k].mean() for k in kept]), np.array([values[part == k].mean(axis=0) for k in kept]))


def refined_curve(points: np.ndarray, grid: np.ndarray, curve: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The centreline again from the points (N, 3) nearest each station of it: their
    section's circle in the plane normal to the curve there."""
    _, near = cKDTree(curve).query(points)
    position = grid[near]
    along = (position - position.min()) / max(float(np.ptp(position)), 1e-300)
    part = np.clip((along * STATIONS).astype(int), 0, STATIONS - 1)
    tangents = np.gradient(curve, axis=0)
    stations, centres = [], []
    for k in range(STATIONS):
        members = np.flatnonzero(part == k)
        if len(members) < STATION_POINTS:
            continue
        middle = near[members[np.argmin(np.abs(position[members] - np.median(position[members])))]]
        frame = frame_around(tangents[middle])
        local = (points[members] - curve[middle]) @ frame.T
        centre, _ = circle_fits(local[None, :, :2])
        stations.append(along[members].mean())
        centres.append(curve[middle] + frame.T @ np.r_[centre[0], local[:, 2].mean()])
    return smooth_curve(np.array(stations), np.array(centres))


def distance_spread(points: np.ndarray, curve: np.ndarray) -> float:
    """The points' (N, 3) distances from a sampled curve (G, 3): their RMS about their
    median, over the median."""
    distance = cKDTree(curve).query(points)[0]
    radius = max(float(np.median(distance)), 1e-300)
    return float(np.sqrt(np.mean((distance - radius) ** 2))) / radius


def rotation_minimising_frames(curve: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two normals (G, 3) each along a sampled curve (G, 3) that turn as little as the
    curve lets them (the double reflection of Wang, Juettler, Zheng and Liu, 2008)."""
    tangents = np.gradient(curve, axis=0)
    tangents /= np.maximum(np.linalg.norm(tangents, axis=1, keepdims=True), 1e-300)
    first = np.empty_like(curve)
    first[0] = frame_around(tangents[0])[0]
    for i in range(len(curve) - 1):
        step = curve[i + 1] - curve[i]
        c1 = max(float(step @ step), 1e-300)
        reflected = first[i] - (2.0 / c1) * (step @ first[i]) * step
        tangent = tangents[i] - (2.0 / c1) * (step @ tangents[i]) * step
        back = tangents[i + 1] - tangent
        c2 = float(back @ back)
        first[i + 1] = reflected - (2.0 / c2) * (back @ reflected) * back if c2 > 1e-30 else reflected
    return first, np.cross(tangents, first)


def parametrise_swept_tube(points: np.ndarray) -> Parametrisation:
    """A tube swept along any curve (an S bend, a hose, a handle that is no arc): its
    centreline from the section centres (:func:`section_centres` on at most 4,000
    points), ordered along the tube (:func:`along_centres`), averaged over ``STATIONS``
    stations and smoothed (:func:`smooth_curve`), then found again twice from those
    points' own sections (:func:`refined_curve`). u: angle around the centreline in
    its rotation-minimising frame (seam in the widest gap), v: position along it over
    the data's extent; ``model_rms``: the RMS of the points' distances from the
    centreline about their median (the radius). Data that do not go round the section
    or lie farther from the tube than ``TUBE_FIT`` of its radius (a ring, whose
    centres fold onto themselves along the graph's diameter, among them) are no swept
    tube (an infinite RMS)."""
    none = Parametrisation(np.zeros((len(points), 2)), {"method": "swept tube", "radius": 0.0, "model_rms": np.inf})
    sample = points[:: max(1, len(points) // 4000)]
    if len(sample) <= SECTION_NEIGHBOURS:
        return none
    centres = section_centres(sample)
    along = along_centres(centres)
    if along is None:
        return none
    found = smooth_curve(*station_means(along, centres))
    if found is None or not distance_spread(sample, found[1]) < FIRST_FIT * TUBE_FIT:
        return none  # not near any tube: refining will not make one
    for _ in range(2):
        found = refined_curve(sample, *found)
        if found is None:
            return none
    grid, curve = found
    first, second = rotation_minimising_frames(curve)
    _, near = cKDTree(curve).query(points)
    offsets = points - curve[near]
    distance = np.linalg.norm(offsets, axis=1)
    radius = float(np.median(distance))
    rms = float(np.sqrt(np.mean((distance - radius) ** 2)))
    u, gap = seam_at_gap(turn_fraction(np.sum(offsets * first[near], axis=1), np.sum(offsets * second[near], axis=1)))
    position = grid[near]
    v = (position - position.min()) / max(float(np.ptp(position)), 1e-300)
    tube = gap <= TUBE_GAP and rms < TUBE_FIT * radius
    first_sample, last_sample = near[np.argmin(position)], near[np.argmax(position)]
    return Parametrisation(np.column_stack([u, v]), {
        "method": "swept tube", "radius": radius, "angular_gap": gap,
        "length": float(np.sum(np.linalg.norm(np.diff(curve[first_sample:last_sample + 1], axis=0), axis=1))),
        "model_rms": rms if tube else np.inf})
