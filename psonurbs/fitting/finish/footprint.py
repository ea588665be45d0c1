"""The data's footprint in the parameter domain, as trim loops.

From the points' final parameters (their foot points on the fitted surface):

1. **Metric.** The domain is scaled by the surface's mean speeds, x = (u |S_u|, v |S_v|),
   so that distances in it are about distances on the surface.
2. **Spacing.** Each point's local spacing s_i = r_k sqrt(pi / k), r_k the distance to
   its k-th neighbour (``NEIGHBOURS``): the grid step of a uniform sampling of the same
   density. k is large enough that a scan's lines (dense along, sparse across) give the
   density, not the step along a line.
3. **Alpha shape.** The Delaunay triangles of the points whose circumradius is at most
   ``ALPHA`` times the spacing of their corners (within a gap the data enclose, where
   the data are: s_i scaled by the root of the share of its disc the data fill,
   :func:`filled_share`; on a hole's rim half the disc is empty) (the largest, at most ``DENSITY_JUMP``
   times the smallest; the smallest across a jump in density on the surface:
   :func:`judging_spacing`): a gap narrower than that is
   sampling, a wider one is a hole or lies outside. Gross outliers (of robust weight 0 and
   farther off the surface than the points' spacing: :func:`marks_the_data`) are left out,
   and so are the points the robust stage doubts (``verdict.doubted``: junk the fit may
   have been bent towards holds no flap of the face) and points apart from the others
   on the surface (:func:`beside_the_data`); a point a side of the surface was
   carried out to (the lone corner of a sparse edge) marks the data.
4. **The face.** The kept triangles' connected pieces: the face is the largest (by
   area); the points of the others lie off it (measured to its boundary, as a scorer
   of the trimmed surface measures them).
5. **Loops.** The piece is rasterised, less the cells of its rim triangles where the
   surface bows sideways out of the triangle through the data (:func:`bent_off`: past
   its last points a fitted surface is often stretched unevenly, a corner spreading or
   an edge bulging where it extrapolates, and a triangle straight in the domain is a
   flap on it), every point of the face kept on it (:func:`rejoined`); its distance
   field is contoured at a margin of a
   quarter of the local spacing outside it (never less than a quarter of the median:
   :func:`local_margin`) (:func:`psonurbs.geometry.contour.contours`; a hole
   of less area than a disc of radius ``ALPHA`` median spacings is a sampling gap and is
   covered), and each contour fitted by a closed cubic B-spline with the fewest control points (doubling)
   that keeps within half the margin of it, inside the domain, every loop simple
   and apart from the others, and the piece's points inside the face.

A footprint of more than ``FOOTPRINT_POINTS`` points is drawn from a well-spread
subsample of them (:func:`well_spread`: one per cell of a grid of about that many cells,
so a sparse region keeps all its points), steps 2-5 at the subsample's spacing (the
resolution of the holes, pieces and margin; the raster is as fine as for all the points,
``MAX_RASTER``): every point then joins the piece of its nearest drawn point when within
the alpha scale of it, and the raster cells along the way from every point of the face to
that drawn point are added to it (:func:`mark_joined`), so that the loops hold them all
(the subsample's own boundary lies inside the data's by a fraction of its spacing). The
points off the face, the fragments' points and the distances are still those of every
point.

A face that holds fewer than half of the points (a fit far from the data, pieces of
the cloud spread over the domain) is not the data's footprint: the surface is left
untrimmed. ``trim: auto`` keeps the loops only when the face has a hole or leaves a real gap
on the surface: an empty disc on the surface outside the face (bounded by the face and the
surface's edge) of radius at least ``ALPHA`` spacings of the data beside it (as wide as
the gaps the alpha shape opens; :func:`gap_scale`), or an edge of the surface running
more than ``EDGE_OVERRUN`` spacings past the data along a stretch of it
(:func:`edge_overrun`: a strip of surface without data, which holds no such disc until it
is twice as deep). Both are measured on the surface (:func:`widest_gap`), so a strip
of stretched surface past the data counts however thin it is in the domain; a cloud that
fills its rectangle leaves only sampling gaps along the edges. A sheet laid flat by its
own geometry (``flattened``: no plane sees it) keeps its loops under ``trim: auto``
too: its square's sides are the flattening's outline of the data, ragged and rounded where
the fine net extrapolates between and past the last points, and no straight edge of the
data says where its face should end (a twisted ribbon's face is 2.1e-5 of the diagonal off
the true surface in rms, the whole surface 9.9e-5; a 270-degree cone sector's 1.4e-4
against 4.4e-4). ``true`` always; ``false`` never.

An open patch projected on a plane has the data's straight edges in it
(:mod:`psonurbs.fitting.finish.straight_edges`): every loop keeps within the margin (on
the surface) of them, and where ``trim: auto`` finds no gap but the surface runs past
one by more than the margin, the face is the whole domain cut there.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree

from psonurbs.fitting.prepare.robust_weights import CUTOFF_SIGMAS, Verdict, biweights, residual_scale
from psonurbs.geometry.contour import contours, simplify_closed
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.raster import rasterised
from psonurbs.geometry.trim import (
    Trim,
    TrimLoop,
    crossing,
    distances_to_face,
    fit_closed_curve,
    inside,
    polygon_loop,
    signed_area,
)

from .carried_sides import domain_frame, joined, reaching_data
from .straight_edges import StraightEdges, reaching_domain, straight_edges

NEIGHBOURS = 16
ALPHA = 2.5
DENSITY_JUMP = 2.5  # corners' spacings this many fold apart on the surface: a jump in density, not a gradient
MARGIN = 0.25  # loops this many local spacings outside the points (at least this many median spacings)
MAX_CONTROL = 128  # control points of a cubic loop at most
# a loop along the domain's edge runs this far outside it (of the unit domain): on the edge
# itself an even-odd test is undecided, and the data's points held on the edge must be inside
EDGE_OUTSET = 1e-9
MAX_RASTER = 1500  # cells along the longer side of the footprint's raster
AREA_GRID = 201  # surface area elements for the empty share
FOOTPRINT_POINTS = 20_000  # a bigger footprint is drawn from a subsample of this many points...
FOOTPRINT_SEED = 14  # ... a fixed one
GAP_SAMPLES = 40_000  # surface samples outside the face that measure its widest gap
EDGE_SAMPLES = 400  # samples along each edge of the surface that measure how far it runs past the data
EDGE_OVERRUN = 2.0  # an edge this many spacings past the data along a stretch: a strip of surface without data
NEAR_EXACT = 0.25  # of the median spacing: a point beyond the robust cut-off but this near marks the data
REJUDGED_SIGMAS = 3.0  # a local outlier the fit passes this near (in its residuals' sigmas) is data
LEAST_FILLED = 0.25  # share of a point's neighbourhood the data fill, at least (a right-angled corner's)
# a disc cut by a chord h (in radii) from its centre, h from 1 to -1 (:func:`filled_share`):
# its remaining area's share A(h) / pi and that area's centroid offset g(h), increasing
_CHORD = np.linspace(1.0, -1.0, 401)
_AREA = np.pi - np.arccos(_CHORD) + _CHORD * np.sqrt(1.0 - _CHORD ** 2)
CHORD_SHARE = _AREA / np.pi
CHORD_OFFSET = np.append(2.0 / 3.0 * (1.0 - _CHORD[:-1] ** 2) ** 1.5 / _AREA[:-1], 1.0)  # 1: a vanishing cap


@dataclass(frozen=True)
class Footprint:
    """The result: the surface, its trim (None: untrimmed), the points' distances to the
    face, and what was found."""

    surface: NurbsSurface
    trim: Trim | None
    distances: np.ndarray  # (N,) of the points to the (trimmed) surface
    loops: int
    empty_share: float  # share of the fitted surface's area outside the face
    points_outside: int  # points whose parameters lie outside the face
    fragments: int  # pieces of the footprint left out of the face
    fragment_points: int
    spacing: float  # median spacing (of the drawn points), in the surface's (approximate) length units
    cut: bool = False  # the face is the whole domain cut where the surface ran past the data's straight edges

    def to_dict(self) -> dict:
        return {"trimmed": self.trim is not None, "loops": self.loops, "empty_share": self.empty_share,
                "points_outside": self.points_outside, "fragments": self.fragments,
                "fragment_points": self.fragment_points, "spacing": self.spacing, "cut": self.cut}


def mean_speeds(surface: NurbsSurface, n: int = 33) -> np.ndarray:
    """(mean |S_u|, mean |S_v|) over an n x n parameter grid."""
    uu, vv = np.meshgrid(*surface.parameter_grid(n, n), indexing="ij")
    _, su, sv = surface.derivatives(uu.ravel(), vv.ravel())
    speeds = np.array([np.linalg.norm(su, axis=1).mean(), np.linalg.norm(sv, axis=1).mean()])
    return np.maximum(speeds, 1e-12 * max(float(speeds.max()), 1e-300))


def nearest(x: np.ndarray, k: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices (N, k' + 1) of each point's k' = min(k, N - 1) nearest
    points, itself first: what :func:`local_spacing` and :func:`filled_share` read."""
    return cKDTree(x).query(x, k=min(k, len(x) - 1) + 1)


def local_spacing(x: np.ndarray, k: int = NEIGHBOURS, near: tuple | None = None) -> np.ndarray:
    """s_i = r_k sqrt(pi / k): the step of a uniform grid with the density around point i
    (``near``: :func:`nearest` of x, if already queried)."""
    dist = (nearest(x, k) if near is None else near)[0]
    return dist[:, -1] * np.sqrt(np.pi / (dist.shape[1] - 1))


def filled_share(x: np.ndarray, k: int = NEIGHBOURS, near: tuple | None = None) -> np.ndarray:
    """The share (N,) of each point's neighbourhood disc (radius r_k, :func:`local_spacing`)
    that the data fill, read from the offset of its k neighbours' centroid: where a
    straight chord h r_k from the point cuts the disc (the data's edge), the neighbours
    fill the rest, of area A(h) = pi - acos h + h sqrt(1 - h^2) (in r_k^2), and their
    centroid lies g(h) = 2/3 (1 - h^2)^(3/2) / A(h) from it (0.42 r_k on the edge, h = 0).
    The offset m is read as g(h) after the scatter of k uniform points' centroid
    (E m^2 = 1 / 2k in a full disc) is taken off, and the share is A(h) / pi, at least
    ``LEAST_FILLED`` (a sharp corner's wedge). ``near``: :func:`nearest` of x, if queried."""
    if len(x) < 2:
        return np.ones(len(x))
    dist, idx = nearest(x, k) if near is None else near
    k = dist.shape[1] - 1
    offset = x[idx[:, 1:]].mean(axis=1) - x
    reach2 = dist[:, -1] ** 2
    m2 = np.divide(np.sum(offset * offset, axis=1), reach2, out=np.zeros(len(x)), where=reach2 > 0)  # no reach: full
    m = np.sqrt(np.maximum(m2 - 0.5 / k, 0.0))
    return np.maximum(np.interp(m, CHORD_OFFSET, CHORD_SHARE), LEAST_FILLED)


def alpha_triangles(x: np.ndarray, spacing: np.ndarray, density: np.ndarray | None = None,
                    share: np.ndarray | None = None) -> tuple[Delaunay, np.ndarray]:
    """The Delaunay triangulation of x (N, 2) and the mask of its alpha-shape triangles:
    those whose circumradius is at most ``ALPHA`` times the spacing their corners judge
    them by (:func:`judging_spacing` of their spacings (N,), and of their spacings on the
    surface ``density`` (N,; default ``spacing``) for a jump in density).

    With ``share`` (N,; :func:`filled_share`), a gap the data enclose is judged by the
    spacing where the data are, each corner's times the root of its share: on a hole's
    rim half the neighbourhood is empty and the spacing reads sqrt 2 too wide, so that a
    slot 3 spacings wide was bridged. The triangles this drops that the outside reaches
    (through triangles it drops or never kept) are kept as without it: past the data's
    outer edge half of a circle is empty by nothing the data say, and judged so the
    edge's own sampling gaps became bays (a graded strip's sparse end lost cover).

    Four far corners are added to the points (indices N .. N+3), so that any query point
    near the data lies inside the triangulation's hull (a point-location query outside it
    is slow); a triangle touching them is never kept, and no kept triangle changes (its
    small circumcircle holds no far corner).
    """
    centre, size = 0.5 * (x.min(0) + x.max(0)), float(np.ptp(x, axis=0).max()) or 1.0
    corners = centre + 100.0 * size * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    pts = np.concatenate([x, corners])
    tri = Delaunay(pts)
    a, b, c = (pts[tri.simplices[:, k]] for k in range(3))
    la, lb, lc = (np.linalg.norm(p - q, axis=1) for p, q in ((b, c), (c, a), (a, b)))
    area2 = np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = la * lb * lc / (2.0 * area2)
    real = np.all(tri.simplices < len(x), axis=1)
    simplices = np.where(real[:, None], tri.simplices, 0)
    density = spacing if density is None else density
    kept = real & np.isfinite(radius) & (radius <= ALPHA * judging_spacing(spacing[simplices], density[simplices]))
    if share is None:
        return tri, kept
    root = np.sqrt(share)[simplices]
    tight = kept & (radius <= ALPHA * judging_spacing(root * spacing[simplices], root * density[simplices]))
    gaps = pieces(tri, ~tight)
    outside = np.isin(gaps, np.unique(gaps[~real]))
    return tri, tight | (kept & outside)


def judging_spacing(corners: np.ndarray, density: np.ndarray) -> np.ndarray:
    """The spacing (T,) a triangle is judged by, from its corners' spacings (T, 3): the
    largest, at most ``DENSITY_JUMP`` times the smallest; where their spacings on the
    surface ``density`` (T, 3) differ more than ``DENSITY_JUMP`` fold, the smallest (the
    dense side's).

    The largest lets a sparse part join the data (a scan's density falling with range,
    the thin edge of a graded cloud, a neck between two parts of a real scan). But a stray
    off the data's edge (a point of junk the surface was bent to) is sparse by its own
    spacing too, and judged by it, it would join the data with every triangle it spans to
    them: a triangle across a jump in density is judged at the dense side's spacing. The
    jump is measured on the surface: where the fit was bent to a few strays, a thin strip
    of the domain is a wide flap of surface, and strays close together in the domain lie
    far apart on it. A scan's density changes gradually (by a few per cent from a point to
    its neighbours where it thins out with range), and a point's spacing estimate varies
    by less than twofold (an edge's half-empty neighbourhood, a corner's). So neither
    does a corner's spacing in the domain differ more than that from its neighbours' where
    the map is fair; where it does (a lone point in the domain, or a flattening that
    spreads one side of a curved strip), the largest would let a triangle bridge the
    concave side of the strip (a horseshoe's mouth): it counts at most ``DENSITY_JUMP``
    times the smallest."""
    jump = density.max(axis=1) > DENSITY_JUMP * density.min(axis=1)
    least = corners.min(axis=1)
    return np.where(jump, least, np.minimum(corners.max(axis=1), DENSITY_JUMP * least))


def pieces(tri: Delaunay, kept: np.ndarray) -> np.ndarray:
    """Label (per triangle, -1 if not kept) of the kept triangles' edge-connected pieces."""
    n = len(kept)
    nb = tri.neighbors
    rows = np.repeat(np.arange(n), 3)
    cols = nb.ravel()
    ok = (cols >= 0) & kept[rows] & kept[np.maximum(cols, 0)]
    graph = coo_matrix((np.ones(ok.sum()), (rows[ok], cols[ok])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return np.where(kept, labels, -1)


@dataclass(frozen=True)
class Contours:
    """The face's contours in the parameter domain, before they are fitted."""

    polygons: list[np.ndarray]  # the outer boundary (counter-clockwise) first, then the holes
    face_points: np.ndarray  # indices of the points (into uv) on the face's piece
    fragments: int
    fragment_points: int
    spacing: float  # median spacing, surface length units
    tolerance: np.ndarray  # (2,) half the margin, in u and v
    widest_gap: float  # the widest empty disc outside the face, in spacings of the data beside it (gap_scale)
    edge_overrun: float  # how far the surface's edges run past the data along a stretch, in spacings
    cut: list[np.ndarray] | None = None  # the domain's contours less the surface past a straight edge of the data

    def reach(self) -> np.ndarray:
        """How far (u below 0, v below 0, u above 1, v above 1) the contours run past the domain."""
        p = np.concatenate(self.polygons)
        return np.maximum(np.concatenate([-p.min(axis=0), p.max(axis=0) - 1.0]), 0.0)


def face_contours(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, distances: np.ndarray,
                  verdict: Verdict | None = None, edges: StraightEdges | None = None,
                  carried: np.ndarray | None = None) -> Contours | None:
    """Steps 1-4 of the module docstring and the contours of step 5 (None: no footprint);
    ``edges``: the data's straight edges, which the face does not cross (:func:`past_straight_edges`)."""
    scale = mean_speeds(surface)
    good = np.flatnonzero(data_marks(distances, uv, scale, verdict, carried))
    drawn = np.arange(len(good)) if len(good) <= FOOTPRINT_POINTS else well_spread(uv[good] * scale, FOOTPRINT_POINTS)
    good, drawn = beside_the_data(points, distances, good, drawn, carried)
    every = uv[good] * scale
    subsampled = len(drawn) < len(good)
    x = every[drawn]
    near = nearest(x)
    spacing = local_spacing(x, near=near)
    data, data_spacing = points[good[drawn]], local_spacing(points[good[drawn]])  # on the surface
    tri, kept = alpha_triangles(x, spacing, data_spacing, filled_share(x, near=near))
    if not kept.any():
        return None
    label = pieces(tri, kept)
    a, b, c = (tri.points[tri.simplices[:, k]] for k in range(3))
    area = 0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    piece_area = np.bincount(label[kept], weights=area[kept])
    in_face = label == int(np.argmax(piece_area))
    face_points = np.unique(tri.simplices[in_face])
    face_drawn = face_points[face_points < len(x)]  # the drawn points on the face, for the local margin
    others = np.setdiff1d(np.unique(tri.simplices[kept & ~in_face]), face_points)
    if subsampled:  # a subsample's pieces, each point on the piece of its nearest drawn point
        face_points, others = pieces_of_every_point(every, x, spacing, face_points, others)
    else:
        face_points, others = drawn[face_points], drawn[others]

    # raster of the face, its distance field, contoured one margin outside it
    margin = MARGIN * float(np.median(spacing))
    lo, hi = np.minimum(every.min(axis=0), 0.0), np.maximum(every.max(axis=0), scale)  # the domain is [0, 1]^2
    cell = max(margin / 3.0, float((hi - lo).max()) / MAX_RASTER)
    margin = max(margin, 3.0 * cell)
    widest = max(margin, MARGIN * float(spacing[face_drawn].max()))  # at least the margin where the data are sparsest
    pad = margin + 3.0 * cell + np.ceil((widest - margin) / cell) * cell  # whole cells more: the same lattice
    xs = np.arange(lo[0] - pad, hi[0] + pad + cell, cell)
    ys = np.arange(lo[1] - pad, hi[1] + pad + cell, cell)
    mask = rasterised(tri.points[tri.simplices[in_face]], xs[0], ys[0], cell, (len(xs), len(ys)))
    mask &= ~bent_off(surface, tri, in_face, mask, xs, ys, scale, cell)
    past = past_square = square = None  # all the edges', and the untilted ones' (past a tilted one, a margin)
    if edges is not None:
        square = edges.untilted()
        sets = [edges] if square is None or square is edges else [edges, square]
        fields = past_straight_edges(surface, sets, xs, ys, scale)
        past, past_square = fields[0], None if square is None else fields[-1]
    reach = MARGIN * float(np.median(data_spacing))  # the loops' margin on the surface

    def bounded(field: np.ndarray) -> np.ndarray:
        """The field held within the loops' margin of the data's straight edges, measured
        on the surface (the raster's margin is one at the mean speeds, wider where an edge
        is stretched), within a raster cell of an untilted one, and closed at the raster's
        rim. An untilted edge stands at the outermost point, where a dense edge's true
        one is: a margin past it is surface past the true edge; the cell keeps the
        outermost points inside the contour. A tilted edge's plane is only so sure."""
        if past is not None:
            field = np.maximum(field, past - reach)
        if past_square is not None:
            field = np.maximum(field, past_square - cell)
        field[[0, -1], :] = field[:, [0, -1]] = np.inf
        return field

    if subsampled:  # every point on the face, joined to the drawn point of its piece
        mark_joined(mask, every[face_points], x[face_drawn], xs[0], ys[0], cell)
    rejoined(mask, every[face_points] if subsampled else x[face_drawn], xs[0], ys[0], cell)
    field = np.where(mask, -ndimage.distance_transform_edt(mask), ndimage.distance_transform_edt(~mask)) * cell
    field = bounded(field - local_margin(field, xs, ys, x[face_drawn], spacing[face_drawn], margin, widest))
    in_domain = ((xs >= 0) & (xs <= scale[0]))[:, None] & ((ys >= 0) & (ys <= scale[1]))[None, :]
    cut = None  # the whole domain less the surface past a straight edge, where it runs past one
    if past is not None and np.any(past[in_domain] > reach):
        outside = np.maximum(np.maximum(-xs, xs - scale[0])[:, None], np.maximum(-ys, ys - scale[1])[None, :])
        cut = outlines(bounded(outside - margin), xs, ys, scale, spacing)  # (the loops are clamped to the domain)
    # the widest gap on the surface outside the face: a real gap, or sampling?
    empty = np.argwhere(in_domain & (field > 0.0))
    rim = np.argwhere(mask & ~ndimage.binary_erosion(mask))  # the face's boundary cells
    room = None if past_square is None else cell - past_square[empty[:, 0], empty[:, 1]]  # to the cut
    gap = widest_gap(surface, np.column_stack([xs[empty[:, 0]], ys[empty[:, 1]]]) / scale,
                     np.column_stack([xs[rim[:, 0]], ys[rim[:, 1]]]) / scale, data, data_spacing, room) \
        if len(empty) and len(rim) else 0.0
    overrun = edge_overrun(surface, data, data_spacing, square)
    polygons = outlines(field, xs, ys, scale, spacing)
    if not polygons:  # a face finer than the raster (a tiny cluster far from the rest): no loops
        return None
    return Contours(polygons, good[face_points], int(np.sum(piece_area > 0) - 1),
                    int(len(others)), float(np.median(spacing)), margin / 2.0 / scale, gap, overrun, cut or None)


def beside_the_data(points: np.ndarray, distances: np.ndarray, good: np.ndarray, drawn: np.ndarray,
                    carried: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The marking points ``good`` (M,) and the drawn ones among them ``drawn`` (indices
    into good), less the drawn points (of the points (N, 3), at ``distances`` (N,) from
    the surface) that lie apart from the others on the surface, their nearest farther
    than ``ALPHA`` times the spacing of the points beside it
    (:func:`psonurbs.fitting.finish.carried_sides.joined`), unless the fit passes within
    the noise of them (``REJUDGED_SIGMAS`` of its residuals' scale, as for a local
    outlier, or ``NEAR_EXACT`` of the median spacing: a noise-free fit's scale is its
    approximation error) or a side was ``carried`` out to them.

    A point marks the data by lying near the surface, within the robust cut-off. But
    where a fit flares past the data's edge, junk near the flare lies near it too, and
    in the domain, which the flare's stretch shrinks, a single stray spans a spike of the
    face to it (a saddle with 5% junk: a stray 4.2 sigmas, 0.85 spacings, off a side,
    held a flap; truth 0.48 noise sigmas with it, 0.17 without). A real point can lie
    as far apart (on a steep step where it meets the data's edge: 3.8 spacings on the
    surface, 3.4 in the domain) but the fit passes through it (1.1 sigmas). Judged among
    the drawn points, whose spacing is the face's resolution."""
    if len(drawn) < 3:
        return good, drawn
    apart = distances[good[drawn]] > REJUDGED_SIGMAS * residual_scale(distances)
    if apart.any():
        apart &= distances[good[drawn]] > NEAR_EXACT * median_spacing(points[good])
    if carried is not None:
        apart &= ~np.isin(good[drawn], carried)
    if apart.any():
        rows = np.flatnonzero(apart)
        apart[rows] = ~joined(points[good[drawn]], rows, np.ones(len(drawn), bool), ALPHA)
    if not apart.any():
        return good, drawn
    keep = np.ones(len(good), bool)
    keep[drawn[apart]] = False
    return good[keep], (np.cumsum(keep) - 1)[drawn[~apart]]


def outlines(field: np.ndarray, xs: np.ndarray, ys: np.ndarray, scale: np.ndarray, spacing: np.ndarray
             ) -> list[np.ndarray]:
    """The zero contours of the face's field (len(xs), len(ys)) in the domain: the outer
    one first, then the holes; a hole smaller than a disc of the alpha scale (``ALPHA``
    median ``spacing``) is a sampling gap (a sliver of wide circumcircle in a random
    sample), not a gap in the data: the face covers it. Empty for a face finer than the
    raster."""
    polygons = [p / scale for p in contours(field, xs, ys, 0.0)]
    polygons = [p for p in polygons if len(p) >= 3 and abs(signed_area(p)) > 0]
    if not polygons:
        return []
    outer = int(np.argmax([signed_area(p) for p in polygons]))
    smallest = np.pi * (ALPHA * float(np.median(spacing))) ** 2
    return [polygons[outer], *(p for k, p in enumerate(polygons) if k != outer and -signed_area(p * scale) >= smallest)]


def past_straight_edges(surface: NurbsSurface, edge_sets: list[StraightEdges], xs: np.ndarray, ys: np.ndarray,
                        scale: np.ndarray, n: int = AREA_GRID) -> list[np.ndarray]:
    """How far the surface at each cell of the raster (len(xs), len(ys); the domain at the
    mean speeds ``scale``) lies past each set of the data's straight edges
    (:mod:`psonurbs.fitting.finish.straight_edges`), in cloud units (negative inside
    them): the surface on one n x n grid over the domain, interpolated linearly (cells
    outside the domain take its edge's)."""
    us, vs = surface.parameter_grid(n, n)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    grid = surface.evaluate(uu.ravel(), vv.ravel())
    (u0, u1), (v0, v1) = surface.domain_u, surface.domain_v
    iu = (np.clip(xs / scale[0], 0.0, 1.0) * (u1 - u0) + u0 - us[0]) / (us[-1] - us[0]) * (n - 1)
    iv = (np.clip(ys / scale[1], 0.0, 1.0) * (v1 - v0) + v0 - vs[0]) / (vs[-1] - vs[0]) * (n - 1)
    ii, jj = np.meshgrid(iu, iv, indexing="ij")
    return [ndimage.map_coordinates(edges.beyond(grid).reshape(n, n), [ii, jj], order=1, mode="nearest")
            for edges in edge_sets]


def bent_off(surface: NurbsSurface, tri: Delaunay, in_face: np.ndarray, mask: np.ndarray, xs: np.ndarray,
             ys: np.ndarray, scale: np.ndarray, cell: float) -> np.ndarray:
    """The face's cells (mask of the raster, cells of side ``cell`` at (xs[i], ys[j]) in the
    domain at the mean speeds ``scale``) in a rim triangle (one with a side on the face's
    boundary) where the surface leaves the data's triangle sideways: S(c) lies farther
    than a cell's step on the surface there (cell max(|S_u| / scale_u, |S_v| / scale_v))
    from the triangle through its corners' foot points S(x_k / scale), along the surface
    (the part of S(c) - sum_k b_k F_k in the tangent plane; b the cell's barycentric
    coordinates in the domain triangle).

    A triangle is straight in the domain and straight through the data; on a surface
    stretched unevenly past its last points (a corner spreading, an edge bulging where
    the fit extrapolates) its image bows out of the data by a spacing and more: a flap
    that no point holds."""
    rim_tri = in_face & np.any((tri.neighbors < 0) | ~in_face[np.maximum(tri.neighbors, 0)], axis=1)
    out = np.zeros_like(mask)
    if not rim_tri.any():
        return out
    cells = np.argwhere(mask & rasterised(tri.points[tri.simplices[rim_tri]], xs[0], ys[0], cell, mask.shape))
    if not len(cells):
        return out
    at = np.column_stack([xs[cells[:, 0]], ys[cells[:, 1]]])
    which = tri.find_simplex(at)
    hit = (which >= 0) & rim_tri[np.maximum(which, 0)]
    cells, at, which = cells[hit], at[hit], which[hit]
    if not len(cells):
        return out
    t = tri.transform[which]  # (K, 3, 2): barycentric b_0, b_1 = T (x - r), b_2 = 1 - b_0 - b_1
    b01 = np.einsum("kij,kj->ki", t[:, :2], at - t[:, 2])
    corners = tri.simplices[which]
    used, back = np.unique(corners, return_inverse=True)  # the corners' feet, each evaluated once
    feet = surface.evaluate(*(np.clip(tri.points[used] / scale, 0.0, 1.0)).T)[back.reshape(corners.shape)]
    lifted = np.einsum("kc,kcd->kd", np.column_stack([b01, 1.0 - b01.sum(axis=1)]), feet)
    uv = np.clip(at / scale, 0.0, 1.0)
    on, su, sv = surface.derivatives(uv[:, 0], uv[:, 1])
    normal = np.cross(su, sv)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    d = on - lifted
    sideways = np.linalg.norm(d - np.sum(d * normal, axis=1, keepdims=True) * normal, axis=1)
    step = cell * np.maximum(np.linalg.norm(su, axis=1) / scale[0], np.linalg.norm(sv, axis=1) / scale[1])
    far = sideways > step
    out[cells[far, 0], cells[far, 1]] = True
    return out


def rejoined(mask: np.ndarray, points: np.ndarray, x0: float, y0: float, cell: float) -> None:
    """Join, in place, the raster's pieces holding some of the points (N, 2) to the piece
    holding most of them: each point of another piece (or of none) by the cells along
    the segment to the nearest point of that one (:func:`mark_joined`). A point the alpha
    shape joins to the face by sides the surface bows away from (:func:`bent_off`; a
    point past the surface's edge, its foot on it) stays on the face, by a thin strip."""
    labels, count = ndimage.label(mask)
    at = np.floor((points - [x0, y0]) / cell).astype(int)
    around = np.stack([labels[at[:, 0] + di, at[:, 1] + dj] for di, dj in ((0, 0), (0, 1), (1, 0), (1, 1))], axis=1)
    if count == 0 or not np.any(around > 0):
        return
    main = np.argmax(np.bincount(around[around > 0]))
    apart = ~np.any(around == main, axis=1)  # no cell around the point on the main piece
    if apart.any() and not apart.all():
        mark_joined(mask, points[apart], points[~apart], x0, y0, cell)


def local_margin(field: np.ndarray, xs: np.ndarray, ys: np.ndarray, face: np.ndarray, spacing: np.ndarray,
                 least: float, most: float) -> np.ndarray:
    """The loops' margin at every cell of the raster (len(xs), len(ys)): ``MARGIN`` times the
    local spacing of the nearest face point (face (M, 2) with their spacings (M,); the
    median over its ``NEIGHBOURS`` nearest face points: a sparse end's, not one point's
    sampling luck) over sqrt 2
    (the nearest face point lies on its edge, its neighbours filling half a disc, which
    reads the spacing sqrt 2 too wide: :func:`gap_scale`), never below ``least`` (a
    quarter of the median spacing, or the raster's resolution); cells inside the face or
    farther out than ``most`` keep ``least``.

    Where the data thin out (a scan's density falling with range) the true edge lies
    farther beyond the last points, in proportion to their spacing: a margin of the
    median spacing leaves the sparse end's last spacings uncovered."""
    out = np.full(field.shape, least)
    band = np.argwhere((field > 0.0) & (field <= most))
    if len(band) and most > least:
        tree = cKDTree(face)
        rim = np.median(spacing[tree.query(face, k=min(NEIGHBOURS, len(face)))[1].reshape(len(face), -1)], axis=1)
        nearest = tree.query(np.column_stack([xs[band[:, 0]], ys[band[:, 1]]]))[1]
        out[band[:, 0], band[:, 1]] = np.maximum(least, MARGIN * rim[nearest] / np.sqrt(2.0))
    return out


def median_spacing(x: np.ndarray) -> float:
    """The median of the local spacings of the points x (N, 2) (:func:`local_spacing`),
    from a random subsample of ``FOOTPRINT_POINTS`` of a bigger set (a uniform thinning
    by m / N widens every spacing by sqrt(N / m))."""
    if len(x) < 2:
        return 0.0
    if len(x) <= FOOTPRINT_POINTS:
        return float(np.median(local_spacing(x)))
    drawn = np.random.default_rng(FOOTPRINT_SEED).choice(len(x), FOOTPRINT_POINTS, replace=False)
    return float(np.median(local_spacing(x[drawn]))) * float(np.sqrt(FOOTPRINT_POINTS / len(x)))


def data_marks(distances: np.ndarray, uv: np.ndarray, scale: np.ndarray, verdict: Verdict | None,
               carried: np.ndarray | None = None) -> np.ndarray:
    """The points (N,) that say where the data lie: those :func:`marks_the_data` and those a
    side was ``carried`` out to (indices), less those the robust stage doubts (``verdict``)."""
    marks = marks_the_data(distances, uv, scale)
    if verdict is not None and verdict.doubted is not None:
        marks &= ~verdict.doubted
    if carried is not None:
        marks[carried] = True
    return marks


def marks_the_data(distances: np.ndarray, uv: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Which points (N,) say where the data lie on the surface: all but gross outliers,
    of robust weight 0 (:func:`psonurbs.fitting.prepare.robust_weights.biweights`) *and*
    farther from the surface than ``NEAR_EXACT`` of the points' median spacing (their
    parameters uv (N, 2), at the mean speeds ``scale`` (2,)). A stray the fit was bent
    towards (junk just past an edge) lies beyond the cut-off but within a spacing of the
    surface: it must not widen the face. A point whose foot lies on the domain's edge
    lies past the surface's edge, its distance the gap to it: it marks the data within a
    whole spacing (the data run on a little past where the surface ends; on the edge it
    cannot widen the face beyond the domain).

    The robust scale of a near-exact fit (noise-free points of a shape the net almost
    holds) is the net's approximation error, so the larger residuals at a feature or
    along an edge pass its cut-off while lying well within the data's sampling layer:
    their foot points mark the data as well as any. Left out, the face shrank away from
    them, and a trimmed fit left them off it (a narrow bump's 9 of 3,000 points along an
    edge, 0.4-0.7 thousandths off a surface whose median residual was 0.024 thousandths,
    in a cloud of diagonal 1.43 and median spacing about 26 thousandths)."""
    gross = biweights(distances) <= 0
    if gross.any():
        on_edge = np.any((uv <= 0.0) | (uv >= 1.0), axis=1)
        gross &= distances > np.where(on_edge, 1.0, NEAR_EXACT) * median_spacing(uv * scale)
    return ~gross


def widest_gap(surface: NurbsSurface, empty_uv: np.ndarray, face_uv: np.ndarray, points: np.ndarray,
               spacing: np.ndarray, room: np.ndarray | None = None) -> float:
    """The widest gap on the surface outside the face, in the spacing of the points
    (N, 3) beside it (their local spacing (N,): :func:`gap_scale`): max over the surface
    at the parameters ``empty_uv`` (M, 2) (at most ``GAP_SAMPLES`` of them, evenly taken)
    of the radius of the empty disc there, the
    smaller of the distance to the face (its boundary sampled at ``face_uv``) and the
    distance to the surface's edge (the chord to the edge point along each parameter
    line of an open direction) and, given, the ``room`` (M,) to the cut at the data's
    straight edges (surface past them is cut off, not a gap beside the data), over the
    points' spacing there (:func:`gap_scale`, on the surface).

    Measured on the surface itself, not in the parameter domain at the mean speeds:
    where the surface is stretched (an edge row of control points far out, a flap past
    the data) a sliver of the domain is a wide band of surface with no data on it."""
    every = max(1, -(-len(empty_uv) // GAP_SAMPLES))
    empty_uv = empty_uv[::every]
    face_uv = face_uv[::max(1, -(-len(face_uv) // GAP_SAMPLES))]
    at = surface.evaluate(empty_uv[:, 0], empty_uv[:, 1])
    radius = cKDTree(surface.evaluate(face_uv[:, 0], face_uv[:, 1])).query(at)[0]
    if room is not None:
        radius = np.minimum(radius, room[::every])
    for k, closed, ends in ((0, surface.closed_u, surface.domain_u), (1, surface.closed_v, surface.domain_v)):
        if closed:
            continue
        for end in ends:
            edge = empty_uv.copy()
            edge[:, k] = end
            radius = np.minimum(radius, np.linalg.norm(at - surface.evaluate(edge[:, 0], edge[:, 1]), axis=1))
    return float(np.max(radius / gap_scale(points, spacing, at)))


def edge_overrun(surface: NurbsSurface, points: np.ndarray, spacing_of: np.ndarray,
                 cut: StraightEdges | None = None, samples: int = EDGE_SAMPLES) -> float:
    """How far the surface's edges run past the data (N, 3): the distance on the surface
    from an open direction's edge to the nearest point, in that point's local spacing
    ``spacing_of`` (N,; :func:`local_spacing`: the density's, not the step along a scan
    line), as far as the edge keeps it along a stretch of ``ALPHA`` spacings; the largest
    over the edges.

    Along the edge of a cloud that fills its rectangle some point comes within about a
    spacing of every such stretch (a random sample's widest gap at an edge, 2 to 4
    spacings deep, is a single gap, narrower than the stretch; the held distance is 1.0
    to 1.2 spacings in the median of uniform and 50-fold graded squares, 2.2 at most over
    72 of them); a strip of surface the polish let grow past the data, where a step or a
    ridge meets the edge, or a flap held by a stray keeps its depth along it.

    With ``cut`` (the data's untilted straight edges), an edge runs past the data no farther
    than to them (beyond, it is cut off)."""
    if len(points) <= NEIGHBOURS:
        return 0.0
    tree = cKDTree(points)
    t = np.linspace(0.0, 1.0, samples)
    deepest = 0.0
    for k, closed, ends, other in ((0, surface.closed_u, surface.domain_u, surface.domain_v),
                                   (1, surface.closed_v, surface.domain_v, surface.domain_u)):
        if closed:
            continue
        for end in ends:
            uv = np.empty((samples, 2))
            uv[:, k], uv[:, 1 - k] = end, other[0] + t * (other[1] - other[0])
            at = surface.evaluate(uv[:, 0], uv[:, 1])
            gap, nearest = tree.query(at)
            if cut is not None:
                gap = np.minimum(gap, np.maximum(-cut.beyond(at), 0.0))
            spacing = spacing_of[nearest]
            step = float(np.median(np.linalg.norm(np.diff(at, axis=0), axis=1)))
            window = int(np.clip(round(ALPHA * float(np.median(spacing)) / max(step, 1e-300)), 1, samples))
            held = ndimage.minimum_filter1d(gap / np.maximum(spacing, 1e-300), window, mode="nearest")
            deepest = max(deepest, float(held.max()))
    return deepest


def gap_scale(points: np.ndarray, spacing: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The spacing (M,) a gap at the surface points ``at`` (M, 3) is measured in: the
    local spacing (N,) of the nearest of the points (N, 3) over sqrt 2, never below their
    median spacing.

    A random sample leaves gaps as wide as its local spacing, so where the data thin
    out (a scan's density falling with range) the median spacing of the whole cloud
    makes sampling gaps look real: a rectangle filled with a density falling 50-fold
    across it was trimmed on most draws. The nearest point to a gap lies on the data's
    edge, where its neighbours fill half a disc and :func:`local_spacing` reads sqrt 2
    too wide; the median keeps the measure where the data are dense as it was."""
    nearest = cKDTree(points).query(at)[1]
    return np.maximum(spacing[nearest] / np.sqrt(2.0), max(float(np.median(spacing)), 1e-300))


def well_spread(x: np.ndarray, size: int) -> np.ndarray:
    """Sorted indices of about ``size`` of the points x (N, 2), one per occupied cell of a
    square grid (the first in a fixed random order): dense regions thinned to the cell's
    side, sparse ones (a few points bridging a gap) kept whole. The side makes ``size``
    cells of the bounding box, shrunk by the root of the share of them the points occupy
    (a footprint that fills little of its box is not thinned more)."""
    low, extent = x.min(axis=0), np.ptp(x, axis=0)
    extent = np.maximum(extent, 1e-12 * max(float(extent.max()), 1e-300))
    order = np.random.default_rng(FOOTPRINT_SEED).permutation(len(x))

    def first_per_cell(side: float) -> tuple[np.ndarray, int]:
        cell = np.floor((x[order] - low) / side).astype(np.int64)
        _, first = np.unique(cell[:, 0] * (int(extent[1] / side) + 2) + cell[:, 1], return_index=True)
        return first, (int(extent[0] / side) + 1) * (int(extent[1] / side) + 1)

    side = float(np.sqrt(extent[0] * extent[1] / size))
    first, cells = first_per_cell(side)
    first, _ = first_per_cell(side * float(np.sqrt(min(len(first) / cells, 1.0))))
    return np.sort(order[first])


def mark_joined(mask: np.ndarray, points: np.ndarray, drawn: np.ndarray, x0: float, y0: float, cell: float,
                chunk: int = 65_536) -> None:
    """Set the raster cells (the four centres around each sample) along the segment from
    each of the points (N, 2) to the nearest of the drawn points (M, 2), in place: a point
    past the subsample's boundary (by up to the alpha scale) is then joined to the face,
    not an island the contours would leave out."""
    tree = cKDTree(drawn)
    for start in range(0, len(points), chunk):
        p = points[start:start + chunk]
        q = drawn[tree.query(p)[1]]
        steps = np.linspace(0.0, 1.0, int(np.ceil(float(np.linalg.norm(p - q, axis=1).max()) / cell)) + 2)
        along = (p[:, None, :] + steps[None, :, None] * (q - p)[:, None, :]).reshape(-1, 2)
        at = np.floor((along - [x0, y0]) / cell).astype(int)
        for di, dj in ((0, 0), (0, 1), (1, 0), (1, 1)):
            mask[at[:, 0] + di, at[:, 1] + dj] = True


def pieces_of_every_point(every: np.ndarray, drawn: np.ndarray, spacing: np.ndarray, face: np.ndarray,
                          others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points (indices into ``every`` (N, 2)) on the face and on the other pieces
    found from a subsample ``drawn`` (M, 2) of them (its spacing (M,), the indices of its
    face's and the other pieces' points): a point is on the piece of its nearest drawn
    point when within the alpha scale (``ALPHA`` times that point's spacing) of it, as
    the alpha shape joins points; farther, it is on none (a stray)."""
    piece = np.zeros(len(drawn), np.int8)  # 0: no piece, 1: the face, 2: another
    piece[others], piece[face] = 2, 1
    gap, nearest = cKDTree(drawn).query(every)
    joined = np.where(gap <= ALPHA * spacing[nearest], piece[nearest], 0)
    return np.flatnonzero(joined == 1), np.flatnonzero(joined == 2)


def footprint(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, distances: np.ndarray,
              mode: str | bool, verdict: Verdict | None = None, seen_along: np.ndarray | None = None,
              flattened: bool = False) -> Footprint:
    """The trim of an open fit from its points (N, 3), their foot-point parameters uv
    (N, 2) and distances (N,), and the points' distances to the trimmed surface;
    ``verdict``: the points the robust stage doubts (local outliers, junk joined to the
    surface from beyond its neighbours' reach), which mark no data, and those it spares,
    which may carry a side; ``seen_along`` (3,): the normal of the plane the patch was projected on (its
    data's straight edges bound the face, :func:`past_straight_edges`). Where ``trim:
    auto`` finds no gap but the surface runs past a straight edge by more than the loops'
    margin, the face is the whole domain cut there. A side of the surface that ends short
    of a straight edge by more than the margin is first carried past it
    (:func:`psonurbs.fitting.finish.straight_edges.reaching_domain`); without such an edge,
    a side that spared points (or local outliers) lie more than a spacing past is carried
    out to those the longer surface then passes near
    (:func:`psonurbs.fitting.finish.carried_sides.reaching_data`), and they mark the data
    on it. The face's surface is
    then the longer one, if it is trimmed and leaves no more points off it than the
    surface as fitted: outside its loops when cut at straight edges, farther than a
    point that marks the data may lie (the robust cut-off, or ``NEAR_EXACT`` spacings)
    when carried to points (a point past the fitted surface's side is as far off it as
    the side is short of it, whatever the trim). ``flattened``: the sheet was laid flat by its own geometry, and
    ``trim: auto`` keeps its loops (see the module docstring)."""
    if mode is False or len(uv) < 4:
        return Footprint(surface, None, np.asarray(distances, float), 0, 0.0, 0, 0, 0, 0.0)
    if flattened and mode == "auto":
        mode = True
    # from the points that mark the data (a stray past an edge moves no edge)
    scale = mean_speeds(surface)
    good = data_marks(distances, uv, scale, verdict)
    spacing = median_spacing(points[good])
    sigma = residual_scale(distances)
    band = max(CUTOFF_SIGMAS * sigma, NEAR_EXACT * spacing)  # a point this near marks the data
    within = REJUDGED_SIGMAS * sigma  # a local outlier this near is data
    rejudged = None if verdict is None else verdict.rejudged(distances, within)
    if rejudged is not verdict:  # local outliers the fit passes through mark the data too
        verdict, good = rejudged, data_marks(distances, uv, scale, rejudged)
    edges = None if seen_along is None else straight_edges(points[good], seen_along, ALPHA)
    domain, carried = None if edges is None else reaching_domain(surface, edges, spacing), None
    if domain is None and verdict is not None and verdict.spared is not None:
        reach = reaching_data(surface, points, uv, good, verdict, spacing, ALPHA, band, within)
        domain, carried = (None, None) if reach is None else (reach.domain, reach.points)
    if domain is not None:
        longer = surface.restricted(*domain)
        lo, width = domain_frame(domain)
        longer_uv, longer_distances = closest_parameters(longer, points, (uv - lo) / width)
        # a global search where the foot may move far: junk, and points past an edge
        moved = ~good | np.any((uv <= 0.0) | (uv >= 1.0), axis=1)
        if moved.any():
            longer_uv[moved], longer_distances[moved] = closest_parameters(longer, points[moved])
        face = trimmed_face(longer, points, longer_uv, longer_distances, mode, verdict, edges, carried)
        if face.trim is not None:
            as_fitted = trimmed_face(surface, points, uv, distances, mode, verdict, edges)
            if carried is None:  # cut at straight edges: no more points off the trimmed face
                longer_kept = face.points_outside <= as_fitted.points_outside
            else:  # carried to points past a side: off the fitted face whatever its trim, so by distance
                longer_kept = np.sum(face.distances > band) <= np.sum(as_fitted.distances > band)
            return face if longer_kept else as_fitted
    return trimmed_face(surface, points, uv, distances, mode, verdict, edges)


def trimmed_face(surface: NurbsSurface, points: np.ndarray, uv: np.ndarray, distances: np.ndarray,
                 mode: str | bool, verdict: Verdict | None, edges: StraightEdges | None,
                 carried: np.ndarray | None = None) -> Footprint:
    """:func:`footprint` on one surface, the data's straight ``edges`` given."""
    whole = Footprint(surface, None, np.asarray(distances, float), 0, 0.0, 0, 0, 0, 0.0)
    found = face_contours(surface, points, uv, distances, verdict, edges, carried)
    if found is None or len(found.face_points) < 0.5 * len(uv):  # a face without most of the points is not theirs
        return whole
    polygons, cut = found.polygons, False
    if mode == "auto" and found.widest_gap < ALPHA and found.edge_overrun <= EDGE_OVERRUN and len(found.polygons) == 1:
        if found.cut is None:
            return Footprint(surface, None, whole.distances, 0, 0.0, 0, found.fragments, found.fragment_points,
                             found.spacing)
        polygons, cut = found.cut, True
    lo, hi = -EDGE_OUTSET, 1.0 + EDGE_OUTSET
    loops = fitted_loops(polygons, found.tolerance, ((lo, hi), (lo, hi)), uv[found.face_points])
    trim = Trim(tuple(loops))
    empty = empty_share(surface, trim)
    outside = ~trim.contains(uv)
    dist = distances_to_face(surface, trim, points, uv, distances)
    return Footprint(surface, trim, dist, len(loops), empty, int(outside.sum()), found.fragments,
                     found.fragment_points, found.spacing, cut)


def fitted_loops(polygons: list[np.ndarray], tolerance: np.ndarray, bounds, must_inside: np.ndarray
                 ) -> list[TrimLoop]:
    """Closed B-splines for the contours (outer first).

    Each loop is first a cubic with the fewest control points, doubling from 8 up to
    ``MAX_CONTROL``, within ``tolerance`` (per direction, (2,)) of its contour. Then,
    together, the loops must be simple, apart, and hold ``must_inside`` (or pass within
    the tolerance of them, unless they are held on the domain's edge): a loop nearest a
    point left out gets twice the control points, and one already at the cap becomes its
    contour itself, simplified within the tolerance keeping its runs along the domain's
    edge (degree 1: it follows the contour, which lies a margin outside the points); if
    two loops cross, all do.
    """
    lo, hi = np.array([bounds[0][0], bounds[1][0]]), np.array([bounds[0][1], bounds[1][1]])
    clamped = [q[not_between_on_an_edge(q, lo, hi)] for q in (np.clip(p, lo, hi) for p in polygons)]
    probe = np.asarray(must_inside, float)
    on_edge = np.any((probe <= 0.0) | (probe >= 1.0), axis=1)

    def close_enough(loop: TrimLoop, polygon: np.ndarray) -> bool:
        """Whether the loop keeps within the tolerance of its contour (where it would add
        empty surface; cutting inside is judged by ``must_inside``)."""
        dense = np.concatenate([polygon, 0.5 * (polygon + np.roll(polygon, -1, axis=0))]) / tolerance
        return bool(cKDTree(dense).query(loop.polygon(4 * len(polygon)) / tolerance)[0].max() <= 1.0)

    def cubic(k: int, n: int) -> TrimLoop:
        return fit_closed_curve(polygons[k], n, 3, bounds=bounds, snap=tuple(2.0 * tolerance))

    def polyline(k: int, exact: bool = False) -> TrimLoop:
        if exact:
            return polygon_loop(clamped[k])
        on = (clamped[k] <= lo) | (clamped[k] >= hi)  # (M, 2): the vertices on the domain's edge
        run_ends = np.any(on & ~(np.roll(on, 1, axis=0) & np.roll(on, -1, axis=0)), axis=1)
        simple = simplify_closed(clamped[k], float(tolerance.min()), fixed=run_ends)
        return polygon_loop(simple[not_between_on_an_edge(simple, lo, hi)])  # the runs the dips between them left

    cap = [min(MAX_CONTROL, len(p) // 2) for p in clamped]
    counts, loops, exact = [], [], set()  # exact: the loops that are their contours themselves
    for k, p in enumerate(clamped):
        n, loop = 8, cubic(k, 8)
        close = close_enough(loop, p)
        while not close and 2 * n <= cap[k]:
            n *= 2
            loop = cubic(k, n)
            close = close_enough(loop, p)
        counts.append(n)
        loops.append(loop if close else polyline(k))
    while True:
        sampled = [loop.polygon() for loop in loops]
        if crossing(sampled):
            if len(exact) == len(loops):
                return loops  # the contours themselves
            blamed = set(range(len(loops)))
        else:
            out = ~inside(sampled, probe)
            missed = probe[out] / tolerance
            # a point within the tolerance of a cubic loop is as good as on it (the loop is
            # a margin outside the points, and only so precise), unless it is held on the
            # domain's edge: there the margin is cut off, the loop can run along the edge;
            # a simplified contour has no such excuse: the contour itself holds every point
            nearest = np.asarray([cKDTree(p / tolerance).query(missed)[0] for p in sampled]) if len(missed) \
                else np.zeros((len(loops), 0))
            simplified = np.array([loop.degree == 1 and k not in exact for k, loop in enumerate(loops)])
            far = (nearest.min(axis=0) > 1.0) | on_edge[out] | simplified[np.argmin(nearest, axis=0)] \
                if len(missed) else np.zeros(0, bool)
            if not far.any():
                return loops
            blamed = set(np.argmin(nearest[:, far], axis=0).tolist())
        changed = False
        for k in blamed:
            if loops[k].degree == 1:
                if k not in exact:  # simplified: the contour itself
                    loops[k] = polyline(k, exact=True)
                    exact.add(k)
                    changed = True
                continue
            changed = True
            if 2 * counts[k] <= cap[k]:
                counts[k] *= 2
                loops[k] = cubic(k, counts[k])
            else:
                loops[k] = polyline(k)
        if not changed:  # the points left out are nearest polylines: they lie off the face (strays)
            return loops


def not_between_on_an_edge(polygon: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mask (M,) of the vertices of a polygon (M, 2) clamped to the domain [lo, hi] that do
    not lie between two neighbours on the same edge of it: a contour that runs in and out
    past an edge leaves, clamped, runs of vertices in a row on the edge's line, which add
    nothing to the loop but vertices (its simplification keeps every run's ends); the
    runs' ends stay, and a vertex where the contour turns back along the edge."""
    keep = np.ones(len(polygon), bool)
    for k in (0, 1):
        t = polygon[:, 1 - k]
        between = (np.roll(t, 1) - t) * (np.roll(t, -1) - t) < 0
        for bound in (lo[k], hi[k]):
            on = polygon[:, k] == bound
            keep &= ~(on & np.roll(on, 1) & np.roll(on, -1) & between)
    return keep if keep.sum() >= 3 else np.ones(len(polygon), bool)


def empty_share(surface: NurbsSurface, trim: Trim, n: int = AREA_GRID) -> float:
    """Share of the surface's area outside the face (midpoint rule on an n x n grid of cells)."""
    (u0, u1), (v0, v1) = surface.domain_u, surface.domain_v
    us = u0 + (np.arange(n) + 0.5) / n * (u1 - u0)
    vs = v0 + (np.arange(n) + 0.5) / n * (v1 - v0)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    _, su, sv = surface.derivatives(uu.ravel(), vv.ravel())
    dA = np.linalg.norm(np.cross(su, sv), axis=1)
    inner = trim.contains(np.stack([uu.ravel(), vv.ravel()], axis=1))
    return float(1.0 - dA[inner].sum() / max(dA.sum(), 1e-300))


def footprint_notes(face: Footprint, n_points: int) -> list[str]:
    """What the user should know about the trim, for the fit's notes."""
    if face.trim is None:
        return []
    holes = face.loops - 1
    notes = [f"trimmed where the surface ran past the data's straight edges "
             f"({100 * face.empty_share:.2g}% of its area cut off)"] if face.cut else \
        [f"trimmed to the data's footprint: {face.loops} loop{'s' if face.loops > 1 else ''} "
         f"(the outer boundary{f' and {holes} hole' + ('s' if holes > 1 else '') if holes else ''}); "
         f"{100 * face.empty_share:.1f}% of the untrimmed surface had no data"]
    if face.points_outside:
        what = (f" ({face.fragment_points} in {face.fragments} detached piece{'s' if face.fragments > 1 else ''} "
                "of the footprint)") if face.fragment_points else ""
        notes.append(f"{face.points_outside} of {n_points} points lie off the trimmed face{what}; "
                     "rmse and max_error measure them to its boundary")
    return notes
