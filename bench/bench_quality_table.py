"""Quality table of issue 5 (item 5): eight sampling + reconstruction methods at equal budget.

Part 1, equal budget.  On every built-in Mitsuba scene (128 px wide, default height) and on
``toy:mixed`` (128×96, exact truth) at 4, 16, 64, 256 and 1024 spp: relMSE (ε = 0.01,
Rousselle 2011 §7), SMAPE and HDR-FLIP of

=========================  =======================================  ======================
method                     sampling                                 reconstruction
=========================  =======================================  ======================
uniform+box                uniform                                  pixel means
uniform+GEM                uniform                                  GEM (Rousselle 2011)
adaptive GEM               GEM sampler, 4 spp + 8 even passes       GEM
uniform+OIDN               uniform                                  OIDN (the peer)
OIDN+combiner              uniform                                  Back 2020 combiner [*]
OIDN+progressive           uniform                                  Firmino 2022 progressive
DA+OIDN                    denoising-aware (Firmino 2023, OIDN)     OIDN
DA+progressive             DA map of the progressive output         progressive
=========================  =======================================  ======================

[*] looked up in :data:`statmc.pipeline.RECONSTRUCTIONS` at run time (``oidn+combine`` or a
close name); the column reads "n/a" while no such method exists.  At 4 spp the adaptive
methods use an initial pass of 2 spp (the default 4 would leave nothing to place).

Part 2, relative budget to equal error (Salehi et al. 2022, Table 1 protocol, §5.2): every
sampler runs once with the doubling schedule (8 spp, then B_t = 2^(t+3) up to 1024 spp); after
each pass every reconstruction of that sampler is scored, which gives its error-against-budget
curve.  For the errors of uniform+OIDN at 16, 64 and 512 spp (low, mid, high) each method's
curve is interpolated log-log to the budget at which it first reaches that error; the table
shows that budget relative to the reference's (below 100 % = cheaper than uniform+OIDN).
Bounds (``<``, ``>``) mean the curve never crossed inside 8–1024 spp.

References are the highest-spp renders cached in ``out/cache`` (never re-rendered when one
exists); ``toy:mixed`` uses its exact mean.  Writes ``out/bench/quality_table.md``,
``quality_table.json`` (all numbers and the configuration) and per-scene convergence plots
``quality_<scene>.png`` (part 1) and ``quality_<scene>_doubling.png`` (part 2).

Usage: ``python bench/bench_quality_table.py [--scenes ...] [--spps ...] [--seeds N]``.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from statmc import metrics, pipeline  # noqa: E402
from statmc.adaptive import adaptive_render  # noqa: E402
from statmc.errors import InputError  # noqa: E402

SCENES = ("cornell-box", "glossy-spheres", "glass-caustic", "textured-dof", "toy:mixed")
SPPS = (4, 16, 64, 256, 1024)
METRICS = ("relmse", "smape", "flip")
METRIC_LABEL = {"relmse": "relMSE (ε = 0.01)", "smape": "SMAPE", "flip": "HDR-FLIP"}
COMBINER_NAMES = ("oidn+combine", "oidn+combiner", "combine", "combiner", "oidn-combine")

# A "render" is one sampler configuration; each is reconstructed by one or more methods.
# name -> (adaptive_render sampler, its options)
RENDERS = {
    "uniform": ("uniform", {}),
    "gem": ("gem", {}),
    "da": ("denoising-aware", {"denoiser": "oidn"}),
    "da-prog": ("denoising-aware", {"denoiser": "oidn", "output": "progressive"}),
}
# method -> (render, reconstruction); reconstruction None = the combiner, resolved at run time
METHODS = {
    "uniform+box": ("uniform", "none"),
    "uniform+GEM": ("uniform", "gem"),
    "adaptive GEM": ("gem", "gem"),
    "uniform+OIDN": ("uniform", "oidn"),
    "OIDN+combiner": ("uniform", None),
    "OIDN+progressive": ("uniform", "progressive"),
    "DA+OIDN": ("da", "oidn"),
    "DA+progressive": ("da-prog", "progressive"),
}
PEER = "uniform+OIDN"
QUALITY = (("low", 16), ("mid", 64), ("high", 512))


# ------------------------------------------------------------------ set-up
def combiner_name():
    """The OIDN-combiner reconstruction in :mod:`statmc.pipeline`, or None if there is none."""
    known = tuple(getattr(pipeline, "RECONSTRUCTIONS", ()))
    for name in COMBINER_NAMES:
        if name in known:
            return name
    return next((name for name in known if "comb" in name), None)


def reconstruction(method, combiner):
    rec = METHODS[method][1]
    return combiner if rec is None else rec


def make_scene(scene):
    """``(renderer, reference image, reference description)``."""
    from statmc.demo import cached_reference
    from statmc.renderers import make_renderer

    if scene.startswith("toy:"):
        r = make_renderer(scene, width=128, height=96)
        return r, r.true_mean(), "exact mean"
    r = make_renderer(scene, width=128)
    cache = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "out", "cache")
    pat = re.compile(re.escape(f"{r.name}-{r.width}x{r.height}-") + r"(\d+)spp\.exr$")
    have = [int(m.group(1)) for p in glob.glob(os.path.join(cache, "*.exr"))
            if (m := pat.search(os.path.basename(p)))]
    ref_spp = max(have) if have else 4096  # rendered once (slow) only when nothing is cached
    ref, path = cached_reference(r, ref_spp, cache)
    ref = np.asarray(ref, np.float64)
    return r, ref, f"{ref_spp} spp ({os.path.basename(path)}{_floor(path, ref)})"


def _floor(path, ref):
    """The reference's own relMSE, ``mean(Var[ref]/(ref² + ε))`` from its variance of the
    mean: every measured relMSE carries about this much on top of the true error."""
    from statmc.exr import read_exr
    try:
        st = read_exr(path)
    except Exception:  # a reference without variance channels: no floor to report
        return ""
    return f"; its own relMSE ≈ {float(np.mean(st.mean_var / (ref ** 2 + 0.01))):.2g}"


def score(image, ref, which=METRICS):
    fns = {"relmse": metrics.relmse, "smape": metrics.smape, "flip": metrics.flip}
    return {k: fns[k](image, ref) for k in which}


def reconstruct_all(stats, methods, combiner, ref, seed, timing, which=METRICS):
    """Scores of every method (all share ``stats``); None for a missing method."""
    out = {}
    for m in methods:
        rec = reconstruction(m, combiner)
        if rec is None:
            out[m] = None
            continue
        t0 = time.perf_counter()
        img, _ = pipeline.reconstruct_stats(stats, rec, denoiser="oidn", seed=seed)
        t1 = time.perf_counter()
        out[m] = score(img, ref, which)
        timing["reconstruct"] = timing.get("reconstruct", 0.0) + t1 - t0
        timing["metrics"] = timing.get("metrics", 0.0) + time.perf_counter() - t1
    return out


def methods_of(render):
    return [m for m, (r, _) in METHODS.items() if r == render]


# ------------------------------------------------------------------ part 1
def part1(scene, r, ref, spps, seeds, combiner):
    rows = []
    for spp in spps:
        t_spp = time.perf_counter()
        timing = {}
        acc = {m: [] for m in METHODS}
        for seed in seeds:
            for render, (sampler, opts) in RENDERS.items():
                init = 2 if spp < 8 else 4
                t0 = time.perf_counter()
                if sampler == "uniform":
                    stats = r.render(np.full((r.height, r.width), spp, np.int64),
                                     seed=10_007 * seed + spp)
                else:
                    stats = adaptive_render(r, spp, sampler=sampler, initial_spp=init,
                                            seed=10_007 * seed + spp, **opts).stats
                timing[f"render {render}"] = timing.get(f"render {render}", 0.0) + \
                    time.perf_counter() - t0
                for m, s in reconstruct_all(stats, methods_of(render), combiner, ref, seed,
                                            timing).items():
                    acc[m].append(s)
        for m, vals in acc.items():
            row = {"scene": scene, "spp": spp, "method": m,
                   "initial_spp": (2 if spp < 8 else 4) if METHODS[m][0] != "uniform" else None}
            if any(v is None for v in vals):
                row.update({k: None for k in METRICS})
            else:
                row.update({k: float(np.mean([v[k] for v in vals])) for k in METRICS})
                row["per_seed"] = vals
            rows.append(row)
        got = {row["method"]: row["relmse"] for row in rows if row["spp"] == spp}
        t = " ".join(f"{k.split()[-1]} {v:.1f}s" for k, v in timing.items()
                     if k.startswith("render"))
        print(f"  {scene:15s} {spp:5d} spp  {time.perf_counter() - t_spp:6.1f} s  (render: {t};"
              f" reconstruct {timing.get('reconstruct', 0):.1f}s, metrics "
              f"{timing.get('metrics', 0):.1f}s)  relMSE box {got['uniform+box']:.3g} "
              f"OIDN {got['uniform+OIDN']:.3g} comb {_fmt(got['OIDN+combiner'])} "
              f"prog {got['OIDN+progressive']:.3g} DA+OIDN {got['DA+OIDN']:.3g}", flush=True)
    return rows


# ------------------------------------------------------------------ part 2
def part2(scene, r, ref, start, stop, seeds, combiner, which):
    """Error-against-budget curves of every method from one doubling run per sampler."""
    curves = {m: {"budget": [], **{k: [] for k in which}} for m in METHODS}
    hw = r.height * r.width
    for render, (sampler, opts) in RENDERS.items():
        t0 = time.perf_counter()
        timing = {}
        per_seed = []
        for seed in seeds:
            pts = []

            def cb(k, stats, counts, pts=pts, seed=seed):
                pts.append((stats.n.sum() / hw,
                            reconstruct_all(stats, methods_of(render), combiner, ref, seed,
                                            timing, which)))

            adaptive_render(r, stop, sampler=sampler, initial_spp=start, schedule="doubling",
                            seed=20_011 * seed + 1, callback=cb, **opts)
            per_seed.append(pts)
        for m in methods_of(render):
            for i, (budget, _) in enumerate(per_seed[0]):
                curves[m]["budget"].append(float(budget))
                for k in which:
                    vals = [ps[i][1][m] for ps in per_seed]
                    curves[m][k].append(None if any(v is None for v in vals)
                                        else float(np.mean([v[k] for v in vals])))
        print(f"  {scene:15s} doubling {start}->{stop} spp, {render:8s} "
              f"{time.perf_counter() - t0:6.1f} s  (reconstruct "
              f"{timing.get('reconstruct', 0):.1f}s, metrics {timing.get('metrics', 0):.1f}s)",
              flush=True)
    return curves


def budget_to_reach(budgets, errors, target):
    """Smallest budget at which the log-log interpolated curve reaches ``target``.

    Returns ``(budget, bound)`` with ``bound`` "" (crossed inside the range), "<" (already
    below ``target`` at the first budget) or ">" (never reached).
    """
    b = np.log(np.asarray(budgets, float))
    e = np.log(np.maximum(np.asarray(errors, float), 1e-300))
    t = np.log(target)
    if e[0] <= t:
        return float(budgets[0]), "<"
    for i in range(1, len(b)):
        if e[i] <= t:  # first crossing from above: interpolate in log-log
            f = (e[i - 1] - t) / (e[i - 1] - e[i])
            return float(np.exp(b[i - 1] + f * (b[i] - b[i - 1]))), ""
    return float(budgets[-1]), ">"


def relative_budgets(curves, metric):
    """``{(quality, method): (ratio, bound)}`` against :data:`PEER` (Salehi Table 1)."""
    out = {}
    peer = curves[PEER]
    for q, spp in QUALITY:
        if spp not in peer["budget"]:
            continue
        target = peer[metric][peer["budget"].index(spp)]
        for m, c in curves.items():
            if not c["budget"] or any(v is None for v in c[metric]):
                out[(q, m)] = (None, "")
                continue
            b, bound = budget_to_reach(c["budget"], c[metric], target)
            out[(q, m)] = (b / spp, bound)
    return out


def mean_curves(all_curves, scenes):
    """Geometric mean of the error curves over ``scenes``: Salehi's "same average error",
    with every scene weighing the same whatever its error level."""
    out = {}
    for m in METHODS:
        cs = [all_curves[s][m] for s in scenes]
        c = {"budget": list(cs[0]["budget"])}
        for k in [k for k in METRICS if k in cs[0]]:
            col = [x[k] for x in cs]
            c[k] = [None if any(v[i] is None for v in col)
                    else float(np.exp(np.mean(np.log([v[i] for v in col]))))
                    for i in range(len(c["budget"]))]
        out[m] = c
    return out


# ------------------------------------------------------------------ report
def _fmt(v):
    return "n/a" if v is None else f"{v:.3g}" if v >= 1e-3 else f"{v:.2e}"


def table1(rows, scene, metric):
    spps = sorted({r["spp"] for r in rows if r["scene"] == scene})
    by = {(r["spp"], r["method"]): r for r in rows if r["scene"] == scene}
    lines = ["| spp | " + " | ".join(METHODS) + " |", "| ---: |" + " ---: |" * len(METHODS)]
    for s in spps:
        vals = {m: by[(s, m)][metric] for m in METHODS}
        best = min(v for v in vals.values() if v is not None)
        cells = [("**" + _fmt(v) + "**") if v == best else _fmt(v) for v in vals.values()]
        lines.append(f"| {s}{'†' if s < 8 else ''} | " + " | ".join(cells) + " |")
    return lines


def checks(rows, scenes):
    """Issue 5's claims, per scene and spp, on relMSE."""
    lines = ["| scene | spp | OIDN+progressive / min(OIDN, raw) | OIDN+combiner / min(OIDN, raw) "
             "| DA+OIDN / uniform+OIDN | DA+progressive / OIDN+progressive | uniform+OIDN / "
             "uniform+box |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    by = {(r["scene"], r["spp"], r["method"]): r["relmse"] for r in rows}
    for sc in scenes:
        for s in sorted({r["spp"] for r in rows if r["scene"] == sc}):
            g = lambda m: by[(sc, s, m)]  # noqa: E731
            peer = min(g("uniform+OIDN"), g("uniform+box")) if s >= 64 else g("uniform+OIDN")

            def ratio(a, b, limit):
                if a is None or b is None:
                    return "n/a"
                x = a / b
                return f"{x:.4f} {'✓' if x < limit else '✗'}"

            lim = 1.0 if s >= 64 else 1.05
            lines.append(f"| {sc} | {s} | {ratio(g('OIDN+progressive'), peer, lim)} | "
                         f"{ratio(g('OIDN+combiner'), peer, lim)} | "
                         f"{ratio(g('DA+OIDN'), g('uniform+OIDN'), 1.0)} | "
                         f"{ratio(g('DA+progressive'), g('OIDN+progressive'), 1.0)} | "
                         f"{g('uniform+OIDN') / g('uniform+box'):.3f} |")
    return lines


def table2(rel, label):
    lines = ["| scene | quality | " + " | ".join(m for m in METHODS if m != PEER) + " |",
             "| --- | --- |" + " ---: |" * (len(METHODS) - 1)]
    for q, spp in QUALITY:
        if not any(k[0] == q for k in rel):
            continue  # the doubling run stopped below this quality level
        cells = []
        for m in METHODS:
            if m == PEER:
                continue
            v, bound = rel.get((q, m), (None, ""))
            cells.append("n/a" if v is None else f"{bound}{100 * v:.0f}%")
        lines.append(f"| {label if len(lines) == 2 else ''} | {q} ({spp} spp) | "
                     + " | ".join(cells) + " |")
    return lines


def write_report(path, cfg, rows, curves, scenes, mitsuba_scenes, runtime):
    md = ["# Quality table (issue 5, item 5)", "",
          f"Generated by `bench/bench_quality_table.py` in {runtime / 60:.1f} min "
          f"(load average before the run {cfg['load_before']}, after {cfg['load_after']}). "
          f"Seeds: {len(cfg['seeds'])} ({', '.join(map(str, cfg['seeds']))}); every number is "
          "one render per method (mean over seeds when several).  "
          f"Combiner method: `{cfg['combiner'] or 'n/a (not in statmc.pipeline yet)'}`.", "",
          "References: " + "; ".join(f"{s}: {cfg['references'][s]}" for s in scenes) + ".", "",
          "† at 4 spp the adaptive methods (adaptive GEM, DA+OIDN, DA+progressive) start with "
          "a 2-spp uniform pass (the usual 4 would leave no samples to place); elsewhere 4 spp "
          "+ 8 even passes (Rousselle 2011 §6).  Bold: best in the row.", ""]
    md += ["## Part 1: equal budget", ""]
    for k in METRICS:
        md += [f"### {METRIC_LABEL[k]}", ""]
        for sc in scenes:
            md += [f"**{sc}**", ""] + table1(rows, sc, k) + [""]
    md += ["### Issue 5's claims (relMSE ratios; ✓ when below 1, or below 1.05 against plain "
           "OIDN under 64 spp)", "",
           "One render per sampler and spp: the first two columns compare reconstructions of the "
           "same render (paired); the DA columns compare different renders, so differences of "
           "a few per cent are within render-to-render noise.  The last column (no claim) shows "
           "whether OIDN alone still beats the raw render.", "",
           "At ≥ 64 spp the progressive and combiner columns divide by min(uniform+OIDN, "
           "uniform+box); below 64 spp by uniform+OIDN.", ""] + checks(rows, scenes) + [""]
    if curves:
        md += ["## Part 2: relative budget to equal error against uniform+OIDN", "",
               f"Salehi 2022 Table 1 protocol: each sampler starts at {cfg['start']} spp and "
               f"doubles its budget every pass up to {cfg['stop']} spp; every method's "
               "error-vs-budget curve "
               "is interpolated log-log to the budget at which it first reaches the error of "
               "uniform+OIDN at 16 (low), 64 (mid) and 512 (high) spp.  Percentages are that "
               "budget over the reference's; `<` / `>`: the curve was already below the target at "
               f"{cfg['start']} spp / never reached it by {cfg['stop']} spp (the number is then "
               "a bound).",
               ""]
        for k in cfg["part2_metrics"]:
            md += [f"### {METRIC_LABEL[k]}", ""]
            first = True
            groups = [(sc, curves[sc]) for sc in scenes]
            if len(mitsuba_scenes) > 1:
                groups.append(("geometric mean, Mitsuba scenes",
                               mean_curves(curves, mitsuba_scenes)))
                calm = [sc for sc in mitsuba_scenes if sc != "glass-caustic"]
                if len(calm) > 1 and len(calm) < len(mitsuba_scenes):
                    groups.append(("geometric mean without glass-caustic",
                                   mean_curves(curves, calm)))
            for label, c in groups:
                t = table2(relative_budgets(c, k), label)
                md += t if first else t[2:]
                first = False
            md += [""]
    with open(path, "w") as f:
        f.write("\n".join(md) + "\n")
    return md


def plots(out, scene, rows, curves, ref_desc):
    from statmc.plots import write_convergence_plot
    tag = scene.replace(":", "_")
    series = {}
    for m in METHODS:
        pts = [(r["spp"], r["relmse"]) for r in rows if r["scene"] == scene and r["method"] == m
               and r["relmse"] is not None]
        if pts:
            series[m] = tuple(zip(*pts))
    write_convergence_plot(os.path.join(out, f"quality_{tag}.png"), series,
                           title=f"{scene}: equal budget, reference {ref_desc.split(' (')[0]}")
    if curves and "relmse" in next(iter(curves.values())):
        series = {m: (c["budget"], c["relmse"]) for m, c in curves.items()
                  if c["budget"] and None not in c["relmse"]}
        write_convergence_plot(os.path.join(out, f"quality_{tag}_doubling.png"), series,
                               title=f"{scene}: one doubling run per sampler")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--spps", nargs="+", type=int, default=list(SPPS))
    ap.add_argument("--seeds", type=int, default=1, help="renders per method and spp (mean)")
    ap.add_argument("--doubling", nargs=2, type=int, default=(8, 1024), metavar=("START", "STOP"),
                    help="part 2's doubling run (Salehi 2022: from 8 spp)")
    ap.add_argument("--no-part2", action="store_true")
    ap.add_argument("--part2-metrics", nargs="+", choices=METRICS, default=["relmse", "smape"],
                    help="metrics of the doubling curves (FLIP costs ~1 s a call, 64 per scene)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                  "..", "out", "bench"))
    ap.add_argument("--rewrite", action="store_true",
                    help="only rewrite the Markdown and plots from OUT/quality_table.json")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    if args.rewrite:
        with open(os.path.join(args.out, "quality_table.json")) as f:
            d = json.load(f)
        cfg, rows, curves = d["config"], d["rows"], d["curves"]
        cfg.setdefault("part2_metrics", [k for k in METRICS if k in next(iter(curves.values()),
                                                                            {}).get(PEER, {})])
        for sc in cfg["scenes"]:
            plots(args.out, sc, rows, curves.get(sc), cfg["references"][sc])
        write_report(os.path.join(args.out, "quality_table.md"), cfg, rows, curves,
                     cfg["scenes"], [s for s in cfg["scenes"] if not s.startswith("toy:")],
                     cfg["seconds"])
        print(f"rewrote {os.path.join(args.out, 'quality_table.md')}")
        return
    t_start = time.perf_counter()
    combiner = combiner_name()
    seeds = list(range(args.seeds))
    cfg = {"scenes": args.scenes, "spps": args.spps, "seeds": seeds, "start": args.doubling[0],
           "stop": args.doubling[1], "combiner": combiner, "references": {},
           "part2_metrics": args.part2_metrics,
           "load_before": " ".join(f"{x:.2f}" for x in os.getloadavg()),
           "methods": {m: [RENDERS[r][0], RENDERS[r][1], reconstruction(m, combiner)]
                       for m, (r, _) in METHODS.items()}}
    print(f"quality table: scenes {args.scenes}, spp {args.spps}, {len(seeds)} seed(s); "
          f"combiner method: {combiner or 'n/a'}; load average {cfg['load_before']}", flush=True)
    rows, curves = [], {}
    for scene in args.scenes:
        t0 = time.perf_counter()
        r, ref, desc = make_scene(scene)
        cfg["references"][scene] = desc
        print(f"{scene} {r.width}x{r.height}, reference {desc}", flush=True)
        rows += part1(scene, r, ref, args.spps, seeds, combiner)
        if not args.no_part2:
            curves[scene] = part2(scene, r, ref, args.doubling[0], args.doubling[1], seeds,
                                  combiner, args.part2_metrics)
        plots(args.out, scene, rows, curves.get(scene), desc)
        print(f"  {scene}: {time.perf_counter() - t0:.0f} s", flush=True)
    runtime = time.perf_counter() - t_start
    cfg["load_after"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    cfg["seconds"] = runtime
    mitsuba = [s for s in args.scenes if not s.startswith("toy:")]
    md = write_report(os.path.join(args.out, "quality_table.md"), cfg, rows, curves,
                      args.scenes, mitsuba, runtime)
    with open(os.path.join(args.out, "quality_table.json"), "w") as f:
        json.dump({"config": cfg, "rows": rows, "curves": curves}, f, indent=1)
    print("\n".join(md))
    print(f"\nwrote {os.path.join(args.out, 'quality_table.md')} in {runtime:.0f} s")


if __name__ == "__main__":
    try:
        main()
    except InputError as e:
        sys.exit(f"error: {e}")
