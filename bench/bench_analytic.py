"""Benchmark and demonstration for :mod:`statmc.analytic`.

1. Speed: ``expected_kernel_loss`` on a 1920x1080x3 image with 7x7 per-pixel kernels
   (float32, as a kernel-predicting network exports them), compiled kernel vs. the plain
   NumPy reference (the peer), with and without the gradient.  Target: < 1 s on 2 cores.
2. The expected-error sampler vs. uniform sampling at equal budget on a toy scene, in the
   closed-form objective and in relMSE measured over real (firefly) samples.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_analytic.py``
"""

from __future__ import annotations

import time

import numpy as np

from statmc import analytic
from statmc.analytic import (apply_kernels, expected_kernel_loss, optimal_sample_counts,
                             optimal_sample_map)


from _timing import best_of  # noqa: E402


def bench_speed(h=1080, w=1920, c=3, k=7):
    rng = np.random.default_rng(0)
    kern = rng.random((h, w, k, k), dtype=np.float32)
    kern /= kern.sum(axis=(2, 3), keepdims=True)
    x_g = rng.random((h, w, c))
    var_g = rng.random((h, w, c))
    s_bar = np.full((h, w), 16.0)
    x_t = x_g + rng.normal(size=(h, w, c)) * np.sqrt(var_g / 16)
    s = rng.uniform(0, 32, (h, w))
    args = (kern, x_t, s_bar, s, x_g, var_g)
    expected_kernel_loss(kern[:8, :8], *(a[:8, :8] for a in args[1:]))  # compile outside timing
    expected_kernel_loss(kern[:8, :8], *(a[:8, :8] for a in args[1:]), return_grad=True)
    t_fast, val = best_of(lambda: expected_kernel_loss(*args, loss="mrse"), 3)
    t_grad, _ = best_of(lambda: expected_kernel_loss(*args, loss="mrse", return_grad=True), 3)

    def numpy_reference(grad):
        xt, sb, sm, xg, vg, mvt, _ = analytic._prepare(*args[1:])
        kk = analytic._check_kernels(kern, xt.shape[:2])
        return analytic._evaluate(kk, xt, sb, sm, xg, vg, mvt, "mrse", 0.01, grad, engine="numpy")[:2]

    t_ref, (val_ref, _) = best_of(lambda: numpy_reference(False), 1)
    t_ref_g, _ = best_of(lambda: numpy_reference(True), 1)
    print(f"expected_kernel_loss {w}x{h}x{c}, {k}x{k} float32 kernels (relMSE):")
    print(f"  numba   loss       {t_fast:7.3f} s   (target < 1 s)")
    print(f"  numpy   loss       {t_ref:7.3f} s   (reference, the peer)   speed-up x{t_ref / t_fast:.1f}")
    print(f"  numba   loss+grad  {t_grad:7.3f} s")
    print(f"  numpy   loss+grad  {t_ref_g:7.3f} s                           speed-up x{t_ref_g / t_grad:.1f}")
    print(f"  values agree: {val:.12g} vs {val_ref:.12g} (rel. diff {abs(val - val_ref) / val_ref:.1e})")


# --------------------------------------------------------------------------- toy scene
def toy_scene(h=48, w=48, c=3, seed=0):
    """Smooth colour ramp, a bright square edge, and a firefly-prone region."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([0.2 + 0.6 * xx, 0.3 + 0.4 * yy, 0.5 + 0.2 * xx * yy], -1)[..., :c]
    base[h // 4:h // 2, w // 4:w // 2] += 1.5
    x_g = base
    # sample variance: mostly moderate, a 'caustic' strip with fireflies
    var_g = 0.05 * x_g ** 2
    var_g[:, 3 * w // 4:] = 4.0 * x_g[:, 3 * w // 4:] ** 2
    var_g *= rng.uniform(0.5, 1.5, (h, w, 1))
    return x_g, var_g


def firefly_mean(x_g, var_g, counts, rng, reps=1):
    """Means of `counts` raw two-point 'firefly' samples: x_g/p w.p. p, else 0.

    p = x_g²/(x_g² + var_g) gives mean x_g and variance var_g; one uniform per sample is
    shared by the channels.  Returns (reps, H, W, C) (zeros where counts == 0).
    """
    h, w, c = x_g.shape
    p = np.where(var_g > 0, x_g ** 2 / np.maximum(x_g ** 2 + var_g, 1e-300), 1.0)
    val = np.where(p > 0, x_g / np.where(p > 0, p, 1.0), 0.0)
    flat_p, flat_v = p.reshape(-1, c), val.reshape(-1, c)
    cnt = counts.reshape(-1).astype(np.int64)
    pix = np.repeat(np.arange(h * w), cnt)
    out = np.zeros((reps, h * w, c))
    if pix.size:
        u = rng.random((reps, pix.size, 1))
        hit = u < flat_p[pix][None]
        contrib = hit * flat_v[pix][None]
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        nz = cnt > 0
        sums = np.add.reduceat(contrib, starts[nz], axis=1)
        out[:, nz] = sums / cnt[nz][None, :, None]
    return out.reshape(reps, h, w, c)


def gaussian_kernels(h, w, sigma, k):
    r = k // 2
    ax = np.arange(-r, r + 1)
    g = np.exp(-(ax[:, None] ** 2 + ax[None] ** 2) / (2 * sigma ** 2))
    return np.broadcast_to(g / g.sum(), (h, w, k, k))


def measured_relmse(kern, x_t, s_bar, counts, x_g, var_g, rng, reps):
    new = firefly_mean(x_g, var_g, counts, rng, reps)
    sb, s = s_bar[..., None], counts[..., None].astype(float)
    y = (sb * x_t + s * new) / (sb + s)
    d = apply_kernels(kern, y)
    per = ((d - x_g) ** 2 / (x_g ** 2 + 0.01)).mean(axis=(1, 2, 3))
    return per.mean(), per.std(ddof=1) / np.sqrt(reps)


def bench_sampler(reps=400):
    rng = np.random.default_rng(1)
    x_g, var_g = toy_scene()
    h, w, c = x_g.shape
    s_bar = np.full((h, w), 8.0)
    x_t = firefly_mean(x_g, var_g, s_bar, rng)[0]
    kern = gaussian_kernels(h, w, 1.0, 5)
    budget = int(s_bar.sum())
    uniform = np.full((h, w), budget // (h * w), np.int64)
    print(f"\nSampler on a {w}x{h} toy scene, s_bar = 8 spp, budget = +8 spp, fixed 5x5 Gaussian "
          "(sigma 1), relMSE (eps 0.01):")
    for label, kw in (("oracle x_g, conditional on x_t", dict(x_g_est=x_g, var_g_est=var_g)),):
        t0 = time.perf_counter()
        smap, info = optimal_sample_map(kern, x_t, s_bar, kw["x_g_est"], kw["var_g_est"], budget,
                                        loss="mrse", return_info=True)
        counts = optimal_sample_counts(kern, x_t, s_bar, kw["x_g_est"], kw["var_g_est"], budget,
                                       loss="mrse", rng=2)
        dt = time.perf_counter() - t0
        cf_u = expected_kernel_loss(kern, x_t, s_bar, uniform, x_g, var_g, loss="mrse")
        cf_o = expected_kernel_loss(kern, x_t, s_bar, counts, x_g, var_g, loss="mrse")
        mu, su = measured_relmse(kern, x_t, s_bar, uniform, x_g, var_g, rng, reps)
        mo, so = measured_relmse(kern, x_t, s_bar, counts, x_g, var_g, rng, reps)
        print(f"  [{label}] solver {info['iterations']} it, {dt:.2f} s, start {info['start']}")
        print(f"    closed form : uniform {cf_u:.5f}   optimised {cf_o:.5f}   ratio {cf_o / cf_u:.3f}")
        print(f"    measured    : uniform {mu:.5f}±{su:.5f}   optimised {mo:.5f}±{so:.5f}   "
              f"ratio {mo / mu:.3f}   ({reps} renders each)")

    # Estimates only: pilot mean and sample variance, blurred; unconditional objective.
    per_u, per_o = [], []
    for rep in range(reps // 8):
        pil = firefly_mean(x_g, var_g, np.full((h, w), 8), rng, 8)
        x_t = pil.mean(0)
        sv = pil.var(0, ddof=1) * 8           # per-sample variance from 8 sub-means of 8
        xe = apply_kernels(kern, x_t)
        ve = np.maximum(apply_kernels(kern, sv), 1e-6)
        sb = np.full((h, w), 64.0)
        cnt = optimal_sample_counts(kern, x_t, sb, xe, ve, budget * 8, loss="mrse",
                                    mean_var_t=ve / sb[..., None], rng=rng)
        uni = np.full((h, w), 64, np.int64)
        for cc, acc in ((uni, per_u), (cnt, per_o)):
            new = firefly_mean(x_g, var_g, cc, rng)[0]
            y = (64 * x_t + cc[..., None] * new) / (64 + cc[..., None])
            d = apply_kernels(kern, y)
            acc.append(((d - x_g) ** 2 / (x_g ** 2 + 0.01)).mean())
    per_u, per_o = np.array(per_u), np.array(per_o)
    print("  [estimates only: 64 spp pilot, blurred mean/variance, unconditional objective, +64 spp]")
    print(f"    measured    : uniform {per_u.mean():.5f}±{per_u.std(ddof=1) / np.sqrt(per_u.size):.5f}"
          f"   optimised {per_o.mean():.5f}±{per_o.std(ddof=1) / np.sqrt(per_o.size):.5f}"
          f"   ratio {per_o.mean() / per_u.mean():.3f}   ({per_u.size} pilot+future renders each)")


if __name__ == "__main__":
    bench_speed()
    bench_sampler()
