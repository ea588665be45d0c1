#!/usr/bin/env python3
"""Fit a suite of benchmark clouds with ``psonurbs fit``, score them independently, tabulate.

    python3 benchmarks/run.py --suite public                  # the README's table
    python3 benchmarks/run.py --suite features --cases cliff_noisy vase --variants swarm
    python3 benchmarks/run.py --cases torus --seed 3          # a fresh draw of a case
    python3 benchmarks/run.py --suite real --scans SCANS/     # real scans, no ground truth
    python3 benchmarks/run.py --baseline /other/bin/psonurbs  # rows of another build alternate
    python3 benchmarks/run.py --build /dev/bin/psonurbs --baseline psonurbs  # a build under test
    python3 benchmarks/run.py --scorer OTHER_SCORE.py         # an outside scorer
    python3 benchmarks/run.py --docs                          # regenerate docs/benchmark.md

The suites and their cases are in ``benchmarks/cases.py``; ``real`` fits every cloud of
``--scans`` with ``--config`` (default ``configs/auto.yaml``). Each cloud is fitted by the
``psonurbs`` command on PATH or ``--build EXE`` (and ``--baseline EXE`` too, right before
it, so both see the same machine load), timed (wall clock, whole command), then scored by
``benchmarks/score.py`` (which re-evaluates the JSON with scipy, nothing of psonurbs) or by
``--scorer SCRIPT``, run as ``python SCRIPT CLOUD OUTDIR --gt GT`` and printing one JSON
line. Figures are relative to the cloud's bounding-box diagonal.

Variants:
  swarm      the case's config as it is (knots and weights by the swarm)
  classical  the same pipeline without a swarm: one particle, one iteration, i.e. uniform
             knots, unit weights, least squares, the same parametrisation and polish
  full       strategy full: the paper's own search space (Eq. 10)
  auto       topology auto: the tool chooses the topology (the column says which)

With ``--out DIR`` the clouds, the fits and each row's figures (``ROW.json`` beside each
fit) stay in DIR; ``--reuse DIR`` takes the rows already in DIR (same seed) and fits only
the others, so ``--docs --reuse DIR`` writes the document from a run just made.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from cases import SUITES, write
from score import score

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "benchmark.md"
VARIANT_ARGS = {"swarm": [], "classical": ["--particles", "1", "--iterations", "1"],
                "full": ["--strategy", "full"], "auto": ["--topology", "auto"]}
FULL = ["topology", "param", "rmse", "truth_rms", "truth_max", "cover_max", "cover_max_sp", "overhang", "overrun_max",
        "overrun_p95", "seam", "pole_spread", "mesh_vs_nurbs", "claim_err", "curve_ok", "suspect", "noise"]


@dataclass(frozen=True)
class SuiteView:
    """How a suite is run and shown: its default variants and its table's columns."""

    variants: tuple[str, ...]
    columns: tuple[str, ...]


VIEWS = {
    "public": SuiteView(("classical", "swarm"), tuple(FULL)),
    "features": SuiteView(("classical", "swarm"), tuple(FULL)),
    "robust": SuiteView(("swarm",), ("topology", "outliers", "rmse", "inlier_rmse", "truth_rms", "truth_max",
                                     "cover_max", "cover_max_sp", "overrun_max", "overrun_p95", "noise")),
    "unseen": SuiteView(("swarm",), ("param", "rmse", "inlier_rmse", "truth_rms", "truth_max", "cover_max",
                                     "cover_max_sp", "overrun_max", "overrun_p95", "overhang", "outliers", "suspect")),
    "trims": SuiteView(("swarm",), ("points", "loops", "expected", "overhang", "rmse", "truth_rms", "truth_max",
                                    "cover_max", "cover_max_sp", "overrun_max", "overrun_p95", "mesh_vs_nurbs",
                                    "noise")),
    "edges": SuiteView(("swarm",), ("topology", "param", "loops", "rmse", "truth_rms", "truth_sigma", "cover_max_sp",
                                    "sample_cover_sp", "overrun_max", "overrun_p95", "bare_share", "empty_share")),
    "thick": SuiteView(("swarm",), ("param", "rmse", "truth_rms", "truth_sigma", "cover_max_sp", "overrun_max",
                                    "overrun_p95", "bare_share", "overhang")),
    "real": SuiteView(("swarm",), ("points", "topology", "outliers", "rmse", "p99", "max", "overhang",
                                   "claim_err")),
}
READABLE = (".ply", ".xyz", ".txt", ".pts", ".pcd", ".las", ".laz", ".e57")
SCORABLE = (".ply", ".xyz", ".txt", ".pts")  # what the scorer reads


@dataclass(frozen=True)
class Job:
    """One cloud to fit: its files (``truth`` None for a real scan) and the loops its
    footprint calls for."""

    name: str
    cloud: Path
    config: Path
    truth: Path | None = None
    loops: int | None = None


def outside_score(script: Path):
    """A scorer run as ``python SCRIPT CLOUD OUTDIR [--gt TRUTH]`` that prints one JSON line
    last, as a function like :func:`score.score`."""
    def scored(cloud: Path, outdir: Path, truth: Path | None) -> dict:
        gt = ["--gt", str(truth)] if truth else []
        done = subprocess.run([sys.executable, str(script), str(cloud), str(outdir), *gt],
                              capture_output=True, text=True, check=True)
        return json.loads(done.stdout.strip().splitlines()[-1])
    return scored


def fit_and_score(job: Job, variant: str, out: Path, exe: str = "psonurbs", scorer=score) -> dict:
    """``EXE fit`` on the job's cloud into ``out``, timed, then its figures: the scorer's and
    what the JSON says (topology, parametrisation, self-checks, outliers, trim loops and the
    share of the untrimmed surface the fit found empty)."""
    cmd = [exe, "fit", str(job.cloud), "--config", str(job.config), "--out", str(out), "--quiet",
           *VARIANT_ARGS[variant]]
    start = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        return {"error": (run.stderr or run.stdout).strip().splitlines()[-1], "seconds": seconds}
    if job.cloud.suffix.lower() not in SCORABLE:
        return {"error": f"fitted; the scorer reads PLY or text clouds, not {job.cloud.suffix}", "seconds": seconds}
    result = scorer(job.cloud, out, job.truth)
    doc = json.loads((out / f"{job.cloud.stem}.json").read_text())
    result["topology"] = doc["topology"]
    result["param"] = doc["fit"].get("parametrisation", {}).get("method")
    result["suspect"] = {True: "SUSPECT", False: "no"}.get(doc["metrics"].get("suspect"))  # None: not checked
    result["outliers"] = doc["metrics"].get("outliers")
    result["loops"] = len(doc["surface"].get("trim") or []) or None
    trim = doc["fit"].get("trim")
    result["empty_share"] = trim.get("empty_share") if isinstance(trim, dict) else None  # the fit's own figure
    result["expected"] = job.loops
    seams = [result[k] for k in ("seam_u", "seam_v") if k in result]
    result["seam"] = max(seams) if seams else None
    if result.get("claimed_rmse") and result.get("rmse"):
        result["claim_err"] = abs(result["claimed_rmse"] / result["rmse"] - 1.0)
    result["seconds"] = seconds
    return result


def cell(value, digits: int = 3) -> str:
    """A table cell: ``-`` for nothing, ``yes``/``NO`` for a check, floats to ``digits`` digits."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "NO"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def table_row(name: str, variant: str, build: str | None, result: dict, columns) -> list[str]:
    label = [build] if build else []
    if "error" in result:
        return [name, variant, *label, f"failed: {result['error']}", *["" for _ in columns]]
    return [name, variant, *label, *(cell(result.get(c)) for c in columns), f"{result['seconds']:.1f}"]


def comparison(results: dict) -> str:
    """Per case: rmse and truth_rms of both variants, and the swarm's truth_rms over the
    classical one's (the swarm should never be meaningfully worse)."""
    rows = []
    for name in dict.fromkeys(name for name, _ in results):
        classical, swarm = results.get((name, "classical"), {}), results.get((name, "swarm"), {})
        if "rmse" not in classical or "rmse" not in swarm:
            continue
        ratio = swarm.get("truth_rms") / classical["truth_rms"] if classical.get("truth_rms") else None
        rows.append([name, cell(classical["rmse"]), cell(swarm["rmse"]), cell(classical.get("truth_rms")),
                     cell(swarm.get("truth_rms")), "-" if ratio is None else f"{ratio:.2f}"])
    if not rows:
        return ""
    return markdown(["case", "rmse classical", "rmse swarm", "truth_rms classical", "truth_rms swarm",
                     "truth_rms swarm / classical"], rows)


def jobs_for(suite: str, names: list[str] | None, root: Path, seed: int, scans: Path | None,
             config: Path) -> list[Job]:
    if suite == "real":
        return real_jobs(scans, names, config)
    cases = SUITES[suite]
    unknown = [n for n in names or [] if n not in cases]
    if unknown:
        raise SystemExit(f"run.py: suite {suite} has no case {unknown[0]!r} (see benchmarks/cases.py --list "
                         f"--suite {suite})")
    folder = root / "cases"
    folder.mkdir(parents=True, exist_ok=True)
    jobs = []
    for name in names or list(cases):
        files = write(cases[name], folder, seed)
        jobs.append(Job(name, files.cloud, files.config, files.truth, cases[name].loops))
    return jobs


def real_jobs(scans: Path | None, names: list[str] | None, config: Path) -> list[Job]:
    """Every readable cloud of ``scans``, one per stem (a PLY before the same cloud's XYZ)."""
    if scans is None or not scans.is_dir():
        raise SystemExit(f"run.py: --suite real needs --scans DIR, a directory of scans (got {scans})")
    found: dict[str, Path] = {}
    for path in sorted(scans.iterdir(), key=lambda p: (p.stem, READABLE.index(p.suffix.lower())
                                                       if p.suffix.lower() in READABLE else 99)):
        if path.suffix.lower() in READABLE:
            found.setdefault(path.stem, path)
    missing = [n for n in names or [] if n not in found]
    if missing or not found:
        raise SystemExit(f"run.py: {scans}: no cloud named {missing[0]!r}" if missing else f"run.py: {scans}: no clouds")
    return [Job(name, found[name], config) for name in names or sorted(found)]


def run_suite(args, root: Path, print_rows: bool = True) -> tuple[str, dict]:
    """Fit and score every job and variant (and build); the table, and the results of this
    build by (case, variant)."""
    view = VIEWS[args.suite]
    variants = args.variants or list(view.variants)
    scorer = score if args.scorer is None else outside_score(args.scorer)
    builds = ([("baseline", args.baseline)] if args.baseline else []) + [("this", args.build)]
    header = ["case", "variant", *(["build"] if args.baseline else []), *view.columns, "seconds"]
    if print_rows:
        print("| " + " | ".join(header) + " |\n|" + "---|" * len(header), flush=True)
    rows, results = [], {}
    for job in jobs_for(args.suite, args.cases, root, args.seed, args.scans, args.config):
        for variant in variants:
            for build, exe in builds:
                out = root / "results" / build / variant / job.name
                saved = out.with_name(f"{job.name}.row.json")
                result = json.loads(saved.read_text()) if args.reuse and saved.exists() else {}
                if result.get("seed") != args.seed or "error" in result:
                    result = fit_and_score(job, variant, out, exe, scorer)
                    saved.parent.mkdir(parents=True, exist_ok=True)  # a build that failed made no folder
                    saved.write_text(json.dumps({**result, "seed": args.seed}))
                rows.append(table_row(job.name, variant, build if args.baseline else None, result, view.columns))
                if print_rows:
                    print("| " + " | ".join(rows[-1]) + " |", flush=True)
                if build == "this":
                    results[job.name, variant] = result
    return markdown(header, rows), results


def case_list() -> str:
    """Every suite's cases: what each tests and how it is fitted."""
    parts = []
    for suite, cases in SUITES.items():
        rows = [[f"`{c.name}`", c.note, f"{c.net[0]} x {c.net[1]}, orders {c.orders[0]} x {c.orders[1]}, {c.topology}",
                 cell(c.noise) if c.noise else "-", f"{c.junk.kind} {c.junk.share:g}" if c.junk else "-",
                 f"{c.swarm['particles']} x {c.swarm['iterations']}"] for c in cases.values()]
        parts.append(f"### {suite}\n\n" + markdown(["case", "what it tests", "net", "noise", "junk", "swarm"], rows))
    return "\n\n".join(parts)


def document(table: str, summary: str, seed: int) -> str:
    return f"""# The benchmark

Everything here runs from a plain clone (numpy and scipy for the clouds and the scorer,
`psonurbs` for the fits). This page is written by

    python3 benchmarks/run.py --docs

which fits the public suite (seed {seed}) with both variants and scores every fit with the
repository's own scorer, `benchmarks/score.py`. `benchmarks/README.md` says what each
suite measures and how to run it; the figures are defined in `benchmarks/score.py`.
Each suite on its own:

    python3 benchmarks/run.py --suite public      # the table below
    python3 benchmarks/run.py --suite features    # also robust, unseen, trims, edges, thick
    python3 benchmarks/run.py --suite real --scans SCANS/

## The public table

`classical` is the same pipeline without a swarm (one particle, one iteration: uniform
knots, unit weights); `swarm` is each case's own config. Every distance is relative to the
cloud's bounding-box diagonal; `seconds` is the wall time of the whole `psonurbs fit`
command on the machine that wrote this page.

{summary}

All figures:

{table}

## The cases

Each case is a PLY (double x, y, z), a YAML config and `CASE.gt.npz`: the true surface as
a 241 x 241 triangulation of its parameter square (only inside the footprint where the
case has one), the noise sigma and the junk share. `--seed N` draws the same cases
afresh: a method tuned to the public clouds shows itself there.

{case_list()}

## Real scans

`python3 benchmarks/run.py --suite real --scans SCANS/` fits every cloud in a directory of yours. No scans ship
with the repository: each has its owner's terms. These public scans serve well, each converted to PLY without resampling or moving (coordinates in the
source's units):

- `bunny_front`: the Stanford Bunny's range image `bun000` (Stanford 3D Scanning
  Repository; Cyberware 3030MS), its vertices unchanged; 40,256 points.
- `terrain_isprs_samp51`: every point of the ground-only UTM version of ISPRS filter test
  sample 51 (`terrain/samp51-utm-ground.pcd` in the Point Cloud Library's data
  repository); stored as float32 at source, so the northings come in steps of 0.5 m;
  13,950 points.
- `terrain_lidr_topography`: the ground points (class 2) of the lidR package's example
  tile `Topography.laz`; 8,159 points with lakes as holes.
- `face_lps`: the front of Lee Perry-Smith's "Infinite, 3D Head Scan" (CC BY 3.0, credit
  "Infinite, 3D Head Scan by Lee Perry-Smith / Infinite-Realities, based on a work at
  www.triplegangers.com"): mesh vertices with z > -0.045, -0.15 < y < 0.07, |x| < 0.072,
  facing +z and seen from +z; 2,252 points.
- `soupcan_wall`, `mustard_body`, `tennis_ball`: YCB objects 005, 006 and 056 (CC BY 4.0,
  the YCB Object and Model Set), vertices of the google_16k reconstructions: the can's
  wall (0.008 < y < 0.094, duplicates removed), the bottle's body (0.012 < z < 0.13), the
  whole ball.
- `gymball_arkit`: a gym ball scanned with ARKit on an iPad (CurvSurf's FindSurface web
  demo data; no licence found, use for testing only), the visible cap cropped from the
  scene (y > -1.16, within 0.5 m of the ball's axis); raw, stripy, with strays.

To score LAS/LAZ or E57 scans, fit them with `psonurbs fit` and give the scorer the same
points as PLY or text (`benchmarks/score.py` reads PLY and x y z text only).

## Whole objects

Objects of several faces (`--patches auto`), their STEP read back by OpenCASCADE:
[objects.md](objects.md), written by `python3 benchmarks/objects.py --docs`.
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="public", choices=[*SUITES, "real"], help="the case set (default: public)")
    ap.add_argument("--cases", nargs="*", metavar="CASE", help="these cases only (default: the whole suite)")
    ap.add_argument("--variants", nargs="*", choices=list(VARIANT_ARGS), help="default: the suite's")
    ap.add_argument("--seed", type=int, default=0, help="cloud seed: 0 the public clouds, others fresh draws")
    ap.add_argument("--build", metavar="EXE", default="psonurbs",
                    help="the psonurbs executable whose rows are 'this' (default: the one on PATH; a pyenv "
                         "shim's python puts its own bin first on PATH, so name a build under test)")
    ap.add_argument("--baseline", metavar="EXE", help="another psonurbs executable to fit every case with too")
    ap.add_argument("--scorer", type=Path, metavar="SCRIPT", help="score with this script instead of "
                    "benchmarks/score.py (python SCRIPT CLOUD OUTDIR --gt GT, printing one JSON line)")
    ap.add_argument("--out", type=Path, help="keep the clouds and results here (default: a temporary folder)")
    ap.add_argument("--reuse", type=Path, metavar="DIR", help="as --out, taking the rows already scored there")
    ap.add_argument("--scans", type=Path, help="--suite real: the directory of scans")
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "auto.yaml", help="--suite real: the config")
    ap.add_argument("--docs", action="store_true", help=f"write {DOC.relative_to(REPO)} from the public suite")
    args = ap.parse_args(argv)
    if args.docs:
        args.suite, args.variants, args.baseline = "public", ["classical", "swarm"], None
    root = args.reuse or args.out or Path(tempfile.mkdtemp(prefix="psonurbs-bench-"))
    table, results = run_suite(args, root, print_rows=not args.docs)
    summary = comparison(results)
    if args.docs:
        DOC.write_text(document(table, summary, args.seed))
        print(f"wrote {DOC}")
        return 0
    if summary:
        print("\n" + summary)
    print(f"\nclouds and results in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
