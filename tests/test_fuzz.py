"""Property-based fuzzing of ``psonurbs fit``: generated clouds, configs, options and paths
thrown at the command line, and the contract checked on each.

The contract: exit 0 or 2 (never 1, never a traceback), every stderr line in the tool's
format, nothing written for a cloud on refusal, finite metrics in the JSON on success,
and each run within a time bound. The CLI's own work (reading, validating, reporting,
writing) is fuzzed with the stand-in fitter of conftest.py; a smaller test fits tiny
generated clouds for real. Derandomised (a fixed sequence of examples, no database), so
a failure here fails the same way on every machine.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import struct
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import FakeFit, FakeResult, run

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SECONDS_PER_RUN = 10.0  # the time bound of one command (the stand-in fitter takes milliseconds)

FUZZ = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ---- numbers and values ------------------------------------------------------------------

def huge_ints():
    return st.sampled_from([0, -1, -5, 10**3, 10**6, 10**9, 2**31, 2**63, 10**23, -(10**30), 10**400])


def awkward_floats():
    return st.sampled_from([0.0, -0.0, 1e-320, 1e-308, 1e-154, 1e154, 1e200, 1e308, -1e308, math.nan, math.inf,
                            -math.inf, 0.5, 1.5, 3.0, 1e-12])


def yaml_values(depth: int = 2):
    scalars = st.one_of(st.integers(-3, 60), huge_ints(), awkward_floats(), st.booleans(), st.none(),
                        st.sampled_from(["open", "sphere", "Sphere", "auto", "hybrid", "full", "", "x" * 300,
                                         "1e400", "0x10", "\u00e9\u00e8", "null", "~", "[1, 2]"]))
    if depth == 0:
        return scalars
    return st.one_of(scalars, st.lists(yaml_values(depth - 1), max_size=4),
                     st.dictionaries(st.sampled_from(["particles", "iterations", "seed", "inertia", "x", "1"]),
                                     yaml_values(depth - 1), max_size=3))


KEYS = ["orders", "net_size", "topology", "strategy", "smoothing", "swarm_points", "polish_iterations",
        "tessellation", "weight_bounds", "min_knot_gap", "cross_validation", "refine", "refine_iterations",
        "remove_outliers",
        "robust", "swarm", "swarm_x", "Orders", "1"]
SWARM_KEYS = ["particles", "iterations", "inertia", "c1", "c2", "seed", "particle"]


def small_sizes():
    """Mostly sane values for the size keys (so that some configs pass), some hostile."""
    pair = st.lists(st.integers(1, 12), min_size=2, max_size=2)
    return st.one_of(pair, yaml_values(1))


@st.composite
def configs(draw) -> str | None:
    """YAML text: generated keys and values, or a hand-written hostile document."""
    kind = draw(st.integers(0, 9))
    if kind <= 2:
        return None
    if kind == 3:
        return draw(st.sampled_from([
            "a: &a [1, 2]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\nc: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n"
            "d: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]\ntessellation: *d\n",
            "tessellation: " + "[" * 5000 + "]" * 5000 + "\n",
            "swarm: " + "{a: " * 200 + "1" + "}" * 200 + "\n",
            "swarm: &s {particles: 3}\nrefine: *s\n",
            "orders: !!python/object:os.system [ls]\n",
            "orders: !!binary aGVsbG8=\n", "net_size: 1999-01-01\n", "? [1, 2]\n: 3\n",
            "\ufeffswarm: {particles: 3, iterations: 2}\n", "orders: [3, 3\n", "\x00\x01\x02", "- 1\n- 2\n",
            "swarm:\n  particles: " + "9" * 5000 + "\n", "topology: " + "y" * 100_000 + "\n",
            "net_size: [40, 40]\n", "net_size: [200, 200]\n", "tessellation: [100000, 100000]\n",
            "tessellation: [3000, 3000]\n", "swarm: {iterations: 1000000000}\n",
            "swarm: {particles: 5000, iterations: 5000}\n", "strategy: full\nnet_size: [30, 30]\n",
            "swarm_points: 1e9\n", "weight_bounds: [1e-300, 1e300]\n", "smoothing: 1e308\n",
        ]))
    doc: dict = {}
    for key in draw(st.lists(st.sampled_from(KEYS), max_size=4, unique=True)):
        if key == "swarm":
            doc[key] = draw(st.one_of(
                st.dictionaries(st.sampled_from(SWARM_KEYS),
                                st.one_of(st.integers(1, 4), yaml_values(1)), max_size=3),
                yaml_values(1)))
        elif key in ("orders", "net_size", "tessellation"):
            doc[key] = draw(small_sizes())
        else:
            doc[key] = draw(yaml_values(2))
    return json.dumps(doc, default=str) if draw(st.booleans()) else _yaml(doc)


def _yaml(doc) -> str:
    import yaml

    try:
        return yaml.safe_dump(doc)
    except (ValueError, yaml.YAMLError):  # an int beyond Python's printing limit
        return "orders: [3, 3]\n"


# ---- clouds -------------------------------------------------------------------------------

def cloud_points(draw, hostile: bool = True) -> np.ndarray:
    """Points of a surface, most of the time; with ``hostile``, also of a line, all one point
    but one, a line with 1e-15 noise, scaled out of range, with a NaN or an infinity."""
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    if hostile:
        n = draw(st.sampled_from([0, 1, 3, 9, 12, 40, 40, 200, 200]))
        shape = draw(st.sampled_from(["surface"] * 4 + ["line", "identical", "one_off", "tiny_noise_line"]))
        scale = draw(st.sampled_from([1.0] * 6 + [1e6, 1e-6, 1e154, 1e-308, 1e300, 2.0**400]))
        offset = draw(st.sampled_from([0.0] * 4 + [1e7, -1e15]))
    else:  # fittable, but odd: few points, far from the origin, tiny or huge, nearly flat
        n = draw(st.sampled_from([10, 16, 40, 80]))
        shape = draw(st.sampled_from(["surface", "surface", "flat", "one_off_surface"]))
        scale = draw(st.sampled_from([1.0, 1e-9, 1e9, 2.0**300]))
        offset = draw(st.sampled_from([0.0, 1e3]))
    x, y = rng.random((2, n))
    if shape == "surface":
        p = np.column_stack([x, y, np.sin(3 * x) * y])
    elif shape == "flat":
        p = np.column_stack([x, y, 1e-7 * rng.standard_normal(n)])
    elif shape == "one_off_surface":
        p = np.column_stack([x, y, np.sin(3 * x) * y])
        p[0, 2] += 100.0
    elif shape == "line":
        p = np.column_stack([x, 2 * x, 3 * x])
    elif shape == "tiny_noise_line":
        p = np.column_stack([x, 2 * x, 3 * x]) + 1e-15 * rng.standard_normal((n, 3))
    else:
        p = np.ones((n, 3))
        if shape == "one_off" and n:
            p[0] = [2.0, 3.0, 4.0]
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        p = p * scale + offset
    if hostile and n and draw(st.integers(0, 7)) == 0:
        p[rng.integers(n)] = draw(st.sampled_from([math.nan, math.inf, -math.inf, 1e308]))
    return p


def ply(draw, p: np.ndarray) -> bytes:
    fmt = draw(st.sampled_from(["binary_little_endian", "binary_big_endian", "ascii"]))
    typ, code = draw(st.sampled_from([("double", "f8"), ("float", "f4"), ("int", "i4")]))
    names = draw(st.permutations(["x", "y", "z", "nx", "intensity"][:draw(st.integers(3, 5))]))
    if draw(st.integers(0, 9)) == 0:
        names = [n for n in names if n != "z"]
    cols = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]} if len(p) else {c: np.zeros(0) for c in "xyz"}
    table = np.column_stack([cols.get(c, np.arange(len(p), dtype=float)) for c in names]) if len(p) \
        else np.zeros((0, len(names)))
    count = draw(st.one_of(st.just(len(p)), st.sampled_from([-1, 0, len(p) + 1, 10**12, "many", "1e3"])))
    head = ["ply", f"format {fmt} 1.0", f"element vertex {count}"]
    head += [f"property {typ} {c}" for c in names]
    if draw(st.integers(0, 4)) == 0:
        head += ["element face 1", "property list uchar int vertex_indices"]
    head.append("end_header")
    out = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        with np.errstate(invalid="ignore", over="ignore"):
            out += "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in table).encode()
    else:
        with np.errstate(invalid="ignore", over="ignore"):
            out += table.astype(("<" if "little" in fmt else ">") + code).tobytes()
    return _mutilate(draw, out)


def pcd(draw, p: np.ndarray) -> bytes:
    data = draw(st.sampled_from(["ascii", "binary", "binary_compressed", "utf8"]))
    count = draw(st.one_of(st.just(len(p)), st.sampled_from([-3, len(p) + 5, 10**10, "x"])))
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {count}\n"
            f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA {data}\n").encode()
    with np.errstate(invalid="ignore", over="ignore"):
        if data == "ascii":
            body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in p.tolist()).encode()
        elif data == "binary_compressed":
            body = struct.pack("<II", 10, 12 * len(p)) + b"\x00" * 10
        else:
            body = p.astype("<f4").tobytes()
    return _mutilate(draw, head + body)


def text(draw, p: np.ndarray) -> bytes:
    sep = draw(st.sampled_from([" ", ",", "\t", " , "]))
    lines = [sep.join(repr(float(v)) for v in row) for row in p.tolist()]
    if lines and draw(st.booleans()):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(
            ["# comment", "", "1 2", "a b c", "1 2 3 4 5 6", "nan nan nan", str(len(lines)), "\x00\x00", "1e999 0 0"])))
    body = "\n".join(lines).encode()
    if draw(st.booleans()):
        body = b"\xef\xbb\xbf" + body
    return _mutilate(draw, body)


def _mutilate(draw, data: bytes) -> bytes:
    kind = draw(st.integers(0, 9))
    if kind == 0 and data:
        return data[:draw(st.integers(0, len(data) - 1))]
    if kind == 1 and data:
        at = draw(st.integers(0, len(data) - 1))
        return data[:at] + draw(st.binary(min_size=1, max_size=64)) + data[at + 1:]
    if kind == 2:
        return data + draw(st.binary(max_size=256))
    return data


SUFFIXES = [".ply"] * 3 + [".xyz"] * 2 + [".pcd", ".txt", ".pts", ".PLY", ".stl", ""]
NAMES = ["cloud"] * 6 + ["summary", "s p a c e", "\u00fcnic\u00f8de-\u4e91", "new\nline", "-dash", ".hidden", "a" * 200]


@st.composite
def clouds(draw, directory: Path) -> Path:
    """A cloud file (or a path that is not one) written into ``directory``."""
    name = draw(st.sampled_from(NAMES)) + draw(st.sampled_from(SUFFIXES))
    path = directory / name
    special = draw(st.integers(0, 24))
    if special == 0:
        os.mkfifo(path)
    elif special == 1:
        path.symlink_to("/dev/zero")
    elif special == 2:
        path.symlink_to(directory / "nowhere.ply")
    elif special == 3:
        path.mkdir()
    elif special == 4:
        return directory / ("missing" + path.suffix)
    elif special == 5:
        path.write_bytes(draw(st.binary(max_size=512)))
    else:
        p = cloud_points(draw)
        writer = {".ply": ply, ".PLY": ply, ".pcd": pcd}.get(path.suffix, text)
        path.write_bytes(writer(draw, p))
    return path


OPTIONS = st.one_of(st.just([]), st.just([("--particles", "3"), ("--iterations", "2")]), st.lists(st.sampled_from([
    ("--particles", "3"), ("--particles", "0"), ("--particles", "99999999999999999999999"), ("--particles", "x"),
    ("--iterations", "2"), ("--iterations", "-1"), ("--iterations", "1000000000"), ("--seed", "-1"),
    ("--seed", "340282366920938463463374607431768211456"), ("--topology", "Sphere"), ("--topology", "torus"),
    ("--strategy", "full"), ("--jobs", "0"), ("--max-rmse", "nan"), ("--max-rmse", "-1"), ("--format", "stl"),
    ("--max-rmse-rel", "1e-300"), ("--bogus", "1"),
]), max_size=2))


# ---- the contract ---------------------------------------------------------------------------

class _TooSlow(Exception):
    pass


@contextlib.contextmanager
def time_bound(seconds: float):
    """Fail a run that takes longer than ``seconds`` (SIGALRM also interrupts a blocked open())."""
    def expire(signum, frame):
        raise _TooSlow(f"a run took longer than {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def check_contract(result, out: Path, cloud: Path, seconds: float, bound: float = SECONDS_PER_RUN) -> None:
    event(f"exit {result.exit_code}")
    assert result.exit_code in (0, 2, 3), (result.exit_code, result.stderr[-3000:])  # 3: the gate
    for stream in (result.stdout, result.stderr):
        assert "Traceback" not in stream and "internal error" not in stream, stream[-3000:]
    for line in result.stderr.splitlines():
        assert line.startswith("psonurbs: "), result.stderr[-3000:]
        assert len(line) < 1000, line[:300]
    assert seconds < bound, f"{seconds:.1f} s"
    stem_files = [p for p in out.iterdir() if not p.name.startswith("summary.")] if out.exists() else []
    if result.exit_code == 2:
        assert stem_files == [], (result.stderr, stem_files)  # nothing of a refused cloud
        return
    document = json.loads((out / f"{cloud.stem}.json").read_text())
    assert all(math.isfinite(v) for v in document["metrics"].values() if isinstance(v, float))
    status = ("suspect" if document["metrics"].get("suspect") else "ok") if result.exit_code == 0 else "gate-exceeded"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit_code"] == result.exit_code and [c["status"] for c in summary["clouds"]] == [status]


@FUZZ
@given(data=st.data())
def test_fuzz_the_command_line(data):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cloud = data.draw(clouds(tmp), label="cloud")
        args = ["fit", str(cloud), "-o", str(tmp / "out"), "-q"]
        config = data.draw(configs(), label="config")
        if config is not None:
            (tmp / "cfg.yaml").write_text(config, encoding="utf-8", errors="surrogatepass")
            args += ["-c", str(tmp / "cfg.yaml")]
        for option in data.draw(OPTIONS, label="options"):
            args += list(option)
        start = time.perf_counter()
        with time_bound(2 * SECONDS_PER_RUN):
            result = run(*args, fit=FakeFit())
        check_contract(result, tmp / "out", cloud, time.perf_counter() - start)


@st.composite
def valid_configs(draw) -> str:
    """A config inside every bound, its choices at random, with a tiny swarm."""
    k, l = draw(st.integers(2, 5)), draw(st.integers(2, 5))
    topology = draw(st.sampled_from(["open", "cylinder", "sphere", "torus", "auto"]))
    nu, nv = draw(st.integers(k, 9)), draw(st.integers(max(l, 3 if topology == "sphere" else l), 9))
    lo, hi = draw(st.sampled_from([0.2, 1e-6, 0.9, 1.0])), draw(st.sampled_from([5.0, 1.0, 1e6, 1.1]))
    doc = {"orders": [k, l], "net_size": [nu, nv], "topology": topology,
           "strategy": draw(st.sampled_from(["hybrid", "hybrid", "full"])),
           "swarm": {"particles": draw(st.integers(1, 4)), "iterations": draw(st.integers(1, 3)),
                     "inertia": draw(st.sampled_from([0.0, 0.7, 10.0])), "c1": draw(st.sampled_from([0.0, 1.5, 10.0])),
                     "c2": draw(st.sampled_from([0.0, 1.5, 10.0])), "seed": draw(st.integers(0, 2**64 - 1))},
           "smoothing": draw(st.sampled_from([0.0, 1e-6, 1.0, 1e6])), "swarm_points": draw(st.sampled_from([16, 17, 100])),
           "polish_iterations": draw(st.sampled_from([0, 1, 3])), "tessellation": [draw(st.integers(2, 30))] * 2,
           "weight_bounds": [lo, hi], "min_knot_gap": draw(st.sampled_from([1e-9, 0.2, 0.999])),
           "cross_validation": draw(st.booleans()), "refine": draw(st.booleans()),
           "robust": draw(st.booleans())}
    if draw(st.booleans()):  # its other name, which must agree with it
        doc["remove_outliers"] = doc["robust"]
    return json.dumps(doc)


REAL_EXAMPLES = int(os.environ.get("PSONURBS_FUZZ_REAL_EXAMPLES", "8"))  # more for a longer local run


@settings(max_examples=REAL_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_real_fits_of_tiny_clouds(data):
    """The real fitter on small generated clouds (odd shapes and scales) with configs drawn
    inside the bounds (every choice at random, tiny swarms)."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        p = cloud_points(data.draw, hostile=False)
        cloud = tmp / "tiny.xyz"
        np.savetxt(cloud, p, fmt="%.17g")
        (tmp / "cfg.yaml").write_text(data.draw(valid_configs(), label="config"))
        start = time.perf_counter()
        with time_bound(60):
            result = run("fit", cloud, "-c", tmp / "cfg.yaml", "-o", tmp / "out", "-q")
        check_contract(result, tmp / "out", cloud, time.perf_counter() - start, bound=60)


# ---- valid clouds in every layout are read exactly --------------------------------------------

@st.composite
def valid_cloud_files(draw, directory: Path) -> tuple[Path, np.ndarray, float]:
    """A valid cloud in a drawn format and layout; returns (path, points, tolerance)."""
    n = draw(st.integers(10, 120))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    kind = draw(st.sampled_from(["ply", "pcd", "xyz"]))
    # (a float32 file far from the origin would hold too few digits: offsets only in double)
    offset = draw(st.sampled_from([0.0, -50.0, 1e5] if kind == "xyz" else [0.0, -50.0]))
    points = rng.random((n, 3)) * draw(st.sampled_from([1.0, 1e-3, 1e4])) + offset
    if kind == "ply":
        fmt = draw(st.sampled_from(["binary_little_endian", "binary_big_endian", "ascii"]))
        typ, code = draw(st.sampled_from([("double", "f8"), ("float", "f4")]))
        names = draw(st.permutations(["x", "y", "z", "nx", "intensity", "red"][:draw(st.integers(3, 6))]))
        extras = {c: rng.random(n) for c in names if c not in "xyz"}
        table = np.column_stack([points[:, "xyz".index(c)] if c in "xyz" else extras[c] for c in names])
        faces_first = draw(st.booleans()) and fmt == "ascii"
        head = ["ply", f"format {fmt} 1.0", "comment generated"]
        if faces_first:
            head += ["element face 1", "property list uchar int vertex_indices"]
        head += [f"element vertex {n}"] + [f"property {typ} {c}" for c in names]
        if draw(st.booleans()):
            head += ["element face 1", "property list uchar int vertex_indices"]
        head.append("end_header")
        body = ("\n".join(head) + "\n").encode()
        if fmt == "ascii":
            rows = "".join(" ".join(repr(float(v)) for v in row.astype(code)) + "\n" for row in table)
            body += (b"3 0 1 2\n" if faces_first else b"") + rows.encode() + b"3 0 1 2\n"
        else:
            body += table.astype(("<" if "little" in fmt else ">") + code).tobytes()
            if "element face 1" in head[-3:]:
                body += struct.pack("<Biii" if "little" in fmt else ">Biii", 3, 0, 1, 2)
        path = directory / "valid.ply"
        path.write_bytes(body)
        tolerance = 0.0 if code == "f8" else 1e-6
        expected = points.astype(code).astype(float)
    elif kind == "pcd":
        data = draw(st.sampled_from(["ascii", "binary"]))
        fields = draw(st.permutations(["x", "y", "z", "intensity"]))
        extras = rng.random(n)
        table = np.column_stack([points[:, "xyz".index(c)] if c in "xyz" else extras for c in fields]).astype("<f4")
        head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()
        body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in table).encode() if data == "ascii" \
            else table.tobytes()
        path = directory / "valid.pcd"
        path.write_bytes(head + body)
        tolerance, expected = 1e-6, points.astype("f4").astype(float)
    else:
        sep = draw(st.sampled_from([" ", ",", "\t", " , "]))
        end = draw(st.sampled_from(["\n", "\r\n"]))
        lines = [sep.join(repr(float(v)) for v in row) + draw(st.sampled_from(["", " 255 0 0", " # note"]))
                 for row in points]
        if draw(st.booleans()):
            lines.insert(0, "# x y z")
        text = end.join(lines) + end
        path = directory / draw(st.sampled_from(["valid.xyz", "valid.txt", "valid.pts"]))
        path.write_bytes((b"\xef\xbb\xbf" if draw(st.booleans()) else b"") + text.encode())
        tolerance, expected = 0.0, points
    return path, expected, tolerance


@settings(max_examples=50, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_valid_clouds_in_any_layout_are_read_exactly(data):
    """Every valid layout (property order, extra properties, byte order, float or double, faces
    before or after, ASCII or binary, separators, comments, BOM, CRLF) reaches the fitter with
    exactly its points, and the run writes its outputs with finite metrics."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path, expected, tolerance = data.draw(valid_cloud_files(tmp), label="cloud")
        seen = []

        def fit(points, config, on_iteration=None):
            seen.append(np.array(points))
            return FakeResult()

        (tmp / "cfg.yaml").write_text("tessellation: [5, 5]\n")  # the mesh is not what is fuzzed here
        with time_bound(2 * SECONDS_PER_RUN):
            result = run("fit", path, "-c", tmp / "cfg.yaml", "-o", tmp / "out", "-q", fit=fit)
        event(path.suffix)
        check_contract(result, tmp / "out", path, 0.0)
        assert result.exit_code == 0, result.stderr
        np.testing.assert_allclose(seen[0], expected, rtol=tolerance, atol=0)
