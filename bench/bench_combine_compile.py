"""Cold-cache compile time of the combination: what a user waits on at the first
``combine.statistical_weights``, ``combine.combine_denoised`` and ``combine.combine_bins``
(``statmc render --reconstruct oidn+combine`` / ``gem+bins``) before numba's cache holds
the kernels.

Each call runs in a fresh process with its own empty ``NUMBA_CACHE_DIR`` on a 40x48x3
float64 image (``combine_bins``: 4 bins; ``both``: ``combine_denoised`` then
``combine_bins`` in one process), with a SciPy box blur as the denoiser, so only
the combination's own kernels compile (those of ``statmc.analytic`` that the SURE mix
uses included; GEM's or OIDN's are not).  It prints process CPU seconds
(``time.process_time``, all threads) and wall seconds of the call, and with
``--breakdown`` the CPU seconds of each compiled function, exclusive of the functions it
calls (numba's ``numba:compile`` events), and how many argument types each was compiled
for.  Give several checkouts to alternate them (the machine may be shared: compare runs
made side by side)::

    python bench/bench_combine_compile.py [--repeat 2] [--breakdown] [--calls weights ...] [CHECKOUT ...]

A checkout is a directory holding ``statmc/`` (default: this one).
"""

from __future__ import annotations

import argparse
import os

CALLS = ("weights", "denoised", "bins", "both")

from _timing import run_cold  # noqa: E402  (bench/ is the script's folder)

CHILD = r"""
import json, sys, time
import numpy as np
from numba.core import event

stack, rows = [], []


class Listener(event.Listener):
    def on_start(self, ev):
        stack.append([time.process_time(), 0.0])

    def on_end(self, ev):
        c0, child = stack.pop()
        c = time.process_time() - c0
        d = ev.data.get("dispatcher")
        rows.append((getattr(getattr(d, "py_func", None), "__name__", str(d)),
                     str(ev.data.get("args")), c - child))
        if stack:
            stack[-1][1] += c


event.register("numba:compile", Listener())
import statmc.combine as cb
from scipy.ndimage import uniform_filter
assert cb.__file__.startswith(sys.argv[1]), cb.__file__


def blur(c):
    return uniform_filter(np.asarray(c, np.float64), size=(5, 5, 1), mode="reflect")


rng = np.random.default_rng(0)
H, W, C = 40, 48, 3
y = rng.uniform(0.1, 1.0, (H, W, C))
mv = np.full((H, W, C), 0.01)
cov = np.full((H, W, 5, 5, C), 0.001)
cov[:, :, 2, 2] = 0.004
ys = rng.uniform(0.1, 1.0, (4, H, W, C))
call = {"weights": lambda: cb.statistical_weights(y, blur(y), mv, cov, 7),
        "denoised": lambda: cb.combine_denoised(y, mv, blur, rng=0),
        "bins": lambda: cb.combine_bins(ys, mv, blur, rng=0),
        "both": lambda: (cb.combine_denoised(y, mv, blur, rng=0),
                         cb.combine_bins(ys, mv, blur, rng=0))}[sys.argv[2]]
c, w = time.process_time(), time.perf_counter()
call()
print(json.dumps({"cpu": time.process_time() - c, "wall": time.perf_counter() - w,
                  "rows": rows}))
"""


def run(checkout: str, call: str) -> dict:
    return run_cold(checkout, CHILD, call)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkouts", nargs="*",
                   default=[os.path.dirname(os.path.dirname(os.path.abspath(__file__)))])
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--calls", nargs="+", choices=CALLS, default=list(CALLS[:3]))
    p.add_argument("--breakdown", action="store_true")
    a = p.parse_args()
    for r in range(a.repeat):
        for call in a.calls:
            for c in a.checkouts:
                t = run(os.path.abspath(c), call)
                print(f"run {r + 1} {call:8s} {c}: {t['cpu']:5.1f} s CPU / {t['wall']:5.1f} s "
                      f"wall", flush=True)
                if a.breakdown:
                    per = {}
                    for name, args, cpu in t["rows"]:
                        n = per.setdefault(name, [0.0, set()])
                        n[0] += cpu
                        n[1].add(args)
                    for name, (cpu, sigs) in sorted(per.items(), key=lambda kv: -kv[1][0]):
                        if cpu >= 0.05:
                            print(f"    {name:30s} {cpu:5.1f} s CPU, {len(sigs)} argument "
                                  f"type(s)", flush=True)


if __name__ == "__main__":
    main()
