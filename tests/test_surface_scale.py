"""Normals at the scale where a cloud is a surface (psonurbs.fitting.prepare.surface_scale),
and what they decide: a thick cloud's plane and its first parameters."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from psonurbs.fitting.parameters.intrinsic import surface_graph
from psonurbs.fitting.parameters.open_patch import parametrise_open_patch
from psonurbs.fitting.prepare.surface_scale import THIN, normals_and_variation, surface_scale


def cap(n=4000, polar_degrees=60.0, noise=0.0, seed=0):
    """Area-uniform points of a unit sphere's cap about +z, with normal noise, and the
    true normals."""
    rng = np.random.default_rng(seed)
    z = 1.0 - rng.random(n) * (1.0 - np.cos(np.radians(polar_degrees)))
    phi = 2 * np.pi * rng.random(n)
    r = np.sqrt(1.0 - z * z)
    true = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return true + rng.normal(0.0, noise, (n, 3)), true


def spacing(points):
    return float(np.median(cKDTree(points).query(points, 2)[0][:, 1]))


def angles(normals, true):
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(normals * true, axis=1)), 0.0, 1.0)))


def test_a_thin_cloud_keeps_the_neighbourhoods_it_asked_for():
    points, true = cap(noise=0.002)
    scale = surface_scale(points, 12)
    assert not scale.widened and scale.neighbours == 12 and scale.thickness <= THIN
    plain = normals_and_variation(points, cKDTree(points).query(points, 12)[1])[0]
    assert np.array_equal(scale.normals, plain)
    assert np.median(angles(scale.normals, true)) < 3.0


@pytest.mark.parametrize("noise", [0.03, 0.06])
def test_a_cloud_as_thick_as_its_spacing_is_seen_at_a_wider_scale(noise):
    points, true = cap(noise=noise)
    assert noise > spacing(points)  # thicker than the points are apart
    near = normals_and_variation(points, cKDTree(points).query(points, 12)[1])[0]
    scale = surface_scale(points, 12)
    assert scale.widened and scale.neighbours > 12
    assert np.median(angles(near, true)) > 25.0  # a dozen neighbours: a blob, its normal noise
    assert np.median(angles(scale.normals, true)) < 8.0
    assert np.percentile(angles(scale.normals, true), 95) < 20.0


def test_a_thick_cap_is_a_height_field_over_its_axis_plane():
    """A dozen neighbours' normals of a cloud as thick as its spacing scatter past 80
    degrees from the axis: the cap read as folded (edge-on) and was laid flat instead."""
    points, _ = cap(noise=0.03)
    par = parametrise_open_patch(points)
    assert par.info["method"] == "plane"
    assert abs(par.info["normal"][2]) > np.cos(np.radians(2.0))
    assert par.info["choice"]["edge_on_share"] < 0.01


def test_a_thick_hemisphere_is_laid_flat_from_its_surface_not_its_noise():
    points, true = cap(polar_degrees=90.0, noise=0.03)
    graph = surface_graph(points)
    assert graph.thinned_over > 10
    assert np.median(angles(graph.normals, true)) < 5.0
    # the moved points lie on a sphere (a little inside: each plane is a chord) far
    # thinner than the noise
    assert np.std(np.linalg.norm(graph.points, axis=1)) < 0.3 * 0.03
    par = parametrise_open_patch(points)
    assert par.info["method"] == "intrinsic" and par.info["folded_share"] < 0.002
