"""Where the cold-cache compile time of a user call goes: per compiled function.

Each scenario runs in a fresh process with its own empty ``NUMBA_CACHE_DIR``.  For each
user call of the scenario it prints the process CPU and wall seconds of the call, then
every numba compilation made inside it: the function, its argument types (abridged),
the CPU seconds of that compilation including the functions it compiled in turn
(``incl``) and without them (``excl``), and the number of signatures each dispatcher of
``statmc`` gained during the call.  Alternate checkouts to compare them::

    python bench/bench_compile_profile.py [--repeat 2] [--scenario gem ...] [CHECKOUT ...]

Scenarios (64x64x3 images): ``gem`` (float64 ``reconstruct`` then ``sampling_map``),
``gem32`` (float32 ``reconstruct``), ``mixing_weights`` (float64, defaults),
``mc_sure`` and ``output_variance`` (``denoisers.gaussian(1.0)``), ``analytic``
(``kernel_bias_variance`` then ``optimal_sample_map`` with ``scale_kernels``), ``gate``
(``confidence_gate`` on a float64 image, then on a float32 one, whose ``alpha`` is float32).
"""

from __future__ import annotations

import argparse
import os

from _timing import run_cold  # noqa: E402  (bench/ is the script's folder)

CHILD = r"""
import json, sys, time
from numba.core import event as ev
records = []          # (depth, name, argtypes, incl_cpu, excl_cpu)

class _L(ev.Listener):
    def __init__(self):
        self.stack = []
    def on_start(self, event):
        self.stack.append([time.process_time(), 0.0, event.data])
    def on_end(self, event):
        t0, child, data = self.stack.pop()
        incl = time.process_time() - t0
        if self.stack:
            self.stack[-1][1] += incl
        d = data["dispatcher"]
        name = d.py_func.__module__.rsplit(".", 1)[-1] + "." + d.py_func.__name__
        args = ",".join(str(a)[:28] for a in data["args"])
        records.append((len(self.stack), name, args, incl, incl - child))

ev.register("numba:compile", _L())

import numpy as np
import numba
import statmc
assert statmc.__file__.startswith(sys.argv[1]), statmc.__file__
from statmc import gem, progressive, sure, analytic, denoisers
from numba.core.registry import CPUDispatcher

def dispatchers():
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("statmc") and mod is not None:
            for k, v in vars(mod).items():
                if isinstance(v, CPUDispatcher):
                    out[name.rsplit(".", 1)[-1] + "." + k] = v
    return out

rng = np.random.default_rng(0)
m = rng.uniform(0.1, 1.0, (64, 64, 3))
v = np.full_like(m, 0.01)
n = np.full((64, 64), 8)
y = m + rng.normal(0, 0.02, m.shape)

def scen(name):
    if name == "gem":
        return [("reconstruct", lambda: gem.reconstruct(m, v)),
                ("sampling_map", lambda: gem.sampling_map(m, v, n, 10000, rng=0))]
    if name == "gem32":
        return [("reconstruct f32", lambda: gem.reconstruct(m.astype(np.float32), v.astype(np.float32)))]
    if name == "mixing_weights":
        return [("mixing_weights", lambda: progressive.mixing_weights(m, y, v, v, 0.5 * v))]
    if name == "mc_sure":
        return [("mc_sure", lambda: sure.mc_sure(denoisers.gaussian(1.0), m, v, rng=0))]
    if name == "output_variance":
        return [("output_variance", lambda: sure.output_variance(denoisers.gaussian(1.0), m, v, k=4, rng=0))]
    if name == "analytic":
        sc = rng.integers(0, 3, (64, 64))
        K = analytic.scale_kernels(sc, [0.0, 1.0, 2.0])
        sb = np.full((64, 64), 8.0)
        return [("kernel_bias_variance", lambda: analytic.kernel_bias_variance(K, m, sb, sb, m, v * 8)),
                ("optimal_sample_map", lambda: analytic.optimal_sample_map(K, m, sb, m, v * 8, 10000.0))]
    if name == "gate":
        al = np.full((64, 64, 3), 0.7)
        f4 = lambda a: a.astype(np.float32)
        return [("confidence_gate x64", lambda: progressive.confidence_gate(m, y, v, al)),
                ("confidence_gate x32", lambda: progressive.confidence_gate(f4(m), f4(y), f4(v), f4(al)))]
    raise SystemExit("unknown scenario " + name)

out = []
for label, call in scen(sys.argv[2]):
    before = {k: len(d.signatures) for k, d in dispatchers().items()}
    del records[:]
    c, w = time.process_time(), time.perf_counter()
    call()
    cpu, wall = time.process_time() - c, time.perf_counter() - w
    sigs = {k: len(d.signatures) - before.get(k, 0) for k, d in dispatchers().items()
            if len(d.signatures) - before.get(k, 0)}
    out.append({"call": label, "cpu": cpu, "wall": wall, "compiles": list(records), "sigs": sigs})
print(json.dumps(out))
"""

SCENARIOS = ("gem", "gem32", "mixing_weights", "mc_sure", "output_variance", "analytic", "gate")


def run(checkout: str, scenario: str) -> list:
    return run_cold(checkout, CHILD, scenario)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkouts", nargs="*",
                   default=[os.path.dirname(os.path.dirname(os.path.abspath(__file__)))])
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--scenario", action="append", choices=SCENARIOS)
    p.add_argument("--brief", action="store_true", help="only the per-call totals")
    a = p.parse_args()
    for r in range(a.repeat):
        for s in a.scenario or SCENARIOS:
            for c in a.checkouts:
                for call in run(os.path.abspath(c), s):
                    print(f"run {r + 1} {c} {s}: {call['call']} {call['cpu']:.1f} s CPU / "
                          f"{call['wall']:.1f} s wall; signatures "
                          + ", ".join(f"{k} +{v}" for k, v in sorted(call["sigs"].items())),
                          flush=True)
                    if a.brief:
                        continue
                    for depth, name, args, incl, excl in call["compiles"]:
                        print(f"    {'  ' * depth}{name}({args[:90]}) incl {incl:.2f} excl {excl:.2f}")


if __name__ == "__main__":
    main()
