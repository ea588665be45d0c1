#!/usr/bin/env python3
"""Big clouds: seconds and peak resident memory of every stage against the number of points.

    python benchmarks/perf/scale.py --real SCANS/                # ripples at 10k, 100k, 300k, 1M; SCANS/bunny_front.ply
    python benchmarks/perf/scale.py --points 10000 100000        # ripples only
    python benchmarks/perf/scale.py --json mine.json             # keep the figures ...
    python benchmarks/perf/scale.py --plot docs/scale.png mine.json:this other.json:baseline   # ... and plot them
    python benchmarks/perf/scale.py --reading 1000000            # read a binary PLY and an XYZ file of 1M points

**The ripples** (generated here, fixed seed): the height field over the unit square

    z = 0.03 (sin(4 pi x + 1) + cos(3 pi y) + 0.5 sin(2 pi (x + y)))

(two waves along x, one and a half along y and one across the diagonal; 0.15 from
trough to crest), sampled at N points uniform on [0, 1]^2, each moved along the true
surface normal by Gaussian noise of sigma = 1e-3 (of the square's side). A 16 x 16
cubic net represents it to 2.4e-5 (0.024 sigma, least squares on the exact surface),
so the figures judge the method, not the net. Fitted with a 16 x 16 cubic net, the
default swarm (40 particles, 300 iterations) and every other key at its default.

Each fit runs in its own process, as ``psonurbs fit`` would run it (read the binary
PLY, fit, tessellate, write the files), so the peak memory is its own. The stages are
told apart by wrapping the pipeline's functions (outermost call wins):

    read         reading the cloud file
    organise     validation, de-duplication, normalisation, the local outlier test
    parametrise  the first (u, v) (and with ``topology: auto`` the choice of topology)
    swarm        the robust start (the classical fit's weights), the swarm and its validation
    polish       both polishes, the leave-one-out smoothing between them (and a big
                 cloud's last rounds on every point)
    refine       the joint refinement and its anchoring
    write        the final distances (metrics), tessellation and writing the files

Per stage: the process's CPU seconds (the fit runs on one thread, so on a quiet machine
they are its wall seconds; on a shared machine they are the fairer figure) and the peak
resident set size while the stage ran (a thread samples /proc/self/statm every 5 ms;
the process's high-water mark ``ru_maxrss`` is exact and is credited to the stage that
raised it); for the whole command, its CPU and wall seconds and peak. Figures of the
fit: ``rmse`` (the points' distance to the fitted surface) and ``truth_rms`` /
``truth_max`` (the fitted surface's distance to the true one, on a 301 x 301 grid of
its domain), in units of the noise sigma, measured here on triangle meshes with open3d
(601 x 601 of the fit, 1201 x 1201 of the truth: chord errors below 0.002 sigma),
independently of psonurbs's own foot points. ``bunny_front`` is the real scan with
``configs/auto.yaml``; its rmse is relative to the bounding-box diagonal.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
SIGMA = 1e-3
SEED = 14
STAGES = ["read", "organise", "parametrise", "swarm", "polish", "refine", "write"]
# function (module, name) -> (the stage it starts, the stage that starts when it returns)
WRAPPED = {
    ("psonurbs.run.batch", "load_cloud"): ("read", None),
    ("psonurbs.fitting.pipeline", "organise"): ("organise", None),
    ("psonurbs.fitting.pipeline", "parametrise_for"): ("parametrise", None),
    ("psonurbs.fitting.pipeline", "choose_topology"): ("parametrise", None),
    ("psonurbs.fitting.pipeline", "local_outliers"): ("organise", None),
    ("psonurbs.fitting.pipeline", "classical_weights"): ("swarm", None),
    ("psonurbs.fitting.pipeline", "minimise"): ("swarm", None),
    ("psonurbs.fitting.pipeline", "held_out_choice"): ("swarm", None),  # the validation finishes its candidates
    ("psonurbs.fitting.pipeline", "finish"): ("polish", None),  # polish, smoothing, polish
    ("psonurbs.fitting.pipeline", "refined_if_better"): ("refine", None),  # refinement, its polish, acceptance
    ("psonurbs.fitting.pipeline", "run_hybrid"): (None, "write"),
    ("psonurbs.fitting.pipeline", "run_full"): (None, "write"),
    ("psonurbs.fitting.pipeline", "finished"): ("polish", "write"),  # a big cloud's last rounds on all points
}


# ---- the ripples -----------------------------------------------------------

def ripple_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.03 * (np.sin(4 * np.pi * x + 1.0) + np.cos(3 * np.pi * y) + 0.5 * np.sin(2 * np.pi * (x + y)))


def ripple_gradient(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    diagonal = 0.5 * 2 * np.pi * np.cos(2 * np.pi * (x + y))
    return (0.03 * (4 * np.pi * np.cos(4 * np.pi * x + 1.0) + diagonal),
            0.03 * (-3 * np.pi * np.sin(3 * np.pi * y) + diagonal))


def ripples(n: int, seed: int = SEED) -> np.ndarray:
    """(n, 3) noisy samples of the ripples, noise along the true normal (sigma = SIGMA)."""
    rng = np.random.default_rng(seed)
    x, y = rng.random(n), rng.random(n)
    gx, gy = ripple_gradient(x, y)
    normal = np.stack([-gx, -gy, np.ones(n)], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return np.stack([x, y, ripple_height(x, y)], axis=1) + SIGMA * rng.standard_normal(n)[:, None] * normal


def grid_mesh(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an (a, b, 3) grid of points."""
    a, b = points.shape[:2]
    i, j = np.meshgrid(np.arange(a - 1), np.arange(b - 1), indexing="ij")
    p = (i * b + j).ravel()
    tris = np.concatenate([np.stack([p, p + b, p + 1], 1), np.stack([p + 1, p + b, p + b + 1], 1)])
    return points.reshape(-1, 3), tris


def mesh_distance(vertices: np.ndarray, triangles: np.ndarray, queries: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(queries.astype(np.float32))).numpy().astype(float)


def surface_grid(surface, res: int) -> np.ndarray:
    return surface.evaluate_grid(*surface.parameter_grid(res, res))


def figures(surface, points: np.ndarray, truth: bool) -> dict:
    """rmse (points to the fit) and, for the ripples, truth_rms / truth_max (fit to truth)."""
    d = mesh_distance(*grid_mesh(surface_grid(surface, 601)), points)
    out = {"rmse": float(np.sqrt(np.mean(d ** 2)))}
    if truth:
        g = np.linspace(0.0, 1.0, 1201)
        x, y = np.meshgrid(g, g, indexing="ij")
        true = np.stack([x, y, ripple_height(x, y)], axis=2)
        t = mesh_distance(*grid_mesh(true), surface_grid(surface, 301).reshape(-1, 3))
        out.update(truth_rms=float(np.sqrt(np.mean(t ** 2))), truth_max=float(t.max()))
    return out


def write_binary_ply(path: Path, points: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property double x\nproperty double y\nproperty double z\nend_header\n").encode("ascii")
    path.write_bytes(header + np.ascontiguousarray(points, "<f8").tobytes())


def write_xyz(path: Path, points: np.ndarray) -> None:
    np.savetxt(path, points, fmt="%.9f")


def write_pts(path: Path, points: np.ndarray) -> None:
    np.savetxt(path, points, fmt="%.9f", header=str(len(points)), comments="")


# ---- the stage clock -------------------------------------------------------

def resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def high_water_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


class StageClock:
    """Wall seconds and peak RSS per stage; the stage is switched by wrapped functions."""

    def __init__(self, interval: float = 0.005):
        self.seconds = {s: 0.0 for s in STAGES}
        self.cpu = {s: 0.0 for s in STAGES}
        self.peak = {s: 0 for s in STAGES}
        self.stage, self.depth, self.interval = "read", 0, interval
        self.started = self.mark = time.perf_counter()
        self.cpu_started = self.cpu_mark = time.process_time()
        self.high_water = high_water_bytes()
        self.running = True
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()

    def _sample(self) -> None:
        while self.running:
            stage = self.stage
            self.peak[stage] = max(self.peak[stage], resident_bytes())
            time.sleep(self.interval)

    def switch(self, stage: str) -> None:
        now, cpu = time.perf_counter(), time.process_time()
        self.seconds[self.stage] += now - self.mark
        self.cpu[self.stage] += cpu - self.cpu_mark
        water = high_water_bytes()
        if water > self.high_water:  # this stage raised the process's high-water mark
            self.peak[self.stage] = max(self.peak[self.stage], water)
            self.high_water = water
        self.peak[self.stage] = max(self.peak[self.stage], resident_bytes())
        self.stage, self.mark, self.cpu_mark = stage, now, cpu

    def stop(self) -> dict:
        self.switch(self.stage)
        self.running = False
        self.thread.join()
        return {"seconds": self.seconds, "cpu_seconds": self.cpu,
                "peak_mb": {s: b / 2 ** 20 for s, b in self.peak.items()},
                "total_seconds": time.perf_counter() - self.started,
                "total_cpu_seconds": time.process_time() - self.cpu_started,
                "peak_total_mb": high_water_bytes() / 2 ** 20}

    def wrap(self, module, name: str, starts: str | None, ends: str | None) -> None:
        inner = getattr(module, name)  # AttributeError: the pipeline changed, update WRAPPED

        def wrapped(*args, **kwargs):
            outermost = self.depth == 0
            if outermost and starts:
                self.switch(starts)
            nested = 1 if starts else 0  # a function that only ends a stage does not hide its callees
            self.depth += nested
            try:
                return inner(*args, **kwargs)
            finally:
                self.depth -= nested
                if outermost and ends:
                    self.switch(ends)

        setattr(module, name, wrapped)


def run_child(spec: dict) -> dict:
    """One fit as ``psonurbs fit`` runs it, with the stage clock; returns its figures."""
    import importlib

    from psonurbs.config import load_config
    from psonurbs.geometry.nurbs import NurbsSurface
    from psonurbs.run.batch import run_batch
    from psonurbs.run.inputs import Job

    with tempfile.TemporaryDirectory(prefix="psonurbs-scale-") as tmp:
        tmp = Path(tmp)
        if spec["kind"] == "ripples":
            cloud = tmp / "ripples.ply"
            write_binary_ply(cloud, ripples(spec["points"]))
            config = load_config(None).with_overrides(orders=[4, 4], net_size=[16, 16], topology="open")
        else:
            cloud = Path(spec["path"])
            config = load_config(REPO / "configs" / "auto.yaml")
        clock = StageClock()
        for (module, name), (starts, ends) in WRAPPED.items():
            module = importlib.import_module(module)
            if hasattr(module, name) or name != "finished":  # "finished" only exists where big clouds are finished
                clock.wrap(module, name, starts, ends)
        clock.switch("read")
        row = run_batch([Job(cloud, config)], tmp / "out")[0]
        timing = clock.stop()
        result = tmp / "out" / f"{cloud.stem}.json"
        if not result.exists():  # not fitted (a "suspect" fit is written and measured)
            return {**spec, "error": row.message}
        doc = json.loads(result.read_text())
        surface = NurbsSurface.from_dict(doc["surface"])
        from psonurbs.formats.clouds import read_cloud

        points = read_cloud(cloud)
        scores = figures(surface, points, spec["kind"] == "ripples")
        scale = SIGMA if spec["kind"] == "ripples" else float(np.linalg.norm(np.ptp(points, axis=0)))
        scores = {k: v / scale for k, v in scores.items()}
        return {**spec, "points": int(len(points)), **timing, **scores, "claimed_rmse": doc["metrics"]["rmse"] / scale,
                "topology": doc["topology"], "polish_iterations": doc["fit"].get("polish_iterations"),
                "status": row.status}


# ---- the table -------------------------------------------------------------

def row_cells(r: dict) -> list[str]:
    if "error" in r:
        return [r["name"], f"failed: {r['error']}"]
    unit = "sigma" if r["kind"] == "ripples" else "diag"
    stages = [f"{r['cpu_seconds'][s]:.1f} / {r['peak_mb'][s]:.0f}" for s in STAGES]
    truth = [f"{r['truth_rms']:.3f}", f"{r['truth_max']:.2f}"] if "truth_rms" in r else ["-", "-"]
    rmse = f"{r['rmse']:.4f}" if unit == "sigma" else f"{r['rmse']:.3e}"
    return [r["name"], f"{r['points']:,}", *stages, f"{r['total_cpu_seconds']:.1f}", f"{r['total_seconds']:.1f}",
            f"{r['peak_total_mb']:.0f}",
            f"{rmse} {unit}", *truth]


HEADER = ["cloud", "points", *(f"{s} s / MB" for s in STAGES), "cpu s", "wall s", "peak MB", "rmse", "truth_rms sigma",
          "truth_max sigma"]


def print_row(cells: list[str]) -> None:
    print("| " + " | ".join(cells) + " |", flush=True)


def measure(specs: list[dict], python: str) -> list[dict]:
    print_row(HEADER)
    print("|" + "---|" * len(HEADER), flush=True)
    results = []
    for spec in specs:
        run = subprocess.run([python, str(Path(__file__).resolve()), "--child", json.dumps(spec)],
                             capture_output=True, text=True)
        if run.returncode != 0:
            result = {**spec, "error": (run.stderr or run.stdout).strip().splitlines()[-1]}
        else:
            result = json.loads(run.stdout.strip().splitlines()[-1])
        results.append(result)
        print_row(row_cells(result))
    return results


def reading(n: int) -> None:
    """Seconds to read a binary PLY, an XYZ and a PTS text file (with its count line) of
    n ripples points (open3d imported before the clock starts)."""
    import open3d  # noqa: F401  (its import takes seconds of its own)

    from psonurbs.formats.clouds import read_cloud

    points = ripples(n)
    with tempfile.TemporaryDirectory(prefix="psonurbs-read-") as tmp:
        print("| file | points | MB | cpu s | wall s |\n|---|---|---|---|---|")
        for suffix, write in ((".ply", write_binary_ply), (".xyz", write_xyz), (".pts", write_pts)):
            path = Path(tmp) / f"ripples{suffix}"
            write(path, points)
            start, cpu = time.perf_counter(), time.process_time()
            got = read_cloud(path)
            cpu, seconds = time.process_time() - cpu, time.perf_counter() - start
            assert got.shape == points.shape and np.allclose(got, points, atol=1e-8)
            print(f"| {suffix} | {n:,} | {path.stat().st_size / 2 ** 20:.0f} | {cpu:.2f} | {seconds:.2f} |", flush=True)


def plot(path: Path, sources: list[str]) -> None:
    """CPU seconds of the whole command against points, log-log, one line per saved result
    file (FILE:LABEL), with the marks (60 s at 300k points, 180 s at 1M)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for source in sources:
        file, _, label = source.partition(":")
        rows = [r for r in json.loads(Path(file).read_text()) if r["kind"] == "ripples" and "error" not in r]
        rows.sort(key=lambda r: r["points"])
        ax.plot([r["points"] for r in rows], [r["total_cpu_seconds"] for r in rows], "o-", label=label or file)
    ax.plot([3e5, 1e6], [60, 180], "kv", label="targets: 60 s at 300k, 180 s at 1M")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("points (ripples, 16 x 16 cubic, default swarm)")
    ax.set_ylabel("CPU seconds (read, fit, write)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, nargs="*", default=[10_000, 100_000, 300_000, 1_000_000])
    ap.add_argument("--real", type=Path, help="a directory of real scans holding bunny_front.ply (the Stanford "
                    "bunny's range image bun000; none ship with the repository)")
    ap.add_argument("--python", default=sys.executable, help="interpreter whose psonurbs is measured")
    ap.add_argument("--json", type=Path, help="save the figures here")
    ap.add_argument("--plot", type=Path, help="plot saved figures (FILE[:LABEL] ...) to this PNG")
    ap.add_argument("--reading", type=int, help="time reading a binary PLY and an XYZ file of this many points")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("sources", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(run_child(json.loads(args.child))))
        return 0
    if args.plot:
        plot(args.plot, args.sources)
        return 0
    if args.reading:
        reading(args.reading)
        return 0
    specs = [{"kind": "ripples", "name": "ripples", "points": n} for n in args.points]
    if args.real:
        bunny = args.real / "bunny_front.ply"
        if not bunny.is_file():
            ap.error(f"{bunny}: no such file")
        specs.append({"kind": "bunny_front", "name": "bunny_front", "path": str(bunny.resolve())})
    results = measure(specs, args.python)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
