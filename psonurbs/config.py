"""The fit configuration: its table of fields, the dataclasses, validation and the YAML reader.

A config is a YAML mapping in the paper's vocabulary (see docs/design.md)::

    orders: [4, 4]        # k, l: order = degree + 1
    net_size: [8, 8]      # (m+1) x (n+1) control points
    topology: open        # open | cylinder | sphere | torus | auto
    swarm:
      particles: 20
      seed: 3

Every key is optional. :data:`FIELDS` holds one row per key (type, default, bounds, one
line of help): the dataclasses' defaults, their validation, the README's configuration
table and docs/configuration.md come from it (``python3 -m psonurbs.config --readme
README.md --docs docs/configuration.md`` renders both).

Validation is strict: an unknown key, a value of the wrong type (``true`` is not an
integer) or an impossible value raises :class:`psonurbs.errors.ConfigError` whose message
names the file and the key. The dataclasses validate themselves in ``__post_init__``, so a
config built in Python is checked by the same rules as one read from YAML.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import os
import re
import reprlib
import textwrap
from dataclasses import dataclass, field
from typing import Any, Hashable, Mapping

import yaml

from psonurbs.errors import ConfigError, existing_file

__all__ = [
    "SwarmConfig",
    "FitConfig",
    "TOPOLOGIES",
    "STRATEGIES",
    "PARAMETRISATIONS",
    "load_config",
    "config_from_dict",
    "Field",
    "FIELDS",
    "ALIASES",
    "render_readme_table",
    "render_configuration_doc",
]


# ---- value checks ----------------------------------------------------------
# A value in a message is shown as the user wrote it, cut short.

SHOWN_CHARACTERS = 40  # a value in an error message is cut to about this many characters
_SHORT = reprlib.Repr()
_SHORT.maxstring = _SHORT.maxother = _SHORT.maxlong = SHOWN_CHARACTERS
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = _SHORT.maxset = 6
_SHORT.maxlevel = 3


def _show(value: Any) -> str:
    """A value as the user wrote it (YAML words for null and booleans), cut to a few dozen
    characters: never the whole of a huge or deeply nested value (reprlib stops early)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    try:
        text = _SHORT.repr(value) if isinstance(value, str) else _plain(value)
    except ValueError:  # an integer with more digits than Python will print
        return "an integer with more than 4300 digits"
    return text if len(text) <= 2 * SHOWN_CHARACTERS else text[:SHOWN_CHARACTERS] + "..."


def _plain(value: Any) -> str:
    """str() for numbers (``1e-06``, not ``1e-06`` in quotes), the short repr for the rest."""
    if isinstance(value, numbers.Number):
        text = str(value)
        return text if len(text) <= SHOWN_CHARACTERS else f"{text[:12]}...{text[-12:]} ({len(text)} digits)"
    return _SHORT.repr(value)


def _fail(key: str, expected: str, value: Any) -> ConfigError:
    return ConfigError(f"config key '{key}': expected {expected}, got {_show(value)}")


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _as_float(value: numbers.Real) -> float:
    """The value as a float; a YAML integer beyond the float range is infinite, as ``.inf`` is."""
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def _exponent(text: str) -> str:
    """'1e-06' -> '1e-6', '1e+06' -> '1e6'."""
    return re.sub(r"e([+-])0*(\d)", lambda m: "e" + ("-" if m.group(1) == "-" else "") + m.group(2), text)


def _number(x: float) -> str:
    """A bound: ``10,000``, ``1e6``."""
    return f"{x:,}" if isinstance(x, int) else _exponent(f"{x:g}")


class _TooLarge(ConfigError):
    """A value above its bound: its own message, kept when the value is an item of a list."""


# ---- the table of fields ---------------------------------------------------
# One row per key. The dataclasses below take their defaults from it, validation its
# rules, the README's and docs/configuration.md's tables their rows (render_readme_table,
# render_configuration_doc) and ``psonurbs fit``'s overriding options their --help.
# Every size has an upper bound (``most``), so that no value can make a fit allocate or
# compute without end; the message names it. A new key adds a row here and a field to
# its dataclass.

INTEGER, NUMBER, CHOICE, SWITCH, AUTO_SWITCH = "integer", "number", "choice", "switch", "auto-switch"
AUTO_INTEGER = "auto-integer"  # auto or an integer
TOLERANCE_MEASURES = ("p99", "max", "rms")  # of the point-to-surface distances a tolerance bounds
TOPOLOGIES = ("open", "cylinder", "sphere", "torus", "auto")
STRATEGIES = ("hybrid", "full")
PARAMETRISATIONS = ("auto", "plane", "intrinsic")  # first parameters of an open patch

# Rules between keys (checked by the dataclasses, said in the tables' ``also``):
MAX_EVALUATIONS = 10_000_000  # swarm.particles x swarm.iterations: fitness evaluations of one fit
MAX_TESSELLATION_VERTICES = 4_000_000  # tessellation[0] x tessellation[1]
MIN_SWARM_POINTS = 16  # fewer cannot judge a particle (and the robust pass may leave none of them)
MIN_WEIGHT_BOUND = 1e-6  # weight_bounds[0] at least this (its log bounds the swarm's search)
SPHERE_MIN_V = 3  # control points along v of a sphere: the first and last collapse to the poles
MAX_PATCHES = 32  # faces of a whole object at most

# What a whole config implies for a cloud, judged by psonurbs.fitting.budget before fitting:
ARRAY_LIMIT = 1 << 30  # bytes one array of a fit may take (1 GiB)
NET_PER_POINT = 4  # control points per point of the cloud, at most ...
NET_FLOOR = 100  # ... but never fewer than this many (16 points on the paper's 5 x 5 net are fine)


@dataclass(frozen=True)
class Field:
    """One config key: its YAML name, kind, default, allowed values and one line of help.

    kind: integer, number, choice (one of ``choices``), switch (true or false) or
    auto-switch (auto, true or false). ``pair``: a list of 2 of that kind (along u, v),
    each item checked alone. An integer or number is at least ``least`` (more than it with
    ``least_open``), below ``below`` when given, and at most ``most``; ``why`` says what
    that bound protects. ``note`` follows the expected value in a message, ``also`` says a
    rule between keys that the dataclass checks, ``option`` is the option of ``psonurbs
    fit`` that overrides the key.
    """

    key: str  # dotted: "swarm.seed"
    kind: str
    default: Any
    help: str
    pair: bool = False
    least: float | None = None
    least_open: bool = False
    below: float | None = None
    most: float | None = None
    why: str = ""
    choices: tuple[str, ...] = ()
    note: str = ""
    also: str = ""
    option: str = ""

    @property
    def name(self) -> str:
        """The dataclass attribute: ``seed`` for ``swarm.seed``."""
        return self.key.rsplit(".", 1)[-1]

    def expected(self) -> str:
        """What a value must be, in the words of the error message: 'a positive integer',
        'a list of 2 integers >= 2 (order = degree + 1)'."""
        if self.kind == CHOICE:
            return "one of " + ", ".join(self.choices)
        if self.kind == SWITCH:
            return "true or false"
        if self.kind == AUTO_SWITCH:
            return "auto, true or false"
        if self.kind == AUTO_INTEGER:
            return f"auto or an integer in [{self.least}, {self.most}]"
        noun = self.kind
        if self.below is not None:
            interval = f"{'(' if self.least_open else '['}{self.least}, {self.below})"
            one, many = f"a {noun} in {interval}", f"{noun}s in {interval}"
        elif self.least == (1 if noun == INTEGER else 0) and (noun == INTEGER or self.least_open):
            one, many = f"a positive {noun}", f"positive {noun}s"
        elif noun == INTEGER:
            one, many = f"an integer >= {self.least}", f"integers >= {self.least}"
        else:
            one, many = f"a finite number >= {self.least}", f"finite numbers >= {self.least}"
        text = f"a list of 2 {many}" if self.pair else one
        return f"{text} {self.note}" if self.note else text

    def check(self, value: Any) -> Any:
        """``value`` normalised (Python int, float or a tuple of 2), or ConfigError naming the key."""
        if self.kind == CHOICE:
            if not isinstance(value, str) or value not in self.choices:
                raise _fail(self.key, self.expected(), value)
            return value
        if self.kind == SWITCH:
            if not isinstance(value, bool):
                raise _fail(self.key, self.expected(), value)
            return value
        if self.kind == AUTO_SWITCH:
            if not (isinstance(value, bool) or value == "auto"):
                raise _fail(self.key, self.expected(), value)
            return value
        if self.kind == AUTO_INTEGER:
            if value == "auto":
                return value
            if not _is_int(value) or value < self.least:
                raise _fail(self.key, self.expected(), value)
            self._within_bound(value)
            return int(value)
        if not self.pair:
            return self._one(value, self.expected())
        if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__") or len(value) != 2:
            raise _fail(self.key, self.expected(), value)
        try:
            return tuple(self._one(v, "") for v in value)
        except _TooLarge:
            raise
        except ConfigError:
            raise _fail(self.key, self.expected(), list(value)) from None

    def _one(self, value: Any, expected: str) -> int | float:
        """One integer or number, checked against ``least``, ``below`` and ``most``."""
        if self.kind == INTEGER:
            if not _is_int(value) or value < self.least:
                raise _fail(self.key, expected, value)
            self._within_bound(value)
            return int(value)
        if not _is_real(value) or not math.isfinite(_as_float(value)) or not self._allows(float(value)):
            raise _fail(self.key, expected, value)
        self._within_bound(float(value))
        return float(value)

    def _allows(self, x: float) -> bool:
        above_least = x > self.least if self.least_open else x >= self.least
        return above_least and (self.below is None or x < self.below)

    def _within_bound(self, value) -> None:
        """Refuse a value above ``most``, naming the bound."""
        if self.most is not None and value > self.most:
            raise _TooLarge(f"config key '{self.key}': {_show(value)} is too large: at most {self.most:,} "
                            f"({self.why})")


def _learning_factor(key: str, towards: str) -> Field:
    return Field(key, NUMBER, 1.5, f"learning factor towards {towards} best", least=0, most=10,
                 why="learning factor")


FIELDS: dict[str, Field] = {f.key: f for f in (
    Field("orders", INTEGER, (3, 3), "orders k, l (degree + 1) along u, v", pair=True, least=2,
          most=10, why="degree 9 at most", note="(order = degree + 1)", also="each <= its `net_size`"),
    Field("net_size", INTEGER, (5, 5), "control points along u, v; with a tolerance, the largest net "
          "its search may use (`auto`, the default then: no limit)", pair=True, least=1, most=1000,
          why="control points along one direction",
          also=f"at least {SPHERE_MIN_V} along v for a sphere; `auto` only with a tolerance"),
    Field("topology", CHOICE, "open", "shape of the parameter domain (closed directions periodic; a "
          "cylinder: a tube, straight or bent); auto: chosen from the cloud", choices=TOPOLOGIES,
          option="--topology"),
    Field("strategy", CHOICE, "hybrid", "hybrid: the swarm searches knots and weights, least squares the "
          "control points; full: the paper's space (Eq. 10)", choices=STRATEGIES,
          option="--strategy"),
    Field("swarm.particles", INTEGER, 40, "swarm size", least=1, most=10_000, why="particles of the swarm",
          also=f"particles x iterations <= {MAX_EVALUATIONS:,}", option="--particles"),
    Field("swarm.iterations", INTEGER, 300, "generations of the swarm (rows of the error curve)", least=1,
          most=100_000, why="generations of the swarm, rows of the error curve",
          also=f"particles x iterations <= {MAX_EVALUATIONS:,}", option="--iterations"),
    Field("swarm.inertia", NUMBER, 0.7, "w, the weight of a particle's previous velocity", least=0, most=10,
          why="w; a swarm is stable below 1"),
    _learning_factor("swarm.c1", "the swarm's"),
    _learning_factor("swarm.c2", "the particle's own"),
    Field("swarm.seed", INTEGER, 7, "seed of the random generator; the same seed gives the same fit",
          least=0, most=2**64 - 1, why="a 64-bit seed", option="--seed"),
    Field("smoothing", NUMBER, 1e-6, "weight of the net's smoothness term at the classical start; the "
          "swarm then picks it by leave-one-out error", least=0, most=1e6,
          why="relative weight of the smoothness term"),
    Field("swarm_points", INTEGER, 1500, "the swarm sees at most this many points (a subsample); the final "
          "solve sees all", least=MIN_SWARM_POINTS, most=100_000,
          why="points the swarm's fitness sees"),
    Field("polish_iterations", INTEGER, 100, "rounds of parameter correction, before and after the smoothing is "
          "picked again", least=0, most=10_000,
          why="rounds of parameter correction"),
    Field("tessellation", INTEGER, (101, 101), "mesh resolution along u, v", pair=True, least=2,
          most=10_000, why="mesh vertices along one direction",
          also=f"<= {MAX_TESSELLATION_VERTICES:,} vertices"),
    Field("weight_bounds", NUMBER, (0.2, 5.0), "lowest and highest NURBS weight [lo, hi]", pair=True, least=0,
          least_open=True, most=1e6, why="NURBS weights", also=f"{_number(MIN_WEIGHT_BOUND)} <= lo <= 1 <= hi"),
    Field("min_knot_gap", NUMBER, 0.2, "smallest gap between knots, as a fraction of the uniform spacing",
          least=0, least_open=True, below=1),
    Field("cross_validation", SWITCH, True, "judge particles by their leave-one-out error, not the plain "
          "fit error"),
    Field("refine", SWITCH, True, "refine control points, weights and parameters jointly "
          "(Levenberg-Marquardt) after the polish; kept only when the fit gains"),
    Field("refine_iterations", INTEGER, 12, "at most this many steps of that refinement (fewer once a step gains "
          "almost nothing)", least=0, most=10_000,
          why="Levenberg-Marquardt steps of the joint refinement"),
    Field("robust", SWITCH, True, "leave out gross outliers and weigh every solve by a robust loss; "
          "the metrics count every point"),
    Field("parametrisation", CHOICE, "auto", "first parameters of an open patch: plane (a projection), "
          "intrinsic (the cloud's graph laid flat), auto (the plane where it is a height field)", choices=PARAMETRISATIONS, option="--parametrisation"),
    Field("trim", AUTO_SWITCH, "auto", "trim an open surface to the data's footprint: auto where the "
          "footprint leaves a gap or a hole or an edge runs past the data (a flattened sheet: always), "
          "true always, false never"),
    Field("tolerance", NUMBER, None, "fit to this tolerance (cloud units): the smallest net meeting it "
          "is searched", least=0, least_open=True,
          also="`tolerance` or `tolerance_rel`, not both", option="--tolerance"),
    Field("tolerance_rel", NUMBER, None, "the tolerance as a fraction of the cloud's bounding-box diagonal",
          least=0, least_open=True, most=1, why="a fraction of the bounding-box diagonal",
          also="`tolerance` or `tolerance_rel`, not both", option="--tolerance-rel"),
    Field("tolerance_measure", CHOICE, "p99", "what the tolerance bounds: the point distances' 99th "
          "percentile, max or rms", choices=TOLERANCE_MEASURES),
    Field("align_edges", SWITCH, True, "stretch the data onto the domain's edges (the surface ends where "
          "they do); false for faces the join extends"),
    Field("patches", AUTO_INTEGER, 1, "faces: 1, one surface; auto, split at creases, a face per region, "
          "cut and sewn into a shell (a solid if closed); N, the N largest regions", least=1, most=MAX_PATCHES,
          why="faces of one object", option="--patches"),
)}
ALIASES = {"remove_outliers": "robust"}  # another name: the key it stands for


def default(key: str) -> Any:
    """The default of a key of :data:`FIELDS`."""
    return FIELDS[key].default


# ---- the schema ------------------------------------------------------------

def _normalise(config, prefix: str, *names: str) -> None:
    """Replace each field ``name`` of the frozen dataclass ``config`` by its value as checked
    and normalised by the row ``prefix + name`` of :data:`FIELDS`."""
    for name in names:
        object.__setattr__(config, name, FIELDS[prefix + name].check(getattr(config, name)))


@dataclass(frozen=True)
class SwarmConfig:
    """Particle swarm parameters (the paper's Eq. 1-2); the keys ``swarm.*`` of :data:`FIELDS`.

    particles, iterations: swarm size and number of generations.
    inertia: w, the weight of the previous velocity.
    c1, c2: learning factors towards the swarm's and the particle's best.
    seed: seed of the random generator; the same seed gives the same fit.
    """

    particles: int = default("swarm.particles")
    iterations: int = default("swarm.iterations")
    inertia: float = default("swarm.inertia")
    c1: float = default("swarm.c1")
    c2: float = default("swarm.c2")
    seed: int = default("swarm.seed")

    def __post_init__(self) -> None:
        _normalise(self, "swarm.", "particles", "iterations", "inertia", "c1", "c2", "seed")
        if self.particles * self.iterations > MAX_EVALUATIONS:
            raise ConfigError(f"config keys 'swarm.particles' x 'swarm.iterations': {self.particles:,} x "
                              f"{self.iterations:,} = {self.particles * self.iterations:,} fitness evaluations "
                              f"is too many: at most {MAX_EVALUATIONS:,}")

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class FitConfig:
    """Everything a fit needs besides the points; one field per key of :data:`FIELDS` (the
    swarm's in :class:`SwarmConfig`), which says each one's meaning, default and bounds.

    orders (k, l) and net_size are along u and v; orders = degrees + 1 (:attr:`degrees`).
    robust: gross outliers judged locally before the fit (:mod:`psonurbs.fitting.prepare.outliers`)
    and a robust loss in every solve (:mod:`psonurbs.fitting.prepare.robust_weights`); the YAML key
    ``remove_outliers`` is an alias. trim: :mod:`psonurbs.fitting.finish.footprint`.
    """

    orders: tuple[int, int] = default("orders")
    # None: not given, which is FIELDS' default, or auto when a tolerance is given (kept
    # apart so that an override adding a tolerance still searches the net)
    net_size: tuple[int, int] | str | None = None
    topology: str = default("topology")
    strategy: str = default("strategy")
    swarm: SwarmConfig = field(default_factory=SwarmConfig)
    smoothing: float = default("smoothing")
    swarm_points: int = default("swarm_points")
    polish_iterations: int = default("polish_iterations")
    tessellation: tuple[int, int] = default("tessellation")
    weight_bounds: tuple[float, float] = default("weight_bounds")
    min_knot_gap: float = default("min_knot_gap")
    cross_validation: bool = default("cross_validation")
    refine: bool = default("refine")
    refine_iterations: int = default("refine_iterations")
    robust: bool = default("robust")
    parametrisation: str = default("parametrisation")
    trim: str | bool = default("trim")
    tolerance: float | None = default("tolerance")
    tolerance_rel: float | None = default("tolerance_rel")
    tolerance_measure: str = default("tolerance_measure")
    align_edges: bool = default("align_edges")
    patches: int | str = default("patches")

    def __post_init__(self) -> None:
        # Checked in this order, the rules between keys as soon as their keys are: the
        # first error of a config with several is the one reported.
        _normalise(self, "", "orders")
        self._check_tolerance()
        object.__setattr__(self, "_net_size_given", self.net_size is not None)
        if self.net_size is None:
            object.__setattr__(self, "net_size", "auto" if self.has_tolerance else default("net_size"))
        if self.net_size == "auto":
            if not self.has_tolerance:
                raise ConfigError("config key 'net_size': auto needs a tolerance (tolerance or tolerance_rel)")
        else:
            _normalise(self, "", "net_size")
            for direction, k, n in zip("uv", self.orders, self.net_size):
                if k > n:
                    raise ConfigError(
                        f"config key 'orders': order {k} in {direction} is larger than net_size {n}")
        _normalise(self, "", "topology")
        if self.topology == "sphere" and self.net_size != "auto" and self.net_size[1] < SPHERE_MIN_V:
            raise ConfigError(f"config key 'net_size': a sphere needs at least {SPHERE_MIN_V} control points "
                              f"along v (the first and last collapse to the poles), got {self.net_size[1]}")
        _normalise(self, "", "parametrisation", "strategy")
        swarm = self.swarm
        if swarm is None:
            swarm = SwarmConfig()
        elif isinstance(swarm, Mapping):
            swarm = _swarm_from_mapping(swarm)
        elif not isinstance(swarm, SwarmConfig):
            raise _fail("swarm", "a mapping", swarm)
        object.__setattr__(self, "swarm", swarm)
        _normalise(self, "", "smoothing", "swarm_points", "polish_iterations", "refine_iterations", "tessellation")
        vertices = self.tessellation[0] * self.tessellation[1]
        if vertices > MAX_TESSELLATION_VERTICES:
            raise ConfigError(f"config key 'tessellation': {self.tessellation[0]:,} x {self.tessellation[1]:,} = "
                              f"{vertices:,} mesh vertices is too many: at most {MAX_TESSELLATION_VERTICES:,}")
        _normalise(self, "", "weight_bounds")
        lo, hi = self.weight_bounds
        if not lo <= 1.0 <= hi:
            raise _fail("weight_bounds", "[lo, hi] with 0 < lo <= 1 <= hi", [lo, hi])
        if lo < MIN_WEIGHT_BOUND:
            raise ConfigError(f"config key 'weight_bounds': {_show(lo)} is too small: at least {MIN_WEIGHT_BOUND:g}")
        _normalise(self, "", "min_knot_gap", "cross_validation", "refine", "robust", "trim", "align_edges", "patches")

    def _check_tolerance(self) -> None:
        """At most one of tolerance and tolerance_rel, each a positive finite number."""
        for name in ("tolerance", "tolerance_rel"):
            if getattr(self, name) is not None:
                _normalise(self, "", name)
        if self.tolerance is not None and self.tolerance_rel is not None:
            raise ConfigError("config keys 'tolerance' and 'tolerance_rel' do not go together: give one of them")
        _normalise(self, "", "tolerance_measure")

    @property
    def net_size_given(self) -> bool:
        """The net size was given (else it is the default, or searched with a tolerance)."""
        return self._net_size_given

    @property
    def has_tolerance(self) -> bool:
        """A tolerance is given (in cloud units or relative): the net is searched."""
        return self.tolerance is not None or self.tolerance_rel is not None

    @property
    def degrees(self) -> tuple[int, int]:
        """(p, q) = (k - 1, l - 1)."""
        return (self.orders[0] - 1, self.orders[1] - 1)

    def to_dict(self) -> dict:
        """Plain JSON-able dict, same shape as the YAML (lists, nested swarm)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if (f.name in TOLERANCE_KEYS and not self.has_tolerance or f.name == "patches" and self.patches == 1
                    or f.name == "align_edges" and self.align_edges):
                continue  # a fit without a tolerance (of one face) writes the config it always wrote
            value = getattr(self, f.name)
            if isinstance(value, SwarmConfig):
                value = value.to_dict()
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out

    def with_overrides(self, source: str = "command-line options", **overrides: Any) -> "FitConfig":
        """A copy with some keys replaced; ``None`` values are ignored.

        Swarm keys may be given bare (``seed=3``, ``particles=20``) or dotted
        (``**{"swarm.seed": 3}``). The result is validated like a file; errors
        name ``source``.
        """
        d = self.to_dict()
        if not self._net_size_given:  # still auto if the overrides add a tolerance
            d.pop("net_size")
        swarm_keys = {f.name for f in dataclasses.fields(SwarmConfig)}
        for key, value in overrides.items():
            if value is None:
                continue
            if key.startswith("swarm."):
                d["swarm"][key[len("swarm."):]] = value
            elif key in swarm_keys:
                d["swarm"][key] = value
            else:
                d[key] = value
        return config_from_dict(d, source=source)


TOLERANCE_KEYS = ("tolerance", "tolerance_rel", "tolerance_measure")
_TOP_KEYS = tuple(f.name for f in dataclasses.fields(FitConfig))
_SWARM_KEYS = tuple(f.name for f in dataclasses.fields(SwarmConfig))


def _check_keys(d: Mapping, known: tuple[str, ...], prefix: str) -> None:
    for key in d:
        if not isinstance(key, str) or key not in known:
            name = f"{prefix}{key}" if isinstance(key, str) else f"{prefix}{_show(key)}"
            if len(name) > 2 * SHOWN_CHARACTERS:
                name = name[:SHOWN_CHARACTERS] + "..."
            hint = ""
            if isinstance(key, str) and len(key) <= 2 * SHOWN_CHARACTERS:
                close = difflib.get_close_matches(key, known, n=1)
                if close:
                    hint = f"; did you mean '{prefix}{close[0]}'?"
            raise ConfigError(f"unknown config key '{name}' (known: {', '.join(known)}){hint}")


def _swarm_from_mapping(d: Mapping) -> SwarmConfig:
    _check_keys(d, _SWARM_KEYS, "swarm.")
    return SwarmConfig(**d)


def config_from_dict(d: Mapping | None, source: str | None = None) -> FitConfig:
    """Validate a parsed config mapping and build a :class:`FitConfig`.

    ``None`` (an empty file) gives the defaults. ``source`` (usually the file
    name) prefixes every error message.
    """
    try:
        if d is None:
            d = {}
        if not isinstance(d, Mapping):
            raise ConfigError(f"the top level must be a mapping of config keys, got {_show(d)}")
        _check_keys(d, _TOP_KEYS + tuple(ALIASES), "")
        kwargs = dict(d)
        for alias, key in ALIASES.items():
            if alias in kwargs:
                value = kwargs.pop(alias)
                if not isinstance(value, bool):
                    raise _fail(alias, "true or false", value)
                if key in kwargs and kwargs[key] != value:
                    raise ConfigError(f"config keys '{alias}' and '{key}' disagree ('{alias}' is another name "
                                      f"for '{key}')")
                kwargs[key] = value
        swarm = kwargs.get("swarm")
        if swarm is not None and not isinstance(swarm, Mapping):
            raise _fail("swarm", "a mapping", swarm)
        return FitConfig(**kwargs)
    except ConfigError as e:
        if source:
            raise ConfigError(f"{source}: {e}") from None
        raise


# ---- YAML ------------------------------------------------------------------

MAX_CONFIG_BYTES = 1 << 20  # a config file is a few hundred bytes; 1 MiB is plenty
MAX_ALIASES = 100  # YAML aliases (*name) in one file
MAX_NODES = 10_000  # nodes of the document with every alias expanded ("billion laughs")
MAX_DEPTH = 32  # nesting of sequences and mappings


class _Loader(yaml.SafeLoader):
    """SafeLoader that reads ``1e-4`` as a float (YAML 1.2), rejects duplicate keys and
    refuses documents that would expand without bound: more than :data:`MAX_ALIASES`
    aliases, more than :data:`MAX_NODES` nodes once the aliases are expanded, nesting
    deeper than :data:`MAX_DEPTH` (the composer is recursive: 100,000 ``[`` would end in
    a RecursionError). Each limit is checked while composing, before anything is built."""

    def __init__(self, stream):
        super().__init__(stream)
        self._aliases = self._depth = self._expanded = 0
        self._sizes: dict[int, int] = {}  # id(node) -> its node count with aliases expanded

    def _refuse(self, problem: str):
        raise yaml.composer.ComposerError(None, None, problem, self.peek_event().start_mark)

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_ALIASES:
                self._refuse(f"more than {MAX_ALIASES} aliases")
            node = super().compose_node(parent, index)
            self._count(self._sizes.get(id(node), 1))
            return node
        if self._depth >= MAX_DEPTH:
            self._refuse(f"nested deeper than {MAX_DEPTH} levels")
        self._depth += 1
        start = self._expanded
        self._count(1)
        node = super().compose_node(parent, index)
        self._sizes[id(node)] = self._expanded - start
        self._depth -= 1
        return node

    def _count(self, nodes: int) -> None:
        self._expanded += nodes
        if self._expanded > MAX_NODES:
            self._refuse(f"more than {MAX_NODES:,} values once its aliases are expanded")


_Loader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X)
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))


def _construct_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False):
    seen: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if not isinstance(key, Hashable):
            raise yaml.constructor.ConstructorError(
                None, None, f"a {type(key).__name__} cannot be a key", key_node.start_mark)
        if isinstance(key, str) and key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key '{key}'", key_node.start_mark)
        seen[key] = True
    return yaml.SafeLoader.construct_mapping(loader, node, deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_config(path: str | os.PathLike | None) -> FitConfig:
    """Read and validate a YAML config file; ``None`` gives the defaults."""
    if path is None:
        return FitConfig()
    path = existing_file(path, "a config file", ConfigError, missing="config file not found",
                         max_bytes=MAX_CONFIG_BYTES)
    name = str(path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ConfigError(f"{name}: config file is not UTF-8 text") from None
    except OSError as e:
        raise ConfigError(f"{name}: cannot read config file ({e.strerror or e})") from None
    try:
        data = yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as e:
        message = " ".join(str(e).split())
        raise ConfigError(f"malformed YAML in {name}: {_cut(message, 300)}") from None
    except ValueError as e:  # an integer of more than 4300 digits
        raise ConfigError(f"malformed YAML in {name}: {_cut(str(e), 120)}") from None
    return config_from_dict(data, source=name)


def _cut(text: str, length: int) -> str:
    return text if len(text) <= length else text[:length] + "..."


# ---- the tables, rendered ----------------------------------------------------
# The README's configuration table and docs/configuration.md are made from FIELDS and
# the limits above (python3 -m psonurbs.config --readme README.md, --docs
# docs/configuration.md); tests/test_config.py checks that both are as rendered.

README_START = "<!-- config-table: generated by python3 -m psonurbs.config --readme -->"
README_END = "<!-- /config-table -->"
DOCS_PATH = "docs/configuration.md"


def yaml_text(value: Any) -> str:
    """A default as it is written in YAML: ``[3, 3]``, ``1e-6``, ``true``, ``open``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return "[" + ", ".join(yaml_text(v) for v in value) + "]"
    if isinstance(value, float):
        return _exponent(repr(value))
    return str(value)


def kind_text(f: Field) -> str:
    """The table's type column: integer, 2 numbers, string, boolean, ..."""
    kind = {CHOICE: "string", SWITCH: "boolean", AUTO_SWITCH: "`auto` or boolean",
            AUTO_INTEGER: "`auto` or integer"}.get(f.kind, f.kind)
    return f"2 {kind}s" if f.pair else kind


def allowed_text(f: Field) -> str:
    """The table's allowed-values column: the words of a choice, or the range and bound of a
    number (each item of a pair), then the rule between keys."""
    if f.kind in (CHOICE, SWITCH, AUTO_SWITCH):
        words = {SWITCH: ("true", "false"), AUTO_SWITCH: ("auto", "true", "false")}.get(f.kind, f.choices)
        return ", ".join(f"`{w}`" for w in words)
    if f.below is not None:
        parts = [f"in {'(' if f.least_open else '['}{_number(f.least)}, {_number(f.below)})"]
    else:
        parts = [f"{'>' if f.least_open else '>='} {_number(f.least)}"]
    if f.kind == AUTO_INTEGER:
        parts.insert(0, "`auto`")
    if f.most is not None:
        parts.append(f"<= {_number(f.most)}")
    text = ("each " if f.pair else "") + ", ".join(parts)
    return f"{text}; {f.also}" if f.also else text


def option_help(key: str) -> str:
    """The --help of the ``psonurbs fit`` option that overrides ``key``."""
    f = FIELDS[key]
    return f"Override {key} (default {yaml_text(f.default)}): {f.help}."


def _row(*cells: str) -> str:
    return "| " + " | ".join(cells) + " |"


def render_readme_table() -> str:
    """The README's configuration table (markdown, ending in a newline): one row per key of
    :data:`FIELDS`, then the aliases."""
    lines = [_row("key", "type", "default", "allowed", "meaning"), "|---|---|---|---|---|"]
    for f in FIELDS.values():
        meaning = f"{f.help}; command line: `{f.option}`" if f.option else f.help
        lines.append(_row(f"`{f.key}`", kind_text(f), f"`{yaml_text(f.default)}`", allowed_text(f), meaning))
    for alias, key in ALIASES.items():
        lines.append(_row(f"`{alias}`", kind_text(FIELDS[key]), "", allowed_text(FIELDS[key]),
                          f"another name for `{key}`; giving both with different values is an error"))
    return "\n".join(lines) + "\n"


def with_readme_table(readme: str) -> str:
    """``readme`` with the text between :data:`README_START` and :data:`README_END` replaced
    by :func:`render_readme_table` (ValueError when a marker is missing)."""
    start, end = readme.index(README_START) + len(README_START), readme.index(README_END)
    return readme[:start] + "\n" + render_readme_table() + readme[end:]


def _refusal(d: Mapping) -> str:
    """The error line ``psonurbs fit -c cfg.yaml`` prints for a config holding ``d``."""
    try:
        config_from_dict(d, source="cfg.yaml")
    except ConfigError as e:
        return f"psonurbs: error: {e}"
    raise ValueError(f"{d} is a valid config")


def _paragraph(text: str) -> str:
    return textwrap.fill(text, 90, break_long_words=False, break_on_hyphens=False)


def render_configuration_doc() -> str:
    """docs/configuration.md in full: the keys, their bounds, the rules between them, the
    memory budget (:mod:`psonurbs.fitting.budget`) and the limits on the YAML file."""
    bounds = [_row("key", "at most", "what the bound protects"), "|---|---|---|"]
    bounds += [_row(f"`{f.key}`", _number(f.most) + (" each" if f.pair else ""), f.why)
               for f in FIELDS.values() if f.most is not None]
    rules: dict[str, list[str]] = {}  # a rule between keys -> the keys that say it
    for f in FIELDS.values():
        if f.also:
            rules.setdefault(f.also, []).append(f"`{f.key}`")
    examples = [_refusal({"swarm": {"particles": -3}}), _refusal({"swarm": {"partciles": 3}}),
                _refusal({"orders": [6, 3], "net_size": [5, 5]}), _refusal({"swarm": {"iterations": 10**9}}),
                _refusal({"swarm": {"particles": 5000, "iterations": 5000}})]
    limit = f"{ARRAY_LIMIT / 2**30:g} GiB"
    return "\n".join([
        "# Configuration",
        "",
        f"<!-- generated by python3 -m psonurbs.config --docs {DOCS_PATH}: edit the table in "
        "psonurbs/config.py, not this file -->",
        "",
        _paragraph("A fit is configured by a YAML file in the paper's names (`psonurbs fit CLOUD -c "
                   "CFG.yaml`). Every key is optional: a missing key, or an empty file, takes the default "
                   "below. The swarm's keys are nested under `swarm:`; a dotted key of the table "
                   "(`swarm.seed`) is `seed:` under `swarm:`. A fit's JSON output repeats the whole "
                   "config it was fitted with under `config`."),
        "",
        "## Keys",
        "",
        render_readme_table().rstrip("\n"),
        "",
        "## Validation",
        "",
        _paragraph("Validation is strict, and the message names the file and the key: an unknown key "
                   "(with the nearest known one as a hint), a value of the wrong type, a value out of its "
                   "range and a key given twice are errors, and no cloud is fitted (exit 2). `true` is "
                   "not an integer, an integer is accepted where a number is expected, and `1e-4` is a "
                   "number (as in YAML 1.2). The command-line options named in the table override the "
                   "file and are checked by the same rules; their errors name `command-line options`. "
                   "For example:"),
        "",
        *[f"    {line}" for line in examples],
        "",
        "## Bounds",
        "",
        _paragraph("Every size has an upper bound, so that no value can make a fit allocate or compute "
                   "without end; the message names it:"),
        "",
        *bounds,
        "",
        "Between keys:",
        "",
        *[f"- {', '.join(keys)}: {rule}" for rule, keys in rules.items()],
        "",
        "## Budget",
        "",
        _paragraph("What the keys imply together is judged before anything is allocated "
                   "(`psonurbs/fitting/budget.py`): for the config alone before any cloud is read (a "
                   "refusal is exit 2 and nothing is fitted), then for each cloud with its N points (that "
                   "cloud is reported unusable; the others are still fitted). With n = `net_size[0] x "
                   "net_size[1]` control points and orders k, l, the largest arrays of a fit, in 8-byte "
                   "floats, are:"),
        "",
        _row("array", "size"),
        "|---|---|",
        _row("the least-squares solve's normal matrix", "n x n"),
        _row("the joint refinement's matrix (`refine: true`)", "4n x 4n"),
        _row("the full strategy's constraints (`strategy: full`)",
             "2D x D, D = 4n + (net_size[0] - k) + (net_size[1] - l) + 2N"),
        _row("the basis rows", "N x k l"),
        _row("the mesh", "the tessellation's vertices with their faces and OBJ text"),
        "",
        _paragraph(f"A fit is refused when one of them would take more than {limit} (the message names "
                   "the array, its estimated size and the keys that shrink it), and when the net has more "
                   f"control points than {NET_PER_POINT} per point of the cloud (at least {NET_FLOOR} are "
                   "always allowed): beyond that the smoothness term, not the data, decides the surface. "
                   f"A cloud with more points than the config can fit within {limit} is refused from its "
                   "file's header, before it is read."),
        "",
        "## The YAML file",
        "",
        _paragraph(f"A config file is at most {MAX_CONFIG_BYTES / 2**20:.0f} MiB of UTF-8 text (a byte "
                   "order mark is allowed) and must be a regular file: a directory or a named pipe is "
                   "refused. Its YAML is read safely (no tag builds an object) and may hold at most "
                   f"{MAX_ALIASES} aliases, {MAX_NODES:,} values once the aliases are expanded, and "
                   f"{MAX_DEPTH} levels of nesting; each limit is checked while the document is read, "
                   f"before anything is built. A value quoted in a message is cut to about "
                   f"{SHOWN_CHARACTERS} characters."),
        "",
    ])


def main(argv: list[str] | None = None) -> None:
    """``python3 -m psonurbs.config``: print or rewrite the README's table, write the docs."""
    import argparse

    parser = argparse.ArgumentParser(prog="python3 -m psonurbs.config",
                                     description="Render the configuration tables from psonurbs/config.py.")
    parser.add_argument("--readme", nargs="?", const="-", metavar="README.md",
                        help="print the README's configuration table, or rewrite it in README.md "
                             "between its marker lines")
    parser.add_argument("--docs", metavar="PATH", help=f"write the configuration doc ({DOCS_PATH})")
    args = parser.parse_args(argv)
    if args.readme is None and args.docs is None:
        parser.error("give --readme and/or --docs")
    if args.readme == "-":
        print(render_readme_table(), end="")
    elif args.readme is not None:
        with open(args.readme, encoding="utf-8") as file:
            text = file.read()
        if README_START not in text or README_END not in text:
            parser.error(f"{args.readme} lacks the marker lines {README_START} and {README_END}")
        with open(args.readme, "w", encoding="utf-8") as file:
            file.write(with_readme_table(text))
    if args.docs is not None:
        with open(args.docs, "w", encoding="utf-8") as file:
            file.write(render_configuration_doc())


if __name__ == "__main__":
    main()
