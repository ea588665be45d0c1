"""What a fit will need, judged before it starts: the largest array a config implies.

Each size key has its own bound (:data:`psonurbs.config.FIELDS`); this module judges
what they imply together, for a cloud of N points, before anything is allocated, against
the limits :mod:`psonurbs.config` sets (and docs/configuration.md states). The
largest arrays of a fit, in 8-byte floats (n = control points, at most nu x nv):

    solve                 n x n            the normal matrix of the least-squares solve
    joint refinement      4n x 4n          control points and weights (``refine``)
    strategy full         2D x D           the swarm's feasible set, D = 4n + knots + 2N
    basis rows            N x k l          k l basis functions at each point
    mesh                  ~130 bytes per tessellation vertex (coordinates, faces, OBJ text)

A fit is refused when one of them is above :data:`ARRAY_LIMIT` (the working memory is a
few times the largest array), or when the net has more control points than
:data:`NET_PER_POINT` per point (and :data:`NET_FLOOR`): beyond that the smoothness term,
not the data, decides the surface.
"""
from __future__ import annotations

from dataclasses import dataclass

from psonurbs.config import ARRAY_LIMIT, NET_FLOOR, NET_PER_POINT
from psonurbs.errors import ConfigError, InputError

__all__ = ["ARRAY_LIMIT", "NET_PER_POINT", "NET_FLOOR", "Estimate", "largest_arrays", "check_budget", "max_points", "judged_net"]

MESH_BYTES_PER_VERTEX = 130


@dataclass(frozen=True)
class Estimate:
    """One large array a fit will allocate."""

    bytes: int
    what: str  # e.g. "the joint refinement's 16,000 x 16,000 matrix"


def _gib(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def judged_net(config) -> tuple[int, int]:
    """The net a config is judged by: its net_size, or with ``net_size: auto`` the orders
    (the search's first net; it judges each larger net it tries by this budget itself)."""
    return tuple(config.orders) if config.net_size == "auto" else tuple(config.net_size)


def largest_arrays(config, n_points: int | None = None) -> list[Estimate]:
    """The large arrays a fit with this config allocates; those that depend on the
    cloud only when ``n_points`` is given. Largest first."""
    nu, nv = judged_net(config)
    n = nu * nv
    out = [Estimate(8 * n * n, f"the least-squares solve's {n:,} x {n:,} matrix")]
    if config.refine:
        out.append(Estimate(8 * (4 * n) ** 2, f"the joint refinement's {4 * n:,} x {4 * n:,} matrix"))
    vertices = config.tessellation[0] * config.tessellation[1]
    out.append(Estimate(MESH_BYTES_PER_VERTEX * vertices, f"the mesh of {vertices:,} vertices"))
    if n_points is not None:
        k, l = config.orders
        out.append(Estimate(8 * n_points * k * l, f"the basis rows ({n_points:,} points x {k * l} functions)"))
        if config.strategy == "full":
            d = 4 * n + (nu - k) + (nv - l) + 2 * n_points
            out.append(Estimate(8 * 2 * d * d, f"the full strategy's {2 * d:,} x {d:,} constraint matrix "
                                               f"({d:,} unknowns for {n_points:,} points)"))
    return sorted(out, key=lambda e: -e.bytes)


def max_points(config) -> int:
    """The most points a fit with this config can take within :data:`ARRAY_LIMIT` (the basis
    rows; for strategy full, its constraint matrix): a reader can refuse a larger cloud from
    its header, before reading it."""
    k, l = config.orders
    most = ARRAY_LIMIT // (8 * k * l)
    if config.strategy == "full":
        nu, nv = judged_net(config)
        d = int((ARRAY_LIMIT / 16) ** 0.5)
        most = min(most, max((d - 4 * nu * nv - (nu - k) - (nv - l)) // 2, 0))
    return most


def check_budget(config, n_points: int | None = None) -> None:
    """Refuse a config (ConfigError) or a config for this cloud (InputError, with
    ``n_points``) whose largest array is above :data:`ARRAY_LIMIT`, or whose net has more
    control points than the cloud can decide."""
    error = ConfigError if n_points is None else InputError
    largest = largest_arrays(config, n_points)[0]
    if largest.bytes > ARRAY_LIMIT:
        raise error(f"the config needs an estimated {_gib(largest.bytes)} for {largest.what}, more than the "
                    f"{_gib(ARRAY_LIMIT)} one array may take: use a smaller net_size, tessellation"
                    + (", strategy hybrid" if config.strategy == "full" else "")
                    + (" or refine: false" if config.refine else ""))
    if n_points is not None:
        nu, nv = judged_net(config)
        most = max(NET_FLOOR, NET_PER_POINT * n_points)
        if nu * nv > most:
            raise error(f"config key 'net_size': {nu} x {nv} = {nu * nv:,} control points are too many for "
                        f"{n_points:,} points: at most {most:,} ({NET_PER_POINT} per point, at least {NET_FLOOR})")
