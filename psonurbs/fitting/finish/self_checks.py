"""Self-checks of a fitted surface that need no ground truth: did the fit go wrong?

A least-squares surface is judged by its distance to the points, and a surface that
flaps far outside the data, or folds over itself where no point holds it, can still
pass close to every point. Three figures, on a ``GRID x GRID`` sample of the domain,
in units of the cloud's bounding-box diagonal:

* ``extent_ratio``: the diagonal of the bounding box of cloud and surface together over
  the cloud's own (1 when the surface stays inside the cloud's box); ``net_extent_ratio``
  the same for the control net. An open patch that extrapolates over a corner the data
  leave empty reaches a little past the box (1.2 on an elliptic plate); a surface that
  went wrong reaches several times past it.
* ``folded``: the share of the sample's neighbouring pairs whose normals point in opposite
  directions (``n_a . n_b < 0``): the surface folds back over itself. A smooth fit turns
  its normal by a few degrees between neighbours, never by more than 90.
* ``uncovered``: the share of the sample farther from every point than
  ``UNCOVERED_DISTANCE`` or, on a sparse cloud, twice the points' median spacing: surface
  where there are no data at all. A patch over a round or holed footprint leaves its
  corners uncovered, so only a surface that is mostly away from the data is suspect.

On a trimmed face only the samples inside the trim loops are judged: the surface beyond
them is not part of what the user gets (the mesh and the CAD files are trimmed), so a fold
or an excursion there is no fault of the fit.

A fit is *suspect* when any figure passes its bound (``MAX_EXTENT_RATIO``,
``MAX_NET_EXTENT_RATIO``, ``MAX_FOLDED``, ``MAX_UNCOVERED``); :attr:`FitChecks.warnings`
says which, in words for the user. The files of a suspect fit are written as usual.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.trim import Trim

GRID = 64  # samples along each direction of the domain
UNCOVERED_DISTANCE = 0.05  # of the diagonal: surface this far from every point has no data
MAX_EXTENT_RATIO = 1.5
MAX_NET_EXTENT_RATIO = 4.0
MAX_FOLDED = 0.002  # a fold line across a 64 x 64 sample flips about 1/64 of the pairs
MAX_UNCOVERED = 0.5


@dataclass(frozen=True)
class FitChecks:
    """The self-check figures of one fit and what they say."""

    extent_ratio: float
    net_extent_ratio: float
    folded: float
    uncovered: float

    @property
    def warnings(self) -> list[str]:
        out = []
        if self.extent_ratio > MAX_EXTENT_RATIO:
            out.append(f"the surface reaches {self.extent_ratio:.1f} times the cloud's size "
                       f"(bounding-box diagonal; at most {MAX_EXTENT_RATIO:g} expected)")
        if self.net_extent_ratio > MAX_NET_EXTENT_RATIO:
            out.append(f"the control net reaches {self.net_extent_ratio:.1f} times the cloud's size "
                       f"(at most {MAX_NET_EXTENT_RATIO:g} expected)")
        if self.folded > MAX_FOLDED:
            out.append(f"the surface folds: its normal flips across {self.folded:.1%} of the domain")
        if self.uncovered > MAX_UNCOVERED:
            out.append(f"{self.uncovered:.0%} of the surface is far from every point "
                       f"(over {UNCOVERED_DISTANCE:.0%} of the cloud's size)")
        return out

    @property
    def suspect(self) -> bool:
        return bool(self.warnings)

    def to_dict(self) -> dict:
        return {"extent_ratio": self.extent_ratio, "net_extent_ratio": self.net_extent_ratio,
                "folded": self.folded, "uncovered": self.uncovered, "suspect": self.suspect}


def extent_ratio(points: np.ndarray, others: np.ndarray) -> float:
    """Diagonal of the bounding box of ``points`` and ``others`` over that of ``points``."""
    both = np.vstack([points, others])
    return float(np.linalg.norm(np.ptp(both, axis=0)) / np.linalg.norm(np.ptp(points, axis=0)))


def flipped_share(normals: np.ndarray, judged: np.ndarray | None = None) -> float:
    """Share of the neighbouring pairs of a (n_u, n_v, 3) grid of normals that point in
    opposite directions; pairs with a vanishing normal (a sphere's pole) are not judged,
    nor pairs with a sample outside ``judged`` (n_u, n_v), when given."""
    length = np.linalg.norm(normals, axis=2)
    ok = length > 1e-9 * max(float(np.median(length)), 1e-300)
    if judged is not None:
        ok &= judged
    unit = normals / np.where(ok, length, 1.0)[..., None]
    flips, pairs = 0, 0
    for a, b, valid in ((unit[1:], unit[:-1], ok[1:] & ok[:-1]), (unit[:, 1:], unit[:, :-1], ok[:, 1:] & ok[:, :-1])):
        flips += int(np.sum((np.sum(a * b, axis=2) < 0) & valid))
        pairs += int(np.sum(valid))
    return flips / max(pairs, 1)


def check_fit(surface: NurbsSurface, points: np.ndarray, grid: int = GRID, trim: Trim | None = None) -> FitChecks:
    """The self-check figures of ``surface`` against the cloud ``points`` (N, 3); with a
    ``trim``, of the trimmed face (the samples inside its loops)."""
    us, vs = surface.parameter_grid(grid, grid)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    s, s_u, s_v = surface.derivatives(uu.ravel(), vv.ravel())
    judged = np.ones(len(s), bool) if trim is None else trim.contains(np.column_stack([uu.ravel(), vv.ravel()]))
    if not judged.any():  # a face thinner than the sample spacing: judge the whole surface
        judged[:] = True
    tree = cKDTree(points)
    spacing = float(np.median(tree.query(points, k=2)[0][:, 1]))
    far = max(UNCOVERED_DISTANCE * float(np.linalg.norm(np.ptp(points, axis=0))), 2.0 * spacing)
    return FitChecks(extent_ratio=extent_ratio(points, s[judged]),
                     net_extent_ratio=extent_ratio(points, surface.control_points.reshape(-1, 3)),
                     folded=flipped_share(np.cross(s_u, s_v).reshape(grid, grid, 3), judged.reshape(grid, grid)),
                     uncovered=float(np.mean(tree.query(s[judged])[0] > far)))
