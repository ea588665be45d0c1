"""How often ``trim: auto`` trims a cloud that fills its rectangle: sampling gaps only.

    python benchmarks/trim_sampling.py                      # 10 draws of each sampling
    python benchmarks/trim_sampling.py --draws 40 --points 1000 10000

The contract says a cloud that fills its rectangle stays untrimmed. A random sample
leaves gaps along its edges and inside; ``trim: auto`` must tell them from real gaps
(a hole, a flap of surface past the data). Here flat squares are sampled in several
ways (uniform; a density falling 7, 20 and 50-fold across, as a scan's falls with range;
scan lines 4 and 16 x denser along than across) and the footprint of each is found on
the exact surface (:func:`psonurbs.fitting.footprint.footprint`, no fit involved). The
table gives, per sampling and size, the draws trimmed and the widest gap (the empty
disc's radius in the spacings it is measured in; ``trim: auto`` trims from 2.5).
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from psonurbs.fitting.footprint import ALPHA, face_contours, footprint
from psonurbs.geometry.basis import clamped_knots
from psonurbs.geometry.nurbs import NurbsSurface


def flat_square() -> NurbsSurface:
    """A gently bent unit square, (u, v) -> (u, v, 0.1 u v)."""
    g = np.linspace(0, 1, 4)
    uu, vv = np.meshgrid(g, g, indexing="ij")
    return NurbsSurface(3, 3, clamped_knots(4, 3), clamped_knots(4, 3), np.stack([uu, vv, 0.1 * uu * vv], axis=-1),
                        np.ones((4, 4)))


def falling(ratio: float):
    """Parameters (n, 2) whose density falls ``ratio``-fold from u = 1 to u = 0 (as u^2)."""
    def draw(n: int, rng: np.random.Generator) -> np.ndarray:
        uv = rng.random((int(3 * ratio) * n, 2))
        keep = rng.random(len(uv)) < 1.0 / ratio + (1.0 - 1.0 / ratio) * uv[:, 0] ** 2
        return uv[keep][:n]
    return draw


def scan_lines(along: int):
    """Parameters on lines v = const, ``along`` x denser along them than across."""
    def draw(n: int, rng: np.random.Generator) -> np.ndarray:
        rows = max(2, int(np.sqrt(n / along)))
        v = (np.arange(rows) + rng.random()) / rows
        uv = np.column_stack([rng.random(rows * along * rows),
                              np.repeat(v, along * rows) + 0.05 / rows * rng.standard_normal(rows * along * rows)])
        return uv[(uv[:, 1] >= 0) & (uv[:, 1] <= 1)]
    return draw


SAMPLINGS = {
    "uniform": lambda n, rng: rng.random((n, 2)),
    "density falling 7 x": falling(7),
    "density falling 20 x": falling(20),
    "density falling 50 x": falling(50),
    "scan lines 4:1": scan_lines(4),
    "scan lines 16:1": scan_lines(16),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--points", type=int, nargs="+", default=[1000, 3000, 10000])
    ap.add_argument("--only", nargs="*", choices=sorted(SAMPLINGS), help="these samplings only")
    args = ap.parse_args(argv)
    surface = flat_square()
    print(f"| sampling | points | trimmed by auto | widest gap, median | widest gap, largest (trims from {ALPHA:g}) |")
    print("|---|---|---|---|---|")
    for name, draw in SAMPLINGS.items():
        if args.only and name not in args.only:
            continue
        for n in args.points:
            trimmed, widest = 0, []
            for seed in range(args.draws):
                uv = draw(n, np.random.default_rng(9000 + seed))
                points = surface.evaluate(uv[:, 0], uv[:, 1])
                distances = np.full(len(uv), 1e-6)
                trimmed += footprint(surface, points, uv, distances, "auto").trim is not None
                widest.append(face_contours(surface, points, uv, distances).widest_gap)
            print(f"| {name} | {n} | {trimmed} of {args.draws} | {np.median(widest):.2f} | {max(widest):.2f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
