"""The local test of gross outliers (psonurbs.fitting.prepare.outliers): normal noise is never an
outlier (nor the thin edge of a graded cloud, nor structured sampling), junk in the
bounding box and a floating blob are, and a separate piece is not chained to the surface."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import franke_z

from psonurbs.fitting.prepare.outliers import (
    MIN_POINTS,
    NEIGHBOURS,
    Neighbourhoods,
    local_outliers,
    nearest_among,
    shared_neighbours,
    spatial_order,
)


def normalised(points: np.ndarray) -> np.ndarray:
    return (points - points.mean(axis=0)) / np.linalg.norm(points.max(axis=0) - points.min(axis=0))


def franke_cloud(n, seed, noise, u=None):
    """Franke's surface over [0, 1]^2, normal noise ``noise`` (a share of the diagonal) in
    every coordinate; and the cloud's diagonal and random generator."""
    rng = np.random.default_rng(seed)
    x = rng.random(n) if u is None else u(rng, n)
    y = rng.random(n)
    pts = np.column_stack([x, y, franke_z(x, y)])
    diag = np.linalg.norm(pts.max(0) - pts.min(0))
    pts += rng.normal(0.0, noise * diag, (n, 3))
    return pts, diag, rng


def test_normal_noise_is_never_an_outlier_and_its_scale_is_measured():
    # 20,000 points of a curved surface, noise 1e-3 of the diagonal: the quadric takes the
    # curvature, the studentised residual is normal (measured: max 4.1 robust sigmas)
    pts, _, _ = franke_cloud(20_000, 0, 1e-3)
    verdict = local_outliers(normalised(pts))
    assert not verdict.outliers.any()
    assert verdict.statistic.max() < 6.0
    assert verdict.noise == pytest.approx(1e-3, rel=0.05)


def test_the_verdict_is_the_same_in_any_number_of_threads(monkeypatch):
    # 20,000 points with junk: three chunks of neighbourhood fits, the KD-tree's queries
    # and the chunks shared among threads; every array the same bits
    pts, _, rng = franke_cloud(20_000, 4, 1e-3)
    cloud = normalised(np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (300, 3))]))
    verdicts = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("PSONURBS_THREADS", threads)
        verdicts.append(local_outliers(cloud))
    for other in verdicts[1:]:
        for name in ("outliers", "statistic", "support", "neighbours", "agree", "order"):
            np.testing.assert_array_equal(getattr(other, name), getattr(verdicts[0], name))
        assert other.noise == verdicts[0].noise
    assert verdicts[0].outliers.sum() > 100


def test_junk_in_the_bounding_box_is_caught_and_no_surface_point():
    pts, diag, rng = franke_cloud(4500, 1, 1e-3)
    junk = rng.uniform(pts.min(0), pts.max(0), (500, 3))
    verdict = local_outliers(normalised(np.vstack([pts, junk])))
    assert not verdict.outliers[:4500].any()
    # far junk: over 0.1 of the diagonal above or below the surface (over 40 sigmas along its normal)
    far = np.abs(junk[:, 2] - franke_z(junk[:, 0], junk[:, 1])) > 0.1 * diag
    # measured: 97% (the rest: junk beside an edge of the data, in the surface's continuation,
    # which no local test can tell from surface; the robust loss judges it)
    assert far.sum() > 300
    assert verdict.outliers[4500:][far].mean() >= 0.95


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_the_thin_edge_of_a_graded_cloud_is_no_outlier(noise):
    # density rising from 0 at x = 0 (the thin edge, neighbourhoods ten times wider)
    pts, _, _ = franke_cloud(8000, 2, noise, u=lambda rng, n: np.sqrt(rng.random(n)))
    verdict = local_outliers(normalised(pts))
    assert not verdict.outliers.any()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_lone_point_beyond_a_gap_is_judged_with_its_neighbours_but_neither_vouched_for_nor_spared(seed):
    # the surface's own corner beyond a gap of about six spacings: the corner point's
    # neighbours are the data's corner, whose own neighbourhoods (denser) do not reach back
    # to it, so it links to none; it joins their piece (the loss judges it against where
    # they lie), but it lies beyond every neighbourhood of theirs, where junk past an edge
    # lies too (on their quadric's continuation, as consistent as any point): nothing
    # vouches for it and the loss does not spare it
    rng = np.random.default_rng(seed)
    x, y = 0.06 + 0.94 * rng.random((2, 5000))
    x, y = np.r_[x, 0.0], np.r_[y, 0.0]
    pts = np.column_stack([x, y, franke_z(x, y)])
    pts += rng.normal(0, 1e-3 * np.linalg.norm(pts.max(0) - pts.min(0)), pts.shape)
    verdict = local_outliers(normalised(pts))
    pieces = verdict.neighbourhoods()
    assert not verdict.outliers.any() and verdict.support[-1]
    assert pieces.on_main_piece.all() and pieces.vouched[:-1].all() and not pieces.vouched[-1]
    assert not pieces.spared[-1] and not verdict.reached[-1].any()
    assert (pieces.index[-1] >= 0).sum() == pieces.index.shape[1]  # its neighbours count for it


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_strays_on_the_surface_past_an_edge_are_not_vouched_for(seed):
    # Franke's surface on x < 0.8 and twelve strays on its continuation 5 to 10 spacings
    # past that edge (off it by a noise sigma): their neighbours' quadric, extrapolated,
    # passes through them within its growing uncertainty, so the quadric test cannot tell
    # them from the edge; but no neighbourhood of the data reaches out to them (k = 24
    # neighbours reach about 4 spacings past an edge: a stray within that is as much
    # data as the edge's last points). Every point of the data is vouched for, none of
    # the strays is, nor spared by the loss.
    rng = np.random.default_rng(seed)
    n, spacing = 5000, np.sqrt(0.8 / 5000)
    x, y = 0.8 * rng.random(n), rng.random(n)
    x = np.r_[x, 0.8 + rng.uniform(5, 10, 12) * spacing]
    y = np.r_[y, rng.random(12)]
    pts = np.column_stack([x, y, franke_z(x, y)])
    pts += rng.normal(0, 1e-3 * np.linalg.norm(pts.max(0) - pts.min(0)), pts.shape)
    verdict = local_outliers(normalised(pts))
    pieces = verdict.neighbourhoods()
    kept = verdict.inliers
    data, strays = kept[:n], kept[n:]
    assert data.all()
    assert pieces.vouched[:n].all()
    assert not pieces.spared[data.sum():].any() and strays.sum() >= 6


def test_structured_sampling_is_no_outlier():
    # a latitude-longitude grid on a sphere (rings of one latitude lie on a plane: a
    # robust fit must not settle on one ring) and a terrain along scan lines
    u, v = np.meshgrid(np.arange(32) / 32, (np.arange(24) + 0.5) / 24, indexing="ij")
    th, ph = 2 * np.pi * u.ravel(), np.pi * v.ravel()
    sphere = np.column_stack([np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)])
    x, y = np.meshgrid(np.linspace(0, 1, 50), np.linspace(0, 1, 120), indexing="ij")
    terrain = np.column_stack([x.ravel(), y.ravel(), 0.15 * np.sin(2 * x.ravel() + 1) * np.cos(1.5 * y.ravel())])
    for pts in (sphere, terrain):
        assert not local_outliers(normalised(pts)).outliers.any()


def test_a_floating_blob_is_caught():
    # 5% of the points in a ball 0.1 over the surface: the blob's own neighbourhoods are
    # no surface (thick), so it is judged against the surface under it
    pts, diag, rng = franke_cloud(4750, 3, 1e-3)
    d = rng.normal(size=(250, 3))
    d *= (0.03 * diag * rng.random(250) ** (1 / 3) / np.linalg.norm(d, axis=1))[:, None]
    blob = np.array([0.5, 0.5, franke_z(0.5, 0.5) + 0.1 * diag]) + d
    verdict = local_outliers(normalised(np.vstack([pts, blob])))
    assert verdict.outliers[4750:].all() and not verdict.outliers[:4750].any()


def test_a_separate_flat_piece_is_an_inlier_but_not_on_the_main_piece():
    # a flat square of another object 0.1 over the surface: locally consistent (the robust
    # loss must judge it), but not chained to the surface through agreeing neighbourhoods
    pts, diag, rng = franke_cloud(4750, 4, 1e-3)
    a, b = rng.uniform(-0.05, 0.05, (2, 250)) * diag
    centre = np.array([0.5, 0.5, franke_z(0.5, 0.5) + 0.1 * diag])
    piece = centre + np.column_stack([a, b, 0.3 * a]) + rng.normal(0, 1e-3 * diag, (250, 3))
    verdict = local_outliers(normalised(np.vstack([pts, piece])))
    assert not verdict.outliers.any()
    pieces = verdict.neighbourhoods()
    # measured: 10 surface points under the piece's lowest corner, 0.025 below it, vote with
    # it (their neighbourhoods mix both); no piece point is on the main piece
    assert pieces.on_main_piece[:4750].mean() > 0.99 and not pieces.on_main_piece[4750:].any()
    # a point's neighbours are on its piece only; off the main piece, there are none
    assert (pieces.index[4750:] == -1).all() and (pieces.index[:4750].max(axis=1) < 4750).all()


def test_a_small_cloud_is_not_judged():
    pts, _, _ = franke_cloud(MIN_POINTS - 1, 5, 1e-3)
    pts[0, 2] += 1.0
    verdict = local_outliers(normalised(pts))
    assert not verdict.outliers.any() and verdict.neighbourhoods() is None


def test_neighbourhood_median_skips_missing_neighbours():
    rng = np.random.default_rng(1)
    index = rng.integers(-1, 40, (40, 7))
    index[0] = -1
    values = rng.random(40)
    expected = [np.median(values[r[r >= 0]]) if (r >= 0).any() else 0.0 for r in index]
    np.testing.assert_allclose(Neighbourhoods(index, np.ones(40, bool), np.ones(40, bool)).median(values), expected)


@pytest.mark.parametrize("grid", [False, True], ids=["scattered", "grid"])
def test_every_point_is_judged_against_its_nearest_support_points(grid):
    """The second pass searches only where a neighbour is no support point (every point
    when distances are tied, as on a grid): the neighbours it judges with are still each
    point's nearest support points, as a search of every point finds them."""
    rng = np.random.default_rng(3)
    if grid:
        g = np.linspace(0.0, 1.0, 60)
        x, y = (a.ravel() for a in np.meshgrid(g, g))
    else:
        x, y = rng.random((2, 3600))
    pts = np.column_stack([x, y, 0.2 * np.sin(3 * x) * y])
    pts[:150] = rng.uniform(pts.min(0), pts.max(0) + [0, 0, 0.5], (150, 3))  # junk
    pts = normalised(pts)
    verdict = local_outliers(pts)
    assert verdict.outliers[:150].sum() > 100 and not verdict.support.all()
    np.testing.assert_array_equal(verdict.neighbours, nearest_among(pts, verdict.support, NEIGHBOURS).index)
    # the points taken in a spatial order: the same neighbours
    order = spatial_order(pts)
    np.testing.assert_array_equal(nearest_among(pts, verdict.support, NEIGHBOURS, order).index,
                                  verdict.neighbours[order])


def test_shared_neighbours_are_counted_as_sets_intersect():
    rng = np.random.default_rng(4)
    n, k = 300, 6
    index = np.array([rng.choice(np.delete(np.arange(n), i), k, replace=False) for i in range(n)])
    index[rng.random((n, k)) < 0.2] = -1  # missing neighbours
    sets = [set(row[row >= 0]) for row in index]
    expected = np.array([[len(sets[i] & sets[j]) if j >= 0 else 0 for j in row] for i, row in enumerate(index)])
    np.testing.assert_array_equal(shared_neighbours(index), expected)
    np.testing.assert_array_equal(shared_neighbours(index, rng.permutation(n)), expected)
