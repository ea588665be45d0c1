"""A four-sided flattening mapped onto the unit square, its four sides on the square's four.

The rigid flattening keeps a sheet's own shape: a cone sector unrolls to an annular
sector, which its minimum-area rectangle holds with a third of it empty. A tensor-product
patch wants the footprint's four sides on the square's sides (a cone's rulings and
circles as its parameter lines). For plane positions x (M, 2) of the embedded points:

1. **Footprint** (:func:`outline`): the alpha shape of x in the metric of their local
   spacing (:func:`psonurbs.fitting.finish.footprint.alpha_triangles`), its largest piece,
   and the outer boundary of that piece, a counter-clockwise loop of its vertices, with
   every fin and sliver of a notch cut off at its neck (:func:`without_detours`).
2. **Corners** (:func:`corners`): the boundary smoothed along its arc length by a Gaussian
   of width h / 3 (:class:`SmoothLoop`; h = ``SCALE`` local spacings of the boundary's
   vertices), and its turning at each vertex: the angle from the chord over the arc
   length h before the vertex to the chord over h after it. The corners are the peaks
   turning at least ``CORNER`` in magnitude (each the largest within h), each placed
   where its two sides, extrapolated, meet (:func:`corner_place`). Four-sided: exactly
   four peaks, all convex (a corner beside a concave side, or where the data thin out,
   may turn less at h: :func:`corners`).
3. **Boundary values** (:func:`boundary_values`): each side a curve from its corner to
   the next (the boundary smoothed over a spacing), mapped by its arc length onto a side
   of the square, u along the pair of opposite sides that are longer; each boundary
   vertex goes to its nearest point on its side's curve, as far inside the square's side
   as it lies inside the curve (a random sample's edge is ragged), in the scale of the
   two sides across.
4. **Interior** (:func:`square_map`): with the cotangent weights of the piece's triangles
   (the Laplacian reproduces affine maps, linear precision; its weights are positive on a
   Delaunay triangulation), first the harmonic map ``L u = 0``, ``L v = 0`` with the
   boundary values fixed (holes, unconstrained, keep natural boundary conditions); then
   each coordinate again with each triangle's weights scaled by the gradient of the other:

       div(|grad v| grad u) = 0,   div(|grad u| grad v) = 0.

   Both keep affine maps (the scale is constant there). On an annular sector of radii
   r0 < r1 the harmonic v is (log r - log r0) / (log r1 - log r0), up to 8.6% of the range
   off the radius (at r1 / r0 = 2); weighted by |grad u| ~ 1 / r, the equation is
   d/dr (r (1/r) dv/dr) = 0, so v is affine in r, and u (harmonic with a weight that is a
   function of r) stays the angle: the angle and the ruling, exactly.
5. **Every point** (:meth:`SquareMap.place`): inside a triangle of the piece, by its
   barycentric coordinates; outside (past the ragged boundary, a stray's cut offset), its
   nearest vertex's (u, v) plus its offset through that vertex's mean Jacobian; clipped
   to the square.

Cost: a Delaunay triangulation and three sparse solves on the M <= 5,000 embedded points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.linalg import splu
from scipy.spatial import Delaunay, cKDTree
from threadpoolctl import threadpool_limits

from psonurbs.fitting.finish.footprint import alpha_triangles, local_spacing, pieces

SCALE = 6.0  # local spacings of the boundary: the arc length h of the chords that measure its turning
# A corner turns at least 45 degrees: half the turn of a rectangle's corner (a regular
# octagon's corners turn 45). A quad's four corners and its sides' net turning make 360
# degrees, so a real corner turns well over it; a bend turning less leaves an angle of
# over 135 degrees inside, which a side of a patch can pass straight through. At the
# scale h, smoothed, a random sample's ragged boundary turns by up to about 30 degrees
# and a right-angled corner by 55 to 80 (it is rounded within the chords).
CORNER = np.radians(45.0)
SIDES = 4
SIDE_OFFSET = 1.5  # h: a side's own turning is read this far from a corner (its chords clear of the corner)
NECK = 1.5  # local spacings: a boundary coming back this close to itself ...
DETOUR = 2.0 * SCALE  # ... after at most this long a detour (a fin or a notch) is cut there


@dataclass(frozen=True)
class Outline:
    """The footprint of plane positions x (M, 2): the alpha shape's largest piece."""

    tri: Delaunay  # of x and four far corners (indices M .. M+3)
    faces: np.ndarray  # (T, 3) the piece's triangles, vertex indices into x, counter-clockwise
    simplices: np.ndarray  # (T,) each face's simplex in ``tri``
    loop: np.ndarray  # (B,) the outer boundary's vertices, counter-clockwise
    loop_spacing: np.ndarray  # (B,) the local spacing of each of them

    @property
    def spacing(self) -> float:
        """The median local spacing of the outer boundary's vertices."""
        return float(np.median(self.loop_spacing))


@dataclass(frozen=True)
class SmoothLoop:
    """A closed polygon p (B, 2) and its smoothing: the polygon resampled evenly along its
    arc length and filtered by a Gaussian along it (wrapping round)."""

    p: np.ndarray  # (B, 2)
    s: np.ndarray  # (B,) arc length of each vertex along the polygon
    length: float  # the polygon's
    t: np.ndarray  # (F + 1,) arc length (along the polygon) of the samples, the first repeated last
    curve: np.ndarray  # (F + 1, 2) the smoothed samples, the first repeated last

    @classmethod
    def of(cls, p: np.ndarray, sigma: float, step: float) -> "SmoothLoop":
        """``p`` smoothed by a Gaussian of width ``sigma``, sampled every ``step`` at most."""
        seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
        length = float(seg.sum())
        s = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
        fine = max(int(np.ceil(length / step)), 8)
        t = np.arange(fine + 1) * (length / fine)
        closed = np.vstack([p, p[:1]])
        raw = np.column_stack([np.interp(t[:-1], np.append(s, length), closed[:, k]) for k in range(2)])
        curve = ndimage.gaussian_filter1d(raw, sigma=sigma * fine / length, axis=0, mode="wrap")
        return cls(p, s, length, t, np.vstack([curve, curve[:1]]))

    def at(self, s: np.ndarray) -> np.ndarray:
        """(n, 2) the smoothed curve at arc lengths s (n,) along the polygon (any, wrapping)."""
        s = np.asarray(s, float) % self.length
        return np.column_stack([np.interp(s, self.t, self.curve[:, k]) for k in range(2)])

    def turning(self, h: float | np.ndarray, s: np.ndarray | None = None) -> np.ndarray:
        """(B,) the turning (radians, positive to the left) at each vertex (or at arc
        lengths ``s`` (B,) along the polygon): from the chord of the smoothed curve over
        arc length h (one, or (B,): each vertex's own) before it to the chord over h after it."""
        s = self.s if s is None else s
        here = self.at(s)
        before, after = here - self.at(s - h), self.at(s + h) - here
        turn = np.arctan2(after[:, 1], after[:, 0]) - np.arctan2(before[:, 1], before[:, 0])
        return (turn + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class Corners:
    """The outer boundary's corners, in its order."""

    at: np.ndarray  # (K,) indices into the loop of the peaks of the turning
    turning: np.ndarray  # (K,) radians, positive where convex
    points: np.ndarray  # (K, 2) the corners' places (each side's run extrapolated to the peak)
    split: np.ndarray  # (K,) arc length along the loop's polygon where one side ends and the next begins

    @property
    def four_sided(self) -> bool:
        return len(self.at) == SIDES and bool(np.all(self.turning > 0))


@dataclass(frozen=True)
class SquareMap:
    """The footprint on the unit square: (u, v) of its vertices and how to place any point."""

    outline: Outline
    x: np.ndarray  # (M, 2) plane positions
    uv: np.ndarray  # (M, 2) of the faces' vertices in [0, 1]^2 (other rows unused)
    jacobians: np.ndarray  # (M, 2, 2) d(u, v)/dx of each vertex, the mean over its faces by area

    def place(self, q: np.ndarray) -> np.ndarray:
        """(N, 2) (u, v) of plane positions q (N, 2) (see the module docstring, step 5)."""
        tri = self.outline.tri
        is_face = np.zeros(len(tri.simplices), bool)
        is_face[self.outline.simplices] = True
        with threadpool_limits(limits=1):  # its first call solves a 2 x 2 system per simplex by LAPACK:
            simplex = tri.find_simplex(q)  # threaded, that took seconds on a busy machine
        hit = (simplex >= 0) & is_face[np.maximum(simplex, 0)]
        out = np.empty((len(q), 2))
        corner = tri.simplices[simplex[hit]]  # (n, 3)
        a, b, c = (tri.points[corner[:, k]] for k in range(3))
        p = q[hit]
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        lb = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (p[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])) / det
        lc = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (p[:, 0] - a[:, 0])) / det
        bary = np.column_stack([1.0 - lb - lc, lb, lc])
        out[hit] = np.einsum("nk,nkc->nc", bary, self.uv[corner])
        if not hit.all():
            used = np.unique(self.outline.faces)
            near = used[cKDTree(self.x[used]).query(q[~hit])[1]]
            out[~hit] = self.uv[near] + np.einsum("nab,nb->na", self.jacobians[near], q[~hit] - self.x[near])
        return np.clip(out, 0.0, 1.0)


def counter_clockwise(tri: Delaunay) -> tuple[np.ndarray, np.ndarray]:
    """The simplices (S, 3) of ``tri`` ordered counter-clockwise, and their neighbours
    (S, 3; neighbour k opposite vertex k, -1 none) permuted alike."""
    s, nb = tri.simplices.copy(), tri.neighbors.copy()
    a, b, c = (tri.points[s[:, k]] for k in range(3))
    clockwise = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
    s[clockwise] = s[clockwise][:, [0, 2, 1]]
    nb[clockwise] = nb[clockwise][:, [0, 2, 1]]
    return s, nb


def boundary_loops(simplices: np.ndarray, neighbours: np.ndarray, face: np.ndarray) -> list[np.ndarray]:
    """The boundary loops (vertex indices, the face on the left) of the triangles ``face``
    (S,) bool of counter-clockwise ``simplices`` (S, 3) with ``neighbours`` (S, 3).

    Edge k of triangle t runs from its vertex (k+1) % 3 to (k+2) % 3; it is on the
    boundary when the triangle across it is not a face. From a boundary edge a -> b the
    next one is found by turning about b through the faces around it (across b's other
    edge in each), so a vertex where two parts of the face touch is passed through, not
    jumped."""
    across = np.where(neighbours >= 0, face[np.maximum(neighbours, 0)], False)
    todo = {(int(t), int(k)) for t, k in np.argwhere(face[:, None] & ~across)}
    loops = []
    while todo:
        start = min(todo)
        t, k = start
        loop = []
        while True:
            todo.discard((t, k))
            loop.append(int(simplices[t, (k + 1) % 3]))
            b = simplices[t, (k + 2) % 3]
            k = (k + 1) % 3  # t's edge from b
            while across[t, k]:
                t = int(neighbours[t, k])
                k = (int(np.flatnonzero(simplices[t] == b)[0]) + 2) % 3
            if (t, k) not in todo:
                break
        loops.append(np.array(loop))
    return loops


def signed_area(p: np.ndarray) -> float:
    """The signed area of the closed polygon p (B, 2) (positive: counter-clockwise)."""
    q = np.roll(p, -1, axis=0)
    return 0.5 * float(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]))


def outline(x: np.ndarray) -> Outline | None:
    """Step 1: the alpha shape's largest piece (by area) and its outer boundary (None: no
    triangle kept)."""
    spacing = local_spacing(x)
    tri, kept = alpha_triangles(x, spacing)
    if not kept.any():
        return None
    label = pieces(tri, kept)
    simplices, neighbours = counter_clockwise(tri)
    a, b, c = (tri.points[simplices[:, k]] for k in range(3))
    area = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    face = label == int(np.argmax(np.bincount(label[kept], weights=area[kept])))
    loops = boundary_loops(simplices, neighbours, face)
    outer = loops[int(np.argmax([signed_area(x[loop]) for loop in loops]))]
    return Outline(tri, simplices[face], np.flatnonzero(face), outer, spacing[outer])


def without_detours(p: np.ndarray, spacing: float) -> np.ndarray:
    """(B,) bool: the vertices of the closed polygon p (B, 2) to keep when every detour is
    cut off at its neck: where two vertices within ``NECK`` spacings of each other are
    ``DETOUR`` spacings or less apart along the polygon (the shorter way, and more than a
    right-angled corner's ``NECK`` times sqrt 2), the vertices between them go. An alpha
    shape of a random sample grows a one-triangle fin or opens a sliver of a notch here
    and there, most where its spacing is widest (at corners); such a detour turns by 180
    degrees each way and would pass for corners."""
    seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
    length = float(seg.sum())
    s = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    keep = np.ones(len(p), bool)
    pairs = cKDTree(p).query_pairs(NECK * spacing, output_type="ndarray")
    if not len(pairs):
        return keep
    i, j = pairs.min(axis=1), pairs.max(axis=1)
    ahead = s[j] - s[i]  # along the polygon from i to j; the other way round is length - ahead
    shortest, least = np.minimum(ahead, length - ahead), NECK * np.sqrt(2.0) * spacing
    detour = (shortest > least) & (shortest <= DETOUR * spacing)
    for a, b, forward in zip(i[detour], j[detour], (ahead <= length - ahead)[detour]):
        if forward:
            keep[a + 1:b] = False
        else:
            keep[b + 1:] = False
            keep[:a] = False
    return keep


def corners(loop: SmoothLoop, h: float, spacing: np.ndarray | None = None) -> Corners:
    """Step 2: the vertices of the loop turning at least ``CORNER`` at the scale h, each
    the largest turn within arc length h of it (the first of equals), and their places.

    With the local ``spacing`` (B,) of the loop's vertices, a fourth corner may be found
    where three are: where the data thin out, a corner is rounded over a spacing of the
    sparse sampling (a random sample does not reach it), and at the scale h, set by the
    median spacing, it turns less than its angle (the sparse corners a 20-fold density
    gradient hid: 29 to 43 degrees). So where only three peaks turn ``CORNER``, the largest
    other convex peak turning at least half of it is the fourth if, measured at ``SCALE``
    of its own local spacing, it turns ``CORNER`` too. Where the sampling is even, its
    scale is h, and a peak that turns less is no corner there either.

    Where the corners are still fewer than four, the convex peaks turning at least half of
    ``CORNER`` complete them if they turn ``CORNER`` with a concave side's own turning
    added back (:func:`concave_added`, at h or at their own scale) and make exactly four:
    the chord from a corner along a side that curves inwards (the inner arc of a C, a
    helicoid laid flat) turns away with that side, and a right angle there read 35 to 49
    degrees. Only the concave part counts: a convex side, or the next corner read across
    a short side, adds nothing."""
    turn = loop.turning(h)
    size = np.abs(turn)
    index = np.arange(len(size))
    peaks, weaker = [], []
    for i in np.flatnonzero(size >= 0.5 * CORNER):
        gap = np.abs(loop.s - loop.s[i])
        near = np.minimum(gap, loop.length - gap) <= h
        if size[i] >= size[near].max() and not np.any(size[near & (index < i)] == size[i]):
            (peaks if size[i] >= CORNER else weaker).append(i)
    own = np.full(len(size), h) if spacing is None else np.maximum(SCALE * np.asarray(spacing, float), h)
    if spacing is not None and len(peaks) == SIDES - 1 and np.all(turn[peaks] > 0):
        at_own_scale = loop.turning(own)
        rounded = [i for i in weaker if turn[i] > 0 and at_own_scale[i] >= CORNER]
        if rounded:
            peaks = sorted(peaks + [max(rounded, key=lambda i: turn[i])])
    convex = [i for i in weaker if turn[i] > 0 and i not in peaks]
    if len(peaks) < SIDES and convex:
        at = loop.s[convex]
        reading = np.max([concave_added(loop, at, scale) for scale in (np.full(len(at), h), own[convex])], axis=0)
        completing = [i for i, t in zip(convex, reading) if t >= CORNER]
        if len(peaks) + len(completing) == SIDES:
            peaks = sorted(peaks + completing)
    peaks = np.array(peaks, dtype=int)
    places = [corner_place(loop, i, h) for i in peaks]
    return Corners(peaks, turn[peaks], np.array([p for p, _ in places]).reshape(-1, 2),
                   np.array([s for _, s in places]))


def concave_added(loop: SmoothLoop, at: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(n,) the turning at arc lengths ``at`` (n,) over chords h (n,), plus half the
    turning of each side ``SIDE_OFFSET`` h away where that side curves inwards (negative):
    a corner's own turning where the chord beside it follows a concave side."""
    sides = [np.minimum(loop.turning(h, at + sign * SIDE_OFFSET * h), 0.0) for sign in (-1.0, 1.0)]
    return loop.turning(h, at) - 0.5 * (sides[0] + sides[1])


def corner_place(loop: SmoothLoop, i: int, h: float) -> tuple[np.ndarray, float]:
    """Where the corner whose turning peaks at vertex i is: the mean of the two sides'
    runs (the vertices from h / 4 to 3 h / 2 along the polygon before it and after it),
    each fitted by a line in its arc length and extrapolated to vertex i's; and the arc
    length of the polygon's point nearest it, where the sides are split.

    A random sample does not reach its footprint's corner: the vertex where the turning
    peaks lies a spacing or so inside (0.3 to 1.2 spacings on an annular sector's four
    corners over six draws; extrapolated, 0.1 to 1.0). The sides' arc lengths are taken
    from this place: from the peak, a radius of the sector was 4% short of its length
    at one end, and its points' parameters as much off."""
    gap = (loop.s - loop.s[i] + 0.5 * loop.length) % loop.length - 0.5 * loop.length  # signed, wrapped
    ends = []
    for sign in (-1.0, 1.0):
        run = (sign * gap >= 0.25 * h) & (sign * gap <= 1.5 * h)
        if np.sum(run) < 2:
            return loop.p[i], float(loop.s[i])
        ends.append([np.polyval(np.polyfit(gap[run], loop.p[run, k], 1), 0.0) for k in range(2)])
    place = np.mean(ends, axis=0)
    near = np.flatnonzero(np.abs(gap) <= h)
    near = near[np.argsort(gap[near])]  # in order along the polygon, across its start
    a, b = loop.p[near], loop.p[(near + 1) % len(loop.p)]
    arc, _ = nearest_on_polyline(place[None, :], a, b)
    return place, float((loop.s[near[0]] + arc[0]) % loop.length)


def nearest_on_polyline(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For points q (n, 2) and the polyline of segments a -> b (F, 2 each, end to end):
    the arc length along it of each point's nearest point on it, and the point's signed
    distance from it (positive to its left)."""
    ab = b - a
    length = np.linalg.norm(ab, axis=1)
    start = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    rel = q[:, None, :] - a[None, :, :]  # (n, F, 2)
    share = np.clip(np.sum(rel * ab, axis=2) / np.maximum(length ** 2, 1e-300), 0.0, 1.0)
    off = rel - share[:, :, None] * ab
    k = np.argmin(np.sum(off * off, axis=2), axis=1)
    rows = np.arange(len(q))
    side = ab[k, 0] * off[rows, k, 1] - ab[k, 1] * off[rows, k, 0]
    return start[k] + share[rows, k] * length[k], np.sign(side) * np.linalg.norm(off[rows, k], axis=1)


def boundary_values(loop: SmoothLoop, found: Corners, spacing: float) -> np.ndarray:
    """Step 3: (B, 2) the (u, v) of each vertex of the loop, in its order. Each side runs
    from its corner's place to the next corner's along the loop smoothed over a spacing
    (straight over the ``2 * spacing`` next to each corner, where the smoothing rounds the
    corner off); a vertex of the side goes to its nearest point on that curve: along the
    side its share of the curve's length, across it its distance inside the curve over
    the mean length of the two sides across (outside: on the square's side). Side 0 runs
    along u = [0, 1] at v = 0 when sides 0 and 2 are the longer pair (else side 1)."""
    n = len(loop.p)
    order = np.argsort(found.split)
    split, places = found.split[order], found.points[order]
    which = (np.searchsorted(split, loop.s, side="right") - 1) % SIDES  # vertex -> side (index into split)
    curves = []
    for k in range(SIDES):
        start, end = split[k], split[(k + 1) % SIDES] + (loop.length if k == SIDES - 1 else 0.0)
        inner = np.arange(start + 2.0 * spacing, end - 2.0 * spacing, 0.5 * spacing)
        curves.append(np.vstack([places[k], loop.at(inner), places[(k + 1) % SIDES]]))
    lengths = np.array([np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)) for c in curves])
    first = 0 if lengths[0] + lengths[2] >= lengths[1] + lengths[3] else 1
    out = np.empty((n, 2))
    for k, curve in enumerate(curves):
        on = np.flatnonzero(which == k)
        arc, inside = nearest_on_polyline(loop.p[on], curve[:-1], curve[1:])
        t = np.clip(arc / lengths[k], 0.0, 1.0)
        d = np.clip(inside / (0.5 * (lengths[k - 1] + lengths[(k + 1) % SIDES])), 0.0, 1.0)
        out[on] = [np.column_stack([t, d]), np.column_stack([1 - d, t]),
                   np.column_stack([1 - t, 1 - d]), np.column_stack([d, 1 - t])][(k - first) % SIDES]
    return out


def cotangent_weights(x: np.ndarray, faces: np.ndarray, scale: np.ndarray | None = None) -> sp.csr_array:
    """(M, M) symmetric weights w_ij = sum over the faces (T, 3) at edge ij of
    scale_t cot(angle opposite ij) / 2 (scale (T,), 1 if None), kept just above 0: a hole's
    edge has one face, whose angle there may be obtuse, and a face held on one side of the
    square has no gradient; every edge of the piece keeps it connected, so the solve has
    one answer."""
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3], faces[:, k]
        e1, e2 = x[i] - x[o], x[j] - x[o]
        cross = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        w = 0.5 * np.sum(e1 * e2, axis=1) / np.maximum(cross, 1e-300) * (1.0 if scale is None else scale)
        rows += [i, j]
        cols += [j, i]
        vals += [w, w]
    m = len(x)
    weights = sp.csr_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(m, m))
    weights.sum_duplicates()
    weights.data = np.maximum(weights.data, 1e-9 * float(np.abs(weights.data).mean()))
    return weights


def dirichlet_solve(weights: sp.csr_array, fixed: np.ndarray, values: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(M, c) minimising sum_ij w_ij |f_i - f_j|^2 over the ``free`` vertices with the
    ``fixed`` ones at ``values`` (F, c): ``L_ff f_f = -L_fb values``, L = diag(W 1) - W."""
    laplacian = (sp.diags(np.asarray(weights.sum(axis=1)).ravel()) - weights).tocsr()
    out = np.zeros((weights.shape[0], values.shape[1]))
    out[fixed] = values
    out[free] = splu(laplacian[free][:, free].tocsc()).solve(-(laplacian[free][:, fixed] @ values))
    return out


def gradients(x: np.ndarray, faces: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, c, 2) the gradient of each column of the piecewise linear f (M, c) on each
    counter-clockwise face (T, 3), and the faces' areas (T,)."""
    e1, e2 = x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    d1, d2 = f[faces[:, 1]] - f[faces[:, 0]], f[faces[:, 2]] - f[faces[:, 0]]  # (T, c): grad . e1, grad . e2
    gx = (d1 * e2[:, 1:2] - d2 * e1[:, 1:2]) / det[:, None]
    gy = (d2 * e1[:, 0:1] - d1 * e2[:, 0:1]) / det[:, None]
    return np.stack([gx, gy], axis=-1), 0.5 * det


def square_map(x: np.ndarray) -> tuple[SquareMap | None, list[float]]:
    """The four-sided map of plane positions x (M, 2) onto the unit square (None if the
    footprint is not four-sided), and the turning of the corners found (degrees)."""
    found = outline(x)
    if found is None:
        return None, []
    h = SCALE * found.spacing
    kept = without_detours(x[found.loop], found.spacing)
    boundary = found.loop[kept]
    where = corners(SmoothLoop.of(x[boundary], h / 3.0, h / 12.0), h, found.loop_spacing[kept])
    turns = [round(float(np.degrees(t)), 1) for t in where.turning]
    if not where.four_sided:
        return None, turns
    values = boundary_values(SmoothLoop.of(x[boundary], found.spacing, 0.25 * found.spacing), where, found.spacing)
    fixed, first = np.unique(boundary, return_index=True)  # a vertex passed twice keeps its first visit
    values = values[first]
    faces = found.faces
    free = np.setdiff1d(np.unique(faces), fixed)
    uv = dirichlet_solve(cotangent_weights(x, faces), fixed, values, free)
    speed = np.linalg.norm(gradients(x, faces, uv)[0], axis=2)  # (T, 2): |grad u|, |grad v|
    u = dirichlet_solve(cotangent_weights(x, faces, speed[:, 1]), fixed, values[:, :1], free)
    v = dirichlet_solve(cotangent_weights(x, faces, speed[:, 0]), fixed, values[:, 1:], free)
    uv = np.column_stack([u, v])
    grad, area = gradients(x, faces, uv)
    jacobians, weight = np.zeros((len(x), 2, 2)), np.zeros(len(x))
    for k in range(3):
        np.add.at(jacobians, faces[:, k], area[:, None, None] * grad)
        np.add.at(weight, faces[:, k], area)
    jacobians /= np.maximum(weight, 1e-300)[:, None, None]
    return SquareMap(found, x, uv, jacobians), turns


def aligned(uv: np.ndarray, like: np.ndarray) -> np.ndarray:
    """uv (N, 2) with u and v each reversed where that agrees better with ``like`` (N, 2):
    a parameter's direction is free, and keeping another map's keeps a fit near it."""
    flip = np.sum((uv - 0.5) * (like - 0.5), axis=0) < 0
    return np.where(flip, 1.0 - uv, uv)
