"""Tests of the analytic toy renderer: its samples follow the advertised closed forms.

Statistical checks use fixed seeds and real p-values at level ``ALPHA`` with a
Bonferroni correction over the tests made together; on failure the assertion message
lists the offending statistics.
"""

from __future__ import annotations

import doctest
import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats as sps

import statmc.toy as toy
from statmc.errors import InputError
from statmc.stats import PixelStats
from statmc.toy import FAMILIES, ToyRenderer, sample_throughput, throughput_central_moments

ALPHA = 1e-3
SIZE = 32
SPP = 4096
SCENES = list(ToyRenderer.scenes())


@functools.lru_cache(maxsize=None)
def converged(scene):
    """(renderer, stats) at SPP samples per pixel, rendered once per test session."""
    r = ToyRenderer(scene, width=SIZE, height=SIZE)
    return r, r.render_uniform(SPP, seed=12345)


def z_mean(stats, r):
    """Standardised mean errors ``(mean − μ)/sqrt(σ²/n)`` (N(0, 1) by the CLT)."""
    return (stats.mean - r.true_mean()) / np.sqrt(r.true_var() / stats.n[..., None])


def z_sample_var(stats, r):
    """Standardised sample-variance errors, exact mean 0 and variance 1.

    ``Var[s²] = (μ4 − σ⁴ (n − 3)/(n − 1))/n`` for the unbiased sample variance ``s²``.
    """
    n = stats.n[..., None].astype(float)
    var = r.true_var()
    m4 = r.true_central_moment(4)
    var_s2 = (m4 - var ** 2 * (n - 3) / (n - 1)) / n
    return (stats.sample_var - var) / np.sqrt(var_s2)


def ks_normal(z):
    return sps.kstest(np.ravel(z), "norm").pvalue


def ks_uniform(u):
    return sps.kstest(np.ravel(u), "uniform").pvalue


def aggregate_p(z):
    """Two-sided p-value of ``Σz/sqrt(P)`` for P independent z with mean 0, variance 1."""
    z = np.ravel(z)
    return 2 * sps.norm.sf(abs(z.sum()) / np.sqrt(z.size))


# ---------------------------------------------------------------------------- closed forms
def test_scene_list_and_defaults():
    names = ToyRenderer.scenes()
    assert {"mixed", "constant", "edges", "gradient"} <= set(names)
    assert all(isinstance(v, str) and v for v in names.values())
    r = ToyRenderer()
    assert (r.height, r.width, r.channels, r.name) == (64, 64, 3, "toy:mixed")
    # the default scene really holds all four ingredients
    assert set(np.unique(r.family)) == {toy.GAUSSIAN, toy.UNIFORM, toy.GAMMA, toy.FIREFLY}


@pytest.mark.parametrize("scene", SCENES)
def test_truth_is_a_radiance_with_noise_spanning_4_to_4096_spp(scene):
    r = ToyRenderer(scene)
    mu, var = r.true_mean(), r.true_var()
    assert mu.shape == var.shape == (64, 64, 3) and mu.dtype == var.dtype == np.float64
    assert mu.min() > 0 and var.min() > 0
    rel_sd = np.sqrt(var) / mu  # relative standard deviation of ONE sample
    assert np.median(rel_sd / np.sqrt(4)) > 0.2, "4 spp should be very noisy"
    if scene != "fireflies":
        assert np.median(rel_sd / np.sqrt(4096)) < 0.02, "4096 spp should be nearly converged"


def test_firefly_closed_form_equals_two_point_enumeration():
    """Firefly law: value v/p with prob. p, else 0 -> mean v, variance v²(1−p)/p."""
    for p in [1e-3, 0.01, 0.05, 0.3, 0.5, 0.9, 1.0]:
        support = np.array([0.0, 1.0 / p]) - 1.0  # deviations of S from its mean 1
        prob = np.array([1 - p, p])
        assert np.isclose((prob * (support + 1)).sum(), 1.0, rtol=1e-14)
        var, m3, m4 = throughput_central_moments(np.array([toy.FIREFLY]), p)
        for k, got in [(2, var), (3, m3), (4, m4)]:
            assert np.isclose(got[0], (prob * support ** k).sum(), rtol=1e-12, atol=1e-12), (p, k)
        v = 0.7  # a radiance
        assert np.isclose(v ** 2 * var[0], v ** 2 * (1 - p) / p, rtol=1e-12, atol=0)
    r = ToyRenderer("fireflies", width=16, height=16)
    p = r.family_param[..., None]
    mu = r.true_mean()
    np.testing.assert_allclose(r.true_var(), mu ** 2 * (1 - p) / p, rtol=1e-12)
    # the samples take only the values 0 and v/p
    idx = np.repeat(np.arange(256), 200)
    x = r.sample_values(idx, 7)
    hit = x[:, 0] > 0
    np.testing.assert_allclose(x[hit], (mu.reshape(256, 3) / p.reshape(256, 1))[idx[hit]], rtol=1e-12)
    assert np.all(x[~hit] == 0)


def test_firefly_counts_are_exactly_binomial():
    """Exact test: the number K of fireflies in a pixel is Binomial(n, p).

    The pixel mean is v K/(n p), so K is recovered from the rendered mean; a randomised
    probability-integral transform of a discrete law is exactly uniform.
    """
    r, s = converged("fireflies")
    p = r.family_param
    k_float = s.mean[..., 0] * s.n * p / r.true_mean()[..., 0]
    k = np.round(k_float)
    assert np.abs(k_float - k).max() < 1e-6
    rng = np.random.default_rng(3)
    u = sps.binom.cdf(k - 1, s.n, p) + rng.random(k.shape) * sps.binom.pmf(k, s.n, p)
    pval = ks_uniform(u)
    assert pval > ALPHA, f"binomial PIT KS p = {pval:.3g}"


CASES = [(toy.CONST, 0.0), (toy.GAUSSIAN, 0.5), (toy.UNIFORM, 1.0), (toy.GAMMA, 0.7),
         (toy.GAMMA, 3.0), (toy.FIREFLY, 0.05), (toy.FIREFLY, 0.3)]


def test_throughput_moments_match_monte_carlo():
    """Batch-means t-tests of E[(S−1)^k], k = 1..4, against the closed forms.

    With the mean known (1), the average of (S−1)^k is unbiased; 64 batches of 2^15 draws
    give nearly normal batch averages, so a one-sample t-test is valid.
    """
    rng = np.random.default_rng(2024)
    batches, per = 64, 1 << 15
    pvals = {}
    for fam, par in CASES:
        s = sample_throughput(np.full(batches * per, fam), par, rng).reshape(batches, per)
        assert s.shape == (batches, per)
        var, m3, m4 = throughput_central_moments(np.array([fam]), par)
        for k, truth in [(1, 0.0), (2, var[0]), (3, m3[0]), (4, m4[0])]:
            est = ((s - 1.0) ** k).mean(axis=1)
            if fam == toy.CONST:
                assert np.all(est == 0)
                continue
            pvals[(FAMILIES[fam], par, k)] = sps.ttest_1samp(est, truth).pvalue
    worst = min(pvals, key=pvals.get)
    assert pvals[worst] > ALPHA / len(pvals), f"worst {worst}: p = {pvals[worst]:.3g}"


def test_throughput_support():
    rng = np.random.default_rng(0)
    assert np.all(sample_throughput(np.full(10000, toy.GAMMA), 0.5, rng) >= 0)
    u = sample_throughput(np.full(10000, toy.UNIFORM), 0.8, rng)
    assert u.min() >= 0.2 and u.max() <= 1.8
    assert np.all(sample_throughput(np.full(5, toy.CONST), 0.0, rng) == 1)
    with pytest.raises(InputError, match="param"):
        throughput_central_moments(np.array([toy.FIREFLY]), 1.5)
    with pytest.raises(InputError, match="param"):
        sample_throughput(np.array([toy.GAMMA]), 0.0, rng)
    with pytest.raises(InputError, match="family"):
        sample_throughput(np.array([7]), 1.0, rng)
    with pytest.raises(InputError, match="family"):
        throughput_central_moments(np.array([1.0]), 1.0)


@pytest.mark.parametrize("scene, pixel", [("mixed", (5, 5)), ("mixed", (10, 40)),
                                          ("mixed", (40, 12)), ("mixed", (50, 50)),
                                          ("constant", (3, 3))])
def test_pixel_moments_and_covariance_match_samples(scene, pixel):
    """Central moments 2–4 per channel and the channel covariance of one pixel's samples."""
    r = ToyRenderer(scene)
    flat = pixel[0] * r.width + pixel[1]
    batches, per = 64, 1 << 14
    x = r.sample_values(np.full(batches * per, flat), 99).reshape(batches, per, 3)
    d = x - r.true_mean()[pixel]
    pvals = {}
    for order in (2, 3, 4):
        truth = r.true_central_moment(order)[pixel]
        est = (d ** order).mean(axis=1)  # (batches, C), unbiased as the mean is known
        for c in range(3):
            if np.all(est[:, c] == truth[c]):  # e.g. odd moments of Gaussian pixels are 0
                continue
            pvals[(order, c)] = sps.ttest_1samp(est[:, c], truth[c]).pvalue
    cov = r.true_cov()[pixel]
    np.testing.assert_allclose(np.diagonal(cov), r.true_var()[pixel], rtol=1e-12)
    est = (d[..., 0] * d[..., 2]).mean(axis=1)
    pvals["cov02"] = sps.ttest_1samp(est, cov[0, 2]).pvalue
    worst = min(pvals, key=pvals.get)
    assert pvals[worst] > ALPHA / len(pvals), f"{scene} {pixel} worst {worst}: p = {pvals[worst]:.3g}"


# ---------------------------------------------------------------------------- rendered images
@pytest.mark.parametrize("scene", SCENES)
def test_rendered_means_match_true_mean(scene):
    """KS test of z = (mean − μ)/sqrt(σ²/n) against N(0, 1) per channel, and per family.

    z is N(0, 1) only up to the CLT; at n = 4096 its skewness is at most
    ≈ 9.9/64 = 0.15 (firefly pixels with p = 0.01), which moves the CDF by ≤ 0.01, far
    below the KS critical distance 0.065 for 1024 pixels.
    """
    r, s = converged(scene)
    z = z_mean(s, r)
    pvals = {("ks", c): ks_normal(z[..., c]) for c in range(3)}
    for f in np.unique(r.family):
        for c in range(3):
            pvals[(FAMILIES[f], c)] = aggregate_p(z[r.family == f, c])
    worst = min(pvals, key=pvals.get)
    assert pvals[worst] > ALPHA / len(pvals), f"{scene}: worst {worst} p = {pvals[worst]:.3g}"


@pytest.mark.parametrize("scene", SCENES)
def test_rendered_sample_variances_match_true_var(scene):
    """Per family region and channel: Σz/sqrt(P) for z = (s² − σ²)/sd(s²) is N(0, 1).

    Each z has exact mean 0 and variance 1 (sd from the 4th central moment), pixels are
    independent, so the sum over a region is normal to a very good approximation.
    """
    r, s = converged(scene)
    z = z_sample_var(s, r)
    pvals = {}
    for f in np.unique(r.family):
        for c in range(3):
            pvals[(FAMILIES[f], c)] = aggregate_p(z[r.family == f, c])
    worst = min(pvals, key=pvals.get)
    assert pvals[worst] > ALPHA / len(pvals), f"{scene}: worst {worst} p = {pvals[worst]:.3g}"
    # and the average relative error of the variance is small in absolute terms
    assert abs(np.mean(s.sample_var / r.true_var()) - 1) < 0.05


@pytest.mark.parametrize("scene, where", [("constant", None), ("mixed", "gaussian")])
def test_gaussian_pixels_chi2(scene, where):
    """Gaussian pixels: (n−1) s²/σ² ~ χ²(n−1) and the mean ~ N(μ, σ²/n), exactly."""
    r, s = converged(scene)
    mask = np.ones(r.family.shape, bool) if where is None else r.family == toy.GAUSSIAN
    n = s.n[mask][:, None]
    u = sps.chi2.cdf((n - 1) * s.sample_var[mask] / r.true_var()[mask], n - 1)
    pvals = [ks_uniform(u[:, c]) for c in range(3)]
    pvals += [ks_normal(z_mean(s, r)[mask][:, c]) for c in range(3)]
    assert min(pvals) > ALPHA / len(pvals), pvals


def test_gamma_pixel_means_exact():
    """Exponential/gamma pixels: the mean of n Gamma(k, 1/k) is Gamma(nk, 1/(nk))·μ exactly."""
    r, s = converged("edges")
    k = r.family_param
    ratio = s.mean[..., 0] / r.true_mean()[..., 0]
    u = sps.gamma.cdf(ratio, a=s.n * k, scale=1 / (s.n * k))
    pval = ks_uniform(u)
    assert pval > ALPHA, f"gamma PIT KS p = {pval:.3g}"


def test_render_matches_reference_statistics():
    """The fast shifted-sum statistics equal the two-pass reference on the same samples."""
    r = ToyRenderer("mixed", width=24, height=20)
    counts = np.random.default_rng(1).integers(0, 40, (20, 24))
    counts[3, :5] = [0, 1, 2, 0, 1]
    fast = r.render(counts, seed=8)
    idx = np.repeat(np.arange(counts.size), counts.ravel())
    ref = PixelStats.from_pixel_samples(idx, r.sample_values(idx, 8), (20, 24))
    np.testing.assert_array_equal(fast.n, ref.n)
    np.testing.assert_allclose(fast.mean, ref.mean, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(fast.m2, ref.m2, rtol=1e-9, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 6), w=st.integers(1, 6), hi=st.integers(0, 9), seed=st.integers(0, 2**31))
def test_exact_counts_random_maps(h, w, hi, seed):
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, hi + 1, (h, w)) * (rng.random((h, w)) < 0.6)
    r = ToyRenderer("mixed", width=w, height=h)
    s = r.render(counts, seed=seed, chunk_size=int(rng.integers(1, 20)))
    np.testing.assert_array_equal(s.n, counts)
    assert s.n.dtype == np.int64
    assert np.all(s.mean[counts == 0] == 0) and np.all(s.m2[counts == 0] == 0)
    assert np.all(s.m2 >= 0)


def test_exact_counts_large_map_and_float_counts():
    r = ToyRenderer("mixed")
    rng = np.random.default_rng(4)
    counts = rng.poisson(rng.gamma(0.5, 40, (64, 64)))
    counts[rng.random((64, 64)) < 0.2] = 0
    counts[0, 0] = 20000  # one pixel spanning several chunks
    s = r.render(counts, seed=1, chunk_size=5000)
    np.testing.assert_array_equal(s.n, counts)
    assert s.total_samples == counts.sum()
    s2 = r.render(counts.astype(np.float32), seed=1, chunk_size=5000)
    np.testing.assert_array_equal(s2.mean, s.mean)
    empty = r.render(np.zeros((64, 64)), seed=0)
    assert empty.total_samples == 0 and np.all(empty.mean == 0)
    assert r.render_uniform(0).total_samples == 0


def test_same_seed_identical_and_features():
    r = ToyRenderer("mixed", width=16, height=12)
    a, b = r.render_uniform(8, seed=5), r.render_uniform(8, seed=5)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.m2, b.m2)
    assert a.meta["scene"] == "mixed" and a.meta["seed"] == 5
    np.testing.assert_array_equal(r.sample_values(np.arange(50), 3), r.sample_values(np.arange(50), 3))
    assert a.albedo.shape == a.normal.shape == (12, 16, 3) and a.depth.shape == (12, 16)
    np.testing.assert_allclose(np.linalg.norm(a.normal, axis=-1), 1, rtol=1e-6)
    c = r.render_uniform(8, seed=5, features=False)
    assert c.albedo is None and c.normal is None and c.depth is None
    np.testing.assert_array_equal(c.mean, a.mean)


def test_different_seeds_independent():
    """Fisher-z test that z-scores of two seeds are uncorrelated, per channel."""
    r = ToyRenderer("mixed", width=SIZE, height=SIZE)
    z1 = z_mean(r.render_uniform(64, seed=0), r)
    z2 = z_mean(r.render_uniform(64, seed=1), r)
    assert not np.array_equal(z1, z2)
    pvals = []
    for c in range(3):
        rho = np.corrcoef(z1[..., c].ravel(), z2[..., c].ravel())[0, 1]
        stat = np.arctanh(rho) * np.sqrt(z1[..., c].size - 3)
        pvals.append(2 * sps.norm.sf(abs(stat)))
    assert min(pvals) > ALPHA / 3, pvals
    # generators passed in are consumed, so successive draws differ
    g = np.random.default_rng(0)
    assert not np.array_equal(r.sample_values(np.arange(10), g), r.sample_values(np.arange(10), g))


@pytest.mark.parametrize("scene", ["edges", "texture", "fireflies"])
def test_chunking_is_exact_for_single_stream_scenes(scene):
    """Where a chunk's draws are a plain continuation of the stream, chunked = unchunked."""
    r = ToyRenderer(scene, width=16, height=16)
    counts = np.random.default_rng(0).integers(0, 300, (16, 16))
    a = r.render(counts, seed=3, chunk_size=997)
    b = r.render(counts, seed=3)
    np.testing.assert_array_equal(a.n, b.n)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(a.m2, b.m2, rtol=1e-9, atol=1e-12 * b.m2.max())


def test_chunked_render_same_distribution():
    """Mixed scene with chunks splitting pixels: same law (KS vs N(0,1), two-sample KS)."""
    r = ToyRenderer("mixed", width=SIZE, height=SIZE)
    chunked = r.render_uniform(256, seed=21, chunk_size=4099)
    whole = r.render_uniform(256, seed=22)
    np.testing.assert_array_equal(chunked.n, whole.n)
    zc, zw = z_mean(chunked, r), z_mean(whole, r)
    vc, vw = z_sample_var(chunked, r), z_sample_var(whole, r)
    pvals = [ks_normal(zc[..., c]) for c in range(3)]
    pvals += [sps.ks_2samp(zc[..., c].ravel(), zw[..., c].ravel()).pvalue for c in range(3)]
    pvals += [sps.ks_2samp(vc[..., c].ravel(), vw[..., c].ravel()).pvalue for c in range(3)]
    pvals += [aggregate_p(vc[r.family == f, c]) for f in np.unique(r.family) for c in range(3)]
    assert min(pvals) > ALPHA / len(pvals), pvals


def test_features_follow_image_edges():
    """Wherever the mean jumps between neighbours, albedo or normal jumps too."""
    for scene in ["mixed", "edges", "texture"]:
        r = ToyRenderer(scene)
        mu = r.true_mean()
        f = np.concatenate([r.features()["albedo"], r.features()["normal"]], -1).astype(float)
        for ax in (0, 1):
            jump = (np.abs(np.diff(mu, axis=ax)) > 0.05 * mu.max()).any(-1)
            fjump = (np.abs(np.diff(f, axis=ax)) > 1e-3).any(-1)
            assert jump.any()
            assert np.all(fjump[jump]), f"{scene}: {int((jump & ~fjump).sum())} unexplained edges"


@pytest.mark.parametrize("channels", [1, 2, 5])
def test_other_channel_counts(channels):
    r = ToyRenderer("mixed", width=8, height=8, channels=channels)
    s = r.render_uniform(4, seed=0)
    assert s.mean.shape == r.true_mean().shape == r.true_var().shape == (8, 8, channels)
    assert r.true_cov().shape == (8, 8, channels, channels)
    assert s.albedo.shape == (8, 8, 3)
    assert r.true_mean().min() > 0


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("counts, match", [
    (np.ones((4, 5)), "shape"),
    (np.ones(20), "dimensions"),
    (np.ones((5, 4, 1)), "dimensions"),
    (-np.ones((5, 4)), ">= 0"),
    (np.full((5, 4), 1.5), "whole"),
    (np.full((5, 4), np.nan), "NaN"),
    (np.full((5, 4), np.inf), "Inf"),
    (np.full((5, 4), "a"), "numeric"),
    (np.full((5, 4), 2**31), r"below 2\*\*31 .*got max 2147483648"),
    (np.full((5, 4), 2**40), r"below 2\*\*31"),
])
def test_bad_counts(counts, match):
    r = ToyRenderer("mixed", width=4, height=5)
    with pytest.raises(InputError, match=match):
        r.render(counts)


def test_counts_up_to_the_bound_are_taken():
    # check only: a render of 2**31 - 1 samples per pixel would take hours
    r = ToyRenderer("mixed", width=4, height=5)
    n = r.check_counts(np.full((5, 4), 2**31 - 1))
    assert n.dtype == np.int64 and (n == 2**31 - 1).all()


@pytest.mark.parametrize("kwargs, match", [
    (dict(scene="nope"), "scene"), (dict(scene=3), "scene"),
    (dict(width=0), "width"), (dict(height=-2), "height"), (dict(width=2.5), "width"),
    (dict(channels=0), "channels"), (dict(width=True), "width"),
])
def test_bad_constructor(kwargs, match):
    with pytest.raises(InputError, match=match):
        ToyRenderer(**kwargs)


def test_bad_options():
    r = ToyRenderer("constant", width=4, height=4)
    for spp in (-1, 2.5, "8", None):
        with pytest.raises(InputError, match="spp"):
            r.render_uniform(spp)
    with pytest.raises(InputError, match="chunk_size"):
        r.render_uniform(4, chunk_size=0)
    for idx, match in [(np.array([16]), r"\[0, 16\)"), (np.array([-1]), r"\[0, 16\)"),
                       (np.zeros((2, 2), int), "1-D"), (np.array([0.5]), "integer")]:
        with pytest.raises(InputError, match=match):
            r.sample_values(idx, 0)
    with pytest.raises(InputError, match="order"):
        r.true_central_moment(5)


def test_docstring_examples():
    result = doctest.testmod(toy, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 2 and result.failed == 0


def test_identical_samples_have_zero_m2():
    """Regression: firefly pixels without a hit (all samples 0) must have M2 = 0 exactly."""
    r = ToyRenderer("fireflies", width=8, height=8)
    s = r.render_uniform(3, seed=0)
    none = s.mean[..., 0] == 0
    assert none.any()
    assert np.all(s.m2[none] == 0) and np.all(s.sample_var[none] == 0)


# ---------------------------------------------------------------------------- channel covariance
def test_render_channel_covariance_matches_reference_and_chunking():
    """The shifted-sum co-moment equals the two-pass reference on the same samples, and
    chunked renders merge it exactly."""
    r = ToyRenderer("mixed", width=24, height=20)
    counts = np.random.default_rng(1).integers(0, 40, (20, 24))
    counts[3, :5] = [0, 1, 2, 0, 1]
    fast = r.render(counts, seed=8)
    idx = np.repeat(np.arange(counts.size), counts.ravel())
    ref = PixelStats.from_pixel_samples(idx, r.sample_values(idx, 8), (20, 24))
    scale = ref.m2.max()
    np.testing.assert_allclose(fast.m2_cross, ref.m2_cross, rtol=1e-9, atol=1e-12 * scale)
    k = np.arange(3)
    assert np.array_equal(fast.m2_cross[..., k, k], fast.m2)
    r2 = ToyRenderer("edges", width=16, height=16)
    counts = np.random.default_rng(0).integers(0, 300, (16, 16))
    a, b = r2.render(counts, seed=3, chunk_size=997), r2.render(counts, seed=3)
    np.testing.assert_allclose(a.m2_cross, b.m2_cross, rtol=1e-9, atol=1e-12 * b.m2.max())
    # all-equal runs (firefly pixels without a hit) have zero cross terms exactly
    s = ToyRenderer("fireflies", width=8, height=8).render_uniform(3, seed=0)
    none = s.mean[..., 0] == 0
    assert none.any() and np.all(s.m2_cross[none] == 0)


@pytest.mark.parametrize("scene, where", [("constant", None), ("mixed", "gaussian")])
def test_rendered_sample_covariance_matches_true_cov(scene, where):
    """Gaussian pixels are exactly normal, so the sample covariance is Wishart:
    ``E[s_ab] = Σ_ab``, ``Var[s_ab] = (Σ_aa Σ_bb + Σ_ab²)/(n − 1)``.  Per channel pair,
    Σz/sqrt(P) over the pixels is N(0, 1) (Bonferroni over the 6 pairs).  Power: the
    diagonal covariance (zero cross terms) is rejected on the correlated ``mixed`` pixels."""
    r, s = converged(scene)
    mask = np.ones(r.family.shape, bool) if where is None else r.family == toy.GAUSSIAN
    cov = r.true_cov()[mask]
    n = s.n[mask].astype(float)[:, None, None]
    d = np.diagonal(cov, axis1=1, axis2=2)
    sd = np.sqrt((d[:, :, None] * d[:, None, :] + cov ** 2) / (n - 1))
    iu = np.triu_indices(3)
    z = ((s.sample_cov[mask] - cov) / sd)[:, iu[0], iu[1]]
    pvals = [aggregate_p(z[:, p]) for p in range(z.shape[1])]
    assert min(pvals) > ALPHA / len(pvals), pvals
    if where is not None:
        diag_only = cov * np.eye(3)
        z_diag = ((s.sample_cov[mask] - diag_only) / sd)[:, [0, 0, 1], [1, 2, 2]]
        assert max(2 * sps.norm.sf(abs(z_diag[:, p].sum()) / np.sqrt(z_diag.shape[0]))
                   for p in range(3)) < ALPHA / 3


# ---------------------------------------------------------------------------- rounding
NONNEGATIVE_SCENES = ["edges", "gradient", "texture", "fireflies"]  # no Gaussian noise, w <= 1


def _sample_range(r, counts, seed):
    """Per-pixel min and max of the very samples ``render(counts, seed=seed)`` draws
    (one stream: :meth:`ToyRenderer.sample_values` with the same seed)."""
    idx = np.repeat(np.arange(counts.size), counts.ravel())
    x = r.sample_values(idx, seed)
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    lo = np.full((counts.size, r.channels), np.inf)
    hi = np.full((counts.size, r.channels), -np.inf)
    lo[idx[starts]] = np.minimum.reduceat(x, starts)
    hi[idx[starts]] = np.maximum.reduceat(x, starts)
    h, w = counts.shape
    return x, lo.reshape(h, w, -1), hi.reshape(h, w, -1)


def _check_in_range(s, lo, hi):
    seen = s.n > 0
    out = seen[..., None] & ((s.mean < lo) | (s.mean > hi))
    assert not out.any(), (f"{int(out.sum())} means outside their samples' range, e.g. mean "
                           f"{s.mean[out][:3]} vs [{lo[out][:3]}, {hi[out][:3]}]")
    flat = seen[..., None] & (lo == hi)
    assert np.array_equal(s.mean[flat], lo[flat]), "all-equal pixels must have that mean exactly"
    assert np.all(s.m2[flat] == 0)
    rows = np.moveaxis(s.m2_cross, -1, -2)  # rows[..., a, :] is column a
    assert np.all(s.m2_cross[flat] == 0) and np.all(rows[flat] == 0)
    return int(flat.sum())


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("spp, seed", [(1, 0), (3, 1), (16, 2), (16, 3), (64, 4)])
def test_means_never_leave_their_samples_range(scene, spp, seed):
    """Regression (fresh-clone trial): ``mean = μ + Σd/n`` left a firefly pixel without a
    hit (every sample exactly 0) at ``−1e-16``, a negative radiance that made every toy
    render useless as a logLoss reference (``toy:mixed`` 32x32 16 spp: 95 such pixels,
    ``toy:fireflies``: 1856).  Now each mean lies in ``[min x, max x]`` of its pixel's
    samples, an all-equal pixel has exactly that value with ``M2 = 0`` and zero cross
    terms, and non-negative scenes have non-negative means."""
    r = ToyRenderer(scene, width=24, height=20)
    counts = np.full((20, 24), spp)
    s = r.render(counts, seed=seed)
    x, lo, hi = _sample_range(r, counts, seed)
    n_flat = _check_in_range(s, lo, hi)
    if scene in NONNEGATIVE_SCENES:
        assert x.min() >= 0 and s.mean.min() >= 0, s.mean.min()
    if scene == "fireflies":
        assert n_flat > 0  # the case the regression is about is exercised


@pytest.mark.parametrize("chunk", [1, 7])
@pytest.mark.parametrize("scene", ["edges", "fireflies"])
def test_means_stay_in_range_after_chunk_merges(scene, chunk):
    """Same guarantee when a pixel's samples are split over chunks and merged (Chan's
    update rounds too, but stays between the merged means: see
    test_chan_merge_keeps_the_mean_between_the_merged_means); these scenes draw one
    stream, so the chunks' samples are ``sample_values``' (see
    test_chunking_is_exact_for_single_stream_scenes).  ``chunk = 1`` merges every sample."""
    r = ToyRenderer(scene, width=16, height=16)
    counts = np.random.default_rng(5).integers(0, 24, (16, 16))
    s = r.render(counts, seed=6, chunk_size=chunk)
    x, lo, hi = _sample_range(r, counts, 6)
    n_flat = _check_in_range(s, lo, hi)
    assert s.mean.min() >= 0 and (scene == "edges" or n_flat > 0)


def test_chan_merge_keeps_the_mean_between_the_merged_means():
    """What lets :meth:`ToyRenderer.render` merge chunks without re-clipping (the proof is
    in ``toy._stats_from_deviations``' Notes): ``PixelStats.merge``'s mean
    ``a + (b − a)·n_b/n`` stays in ``[min(a, b), max(a, b)]`` after rounding, and merging
    two runs flat at the same value keeps that value, ``M2 = 0`` and zero cross terms
    exactly.  Adversarial pairs: signs and magnitudes over 2^±60 (``b − a`` rounds),
    neighbours one ulp apart, relative gaps of a few ulps, ``n_b/n`` near 0 and near 1,
    counts up to 2^40, and empty sides (``n_a = 0`` with ``a = 0``: the result is ``b``)."""
    rng = np.random.default_rng(123)
    m = 400_000
    a = rng.choice([-1.0, 1.0], m) * rng.random(m) * 2.0 ** rng.integers(-60, 60, m)
    b = rng.choice([-1.0, 1.0], m) * rng.random(m) * 2.0 ** rng.integers(-60, 60, m)
    q = m // 4
    b[:q] = np.nextafter(a[:q], rng.choice([-np.inf, np.inf], q))
    b[q:2 * q] = a[q:2 * q] * (1 + rng.integers(-8, 9, q) * 2.0 ** -52)
    na = rng.integers(1, 2 ** rng.integers(1, 41, m), dtype=np.int64)
    nb = rng.integers(1, 2 ** rng.integers(1, 41, m), dtype=np.int64)
    na[:m // 3] = 1                  # n_b / n close to 1
    nb[m // 3:2 * m // 3] = 1        # close to 0
    na[-1000:], a[-1000:] = 0, 0.0   # a pixel the first chunk did not reach
    one = np.zeros((1, m, 1))
    merged = PixelStats(na[None], a[None, :, None], one).merge(
        PixelStats(nb[None], b[None, :, None], one)).mean.ravel()
    out = (merged < np.minimum(a, b)) | (merged > np.maximum(a, b))
    out[-1000:] = merged[-1000:] != b[-1000:]
    i = np.flatnonzero(out)[:3]
    assert not out.any(), (f"{int(out.sum())} of {m} merged means leave [min(a, b), max(a, b)],"
                           f" e.g. a={a[i]}, b={b[i]}, n_a={na[i]}, n_b={nb[i]} -> {merged[i]}")
    # flat runs: channel 0 flat at the same value on both sides, channel 1 not
    v = rng.standard_normal(m)
    mean_a, mean_b = np.stack([v, v + 1], -1)[None], np.stack([v, v - 1], -1)[None]
    m2_a, m2_b = np.stack([0 * v, v * v + 1], -1)[None], np.stack([0 * v, v * v + 2], -1)[None]
    cross = np.zeros((1, m, 2, 2))
    cross[..., 1, 1] = m2_a[..., 1]
    sa = PixelStats(na[None].clip(1), mean_a, m2_a, m2_cross=cross)
    cross_b = cross.copy()
    cross_b[..., 1, 1] = m2_b[..., 1]
    f = sa.merge(PixelStats(nb[None], mean_b, m2_b, m2_cross=cross_b))
    assert np.array_equal(f.mean[..., 0], mean_a[..., 0])
    assert np.all(f.m2[..., 0] == 0) and np.all(f.m2_cross[..., 0, :] == 0)
    assert np.all(f.m2_cross[..., :, 0] == 0)
