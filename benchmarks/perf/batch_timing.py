#!/usr/bin/env python3
"""Wall time of ``psonurbs fit DIR --jobs 2`` against ``--jobs 1`` on 20 clouds.

    python benchmarks/perf/batch_timing.py [--copies 4] [--particles 20] [--iterations 30]
    python benchmarks/perf/batch_timing.py --source /tmp/snapshot   # a checkout to time instead


The clouds are open benchmark cases of ``benchmarks/cases.py`` (written to a
temporary directory), each copied ``--copies`` times (5 cases x 4 = 20 clouds). Both
runs use the installed ``psonurbs`` command with the same small swarm; the script
checks that every output except the summaries (which hold run times) is byte-identical
between the two runs, and prints both wall times. ``--source DIR`` runs the package
found in DIR (e.g. ``git archive HEAD | tar -x -C DIR``) instead of the installed one,
so that edits made to the working tree during the run cannot mix into it.
"""
from __future__ import annotations

import argparse
import filecmp
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/, for the cases
from cases import CASES, write  # noqa: E402

OPEN_CASES = ["seed_patch16", "franke_grid", "franke_noisy", "wave_graded", "quarter_cylinder"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--copies", type=int, default=4)
    ap.add_argument("--particles", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--source", type=Path, default=None,
                    help="directory holding cli/ and psonurbs/ to run instead of the installed package")
    args = ap.parse_args(argv)
    env = dict(os.environ)
    psonurbs = ["psonurbs"]
    if args.source is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(args.source.resolve()), env.get("PYTHONPATH", "")])
        psonurbs = [sys.executable, str(args.source.resolve() / "cli" / "main.py")]

    with tempfile.TemporaryDirectory(prefix="psonurbs-batch-") as tmp:
        tmp = Path(tmp)
        cases = tmp / "cases"
        cases.mkdir()
        for case in OPEN_CASES:
            write(CASES[case], cases)
        clouds = tmp / "clouds"
        clouds.mkdir()
        for case in OPEN_CASES:
            for k in range(args.copies):
                shutil.copy(cases / f"{case}.ply", clouds / f"{case}_{k}.ply")
        n = len(list(clouds.iterdir()))
        times = {}
        for jobs in (1, 2):
            out = tmp / f"out{jobs}"
            cmd = [*psonurbs, "fit", str(clouds), "-o", str(out), "-q", "--jobs", str(jobs),
                   "--particles", str(args.particles), "--iterations", str(args.iterations)]
            start = time.perf_counter()
            run = subprocess.run(cmd, capture_output=True, text=True, env=env)
            times[jobs] = time.perf_counter() - start
            if run.returncode != 0:
                print(run.stderr, file=sys.stderr)
                return run.returncode
        names = sorted(p.name for p in (tmp / "out1").iterdir() if not p.name.startswith("summary."))
        other = sorted(p.name for p in (tmp / "out2").iterdir() if not p.name.startswith("summary."))
        differ = [f for f in names if f in other
                  and not filecmp.cmp(tmp / "out1" / f, tmp / "out2" / f, shallow=False)]
        same = names == other and not differ
        json_files = [f for f in names if f.endswith(".json")]
        print(f"{n} clouds ({len(OPEN_CASES)} open cases x {args.copies}), swarm {args.particles} "
              f"particles x {args.iterations} iterations, {os.cpu_count()} CPUs")
        print(f"--jobs 1: {times[1]:7.1f} s")
        print(f"--jobs 2: {times[2]:7.1f} s   (speed-up {times[1] / times[2]:.2f}x)")
        print(f"outputs byte-identical: {'yes' if same else 'NO'} "
              f"({len(json_files)} JSON, {len(names)} files compared)")
        if differ:
            print("differing files: " + ", ".join(differ))
        return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
