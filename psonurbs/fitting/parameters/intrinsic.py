"""Intrinsic first parameters of an open surface: the cloud's neighbourhood graph laid
flat in the plane, as rigidly as the surface allows.

No plane sees a curled sheet or a twisted strip as a height field, so their first
parameters come from the surface itself. On at most ``EMBEDDED_POINTS`` of the points:

1. **Graph** (:func:`surface_graph`): the k nearest neighbours of every point, a tangent
   frame ``(e1, e2, n)`` by PCA of each neighbourhood, and the normals oriented
   consistently (propagated along the minimum spanning tree of ``1 - |n_i . n_j|``,
   Hoppe et al. 1992). The edges are the mutual neighbours (each among the other's k
   nearest): a stray point off the surface keeps none and falls out of the graph's
   largest part, which alone is embedded. Each edge seen from its source,
   ``t_ij = [e1_i, e2_i] (x_j - x_i)``, is the neighbour's offset in the source's tangent plane.
2. **Geodesic start** (:func:`geodesic_embedding`): landmark Isomap (de Silva &
   Tenenbaum 2003). Graph distances (Dijkstra) from ``LANDMARKS`` farthest-point
   landmarks, classical MDS of the landmarks, every point placed from its squared
   distances to them. Exact for a developable surface up to the graph's zigzag (a few
   per cent), fold-free, but it stretches where the graph's paths zigzag.
3. **As-rigid-as-possible** (:func:`rigid_embedding`, Sorkine & Alexa 2007 on the graph,
   free boundary): minimise

       E(U, R) = sum_i sum_j w_ij |(u_j - u_i) - R_i t_ij|^2,   w_ij = 1 / |x_j - x_i|^2,

   over the plane positions U (M, 2) and a rotation R_i per point, alternately: each
   R_i is the rotation nearest to ``S_i = sum_j w_ij (u_j - u_i) t_ij^T`` (closed form in
   2D), then U solves the graph Laplacian system ``L U = A^T W (R t)`` (factored once);
   the rounds are Anderson-mixed (plain ones leave 1% of bending after 30 rounds).
   The edges' lengths are kept, so a developable surface is unrolled isometrically;
   elsewhere (a twisted strip, a cap) the stretch is spread evenly.
4. **All points** (:func:`extended`): a point off the sample takes its nearest sample
   point's position plus its offset in that point's frame, rotated by its R_i (the
   offset cut to the neighbourhood's reach, so a stray is not flung out).

Cost: O(N log M) for the nearest sample point of every point, the rest on the M <= ``EMBEDDED_POINTS``.

The plane coordinates then go onto the unit square, scaled along the rectangle they fill
best, as a plane projection is (:func:`psonurbs.fitting.parameters.parametrisation.unit_square`);
but a flattening with four corners that its rectangle does not fill (a trapezoid, an
annular sector: a cone's or a band's) is mapped with its four sides on the square's
sides (:mod:`psonurbs.fitting.parameters.four_sided`), unless that map folds where the
flattening does not (:func:`intrinsic_parameters`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from psonurbs.fitting.finish.polish import AndersonMixing

from .four_sided import aligned, square_map
from .parametrisation import FILL_MARGIN, Parametrisation, fill, fill_cells, unit_square

NEIGHBOURS = 10  # graph degree: enough for a connected, rigid graph, few enough to stay local
EMBEDDED_POINTS = 5000  # points embedded (the others follow by their local frame)
LANDMARKS = 24
RIGID_ROUNDS = 30  # local/global rounds, Anderson-mixed: a 250-degree cylinder section is unrolled to 6e-5 RMS
CONVERGED = 1e-9  # relative energy drop below which the rounds stop
# of the points: the four-sided map may fold on this many more than the flattening, the
# share of a fit's surface its self-check lets fold. A ragged boundary's vertex or two can
# turn over (a 270-degree cone sector: 1 of 4,000 points), which is no fold of the map.
FOLD_MARGIN = 0.002


@dataclass(frozen=True)
class SurfaceGraph:
    """The k-nearest-neighbour graph of a cloud with an oriented tangent frame per point."""

    points: np.ndarray  # (M, 3)
    neighbours: np.ndarray  # (M, k) indices of each point's nearest neighbours
    lengths: np.ndarray  # (M, k) their distances
    mutual: np.ndarray  # (M, k) bool: the edges of the graph (each end among the other's neighbours)
    frames: np.ndarray  # (M, 3, 3) rows e1, e2, n: right-handed, n oriented consistently
    component: np.ndarray  # (M,) bool: in the largest connected part of the graph

    @property
    def normals(self) -> np.ndarray:
        return self.frames[:, 2]

    def offsets(self) -> np.ndarray:
        """(M, k, 2) each neighbour's offset in its source's tangent plane, ``t_ij``."""
        d = self.points[self.neighbours] - self.points[:, None, :]
        return np.einsum("nkc,nac->nka", d, self.frames[:, :2])

    def edge_weights(self) -> np.ndarray:
        """(M, k) ``1 / |x_j - x_i|^2`` on the graph's edges (every edge judged by its
        relative stretch), 0 for a neighbour that is not an edge."""
        return np.where(self.mutual, 1.0 / np.maximum(self.lengths, 1e-300) ** 2, 0.0)

    def lengths_matrix(self) -> sp.csr_array:
        """Symmetric sparse matrix of edge lengths (the graph for Dijkstra)."""
        return edge_matrix(self.neighbours, self.mutual, self.lengths)


def edge_matrix(neighbours: np.ndarray, mutual: np.ndarray, values: np.ndarray) -> sp.csr_array:
    """(M, M) sparse matrix holding ``values`` (M, k) on the mutual edges (symmetric)."""
    m, k = neighbours.shape
    rows = np.repeat(np.arange(m), k).reshape(m, k)
    return sp.csr_array((values[mutual], (rows[mutual], neighbours[mutual])), shape=(m, m))


def mutual_neighbours(neighbours: np.ndarray) -> np.ndarray:
    """(M, k) bool: j is among i's neighbours and i among j's. A stray point's nearest
    neighbours on the surface have nearer neighbours of their own, so it keeps no edge
    to them and falls out of the graph's largest part."""
    m, k = neighbours.shape
    rows = np.repeat(np.arange(m), k)
    adjacency = sp.csr_array((np.ones(m * k), (rows, neighbours.ravel())), shape=(m, m))
    return (adjacency.T[rows, neighbours.ravel()] > 0).reshape(m, k)


def surface_graph(points: np.ndarray, neighbours: int = NEIGHBOURS) -> SurfaceGraph:
    """Neighbours, tangent frames and consistently oriented normals of ``points`` (M, 3)."""
    k = min(neighbours, len(points) - 1)
    lengths, idx = cKDTree(points).query(points, k=k + 1)
    lengths, idx = lengths[:, 1:], idx[:, 1:]
    mutual = mutual_neighbours(idx)
    hood = np.concatenate([points[:, None, :], points[idx]], axis=1)
    hood = hood - hood.mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", hood, hood))
    normals = oriented(vecs[:, :, 0], idx, mutual)
    e1 = vecs[:, :, 2]
    frames = np.stack([e1, np.cross(normals, e1), normals], axis=1)
    _, labels = csgraph.connected_components(edge_matrix(idx, mutual, lengths), directed=False)
    largest = np.argmax(np.bincount(labels))
    return SurfaceGraph(points, idx, lengths, mutual, frames, labels == largest)


def oriented(normals: np.ndarray, neighbours: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Unoriented normals (M, 3) flipped to agree along the minimum spanning tree of
    ``1 - |n_i . n_j|`` over the ``edges`` (M, k mask of ``neighbours``; Hoppe et al. 1992): the flip of each point is the product of
    the flips along its tree path, done for all points at once by pointer doubling."""
    m = len(normals)
    cost = 1.0 + 1e-9 - np.abs(np.einsum("nc,nkc->nk", normals, normals[neighbours]))  # > 0: zero means no edge
    tree = csgraph.minimum_spanning_tree(edge_matrix(neighbours, edges, cost))
    parent = np.arange(m)
    n_parts, labels = csgraph.connected_components(tree, directed=False)
    for part in range(n_parts):
        root = int(np.argmax(labels == part))
        order, pred = csgraph.breadth_first_order(tree, root, directed=False, return_predecessors=True)
        parent[order[1:]] = pred[order[1:]]
    flip = np.where(np.sum(normals * normals[parent], axis=1) < 0, -1.0, 1.0)
    while np.any(parent != parent[parent]):  # flip[i] becomes the product up to the root
        flip, parent = flip * flip[parent], parent[parent]
    return normals * flip[:, None]


def farthest_landmarks(lengths: sp.csr_array, count: int, start: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` landmarks by farthest-point sampling in graph distance from ``start``,
    and their graph distances to every point (count, M)."""
    seen = csgraph.dijkstra(lengths, directed=False, indices=[start])[0]
    landmarks, distances = [], []
    nearest = np.where(np.isfinite(seen), seen, -1.0)
    for _ in range(count):
        landmarks.append(int(np.argmax(nearest)))
        distances.append(csgraph.dijkstra(lengths, directed=False, indices=[landmarks[-1]])[0])
        nearest = np.minimum(nearest, np.where(np.isfinite(distances[-1]), distances[-1], -1.0))
    return np.array(landmarks), np.array(distances)


def geodesic_embedding(graph: SurfaceGraph, landmarks: int = LANDMARKS) -> np.ndarray:
    """(M, 2) landmark Isomap of the graph's largest part (others at the origin).

    With D (L, M) the graph distances from the landmarks and D_L their (L, L) block:
    B = -1/2 J D_L^2 J (J centres), its top two eigenpairs (lambda_k, v_k) place the
    landmarks, and point i goes to ``-1/2 [v_k / sqrt(lambda_k)]^T (D_i^2 - mean_L D_L^2)``.
    """
    part = np.flatnonzero(graph.component)
    lengths = graph.lengths_matrix()[part][:, part]
    lm, dist = farthest_landmarks(lengths, min(landmarks, len(part)), 0)
    squared = dist ** 2
    block = squared[:, lm]
    centred = block - block.mean(axis=0) - block.mean(axis=1, keepdims=True) + block.mean()
    values, vectors = np.linalg.eigh(-0.5 * centred)
    top = np.argsort(values)[::-1][:2]
    lift = vectors[:, top] / np.sqrt(np.maximum(values[top], 1e-300))
    uv = np.zeros((len(graph.points), 2))
    uv[part] = -0.5 * (squared - block.mean(axis=1, keepdims=True)).T @ lift
    return uv


def local_maps(graph: SurfaceGraph, uv: np.ndarray) -> np.ndarray:
    """(M, 2, 2) ``S_i = sum_j w_ij (u_j - u_i) t_ij^T``: the least-squares linear map from
    each tangent plane to the parameter plane (up to a positive scale). ``det S_i < 0``:
    the parametrisation reverses the surface's orientation there (a fold)."""
    du = uv[graph.neighbours] - uv[:, None, :]
    return np.einsum("nk,nka,nkb->nab", graph.edge_weights(), du, graph.offsets())


def reversed_points(graph: SurfaceGraph, uv: np.ndarray) -> np.ndarray:
    """(M,) bool: where ``uv`` folds, its local map reverses the orientation that most of
    the graph's largest part has. Points outside that part, and points whose edges all
    run one way (a rank-1 map: a point with a single edge), are not judged."""
    s = local_maps(graph, uv)
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    judged = graph.component & (np.abs(det) > 1e-6 * np.sum(s * s, axis=(1, 2)))
    majority = 1.0 if np.sum(det[judged] > 0) >= np.sum(det[judged] < 0) else -1.0
    return judged & (det * majority < 0)


def reversed_share(graph: SurfaceGraph, uv: np.ndarray) -> float:
    """Share of the graph's largest part where ``uv`` folds (0 for a fold-free map)."""
    return float(np.sum(reversed_points(graph, uv)) / max(int(graph.component.sum()), 1))


def nearest_rotations(maps: np.ndarray) -> np.ndarray:
    """(M, 2, 2) the rotation nearest to each 2 x 2 map (the polar factor, in closed form)."""
    angle = np.arctan2(maps[:, 1, 0] - maps[:, 0, 1], maps[:, 0, 0] + maps[:, 1, 1])
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], axis=-1), np.stack([s, c], axis=-1)], axis=-2)


class RigidProblem:
    """The as-rigid-as-possible energy of the graph's largest part (see the module
    docstring): its edges ``src -> dst`` with offsets ``t`` and weights ``w``, and the
    graph Laplacian ``L = A^T W A`` (A the edge incidence), factored once with u_0 = 0."""

    def __init__(self, graph: SurfaceGraph):
        self.part = np.flatnonzero(graph.component)
        index = np.full(len(graph.points), -1)
        index[self.part] = np.arange(len(self.part))
        nbr = graph.neighbours[self.part]
        inside = (index[nbr] >= 0) & graph.mutual[self.part]
        self.src = np.repeat(np.arange(len(self.part)), nbr.shape[1])[inside.ravel()]
        self.dst = index[nbr][inside]
        self.t = graph.offsets()[self.part][inside]
        self.w = graph.edge_weights()[self.part][inside]
        m, e = len(self.part), len(self.src)
        self.incidence = sp.csr_array((np.r_[-np.ones(e), np.ones(e)],
                                       (np.r_[np.arange(e), np.arange(e)], np.r_[self.src, self.dst])), shape=(e, m))
        self.gather = sp.csr_array((np.ones(e), (self.src, np.arange(e))), shape=(m, e))  # sums edges per source
        laplacian = (self.incidence.T @ (self.incidence * self.w[:, None])).tocsc()
        self.factor = splu(laplacian[1:, 1:].tocsc())  # u_0 = 0 fixes the translation

    def maps(self, uv: np.ndarray) -> np.ndarray:
        """(m, 2, 2) each point's ``S_i = sum_j w_ij (u_j - u_i) t_ij^T``."""
        d = (uv[self.dst] - uv[self.src]) * self.w[:, None]
        per_edge = np.column_stack([d[:, 0] * self.t[:, 0], d[:, 0] * self.t[:, 1],
                                    d[:, 1] * self.t[:, 0], d[:, 1] * self.t[:, 1]])
        return (self.gather @ per_edge).reshape(-1, 2, 2)

    def local(self, uv: np.ndarray) -> tuple[float, np.ndarray]:
        """The best rotations for ``uv`` (m, 2, 2) and the energy with them. With the
        rotation nearest to S_i, ``sum_j w_ij (u_j - u_i) . R_i t_ij = tr(R_i^T S_i)`` is
        ``|(S_00 + S_11, S_10 - S_01)|``, so the energy needs no per-edge rotation."""
        s = self.maps(uv)
        d = uv[self.dst] - uv[self.src]
        aligned = np.hypot(s[:, 0, 0] + s[:, 1, 1], s[:, 1, 0] - s[:, 0, 1])
        energy = float(np.sum(self.w * (np.sum(d * d, axis=1) + np.sum(self.t * self.t, axis=1)))
                       - 2.0 * np.sum(aligned))
        return energy, nearest_rotations(s)

    def solve(self, rotations: np.ndarray) -> np.ndarray:
        """The positions that best keep every edge as ``R_i t_ij``: ``L U = A^T W (R t)``."""
        c, s = rotations[self.src, 0, 0], rotations[self.src, 1, 0]
        target = np.column_stack([c * self.t[:, 0] - s * self.t[:, 1], s * self.t[:, 0] + c * self.t[:, 1]])
        rhs = self.incidence.T @ (self.w[:, None] * target)
        return np.vstack([np.zeros((1, 2)), self.factor.solve(rhs[1:])])


class Flattening(NamedTuple):
    positions: np.ndarray  # (M, 2) in the plane, in the cloud's units
    rotations: np.ndarray  # (M, 2, 2) from each point's tangent frame to the plane
    rounds: int  # local/global rounds taken


def rigid_embedding(graph: SurfaceGraph, start: np.ndarray, rounds: int = RIGID_ROUNDS) -> Flattening:
    """As-rigid-as-possible plane positions (M, 2) from ``start``, and each point's rotation
    (M, 2, 2) from its tangent frame to the plane (see the module docstring). Only the
    graph's largest part is moved; the start is reflected first if it reverses the
    frames' orientation (MDS does not know it).

    The local/global alternation lowers the energy every round but slowly (its bending
    modes contract by little per round), so the positions are Anderson-mixed
    (:class:`psonurbs.fitting.finish.polish.AndersonMixing`); a mixed round that does not lower
    the energy is replaced by the plain one and the mixing restarted.
    """
    problem = RigidProblem(graph)
    uv = start[problem.part] - start[problem.part][0]
    s = problem.maps(uv)
    if np.median(s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]) < 0:
        uv = uv * np.array([1.0, -1.0])
    energy, rotations = problem.local(uv)
    mixer = AndersonMixing((False, False))
    taken = 0
    for taken in range(1, rounds + 1):
        plain = problem.solve(rotations)
        mixed = mixer.next(uv, plain)
        mixed_energy, mixed_rotations = problem.local(mixed)
        last = energy
        if mixed_energy < energy:
            uv, energy, rotations = mixed, mixed_energy, mixed_rotations
        else:
            mixer.reset()
            uv = plain
            energy, rotations = problem.local(uv)
        if last - energy <= CONVERGED * last:
            break
    out_uv = np.zeros((len(graph.points), 2))
    out_rot = np.tile(np.eye(2), (len(graph.points), 1, 1))
    out_uv[problem.part], out_rot[problem.part] = uv, rotations
    return Flattening(out_uv, out_rot, taken)


def extended(graph: SurfaceGraph, uv: np.ndarray, rotations: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) positions of any points: their nearest embedded point's position plus their
    offset in its tangent frame, rotated like it. The offset is cut to that point's
    neighbourhood radius: a point farther off is a stray, not a part of the surface to
    unroll (points outside the largest part have no frame of their own, so the same)."""
    part = np.flatnonzero(graph.component)
    _, near = cKDTree(graph.points[part]).query(points)
    near = part[near]
    offset = np.einsum("nac,nc->na", graph.frames[near, :2], points - graph.points[near])
    reach = graph.lengths[near, -1]
    length = np.linalg.norm(offset, axis=1)
    offset *= (np.minimum(length, reach) / np.maximum(length, 1e-300))[:, None]
    return uv[near] + np.einsum("nab,nb->na", rotations[near], offset)


def embedding_sample(n: int, size: int = EMBEDDED_POINTS) -> np.ndarray:
    """Sorted indices of the points to embed: all, or ``size`` drawn with a fixed seed
    (the parametrisation must not depend on the swarm's random stream)."""
    if n <= size:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, size, replace=False))


@dataclass(frozen=True)
class Intrinsic:
    """The intrinsic parameters, and the flattening's rectangle (the parameters themselves
    unless the four-sided map was taken)."""

    par: Parametrisation
    rectangle: np.ndarray  # (N, 2) the flattening scaled onto [0, 1]^2 along its rectangle


def intrinsic_parameters(points: np.ndarray, graph: SurfaceGraph | None = None,
                         rounds: int = RIGID_ROUNDS) -> Intrinsic:
    """First (u, v) in [0, 1]^2 for every point of an open surface from its own geometry
    (see the module docstring), and the flattening's rectangle. ``graph`` may be given
    (built on a sample of ``points``).

    The four-sided map is taken when it fills at least ``FILL_MARGIN`` more of the square
    than the rectangle (on the embedded points) and folds on at most ``FOLD_MARGIN`` more
    of them than the flattening; it keeps the rectangle's directions (:func:`aligned`).
    A rectangle that fills the square has its sides on the square's already: the map
    would only add its ragged edge (``info["sides"]``: ``rectangle``; ``four`` when the map
    is taken, ``free`` for any other footprint or a map that folds)."""
    if graph is None:
        graph = surface_graph(points[embedding_sample(len(points))])
    flattening = rigid_embedding(graph, geodesic_embedding(graph), rounds)
    flat = extended(graph, flattening.positions, flattening.rotations, points)
    embedded = flattening.positions[graph.component]
    uv = unit_square(flat, reference=embedded)  # the embedded points' rectangle
    folded = reversed_share(graph, flattening.positions)
    info = {"method": "intrinsic", "embedded_points": int(graph.component.sum()),
            "neighbours": int(graph.neighbours.shape[1]), "rigid_rounds": flattening.rounds, "folded_share": folded}
    square, corners = square_map(embedded)
    info["corners_degrees"] = corners
    if square is None:
        return Intrinsic(Parametrisation(uv, {**info, "sides": "free"}), uv)
    cells = fill_cells(len(embedded))
    on_embedded = square.place(flattening.positions)
    fills = {"fill_rectangle": fill(unit_square(embedded), cells),
             "fill_four_sided": fill(on_embedded[graph.component], cells)}
    if fills["fill_four_sided"] < fills["fill_rectangle"] + FILL_MARGIN:
        return Intrinsic(Parametrisation(uv, {**info, "sides": "rectangle", **fills}), uv)
    four_folded = reversed_share(graph, on_embedded)
    if four_folded > folded + FOLD_MARGIN:  # the sides' map folds where the flattening did not
        return Intrinsic(Parametrisation(uv, {**info, "sides": "free", **fills,
                                              "four_sided_folded_share": four_folded}), uv)
    return Intrinsic(Parametrisation(aligned(square.place(flat), uv),
                                     {**info, "sides": "four", **fills, "folded_share": four_folded}), uv)


def parametrise_intrinsic(points: np.ndarray, graph: SurfaceGraph | None = None,
                          rounds: int = RIGID_ROUNDS) -> Parametrisation:
    """First (u, v) in [0, 1]^2 for every point of an open surface from its own geometry
    (:func:`intrinsic_parameters`). ``graph`` may be given (built on a sample of ``points``)."""
    return intrinsic_parameters(points, graph, rounds).par
