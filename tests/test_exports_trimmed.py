"""Trimmed (and untrimmed) surfaces read back by an independent kernel: STEP and IGES by
OpenCASCADE (one valid face, its wires, the surface evaluating as ours within 1e-9 of the
diagonal), OBJ's curv2/trim/hole by a parser here (scipy evaluates the loops), 3DM by
rhino3dm (the surface and its loops as curves on it: rhino3dm cannot build a trimmed Brep)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import closed_u_surface, open_surface
from scipy.interpolate import BSpline
from test_exports import assert_same_points, diagonal, sample_params
from test_trim import plate_trim

from psonurbs.errors import ConfigError
from psonurbs.formats.cad import check_formats, render_3dm, render_iges, render_obj_nurbs
from psonurbs.geometry.trim import Trim


def occ_faces(shape):
    from OCP.TopAbs import TopAbs_FACE, TopAbs_WIRE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    faces, explorer = [], TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        faces.append(TopoDS.Face(explorer.Current()))
        explorer.Next()
    wires = []
    for face in faces:
        explorer, n = TopExp_Explorer(face, TopAbs_WIRE), 0
        while explorer.More():
            n += 1
            explorer.Next()
        wires.append(n)
    return faces, wires


def check_occ_shape(shape, surface, loops: int):
    from OCP.BRep import BRep_Tool
    from OCP.BRepCheck import BRepCheck_Analyzer

    faces, wires = occ_faces(shape)
    assert len(faces) == 1 and wires == [loops]
    assert BRepCheck_Analyzer(shape).IsValid()
    geom = BRep_Tool.Surface_s(faces[0])
    uv = sample_params(surface)
    pts = np.array([[p.X(), p.Y(), p.Z()] for p in (geom.Value(float(u), float(v)) for u, v in uv)])
    assert_same_points(surface, pts, uv)
    return faces[0]


def step_read_back(tmp_path, surface, name: str):
    """The untrimmed surface's STEP file as OpenCASCADE reads it back (its one shape)."""
    from OCP.STEPControl import STEPControl_Reader

    from psonurbs.formats.step import render_step

    path = tmp_path / f"{name}.step"
    path.write_bytes(render_step(surface, None, name))
    reader = STEPControl_Reader()
    reader.ReadFile(str(path))
    reader.TransferRoots()
    return reader.OneShape()


def face_area(face) -> float:
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, props)
    return props.Mass()


def trimmed_area(surface, trim: Trim, n: int = 400) -> float:
    """The trimmed face's area by the midpoint rule (our side of the comparison)."""
    s = (np.arange(n) + 0.5) / n
    uu, vv = np.meshgrid(s, s, indexing="ij")
    _, su, sv = surface.derivatives(uu.ravel(), vv.ravel())
    dA = np.linalg.norm(np.cross(su, sv), axis=1) / n / n
    return float(dA[trim.contains(np.c_[uu.ravel(), vv.ravel()])].sum())


@pytest.mark.parametrize("trimmed", [True, False], ids=["trimmed", "untrimmed"])
def test_step_read_back_by_opencascade(tmp_path, trimmed):
    pytest.importorskip("OCP")
    from OCP.STEPControl import STEPControl_Reader

    from psonurbs.formats.step import render_step

    s, trim = open_surface(), plate_trim() if trimmed else None
    data = render_step(s, trim, "plate")
    assert data == render_step(s, trim, "plate")  # byte-identical
    text = data.decode()
    assert "FILE_SCHEMA(('AUTOMOTIVE_DESIGN" in text and text.count("ADVANCED_FACE(") == 1
    assert "B_SPLINE_SURFACE_WITH_KNOTS" in text and "RATIONAL_B_SPLINE_SURFACE" in text
    path = tmp_path / "s.step"
    path.write_bytes(data)
    reader = STEPControl_Reader()
    reader.ReadFile(str(path))
    reader.TransferRoots()
    face = check_occ_shape(reader.OneShape(), s, len(trim.loops) if trimmed else 1)
    if trimmed:
        assert face_area(face) == pytest.approx(trimmed_area(s, trim), rel=2e-3)


def test_step_of_a_closed_surface(tmp_path):
    pytest.importorskip("OCP")
    s = closed_u_surface()
    faces, _ = occ_faces(step_read_back(tmp_path, s, "tube"))
    assert len(faces) == 1
    from OCP.BRep import BRep_Tool
    geom = BRep_Tool.Surface_s(faces[0])
    uv = sample_params(s)
    pts = np.array([[p.X(), p.Y(), p.Z()] for p in (geom.Value(float(u), float(v)) for u, v in uv)])
    assert_same_points(s, pts, uv)


@pytest.mark.parametrize("closes, axes", [(True, (1.0, 1.0, 1.0)), (True, (1.0, 0.7, 1.6)), (False, None)],
                         ids=["sphere", "ellipsoid", "tube"])
def test_step_of_a_surface_closed_on_itself_is_its_solid(tmp_path, closes, axes):
    """A sphere-topology fit (closed in u, poles at both ends of v) has no free edge: its
    STEP is the solid it bounds, valid, of the volume it encloses (4/3 pi abc for an
    ellipsoid, the fit within 1e-3); a tube keeps its two rims and stays one face."""
    pytest.importorskip("OCP")
    from OCP.BRepCheck import BRepCheck_Analyzer
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer

    if closes:
        from psonurbs.config import config_from_dict
        from psonurbs.fitting.parameters.closed import parametrise_sphere
        from psonurbs.fitting.parameters.topology import classical_surface
        from psonurbs.geometry.net import NetLayout

        k = np.arange(4000) + 0.5  # a Fibonacci sphere, stretched to the ellipsoid
        z, a = 1 - 2 * k / 4000, np.pi * (1 + 5 ** 0.5) * k
        pts = np.column_stack([np.sqrt(1 - z ** 2) * np.cos(a), np.sqrt(1 - z ** 2) * np.sin(a), z]) * axes
        layout = NetLayout((12, 10), (3, 3), (True, False), poles=True)
        s = classical_surface(layout, parametrise_sphere(pts), pts, config_from_dict({}))
    else:
        s = closed_u_surface()
    shape = step_read_back(tmp_path, s, "closed")
    solids = TopExp_Explorer(shape, TopAbs_SOLID)
    assert solids.More() == closes and len(occ_faces(shape)[0]) == 1
    assert BRepCheck_Analyzer(shape).IsValid()
    if closes:
        props = GProp_GProps()
        BRepGProp.VolumeProperties_s(shape, props, 1e-7, False)
        assert props.Mass() == pytest.approx(4 / 3 * np.pi * np.prod(axes), rel=1e-3)


def test_iges_trimmed_surface_read_back_by_opencascade(tmp_path):
    pytest.importorskip("OCP")
    from OCP.IGESControl import IGESControl_Reader

    s, trim = open_surface(), plate_trim()
    text = render_iges(s, "plate", trim)
    assert all(len(line) == 80 for line in text.splitlines())
    kinds = [int(line[:8]) for line in text.splitlines() if line[72] == "D"][::2]
    assert kinds == [128, 126, 126, 142, 142, 144]
    path = tmp_path / "s.igs"
    path.write_text(text)
    reader = IGESControl_Reader()
    reader.ReadFile(str(path))
    reader.TransferRoots()
    face = check_occ_shape(reader.OneShape(), s, len(trim.loops))
    assert face_area(face) == pytest.approx(trimmed_area(s, trim), rel=2e-3)


def parse_obj_trim(text: str):
    """The loops of an OBJ free-form block: (kind, degree, knots, control points (n, 2))."""
    vp, curves, out, deg = [], [], [], None
    lines = iter(text.splitlines())
    for line in lines:
        f = line.split()
        if not f:
            continue
        if f[0] == "vp":
            vp.append([float(f[1]), float(f[2])])
        elif f[0] == "deg":
            deg = [int(x) for x in f[1:]]
        elif f[0] == "curv2":
            idx = [int(x) - 1 for x in f[1:]]
            knots = [float(x) for x in next(lines).split()[2:]]
            curves.append((deg[0], np.array(knots), np.array(vp)[idx]))
        elif f[0] in ("trim", "hole"):
            t0, t1, k = float(f[1]), float(f[2]), int(f[3])
            degree, knots, cps = curves[k - 1]
            assert (t0, t1) == (knots[degree], knots[-degree - 1])
            out.append((f[0], degree, knots, cps))
    return out


def test_obj_trim_and_hole_statements_read_back():
    s, trim = open_surface(), plate_trim()
    loops = parse_obj_trim(render_obj_nurbs(s, 1, "plate", trim))
    assert [kind for kind, *_ in loops] == ["trim", "hole"]
    t = np.linspace(0, 1, 301)
    for (_, degree, knots, cps), loop in zip(loops, trim.loops):
        assert np.abs(BSpline(knots, cps, degree)(t) - loop.evaluate(t)).max() == 0.0


def test_3dm_carries_the_surface_and_its_loops_as_curves(tmp_path):
    rhino3dm = pytest.importorskip("rhino3dm")
    s, trim = open_surface(), plate_trim()
    path = tmp_path / "s.3dm"
    path.write_bytes(render_3dm(s, "plate", trim))
    model = rhino3dm.File3dm.Read(str(path))
    names = [o.Attributes.Name for o in model.Objects]
    assert names == ["plate", "plate trim 1 (outer boundary)", "plate trim 2 (hole)"]
    for obj, loop in zip(list(model.Objects)[1:], trim.loops):
        curve = obj.Geometry
        assert curve.IsClosed
        uv = loop.polygon(2000)
        on = s.evaluate(uv[:, 0], uv[:, 1])
        pts = np.array([[p.X, p.Y, p.Z] for p in (curve.PointAt(curve.Domain.T0 + k) for k in range(0, 2000, 97))])
        assert np.abs(pts - on[::97]).max() <= 1e-9 * diagonal(s)


def test_step_missing_ocp_is_a_clear_config_error(monkeypatch):
    import psonurbs.formats.cad as cad

    monkeypatch.setattr(cad, "step_available", lambda: False)
    with pytest.raises(ConfigError, match=r"cadquery-ocp.*pip install 'psonurbs\[cad\]'"):
        check_formats(["iges", "step"])


def test_fit_refuses_step_without_ocp_before_fitting(tmp_path, monkeypatch):
    from conftest import run

    import psonurbs.formats.cad as cad

    monkeypatch.setattr(cad, "step_available", lambda: False)
    result = run("fit", "no_such_cloud.ply", "-o", str(tmp_path), "--format", "step")
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line]
    assert lines == ["psonurbs: error: --format step needs the optional package cadquery-ocp (OpenCASCADE), "
                     "which is not installed: pip install 'psonurbs[cad]'"]
