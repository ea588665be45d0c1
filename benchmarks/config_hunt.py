"""Random valid configs on odd small clouds, through one cloud's job as ``psonurbs fit``
runs it: does any config the validation accepts crash the fitter?

    python benchmarks/config_hunt.py [TRIALS] [SEED]

Each trial draws a config inside every bound (orders, net, topology, strategy, swarm
factors, smoothing, weight bounds, knot gap, the switches; tiny swarms) and a cloud of
10 to 80 points (a surface, a nearly flat patch, a sphere; scaled by 1e-9 .. 1e9, offset),
and runs :func:`psonurbs.run.batch.fit_job`. Prints the count of each outcome: ``ok``,
each refusal (``bad-input``: the contract) and each internal error with where it was
raised (a bug: the contract broken), with one config that raised it.
"""
from __future__ import annotations

import collections
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from psonurbs.config import config_from_dict
from psonurbs.errors import ConfigError
from psonurbs.formats.outputs import render_ply
from psonurbs.run.batch import fit_job
from psonurbs.run.inputs import Job


def random_config(rng: np.random.Generator) -> dict:
    k, l = (int(v) for v in rng.integers(2, 6, 2))
    topology = str(rng.choice(["open", "cylinder", "sphere", "torus", "auto"]))
    nu = int(rng.integers(k, 10))
    nv = int(rng.integers(max(l, 3 if topology == "sphere" else l), 10))
    return {"orders": [k, l], "net_size": [nu, nv], "topology": topology,
            "strategy": str(rng.choice(["hybrid", "hybrid", "full"])),
            "swarm": {"particles": int(rng.integers(1, 5)), "iterations": int(rng.integers(1, 4)),
                      "inertia": float(rng.choice([0, 0.7, 10])), "c1": float(rng.choice([0, 1.5, 10])),
                      "c2": float(rng.choice([0, 1.5, 10])), "seed": int(rng.integers(0, 2**62))},
            "smoothing": float(rng.choice([0, 1e-6, 1, 1e6])), "swarm_points": int(rng.choice([16, 17, 100])),
            "polish_iterations": int(rng.choice([0, 1, 3])), "tessellation": [int(rng.integers(2, 30))] * 2,
            "weight_bounds": [float(rng.choice([0.2, 1e-6, 0.9, 1.0])), float(rng.choice([5.0, 1.0, 1e6, 1.1]))],
            "min_knot_gap": float(rng.choice([1e-9, 0.2, 0.999])),
            "cross_validation": bool(rng.integers(2)), "refine": bool(rng.integers(2)),
            "robust": bool(rng.integers(2))}


def random_cloud(rng: np.random.Generator) -> np.ndarray:
    n = int(rng.choice([10, 16, 40, 80]))
    x, y = rng.random((2, n))
    shape = rng.choice(["surface", "flat", "sphere"])
    if shape == "surface":
        p = np.column_stack([x, y, np.sin(3 * x) * y])
    elif shape == "flat":
        p = np.column_stack([x, y, 1e-7 * rng.standard_normal(n)])
    else:
        t, f = 2 * np.pi * x, np.pi * (y - 0.5)
        p = np.column_stack([np.cos(f) * np.cos(t), np.cos(f) * np.sin(t), np.sin(f)])
    return p * float(rng.choice([1, 1e-9, 1e9])) + float(rng.choice([0, 1e3]))


def main() -> int:
    trials = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    rng = np.random.default_rng(int(sys.argv[2]) if len(sys.argv) > 2 else 0)
    outcomes: collections.Counter = collections.Counter()
    example: dict[str, dict] = {}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cloud.ply"
        for _ in range(trials):
            d = random_config(rng)
            path.write_bytes(render_ply(random_cloud(rng), np.zeros((0, 3), np.int64)))
            try:
                config = config_from_dict(d)
            except ConfigError as e:
                outcomes[f"config refused: {str(e)[:70]}"] += 1
                continue
            row = fit_job(Job(path, config)).row
            if row.status == "internal-error":
                where = row.detail.strip().splitlines()[-3].strip() if row.detail else ""
                key = f"INTERNAL ERROR: {row.message[:70]} ({where[:60]})"
                example.setdefault(key, d)
            else:
                key = row.status if row.status == "ok" else f"{row.status}: {row.message.split(': ', 1)[-1][:70]}"
            outcomes[key] += 1
    print(f"{trials} trials in {time.perf_counter() - start:.0f} s")
    for key, count in outcomes.most_common():
        print(f"{count:5d}  {key}")
    for key, d in example.items():
        print(f"\n{key}\n    {d}")
    return 1 if example else 0


if __name__ == "__main__":
    sys.exit(main())
