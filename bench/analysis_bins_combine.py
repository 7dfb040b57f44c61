"""Sample bins and GEM's exposed kernel in the combination kernel (issue 5, Back 2020 §4.4).

Per scene, spp and seed, one uniform render is made as ``B = 4`` sample bins
(:func:`statmc.pipeline.render_bins`); the merged bins are the full render, so every method
below sees the same samples (equal budget).  Printed: relMSE (ε = 0.01, cached high-spp
reference) of

* ``gem``: GEM's final reconstruction of the full render;
* ``combine, GEM black box``: :func:`statmc.combine.combine_denoised` with GEM as a black
  box (it selects again on every probe; the pipeline's ``"combine"`` before session 5);
* ``combine, GEM kernel``: the same with GEM's full-sample kernel as a fixed linear filter
  (:func:`statmc.gem.selected_filter`; the pipeline's ``"combine"`` with ``denoiser="gem"``);
* ``gem+bins``: Eq. 14 on the bins with that kernel shared by the bins
  (:func:`statmc.pipeline.reconstruct_bins` with ``mix=None``);
* ``gem bins, moments from spread``: the same bins and per-bin images combined by
  :func:`statmc.combine.combine_bin_images` (``statmc combine bins.exr``), whose moments
  come from the spread over the bins instead of the probes;
* ``gem+bins, per-bin variances``: the same, but each bin's ``y`` variance is the larger
  of ``B`` times the smoothed full-sample one and the bin's own sample variance of the
  mean — weights that differ between bins, the variant ``combine_bins`` does not offer;
* ``oidn``, ``oidn+combine`` and ``oidn+bins`` (OIDN applied to each bin, ``mix=None``);
* ``gem+bins, mix`` and ``oidn+bins, mix``: the same with the SURE mix with the denoiser's
  output on the merged render (``reconstruct_bins(..., mix="local")``, its default since
  session 7; ``mix="global"`` as ``..., global mix``); the mean mix weight Σλ is printed
  beside them; ``oidn+bins, mix, probes at ȳ only``: the local mix with
  ``bin_probes=0``, its Stein terms from the probes at the merged render alone (first order
  at ``ȳ``) instead of 2 probes per bin;

and the ratios to ``gem`` and ``oidn`` (mean over seeds, per-seed range).

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/analysis_bins_combine.py``
(``--scenes``, ``--spp``, ``--seeds``, ``--methods`` (a subset of the names above; ``gem``
and ``oidn``, the baselines of the ratios, always run), ``--json``).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from statmc import metrics
from scipy.ndimage import uniform_filter

from statmc import gem
from statmc.combine import (combine_bin_images, combine_bins, combine_denoised, combine_multi,
                            denoiser_moments, statistical_weights)
from statmc.pipeline import merge_bins, reconstruct_bins, reconstruct_stats, render_bins
from statmc.progressive import bind_denoiser

from _scenes import scene_reference  # noqa: E402  (bench/ is the script's directory)

SCENES = ("cornell-box", "glossy-spheres", "textured-dof", "glass-caustic")
BASE = {"gem": "gem", "combine, GEM black box": "gem", "combine, GEM kernel": "gem",
        "gem+bins": "gem", "gem bins, moments from spread": "gem",
        "gem+bins, per-bin variances": "gem", "oidn": "oidn",
        "oidn+combine": "oidn", "oidn+bins": "oidn", "gem+bins, mix": "gem",
        "gem+bins, global mix": "gem", "oidn+bins, mix": "oidn", "oidn+bins, global mix": "oidn",
        "oidn+bins, mix, probes at ȳ only": "oidn"}


def per_bin_variances(bl, full, seed):
    """gem+bins with each bin's own variance in the weights (max with the smoothed shared
    one): ``combine_bins``' steps written out, with ``var_y`` per bin."""
    B = len(bl)
    _, f = gem.selected_filter(full.mean.astype(np.float32), full.mean_var.astype(np.float32))
    ys = np.stack([b.mean for b in bl])
    zs = np.stack([f(y.astype(np.float32)) for y in ys]).astype(np.float64)
    _, cov_z, cov_yz = denoiser_moments(f, ys.mean(axis=0), full.mean_var, rng=seed)
    box = lambda a, n: uniform_filter(a, (n, n) + (1,) * (a.ndim - 2), mode="reflect")  # noqa: E731
    shared = B * box(full.mean_var, 5)
    var_y = np.maximum(shared[None], np.stack([b.mean_var for b in bl]))
    w = statistical_weights(ys, zs, var_y, B * box(cov_z, 5), 15, cov_yz=B * box(cov_yz, 5))
    return combine_multi(ys, zs, w)


def cell(r, ref, spp, seed, bins, methods=None):
    """relMSE of every method on one binned render, the seconds each took and the mean mix
    weight of the mixed ones."""
    bl = render_bins(r, spp, bins, seed=9000 + seed)
    full = merge_bins(bl)
    out, sec, mixw = {}, {}, {}

    def run(name, fn):
        if methods is not None and name not in methods and name not in ("gem", "oidn"):
            return
        t0 = time.perf_counter()
        img = fn()
        sec[name] = time.perf_counter() - t0
        out[name] = metrics.relmse(np.asarray(img, np.float64), ref)

    run("gem", lambda: reconstruct_stats(full, "gem")[0])
    run("combine, GEM black box", lambda: combine_denoised(
        full.mean, full.mean_var, bind_denoiser("gem", full), rng=seed))
    run("combine, GEM kernel", lambda: reconstruct_stats(full, "combine", denoiser="gem",
                                                         seed=seed)[0])
    binned = {}

    def gem_bins():
        img, _, binned["gem"] = reconstruct_bins(bl, "gem+bins", seed=seed, mix=None,
                                                 return_bins=True)
        return img

    run("gem+bins", gem_bins)
    run("gem bins, moments from spread", lambda: combine_bin_images(*binned["gem"]))
    run("gem+bins, per-bin variances", lambda: per_bin_variances(bl, full, seed))
    run("oidn", lambda: reconstruct_stats(full, "oidn")[0])
    run("oidn+combine", lambda: reconstruct_stats(full, "oidn+combine", seed=seed)[0])
    run("oidn+bins", lambda: reconstruct_bins(bl, "oidn+bins", seed=seed, mix=None)[0])
    for method in ("gem+bins", "oidn+bins"):
        for mix, label in (("local", "mix"), ("global", "global mix")):
            def mixed(method=method, mix=mix, name=f"{method}, {label}"):
                img, maps = reconstruct_bins(bl, method, seed=seed, mix=mix)
                mixw[name] = float(np.mean(maps["mix"]))
                return img
            run(f"{method}, {label}", mixed)

    def oidn_mix_ybar_probes(name="oidn+bins, mix, probes at ȳ only"):
        img, info = combine_bins(np.stack([b.mean for b in bl]), full.mean_var,
                                 bind_denoiser("oidn", full), rng=seed, bin_probes=0,
                                 extra_output=True)
        mixw[name] = float(np.mean(info["mix"]))
        return img

    run("oidn+bins, mix, probes at ȳ only", oidn_mix_ybar_probes)
    return out, sec, mixw


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--spp", type=int, nargs="*", default=[16, 64])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--bins", type=int, default=4)
    ap.add_argument("--methods", nargs="*", default=None, choices=list(BASE))
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    rows = []
    for scene in a.scenes:
        r, ref = scene_reference(scene)
        ref = ref.mean
        for spp in a.spp:
            res, secs, mixes = {}, {}, {}
            for s in range(a.seeds):
                out, sec, mixw = cell(r, ref, spp, s, a.bins, a.methods)
                for key, v in out.items():
                    res.setdefault(key, []).append(v)
                    secs.setdefault(key, []).append(sec[key])
                for key, v in mixw.items():
                    mixes.setdefault(key, []).append(v)
            print(f"{scene} {spp} spp ({a.seeds} seeds, {r.width}x{r.height}, B = {a.bins})",
                  flush=True)
            for key, v in res.items():
                v = np.array(v)
                base = np.array(res[BASE[key]])
                ratio = v / base
                mix = f"   mix {np.mean(mixes[key]):.2f}" if key in mixes else ""
                print(f"  {key:30s} relMSE {v.mean():.4g}   / {BASE[key]:4s} "
                      f"{v.mean() / base.mean():.3f} (per seed {ratio.min():.3f}–{ratio.max():.3f})"
                      f"   {np.mean(secs[key]):.2f} s{mix}", flush=True)
                rows.append({"scene": scene, "spp": spp, "method": key, "relmse": v.tolist(),
                             "ratio": float(v.mean() / base.mean()), "base": BASE[key],
                             "seconds": float(np.mean(secs[key])),
                             "mix": mixes.get(key)})
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
