"""Net layouts of the closed topologies (seams, poles, free-point counts, smoothness
operator), first parametrisations against known geometry, and choosing a topology."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from psonurbs.config import config_from_dict
from psonurbs.fitting.parameters.closed import STRAY_SHARE, parametrise_sphere, parametrise_torus
from psonurbs.fitting.parameters.plane import parametrise_open
from psonurbs.fitting.parameters.topology import (
    LAYOUTS,
    choose_topology,
    closed_round,
    layout_for,
    topology_note,
    unsupported,
)
from psonurbs.fitting.parameters.tubes import parametrise_bent_tube, parametrise_cylinder
from psonurbs.geometry.net import NetLayout

CLOSED = {
    "cylinder": NetLayout((6, 5), (3, 3), (True, False)),
    "sphere": NetLayout((6, 5), (3, 3), (True, False), poles=True),
    "torus": NetLayout((6, 5), (3, 3), (True, True)),
}


def random_surface(layout: NetLayout, seed: int, with_knots: bool = True):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(layout.n_free, 3))
    weights = rng.uniform(0.4, 2.5, layout.n_free)
    inner = [None, None]
    if with_knots:
        for k, c in enumerate(layout.inner_counts):
            inner[k] = np.sort(rng.uniform(0.05, 0.95, c))
    return layout.surface(points, weights, *inner)


def homogeneous(surface, u, v, du, dv):
    """(A, W) derivatives: A = sum w P N, W = sum w N; S = A / W is C^k where both are."""
    t = surface.tensor(u, v, du, dv)
    w = surface.weights.reshape(-1)
    aw = (surface.control_points * surface.weights[..., None]).reshape(-1, 3)
    return np.column_stack([t @ aw, t @ w])


@pytest.mark.parametrize("name", ["cylinder", "sphere", "torus"])
@pytest.mark.parametrize("seed", [0, 1])
def test_closed_surfaces_have_no_seam_along_u(name, seed):
    s = random_surface(CLOSED[name], seed)
    assert s.closed_u and s.domain_u == (0.0, 1.0)
    v = np.linspace(0.0, 1.0, 17)
    zero, one = np.zeros_like(v), np.ones_like(v)
    a0, a1 = s.derivatives(zero, v), s.derivatives(one, v)
    scale = np.abs(s.control_points).max()
    for x, y in zip(a0, a1):  # S, S_u, S_v
        np.testing.assert_allclose(x, y, atol=1e-9 * scale * 10)
    for du in (0, 1, 2):  # cubic: C^2 across the seam
        h0, h1 = homogeneous(s, zero, v, du, 0), homogeneous(s, one, v, du, 0)
        np.testing.assert_allclose(h0, h1, atol=1e-9 * np.abs(h0).max())
    # second derivative of S itself: S_uu = (A_uu - 2 W_u S_u - W_uu S) / W, equal on both sides
    def s_uu(u):
        (h, hu, huu) = (homogeneous(s, u, v, k, 0) for k in (0, 1, 2))
        w, wu, wuu = h[:, 3:], hu[:, 3:], huu[:, 3:]
        p = h[:, :3] / w
        pu = (hu[:, :3] - wu * p) / w
        return (huu[:, :3] - 2 * wu * pu - wuu * p) / w
    a, b = s_uu(zero), s_uu(one)
    np.testing.assert_allclose(a, b, atol=1e-9 * np.abs(a).max())
    assert np.abs(a).max() > 1.0  # not trivially zero


def test_torus_has_no_seam_along_v():
    s = random_surface(CLOSED["torus"], 4)
    assert s.closed_v
    u = np.linspace(0.0, 1.0, 19)
    zero, one = np.zeros_like(u), np.ones_like(u)
    for x, y in zip(s.derivatives(u, zero), s.derivatives(u, one)):
        np.testing.assert_allclose(x, y, atol=1e-9 * np.abs(x).max())
    for dv in (0, 1, 2):
        h0, h1 = homogeneous(s, u, zero, 0, dv), homogeneous(s, u, one, 0, dv)
        np.testing.assert_allclose(h0, h1, atol=1e-9 * np.abs(h0).max())
    # the corner (0, 0) = (1, 1) = (0, 1) = (1, 0)
    corners = s.evaluate(np.array([0.0, 1.0, 0.0, 1.0]), np.array([0.0, 1.0, 1.0, 0.0]))
    assert np.ptp(corners, axis=0).max() < 1e-12


def test_cylinder_is_open_along_v():
    s = random_surface(CLOSED["cylinder"], 5)
    u = np.linspace(0, 1, 9)
    gap = np.linalg.norm(s.evaluate(u, np.zeros_like(u)) - s.evaluate(u, np.ones_like(u)), axis=1)
    assert gap.min() > 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sphere_pole_rows_are_single_points(seed):
    layout = CLOSED["sphere"]
    s = random_surface(layout, seed)
    u = np.linspace(0.0, 1.0, 101)
    for v in (0.0, 1.0):
        row = s.evaluate(u, np.full_like(u, v))
        assert np.ptp(row, axis=0).max() < 1e-12
    # and the two poles are the first and last free points
    rng = np.random.default_rng(seed)
    free = rng.normal(size=(layout.n_free, 3))
    s2 = layout.surface(free, np.ones(layout.n_free))
    np.testing.assert_allclose(s2.evaluate(np.array([0.3]), np.array([0.0]))[0], free[0], atol=1e-14)
    np.testing.assert_allclose(s2.evaluate(np.array([0.3]), np.array([1.0]))[0], free[-1], atol=1e-14)


@pytest.mark.parametrize("topology, size, degrees, n_free, full_shape", [
    ("open", (5, 4), (2, 3), 20, (5, 4)),
    ("cylinder", (6, 5), (3, 2), 30, (9, 5)),
    ("sphere", (5, 5), (2, 2), 5 * 3 + 2, (7, 5)),
    ("sphere", (8, 6), (3, 3), 8 * 4 + 2, (11, 6)),
    ("torus", (6, 5), (3, 2), 30, (9, 7)),
])
def test_free_point_counts(topology, size, degrees, n_free, full_shape):
    layout = layout_for(topology, size, degrees)
    assert layout.n_free == n_free
    assert layout.full_shape == full_shape
    assert layout.free_index.shape == (full_shape[0] * full_shape[1],)
    assert set(np.unique(layout.free_index)) == set(range(n_free))
    closed, poles = LAYOUTS[topology]
    idx = layout.free_index.reshape(full_shape)
    if closed[0]:  # the last degree rows repeat the first
        np.testing.assert_array_equal(idx[-degrees[0]:], idx[:degrees[0]])
    if closed[1]:
        np.testing.assert_array_equal(idx[:, -degrees[1]:], idx[:, :degrees[1]])
    if poles:
        assert np.all(idx[:, 0] == 0) and np.all(idx[:, -1] == n_free - 1)


def test_smoothness_operator_annihilates_affine_net_on_open_layout():
    layout = NetLayout((6, 5), (3, 2))
    i, j = np.meshgrid(np.arange(6), np.arange(5), indexing="ij")
    affine = np.stack([2 + i - 3 * j, 0.5 * i, 4 * j - 1], axis=-1).reshape(-1, 3).astype(float)
    op = layout.smoothness_operator()
    assert op.shape == (4 * 5 + 6 * 3 + 5 * 4, 30)
    np.testing.assert_allclose(op @ affine, 0.0, atol=1e-12)
    # a bilinear term i*j is caught by the mixed difference (weight sqrt 2)
    bilinear = np.stack([i * j, 0 * i, 0 * j], axis=-1).reshape(-1, 3).astype(float)
    energy = np.sum((op @ bilinear) ** 2)
    assert energy == pytest.approx(2.0 * 5 * 4, rel=1e-12)
    # closed: a constant net costs nothing, a periodic ramp does
    closed = NetLayout((6, 5), (3, 2), (True, False))
    np.testing.assert_allclose(closed.smoothness_operator() @ np.ones((30, 3)), 0.0, atol=1e-12)
    assert np.abs(closed.smoothness_operator() @ affine).max() > 1


# ---- parametrisations -------------------------------------------------------

def angle_deg(a, b):
    a, b = np.asarray(a) / np.linalg.norm(a), np.asarray(b) / np.linalg.norm(b)
    return np.degrees(np.arccos(np.clip(abs(a @ b), -1, 1)))


def height_field(n=600, seed=0, rotation=None):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (n, 2))
    z = 0.6 * np.exp(-2.0 * np.sum(xy ** 2, axis=1))  # a peaked bump: PCA tilts, "up" does not
    pts = np.column_stack([xy, z])
    return pts if rotation is None else pts @ rotation.as_matrix().T


def cylinder_cloud(n=600, seed=0, radius=1.7, height=3.0, arc=2 * np.pi, axis=None, centre=(1.0, -2.0, 0.5)):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, arc, n)
    h = rng.uniform(0, height, n)
    local = np.column_stack([radius * np.cos(a), radius * np.sin(a), h])
    rot = Rotation.align_vectors([axis], [[0, 0, 1]])[0] if axis is not None else Rotation.identity()
    return local @ rot.as_matrix().T + np.asarray(centre)


def sphere_cloud(n=500, seed=0, centre=(0.3, -1.0, 2.0), radius=1.3):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + radius * d


def torus_cloud(n=600, seed=0, major=2.0, minor=0.6, rotation=None):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0, 2 * np.pi, (2, n))
    pts = np.column_stack([(major + minor * np.cos(b)) * np.cos(a), (major + minor * np.cos(b)) * np.sin(a),
                           minor * np.sin(b)])
    return pts if rotation is None else pts @ rotation.as_matrix().T


def elbow_cloud(n=1500, seed=0, major=1.0, minor=0.25, arc=0.5 * np.pi, noise=5e-4, rotation=None,
                centre=(0.4, -0.7, 1.1)):
    """A bent tube (a pipe elbow, a handle): the torus's tube of radius ``minor`` over an
    arc of its circle of radius ``major``, area-uniform, with Gaussian noise; also its
    true angles along the arc and around the tube (N,) each."""
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0, arc, 4 * n), rng.uniform(0, 2 * np.pi, 4 * n)
    keep = np.flatnonzero(rng.random(4 * n) < (major + minor * np.cos(b)) / (major + minor))[:n]
    a, b = a[keep], b[keep]
    pts = np.column_stack([(major + minor * np.cos(b)) * np.cos(a), (major + minor * np.cos(b)) * np.sin(a),
                           minor * np.sin(b)]) + noise * rng.standard_normal((len(a), 3))
    rot = rotation or Rotation.identity()
    return rot.apply(pts) + np.asarray(centre), a, b


def s_bend_cloud(n=3000, seed=0, radius=0.2, noise=5e-4):
    """A tube of the given radius swept along the S curve (t, 0.5 sin(pi t), 0), t in
    0 .. 2, area-uniform with Gaussian noise; also each point's t and angle around it."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.0, 4001)
    centre = np.column_stack([t, 0.5 * np.sin(np.pi * t), np.zeros_like(t)])
    tangent = np.gradient(centre, axis=0)
    step = np.linalg.norm(tangent, axis=1)
    tangent /= step[:, None]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0], np.zeros_like(t)])
    binormal = np.cross(tangent, normal)
    pick, around = rng.choice(len(t), n, p=step / step.sum()), rng.uniform(0, 2 * np.pi, n)
    pts = centre[pick] + radius * (np.cos(around)[:, None] * normal[pick] + np.sin(around)[:, None] * binormal[pick])
    return pts + noise * rng.standard_normal(pts.shape), t[pick], around


def capsule_cloud(n=1500, seed=0, radius=0.4, length=1.2, rotation=None):
    """A cylinder with hemispherical ends, uniform over its area: closed, prolate, no crease."""
    rng = np.random.default_rng(seed)
    side = 2 * np.pi * radius * length
    on_side = rng.uniform(0, side + 4 * np.pi * radius ** 2, n) < side
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = rng.uniform(0, 2 * np.pi, n)
    wall = np.column_stack([radius * np.cos(a), radius * np.sin(a), rng.uniform(-length / 2, length / 2, n)])
    ends = radius * d + np.outer(np.sign(d[:, 2]) * length / 2, [0, 0, 1])
    pts = np.where(on_side[:, None], wall, ends)
    return pts if rotation is None else pts @ rotation.as_matrix().T


def test_parametrise_open_uv_fills_the_unit_square_along_the_field_axes():
    rot = Rotation.from_euler("xyz", [25, -15, 40], degrees=True)
    pts = height_field(seed=0, rotation=rot)
    par = parametrise_open(pts)
    np.testing.assert_allclose(par.uv.min(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(par.uv.max(axis=0), 1.0, atol=1e-12)
    assert par.info["footprint_fill"] == 1.0
    # the footprint's rectangle sides are the square's sides: u, v ~ the field's x, y
    xy = rot.inv().apply(pts)[:, :2]
    corr = np.abs(np.corrcoef(np.column_stack([par.uv, xy]).T)[:2, 2:])
    assert np.sort(corr.max(axis=1)).min() > 0.98
    assert angle_deg(par.info["normal"], rot.apply([0, 0, 1])) < 30.0  # 1 degree: see the test below


@pytest.mark.parametrize("amplitude, seed", [(0.0, 0), (0.0, 1), (0.6, 0), (0.6, 2)])
def test_parametrise_open_recovers_the_height_field_plane(amplitude, seed):
    rot = Rotation.random(random_state=seed)
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1, 1, (600, 2))
    z = amplitude * np.exp(-2.0 * np.sum(xy ** 2, axis=1))
    pts = rot.apply(np.column_stack([xy, z]))
    par = parametrise_open(pts)
    assert angle_deg(par.info["normal"], rot.apply([0, 0, 1])) < 1.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_parametrise_cylinder_recovers_axis_and_radius(seed):
    rng = np.random.default_rng(100 + seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    pts = cylinder_cloud(seed=seed, axis=axis, radius=1.7)
    par = parametrise_cylinder(pts)
    assert angle_deg(par.info["axis"], axis) < 1.0
    assert par.info["radius"] == pytest.approx(1.7, rel=0.01)
    assert par.uv.min() >= 0 and par.uv.max() <= 1
    assert par.info["angular_gap"] < 0.05
    # v is the height along the axis, up to orientation
    h = (pts - pts.mean(axis=0)) @ axis
    assert abs(np.corrcoef(par.uv[:, 1], h)[0, 1]) > 0.9999


@pytest.mark.parametrize("arc", [60, 90, 180, 260])
def test_a_bent_tube_is_parametrised_by_its_angles(arc):
    """An elbow's normals all meet the axis of its torus: u is the angle around the tube,
    v the angle along the arc, its radii and axis those of the torus."""
    rot = Rotation.from_euler("zyx", [25, -40, 70], degrees=True)
    pts, along, around = elbow_cloud(arc=np.radians(arc), seed=arc, rotation=rot)
    par = parametrise_cylinder(pts)
    assert par.info["method"] == "bent tube"
    assert angle_deg(par.info["axis"], rot.apply([0, 0, 1])) < 1.0
    np.testing.assert_allclose(par.info["centre"], [0.4, -0.7, 1.1], atol=0.01)
    assert par.info["major_radius"] == pytest.approx(1.0, rel=0.01)
    assert par.info["radius"] == pytest.approx(0.25, rel=0.01)
    assert par.info["arc"] == pytest.approx(arc / 360.0, abs=0.01)
    assert par.uv.min() >= 0 and par.uv.max() <= 1
    assert abs(np.corrcoef(par.uv[:, 1], along)[0, 1]) > 0.9999
    # u turns with the angle around the tube, one way or the other, from its seam
    turn = np.exp(2j * np.pi * par.uv[:, 0])
    assert max(abs(np.mean(turn * np.exp(1j * around))), abs(np.mean(turn * np.exp(-1j * around)))) > 0.999
    assert unsupported(par, pts, "cylinder") is None


@pytest.mark.parametrize("seed, n", [(0, 3000), (1, 800)])
def test_a_tube_swept_along_an_s_bend_is_parametrised_along_its_centreline(seed, n):
    """No arc carries an S bend: its centreline comes from the sections' centres, ordered
    along the tube; u turns round it, v runs along it."""
    rot = Rotation.from_euler("zyx", [-30, 45, 10], degrees=True)
    pts, along, around = s_bend_cloud(n=n, seed=seed)
    pts = rot.apply(pts)
    par = parametrise_cylinder(pts)
    assert par.info["method"] == "swept tube"
    assert par.info["radius"] == pytest.approx(0.2, rel=0.02)
    assert par.uv.min() >= 0 and par.uv.max() <= 1
    assert abs(np.corrcoef(par.uv[:, 1], along)[0, 1]) > 0.995
    turn = np.exp(2j * np.pi * par.uv[:, 0])
    assert max(abs(np.mean(turn * np.exp(1j * around))), abs(np.mean(turn * np.exp(-1j * around)))) > 0.99
    assert unsupported(par, pts, "cylinder") is None


def test_a_straight_tube_a_ring_and_a_folded_sheet_are_no_bent_tube():
    """The straight cylinder lies closer to a straight tube; a torus's arc closes; a
    profile of revolution that does not go round its section (a vase's) and a sheet
    folded like an S lie far from any torus: each keeps the straight tube's parameters."""
    straight = cylinder_cloud(n=1500, seed=13)
    assert parametrise_cylinder(straight).info["method"] == "cylinder"
    ring = torus_cloud(n=1500, seed=13)
    assert parametrise_bent_tube(ring).info["model_rms"] == np.inf
    rng = np.random.default_rng(13)
    a, h = rng.uniform(0, 2 * np.pi, 1500), rng.uniform(-1, 1, 1500)
    r = 1.0 + 0.3 * np.cos(1.5 * h)
    vase = np.column_stack([r * np.cos(a), r * np.sin(a), h])
    assert parametrise_bent_tube(vase).info["model_rms"] == np.inf
    t, w = rng.uniform(-1, 1, 1500), rng.uniform(0, 2, 1500)
    s_fold = np.column_stack([np.sin(np.pi * t), w, np.sign(t) * (1 - np.cos(np.pi * t))])
    assert parametrise_cylinder(s_fold).info["method"] == "cylinder"


@pytest.mark.filterwarnings("error")
def test_a_plane_or_repeated_points_are_no_tube_and_raise_nothing():
    """Parallel normals meet no line: the bent tube's first start is skipped, not divided by zero."""
    rng = np.random.default_rng(14)
    for pts in (np.column_stack([rng.random((500, 2)), np.zeros(500)]), np.repeat(rng.random((5, 3)), 100, axis=0)):
        par = parametrise_cylinder(pts)
        assert par.info["method"] == "cylinder" and np.isfinite(par.uv).all()


def test_parametrise_sphere_recovers_centre_and_radius():
    pts = sphere_cloud(centre=(0.3, -1.0, 2.0), radius=1.3)
    par = parametrise_sphere(pts)
    np.testing.assert_allclose(par.info["centre"], [0.3, -1.0, 2.0], atol=1e-9)
    assert par.info["radius"] == pytest.approx(1.3, rel=1e-9)
    # v is the polar angle around the axis, from 0 to 1
    axis = np.asarray(par.info["axis"])
    cos_polar = (pts - [0.3, -1.0, 2.0]) @ axis / 1.3
    np.testing.assert_allclose(par.uv[:, 1], np.arccos(-cos_polar) / np.pi, atol=1e-9)
    # the range the data reach, a share STRAY_SHARE of strays aside at each end
    lo, hi = par.info["latitude_range"]
    np.testing.assert_allclose([lo, hi], np.quantile(par.uv[:, 1], [STRAY_SHARE, 1 - STRAY_SHARE]))
    assert lo < 0.1 and hi > 0.9


@pytest.mark.parametrize("stretch, long_axis", [(1.0, None), (1.1, None), (2.5, True), (0.4, False)])
def test_a_closed_clouds_poles_lie_on_its_axis_of_symmetry(stretch, long_axis):
    """A prolate cloud (capsule, egg) has its poles at its ends, an oblate one (a lentil)
    at its flat sides: the PCA axis whose spread stands apart from the other two."""
    rot = Rotation.from_euler("zyx", [20, 40, -30], degrees=True)
    pts = sphere_cloud(n=3000, seed=9, centre=(0, 0, 0), radius=1.0) * [1.0, 1.0, stretch]
    par = parametrise_sphere(rot.apply(pts))
    if long_axis is not None:  # along z: the longest axis of a prolate cloud, the thinnest of an oblate one
        assert angle_deg(par.info["axis"], rot.apply([0, 0, 1])) < 2.0
    assert unsupported(par, rot.apply(pts), "sphere") is None


def test_parametrise_torus_recovers_axis():
    rot = Rotation.from_euler("zyx", [30, 50, -20], degrees=True)
    pts = torus_cloud(rotation=rot)
    par = parametrise_torus(pts)
    assert angle_deg(par.info["axis"], rot.apply([0, 0, 1])) < 1.0
    assert par.info["major_radius"] == pytest.approx(2.0, rel=0.05)
    assert max(par.info["angular_gaps"]) < 0.1


def test_unsupported_rejects_half_cylinder_accepts_full():
    half = cylinder_cloud(arc=np.pi, seed=3)
    full = cylinder_cloud(seed=3)
    reason = unsupported(parametrise_cylinder(half), half, "cylinder")
    assert reason is not None and "no data" in reason
    assert parametrise_cylinder(half).info["angular_gap"] == pytest.approx(0.5, abs=0.02)
    assert unsupported(parametrise_cylinder(full), full, "cylinder") is None


def test_unsupported_sphere_needs_both_poles():
    sph = sphere_cloud(seed=4)
    assert unsupported(parametrise_sphere(sph), sph, "sphere") is None
    cap = sph[(sph - [0.3, -1.0, 2.0])[:, 2] > -0.4]  # the lower part cut away: one pole missing
    assert "poles" in unsupported(parametrise_sphere(cap), cap, "sphere")


def test_a_closed_end_is_no_tube_and_no_ring():
    """A capsule's data reach its axis at both ends: neither a cylinder (two rims) nor a
    torus (a hole through it) can carry it; an open tube's data stay a radius away."""
    pts = capsule_cloud(seed=12)
    for topology, parametrise in (("cylinder", parametrise_cylinder), ("torus", parametrise_torus)):
        assert "axis" in unsupported(parametrise(pts), pts, topology)
    tube = cylinder_cloud(n=1500, seed=12)
    assert unsupported(parametrise_cylinder(tube), tube, "cylinder") is None
    ring = torus_cloud(n=1500, seed=12)
    assert unsupported(parametrise_torus(ring), ring, "torus") is None


def test_a_few_strays_neither_close_a_gap_nor_reach_a_pole():
    # 0.3% stray points (a scan's background) scattered over what the data leave empty
    rng = np.random.default_rng(11)
    half = cylinder_cloud(n=2000, arc=np.pi, seed=3)
    a = rng.uniform(np.pi, 2 * np.pi, 6)
    strays = np.column_stack([1.7 * np.cos(a) + 1.0, 1.7 * np.sin(a) - 2.0, rng.uniform(0.5, 3.5, 6)])
    par = parametrise_cylinder(np.vstack([half, strays]))
    assert par.info["angular_gap"] > 0.4
    assert "no data" in unsupported(par, np.vstack([half, strays]), "cylinder")
    sph = sphere_cloud(n=2000, seed=4)
    cap = sph[(sph - [0.3, -1.0, 2.0])[:, 2] > -0.4]
    far = np.asarray([0.3, -1.0, 2.0]) + 1.3 * np.array([[0.1, 0.0, -1.0], [0.0, 0.1, -1.0], [-0.1, 0.0, -1.0]])
    with_strays = np.vstack([cap, far])
    assert "poles" in unsupported(parametrise_sphere(with_strays), with_strays, "sphere")


@pytest.mark.parametrize("expected, cloud", [
    ("open", lambda: height_field(n=300, seed=5, rotation=Rotation.from_euler("x", 20, degrees=True))),
    ("cylinder", lambda: cylinder_cloud(n=400, seed=6, axis=np.array([0.2, 1.0, 0.3]))),
    ("sphere", lambda: sphere_cloud(n=400, seed=7)),
    ("torus", lambda: torus_cloud(n=500, seed=8, rotation=Rotation.from_euler("y", 35, degrees=True))),
    ("sphere", lambda: capsule_cloud(seed=10, rotation=Rotation.from_euler("xz", [30, 60], degrees=True))),
    ("cylinder", lambda: elbow_cloud(n=800, seed=11, rotation=Rotation.from_euler("xy", [50, 20], degrees=True))[0]),
    ("cylinder", lambda: s_bend_cloud(n=1500, seed=12)[0]),
])
def test_choose_topology(expected, cloud):
    pts = cloud()
    pts = (pts - pts.mean(axis=0)) / np.linalg.norm(np.ptp(pts, axis=0))
    config = config_from_dict({"net_size": [6, 5], "orders": [3, 3]})
    topology, par, scores = choose_topology(pts, np.arange(len(pts)), config)
    assert topology == expected, scores
    assert set(scores) == set(LAYOUTS)
    assert "classical_error_relative" in scores[expected]
    assert par.uv.shape == (len(pts), 2)


def test_a_tube_whose_data_go_all_the_way_round_is_no_open_patch():
    """A handle's data (a bent tube, points all round it) close round: the open patch is
    not tried, its seam would run through them; a slot along the tube wider than the
    data's spacing, or a flat ring (no tube), leaves the open patch a candidate."""
    pts, _, around = elbow_cloud(n=1500, seed=3, arc=0.9 * np.pi)
    assert "close round a tube" in closed_round(parametrise_cylinder(pts), pts)
    for slot, closes in ((0.2, True), (0.8, False)):  # radians of the tube's 0.25 radius: 0.9 and 3.6 spacings
        slotted = pts[np.mod(around, 2 * np.pi) >= slot]
        assert (closed_round(parametrise_cylinder(slotted), slotted) is not None) == closes
    rng = np.random.default_rng(0)
    r, t = np.sqrt(rng.uniform(0.25, 1.0, 1500)), rng.uniform(0, 2 * np.pi, 1500)
    ring = np.column_stack([r * np.cos(t), r * np.sin(t), 1e-3 * rng.standard_normal(1500)])
    assert closed_round(parametrise_cylinder(ring), ring) is None
    pts = (pts - pts.mean(axis=0)) / np.linalg.norm(np.ptp(pts, axis=0))
    topology, _, scores = choose_topology(pts, np.arange(len(pts)), config_from_dict({"net_size": [4, 4]}))
    assert topology == "cylinder"
    assert "close round a tube" in scores["open"]["rejected"] and list(scores) == list(LAYOUTS)


def test_pole_conditions_hold_for_a_tangent_plane_and_fail_for_a_cone_or_a_saddle():
    """At each pole the first ring must be the pole plus an affine image of a circle
    (P[i, 1] = pole + a cos + b sin): any such ring, tilted or elliptic, meets the
    conditions; a pole lifted off its ring (a cone) or a saddle-shaped ring does not."""
    layout = NetLayout((6, 5), (3, 3), (True, False), poles=True)
    rows = layout.pole_tangent_planes().toarray()
    nu, nv = layout.size
    t = 2 * np.pi * np.arange(nu) / nu
    rng = np.random.default_rng(0)
    net = rng.normal(size=(nu, nv, 3))  # the middle rows are free
    for pole, ring in ((0, 1), (nv - 1, nv - 2)):
        centre, a, b = rng.normal(size=(3, 3))
        net[:, pole] = centre
        net[:, ring] = centre + np.cos(t)[:, None] * a + np.sin(t)[:, None] * b
    np.testing.assert_allclose(rows @ net.reshape(-1, 3), 0.0, atol=1e-12)
    cone = net.copy()
    cone[:, 0] += [0.0, 0.0, 1.0]  # the south pole lifted by 1 off its ring's plane
    np.testing.assert_allclose((rows @ cone.reshape(-1, 3))[:nu], np.tile([0.0, 0.0, -1.0], (nu, 1)), atol=1e-12)
    saddle = net.copy()
    saddle[:, nv - 2, 2] += np.cos(2 * t)  # the north ring bent up and down twice
    assert np.abs(rows @ saddle.reshape(-1, 3))[nu:, 2].max() > 0.5


def test_only_the_sphere_layout_has_conditions():
    assert layout_for("sphere", (6, 5), (3, 3)).constraint_operator().shape == (12, 6 * 3 + 2)
    for name in ("open", "cylinder", "torus"):
        assert layout_for(name, (6, 5), (3, 3)).constraint_operator() is None


def test_the_note_says_which_topology_was_kept_when_every_candidate_failed():
    """``topology: auto`` keeps the least error when every candidate is suspect: the note
    calls that one kept, not rejected, and the others rejected with their reasons."""
    all_suspect = {"open": {"classical_error_relative": 2.35e-3, "rejected": "suspect: the net reaches 14 times"},
                   "cylinder": {"classical_error_relative": 3.1e-3, "rejected": "suspect: it folds"},
                   "sphere": {"rejected": "the data do not reach both poles"}}
    note = topology_note("open", all_suspect)
    assert note.startswith("topology auto: open (open 2.35e-03, kept as the least error: every candidate failed")
    assert "open rejected" not in note and "(its own: the net reaches 14 times)" in note
    assert "cylinder rejected: suspect: it folds" in note and "sphere rejected: the data do not reach both poles" in note
    fine = {"open": {"classical_error_relative": 1e-3}, "torus": {"classical_error_relative": 4e-3,
                                                                  "rejected": "suspect: it flaps"}}
    assert topology_note("open", fine) == "topology auto: open (open 1.00e-03, torus rejected: suspect: it flaps)"
