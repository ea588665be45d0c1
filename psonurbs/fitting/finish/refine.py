"""Joint refinement: Levenberg-Marquardt over control points, weights and parameters.

Alternating parameter correction with linear least squares converges slowly and
cannot move the weights. Here all of them are the unknowns of one non-linear least
squares problem (the knots stay where the swarm put them):

    min  sum_i c_i |S(u_i, v_i; P, w) - x_i|^2 + lam |L P|^2 + kappa |C P|^2

(c_i > 0 the robust loss's point weights, 1 without them; below, every point's residual
and Jacobian rows are scaled by sqrt(c_i), which makes the problem the unweighted one)

With R the rational basis at the points, the Jacobian of point i's residual is

    dS_i / dP_c        = R_ic                (per coordinate)
    dS_i / d log w_c   = R_ic (P_c - S_i)
    dS_i / d(u_i, v_i) = [S_u  S_v]          (each point moves only its own parameters)

so the damped normal equations have a small dense block G for the net (4 unknowns per
control point), a 2 x 2 block C_i per point and a coupling B_i between them. The
points are eliminated exactly (Schur complement, as in bundle adjustment):

    (G - sum_i B_i C_i^-1 B_i^T) d_net = -g + sum_i B_i C_i^-1 c_i
    d_i = -C_i^-1 (c_i + B_i^T d_net)

Every point's block touches only its knot-span cell's control points, so the sums are
cell-block Grams (:class:`psonurbs.geometry.rows.CellBlocks`), each cell's (4m, 4m) block
added straight into the band storage of the net system, whose unknowns couple only
within cells and the regulariser's stencil: in reverse Cuthill-McKee order
(:class:`psonurbs.fitting.leastsq.banded.BandOrder`) a band of half-width w, assembled in
O(n w) memory and factorised in O(n w^2) (a 53 x 20 cylinder net: 4,240 unknowns, w 933).
Levenberg damping ``mu * mean(diag) * I`` also tames the exact null directions of a
rational patch (the weights' common scale, their Moebius reparametrisation). Log-weights
stay inside their bounds; parameters of an open direction inside [0, 1], those of a
closed one wrap.

The refined surface is kept only if it earns it (:func:`refined_if_better`): the drop in
the residual pays for the weights it frees (Akaike), or, for a swarm's particle whose
weights were free already, it fits as well and ends nearer the data.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.fitting.leastsq.banded import BandOrder
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares, weighted_rms
from psonurbs.fitting.prepare.organise import RESOLUTION
from psonurbs.fitting.search.validation import Z, paired_test, reach
from psonurbs.geometry import compiled
from psonurbs.geometry.compiled import chunks
from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters, keep_in_domain
from psonurbs.geometry.rows import Rows

from .finishing import Finished
from .polish import polish

REFINE_CHUNK = 1 << 13  # points whose Jacobian blocks are formed together (some 20 MB at m = 16), a thread's share


class Chunk(NamedTuple):
    """A chunk of the points with what every step reuses from the linearisation."""
    part: slice  # the chunk's points
    piece: Rows  # their basis rows
    scaled: Rows  # the rows of the weighted problem, sqrt(c_i) R
    blocks: object  # piece.blocks(): the rows grouped by knot-span cell
    t: np.ndarray  # (c, m, 2) t_i = (P_c - S_i) . J_l: the weights' coupling to the parameters
    places: list  # per batch of blocks: (flat band places, kept) of its (blocks, 4m, 4m) entries


def unknowns(columns: np.ndarray, n: int) -> np.ndarray:
    """The net system's unknowns of the control points ``columns`` (..., m): (..., 4m), their
    x, y, z (3c + k, one coordinate after the other) and then their log-weights (3n + c)."""
    return np.concatenate([3 * columns + k for k in range(3)] + [3 * n + columns], axis=-1)


def net_order(layout: NetLayout, solver: RegularisedLeastSquares, inner: tuple) -> BandOrder:
    """The band order of the net system's 4n unknowns: two couple when their control points
    share a knot-span cell (any cell of the domain: the points move between cells) or the
    regulariser joins them."""
    n = layout.n_free
    mids = []
    for knots in layout.knots(*inner):
        breaks = np.unique(knots[(knots >= 0.0) & (knots <= 1.0)])
        mids.append(0.5 * (breaks[1:] + breaks[:-1]))
    centres = np.stack(np.meshgrid(*mids, indexing="ij"), axis=-1).reshape(-1, 2)
    columns = layout.rows(centres, np.ones(n), *inner).columns  # (cells, m)
    coupled = solver.penalty != 0
    if solver.condition is not None:
        coupled |= solver.condition != 0
    coupled[columns[:, :, None], columns[:, None, :]] = True
    a, b = np.nonzero(coupled)
    each = unknowns(np.arange(n)[:, None], n)  # (n, 4)
    pattern = np.zeros((4 * n, 4 * n), bool)
    pattern[each[a][:, :, None], each[b][:, None, :]] = True
    return BandOrder.for_pattern(pattern)


class JointProblem:
    def __init__(self, layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray,
                 inner_u: np.ndarray, inner_v: np.ndarray, point_weights: np.ndarray | None = None):
        self.layout, self.solver, self.points = layout, solver, points
        self.inner = (inner_u, inner_v)
        self.n = layout.n_free
        self.root = np.ones(len(points)) if point_weights is None else np.sqrt(point_weights)  # sqrt(c_i)
        self.order = net_order(layout, solver, self.inner)  # the net system is assembled in its band
        a, b = np.nonzero(solver.regulariser(1.0))  # the regulariser's entries, on each coordinate
        flat, kept = self.order.places(np.concatenate([3 * a + k for k in range(3)]),
                                       np.concatenate([3 * b + k for k in range(3)]))
        self.penalty_entries = (np.tile(a, 3)[kept], np.tile(b, 3)[kept], flat[kept])

    def evaluate(self, control: np.ndarray, weights: np.ndarray, uv: np.ndarray) -> dict:
        """Residuals, objective and the basis rows at the given unknowns."""
        rows = self.layout.rows(uv, weights, *self.inner)
        residual = self.root[:, None] * (rows @ control - self.points)
        regulariser = self.solver.regulariser(float(np.sum(self.root[:, None] ** 2 * rows.values ** 2)))
        objective = float(np.sum(residual ** 2) + np.sum(control * (regulariser @ control)))
        return {"rows": rows, "residual": residual, "regulariser": regulariser, "objective": objective}

    def pinned(self, uv: np.ndarray, d_uv: np.ndarray) -> np.ndarray:
        """(N, 2) mask of open-direction parameters that the step would push out of [0, 1]:
        they stay on the bound (the active set of the bound constraints)."""
        target = uv + d_uv
        return ((target < 0.0) | (target > 1.0)) & ~np.array(self.layout.closed)[None, :]

    def linearise(self, control: np.ndarray, weights: np.ndarray, uv: np.ndarray, ev: dict) -> dict:
        """The parts of the normal equations that do not depend on the damping:
        ``J_net^T J_net`` (with the regulariser) and ``J_net^T r``, summed over chunks of
        points from per-point arrays of m values (the structure of J_net above: the
        rows v and ``v_c (P_c - S_i)``), and every point's ``J_l = [S_u S_v]`` (N, 3, 2).
        The chunks run in threads (:func:`compiled.in_order`), their sums added in order."""
        n, rows, res = self.n, ev["rows"], ev["residual"]
        surface = self.layout.surface(control, weights, *self.inner)
        _, su, sv = surface.derivatives(uv[:, 0], uv[:, 1])
        jl = self.root[:, None, None] * np.stack([su, sv], axis=2)
        gram, g, parts = 0.0, np.zeros(4 * n), []
        terms = compiled.in_order(lambda part: self._chunk_normal_equations(part, rows, control, res, jl),
                                  chunks(len(res), REFINE_CHUNK))
        for chunk_gram, chunk_g, chunk in terms:
            gram += chunk_gram
            g += chunk_g
            parts.append(chunk)
        penalty = ev["regulariser"]  # (n, n), the same for each coordinate
        a, b, flat = self.penalty_entries
        gram = gram + self.order.gathered(flat, penalty[a, b])
        g[:3 * n] += (penalty @ control).ravel()
        return {"parts": parts, "control": control, "jl": jl, "gram": gram, "g": g, "residual": res}

    def _chunk_normal_equations(self, part: slice, rows: Rows, control: np.ndarray, res: np.ndarray,
                                jl: np.ndarray) -> tuple[np.ndarray, np.ndarray, Chunk]:
        """One chunk's ``J_net^T J_net`` (in the band order's storage) and ``J_net^T r``
        (4n,), and its :class:`Chunk`."""
        n = self.n
        wts = slice(3 * n, 4 * n)
        gram, g, places = 0.0, np.zeros(4 * n), []
        piece = rows.take(part)
        scaled = piece.scaled(self.root[part])  # the rows of the weighted problem, sqrt(c_i) R
        blocks = piece.blocks()
        offsets = control[piece.columns] - (piece @ control)[:, None, :]  # P_c - S_i, (c, m, 3)
        vs = scaled.values[:, :, None] * offsets
        m = piece.values.shape[1]
        for batch in blocks.batches:
            v, vs_b = blocks.pad(scaled.values, batch), blocks.pad(vs, batch)
            local = np.zeros((v.shape[0], 4 * m, 4 * m))  # each block's entries at its unknowns
            plain = np.matmul(v.transpose(0, 2, 1), v)
            for k in range(3):
                local[:, k * m:(k + 1) * m, k * m:(k + 1) * m] = plain
                cross = np.matmul(v.transpose(0, 2, 1), vs_b[..., k])
                local[:, k * m:(k + 1) * m, 3 * m:] = cross
                local[:, 3 * m:, k * m:(k + 1) * m] = cross.transpose(0, 2, 1)
                local[:, 3 * m:, 3 * m:] += np.matmul(vs_b[..., k].transpose(0, 2, 1), vs_b[..., k])
            at = unknowns(blocks.columns[batch], n)
            flat, kept = self.order.places(at[:, :, None], at[:, None, :])
            places.append((flat[kept], kept))
            gram = gram + self.order.gathered(flat[kept], local[kept])
        g[:3 * n] += scaled.project(res[part]).ravel()
        g[wts] += np.bincount(piece.columns.ravel(), np.sum(vs * res[part][:, None, :], axis=2).ravel(), n)
        t = sum(offsets[:, :, k, None] * jl[part][:, None, k, :] for k in range(3))
        return gram, g, Chunk(part, piece, scaled, blocks, t, places)

    @staticmethod
    def _point_terms(lin: dict, chunk: "Chunk", damping: float, frozen: np.ndarray | None) -> dict:
        """A chunk's per-point blocks: C_i = J_l^T J_l + damping (its Cholesky factor L_i
        in closed form), ``t_i = (P_c - S_i) . J_l`` (chunk, m, 2) and ``J_l^T r_i``; a
        frozen parameter's column of J_l (and of t) is zero."""
        part = chunk.part
        jl = lin["jl"][part] if frozen is None else lin["jl"][part] * ~frozen[part, None, :]  # (c, 3, 2)
        a = np.sum(jl[:, :, 0] ** 2, axis=1)
        c = np.sum(jl[:, :, 1] ** 2, axis=1)
        off = np.sum(jl[:, :, 0] * jl[:, :, 1], axis=1)
        shift = damping * np.maximum((a + c) / 2.0, 1e-300)
        a, c = a + shift, c + shift
        if frozen is not None:
            a, c = a + frozen[part, 0], c + frozen[part, 1]
        l11 = np.sqrt(a)
        l21 = off / l11
        l22 = np.sqrt(np.maximum(c - l21 ** 2, 1e-300))
        t = chunk.t if frozen is None else chunk.t * ~frozen[part, None, :]
        return {"jl": jl, "a": a, "c": c, "off": off, "det": a * c - off ** 2, "l11": l11, "l21": l21, "l22": l22,
                "t": t, "c_vec": np.sum(jl * lin["residual"][part][:, :, None], axis=1)}

    @staticmethod
    def _c_inverse(q: dict, x: np.ndarray) -> np.ndarray:
        """``C_i^-1 x_i`` for (chunk, 2) x."""
        return np.stack([q["c"] * x[:, 0] - q["off"] * x[:, 1], q["a"] * x[:, 1] - q["off"] * x[:, 0]],
                        axis=1) / q["det"][:, None]

    def step(self, lin: dict, damping: float, frozen: np.ndarray | None = None):
        """The damped Gauss-Newton step (d_control, d_log_weights, d_uv); parameters
        marked ``frozen`` (N, 2) stay where they are. The 2 x 2 blocks are inverted
        in closed form; the chunks run in threads, their sums added in order.

        With ``B_i L_i^-T = [y0 y1]`` (C_i = L_i L_i^T) the Schur complement subtracts
        ``sum_i y0 y0^T + y1 y1^T``. On control point c, coordinate k, y_e is
        ``v_c a_ek`` (a scalar a_ek per point), on weight c ``z_ec = v_c (L_i^-1 t_ic)_e``,
        so its blocks are cross Grams of per-point arrays of m values, a chunk at a time.
        """
        n = self.n
        schur, rhs, terms = lin["gram"].copy(), -lin["g"], []
        for reduction, rhs_part, q in compiled.in_order(lambda chunk: self._chunk_schur(lin, chunk, damping, frozen),
                                                        lin["parts"]):
            schur -= reduction
            rhs += rhs_part
            terms.append(q)
        schur[0] += damping * schur[0].sum() / schur.shape[1]  # the diagonal is the band's first row
        d_net = self.order.solve(schur, rhs)
        d_control, d_log_w = d_net[:3 * n].reshape(n, 3), d_net[3 * n:]
        d_uv = np.empty((len(lin["residual"]), 2))

        def back_substitute(job: tuple[Chunk, dict]) -> None:  # one chunk's d_uv rows
            chunk, q = job
            piece, scaled = chunk.piece, chunk.scaled
            moved = scaled @ d_control  # (c, 3)
            jl = q["jl"]
            along = jl[:, 0] * moved[:, 0, None] + jl[:, 1] * moved[:, 1, None] + jl[:, 2] * moved[:, 2, None]
            bt_d = along + np.sum((scaled.values * d_log_w[piece.columns])[:, :, None] * q["t"], axis=1)
            d_uv[chunk.part] = -self._c_inverse(q, q["c_vec"] + bt_d)

        compiled.each(back_substitute, zip(lin["parts"], terms))
        return d_control, d_log_w, d_uv

    def _chunk_schur(self, lin: dict, chunk: Chunk, damping: float, frozen: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, dict]:
        """One chunk's ``sum_i B_i C_i^-1 B_i^T`` (in the band order's storage), its
        ``sum_i B_i C_i^-1 c_i`` (4n,) and its point terms (:meth:`_point_terms`)."""
        n = self.n
        wts = slice(3 * n, 4 * n)
        reduction, rhs = 0.0, np.zeros(4 * n)
        piece, scaled, blocks = chunk.piece, chunk.scaled, chunk.blocks
        q = self._point_terms(lin, chunk, damping, frozen)
        v, jl, t, l11, l22, ratio = scaled.values, q["jl"], q["t"], q["l11"], q["l22"], q["l21"] / q["l11"]
        a = np.stack([jl[:, :, 0] / l11[:, None], (jl[:, :, 1] - jl[:, :, 0] * ratio[:, None]) / l22[:, None]],
                     axis=2)  # (c, 3, 2): a_ek
        z = v[:, :, None] * np.stack([t[:, :, 0] / l11[:, None],
                                      (t[:, :, 1] - t[:, :, 0] * ratio[:, None]) / l22[:, None]], axis=2)
        m = v.shape[1]
        for batch, (flat, kept) in zip(blocks.batches, chunk.places):
            vb, ab, zb = blocks.pad(v, batch), blocks.pad(a, batch), blocks.pad(z, batch)
            vt = vb.transpose(0, 2, 1)
            local = np.empty((vb.shape[0], 4 * m, 4 * m))  # each block's entries at its unknowns
            for k in range(3):
                for j in range(k, 3):
                    scale = (ab[:, :, k, 0] * ab[:, :, j, 0] + ab[:, :, k, 1] * ab[:, :, j, 1])[:, :, None]
                    block = np.matmul(vt, scale * vb)
                    local[:, k * m:(k + 1) * m, j * m:(j + 1) * m] = block
                    local[:, j * m:(j + 1) * m, k * m:(k + 1) * m] = block.transpose(0, 2, 1)
                # sum over e of a_ek z_ec, written out: a reduction over a last axis of 2 is slow
                mixed = ab[:, :, k, None, 0] * zb[..., 0] + ab[:, :, k, None, 1] * zb[..., 1]
                cross = np.matmul(vt, mixed)
                local[:, k * m:(k + 1) * m, 3 * m:] = cross
                local[:, 3 * m:, k * m:(k + 1) * m] = cross.transpose(0, 2, 1)
            local[:, 3 * m:, 3 * m:] = sum(np.matmul(zb[..., e].transpose(0, 2, 1), zb[..., e]) for e in range(2))
            reduction = reduction + self.order.gathered(flat, local[kept])
        w_vec = self._c_inverse(q, q["c_vec"])
        # sums over a last axis of 2 written out (numpy's reduction over it is slow)
        rhs[:3 * n] += scaled.project(jl[..., 0] * w_vec[:, None, 0] + jl[..., 1] * w_vec[:, None, 1]).ravel()
        rhs[wts] += np.bincount(piece.columns.ravel(),
                                (v * (t[..., 0] * w_vec[:, None, 0] + t[..., 1] * w_vec[:, None, 1])).ravel(), n)
        return reduction, rhs, q


class Refined(NamedTuple):
    control: np.ndarray  # (n_free, 3) the free control points
    shape: NetShape  # the start's knots with the refined weights
    uv: np.ndarray  # (N, 2) the points' parameters
    rounds: int


def refine_jointly(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
                   control: np.ndarray, shape: NetShape, log_bounds, iterations: int = 12, tolerance: float = 1e-6,
                   point_weights: np.ndarray | None = None) -> Refined:
    """Control points, weights and parameters refined together from the given ones (the
    knots of ``shape`` kept); ``point_weights`` (N,), all positive, weigh the points'
    squared distances."""
    problem = JointProblem(layout, solver, points, shape.inner_u, shape.inner_v, point_weights)
    log_w = np.clip(np.log(shape.weights), *log_bounds)
    uv = keep_in_domain(uv, layout.closed)
    ev = problem.evaluate(control, np.exp(log_w), uv)
    damping, taken = 1e-3, 0
    for taken in range(1, iterations + 1):
        gain = None
        lin = problem.linearise(control, np.exp(log_w), uv, ev)
        while damping < 1e6:
            try:
                d_control, d_log_w, d_uv = problem.step(lin, damping)
                pinned = problem.pinned(uv, d_uv)
                if pinned.any():
                    d_control, d_log_w, d_uv = problem.step(lin, damping, pinned)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            trial = (control + d_control, np.clip(log_w + d_log_w, *log_bounds),
                     keep_in_domain(uv + d_uv, layout.closed))
            trial_ev = problem.evaluate(trial[0], np.exp(trial[1]), trial[2])
            if trial_ev["objective"] < ev["objective"]:
                gain = 1.0 - trial_ev["objective"] / ev["objective"]
                (control, log_w, uv), ev = trial, trial_ev
                damping = max(damping / 4.0, 1e-9)
                break
            damping *= 8.0
        if gain is None or gain < tolerance:
            break
    return Refined(control, shape._replace(weights=np.exp(log_w)), uv, taken)


def pays_for_weights(before: np.ndarray, after: np.ndarray, n_weights: int,
                     point_weights: np.ndarray | None = None) -> bool:
    """Whether the refinement's drop in the residual sum of squares pays for the weights
    it frees (Akaike): ``n ln(RSS_before / RSS_after) > 2 n_weights``.

    On noisy data the extra freedom buys a percent or two of RMSE by fitting the noise,
    at the price of the true shape; on a conic it takes the error to zero.
    """
    c = 1.0 if point_weights is None else point_weights
    rss_before, rss_after = float(np.sum(c * before ** 2)), float(np.sum(c * after ** 2))
    if rss_after <= 0.0:
        return rss_before > 0.0
    return len(before) * np.log(rss_before / rss_after) > 2.0 * n_weights


def ends_nearer(polished: NurbsSurface, refined: NurbsSurface, points: np.ndarray, before: np.ndarray,
               after: np.ndarray, point_weights: np.ndarray | None = None) -> bool:
    """Whether the refined surface fits the points (N, 3) as well as the polished one and
    ends nearer the data, by the validation's paired tests (:mod:`psonurbs.fitting.search.validation`):
    the points' distances ``after`` (N,) not significantly larger than ``before`` (z < Z),
    and the surface's samples significantly nearer the cloud (z < -Z).

    For a swarm's particle, whose weights were searched, the refinement frees no weights,
    so the Akaike price of :func:`pays_for_weights` does not apply; what the refined
    surface can offer is its edges back on the data (:func:`anchored`). On step_bump the
    polished surface of the swarm's knots runs up to 0.09 past the data's edge, the
    anchored refined one does not, at an rmse 0.1% higher.
    """
    cloud = cKDTree(points)
    return paired_test(before, after, point_weights).z < Z and \
        paired_test(reach(polished, cloud), reach(refined, cloud)).z < -Z


def anchored(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
             control: np.ndarray, shape: NetShape, polish_iterations: int,
             point_weights: np.ndarray | None = None) -> NurbsSurface:
    """The jointly refined surface with its edges back on the data.

    The refinement may let the data retreat from a bounded direction's edges (see
    ``NetLayout.bounded``): the surface then grows past the data's boundary at no cost
    and overshoots the true one. If the refined surface is exact (the data on it to
    within ``RESOLUTION``: a noise-free cloud of a shape the net represents, e.g. a conic
    with the right weights) its only freedom left is where it ends, and it is
    restricted exactly to the data's parameter extent. Otherwise it is polished again
    with its weights, the data's edges re-aligned onto the domain's at every round. A
    surface without edges (sphere, torus) is kept as refined.
    """
    surface = layout.surface(control, *shape)
    if not any(layout.bounded):
        return surface
    if weighted_rms(closest_parameters(surface, points, uv)[1] ** 2, point_weights) <= RESOLUTION:
        extent = [(float(uv[:, k].min()), float(uv[:, k].max())) if layout.bounded[k] else (0.0, 1.0)
                  for k in (0, 1)]
        return surface.restricted(*extent)
    return polish(layout, solver, points, uv, shape, polish_iterations, realign=True,
                  point_weights=point_weights).surface


@dataclass(frozen=True)
class Refinement:
    surface: NurbsSurface  # the refined surface if it was accepted, else the finished one
    accepted: bool
    rounds: int  # the joint refinement's rounds


def refined_if_better(layout: NetLayout, done: Finished, shape: NetShape, log_weight_bounds, iterations: int,
                      polish_iterations: int) -> Refinement:
    """The finished surface refined jointly (:func:`refine_jointly`), anchored to the
    data's edges (:func:`anchored`), and accepted if the gain pays for the weights it frees
    (:func:`pays_for_weights`) or, where the weights were searched already (a swarm's
    particle), if it fits the points as well and ends nearer the data (:func:`ends_nearer`)."""
    fit, solver = done.fitted, done.solver
    points, c = fit.points, fit.point_weights
    searched = np.any(shape.weights != 1.0)  # the weights already free: a swarm's particle, not unit weights
    control, shape, uv, rounds = refine_jointly(layout, solver, points, fit.uv, done.control, shape,
                                                log_weight_bounds, iterations, point_weights=c)
    refined = anchored(layout, solver, points, uv, control, shape, polish_iterations, c)
    before, after = closest_parameters(done.surface, points)[1], closest_parameters(refined, points)[1]
    accepted = pays_for_weights(before, after, layout.n_free, c) or \
        (searched and ends_nearer(done.surface, refined, points, before, after, c))
    return Refinement(refined if accepted else done.surface, bool(accepted), rounds)
