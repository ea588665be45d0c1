#!/usr/bin/env python3
"""Whole objects of several faces: ``psonurbs fit --patches auto`` end to end, its STEP
read back by OpenCASCADE.

    python benchmarks/objects.py --out DIR [--only can shaft] [--seed N] [--scorer SCORE_PY]
    python benchmarks/objects.py --out DIR --clouds scan.ply other.ply --tolerance-rel 4e-3
    python benchmarks/objects.py --out DIR --only can --points 50000   # a denser scan
    python benchmarks/objects.py --docs          # every object, written to docs/objects.md

Each object is a list of true faces, maps (u, v) in [0, 1]^2 -> xyz, sampled
area-uniformly (N points in all) with Gaussian noise (a fraction of the bounding-box
diagonal); its ground truth is the faces' union as one triangle mesh, its volume known in
closed form. Each is fitted with orders 4 x 4, ``patches: auto`` and a p99 tolerance of
2e-3 of the diagonal, and written as STEP. One row per object:

  faces / true      faces written, faces of the truth
  p99, truth_rms, cover_max   of the JSON's faces (``benchmarks/score.py``, or --scorer),
                    relative to the diagonal; far_max: the farthest point from every face
                    in median nearest-neighbour spacings
  solids, shells, free, valid   the STEP read back: solids, shells, free edges (a closed
                    shell has none), BRepCheck validity
  volume err        the solid's volume (adaptive integration) against the true one
  gap               the widest gap between two faces' edges (the sewing's edge tolerance)
  seconds           the fit's wall time

``--clouds`` fits other clouds (real scans of whole objects) the same way, without a truth.
Needs the optional package cadquery-ocp.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cases import ply  # noqa: E402

TAU = 2.0 * np.pi
Face = Callable[[np.ndarray, np.ndarray], np.ndarray]


def wall(r0: float, r1: float, z0: float, z1: float) -> Face:
    """A cone's (a cylinder's when r0 = r1) side between heights z0 and z1."""
    def face(u, v):
        r = r0 + (r1 - r0) * v
        return np.stack([r * np.cos(TAU * u), r * np.sin(TAU * u), z0 + (z1 - z0) * v], -1)
    return face


def ring(r0: float, r1: float, z: float) -> Face:
    """A flat annulus (a disc when r0 = 0) at height z."""
    def face(u, v):
        r = r0 + (r1 - r0) * v
        return np.stack([r * np.cos(TAU * u), r * np.sin(TAU * u), np.full_like(u, z)], -1)
    return face


def dome(r: float, z: float, up: bool) -> Face:
    """A hemisphere of radius r on the circle at height z, up or down."""
    s = 1.0 if up else -1.0
    def face(u, v):
        c = np.cos(0.5 * np.pi * v)
        return np.stack([r * c * np.cos(TAU * u), r * c * np.sin(TAU * u), z + s * r * np.sin(0.5 * np.pi * v)], -1)
    return face


def fillet(R: float, r: float, z: float, up: bool) -> Face:
    """A quarter of a torus: the round of radius r joining a disc of radius R at height
    z +- r to a cylinder of radius R + r, tangent to both."""
    s = 1.0 if up else -1.0
    def face(u, v):
        a = 0.5 * np.pi * v
        rho = R + r * np.cos(a)
        return np.stack([rho * np.cos(TAU * u), rho * np.sin(TAU * u), z + s * r * np.sin(a)], -1)
    return face


def holed_square(side: float, r: float, z: float) -> Face:
    """A square of the given side at height z, centred on the axis, with a hole of radius
    r: each ray from the centre runs from the hole's circle (v = 0) to the square (v = 1)."""
    def face(u, v):
        c, s = np.cos(TAU * u), np.sin(TAU * u)
        reach = 0.5 * side / np.maximum(np.abs(c), np.abs(s))
        rho = (1.0 - v) * r + v * reach
        return np.stack([rho * c, rho * s, np.full_like(u, z)], -1)
    return face


def square(origin, a, b) -> Face:
    """The parallelogram origin + u a + v b."""
    o, a, b = (np.asarray(x, float) for x in (origin, a, b))
    return lambda u, v: o + u[..., None] * a + v[..., None] * b


def box(x: float, y: float, z: float) -> list[Face]:
    return [square((0, 0, 0), (x, 0, 0), (0, y, 0)), square((0, 0, z), (x, 0, 0), (0, y, 0)),
            square((0, 0, 0), (x, 0, 0), (0, 0, z)), square((0, y, 0), (x, 0, 0), (0, 0, z)),
            square((0, 0, 0), (0, y, 0), (0, 0, z)), square((x, 0, 0), (0, y, 0), (0, 0, z))]


def bracket(width: float) -> list[Face]:
    """An L profile in (x, z), a 1 x 0.3 foot and a 0.3 x 0.5 upright, extruded along y
    over ``width``: six walls (one meeting the others at a concave edge) and two L-shaped
    ends, each two coplanar rectangles."""
    profile = [(0, 0), (1, 0), (1, 0.3), (0.3, 0.3), (0.3, 0.8), (0, 0.8)]
    walls = [square((x0, 0, z0), (x1 - x0, 0, z1 - z0), (0, width, 0))
             for (x0, z0), (x1, z1) in zip(profile, profile[1:] + profile[:1])]
    ends = [square((0, y, z), (a, 0, 0), (0, 0, c)) for y in (0.0, width) for z, a, c in ((0, 1, 0.3), (0.3, 0.3, 0.5))]
    return walls + ends


def filleted_box(r: float) -> list[Face]:
    """A 1 x 0.7 x 0.4 box whose edge along x at y = z = 0 is rounded to radius r: five
    flat faces, a quarter cylinder tangent to two of them, two ends each a rectangle, a
    strip and a quarter disc."""
    def fillet(u, v):
        a = np.pi * (1.0 + 0.5 * v)
        return np.stack([u, r + r * np.cos(a), r + r * np.sin(a)], -1)

    def corner(x):
        def face(u, v):
            a = np.pi * (1.0 + 0.5 * u)
            return np.stack([np.full_like(u, x), r + r * v * np.cos(a), r + r * v * np.sin(a)], -1)
        return face
    ends = [piece for x in (0.0, 1.0) for piece in (square((x, r, 0), (0, 0.7 - r, 0), (0, 0, 0.4)),
                                                   square((x, 0, r), (0, r, 0), (0, 0, 0.4 - r)), corner(x))]
    return [square((0, r, 0), (1, 0, 0), (0, 0.7 - r, 0)), square((0, 0, 0.4), (1, 0, 0), (0, 0.7, 0)),
            square((0, 0, r), (1, 0, 0), (0, 0, 0.4 - r)), square((0, 0.7, 0), (1, 0, 0), (0, 0, 0.4)), fillet] + ends


def handle(radius: float, height: float, bend: float, tube: float) -> Face:
    """A mug's handle: a tube of radius ``tube`` bent round a circle of radius ``bend`` in
    the plane y = 0, centred on a can's wall (radius ``radius``) at half its height; u
    along the bend, v around the tube. Only its part outside the can belongs to the mug
    (:func:`outside_can`)."""
    def face(u, v):
        ring = bend + tube * np.cos(TAU * v)
        return np.stack([radius + ring * np.cos(TAU * u), tube * np.sin(TAU * v), 0.5 * height + ring * np.sin(TAU * u)], -1)
    return face


def outside_can(radius: float):
    """Keeps the triangles (centres (T, 3)) outside the can's wall."""
    return lambda c: np.hypot(c[:, 0], c[:, 1]) > radius


def outside_handle(radius: float, height: float, bend: float, tube: float):
    """Keeps the triangles (centres (T, 3)) outside the handle's tube (the wall under its feet)."""
    return lambda c: np.hypot(np.hypot(c[:, 0] - radius, c[:, 2] - 0.5 * height) - bend, c[:, 1]) > tube


def handle_volume(radius: float, bend: float, tube: float, n: int = 400) -> float:
    """The volume of the handle's tube outside the can: the midpoint rule in the tube's
    coordinates (r, theta around the tube, phi along the bend), dV = r (bend + r cos theta)
    dr dtheta dphi, over the points with x^2 + y^2 > radius^2 (error ~1e-5 relative)."""
    r = (np.arange(n // 4) + 0.5) / (n // 4) * tube
    theta = (np.arange(n) + 0.5) / n * TAU
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * TAU
    rr, tt = np.meshgrid(r, theta, indexing="ij")
    ring = bend + rr * np.cos(tt)
    volume = 0.0
    for p in phi:  # one slice along the bend at a time: n^2 / 4 points
        outside = (radius + ring * np.cos(p)) ** 2 + (rr * np.sin(tt)) ** 2 > radius ** 2
        volume += float(np.sum(rr * ring * outside))
    return volume * (tube / len(r)) * (TAU / n) * (TAU / len(phi))


@dataclass(frozen=True)
class Object:
    name: str
    faces: list[Face]
    volume: float
    points: int
    note: str
    noise: float = 5e-4
    true_faces: int | None = None  # faces of the part, where some are sampled as several pieces
    keep: tuple = ()  # per face, None or which of its triangles (centres (T, 3) -> bool) belong to the part

    @property
    def face_count(self) -> int:
        return self.true_faces or len(self.faces)


OBJECTS = {o.name: o for o in [
    Object("can", [wall(0.5, 0.5, 0.0, 1.2), ring(0.0, 0.5, 0.0), ring(0.0, 0.5, 1.2)], np.pi * 0.25 * 1.2, 8000,
           "a cylinder and two flat caps, creases at the rims"),
    Object("capsule", [wall(0.4, 0.4, 0.0, 1.0), dome(0.4, 0.0, False), dome(0.4, 1.0, True)],
           np.pi * 0.16 * 1.0 + 4.0 / 3.0 * np.pi * 0.064, 8000, "a cylinder and two hemispheres: tangent joins"),
    Object("shaft", [wall(0.5, 0.5, 0.0, 0.6), wall(0.3, 0.3, 0.6, 1.4), ring(0.0, 0.5, 0.0), ring(0.3, 0.5, 0.6),
                     ring(0.0, 0.3, 1.4)], np.pi * (0.25 * 0.6 + 0.09 * 0.8), 10000,
           "two coaxial cylinders, the step between them and two end faces"),
    Object("box", box(1.0, 0.7, 0.4), 1.0 * 0.7 * 0.4, 8000, "six flat faces, three meeting at each corner"),
    Object("frustum", [wall(0.5, 0.25, 0.0, 0.8), ring(0.0, 0.5, 0.0), ring(0.0, 0.25, 0.8)],
           np.pi * 0.8 / 3.0 * (0.25 + 0.125 + 0.0625), 8000, "a cone's side and two discs: 63 and 117 degree creases"),
    Object("washer", [ring(0.25, 0.6, 0.0), ring(0.25, 0.6, 0.3), wall(0.6, 0.6, 0.0, 0.3), wall(0.25, 0.25, 0.0, 0.3)],
           np.pi * (0.36 - 0.0625) * 0.3, 8000, "a ring with a hole through it: two annuli, two walls"),
    Object("rounded_can", [wall(0.5, 0.5, 0.1, 1.1), fillet(0.4, 0.1, 0.1, False), fillet(0.4, 0.1, 1.1, True),
                           ring(0.0, 0.4, 0.0), ring(0.0, 0.4, 1.2)],
           np.pi * 0.25 * 1.0 + 2.0 * np.pi * (0.016 + 0.4 * np.pi * 0.01 / 2.0 + 0.001 * 2.0 / 3.0), 8000,
           "a can whose rims are rounded (radius 0.1): every join tangent"),
    Object("cup", [wall(0.5, 0.5, 0.1, 1.2), fillet(0.4, 0.1, 0.1, False), ring(0.0, 0.4, 0.0), ring(0.0, 0.5, 1.2)],
           np.pi * 0.25 * 1.1 + np.pi * (0.016 + 0.4 * np.pi * 0.01 / 2.0 + 0.001 * 2.0 / 3.0), 8000,
           "a can rounded at its foot (radius 0.1), its lid's rim sharp: the wall and the base one bag"),
    Object("holed_plate", [holed_square(1.0, 0.2, 0.0), holed_square(1.0, 0.2, 0.25), wall(0.2, 0.2, 0.0, 0.25)]
           + [square((x, y, 0.0), (dx, dy, 0.0), (0, 0, 0.25)) for x, y, dx, dy in
              ((-0.5, -0.5, 1, 0), (0.5, -0.5, 0, 1), (0.5, 0.5, -1, 0), (-0.5, 0.5, 0, -1))],
           (1.0 - np.pi * 0.04) * 0.25, 8000, "a square plate with a round hole through it"),
    Object("filleted_box", filleted_box(0.1), 0.28 - (0.01 - np.pi * 0.01 / 4.0), 8000,
           "a box with one edge rounded: a fillet tangent to two faces, sharp edges elsewhere", true_faces=7),
    Object("bracket", bracket(0.6), (0.3 + 0.3 * 0.5) * 0.6, 8000,
           "an L extruded: a concave edge, two L-shaped ends", true_faces=8),
    Object("mug", [wall(0.5, 0.5, 0.0, 1.2), ring(0.0, 0.5, 0.0), ring(0.0, 0.5, 1.2), handle(0.5, 1.2, 0.35, 0.1)],
           np.pi * 0.25 * 1.2 + handle_volume(0.5, 0.35, 0.1), 9000,
           "a can with a handle: a tube bent along an arc, its feet on the wall",
           keep=(outside_handle(0.5, 1.2, 0.35, 0.1), None, None, outside_can(0.5))),
]}


def sample(obj: Object, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cloud (N, 3), and the truth as one mesh (vertices, triangles)."""
    rng = np.random.default_rng(seed)
    meshes, areas = [], []
    for face, keep in zip(obj.faces, obj.keep or [None] * len(obj.faces)):
        cells = 160 if keep is None else 640  # a clipped face ends within half a cell of its cut
        grid = np.linspace(0.0, 1.0, cells + 1)
        uu, vv = np.meshgrid(grid, grid, indexing="ij")
        vertices = face(uu.ravel(), vv.ravel())
        k = np.arange(cells)
        i, j = np.meshgrid(k, k, indexing="ij")
        a, b = (i * (cells + 1) + j).ravel(), ((i + 1) * (cells + 1) + j).ravel()
        triangles = np.concatenate([np.column_stack([a, b, b + 1]), np.column_stack([a, b + 1, a + 1])])
        if keep is not None:  # the part's triangles only, and only their vertices (the truth's samples)
            used, triangles = np.unique(triangles[keep(vertices[triangles].mean(axis=1))], return_inverse=True)
            vertices, triangles = vertices[used], triangles.reshape(-1, 3)
        e1, e2 = vertices[triangles[:, 1]] - vertices[triangles[:, 0]], vertices[triangles[:, 2]] - vertices[triangles[:, 0]]
        meshes.append((vertices, triangles))
        areas.append(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1))
    counts = rng.multinomial(obj.points, np.array([a.sum() for a in areas]) / sum(a.sum() for a in areas))
    cloud = []
    for (vertices, triangles), area, count in zip(meshes, areas, counts):
        pick = rng.choice(len(triangles), count, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
        t = vertices[triangles[pick]]
        cloud.append((1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2])
    points = np.concatenate(cloud)
    diagonal = np.linalg.norm(np.ptp(points, axis=0))
    points = rng.permutation(points + obj.noise * diagonal * rng.standard_normal(points.shape))
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])
    return (points, np.concatenate([v for v, _ in meshes]),
            np.concatenate([t + o for (_, t), o in zip(meshes, offsets)]))


def step_figures(path: Path) -> dict:
    """The STEP file read back: solids, shells, faces, free edges, validity, volume, gap."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.ShapeAnalysis import ShapeAnalysis_FreeBounds
    from OCP.STEPControl import STEPControl_Reader
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_SHELL, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    reader = STEPControl_Reader()
    reader.ReadFile(str(path))
    reader.TransferRoots()
    shape = reader.OneShape()

    def count(kind) -> int:
        n, explorer = 0, TopExp_Explorer(shape, kind)
        while explorer.More():
            n, _ = n + 1, explorer.Next()
        return n

    free = ShapeAnalysis_FreeBounds(shape)
    gap, explorer = 0.0, TopExp_Explorer(shape, TopAbs_EDGE)
    while explorer.More():
        gap = max(gap, BRep_Tool.Tolerance_s(TopoDS.Edge(explorer.Current())))
        explorer.Next()
    out = {"solids": count(TopAbs_SOLID), "shells": count(TopAbs_SHELL), "step_faces": count(TopAbs_FACE),
           "free": count_edges(free.GetOpenWires()) + count_edges(free.GetClosedWires()),
           "valid": bool(BRepCheck_Analyzer(shape).IsValid()), "gap": gap, "volume": None}
    if out["solids"]:
        props = GProp_GProps()
        BRepGProp.VolumeProperties_s(shape, props, 1e-7, False)
        out["volume"] = abs(props.Mass())
    return out


def count_edges(shape) -> int:
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer

    n, explorer = 0, TopExp_Explorer(shape, TopAbs_EDGE)
    while explorer.More():
        n, _ = n + 1, explorer.Next()
    return n


def fit(cloud: Path, out: Path, config: Path | None, extra: list[str]) -> float:
    start = time.perf_counter()
    cmd = ["psonurbs", "fit", str(cloud), "-o", str(out), "--format", "step", "-q", *extra]
    if config is not None:
        cmd += ["-c", str(config)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode not in (0, 3):
        raise RuntimeError(f"{cloud.name}: psonurbs exit {done.returncode}: {done.stderr.strip()[-400:]}")
    return time.perf_counter() - start


def scored(cloud: Path, out: Path, truth: Path | None, scorer: Path | None) -> dict:
    script = scorer or Path(__file__).resolve().parent / "score.py"
    cmd = [sys.executable, str(script), str(cloud), str(out)] + (["--gt", str(truth)] if truth else [])
    done = subprocess.run(cmd, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def row(name: str, true_faces, doc: dict, figures: dict, step: dict, volume: float | None, seconds: float) -> list:
    err = None if volume is None or step["volume"] is None else step["volume"] / volume - 1.0
    cells = [name, f"{len(doc.get('surfaces') or [doc['surface']])} / {true_faces}",
             *(figures.get(k) for k in ("p99", "truth_rms", "cover_max", "far_max")),
             step["solids"], step["shells"], step["free"], "yes" if step["valid"] else "NO",
             None if err is None else f"{100 * err:+.2f}%", step["gap"], f"{seconds:.1f}"]
    return ["-" if c is None else f"{c:.3g}" if isinstance(c, float) else str(c) for c in cells]


DOC = Path(__file__).resolve().parents[1] / "docs" / "objects.md"


def document(table: str, seed: int) -> str:
    lines = "\n".join(f"- `{o.name}`: {o.note}; {o.points:,} points, noise {o.noise:g} of the diagonal"
                      for o in OBJECTS.values())
    return f"""# Whole objects

`psonurbs fit --patches auto` on clouds of objects made of several faces, each fitted with
orders 4 x 4 and a p99 tolerance of 2e-3 of the bounding-box diagonal and written as STEP,
which OpenCASCADE then reads back. This page is written by

    python3 benchmarks/objects.py --docs

(seed {seed}; the repository's scorer, `benchmarks/score.py`; the cad extra). The objects:

{lines}

Columns (distances relative to the diagonal): `p99` of the points to their nearest face;
`truth_rms` of the faces to the true surface; `cover_max` the true surface's farthest
point from every face; `far_max` the farthest point from every face in median point
spacings; the STEP read back: `solids`, `shells`, `free` edges (none: closed), BRepCheck
`valid`; `volume err` the solid's volume against the true one; `gap` the widest gap
between two faces' edges; `seconds` of the whole `psonurbs fit`.

{table}
"""


HEADER = ["object", "faces / true", "p99", "truth_rms", "cover_max", "far_max", "solids", "shells", "free", "valid",
          "volume err", "gap", "seconds"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--docs", action="store_true", help=f"write {DOC.name} in docs/ from every object")
    ap.add_argument("--only", nargs="+", choices=list(OBJECTS), help="these objects only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scorer", type=Path, help="another score.py to score the faces with")
    ap.add_argument("--clouds", nargs="+", type=Path, default=[], help="other clouds (no truth)")
    ap.add_argument("--tolerance-rel", default="2e-3", help="the clouds' tolerance (default 2e-3)")
    ap.add_argument("--points", type=int, help="sample every object with this many points (default: its own)")
    ap.add_argument("--swarm", nargs=2, type=int, metavar=("PARTICLES", "ITERATIONS"),
                    help="a smaller swarm (default: the config's, 40 x 300)")
    args = ap.parse_args(argv)
    if args.docs:
        args.only, args.clouds, args.swarm, args.points = None, [], None, None
    if args.out is None:
        import tempfile

        args.out = Path(tempfile.mkdtemp(prefix="psonurbs-objects-"))
    cases, results = args.out / "cases", args.out / "results"  # the fit's PLY mesh must not replace the cloud
    cases.mkdir(parents=True, exist_ok=True)
    swarm = ["--particles", str(args.swarm[0]), "--iterations", str(args.swarm[1])] if args.swarm else []
    rows = []
    for name in ([] if args.clouds and not args.only else args.only or list(OBJECTS)):
        obj = OBJECTS[name] if args.points is None else replace(OBJECTS[name], points=args.points)
        points, vertices, triangles = sample(obj, args.seed)
        cloud, config, truth = cases / f"{name}.ply", cases / f"{name}.yaml", cases / f"{name}.gt.npz"
        cloud.write_bytes(ply(points))
        config.write_text("orders: [4, 4]\npatches: auto\ntolerance_rel: 0.002\n")
        np.savez_compressed(truth, vertices=vertices, triangles=triangles, noise=obj.noise, outliers=0.0)
        seconds = fit(cloud, results, config, swarm)
        doc = json.loads((results / f"{name}.json").read_text())
        rows.append(row(name, obj.face_count, doc, scored(cloud, results, truth, args.scorer),
                        step_figures(results / f"{name}.step"), obj.volume, seconds))
        print(" | ".join(rows[-1]), flush=True)
    for cloud in args.clouds:
        seconds = fit(cloud, results, None, ["--patches", "auto", "--tolerance-rel", args.tolerance_rel, *swarm])
        doc = json.loads((results / f"{cloud.stem}.json").read_text())
        rows.append(row(cloud.stem, "?", doc, scored(cloud, results, None, args.scorer),
                        step_figures(results / f"{cloud.stem}.step"), None, seconds))
        print(" | ".join(rows[-1]), flush=True)
    table = "\n".join(["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER),
                       *("| " + " | ".join(r) + " |" for r in rows)])
    if args.docs:
        DOC.write_text(document(table, args.seed))
        print(f"wrote {DOC}")
        return 0
    print("\n" + table + f"\n\nclouds and results in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
