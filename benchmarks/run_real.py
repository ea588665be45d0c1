#!/usr/bin/env python3
"""Fit real scans with ``psonurbs fit`` and score them independently.

    python benchmarks/run_real.py SCANS/                        # every cloud in SCANS/, topology auto
    python benchmarks/run_real.py SCANS/ --clouds tennis_ball --config configs/auto.yaml

SCANS is a directory of real scanned clouds (any format ``psonurbs fit`` reads: PLY,
XYZ, LAS/LAZ, E57, ...). None ship with the repository: scans carry their owners'
licences. The README's real-scan table used public ones (the Stanford bunny's range
image bun000, the ISPRS filter-test sample 51 and the lidR Topography tile, YCB objects,
a CC BY head scan; see "Real scans" in the README for where each comes from).

There is no ground truth, so ``benchmarks/score.py`` reports how far the points are
from the surface and how much surface lies away from every point (``overhang``).
Figures are relative to the cloud's bounding-box diagonal; ``claim_err`` is how far the
JSON's own rmse is from the scorer's; ``seconds`` is the wall time of the whole command.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from run_cases import cell
from score import score

REPO = Path(__file__).resolve().parents[1]
COLUMNS = ["points", "topology", "outliers", "rmse", "p99", "max", "overhang", "claim_err"]
READABLE = (".ply", ".xyz", ".txt", ".pts", ".pcd", ".las", ".laz", ".e57")


def fit_and_score(cloud: Path, config: Path, out: Path) -> dict:
    cmd = ["psonurbs", "fit", str(cloud), "--config", str(config), "--out", str(out), "--quiet"]
    start = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        return {"error": (run.stderr or run.stdout).strip().splitlines()[-1], "seconds": seconds}
    if cloud.suffix.lower() not in (".ply", ".xyz", ".txt", ".pts"):  # the scorer reads PLY and text
        return {"error": f"fitted; the scorer reads PLY or text clouds, not {cloud.suffix}", "seconds": seconds}
    result = score(cloud, out)
    doc = json.loads((out / f"{cloud.stem}.json").read_text())
    result["topology"], result["outliers"] = doc["topology"], doc["metrics"].get("outliers")
    result["claim_err"] = abs(result["claimed_rmse"] / result["rmse"] - 1.0) if result.get("rmse") else None
    result["seconds"] = seconds
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scans", type=Path, help="directory of real scans")
    ap.add_argument("--clouds", nargs="*", help="their stems (default: every cloud in SCANS, one file per stem)")
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "auto.yaml")
    ap.add_argument("--out", type=Path, help="keep the results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    if not args.scans.is_dir():
        print(f"run_real.py: {args.scans}: not a directory of scans", file=sys.stderr)
        return 2
    found: dict[str, Path] = {}
    for path in sorted(args.scans.iterdir(), key=lambda p: (p.stem, READABLE.index(p.suffix.lower())
                                                            if p.suffix.lower() in READABLE else 99)):
        if path.suffix.lower() in READABLE:
            found.setdefault(path.stem, path)  # a PLY before the same cloud's XYZ
    names = args.clouds or sorted(found)
    missing = [n for n in names if n not in found]
    if missing or not names:
        print(f"run_real.py: {args.scans}: no cloud named {missing[0]!r}" if missing else
              f"run_real.py: {args.scans}: no clouds", file=sys.stderr)
        return 2
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-real-"))
    header = ["cloud", *COLUMNS, "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name in names:
        r = fit_and_score(found[name], args.config, root / name)
        if "error" in r:
            print(f"| {name} | failed: {r['error']} |" + " |" * (len(header) - 2), flush=True)
            continue
        print("| " + " | ".join([name, *(cell(r.get(c)) for c in COLUMNS), f"{r['seconds']:.1f}"]) + " |",
              flush=True)
    print(f"\nresults in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
