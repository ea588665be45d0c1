"""First parameters of an open patch: a plane projection where the cloud is a proper
height field over the plane, the intrinsic embedding otherwise (``parametrisation``).

``plane`` is :func:`psonurbs.fitting.parameters.plane.parametrise_open` (the plane the surface
faces most squarely), ``intrinsic`` is :func:`psonurbs.fitting.parameters.intrinsic.parametrise_intrinsic`
(the cloud's own graph laid flat). ``auto`` keeps the plane unless one of three things
shows that the projection misrepresents the surface:

* **edge-on or folded**: with ``n`` the local normals and ``d`` the plane's normal, the
  share of the surface's area where ``|n . d| < cos 80 deg`` is above ``EDGE_ON_SHARE``.
  Where a surface folds over the plane its normal passes edge-on; where it turns
  vertical (a shell's sides) the projection squeezes it more than 5.8 times. The share
  is of area (each point weighted by the square of its neighbourhood radius), so
  uneven sampling does not hide a sparse steep part; ``|n . d|`` needs no orientation,
  so a stray's wrong normal counts only as itself.
* **stacked**: the share of the surface's area that the projection lays over another
  part of it is above ``EDGE_ON_SHARE`` (:func:`stacked_share`): a point whose nearest
  neighbours in the projection include one farther off in space than twice its own
  neighbourhood's radius and than a surface steeper than 80 degrees would put it. A
  surface winding round an axis (a helicoid, a spiral ramp) is never edge-on and its
  projection fills the square, but the plane stacks its turns.
* **the footprint fills less**: the flattening, scaled along its rectangle, occupies at
  least ``FILL_MARGIN`` more of the cells of the unit square than the projection (a
  twisted strip projects onto a bow tie: the square's corners would be extrapolated).
  Little is enough: a strip twisted by 90 degrees leaves 5% of the square empty, and its
  fit over the plane is 25 times farther from the true surface than over the intrinsic
  parameters. The rectangle is judged, not the four-sided map the intrinsic parameters
  may take instead (:mod:`psonurbs.fitting.parameters.four_sided`): that fills the square
  by construction, and would take a height field over a trapezoid or an annular sector
  from the plane (a 220-degree cone section over its axis plane: twice the plane's rmse).

A surface flat over the plane (95% of its normals within 15 degrees of the plane's,
:func:`psonurbs.fitting.parameters.plane.facing`) is the plane's, whatever the fills: its projection shortens no
distance by more than 3.4%, so it already is the flattening, while an embedding of its
graph bends where the footprint is not convex (geodesics round an L's inner corner) and
may fill a turned rectangle better for that alone (a flat L: 52% against 58%, and a
surface flapping 3.5 times the cloud's size over the empty quarter).

A height field over a rectangle, steep flanks and all, projects onto exactly its
rectangle, which the unrolled surface (whose boundary curves where the surface
climbs) never fills better; a plate over an ellipse fills both alike. Ties go to
the plane, whose parameters of a height field need no correction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.geometry import compiled

from .intrinsic import embedding_sample, intrinsic_parameters, parametrise_intrinsic, surface_graph
from .parametrisation import FILL_MARGIN, FLAT, Parametrisation, fill, fill_cells
from .plane import parametrise_open

METHODS = ("auto", "plane", "intrinsic")
EDGE_ON = float(np.cos(np.radians(80.0)))  # |n . d| below this: seen edge-on, squeezed over 5.8 times
EDGE_ON_SHARE = 0.05  # of the surface's area that may be seen edge-on or stacked (noise, strays, a rim)
STACK_NEIGHBOURS = 6  # a point's nearest neighbours in the projection that may lie on another sheet
STACK_REACH = 2.0  # another sheet lies farther than this many neighbourhood radii (junk a few sigmas off, nearer)


@dataclass(frozen=True)
class OpenChoice:
    """The evidence behind ``auto``: how much of the surface the plane sees edge-on or
    stacks on another part of it, and how much of the unit square each parametrisation
    fills."""

    edge_on_share: float
    fill_plane: float
    fill_intrinsic: float
    method: str
    reason: str
    stacked_share: float = 0.0

    def to_dict(self) -> dict:
        return {"edge_on_share": self.edge_on_share, "stacked_share": self.stacked_share,
                "fill_plane": self.fill_plane, "fill_intrinsic": self.fill_intrinsic, "reason": self.reason}


def edge_on_share(normals: np.ndarray, areas: np.ndarray, direction: np.ndarray) -> float:
    """Share of the area (``areas`` per point) whose normal is within 10 degrees of
    perpendicular to ``direction``."""
    return float(np.sum(areas[np.abs(normals @ direction) < EDGE_ON]) / np.sum(areas))


def stacked_share(points: np.ndarray, reach: np.ndarray, areas: np.ndarray, direction: np.ndarray,
                  neighbours: int = STACK_NEIGHBOURS) -> float:
    """Share of the area (``areas`` per point of ``points`` (M, 3)) that the projection
    along ``direction`` lays over another part of the surface: a point with one of its
    nearest neighbours in the projection farther off in space than both ``STACK_REACH``
    times its own neighbourhood's radius ``reach`` (M,) and 1 / cos 80 degrees times their
    distance in the projection (steeper than the edge-on test's surface: a sheet above or
    below, not a point of junk a few noise sigmas off it).

    A surface that winds round an axis (a helicoid, a spiral ramp) is never seen edge-on
    and its projection fills the square, yet the plane stacks its turns on each other."""
    direction = direction / np.linalg.norm(direction)
    flat = points - np.outer(points @ direction, direction)
    k = min(neighbours, len(points) - 1)
    planar, near = cKDTree(flat).query(flat, k=k + 1)
    spatial = np.linalg.norm(points[near[:, 1:]] - points[:, None, :], axis=2)
    stacked = np.any(spatial > np.maximum(planar[:, 1:] / EDGE_ON, STACK_REACH * reach[:, None]), axis=1)
    return float(np.sum(areas[stacked]) / np.sum(areas))


def choose(edge_on: float, fill_plane: float, fill_intrinsic: float, stacked: float = 0.0,
           flat: bool = False) -> OpenChoice:
    """``flat``: the surface faces the plane within 15 degrees nearly everywhere (the
    plane's ``facing``, at least :data:`FLAT`)."""
    def chosen(method: str, reason: str) -> OpenChoice:
        return OpenChoice(edge_on, fill_plane, fill_intrinsic, method, reason, stacked)

    if edge_on > EDGE_ON_SHARE:
        return chosen("intrinsic", f"{edge_on:.0%} of the surface is seen edge-on from the plane (folds or turns "
                      "vertical)")
    if stacked > EDGE_ON_SHARE:
        return chosen("intrinsic", f"the plane lays {stacked:.0%} of the surface over another part of it")
    if flat:
        return chosen("plane", "flat over the plane: the projection is its own flattening")
    if fill_intrinsic >= fill_plane + FILL_MARGIN:
        return chosen("intrinsic", f"the projection fills {fill_plane:.0%} of the parameter square, "
                      f"the intrinsic parameters {fill_intrinsic:.0%}")
    return chosen("plane", "a height field over the plane")


def parametrise_open_patch(points: np.ndarray, method: str = "auto") -> Parametrisation:
    """First (u, v) in [0, 1]^2 of an open patch by ``method`` (auto | plane | intrinsic);
    ``info["method"]`` says which was used and, for auto, ``info["choice"]`` why."""
    if method == "plane":
        return parametrise_open(points)
    sample = embedding_sample(len(points))
    graph = surface_graph(points[sample])
    if method == "intrinsic":
        return parametrise_intrinsic(points, graph)
    # the two candidates are independent: side by side in threads
    intrinsic, plane = compiled.in_order(lambda candidate: candidate(),
                                         [lambda: intrinsic_parameters(points, graph), lambda: parametrise_open(points)])
    areas = graph.lengths[:, -1] ** 2  # ~ the surface area each point stands for
    part = graph.component
    cells = fill_cells(len(sample))
    normal = np.asarray(plane.info["normal"])
    choice = choose(edge_on_share(graph.normals[part], areas[part], normal),
                    fill(plane.uv[sample], cells), fill(intrinsic.rectangle[sample], cells),
                    stacked_share(graph.points[part], graph.lengths[part, -1], areas[part], normal),
                    plane.info["facing"] >= FLAT)
    chosen = intrinsic.par if choice.method == "intrinsic" else plane
    return Parametrisation(chosen.uv, {**chosen.info, "choice": choice.to_dict()})
