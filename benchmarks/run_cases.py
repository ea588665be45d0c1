#!/usr/bin/env python3
"""Fit the benchmark cases with ``psonurbs fit`` and score them independently.

    python benchmarks/run_cases.py                    # every case, swarm and classical
    python benchmarks/run_cases.py --cases franke_grid wave_graded --variants swarm
    python benchmarks/run_cases.py --cases torus --seed 3   # a fresh draw of a case
    python benchmarks/run_cases.py --variants swarm --baseline /path/to/other/bin/psonurbs

The cases come from ``benchmarks/cases.py`` and the figures from ``benchmarks/score.py``
(which re-evaluates the JSON with scipy, nothing of psonurbs). Each case is fitted with
its own YAML by the installed ``psonurbs`` command, timed (wall clock, whole command),
then scored; figures are relative to the cloud's bounding-box diagonal.

With ``--baseline EXE`` every case and variant is also fitted by that other build
(say, a snapshot of main), right before this one: rows ``main`` and ``this`` alternate,
so both see the same machine load.

Variants:
  swarm      the case's config as it is (strategy hybrid: knots and weights by the swarm)
  classical  the same pipeline without a swarm: one particle, one iteration, i.e. uniform
             knots, unit weights, least squares, the same parametrisation and polish
  full       strategy full: the paper's own search space (Eq. 10)
  auto       topology auto: the tool chooses the topology (the column says which)
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cases import CASES, write
from score import score

VARIANT_ARGS = {"swarm": [], "classical": ["--particles", "1", "--iterations", "1"],
                "full": ["--strategy", "full"], "auto": ["--topology", "auto"]}
COLUMNS = ["topology", "param", "rmse", "truth_rms", "truth_max", "cover_max", "overhang", "seam", "pole_spread",
           "mesh_vs_nurbs", "claim_err", "curve_ok", "suspect"]


def outside_score(script: Path):
    """A scorer run as ``python SCRIPT CLOUD OUTDIR --gt TRUTH`` that prints one JSON line last
    (the shared scorer's interface), as a function like :func:`score`."""
    def scored(cloud: Path, outdir: Path, truth: Path) -> dict:
        done = subprocess.run([sys.executable, str(script), str(cloud), str(outdir), "--gt", str(truth)],
                              capture_output=True, text=True, check=True)
        return json.loads(done.stdout.strip().splitlines()[-1])
    return scored


def fit_and_score(case: str, variant: str, cases_dir: Path, out_root: Path, exe: str = "psonurbs",
                  scorer=score) -> dict:
    out = out_root / variant / case
    cmd = [exe, "fit", str(cases_dir / f"{case}.ply"), "--config", str(cases_dir / f"{case}.yaml"),
           "--out", str(out), "--quiet", *VARIANT_ARGS[variant]]
    start = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        return {"error": (run.stderr or run.stdout).strip().splitlines()[-1], "seconds": seconds}
    result = scorer(cases_dir / f"{case}.ply", out, cases_dir / f"{case}.gt.npz")
    doc = json.loads((out / f"{case}.json").read_text())
    result["topology"] = doc["topology"]
    result["param"] = doc["fit"].get("parametrisation", {}).get("method")
    result["suspect"] = {True: "SUSPECT", False: "no"}.get(doc["metrics"].get("suspect"))  # None: not checked
    seams = [result[k] for k in ("seam_u", "seam_v") if k in result]
    result["seam"] = max(seams) if seams else None
    if result.get("claimed_rmse") and result.get("rmse"):
        result["claim_err"] = abs(result["claimed_rmse"] / result["rmse"] - 1.0)
    result["seconds"] = seconds
    return result


def cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES), metavar="CASE",
                    help="cases to run (default: all; see benchmarks/cases.py --list)")
    ap.add_argument("--seed", type=int, default=0, help="cloud seed: 0 the public clouds, others fresh draws")
    ap.add_argument("--variants", nargs="*", default=["classical", "swarm"], choices=list(VARIANT_ARGS))
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--baseline", metavar="EXE", help="another psonurbs executable to fit every case with too")
    ap.add_argument("--scorer", type=Path, metavar="SCORE_PY",
                    help="score with this script instead of benchmarks/score.py (same command line and JSON "
                         "line; the earlier shared scorer is about 50 times faster on the fine truth meshes)")
    args = ap.parse_args(argv)
    scorer = score if args.scorer is None else outside_score(args.scorer)
    builds = ([("main", args.baseline)] if args.baseline else []) + [("this", "psonurbs")]
    root = args.out or Path(tempfile.mkdtemp(prefix="psonurbs-bench-"))
    cases_dir = root / "cases"
    cases_dir.mkdir(parents=True, exist_ok=True)
    for case in args.cases:
        write(CASES[case], cases_dir, args.seed)
    header = ["case", "variant", *(["build"] if args.baseline else []), *COLUMNS, "noise", "seconds"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for case in args.cases:
        for variant in args.variants:
            for build, exe in builds:
                label = [build] if args.baseline else []
                r = fit_and_score(case, variant, cases_dir, root / "results" / build, exe, scorer)
                if "error" in r:
                    print(f"| {case} | {variant} | " + " | ".join(label + [f"failed: {r['error']}"]) + " |"
                          + " |" * (len(header) - 3 - len(label)), flush=True)
                    continue
                row = [case, variant, *label, *(cell(r.get(c)) for c in COLUMNS), cell(r.get("noise")),
                       f"{r['seconds']:.1f}"]
                print("| " + " | ".join(row) + " |", flush=True)
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
