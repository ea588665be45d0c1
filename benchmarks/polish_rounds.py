#!/usr/bin/env python3
"""How fast the polish (parameter correction, Anderson-mixed) lowers the error, for
several relaxations of the mix.

    python benchmarks/polish_rounds.py CLOUD --config CONFIG [--relaxation 1 1.6 2] [--rounds 50 100 200 300]

The cloud is fitted once as ``psonurbs fit`` fits it (``psonurbs.fitting.pipeline.fit_points``),
and the inputs of its first polish (the one after the swarm) are kept; that polish is
then run again for ``max(--rounds)`` rounds with each relaxation beta of
:class:`psonurbs.fitting.polish.AndersonMixing` (1: the pipeline's), and the
table gives the rmse of the points it takes (a big cloud's subsample, weighted as in the
fit) to the best surface within the first R rounds (the polish's result with
``polish_iterations`` R), relative to the cloud's bounding-box diagonal, and the seconds
of the whole run. One BLAS thread, as in a fit.
"""
from __future__ import annotations

import argparse
import functools
import sys
import time

import numpy as np
import scipy  # noqa: F401  (loaded before the thread limit, as a fit loads it)
from threadpoolctl import threadpool_limits

import psonurbs.fitting.pipeline as pipeline
import psonurbs.fitting.polish as polish_module
from psonurbs.config import load_config
from psonurbs.fitting.solve import weighted_rms
from psonurbs.formats.clouds import read_cloud


def first_polish_inputs(points: np.ndarray, config) -> tuple[tuple, dict]:
    """The positional and keyword arguments of the fit's first polish."""
    kept = []

    def recording(*args, **kwargs):
        if not kept:
            kept.append((args, kwargs))
        return polish_module.polish(*args, **kwargs)

    pipeline.polish = recording
    try:
        pipeline.fit_points(points, config)
    finally:
        pipeline.polish = polish_module.polish
    return kept[0]


def trajectory(args: tuple, kwargs: dict, rounds: int, relaxation: float) -> tuple[np.ndarray, float]:
    """The error of every round's surface (N rounds + 1) and the seconds taken."""
    errors, search = [], polish_module.closest_parameters
    weights = kwargs.get("point_weights")

    def measured(surface, points, uv=None):
        found = search(surface, points, uv)
        errors.append(weighted_rms(found[1] ** 2, weights))
        return found

    mixing = polish_module.AndersonMixing
    polish_module.closest_parameters = measured
    polish_module.AndersonMixing = functools.partial(mixing, relaxation=relaxation)
    try:
        start = time.perf_counter()
        layout, solver, points, uv, shape, _ = args
        polish_module.polish(layout, solver, points, uv, shape, rounds, **kwargs)
        return np.minimum.accumulate(errors), time.perf_counter() - start
    finally:
        polish_module.closest_parameters, polish_module.AndersonMixing = search, mixing


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cloud")
    ap.add_argument("--config", required=True)
    ap.add_argument("--relaxation", type=float, nargs="+", default=[1.0, 1.6, 2.0])
    ap.add_argument("--rounds", type=int, nargs="+", default=[50, 100, 200, 300])
    args = ap.parse_args(argv)
    points = read_cloud(args.cloud)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    config = load_config(args.config)
    polish_args, polish_kwargs = first_polish_inputs(points, config)
    scale = diagonal / pipeline.organise(points, tuple(config.orders)).frame.diagonal
    print("| relaxation | " + " | ".join(f"rmse after {r} rounds" for r in args.rounds) + " | seconds |")
    print("|---|" + "---|" * (len(args.rounds) + 1))
    with threadpool_limits(limits=1):
        for beta in args.relaxation:
            errors, seconds = trajectory(polish_args, polish_kwargs, max(args.rounds), beta)
            cells = [f"{errors[min(r, len(errors) - 1)] / scale:.4e}" for r in args.rounds]
            print(f"| {beta:g} | " + " | ".join(cells) + f" | {seconds:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
