"""The fit configuration: schema, defaults and validation.

A config is a YAML mapping in the paper's vocabulary (see DESIGN.md)::

    orders: [3, 3]        # k, l: order = degree + 1
    net_size: [5, 5]      # (m+1) x (n+1) control points
    topology: open        # open | cylinder | sphere | torus | auto
    swarm:
      particles: 40
      iterations: 300
      inertia: 0.7        # w
      c1: 1.5
      c2: 1.5
      seed: 7

Every key is optional. Validation is strict: an unknown key, a value of the wrong
type (``true`` is not an integer) or an impossible value raises
:class:`psonurbs.errors.ConfigError` whose message names the file and the key.

The dataclasses validate themselves in ``__post_init__``, so a config built in
Python is checked by the same rules as one read from YAML.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import os
import re
import reprlib
from dataclasses import dataclass, field
from typing import Any, Hashable, Mapping

import yaml

from psonurbs.errors import ConfigError, existing_file

TOPOLOGIES = ("open", "cylinder", "sphere", "torus", "auto")
STRATEGIES = ("hybrid", "full")
PARAMETRISATIONS = ("auto", "plane", "intrinsic")  # first parameters of an open patch

__all__ = [
    "SwarmConfig",
    "FitConfig",
    "TOPOLOGIES",
    "STRATEGIES",
    "PARAMETRISATIONS",
    "load_config",
    "config_from_dict",
    "BOUNDS",
    "Bound",
]


# ---- value checks ----------------------------------------------------------
# Each takes the dotted key (for the message) and the raw value, and returns the
# normalised value (Python int / float / tuple) or raises ConfigError.

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


def _int(key: str, value: Any, *, minimum: int, what: str) -> int:
    if not _is_int(value) or value < minimum:
        raise _fail(key, what, value)
    _within_bound(key, value)
    return int(value)


def _float(key: str, value: Any, *, what: str, ok=lambda x: True) -> float:
    if not _is_real(value) or not math.isfinite(float(value)) or not ok(float(value)):
        raise _fail(key, what, value)
    _within_bound(key, float(value))
    return float(value)


class _TooLarge(ConfigError):
    """A value above its bound: its own message, kept when the value is an item of a list."""


def _within_bound(key: str, value) -> None:
    """Refuse a value above the key's bound in :data:`BOUNDS`, naming the bound."""
    bound = BOUNDS.get(key)
    if bound is not None and value > bound.most:
        raise _TooLarge(f"config key '{key}': {_show(value)} is too large: at most {bound.most:,} "
                          f"({bound.why})")


def _pair(key: str, value: Any, item, what: str) -> tuple:
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__") or len(value) != 2:
        raise _fail(key, f"a list of 2 {what}", value)
    try:
        return tuple(item(v) for v in value)
    except _TooLarge:
        raise
    except ConfigError:
        raise _fail(key, f"a list of 2 {what}", list(value)) from None


def _choice(key: str, value: Any, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise _fail(key, "one of " + ", ".join(choices), value)
    return value


# ---- bounds ----------------------------------------------------------------
# Every size a config sets has an upper bound, so that no value can make a fit allocate
# or compute without end; the error names the bound. New keys add a row. (What a whole
# config implies for a given cloud, the largest array and the net against the point
# count, is judged by psonurbs.fitting.budget before fitting.)

@dataclass(frozen=True)
class Bound:
    most: float  # the largest value allowed
    why: str  # what the bound protects, for the message


BOUNDS: dict[str, Bound] = {
    "orders": Bound(10, "degree 9 at most"),
    "net_size": Bound(1000, "control points along one direction"),
    "tessellation": Bound(10_000, "mesh vertices along one direction"),
    "swarm_points": Bound(100_000, "points the swarm's fitness sees"),
    "polish_iterations": Bound(10_000, "rounds of parameter correction"),
    "refine_iterations": Bound(10_000, "Levenberg-Marquardt steps of the joint refinement"),
    "swarm.particles": Bound(10_000, "particles of the swarm"),
    "swarm.iterations": Bound(100_000, "generations of the swarm, rows of the error curve"),
    "swarm.seed": Bound(2**64 - 1, "a 64-bit seed"),
    "swarm.inertia": Bound(10, "w; a swarm is stable below 1"),
    "swarm.c1": Bound(10, "learning factor"),
    "swarm.c2": Bound(10, "learning factor"),
    "smoothing": Bound(1e6, "relative weight of the smoothness term"),
    "weight_bounds": Bound(1e6, "NURBS weights"),
}
MAX_EVALUATIONS = 10_000_000  # swarm.particles x swarm.iterations: fitness evaluations of one fit
MAX_TESSELLATION_VERTICES = 4_000_000  # tessellation[0] x tessellation[1]
MIN_SWARM_POINTS = 16  # fewer cannot judge a particle (and the robust pass may leave none of them)
MIN_WEIGHT_BOUND = 1e-6  # weight_bounds[0] at least this (its log bounds the swarm's search)


# ---- the schema ------------------------------------------------------------

@dataclass(frozen=True)
class SwarmConfig:
    """Particle swarm parameters (the paper's Eq. 1-2).

    particles, iterations: swarm size and number of generations (>= 1).
    inertia: w, the weight of the previous velocity (>= 0).
    c1, c2: learning factors towards the swarm's and the particle's best (>= 0).
    seed: seed of the random generator (>= 0); the same seed gives the same fit.
    """

    particles: int = 40
    iterations: int = 300
    inertia: float = 0.7
    c1: float = 1.5
    c2: float = 1.5
    seed: int = 7

    def __post_init__(self) -> None:
        def put(name, value):
            object.__setattr__(self, name, value)

        put("particles", _int("swarm.particles", self.particles, minimum=1, what="a positive integer"))
        put("iterations", _int("swarm.iterations", self.iterations, minimum=1, what="a positive integer"))
        for name in ("inertia", "c1", "c2"):
            put(name, _float(f"swarm.{name}", getattr(self, name), what="a finite number >= 0",
                             ok=lambda x: x >= 0))
        put("seed", _int("swarm.seed", self.seed, minimum=0, what="an integer >= 0"))
        if self.particles * self.iterations > MAX_EVALUATIONS:
            raise ConfigError(f"config keys 'swarm.particles' x 'swarm.iterations': {self.particles:,} x "
                              f"{self.iterations:,} = {self.particles * self.iterations:,} fitness evaluations "
                              f"is too many: at most {MAX_EVALUATIONS:,}")

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class FitConfig:
    """Everything a fit needs besides the points.

    orders: (k, l), order = degree + 1, each >= 2 and <= the net size.
    net_size: control points along u and v.
    topology: open | cylinder | sphere | torus | auto.
    strategy: "hybrid" (swarm over knots and weights, control points by least
        squares) or "full" (the paper's Eq. 10 search space).
    smoothing: relative weight of the control-net smoothness term (>= 0).
    swarm_points: at most this many points (a subsample) are seen by the swarm.
    polish_iterations: rounds of parameter correction after the swarm (>= 0).
    tessellation: mesh resolution (n_u, n_v), each >= 2.
    weight_bounds: (lo, hi) bounds on the NURBS weights, 0 < lo <= 1 <= hi.
    min_knot_gap: minimum gap between knots, as a fraction of the uniform spacing.
    cross_validation: judge the swarm's particles by their leave-one-out error (true)
        or by the plain fit error on the points they were fitted to (false).
    refine: after the polish, refine control points, weights and parameters jointly
        (Levenberg-Marquardt), then polish again.
    refine_iterations: at most this many Levenberg-Marquardt steps of that refinement
        (>= 0); it stops sooner once a step lowers its objective by less than 1e-6.
    robust: gross outliers judged locally before the fit (far from the surface their
        neighbours describe, :mod:`psonurbs.fitting.prepare.outliers`) and a robust loss in every
        solve (:mod:`psonurbs.fitting.prepare.robust_weights`); the metrics still count every point. The
        YAML key ``remove_outliers`` is an alias.
    parametrisation: first parameters of an open patch: "plane" (projection), "intrinsic"
        (the cloud's own graph laid flat, then corrected from a coarse net to the
        configured one) or "auto" (the plane where the cloud is a height field over it).
    trim: trim an open surface to the data's footprint (:mod:`psonurbs.fitting.finish.footprint`):
        "auto" where the footprint leaves part of the domain empty, true always, false never.
    """

    orders: tuple[int, int] = (3, 3)
    net_size: tuple[int, int] = (5, 5)
    topology: str = "open"
    strategy: str = "hybrid"
    swarm: SwarmConfig = field(default_factory=SwarmConfig)
    smoothing: float = 1e-6
    swarm_points: int = 1500
    polish_iterations: int = 100
    tessellation: tuple[int, int] = (101, 101)
    weight_bounds: tuple[float, float] = (0.2, 5.0)
    min_knot_gap: float = 0.2
    cross_validation: bool = True
    refine: bool = True
    refine_iterations: int = 12
    robust: bool = True
    parametrisation: str = "auto"
    trim: str | bool = "auto"

    def __post_init__(self) -> None:
        def put(name, value):
            object.__setattr__(self, name, value)

        def order(v):
            return _int("orders", v, minimum=2, what="")

        def count(v):
            return _int("net_size", v, minimum=1, what="")

        put("orders", _pair("orders", self.orders, order, "integers >= 2 (order = degree + 1)"))
        put("net_size", _pair("net_size", self.net_size, count, "positive integers"))
        for direction, k, n in zip("uv", self.orders, self.net_size):
            if k > n:
                raise ConfigError(
                    f"config key 'orders': order {k} in {direction} is larger than net_size {n}")
        put("topology", _choice("topology", self.topology, TOPOLOGIES))
        if self.topology == "sphere" and self.net_size[1] < 3:
            raise ConfigError(f"config key 'net_size': a sphere needs at least 3 control points along v "
                              f"(the first and last collapse to the poles), got {self.net_size[1]}")
        put("parametrisation", _choice("parametrisation", self.parametrisation, PARAMETRISATIONS))
        put("strategy", _choice("strategy", self.strategy, STRATEGIES))
        swarm = self.swarm
        if swarm is None:
            swarm = SwarmConfig()
        elif isinstance(swarm, Mapping):
            swarm = _swarm_from_mapping(swarm)
        elif not isinstance(swarm, SwarmConfig):
            raise _fail("swarm", "a mapping", swarm)
        put("swarm", swarm)
        put("smoothing", _float("smoothing", self.smoothing, what="a finite number >= 0",
                                ok=lambda x: x >= 0))
        put("swarm_points", _int("swarm_points", self.swarm_points, minimum=MIN_SWARM_POINTS,
                                 what=f"an integer >= {MIN_SWARM_POINTS}"))
        put("polish_iterations", _int("polish_iterations", self.polish_iterations, minimum=0,
                                      what="an integer >= 0"))
        put("refine_iterations", _int("refine_iterations", self.refine_iterations, minimum=0,
                                      what="an integer >= 0"))
        put("tessellation", _pair("tessellation", self.tessellation,
                                  lambda v: _int("tessellation", v, minimum=2, what=""),
                                  "integers >= 2"))
        vertices = self.tessellation[0] * self.tessellation[1]
        if vertices > MAX_TESSELLATION_VERTICES:
            raise ConfigError(f"config key 'tessellation': {self.tessellation[0]:,} x {self.tessellation[1]:,} = "
                              f"{vertices:,} mesh vertices is too many: at most {MAX_TESSELLATION_VERTICES:,}")
        lo, hi = _pair("weight_bounds", self.weight_bounds,
                       lambda v: _float("weight_bounds", v, what="", ok=lambda x: x > 0),
                       "positive numbers")
        if not lo <= 1.0 <= hi:
            raise _fail("weight_bounds", "[lo, hi] with 0 < lo <= 1 <= hi", [lo, hi])
        if lo < MIN_WEIGHT_BOUND:
            raise ConfigError(f"config key 'weight_bounds': {_show(lo)} is too small: at least {MIN_WEIGHT_BOUND:g}")
        put("weight_bounds", (lo, hi))
        put("min_knot_gap", _float("min_knot_gap", self.min_knot_gap,
                                   what="a number in (0, 1)", ok=lambda x: 0 < x < 1))
        for name in ("cross_validation", "refine", "robust"):
            if not isinstance(getattr(self, name), bool):
                raise _fail(name, "true or false", getattr(self, name))
        if not (isinstance(self.trim, bool) or self.trim == "auto"):
            raise _fail("trim", "auto, true or false", self.trim)

    @property
    def degrees(self) -> tuple[int, int]:
        """(p, q) = (k - 1, l - 1)."""
        return (self.orders[0] - 1, self.orders[1] - 1)

    def to_dict(self) -> dict:
        """Plain JSON-able dict, same shape as the YAML (lists, nested swarm)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
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


_TOP_KEYS = tuple(f.name for f in dataclasses.fields(FitConfig))
ALIASES = {"remove_outliers": "robust"}  # an older name: the key it stands for
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
