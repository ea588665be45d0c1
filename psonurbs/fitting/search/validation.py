"""Whether the swarm's knots beat the classical ones: paired tests on points it never saw.

Among thousands of particles, the least leave-one-out error on one sample is an
optimistic pick: on noisy data some knots and weights fit that sample's noise. So the
swarm's best and the classical start (uniform knots, unit weights) are both fitted to
the swarm's points and half of the others, and compared on the other half. With
``d_i = e_swarm,i^2 - e_classical,i^2`` the paired difference of squared errors at
held-out point i (the noise common to both cancels in it) and
``z = mean(d) / (sd(d) / sqrt(n))``, the swarm is kept only if

* at the first parameters, where the swarm chose its knots, it predicts the held-out
  points better by more than ``Z`` standard errors (``z < -Z``): the gain is real, not
  the sample's noise; and
* once both are finished as the pipeline finishes them (polished at their own smoothing,
  the smoothing re-chosen by leave-one-out at the corrected parameters, polished again),
  it is still closer to them by more than ``Z`` standard errors (``z < -Z``): the gain
  survives the parameter correction (knots chosen at the first parameters can lose it
  once the points slide to their foot points); and its surface is not significantly
  farther from the data (``z < Z`` over a grid of surface samples, each one's distance
  to the nearest point of the cloud): the gain does not come with a surface that
  overshoots the data.

The finish follows the pipeline's smoothing path because that path decides the classical
fit: started at the smoothing the leave-one-out error picks at the first parameters (on
a steep cliff those cannot represent the step, so the pick is heavy), a classical
candidate stays over-smoothed through its polish, and a swarm whose knots merely
escape that handicap looks better than the classical fit the user would get. On a noisy
cliff a swarm's candidate at 0.47 x the classical candidate's truth error, judged
unfinished, ends at 1.38 x once both are finished as the pipeline finishes them;
finished this way, the candidates compare at 1.23 x.

Point-to-surface distances see only where the points are. A polish of uniform knots on
a steep step slides the points off a fold the surface makes, and the fold is invisible
in them; a surface that extrapolates farther past the data's edges is invisible too.
The surface-to-data distances see both. A difference within the sampling error keeps
the classical fit, which has no knots tuned to anything.

Under the robust loss's point weights w every fit is the weighted one and the held-out
points are compared by the weighted mean and spread of d, with ``n_eff = (sum w)^2 /
sum w^2`` points (unit weights give the plain test).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.fitting.finish.finishing import FitPoints, finish, loo_smoothing
from psonurbs.fitting.leastsq.regularised import weighted_rms
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.projection import closest_parameters

from .knot_weight_space import KnotWeightSpace

Z = 2.0  # standard errors: a one-sided paired z-test at about 2%
HELD_OUT = 200  # points a cloud of at least 4 x as many keeps from the swarm, for its validation
ROUNDS = 10  # rounds of each of a candidate's two polishes: most of the parameter correction, a tenth of the time
SAMPLES = 64  # surface samples per direction for the surface-to-data distances


def reach(surface, cloud: cKDTree) -> np.ndarray:
    """Distances (SAMPLES^2,) from a SAMPLES x SAMPLES grid of the surface to the nearest
    point of the cloud: where a surface runs past the data, or folds away from them."""
    return cloud.query(surface.evaluate_grid(*surface.parameter_grid(SAMPLES, SAMPLES)).reshape(-1, 3))[0]


def swarm_points_of(seen: np.ndarray, n_points: int) -> np.ndarray:
    """The swarm's points (sorted indices) among the sample ``seen`` (sorted indices into
    the n points): the whole sample, unless the cloud has at least ``4 HELD_OUT`` points
    of which the sample leaves fewer than ``HELD_OUT`` out; then points spread evenly
    through the sample are held out of the swarm as well, up to ``HELD_OUT``.

    Without points it never saw, the swarm's best (the least leave-one-out error among
    thousands of particles: an optimistic pick) would be kept untested; ``HELD_OUT``
    points give the paired tests half of them to judge on. A smaller cloud is all the
    swarm's: there it needs every point. Only the swarm and its validation see the
    smaller set; the rest of the fit (the smoothing's choice, the polish) sees the sample.
    """
    missing = HELD_OUT - (n_points - len(seen))
    if n_points < 4 * HELD_OUT or missing <= 0:
        return seen
    held = np.zeros(len(seen), bool)
    held[(np.arange(missing) * (len(seen) / missing)).astype(int)] = True
    return seen[~held]


@dataclass(frozen=True)
class PairedTest:
    """One comparison on the held-out points (errors in the fit's normalised units)."""

    points: int
    classical_error: float  # rms error of the held-out points under the classical fit
    swarm_error: float
    z: float  # mean(d) / standard error: negative where the swarm is closer


def paired_test(classical: np.ndarray, swarm: np.ndarray, weights: np.ndarray | None = None) -> PairedTest:
    """The paired z statistic of per-point errors (n,) of the two candidates (weighted
    by ``weights`` (n,), if given)."""
    d = swarm ** 2 - classical ** 2
    if weights is None:
        n_eff, mean = len(d), float(np.mean(d))
        spread = float(np.std(d, ddof=1)) if len(d) > 1 else 0.0
    else:
        w = np.asarray(weights, float)
        n_eff = float(np.sum(w) ** 2 / np.sum(w ** 2))
        mean = float(np.sum(w * d) / np.sum(w))
        spread = float(np.sqrt(np.sum(w * (d - mean) ** 2) / np.sum(w) * n_eff / (n_eff - 1))) if n_eff > 1 else 0.0
    if spread > 0:
        z = mean * np.sqrt(n_eff) / spread
    else:
        z = 0.0 if mean == 0 else float(np.copysign(np.inf, mean))
    return PairedTest(len(d), weighted_rms(classical ** 2, weights), weighted_rms(swarm ** 2, weights), z)


@dataclass(frozen=True)
class Validation:
    first: PairedTest  # at the first parameters: the swarm's own measure, out of sample
    polished: PairedTest  # held-out points to both surfaces polished
    overshoot: PairedTest  # samples of both polished surfaces to the cloud

    @property
    def kept(self) -> str:
        return "swarm" if self.first.z < -Z and self.polished.z < -Z and self.overshoot.z < Z else "classical"

    def to_dict(self) -> dict:
        return {"held_out_points": self.polished.points,
                "held_out_error": {"classical": self.polished.classical_error, "swarm": self.polished.swarm_error},
                "held_out_z": {"first": self.first.z, "polished": self.polished.z, "overshoot": self.overshoot.z},
                "kept": self.kept}


def held_out_choice(search: KnotWeightSpace, best: np.ndarray, layout: NetLayout, points: np.ndarray,
                    uv: np.ndarray, seen: np.ndarray, polish_iterations: int,
                    point_weights: np.ndarray | None = None) -> tuple[np.ndarray, Validation | None]:
    """The swarm's best particle or the classical start (see the module doc); the best
    itself (and no test) when fewer than four points were not seen or the best is the
    classical start.

    The candidates are fitted to the swarm's points and every other unseen point (closer
    to the final fit, which sees every point, than the swarm's sample alone: knots chosen
    for a sample can beat uniform ones on it and lose with all the points) and judged on
    the rest: at the first parameters (the classical start with the smoothing the
    leave-one-out error picks there: it carries the configured one, which the classical
    fit does not end with), and finished as the pipeline finishes it (:func:`psonurbs.fitting.finish.finishing.finish`)."""
    unseen = np.setdiff1d(np.arange(len(points)), seen)
    classical = search.classical()
    if len(unseen) < 4 or np.array_equal(best, classical):
        return best, None
    judged, fitted = unseen[::2], np.concatenate([seen, unseen[1::2]])
    c = (lambda idx: None) if point_weights is None else (lambda idx: point_weights[idx])  # weights of a subset
    cloud = cKDTree(points)
    first, polished, overshoot = [], [], []
    for x in (classical, best):
        shape, smoothing = search.split(x)
        at_first = loo_smoothing(layout, search.solver, points[seen], uv[seen], shape, c(seen)) \
            if x is classical else smoothing
        control = search.solver.with_smoothing(at_first).solve(layout.rows(uv[fitted], *shape), points[fitted],
                                                                c(fitted))
        first.append(np.linalg.norm(layout.rows(uv[judged], *shape) @ control - points[judged], axis=1))
        candidate = FitPoints(points[fitted], uv[fitted], slice(0, len(seen)), c(fitted))  # the swarm's points first
        surface = finish(layout, search.solver.with_smoothing(smoothing), candidate, shape,
                         min(polish_iterations, ROUNDS)).surface
        polished.append(closest_parameters(surface, points[judged])[1])
        overshoot.append(reach(surface, cloud))
    test = Validation(paired_test(*first, c(judged)), paired_test(*polished, c(judged)), paired_test(*overshoot))
    return (best if test.kept == "swarm" else classical), test
