"""Topologies: the net layout and first parameters of each, and choosing one from a cloud.

    open      an open patch: clamped knots both ways
    cylinder  closed in u (periodic), open in v: a tube with two rims
    sphere    closed in u, open in v, the first and last rows collapsed to the poles
    torus     closed in both directions

``auto`` tries every topology whose parametrisation the cloud supports (a closed
direction needs data all the way round; a sphere needs data near both poles; a
cylinder needs rims, not ends that close to a point) and keeps the one whose
classical fit (uniform knots, unit weights, least squares) has the smallest
leave-one-out error. Every candidate's score or reason for rejection is reported.
The open candidate's first parameters follow ``parametrisation`` (plane or intrinsic,
:mod:`psonurbs.fitting.parameters.open_patch`), intrinsic ones corrected from coarse to fine
(:mod:`psonurbs.fitting.parameters.coarse_to_fine`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from psonurbs.fitting.finish.self_checks import check_fit
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.search.knot_weight_space import KnotWeightSpace
from psonurbs.geometry.net import NetLayout

from .closed import parametrise_cylinder, parametrise_sphere, parametrise_torus
from .coarse_to_fine import coarse_to_fine
from .open_patch import parametrise_open_patch
from .parametrisation import Parametrisation
from .plane import parametrise_open

LAYOUTS = {  # closed (u, v), poles
    "open": ((False, False), False),
    "cylinder": ((True, False), False),
    "sphere": ((True, False), True),
    "torus": ((True, True), False),
}
MAX_GAP = 0.25  # widest empty arc (in turns) that a closed direction may have
POLE_REACH = 0.15  # a sphere's data must come this close (in v) to each pole
RIM_RATIO = 0.3  # a cylinder's ends must keep this share of its middle radius
SUSPECT = "suspect: "  # a candidate rejected by the self-checks: its reason in ``topology_scores``

PARAMETRISATIONS = {"open": parametrise_open, "cylinder": parametrise_cylinder,
                    "sphere": parametrise_sphere, "torus": parametrise_torus}


def parametrise(points: np.ndarray, topology: str) -> Parametrisation:
    """First (u, v) in [0, 1]^2 for every point, for the given topology."""
    return PARAMETRISATIONS[topology](points)



def layout_for(topology: str, net_size, degrees) -> NetLayout:
    closed, poles = LAYOUTS[topology]
    return NetLayout(tuple(net_size), tuple(degrees), closed, poles)


def unsupported(par: Parametrisation, points: np.ndarray, topology: str) -> str | None:
    """Why the cloud cannot carry this topology's parametrisation (None if it can)."""
    info = par.info
    gaps = info.get("angular_gaps") or ([info["angular_gap"]] if "angular_gap" in info else [])
    for name, gap in zip(("around the axis", "around the tube"), gaps):
        if gap > MAX_GAP:
            return f"no data on {gap:.0%} of the turn {name}"
    if topology == "sphere":
        lo, hi = info["latitude_range"]
        if lo > POLE_REACH or hi < 1.0 - POLE_REACH:
            return "the data do not reach both poles"
    if topology == "cylinder":
        axis = np.asarray(info["axis"])
        radial = points - points.mean(axis=0)
        radial = np.linalg.norm(radial - np.outer(radial @ axis, axis), axis=1)
        v = par.uv[:, 1]
        middle = np.median(radial[(v > 0.3) & (v < 0.7)]) if np.any((v > 0.3) & (v < 0.7)) else 0.0
        ends = [np.median(radial[v <= 0.05]) if np.any(v <= 0.05) else 0.0,
                np.median(radial[v >= 0.95]) if np.any(v >= 0.95) else 0.0]
        if middle <= 0 or min(ends) < RIM_RATIO * middle:
            return "an end closes to a point (not a tube with two rims)"
    return None


def classical_error(layout: NetLayout, par: Parametrisation, points: np.ndarray, config) -> float:
    """Leave-one-out RMSE of the classical fit (uniform knots, unit weights)."""
    solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing, layout.constraint_operator())
    search = KnotWeightSpace(layout, solver, points, par.uv, config.cross_validation,
                              config.min_knot_gap, tuple(config.weight_bounds))
    return search.error(search.classical())


def oriented(par: Parametrisation, layout: NetLayout, points: np.ndarray, config) -> Parametrisation:
    """An open patch whose two directions differ (orders or net size) gets the (u, v)
    roles that fit better; closed topologies have fixed roles."""
    if any(layout.closed) or (layout.degrees[0] == layout.degrees[1] and layout.size[0] == layout.size[1]):
        return par
    candidates = [par, par.swapped()]
    errors = [classical_error(layout, c, points, config) for c in candidates]
    return candidates[int(np.argmin(errors))]


def parametrise_for(points: np.ndarray, sample: np.ndarray, topology: str, config) -> Parametrisation:
    """First parameters of all points for a given topology (orientation settled on
    ``sample``); intrinsic ones of an open patch corrected from coarse to fine."""
    par = parametrise_open_patch(points, config.parametrisation) if topology == "open" else parametrise(points, topology)
    layout = layout_for(topology, config.net_size, config.degrees)
    if oriented(Parametrisation(par.uv[sample], par.info), layout, points[sample], config).info.get("swapped"):
        par = par.swapped()
    if par.info["method"] == "intrinsic":
        uv, levels = coarse_to_fine(layout, points, par.uv, config.smoothing, direct=par.info.get("sides") == "four")
        par = Parametrisation(uv, {**par.info, "coarse_to_fine": levels})
    return par


def classical_surface(layout: NetLayout, par: Parametrisation, points: np.ndarray, config):
    """The classical fit's surface (uniform knots, unit weights, least squares)."""
    solver = RegularisedLeastSquares(layout.smoothness_operator(), config.smoothing, layout.constraint_operator())
    weights = np.ones(layout.n_free)
    return layout.surface(solver.solve(layout.rows(par.uv, weights), points), weights)


def choose_topology(points: np.ndarray, sample: np.ndarray, config,
                    log: Callable[[str], None] | None = None) -> tuple[str, Parametrisation, dict]:
    """The topology that fits the cloud best, its parametrisation and every candidate's score.

    A candidate whose classical surface fails a self-check (:mod:`psonurbs.fitting.finish.self_checks`)
    is rejected: an open patch laid over a tube caps its end and folds there, a torus
    forced onto a curled sheet flaps far outside it, both while passing near every
    point. If every candidate fails, the least error is kept all the same.
    """
    scores, candidates, suspect = {}, {}, {}
    for topology in LAYOUTS:
        if topology == "sphere" and config.net_size[1] < 3:
            scores[topology] = {"rejected": "net_size along v is below 3"}
            continue
        par = parametrise_for(points, sample, topology, config)
        reason = None if topology == "open" else unsupported(par, points, topology)
        if reason is not None:
            scores[topology] = {"rejected": reason}
            continue
        layout = layout_for(topology, config.net_size, config.degrees)
        on_sample = Parametrisation(par.uv[sample], par.info)
        error = classical_error(layout, on_sample, points[sample], config)
        scores[topology] = {"classical_error_relative": float(error)}
        if topology == "open":
            scores[topology]["parametrisation"] = par.info["method"]
        warnings = check_fit(classical_surface(layout, on_sample, points[sample], config), points[sample]).warnings
        (suspect if warnings else candidates)[topology] = (error, par)
        if warnings:
            scores[topology]["rejected"] = SUSPECT + "; ".join(warnings)
    pool = candidates or suspect
    best = min(pool, key=lambda t: (pool[t][0], list(LAYOUTS).index(t)))
    return best, pool[best][1], scores


def topology_note(chosen: str, scores: dict) -> str:
    """The fit's note on ``topology: auto``: each candidate's classical error or why it
    was rejected. Where every candidate failed a self-check, the one kept (the least
    error) is said to be kept, with what its check found."""
    def entry(name: str, score: dict) -> str:
        if "rejected" not in score:
            return f"{name} {score['classical_error_relative']:.2e}"
        if name == chosen:
            found = score["rejected"].removeprefix(SUSPECT)
            return (f"{name} {score['classical_error_relative']:.2e}, kept as the least error: "
                    f"every candidate failed a self-check (its own: {found})")
        return f"{name} rejected: {score['rejected']}"

    return f"topology auto: {chosen} (" + ", ".join(entry(name, s) for name, s in scores.items()) + ")"
