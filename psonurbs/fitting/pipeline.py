"""The fitter: organise -> parametrise -> swarm -> polish (-> refine), for one cloud.

``strategy: hybrid`` (default): the swarm searches what is non-linear (the inner knots
of both directions, the weights and the smoothing weight); inside its fitness the
control points come from the regularised least-squares solve, and a particle is
judged by its leave-one-out RMSE (each point against the solve that did not see it),
so the swarm cannot win by tuning knots to noise. With ``robust``, gross outliers are
left out first (:mod:`psonurbs.fitting.robust`). The best particle is kept only if, polished,
it is nearer than the classical start to the points the swarm never saw
(:func:`validated`); it is polished (parameter correction), the smoothing re-chosen by
leave-one-out at the corrected parameters and polished again; then, with ``refine``,
control points, weights and parameters are refined jointly (:mod:`psonurbs.fitting.refine`),
anchored to the data's edges and kept if the gain pays for the freed weights
(:func:`pays_for_weights`). ``strategy: full`` is the paper's own search space
(Eq. 10, :mod:`psonurbs.fitting.paper`): the swarm's best surface is the result.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import Trim

from .footprint import footprint, footprint_notes
from .hybrid import SMOOTHING_RANGE, KnotWeightSearch
from .organise import RESOLUTION, Cloud, organise, subsample
from .paper import FullSearch
from .parametrise import Parametrisation
from .polish import polish
from .pso import SwarmResult, minimise
from .refine import refine_jointly
from .robust import OUTLIER_SIGMAS, classical_inliers, kept_sample, refreshed_inliers
from .solve import RegularisedLeastSquares
from .topology import choose_topology, layout_for, parametrise_for

CURVE_HEADER = ["iteration", "best_rmse", "mean_rmse"]


@dataclass
class FitResult:
    surface: NurbsSurface  # in the cloud's own coordinates
    topology: str
    metrics: dict
    curve: np.ndarray  # (iterations, 3): iteration, best and mean RMSE (cloud units)
    info: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    curve_header: list[str] = field(default_factory=lambda: list(CURVE_HEADER))
    trim: Trim | None = None  # the face's loops in the surface's parameter domain (None: untrimmed)


def rms(distances: np.ndarray) -> float:
    return float(np.sqrt(np.mean(distances ** 2)))


def loo_smoothing(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
                  weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray) -> float:
    """The smoothing weight with the least leave-one-out error at these parameters.

    After the polish the parameters are close to foot points, so the choice is sharp:
    vanishing where the net represents the shape, larger where the data are noisy.
    """
    rows = layout.rows(uv, weights, inner_u, inner_v)
    grid = 10.0 ** np.arange(SMOOTHING_RANGE[0], SMOOTHING_RANGE[1] + 0.25, 0.5)
    errors = []
    for s in grid:
        try:
            errors.append(solver.with_smoothing(s).leave_one_out_rmse(rows, points))
        except np.linalg.LinAlgError:
            errors.append(np.inf)
    return float(grid[int(np.argmin(errors))])


def validated(search: KnotWeightSearch, best: np.ndarray, layout: NetLayout, points: np.ndarray, uv: np.ndarray,
              seen: np.ndarray, polish_iterations: int) -> tuple[np.ndarray, dict]:
    """The swarm's best particle, or the classical start if the best does worse on the
    points the swarm never saw.

    Among thousands of particles, the least leave-one-out error on one sample is an
    optimistic pick (on noisy data: knots and weights tuned to that sample's noise).
    Both are polished on the swarm's points; the surface nearer the others is kept.
    """
    unseen = np.setdiff1d(np.arange(len(points)), seen)
    candidates = {"classical": search.classical(), "swarm": best}
    if len(unseen) == 0 or np.array_equal(best, candidates["classical"]):
        return best, {}
    errors = {}
    for name, x in candidates.items():
        inner_u, inner_v, weights, smoothing = search.split(x)
        surface = polish(layout, search.solver.with_smoothing(smoothing), points[seen], uv[seen], weights,
                         inner_u, inner_v, polish_iterations)[1]
        errors[name] = rms(closest_parameters(surface, points[unseen])[1])
    kept = "swarm" if errors["swarm"] < errors["classical"] else "classical"
    return candidates[kept], {"held_out_points": int(len(unseen)), "held_out_error": errors, "kept": kept}


def pays_for_weights(before: np.ndarray, after: np.ndarray, n_weights: int) -> bool:
    """Whether the refinement's drop in the residual sum of squares pays for the weights
    it frees (Akaike): ``n ln(RSS_before / RSS_after) > 2 n_weights``.

    On noisy data the extra freedom buys a percent or two of RMSE by fitting the noise,
    at the price of the true shape; on a conic it takes the error to zero.
    """
    rss_before, rss_after = float(np.sum(before ** 2)), float(np.sum(after ** 2))
    if rss_after <= 0.0:
        return rss_before > 0.0
    return len(before) * np.log(rss_before / rss_after) > 2.0 * n_weights


def anchored(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
             control: np.ndarray, weights: np.ndarray, inner_u: np.ndarray, inner_v: np.ndarray,
             polish_iterations: int) -> NurbsSurface:
    """The jointly refined surface with its edges back on the data.

    The refinement may let the data retreat from a bounded direction's edges (see
    ``NetLayout.bounded``): the surface then grows past the data's boundary at no cost
    and overshoots the true one. If the refined surface is exact (the data on it to
    within ``RESOLUTION``: a noise-free cloud of a shape the net represents, e.g. a conic
    with the right weights) its only freedom left is where it ends, and it is
    restricted exactly to the data's parameter extent. Otherwise it is polished again
    with its weights, the data's edges re-aligned onto the domain's at every round. A
    surface without edges (sphere, torus) is kept as refined.
    """
    surface = layout.surface(control, weights, inner_u, inner_v)
    if not any(layout.bounded):
        return surface
    if rms(closest_parameters(surface, points, uv)[1]) <= RESOLUTION:
        extent = [(float(uv[:, k].min()), float(uv[:, k].max())) if layout.bounded[k] else (0.0, 1.0)
                  for k in (0, 1)]
        return surface.restricted(*extent)
    return polish(layout, solver, points, uv, weights, inner_u, inner_v, polish_iterations, realign=True)[1]


def run_hybrid(cloud: Cloud, layout: NetLayout, par: Parametrisation, sample: np.ndarray, config,
               rng: np.random.Generator, progress) -> tuple[NurbsSurface, SwarmResult, dict]:
    """Swarm over knots, weights and smoothing (least-squares control points), then the
    polish and the optional joint refinement; with ``robust``, on the inliers only
    (:mod:`psonurbs.fitting.robust`: of the classical fit first, of the polished one after)."""
    solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing, layout.constraint_operator())
    keep = classical_inliers(layout, solver, cloud.points, par.uv) if config.robust else np.ones(len(cloud), bool)
    points, uv, seen = cloud.points[keep], par.uv[keep], kept_sample(sample, keep)
    search = KnotWeightSearch(layout, solver, points[seen], uv[seen], config.cross_validation,
                              config.min_knot_gap, tuple(config.weight_bounds))
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    chosen, validation = validated(search, swarm.best_position, layout, points, uv, seen, config.polish_iterations)
    inner_u, inner_v, weights, smoothing = search.split(chosen)
    solver = solver.with_smoothing(smoothing)
    control, surface, uv, steps = polish(layout, solver, points, uv, weights, inner_u, inner_v,
                                         config.polish_iterations)
    if config.robust:
        keep, uv = refreshed_inliers(surface, cloud.points, keep, uv)
        points, seen = cloud.points[keep], kept_sample(sample, keep)
    # with parameters near the foot points, the leave-one-out choice of smoothing is sharp
    solver = solver.with_smoothing(loo_smoothing(layout, solver, points[seen], uv[seen], weights,
                                                 inner_u, inner_v))
    control, surface, uv, more = polish(layout, solver, points, uv, weights, inner_u, inner_v,
                                        config.polish_iterations)
    steps += more
    refine_steps, kept = 0, False
    if config.refine:
        control, weights, uv, refine_steps = refine_jointly(layout, solver, points, uv, control, weights,
                                                            inner_u, inner_v, np.log(config.weight_bounds))
        refined = anchored(layout, solver, points, uv, control, weights, inner_u, inner_v,
                           config.polish_iterations)
        kept = pays_for_weights(closest_parameters(surface, points)[1], closest_parameters(refined, points)[1],
                                layout.n_free)
        if kept:
            surface = refined
    info = {"strategy": "hybrid", "parametrisation": par.info, "smoothing": float(solver.smoothing),
            "swarm": {"points": int(len(seen)), "cross_validation": bool(config.cross_validation), "evaluations": int(swarm.evaluations),
                      "classical_error": float(search.error(search.classical())), **validation},
            "polish_iterations": int(steps), "refine_iterations": int(refine_steps), "refined": bool(kept),
            "outliers": int(len(keep) - keep.sum())}
    return surface, swarm, info


def run_full(cloud: Cloud, layout: NetLayout, par: Parametrisation, sample: np.ndarray, config,
             rng: np.random.Generator, progress) -> tuple[NurbsSurface, SwarmResult, dict]:
    """The paper's search space over every point: the swarm's best surface, unpolished."""
    search = FullSearch(layout, cloud.points, par.uv, config.min_knot_gap, tuple(config.weight_bounds))
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    info = {"strategy": "full", "parametrisation": par.info,
            "swarm": {"points": len(cloud), "dimension": int(search.dimension),
                      "evaluations": int(swarm.evaluations)}}
    return search.surface(swarm.best_position), swarm, info


def fit_points(points: np.ndarray, config, on_iteration: Callable[[int, float, float], None] | None = None
               ) -> FitResult:
    """Fit one cloud (N, 3) given in its own units; see the module docstring.

    ``on_iteration(i, best, mean)`` is called after each swarm iteration (cloud units).
    """
    points = np.asarray(points, float)
    with threadpool_limits(limits=1):
        cloud = organise(points, tuple(config.orders), config.remove_outliers)
        diag = cloud.frame.diagonal
        rng = np.random.default_rng(config.swarm.seed)
        sample = subsample(len(cloud), config.swarm_points, rng)
        scores = None
        if config.topology == "auto":
            topology, par, scores = choose_topology(cloud.points, sample, config)
        else:
            topology = config.topology
            par = parametrise_for(cloud.points, sample, topology, config)
        layout = layout_for(topology, config.net_size, config.degrees)
        progress = None if on_iteration is None else (lambda i, b, m: on_iteration(i, b * diag, m * diag))
        run = run_full if config.strategy == "full" else run_hybrid
        surface, swarm, info = run(cloud, layout, par, sample, config, rng, progress)
        local = cloud.frame.to_local(points)
        uv, dist = closest_parameters(surface, local)
        face = footprint(surface, local, uv, dist, config.trim if topology == "open" else False)
        surface, dist = face.surface, face.distances
        info["trim"] = face.to_dict()
    world = NurbsSurface(surface.degree_u, surface.degree_v, surface.knots_u, surface.knots_v,
                         cloud.frame.to_world(surface.control_points), surface.weights,
                         surface.closed_u, surface.closed_v)
    dist = dist * diag
    input_diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    rmse = rms(dist)
    metrics = {
        "rmse": rmse,
        "max_error": float(dist.max()),
        "rmse_relative": rmse / input_diag,
        "max_error_relative": float(dist.max()) / input_diag,
        "bbox_diagonal": input_diag,
        "points": int(len(points)),
        "control_points": int(layout.n_free),
        "swarm_best_error": float(swarm.best_value * diag),
        "outliers": int(info.get("outliers", 0)),
    }
    if "classical_error" in info["swarm"]:
        info["swarm"]["classical_error"] *= diag
    for name in info["swarm"].get("held_out_error", {}):
        info["swarm"]["held_out_error"][name] *= diag
    iterations = np.arange(1, len(swarm.best_history) + 1)
    curve = np.column_stack([iterations, swarm.best_history * diag, swarm.mean_history * diag])
    notes = []
    if len(cloud) < layout.n_free:
        notes.append(f"under-determined: {len(cloud)} points for {layout.n_free} control points, "
                     "the smoothness term decides between them")
    if metrics["outliers"]:
        notes.append(f"{metrics['outliers']} gross outliers (over {OUTLIER_SIGMAS:g} robust standard deviations "
                     "off the surface) left out of the fit; rmse and max_error still count them")
    if cloud.duplicates:
        notes.append(f"{cloud.duplicates} duplicate points ignored")
    if scores is not None:
        info["topology_scores"] = scores
        notes.append(f"topology auto: {topology} (" + ", ".join(
            f"{name} {s['classical_error_relative']:.2e}" if "rejected" not in s else f"{name} rejected: {s['rejected']}"
            for name, s in scores.items()) + ")")
    notes += footprint_notes(face, len(points))
    metrics["outside_trim"] = int(face.points_outside)
    return FitResult(world, topology, metrics, curve, info, notes, trim=face.trim)
