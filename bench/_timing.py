"""Timing helpers shared by the benchmark scripts (run as ``python bench/NAME.py``)."""

import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager


def best_of(fn, repeat):
    """Shortest wall time of ``repeat`` calls, and the last call's result."""
    times = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def best_wall_cpu(fn, repeat=3):
    """``(wall, cpu)`` seconds of the fastest of ``repeat`` calls (CPU time shows how many
    cores a run really had on a shared machine)."""
    best = (float("inf"), 0.0)
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - t0, time.process_time() - c0))
    return best


@contextmanager
def busy_loops(n, nice):
    """``n`` busy loops ``python -c 'while 1: pass'`` at ``nice -n nice`` for the block
    (after a second to get going): other work competing for the cores."""
    loops = [subprocess.Popen(["nice", "-n", str(nice), sys.executable, "-c", "while 1: pass"])
             for _ in range(n)]
    try:
        time.sleep(1.0)
        yield
    finally:
        for p in loops:
            p.kill()
            p.wait()


def run_cold(checkout: str, child: str, *args: str):
    """The JSON on the last stdout line of ``python -c child CHECKOUT/statmc *args``, run in
    ``checkout`` (first on ``PYTHONPATH``) with an empty private ``NUMBA_CACHE_DIR``: a
    user's first calls, whatever this machine has cached (the ``*_compile`` scripts)."""
    with tempfile.TemporaryDirectory(prefix="numba_cache_") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache,
                   PYTHONPATH=os.pathsep.join([checkout, os.environ.get("PYTHONPATH", "")]))
        res = subprocess.run([sys.executable, "-c", child, os.path.join(checkout, "statmc"),
                              *args], env=env, cwd=checkout, check=True,
                             capture_output=True, text=True)
    return json.loads(res.stdout.strip().splitlines()[-1])
