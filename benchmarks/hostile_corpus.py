"""An adversarial corpus for ``psonurbs fit``: hostile clouds, configs, options, paths and
output directories, each run as a real command (the real fitter, tiny swarms) in a fresh
process under a time limit and an address-space limit, with its peak memory measured.

    python benchmarks/hostile_corpus.py [--only SUBSTRING] [--keep DIR]

Prints one row per case (exit code, seconds, peak RSS, the first stderr line) and whether
the contract held: the expected exit code (0 or 2 for inputs; 3, 4, 143 where the case is
about them), no traceback, every stderr line one ``psonurbs: ...`` line, nothing written
for a refused cloud, no time-out, no memory blow-up. The last lines are the counts and the
peak memory of the refused oversized configs (the mark: under 200 MB).
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from cases import franke_height

TIME_LIMIT = 120  # seconds per case
SIGNAL_AFTER = 3.0  # seconds before a batch case signals its run (once its workers exist)
MEMORY_LIMIT = 4 << 30  # address space per case (the imports alone map about 1.2 GiB)
QUICK = "swarm: {particles: 4, iterations: 3}\npolish_iterations: 5\n"  # a tiny swarm: the corpus is about inputs


@dataclass
class Case:
    name: str
    args: list  # after "psonurbs fit"; {dir} is the case's directory
    expect: tuple = (2,)
    group: str = ""
    oversized: bool = False  # a refused oversized config: its peak memory is reported
    setup: object = None  # callable(dir) run before, e.g. to start a killer
    files: dict = field(default_factory=dict)  # name -> bytes | str | callable(dir)


# ---- cloud makers ----------------------------------------------------------------------

def franke(n=200, seed=4, noise=0.0):
    """n points of Franke's function (benchmarks/cases.py) at uniform (x, y), noise in z."""
    rng = np.random.default_rng(seed)
    x, y = rng.random((2, n))
    return np.column_stack([x, y, franke_height(x, y) + noise * rng.standard_normal(n)])


def ply(points, order="xyz", fmt="binary_little_endian", typ="double", count=None, extra=(), before="") -> bytes:
    points = np.asarray(points, float).reshape(-1, 3)
    names = list(order) + list(extra)
    cols = {c: points[:, "xyz".index(c)] for c in "xyz"}
    table = np.column_stack([cols.get(c, np.arange(len(points), dtype=float)) for c in names])
    head = f"ply\nformat {fmt} 1.0\n{before}element vertex {len(points) if count is None else count}\n"
    head += "".join(f"property {typ} {c}\n" for c in names) + "end_header\n"
    code = {"double": "f8", "float": "f4", "uchar": "u1", "int": "i4"}[typ]
    if fmt == "ascii":
        return head.encode() + "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in table).encode()
    return head.encode() + table.astype(("<" if "little" in fmt else ">") + code).tobytes()


def xyz(points, sep=" ") -> bytes:
    return "".join(sep.join(repr(float(v)) for v in p) + "\n" for p in np.asarray(points)).encode()


def pcd(points, data="ascii", count=None, fields="x y z", size="4 4 4", typ="F F F", width=None, points_line=True):
    points = np.asarray(points, float)
    n = len(points) if count is None else count
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {typ}\nCOUNT 1 1 1\n"
            f"WIDTH {n if width is None else width}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            + (f"POINTS {n}\n" if points_line else "") + f"DATA {data}\n").encode()
    if data == "ascii":
        return head + "".join(" ".join(repr(v) for v in row) + "\n" for row in points.tolist()).encode()
    return head + points.astype("<f4").tobytes()


def scaled(s):
    with np.errstate(over="ignore", under="ignore"):
        return franke(120) * s


def line_cloud(noise, n=100):
    rng = np.random.default_rng(1)
    t = rng.random(n)
    return np.column_stack([t, 2 * t, 3 * t]) + noise * rng.standard_normal((n, 3))


def identical_but_one():
    p = np.ones((50, 3))
    p[7] = [2.0, 3.0, 5.0]
    return p


def with_nan_in_middle():
    p = franke(100)
    p[50, 1] = np.nan
    return p


def garbage_after_header(typ="double", n=100, seed=0):
    rng = np.random.default_rng(seed)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
            + "".join(f"property {typ} {c}\n" for c in "xyz") + "end_header\n").encode()
    return head + rng.bytes(n * 3 * (8 if typ == "double" else 4))


def lzf_pcd():
    head = (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100\n"
            b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 100\nDATA binary_compressed\n")
    return head + struct.pack("<II", 50, 1200) + os.urandom(50)


def laughs(levels: int = 9, width: int = 9, key: str = "tessellation") -> str:
    """A "billion laughs" under a config key: width**levels values once expanded (9**9: 387
    million), which printing the value in the message would have built."""
    lines = [f"{key}:", "  - &a0 [" + ", ".join(["1"] * width) + "]"]
    lines += [f"  - &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


def fifo(name):
    return lambda d: os.mkfifo(d / name)


def link(name, target):
    return lambda d: (d / name).symlink_to(target if str(target).startswith("/") else d / target)


# ---- the corpus --------------------------------------------------------------------------

GOOD = ply(franke())


def corpus() -> list[Case]:
    cases: list[Case] = []

    def cloud(name, content, expect=(2,), group="cloud", extra_args=(), quick=True):
        cfg = ["-c", "{dir}/quick.yaml"] if quick else []
        cases.append(Case(name, [f"{{dir}}/{name}", *cfg, "-o", "{dir}/out", "-q", *extra_args], expect, group,
                          files={name: content, "quick.yaml": QUICK}))

    def config(name, text, expect=(2,), oversized=False, cloud_bytes=GOOD):
        cases.append(Case(name, ["{dir}/c.ply", "-c", "{dir}/cfg.yaml", "-o", "{dir}/out", "-q"], expect, "config",
                          oversized, files={"c.ply": cloud_bytes, "cfg.yaml": text}))

    # the control
    cloud("good.ply", GOOD, (0,))
    # coordinates
    for s in (1e308, 1e200, 1e154, 1e-308, 1e-320):
        cloud(f"scaled_{s:g}.ply", ply(scaled(s)))
    cloud("scaled_2^400.ply", ply(franke(120) * 2.0 ** 400), (0,))
    cloud("scaled_2^-400.ply", ply(franke(120) * 2.0 ** -400), (0,))
    cloud("offset_1e11.ply", ply(franke(120) + 1e11), (0,))
    cloud("offset_1e15.ply", ply(franke(120) + 1e15))
    cloud("outlier_1e100.ply", ply(np.vstack([franke(120), [[1e100, 0, 0]]])), (0, 2))
    cloud("three_points.xyz", xyz(franke(3)))
    cloud("nine_points.xyz", xyz(franke(9)), (0, 2))
    cloud("all_identical.xyz", xyz(np.ones((40, 3))))
    cloud("identical_but_one.xyz", xyz(identical_but_one()))
    cloud("line.xyz", xyz(line_cloud(0.0)))
    cloud("line_noise_1e-15.xyz", xyz(line_cloud(1e-15)))
    cloud("line_noise_1e-6.xyz", xyz(line_cloud(1e-6)), (0, 2))
    cloud("exact_plane.xyz", xyz(np.column_stack([franke(100)[:, :2], np.zeros(100)])), (0,))
    cloud("two_far_clusters.xyz", xyz(np.vstack([franke(60), franke(60, seed=5) + 1e6])), (0, 2))
    cloud("nan_in_middle.ply", ply(with_nan_in_middle()))
    cloud("inf_text.xyz", b"0 0 0\n1 0 1\n1e999 1 1\n" + xyz(franke(30)))
    # PLY layouts and lies
    cloud("garbage_f8.ply", garbage_after_header("double"))
    cloud("garbage_f4.ply", garbage_after_header("float"), (0, 2))
    cloud("count_1e12.ply", ply(franke(50), count=10**12))
    cloud("count_2^63.ply", ply(franke(50), count=2**63))
    cloud("count_negative.ply", ply(franke(50), count=-7))
    cloud("count_word.ply", ply(franke(50), count="lots"))
    cloud("count_more_ascii.ply", ply(franke(50), fmt="ascii", count=500))
    cloud("count_fewer.ply", ply(franke(50), count=20), (0,))  # fewer than held: the rest is other data
    cloud("zxy.ply", ply(franke(), order="zxy"), (0,))
    cloud("extra_props.ply", ply(franke(), order="yzx", extra=("nx", "ny", "nz", "intensity")), (0,))
    cloud("big_endian.ply", ply(franke(), fmt="binary_big_endian"), (0,))
    cloud("ascii_zxy.ply", ply(franke(), order="zxy", fmt="ascii"), (0,))
    cloud("uchar.ply", ply(np.round(franke() * 200), typ="uchar"), (0, 2))
    cloud("faces_first.ply", b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
          b"element vertex 100\nproperty float x\nproperty float y\nproperty float z\nend_header\n3 0 1 2\n"
          + xyz(franke(100)), (0,))
    cloud("crlf_header.ply", ply(franke()).replace(b"\n", b"\r\n", 7), (0, 2))
    cloud("no_end_header.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n")
    cloud("unknown_type.ply", ply(franke()).replace(b"property double x", b"property quad x"))
    cloud("unknown_format.ply", ply(franke()).replace(b"binary_little_endian", b"binary_middle_endian"))
    cloud("no_z.ply", ply(franke(), order="xy"))
    cloud("header_only.ply", b"ply\nformat binary_little_endian 1.0\nend_header\n")
    cloud("truncated_body.ply", ply(franke())[:-500])
    cloud("random_bytes.ply", os.urandom(4096))
    cloud("huge_header_line.ply", b"ply\nformat ascii 1.0\ncomment " + b"x" * 70000 + b"\nend_header\n")
    # PCD
    cloud("short_ascii.pcd", pcd(franke(40), count=100))
    cloud("short_binary.pcd", pcd(franke(40), data="binary", count=100))
    cloud("good_binary.pcd", pcd(franke(), data="binary"), (0,))
    cloud("good_ascii.pcd", pcd(franke()), (0,))
    cloud("organised_no_points.pcd", pcd(franke(), points_line=False), (0,))
    cloud("bogus_compressed.pcd", lzf_pcd())
    cloud("no_z.pcd", pcd(franke()[:, :2], fields="x y", size="4 4", typ="F F").replace(b"COUNT 1 1 1", b"COUNT 1 1"))
    cloud("bad_data.pcd", pcd(franke(), data="zip"))
    cloud("negative_points.pcd", pcd(franke(), count=-5))
    cloud("pcd_size_3.pcd", pcd(franke(), size="3 3 3"))
    # text
    cloud("bom.xyz", b"\xef\xbb\xbf" + xyz(franke()), (0,))
    cloud("crlf.xyz", xyz(franke()).replace(b"\n", b"\r\n"), (0,))
    cloud("commas.txt", xyz(franke(), sep=", "), (0,))
    cloud("pts_count.pts", b"200\n" + xyz(franke()), (0,))
    cloud("two_columns.xyz", b"1 2\n3 4\n5 6\n")
    cloud("latin1.xyz", "0 0 0 # caf\xe9\n".encode("latin-1") + xyz(franke()))
    cloud("nul_bytes.xyz", xyz(franke())[:100] + b"\x00" * 50)
    cloud("one_long_line.xyz", b"1 " * 5_000_000)
    cloud("arabic_digits.xyz", "\u0661 \u0662 \u0663\n".encode() + xyz(franke()), (0,))
    cloud("utf16.xyz", xyz(franke()).decode().encode("utf-16"))
    # paths
    cases.append(Case("fifo.ply", ["{dir}/fifo.ply", "-o", "{dir}/out"], (2,), "path", files={"": fifo("fifo.ply")}))
    cases.append(Case("dev_zero_link.xyz", ["{dir}/z.xyz", "-o", "{dir}/out"], (2,), "path",
                      files={"": link("z.xyz", "/dev/zero")}))
    cases.append(Case("dev_null_link.ply", ["{dir}/n.ply", "-o", "{dir}/out"], (2,), "path",
                      files={"": link("n.ply", "/dev/null")}))
    cases.append(Case("dangling_link.ply", ["{dir}/d.ply", "-o", "{dir}/out"], (2,), "path",
                      files={"": link("d.ply", "nowhere.ply")}))
    cases.append(Case("link_loop.ply", ["{dir}/loop.ply", "-o", "{dir}/out"], (2,), "path",
                      files={"": lambda d: (os.symlink(d / "loop.ply", d / "loop.ply"))}))
    cases.append(Case("dir_named_ply", ["{dir}/d.ply", "-o", "{dir}/out"], (2,), "path",
                      files={"": lambda d: (d / "d.ply").mkdir()}))
    cases.append(Case("link_to_good.ply", ["{dir}/l.ply", "-c", "{dir}/quick.yaml", "-o", "{dir}/out", "-q"], (0,),
                      "path", files={"g.ply": GOOD, "quick.yaml": QUICK, "": link("l.ply", "g.ply")}))
    cloud("\u00fcnic\u00f8de \u4e91.ply", GOOD, (0,), group="path")
    cloud("new\nline.ply", GOOD, (0,), group="path")
    cases.append(Case("undecodable_name.ply", [b"{dir}/\xff\xfe.ply", "-c", "{dir}/quick.yaml", "-o", "{dir}/out",
                                              "-q"], (0,), "path",
                      files={"quick.yaml": QUICK, "": lambda d: Path(os.fsdecode(os.fsencode(d) + b"/\xff\xfe.ply"))
                             .write_bytes(GOOD)}))
    cloud("n" * 250 + ".ply", GOOD, (2,), group="path")  # its outputs (STEM_error.csv) exceed 255 bytes
    cases.append(Case("name_too_long", ["{dir}/" + "a/" * 2100 + "x.ply", "-o", "{dir}/out"], (2,), "path"))
    cloud("summary.ply", GOOD, (2,), group="path")
    # output directories
    cases.append(Case("out_proc", ["{dir}/c.ply", "-o", "/proc/self/psonurbs", "-q"], (2,), "output",
                      files={"c.ply": GOOD}))
    cases.append(Case("out_is_file", ["{dir}/c.ply", "-o", "{dir}/c.ply"], (2,), "output", files={"c.ply": GOOD}))
    cases.append(Case("out_under_file", ["{dir}/c.ply", "-o", "{dir}/c.ply/out"], (2,), "output",
                      files={"c.ply": GOOD}))
    cases.append(Case("out_is_fifo", ["{dir}/c.ply", "-o", "{dir}/p"], (2,), "output",
                      files={"c.ply": GOOD, "": fifo("p")}))
    cases.append(Case("out_disk_full", ["{dir}/c.ply", "-c", "{dir}/quick.yaml", "-o", "{dir}/out", "-q"], (2,),
                      "output", files={"c.ply": GOOD, "quick.yaml": QUICK}, setup="fsize"))
    # configs
    config("billion_laughs.yaml", laughs(), oversized=True)
    config("laughs_small_under_key.yaml", "t: &t [[1, 2, 3, 4, 5, 6, 7, 8], [9, 10]]\n"
           "tessellation: [" + ", ".join(["*t"] * 90) + "]\n")
    config("nested_brackets.yaml", "tessellation: " + "[" * 100_000 + "]" * 100_000 + "\n")
    config("nested_maps.yaml", "swarm: " + "{a: " * 20_000 + "1" + "}" * 20_000 + "\n")
    config("nested_block_maps.yaml", "".join("  " * i + f"k{i}:\n" for i in range(200)) + "  " * 200 + "x: 1\n")
    config("int_5000_digits.yaml", "swarm:\n  particles: " + "9" * 5000 + "\n")
    config("string_1MB.yaml", "topology: " + "s" * 1_000_000 + "\n")
    config("file_2MB.yaml", "# " + "c" * 2_000_000 + "\n")
    config("iterations_1e9.yaml", "swarm: {iterations: 1000000000}\n", oversized=True)
    config("particles_1e9.yaml", "swarm: {particles: 1000000000}\n", oversized=True)
    config("evaluations_25e6.yaml", "swarm: {particles: 5000, iterations: 5000}\n", oversized=True)  # > 1e7
    config("tessellation_1e5.yaml", "tessellation: [100000, 100000]\n", oversized=True)
    config("tessellation_3000.yaml", "tessellation: [3000, 3000]\n", oversized=True)
    config("net_200.yaml", "net_size: [200, 200]\n", oversized=True)
    config("net_40_on_200_points.yaml", "net_size: [40, 40]\n", oversized=True)
    config("net_2x1000.yaml", "net_size: [3, 1000]\n", oversized=True)
    config("full_strategy_5000_points.yaml", "strategy: full\n" + QUICK, oversized=True, cloud_bytes=ply(franke(5000)))
    config("swarm_points_1e9.yaml", "swarm_points: 1000000000\n", oversized=True)
    config("weights_1e-300.yaml", "weight_bounds: [1.0e-300, 1.0e+300]\n")
    config("smoothing_1e308.yaml", "smoothing: 1.0e+308\n")
    config("inertia_1e308.yaml", "swarm: {inertia: 1.0e+308}\n")
    config("orders_10.yaml", "orders: [10, 10]\nnet_size: [10, 10]\n" + QUICK, (0, 2))
    config("orders_11.yaml", "orders: [11, 3]\nnet_size: [12, 5]\n")
    config("net_2x2.yaml", "orders: [2, 2]\nnet_size: [2, 2]\n" + QUICK, (0,))
    config("sphere_tiny.yaml", "topology: sphere\n" + QUICK, (0, 2), cloud_bytes=ply(franke(20)))
    config("torus_line.yaml", "topology: torus\n" + QUICK, (2,), cloud_bytes=ply(line_cloud(1e-15)))
    config("auto_plane.yaml", "topology: auto\n" + QUICK, (0,))
    config("key_int.yaml", "1: 2\n")
    config("key_list.yaml", "? [1, 2]\n: 3\n")
    config("key_null.yaml", "null: 3\n")
    config("key_map_in_swarm.yaml", "swarm: {? {a: 1} : 2}\n")
    config("python_tag.yaml", "orders: !!python/object/apply:os.system [echo pwned]\n")
    config("binary_tag.yaml", "topology: !!binary aGVsbG8=\n")
    config("timestamp.yaml", "swarm: {seed: " + "-".join(["2001", "12", "14"]) + "}\n")  # a YAML date
    config("set_tag.yaml", "orders: !!set {3: null}\n")
    config("duplicate_keys.yaml", "refine: true\nrefine: false\n")
    config("list_top.yaml", "- orders\n")
    config("not_utf8.yaml", "topology: caf\xe9\n".encode("latin-1"))
    config("bom.yaml", b"\xef\xbb\xbf" + QUICK.encode(), (0,))
    config("empty.yaml", "", (0,))
    config("recursive_alias.yaml", "swarm: &s {particles: *s}\n")
    config("merge_keys.yaml", "base: &b {particles: 4}\nswarm: {<<: *b, iterations: 3}\npolish_iterations: 5\n")
    config("true_as_int.yaml", "swarm: {particles: true}\n")
    config("float_int.yaml", "swarm: {particles: 4.0}\n")
    config("nan_gap.yaml", "min_knot_gap: .nan\n")
    cases.append(Case("config_fifo", ["{dir}/c.ply", "-c", "{dir}/p.yaml", "-o", "{dir}/out"], (2,), "config",
                      files={"c.ply": GOOD, "": fifo("p.yaml")}))
    cases.append(Case("config_dev_zero", ["{dir}/c.ply", "-c", "{dir}/z.yaml", "-o", "{dir}/out"], (2,), "config",
                      files={"c.ply": GOOD, "": link("z.yaml", "/dev/zero")}))
    # options
    for name, opts, expect in [
        ("iterations_1e23", ["--iterations", "99999999999999999999999"], (2,)),
        ("particles_negative", ["--particles", "-1"], (2,)),
        ("seed_2^128", ["--seed", str(2**128)], (2,)),
        ("seed_2^64-1", ["--seed", str(2**64 - 1), "-c", "{dir}/quick.yaml"], (0,)),
        ("topology_Sphere", ["--topology", "Sphere"], (2,)),
        ("jobs_0", ["--jobs", "0"], (2,)),
        ("jobs_1000", ["--jobs", "1000", "-c", "{dir}/quick.yaml"], (0,)),
        ("max_rmse_nan", ["--max-rmse", "nan"], (2,)),
        ("max_rmse_rel_tiny", ["--max-rmse-rel", "1e-300", "-c", "{dir}/quick.yaml"], (3,)),
        ("format_unknown", ["--format", "stl"], (2,)),
        ("unknown_option", ["--frobnicate"], (2,)),
        ("particles_word", ["--particles", "many"], (2,)),
    ]:
        cases.append(Case(name, ["{dir}/c.ply", "-o", "{dir}/out", "-q", *opts], expect, "option",
                          files={"c.ply": GOOD, "quick.yaml": QUICK}))
    # the batch: a worker killed for real, a run terminated
    batch = {f"b{k}.ply": ply(franke(300, seed=k, noise=1e-3)) for k in range(4)}
    # seconds per cloud, well past SIGNAL_AFTER whatever the machine (with the compiled fitness too: 40 x 300 took
    # under a second a cloud, and the batch could end before its signal)
    slow = "swarm: {particles: 40, iterations: 3000}\npolish_iterations: 20\n"
    cases.append(Case("jobs2_worker_sigkill", ["{dir}", "-c", "{dir}/slow.yaml", "-o", "{dir}/out", "-q", "--jobs",
                                                "2"], (4,), "batch", setup="kill_worker",
                      files={**batch, "slow.yaml": slow}))
    cases.append(Case("sigterm_mid_run", ["{dir}", "-c", "{dir}/slow.yaml", "-o", "{dir}/out", "-q", "--jobs", "2"],
                      (143,), "batch", setup="terminate", files={**batch, "slow.yaml": slow}))
    cases.append(Case("mixed_batch", ["{dir}", "-c", "{dir}/quick.yaml", "-o", "{dir}/out", "-q", "--jobs", "2"], (2,),
                      "batch", files={"a.ply": GOOD, "b.ply": ply(scaled(1e200)), "c.pcd": pcd(franke(10), count=99),
                                      "d.xyz": b"\xef\xbb\xbf" + xyz(franke()), "quick.yaml": QUICK}))
    return cases


# ---- running a case ------------------------------------------------------------------------

@dataclass
class Outcome:
    code: int | None
    seconds: float
    rss_mb: float
    stderr: str
    verdict: str


def children_of(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def run_case(case: Case, directory: Path) -> Outcome:
    directory.mkdir(parents=True)
    for name, content in case.files.items():
        if callable(content):
            content(directory)
        elif isinstance(content, str):
            (directory / name).write_text(content, encoding="utf-8")
        else:
            (directory / name).write_bytes(content)
    args = [a.replace(b"{dir}", os.fsencode(directory)) if isinstance(a, bytes) else a.replace("{dir}", str(directory))
            for a in case.args]

    def limits():
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
        if case.setup == "fsize":  # a full disk: writes beyond 64 KiB fail with EFBIG
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (64 << 10, 64 << 10))

    command = [sys.executable, "-c", "from psonurbs.cli.main import main; main()", "fit", *args]
    start = time.perf_counter()
    logs = directory.parent / f"{directory.name}.stdout", directory.parent / f"{directory.name}.stderr"
    with open(logs[0], "wb") as out, open(logs[1], "wb") as err:  # beside: a case may fit its whole directory
        process = subprocess.Popen(command, stdout=out, stderr=err, preexec_fn=limits, cwd=directory,
                                   env={**os.environ, "PSONURBS_DEBUG": ""})
        signalled = False
        while True:  # wait4: this child's own peak memory, not the maximum over all children
            pid, status, usage = os.wait4(process.pid, os.WNOHANG)
            if pid:
                break
            elapsed = time.perf_counter() - start
            if case.setup in ("kill_worker", "terminate") and not signalled and elapsed > SIGNAL_AFTER:
                workers = [w for w in children_of(process.pid)
                           if b"spawn_main" in Path(f"/proc/{w}/cmdline").read_bytes()]
                if workers:  # the workers have started and are fitting
                    signalled = True
                    if case.setup == "terminate":
                        process.send_signal(signal.SIGTERM)
                    else:
                        os.kill(workers[0], signal.SIGKILL)
            if elapsed > TIME_LIMIT:
                process.kill()
                _, status, usage = os.wait4(process.pid, 0)
                status = None
                break
            time.sleep(0.05)
        process.returncode = 0  # reaped here: keep Popen from waiting again
    code = None if status is None else os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - start
    text = logs[1].read_bytes().decode("utf-8", "backslashreplace")
    longest = max((len(a) for a in args), default=0)  # a message may quote a path in full
    return Outcome(code, seconds, usage.ru_maxrss / 1024, text, verdict(case, code, text, directory / "out", longest))


def verdict(case: Case, code, stderr: str, out: Path, longest_argument: int = 0) -> str:
    problems = []
    if code is None:
        problems.append(f"timed out ({TIME_LIMIT} s)")
    elif code not in case.expect:
        problems.append(f"exit {code}, expected {'/'.join(map(str, case.expect))}")
    if "Traceback" in stderr or "internal error" in stderr:
        problems.append("traceback/internal error")
    if any(not line.startswith("psonurbs: ") or len(line) > 600 + longest_argument for line in stderr.splitlines()):
        problems.append("stderr not one-line psonurbs messages")
    if code == 2 and case.group != "batch" and out.is_dir():
        written = [p.name for p in out.iterdir() if not p.name.startswith("summary.")]
        if written:
            problems.append(f"wrote {written[:3]} on refusal")
    return "held" if not problems else "BROKEN: " + "; ".join(problems)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", default="", help="run the cases whose name contains this")
    parser.add_argument("--keep", default=None, help="keep the case directories here")
    options = parser.parse_args()
    cases = [c for c in corpus() if options.only in c.name]
    root = Path(options.keep or tempfile.mkdtemp(prefix="psonurbs-hostile-"))
    held = 0
    memory = []
    print(f"{len(cases)} cases, each `psonurbs fit` in a fresh process (limits: {TIME_LIMIT} s, "
          f"{MEMORY_LIMIT >> 30} GiB address space)\n")
    print("| # | group | case | exit | seconds | peak RSS MiB | verdict | first stderr line |")
    print("|---|---|---|---|---|---|---|---|")
    for k, case in enumerate(cases, 1):
        directory = root / f"case{k:03d}"
        outcome = run_case(case, directory)
        if case.oversized:
            memory.append((case.name, outcome.rss_mb))
        held += outcome.verdict == "held"
        first = (outcome.stderr.splitlines() or [""])[0].replace(str(directory), "D").replace("|", "/")
        shown = case.name.encode("unicode_escape").decode()[:40]
        print(f"| {k} | {case.group} | {shown} | {outcome.code} | {outcome.seconds:.1f} | "
              f"{outcome.rss_mb:.0f} | {outcome.verdict} | {first[:110]} |", flush=True)
    print(f"\ncontract held on {held} of {len(cases)} cases")
    if memory:
        worst = max(memory, key=lambda m: m[1])
        print(f"refused oversized configs: {len(memory)}, peak RSS at most {worst[1]:.0f} MiB ({worst[0]})")
    if not options.keep:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if held == len(cases) else 1


if __name__ == "__main__":
    sys.exit(main())
