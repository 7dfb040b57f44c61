"""numba kernels on a busy machine: libgomp's default spin-wait vs statmc's passive waits.

numba's ``omp`` threading layer runs statmc's parallel kernels on the system's libgomp,
which reads ``OMP_WAIT_POLICY`` / ``GOMP_SPINCOUNT`` once, when numba starts its pool.
statmc makes numba start that pool (at the first parallel kernel call) with
``OMP_WAIT_POLICY=PASSIVE`` for that moment only (``statmc._threads.wait_passively_in_numba``).
Each mode runs in a fresh subprocess:

* ``statmc`` -- the environment without any OpenMP variable: statmc's passive waits;
* ``spin``   -- ``GOMP_SPINCOUNT=300000``, libgomp's own default when nothing is set (what
  statmc's kernels ran with before); statmc keeps out when a user sets a wait variable.

Each child times ``gem.reconstruct`` (final, pooled: the default) of a 64x64 and a 512x512
RGB image, and prints the median, max and total per size; the table gives the ratio
against ``spin`` measured in the same run, the load average, and checks that both modes
return the same images bit for bit.  (statmc runs images below ``_threads.SERIAL_VALUES``
values, here the 64x64 one, on one thread while its pool waits passively; with a wait
variable set, as in ``spin``, it stays parallel as before.)  Three settings:

* as is (whatever else the machine runs);
* ``--loops`` busy loops ``python -c 'while 1: pass'`` at ``nice -n --nice`` (default: one
  per core at nice 0, other work of the same priority);
* two children of the same mode at once (two statmc jobs side by side: each one's
  spinning workers take the cores the other's need).

Run: ``.venv/bin/python bench/bench_numba_load.py [--loops 2] [--nice 0] [--reps 100 6]``
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from _timing import busy_loops  # noqa: E402  (bench/ is the script's folder)

_CHILD = r"""
import hashlib, json, sys, time
import numpy as np
import statmc.gem as gem
import numba
reps = {64: int(sys.argv[1]), 512: int(sys.argv[2])}
out = {}
for n, k in reps.items():
    rng = np.random.default_rng(n)
    m = rng.random((n, n, 3)).astype(np.float32)
    v = (0.01 * rng.random((n, n, 3))).astype(np.float32)
    img = gem.reconstruct(m, v)                       # compiled (cache) and warm
    ts = []
    for _ in range(k):
        t0 = time.perf_counter()
        gem.reconstruct(m, v)
        ts.append(time.perf_counter() - t0)
    out[str(n)] = {"times": ts, "hash": hashlib.sha1(img.tobytes()).hexdigest()}
out["cpu"] = time.process_time()
out["layer"] = numba.threading_layer()       # known once the pool has started
print(json.dumps(out))
"""

MODES = {"statmc": {}, "spin": {"GOMP_SPINCOUNT": "300000"}}


def run_mode(mode, reps, copies=1):
    """Run ``copies`` children of ``mode`` at once; returns the first one's results, with
    each size's times of all children concatenated."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")}
    env.update(MODES[mode])
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env.setdefault("NUMBA_CACHE_DIR", os.path.join(root, ".cache", "numba"))
    procs = [subprocess.Popen([sys.executable, "-c", _CHILD, *map(str, reps)], env=env,
                              stdout=subprocess.PIPE, text=True, cwd=root)
             for _ in range(copies)]
    outs = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
    if any(p.returncode for p in procs):
        raise RuntimeError(f"a {mode} child failed")
    for o in outs[1:]:
        for n in ("64", "512"):
            outs[0][n]["times"] += o[n]["times"]
    return outs[0]


def table(label, res):
    la = os.getloadavg()
    print(f"\n== {label}   (load average {la[0]:.2f} {la[1]:.2f}; numba threading layer "
          f"{res['statmc']['layer']})")
    print(f"{'mode':7s} {'size':>5s} {'median ms':>10s} {'max ms':>8s} {'total s':>8s} "
          f"{'vs spin (total)':>16s}")
    for n in ("64", "512"):
        base = sum(res["spin"][n]["times"])
        for mode, d in res.items():
            ts = np.array(d[n]["times"])
            print(f"{mode:7s} {n + '²':>5s} {1e3 * np.median(ts):10.1f} {1e3 * ts.max():8.0f} "
                  f"{ts.sum():8.2f} {ts.sum() / base:15.2f}x")
        same = len({d[n]["hash"] for d in res.values()}) == 1
        print(f"   {n}²: images identical across modes: {'yes' if same else 'NO'}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--nice", type=int, default=0)
    ap.add_argument("--reps", type=int, nargs=2, default=(100, 6), metavar=("N64", "N512"))
    ap.add_argument("--no-idle", action="store_true", help="skip the run without busy loops")
    a = ap.parse_args()
    if not a.no_idle:
        table("as is (no busy loops of ours)", {m: run_mode(m, a.reps) for m in MODES})
    with busy_loops(a.loops, a.nice):
        res = {m: run_mode(m, a.reps) for m in MODES}
    table(f"{a.loops} busy loops at nice {a.nice}", res)
    table("two children of each mode at once", {m: run_mode(m, a.reps, copies=2) for m in MODES})


if __name__ == "__main__":
    main()
