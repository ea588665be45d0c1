"""CAD exports read back by independent readers.

3DM: rhino3dm (openNURBS's own evaluator). IGES: pyiges's parser, evaluated with the
scipy reference of conftest.py. OBJ: a small parser in this file, evaluated the same way. Each must
give the same points as psonurbs's NurbsSurface within 1e-9 of the diagonal, for an
open rational surface, a polynomial one and one closed (periodic) in u.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import closed_u_surface, open_surface, reference_evaluate

from psonurbs.errors import ConfigError
from psonurbs.formats.cad import check_formats, render_3dm, render_iges, render_obj_nurbs
from psonurbs.geometry.nurbs import NurbsSurface

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"


SURFACES = {"open": open_surface, "polynomial": lambda: open_surface(True), "closed_u": closed_u_surface}


def diagonal(surface: NurbsSurface) -> float:
    pts = surface.evaluate_grid(*surface.parameter_grid(30, 30)).reshape(-1, 3)
    return float(np.linalg.norm(pts.max(0) - pts.min(0)))


def sample_params(surface: NurbsSurface, n: int = 23) -> np.ndarray:
    us = np.linspace(*surface.domain_u, n)
    vs = np.linspace(*surface.domain_v, n)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    return np.stack([uu.ravel(), vv.ravel()], -1)


def reference_evaluate_uv(ku, kv, p, q, cp, w, uv) -> np.ndarray:
    return reference_evaluate(ku, kv, p, q, cp, w, uv[:, 0], uv[:, 1])


def assert_same_points(surface, points, uv):
    ours = surface.evaluate(uv[:, 0], uv[:, 1])
    err = np.abs(points - ours).max()
    assert err <= 1e-9 * diagonal(surface), err


def test_scipy_reference_agrees_with_psonurbs():
    s = open_surface()
    uv = sample_params(s)
    assert_same_points(s, reference_evaluate_uv(s.knots_u, s.knots_v, s.degree_u, s.degree_v,
                                         s.control_points, s.weights, uv), uv)


def test_closed_surface_is_closed():
    s = closed_u_surface()
    v = np.linspace(0, 1, 7)
    a, b = s.domain_u
    assert np.allclose(s.evaluate(np.full(7, a), v), s.evaluate(np.full(7, b), v), atol=1e-12)


# ---- 3DM -----------------------------------------------------------------------

@pytest.mark.parametrize("kind", SURFACES)
def test_3dm_read_back_by_rhino3dm(tmp_path, kind):
    rhino3dm = pytest.importorskip("rhino3dm")
    s = SURFACES[kind]()
    path = tmp_path / "s.3dm"
    path.write_bytes(render_3dm(s, "bump"))
    model = rhino3dm.File3dm.Read(str(path))
    assert len(model.Objects) == 1
    obj = model.Objects[0]
    assert obj.Attributes.Name == "bump"
    srf = obj.Geometry
    assert isinstance(srf, rhino3dm.NurbsSurface)
    assert (srf.OrderU, srf.OrderV) == (s.degree_u + 1, s.degree_v + 1)
    assert (srf.Points.CountU, srf.Points.CountV) == s.shape
    # openNURBS: n + degree - 1 knots, the full vector without its first and last knot
    assert list(srf.KnotsU) == list(s.knots_u[1:-1])
    assert list(srf.KnotsV) == list(s.knots_v[1:-1])
    assert srf.IsRational == (kind != "polynomial")
    dom_u, dom_v = srf.Domain(0), srf.Domain(1)
    assert (dom_u.T0, dom_u.T1) == s.domain_u and (dom_v.T0, dom_v.T1) == s.domain_v
    if kind == "closed_u":
        assert srf.IsClosed(0) and srf.IsPeriodic(0) and not srf.IsClosed(1)
    uv = sample_params(s)
    pts = np.array([[c.X, c.Y, c.Z] for c in (srf.PointAt(float(u), float(v)) for u, v in uv)])
    assert_same_points(s, pts, uv)


def test_3dm_missing_rhino3dm_is_a_clear_config_error(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_rhino(name, *args, **kwargs):
        if name == "rhino3dm":
            raise ImportError("No module named 'rhino3dm'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rhino)
    with pytest.raises(ConfigError, match=r"rhino3dm.*pip install 'psonurbs\[cad\]'"):
        check_formats(["iges", "3dm"])
    assert check_formats(["iges", "obj-nurbs", "iges"]) == ("iges", "obj-nurbs")


# ---- IGES ----------------------------------------------------------------------

@pytest.mark.parametrize("kind", SURFACES)
def test_iges_read_back_by_pyiges(tmp_path, kind):
    pyiges = pytest.importorskip("pyiges")
    s = SURFACES[kind]()
    text = render_iges(s, "bump")
    path = tmp_path / "s.igs"
    path.write_text(text)
    iges = pyiges.read(str(path))
    (entity,) = iges.bspline_surfaces()
    nu, nv = s.shape
    assert (entity.k1, entity.k2, entity.m1, entity.m2) == (nu - 1, nv - 1, s.degree_u, s.degree_v)
    # PROP1..5: closed u, closed v, polynomial, periodic u, periodic v
    assert (entity.flag1, entity.flag2, entity.flag3, entity.flag4, entity.flag5) == \
        (kind == "closed_u", False, kind == "polynomial", kind == "closed_u", False)
    assert np.array_equal(entity.knot1, s.knots_u) and np.array_equal(entity.knot2, s.knots_v)
    # IGES lists weights and points with the first (u) index varying fastest
    w = np.asarray(entity.weights).reshape(nv, nu).T
    cp = np.asarray(entity.control_points()).reshape(nv, nu, 3).transpose(1, 0, 2)
    assert np.array_equal(w, s.weights) and np.array_equal(cp, s.control_points)
    uv = sample_params(s)
    assert_same_points(s, reference_evaluate_uv(entity.knot1, entity.knot2, entity.m1, entity.m2, cp, w, uv), uv)


def test_iges_layout_is_fixed_80_columns():
    s = open_surface()
    lines = render_iges(s, "a name with ünïcode, commas; and a long tail").splitlines()
    assert all(len(line) == 80 for line in lines)
    assert all(line.isascii() for line in lines)
    sections = [line[72] for line in lines]
    assert sections == sorted(sections, key="SGDPT".index)  # S, G, D, P, T in this order
    for sec in "SGDP":  # sequence numbers 1, 2, ... in each section
        seq = [int(line[73:]) for line in lines if line[72] == sec]
        assert seq == list(range(1, len(seq) + 1))
    term = lines[-1]
    counts = {term[i]: int(term[i + 1:i + 8]) for i in range(0, 32, 8)}
    assert counts == {sec: sections.count(sec) for sec in "SGDP"}
    d1, d2 = [line for line in lines if line[72] == "D"]
    assert int(d1[:8]) == 128 and int(d1[8:16]) == 1 and int(d2[:8]) == 128
    assert int(d2[24:32]) == sections.count("P")  # parameter line count
    assert all(int(line[64:72]) == 1 for line in lines if line[72] == "P")  # DE pointer
    glob = "".join(line[:72] for line in lines if line[72] == "G").rstrip()
    assert glob.startswith("1H,,1H;,") and glob.endswith(";")
    assert ",11,0," in glob  # version flag 11 = IGES 5.3, drafting standard 0


def test_iges_is_deterministic():
    assert render_iges(open_surface(), "x") == render_iges(open_surface(), "x")


# ---- OBJ free-form block -------------------------------------------------------

def parse_obj_nurbs(text: str):
    """A minimal reader of one OBJ `cstype rat bspline` surface (independent of psonurbs)."""
    vertices, state = [], {}
    for line in text.splitlines():
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if words[0] == "v":
            xyzw = [float(x) for x in words[1:]]
            vertices.append(xyzw + [1.0] * (4 - len(xyzw)))
        elif words[0] == "cstype":
            state["cstype"] = words[1:]
        elif words[0] == "deg":
            state["deg"] = [int(x) for x in words[1:]]
        elif words[0] == "surf":
            state["range"] = [float(x) for x in words[1:5]]
            state["cv"] = [int(x.split("/")[0]) for x in words[5:]]
        elif words[0] == "parm":
            state[f"parm_{words[1]}"] = np.array([float(x) for x in words[2:]])
        elif words[0] == "end":
            state["end"] = True
    assert state["cstype"] == ["rat", "bspline"] and state.get("end")
    p, q = state["deg"]
    ku, kv = state["parm_u"], state["parm_v"]
    nu, nv = len(ku) - p - 1, len(kv) - q - 1
    cv = np.array([vertices[i - 1] for i in state["cv"]])  # 1-based
    cv = cv.reshape(nv, nu, 4).transpose(1, 0, 2)  # u varies fastest
    return p, q, ku, kv, cv[..., :3], cv[..., 3], state["range"], len(vertices)


@pytest.mark.parametrize("kind", SURFACES)
def test_obj_nurbs_block_read_back(kind):
    s = SURFACES[kind]()
    mesh_vertices = 7
    mesh = "".join(f"v {k} 0 0\n" for k in range(mesh_vertices)) + "f 1 2 3\n"
    text = mesh + render_obj_nurbs(s, mesh_vertices + 1, "bump")
    p, q, ku, kv, cp, w, (u0, u1, v0, v1), n_vertices = parse_obj_nurbs(text)
    assert n_vertices == mesh_vertices + s.shape[0] * s.shape[1]
    assert (p, q) == (s.degree_u, s.degree_v)
    assert np.array_equal(ku, s.knots_u) and np.array_equal(kv, s.knots_v)
    assert (u0, u1) == s.domain_u and (v0, v1) == s.domain_v
    assert np.array_equal(cp, s.control_points) and np.array_equal(w, s.weights)
    uv = sample_params(s)
    assert_same_points(s, reference_evaluate_uv(ku, kv, p, q, cp, w, uv), uv)


# ---- through the CLI -------------------------------------------------------------

def test_fit_with_every_format(tmp_path):
    pytest.importorskip("psonurbs.fitting.pipeline")
    pytest.importorskip("rhino3dm")
    pytest.importorskip("pyiges")
    from click.testing import CliRunner

    from psonurbs.cli.main import cli

    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["fit", str(SAMPLES / "quarter_cylinder.ply"), "-o", str(out),
                                      "-c", str(SAMPLES / "quarter_cylinder.yaml"),
                                      "--particles", "6", "--iterations", "5", "-q",
                                      "--format", "3dm", "--format", "iges", "--format", "obj-nurbs"])
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["quarter_cylinder.3dm", "quarter_cylinder.igs", "quarter_cylinder.json",
                     "quarter_cylinder.obj", "quarter_cylinder.ply", "quarter_cylinder_error.csv",
                     "summary.csv", "summary.json"]
    s = NurbsSurface.from_dict(json.loads((out / "quarter_cylinder.json").read_text())["surface"])
    obj = (out / "quarter_cylinder.obj").read_text()
    assert obj.count("\nf ") == 2 * 100 * 100  # the mesh is still there
    p, q, ku, kv, cp, w, _, _ = parse_obj_nurbs(obj)
    uv = sample_params(s)
    assert_same_points(s, reference_evaluate_uv(ku, kv, p, q, cp, w, uv), uv)


def test_unknown_format_is_a_usage_error(tmp_path):
    from click.testing import CliRunner

    from psonurbs.cli.main import cli

    result = CliRunner().invoke(cli, ["fit", "x.ply", "-o", str(tmp_path), "--format", "sat"])
    assert result.exit_code == 2
    assert "'sat' is not one of" in result.output
