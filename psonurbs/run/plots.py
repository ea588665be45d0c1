"""Pictures of a fit (``psonurbs plot``): matplotlib, headless (Agg canvas, no display).

From a fit's ``STEM.json`` (and ``STEM_error.csv`` beside it, and the cloud when it
can be found) :func:`plot_result` writes:

* ``STEM_curve.png``: the error curve, best and mean RMSE per swarm iteration, log y;
* ``STEM_views.png``: the cloud with the fitted (trimmed) surface and its control net, from four
  viewpoints (surface and net only when there is no cloud);
* ``STEM_distance.png``: the points coloured by their distance to the surface, with a
  histogram of the distances (only with a cloud);
* ``STEM_domain.png``: the parameter domain: the points' foot points, the knot lines and
  the trim loops (outer boundary and holes);
* ``STEM_basis.png``: the B-spline basis functions of both knot vectors (the paper's
  Fig. 4), knots marked;
* ``STEM_tolerance.png``: for a fit to a tolerance (``fit.tolerance`` in the JSON), the
  held-out error of each net the search tried against its control points (the uniform
  knots' and the swarm's apart), the tolerance and the delivered fit marked.

Each picture has a fixed pixel size (:data:`SIZES`) and is written atomically.
"""
from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from psonurbs.errors import ConfigError, InputError

__all__ = ["SIZES", "plot_result", "find_cloud", "read_curve"]

DPI = 100
#: (width, height) in pixels of each picture, by name suffix.
SIZES = {"curve": (900, 560), "views": (1200, 1000), "distance": (1200, 560), "basis": (900, 700),
         "domain": (800, 800), "tolerance": (900, 560)}
MAX_DRAWN_POINTS = 6000


def _matplotlib():
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise ConfigError("psonurbs plot needs the optional package matplotlib, which is not "
                          "installed: pip install 'psonurbs[plot]'") from None
    return Figure, FigureCanvasAgg


def _figure(kind: str):
    Figure, FigureCanvasAgg = _matplotlib()
    w, h = SIZES[kind]
    fig = Figure(figsize=(w / DPI, h / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:
    from psonurbs.formats.outputs import atomic_write

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI, metadata={"Software": None})
    return atomic_write(path, buffer.getvalue())


def find_cloud(json_path: Path, document: dict) -> Path | None:
    """The fit's cloud: the JSON's ``cloud`` file name beside the JSON, else in the cwd."""
    name = document.get("cloud")
    if not isinstance(name, str) or not name:
        return None
    for candidate in (json_path.parent / name, Path.cwd() / name):
        if candidate.is_file():
            return candidate
    return None


def read_curve(path: Path) -> tuple[list[str], np.ndarray] | None:
    """The error curve CSV (header, rows), or None if there is none."""
    if not path.is_file():
        return None
    lines = path.read_text(encoding="utf-8").splitlines()
    if len(lines) < 2:
        return None
    header = lines[0].split(",")
    rows = np.array([[float(x) for x in line.split(",")] for line in lines[1:] if line.strip()])
    return header, rows.reshape(-1, len(header))


def _subsample(points: np.ndarray, n: int = MAX_DRAWN_POINTS) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), n, replace=False))]


def _equal_axes(ax, points: np.ndarray) -> None:
    lo, hi = points.min(0), points.max(0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-12)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))


def plot_curve(header: list[str], rows: np.ndarray, title: str, path: Path) -> Path:
    fig = _figure("curve")
    ax = fig.add_subplot(1, 1, 1)
    x = rows[:, header.index("iteration")] if "iteration" in header else np.arange(1, len(rows) + 1)
    for k, name in enumerate(header):
        if name == "iteration":
            continue
        y = np.where(np.isfinite(rows[:, k]) & (rows[:, k] > 0), rows[:, k], np.nan)
        style = dict(lw=2.0) if "best" in name else dict(lw=1.2, ls="--")
        ax.plot(x, y, label=name.replace("_", " "), **style)
    ax.set_yscale("log")
    ax.set_xlabel("swarm iteration")
    ax.set_ylabel("RMSE (cloud units)")
    ax.set_title(f"{title}: error curve")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return _save(fig, path)


FACE_COLOURS = ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
                "tab:cyan", "tab:gray", "tab:red"]


def plot_views(faces, points: np.ndarray | None, title: str, path: Path) -> Path:
    """Cloud, surface and control net from four viewpoints; several faces each in its own
    colour (their nets left out)."""
    from psonurbs.geometry.trim import trimmed_mesh

    fig = _figure("views")
    meshes = []
    for surface, trim in faces:
        if trim is None:
            grid = surface.evaluate_grid(*surface.parameter_grid(41, 41))
            meshes.append(("grid", grid))
        else:
            verts, tris, _ = trimmed_mesh(surface, trim, 41, 41)
            meshes.append(("mesh", (verts, tris)))
    net = faces[0][0].control_points if len(faces) == 1 else None
    every = [m.reshape(-1, 3) if kind == "grid" else m[0] for kind, m in meshes]
    if net is not None:
        every.append(net.reshape(-1, 3))
    if points is not None:
        every.append(points)
    bounds = np.concatenate(every)
    drawn = None if points is None else _subsample(points)
    views = [(25, -60, "perspective"), (25, 30, "side"), (90, -90, "top"), (0, -90, "front")]
    for k, (elev, azim, name) in enumerate(views, 1):
        ax = fig.add_subplot(2, 2, k, projection="3d")
        for f, (kind, m) in enumerate(meshes):
            colour = FACE_COLOURS[f % len(FACE_COLOURS)]
            if kind == "grid":
                ax.plot_surface(m[..., 0], m[..., 1], m[..., 2], color=colour, alpha=0.45,
                                linewidth=0, antialiased=True, shade=True)
            elif len(m[1]):  # a trimmed face
                ax.plot_trisurf(m[0][:, 0], m[0][:, 1], m[0][:, 2], triangles=m[1], color=colour,
                                alpha=0.45, linewidth=0, antialiased=True, shade=True)
        if net is not None:
            for i in range(net.shape[0]):
                ax.plot(net[i, :, 0], net[i, :, 1], net[i, :, 2], color="tab:red", lw=0.8)
            for j in range(net.shape[1]):
                ax.plot(net[:, j, 0], net[:, j, 1], net[:, j, 2], color="tab:red", lw=0.8)
            ax.scatter(net[..., 0].ravel(), net[..., 1].ravel(), net[..., 2].ravel(), color="tab:red", s=10)
        if drawn is not None:
            ax.scatter(drawn[:, 0], drawn[:, 1], drawn[:, 2], color="k", s=0.6, alpha=0.5,
                       depthshade=False)
        _equal_axes(ax, bounds)
        ax.view_init(elev=elev, azim=azim)
        if name == "top":
            ax.set_zticks([])  # seen end-on: the labels would pile up
        elif name == "front":
            ax.set_yticks([])
        ax.set_title(name, fontsize=10)
        ax.tick_params(labelsize=7)
    shown = "surface (blue), control net (red)" if net is not None else f"{len(faces)} faces (a colour each)"
    what = f"cloud (black), {shown}" if points is not None else f"{shown}; no cloud found"
    fig.suptitle(f"{title}: {what}")
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.03, top=0.92, wspace=0.05, hspace=0.12)
    return _save(fig, path)


def plot_distance(faces, points: np.ndarray, title: str, path: Path) -> Path:
    from psonurbs.run.scoring import nearest_distances

    distances = nearest_distances(faces, points)
    fig = _figure("distance")
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    keep = np.arange(len(points)) if len(points) <= MAX_DRAWN_POINTS else \
        np.sort(np.random.default_rng(0).choice(len(points), MAX_DRAWN_POINTS, replace=False))
    p, d = points[keep], distances[keep]
    drawn = ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=d, cmap="viridis", s=3, depthshade=False)
    _equal_axes(ax, points)
    ax.view_init(elev=30, azim=-60)
    ax.tick_params(labelsize=7)
    fig.colorbar(drawn, ax=ax, shrink=0.7, label="distance to the surface")
    hist = fig.add_subplot(1, 2, 2)
    hist.hist(distances, bins=50, color="tab:green")
    rmse = float(np.sqrt(np.mean(distances ** 2)))
    hist.axvline(rmse, color="k", ls="--", label=f"rmse {rmse:.3g}")
    hist.set_xlabel("distance to the surface (cloud units)")
    hist.set_ylabel("points")
    hist.legend()
    fig.suptitle(f"{title}: {len(points)} points, max {distances.max():.3g}")
    fig.subplots_adjust(left=0.02, right=0.97, bottom=0.1, top=0.9, wspace=0.25)
    return _save(fig, path)


def plot_domain(surface, trim, points: np.ndarray | None, title: str, path: Path) -> Path:
    """The parameter domain: the points' foot-point parameters, the knot lines and the trim loops."""
    from psonurbs.geometry.projection import closest_parameters

    fig = _figure("domain")
    ax = fig.add_subplot(1, 1, 1)
    if points is not None:
        uv, _ = closest_parameters(surface, _subsample(points))
        ax.plot(uv[:, 0], uv[:, 1], ".", color="k", ms=1.5, alpha=0.6, label="points (foot points)")
    (u0, u1), (v0, v1) = surface.domain_u, surface.domain_v
    for t in np.unique(surface.knots_u[(surface.knots_u >= u0) & (surface.knots_u <= u1)]):
        ax.axvline(t, color="grey", lw=0.5, alpha=0.6)
    for t in np.unique(surface.knots_v[(surface.knots_v >= v0) & (surface.knots_v <= v1)]):
        ax.axhline(t, color="grey", lw=0.5, alpha=0.6)
    for k, loop in enumerate(trim.loops if trim is not None else ()):
        p = loop.polygon()
        p = np.concatenate([p, p[:1]])
        ax.plot(p[:, 0], p[:, 1], color="tab:red" if k == 0 else "tab:orange", lw=1.5,
                label="outer loop" if k == 0 else ("holes" if k == 1 else None))
    ax.set_xlim(u0, u1)
    ax.set_ylim(v0, v1)
    ax.set_aspect("equal")
    ax.set_xlabel("u")
    ax.set_ylabel("v")
    loops = 0 if trim is None else len(trim.loops)
    ax.set_title(f"{title}: parameter domain, knot lines (grey), {loops} trim loop{'s' if loops != 1 else ''}",
                 fontsize=10)
    if ax.get_legend_handles_labels()[1]:  # foot points or loops drawn: say which is which
        ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_basis(surface, title: str, path: Path) -> Path:
    from psonurbs.geometry.basis import design_matrix

    fig = _figure("basis")
    directions = [("u", surface.knots_u, surface.degree_u, surface.domain_u, surface.closed_u),
                  ("v", surface.knots_v, surface.degree_v, surface.domain_v, surface.closed_v)]
    for k, (name, knots, degree, (a, b), closed) in enumerate(directions, 1):
        ax = fig.add_subplot(2, 1, k)
        x = np.linspace(a, b, 600)
        basis = design_matrix(x, knots, degree).toarray()
        for i in range(basis.shape[1]):
            if np.any(basis[:, i] > 0):
                ax.plot(x, basis[:, i], lw=1.4)
        ax.plot(x, basis.sum(axis=1), color="k", lw=0.8, ls=":", label="sum (partition of unity)")
        inner = knots[(knots >= a) & (knots <= b)]
        for t in inner:
            ax.axvline(t, color="grey", lw=0.5, alpha=0.6)
        ax.plot(inner, np.zeros_like(inner), "k^", ms=5, label="knots")
        ax.set_xlim(a, b)
        ax.set_ylim(-0.05, 1.1)
        kind = "periodic" if closed else "clamped"
        ax.set_title(f"{name}: degree {degree}, {basis.shape[1]} basis functions, {kind} knot vector",
                     fontsize=10)
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{title}: B-spline basis functions N_i,p")
    fig.tight_layout()
    return _save(fig, path)


def plot_tolerance(tolerance: dict, title: str, path: Path) -> Path:
    """Achieved error (``fit.tolerance.searched``) against control points nu x nv, log y."""
    fig = _figure("tolerance")
    ax = fig.add_subplot(1, 1, 1)
    for knots, marker, words in (("uniform", "o-", "uniform knots"), ("swarm", "^--", "knots placed by the swarm"),
                                 ("rational", "v:", "knots and weights placed by the swarm")):
        steps = sorted((s for s in tolerance["searched"] if s.get("knots", "uniform") == knots),
                       key=lambda s: s["net_size"][0] * s["net_size"][1])
        if not steps:
            continue
        x = [s["net_size"][0] * s["net_size"][1] for s in steps]
        y = [s["achieved"] for s in steps]
        ax.plot(x, y, marker, lw=1.2, label=f"held-out {tolerance['measure']}, {words}")
        for s, cx, cy in zip(steps, x, y):
            ax.annotate(f"{s['net_size'][0]}x{s['net_size'][1]}", (cx, cy), textcoords="offset points",
                        xytext=(4, 4), fontsize=8)
    nu, nv = tolerance["net_size"]
    ax.plot([nu * nv], [tolerance["achieved"]], "s", ms=9, label=f"delivered {nu}x{nv}, over all points")
    ax.axhline(tolerance["value"], color="k", ls="--", lw=1.0, label=f"tolerance {tolerance['value']:.2e}")
    ax.set_yscale("log")
    ax.set_xlabel("control points (nu x nv)")
    ax.set_ylabel(f"{tolerance['measure']} distance (cloud units)")
    ax.set_title(f"{title}: tolerance {'met' if tolerance['met'] else 'not met'}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return _save(fig, path)


def plot_result(json_path: str | os.PathLike, out_dir: str | os.PathLike | None = None,
                cloud: str | os.PathLike | None = None) -> tuple[list[Path], list[str]]:
    """Write the pictures of one fit; returns (the PNG paths, notes for the user).

    ``cloud`` defaults to :func:`find_cloud`. Raises :class:`InputError` for an
    unusable JSON or cloud, :class:`ConfigError` without matplotlib.
    """
    from psonurbs.formats.clouds import read_cloud
    from psonurbs.run.scoring import load_faces

    _matplotlib()
    json_path = Path(json_path)
    faces, document = load_faces(json_path)
    stem = json_path.stem
    out = Path(out_dir) if out_dir is not None else json_path.parent
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{out}: cannot create the output directory ({e.strerror or e})") from None
    notes: list[str] = []
    if cloud is None:
        cloud = find_cloud(json_path, document)
        if cloud is None:
            notes.append(f"cloud {document.get('cloud', '?')!s} not found beside {json_path} or in "
                         "the current directory (use --cloud): drew the surface and net only")
    points = read_cloud(cloud) if cloud is not None else None
    title = stem
    written: list[Path] = []
    curve = read_curve(json_path.with_name(f"{stem}_error.csv"))
    if curve is not None:
        written.append(plot_curve(*curve, title, out / f"{stem}_curve.png"))
    else:
        notes.append(f"no error curve {stem}_error.csv beside the JSON: skipped {stem}_curve.png")
    written.append(plot_views(faces, points, title, out / f"{stem}_views.png"))
    if points is not None:
        written.append(plot_distance(faces, points, title, out / f"{stem}_distance.png"))
    if len(faces) == 1:
        surface, trim = faces[0]
        written.append(plot_domain(surface, trim, points, title, out / f"{stem}_domain.png"))
        written.append(plot_basis(surface, title, out / f"{stem}_basis.png"))
    else:
        notes.append(f"an object of {len(faces)} faces: {stem}_domain.png and {stem}_basis.png draw one "
                     "surface, skipped")
    tolerance = (document.get("fit") or {}).get("tolerance")
    if isinstance(tolerance, dict) and tolerance.get("searched"):
        written.append(plot_tolerance(tolerance, title, out / f"{stem}_tolerance.png"))
    return written, notes
