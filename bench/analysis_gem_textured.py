"""Where uniform+GEM loses against the oracle on ``textured-dof`` (docs/gem.md §5c).

The scale selection of Rousselle et al. 2011 (§4.2–4.4) is re-run with one ingredient at a
time replaced by its true value: the incremental rule on the true MSE, the quadratic bias
approximation (Eq. 1) on noise-free filtered values, then on the noisy values, with and
without the outlier removal.  True bias comes from the cached 65536-spp reference, true
variances of the mean from a 1024-spp render.  Prints relMSE ratios to uniform+box.

With ``--variants`` it instead prints the tables of docs/gem.md §5d: uniform+GEM / box
for the selector variants that were tried (the paper's Eq. 1, the pooled noise-corrected
bias estimate with several banks and outlier filters), on the four built-in Mitsuba scenes at
16/32/64 spp (``--seeds`` renders each, 16 for glass-caustic, seeds ``1000 s + spp`` as in
``bench_quality_gem.py``, against the cached 65536-spp references, 32768 for
glass-caustic) and on the toy scenes (64×48, exact truth, 4 renders).

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/analysis_gem_textured.py
[--variants [--seeds N]]`` (about a minute, or a few minutes with ``--variants``;
renders a missing reference first).
"""

import argparse

import numpy as np
from scipy.ndimage import correlate1d

from statmc import gem, metrics
from statmc.demo import cached_reference
from statmc.filters import DEFAULT_TRUNCATE, filter_bank, gaussian_kernel_1d
from statmc.gem import _weight_map
from statmc.pipeline import render_with_sampler
from statmc.renderers import make_renderer

S2 = 2 ** 0.5
SIGMA_FROM_1 = (0.0,) + tuple(S2 ** k for k in range(8))  # 8 scales ×√2 from σ = 1


def _filt(a, s):
    k = gaussian_kernel_1d(s, truncate=DEFAULT_TRUNCATE)
    out = correlate1d(correlate1d(a, k, 0, mode="constant"), k, 1, mode="constant")
    return out, k[len(k) // 2] ** 2


def _first_stop(stop):
    return np.where(stop.any(0), stop.argmax(0), stop.shape[0])


def _postprocess(S, sig, mult):
    """§4.4/§6 outlier removal with a map filter of ``mult`` × the coarse scale, centre left
    out, only switches to the coarser scale accepted."""
    raw = (S > 0).astype(float)
    maps = np.empty_like(raw)
    for k in range(len(sig) - 1):
        num, w0 = _filt(raw[k], sig[k + 1] * mult)
        den, _ = _filt(np.ones_like(raw[k]), sig[k + 1] * mult)
        maps[k] = ((num - w0 * raw[k]) / (den - w0) >= 0.5) & (raw[k] > 0.5)
    return _first_stop(maps > 0.5)


def _pick(vals, scales):
    return np.take_along_axis(vals, scales[None, ..., None].repeat(vals.shape[-1], -1), 0)[0]


def main():
    r = make_renderer("textured-dof")
    ref, _ = cached_reference(r, 65536, "out/cache")
    pvar = render_with_sampler(r, 1024, sampler="uniform", seed=99).sample_var
    names = ["the paper's §6 (bias='paper')", "incremental rule, true MSE", "Eq. 1 on noise-free values",
             "  same with ρ·z(γ)", "noisy values, true variances", "all estimated, no post",
             "σ from 1, map filter 1×", "expected-error oracle (σ from 1)"]
    for spp in (16, 64):
        rows = []
        for seed in (1, 2):
            st = render_with_sampler(r, spp, sampler="uniform", seed=seed)
            info = gem.select(st.mean, st.mean_var, n=st.n, sigmas=SIGMA_FROM_1, postprocess=False,
                              bias="paper")
            vals, var, r2 = info["values"], info["variances"], info["r2"]
            tv, tvar = (np.asarray(a) for a in filter_bank(ref, pvar / spp, SIGMA_FROM_1))
            emse = ((tv - ref[None]) ** 2).sum(-1) + tvar.sum(-1)
            w = _weight_map(st.n, 0.2, st.n.shape, np.float64)
            S_noisy = gem.selector(vals, var, r2, weight=w)
            eerr = (((tv - ref[None]) ** 2 + tvar) / (ref[None] ** 2 + 0.01)).mean(-1)
            images = [
                gem.reconstruct(st.mean, st.mean_var, n=st.n, bias="paper"),
                _pick(vals, _first_stop(emse[1:] - emse[:-1] > 0)),
                _pick(vals, _first_stop(gem.selector(tv, tvar, r2, weight=1.0) > 0)),
                _pick(vals, _first_stop(gem.selector(tv, tvar, r2, weight=w) > 0)),
                _pick(vals, _first_stop(gem.selector(vals, tvar, r2, weight=w) > 0)),
                _pick(vals, _first_stop(S_noisy > 0)),
                _pick(vals, _postprocess(S_noisy, SIGMA_FROM_1, 1.0)),
                _pick(vals, eerr.argmin(0)),
            ]
            box = metrics.relmse(st.mean, ref)
            rows.append([metrics.relmse(im, ref) / box for im in images])
        print(f"textured-dof, {spp} spp (relMSE / uniform+box, mean of 2 renders)")
        for name, v in zip(names, np.mean(rows, 0)):
            print(f"  {name:36s} {v:.3f}")


# ------------------------------------------------------------------ --variants (§5d)
def _bank(lo, count):
    return (0.0,) + tuple(lo * S2 ** k for k in range(count))


#: name -> keyword arguments of gem.reconstruct
VARIANTS = {
    "paper §6 (bias='paper')": dict(bias="paper"),
    "paper, σ from 1, map 1× (§5c)": dict(bias="paper", sigmas=SIGMA_FROM_1, map_scale=1.0),
    "paper, σ from 0.6": dict(bias="paper", sigmas=_bank(0.6, 10)),
    "pooled, §6 bank (σ from √2)": dict(bias="pooled", sigmas=_bank(S2, 8)),
    "pooled, σ from 1": dict(bias="pooled", sigmas=_bank(1.0, 9)),
    "pooled, σ from 1/√2": dict(bias="pooled", sigmas=_bank(0.5 * S2, 10)),
    "pooled, σ from 0.5": dict(bias="pooled", sigmas=_bank(0.5, 11)),
    "pooled, σ from 0.6, map 1× ": dict(bias="pooled", map_scale=1.0),
    "**pooled default** (σ from 0.6, map 2×)": dict(),
}


def variants(seeds, caustic_seeds):
    from statmc.toy import ToyRenderer
    REF = {"glass-caustic": 32768}
    cases = []
    for scene in ("cornell-box", "glossy-spheres", "glass-caustic", "textured-dof"):
        r = make_renderer(scene)
        ref, _ = cached_reference(r, REF.get(scene, 65536), "out/cache")
        for spp in (16, 32, 64):
            for s in range(caustic_seeds if scene == "glass-caustic" else seeds):
                cases.append((scene, spp, lambda r=r, spp=spp, s=s: render_with_sampler(
                    r, spp, sampler="uniform", seed=1000 * s + spp), ref))
    for scene in ("texture", "edges", "mixed", "gradient", "fireflies"):
        r = ToyRenderer(scene, width=64, height=48)
        for spp in (16, 32, 64):
            for s in range(4):
                cases.append((f"toy:{scene}", spp, lambda r=r, spp=spp, s=s: r.render_uniform(
                    spp, seed=100 * s + spp), r.true_mean()))
    res = {}
    for scene, spp, render, ref in cases:
        st = render()
        m, mv = st.mean.astype(np.float32), st.mean_var.astype(np.float32)
        box = metrics.relmse(m, ref)
        for name, kw in VARIANTS.items():
            img = gem.reconstruct(m, mv, n=st.n, **kw)
            res.setdefault((scene, spp, name), []).append(metrics.relmse(img, ref) / box)
    cols = list(dict.fromkeys((c[0], c[1]) for c in res))
    for group in (lambda c: not c[0].startswith("toy"), lambda c: c[0].startswith("toy")):
        cs = [c for c in cols if group(c)]
        print("| selector | " + " | ".join(f"{c[0]} {c[1]}" for c in cs) + " |")
        print("| --- " * (len(cs) + 1) + "|")
        for name in VARIANTS:
            print(f"| {name} | " + " | ".join(f"{np.mean(res[c + (name,)]):.3f}" for c in cs) + " |")
        print()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", action="store_true", help="the §5d tables instead")
    ap.add_argument("--seeds", type=int, default=2, help="renders per Mitsuba cell (--variants)")
    ap.add_argument("--caustic-seeds", type=int, default=16,
                    help="renders per glass-caustic cell (--variants): its relMSE is ruled by "
                         "rare fireflies")
    a = ap.parse_args()
    if a.variants:
        variants(a.seeds, a.caustic_seeds)
    else:
        main()
