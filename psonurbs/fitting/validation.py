"""Whether the swarm's knots beat the classical ones: a paired test on points it never saw.

Among thousands of particles, the least leave-one-out error on one sample is an
optimistic pick: on noisy data some knots and weights fit that sample's noise. Both
candidates, the swarm's best and the classical start (uniform knots, unit weights), are
polished on the swarm's points and judged on the others. With
``d_i = e_swarm,i^2 - e_classical,i^2`` the paired difference of squared distances at
held-out point i (the noise common to both cancels in it), the swarm is kept only if

    mean(d) + Z * sd(d) / sqrt(n) < 0,          Z = 2,

i.e. if it is closer to the unseen points by more than twice the standard error of that
mean: a one-sided paired z-test at about 2%. A difference within the sampling error of
the comparison keeps the classical fit, which has no knots tuned to anything.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import closest_parameters

from .hybrid import KnotWeightSearch, loo_smoothing
from .polish import polish

Z = 2.0  # standard errors by which the swarm must win


@dataclass(frozen=True)
class HeldOutTest:
    """The comparison on the held-out points (distances in the fit's normalised units)."""

    points: int
    classical_error: float  # rms distance of the held-out points to the polished classical fit
    swarm_error: float
    z: float  # mean(d) / standard error: negative where the swarm is closer

    @property
    def kept(self) -> str:
        return "swarm" if self.z < -Z else "classical"

    def to_dict(self, scale: float = 1.0) -> dict:
        return {"held_out_points": self.points,
                "held_out_error": {"classical": self.classical_error * scale, "swarm": self.swarm_error * scale},
                "held_out_z": self.z, "kept": self.kept}


def paired_test(classical: np.ndarray, swarm: np.ndarray) -> HeldOutTest:
    """The test on per-point distances (n,) of the two candidates."""
    d = swarm ** 2 - classical ** 2
    spread = float(np.std(d, ddof=1)) if len(d) > 1 else 0.0
    mean = float(np.mean(d))
    if spread > 0:
        z = mean * np.sqrt(len(d)) / spread
    else:
        z = 0.0 if mean == 0 else float(np.copysign(np.inf, mean))
    return HeldOutTest(len(d), float(np.sqrt(np.mean(classical ** 2))), float(np.sqrt(np.mean(swarm ** 2))), z)


def held_out_choice(search: KnotWeightSearch, best: np.ndarray, layout: NetLayout, points: np.ndarray,
                    uv: np.ndarray, seen: np.ndarray, polish_iterations: int) -> tuple[np.ndarray, HeldOutTest | None]:
    """The swarm's best particle or the classical start, by :func:`paired_test` on the
    points outside ``seen``; the best itself (and no test) when every point was seen or
    the best is the classical start.

    Each candidate is judged as the pipeline would finish it: polished on the swarm's
    points with its own smoothing, the smoothing then chosen again by leave-one-out at
    the corrected parameters (the classical start carries the configured smoothing,
    which the classical fit does not end with)."""
    unseen = np.setdiff1d(np.arange(len(points)), seen)
    classical = search.classical()
    if len(unseen) < 2 or np.array_equal(best, classical):
        return best, None
    distances = []
    for x in (classical, best):
        inner_u, inner_v, weights, smoothing = search.split(x)
        solver = search.solver.with_smoothing(smoothing)
        corrected = polish(layout, solver, points[seen], uv[seen], weights, inner_u, inner_v, polish_iterations)[2]
        solver = solver.with_smoothing(loo_smoothing(layout, solver, points[seen], corrected, weights,
                                                     inner_u, inner_v))
        control = solver.solve(layout.rows(corrected, weights, inner_u, inner_v), points[seen])
        surface = layout.surface(control, weights, inner_u, inner_v)
        distances.append(closest_parameters(surface, points[unseen])[1])
    test = paired_test(*distances)
    return (best if test.kept == "swarm" else classical), test
