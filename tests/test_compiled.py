"""The optional compiled kernels' switch (psonurbs.geometry.compiled)."""
import os
import subprocess
import sys
import threading

import numpy as np

from psonurbs.geometry import compiled


def flags(env_value):
    env = dict(os.environ, PSONURBS_NO_JIT=env_value)
    code = "from psonurbs.geometry import compiled; print(compiled.ENABLED)"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_no_jit_forces_the_numpy_path():
    assert flags("1") == "False"


def test_a_kernel_computes_what_its_python_source_does():
    def weighted_sum(x, w):
        total = 0.0
        for i in range(x.shape[0]):
            total += x[i] * w[i]
        return total

    x, w = np.arange(5.0), np.array([1.0, -2.0, 0.5, 3.0, 0.25])
    assert compiled.kernel(weighted_sum)(x, w) == weighted_sum(x, w) == 9.0


def test_an_inline_helper_computes_the_same_inside_a_kernel():
    @compiled.kernel(inline=True)
    def squared_plus_one(x):
        return x * x + 1.0

    @compiled.kernel
    def total(x):
        out = 0.0
        for i in range(x.shape[0]):
            out += squared_plus_one(x[i])
        return out

    assert total(np.arange(4.0)) == 1.0 + 2.0 + 5.0 + 10.0 and squared_plus_one(3.0) == 10.0


def test_threads_come_from_the_environment_and_the_worker_limit(monkeypatch):
    monkeypatch.setenv("PSONURBS_THREADS", "3")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert compiled.threads() == 3
    monkeypatch.delenv("PSONURBS_THREADS")
    assert compiled.threads() == 1  # a worker process of --jobs or dask: one thread a fit
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert compiled.threads() >= 1


def test_over_parts_covers_every_item_once_in_parts_of_at_least_the_smallest(monkeypatch):
    monkeypatch.setenv("PSONURBS_THREADS", "4")
    for count, smallest in ((10, 1), (10, 3), (5, 10), (0, 1), (1001, 100)):
        seen, parts = np.zeros(count, int), []

        def run(part, seen=seen, parts=parts):
            seen[part] += 1
            parts.append(part.stop - part.start)

        compiled.over_parts(count, run, smallest)
        assert (seen == 1).all(), (count, smallest)
        expected = max(1, min(4, count // smallest)) if compiled.ENABLED else 1
        assert len(parts) == expected and (count == 0 or min(parts) >= min(smallest, count)), (count, parts)


def test_each_calls_the_function_once_per_item_in_threads(monkeypatch):
    monkeypatch.setenv("PSONURBS_THREADS", "3")
    out, threads = np.zeros(100), set()

    def work(part):
        threads.add(threading.get_ident())
        out[part] += np.arange(part.start, part.stop)

    compiled.each(work, [slice(k, k + 10) for k in range(0, 100, 10)])
    np.testing.assert_array_equal(out, np.arange(100))
    assert 1 <= len(threads) <= 3


def test_work_shared_inside_a_pool_worker_runs_there(monkeypatch):
    # nested sharing would wait on the very workers it occupies: it runs in the worker instead
    monkeypatch.setenv("PSONURBS_THREADS", "2")
    out = np.zeros((2, 100))

    def outer(row):
        def inner(part):
            out[row, part] += 1.0 + row
        compiled.over_parts(100, inner, 10)
        return sum(compiled.in_order(lambda k: k * row, range(5)))

    done = []
    runner = threading.Thread(target=lambda: done.append(list(compiled.in_order(outer, [0, 1]))), daemon=True)
    runner.start()
    runner.join(timeout=30)
    assert done == [[0, 10]]
    np.testing.assert_array_equal(out, [[1.0] * 100, [2.0] * 100])
