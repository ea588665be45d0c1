"""Topologies: the net layout and first parameters of each, and choosing one from a cloud.

    open      an open patch: clamped knots both ways
    cylinder  closed in u (periodic), open in v: a tube with two rims
    sphere    closed in u, open in v, the first and last rows collapsed to the poles
    torus     closed in both directions

``auto`` tries every topology whose parametrisation the cloud supports (an open patch
needs data with an edge, and not a tube's data that go all the way round it; a closed
direction needs data all the way round; a sphere needs data near both poles; a
cylinder needs rims, not ends that close to a point, and a tube or a ring no data on
its axis) and keeps the one whose
classical fit (uniform knots, unit weights, least squares) has the smallest
leave-one-out error. Every candidate's score or reason for rejection is reported.
The open candidate's first parameters follow ``parametrisation`` (plane or intrinsic,
:mod:`psonurbs.fitting.parameters.open_patch`), intrinsic ones corrected from coarse to fine
(:mod:`psonurbs.fitting.parameters.coarse_to_fine`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.fitting.finish.footprint import median_spacing
from psonurbs.fitting.finish.self_checks import check_fit
from psonurbs.fitting.leastsq.regularised import RegularisedLeastSquares
from psonurbs.fitting.prepare.organise import normals_and_variation
from psonurbs.fitting.search.knot_weight_space import KnotWeightSpace
from psonurbs.geometry.net import NetLayout

from .closed import parametrise_sphere, parametrise_torus
from .coarse_to_fine import coarse_to_fine
from .open_patch import parametrise_open_patch
from .parametrisation import Parametrisation
from .plane import parametrise_open
from .tubes import TUBE_FIT, parametrise_cylinder

LAYOUTS = {  # closed (u, v), poles
    "open": ((False, False), False),
    "cylinder": ((True, False), False),
    "sphere": ((True, False), True),
    "torus": ((True, True), False),
}
MAX_GAP = 0.25  # widest empty arc (in turns) that a closed direction may have
POLE_REACH = 0.15  # a sphere's data must come this close (in v) to each pole
RIM_RATIO = 0.3  # a cylinder's ends must keep this share of its middle radius
ON_AXIS_SPACINGS = 2.0  # data this close (in point spacings) to a tube's axis close it there ...
ON_AXIS_POINTS = 3  # ... when at least this many points lie there (one stray point does not)
EDGE_NEIGHBOURS = 24  # a point's neighbourhood when judging whether it lies on the data's edge
EDGE_OFFSET = 0.35  # ... on it when its neighbours' centroid lies this share of their reach to one side
EDGE_SAMPLE = 2000  # points judged (a random thinning of more): an open sheet's share stays above ~5%
CLOSED_SHARE = 0.01  # data with fewer edge points than this share have no edge: an open patch cannot cover them
ROUND_GAP = 2.0  # a tube's data whose widest gap round it spans fewer point spacings than this close round it
SUSPECT = "suspect: "  # a candidate rejected by the self-checks: its reason in ``topology_scores``

PARAMETRISATIONS = {"open": parametrise_open, "cylinder": parametrise_cylinder,
                    "sphere": parametrise_sphere, "torus": parametrise_torus}


def parametrise(points: np.ndarray, topology: str) -> Parametrisation:
    """First (u, v) in [0, 1]^2 for every point, for the given topology."""
    return PARAMETRISATIONS[topology](points)



def layout_for(topology: str, net_size, degrees, free_edges: bool = False) -> NetLayout:
    closed, poles = LAYOUTS[topology]
    return NetLayout(tuple(net_size), tuple(degrees), closed, poles, free_edges)


def on_axis(points: np.ndarray, axis: np.ndarray, through: np.ndarray | None = None) -> bool:
    """Whether the data (N, 3) reach the line along ``axis`` through ``through`` (default:
    their centroid): ``ON_AXIS_POINTS`` of them within ``ON_AXIS_SPACINGS`` median
    spacings of it. A tube or a ring has a hole there; a closed end (a capsule's, a
    bottle's) does not."""
    radial = points - (points.mean(axis=0) if through is None else through)
    radial = np.linalg.norm(radial - np.outer(radial @ axis, axis), axis=1)
    return int(np.sum(radial < ON_AXIS_SPACINGS * median_spacing(points))) >= ON_AXIS_POINTS


def edge_share(points: np.ndarray) -> float:
    """The share of points (N, 3) on the data's edge: those whose ``EDGE_NEIGHBOURS``
    nearest neighbours' centroid, in their tangent plane, lies more than ``EDGE_OFFSET``
    of the neighbourhood's radius r to one side. Inside a uniform sampling the offset is
    about r / sqrt(2 k) (0.14 r); at a straight edge 4 r / (3 pi) (0.42 r). A closed
    surface has no edge: the share is a few in a thousand at most, while an open sheet
    of n points keeps about 3.5 / sqrt(n) of them on its edge or more (a disc; a square
    4 / sqrt(n)), about 0.7 of which the offset finds: 5% of ``EDGE_SAMPLE``."""
    if len(points) > EDGE_SAMPLE:  # a uniform thinning: the share is one of EDGE_SAMPLE points
        points = points[np.random.default_rng(0).choice(len(points), EDGE_SAMPLE, replace=False)]
    k = min(EDGE_NEIGHBOURS, len(points) - 1)
    if k < 3:
        return 1.0
    reach, nearest = cKDTree(points).query(points, k=k + 1)
    normal = normals_and_variation(points, nearest[:, 1:])[0]
    shift = points[nearest[:, 1:]].mean(axis=1) - points  # (N, 3): the neighbours' centroid, from the point
    shift -= np.sum(shift * normal, axis=1, keepdims=True) * normal
    return float(np.mean(np.linalg.norm(shift, axis=1) > EDGE_OFFSET * np.maximum(reach[:, -1], 1e-300)))


def without_edge(points: np.ndarray) -> str | None:
    """Why an open patch cannot cover the data (N, 3): they have no edge, they close
    (None if they have one)."""
    share = edge_share(points)
    return None if share >= CLOSED_SHARE else f"the data have no edge ({share:.1%} of points on one): they close"


def closed_round(tube: Parametrisation, points: np.ndarray) -> str | None:
    """Why an open patch cannot cover the data (N, 3) that ``tube`` (the cylinder's
    parametrisation) finds to be a tube: they go all the way round it, the widest gap in
    their angles ``angular_gap * 2 pi r`` under ``ROUND_GAP`` median spacings (None if they
    do not, or are no tube within ``TUBE_FIT`` of its radius). Such data have two rims
    (an annulus); an open patch over them either caps one rim or runs a seam through the
    data, which no other face meets: a mug's handle laid flat as a 5 x 5 sheet fitted its
    points within the tolerance but left the seam's edges free in the shell."""
    info = tube.info
    radius = float(info.get("radius", 0.0))
    if not info.get("model_rms", np.inf) < TUBE_FIT * radius:
        return None
    gap = float(info["angular_gap"]) * 2.0 * np.pi * radius / max(median_spacing(points), 1e-300)
    if gap >= ROUND_GAP:
        return None
    return f"the data close round a tube (its widest gap {gap:.1f} point spacings): an open patch would seam them"


def unsupported(par: Parametrisation, points: np.ndarray, topology: str) -> str | None:
    """Why the cloud cannot carry this closed topology's parametrisation (None if it can)."""
    info = par.info
    if topology in ("cylinder", "torus") and "axis" in info and on_axis(points, np.asarray(info["axis"]),
                                                                       info.get("centre")):
        return "the data reach its axis (an end closes there, no hole through it)"
    gaps = info.get("angular_gaps") or ([info["angular_gap"]] if "angular_gap" in info else [])
    for name, gap in zip(("around the axis", "around the tube"), gaps):
        if gap > MAX_GAP:
            return f"no data on {gap:.0%} of the turn {name}"
    if topology == "sphere":
        lo, hi = info["latitude_range"]
        if lo > POLE_REACH or hi < 1.0 - POLE_REACH:
            return "the data do not reach both poles"
    if topology == "cylinder" and info["method"] == "cylinder":  # a straight tube's ends (a bent one's are its section)
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
    layout = layout_for(topology, config.net_size, config.degrees, not config.align_edges)
    if oriented(Parametrisation(par.uv[sample], par.info), layout, points[sample], config).info.get("swapped"):
        par = par.swapped()
    if par.info["method"] == "intrinsic":
        uv, levels = coarse_to_fine(layout, points, par.uv, config.smoothing)
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
    point. If every candidate fails, the least error is kept all the same; if none is
    supported, the open patch.
    """
    scores, candidates, suspect, tube = {}, {}, {}, None
    for topology in ("cylinder", "sphere", "torus", "open"):  # the open patch last: the tube tells whether it closes
        if topology == "sphere" and config.net_size[1] < 3:
            scores[topology] = {"rejected": "net_size along v is below 3"}
            continue
        if topology == "open":  # judged on the data alone, before the costliest parametrisation
            reason = without_edge(points) or (closed_round(tube, points) if tube is not None else None)
            par = None if reason else parametrise_for(points, sample, topology, config)
        else:
            par = parametrise_for(points, sample, topology, config)
            reason = unsupported(par, points, topology)
            if topology == "cylinder" and reason is None:
                tube = par
        if reason is not None:
            scores[topology] = {"rejected": reason}
            continue
        layout = layout_for(topology, config.net_size, config.degrees, not config.align_edges)
        on_sample = Parametrisation(par.uv[sample], par.info)
        error = classical_error(layout, on_sample, points[sample], config)
        scores[topology] = {"classical_error_relative": float(error)}
        if topology == "open":
            scores[topology]["parametrisation"] = par.info["method"]
        warnings = check_fit(classical_surface(layout, on_sample, points[sample], config), points[sample]).warnings
        (suspect if warnings else candidates)[topology] = (error, par)
        if warnings:
            scores[topology]["rejected"] = SUSPECT + "; ".join(warnings)
    scores = {name: scores[name] for name in LAYOUTS if name in scores}
    pool = candidates or suspect
    if not pool:  # no topology carries the data: the open patch, the one without conditions on them
        return "open", parametrise_for(points, sample, "open", config), scores
    best = min(pool, key=lambda t: (pool[t][0], list(LAYOUTS).index(t)))
    return best, pool[best][1], scores


def topology_note(chosen: str, scores: dict) -> str:
    """The fit's note on ``topology: auto``: each candidate's classical error or why it
    was rejected. Where every candidate failed a self-check, the one kept (the least
    error) is said to be kept, with what its check found."""
    def entry(name: str, score: dict) -> str:
        if "rejected" not in score:
            return f"{name} {score['classical_error_relative']:.2e}"
        if name == chosen and "classical_error_relative" not in score:
            return f"{name} kept: no topology carries the data (its own: {score['rejected']})"
        if name == chosen:
            found = score["rejected"].removeprefix(SUSPECT)
            return (f"{name} {score['classical_error_relative']:.2e}, kept as the least error: "
                    f"every candidate failed a self-check (its own: {found})")
        return f"{name} rejected: {score['rejected']}"

    return f"topology auto: {chosen} (" + ", ".join(entry(name, s) for name, s in scores.items()) + ")"
