"""The ``expected-error`` sampler vs uniform sampling at equal budget (issue 4's table).

Both samplers run the adaptive loop of :func:`statmc.adaptive.adaptive_render` (4 spp
uniform, then 8 passes) with the *same fixed denoiser*, one of

* ``gauss`` — a Gaussian of σ = 1 px (``--sigma``);
* ``gem`` — GEM's per-pixel scale selection (adaptive bank σ = 0, 1, 2, 4, 8) made on the
  4-spp pilot render and then held fixed (:func:`statmc.analytic.gem_kernels`, the
  kernels of :class:`statmc.analytic.PilotKernelSampler`), so Lemma A.1 holds for the
  final denoised image.

With the same seed the pilot is identical for both samplers, so the comparison is paired
over seeds (seeds start at 100: seed 1 of the render loop would reuse the cached
references' first pass seed).  For each scene, spp and denoiser:

* **closed form** — ``expected_kernel_loss`` of the final count map ``n`` with the truth
  (toy scenes: exact mean and sample variance; Mitsuba: the best cached reference's mean
  and sample variance), averaged over the render (``mean_var_t = var/n``):
  ``mean_p w_p ((K x_g − x_g)_p² + Σ_q K_pq² var_q/n_q)``, relMSE weights; the expected
  error of a *fresh* render with that count map;
* **oracle** — the same closed form at the best count map for the true statistics
  (water-filling with ``n >= 4``), relative to uniform: the gain that was available;
* **measured** — relMSE (ε = 0.01) of the denoised render against the truth/reference;
  the ratio expected-error / uniform (mean of the per-seed ratios) with its standard
  error, and a one-sided Wilcoxon signed-rank p-value for "expected-error is lower" over
  the paired seeds;
* **fresh** — relMSE of a new, independent render with expected-error's final count map
  (same denoiser), over uniform's measured relMSE: what the *allocation* achieves without
  the adaptive loop's data dependence (its expectation is the closed form).

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_quality_expected_error.py``
(options: ``--toy``, ``--mitsuba``, ``--spp``, ``--seeds``, ``--denoisers``, ``--mix``,
``--loss``, ``--weight-sigma``, ``--prior-dof``, ``--pool-sigma``; the sampler's defaults
otherwise).  Writes the table to ``out/bench/quality_expected_error.md``
(``--out``/``--name``); docs/analytic.md has the numbers.  About 15 min on 2 busy cores.
"""

from __future__ import annotations

import argparse
import inspect
import os
import sys
import time

import numpy as np
from scipy import stats as sps

from statmc.adaptive import adaptive_render
from statmc.analytic import (_unconditional_map, apply_kernels, expected_error_sampler,
                             expected_kernel_loss, gem_kernels)
from statmc.denoisers import gaussian
from statmc.metrics import relmse

#: Highest-spp reference cached per Mitsuba scene (docs: session notes).
REF_SPP = {"cornell-box": 65536, "glossy-spheres": 65536, "textured-dof": 65536,
           "glass-caustic": 32768}
SEED0 = 100
_sig = inspect.signature(expected_error_sampler).parameters
DEFAULT_LOSS, DEFAULT_MIX = _sig["loss"].default, _sig["mix"].default


def truth_of(scene, width, height, ref_spp=None):
    """(renderer, x_g, var_g, label) for a toy scene name or a Mitsuba scene name."""
    if scene.startswith("toy:"):
        from statmc.toy import ToyRenderer
        r = ToyRenderer(scene[4:], width=width, height=height)
        return (r, np.asarray(r.true_mean(), np.float64), np.asarray(r.true_var(), np.float64),
                "exact")
    from statmc.demo import cached_reference
    from statmc.exr import read_exr
    from statmc.renderers import make_renderer
    r = make_renderer(scene)
    spp = ref_spp or REF_SPP.get(scene, 4096)
    _, path = cached_reference(r, spp, "out/cache")
    ref = read_exr(path)
    return r, np.asarray(ref.mean, np.float64), np.asarray(ref.sample_var, np.float64), f"{spp} spp"


def closed_form(kernels, n, x_g, var_g):
    n = np.asarray(n, np.float64)
    return expected_kernel_loss(kernels, x_g, n, 0.0, x_g, var_g, loss="mrse",
                                mean_var_t=var_g / n[..., None])


def oracle_map(kernels, total, x_g, var_g, initial=4):
    """Best real count map (>= ``initial``) for the true statistics, unconditional objective."""
    h, w = x_g.shape[:2]
    base = np.full((h, w), float(initial))
    return base + _unconditional_map(kernels, base, x_g, var_g, float(total - base.sum()),
                                     "mrse", 0.01)


def run_cell(renderer, x_g, var_g, spp, seeds, denoisers, variants, sigma, **options):
    """Per-seed arrays for every (denoiser, sampler) of one scene and spp."""
    gk = gaussian(sigma).kernels(x_g.shape)
    keys = [(d, "uniform") for d in denoisers] + [(d, v) for d in denoisers for v in variants]
    out = {k: {"cf": [], "meas": [], "fresh": [], "sec": 0.0} for k in keys}
    oracle = {d: [] for d in denoisers}
    h, w = x_g.shape[:2]
    total = int(round(spp * h * w))
    for seed in range(SEED0, SEED0 + seeds):
        pilot = {}

        def grab(k, stats, counts):
            if k == 0:
                pilot["stats"] = stats

        t0 = time.perf_counter()
        uni = adaptive_render(renderer, spp, sampler="uniform", seed=seed, callback=grab)
        t_uni = time.perf_counter() - t0
        kern = {}
        for d in denoisers:
            p = pilot["stats"]
            kern[d] = gk if d == "gauss" else gem_kernels(p.mean, p.mean_var, n=p.n)
            rec = out[(d, "uniform")]
            rec["sec"] += t_uni
            rec["cf"].append(closed_form(kern[d], uni.stats.n, x_g, var_g))
            rec["meas"].append(relmse(apply_kernels(kern[d], uni.stats.mean), x_g))
            rec["fresh"].append(np.nan)
            oracle[d].append(closed_form(kern[d], oracle_map(kern[d], total, x_g, var_g),
                                         x_g, var_g))
            for loss, m in variants:
                K = kern[d]

                def sampler(stats, budget, rng, K=K, m=m, loss=loss):
                    return expected_error_sampler(stats, budget, rng, kernels=K, mix=m,
                                                  loss=loss, **options)

                t0 = time.perf_counter()
                res = adaptive_render(renderer, spp, sampler=sampler, seed=seed)
                rec = out[(d, (loss, m))]
                rec["sec"] += time.perf_counter() - t0
                n = res.stats.n
                rec["cf"].append(closed_form(K, n, x_g, var_g))
                rec["meas"].append(relmse(apply_kernels(K, res.stats.mean), x_g))
                fresh = renderer.render(n, seed=seed * 1_000_003 + 7919 * 50, features=False)
                rec["fresh"].append(relmse(apply_kernels(K, fresh.mean), x_g))
    cell = {k: {m: (np.asarray(v[m]) if m != "sec" else v[m]) for m in v} for k, v in out.items()}
    return cell, {d: np.asarray(v) for d, v in oracle.items()}


def compare(base, other):
    """Mean ratio other/base over paired seeds, its standard error, one-sided p-value."""
    ratio = other / base
    se = ratio.std(ddof=1) / np.sqrt(ratio.size) if ratio.size > 1 else np.nan
    p = sps.wilcoxon(other, base, alternative="less").pvalue if ratio.size > 1 else np.nan
    return ratio.mean(), se, p


HEAD = ("| scene | spp | denoiser | sampler loss | λ | closed form: uniform | expected-error | ratio | oracle ratio | "
        "measured relMSE: uniform | expected-error | ratio ± s.e. | p (one-sided) | "
        "fresh render: ratio ± s.e. | p | time ee : uniform |")


def rows(scene, spp, cell, oracle, denoisers, variants):
    lines = []
    for d in denoisers:
        u = cell[(d, "uniform")]
        o_r = oracle[d].mean() / u["cf"].mean()
        for loss, m in variants:
            e = cell[(d, (loss, m))]
            cf_r = e["cf"].mean() / u["cf"].mean()
            m_r, m_se, m_p = compare(u["meas"], e["meas"])
            f_r, f_se, f_p = compare(u["meas"], e["fresh"])
            lines.append(
                f"| {scene} | {spp} | {d} | {loss} | {m:g} | {u['cf'].mean():.4g} | {e['cf'].mean():.4g} | "
                f"{cf_r:.3f} | {o_r:.3f} | {u['meas'].mean():.4g} | {e['meas'].mean():.4g} | "
                f"{m_r:.3f} ± {m_se:.3f} | {m_p:.2g} | {f_r:.3f} ± {f_se:.3f} | {f_p:.2g} | "
                f"{e['sec'] / u['sec']:.2f} |")
    return lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--toy", nargs="*", default=["mixed", "edges", "fireflies", "gradient"])
    p.add_argument("--mitsuba", nargs="*", default=["cornell-box", "glossy-spheres",
                                                    "glass-caustic", "textured-dof"])
    p.add_argument("--spp", nargs="*", type=int, default=[16, 64])
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--toy-size", type=int, default=64)
    p.add_argument("--ref-spp", type=int, default=None,
                   help="Mitsuba reference spp (default: the best cached one, REF_SPP)")
    p.add_argument("--sigma", type=float, default=1.0, help="the fixed Gaussian denoiser")
    p.add_argument("--denoisers", nargs="*", default=["gauss", "gem"], choices=["gauss", "gem"])
    p.add_argument("--mix", nargs="*", type=float, default=[None],
                   help="defensive mixture weights λ of uniform sampling to compare "
                        "(default: the sampler's default)")
    p.add_argument("--loss", nargs="*", default=[None], choices=[None, "mrse", "mse"],
                   help="the loss the sampler minimises (default: the sampler's default); "
                        "the bench always measures relMSE")
    p.add_argument("--prior-dof", type=float, default=None,
                   help="expected_error_sampler's prior_dof (default: its own)")
    p.add_argument("--weight-sigma", type=float, default=None,
                   help="expected_error_sampler's weight_sigma (default: its own)")
    p.add_argument("--pool-sigma", type=float, default=None,
                   help="expected_error_sampler's pool_sigma (default: its own)")
    p.add_argument("--out", default="out/bench")
    p.add_argument("--name", default="quality_expected_error.md")
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    lines = [HEAD, "|" + " --- |" * (HEAD.count("|") - 1)]
    refs = []
    variants = [(loss or DEFAULT_LOSS, DEFAULT_MIX if m is None else m)
                for loss in a.loss for m in a.mix]
    t_start = time.perf_counter()
    scenes = [f"toy:{s}" for s in a.toy] + list(a.mitsuba)
    for scene in scenes:
        r, x_g, var_g, label = truth_of(scene, a.toy_size, a.toy_size, a.ref_spp)
        refs.append(f"{scene}: {label}")
        for spp in a.spp:
            opts = {k: v for k, v in (("prior_dof", a.prior_dof), ("pool_sigma", a.pool_sigma),
                                             ("weight_sigma", a.weight_sigma))
                    if v is not None}
            cell, oracle = run_cell(r, x_g, var_g, spp, a.seeds, a.denoisers, variants, a.sigma,
                                    **opts)
            for line in rows(scene, spp, cell, oracle, a.denoisers, variants):
                lines.append(line)
                print(line, flush=True)
    table = "\n".join(lines)
    load = os.getloadavg()
    with open(os.path.join(a.out, a.name), "w") as f:
        f.write(f"Fixed denoisers: Gaussian σ = {a.sigma} (gauss), GEM selection from the 4-spp "
                f"pilot held fixed (gem); adaptive loop 4 spp + 8 passes; {a.seeds} paired seeds "
                f"({SEED0}..{SEED0 + a.seeds - 1}); relMSE ε = 0.01; toy scenes {a.toy_size}²; "
                f"truth: {', '.join(refs)}.  Run time {time.perf_counter() - t_start:.0f} s, "
                f"load average {load[0]:.2f}.\n\n{table}\n")
    print("\n" + table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
