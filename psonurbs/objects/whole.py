"""A whole object fitted as several faces: regions -> a face each -> joined.

With ``patches: auto`` (or N) the cloud is split into regions
(:mod:`psonurbs.objects.regions`); a cloud that stays one region is fitted as one surface
with ``topology: auto``, as ``patches: 1`` would with it. Otherwise each region is fitted
by the single-surface pipeline with ``topology: auto`` (a cylinder's wall, a flat cap, a sphere's end each get
theirs) and the object's tolerance in cloud units, untrimmed; a region's points that lie
nearer a neighbouring region's surface move to it, a region fitted again at its net
where it lost one its fit strained for (:func:`moved_to_nearest`);
a region whose fit misses the tolerance is split where its normals turn (:func:`split_missed`), the split kept where its
faces join into a better shell (:func:`shell_rank`); the faces are then extended,
cut where they cross, the pieces the data hold kept and sewn
(:mod:`psonurbs.objects.join`). Every point is measured to its nearest kept face, trims
included: the object's rmse, max and 99th percentile. Without OpenCASCADE (the optional
``cadquery-ocp``) the faces are not joined: each is trimmed to its own data's footprint.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from psonurbs import progress
from psonurbs.fitting.pipeline import CURVE_HEADER, FitResult, fit_points
from psonurbs.fitting.search.tolerance import fit_again, measure
from psonurbs.formats.step import step_available
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.trim import Trim

from .join import face_distances
from .regions import CONTACT, MIN_SHARE, Regions, segment, split_where_facing

# nearest points that reach a region across a crease's band: the band is a neighbourhood wide
# on either side of the crease, where regions touch across it within CONTACT
ACROSS = 2 * CONTACT


@dataclass(frozen=True)
class Face:
    """One face of the object: its (extended) surface in cloud units, its loops, its
    topology, the region it was fitted to and the region fit's notes and info."""

    surface: NurbsSurface
    trim: Trim | None
    topology: str
    region: int
    metrics: dict
    info: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ObjectFit:
    """The faces, the object's metrics (over every point, to its nearest face), the
    shell's report (None when not joined), notes, the error curve of the faces' swarms
    together (:func:`object_curve`) and the OpenCASCADE shape for STEP (None if not joined)."""

    faces: tuple[Face, ...]
    metrics: dict
    shell: dict | None
    notes: list[str]
    curve: np.ndarray
    warnings: list[str] = field(default_factory=list)
    shape: object = field(default=None, repr=False)
    curve_header: list[str] = field(default_factory=lambda: list(CURVE_HEADER))


def object_curve(curves: list[np.ndarray], points: list[int]) -> np.ndarray:
    """The faces' error curves (each (I_k, 3): iteration, best, mean RMSE) as one (I, 3):
    at iteration i the RMSE over all their points, sqrt(sum n_k e_k(i)^2 / sum n_k), a
    shorter curve holding its last row."""
    length = max(len(c) for c in curves)
    held = [np.vstack([c, np.repeat(c[-1:], length - len(c), axis=0)]) for c in curves]
    n = np.asarray(points, float)[:, None]
    best, mean = (np.sqrt(np.sum(n * np.array([h[:, k] for h in held]) ** 2, axis=0) / n.sum()) for k in (1, 2))
    return np.column_stack([np.arange(1, length + 1), best, mean])


def face_config(config, diagonal: float, joined: bool):
    """A region's config: topology auto, one patch, the object's tolerance in cloud units;
    when the faces are joined, untrimmed (the join trims them) and with free edges (the
    first parameters' smooth map, which extends smoothly past the data)."""
    d = config.to_dict()
    d.update(topology="auto", patches=1)
    if config.tolerance_rel is not None:
        d.update(tolerance=config.tolerance_rel * diagonal, tolerance_rel=None)
    if joined:
        d.update(trim=False, align_edges=False)
    if not config.net_size_given:
        d.pop("net_size", None)
    from psonurbs.config import config_from_dict

    return config_from_dict({k: v for k, v in d.items() if v is not None}, source="a face's config")


def plural(count: int, noun: str) -> str:
    """'1 point', '3 points'."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def missed_by(result: FitResult) -> float:
    """How far a region's fit is from its tolerance: achieved / tolerance (0 without one)."""
    tolerance = result.info.get("tolerance")
    return tolerance["achieved"] / tolerance["value"] if tolerance else 0.0


def moved_to_nearest(points: np.ndarray, members: list[np.ndarray], fits: list[FitResult], tolerance: float,
                     fit_region: Callable[[np.ndarray, FitResult], FitResult]) -> tuple[int, int]:
    """Among the regions whose fits meet the tolerance, the points that lie nearer a
    neighbouring region's surface than their own region's moved to that region, in place
    in ``members``; a region that lost one its surface passes farther than ``tolerance``
    from is fitted again (in ``fits``, by ``fit_region(member, its fit)``). A surface
    that misses the tolerance does not say which face a point lies on (the region is
    split next, :func:`split_missed`, and its parts fitted anew). A region neighbours a point
    when one of the point's ``ACROSS`` nearest points is the region's (a surface extends
    past its region untrimmed, and away from its data it is nobody's face). No region is
    left with fewer than ``MIN_SHARE`` of the points (a region that small is given up in
    :mod:`psonurbs.objects.regions`): its points stay. Returns (points moved, regions
    fitted again). Region growing takes a crease's first points by their normals, which lean
    halfway over the crease: four of a wall's points just below a narrow top joined the
    top's region, its fit bent to them (one 0.0086 off it, three tolerances), its
    extension's corner folded back over its data, and the cut that closes the shell
    missed it. A region that gained points, or lost only points its surface holds, is
    not fitted again (its surface holds them already)."""
    where = np.concatenate(members)
    owner = np.repeat(np.arange(len(members)), [len(m) for m in members])
    met = np.array([missed_by(f) <= 1.0 for f in fits])
    judged = np.flatnonzero(met[owner])  # only the points of regions that meet may move, only to those
    if judged.size == 0:
        return 0, 0
    distances = np.full((len(fits), len(where)), np.inf)
    distances[np.ix_(met, judged)] = face_distances([(fits[r].surface, None) for r in np.flatnonzero(met)],
                                                    points[where[judged]])
    column = np.arange(len(where))
    nearest = np.argmin(distances, axis=0)
    moved = (nearest != owner) & met[owner]
    if moved.any():
        label = np.full(len(points), -1)
        label[where] = owner
        taken = np.flatnonzero(moved)
        _, around = cKDTree(points).query(points[where[taken]], min(ACROSS, len(points)))
        moved[taken] = (label[around] == nearest[taken, None]).any(axis=1)
    kept = np.bincount(owner[~moved], minlength=len(members))
    for r in np.flatnonzero(kept < MIN_SHARE * len(points)):  # a region is not emptied: as small, it is given up
        moved[owner == r] = False
    strained = np.unique(owner[moved & (distances[owner, column] > tolerance)])
    changed = np.unique(np.concatenate([owner[moved], nearest[moved]]))
    owner = np.where(moved, nearest, owner)
    for r in changed:
        members[r] = np.sort(where[owner == r])
    for r in strained:
        fits[r] = fit_region(members[r], fits[r])
    return int(moved.sum()), len(strained)


def split_missed(points: np.ndarray, regions: Regions, members: list[np.ndarray], fits: list[FitResult],
                 fit_region: Callable[[np.ndarray], FitResult]) -> int:
    """Regions whose fit misses the tolerance split (:func:`split_where_facing`) and their
    parts fitted, in place in ``members`` and ``fits`` (the first part where the region
    was, the others appended, themselves split again if they miss); a split is kept when
    every part's fit comes nearer the tolerance than the region's. At most as many splits
    are tried as there were regions, so the time stays bounded. Returns the splits kept."""
    least = int(np.ceil(MIN_SHARE * len(points)))
    tries, kept, r = len(members), 0, 0
    while r < len(members) and tries > 0:
        if missed_by(fits[r]) <= 1.0:
            r += 1
            continue
        parts = split_where_facing(points[members[r]], regions.normals[members[r]], least)
        if parts.max() <= 0:
            r += 1
            continue
        tries -= 1
        pieces = [members[r][parts == p] for p in range(int(parts.max()) + 1)]
        part_fits = [fit_region(piece) for piece in pieces]
        if max(missed_by(f) for f in part_fits) >= missed_by(fits[r]):
            r += 1
            continue
        kept += 1
        members[r], fits[r] = pieces[0], part_fits[0]
        members.extend(pieces[1:])
        fits.extend(part_fits[1:])
    return kept


def joined_faces(fits: list[FitResult], members: list[np.ndarray], points: np.ndarray, tolerance: float,
                 spacing: float):
    """The faces of ``fits`` (fitted to ``points[members[k]]``) cut and sewn
    (:func:`psonurbs.objects.join.join`): (Joined, None), or (None, why) when
    OpenCASCADE fails (its failures are many and rare: the faces then stay apart)."""
    from .join import join

    try:
        return join([f.surface for f in fits], points, tolerance, spacing, [points[m] for m in members]), None
    except Exception as e:
        return None, f"{type(e).__name__}: {e}"


def shell_rank(done, name: str) -> tuple[bool, float]:
    """How good a join is, larger better: a closed shell first, then the lower tolerance
    measure ``name`` (p99, max or rms) of the points' distances to their nearest face
    (no join: the worst)."""
    if done is None or not done.faces:
        return (False, -np.inf)
    return (bool(done.closed), -measure(done.distances.min(axis=0), name))


def faces_of(region: int, faces) -> str:
    """How a region's fit is named to the user: by its faces' places in the JSON's
    ``surfaces`` (a cut can keep several pieces of one region, or none)."""
    places = [str(k) for k, face in enumerate(faces) if face.region == region]
    if not places:
        return f"region {region} (no face kept)"
    return ("face " if len(places) == 1 else "faces ") + ", ".join(places)


def fit_object(points: np.ndarray, config, on_iteration: Callable | None = None,
               fit: Callable = fit_points) -> ObjectFit | FitResult:
    """The object's faces; a cloud that is one region is one face, fitted as one surface
    with ``topology: auto`` (its :class:`FitResult`)."""
    points = np.asarray(points, float)
    progress.stage("regions grown on the normals, parted at creases")
    regions = segment(points, None if config.patches == "auto" else int(config.patches))
    if regions.count <= 1:
        return fit(points, config.with_overrides(source="patches: auto", topology="auto", patches=1),
                   on_iteration=on_iteration)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    joined = step_available()
    region_config = face_config(config, diagonal, joined)
    members = [regions.members(r) for r in range(regions.count)]
    parts = itertools.count(1)
    searched = region_config.has_tolerance  # the search reports each net it fits; else one fit's swarm

    def fitted(member: np.ndarray, name: str) -> FitResult:
        with progress.within(f"{name} ({len(member)} points)", None if searched else region_config.swarm.iterations):
            return fit(points[member], region_config, on_iteration=on_iteration)

    fits: list[FitResult] = [fitted(m, f"region {r + 1} of {regions.count}") for r, m in enumerate(members)]
    tolerance = region_config.tolerance if region_config.has_tolerance else 1e-3 * diagonal

    def fitted_again(member: np.ndarray, previous: FitResult) -> FitResult:
        with progress.within(f"a region fitted again without another face's points ({len(member)} points)",
                             None if searched else region_config.swarm.iterations):
            if searched:  # the net its search chose, not a new search
                return fit_again(points[member], region_config, previous, fit, on_iteration)
            return fit(points[member], region_config.with_overrides(source="a region fitted again",
                                                                    topology=previous.topology),
                       on_iteration=on_iteration)

    moved, again = moved_to_nearest(points, members, fits, tolerance, fitted_again)
    whole = (list(members), list(fits))
    splits = split_missed(points, regions, members, fits,
                          lambda m: fitted(m, f"part {next(parts)} of a region split where it missed the tolerance"))
    shell, shape, distances, done, joined_notes = None, None, None, None, []
    if joined:
        progress.stage(f"{len(fits)} faces cut and sewn")
        done, reason = joined_faces(fits, members, points, tolerance, regions.spacing)
        if splits:
            progress.stage(f"the unsplit regions' {len(whole[1])} faces cut and sewn, to compare")
            unsplit, unsplit_reason = joined_faces(whole[1], whole[0], points, tolerance, regions.spacing)
            if shell_rank(unsplit, config.tolerance_measure) > shell_rank(done, config.tolerance_measure):
                (members, fits), done, reason, splits = whole, unsplit, unsplit_reason, 0
                joined_notes.append("a split region's faces joined worse than the whole region's: kept whole")
    unclaimed = len(points) - sum(len(m) for m in members)
    notes = [f"{regions.count} regions (creases part them)"
             + (f", {plural(moved, 'point')} moved to a neighbouring region whose face lies nearer "
                f"({plural(again, 'region')} fitted again)" if moved else "")
             + (f", {splits} split where one surface missed the tolerance" if splits else "")
             + f"; {unclaimed} points in creases' bands or in regions too small, measured to their nearest face"]
    notes += joined_notes
    pieces = [(f.surface, f.trim, f.topology, r) for r, f in enumerate(fits)]
    if joined:
        if done is not None and done.faces:
            pieces = [(face.surface, face.trim, fits[face.region].topology, face.region) for face in done.faces]
            shell, shape, distances = done.to_dict(), done.shape, done.distances
            notes.append(f"{len(pieces)} faces sewn into a {'closed' if done.closed else 'open'} shell"
                         + (f" (a solid of volume {done.volume:.6g})" if done.closed
                            else f", {done.free_edges} free edges"))
        else:
            notes.append("faces not joined: OpenCASCADE could not cut them "
                         f"({reason if done is None else 'no piece held by the data'}); each is untrimmed")
    else:
        notes.append("faces not joined: cutting and sewing them needs the optional package cadquery-ocp "
                     "(pip install 'psonurbs[cad]'); each is trimmed to its own data")
    if distances is None:
        distances = face_distances([(s, t) for s, t, _, _ in pieces], points)
    nearest = np.argmin(distances, axis=0)
    distances = distances[nearest, np.arange(len(points))]  # each point's to its nearest face
    faces = []
    for k, (surface, trim, topology, region) in enumerate(pieces):
        d = distances[nearest == k]
        faces.append(Face(surface, trim, topology, region,
                          {"points": int(len(d)), "rmse": float(np.sqrt(np.mean(d ** 2))) if len(d) else 0.0,
                           "region_points": int(len(members[region])),
                           "control_points": int(fits[region].metrics["control_points"])},
                          {"region_fit": fits[region].info, "notes": fits[region].notes}))
    rmse = float(np.sqrt(np.mean(distances ** 2)))
    metrics = {"rmse": rmse, "max_error": float(distances.max()), "p99": float(np.percentile(distances, 99)),
               "rmse_relative": rmse / diagonal, "max_error_relative": float(distances.max()) / diagonal,
               "bbox_diagonal": diagonal, "points": int(len(points)), "faces": len(faces),
               "control_points": int(sum(f.metrics["control_points"] for f in faces))}
    if region_config.has_tolerance:
        metrics["tolerance"] = {"value": region_config.tolerance, "measure": config.tolerance_measure,
                                "met": measure(distances, config.tolerance_measure) <= region_config.tolerance}
    curve = object_curve([f.curve for f in fits], [f.metrics["points"] for f in fits])
    warnings = [f"{faces_of(r, faces)}: {w}" for r, f in enumerate(fits) for w in f.warnings]
    return ObjectFit(tuple(faces), metrics, shell, notes, curve, warnings, shape)
