"""How far a fit moves when its input moves by almost nothing.

    python benchmarks/stability.py CLOUD --config CONFIG                 # 3 draws at 1e-12
    python benchmarks/stability.py CLOUD --config CONFIG --draws 5 --scale 1e-9
    python benchmarks/stability.py CLOUD --config CONFIG --set refine_iterations=60

The same cloud and config give byte-identical files; that says nothing about a cloud
that differs in its last bits (re-exported, converted, read on another machine). Here
the cloud is fitted as it is, then ``--draws`` times with every point moved by Gaussian
noise of ``--scale`` times its bounding-box diagonal (a fixed seed per draw), each by
``psonurbs fit`` in its own process. The table gives each fit's rmse (of the diagonal,
from its JSON) and what the pipeline decided on the way: the rounds of its polishes, the
refinement's steps and whether it was kept, the smoothing, the swarm's choice; then the
spread of the rmse, largest over smallest. A stable pipeline shows the same decisions
and a spread near 1; a fit decided by a knife-edge (a polish that stops on one round,
a refinement capped mid-descent, a leave-one-out pick between near-equal values) does
not (README, Output contract).

``--set KEY=VALUE`` (YAML values, repeatable) adds keys to the config, to see what they
do to the spread. The perturbed clouds are written as text with 17 significant digits,
so they hold the moved coordinates exactly; the draw 0 row is the cloud itself,
converted the same way.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from run import cell

from psonurbs.formats.clouds import read_cloud

COLUMNS = ["draw", "rmse / diagonal", "polish rounds", "refine steps", "refined", "smoothing", "swarm kept", "seconds"]


def fit(cloud: Path, config: Path, out: Path, exe: str) -> dict:
    """``psonurbs fit`` on one cloud; its JSON's figures (or the error it printed)."""
    run = subprocess.run([exe, "fit", str(cloud), "--config", str(config), "--out", str(out), "--quiet"],
                         capture_output=True, text=True)
    if run.returncode != 0:
        return {"error": (run.stderr or run.stdout).strip().splitlines()[-1]}
    doc = json.loads((out / f"{cloud.stem}.json").read_text())
    info = doc["fit"]
    return {"rmse / diagonal": doc["metrics"]["rmse_relative"], "polish rounds": info.get("polish_iterations"),
            "refine steps": info.get("refine_iterations"), "refined": info.get("refined"),
            "smoothing": info.get("smoothing"), "swarm kept": info.get("swarm", {}).get("kept")}


def config_with(config: Path | None, settings: list[str], folder: Path) -> Path:
    """The config with the ``KEY=VALUE`` settings added, written to ``folder``."""
    doc = (yaml.safe_load(config.read_text()) or {}) if config else {}
    for setting in settings:
        key, sep, value = setting.partition("=")
        if not sep:
            raise SystemExit(f"stability.py: --set {setting!r}: expected KEY=VALUE")
        doc[key.strip()] = yaml.safe_load(value)
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cloud", type=Path)
    ap.add_argument("--config", type=Path, help="the fit's YAML (default: the defaults)")
    ap.add_argument("--draws", type=int, default=3, help="perturbed copies to fit (default 3)")
    ap.add_argument("--scale", type=float, default=1e-12, help="the noise, times the diagonal (default 1e-12)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config key to add")
    ap.add_argument("--exe", default="psonurbs", help="the psonurbs command to run (default: the installed one)")
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    if args.draws < 1 or not args.scale > 0:
        ap.error("--draws must be at least 1 and --scale positive")
    points = read_cloud(args.cloud)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-stability-"))
    root.mkdir(parents=True, exist_ok=True)
    config = config_with(args.config, args.set, root)
    print(f"{args.cloud.name}: {len(points):,} points, noise {args.scale:g} x diagonal ({args.scale * diagonal:.3g}), "
          f"config {args.config or 'defaults'}{' + ' + ', '.join(args.set) if args.set else ''}\n")
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    errors = []
    for draw in range(args.draws + 1):
        moved = points if draw == 0 else points + args.scale * diagonal * np.random.default_rng(draw).normal(
            size=points.shape)
        cloud = root / f"draw{draw}" / f"{args.cloud.stem}.xyz"
        cloud.parent.mkdir(exist_ok=True)
        np.savetxt(cloud, moved, fmt="%.17g")
        start = time.perf_counter()
        result = fit(cloud, config, cloud.parent / "out", args.exe)
        seconds = time.perf_counter() - start
        if "error" in result:
            print(f"| {draw} | failed: {result['error']} |" + " |" * (len(COLUMNS) - 2), flush=True)
            continue
        errors.append(result["rmse / diagonal"])
        print("| " + " | ".join([str(draw), *(cell(result[c], 4) for c in COLUMNS[1:-1]), f"{seconds:.1f}"]) + " |",
              flush=True)
    if len(errors) > 1:
        print(f"\nrmse spread (largest / smallest): {max(errors) / min(errors):.3f}")
    print(f"results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
