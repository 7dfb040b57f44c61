"""numba kernels on a busy machine: libgomp's default spin-wait vs statmc's passive waits.

numba's ``omp`` threading layer runs statmc's parallel kernels on the system's libgomp,
which reads ``OMP_WAIT_POLICY`` / ``GOMP_SPINCOUNT`` once, when numba starts its pool.
statmc makes numba start that pool (at the first parallel kernel call) with
``OMP_WAIT_POLICY=PASSIVE`` for that moment only (``statmc._threads.wait_passively_in_numba``).
Each mode runs in a fresh subprocess:

* ``statmc`` -- the environment without any OpenMP variable: statmc's passive waits;
* ``spin``   -- ``GOMP_SPINCOUNT=300000``, libgomp's own default when nothing is set (what
  statmc's kernels ran with before); statmc keeps out when a user sets a wait variable;
* ``spinN``  -- ``GOMP_SPINCOUNT=N`` for each ``--spin N`` given: libgomp spins N rounds
  (about 25 ns each on the machine measured) before it sleeps; session 11's sweep of
  spin counts between the two (docs/gem.md §7).

Each child times ``gem.reconstruct`` (final, pooled: the default) of RGB images of each
``--sizes`` (default 64x64, 256x256, 512x512, 1920x1080) for ``--seconds`` per size (at
least 3 calls), and prints the median, max and total per size; the table gives the ratio of
medians against ``spin`` measured in the same run, the CPU time other processes used while the
children ran (``other cores``, from /proc/stat), the load average, and checks that all
modes return the same images bit for bit.  (The pooled ``reconstruct`` runs images below
``gem.FUSED_SERIAL_VALUES`` values, here 64x64, on the calling thread in every mode.  Since
session 16 statmc's kernels run on its own Python task threads and never start numba's
OpenMP pool, so the modes should no longer differ; the script stays to show that.)
Three settings:

* as is (whatever else the machine runs);
* ``--loops`` busy loops ``python -c 'while 1: pass'`` at ``nice -n --nice`` (default: one
  per core at nice 0, other work of the same priority);
* two children of the same mode at once (two statmc jobs side by side: each one's
  spinning workers take the cores the other's need).

Run: ``.venv/bin/python bench/bench_numba_load.py [--loops 2] [--nice 0] [--seconds 2]
[--sizes 64 256 512 1080] [--spin 1000 10000]``
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from _timing import busy_loops  # noqa: E402  (bench/ is the script's folder)

_CHILD = r"""
import hashlib, json, sys, time
import numpy as np
import statmc.gem as gem
import numba
budget = float(sys.argv[1])
out = {}
for size in sys.argv[2:]:
    h, w = map(int, size.split("x"))
    rng = np.random.default_rng(h)
    m = rng.random((h, w, 3)).astype(np.float32)
    v = (0.01 * rng.random((h, w, 3))).astype(np.float32)
    img = gem.reconstruct(m, v)                       # compiled (cache) and warm
    ts = []
    end = time.perf_counter() + budget
    while time.perf_counter() < end or len(ts) < 3:
        t0 = time.perf_counter()
        gem.reconstruct(m, v)
        ts.append(time.perf_counter() - t0)
    out[size] = {"times": ts, "hash": hashlib.sha1(img.tobytes()).hexdigest()}
out["cpu"] = time.process_time()
out["layer"] = numba.threading_layer()       # known once the pool has started
print(json.dumps(out))
"""

SIZES = {64: "64x64", 256: "256x256", 512: "512x512", 1080: "1080x1920"}


def _busy_seconds():
    """CPU seconds all processes have used (Linux /proc/stat), or None."""
    try:
        with open("/proc/stat") as f:
            v = [int(t) for t in f.readline().split()[1:]]
    except OSError:
        return None
    return (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


MODES = {"statmc": {}, "spin": {"GOMP_SPINCOUNT": "300000"}}


def run_mode(mode, sizes, seconds, copies=1):
    """Run ``copies`` children of ``mode`` at once; returns the first one's results, with
    each size's times of all children concatenated, and ``other``: the cores other
    processes (not these children) kept busy meanwhile."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")}
    env.update(MODES[mode])
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env.setdefault("NUMBA_CACHE_DIR", os.path.join(root, ".cache", "numba"))
    busy0, wall0 = _busy_seconds(), time.time()
    procs = [subprocess.Popen([sys.executable, "-c", _CHILD, str(seconds), *sizes], env=env,
                              stdout=subprocess.PIPE, text=True, cwd=root)
             for _ in range(copies)]
    outs = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
    if any(p.returncode for p in procs):
        raise RuntimeError(f"a {mode} child failed")
    busy1 = _busy_seconds()
    own = sum(o["cpu"] for o in outs)                  # each child's CPU time, all threads
    outs[0]["other"] = (None if busy0 is None else
                        (busy1 - busy0 - own) / max(time.time() - wall0, 1e-9))
    for o in outs[1:]:
        for n in sizes:
            outs[0][n]["times"] += o[n]["times"]
    return outs[0]



def table(label, res, sizes):
    la = os.getloadavg()
    print(f"\n== {label}   (load average {la[0]:.2f} {la[1]:.2f}; numba threading layer "
          f"{res['statmc']['layer']})")
    print(f"{'mode':10s} {'size':>10s} {'median ms':>10s} {'max ms':>8s} {'total s':>8s} "
          f"{'vs spin':>8s} {'other cores':>12s}")
    for n in sizes:
        base = np.median(res["spin"][n]["times"])
        for mode, d in res.items():
            ts = np.array(d[n]["times"])
            other = "?" if d["other"] is None else f"{d['other']:.2f}"
            print(f"{mode:10s} {n:>10s} {1e3 * np.median(ts):10.1f} {1e3 * ts.max():8.0f} "
                  f"{ts.sum():8.2f} {np.median(ts) / base:7.2f}x {other:>12s}")
        same = len({d[n]["hash"] for d in res.values()}) == 1
        print(f"   {n}: images identical across modes: {'yes' if same else 'NO'}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--nice", type=int, default=0)
    ap.add_argument("--seconds", type=float, default=2.0, help="timing per size and mode")
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--spin", type=int, nargs="*", default=[], metavar="N",
                    help="also run with GOMP_SPINCOUNT=N (mode spinN)")
    ap.add_argument("--no-idle", action="store_true", help="skip the run without busy loops")
    a = ap.parse_args()
    for n in a.spin:
        MODES[f"spin{n}"] = {"GOMP_SPINCOUNT": str(n)}
    sizes = [SIZES[n] for n in a.sizes]
    if not a.no_idle:
        table("as is (no busy loops of ours)",
              {m: run_mode(m, sizes, a.seconds) for m in MODES}, sizes)
    with busy_loops(a.loops, a.nice):
        res = {m: run_mode(m, sizes, a.seconds) for m in MODES}
    table(f"{a.loops} busy loops at nice {a.nice}", res, sizes)
    table("two children of each mode at once",
          {m: run_mode(m, sizes, a.seconds, copies=2) for m in MODES}, sizes)


if __name__ == "__main__":
    main()
