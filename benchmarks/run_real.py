"""Fit the real scans with ``psonurbs fit`` and score them independently.

    python benchmarks/run_real.py                          # every scan, topology auto
    python benchmarks/run_real.py --clouds tennis_ball --config configs/auto.yaml

The scans are ``../shared/data/real/*.ply`` (see SOURCES.md there); there is no ground
truth, so the scorer (``../shared/bench/score.py``) reports how far the points are from
the surface and how much surface lies away from every point (``overhang``). Figures
are relative to the cloud's bounding-box diagonal; ``claim_err`` is how far the JSON's
own rmse is from the scorer's; ``seconds`` is the wall time of the whole command.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from run_cases import SHARED, cell

REAL = SHARED.parent / "data" / "real"
REPO = Path(__file__).resolve().parents[1]
COLUMNS = ["points", "topology", "outliers", "rmse", "p99", "max", "overhang", "claim_err"]


def fit_and_score(cloud: Path, config: Path, out: Path) -> dict:
    cmd = ["psonurbs", "fit", str(cloud), "--config", str(config), "--out", str(out), "--quiet"]
    start = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        return {"error": (run.stderr or run.stdout).strip().splitlines()[-1], "seconds": seconds}
    score = subprocess.run([sys.executable, str(SHARED / "score.py"), str(cloud), str(out)],
                           capture_output=True, text=True)
    result = json.loads(score.stdout.strip().splitlines()[-1])
    doc = json.loads((out / f"{cloud.stem}.json").read_text())
    result["topology"], result["outliers"] = doc["topology"], doc["metrics"].get("outliers")
    result["claim_err"] = abs(result["claimed_rmse"] / result["rmse"] - 1.0) if result.get("rmse") else None
    result["seconds"] = seconds
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clouds", nargs="*", default=sorted(p.stem for p in REAL.glob("*.ply")))
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "auto.yaml")
    ap.add_argument("--out", type=Path, help="keep the results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-real-"))
    header = ["cloud", *COLUMNS, "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for name in args.clouds:
        r = fit_and_score(REAL / f"{name}.ply", args.config, root / name)
        if "error" in r:
            print(f"| {name} | failed: {r['error']} |" + " |" * (len(header) - 2), flush=True)
            continue
        print("| " + " | ".join([name, *(cell(r.get(c)) for c in COLUMNS), f"{r['seconds']:.1f}"]) + " |",
              flush=True)
    print(f"\nresults in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
