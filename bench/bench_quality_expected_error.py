"""The ``expected-error`` sampler vs uniform sampling at equal budget (issue 4's table).

Both use the adaptive loop of :func:`statmc.adaptive.adaptive_render` (4 spp uniform, then
8 passes) and the *same fixed denoiser*, a Gaussian of σ = 1 px; with the same seed the
first pass is identical, so the comparison is paired over seeds.  For each scene and spp:

* **closed form** — ``expected_kernel_loss`` of the final count map ``n`` with the truth
  (toy scenes: exact mean and sample variance; Mitsuba: the 4096-spp reference's mean and
  sample variance), averaged over the render (``mean_var_t = var/n``):
  ``mean_p w_p ((K x_g − x_g)_p² + Σ_q K_pq² var_q/n_q)``, relMSE weights;
* **measured** — relMSE (ε = 0.01) of the denoised render against the truth/reference;
* the ratio expected-error / uniform (mean of the per-seed ratios) with its standard
  error, and a one-sided Wilcoxon signed-rank p-value for "expected-error is lower"
  over the paired seeds.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_quality_expected_error.py``
(options: ``--toy``, ``--mitsuba``, ``--spp``, ``--seeds``, ``--objective``).  Writes the
table to ``out/bench/quality_expected_error.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from scipy import stats as sps

from statmc.adaptive import adaptive_render
from statmc.analytic import expected_kernel_loss
from statmc.denoisers import gaussian
from statmc.metrics import relmse


def truth_of(scene, width, height, ref_spp):
    """(renderer, x_g, var_g) for a toy scene name or a Mitsuba scene name."""
    if scene.startswith("toy:"):
        from statmc.toy import ToyRenderer
        r = ToyRenderer(scene[4:], width=width, height=height)
        return r, np.asarray(r.true_mean(), np.float64), np.asarray(r.true_var(), np.float64)
    from statmc.demo import cached_reference
    from statmc.exr import read_exr
    from statmc.renderers import make_renderer
    r = make_renderer(scene)
    _, path = cached_reference(r, ref_spp, "out/cache")
    ref = read_exr(path)
    return r, np.asarray(ref.mean, np.float64), np.asarray(ref.sample_var, np.float64)


def closed_form(kernels, n, x_g, var_g):
    n = np.asarray(n, np.float64)
    return expected_kernel_loss(kernels, x_g, n, 0.0, x_g, var_g, loss="mrse",
                                mean_var_t=var_g / n[..., None])


def run_cell(renderer, x_g, var_g, spp, seeds, samplers, sigma):
    den = gaussian(sigma)
    kernels = den.kernels(x_g.shape)
    out = {name: {"cf": [], "meas": [], "sec": 0.0} for name in samplers}
    for seed in range(seeds):
        for name, (sampler, opts) in samplers.items():
            t0 = time.perf_counter()
            res = adaptive_render(renderer, spp, sampler=sampler, seed=seed, **opts)
            out[name]["sec"] += time.perf_counter() - t0
            out[name]["cf"].append(closed_form(kernels, res.stats.n, x_g, var_g))
            out[name]["meas"].append(relmse(den(res.stats.mean), x_g))
    return {k: {m: np.asarray(v[m]) if m != "sec" else v[m] for m in v} for k, v in out.items()}


def compare(base, other):
    """Mean ratio other/base over paired seeds, its standard error, one-sided p-value."""
    ratio = other / base
    se = ratio.std(ddof=1) / np.sqrt(ratio.size) if ratio.size > 1 else np.nan
    p = sps.wilcoxon(other, base, alternative="less").pvalue if ratio.size > 1 else np.nan
    return ratio.mean(), se, p


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--toy", nargs="*", default=["mixed", "edges", "fireflies", "gradient"])
    p.add_argument("--mitsuba", nargs="*", default=["cornell-box", "glossy-spheres",
                                                    "glass-caustic", "textured-dof"])
    p.add_argument("--spp", nargs="*", type=int, default=[16, 64])
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--toy-size", type=int, default=64)
    p.add_argument("--ref-spp", type=int, default=4096)
    p.add_argument("--sigma", type=float, default=1.0, help="the fixed Gaussian denoiser")
    p.add_argument("--objective", nargs="*", default=["unconditional"],
                   choices=["unconditional", "conditional"],
                   help="expected-error objectives to compare against uniform")
    p.add_argument("--out", default="out/bench")
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    samplers = {"uniform": ("uniform", {})}
    for obj in a.objective:
        samplers[f"ee-{obj}"] = ("expected-error", {"objective": obj, "sigma": a.sigma})
    head = ("| scene | spp | closed form: uniform | expected-error | ratio | "
            "measured relMSE: uniform | expected-error | ratio ± s.e. | p (one-sided) | "
            "time ee : uniform |")
    lines = [head, "| --- " * 10 + "|"]
    scenes = [f"toy:{s}" for s in a.toy] + list(a.mitsuba)
    for scene in scenes:
        r, x_g, var_g = truth_of(scene, a.toy_size, a.toy_size, a.ref_spp)
        for spp in a.spp:
            cell = run_cell(r, x_g, var_g, spp, a.seeds, samplers, a.sigma)
            u = cell["uniform"]
            for obj in a.objective:
                e = cell[f"ee-{obj}"]
                cf_r = e["cf"].mean() / u["cf"].mean()
                m_r, m_se, m_p = compare(u["meas"], e["meas"])
                label = scene if len(a.objective) == 1 else f"{scene} ({obj})"
                lines.append(
                    f"| {label} | {spp} | {u['cf'].mean():.4g} | {e['cf'].mean():.4g} | {cf_r:.3f} | "
                    f"{u['meas'].mean():.4g} | {e['meas'].mean():.4g} | {m_r:.3f} ± {m_se:.3f} | "
                    f"{m_p:.2g} | {e['sec'] / u['sec']:.2f} |")
                print(lines[-1], flush=True)
    table = "\n".join(lines)
    with open(os.path.join(a.out, "quality_expected_error.md"), "w") as f:
        f.write(f"Fixed Gaussian denoiser σ = {a.sigma}; adaptive loop 4 spp + 8 passes; "
                f"{a.seeds} paired seeds; relMSE ε = 0.01; toy scenes {a.toy_size}², "
                f"Mitsuba references {a.ref_spp} spp.\n\n{table}\n")
    print("\n" + table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
