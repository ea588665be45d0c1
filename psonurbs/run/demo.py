"""Sample clouds for a first run (``psonurbs demo OUT``).

Two small synthetic clouds, sampled with a fixed seed so every run writes the same
files, each with a YAML config in the documented schema and a small swarm so that
fitting both takes seconds:

* ``bump``: a Gaussian bump over a square (an open patch, like the paper's first
  experiment), 1,500 scattered points with a little noise;
* ``quarter_cylinder``: a quarter of a cylinder, 800 scattered points; exactly a
  rational quadratic surface (middle row of weights sqrt(2)/2), so only a fit with
  the right weights reaches the noise-free floor.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from psonurbs.config import SwarmConfig

__all__ = ["SAMPLES", "Sample", "write_samples"]


@dataclass(frozen=True)
class Sample:
    name: str
    note: str
    points: int
    config: dict
    noise: float  # Gaussian sigma as a fraction of the bounding-box diagonal

    def surface(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        if self.name == "bump":
            x, y = 2 * u - 1, 2 * v - 1
            return np.stack([x, y, 0.6 * np.exp(-2.0 * (x * x + y * y))], -1)
        angle = 0.5 * np.pi * u
        return np.stack([np.cos(angle), np.sin(angle), 1.5 * v], -1)

    def cloud(self, seed: int = 0) -> np.ndarray:
        rng = np.random.default_rng(seed)
        pts = self.surface(rng.random(self.points), rng.random(self.points))
        if self.noise:
            diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
            pts = pts + rng.normal(0.0, self.noise * diag, pts.shape)
        return pts


def _swarm(particles: int = 12, iterations: int = 25) -> dict:
    """A small swarm for a quick first run, every other setting the config's default."""
    return SwarmConfig(particles=particles, iterations=iterations).to_dict()


SAMPLES = (
    Sample("bump", "a Gaussian bump over a square: an open bicubic patch", 1500,
           {"orders": [4, 4], "net_size": [6, 6], "topology": "open", "swarm": _swarm()},
           noise=0.001),
    Sample("quarter_cylinder", "a quarter cylinder: exact only with rational weights "
           "(middle row sqrt(2)/2)", 800,
           {"orders": [3, 2], "net_size": [3, 2], "topology": "open", "swarm": _swarm()},
           noise=0.0),
)


def write_samples(out_dir: str | os.PathLike, seed: int = 0) -> list[tuple[Path, Path]]:
    """Write ``NAME.ply`` and ``NAME.yaml`` for each sample; returns (cloud, config) paths."""
    from psonurbs.formats.outputs import atomic_write, render_ply

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for sample in SAMPLES:
        cloud = out / f"{sample.name}.ply"
        config = out / f"{sample.name}.yaml"
        atomic_write(cloud, render_ply(sample.cloud(seed), np.zeros((0, 3), dtype=np.int64)))
        text = f"# {sample.note}\n" + yaml.safe_dump(sample.config, sort_keys=False,
                                                     default_flow_style=None)
        atomic_write(config, text)
        written.append((cloud, config))
    return written
