"""Faces made to meet: extended past their data, cut where they cross, the pieces the
data hold kept and sewn into one shell (a solid where it closes), through OpenCASCADE.

1. **Extend** (:func:`extended_face`): each face's open directions grow by ``EXTEND``
   of the object's diagonal (at least ``EXTEND_SPACINGS`` point spacings) in space, its
   end spans' polynomials continued (:meth:`NurbsSurface.restricted`, exact), so that
   two faces whose data stop a crease's band short of each other cross.
   An open face (no closed direction) is then bounded to where it lies within
   ``BOUND`` reaches of its own data (:func:`within_reach`): free corners the data
   never held (a narrow band's patch, its corners flung far out) are no part of any
   face, while every crossing with a neighbour (a crease's band from the data, within
   the one reach the extension gives) stays well inside.
2. **Cut** (OpenCASCADE's general fuse, ``BOPAlgo_Builder``): every face split along its
   intersections with the others; closed directions go in as periodic B-splines.
3. **Keep** (:func:`held_pieces`): each point is given to the piece nearest it (exact
   distances to the trimmed pieces); a piece is kept when it holds points at
   least ``HELD_DENSITY`` of the density of the pieces holding most of them, and at
   least half the share of the cloud a region needs (a sliver holding a few points is
   no face), or when that many of them lie within the tolerance of it (a narrow face's
   area is mostly its extension). The parts of an extension past a crease, and of a
   face inside the solid, hold none.
4. **Sew** (``BRepBuilderAPI_Sewing`` at the tolerance): the kept pieces already share
   their cut edges; a shell with no free edge is made a solid (oriented outward).
5. **Trims**: each kept piece's wires read back in its surface's (u, v) as loops
   (outer counter-clockwise, holes clockwise), the JSON's trims of that face.

OCP is imported only here, when an object is joined.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psonurbs.fitting.finish.footprint import EDGE_OUTSET
from psonurbs.formats.step import occ_face, occ_surface, sew
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import Trim, distances_to_face, polygon_loop, signed_area

from .regions import MIN_SHARE

EXTEND = 0.05  # of the object's diagonal: how far a face reaches past its data
EXTEND_SPACINGS = 8.0  # ... and at least this many point spacings
HELD_DENSITY = 0.25  # a piece is kept when its points per area reach this share of the faces'
EDGE_SAMPLES = 48  # points per edge of a trim loop read back from OpenCASCADE
POLE = 1e-9  # an end's edge shorter than this many reaches is a point
FLARE = 3.0  # an extended end's edge lies at most this many reaches from where the surface ended
BOUND = 2.0  # an open face is bounded to within this many reaches of its data
REACH_CELLS = 96  # the (u, v) grid on which an open face's bound is traced


@dataclass(frozen=True)
class JoinedFace:
    """One face of the shell: the (extended) surface of region ``region`` and its loops."""

    region: int
    surface: NurbsSurface
    trim: Trim
    area: float
    points: int  # points nearest this face


@dataclass(frozen=True)
class Joined:
    """The sewn shell: its faces, whether it closed (no free edge) into a valid solid,
    its volume (None when open), how many free edges it has and its widest gap between
    two faces' edges (the largest edge tolerance the sewing needed)."""

    faces: list[JoinedFace]
    closed: bool
    valid: bool
    volume: float | None
    free_edges: int
    gap: float
    distances: np.ndarray = field(repr=False, default=None)  # (faces, N): each point's to each face
    shape: object = field(repr=False, default=None)  # the TopoDS shape (solid or shell)

    def to_dict(self) -> dict:
        return {"faces": len(self.faces), "closed": self.closed, "valid": self.valid,
                "volume": self.volume, "free_edges": self.free_edges, "gap": self.gap}


def extended_face(surface: NurbsSurface, reach: float) -> NurbsSurface:
    """The surface with each open direction extended by ``reach`` in space at both ends
    (in parameters: reach over the mean speed along that end's edge), but not past a pole
    (an end whose edge is one point, a sphere's: past it the surface would open a ring
    round the pole, an edge no other face meets), halved until its
    weights stay positive and no point of an end's new edge lies farther than
    ``FLARE`` reaches from the old one: the end span's polynomial, continued over many
    of its own lengths (a dense net's short end span), flares far past where it was sent."""
    ranges = []
    for k, closed in enumerate((surface.closed_u, surface.closed_v)):
        if closed:
            ranges.append((0.0, 1.0))
            continue
        t = np.linspace(0.0, 1.0, 25)
        ends = []
        for edge in (0.0, 1.0):
            u, v = (np.full_like(t, edge), t) if k == 0 else (t, np.full_like(t, edge))
            if np.ptp(surface.evaluate(u, v), axis=0).max() <= POLE * reach:  # a pole: no edge to go past
                ends.append(0.0)
                continue
            speed = np.linalg.norm(surface.derivatives(u, v)[1 + k], axis=1).mean()
            ends.append(reach / max(speed, 1e-12))
        ranges.append((-ends[0], 1.0 + ends[1]))
    across = np.linspace(0.0, 1.0, 49)
    for _ in range(6):
        try:
            grown = surface.restricted(*ranges)
        except ValueError:  # the weights' extrapolation turned negative: reach less far
            ranges = [(0.5 * a, 1.0 + 0.5 * (b - 1.0)) for a, b in ranges]
            continue
        flaring = _flaring(grown, ranges, across, FLARE * reach)
        if not any(flaring):
            return grown
        ranges = [(0.5 * a if flaring[2 * k] else a, 1.0 + 0.5 * (b - 1.0) if flaring[2 * k + 1] else b)
                  for k, (a, b) in enumerate(ranges)]
    return surface


def _flaring(grown: NurbsSurface, ranges, t: np.ndarray, most: float) -> list[bool]:
    """For each end (u = 0, u = 1, v = 0, v = 1) of the grown surface, whether its edge
    lies farther than ``most`` from where the surface ended (their points at the same
    parameter across, ``t`` (M,) of them)."""
    out = []
    for k, (lo, hi) in enumerate(ranges):
        for new, old in ((0.0, -lo / (hi - lo)), (1.0, (1.0 - lo) / (hi - lo))):
            if abs(new - old) < 1e-12:
                out.append(False)
                continue
            ends = [grown.evaluate(*((np.full_like(t, x), t) if k == 0 else (t, np.full_like(t, x))))
                    for x in (new, old)]
            out.append(bool(np.max(np.linalg.norm(ends[0] - ends[1], axis=1)) > most))
    return out


def within_reach(surface: NurbsSurface, data: np.ndarray, reach: float, cells: int = REACH_CELLS) -> Trim | None:
    """The part of an open surface within ``reach`` of its data (M, 3) as one outer loop
    in its (u, v): the contour at ``reach`` of d(u, v), the distance from the surface's
    point at (u, v) to the nearest datum, traced on a (cells + 1)^2 grid (the domain's
    edge counted as beyond reach, so the loop closes along it), the largest loop only
    (holes and islands left to the cut). None when no sample lies beyond reach (the
    whole surface is kept) or the surface closes in a direction."""
    from scipy.spatial import cKDTree

    from psonurbs.geometry.contour import contours, simplify_closed

    if surface.closed_u or surface.closed_v or len(data) == 0:
        return None
    t = np.linspace(0.0, 1.0, cells + 1)
    d = cKDTree(data).query(surface.evaluate_grid(t, t).reshape(-1, 3))[0].reshape(len(t), len(t))
    if d.max() <= reach:
        return None
    beyond = 2.0 * float(d.max()) + reach  # the border: outside, the loop runs along the domain's edge
    field = np.pad(d, 1, constant_values=beyond)
    edge = np.concatenate([[-1e-9], t, [1.0 + 1e-9]])
    loops = [np.clip(loop, 0.0, 1.0) for loop in contours(field, edge, edge, reach)]
    loops = [loop for loop in loops if len(loop) >= 3]
    if not loops:
        return None
    outer = max(loops, key=lambda loop: abs(signed_area(loop)))
    outer = simplify_closed(outer, 0.25 / cells)
    if signed_area(outer) < 0:
        outer = outer[::-1]
    return Trim((polygon_loop(outer),))


def _count(shape, kind) -> int:
    """How many sub-shapes of a kind the shape holds (a seam edge counted twice)."""
    from OCP.TopExp import TopExp_Explorer

    n, explorer = 0, TopExp_Explorer(shape, kind)
    while explorer.More():
        n += 1
        explorer.Next()
    return n


def face_distances(faces: list[tuple[NurbsSurface, Trim | None]], points: np.ndarray) -> np.ndarray:
    """Distances (F, N) of the points (N, 3) to each face (surface, its loops or None):
    exact, to the trimmed face (:func:`psonurbs.geometry.trim.distances_to_face`); the
    foot points found once per surface, whatever the number of its faces."""
    distances, feet = np.empty((len(faces), len(points))), {}
    for k, (surface, trim) in enumerate(faces):
        if id(surface) not in feet:
            feet[id(surface)] = closest_parameters(surface, points)
        uv, d = feet[id(surface)]
        distances[k] = d if trim is None else distances_to_face(surface, trim, points, uv, d)
    return distances


def held_pieces(distances: np.ndarray, areas: np.ndarray, points: int, tolerance: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Which pieces the data hold, from the points' distances (F, N) to the pieces and
    the pieces' areas (F,), and each one's count of points: each point counts for the
    piece nearest it. A piece is held by its points' density (against the pieces holding
    most of them), or by the points it fits: as many within ``tolerance`` of it as a
    piece needs. A narrow face (a bottle's shoulder, a band between two creases) reads
    sparse by area, its extension past the data being most of it, though every point
    nearest it lies on it."""
    nearest = np.argmin(distances, axis=0)
    counts = np.bincount(nearest, minlength=len(areas))
    on = distances[nearest, np.arange(distances.shape[1])] <= tolerance  # (N,): within it of its piece
    fitted = np.bincount(nearest[on], minlength=len(areas))
    density = counts / np.maximum(np.abs(areas), 1e-300)  # a reversed face's area reads negative
    main = counts >= 0.05 * points
    reference = np.median(density[main]) if main.any() else density.max()
    enough = 0.5 * MIN_SHARE * points
    return ((density >= HELD_DENSITY * reference) & (counts >= enough)) | (fitted >= enough), counts


def _loops(face, surface: NurbsSurface) -> Trim | None:
    """The face's wires as loops in (u, v): each edge's curve on the surface sampled
    along the wire's order, the outer loop counter-clockwise and holes clockwise; a
    closed direction's seam pushed ``EDGE_OUTSET`` past the domain's edge. An internal
    edge (a section that ends inside the piece: two faces' cut running on past a corner)
    bounds nothing and is no loop. None when no outer loop is left (a degenerate piece)."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve2d
    from OCP.BRepTools import BRepTools
    from OCP.TopAbs import TopAbs_FORWARD, TopAbs_REVERSED, TopAbs_WIRE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    outer = BRepTools.OuterWire_s(face)
    loops = []
    explorer = TopExp_Explorer(face, TopAbs_WIRE)
    while explorer.More():
        wire = TopoDS.Wire(explorer.Current())
        polygon = []
        for edge in _edges_in_order(wire, face):
            if edge.Orientation() not in (TopAbs_FORWARD, TopAbs_REVERSED):  # internal: inside the piece
                continue
            curve = BRepAdaptor_Curve2d(edge, face)
            t = np.linspace(curve.FirstParameter(), curve.LastParameter(), EDGE_SAMPLES)
            if edge.Orientation() == TopAbs_REVERSED:
                t = t[::-1]
            polygon += [(lambda q: (q.X(), q.Y()))(curve.Value(float(s))) for s in t[:-1]]
        explorer.Next()
        if len(polygon) < 3:  # a degenerate wire (a seam's sliver): no loop
            continue
        p = np.array(polygon)
        for k, closed in enumerate((surface.closed_u, surface.closed_v)):
            if closed:
                p[:, k] = np.where(p[:, k] <= 1e-9, -EDGE_OUTSET, np.where(p[:, k] >= 1 - 1e-9, 1 + EDGE_OUTSET, p[:, k]))
        is_outer = wire.IsSame(outer)
        if (signed_area(p) > 0) != is_outer:
            p = p[::-1]
        loops.append((not is_outer, polygon_loop(p)))
    if not any(not hole for hole, _ in loops):
        return None
    return Trim(tuple(loop for _, loop in sorted(loops, key=lambda x: x[0])))


def _edges_in_order(wire, face) -> list:
    """The wire's edges in their order along it (OpenCASCADE's wire explorer; the stored
    order where it finds none), each once but a seam's two passes."""
    from OCP.BRepTools import BRepTools_WireExplorer
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    edges, walker, count = [], BRepTools_WireExplorer(wire, face), _count(wire, TopAbs_EDGE)
    while walker.More() and len(edges) < count:
        edges.append(walker.Current())
        walker.Next()
    if not edges:
        explorer = TopExp_Explorer(wire, TopAbs_EDGE)
        while explorer.More():
            edges.append(TopoDS.Edge(explorer.Current()))
            explorer.Next()
    return edges


def join(surfaces: list[NurbsSurface], points: np.ndarray, tolerance: float, spacing: float,
         data: list[np.ndarray]) -> Joined:
    """The faces (each a region's fitted surface, cloud units) extended, bounded within
    reach of their own data (``data[k]``: face k's points (M_k, 3)), cut, kept where the
    data (N, 3) hold them and sewn at ``tolerance``."""
    from OCP.BOPAlgo import BOPAlgo_Builder
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
    from OCP.BRepGProp import BRepGProp
    from OCP.collections import List_TopoDS_Shape
    from OCP.GProp import GProp_GProps
    from OCP.TopoDS import TopoDS

    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    reach = max(EXTEND * diagonal, EXTEND_SPACINGS * spacing)
    grown = [extended_face(s, reach) for s in surfaces]
    bounds = [within_reach(s, own, BOUND * reach) for s, own in zip(grown, data)]
    builder, arguments = BOPAlgo_Builder(), List_TopoDS_Shape()
    faces = [BRepBuilderAPI_MakeFace(occ_surface(s, periodic=True), 1e-7).Face() if bound is None
             else occ_face(s, bound) for s, bound in zip(grown, bounds)]
    for face in faces:
        arguments.Append(face)
    builder.SetArguments(arguments)
    builder.SetRunParallel(False)
    builder.Perform()
    pieces, region = [], []
    for k, face in enumerate(faces):
        modified = builder.Modified(face)
        split = [TopoDS.Face(s) for s in modified] if modified.Size() else [face]
        pieces += split
        region += [k] * len(split)
    described = []
    for k, piece in enumerate(pieces):
        props = GProp_GProps()
        BRepGProp.SurfaceProperties_s(piece, props)
        described.append((grown[region[k]], _loops(piece, grown[region[k]]), float(props.Mass())))
    outlined = [k for k, (_, trim, _) in enumerate(described) if trim is not None]  # a sliver has no loop
    distances = np.full((len(pieces), len(points)), np.inf)
    distances[outlined] = face_distances([described[k][:2] for k in outlined], points)
    held, counts = held_pieces(distances, np.array([area for _, _, area in described]), len(points), tolerance)
    kept = np.flatnonzero(held)
    sewn = sew([pieces[k] for k in kept], tolerance)
    joined = []
    for k in kept:
        joined.append(JoinedFace(region[k], *described[k], int(counts[k])))
    return Joined(joined, sewn.closed, sewn.valid, sewn.volume, sewn.free_edges, sewn.gap, distances[kept],
                  sewn.shape)
