"""Reading clouds (and refusing bad ones) and writing the four fit outputs."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

import psonurbs.formats.clouds as pio
import psonurbs.formats.outputs as pout
from psonurbs.errors import InputError
from psonurbs.formats.clouds import read_cloud
from psonurbs.formats.outputs import atomic_write, render_csv, render_json, render_obj, render_ply, write_fit_outputs

o3d = pytest.importorskip("open3d")

REPO = Path(__file__).resolve().parents[1]


def ply_bytes(points, fmt="binary_little_endian", dtype="double", faces=None) -> bytes:
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    head = ["ply", f"format {fmt} 1.0", f"element vertex {len(points)}"]
    head += [f"property {dtype} {c}" for c in "xyz"]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head.append("end_header")
    out = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        out += "".join("%r %r %r\n" % tuple(p) for p in points.tolist()).encode()
        if faces is not None:
            out += "".join("3 %d %d %d\n" % tuple(f) for f in faces).encode()
    else:
        out += points.astype("<f8" if dtype == "double" else "<f4").tobytes()
    return out


@pytest.fixture
def pts():
    rng = np.random.default_rng(1)
    return rng.normal(size=(50, 3)) * [1.0, 2.0, 1e-3] + [0.0, 0.0, 1e6]


# ---- reading good clouds ---------------------------------------------------

def test_binary_double_ply_is_exact(tmp_path, pts):
    path = tmp_path / "a.ply"
    path.write_bytes(ply_bytes(pts))
    got = read_cloud(path)
    assert got.dtype == np.float64 and got.shape == (50, 3) and got.flags.c_contiguous
    np.testing.assert_array_equal(got, pts)


def test_float_ply_and_uppercase_suffix(tmp_path, pts):
    path = tmp_path / "a.PLY"
    path.write_bytes(ply_bytes(pts, dtype="float"))
    np.testing.assert_array_equal(read_cloud(path), pts.astype(np.float32).astype(np.float64))


def test_ascii_ply_with_faces(tmp_path):
    path = tmp_path / "a.ply"
    path.write_bytes(ply_bytes([[0, 0, 0], [1, 0, 0], [0, 1, 0.5]], fmt="ascii", faces=[(0, 1, 2)]))
    np.testing.assert_array_equal(read_cloud(path), [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]])


def test_pcd(tmp_path, pts):
    path = tmp_path / "a.pcd"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    np.testing.assert_allclose(read_cloud(path), pts, rtol=1e-6)


def test_xyz_whitespace_commas_comments_and_extra_columns(tmp_path):
    path = tmp_path / "a.xyz"
    path.write_text("# x y z r g b\n1 2 3 255 0 0\n\n4.5,\t-5e-3 , 6 # trailing\n7 8 9\n")
    np.testing.assert_array_equal(read_cloud(path), [[1, 2, 3], [4.5, -5e-3, 6], [7, 8, 9]])


def test_pts_with_point_count_line(tmp_path):
    path = tmp_path / "a.pts"
    path.write_text("2\n1 2 3 10 200 200 200\n4 5 6 11 0 0 0\n")
    np.testing.assert_array_equal(read_cloud(path), [[1, 2, 3], [4, 5, 6]])


def test_txt_is_exact(tmp_path, pts):
    path = tmp_path / "a.txt"
    np.savetxt(path, pts, fmt="%.17g")
    np.testing.assert_array_equal(read_cloud(path), pts)


def test_sample_clouds_read():
    shapes = {p.stem: read_cloud(p).shape for p in (REPO / "data_samples").glob("*.ply")}
    assert shapes == {"seed_patch16": (16, 3), "franke_noisy": (5000, 3),
                      "quarter_cylinder": (2000, 3), "seed_sphere169": (169, 3), "torus": (8000, 3)}


# ---- refusing bad clouds ---------------------------------------------------

BAD = {
    "empty.ply": (b"", "file is empty"),
    "empty.xyz": (b"", "file is empty"),
    "comments.xyz": (b"# header only\n\n", "no points found in the file"),
    "garbage.ply": (b"\x00\x13garbage\xff" * 20, "not a PLY file"),
    "noend.ply": (b"ply\nformat ascii 1.0\nelement vertex 3\n", "no 'end_header' line"),
    "zero.ply": (ply_bytes(np.zeros((0, 3))), "PLY file has no vertices (header declares 0)"),
    "faces.ply": (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
                  b"end_header\n3 0 1 2\n",
                  "PLY file has no vertices (no 'vertex' element; elements: face)"),
    "noxyz.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nproperty float b\n"
                  b"end_header\n1 2\n", "PLY vertices have no x/y/z coordinate"),
    "truncated.ply": (ply_bytes(np.ones((10, 3)))[:-100], "malformed or truncated PLY file"),
    "badascii.ply": (ply_bytes(np.ones((3, 3)), fmt="ascii").replace(b"1.0 1.0 1.0\n", b"1 x 1\n", 1),
                     "malformed or truncated PLY file"),
    "bad.pcd": (b"this is not a pcd\n1 2 3\n", "malformed or truncated PCD file"),
    "word.xyz": (b"1 2 3\n4 five 6\n7 8 9\n", "malformed point data at line 2: 'five' is not a number"),
    "short.xyz": (b"1 2 3\n4 5\n7 8\n", "malformed point data at line 2: expected at least 3 "
                                         "numbers (x y z), found 2 (and 1 more bad lines)"),
    "binary.xyz": (b"\x89PNG\r\n\x1a\n\x00\x00\xff", "not a text point cloud"),
    "cloud.stl": (b"solid x\n", "unknown point cloud type ('.stl'); expected one of .ply, .pcd, "
                                ".xyz, .txt, .pts"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_cloud_message_names_file_and_problem(tmp_path, name, capfd):
    content, expected = BAD[name]
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InputError) as info:
        read_cloud(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert expected in message
    assert "\n" not in message
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # open3d / RPly chatter is captured, not printed


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"nope\.ply: no such file$"):
        read_cloud(tmp_path / "nope.ply")


def test_directory(tmp_path):
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(InputError, match=r"d\.ply: is a directory, not a point cloud file$"):
        read_cloud(tmp_path / "d.ply")


def test_unreadable(tmp_path, monkeypatch):
    path = tmp_path / "a.xyz"
    path.write_text("1 2 3\n")

    def denied(*args, **kwargs):  # chmod 0 does not stop root, so deny in open()
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(pio, "open", denied, raising=False)
    with pytest.raises(InputError) as info:
        read_cloud(path)
    assert str(info.value) == f"{path}: cannot read file (Permission denied)"


@pytest.mark.parametrize("suffix", [".ply", ".xyz"])
def test_non_finite_coordinates_are_counted(tmp_path, suffix):
    p = np.arange(30.0).reshape(10, 3)
    p[2, 0] = np.nan
    p[5, 1] = np.nan
    p[5, 2] = np.inf  # counted once, as NaN
    p[7, 2] = -np.inf
    path = tmp_path / f"a{suffix}"
    if suffix == ".ply":
        path.write_bytes(ply_bytes(p))
    else:
        np.savetxt(path, p)
    with pytest.raises(InputError) as info:
        read_cloud(path)
    assert str(info.value) == (f"{path}: 3 of 10 points have non-finite coordinates "
                               "(2 NaN, 1 infinite)")


# ---- writers ---------------------------------------------------------------

def grid_mesh(n_u=4, n_v=3):
    u, v = np.meshgrid(np.linspace(0, 1, n_u), np.linspace(0, 1, n_v), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel(), np.sin(3 * u.ravel()) / 7 + v.ravel() / 3], -1)
    i, j = np.meshgrid(np.arange(n_u - 1), np.arange(n_v - 1), indexing="ij")
    a = (i * n_v + j).ravel()
    tris = np.concatenate([np.stack([a, a + n_v, a + 1], 1), np.stack([a + 1, a + n_v, a + n_v + 1], 1)])
    return verts, tris


CURVE_HEADER = ["iteration", "best_rmse", "mean_rmse"]
CURVE = np.array([[0, 0.5, 0.9], [1, 0.25, 0.5], [2, 1 / 3, 0.4]])
DOC = {"psonurbs_version": "0.1.0", "cloud": "a.ply", "metrics": {"rmse": np.float64(0.1),
       "max_error": np.float32(0.5), "n": np.int64(7)}, "knots": np.array([0.0, 0.5, 1.0])}


def write_sample(out_dir, stem="s"):
    verts, tris = grid_mesh()
    return write_fit_outputs(out_dir, stem, DOC, verts, tris, CURVE_HEADER, CURVE)


def test_write_fit_outputs_writes_four_files(tmp_path):
    paths = write_sample(tmp_path / "new" / "dir")
    assert sorted(p.name for p in (tmp_path / "new" / "dir").iterdir()) == \
        ["s.json", "s.obj", "s.ply", "s_error.csv"]
    assert set(paths) == {"json", "obj", "ply", "csv"}
    doc = json.loads(paths["json"].read_text())
    assert doc == {"psonurbs_version": "0.1.0", "cloud": "a.ply",
                   "metrics": {"rmse": 0.1, "max_error": 0.5, "n": 7}, "knots": [0.0, 0.5, 1.0]}
    assert list(doc) == list(DOC)  # key order kept
    assert paths["json"].read_text().endswith("}\n")


def test_outputs_are_byte_identical(tmp_path):
    a, b = write_sample(tmp_path / "a"), write_sample(tmp_path / "b")
    for kind in a:
        assert a[kind].read_bytes() == b[kind].read_bytes(), kind


def test_ply_round_trips_through_open3d_exactly(tmp_path):
    verts, tris = grid_mesh(7, 5)
    path = tmp_path / "m.ply"
    path.write_bytes(render_ply(verts, tris))
    mesh = o3d.io.read_triangle_mesh(str(path))
    np.testing.assert_array_equal(np.asarray(mesh.vertices), verts)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), tris)


def test_obj_round_trips_through_open3d(tmp_path):
    verts, tris = grid_mesh(7, 5)
    path = tmp_path / "m.obj"
    path.write_text(render_obj(verts, tris))
    mesh = o3d.io.read_triangle_mesh(str(path))
    assert len(mesh.triangles) == len(tris)
    # open3d's OBJ reader stores float32 and may renumber vertices: compare corners.
    corners = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]
    np.testing.assert_allclose(corners, verts[tris], atol=1e-6)


def test_obj_text_is_exact_and_one_based():
    verts = np.array([[0.1, -2.0, 1e-300], [1 / 3, 2.0, 3.0], [4.0, 5.0, 6.0]])
    text = render_obj(verts, np.array([[0, 1, 2]]))
    lines = text.splitlines()
    assert lines[0].startswith("# psonurbs")
    assert lines[-1] == "f 1 2 3"
    v = np.array([[float(x) for x in ln.split()[1:]] for ln in lines if ln.startswith("v ")])
    np.testing.assert_array_equal(v, verts)
    assert lines[2] == "v 0.33333333333333331 2 3"


def test_csv_format():
    assert render_csv(CURVE_HEADER, CURVE) == (
        "iteration,best_rmse,mean_rmse\n0,0.5,0.90000000000000002\n1,0.25,0.5\n"
        "2,0.33333333333333331,0.40000000000000002\n")
    with pytest.raises(ValueError, match="shape"):
        render_csv(CURVE_HEADER, CURVE[:, :2])


def test_json_refuses_nan():
    with pytest.raises(ValueError, match="not valid JSON"):
        render_json({"rmse": float("nan")})
    with pytest.raises(ValueError, match="not valid JSON"):
        render_json({"rmse": np.array([1.0, np.inf])})


def test_bad_mesh_is_refused():
    verts, tris = grid_mesh()
    with pytest.raises(ValueError, match="out of range"):
        render_ply(verts, tris + 1)
    with pytest.raises(ValueError, match="NaN"):
        render_obj(np.full_like(verts, np.nan), tris)


def test_render_failure_writes_nothing(tmp_path):
    verts, tris = grid_mesh()
    with pytest.raises(ValueError):
        write_fit_outputs(tmp_path, "s", {"rmse": float("nan")}, verts, tris, CURVE_HEADER, CURVE)
    assert list(tmp_path.iterdir()) == []


def test_write_failure_midway_removes_placed_files(tmp_path, monkeypatch):
    real = pout.atomic_write
    calls = []

    def flaky(path, data):
        calls.append(Path(path).name)
        if len(calls) == 3:
            raise KeyboardInterrupt  # Ctrl-C while writing the third file
        return real(path, data)

    monkeypatch.setattr(pout, "atomic_write", flaky)
    with pytest.raises(KeyboardInterrupt):
        write_sample(tmp_path)
    assert calls == ["s.obj", "s.ply", "s_error.csv"]
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "x.json"
    atomic_write(path, "old\n")

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        atomic_write(path, "new\n")
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]  # no temporary left behind


def test_atomic_write_text_and_bytes(tmp_path):
    assert atomic_write(tmp_path / "t.txt", "é\n").read_bytes() == "é\n".encode()
    assert atomic_write(tmp_path / "b.bin", b"\x00\x01").read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bin", "t.txt"]
