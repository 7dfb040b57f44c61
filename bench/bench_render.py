"""Throughput of MitsubaRenderer.render against mi.render, measured in the same run.

Target: ``MitsubaRenderer.render`` (per-pixel counts, float64 sums and sums of squares)
reaches at least 0.9x the samples/s of ``mi.render`` (one mean image) on the same scene
at the same uniform spp.  Both are warmed up first (JIT compilation), then timed
``--repeats`` times in interleaved pairs; the verdict uses the median of the per-pair
speed ratios (robust to the load drifting on a shared machine), and the medians of both
speeds are printed too.  An extra line times a
random (non-uniform) count map with about the same total, for information.

Run::

    .venv/bin/python bench/bench_render.py            # ~1-2 minutes on 2 cores
    .venv/bin/python bench/bench_render.py --repeats 3 --scenes cornell-box
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

TARGET_RATIO = 0.9

# (scene, width, height): the Cornell box and a glossy scene
DEFAULT_SCENES = (("cornell-box", 256, 256), ("glossy-spheres", 256, 192))


def _time(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def bench_scene(name: str, width: int, height: int, *, spp: int = 64, repeats: int = 5,
                nonuniform: bool = True) -> dict:
    """Median seconds of our renderer and of ``mi.render`` on one scene; returns a dict."""
    from statmc.mitsuba_backend import MitsubaRenderer

    r = MitsubaRenderer(name, width=width, height=height)
    mi = r._mi
    samples = width * height * spp

    def ours():
        r.render_uniform(spp, seed=seed, features=False)

    def theirs():
        np.asarray(mi.render(r._scene, spp=spp, seed=seed))

    seed = 1000
    ours()                      # warm-up: JIT compilation, caches
    theirs()
    t_ours, t_mi = [], []
    for k in range(repeats):    # interleaved pairs, so load changes hit both alike
        seed = k
        t_ours.append(_time(ours))
        t_mi.append(_time(theirs))
    res = {"scene": name, "width": width, "height": height, "spp": spp, "variant": r.variant,
           "ours_s": statistics.median(t_ours), "mi_s": statistics.median(t_mi)}
    res["ours_sps"] = samples / res["ours_s"]
    res["mi_sps"] = samples / res["mi_s"]
    res["ratio_of_medians"] = res["ours_sps"] / res["mi_sps"]
    # the verdict uses the median of the per-pair ratios: on a shared machine the load
    # drifts between pairs, and a pair's two runs see nearly the same load
    res["ratio"] = statistics.median(m / o for o, m in zip(t_ours, t_mi))
    if nonuniform:
        rng = np.random.default_rng(0)
        counts = rng.integers(0, 2 * spp + 1, size=(height, width))   # mean spp, zeros too
        t = statistics.median(_time(lambda s=s: r.render(counts, seed=s, features=False))
                              for s in range(max(1, repeats // 2)))
        res["nonuniform_sps"] = int(counts.sum()) / t
    res["feature_pass_s"] = r.render_uniform(spp, seed=1, features=True).meta["feature_seconds"]
    return res


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--scenes", nargs="*", default=None,
                    help="scene names (default: cornell-box 256x256, glossy-spheres 256x192)")
    args = ap.parse_args(argv)
    scenes = DEFAULT_SCENES if not args.scenes else [
        next((s for s in DEFAULT_SCENES if s[0] == n), (n, 256, 192)) for n in args.scenes]

    results = []
    for name, w, h in scenes:
        res = bench_scene(name, w, h, spp=args.spp, repeats=args.repeats)
        results.append(res)
        verdict = "PASS" if res["ratio"] >= TARGET_RATIO else "NOT REACHED"
        print(f"{name} {w}x{h} @ {res['spp']} spp ({res['variant']}):")
        print(f"  MitsubaRenderer.render  {res['ours_sps'] / 1e6:6.2f} M samples/s  "
              f"(median {res['ours_s']:.2f} s)")
        print(f"  mi.render               {res['mi_sps'] / 1e6:6.2f} M samples/s  "
              f"(median {res['mi_s']:.2f} s)")
        print(f"  ratio ours/mi.render    {res['ratio']:6.3f}   (median of {args.repeats} paired runs; "
              f"ratio of medians {res['ratio_of_medians']:.3f})   target >= {TARGET_RATIO}: {verdict}")
        if "nonuniform_sps" in res:
            print(f"  random count map        {res['nonuniform_sps'] / 1e6:6.2f} M samples/s  (info)")
        print(f"  feature pass (16 spp)   {res['feature_pass_s']:6.2f} s, separate from the above  (info)")
    worst = min(r["ratio"] for r in results)
    print(f"overall: worst ratio {worst:.3f} -> {'PASS' if worst >= TARGET_RATIO else 'NOT REACHED'}")
    return results


if __name__ == "__main__":
    main()
