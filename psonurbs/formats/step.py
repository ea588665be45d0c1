"""STEP export (AP214) of a fitted surface through OpenCASCADE (the optional ``cadquery-ocp``).

The file holds one ADVANCED_FACE on a B_SPLINE_SURFACE_WITH_KNOTS (rational when the
weights differ), bounded by its trim loops (each an edge whose curve on the surface is
the loop, B_SPLINE_CURVE_WITH_KNOTS in (u, v), with its 3D curve built by OpenCASCADE),
or by the surface's own boundary when it is untrimmed. OpenCASCADE's conventions are
ours: poles [i][j] with i along u, flat knot vectors as (distinct knots, multiplicities),
the domain [t_p, t_{n}] (so a closed direction's unclamped periodic vector works as it
is), weights beside the poles. The face's material is on the left of its wires: the
outer loop counter-clockwise, holes clockwise, as in the JSON. A surface that closes on
itself untrimmed (a sphere's, a torus's: closed directions and poles, no free edge) is
written as the solid it bounds (:func:`sew`), its closed directions periodic.

OCP is large: it is imported only when a STEP file is written.
"""
from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass

import numpy as np

from psonurbs.errors import ConfigError
from psonurbs.geometry.nurbs import NurbsSurface
from psonurbs.geometry.trim import Trim

__all__ = ["step_available", "render_step", "render_step_shape", "render_iges_shape", "compound_of", "sew",
           "Sewn"]

INSTALL_HINT = "pip install 'psonurbs[cad]'"
TOLERANCE = 1e-7  # OpenCASCADE's edge and vertex tolerance (cloud units)
_FIXED_TIME = "1970-01-01T00:00:00"  # the same fit gives the same file
VOLUME_EPS = 1e-7  # relative accuracy of a solid's volume (OpenCASCADE's adaptive integration)


@dataclass(frozen=True)
class Sewn:
    """Faces sewn: the shape (a solid when they close, else the sewn shell or face),
    whether they closed (no free edge, one shell), whether OpenCASCADE's check finds it
    valid, the solid's volume (None when open), the free edges and the widest gap the
    sewing bridged (its largest edge tolerance)."""

    shape: object
    closed: bool
    valid: bool
    volume: float | None
    free_edges: int
    gap: float


def step_available() -> bool:
    try:
        import OCP.STEPControl  # noqa: F401
    except ImportError:
        return False
    return True


def _knots(flat: np.ndarray):
    """A flat knot vector as OpenCASCADE's (distinct knots, multiplicities) arrays."""
    from OCP.collections import Array1_double, Array1_int

    values, counts = np.unique(np.asarray(flat, float), return_counts=True)
    knots, mults = Array1_double(1, len(values)), Array1_int(1, len(values))
    for k, (t, m) in enumerate(zip(values, counts), 1):
        knots.SetValue(k, float(t))
        mults.SetValue(k, int(m))
    return knots, mults


def occ_surface(surface: NurbsSurface, periodic: bool = False):
    """The surface as a ``Geom_BSplineSurface`` (rational unless all weights are equal).

    ``periodic``: a closed direction becomes OpenCASCADE's periodic B-spline (the
    domain's knots once each, the net without its ``degree`` repeated rows), so that a
    face of it has one seam edge and a shell can close across it; otherwise the closed
    direction's net and unclamped knots are written as they are (the same surface, its
    two seam edges apart)."""
    from OCP.collections import Array2_double, Array2_gp_Pnt
    from OCP.Geom import Geom_BSplineSurface
    from OCP.gp import gp_Pnt

    wrap = [periodic and closed for closed in (surface.closed_u, surface.closed_v)]
    nu, nv = surface.shape
    nu, nv = nu - wrap[0] * surface.degree_u, nv - wrap[1] * surface.degree_v
    poles, weights = Array2_gp_Pnt(1, nu, 1, nv), Array2_double(1, nu, 1, nv)
    for i in range(nu):
        for j in range(nv):
            poles.SetValue(i + 1, j + 1, gp_Pnt(*(float(c) for c in surface.control_points[i, j])))
            weights.SetValue(i + 1, j + 1, float(surface.weights[i, j]))
    flat = [k[p:len(k) - p] if w else k for k, p, w in ((surface.knots_u, surface.degree_u, wrap[0]),
                                                         (surface.knots_v, surface.degree_v, wrap[1]))]
    (ku, mu), (kv, mv) = _knots(flat[0]), _knots(flat[1])
    if np.all(surface.weights == surface.weights.flat[0]):
        return Geom_BSplineSurface(poles, ku, kv, mu, mv, surface.degree_u, surface.degree_v, *wrap)
    return Geom_BSplineSurface(poles, weights, ku, kv, mu, mv, surface.degree_u, surface.degree_v, *wrap)


def occ_face(surface: NurbsSurface, trim: Trim | None):
    """A ``TopoDS_Face`` of the surface bounded by the trim's loops (or its own boundary)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge, BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakeWire
    from OCP.BRepLib import BRepLib
    from OCP.collections import Array1_gp_Pnt2d
    from OCP.Geom2d import Geom2d_BSplineCurve
    from OCP.gp import gp_Pnt2d

    geom = occ_surface(surface)
    if trim is None:
        maker = BRepBuilderAPI_MakeFace(geom, TOLERANCE)
        if not maker.IsDone():
            raise ValueError("OpenCASCADE could not make a face of the surface")
        return maker.Face()
    wires = []
    for loop in trim.loops:
        poles = Array1_gp_Pnt2d(1, len(loop.control_points))
        for k, (u, v) in enumerate(loop.control_points, 1):
            poles.SetValue(k, gp_Pnt2d(float(u), float(v)))
        knots, mults = _knots(loop.knots)
        curve = Geom2d_BSplineCurve(poles, knots, mults, loop.degree, False)
        edge = BRepBuilderAPI_MakeEdge(curve, geom).Edge()
        wire = BRepBuilderAPI_MakeWire(edge).Wire()
        BRepLib.BuildCurves3d_s(wire, TOLERANCE)
        wires.append(wire)
    maker = BRepBuilderAPI_MakeFace(geom, wires[0], True)
    for wire in wires[1:]:
        maker.Add(wire)
    if not maker.IsDone():
        raise ValueError("OpenCASCADE could not make a face of the trimmed surface")
    face = maker.Face()
    BRepLib.SameParameter_s(face, TOLERANCE)
    return face


def compound_of(faces) -> object:
    """The faces ((surface, Trim or None) pairs) side by side as one OpenCASCADE compound,
    not sewn."""
    _require_ocp()
    from OCP.BRep import BRep_Builder
    from OCP.TopoDS import TopoDS_Compound

    compound, builder = TopoDS_Compound(), BRep_Builder()
    builder.MakeCompound(compound)
    for surface, trim in faces:
        builder.Add(compound, occ_face(surface, trim))
    return compound


def sew(faces: list, tolerance: float) -> Sewn:
    """OpenCASCADE faces sewn at ``tolerance`` (``BRepBuilderAPI_Sewing``); with no free
    edge and one shell, that shell made a solid (oriented outward, ``ShapeFix_Solid``)."""
    from OCP.BRep import BRep_Builder, BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeSolid, BRepBuilderAPI_Sewing
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.ShapeFix import ShapeFix_Solid
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS, TopoDS_Shell

    sewing = BRepBuilderAPI_Sewing(tolerance)
    for face in faces:
        sewing.Add(face)
    sewing.Perform()
    sewn = sewing.SewedShape()
    free = int(sewing.NbFreeEdges())
    shells = []
    explorer = TopExp_Explorer(sewn, TopAbs_SHELL)
    while explorer.More():
        shells.append(TopoDS.Shell(explorer.Current()))
        explorer.Next()
    if not shells and sewn.ShapeType() == TopAbs_FACE:  # one face closed on itself is no shell yet
        shell, builder = TopoDS_Shell(), BRep_Builder()
        builder.MakeShell(shell)
        builder.Add(shell, sewn)
        shells = [shell]
    shape, volume, closed = sewn, None, False
    if free == 0 and len(shells) == 1:
        fix = ShapeFix_Solid(BRepBuilderAPI_MakeSolid(shells[0]).Solid())
        fix.Perform()
        shape, closed = fix.Solid(), True
        props = GProp_GProps()
        BRepGProp.VolumeProperties_s(shape, props, VOLUME_EPS, False)  # adaptive: the plain rule is 1-2% off
        volume = abs(float(props.Mass()))
    gap, edges = 0.0, TopExp_Explorer(shape, TopAbs_EDGE)
    while edges.More():
        gap = max(gap, float(BRep_Tool.Tolerance_s(TopoDS.Edge(edges.Current()))))
        edges.Next()
    return Sewn(shape, closed, bool(BRepCheck_Analyzer(shape).IsValid()), volume, free, gap)


def closed_solid(surface: NurbsSurface) -> Sewn | None:
    """The solid an untrimmed surface bounds when it closes on itself (no free edge:
    closed directions, the rest collapsed to poles), else None."""
    if not (surface.closed_u or surface.closed_v):
        return None
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace

    sewn = sew([BRepBuilderAPI_MakeFace(occ_surface(surface, periodic=True), TOLERANCE).Face()], TOLERANCE)
    return sewn if sewn.closed else None


def render_step(surface: NurbsSurface, trim: Trim | None = None, name: str = "surface") -> bytes:
    """A STEP AP214 file with the (trimmed) surface as one ADVANCED_FACE, or the solid
    it bounds when it closes on itself untrimmed (needs OCP)."""
    _require_ocp()
    solid = closed_solid(surface) if trim is None else None
    return render_step_shape(occ_face(surface, trim) if solid is None else solid.shape, name)


def render_step_shape(shape, name: str = "surface") -> bytes:
    """A STEP AP214 file of an OpenCASCADE shape (a face, a shell, a solid)."""
    _require_ocp()
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
    from OCP.TCollection import TCollection_HAsciiString

    _quiet()
    Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    writer = STEPControl_Writer()
    if writer.Transfer(shape, STEPControl_AsIs) != IFSelect_RetDone:
        raise ValueError("OpenCASCADE could not translate the shape to STEP")
    header = APIHeaderSection_MakeHeader(writer.Model())
    header.SetTimeStamp(TCollection_HAsciiString(_FIXED_TIME))
    from psonurbs import __version__
    header.SetOriginatingSystem(TCollection_HAsciiString(f"psonurbs {__version__}"))
    fd, tmp = tempfile.mkstemp(suffix=".step")
    os.close(fd)
    try:
        if writer.Write(tmp) != IFSelect_RetDone:
            raise ValueError("OpenCASCADE could not write the STEP file")
        with open(tmp, "rb") as f:
            data = f.read()
    finally:
        os.unlink(tmp)
    # the writer's time stamp and its numbered product name: fixed, so the same fit gives the same file
    data = re.sub(rb"FILE_NAME\('([^']*)','[^']*'", lambda m: b"FILE_NAME('" + m.group(1) + b"','"
                  + _FIXED_TIME.encode() + b"'", data, count=1)
    label = _step_string(name).encode()
    return re.sub(rb"= PRODUCT\('[^']*',\s*'[^']*'", b"= PRODUCT('" + label + b"','" + label + b"'", data, count=1)


def render_iges_shape(shape) -> str:
    """An IGES file of an OpenCASCADE shape, its faces as trimmed B-spline surfaces."""
    _require_ocp()
    from OCP.IGESControl import IGESControl_Writer

    _quiet()
    writer = IGESControl_Writer("MM", 0)  # 0: each face a trimmed surface (entity 144), as most readers take them
    writer.AddShape(shape)
    writer.ComputeModel()
    fd, tmp = tempfile.mkstemp(suffix=".igs")
    os.close(fd)
    try:
        if not writer.Write(tmp):
            raise ValueError("OpenCASCADE could not write the IGES file")
        with open(tmp, encoding="ascii", errors="replace") as f:
            text = f.read()
    finally:
        os.unlink(tmp)
    # the writer's date stamps (15H...): fixed, so the same fit gives the same file
    return re.sub(r"15H\d{8}\.\d{6}", "15H19700101.000000", text)


def _require_ocp() -> None:
    if not step_available():
        raise ConfigError(f"step export needs the optional package cadquery-ocp: {INSTALL_HINT}")


def _step_string(text: str) -> str:
    return re.sub(r"[^ -~]|'|\\", "_", text) or "surface"


def _quiet() -> None:
    """OpenCASCADE's messages (transfer statistics) are for its own console, not ours."""
    from OCP.Message import Message, Message_Gravity

    printers = Message.DefaultMessenger_s().Printers()
    for printer in printers:
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
