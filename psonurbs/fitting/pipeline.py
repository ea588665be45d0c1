"""The fitter: organise -> parametrise -> swarm -> polish (-> refine), for one cloud.

``strategy: hybrid`` (default): the swarm searches what is non-linear (the inner knots
of both directions, the weights and the smoothing weight); inside its fitness the
control points come from the regularised least-squares solve, and a particle is
judged by its leave-one-out RMSE (each point against the solve that did not see it),
so the swarm cannot win by tuning knots to noise. With ``robust``, gross outliers are
judged locally before anything is parametrised (:mod:`psonurbs.fitting.outliers`) and
every solve weighs the rest by a robust loss (:mod:`psonurbs.fitting.robust`). The best
particle is kept only if it predicts the points the swarm never saw better than the
classical start, by paired tests (:mod:`psonurbs.fitting.validation`); it is polished
(parameter correction), the smoothing re-chosen by
leave-one-out at the corrected parameters and polished again; then, with ``refine``,
control points, weights and parameters are refined jointly (:mod:`psonurbs.fitting.refine`),
anchored to the data's edges and kept if the gain pays for the freed weights
(:func:`pays_for_weights`), or, where the swarm's weights were free already, if it fits
the points as well and ends nearer the data (:func:`ends_nearer`). ``strategy: full`` is
the paper's own search space (Eq. 10, :mod:`psonurbs.fitting.paper`): the swarm's best surface is the result.
The result is checked without ground truth (:mod:`psonurbs.fitting.checks`: the surface
or its net far outside the cloud's box, a fold, surface far from every point); a fit
that fails a check carries warnings and says so in its notes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from psonurbs.geometry.net import NetLayout, NetShape
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters
from psonurbs.geometry.trim import Trim

from .checks import check_fit
from .footprint import footprint, footprint_notes
from .hybrid import KnotWeightSearch, loo_smoothing
from .organise import RESOLUTION, Cloud, organise, subsample
from .outliers import OUTLIER_SIGMAS, local_outliers
from .paper import FullSearch
from .parametrise import Parametrisation
from .polish import polish
from .pso import SwarmResult, minimise
from .refine import refine_jointly
from .robust import (
    CUTOFF_SIGMAS,
    classical_weights,
    kept_sample,
    loss_summary,
    parameters_for_all,
    refreshed_weights,
    trusted_points,
)
from .sampling import big_cloud_sample, every_foot_point, finished
from .solve import RegularisedLeastSquares, weighted_rms
from .topology import choose_topology, layout_for, parametrise_for, topology_note
from .validation import Z, held_out_choice, paired_test, reach, swarm_points_of

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
    warnings: list[str] = field(default_factory=list)  # failed self-checks (:mod:`psonurbs.fitting.checks`)
    trim: Trim | None = None  # the face's loops in the surface's parameter domain (None: untrimmed)


def rms(distances: np.ndarray) -> float:
    return float(np.sqrt(np.mean(distances ** 2)))


def pays_for_weights(before: np.ndarray, after: np.ndarray, n_weights: int,
                     point_weights: np.ndarray | None = None) -> bool:
    """Whether the refinement's drop in the residual sum of squares pays for the weights
    it frees (Akaike): ``n ln(RSS_before / RSS_after) > 2 n_weights``.

    On noisy data the extra freedom buys a percent or two of RMSE by fitting the noise,
    at the price of the true shape; on a conic it takes the error to zero.
    """
    c = 1.0 if point_weights is None else point_weights
    rss_before, rss_after = float(np.sum(c * before ** 2)), float(np.sum(c * after ** 2))
    if rss_after <= 0.0:
        return rss_before > 0.0
    return len(before) * np.log(rss_before / rss_after) > 2.0 * n_weights


def ends_nearer(polished: NurbsSurface, refined: NurbsSurface, points: np.ndarray, before: np.ndarray,
               after: np.ndarray, point_weights: np.ndarray | None = None) -> bool:
    """Whether the refined surface fits the points (N, 3) as well as the polished one and
    ends nearer the data, by the validation's paired tests (:mod:`psonurbs.fitting.validation`):
    the points' distances ``after`` (N,) not significantly larger than ``before`` (z < Z),
    and the surface's samples significantly nearer the cloud (z < -Z).

    For a swarm's particle, whose weights were searched, the refinement frees no weights,
    so the Akaike price of :func:`pays_for_weights` does not apply; what the refined
    surface can offer is its edges back on the data (:func:`anchored`). On step_bump the
    polished surface of the swarm's knots runs up to 0.09 past the data's edge, the
    anchored refined one does not, at an rmse 0.1% higher.
    """
    cloud = cKDTree(points)
    return paired_test(before, after, point_weights).z < Z and \
        paired_test(reach(polished, cloud), reach(refined, cloud)).z < -Z


def anchored(layout: NetLayout, solver: RegularisedLeastSquares, points: np.ndarray, uv: np.ndarray,
             control: np.ndarray, shape: NetShape, polish_iterations: int,
             point_weights: np.ndarray | None = None) -> NurbsSurface:
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
    surface = layout.surface(control, *shape)
    if not any(layout.bounded):
        return surface
    if weighted_rms(closest_parameters(surface, points, uv)[1] ** 2, point_weights) <= RESOLUTION:
        extent = [(float(uv[:, k].min()), float(uv[:, k].max())) if layout.bounded[k] else (0.0, 1.0)
                  for k in (0, 1)]
        return surface.restricted(*extent)
    return polish(layout, solver, points, uv, shape, polish_iterations, realign=True,
                  point_weights=point_weights).surface


def run_hybrid(cloud: Cloud, layout: NetLayout, par: Parametrisation, sample: np.ndarray, config,
               rng: np.random.Generator, progress) -> tuple[NurbsSurface, SwarmResult, dict]:
    """Swarm over knots, weights and smoothing (least-squares control points), the best
    kept only if it predicts the points it never saw better than the classical fit
    (:mod:`psonurbs.fitting.validation`), then the polish and the optional joint
    refinement; with ``robust``, every solve weighted by the robust loss
    (:mod:`psonurbs.fitting.robust`: of the classical fit first, of the polished one
    after), the points of weight 0 left out."""
    solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing, layout.constraint_operator())
    w = classical_weights(layout, solver, cloud.points, par.uv, cloud.neighbourhoods) if config.robust \
        else np.ones(len(cloud))
    keep = w > 0
    points, uv, seen, w = cloud.points[keep], par.uv[keep], kept_sample(sample, keep), w[keep]
    c = w if config.robust else None  # the point weights of every solve
    swarms = swarm_points_of(seen, len(points))  # the sample, some held out for the validation in a small cloud
    search = KnotWeightSearch(layout, solver, points[swarms], uv[swarms], config.cross_validation,
                              config.min_knot_gap, tuple(config.weight_bounds), None if c is None else c[swarms])
    swarm = minimise(search.fitness, search.initial_swarm(config.swarm.particles, rng), search.feasible(),
                     config.swarm.iterations, config.swarm.inertia, config.swarm.c1, config.swarm.c2,
                     rng, progress)
    chosen, test = held_out_choice(search, swarm.best_position, layout, points, uv, swarms, config.polish_iterations,
                                   c)
    shape, smoothing = search.split(chosen)
    solver = solver.with_smoothing(smoothing)
    control, surface, uv, steps = polish(layout, solver, points, uv, shape, config.polish_iterations,
                                         point_weights=c)
    if config.robust:
        w, uv = refreshed_weights(surface, cloud.points, keep, uv, cloud.neighbourhoods)
        keep = w > 0
        points, uv, seen, c = cloud.points[keep], uv[keep], kept_sample(sample, keep), w[keep]
    # with parameters near the foot points, the leave-one-out choice of smoothing is sharp
    solver = solver.with_smoothing(loo_smoothing(layout, solver, points[seen], uv[seen], shape,
                                                 None if c is None else c[seen]))
    control, surface, uv, more = polish(layout, solver, points, uv, shape, config.polish_iterations,
                                        point_weights=c)
    steps += more
    if config.robust:  # the points left out on the first polished surface, judged on the better one
        again, uv_all = refreshed_weights(surface, cloud.points, keep, uv, cloud.neighbourhoods)
        if not np.array_equal(again > 0, keep):
            w, keep = again, again > 0
            points, uv, seen, c = cloud.points[keep], uv_all[keep], kept_sample(sample, keep), w[keep]
            control, surface, uv, more = polish(layout, solver, points, uv, shape, config.polish_iterations,
                                                point_weights=c)
            steps += more
    refine_steps, kept = 0, False
    if config.refine:
        searched = np.any(shape.weights != 1.0)  # the weights already free: a swarm's particle, not unit weights
        control, shape, uv, refine_steps = refine_jointly(layout, solver, points, uv, control, shape,
                                                          np.log(config.weight_bounds), config.refine_iterations,
                                                          point_weights=c)
        refined = anchored(layout, solver, points, uv, control, shape, config.polish_iterations, c)
        before, after = closest_parameters(surface, points)[1], closest_parameters(refined, points)[1]
        kept = pays_for_weights(before, after, layout.n_free, c) or \
            (searched and ends_nearer(surface, refined, points, before, after, c))
        if kept:
            surface = refined
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
        layout = layout_for(topology, config.net_size, config.degrees)
        progress = None if on_iteration is None else (lambda i, b, m: on_iteration(i, b * diag, m * diag))
        run = run_full if config.strategy == "full" else run_hybrid
        surface, swarm, info = run(fitted, layout, par, fitted_sample, config, rng, progress)
        if big is not None:
            done = finished(layout, surface, cloud.points, info["smoothing"], config.robust,
                            info["refined"] and any(layout.bounded), cloud.neighbourhoods)
            surface, info["subsample"] = done.surface, {"points": int(len(big)), "final_rounds": done.rounds}
            if done.point_weights is not None:
                info["robust"] = {"loss": loss_summary(done.point_weights)}
        in_frame = cloud.frame.to_local(points)
        uv, dist = closest_parameters(surface, in_frame) if big is None else \
            every_foot_point(surface, in_frame, cloud.source, done.uv)
        face = footprint(surface, in_frame, uv, dist, config.trim if topology == "open" else False)
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
    return FitResult(world, topology, metrics, curve, info, notes, warnings=checks.warnings, trim=face.trim)
