"""Tests for statmc.da_sampling (Firmino et al. 2023): tone-curve derivatives, the variance
of mixes by Monte Carlo (chi-square), the map formula and its blurs, exact budgets, the
adaptive-loop sampler, equal-budget comparison with uniform sampling, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats as sst

from _images import any_image, image_args
from statmc import da_sampling as da
from statmc import denoisers
from statmc.adaptive import adaptive_render
from statmc.errors import InputError
from statmc.filters import gaussian_filter
from statmc.metrics import relmse
from statmc.progressive import bind_denoiser, mix_error, progressive_denoise
from statmc.stats import PixelStats
from statmc.sure import kernel_variance, mc_sure
from statmc.toy import ToyRenderer


def _chi2_var_pvalues(samples, var):
    """Two-sided p-values of H0: Var = var, per column, from R draws (chi-square)."""
    r = samples.shape[0]
    stat = (r - 1) * samples.var(axis=0, ddof=1) / var
    cdf = sst.chi2.cdf(stat, r - 1)
    return 2 * np.minimum(cdf, 1 - cdf)


# =========================================================================== tone curves
@pytest.mark.parametrize("name", da.TONEMAPS)
@pytest.mark.parametrize("exposure", [1.0, 0.3, 4.0])
def test_tonemap_derivative_matches_central_differences(name, exposure):
    x = np.concatenate([np.linspace(0.001, 0.5, 40), np.linspace(0.5, 20, 40)])
    h = 1e-6
    fd = (da.tonemap(x + h, name, exposure=exposure)
          - da.tonemap(x - h, name, exposure=exposure)) / (2 * h)
    an = da.tonemap_derivative(x, name, exposure=exposure)
    clamped = da.tonemap(x + h, name, exposure=exposure) >= 1.0
    assert np.allclose(an[~clamped], fd[~clamped], rtol=1e-5, atol=1e-8)
    assert np.all(an[clamped] == 0)
    assert np.all(da.tonemap_derivative(-x, name) == 0) and np.all(da.tonemap(-x, name) == 0)


def test_tonemap_values():
    assert float(da.tonemap(np.array(1.0), "reinhard")) == 0.5
    # Narkowicz's ACES fit x(2.51x + 0.03)/(x(2.43x + 0.59) + 0.14), values by hand
    assert np.isclose(float(da.tonemap(np.array(1.0), "aces")), 2.54 / 3.16, rtol=1e-14)
    assert np.isclose(float(da.tonemap(np.array(0.18), "aces")),
                      0.18 * 0.4818 / (0.18 * 1.0274 + 0.14), rtol=1e-14)
    assert np.isclose(float(da.tonemap_derivative(np.array(0.0), "aces")), 0.03 / 0.14,
                      rtol=1e-14)                             # T'(0) = b/e
    y = da.tonemap(np.linspace(0, 100, 1001), "aces")
    assert y[0] == 0 and y[-1] == 1.0 and np.all(np.diff(y) >= 0)
    assert (float(da.tonemap(np.array(0.5), "aces", exposure=2.0))
            == float(da.tonemap(np.array(1.0), "aces")))


# =========================================================================== variance of mixes
def test_mix_variance_of_a_linear_denoiser_by_monte_carlo():
    """z = (1 − α)x + α K x with x ~ N(μ, σ²): Var[z] = (1−α)²σ² + α² Σ K²σ² + 2α(1−α)K_ii σ²,
    the covariance being the divergence term; the NJS-style form without it is rejected."""
    rng = np.random.default_rng(4)
    shape = (16, 16, 1)
    s2 = 0.01 + 0.05 * rng.random(shape)
    f = denoisers.gaussian(0.8)
    K = f.kernels(shape)
    rr = K.shape[2] // 2
    alpha = rng.uniform(0.3, 0.7, shape)
    R = 4000
    x = 0.5 + np.sqrt(s2) * rng.standard_normal((R,) + shape)
    z = np.stack([(1 - alpha) * xi + alpha * f(xi) for xi in x])
    pix = (slice(1, None, 4), slice(1, None, 4), 0)          # 16 pixels, kernels disjoint
    var_y = kernel_variance(K, s2)
    cov = K[:, :, rr, rr][..., None] * s2
    pred = da.mix_variance(alpha, s2, var_y, cov_xy=cov)
    p = _chi2_var_pvalues(z[(slice(None),) + pix], pred[pix])
    assert p.min() > 0.01 / p.size, p                          # Bonferroni over 16 pixels
    p_njs = _chi2_var_pvalues(z[(slice(None),) + pix], da.mix_variance(alpha, s2, var_y)[pix])
    assert p_njs.min() < 1e-6                                   # power: the covariance matters


def test_njs_variance_of_independent_terms_by_monte_carlo():
    rng = np.random.default_rng(9)
    m = 12
    rho, alpha = rng.random(m), rng.random(m)
    va, vb, vx = rng.uniform(0.1, 2, m), rng.uniform(0.1, 2, m), rng.uniform(0.1, 2, m)
    R = 20000
    A = np.sqrt(va) * rng.standard_normal((R, m))
    B = np.sqrt(vb) * rng.standard_normal((R, m))
    X = np.sqrt(vx) * rng.standard_normal((R, m))
    comb = rho * (alpha * A + (1 - alpha) * B) + (1 - rho) * X
    p = _chi2_var_pvalues(comb, da.njs_variance(rho, alpha, va, vb, vx))
    assert p.min() > 0.01 / m
    # a single denoised image (α = 1) with ρ as the mixing parameter is mix_variance
    assert np.allclose(da.njs_variance(rho, 1.0, va, vb, vx), da.mix_variance(rho, vx, va))


# =========================================================================== the map
def _stats(scene="mixed", size=20, spp=8, seed=0):
    return ToyRenderer(scene, width=size, height=size).render_uniform(spp, seed=seed)


def test_density_is_eq3_blurred_for_a_kernel_denoiser():
    stt = _stats()
    f = denoisers.gaussian(1.0)
    dens, info = da.denoising_aware_density(stt, f, method="exact", extra_output=True)
    y = f(stt.mean.astype(np.float32)).astype(np.float64)
    var = kernel_variance(f.kernels(stt.mean.shape), stt.mean_var)
    raw = (var / ((stt.n[..., None] + 1.0) * (y * y + 0.01))).mean(axis=2)
    assert np.allclose(info["raw"], raw, rtol=1e-6)
    assert np.allclose(dens, gaussian_filter(np.maximum(raw, 0), 0.5, truncate=4.0), rtol=1e-6)
    tm, tinfo = da.denoising_aware_density(stt, f, method="exact", tonemap="reinhard",
                                           exposure=2.0, extra_output=True)
    d = da.tonemap_derivative(y, "reinhard", exposure=2.0)
    assert np.allclose(tinfo["raw"], (d * d * var / (stt.n[..., None] + 1.0)).mean(axis=2),
                       rtol=1e-6)


def test_density_mc_sure_variant_is_eq3_with_the_mc_sure_numerator():
    """variant="mc-sure" (Firmino 2023, "AS with MC-SURE"): the per-pixel MC-SURE of
    ``y = f(x)`` (Firmino 2022 Eq. 1, 2; Σ = the variance of the mean) replaces ``Var[f]``
    in Eq. 3; its negative values are clamped to 0 *before* the 17×17 σ = 4 blur.
    (i) Against mc_sure with the same probes.  (ii) Against the truth: for a linear
    denoiser ``E[SURE_i] = ((K − I)μ)_i² + Σ_j K_ij² σ_j²`` exactly (any noise law, as SURE
    is linear in σ̂² and the probes are unbiased), so over 40 renders of known truth the
    numerator's mean sits in its 99.9 % t interval around the exact image-mean MSE; the
    sample variance in place of the variance of the mean (8× here) is rejected."""
    f = denoisers.gaussian(1.0)
    stt = _stats(spp=8)
    dens, info = da.denoising_aware_density(stt, f, variant="mc-sure",
                                            rng=np.random.default_rng(3), extra_output=True)
    sure, sinfo = mc_sure(f, stt.mean, stt.mean_var, k=da.DEFAULT_K,
                          rng=np.random.default_rng(3), extra_output=True)
    y = sinfo["denoised"]
    raw = (sure / ((stt.n[..., None] + 1.0) * (y * y + 0.01))).mean(axis=2)
    assert raw.min() < 0 < raw.max()                  # the clamp matters here
    np.testing.assert_allclose(info["numerator"], sure, rtol=1e-12, atol=0)
    np.testing.assert_allclose(info["raw"], raw, rtol=1e-12, atol=0)
    np.testing.assert_allclose(dens, gaussian_filter(np.maximum(raw, 0), 4.0, truncate=2.0),
                               rtol=1e-12, atol=1e-300)
    # (ii) unbiased for the MSE of y, in the units of the variance of the mean
    r = ToyRenderer("mixed", width=20, height=20)
    mu = r.true_mean()
    K = f.kernels(mu.shape)
    exact = float((((f(mu.astype(np.float32)).astype(np.float64) - mu) ** 2)
                   + kernel_variance(K, r.true_var() / 8)).mean())
    means = []
    for seed in range(40):
        st = r.render_uniform(8, seed=500 + seed)
        _, inf = da.denoising_aware_density(st, f, variant="mc-sure", rng=seed, extra_output=True)
        means.append(inf["numerator"].mean())
    means = np.array(means)
    half = sst.t.ppf(0.9995, means.size - 1) * means.std(ddof=1) / np.sqrt(means.size)
    assert abs(means.mean() - exact) < half, (means.mean(), exact, half)


@pytest.mark.parametrize("variant,side", [("variance", 5), ("mc-sure", 17)])
def test_blur_footprints(variant, side):
    """5×5 σ = 0.5 for the variance, 17×17 σ = 4 for MC-SURE (Firmino 2023, notes)."""
    h = w = 31
    var = np.zeros((h, w, 3))
    var[15, 15] = 0.5                            # one noisy pixel, the rest exact
    stt = PixelStats.from_mean_var(np.full((h, w, 3), 0.5), var, np.full((h, w), 4))
    dens, info = da.denoising_aware_density(stt, denoisers.identity(), variant=variant,
                                            method="exact", rng=3, extra_output=True)
    assert info["raw"][15, 15] > 0
    ys, xs = np.nonzero(dens > 0)
    assert (ys.max() - ys.min() + 1, xs.max() - xs.min() + 1) == (side, side)


def test_progressive_output_uses_the_mix_variance_and_error():
    stt = _stats(spp=16)
    f = denoisers.gaussian(1.5)
    _, info = da.denoising_aware_density(stt, f, output="progressive", method="exact", rng=5,
                                         extra_output=True)
    z, p = progressive_denoise(stt, f, rng=np.random.default_rng(5), extra_output=True, k=4)
    var_y = kernel_variance(f.kernels(stt.mean.shape), stt.mean_var)
    assert np.allclose(info["output"], z)
    assert np.allclose(info["numerator"],
                       da.mix_variance(p["alpha_gated"], stt.mean_var, var_y,
                                       cov_xy=p["divergence"]))
    _, info2 = da.denoising_aware_density(stt, f, output="progressive", method="exact", rng=5,
                                          covariance=False, extra_output=True)
    assert np.allclose(info2["numerator"], da.mix_variance(p["alpha_gated"], stt.mean_var, var_y))
    _, info3 = da.denoising_aware_density(stt, f, output="progressive", variant="mc-sure", rng=5,
                                          extra_output=True)
    assert np.allclose(info3["numerator"], mix_error(p["alpha_gated"], stt.mean_var, p["sure"],
                                                     p["divergence"]))


def test_map_follows_the_oracle_map():
    """With a Gaussian denoiser, the estimated map ranks pixels like the map built from the
    true variance (Spearman, p < 1e-10)."""
    r = ToyRenderer("mixed", width=48, height=48)
    stt = r.render_uniform(16, seed=2)
    f = denoisers.gaussian(1.0)
    dens = da.denoising_aware_density(stt, f, method="exact")
    y = f(stt.mean.astype(np.float32)).astype(np.float64)
    true_var = kernel_variance(f.kernels(stt.mean.shape), r.true_var() / 16)
    oracle = gaussian_filter((true_var / (17 * (y * y + 0.01))).mean(axis=2), 0.5, truncate=4.0)
    rho, p = sst.spearmanr(dens.ravel(), oracle.ravel())
    assert rho > 0.5 and p < 1e-10, (rho, p)


def test_counts_hit_the_budget_exactly_and_are_reproducible():
    stt = _stats()
    for budget in (0, 1, 777, 12345):
        c = da.denoising_aware_map(stt, "gaussian", budget, rng=1)
        assert c.dtype == np.int64 and c.shape == stt.n.shape and int(c.sum()) == budget
        assert c.min() >= 0
    a, b = (da.denoising_aware_map(stt, "gaussian", 5000, rng=np.random.default_rng(8),
                                   variant="mc-sure") for _ in range(2))
    assert np.array_equal(a, b)


# =========================================================================== adaptive loop
def test_sampler_in_the_adaptive_loop_rebuilds_the_denoiser():
    r = ToyRenderer("mixed", width=24, height=24)
    seen = []

    def factory(stats):
        seen.append(int(stats.n.sum()))
        return denoisers.gem(stats.mean_var)

    res = adaptive_render(r, 8, sampler=da.denoising_aware_sampler(factory, k=2), iterations=3)
    assert int(res.stats.n.sum()) == 8 * 24 * 24
    assert len(seen) == 3 and seen == sorted(seen) and seen[0] == 4 * 24 * 24
    res2 = adaptive_render(r, 8, sampler=da.sampler, iterations=2, denoiser="gem", tonemap="aces")
    assert int(res2.stats.n.sum()) == 8 * 24 * 24


def test_denoising_aware_oidn_beats_uniform_oidn_at_equal_budget():
    """Toy `mixed` 64×64 at 16 spp, five seeds: relMSE of OIDN after denoising-aware
    sampling vs after uniform sampling (paired by seed; one-sided t-test on log ratios)."""
    pytest.importorskip("pyoidn")
    r = ToyRenderer("mixed", width=64, height=64)
    mu = r.true_mean()
    logs = []
    for seed in range(5):
        uni = r.render_uniform(16, seed=100 + seed)
        eu = relmse(bind_denoiser("oidn", uni)(uni.mean.astype(np.float32)), mu)
        res = adaptive_render(r, 16, sampler=da.denoising_aware_sampler("oidn"), seed=seed)
        ea = relmse(bind_denoiser("oidn", res.stats)(res.stats.mean.astype(np.float32)), mu)
        logs.append(np.log(ea / eu))
    p = sst.ttest_1samp(logs, 0.0, alternative="less").pvalue
    assert p < 0.05, (np.exp(logs), p)


def test_da_progressive_render_is_bitwise_reproducible_on_any_thread_count():
    """The DA+progressive path of the quality table (map of the progressive output with OIDN,
    then progressive denoising) twice with one seed, and again on one numba thread: the same
    counts, means and image to the bit (docs/quality.md, "DA+progressive reproducibility")."""
    import numba

    pytest.importorskip("pyoidn")
    r = ToyRenderer("mixed", width=32, height=24)
    before = numba.get_num_threads()
    runs = []
    try:
        for nt in (before, before, 1):
            numba.set_num_threads(nt)
            st = adaptive_render(r, 16, sampler="denoising-aware", initial_spp=4, seed=5,
                                 iterations=3, denoiser="oidn", output="progressive").stats
            runs.append((st.n, st.mean, progressive_denoise(st, "oidn", rng=0)))
    finally:
        numba.set_num_threads(before)
    for run in runs[1:]:
        for p, q in zip(runs[0], run):
            assert p.tobytes() == q.tobytes()


# =========================================================================== bad input
def test_bad_input_raises_input_error():
    stt = _stats(size=8)
    f = denoisers.gaussian(1.0)
    with pytest.raises(InputError, match="`variant`"):
        da.denoising_aware_density(stt, f, variant="error")
    with pytest.raises(InputError, match="`output`"):
        da.denoising_aware_density(stt, f, output="combined")
    with pytest.raises(InputError, match="`tonemap`"):
        da.denoising_aware_density(stt, f, tonemap="filmic")
    with pytest.raises(InputError, match="`exposure`"):
        da.denoising_aware_density(stt, f, exposure=0)
    with pytest.raises(InputError, match="`eps`"):
        da.denoising_aware_density(stt, f, eps=-1)
    with pytest.raises(InputError, match="`k`"):
        da.denoising_aware_density(stt, f, k=0)
    with pytest.raises(InputError, match="`blur`"):
        da.denoising_aware_density(stt, f, blur=(1.0,))
    with pytest.raises(InputError, match="`progressive_options`"):
        da.denoising_aware_density(stt, f, output="progressive", progressive_options=[1])
    with pytest.raises(InputError, match="must not set 'mean_var'"):
        da.denoising_aware_density(stt, f, output="progressive",
                                   progressive_options={"mean_var": stt.mean_var})
    with pytest.raises(InputError, match="`stats`"):
        da.denoising_aware_density(stt.mean, f)
    few = PixelStats.from_mean_var(stt.mean, stt.sample_var, np.ones((8, 8)))
    with pytest.raises(InputError, match=">= 2 samples"):
        da.denoising_aware_density(few, f)
    with pytest.raises(InputError, match="`budget`"):
        da.denoising_aware_map(stt, f, -5)
    with pytest.raises(InputError, match="`denoiser_factory`"):
        da.denoising_aware_sampler("bm3d")
    with pytest.raises(InputError, match="`denoiser`"):
        da.sampler(stt, 10, None, denoiser=3)
    with pytest.raises(InputError, match="`tonemap`"):
        da.tonemap(np.ones(3), "filmic")


def test_variance_formulas_and_tonemap_refuse_bad_input():
    """mix_variance, njs_variance and the tone maps turned NaN, Inf and negative variances
    into NaN or a number, and mismatched shapes into NumPy broadcasting errors."""
    v = np.full((4, 5, 3), 0.1)
    assert da.mix_variance(0.3, v, v, cov_xy=0.0).shape == v.shape  # scalars broadcast
    with pytest.raises(InputError, match="`var_y` must be >= 0"):
        da.mix_variance(0.3, v, -v)
    with pytest.raises(InputError, match="`cov_xy` holds 0 NaN and 60 Inf"):
        da.mix_variance(0.3, v, v, cov_xy=v * np.inf)
    with pytest.raises(InputError, match="broadcast together"):
        da.njs_variance(0.5, 0.5, v, v[:, :-1], v)
    with pytest.raises(InputError, match="`var_x` must be >= 0"):
        da.njs_variance(0.5, 0.5, v, v, -v)
    for f in (da.tonemap, da.tonemap_derivative):
        with pytest.raises(InputError, match="`image` holds 1 NaN"):
            f(np.array([0.5, np.nan]))


# --------------------------------------------------------------- properties on any image
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402


def _any_stats(seed, h, w, c, scale, zero_frac, n):
    """Statistics of ``n`` samples per pixel of a non-negative :func:`any_image`."""
    m, v = any_image(seed, h, w, c, scale, zero_frac, nonneg=True)
    return PixelStats.from_mean_var(m, v, np.full((h, w), n))


_ANY = image_args(9)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(denoiser=st.sampled_from(["gaussian", "gem"]), variant=st.sampled_from(["variance", "mc-sure"]),
       output=st.sampled_from(["denoised", "progressive"]), tm=st.sampled_from([None, "aces"]),
       n=st.sampled_from([2, 64]), budget_per_pixel=st.sampled_from([0, 1, 4]),
       extra=st.integers(0, 30), **_ANY)
def test_density_is_non_negative_and_the_map_meets_the_budget_on_any_image(
        seed, h, w, c, scale, zero_frac, denoiser, variant, output, tm, n, budget_per_pixel,
        extra):
    # Eq. 3 of the notes clamps at 0 and blurs with non-negative weights: a finite (H, W)
    # density >= 0; the integer map meets the budget exactly with counts >= 0, also for
    # black or noiseless images and budgets below the pixel count.
    stt = _any_stats(seed, h, w, c, scale, zero_frac, n)
    kw = dict(variant=variant, output=output, tonemap=tm, k=2, rng=seed)
    d = da.denoising_aware_density(stt, denoiser, **kw)
    assert d.shape == (h, w) and d.dtype == np.float64 and np.isfinite(d).all() and d.min() >= 0
    budget = budget_per_pixel * h * w + extra
    counts = da.denoising_aware_map(stt, denoiser, budget, **kw)
    assert counts.shape == (h, w) and counts.min() >= 0 and int(counts.sum()) == budget


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["aces", "reinhard"]), exposure=st.sampled_from([1e-20, 1.0, 1e15]),
       scale=st.sampled_from([0.0, 1e-20, 1.0, 1e15]), seed=st.integers(0, 2 ** 31),
       a=st.floats(0, 1), rho=st.floats(-1, 1))
def test_tone_curves_and_mix_variances_on_any_values(name, exposure, scale, seed, a, rho):
    # The tone curves map into [0, 1], are non-decreasing with non-negative derivatives (0
    # where ACES is clamped at 1);
    # the variance of (1 − α) x + α y with |Cov| <= √(Var x Var y) and α in [0, 1] is
    # in [0, max(Var x, Var y)] (a convex function of α, 0 <= at the ends).
    rng = np.random.default_rng(seed)
    x = np.sort(rng.normal(size=50) * scale * rng.gamma(0.5, 1, size=50))
    t = da.tonemap(x, name, exposure=exposure)
    d = da.tonemap_derivative(x, name, exposure=exposure)
    assert np.isfinite(t).all() and t.min() >= 0 and t.max() <= 1 and (np.diff(t) >= 0).all()
    assert np.isfinite(d).all() and d.min() >= 0
    if name == "aces":
        assert not d[t >= 1].any()                  # the clamped top has no slope
    vx = rng.gamma(0.3, 1, size=50) * scale ** 2
    vy = rng.gamma(0.3, 1, size=50) * scale ** 2
    cov = rho * np.sqrt(vx * vy)
    for mv in (da.mix_variance(a, vx, vy), da.mix_variance(a, vx, vy, cov_xy=cov)):
        assert np.isfinite(mv).all()
        top = np.maximum(vx, vy)
        assert (mv >= -1e-12 * top).all() and (mv <= top * (1 + 1e-12)).all()
