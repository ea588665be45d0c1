"""The fitter, for one cloud: prepare -> parameters -> search -> finish.

``strategy: hybrid`` (default): the swarm searches what is non-linear (the inner knots
of both directions, the weights and the smoothing weight); inside its fitness the
control points come from the regularised least-squares solve, and a particle is
judged by its leave-one-out RMSE (each point against the solve that did not see it),
so the swarm cannot win by tuning knots to noise. With ``robust``, gross outliers are
judged locally before anything is parametrised (:mod:`psonurbs.fitting.prepare.outliers`)
and every solve weighs the rest by a robust loss
(:mod:`psonurbs.fitting.prepare.robust_weights`). The best particle is kept only if it
predicts the points the swarm never saw better than the classical start, by paired
tests (:mod:`psonurbs.fitting.search.validation`); it is finished
(:func:`psonurbs.fitting.finish.finishing.finish`: polished, the smoothing re-chosen by
leave-one-out at the corrected parameters, polished again); then, with ``refine``,
control points, weights and parameters are refined jointly and the result kept only if
it earns it (:func:`psonurbs.fitting.finish.refine.refined_if_better`). ``strategy:
full`` is the paper's own search space (Eq. 10, :mod:`psonurbs.fitting.search.paper_space`):
the swarm's best surface is the result. The result is checked without ground truth
(:mod:`psonurbs.fitting.finish.self_checks`: the surface or its net far outside the
cloud's box, a fold, surface far from every point); a fit that fails a check carries
warnings and says so in its notes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from psonurbs.fitting.finish.finishing import FitPoints, finish
from psonurbs.fitting.finish.footprint import footprint, footprint_notes
from psonurbs.fitting.finish.refine import refined_if_better
from psonurbs.fitting.finish.self_checks import check_fit
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.parameters.parametrisation import Parametrisation
from psonurbs.fitting.parameters.topology import choose_topology, layout_for, parametrise_for, topology_note
from psonurbs.fitting.prepare.big_clouds import big_cloud_sample, every_foot_point, finished
from psonurbs.fitting.prepare.organise import Cloud, organise, subsample
from psonurbs.fitting.prepare.outliers import OUTLIER_SIGMAS, local_outliers
from psonurbs.fitting.prepare.robust_weights import (
    CUTOFF_SIGMAS,
    Verdict,
    classical_weights,
    kept_sample,
    loss_summary,
    parameters_for_all,
    refreshed_weights,
    trusted_points,
)
from psonurbs.fitting.search.knot_weight_space import KnotWeightSpace
from psonurbs.fitting.search.paper_space import PaperSpace
from psonurbs.fitting.search.swarm import SwarmResult, minimise
from psonurbs.fitting.search.tolerance import fit_to_tolerance
from psonurbs.fitting.search.validation import held_out_choice, swarm_points_of
from psonurbs.geometry.net import NetLayout
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import Trim

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
    warnings: list[str] = field(default_factory=list)  # failed self-checks (:mod:`psonurbs.fitting.finish.self_checks`)
    trim: Trim | None = None  # the face's loops in the surface's parameter domain (None: untrimmed)
    distances: np.ndarray | None = None  # (N,) every input point's distance to the (trimmed) surface, cloud units


def rms(distances: np.ndarray) -> float:
    return float(np.sqrt(np.mean(distances ** 2)))


def run_hybrid(cloud: Cloud, layout: NetLayout, par: Parametrisation, sample: np.ndarray, config,
               rng: np.random.Generator, progress, swarm_weights: bool = True
               ) -> tuple[NurbsSurface, SwarmResult, dict]:
    """Swarm over knots, weights (unless ``swarm_weights`` is False: unit weights in the
    swarm, the refinement alone frees them) and smoothing (least-squares control points), the best
    kept only if it predicts the points it never saw better than the classical fit
    (:mod:`psonurbs.fitting.search.validation`), then the polish and the optional joint
    refinement; with ``robust``, every solve weighted by the robust loss
    (:mod:`psonurbs.fitting.prepare.robust_weights`: of the classical fit first, of the polished one
    after), the points of weight 0 left out."""
    solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing, layout.constraint_operator())
    w = classical_weights(layout, solver, cloud.points, par.uv, cloud.neighbourhoods) if config.robust \
        else np.ones(len(cloud))
    keep = w > 0
    points, uv, seen, w = cloud.points[keep], par.uv[keep], kept_sample(sample, keep), w[keep]
    c = w if config.robust else None  # the point weights of every solve
    swarms = swarm_points_of(seen, len(points))  # the sample, some held out for the validation in a small cloud
    bounds = tuple(config.weight_bounds) if swarm_weights else (1.0, 1.0)  # equal bounds: the weights stay 1
    search = KnotWeightSpace(layout, solver, points[swarms], uv[swarms], config.cross_validation,
                              config.min_knot_gap, bounds, None if c is None else c[swarms])
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    chosen, test = held_out_choice(search, swarm.best_position, layout, points, uv, swarms, config.polish_iterations,
                                   c)
    shape, smoothing = search.split(chosen)

    def reweigh(surface: NurbsSurface, fit: FitPoints, again: bool, at: RegularisedLeastSquares) -> FitPoints | None:
        """The robust loss on a polished surface: the points left out judged on it."""
        nonlocal w, keep
        now = np.zeros(len(keep))
        now[keep] = fit.point_weights
        fresh, uv_all = refreshed_weights(surface, cloud.points, keep, fit.uv, cloud.neighbourhoods,
                                          lambda uv_at, of: at.own_leverage(layout.rows(uv_at, *shape), now, of))
        if again and np.array_equal(fresh > 0, keep):
            return None
        w, keep = fresh, fresh > 0
        return FitPoints(cloud.points[keep], uv_all[keep], kept_sample(sample, keep), w[keep])

    done = finish(layout, solver.with_smoothing(smoothing), FitPoints(points, uv, seen, c), shape,
                  config.polish_iterations, reweigh if config.robust else None)
    solver, steps = done.solver, done.rounds
    surface, kept, refine_steps = done.surface, False, 0
    if config.refine:
        refinement = refined_if_better(layout, done, shape, np.log(config.weight_bounds), config.refine_iterations,
                                       config.polish_iterations)
        surface, kept, refine_steps = refinement.surface, refinement.accepted, refinement.rounds
    validation = {} if test is None else test.to_dict()
    info = {"strategy": "hybrid", "parametrisation": par.info, "smoothing": float(solver.smoothing),
            "swarm": {"points": int(len(swarms)), "cross_validation": bool(config.cross_validation), "evaluations": int(swarm.evaluations),
                      "classical_error": float(search.error(search.classical())), **validation},
            "polish_iterations": int(steps), "refine_iterations": int(refine_steps), "refined": bool(kept)}
    if config.robust:
        info["robust"] = {"loss": loss_summary(w)}
    return surface, swarm, info


def run_full(cloud: Cloud, layout: NetLayout, par: Parametrisation, sample: np.ndarray, config,
             rng: np.random.Generator, progress) -> tuple[NurbsSurface, SwarmResult, dict]:
    """The paper's search space over every point: the swarm's best surface, unpolished."""
    search = PaperSpace(layout, cloud.points, par.uv, config.min_knot_gap, tuple(config.weight_bounds))
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    info = {"strategy": "full", "parametrisation": par.info,
            "swarm": {"points": len(cloud), "dimension": int(search.dimension),
                      "evaluations": int(swarm.evaluations)}}
    return search.surface(swarm.best_position), swarm, info


def fit_points(points: np.ndarray, config, on_iteration: Callable[[int, float, float], None] | None = None,
               swarm_weights: bool = True) -> FitResult:
    """Fit one cloud (N, 3) given in its own units; see the module docstring.

    ``on_iteration(i, best, mean)`` is called after each swarm iteration (cloud units).
    With a tolerance the net is searched (:mod:`psonurbs.fitting.search.tolerance`), each
    net tried fitted by this function with ``swarm_weights`` False: the swarm of the
    hybrid strategy then searches knots and smoothing only, the weights left to the refinement.
    """
    if config.has_tolerance:
        return fit_to_tolerance(points, config, fit_points, on_iteration)
    points = np.asarray(points, float)
    with threadpool_limits(limits=1):
        cloud = organise(points, tuple(config.orders))
        local = local_outliers(cloud.points) if config.robust else None
        if local is not None:  # the outliers go before they can steer the parametrisation
            renumbered = np.where(local.inliers, np.cumsum(local.inliers) - 1, -1)
            cloud = Cloud(cloud.points[local.inliers], cloud.frame, cloud.duplicates, local.neighbourhoods(),
                          renumbered[cloud.source])
        diag = cloud.frame.diagonal
        rng = np.random.default_rng(config.swarm.seed)
        sample = subsample(len(cloud), config.swarm_points, rng)
        # a big cloud is fitted on a subsample holding the swarm's points, then finished on all
        big = big_cloud_sample(len(cloud), sample) if config.strategy == "hybrid" else None
        fitted, fitted_sample = (cloud, sample) if big is None else (
            Cloud(cloud.points[big], cloud.frame, cloud.duplicates), np.searchsorted(big, sample))
        scores = None
        trusted = trusted_points(cloud.neighbourhoods, len(cloud))  # they alone steer the parametrisation
        if big is not None:  # (its robust loss weighs by the plain scale: the neighbourhoods are the cloud's)
            trusted = trusted[big]
        points_t, sample_t = fitted.points[trusted], kept_sample(fitted_sample, trusted)
        if config.topology == "auto":
            topology, par, scores = choose_topology(points_t, sample_t, config)
        else:
            topology = config.topology
            par = parametrise_for(points_t, sample_t, topology, config)
        par = Parametrisation(parameters_for_all(fitted.points, trusted, par.uv), par.info)
        layout = layout_for(topology, config.net_size, config.degrees, not config.align_edges)
        progress = None if on_iteration is None else (lambda i, b, m: on_iteration(i, b * diag, m * diag))
        surface, swarm, info = run_full(fitted, layout, par, fitted_sample, config, rng, progress) \
            if config.strategy == "full" else \
            run_hybrid(fitted, layout, par, fitted_sample, config, rng, progress, swarm_weights)
        if big is not None:
            done = finished(layout, surface, cloud.points, info["smoothing"], config.robust,
                            info["refined"] and any(layout.bounded), cloud.neighbourhoods)
            surface, info["subsample"] = done.surface, {"points": int(len(big)), "final_rounds": done.rounds}
            if done.point_weights is not None:
                info["robust"] = {"loss": loss_summary(done.point_weights)}
        in_frame = cloud.frame.to_local(points)
        uv, dist = closest_parameters(surface, in_frame) if big is None else \
            every_foot_point(surface, in_frame, cloud.source, done.uv)
        face = footprint(surface, in_frame, uv, dist, config.trim if topology == "open" else False,
                         Verdict.of(cloud.neighbourhoods, cloud.source),
                         par.info.get("normal") if par.info.get("method") == "plane" else None,
                         par.info.get("method") == "intrinsic")
        surface, dist = face.surface, face.distances
        info["trim"] = face.to_dict()
        checks = check_fit(surface, cloud.points, trim=face.trim)
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
        "outliers": 0,
        **checks.to_dict(),
    }
    if local is not None:  # left out: locally judged outliers, and points of weight 0 in the final solve
        info.setdefault("robust", {})["local"] = local.to_dict(diag)
        metrics["outliers"] = int(local.outliers.sum()) + info["robust"].get("loss", {}).get("left_out", 0)
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
        local_count = int(local.outliers.sum())
        notes.append(f"{metrics['outliers']} gross outliers left out of the fit ({local_count} over {OUTLIER_SIGMAS:g} "
                     "robust sigmas off the surface their neighbours describe, "
                     f"{metrics['outliers'] - local_count} over {CUTOFF_SIGMAS:g} off the fit and from their neighbours); "
                     "rmse and max_error still count them")
    if cloud.duplicates:
        notes.append(f"{cloud.duplicates} duplicate points ignored")
    if "subsample" in info:
        notes.append(f"fitted on {info['subsample']['points']} of the {len(cloud)} points, "
                     f"then {info['subsample']['final_rounds']} rounds of parameter correction on all")
    if scores is not None:
        info["topology_scores"] = scores
        notes.append(topology_note(topology, scores))
    notes += footprint_notes(face, len(points))
    metrics["outside_trim"] = int(face.points_outside)
    notes += [f"suspect fit: {warning}" for warning in checks.warnings]
    return FitResult(world, topology, metrics, curve, info, notes, warnings=checks.warnings, trim=face.trim,
                     distances=dist)
