"""Benchmark and demonstration for :mod:`statmc.sure` with OIDN.

1. Speed: MC-SURE (K = 4) and the finite-difference output variance (k = 16) with OIDN
   on a 512x512 render, against one OIDN call measured in the same run (the peer).
   Target: MC-SURE costs at most K + 1 denoiser calls plus O(pixels) work, i.e. a ratio
   of at most ~K + 1 = 5 (the O(pixels) part is reported separately).  Same for the JVP
   variance of a small torch network against its forward pass.
2. Choice of the finite-difference step: the MC-SURE divergence and the first-order
   variance of OIDN as functions of the relative step ε, on the toy renderer's Gaussian
   quadrant, with the empirical variance of OIDN's output over 200 renders for reference
   (the first-order value exceeds it by ~20 % here; a secant over steps of ±σ does not).
3. Relative vs literal step at high sample counts: the literal ``x + ε b`` of Eq. 2
   perturbs by ``ε σ``, a few float32 ulps when σ is small; the relative step does not.
4. Accuracy: image-level MC-SURE against the true MSE, averaged over renders, with the
   per-pixel channel covariance and with the diagonal variance of the mean.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_sure.py``
"""

from __future__ import annotations


import numpy as np

from statmc import denoisers as D
from statmc import sure as S
from statmc.toy import ToyRenderer


from _timing import best_of  # noqa: E402


def quadrant(size=64):
    """The toy "mixed" scene's Gaussian quadrant (exactly normal samples), size/2 square."""
    r = ToyRenderer("mixed", width=size, height=size)
    crop = (slice(0, size // 2), slice(size // 2, size))
    f = r.features()
    return r, crop, f["albedo"][crop], f["normal"][crop]


def bench_speed(size=512, k_sure=4, k_var=16):
    r = ToyRenderer("mixed", width=size, height=size)
    st = r.render_uniform(16, seed=0)
    x, mv = st.mean, st.mean_var
    f = D.oidn(st.albedo, st.normal)
    x32 = x.astype(np.float32)
    f(x32)  # device + filter creation outside the timing
    t_call, _ = best_of(lambda: f(x32), 5)
    t_sure, (_, info) = best_of(lambda: S.mc_sure(f, x, mv, k=k_sure, rng=0, extra_output=True), 3)
    t_var, _ = best_of(lambda: S.output_variance(f, x, mv, k=k_var, rng=0), 1)
    counted = np.zeros(1, int)

    def free(c):           # a zero-cost "denoiser": isolates the O(pixels) work
        counted[0] += 1
        return c

    t_free, _ = best_of(lambda: S.mc_sure(free, x, mv, k=k_sure, rng=0), 3)
    print(f"OIDN on a {size}x{size} toy render (albedo + normal, quality high):")
    print(f"  one OIDN call (the peer)        {t_call * 1e3:8.1f} ms")
    print(f"  mc_sure K={k_sure}                     {t_sure * 1e3:8.1f} ms   ratio x{t_sure / t_call:.2f}"
          f"   (target <= {k_sure + 1} calls + O(pixels); {info['calls']} calls made)")
    print(f"  mc_sure O(pixels) part alone    {t_free * 1e3:8.1f} ms   = x{t_free / t_call:.2f} of one call")
    print(f"  output_variance fd k={k_var}       {t_var * 1e3:8.1f} ms   ratio x{t_var / t_call:.2f}"
          f"   (target <= {k_var + 1} calls + O(pixels))")
    cov = r.true_cov() / 16
    t_cov, _ = best_of(lambda: S.mc_sure(f, x, cov, k=k_sure, rng=0), 1)
    print(f"  mc_sure K={k_sure} with (H,W,3,3) covariance {t_cov * 1e3:6.1f} ms   ratio x{t_cov / t_call:.2f}")
    try:
        import torch
    except ImportError:
        print("  (torch not installed: JVP timing skipped)")
        return
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 32, 3, padding=1), torch.nn.ReLU(),
                              torch.nn.Conv2d(32, 32, 3, padding=1), torch.nn.ReLU(),
                              torch.nn.Conv2d(32, 3, 3, padding=1)).eval()
    g = D.torch_module(net)
    xs = x[:256, :256]
    g(xs.astype(np.float32))
    t_fwd, _ = best_of(lambda: g(xs.astype(np.float32)), 3)
    t_jvp, _ = best_of(lambda: S.output_variance(g, xs, mv[:256, :256], k=k_var, method="jvp", rng=0), 1)
    t_fd, _ = best_of(lambda: S.output_variance(g, xs, mv[:256, :256], k=k_var, method="fd", rng=0), 1)
    print("3-layer conv net (32 channels) on 256x256, torch CPU:")
    print(f"  one forward pass (the peer)     {t_fwd * 1e3:8.1f} ms")
    print(f"  output_variance jvp k={k_var}      {t_jvp * 1e3:8.1f} ms   ratio x{t_jvp / t_fwd:.2f}"
          "   (Firmino 2023: a JVP costs ~3 forward passes)")
    print(f"  output_variance fd  k={k_var}      {t_fd * 1e3:8.1f} ms   ratio x{t_fd / t_fwd:.2f}")


def bench_step(spp=16, renders=200):
    r, crop, alb, nrm = quadrant()
    f = D.oidn(alb, nrm)
    cov = r.true_cov()[crop] / spp
    x = r.render_uniform(spp, seed=1, features=False).mean[crop]
    outs = np.array([f(r.render_uniform(spp, seed=100 + s, features=False).mean[crop].astype(np.float32))
                     for s in range(renders)], np.float64)
    emp = outs.var(axis=0, ddof=1).mean()
    print(f"Finite-difference step, OIDN on the 32x32 Gaussian quadrant at {spp} spp "
          f"(empirical Var of OIDN output over {renders} renders: {emp:.4g}):")
    print("  relative eps   MC-SURE divergence (mean)   first-order variance (mean)   / empirical")
    for eps in (3e-2, 1e-2, 3e-3, 1e-3, 1e-4, 1e-5, 1e-6):
        div = np.mean([S.mc_sure(f, x, cov, eps=eps, k=4, rng=s, extra_output=True)[1]["divergence"].mean()
                       for s in range(8)])
        var = S.output_variance(f, x, cov, k=32, eps=eps, rng=0).mean()
        mark = "  <- default" if eps in (S.DEFAULT_EPS, S.DEFAULT_VARIANCE_EPS) else ""
        print(f"  {eps:10.0e}     {div:14.5g}              {var:14.5g}            x{var / emp:.3f}{mark}")
    # the step at the noise scale itself: v = ±σ, a secant ("statistical linearisation")
    var = S.output_variance(f, x, cov, k=32, eps=1.0, relative=False, rng=0).mean()
    print(f"  secant (eps=1, relative=False: steps of ±σ)                {var:14.5g}            x{var / emp:.3f}")


def bench_literal_step(spp=65536):
    r, crop, alb, nrm = quadrant()
    f = D.oidn(alb, nrm)
    cov = r.true_cov()[crop] / spp
    x = r.true_mean()[crop]
    print(f"Relative vs literal step at {spp} spp (σ/x ≈ {np.sqrt(cov[..., 0, 0] / x[..., 0] ** 2).mean():.1e}):")
    for relative in (True, False):
        d = [S.mc_sure(f, x, cov, k=4, rng=s, relative=relative, extra_output=True)[1]["divergence"].mean()
             for s in range(20)]
        print(f"  relative={relative!s:5}  divergence mean {np.mean(d):.4g} ± {np.std(d, ddof=1) / np.sqrt(20):.2g}"
              f"  (spread over seeds {np.std(d, ddof=1):.2g})")


def bench_accuracy(spps=(4, 16, 64), renders=60):
    r, crop, alb, nrm = quadrant()
    f = D.oidn(alb, nrm)
    mu = r.true_mean()[crop]
    print(f"Image-level MC-SURE vs true MSE of OIDN, Gaussian quadrant, mean over {renders} renders:")
    print("    spp   true MSE     SURE (covariance)      SURE (diagonal mean_var)")
    for spp in spps:
        rows = []
        for s in range(renders):
            st = r.render_uniform(spp, seed=1000 + s, features=False)
            x = st.mean[crop]
            m, info = S.mc_sure(f, x, r.true_cov()[crop] / spp, rng=s, extra_output=True)
            rows.append((np.mean((info["denoised"] - mu) ** 2), m.mean(),
                         S.mc_sure(f, x, st.mean_var[crop], rng=s).mean()))
        a = np.array(rows)
        se = a.std(axis=0, ddof=1) / np.sqrt(renders)
        print(f"  {spp:5d}   {a[:, 0].mean():.4g}    {a[:, 1].mean():.4g} ± {se[1]:.1g}"
              f"     {a[:, 2].mean():.4g} ± {se[2]:.1g}  (x{a[:, 2].mean() / a[:, 0].mean():.2f})")


if __name__ == "__main__":
    bench_speed()
    print()
    bench_step()
    print()
    bench_literal_step()
    print()
    bench_accuracy()
