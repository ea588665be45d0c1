#!/usr/bin/env python3
"""Where a fit's error lies: near the data, or where the surface runs past them.

    python benchmarks/error_split.py CLOUD RESULT_DIR [RESULT_DIR ...] [--gt CASE.gt.npz]

For each fit (``RESULT_DIR/STEM.json``, as ``psonurbs fit`` wrote it) the surface is
sampled on the shared scorer's grid (301 x 301 in the parameter domain, inside the trim
loops when the JSON has them) and each sample's distance to the nearest cloud point is
taken. The table gives, per fit:

- ``overhang``: the share of samples farther than 2% of the diagonal from every point
  (the scorer's figure), and how much of it lies within 2% of the diagonal of the
  face's edge (the trim line or the surface's edge: a margin question) against inside;
- with ``--gt``: truth_rms (samples to the true surface, as the scorer measures it,
  by ``benchmarks/score.py``'s mesh distance), the share of its square on the samples farther than 1% of the diagonal from every
  point (surface past the data), and the rms on the others (surface over the data);
- ``floor``: the overhang of the data's own footprint: the alpha-shape triangles of the
  points (at their foot-point parameters, as the trim builds them) laid on the points
  themselves and sampled evenly in the parameter domain, as the scorer samples a
  surface. A trimmed surface through every point, ending at the alpha shape, would
  score about this: the part above what the fit scores is the fit's, the rest the
  sampling's (a sparse scan has gaps wider than 4% of its diagonal).

Figures are relative to the cloud's bounding-box diagonal, as the scorer's.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from score import MeshDistance  # benchmarks/score.py, beside this script

from psonurbs.fitting import footprint as fp
from psonurbs.formats.clouds import read_cloud
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import Trim, TrimLoop
from psonurbs.run.scoring import load_surface

GRID = 301  # the scorer's
OVERHANG = 0.02  # of the diagonal: the scorer's overhang distance
PAST = 0.01  # of the diagonal: a sample this far from every point is surface past the data


def samples(surface, trim: Trim | None) -> tuple[np.ndarray, np.ndarray]:
    """The surface on the scorer's grid (M, 3) and the mask (M,) of those on the face."""
    (u0, u1), (v0, v1) = surface.domain_u, surface.domain_v
    s = np.linspace(0.0, 1.0, GRID)
    uu, vv = np.meshgrid(u0 + (u1 - u0) * s, v0 + (v1 - v0) * s, indexing="ij")
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    on = np.ones(len(uv), bool) if trim is None else trim.contains(uv)
    return surface.evaluate(uv[:, 0], uv[:, 1]), on


def footprint_floor(surface, points: np.ndarray, diag: float, rng: np.random.Generator) -> float:
    """Overhang of the data's own alpha shape (see the module docstring)."""
    uv, _ = closest_parameters(surface, points)
    x = uv * fp.mean_speeds(surface)
    tri, kept = fp.alpha_triangles(x, fp.local_spacing(x))
    corners = tri.simplices[kept]
    a, b, c = (x[corners[:, k]] for k in range(3))
    area = 0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    n = 200_000
    pick = rng.choice(len(corners), n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    p, q, r = (points[corners[pick, k]] for k in range(3))
    on_data = (1 - r1)[:, None] * p + (r1 * (1 - r2))[:, None] * q + (r1 * r2)[:, None] * r
    return float(np.mean(cKDTree(points).query(on_data)[0] / diag > OVERHANG))


def split(cloud: Path, result: Path, truth, rng: np.random.Generator) -> dict:
    points = read_cloud(cloud)
    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
    surface, document = load_surface(result / f"{cloud.stem}.json")
    loops = document.get("surface", {}).get("trim")
    trim = Trim(tuple(TrimLoop.from_dict(d) for d in loops)) if loops else None
    at, on = samples(surface, trim)
    gap = cKDTree(points).query(at[on])[0] / diag
    over = gap > OVERHANG
    edge = cKDTree(at[~on]) if (~on).any() else None
    grid_edge = np.zeros((GRID, GRID), bool)  # the surface's own edges (not a closed direction's seam)
    if not surface.closed_u:
        grid_edge[[0, -1], :] = True
    if not surface.closed_v:
        grid_edge[:, [0, -1]] = True
    rims = [cKDTree(at[grid_edge.ravel()])] if grid_edge.any() else []
    near_edge = np.zeros(int(over.sum()), bool)
    for boundary in ([edge] if edge is not None else []) + rims:
        near_edge |= boundary.query(at[on][over])[0] / diag <= OVERHANG
    row = {"fit": str(result), "overhang": float(over.mean()),
           "overhang_at_edge": float(near_edge.sum() / max(len(gap), 1)),
           "floor": footprint_floor(surface, points, diag, rng)}
    if truth is not None:
        t = truth(at[on]) / diag
        past = gap > PAST
        row.update(truth_rms=float(np.sqrt(np.mean(t * t))),
                   truth_share_past=float(np.sum(t[past] ** 2) / max(np.sum(t * t), 1e-300)),
                   truth_rms_over_data=float(np.sqrt(np.mean(t[~past] ** 2))) if (~past).any() else float("nan"))
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cloud", type=Path)
    ap.add_argument("results", type=Path, nargs="+", help="result directories holding CLOUD_STEM.json")
    ap.add_argument("--gt", type=Path, help="the case's ground truth (CASE.gt.npz: vertices, triangles)")
    args = ap.parse_args(argv)
    truth = None
    if args.gt:
        g = np.load(args.gt)
        truth = MeshDistance(g["vertices"], g["triangles"])
    rows = [split(args.cloud, r, truth, np.random.default_rng(0)) for r in args.results]
    head = ["fit", "overhang", "of it at the edge", "floor"] + \
        (["truth_rms", "share past the data", "truth_rms over the data"] if truth else [])
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        cells = [r["fit"], f"{r['overhang']:.4f}", f"{r['overhang_at_edge']:.4f}", f"{r['floor']:.4f}"]
        if truth:
            cells += [f"{r['truth_rms']:.3g}", f"{r['truth_share_past']:.2f}", f"{r['truth_rms_over_data']:.3g}"]
        print("| " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
