"""FLIP call time on a busy machine: flip_evaluator's bundled libgomp, default vs statmc's import.

flip_evaluator ships its own libgomp (``flip_evaluator.libs/libgomp-*.so``), which reads
``OMP_WAIT_POLICY`` / ``GOMP_SPINCOUNT`` / ``OMP_NUM_THREADS`` once, when it is loaded.
Each mode below runs in a fresh subprocess (a runtime cannot be reconfigured after load):

* ``plain``    — ``import flip_evaluator`` with the environment as given (libgomp defaults:
  threads spin for a while at every barrier before they sleep);
* ``statmc``   — ``statmc.metrics._flip_module()``: OMP_WAIT_POLICY=PASSIVE for the import
  only (what ``statmc.metrics.flip`` uses);
* ``threads1`` — ``OMP_NUM_THREADS=1`` in the environment (the session-8 workaround; it
  changes every OpenMP runtime of the process, not only FLIP's).

Under load = ``--loops`` busy loops ``python -c 'while 1: pass'`` started at ``nice -n
--nice`` (default: one per core, nice 10, like other people's niced renders while a test
run is at nice 0).  Prints median / max / total per call size, and the ratio against the
``plain`` peer measured in the same run, plus the load average.  Also checks that the
three modes return the same FLIP values bit for bit.

Run: ``.venv/bin/python bench/bench_flip_load.py [--loops 2] [--nice 10] [--reps 40 8]``
"""

import argparse
import os
import subprocess
import sys
import time

from _timing import busy_loops  # noqa: E402  (bench/ is the script's folder)

_CHILD = r"""
import os, sys, time, json, hashlib
import numpy as np
mode, reps_small, reps_big = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
if mode == "statmc":
    from statmc.metrics import _flip_module
    fe = _flip_module()
else:
    import flip_evaluator as fe
out = {}
for n, reps in ((16, reps_small), (256, reps_big)):
    rng = np.random.default_rng(n)
    r = rng.random((n, n, 3)).astype(np.float32)
    x = np.abs(r + 0.1 * rng.standard_normal(r.shape)).astype(np.float32)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        m, e, _ = fe.evaluate(r, x, "HDR", applyMagma=False, computeMeanError=True, parameters={})
        ts.append(time.perf_counter() - t0)
    out[n] = {"times": ts, "mean": float(e), "map_hash": hashlib.sha1(np.ascontiguousarray(m).tobytes()).hexdigest()}
cpu = time.process_time()
print(json.dumps({"res": out, "cpu": cpu}))
"""

MODES = {"plain": {}, "statmc": {}, "threads1": {"OMP_NUM_THREADS": "1"}}


def run_mode(mode, reps_small, reps_big):
    env = dict(os.environ)
    for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS"):
        env.pop(k, None)
    env.update(MODES[mode])
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", _CHILD, mode, str(reps_small), str(reps_big)],
                       env=env, capture_output=True, text=True, check=True,
                       cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import json
    d = json.loads(p.stdout.strip().splitlines()[-1])
    d["wall"] = time.perf_counter() - t0
    return d


def table(label, results):
    import numpy as np
    print(f"\n== {label}   (load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f})")
    print(f"{'mode':9s} {'size':>5s} {'median ms':>10s} {'max ms':>8s} {'total s':>8s} "
          f"{'vs plain (total)':>16s}")
    for n in ("16", "256"):
        base = sum(results["plain"]["res"][n]["times"])
        for mode, d in results.items():
            ts = np.array(d["res"][n]["times"])
            print(f"{mode:9s} {n + '²':>5s} {1e3 * np.median(ts):10.1f} {1e3 * ts.max():8.0f} "
                  f"{ts.sum():8.2f} {ts.sum() / base:15.2f}x")
    ref = results["plain"]["res"]
    for mode, d in results.items():
        for n in ("16", "256"):
            same = (d["res"][n]["mean"] == ref[n]["mean"]
                    and d["res"][n]["map_hash"] == ref[n]["map_hash"])
            if not same:
                print(f"!! {mode} {n}²: FLIP differs from plain "
                      f"({d['res'][n]['mean']!r} vs {ref[n]['mean']!r})")
    print("FLIP values (mean and map) identical across modes: checked")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--nice", type=int, default=10)
    ap.add_argument("--reps", type=int, nargs=2, default=(40, 8), metavar=("SMALL", "BIG"))
    ap.add_argument("--no-idle", action="store_true", help="skip the run without busy loops")
    a = ap.parse_args()
    if not a.no_idle:
        table("as is (no busy loops of ours)", {m: run_mode(m, *a.reps) for m in MODES})
    with busy_loops(a.loops, a.nice):
        res = {m: run_mode(m, *a.reps) for m in MODES}
    table(f"{a.loops} busy loops at nice {a.nice}", res)


if __name__ == "__main__":
    main()
