"""Surveyors' and scanners' files: LAS, LAZ (laspy + lazrs) and E57 (pye57).

Each file is written here with its own library, read back by psonurbs as the real
coordinates (scale and offset applied, E57 scans placed by their poses), and fitted: the
surface must be the one fitted to the same points stored as PLY, to 1e-6 of the diagonal.
"""
from __future__ import annotations

import json
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest
from conftest import ply_bytes, reference_evaluate, run

from psonurbs.errors import InputError
from psonurbs.formats.clouds import load_cloud, read_cloud

UTM = np.array([493967.0, 5419779.0, 252.0])  # a survey offset: metres in UTM zone 32U
CONFIG = """orders: [4, 4]
net_size: [6, 6]
topology: open
swarm: {particles: 6, iterations: 5, seed: 3}
"""


def terrain(n: int = 700, seed: int = 0) -> np.ndarray:
    """A 100 m x 80 m hillside with 5 cm of noise, in local metres."""
    rng = np.random.default_rng(seed)
    x, y = rng.random(n) * 100.0, rng.random(n) * 80.0
    z = 6.0 * np.sin(x / 30.0) * np.cos(y / 40.0) + 0.02 * x + rng.normal(0.0, 0.05, n)
    return np.column_stack([x, y, z])


def surface_distance(json_a: Path, json_b: Path, shift=(0.0, 0.0, 0.0)) -> float:
    """Largest distance between the two fitted surfaces (b moved by ``shift``), on a 41 x 41
    grid of each one's own domain, over the diagonal of a's grid."""
    grids = []
    for path, move in ((json_a, np.zeros(3)), (json_b, np.asarray(shift, float))):
        s = json.loads(path.read_text())["surface"]
        ku, kv, p, q = np.array(s["knots_u"]), np.array(s["knots_v"]), s["degree_u"], s["degree_v"]
        t = np.linspace(0.0, 1.0, 41)
        u, v = np.meshgrid(ku[p] + t * (ku[-p - 1] - ku[p]), kv[q] + t * (kv[-q - 1] - kv[q]), indexing="ij")
        grids.append(reference_evaluate(ku, kv, p, q, s["control_points"], s["weights"],
                                        u.ravel(), v.ravel()) + move)
    diag = np.linalg.norm(np.ptp(grids[0], axis=0))
    return float(np.abs(grids[0] - grids[1]).max() / diag)


def fit(tmp_path: Path, cloud: Path, out: str) -> Path:
    config = tmp_path / "terrain.yaml"
    config.write_text(CONFIG)
    result = run("fit", cloud, "-c", config, "-o", tmp_path / out, "-q")
    assert result.exit_code == 0, result.stderr
    return tmp_path / out / f"{cloud.stem}.json"


# ---- LAS and LAZ -------------------------------------------------------------------------

def write_las(path: Path, counts: np.ndarray, scale: np.ndarray, offset: np.ndarray) -> None:
    """A LAS 1.4 file (point format 6) holding the integer coordinates ``counts``; LAZ by suffix."""
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = scale, offset
    las = laspy.LasData(header)
    las.X, las.Y, las.Z = counts[:, 0], counts[:, 1], counts[:, 2]
    las.write(str(path))


def las_counts(points: np.ndarray, scale: np.ndarray) -> np.ndarray:
    return np.round(points / scale).astype(np.int32)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_reads_the_real_coordinates(tmp_path, suffix):
    if suffix == ".laz":
        pytest.importorskip("lazrs")
    scale = np.array([0.001, 0.001, 0.0005])
    counts = las_counts(terrain(300), scale)
    path = tmp_path / f"tile{suffix}"
    write_las(path, counts, scale, UTM)
    points = read_cloud(path)
    assert points.dtype == np.float64 and points.shape == (300, 3)
    # x = X * scale + offset, exactly as the LAS specification defines it
    assert np.array_equal(points, counts * scale + UTM)
    assert load_cloud(path).notes == ()


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_fit_is_the_ply_fit_and_the_offset_costs_nothing(tmp_path, suffix):
    if suffix == ".laz":
        pytest.importorskip("lazrs")
    scale = np.array([0.001, 0.001, 0.001])
    counts = las_counts(terrain(), scale)
    scan = tmp_path / f"hill{suffix}"
    write_las(scan, counts, scale, UTM)
    same = tmp_path / "ply" / "hill.ply"  # the same real coordinates as a PLY
    same.parent.mkdir()
    same.write_bytes(ply_bytes(counts * scale + UTM))
    local = tmp_path / "local" / "hill.ply"  # and moved to the origin
    local.parent.mkdir()
    local.write_bytes(ply_bytes(counts * scale))
    fitted = fit(tmp_path, scan, "scan")
    assert surface_distance(fitted, fit(tmp_path, same, "ply")) <= 1e-6
    # 5.4e6 m offsets are as well conditioned as none: the fit works in centred coordinates
    assert surface_distance(fitted, fit(tmp_path, local, "local"), shift=UTM) <= 1e-6
    doc = json.loads(fitted.read_text())
    assert doc["cloud"] == f"hill{suffix}" and doc["metrics"]["rmse"] < 0.2


def test_truncated_las_is_refused(tmp_path):
    scale = np.full(3, 0.01)
    path = tmp_path / "cut.las"
    write_las(path, las_counts(terrain(200), scale), scale, UTM)
    path.write_bytes(path.read_bytes()[:-300])
    with pytest.raises(InputError, match=r"cut\.las: .*LAS file"):
        read_cloud(path)


def test_not_a_las_file(tmp_path):
    pytest.importorskip("laspy")
    path = tmp_path / "fake.las"
    path.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(InputError, match=r"fake\.las: not a readable LAS file"):
        read_cloud(path)


def test_without_the_scan_extra_the_error_names_it(tmp_path, monkeypatch, fake_fit):
    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy raises ImportError
    monkeypatch.setitem(sys.modules, "pye57", None)
    for name in ("tile.las", "tile.laz", "site.e57"):
        (tmp_path / name).write_bytes(b"not read")
    result = fake_fit.run("fit", tmp_path / "tile.las", tmp_path / "site.e57", "-o", tmp_path / "out", "-q")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"psonurbs: error: {tmp_path / 'tile.las'}: reading LAS files needs the optional package laspy, "
        "which is not installed: pip install 'psonurbs[scan]'",
        f"psonurbs: error: {tmp_path / 'site.e57'}: reading E57 files needs the optional package pye57, "
        "which is not installed: pip install 'psonurbs[scan]'"]
    assert fake_fit.calls == []


def test_laz_without_lazrs_names_it(tmp_path, monkeypatch):
    laspy = pytest.importorskip("laspy")
    pytest.importorskip("lazrs")
    scale = np.full(3, 0.01)
    path = tmp_path / "tile.laz"
    write_las(path, las_counts(terrain(50), scale), scale, UTM)
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    with pytest.raises(InputError, match=r"tile\.laz: reading compressed LAZ files needs the optional "
                                         r"package lazrs, which is not installed: pip install 'psonurbs\[scan\]'"):
        read_cloud(path)


# ---- E57 ------------------------------------------------------------------------------------

def rotation_matrix(q) -> np.ndarray:
    """The rotation of a unit quaternion (w, x, y, z), written out (E57's pose convention)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def write_e57_scans(path: Path, scans: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """An E57 file with one scan per (local points, quaternion w x y z, translation)."""
    pye57 = pytest.importorskip("pye57")
    e57 = pye57.E57(str(path), mode="w")
    for k, (local, quaternion, translation) in enumerate(scans):
        data = {f"cartesian{c}": np.ascontiguousarray(local[:, i]) for i, c in enumerate("XYZ")}
        e57.write_scan_raw(data, name=f"station {k}", rotation=np.asarray(quaternion, float),
                           translation=np.asarray(translation, float))
    e57.close()


def stations(points: np.ndarray) -> tuple[list, np.ndarray]:
    """The cloud split between two scanner stations, each scan in its own frame (float32, as
    pye57 stores them); returns the scans and the points they place in the file's frame."""
    poses = [(np.array([np.cos(0.35), 0.0, 0.0, np.sin(0.35)]), np.array([12.0, -3.0, 1.5])),
             (np.array([0.9, 0.1, -0.2, 0.3]), np.array([60.0, 40.0, -2.0]))]
    scans, placed = [], []
    for part, (q, t) in zip(np.array_split(points, 2), poses):
        r = rotation_matrix(q)
        local = ((part - t) @ r).astype(np.float32).astype(np.float64)  # R^T (p - t), stored as float32
        scans.append((local, q, t))
        placed.append(local @ r.T + t)
    return scans, np.concatenate(placed)


def test_e57_merges_every_scan_by_its_pose(tmp_path):
    scans, expected = stations(terrain(400))
    path = tmp_path / "site.e57"
    write_e57_scans(path, scans)
    cloud = load_cloud(path)
    assert cloud.points.shape == (400, 3)
    assert np.allclose(cloud.points, expected, rtol=0, atol=1e-9)
    assert cloud.notes == ("E57: 2 scans merged (200 + 200 valid points), each placed by its pose "
                           "in the file's frame",)


@pytest.mark.slow
def test_e57_fit_is_the_ply_fit(tmp_path):
    scans, expected = stations(terrain())
    scan = tmp_path / "site.e57"
    write_e57_scans(scan, scans)
    same = tmp_path / "ply" / "site.ply"
    same.parent.mkdir()
    same.write_bytes(ply_bytes(expected))
    fitted = fit(tmp_path, scan, "scan")
    assert surface_distance(fitted, fit(tmp_path, same, "ply")) <= 1e-6
    doc = json.loads(fitted.read_text())
    assert doc["notes"][0].startswith("E57: 2 scans merged (350 + 350 valid points)")


def write_e57_scaled(path: Path, counts: np.ndarray, scale: float, offset: np.ndarray,
                     invalid: np.ndarray | None = None) -> None:
    """One scan stored as scaled integers (value = count * scale + offset), written with
    libe57 through pye57's bindings; ``invalid`` marks points as cartesianInvalidState 2."""
    pye57 = pytest.importorskip("pye57")
    e57lib = pye57.libe57
    e57 = pye57.E57(str(path), mode="w")
    imf = e57.image_file
    scan = e57lib.StructureNode(imf)
    scan.set("guid", e57lib.StringNode(imf, "{%s}" % uuid.uuid4()))
    prototype = e57lib.StructureNode(imf)
    for k, c in enumerate("XYZ"):
        prototype.set(f"cartesian{c}", e57lib.ScaledIntegerNode(imf, 0, -(1 << 30), 1 << 30, scale, float(offset[k])))
    # 'q' (long long): the bindings take int64 by that type code only
    columns = {f"cartesian{c}": counts[:, k].astype("q") for k, c in enumerate("XYZ")}
    if invalid is not None:
        prototype.set("cartesianInvalidState", e57lib.IntegerNode(imf, 0, 0, 2))
        columns["cartesianInvalidState"] = np.where(invalid, 2, 0).astype("q")
    points = e57lib.CompressedVectorNode(imf, prototype, e57lib.VectorNode(imf, True))
    scan.set("points", points)
    e57.data3d.append(scan)
    buffers = e57lib.VectorSourceDestBuffer()
    for name, column in columns.items():
        buffers.append(e57lib.SourceDestBuffer(imf, name, column, len(column), True, False))
    writer = points.writer(buffers)
    writer.write(len(counts))
    writer.close()
    e57.close()


def test_e57_scaled_integers_read_as_real_coordinates_without_invalid_points(tmp_path):
    scale = 0.0005
    counts = np.round(terrain(120) / scale).astype(np.int64)
    invalid = np.zeros(120, bool)
    invalid[[3, 50, 77]] = True
    path = tmp_path / "scaled.e57"
    write_e57_scaled(path, counts, scale, UTM, invalid)
    cloud = load_cloud(path)
    assert np.array_equal(cloud.points, (counts * scale + UTM)[~invalid])
    assert cloud.notes == ("E57: 1 scan (117 valid points), placed by its pose in the file's frame",)


def test_not_an_e57_file(tmp_path):
    pytest.importorskip("pye57")
    path = tmp_path / "fake.e57"
    path.write_bytes(b"ASTM-E57" + bytes(2000))
    with pytest.raises(InputError, match=r"fake\.e57: not a readable E57 file"):
        read_cloud(path)
