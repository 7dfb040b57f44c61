"""Timing helpers shared by the benchmark scripts (run as ``python bench/NAME.py``)."""

import subprocess
import sys
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
