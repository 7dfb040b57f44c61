"""Cold-cache compile time of the GEM path: what a user waits on at the first
``gem.reconstruct`` and ``gem.sampling_map`` (``statmc reconstruct``,
``statmc render --sampler gem``) before numba's cache holds the kernels.

Each run is a fresh process with its own empty ``NUMBA_CACHE_DIR``; it times
``gem.reconstruct`` then ``gem.sampling_map`` on a 64x64x3 float64 image (process CPU
seconds, ``time.process_time``, and wall seconds).  Give several checkouts to alternate
them (the machine may be shared: compare runs made side by side)::

    python bench/bench_gem_compile.py [--repeat 2] [CHECKOUT ...]

A checkout is a directory holding ``statmc/`` (default: this one); ``--warm`` also times
a second call of each in the same process (numba's compiled kernels, no compile).
"""

from __future__ import annotations

import argparse
import os

from _timing import run_cold  # noqa: E402  (bench/ is the script's folder)

CHILD = r"""
import json, sys, time
import numpy as np
t0 = time.process_time(), time.perf_counter()
import statmc.gem as gem
assert gem.__file__.startswith(sys.argv[1]), gem.__file__
rng = np.random.default_rng(0)
m = rng.uniform(0.1, 1.0, (64, 64, 3))
v = np.full_like(m, 0.01)
n = np.full((64, 64), 8)
out = {}
for rep in range(2 if sys.argv[2] == "1" else 1):
    for name, call in (("reconstruct", lambda: gem.reconstruct(m, v)),
                       ("sampling_map", lambda: gem.sampling_map(m, v, n, 10000, rng=0))):
        c, w = time.process_time(), time.perf_counter()
        call()
        out[name + ("" if rep == 0 else " (warm)")] = (time.process_time() - c,
                                                      time.perf_counter() - w)
print(json.dumps(out))
"""


def run(checkout: str, warm: bool) -> dict:
    return run_cold(checkout, CHILD, "1" if warm else "0")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkouts", nargs="*",
                   default=[os.path.dirname(os.path.dirname(os.path.abspath(__file__)))])
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--warm", action="store_true")
    a = p.parse_args()
    for r in range(a.repeat):
        for c in a.checkouts:
            t = run(os.path.abspath(c), a.warm)
            cpu = sum(v[0] for k, v in t.items() if "warm" not in k)
            wall = sum(v[1] for k, v in t.items() if "warm" not in k)
            parts = "  ".join(f"{k} {v[0]:.1f} s CPU / {v[1]:.1f} s wall" for k, v in t.items())
            print(f"run {r + 1} {c}: {parts}  | cold total {cpu:.1f} s CPU / {wall:.1f} s wall",
                  flush=True)


if __name__ == "__main__":
    main()
