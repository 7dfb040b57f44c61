"""Is the SURE mix of ``combine_denoised`` biased?  The library's relMSE weights against
two that do not move with the pixel's own value (session 9).

The mix of :func:`statmc.combine.combine_denoised` (``mix="local"``, the default) sets
``out = z + Σ_j λ_j ρ_j``, ``ρ_j = β̂_j − z``, with ``λ`` minimising a SURE estimate of the
relMSE-weighted error, ``λᵀGλ − 2bᵀλ``, ``b_j = −E[Σ_c rel_c (z_c − μ_c) ρ_{j,c}]``.  Stein's
lemma turns ``b`` into observable terms only when ``rel_c`` and the weights of pixel ``c``
do not move with ``y_c``.  Three relMSE weights are compared on the same draws and
renders; the library keeps only the first, and this script swaps the others in for its
hook :func:`statmc.combine._mix_rel` (:func:`mix_rel`, restored on exit):

* ``z`` (the default, "old"): ``1 / (z² + 0.01)``, which moves with ``y_c`` through ``z_c``;
* ``loo``: ``1 / (ỹ² + 0.01)``, ``ỹ_c`` the 5x5 mean of ``y`` leaving ``c`` out;
* ``zc``: ``1 / (ẑ² + 0.01)``, ``ẑ = z + Ĵ (z − y)`` (the centre's first-order share of
  ``z_c`` replaced, ``Ĵ`` from the probes).

Part 1, toy (``--draws``, default 200): toy ``mixed`` (a quadrant of exponential fireflies)
32x32, 16 spp, a σ = 1.5 Gaussian blur as the denoiser (linear, so the probes' Jacobian
terms are unbiased), ``size=7``, ``probes=4``; per draw the estimate of ``b_j`` minus the
truth (both in the mix's own weights ``rel``), summed over the image; printed: the mean
bias with a 95 % CI, its share of ``b`` and a t-test p-value per variance model
(``"smooth"``, ``"max"``); the mean estimated global λ (Σ_j) against the per-draw optimum
of the mix's own criterion and of the metric's (weights ``1 / (μ² + 0.01)``); the relMSE of
the output (local mix), with paired t-tests against ``z``.  Then the same with the true
variance in place of ``mean_var``, and for ``combine_bins`` (4 bins of 4 spp,
``bin_probes=0``; its residual +2 % was suspected to come from the relMSE weights).

Part 2, built-in scenes (``--scenes``, ``--spp``, ``--seeds``, ``--new zc|loo``): one render
per scene, spp and seed; ``combine`` with GEM's exposed kernel (``reconstruct_stats(...,
"combine", denoiser="gem")``) and ``oidn+combine``, with ``z`` ("old") and the ``--new``
weights on the same render and probe seed; relMSE against the cached reference
(``out/cache``), ratio to GEM / OIDN, mean λ.

Run: ``NUMBA_CACHE_DIR=.cache/numba nice -n 10 .venv/bin/python bench/analysis_denoised_mix.py``
(``--part toy|scenes|all``).  Part 1 takes about 3 minutes, part 2 about 5 per ``--new``
on 2 loaded cores.
"""

from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np
from scipy import stats
from scipy.ndimage import gaussian_filter, uniform_filter

import statmc.combine as cbm
from statmc import metrics
from statmc.pipeline import merge_bins, reconstruct_stats
from statmc.toy import ToyRenderer

SCENES = ("cornell-box", "glossy-spheres", "textured-dof", "glass-caustic")
#: Half-width of the 5x5 boxes of the ``loo`` and ``zc`` weights.
RADIUS = 2


def _rel_loo(y, z, pr, mean_var):
    """``1 / (ỹ² + 0.01)``, ``ỹ_c`` the mean of ``y`` over the 5x5 box of pixels around
    ``c`` leaving ``c`` out (taps outside the image dropped): independent of ``y_c``, but a
    worse stand-in for ``μ`` in the metric's ``1 / (μ² + 0.01)`` (the box crosses edges)."""
    n = 2 * RADIUS + 1
    num = uniform_filter(y, (n, n, 1), mode="constant") * (n * n) - y
    den = uniform_filter(np.ones(y.shape[:2]), n, mode="constant") * (n * n) - 1.0
    yl = num / np.maximum(den, 1.0)[..., None]
    return 1.0 / (yl * yl + 0.01)


def _rel_zc(y, z, pr, mean_var):
    """``1 / (ẑ² + 0.01)``, ``ẑ = z + Ĵ (z − y)``: ``z`` with the centre's first-order
    share replaced (``∂ẑ_c/∂y_c = J_cc² ≈ 0``), ``Ĵ`` the 5x5 ratio of ``σ² J_cc`` from the
    probes ``pr`` (``mean_i v_c (J v)_c``) to ``mean_var``, clipped to ``[0, 1]``."""
    dcc = np.zeros(z.shape)
    for i in range(pr.K):
        dcc += pr.v(i) * pr.jv[i]
    dcc /= max(pr.K, 1)
    n = 2 * RADIUS + 1
    num = uniform_filter(dcc, (n, n, 1), mode="reflect")
    den = uniform_filter(np.asarray(mean_var, np.float64), (n, n, 1), mode="reflect")
    with np.errstate(divide="ignore", invalid="ignore"):
        jcc = np.where(den > 0, np.clip(num / den, 0.0, 1.0), 0.0)
    zc = z + jcc * (z - y)
    return 1.0 / (zc * zc + 0.01)


#: The relMSE weights of the mix: ``z`` is the library's own (its hook, 1 / (z² + 0.01)).
REL = {"z": cbm._mix_rel, "loo": _rel_loo, "zc": _rel_zc}
VARIANTS = tuple(REL)
MODES = {"old": "z", "new": "zc"}          # the scenes part (``--new``)


@contextlib.contextmanager
def mix_rel(mode):
    """Within the block, ``combine_denoised`` and ``combine_bins`` pool their mix with the
    weights ``REL[mode]`` (they look the hook ``statmc.combine._mix_rel`` up at each call);
    the library's own hook is restored on leaving, also on an error."""
    saved = cbm._mix_rel
    cbm._mix_rel = REL[mode]
    try:
        yield
    finally:
        cbm._mix_rel = saved


def _blur(x):
    return gaussian_filter(x, (1.5, 1.5, 0), mode="nearest")


def _rm(x, mu):
    return float(np.mean((x - mu) ** 2 / (mu * mu + 0.01)))


def _row(est, tru, rho, rel, mu, z, out, gain):
    """(estimate − truth of b_j, truth, λ̂, λ* of the mix's criterion, λ* of the metric,
    relMSE of the output, estimate − truth with the fixed weights 1 / (μ² + 0.01)) of one
    draw; λ summed over the models, global mix."""
    relm = 1.0 / (mu * mu + 0.01)
    dm = ((gain + (z - mu) * rho) * relm).sum(axis=(1, 2, 3))
    G = np.einsum("jhwc,khwc,hwc->jk", rho, rho, rel)
    Gm = np.einsum("jhwc,khwc,hwc->jk", rho, rho, relm)
    bm = (-(z - mu) * rho * relm).sum(axis=(1, 2, 3))
    return (est - tru, tru, cbm._simplex_mix(G, est).sum(), cbm._simplex_mix(G, tru).sum(),
            cbm._simplex_mix(Gm, bm).sum(), _rm(out, mu), dm)


def toy_denoised(n, truevar=False, H=32, spp=16):
    """Per variant and draw: :func:`_row` of ``combine_denoised`` (local mix)."""
    r = ToyRenderer("mixed", width=H, height=H)
    mu = r.true_mean()
    res = {k: [] for k in VARIANTS}
    for i in range(n):
        st = r.render_uniform(spp, seed=(71, i), features=False)
        mv = r.true_var() / spp if truevar else st.mean_var
        for mode in VARIANTS:
            with mix_rel(mode):
                out, info = cbm.combine_denoised(st.mean, mv, _blur, size=7, probes=4, rng=i,
                                                 extra_output=True, sure_terms=True)
            z, rho, rel = info["denoised"], info["combined"] - info["denoised"][None], info["rel"]
            est = info["weighted_gain"].sum(axis=(1, 2, 3))
            tru = (-(z - mu) * rho * rel).sum(axis=(1, 2, 3))
            res[mode].append(_row(est, tru, rho, rel, mu, z, out, info["gain"]))
    return res


def toy_bins(n, truevar=False, H=32, spp=16, B=4):
    r = ToyRenderer("mixed", width=H, height=H)
    mu = r.true_mean()
    res = {k: [] for k in VARIANTS}
    for i in range(n):
        bins = [r.render_uniform(spp // B, seed=(33, i, b), features=False) for b in range(B)]
        full = merge_bins(bins)
        ys = np.stack([b.mean for b in bins])
        mv = r.true_var() / spp if truevar else full.mean_var
        for mode in VARIANTS:
            with mix_rel(mode):
                out, info = cbm.combine_bins(ys, mv, _blur, size=7, probes=4, rng=i,
                                             bin_probes=0, extra_output=True, sure_terms=True)
            z, rel = info["full_denoised"], info["rel"]
            rho = (info["combined"] - z)[None]
            est = np.array([info["weighted_gain"].sum()])
            tru = (-(z - mu) * rho * rel).sum(axis=(1, 2, 3))
            res[mode].append(_row(est, tru, rho, rel, mu, z, out, info["gain"][None]))
    return res


def _ci(v):
    v = np.asarray(v, float)
    return v.mean(), 1.96 * v.std(ddof=1) / np.sqrt(len(v))


def report(title, res, models):
    print(title, flush=True)
    for key in res:
        d = np.array([x[0] for x in res[key]])
        t = np.array([x[1] for x in res[key]])
        for j in range(d.shape[1]):
            m, h = _ci(d[:, j])
            p = stats.ttest_1samp(d[:, j], 0.0).pvalue
            print(f"  rel {key:3s} {models[j]:6s}: bias of b {m:+8.2f} ± {h:6.2f} "
                  f"({100 * m / t[:, j].mean():+5.1f} % of {t[:, j].mean():7.2f}), p = {p:.1g}")
        if key == "z":
            dm = np.array([x[6] for x in res[key]])
            for j in range(dm.shape[1]):
                m, h = _ci(dm[:, j])
                print(f"        {models[j]:6s}: with fixed weights 1/(μ² + 0.01) instead: "
                      f"{m:+8.2f} ± {h:6.2f}, p = {stats.ttest_1samp(dm[:, j], 0.0).pvalue:.1g}")
        lam = [_ci([x[q] for x in res[key]]) for q in (2, 3, 4, 5)]
        print(f"  rel {key:3s}: mean global λ {lam[0][0]:.3f} ± {lam[0][1]:.3f}, optimum of the "
              f"mix's criterion {lam[1][0]:.3f} ± {lam[1][1]:.3f}, of the metric "
              f"{lam[2][0]:.3f} ± {lam[2][1]:.3f}; relMSE of the output {lam[3][0]:.5f} ± "
              f"{lam[3][1]:.5f}")
    a = np.array([x[5] for x in res["z"]])
    for key in res:
        if key != "z":
            b = np.array([x[5] for x in res[key]])
            m, h = _ci(b - a)
            print(f"  relMSE {key} − z {m:+.5f} ± {h:.5f} (paired t-test p = "
                  f"{stats.ttest_rel(b, a).pvalue:.2g})", flush=True)


def scenes(names, spps, seeds):
    from _scenes import scene_reference
    rows = []
    for scene in names:
        r, ref = scene_reference(scene)
        ref = ref.mean
        for spp in spps:
            acc = {}
            for s in range(seeds):
                st = r.render_uniform(spp, seed=7919 * s + spp)
                for den, method, kw in (("gem", "combine", {"denoiser": "gem"}),
                                        ("oidn", "oidn+combine", {})):
                    base = reconstruct_stats(st, den)[0]
                    acc.setdefault(f"{den} base", []).append(metrics.relmse(np.asarray(base, np.float64), ref))
                    for key, mode in MODES.items():
                        t0 = time.perf_counter()
                        with mix_rel(mode):
                            img, maps = reconstruct_stats(st, method, seed=s, **kw)
                        acc.setdefault(f"{den} {key}", []).append(
                            metrics.relmse(np.asarray(img, np.float64), ref))
                        acc.setdefault(f"{den} {key} λ", []).append(float(np.mean(maps["mix"])))
                        acc.setdefault(f"{den} {key} s", []).append(time.perf_counter() - t0)
            for den in ("gem", "oidn"):
                base = np.array(acc[f"{den} base"])
                o, n_ = np.array(acc[f"{den} old"]), np.array(acc[f"{den} new"])
                print(f"{scene:15s} {spp:5d} spp {den:4s}: {den} {base.mean():.5f}  old "
                      f"{o.mean() / base.mean():.3f}x (seeds {(o / base).min():.3f}–{(o / base).max():.3f}, "
                      f"λ {np.mean(acc[f'{den} old λ']):.2f})  new {n_.mean() / base.mean():.3f}x "
                      f"(seeds {(n_ / base).min():.3f}–{(n_ / base).max():.3f}, λ "
                      f"{np.mean(acc[f'{den} new λ']):.2f})  new/old {n_.mean() / o.mean():.3f} "
                      f"({np.mean(acc[f'{den} new s']):.1f} s)", flush=True)
                rows.append((scene, spp, den, o.mean() / base.mean(), n_.mean() / base.mean()))
    for den in ("gem", "oidn"):
        o = [r[3] for r in rows if r[2] == den]
        n_ = [r[4] for r in rows if r[2] == den]
        print(f"mean ratio to {den}: old {np.mean(o):.3f}, new {np.mean(n_):.3f}; cells new "
              f"better {sum(b < a for a, b in zip(o, n_))} of {len(o)}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("toy", "scenes", "all"), default="all")
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--spp", type=int, nargs="*", default=[16, 64])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--new", choices=("zc", "loo"), default="zc",
                    help="the relMSE weights compared with the old 1 / (z² + 0.01)")
    a = ap.parse_args(argv)
    MODES["new"] = a.new
    if a.part in ("toy", "all"):
        t0 = time.time()
        models = ("smooth", "max")
        report(f"combine_denoised, toy mixed 32x32 16 spp, σ = 1.5 blur, {a.draws} draws",
               toy_denoised(a.draws), models)
        report("  ... with the true variance in place of mean_var", toy_denoised(a.draws, True),
               models)
        report(f"combine_bins (4 bins of 4 spp), the same scene and blur, {a.draws} draws",
               toy_bins(a.draws), ("bins",))
        report("  ... with the true variance in place of mean_var", toy_bins(a.draws, True),
               ("bins",))
        print(f"(toy part {time.time() - t0:.0f} s)")
    if a.part in ("scenes", "all"):
        scenes(a.scenes, a.spp, a.seeds)


if __name__ == "__main__":
    main()
