#!/usr/bin/env python3
"""Swarm fitness evaluations per second: one particle at a time, the batched numpy fitness and
its compiled twin.

    python benchmarks/perf/fitness_rate.py [--points 1500] [--particles 40] [--rounds 7] [--nets 8 12 20] [--stages]

For each cubic open net (8 x 8, 12 x 12, 20 x 20 by default) it builds the swarm's
fitness on a Franke surface sampled at ``--points`` scattered points (noise 0.2% of the
diagonal), takes ``--particles`` particles of the initial swarm (the classical fit,
then particles spread towards random knots, weights and smoothing), and times

    single    ``[search.error(x) for x in swarm]``: one particle at a time, scipy design
              matrices and a dense solve per particle
    numpy     ``search.numpy_fitness(swarm)``: all particles together (stacked_rows + the
              banded stacked solve), the reference path
    compiled  ``search.compiled_fitness(swarm)``: the numba kernel, particle by particle
              (only with numba, the ``fast`` extra)

in interleaved rounds (single, numpy, compiled, single, ...), one BLAS thread and glibc
keeping freed memory as in a fit (:mod:`psonurbs.run.heap`). The best round of each is
reported, as wall time and as process CPU time (on a busy machine the CPU time is the
steadier figure), with the largest relative difference of the numpy and the compiled
fitness from the single one (they compute the same leave-one-out RMSE). The compiled
kernels' first call (compiling them, or loading numba's on-disk cache) is timed apart,
before the rounds; ``NUMBA_CACHE_DIR=$(mktemp -d)`` makes it a fresh compile.

With ``--stages`` a second table splits the batched numpy fitness into its stages, each timed
on its own over the swarm's groups of particles (as the fitness groups them), after a
write of 64 MB that clears the caches as the previous stage does in a fit: the rows
(``stacked_rows``), the normal matrices, the banded factorisation, the solve and
residuals, the selected inverse and the leverages, in CPU ms per evaluation.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[1])]  # the repo, benchmarks/

from cases import franke_height  # noqa: E402

from psonurbs.fitting.leastsq.banded import StackedBandedCholesky  # noqa: E402
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares  # noqa: E402
from psonurbs.fitting.search.knot_weight_space import KnotWeightSpace  # noqa: E402
from psonurbs.geometry import compiled  # noqa: E402
from psonurbs.geometry.net import NetLayout  # noqa: E402
from psonurbs.run.heap import keep_freed_memory  # noqa: E402


def search_for(net: int, n_points: int, rng: np.random.Generator) -> KnotWeightSpace:
    uv = rng.random((n_points, 2))
    points = np.column_stack([uv, franke_height(uv[:, 0], uv[:, 1])])
    points += 0.002 * np.sqrt(3.0) * rng.normal(size=points.shape)
    layout = NetLayout((net, net), (3, 3))
    solver = RegularisedLeastSquares(layout.smoothness_operator(), 1e-6, layout.constraint_operator())
    return KnotWeightSpace(layout, solver, points, uv, True, 0.2, (0.2, 5.0))


def best_rounds(search: KnotWeightSpace, swarm: np.ndarray, rounds: int) -> tuple[dict, dict]:
    """Best (wall, cpu) seconds over interleaved rounds of each way, and the values."""
    runs = {"single": lambda: [search.error(x) for x in swarm], "numpy": lambda: search.numpy_fitness(swarm)}
    if compiled.ENABLED:
        runs["compiled"] = lambda: search.compiled_fitness(swarm)
    best = {name: [np.inf, np.inf] for name in runs}
    values = {}
    with threadpool_limits(limits=1):
        runs["numpy"]()  # warm-up: what is built once per search
        for _ in range(rounds):
            for name, run in runs.items():
                wall, cpu = time.perf_counter(), time.process_time()
                values[name] = np.asarray(run())
                wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
                best[name] = [min(best[name][0], wall), min(best[name][1], cpu)]
    return best, values


def first_call(search: KnotWeightSpace, swarm: np.ndarray) -> float:
    """Wall seconds of the compiled fitness's first call: compiling the kernels (or
    loading them from numba's cache) and one evaluation."""
    wall = time.perf_counter()
    search.compiled_fitness(swarm[:1])
    return time.perf_counter() - wall


def stage_costs(search: KnotWeightSpace, swarm: np.ndarray, rounds: int) -> dict[str, float]:
    """CPU ms per evaluation of each stage of the batched fitness, best of ``rounds``,
    each timed from cold caches over all groups of the swarm."""
    stacked, size = search.stacked, search.group_size
    groups = [swarm[k:k + size] for k in range(0, len(swarm), size)]
    smoothing = [10.0 ** g[:, -1] for g in groups]
    rows = [search.rows(g) for g in groups]
    normal = [stacked.normal_matrices(r, None, s) for r, s in zip(rows, smoothing)]
    order = stacked.order
    factors = [StackedBandedCholesky(m, order.half_bandwidth, order.block) for m in normal]
    runs = {
        "rows": lambda: [search.rows(g) for g in groups],
        "normal matrices": lambda: [stacked.normal_matrices(r, None, s) for r, s in zip(rows, smoothing)],
        "factorisation": lambda: [StackedBandedCholesky(m, order.half_bandwidth, order.block) for m in normal],
        "fit": lambda: [stacked.fit(r, search.points, s) for r, s in zip(rows, smoothing)],
        "selected inverse": lambda: [f.selected_inverse() for f in factors],
        "leverages": lambda: [stacked.leverages(r, f) for r, f in zip(rows, factors)],
        "whole fitness": lambda: search.numpy_fitness(swarm),
    }
    evict = np.zeros(2 ** 23)
    best = dict.fromkeys(runs, np.inf)
    with threadpool_limits(limits=1):
        for _ in range(rounds):
            for name, run in runs.items():
                evict += 1.0  # 64 MB through the caches
                cpu = time.process_time()
                run()
                best[name] = min(best[name], 1e3 * (time.process_time() - cpu) / len(swarm))
    # the fit holds the normal matrices and the factorisation; the leverages the selected inverse
    solve = best["fit"] - best["normal matrices"] - best["factorisation"]
    return {"rows": best["rows"], "normal matrices": best["normal matrices"], "factorisation": best["factorisation"],
            "solve + residuals": solve, "selected inverse": best["selected inverse"],
            "leverages": best["leverages"] - best["selected inverse"], "whole fitness": best["whole fitness"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=1500)
    ap.add_argument("--particles", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--nets", type=int, nargs="*", default=[8, 12, 20])
    ap.add_argument("--stages", action="store_true", help="also the cost of each stage of the batched fitness")
    args = ap.parse_args(argv)
    keep_freed_memory()  # as a fitting process does (psonurbs.run.heap)
    print(f"{args.points} points, {args.particles} particles, best of {args.rounds} interleaved rounds, 1 thread")
    ways = ["single", "numpy"] + (["compiled"] if compiled.ENABLED else [])
    if compiled.ENABLED:
        rng = np.random.default_rng(args.nets[0])
        search = search_for(args.nets[0], args.points, rng)
        print(f"compiled kernels' first call (compile or cache load): "
              f"{first_call(search, search.initial_swarm(2, rng)):.2f} s wall, not in the rates below")
    else:
        print("numba is not there (or PSONURBS_NO_JIT is set): no compiled column")
    print("| net | " + " | ".join(f"{w} ms/eval (wall, cpu)" for w in ways) + " | "
          + " | ".join(f"{w} evals/s" for w in ways) + " | compiled vs numpy, vs single (cpu) "
          "| max rel. diff from single (numpy, compiled) |")
    print("|---" * (2 * len(ways) + 3) + "|")
    for net in args.nets:
        rng = np.random.default_rng(net)
        search = search_for(net, args.points, rng)
        swarm = search.initial_swarm(args.particles, rng)
        best, values = best_rounds(search, swarm, args.rounds)
        per_eval = {k: [1e3 * t / args.particles for t in v] for k, v in best.items()}
        diff = {k: float(np.max(np.abs(values[k] / values["single"] - 1.0))) for k in ways[1:]}
        last = per_eval[ways[-1]][1]
        print(f"| {net} x {net} | " + " | ".join(f"{per_eval[w][0]:.3f}, {per_eval[w][1]:.3f}" for w in ways)
              + " | " + " | ".join(f"{1e3 / per_eval[w][1]:.0f}" for w in ways)
              + f" | {per_eval['numpy'][1] / last:.1f}x, {per_eval['single'][1] / last:.1f}x | "
              + ", ".join(f"{d:.1e}" for d in diff.values()) + " |", flush=True)
    if args.stages:
        print("\nstages of the batched numpy fitness, cpu ms per evaluation (each from cold caches)")
        for k, net in enumerate(args.nets):
            rng = np.random.default_rng(net)
            search = search_for(net, args.points, rng)
            costs = stage_costs(search, search.initial_swarm(args.particles, rng), args.rounds)
            if k == 0:
                print("| net | " + " | ".join(costs) + " |")
                print("|---" * (len(costs) + 1) + "|")
            print(f"| {net} x {net} | " + " | ".join(f"{c:.3f}" for c in costs.values()) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
