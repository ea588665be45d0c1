"""CAD exports of a fitted surface: Rhino 3DM, IGES 5.3 (entity 128), OBJ free-form.

Each renderer takes a :class:`~psonurbs.geometry.nurbs.NurbsSurface` and returns the file's
content (``str`` or ``bytes``); writing is left to :func:`psonurbs.formats.outputs.write_fit_outputs`,
so the exports are atomic and all-or-nothing with the other outputs of a fit.

All three carry the surface exactly: the full net, the weights and the knot vectors,
numbers written with 17 significant digits (``repr``). A closed direction is stored
as psonurbs stores it (the whole periodic net, whose last ``degree`` rows repeat the
first, with an unclamped knot vector); any standard NURBS evaluator then draws the
closed surface on the domain ``[knots[deg], knots[-deg-1]]``.

Conventions of the formats (the places where they differ from ours):

* **3DM** (openNURBS, via the optional ``rhino3dm`` package): order = degree + 1 and a
  knot vector *without* its first and last knot (``n + degree - 1`` knots); control
  points are homogeneous ``(w x, w y, w z, w)``.
* **IGES 128**: the full knot vectors; ``K1 = nu - 1``, ``K2 = nv - 1``, ``M1``, ``M2``
  the degrees; the weights and the points listed with the u index varying fastest;
  flags PROP1/PROP2 closed in u/v, PROP3 polynomial (all weights equal), PROP4/PROP5
  periodic in u/v.
* **OBJ** (``cstype rat bspline``): rational control vertices ``v x y z w`` (Euclidean
  coordinates and the weight), ``surf u0 u1 v0 v1`` followed by the vertex indices
  with u varying fastest, and the full knot vectors in ``parm u`` / ``parm v``.

CAD formats need a length unit; the cloud's numbers are written unchanged and
declared as millimetres (scale on import if the scan was in other units).
"""
from __future__ import annotations

import base64
import re
from typing import Iterable

import numpy as np

from psonurbs.errors import ConfigError
from psonurbs.formats.step import render_step, step_available
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.trim import Trim

__all__ = [
    "FORMATS",
    "SUFFIXES",
    "check_formats",
    "render_3dm",
    "render_iges",
    "render_obj_nurbs",
    "render_exports",
]

#: ``--format`` values, and the file each writes (``None``: a block in ``STEM.obj``).
FORMATS = ("3dm", "iges", "obj-nurbs", "step")
SUFFIXES = {"3dm": ".3dm", "iges": ".igs", "obj-nurbs": None, "step": ".step"}

_INSTALL_HINT = "pip install 'psonurbs[cad]'"


def check_formats(formats: Iterable[str]) -> tuple[str, ...]:
    """Validate and de-duplicate ``formats`` (keeping their order).

    Raises :class:`ConfigError` for an unknown format, or for ``3dm`` or ``step`` when the
    optional ``rhino3dm`` or ``cadquery-ocp`` package is not installed, so that a run stops
    before any fitting.
    """
    out: list[str] = []
    for fmt in formats:
        if fmt not in FORMATS:
            raise ConfigError(f"unknown export format {fmt!r} (known: {', '.join(FORMATS)})")
        if fmt not in out:
            out.append(fmt)
    if "3dm" in out:
        try:
            import rhino3dm  # noqa: F401
        except ImportError:
            raise ConfigError("--format 3dm needs the optional package rhino3dm, which is not "
                              f"installed: {_INSTALL_HINT}") from None
    if "step" in out and not step_available():
        raise ConfigError("--format step needs the optional package cadquery-ocp (OpenCASCADE), which is "
                          f"not installed: {_INSTALL_HINT}")
    return tuple(out)


def _real(x: float) -> str:
    """A float, exactly (shortest round-trip repr), always with a decimal point."""
    s = repr(float(x))
    if not np.isfinite(x):
        raise ValueError(f"cannot export a non-finite number ({s})")
    if "." not in s:
        mantissa, _, exponent = s.partition("e")
        s = mantissa + ".0" + ("E" + exponent if exponent else "")
    return s.replace("e", "E")


def _u_fastest(a: np.ndarray) -> np.ndarray:
    """An (nu, nv, ...) array flattened with the u index varying fastest."""
    a = np.asarray(a, float)
    return np.swapaxes(a, 0, 1).reshape(a.shape[0] * a.shape[1], *a.shape[2:])


# ---- OBJ free-form block -------------------------------------------------------

def render_obj_nurbs(surface: NurbsSurface, first_vertex: int, name: str = "surface",
                     trim: Trim | None = None) -> str:
    """The exact surface as an OBJ free-form block, to append after the mesh.

    ``first_vertex`` is the 1-based index the first control vertex will get (the mesh
    vertex count + 1): the block starts with its own ``v x y z w`` lines. A trim adds
    its loops first, each a ``curv2`` (``cstype bspline``) over parameter vertices
    ``vp u v``, and the surface then names them: ``trim t0 t1 1`` for the outer
    boundary, ``hole t0 t1 k`` for each hole (the OBJ spec's special curves).
    """
    cp = _u_fastest(surface.control_points)
    w = _u_fastest(surface.weights)
    nu, nv = surface.shape
    u0, u1 = surface.domain_u
    v0, v1 = surface.domain_v
    lines = [f"# psonurbs exact NURBS surface: {nu} x {nv} control vertices (u fastest), "
             f"degrees {surface.degree_u} x {surface.degree_v}"
             + (f", {len(trim.loops)} trim loops (outer, then holes)" if trim is not None else ""),
             f"g {name}"]
    lines += [f"v {_real(x)} {_real(y)} {_real(z)} {_real(wt)}" for (x, y, z), wt in zip(cp, w)]
    loops = [] if trim is None else list(trim.loops)
    first_vp = 1
    for loop in loops:
        lines += [f"vp {_real(u)} {_real(v)}" for u, v in loop.control_points]
        lines.append("cstype bspline")
        lines.append(f"deg {loop.degree}")
        n = len(loop.control_points)
        lines.append("curv2 " + " ".join(str(first_vp + k) for k in range(n)))
        lines.append("parm u " + " ".join(_real(t) for t in loop.knots))
        lines.append("end")
        first_vp += n
    lines.append("cstype rat bspline")
    lines.append(f"deg {surface.degree_u} {surface.degree_v}")
    indices = " ".join(str(first_vertex + k) for k in range(nu * nv))
    lines.append(f"surf {_real(u0)} {_real(u1)} {_real(v0)} {_real(v1)} {indices}")
    lines.append("parm u " + " ".join(_real(k) for k in surface.knots_u))
    lines.append("parm v " + " ".join(_real(k) for k in surface.knots_v))
    for k, loop in enumerate(loops, 1):
        t0, t1 = loop.knots[loop.degree], loop.knots[-loop.degree - 1]
        lines.append(f"{'trim' if k == 1 else 'hole'} {_real(t0)} {_real(t1)} {k}")
    lines.append("end")
    return "\n".join(lines) + "\n"


# ---- Rhino 3DM -----------------------------------------------------------------

#: rhino3dm's Python API builds Breps only from whole surfaces and primitives (no loops or
#: trims can be added, nor a surface trimmed by curves), so a trim travels as curves.
TRIM_3DM_NOTE = ("3dm: rhino3dm cannot build a trimmed Brep, so STEM.3dm holds the untrimmed surface and "
                 "its trim loops as curves lying on it (Rhino: Split or Trim with them); STEP and IGES "
                 "carry the trimmed face")

LOOP_CURVE_SAMPLES = 2000


def render_3dm(surface: NurbsSurface, name: str = "surface", trim: Trim | None = None) -> bytes:
    """A Rhino 3DM file holding the surface as one named object (needs ``rhino3dm``); with a
    trim, also each loop's image on the surface, S(C(t)), as a polyline curve through
    ``LOOP_CURVE_SAMPLES`` of its points (named ``NAME trim 1`` for the outer boundary,
    then the holes): see :data:`TRIM_3DM_NOTE`.

    openNURBS stamps the file with its creation time and object ids, so two exports of
    the same surface are equal as geometry but not byte for byte.
    """
    try:
        import rhino3dm
    except ImportError:
        raise ConfigError(f"3dm export needs the optional package rhino3dm: {_INSTALL_HINT}") from None
    nu, nv = surface.shape
    rational = not _polynomial(surface)
    srf = rhino3dm.NurbsSurface.Create(3, rational, surface.degree_u + 1, surface.degree_v + 1, nu, nv)
    # openNURBS drops the first and last knot of each full vector
    for k, t in enumerate(surface.knots_u[1:-1]):
        srf.KnotsU[k] = float(t)
    for k, t in enumerate(surface.knots_v[1:-1]):
        srf.KnotsV[k] = float(t)
    for i in range(nu):
        for j in range(nv):
            x, y, z = (float(c) for c in surface.control_points[i, j])
            w = float(surface.weights[i, j])
            srf.Points[i, j] = rhino3dm.Point4d(x * w, y * w, z * w, w) if rational \
                else rhino3dm.Point4d(x, y, z, 1.0)
    if not srf.IsValid:
        raise ValueError("rhino3dm rejects the surface as invalid")
    model = rhino3dm.File3dm()
    model.Settings.ModelUnitSystem = rhino3dm.UnitSystem.Millimeters
    attributes = rhino3dm.ObjectAttributes()
    attributes.Name = name
    model.Objects.AddSurface(srf, attributes)
    for k, loop in enumerate(trim.loops if trim is not None else (), 1):
        uv = loop.polygon(LOOP_CURVE_SAMPLES)
        xyz = surface.evaluate(uv[:, 0], uv[:, 1])
        points = [rhino3dm.Point3d(*(float(c) for c in p)) for p in np.concatenate([xyz, xyz[:1]])]
        curve_attributes = rhino3dm.ObjectAttributes()
        curve_attributes.Name = f"{name} trim {k} ({'outer boundary' if k == 1 else 'hole'})"
        model.Objects.AddCurve(rhino3dm.PolylineCurve(points), curve_attributes)
    return base64.b64decode(model.Encode())


def _polynomial(surface: NurbsSurface) -> bool:
    w = np.asarray(surface.weights)
    return bool(np.all(w == w.flat[0]))


# ---- IGES 5.3 ------------------------------------------------------------------

_DATE = "19700101.000000"  # fixed: the same fit gives the same file


def _ascii(text: str) -> str:
    return re.sub(r"[^ -~]", "_", text)


def _hollerith(text: str) -> str:
    text = _ascii(text)
    return f"{len(text)}H{text}" if text else ""


def _pack(tokens: list[str], width: int) -> list[str]:
    """Join tokens (each ending in its delimiter) into lines of at most ``width``
    characters, never splitting a token."""
    lines, line = [], ""
    for tok in tokens:
        if len(tok) > width:
            raise ValueError(f"IGES parameter longer than a line: {tok[:20]}...")
        if len(line) + len(tok) > width:
            lines.append(line)
            line = ""
        line += tok
    if line:
        lines.append(line)
    return lines


def _record(data: str, section: str, seq: int) -> str:
    if len(data) > 72:
        raise AssertionError("IGES record data longer than 72 columns")
    return f"{data:<72}{section}{seq:7d}"


def _tokens(values: list[str], end: str = ";") -> list[str]:
    return [v + "," for v in values[:-1]] + [values[-1] + end]


def _surface_parameters(surface: NurbsSurface) -> list[str]:
    """Entity 128 (rational B-spline surface)."""
    nu, nv = surface.shape
    u0, u1 = surface.domain_u
    v0, v1 = surface.domain_v
    params = [str(128), str(nu - 1), str(nv - 1), str(surface.degree_u), str(surface.degree_v),
              str(int(surface.closed_u)), str(int(surface.closed_v)), str(int(_polynomial(surface))),
              str(int(surface.closed_u)), str(int(surface.closed_v))]
    params += [_real(t) for t in surface.knots_u]
    params += [_real(t) for t in surface.knots_v]
    params += [_real(w) for w in _u_fastest(surface.weights)]
    params += [_real(c) for c in _u_fastest(np.asarray(surface.control_points, float)).ravel()]
    return params + [_real(u0), _real(u1), _real(v0), _real(v1)]


def _loop_parameters(loop) -> list[str]:
    """Entity 126 (B-spline curve) for a trim loop: planar (z = 0) in the (u, v) domain, closed."""
    n, d = len(loop.control_points), loop.degree
    params = [str(126), str(n - 1), str(d), "1", "1", "1", "0"]
    params += [_real(t) for t in loop.knots]
    params += ["1.0"] * n
    for u, v in loop.control_points:
        params += [_real(u), _real(v), "0.0"]
    return params + [_real(loop.knots[d]), _real(loop.knots[n]), "0.0", "0.0", "1.0"]


def render_iges(surface: NurbsSurface, name: str = "surface", trim: Trim | None = None) -> str:
    """An IGES 5.3 file with the surface as a rational B-spline surface (entity 128); with a
    trim, as a trimmed surface (entity 144) on it, whose boundaries are curves on the
    surface (entity 142) given by their parameter-space curves (entity 126, z = 0).

    Fixed 80-column records: Start, Global, Directory Entry, Parameter Data and
    Terminate sections; the dates in the Global section are fixed, so the same
    surface always gives the same file.
    """
    nu, nv = surface.shape
    p, q = surface.degree_u, surface.degree_v
    cp = np.asarray(surface.control_points, float)
    what = "trimmed surface (entity 144) on a " if trim is not None else ""
    start = [f"psonurbs NURBS surface {_ascii(name)}: {what}rational B-spline surface (entity 128), "
             f"{nu} x {nv} control points, degrees {p} x {q}"]
    if trim is not None:
        start[0] += f", {len(trim.loops)} trim loops (entities 142, 126)"
    start_lines = [start[0][i:i + 72] for i in range(0, len(start[0]), 72)]

    coord = float(np.max(np.abs(cp))) if cp.size else 1.0
    extent = float(np.linalg.norm(cp.reshape(-1, 3).max(0) - cp.reshape(-1, 3).min(0)))
    resolution = max(extent, 1.0) * 1e-9
    from psonurbs import __version__
    global_params = [
        "1H,", "1H;",
        _hollerith(name), _hollerith(f"{name}.igs"), _hollerith("psonurbs"),
        _hollerith(f"psonurbs {__version__}"),
        "32", "38", "6", "308", "15",
        _hollerith(name), "1.0", "2", "2HMM", "1", "1.0",
        f"15H{_DATE}", _real(resolution), _real(max(coord, resolution)),
        "", "", "11", "0", f"15H{_DATE}", "",
    ]
    global_lines = _pack(_tokens(global_params), 72)

    # entities: (type, parameters, status, label); DE pointers are 2k + 1 in this order
    label = _ascii(name)[:8].upper() or "SURFACE"
    if trim is None:
        entities = [(128, _surface_parameters(surface), "00000000", label)]
    else:
        k = len(trim.loops)
        surface_de = 1
        curve_de = [3 + 2 * i for i in range(k)]
        on_surface_de = [3 + 2 * k + 2 * i for i in range(k)]
        entities = [(128, _surface_parameters(surface), "00010000", label)]
        entities += [(126, _loop_parameters(loop), "00010500", "LOOP") for loop in trim.loops]
        entities += [(142, ["142", "0", str(surface_de), str(de), "0", "1"], "00010000", "BOUNDARY")
                     for de in curve_de]
        entities.append((144, ["144", str(surface_de), "1", str(k - 1), *(str(de) for de in on_surface_de)],
                         "00000000", label))
    directory, param_records = [], []
    for index, (kind, params, status, tag) in enumerate(entities):
        de = 2 * index + 1
        lines = _pack(_tokens(params), 64)
        first = len(param_records) + 1
        param_records += [f"{pl:<64}{de:>8}" for pl in lines]
        directory.append("".join(f"{f:>8}" for f in (kind, first, 0, 0, 0, 0, 0, 0, status)))
        directory.append("".join(f"{f:>8}" for f in (kind, 0, 0, len(lines), 0, "", "", tag, 0)))
    out = [_record(s, "S", i) for i, s in enumerate(start_lines, 1)]
    out += [_record(g, "G", i) for i, g in enumerate(global_lines, 1)]
    out += [_record(d, "D", i) for i, d in enumerate(directory, 1)]
    out += [_record(pl, "P", i) for i, pl in enumerate(param_records, 1)]
    counts = (f"S{len(start_lines):7d}G{len(global_lines):7d}D{len(directory):7d}"
              f"P{len(param_records):7d}")
    out.append(_record(counts, "T", 1))
    return "\n".join(out) + "\n"


# ---- all of them ---------------------------------------------------------------

def render_exports(surface: NurbsSurface, formats: Iterable[str], name: str,
                   mesh_vertices: int, trim: Trim | None = None) -> tuple[str, dict[str, bytes | str]]:
    """Render the requested formats.

    Returns ``(obj_block, files)``: the text to append to ``STEM.obj`` (empty unless
    ``obj-nurbs`` is asked for) and the extra files by suffix (``".igs"``, ``".3dm"``).
    """
    obj_block, files = "", {}
    for fmt in formats:
        if fmt == "obj-nurbs":
            obj_block = render_obj_nurbs(surface, mesh_vertices + 1, name, trim)
        elif fmt == "iges":
            files[".igs"] = render_iges(surface, name, trim)
        elif fmt == "3dm":
            files[".3dm"] = render_3dm(surface, name, trim)
        elif fmt == "step":
            files[".step"] = render_step(surface, trim, name)
        else:
            raise ConfigError(f"unknown export format {fmt!r}")
    return obj_block, files
