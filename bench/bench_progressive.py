"""Benchmark for :mod:`statmc.progressive` and :mod:`statmc.da_sampling` (issue 5, items 2-3).

1. Speed.  The confidence gate (Eq. 12-18 of Firmino et al. 2022) on a 1920x1080x3 image
   against one OIDN call at the same size, measured in the same run.  Target: the gate at
   least 10x faster, for float32 and for float64 input (the gate works in float32 by default;
   ``precision="double"`` is timed for reference).  The machine is shared: the load average
   and the CPU time of each timed call are printed beside the wall time.  Calls are
   interleaved over five rounds (best of each), with a pause before each so that OIDN's
   spinning worker threads have gone idle.

2. Convergence and the peer.  relMSE of the raw render, OIDN (albedo + normal) and
   OIDN + progressive denoising at 4 ... 4096 spp on the toy scenes ``mixed`` and
   ``texture`` (64x64, exact truth) and on the built-in Mitsuba scenes at 128x128 / 128x96
   against 65 536-spp references (cached in ``out/cache``, rendered on first use).  Checks per
   row: progressive <= 1.05x the render (convergence), < min(OIDN, render) at spp >= 64, and
   <= 1.05x OIDN below 64 spp.  Also printed: the progressive mix without the significance
   shrinkage (``shrink=0``) and without the gate.

3. Denoising-aware sampling + OIDN against uniform sampling + OIDN at equal budget (16 and 64
   spp; 4 seeds, paired): the variance map, the MC-SURE map, the map of the progressive
   output (evaluated after progressive denoising, against uniform + OIDN + progressive),
   the ACES tone-mapped map (evaluated by RMSE of the ACES images), and GEM as the denoiser.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_progressive.py``
(``--quick`` for a short run, ``--only speed|convergence|sampling``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from statmc import metrics
from statmc.adaptive import adaptive_render
from statmc.da_sampling import denoising_aware_sampler, tonemap
from statmc.progressive import bind_denoiser, confidence_gate, progressive_denoise
from statmc.toy import ToyRenderer

REF_SPP = 65536
TARGET_RATIO = 10.0
ROUNDS = 5          # interleaved timing rounds of the speed part (best of each)


def _load():
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


from _timing import best_wall_cpu as _timed  # noqa: E402


# =========================================================================== 1. speed
def _speed_inputs():
    h, w = 1080, 1920
    rng = np.random.default_rng(0)
    x = rng.gamma(2.0, 0.25, (h, w, 3)).astype(np.float32)
    y = (x + 0.02 * rng.standard_normal(x.shape)).astype(np.float32)
    var = (0.01 * rng.random(x.shape)).astype(np.float32)
    alpha = rng.random(x.shape).astype(np.float32)
    return x, y, var, alpha


def _gate_child():
    """Time the gate in a process that never loads OIDN (and so torch and TBB): after an
    OIDN call its worker threads keep the cores busy inside the same process, and the
    numba gate timed there took 1.5-2.5x longer with CPU time inflated by OIDN's threads.
    Prints a JSON dict of (wall, cpu) bests."""
    x, y, var, alpha = _speed_inputs()
    x64, y64, v64, a64 = (a.astype(np.float64) for a in (x, y, var, alpha))
    confidence_gate(x[:32, :32], y[:32, :32], var[:32, :32], alpha[:32, :32])   # compile
    confidence_gate(x64[:32, :32], y64[:32, :32], v64[:32, :32], a64[:32, :32])
    best = {}
    for _ in range(ROUNDS):
        for name, fn in (("gate32", lambda: confidence_gate(x, y, var, alpha)),
                         ("gate64", lambda: confidence_gate(x64, y64, v64, a64)),
                         ("gate64d", lambda: confidence_gate(x64, y64, v64, a64,
                                                             precision="double"))):
            time.sleep(0.2)
            best[name] = min(best.get(name, (float("inf"), 0.0)), _timed(fn, 1))
    print(json.dumps(best))


def _gate_times():
    import subprocess
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--gate-child"],
                         check=True, capture_output=True, text=True).stdout
    return {k: tuple(v) for k, v in json.loads(out.strip().splitlines()[-1]).items()}


def speed():
    import numba

    from statmc import denoisers

    x = _speed_inputs()[0]
    h, w = x.shape[:2]
    # The same run, alternating: gate rounds in a clean child process, then OIDN rounds here,
    # twice over; best of each.
    best = {}
    f = None
    for _ in range(2):
        for k, v in _gate_times().items():
            best[k] = min(best.get(k, (float("inf"), 0.0)), v)
        if f is None:
            f = denoisers.oidn()
            f(x)                                      # device and filter setup
        for _ in range(ROUNDS):
            time.sleep(0.2)
            best["oidn"] = min(best.get("oidn", (float("inf"), 0.0)), _timed(lambda: f(x), 1))
    f.close()
    (t_oidn, c_oidn), (t32, c32), (t64, c64) = best["oidn"], best["gate32"], best["gate64"]
    t64d, c64d = best["gate64d"]
    print(f"1. speed at {w}x{h}x3 ({numba.get_num_threads()} numba threads, load average "
          f"{_load():.2f}; gate timed in a child process without OIDN, OIDN here):")
    print(f"   OIDN (one call)          {t_oidn:7.3f} s wall ({c_oidn:.3f} s CPU)")
    for name, t, c, target in (("gate, float32 input", t32, c32, True),
                               ("gate, float64 input", t64, c64, True),
                               ("  (precision='double')", t64d, c64d, False)):
        ok = ("OK" if t_oidn / t >= TARGET_RATIO else "MISSED") if target else "(not a target)"
        print(f"   {name:24s} {t:7.3f} s wall ({c:.3f} s CPU)   OIDN/gate = x{t_oidn / t:5.1f} "
              f"(target >= x{TARGET_RATIO:.0f}) {ok}; CPU time x{c_oidn / c:5.1f}")
    return {"oidn_s": t_oidn, "gate32_s": t32, "gate64_s": t64, "gate64_double_s": t64d,
            "load": _load()}


# =========================================================================== 2. convergence
def _reference(scene, width, height):
    """(renderer, reference image, expected relMSE of the reference itself)."""
    if scene.startswith("toy:"):
        r = ToyRenderer(scene[4:], width=width, height=height)
        return r, r.true_mean(), 0.0
    from statmc.demo import cached_reference
    from statmc.exr import read_exr
    from statmc.renderers import make_renderer

    r = make_renderer(scene, width=width, height=height)
    _, path = cached_reference(r, REF_SPP, "out/cache")
    ref_stats = read_exr(path)
    ref = ref_stats.mean
    floor = float(np.mean(ref_stats.mean_var / (ref * ref + 0.01)))
    return r, ref, floor


def convergence(scenes, spps, seed=0):
    rows = []
    print("\n2. relMSE of the render, OIDN and OIDN + progressive (one render per row; "
          "prog/raw <= 1.05 everywhere, prog < min(OIDN, raw) at >= 64 spp, "
          "prog <= 1.05 OIDN below)")
    for scene, (w, h) in scenes:
        r, ref, floor = _reference(scene, w, h)
        print(f"\n  {scene} {w}x{h}" + ("" if not floor else
              f"  (reference {REF_SPP} spp: its own expected relMSE {floor:.2e})"))
        print(f"  {'spp':>5s} {'raw':>9s} {'OIDN':>9s} {'prog':>9s} {'shrink=0':>9s} "
              f"{'no gate':>9s}"
              f" {'prog/raw':>8s} {'prog/OIDN':>9s} {'OIDN/raw':>8s}  checks")
        for spp in spps:
            t0 = time.perf_counter()
            st = r.render(np.full((r.height, r.width), spp, np.int64), seed=seed * 7919 + spp)
            t_render = time.perf_counter() - t0
            f = bind_denoiser("oidn", st)
            t0 = time.perf_counter()
            z, info = progressive_denoise(st, f, rng=seed, extra_output=True)
            t_prog = time.perf_counter() - t0
            z0 = progressive_denoise(st, f, rng=seed, shrink=0)
            zg = progressive_denoise(st, f, rng=seed, gate=False)
            f.close()
            e = {k: metrics.relmse(v, ref) for k, v in
                 (("raw", st.mean), ("oidn", info["denoised"]), ("prog", z), ("shrink0", z0),
                  ("nogate", zg))}
            checks = []
            checks.append("conv" if e["prog"] <= 1.05 * e["raw"] else "CONV-FAIL")
            if spp >= 64:
                checks.append("peer" if e["prog"] < min(e["oidn"], e["raw"]) else "PEER-FAIL")
            else:
                checks.append("peer" if e["prog"] <= 1.05 * e["oidn"] else "PEER-FAIL")
            print(f"  {spp:5d} {e['raw']:9.3e} {e['oidn']:9.3e} {e['prog']:9.3e} "
                  f"{e['shrink0']:9.3e}"
                  f" {e['nogate']:9.3e} {e['prog'] / e['raw']:8.3f} {e['prog'] / e['oidn']:9.3f}"
                  f" {e['oidn'] / e['raw']:8.3f}  {' '.join(checks)}"
                  f"   (render {t_render:.1f} s, progressive {t_prog:.2f} s)", flush=True)
            rows.append({"scene": scene, "spp": spp, **e, "reference_floor": floor,
                         "alpha_mean": float(info["alpha"].mean()),
                         "alpha_gated_mean": float(info["alpha_gated"].mean())})
    return rows


# =========================================================================== 3. sampling
def _final(stats, how):
    f = bind_denoiser("gem" if how == "gem" else "oidn", stats)
    if how == "progressive":
        out = progressive_denoise(stats, f, rng=0)
    else:
        out = f(stats.mean.astype(np.float32))
    if hasattr(f, "close"):
        f.close()
    return np.asarray(out, np.float64)


def sampling(scenes, spps, seeds):
    from scipy import stats as sst

    variants = [
        ("variance", "oidn", {}, "oidn", "relmse"),
        ("mc-sure", "oidn", {"variant": "mc-sure"}, "oidn", "relmse"),
        ("progressive", "oidn", {"output": "progressive"}, "progressive", "relmse"),
        ("tonemap aces", "oidn", {"tonemap": "aces"}, "oidn", "rmse-aces"),
        ("variance, GEM", "gem", {}, "gem", "relmse"),
    ]
    rows = []
    print("\n3. denoising-aware sampling vs uniform sampling at equal budget "
          f"({len(seeds)} seeds, paired; geometric-mean ratio of the error, one-sided t-test "
          "on log ratios)")
    for scene, (w, h) in scenes:
        r, ref, _ = _reference(scene, w, h)
        print(f"\n  {scene} {w}x{h}")
        print(f"  {'spp':>4s} {'map':15s} {'final':12s} {'metric':9s} {'uniform':>9s} "
              f"{'adaptive':>9s} {'ratio':>6s} {'p':>7s}")
        for spp in spps:
            uni = {s: r.render(np.full((r.height, r.width), spp, np.int64), seed=10_000 + s)
                   for s in seeds}
            for name, den, opts, final, metric in variants:
                eu, ea = [], []
                t0 = time.perf_counter()
                for s in seeds:
                    res = adaptive_render(r, spp, sampler=denoising_aware_sampler(den, **opts),
                                          seed=s)
                    for st, acc in ((uni[s], eu), (res.stats, ea)):
                        img = _final(st, final)
                        if metric == "relmse":
                            acc.append(metrics.relmse(img, ref))
                        else:
                            acc.append(metrics.rmse(tonemap(img, "aces"), tonemap(ref, "aces")))
                lr = np.log(np.array(ea) / np.array(eu))
                p = float(sst.ttest_1samp(lr, 0.0, alternative="less").pvalue)
                print(f"  {spp:4d} {name:15s} {final:12s} {metric:9s} {np.mean(eu):9.3e} "
                      f"{np.mean(ea):9.3e} {np.exp(lr.mean()):6.3f} {p:7.3f}"
                      f"   ({time.perf_counter() - t0:.0f} s)", flush=True)
                rows.append({"scene": scene, "spp": spp, "map": name, "final": final,
                             "metric": metric, "uniform": eu, "adaptive": ea, "p": p})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer scenes, counts and seeds")
    ap.add_argument("--only", choices=("speed", "convergence", "sampling"))
    ap.add_argument("--gate-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json", default="out/bench/progressive.json")
    args = ap.parse_args(argv)
    if args.gate_child:
        _gate_child()
        return
    out = {}
    if args.only in (None, "speed"):
        out["speed"] = speed()
    if args.only in (None, "convergence"):
        if args.quick:
            scenes = [("toy:mixed", (64, 64)), ("cornell-box", (128, 128))]
            spps = (4, 64, 1024)
        else:
            scenes = [("toy:mixed", (64, 64)), ("toy:texture", (64, 64)),
                      ("cornell-box", (128, 128)), ("textured-dof", (128, 96)),
                      ("glossy-spheres", (128, 96))]
            spps = (4, 16, 64, 256, 1024, 4096)
        out["convergence"] = convergence(scenes, spps)
    if args.only in (None, "sampling"):
        scenes = [("toy:mixed", (64, 64)), ("cornell-box", (128, 128))]
        out["sampling"] = sampling(scenes, (16, 64), range(2 if args.quick else 4))
    os.makedirs(os.path.dirname(args.json) or ".", exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"\nresults written to {args.json}")


if __name__ == "__main__":
    main()
