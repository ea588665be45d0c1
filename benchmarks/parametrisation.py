#!/usr/bin/env python3
"""The intrinsic parametrisation of open surfaces: its cost, and the alternatives measured.

    python benchmarks/parametrisation.py                 # all three parts
    python benchmarks/parametrisation.py --parts cost --scans SCANS/   # and a real scan's cost

cost          seconds of ``parametrise_intrinsic`` (graph, geodesic start, rigid flattening,
              extension to all points) on cylinder sections of 10k to 40k points, and on
              the 40k-point bunny_front scan (SCANS/bunny_front.ply, with --scans)
distortion    first parameters of shapes with known intrinsic coordinates (developable:
              arc length and height; the twisted strip and the hemisphere only for folds):
              the RMS residual of the best affine map from them to the truth (of the
              truth's extent) and the share of points where they fold, for
                plane        the projection on the plane the surface faces most squarely
                floater      Floater & Reimers 2001: boundary (angular-gap test) fixed to the
                             unit circle by chord length (ordered around the geodesic start),
                             reciprocal-distance convex weights, one sparse solve
                floater*     the same with the true boundary (its best case)
                isomap       landmark Isomap alone (the start)
                arap-plain   30 plain local/global rounds from the start
                arap         30 Anderson-mixed rounds (what psonurbs uses)
fit           the public curl_sheet and twisted_ribbon: each start taken through the
              coarse-to-fine ladder (or not) and then polished on the configured net
              (classical: uniform knots, unit weights), RMSE over the noise or the diagonal
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from cases import CASES
from scipy.sparse.linalg import spsolve

from psonurbs.config import load_config
from psonurbs.fitting import intrinsic
from psonurbs.fitting.checks import check_fit
from psonurbs.fitting.coarse_to_fine import coarse_to_fine
from psonurbs.fitting.organise import organise
from psonurbs.fitting.parametrise import parametrise_open, unit_square
from psonurbs.fitting.polish import polish
from psonurbs.fitting.solve import RegularisedLeastSquares
from psonurbs.fitting.topology import layout_for
from psonurbs.geometry.net import NetShape


def section(n, degrees, noise=0.0, graded=False, seed=0):
    rng = np.random.default_rng(seed)
    u = np.sqrt(rng.random(n)) if graded else rng.random(n)
    a, z = np.radians(degrees) * u, 1.5 * rng.random(n)
    return np.column_stack([np.cos(a), np.sin(a), z]) + rng.normal(0, noise, (n, 3)), np.column_stack([a, z])


def cone(n, seed=1):
    rng = np.random.default_rng(seed)
    a, s = np.radians(220.0) * rng.random(n), rng.random(n)
    r, h = 0.5 + s, 1.2 * s
    slant = np.hypot(1.0, 1.2)  # the cone unrolls to an annular sector: radius (0.5 / sin + s slant), angle a sin
    half = 1.0 / slant
    rho = 0.5 / half + s * slant
    return np.column_stack([r * np.cos(a), r * np.sin(a), h]), np.column_stack([rho * np.cos(a * half),
                                                                                rho * np.sin(a * half)])


def strip(n, seed=2):
    rng = np.random.default_rng(seed)
    u, w = rng.random(n), rng.random(n) - 0.5
    t = np.radians(150.0) * u
    return np.column_stack([3 * u, w * np.cos(t), w * np.sin(t)]), None


def hemisphere(n, seed=3):
    rng = np.random.default_rng(seed)
    z, phi = rng.random(n), 2 * np.pi * rng.random(n)
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z]), None


def timed(f, *args):
    """(f(*args), wall seconds); the CPU seconds of the last call in ``timed.cpu``."""
    start, cpu = time.perf_counter(), time.process_time()
    out = f(*args)
    timed.cpu = time.process_time() - cpu
    return out, time.perf_counter() - start


def cost(scans: Path | None) -> None:
    print("| cloud | points | graph s | geodesic start s | rigid s | extension + unit square s | total s "
          "| total CPU s | plane projection s (for scale) |")
    print("|---|---|---|---|---|---|---|---|---|")
    clouds = [(f"cylinder section 250 deg, {n // 1000}k", section(n, 250.0, 1e-3)[0]) for n in (10000, 20000, 40000)]
    bunny = scans / "bunny_front.ply" if scans else None
    if bunny is not None and bunny.exists():
        from psonurbs.formats.clouds import read_cloud

        clouds.append(("bunny_front (real scan)", read_cloud(bunny)))
    for name, pts in clouds:
        pts = organise(pts, (2, 2)).points
        graph, t_graph = timed(intrinsic.surface_graph, pts[intrinsic.embedding_sample(len(pts))])
        cpu = timed.cpu
        start, t_start = timed(intrinsic.geodesic_embedding, graph)
        cpu += timed.cpu
        flat, t_rigid = timed(intrinsic.rigid_embedding, graph, start)
        cpu += timed.cpu
        flat_all, t_ext = timed(intrinsic.extended, graph, flat.positions, flat.rotations, pts)
        cpu += timed.cpu
        t_ext += timed(unit_square, flat_all)[1]
        cpu += timed.cpu
        total = t_graph + t_start + t_rigid + t_ext
        t_plane = timed(parametrise_open, pts)[1]
        print(f"| {name} | {len(pts)} | {t_graph:.2f} | {t_start:.2f} | {t_rigid:.2f} | {t_ext:.2f} | {total:.2f} "
              f"| {cpu:.2f} | {t_plane:.2f} |", flush=True)


def gap_boundary(graph: intrinsic.SurfaceGraph) -> np.ndarray:
    """The usual meshless boundary test: the neighbours, seen in the tangent plane, leave
    an angular gap over 0.9 pi (on random samples it also flags many interior points)."""
    t = graph.offsets()
    ordered = np.sort(np.arctan2(t[..., 1], t[..., 0]), axis=1)
    gaps = np.diff(np.concatenate([ordered, ordered[:, :1] + 2 * np.pi], axis=1), axis=1)
    return graph.component & (gaps.max(axis=1) > 0.9 * np.pi)


def floater(graph: intrinsic.SurfaceGraph, boundary: np.ndarray) -> np.ndarray:
    """Floater-Reimers meshless parametrisation: the ``boundary`` points fixed on the unit
    circle (by chord length, in their order around the geodesic start's centre), every
    other point the reciprocal-distance convex combination of its mutual neighbours."""
    part = graph.component
    start = intrinsic.geodesic_embedding(graph)
    b = np.flatnonzero(boundary & part)
    centre = start[b].mean(axis=0)
    b = b[np.argsort(np.arctan2(*(start[b] - centre).T[::-1]))]
    chord = np.linalg.norm(np.diff(graph.points[np.r_[b, b[:1]]], axis=0), axis=1)
    turn = 2 * np.pi * np.r_[0.0, np.cumsum(chord)[:-1]] / chord.sum()
    uv = np.zeros((len(graph.points), 2))
    uv[b] = np.column_stack([np.cos(turn), np.sin(turn)])
    m, k = graph.neighbours.shape
    w = np.where(graph.mutual & part[:, None] & part[graph.neighbours], 1.0 / np.maximum(graph.lengths, 1e-300), 0.0)
    rows = np.repeat(np.arange(m), k)
    lam = sp.csr_array((w.ravel(), (rows, graph.neighbours.ravel())), shape=(m, m))
    lam = sp.diags_array(1.0 / np.maximum(lam.sum(axis=1), 1e-300)) @ lam
    inner = np.flatnonzero(part & ~boundary)
    a = (sp.identity(m, format="csr") - lam)[inner][:, inner].tocsc()
    rhs = lam[inner][:, b] @ uv[b]
    uv[inner] = np.column_stack([spsolve(a, rhs[:, 0]), spsolve(a, rhs[:, 1])])
    return uv


def starts(graph: intrinsic.SurfaceGraph, pts: np.ndarray, truth: np.ndarray | None = None) -> dict:
    """Every first parametrisation compared; ``floater*`` (boundary from the truth: the
    points within 1% of the extent from the true edge) only where the truth is known."""
    geodesic = intrinsic.geodesic_embedding(graph)
    out = {"plane": parametrise_open(pts).uv, "floater": floater(graph, gap_boundary(graph))}
    if truth is not None:
        lo, hi = truth.min(axis=0), truth.max(axis=0)
        edge = np.minimum(truth - lo, hi - truth).min(axis=1) < 0.01 * np.linalg.norm(hi - lo)
        out["floater*"] = floater(graph, edge)
    out.update({"isomap": geodesic, "arap-plain": plain_rigid(graph, geodesic),
                "arap": intrinsic.rigid_embedding(graph, geodesic).positions})
    return out


def plain_rigid(graph: intrinsic.SurfaceGraph, start: np.ndarray, rounds: int = 30) -> np.ndarray:
    """The local/global alternation without Anderson mixing (for comparison)."""
    problem = intrinsic.RigidProblem(graph)
    uv = start[problem.part] - start[problem.part][0]
    s = problem.maps(uv)
    if np.median(s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]) < 0:
        uv = uv * np.array([1.0, -1.0])
    for _ in range(rounds):
        uv = problem.solve(problem.local(uv)[1])
    out = np.zeros((len(graph.points), 2))
    out[problem.part] = uv
    return out


def affine_residual(q: np.ndarray, truth: np.ndarray) -> float:
    design = np.column_stack([q, np.ones(len(q))])
    coeffs = np.linalg.lstsq(design, truth, rcond=None)[0]
    return float(np.sqrt(np.mean(np.sum((design @ coeffs - truth) ** 2, axis=1))) / np.linalg.norm(np.ptp(truth, 0)))


def distortion() -> None:
    shapes = [("cylinder section 250 deg, noise 1e-3", *section(4000, 250.0, 1e-3)),
              ("cylinder section 200 deg, uneven density", *section(4000, 200.0, graded=True)),
              ("cone section 220 deg", *cone(4000)),
              ("strip twisted 150 deg", *strip(3000)),
              ("hemisphere", *hemisphere(4000))]
    names = ["plane", "floater", "floater*", "isomap", "arap-plain", "arap"]
    print("| shape | " + " | ".join(f"{n} distortion / folded" for n in names) + " |")
    print("|---|" + "---|" * len(names))
    for name, pts, truth in shapes:
        graph = intrinsic.surface_graph(pts)
        found = starts(graph, pts, truth)
        cells = []
        for method in names:
            if method not in found:
                cells.append("-")
                continue
            q = found[method]
            dist = "-" if truth is None else f"{affine_residual(q[graph.component], truth[graph.component]):.1e}"
            cells.append(f"{dist} / {intrinsic.reversed_share(graph, q):.3f}")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def fit() -> None:
    print("| case | start | ladder | rmse (of the diagonal) | over noise | suspect | seconds |")
    print("|---|---|---|---|---|---|---|")
    for case in ("curl_sheet", "twisted_ribbon"):
        spec = CASES[case]
        cloud = organise(spec.points(), (4, 4))
        pts = cloud.points
        config = load_config(None).with_overrides(orders=spec.orders, net_size=spec.net)
        layout = layout_for("open", config.net_size, config.degrees)
        graph = intrinsic.surface_graph(pts[intrinsic.embedding_sample(len(pts))])
        assert len(graph.points) == len(pts)  # both cases have under EMBEDDED_POINTS points: all are embedded
        for method, q in starts(graph, pts).items():
            uv0 = q if method == "plane" else unit_square(q, reference=q[graph.component])
            for ladder in (False, True):
                begin = time.perf_counter()
                uv = coarse_to_fine(layout, pts, uv0, config.smoothing)[0] if ladder else uv0
                solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing)
                _, surface, uv, _ = polish(layout, solver, pts, uv, NetShape(np.ones(layout.n_free)), 100)
                seconds = time.perf_counter() - begin
                rmse = float(np.sqrt(np.mean(np.sum((surface.evaluate(uv[:, 0], uv[:, 1]) - pts) ** 2, axis=1))))
                noise = f"{rmse / spec.noise:.3f}" if spec.noise else "-"
                print(f"| {case} | {method} | {'yes' if ladder else 'no'} | {rmse:.2e} | {noise} | "
                      f"{'yes' if check_fit(surface, pts).suspect else 'no'} | {seconds:.1f} |", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", nargs="*", default=["cost", "distortion", "fit"], choices=["cost", "distortion", "fit"])
    ap.add_argument("--scans", type=Path, help="a directory of real scans holding bunny_front.ply (for the cost)")
    args = ap.parse_args(argv)
    for part in args.parts:
        print(f"\n## {part}\n")
        {"cost": lambda: cost(args.scans), "distortion": distortion, "fit": fit}[part]()
    return 0


if __name__ == "__main__":
    sys.exit(main())
