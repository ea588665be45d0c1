"""Fit to a tolerance: the smallest net whose fit meets it, searched.

With ``tolerance`` (cloud units) or ``tolerance_rel`` (a fraction of the bounding-box
diagonal) the net is not given but searched. A share :data:`HOLD_OUT` of the points,
drawn once from the config's seed, is held out for the whole search; every net tried is
a full fit of that size on the other points, judged by the tolerance's measure of the
distances of the held-out points to it (p99, max or rms; a point whose foot lies on the
edge of the domain, beyond the points the fit saw, is left out of the judgement,
:func:`inside`). Two searches, each over nets of one kind of fit (:class:`NetSearch`):

    uniform  the classical fit (uniform knots, one particle): from the smallest net the
             orders allow (an open or closed direction: its order; a sphere's v at
             least 3), *grow* by x GROWTH and at least +1, in the direction whose knot
             spans hold the excess over the tolerance unevenly (the error of a ridge
             sits in a few spans across it), in both when neither does (a direction
             grown alone whose error falls, but slower than the square root of the
             control points it adds, is not what limits the fit: the other is grown
             too and the faster fall per control point kept), until a net meets the
             tolerance; *bisect* back between the last net that failed and the first
             that met; *shrink* one direction at a time (the larger first), bisecting
             the fewest control points along it that still meet (growing both
             directions overshoots the one that needed less)
    swarm    with a swarm configured: from the classical net, shrink again with the
             swarm placing the knots at every size tried, stepping down 1, 2, 4, ...
             from it before bisecting (its net is usually a row or two below the
             classical one: fewer of the swarm's fits). Below the classical net is
             where the places of the knots decide; the classical net stays the
             fallback, so the swarm never costs control points
    rational with a swarm configured, where no uniform net meets and their error
             stalls above the noise (uniform polynomial spans cannot follow the
             shape: a rounded rim's quarter circle, flat on one side, turning within
             one span), unless the uniform net of the least error meets on every
             point (at the margin a held-out p99 is a few percent off either way:
             that net is delivered): grow and shrink with the swarm placing the knots
             and choosing the weights too, the whole NURBS space, from that net of the
             least error: below it the uniform nets have missed already, and a rational
             net that meets there is found by the shrinking (errors taken to fall as a
             net grows, as the shrinking takes them), without the rational fits on the
             way up (each costs one and a half to twice a uniform one)

and each stops at the largest net allowed (``net_size`` when given, else the budget of
:mod:`psonurbs.fitting.budget`), when no growth of the best net so far gains
(:data:`PLATEAU`), or when the error is at what the noise allows. The swarm of these
fits searches the knots and the smoothing, not the weights (the rational search's
does): the weights' one dimension per control point would cost the knot search its precision (the public step_bump,
bicubic, tolerance 3e-4 of the diagonal: the p99 of fits at 10 x 10, 11 x 11 and
12 x 12 is 0.87, 1.00, 1.23 times it with the weights searched, 0.95, 0.92, 0.50
without: the larger net is worse with them). The refinement still frees the weights
where they pay (a conic).

The noise is the local outlier test's scale sigma (:mod:`psonurbs.fitting.prepare.outliers`:
robust residuals of local quadric fits); Gaussian distances along the normal have a p99
of about 2.58 sigma, an rms of sigma and a max of about sigma sqrt(2 ln N). The chosen
net is then fitted as usual on every point (a swarm's net that misses there gives way to
the classical one), and ``achieved`` is the measure of that delivered fit over all
points; ``met`` says whether it meets the tolerance. A net that met on the held-out
points and misses on all by a few percent does not meet: the search goes on from it
(:func:`searched`).
Without a net meeting it, the net
of the least held-out error is delivered (the smaller on a tie): a larger net is never
kept when a smaller one is as good.

The classical search is this search with ``--particles 1 --iterations 1``: the uniform
search alone.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from psonurbs import progress
from psonurbs.config import FIELDS, SPHERE_MIN_V
from psonurbs.errors import PsonurbsError
from psonurbs.fitting.budget import check_budget
from psonurbs.fitting.parameters.topology import layout_for, topology_note
from psonurbs.fitting.prepare.organise import organise
from psonurbs.fitting.prepare.outliers import MIN_POINTS, local_outliers
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.projection import closest_parameters

__all__ = ["HOLD_OUT", "GROWTH", "growths", "measure", "noise_allows", "smallest_net", "fit_to_tolerance",
           "fit_again", "net_config", "tolerance_sentence"]

HOLD_OUT = 0.2  # share of the points the search's fits do not see (drawn once, from the seed)
MIN_HELD_OUT = 50  # a smaller cloud is judged on the points it was fitted on
GROWTH = 1.3  # a net grows by this factor (and at least one control point) per direction
UNEVEN = 1.5  # a direction is grown alone when its spans' excess is this much more concentrated
WEAK = 0.5  # a direction grown alone whose error fell at a lower rate than this gives the other a try
PLATEAU = 0.97  # a grown net gains when its error is below this share of the best so far
GAUSSIAN_P99 = 2.576  # the 99th percentile of |N(0, 1)|
EDGE = 1e-9  # a foot parameter this close to 0 or 1 is on the edge of the domain
NOISE_MARGIN = 1.05  # an error within this factor of what the noise allows cannot fall further
RESEARCHES = 2  # times the search goes on past a net that met on the held-out points and missed on all
RESEARCH_MARGIN = 1.05  # ... by at most this factor: a miss at the margin, not a search gone wrong
KNOTS = {  # how a progress display names the kinds of fit
    "uniform": "uniform knots", "swarm": "knots by the swarm", "rational": "knots and weights by the swarm"}


def measure(distances: np.ndarray, name: str) -> float:
    """The tolerance's measure of distances (n,): their 99th percentile, max or rms."""
    d = np.asarray(distances, float)
    if name == "p99":
        return float(np.percentile(d, 99))
    if name == "max":
        return float(d.max())
    return float(np.sqrt(np.mean(d ** 2)))


def noise_allows(sigma: float, name: str, n: int) -> float:
    """The least value of the measure that Gaussian noise of scale ``sigma`` allows on n points."""
    factor = {"p99": GAUSSIAN_P99, "rms": 1.0}.get(name, math.sqrt(2 * math.log(max(n, 2))))
    return sigma * factor


def smallest_net(topology: str, orders: tuple[int, int]) -> tuple[int, int]:
    """The smallest net the orders allow: the order in each direction (no inner knots when
    open, one span per control point when closed), and a sphere's v at least 3."""
    nu, nv = orders
    return (nu, max(nv, SPHERE_MIN_V) if topology == "sphere" else nv)


@dataclass(frozen=True)
class Step:
    """One net the search fitted: its held-out error (cloud units) and where it lies."""

    net_size: tuple[int, int]
    achieved: float
    seconds: float
    uneven: tuple[float, float]  # concentration of the excess over the knot spans along u, v
    knots: str = "uniform"  # uniform: the classical fit; swarm: knots placed by the swarm; rational: and weights

    def to_dict(self) -> dict:
        return {"net_size": list(self.net_size), "achieved": self.achieved, "seconds": round(self.seconds, 3),
                "knots": self.knots}


def span_concentration(uv: np.ndarray, excess: np.ndarray, surface: NurbsSurface) -> tuple[float, float]:
    """Per direction, how unevenly the excess (n,) over the tolerance of the points at
    parameters uv (n, 2) falls into the surface's knot spans: the largest span's share times
    the number of spans (1: even; the number of spans: all in one span)."""
    total = float(excess.sum())
    out = []
    for column, knots in enumerate((surface.knots_u, surface.knots_v)):
        breaks = np.unique(knots)
        inner = breaks[1:-1]
        if total <= 0 or len(inner) == 0:
            out.append(1.0)
            continue
        span = np.searchsorted(inner, uv[:, column], side="right")
        shares = np.bincount(span, excess, minlength=len(inner) + 1) / total
        out.append(float(shares.max() * len(shares)))
    return tuple(out)


def grown_count(n: int, most: int) -> int:
    """The control points along a direction after one growth: x GROWTH, at least +1, at most ``most``."""
    return min(max(n + 1, math.ceil(n * GROWTH)), most)


def growths(size: tuple[int, int], uneven: tuple[float, float], largest: tuple[int, int]) -> list[tuple[int, int]]:
    """The nets grown from ``size``, the most promising first: the direction whose excess
    is concentrated (:func:`span_concentration`) alone, else both; then the others. Each
    grown direction by x GROWTH and at least +1, within ``largest``."""
    u, v = uneven
    first = (True, False) if u > UNEVEN * v else (False, True) if v > UNEVEN * u else (True, True)
    order = [first] + [d for d in ((True, True), (True, False), (False, True)) if d != first]
    out = []
    for directions in order:
        new = tuple(grown_count(n, most) if grow else n for n, most, grow in zip(size, largest, directions))
        if new != size and new not in out:
            out.append(new)
    return out


def _largest_net(config, n_points: int) -> tuple[int, int]:
    """The largest net the search may use: the config's net_size when given, else as large
    as the budget allows for n points (:func:`psonurbs.fitting.budget.check_budget`)."""
    if config.net_size != "auto":
        return tuple(config.net_size)
    most = int(FIELDS["net_size"].most)
    lo, hi = max(config.orders), most  # the largest square side the budget allows
    while lo < hi:
        mid = (lo + hi + 1) // 2
        try:
            check_budget(dataclasses.replace(config, net_size=(mid, mid), tolerance=None, tolerance_rel=None),
                         n_points)
            lo = mid
        except PsonurbsError:
            hi = mid - 1
    return (lo, lo)


def _noise(points: np.ndarray, orders: tuple[int, int]) -> float:
    """The local noise scale sigma of the cloud, in its units."""
    cloud = organise(points, tuple(orders))
    return float(local_outliers(cloud.points).noise * cloud.frame.diagonal)


def _held_distances(surface: NurbsSurface, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Foot parameters (n, 2) and distances (n,) of points (n, 3) on a surface in the same
    units, computed in a frame of diagonal 1 (the projection's own scale)."""
    centre = points.mean(axis=0)
    scale = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
    local = NurbsSurface(surface.degree_u, surface.degree_v, surface.knots_u, surface.knots_v,
                         (surface.control_points - centre) / scale, surface.weights,
                         surface.closed_u, surface.closed_v)
    uv, dist = closest_parameters(local, (points - centre) / scale)
    return uv, dist * scale


def inside(uv: np.ndarray, bounded: tuple[bool, bool]) -> np.ndarray:
    """(n,) bool: the foot parameters uv (n, 2) not on an edge of a bounded direction. A
    held-out point whose foot is on the edge lies beyond the points the fit saw (its
    domain ends at theirs): its distance is the gap to their footprint, not the fit's error."""
    keep = np.ones(len(uv), bool)
    for column, edge in enumerate(bounded):
        if edge:
            keep &= (uv[:, column] > EDGE) & (uv[:, column] < 1 - EDGE)
    return keep if keep.any() else np.ones(len(uv), bool)


def tolerance_sentence(tolerance: dict) -> str:
    """The summary's words for ``fit.tolerance``: 'tolerance 3.0e-04 (p99) met: 2.7e-04 with
    9x7 control points', or 'not met: best ... (noise ...)'. A noise of 0 is one the local
    test did not judge (a cloud of fewer than its ``MIN_POINTS``): said so, not printed as 0."""
    nu, nv = tolerance["net_size"]
    head = f"tolerance {tolerance['value']:.1e} ({tolerance['measure']})"
    if tolerance["met"]:
        return f"{head} met: {tolerance['achieved']:.1e} with {nu}x{nv} control points"
    noise = f"noise {tolerance['noise']:.1e}" if tolerance["noise"] > 0 else \
        f"noise not judged: fewer than {MIN_POINTS} points"
    return f"{head} not met: best {tolerance['achieved']:.1e} with {nu}x{nv} control points ({noise})"


class NetSearch:
    """The nets one kind of fit tried (:class:`Step` by size): grown from ``base`` until
    one meets the tolerance ``value``, bisected back, and shrunk per direction (the module
    docstring). ``evaluate(size)`` fits a net and judges it; ``floor`` is the least error
    the noise allows (the growth stops there)."""

    def __init__(self, evaluate: Callable[[tuple[int, int]], Step], base: tuple[int, int],
                 largest: tuple[int, int], value: float, floor: float, descend: bool = False):
        self.evaluate, self.base, self.largest = evaluate, base, largest
        self.value, self.floor, self.descend = value, floor, descend
        self.steps: dict[tuple[int, int], Step] = {}

    def step(self, size: tuple[int, int]) -> Step:
        if size not in self.steps:
            self.steps[size] = self.evaluate(size)
        return self.steps[size]

    def meets(self, size: tuple[int, int]) -> bool:
        return self.step(size).achieved <= self.value

    def grown(self, start: tuple[int, int] | None = None) -> tuple[int, int] | None:
        """Grow from ``start`` (the base by default), then bisect: the smallest meeting net
        on the way, or None (none met)."""
        best, meeting = self.step(start or self.base), None
        while best.achieved > self.value and best.achieved > self.floor:
            untried = [g for g in growths(best.net_size, best.uneven, self.largest) if g not in self.steps]
            if not untried:
                break
            step = self.step(untried[0])
            if step.achieved > self.value and self.weak(best, step):
                other = self.other_direction(best, step)
                if other is not None and (other.achieved <= self.value or rate(best, other) > rate(best, step)):
                    step = other
            if step.achieved <= self.value:
                meeting = step.net_size
                break
            if step.achieved < PLATEAU * best.achieved:
                best = step
        if best.achieved <= self.value:
            return best.net_size
        if meeting is None:
            return None
        low, high = best.net_size, meeting
        while True:
            middle = tuple((a + b) // 2 for a, b in zip(low, high))
            if middle == low or middle in self.steps:
                return high
            if self.meets(middle):
                high = middle
            else:
                low = middle

    @staticmethod
    def weak(best: Step, grown: Step) -> bool:
        """A net grown along one direction alone whose error fell, by more than the
        plateau, but slower than the square root of the control points it added
        (:func:`rate` below WEAK): that direction is not what limits the fit, yet the
        plateau rule alone would go on growing it. Along the direction that does, the
        error falls at least as the spans' length (across a kink, the least smooth shape
        a span holds; a smooth shape's as its power the order). An error that did not
        fall is the plateau rule's: the next growth is tried from the same net."""
        alone = sum(a != b for a, b in zip(best.net_size, grown.net_size)) == 1
        return alone and grown.achieved < PLATEAU * best.achieved and rate(best, grown) < WEAK

    def other_direction(self, best: Step, grown: Step) -> Step | None:
        """The net grown from ``best`` along the direction ``grown`` left as it was (by x
        GROWTH and at least +1, within the largest net), fitted; None when it cannot grow."""
        direction = 0 if grown.net_size[0] == best.net_size[0] else 1
        size = tuple(grown_count(n, most) if k == direction else n
                     for k, (n, most) in enumerate(zip(best.net_size, self.largest)))
        return None if size == best.net_size else self.step(size)

    def shrunk(self, size: tuple[int, int]) -> tuple[int, int]:
        """From a net that meets, the fewest control points along each direction in turn
        (the larger first) that still meet with the other as it is then."""
        for direction in (0, 1) if size[0] >= size[1] else (1, 0):
            size = self.shrink(size, direction)
        return size

    def shrink(self, size: tuple[int, int], direction: int) -> tuple[int, int]:
        """Bisect the fewest control points along ``direction`` that meet with the other
        direction as in ``size`` (taken to meet). Errors are taken to fall as a net grows
        in either direction, so a failing net bounds every net it holds. With ``descend`` the
        nets 1, 2, 4, ... below ``size`` are tried first, down to the first that fails, and the
        bisection runs between it and the last that met: the same net when errors fall with
        the net, in fewer fits where it lies near ``size``."""
        other = 1 - direction
        fails = [s[direction] for s, step in self.steps.items()
                 if step.achieved > self.value and s[other] >= size[other] and s[direction] < size[direction]]
        low, high = max(fails, default=self.base[direction] - 1), size[direction]

        def meets_at(n: int) -> bool:
            return self.meets(tuple(n if k == direction else size[k] for k in (0, 1)))

        down = 1
        while self.descend and high - low > 1:
            middle = max(high - down, low + 1)
            if not meets_at(middle):
                low = middle
                break
            high, down = middle, 2 * down
        while high - low > 1:
            middle = (low + high) // 2
            if meets_at(middle):
                high = middle
            else:
                low = middle
        return tuple(high if k == direction else size[k] for k in (0, 1))


def rate(best: Step, grown: Step) -> float:
    """What a grown net bought: log(error fall) / log(control points added), the
    exponent of the error's fall with the net (negative when the error rose)."""
    return math.log(best.achieved / grown.achieved) / math.log(math.prod(grown.net_size) / math.prod(best.net_size))


def chosen_step(steps: list[Step], value: float) -> Step:
    """The fewest control points among the steps that meet ``value`` (the smaller error on
    a tie); without one, the least error (the smaller net on a tie): a larger net is never
    kept when a smaller one is as good."""
    met = [s for s in steps if s.achieved <= value]
    if met:
        return min(met, key=lambda s: (s.net_size[0] * s.net_size[1], s.achieved))
    return min(steps, key=lambda s: (s.achieved, s.net_size[0] * s.net_size[1]))


def searched(uniform: NetSearch, placed: NetSearch | None, rational: NetSearch | None, deliver: Callable,
             value: float):
    """The nets searched and the chosen one delivered: (step, result, achieved, steps).

    The uniform search first, then the placed knots' below its net (``placed``), or,
    where no uniform net meets, their error stalls above the noise and the least-error
    one misses on every point too, the rational search from that least-error net
    (``rational``; both None without a swarm); each step is delivered once; the fewest
    control points that met (:func:`chosen_step`) are fitted on every point,
    ``deliver(step) -> (result, achieved)``. Placed knots that miss there give way to
    the uniform net that met. A uniform or rational net that met on the held-out points
    and misses on all by at most ``RESEARCH_MARGIN`` (at the margin, a fifth of the points
    puts a p99 a few percent off) does not meet: its step takes the all-points figure and
    its search goes on from it, ``RESEARCHES`` times at most (a search repeated costs its
    time again: only a marginal miss is worth it)."""
    searches = {"uniform": uniform, "swarm": placed, "rational": rational}
    starts: dict[str, tuple[int, int] | None] = {"uniform": None, "rational": None}
    delivered: dict[tuple[str, tuple[int, int]], tuple] = {}  # by kind and net: a step re-judged is the same fit

    def delivery(step: Step) -> tuple:
        key = (step.knots, step.net_size)
        if key not in delivered:
            delivered[key] = deliver(step)
        return delivered[key]

    for attempt in range(RESEARCHES + 1):
        meeting = uniform.grown(starts["uniform"])
        if meeting is not None:
            meeting = uniform.shrunk(meeting)
            if placed is not None:  # below the classical net, where the knots' places decide
                placed.shrunk(meeting)
        elif rational is not None:
            nearest = chosen_step(list(uniform.steps.values()), value)
            if nearest.achieved > uniform.floor and delivery(nearest)[1] > value:
                found = rational.grown(starts["rational"] or nearest.net_size)
                if found is not None:
                    rational.shrunk(found)
        steps = [step for search in searches.values() if search is not None for step in search.steps.values()]
        best = chosen_step(steps, value)
        result, achieved = delivery(best)
        if achieved > value and best.knots == "swarm":  # on every point the placed knots miss: the uniform net
            best = uniform.steps[meeting]
            result, achieved = delivery(best)
        if achieved <= value or achieved > RESEARCH_MARGIN * value or best.achieved > value \
                or attempt == RESEARCHES:
            return best, result, achieved, steps
        searches[best.knots].steps[best.net_size] = dataclasses.replace(best, achieved=achieved)
        starts[best.knots] = best.net_size


def net_config(config, size: tuple[int, int], knots: str, topology: str):
    """The config of one net of the search: ``size`` control points, no tolerance, the
    given topology; the swarm off for uniform knots (one particle, one iteration)."""
    swarm = config.swarm if knots != "uniform" else dataclasses.replace(config.swarm, particles=1, iterations=1)
    return dataclasses.replace(config, net_size=size, tolerance=None, tolerance_rel=None, topology=topology,
                               swarm=swarm)


def fit_again(points: np.ndarray, config, previous, fit: Callable, on_iteration=None):
    """``previous`` (a fit to ``config``'s tolerance) fitted once more to ``points`` at the
    net, kind of knots and topology it delivered, no search: a fit whose points changed a
    little (a few moved to another face) keeps the net the search chose for them. Its
    ``info["tolerance"]`` is the previous one's, the figure measured on ``points``."""
    tolerance = previous.info["tolerance"]
    net = net_config(config, tuple(tolerance["net_size"]), tolerance["knots"], previous.topology)
    progress.stage(f"the net {tolerance['net_size'][0]}x{tolerance['net_size'][1]}, {KNOTS[tolerance['knots']]}, "
                   "on the points kept", net.swarm.iterations)
    result = fit(np.asarray(points, float), net, on_iteration=on_iteration,
                 swarm_weights=tolerance["knots"] == "rational")
    achieved = measure(result.distances, tolerance["measure"])
    return reported(result, dict(tolerance, achieved=achieved, met=bool(achieved <= tolerance["value"])),
                    previous.topology, previous.info.get("topology_scores"))


def fit_to_tolerance(points: np.ndarray, config, fit: Callable, on_iteration=None):
    """The fit of the smallest net meeting the config's tolerance (see the module
    docstring). ``fit(points, config, on_iteration)`` is the fit of one net
    (:func:`psonurbs.fitting.pipeline.fit_points`); it returns its FitResult, with
    ``info["tolerance"]`` and the sentence of :func:`tolerance_sentence` first in its notes."""
    points = np.asarray(points, float)
    n = len(points)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    value = float(config.tolerance) if config.tolerance is not None else float(config.tolerance_rel) * diagonal
    name = config.tolerance_measure
    rng = np.random.default_rng(config.swarm.seed)
    held = np.zeros(n, bool)
    if n * HOLD_OUT >= MIN_HELD_OUT:
        held[rng.choice(n, int(round(n * HOLD_OUT)), replace=False)] = True
    train = points[~held] if held.any() else points
    judged = points[held] if held.any() else points
    sigma = _noise(points, config.orders)
    floor = noise_allows(sigma, name, len(judged))
    topology = config.topology
    scores = None  # auto's scores, from the fit that chose the topology
    largest = _largest_net(config, len(train))

    swarm = config.strategy == "hybrid" and config.swarm.particles * config.swarm.iterations > 1

    def sized(size: tuple[int, int], knots: str):
        return net_config(config, size, knots, topology)

    tried = 0

    def one_net(size: tuple[int, int], knots: str) -> Step:
        nonlocal topology, scores, tried
        start, net, tried = time.perf_counter(), sized(size, knots), tried + 1
        progress.stage(f"searched net {tried}: {size[0]}x{size[1]}, {KNOTS[knots]}", net.swarm.iterations)
        result = fit(train, net, on_iteration=on_iteration, swarm_weights=knots == "rational")
        topology = result.topology  # auto: chosen once, at the first net
        scores = result.info.get("topology_scores", scores)
        uv, dist = _held_distances(result.surface, judged)
        covered = inside(uv, layout_for(topology, size, config.degrees).bounded)
        uv, dist = uv[covered], dist[covered]
        return Step(size, measure(dist, name), time.perf_counter() - start,
                    span_concentration(uv, np.maximum(dist - value, 0.0), result.surface), knots)

    base = tuple(min(s, m) for s, m in zip(smallest_net(topology, config.orders), largest))
    uniform = NetSearch(lambda size: one_net(size, "uniform"), base, largest, value, NOISE_MARGIN * floor)
    placed = NetSearch(lambda size: one_net(size, "swarm"), base, largest, value, NOISE_MARGIN * floor, True) \
        if swarm else None
    rational = NetSearch(lambda size: one_net(size, "rational"), base, largest, value, NOISE_MARGIN * floor) \
        if swarm else None

    def deliver(step: Step):
        net = sized(step.net_size, step.knots)
        progress.stage(f"the chosen net {step.net_size[0]}x{step.net_size[1]}, {KNOTS[step.knots]}, on every point",
                       net.swarm.iterations)
        result = fit(points, net, on_iteration=on_iteration, swarm_weights=step.knots == "rational")
        return result, measure(result.distances, name)

    best, result, achieved, steps = searched(uniform, placed, rational, deliver, value)
    tolerance = {"value": value, "relative": value / diagonal if diagonal > 0 else None, "measure": name,
                 "achieved": achieved, "met": bool(achieved <= value), "net_size": list(best.net_size),
                 "knots": best.knots, "noise": sigma, "searched": [s.to_dict() for s in steps]}
    return reported(result, tolerance, topology, scores)


def reported(result, tolerance: dict, topology: str, scores: dict | None):
    """``result`` with its ``info["tolerance"]`` and, first in its notes, the tolerance's
    sentence and (with ``topology: auto``'s ``scores``) the topology's choice: the
    delivered fit was told its topology, the choice was the first net's."""
    result.info["tolerance"] = tolerance
    if scores is not None:
        result.info["topology_scores"] = scores
        result.notes.insert(0, topology_note(topology, scores))
    result.notes.insert(0, tolerance_sentence(tolerance))
    return result
