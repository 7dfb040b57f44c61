"""Adaptive sampling on the firefly-heavy ``glass-caustic`` scene (issues 3 and 5).

Paired renders at equal budget: for every seed, one uniform render and one adaptive render
per sampler variant, each reconstructed by the same final method (GEM for issue 3, OIDN
for issue 5) and scored by relMSE (ε = 0.01) against the cached high-spp reference
(``toy:NAME`` scenes: the exact mean).  Prints, per variant, the mean relMSE, the ratio of
the means to uniform with a paired-bootstrap 90 % interval, the median of the per-seed
ratios, the wins and a one-sided Wilcoxon signed-rank p-value (H1: adaptive < uniform).

Variants (``--variants``): ``uniform``; ``gem`` (the library's adaptive GEM);
``gem-paper`` (``rounds=1, var_prior=0, debias=False``); ``gem-prior<k>[s<σ>]`` (pooled
variance prior of ``k`` pseudo-samples over a Gaussian of σ); ``gem-mix<λ>`` (a share λ of
every pass spread uniformly); ``gem-it<m>`` (m passes); ``gem-init<s>`` (an s-spp pilot);
``gem-rob<τ>`` (pixels whose sample variance exceeds τ × the 5×5 median get the
neighbourhood's median mean and variance before the sampler sees them: no chasing of
outliers); ``da``, ``da-mix<λ>``, ``da-it<m>``, ``da-init<s>``, ``da-rob<τ>``,
``da-prior<k>[s<σ>]`` the same for denoising-aware sampling with OIDN; ``oracle-c<k>``,
``oracle-v<p>``: fixed densities from the reference (see ``oracle_density``).

``--diagnose`` also splits the squared error of the final images by pixel classes:

* by the pilot pass of each adaptive render: pixels whose pilot sample variance is 0 in
  every channel ("zero"), pixels whose pilot caught an outlier (pilot relative sample
  variance in the top 1 %, "hot"), and the rest;
* by the reference: pixels whose per-sample relative variance (from the reference's own
  statistics) is in the top 10 % ("caustic"), and the rest.

``--decompose`` splits the expected relMSE of each variant over ``--seeds`` renders into
the reference's own noise, the squared bias and the variance of the output, with and
without the "catastrophic" renders (relMSE > 1.2 × the median render).

``--trace`` counts, per pass of each adaptive render, the newly caught fireflies (pixel
mean above 5 × (reference + 0.2)) and their distance to the earlier ones.

Findings of session 3 (statmc/gem.py at commit 7bee907 unless stated, 128×96, 32768-spp reference whose
own relMSE is 0.0029):

* relMSE per render is heavy-tailed: most renders sit near the median, a few are 2–80×
  higher ("catastrophes": a caught firefly that the reconstruction keeps).  The ratio of
  the means moves by ±30 % when 24 more seeds are added (16 spp GEM: 1.195 over 24 seeds,
  0.988 over 64, 1.311 over 40); paired-bootstrap 90 % intervals are wide.
* 16 spp, ratio of means adaptive / uniform [90 % CI], median per-seed ratio, wins,
  Wilcoxon p: GEM 0.988 [0.75, 1.29], 0.965, 39/64, 0.67; DA+OIDN 0.976 [0.66, 1.48],
  0.980, 37/64, 0.69.  32 spp GEM (48 seeds) 0.546 [0.34, 0.93], 64 spp 0.473
  [0.31, 0.79]: there uniform itself has the catastrophes.
* The pilot-starvation hypothesis is refuted: pixels with zero pilot variance are 0.05 %
  of the image, carry 1.5 % of the error and get 40 spp on average (var_prior=2).
* Chasing is confirmed: uniform catches 2.4 fireflies per 16-spp render, isolated;
  adaptive GEM 6.2 and DA 7.1, three quarters of them within 5 px of an earlier catch.
  GEM removes 89 % and OIDN 97 % of fireflies caught at n = 16, but only 78–88 % of those
  in pixels with n ≥ 48, where the adaptive samplers put them; the error in the firefly
  pixels per render is 22× (GEM) and 4.4× (OIDN) uniform's.
* The typical (non-catastrophic) uniform+GEM render at 16 spp: 0.0179 = reference noise
  0.0029 + squared bias 0.0127 (0.0096 of it in the 10 % caustic pixels) + variance
  0.0024.  A sampler acts on the variance and a little on the caustic bias: the best
  non-catastrophic adaptive renders reach 0.0168 (0.94×); uniform at 4× the budget
  reaches 0.0150 (0.84×).
* Sampler variants, none better at 16 spp: 8-spp pilot, pooled variance prior k = 8/16
  over σ = 2/4, uniform share λ = 0.3, outlier-robust inputs (τ = 8, 32), a per-pixel
  cap of 24/32 samples (1.4–1.6 relMSE in single renders: undiluted firefly clusters).
* With the pooled final selector (gem.reconstruct bias="pooled", HEAD d5b4499) the
  reconstruction keeps fewer caught fireflies (6 % instead of 12 % at n >= 48) and the
  tail shrinks, but the ratio stays at 1: 16 spp 1.013 [0.94, 1.09], median 0.949,
  47/64 wins, p = 0.010 (a typical 5 % win); 32 spp 1.060 [0.83, 1.40], 64 spp 1.060
  [0.92, 1.22] (32 seeds).  Typical 16-spp uniform render: 0.0154 = reference 0.0029 +
  bias² 0.0100 + variance 0.0027; typical adaptive 0.0145 (0.94×); catastrophes 7/32
  adaptive, 4/32 uniform.
* Session 4, fixed oracle densities from the reference (``oracle-*``, 32 seeds, pooled
  reconstruction): caustic × 4 / × 2 / × 0.5 / × 0.25 give 1.014 / 1.181 / 1.032 / 1.171
  at 16 spp and 1.250 / 1.292 / 0.971 / 0.997 at 64 spp; density ∝ relative variance^0.5
  / ^1 gives 1.310 / 1.997 at 16 spp.  No fixed map beats uniform.
* Session 6, ``--crn`` (per-sample streams of the Mitsuba backend: a uniform and an
  adaptive render of one seed share their first samples per pixel), 192 seeds 500–691,
  16 spp, final seeds: GEM 0.993 [0.95, 1.04], median 0.978, 122/192 wins, p = 0.127
  (an earlier version of the seeds: 1.012 [0.945, 1.090], median 0.970, 137/192).
* toy:mixed at 4 spp (2-spp pilot): DA+OIDN / uniform+OIDN = 0.782 [0.71, 0.85], 24/32
  wins, p < 0.001 — the table's 1.11 was one render.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/analysis_caustic_sampling.py
--scene glass-caustic --spp 16 --seeds 24 --final gem --variants uniform gem`` (about 3 s
per adaptive render, 0.6 s per GEM and 0.3 s per OIDN reconstruction at 128×96).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from scipy import stats as sst

from statmc import metrics
from statmc.adaptive import adaptive_render, get_sampler
from statmc.pipeline import reconstruct_stats

from _scenes import scene_reference  # noqa: E402  (bench/ is the script's directory)

EPS = 0.01


def _write_json(path, out):
    """Write the collected cells to ``path`` (``--json``), if one was given."""
    if path:
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        with open(path, "w") as f:
            json.dump(out, f, indent=1)


def _reference(scene):
    if scene.startswith("toy:"):
        from statmc.stats import PixelStats
        from statmc.toy import ToyRenderer

        r = ToyRenderer(scene[4:], width=128, height=96)
        t = r.true_mean()
        return r, PixelStats.from_mean_var(t, np.zeros_like(t), np.full(t.shape[:2], 2))
    return scene_reference(scene)


# --------------------------------------------------------------------------- variants
def _gem_opts(**kw):
    from statmc.gem import sampling_map

    def s(stats, budget, rng):
        return sampling_map(stats.mean, stats.mean_var, stats.n, budget, rng=rng, **kw)
    return s


def _mix(inner, lam):
    """``(1 − λ)`` of the budget from ``inner``, ``λ`` uniformly."""
    from statmc.sampling import counts_from_density

    def s(stats, budget, rng):
        b_uni = int(round(lam * budget))
        c = counts_from_density(np.ones(stats.n.shape), b_uni, rng=rng)
        return c + inner(stats, budget - b_uni, rng)
    return s


def _robust(stats, tau, size=5):
    """Prototype: pixels whose sample variance exceeds ``tau`` times the median of their
    ``size``×``size`` neighbourhood get the neighbourhood's median mean and variance."""
    from scipy.ndimage import median_filter

    s2 = stats.sample_var
    lum = s2.mean(-1)
    med = median_filter(lum, size=size, mode="nearest")
    out = lum > tau * med
    m = stats.mean.copy()
    v = stats.mean_var.copy()
    for c in range(m.shape[-1]):
        mm = median_filter(stats.mean[..., c], size=3, mode="nearest")
        vv = median_filter(s2[..., c], size=size, mode="nearest") / stats.n
        m[..., c] = np.where(out, mm, m[..., c])
        v[..., c] = np.where(out, vv, v[..., c])
    return m, v, out


def _gem_robust(tau, **kw):
    from statmc.gem import sampling_map

    def s(stats, budget, rng):
        m, v, _ = _robust(stats, tau)
        return sampling_map(m, v, stats.n, budget, rng=rng, **kw)
    return s


def _robust_stats(stats, tau):
    from statmc.stats import PixelStats

    m, v, _ = _robust(stats, tau)
    return PixelStats.from_mean_var(m, v * stats.n[..., None], stats.n, albedo=stats.albedo,
                                    normal=stats.normal, depth=stats.depth)


def _da_robust(tau):
    from statmc.da_sampling import sampler

    def s(stats, budget, rng):
        return sampler(_robust_stats(stats, tau), budget, rng, denoiser="oidn")
    return s


def _shrink(stats, k, sigma=1.0):
    """Prototype of the pooled variance prior (posterior mean of σ² under a scaled-inverse-χ²
    prior of ``k`` pseudo-degrees of freedom centred on the Gaussian-pooled neighbourhood)."""
    from statmc.filters import gaussian_filter
    from statmc.stats import PixelStats

    s2 = stats.sample_var
    pooled = gaussian_filter(s2, sigma)
    nm1 = (stats.n - 1.0)[..., None]
    s2t = (nm1 * s2 + k * pooled) / (nm1 + k)
    return PixelStats.from_mean_var(stats.mean, s2t, stats.n, albedo=stats.albedo,
                                    normal=stats.normal, depth=stats.depth)


def _da_prior(k, sigma=1.0):
    from statmc.da_sampling import sampler

    def s(stats, budget, rng):
        return sampler(_shrink(stats, k, sigma), budget, rng, denoiser="oidn")
    return s


def _cap(inner, cap):
    """At most ``cap`` samples per pixel in total: counts above it go to the pixels below
    it, in proportion to their remaining room (a maximum per-pixel share)."""
    from statmc.sampling import counts_from_density

    def s(stats, budget, rng):
        c = np.asarray(inner(stats, budget, rng), np.int64)
        room = np.maximum(cap - stats.n, 0)
        over = np.maximum(c - room, 0)
        c = c - over
        extra = int(over.sum())
        while extra:
            free = np.maximum(room - c, 0).astype(float)
            if free.sum() <= 0:           # nowhere left below the cap: spread uniformly
                free = np.ones_like(free)
            add = counts_from_density(free, extra, rng=rng)
            fit = np.minimum(add, np.maximum(room - c, 0)) if free.sum() else add
            c = c + fit
            extra -= int(fit.sum())
            if not fit.sum():
                c = c + counts_from_density(np.ones(c.shape), extra, rng=rng)
                break
        return c
    return s


def variant(name):
    """``(sampler, adaptive_render options)`` of a named variant."""
    if name == "uniform":
        return None, {}
    if name == "gem":
        return "gem", {}
    if name == "gem-paper":
        return _gem_opts(rounds=1, var_prior=0.0, debias=False), {}
    if name.startswith("gem-prior"):            # gem-prior<k>[s<sigma>]
        body = name[len("gem-prior"):]
        k, _, sg = body.partition("s")
        return _gem_opts(var_prior=float(k), var_prior_sigma=float(sg or 1.0)), {}
    if name.startswith("gem-rob"):              # gem-rob<tau>
        return _gem_robust(float(name[len("gem-rob"):])), {}
    if name.startswith("gem-cap"):              # gem-cap<max samples per pixel>
        return _cap(get_sampler("gem"), int(name[len("gem-cap"):])), {}
    if name.startswith("da-cap"):
        return _cap(get_sampler("denoising-aware", denoiser="oidn"), int(name[6:])), {}
    if name.startswith("gem-mix"):              # gem-mix<lambda>
        return _mix(get_sampler("gem"), float(name[len("gem-mix"):])), {}
    if name.startswith("gem-it"):               # gem-it<iterations>
        return "gem", {"iterations": int(name[len("gem-it"):])}
    if name.startswith("gem-init"):             # gem-init<initial spp>
        return "gem", {"initial_spp": int(name[len("gem-init"):])}
    if name == "da":
        return "denoising-aware", {"denoiser": "oidn"}
    if name.startswith("da-prior"):             # da-prior<k>[s<sigma>]
        k, _, sg = name[len("da-prior"):].partition("s")
        return _da_prior(float(k), float(sg or 1.0)), {}
    if name.startswith("da-rob"):
        return _da_robust(float(name[6:])), {}
    if name.startswith("da-mix"):
        return _mix(get_sampler("denoising-aware", denoiser="oidn"), float(name[6:])), {}
    if name.startswith("da-it"):
        return "denoising-aware", {"denoiser": "oidn", "iterations": int(name[5:])}
    if name.startswith("da-init"):
        return "denoising-aware", {"denoiser": "oidn", "initial_spp": int(name[7:])}
    raise SystemExit(f"unknown variant {name!r}")


_ORACLE = {}

#: Seed offset of the fixed-count (uniform, oracle) renders against the adaptive ones of
#: the same seed: 10 000 (independent renders), or 0 with ``--crn``: the Mitsuba backend
#: gives sample j of pixel p the same random numbers in both, so a pair shares the first
#: min(n_adaptive, n_uniform) samples of every pixel (common random numbers).
_FIXED_SEED_OFFSET = [10_000]


def oracle_density(name):
    """Fixed sampling densities computed from the reference's own statistics (an oracle no
    sampler has): ``oracle-c<k>``: the reference's caustic class (top 10 % per-sample
    relative variance) gets ``k`` times the density of the rest; ``oracle-v<p>``: density
    ∝ (relative per-sample variance, Gaussian σ = 1) ** p, floored at 0.25 × its mean."""
    ref_stats = _ORACLE["ref"]
    ref = ref_stats.mean
    rel = (ref_stats.sample_var / (ref * ref + EPS)).mean(-1)
    if name.startswith("oracle-c"):
        k = float(name[len("oracle-c"):])
        return np.where(_classes_ref(ref_stats)["caustic"], k, 1.0)
    if name.startswith("oracle-v"):
        from statmc.filters import gaussian_filter

        d = gaussian_filter(rel[..., None], 1.0)[..., 0] ** float(name[len("oracle-v"):])
        return np.maximum(d, 0.25 * d.mean())
    raise SystemExit(f"unknown variant {name!r}")


def render(r, name, spp, seed, initial_spp=None):
    """(final stats, pilot stats or None); adaptive runs start with ``initial_spp``
    (default: 4, or 2 below 8 spp as in bench_quality_table.py)."""
    if name == "uniform":
        return r.render(np.full((r.height, r.width), spp, np.int64),
                        seed=seed + _FIXED_SEED_OFFSET[0]), None
    if name.startswith("oracle"):
        from statmc.sampling import counts_from_density

        c = counts_from_density(oracle_density(name), spp * r.height * r.width, min_count=2,
                                rng=seed)
        return r.render(c, seed=seed + _FIXED_SEED_OFFSET[0]), None
    sampler, opts = variant(name)
    opts = dict(opts)
    opts.setdefault("initial_spp", initial_spp or (2 if spp < 8 else 4))
    pilot = {}

    def cb(k, stats, counts):
        if k == 0:
            pilot["stats"] = stats

    res = adaptive_render(r, spp, sampler=sampler, seed=seed, callback=cb, **opts)
    return res.stats, pilot["stats"]


def final_image(st, final):
    """The final reconstruction: a :func:`statmc.pipeline.reconstruct_stats` method, or
    ``gem-prior<k>[s<σ>]``: GEM on the variance shrunk by the pooled prior, or
    ``gem-maxs<σ>``: GEM on ``max(s², G_σ * s²)/n`` (reconstruction-side experiments: the
    selector sees regional variances)."""
    if final.startswith("gem-maxs"):
        from statmc.filters import gaussian_filter
        from statmc.gem import reconstruct

        s2 = st.sample_var
        v = np.maximum(s2, gaussian_filter(s2, float(final[len("gem-maxs"):]))) / st.n[..., None]
        return np.asarray(reconstruct(st.mean.astype(np.float32), v.astype(np.float32), n=st.n),
                          np.float64)
    if final.startswith("gem-prior"):
        from statmc.gem import reconstruct

        k, _, sg = final[len("gem-prior"):].partition("s")
        v = _shrink(st, float(k), float(sg or 1.0)).mean_var
        return np.asarray(reconstruct(st.mean.astype(np.float32), v.astype(np.float32), n=st.n),
                          np.float64)
    return np.asarray(reconstruct_stats(st, final)[0], np.float64)


# --------------------------------------------------------------------------- diagnosis
def _classes_pilot(pilot, ref):
    s2 = pilot.sample_var / (ref * ref + EPS)
    rel = s2.mean(-1)
    zero = np.all(pilot.sample_var <= 0, axis=-1)
    hot = rel >= np.quantile(rel, 0.99)
    return {"zero": zero, "hot": hot & ~zero, "rest": ~zero & ~hot}


def _classes_ref(ref_stats):
    ref = ref_stats.mean
    rel = (ref_stats.sample_var / (ref * ref + EPS)).mean(-1)
    caustic = rel >= np.quantile(rel, 0.9)
    return {"caustic": caustic, "calm": ~caustic}


def ratio_ci(e, eu, *, level=0.9, reps=20000, seed=0):
    """Paired bootstrap interval of ``mean(e)/mean(eu)`` (seeds resampled together)."""
    e, eu = np.asarray(e), np.asarray(eu)
    idx = np.random.default_rng(seed).integers(0, e.size, (reps, e.size))
    r = e[idx].mean(1) / eu[idx].mean(1)
    return tuple(np.quantile(r, [(1 - level) / 2, (1 + level) / 2]))


def decompose(r, ref_stats, spp, seeds, final, seed0=500, name="uniform"):
    """Split the expected relMSE of sampler ``name`` + ``final`` into the reference's own noise, the
    squared bias and the variance of the output (over ``seeds`` renders), overall and in
    the reference's caustic class; median-render and mean-render relMSE beside them."""
    ref = ref_stats.mean
    den = ref * ref + EPS
    imgs = []
    for i in range(seeds):
        st, _ = render(r, name, spp, seed0 + i)
        imgs.append(final_image(st, final))
    imgs = np.array(imgs)
    per = ((imgs - ref) ** 2 / den).mean(axis=(1, 2, 3))
    keep = per <= 1.2 * np.median(per)          # renders without a surviving firefly
    floor = ref_stats.mean_var / den
    out = {}
    for name, sel in (("all", keep), ("no-catastrophe", keep)):
        x = imgs[sel] if name != "all" else imgs
        mu = x.mean(0)
        var = x.var(0, ddof=1) / den
        bias2 = np.maximum((mu - ref) ** 2 / den - floor - var / len(x), 0)   # E[(mu-r)^2] corrected
        m = _classes_ref(ref_stats)["caustic"]
        out[name] = {"renders": int(len(x)), "relmse": float(((x - ref) ** 2 / den).mean()),
                     "floor": float(floor.mean()), "bias2": float(bias2.mean()),
                     "var": float(var.mean()),
                     "caustic floor": float(floor.mean(-1)[m].sum() / m.size),
                     "caustic bias2": float(bias2.mean(-1)[m].sum() / m.size),
                     "caustic var": float(var.mean(-1)[m].sum() / m.size)}
    out["median render"] = float(np.median(per))
    out["catastrophes"] = int((~keep).sum())
    return out


def trace(r, ref_stats, spp, seeds, name, seed0=500):
    """Fireflies caught per pass: ``[(pass, new, [Chebyshev distance to earlier ones])]``
    per seed; uniform renders are one pass."""
    ref = ref_stats.mean.mean(-1)
    logs = []
    for i in range(seeds):
        prev = {"ff": np.zeros(ref.shape, bool)}
        log = []

        def cb(k, st, counts):
            hot = st.mean.mean(-1) > 5 * (ref + 0.2)
            ys, xs = np.nonzero(hot & ~prev["ff"])
            py, px = np.nonzero(prev["ff"])
            d = [int(np.min(np.maximum(abs(py - y), abs(px - x)))) if py.size else -1
                 for y, x in zip(ys, xs)]
            if ys.size:
                log.append((k, int(ys.size), d))
            prev["ff"] = hot

        if name == "uniform":
            st, _ = render(r, name, spp, seed0 + i)
            cb(0, st, None)
        else:
            sampler, opts = variant(name)
            opts = dict(opts)
            opts.setdefault("initial_spp", 2 if spp < 8 else 4)
            adaptive_render(r, spp, sampler=sampler, seed=seed0 + i, callback=cb, **opts)
        logs.append(log)
    return logs


def survival(r, ref_stats, spp, seeds, name, final, seed0=500):
    """Caught fireflies (raw mean > 5 × (reference + 0.2)) and whether ``final`` removes
    them: rows ``(n of the pixel, kept, relative squared error of the output there)``;
    kept = output > 2 × (reference + 0.2)."""
    ref = ref_stats.mean.mean(-1)
    den = (ref_stats.mean ** 2 + EPS)
    rows = []
    for i in range(seeds):
        st, _ = render(r, name, spp, seed0 + i)
        img = final_image(st, final)
        ff = st.mean.mean(-1) > 5 * (ref + 0.2)
        kept = img.mean(-1) > 2 * (ref + 0.2)
        err = ((img - ref_stats.mean) ** 2 / den).mean(-1)
        for y, x in zip(*np.nonzero(ff)):
            rows.append((int(st.n[y, x]), bool(kept[y, x]), float(err[y, x])))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="glass-caustic")
    ap.add_argument("--spp", type=int, nargs="*", default=[16])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--seed0", type=int, default=500)
    ap.add_argument("--final", default="gem",
                    help="gem, oidn, none (pipeline.reconstruct_stats) or gem-prior<k>[s<σ>]")
    ap.add_argument("--variants", nargs="*", default=["uniform", "gem"])
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--trace", action="store_true", help="only the firefly trace")
    ap.add_argument("--survival", action="store_true",
                    help="only: do caught fireflies survive the final reconstruction, by n")
    ap.add_argument("--decompose", action="store_true",
                    help="only the bias/variance/reference split of uniform renders")
    ap.add_argument("--crn", action="store_true",
                    help="uniform/oracle renders share the adaptive render's seed (common "
                         "random numbers per pixel and sample index; Mitsuba scenes)")
    a = ap.parse_args(argv)
    _FIXED_SEED_OFFSET[0] = 0 if a.crn else 10_000
    r, ref_stats = _reference(a.scene)
    _ORACLE["ref"] = ref_stats
    ref = ref_stats.mean
    floor = float(np.mean(ref_stats.mean_var / (ref * ref + EPS)))
    rc = _classes_ref(ref_stats)
    print(f"{a.scene}: reference {int(ref_stats.n.max())} spp, own relMSE {floor:.4f}; "
          f"final {a.final}; seeds {a.seed0}..{a.seed0 + a.seeds - 1}", flush=True)
    out = {"scene": a.scene, "final": a.final, "floor": floor, "cells": []}
    if a.survival:
        bins = [(0, 16), (16, 24), (24, 48), (48, 96), (96, 10 ** 9)]
        for spp in a.spp:
            for name in a.variants:
                rows = survival(r, ref_stats, spp, a.seeds, name, a.final, a.seed0)
                nn = np.array([x[0] for x in rows] or [0])
                kp = np.array([x[1] for x in rows] or [False])
                er = np.array([x[2] for x in rows] or [0.0])
                print(f"\n{spp} spp {name} + {a.final}: {len(rows) / a.seeds:.2f} fireflies per "
                      f"render, kept {kp.mean():.2f}; their error per render "
                      f"{er.sum() / a.seeds / ref.shape[0] / ref.shape[1]:.5f} (relMSE units)")
                for lo, hi in bins:
                    m = (nn >= lo) & (nn < hi) if rows else np.zeros(1, bool)
                    if m.any():
                        print(f"  n in [{lo}, {min(hi, 9999)}): {int(m.sum()):4d} caught, kept "
                              f"{kp[m].mean():.2f}, mean error there {er[m].mean():8.3f}")
                out["cells"].append({"spp": spp, "variant": name, "survival": rows})
        _write_json(a.json, out)
        return
    if a.trace:
        for spp in a.spp:
            for name in a.variants:
                logs = trace(r, ref_stats, spp, a.seeds, name, a.seed0)
                tot = [sum(c for _, c, _ in lg) for lg in logs]
                near = [sum(1 for _, _, d in lg for x in d if 0 <= x <= 5) for lg in logs]
                print(f"\n{spp} spp {name}: fireflies caught per render {np.mean(tot):.2f} "
                      f"(of them within 5 px of an earlier one: {np.mean(near):.2f})")
                for i, lg in enumerate(logs):
                    print(f"  seed {a.seed0 + i}: {lg}")
                out["cells"].append({"spp": spp, "variant": name, "trace": logs})
        _write_json(a.json, out)
        return
    if a.decompose:
        for spp in a.spp:
            for name in a.variants:
                d = decompose(r, ref_stats, spp, a.seeds, a.final, a.seed0, name)
                out["cells"].append({"spp": spp, "variant": name, "decomposition": d})
                print(f"\n{spp} spp, {name} + {a.final}, {a.seeds} renders:", flush=True)
                for k, v in d.items():
                    txt = (", ".join(f"{kk} {vv:.5f}" if isinstance(vv, float) else f"{kk} {vv}"
                                     for kk, vv in v.items()) if isinstance(v, dict) else f"{v}")
                    print(f"  {k:15s} {txt}", flush=True)
        _write_json(a.json, out)
        return
    for spp in a.spp:
        err = {v: [] for v in a.variants}
        diag = {v: {} for v in a.variants}
        t0 = time.perf_counter()
        for i in range(a.seeds):
            seed = a.seed0 + i
            for v in a.variants:
                st, pilot = render(r, v, spp, seed)
                img = final_image(st, a.final)
                pp = metrics.relmse(img, ref, per_pixel=True)
                err[v].append(float(pp.mean()))
                if a.diagnose:
                    d = diag[v]
                    for cname, m in rc.items():
                        d.setdefault("ref:" + cname, []).append(float(pp[m].sum() / pp.size))
                        d.setdefault("n ref:" + cname, []).append(float(st.n[m].mean()))
                    d.setdefault("box", []).append(float(metrics.relmse(st.mean, ref)))
                    if pilot is not None:
                        for cname, m in _classes_pilot(pilot, ref).items():
                            d.setdefault("pilot:" + cname, []).append(float(pp[m].sum() / pp.size))
                            d.setdefault("n pilot:" + cname, []).append(float(st.n[m].mean()))
                            d.setdefault("frac pilot:" + cname, []).append(float(m.mean()))
                    # bias of the final image in the caustic class (signed, relative)
                    m = rc["caustic"]
                    d.setdefault("signed caustic", []).append(
                        float(((img - ref) / np.sqrt(ref * ref + EPS))[m].mean()))
        eu = np.array(err["uniform"]) if "uniform" in err else None
        print(f"\n{a.scene} {spp} spp, final {a.final} ({time.perf_counter() - t0:.0f} s)")
        print(f"  {'variant':16s} {'mean relMSE':>11s} {'ratio':>6s} {'wins':>5s} {'p':>6s} {'90% CI':>12s} {'median':>6s}  per seed")
        for v in a.variants:
            e = np.array(err[v])
            line = f"  {v:16s} {e.mean():11.5f}"
            cell = {"spp": spp, "variant": v, "errors": err[v]}
            if eu is not None and v != "uniform":
                ratio = e.mean() / eu.mean()
                wins = int((e < eu).sum())
                p = float(sst.wilcoxon(e, eu, alternative="less").pvalue)
                lo, hi = ratio_ci(e, eu)
                med = float(np.median(e / eu))
                line += f" {ratio:6.3f} {wins:2d}/{len(e):<2d} {p:6.3f} [{lo:.2f}, {hi:.2f}] {med:6.3f}"
                cell.update(ratio=ratio, wins=wins, p=p, ci90=(lo, hi), median_ratio=med)
            else:
                line += " " * 42
            print(line + "  " + " ".join(f"{x:.4f}" for x in e), flush=True)
            out["cells"].append(cell)
            if a.diagnose:
                cell["diag"] = diag[v]
                for key, vals in diag[v].items():
                    print(f"      {key:22s} {np.mean(vals):10.5f}  "
                          + " ".join(f"{x:.4f}" for x in vals))
    _write_json(a.json, out)


if __name__ == "__main__":
    main()
