"""Gaussian filter bank: closed forms, numba kernel vs NumPy reference, borders, variance."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import stats as sps

from statmc import InputError
from statmc import filters as F


# ----------------------------------------------------------------------------- kernels
@pytest.mark.parametrize("sigma", [0.5, 1.0, np.sqrt(2), 2.0, 5.3, 16.0])
def test_kernel_is_the_sampled_normalised_gaussian(sigma):
    w = F.gaussian_kernel_1d(sigma)
    r = len(w) // 2
    assert r == int(np.ceil(3 * sigma - 1e-9))
    k = np.arange(-r, r + 1)
    g = np.exp(-k ** 2 / (2 * sigma ** 2))
    np.testing.assert_allclose(w, g / g.sum(), rtol=1e-14)
    np.testing.assert_allclose(w, w[::-1], rtol=0, atol=0)


def test_dyadic_radii_are_not_inflated_by_rounding():
    # sqrt(2)**2 = 2.0000000000000004 must still give radius 6, not 7
    assert [len(F.gaussian_kernel_1d(s)) for s in F.FINAL_SIGMAS] == [1, 11, 13, 19, 25, 35, 49, 69, 97]
    assert F.FINAL_SIGMAS[2] == 2.0 and F.FINAL_SIGMAS[8] == 16.0
    assert F.ADAPTIVE_SIGMAS == (0.0, 1.0, 2.0, 4.0, 8.0)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 4.0])
def test_second_moment_tends_to_sigma_squared(sigma):
    # Poisson summation: the untruncated sampled Gaussian's second moment is
    # σ² (1 − 8π²σ² exp(−2π²σ²)) to leading order (2e-7 relative at σ = 1)
    expected = sigma ** 2 * (1 - 8 * np.pi ** 2 * sigma ** 2 * np.exp(-2 * np.pi ** 2 * sigma ** 2))
    assert F.kernel_moment2(sigma, truncate=10.0) == pytest.approx(expected, rel=1e-12)
    # at the default 3σ cut it is the truncated normal's variance, ~0.973 σ²
    tn = sps.truncnorm(-3, 3).var()
    assert F.kernel_moment2(sigma) == pytest.approx(tn * sigma ** 2, rel=0.03)
    assert F.kernel_moment2(0.0) == 0.0


def _moment2_summed(sigma, r):
    """Σ k² g / Σ g over |k| <= r, summed exactly (math.fsum) from the taps."""
    import math
    k = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (k / sigma) ** 2)
    return math.fsum(g * k * k) / math.fsum(g)


@pytest.mark.parametrize("sigma,truncate", [
    (3000.0, 3.0), (1e5, 1.0), (1e5, 3.0), (1e6, 0.5), (2e6, 3.0),   # closed form
    (2e7, 0.005),            # y = r/σ = 0.005: the small-y integral without cancellation
    (2000.0, 50.0),          # 100000 taps a side, the ones past 40σ (exactly 0) skipped
    (1e-3, 1e6), (1.0, 1e8)])  # a huge cut on a narrow Gaussian: all but a few taps are 0
def test_second_moment_of_long_kernels_without_building_them(sigma, truncate):
    """kernel_moment2 built the whole kernel (and four temporaries like it): σ = 1e6 took
    137 MiB, σ = 1e8 some 20 GiB (gem.reconstruct(sigmas=(0, 1, 1e8)) ran 68 s into a
    MemoryError).  Long kernels now skip their zero taps and beyond 2^16 non-zero taps a
    side take the Euler–Maclaurin closed form; both must be the summed taps' moment."""
    import math
    r = max(1, math.ceil(truncate * sigma - 1e-9))
    want = _moment2_summed(sigma, min(r, math.ceil(40 * sigma)))
    assert F.kernel_moment2(sigma, truncate=truncate) == pytest.approx(want, rel=1e-14, abs=0)


def test_second_moment_is_the_summed_kernel_bit_for_bit_up_to_4096_taps():
    for sigma, t in [(0.3, 3.0), (2.0, 3.0), (7.7, 4.5), (1365.3, 3.0), (4096.0, 1.0)]:
        w = F.gaussian_kernel_1d(sigma, truncate=t)
        k = np.arange(len(w), dtype=np.float64) - len(w) // 2
        assert F.kernel_moment2(sigma, truncate=t) == float(np.sum(w * k * k))


def test_second_moment_of_huge_and_tiny_sigmas():
    """σ·truncate past float64's range raised OverflowError ('cannot convert float
    infinity to integer'); r² ≈ σ² overflows to inf only past ~1e154."""
    # the sum is the integral plus the end taps' O(1/σ) (3.7e-10 relative at σ = 1e8)
    assert F.kernel_moment2(1e8) == pytest.approx(sps.truncnorm(-3, 3).var() * 1e16, rel=1e-9)
    assert F.kernel_moment2(1e150) == pytest.approx(sps.truncnorm(-3, 3).var() * 1e300, rel=1e-12)
    assert F.kernel_moment2(1e300) == np.inf
    assert F.kernel_moment2(1.0, truncate=1e308) == pytest.approx(1.0, rel=1e-6)
    assert F.kernel_moment2(1e-300, truncate=1e308) == 0.0    # the pixel filter itself


def test_kernel_beyond_any_array_is_refused_by_name():
    """σ = 1e300 asked NumPy for 6e300 taps ('Maximum allowed size exceeded', a bare
    ValueError); the filters themselves take it (their kernel is cut to the image)."""
    with pytest.raises(InputError, match=r"`sigma` · `truncate` must be below .* taps a side"):
        F.gaussian_kernel_1d(1e300)
    with pytest.raises(InputError, match=r"`sigma` · `truncate` must be below"):
        F.gaussian_kernel_1d(1.0, truncate=1e308)
    img = np.arange(12.0).reshape(3, 4)
    np.testing.assert_allclose(F.gaussian_filter(img, 1e300), np.full((3, 4), img.mean()),
                               rtol=1e-12)


def test_border_scale_renormalises():
    w = F.gaussian_kernel_1d(2.0)
    s = F.border_scale(9, w)
    r = len(w) // 2
    for p in range(9):
        inside = sum(w[q - p + r] for q in range(max(0, p - r), min(9, p + r + 1)))
        assert s[p] * inside == pytest.approx(1.0, rel=1e-14)


def test_kept_kernels_and_border_factors_are_fresh_copies_of_the_formula():
    """``_gauss`` and ``_border_scale`` keep their results for repeated sizes (session
    16): every call returns its own writable array, bit for bit the direct formula (taps
    ``exp(−k²/2σ²)/Σ``; factors ``1/Σ in-image taps``), for float64 and float32 taps,
    also after a caller scaled an earlier result in place, and past the kept size."""
    F._gauss_kept.cache_clear()
    F._border_scale_kept.cache_clear()
    for s, r in [(0.6, 2), (2.0, 6), (13.6, 41), (3000.0, 9000)]:   # the last is not kept
        k = np.arange(-r, r + 1, dtype=np.float64)
        ref = np.exp(-0.5 * (k / s) ** 2)
        ref = ref / ref.sum()
        for _ in range(2):
            w = F._gauss(s, r)
            assert w.flags.writeable and w.dtype == np.float64
            assert np.array_equal(w, ref)
            w *= 3.0                                   # must not reach the next call
        for dt in (np.float64, np.float32):
            taps = ref.astype(dt)
            for n in (1, 5, 2 * r + 7, 20000):
                c = np.concatenate([[0.0], np.cumsum(taps)])
                pos = np.arange(n)
                lo = np.maximum(pos - r, 0) - (pos - r)
                hi = np.minimum(pos + r, n - 1) - (pos - r) + 1
                expect = 1.0 / (c[hi] - c[lo])
                for _ in range(2):
                    b = F._border_scale(n, taps)
                    assert b.flags.writeable and b.dtype == expect.dtype
                    assert np.array_equal(b, expect)
                    b[:] = -1.0


# ------------------------------------------------------------- numba kernel vs NumPy
@pytest.mark.parametrize("shape", [(23, 31, 3), (1, 40, 1), (40, 1, 2), (1, 1, 3), (7, 9, 4), (12, 10)])
@pytest.mark.parametrize("sigmas", [F.ADAPTIVE_SIGMAS, F.FINAL_SIGMAS, (0.7, 3.3)])
def test_bank_equals_numpy_reference_float64(shape, sigmas):
    rng = np.random.default_rng(hash((shape, len(sigmas))) % 2 ** 32)
    m = rng.normal(size=shape)
    v = rng.uniform(0, 2, size=shape)
    vals, vars_ = F.filter_bank(m, v, sigmas)
    rv, rvar = F.filter_bank_reference(m, v, sigmas)
    assert vals.shape == rv.shape == (len(sigmas),) + shape
    np.testing.assert_allclose(vals, rv, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(vars_, rvar, rtol=1e-12, atol=1e-15)


def test_bank_float32_matches_reference_and_keeps_dtype():
    rng = np.random.default_rng(3)
    m = rng.normal(size=(30, 41, 3)).astype(np.float32)
    v = rng.uniform(0, 1, size=m.shape).astype(np.float32)
    vals, vars_ = F.filter_bank(m, v, F.FINAL_SIGMAS)
    assert vals.dtype == vars_.dtype == np.float32
    rv, rvar = F.filter_bank_reference(m, v, F.FINAL_SIGMAS)
    np.testing.assert_allclose(vals, rv, rtol=0, atol=2e-6)
    np.testing.assert_allclose(vars_, rvar, rtol=1e-5, atol=1e-8)


def test_summed_variance_is_sum_of_channel_variances():
    rng = np.random.default_rng(4)
    m = rng.normal(size=(20, 25, 3))
    v = rng.uniform(0, 1, size=m.shape)
    _, per = F.filter_bank(m, v, F.FINAL_SIGMAS)
    _, tot = F.filter_bank(m, v, F.FINAL_SIGMAS, sum_channels=True)
    assert tot.shape == (9, 20, 25)
    np.testing.assert_allclose(tot, per.sum(-1), rtol=1e-12)


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 14), w=st.integers(1, 14), c=st.integers(1, 3),
       sigma=st.floats(0.3, 9.0), seed=st.integers(0, 2 ** 31))
def test_bank_matches_reference_on_random_shapes(h, w, c, sigma, seed):
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(h, w, c))
    v = rng.uniform(0, 1, size=(h, w, c))
    vals, vars_ = F.filter_bank(m, v, [0.0, sigma])
    rv, rvar = F.filter_bank_reference(m, v, [0.0, sigma])
    np.testing.assert_allclose(vals, rv, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(vars_, rvar, rtol=1e-11, atol=1e-14)


# ------------------------------------------------------------------ borders and meaning
@pytest.mark.parametrize("sigma", [1.0, 4.0, 16.0])
def test_constant_image_stays_constant_up_to_the_border(sigma):
    img = np.full((9, 37, 3), 0.25)
    out = F.gaussian_filter(img, sigma)
    np.testing.assert_allclose(out, 0.25, rtol=1e-13)  # no energy leaks out or in


def test_filter_of_quadratic_has_closed_form_bias():
    # f = a x² + b y² + c xy + d x + e y: interior Gaussian bias is (a + b)·r², r² = Σ w k²
    h, w = 60, 70
    y, x = np.mgrid[0:h, 0:w].astype(float)
    a, b = 0.013, -0.007
    f = a * x ** 2 + b * y ** 2 + 0.003 * x * y + 0.2 * x - 0.1 * y + 1.0
    for s in (1.0, 2.0, 4.0):
        r = len(F.gaussian_kernel_1d(s)) // 2
        out = F.gaussian_filter(f, s)
        inner = (slice(r, h - r), slice(r, w - r))
        np.testing.assert_allclose(out[inner] - f[inner], (a + b) * F.kernel_moment2(s), rtol=1e-9)


def test_variance_is_the_variance_of_the_filtered_noise():
    """Monte Carlo: filter many independent heteroscedastic noise images (as channels)
    and compare the empirical variance of the output with the propagated variance at an
    interior, an edge and a corner pixel (chi-square test per pixel, Bonferroni)."""
    rng = np.random.default_rng(5)
    h, w, reps = 14, 17, 4000
    sd = rng.uniform(0.2, 2.0, size=(h, w, 1))
    noise = rng.normal(size=(h, w, reps)) * sd
    out = F.gaussian_filter(noise, 2.0)
    _, var = F.filter_bank(np.zeros((h, w, 1)), sd ** 2, [2.0])
    pvals = []
    for (i, j) in [(7, 8), (0, 8), (0, 0), (13, 16)]:
        s2 = out[i, j].var(ddof=1)
        stat = (reps - 1) * s2 / var[0, i, j, 0]
        cdf = sps.chi2.cdf(stat, reps - 1)
        pvals.append(2 * min(cdf, 1 - cdf))
    assert min(pvals) > 0.001 / len(pvals), pvals


def test_spread_is_the_adjoint_of_the_filter():
    rng = np.random.default_rng(6)
    a = rng.uniform(size=(11, 13))
    b = rng.uniform(size=(11, 13))
    for s in (1.0, 3.0, 8.0):
        lhs = np.sum(b * F.gaussian_filter(a, s))
        rhs = np.sum(a * F.gaussian_spread(b, s))
        assert lhs == pytest.approx(rhs, rel=1e-12)
        assert F.gaussian_spread(b, s).sum() == pytest.approx(b.sum(), rel=1e-12)
    # one pixel's amount lands on its filter's support in proportion to its weights
    d = np.zeros((11, 13))
    d[0, 2] = 5.0
    ay = F._weight_matrix(11, 2.0, 3.0)
    ax = F._weight_matrix(13, 2.0, 3.0)
    np.testing.assert_allclose(F.gaussian_spread(d, 2.0), 5.0 * np.outer(ay[0], ax[2]), atol=1e-14)


def test_gaussian_filter_2d_and_dtypes():
    img = np.arange(30, dtype=np.float32).reshape(5, 6)
    out = F.gaussian_filter(img, 1.0)
    assert out.shape == (5, 6) and out.dtype == np.float32
    assert F.gaussian_filter(img.astype(int), 1.0).dtype == np.float64
    np.testing.assert_array_equal(F.gaussian_filter(img, 0.0), img)


# -------------------------------------------------------------------------- bad input
def test_bad_input_raises_input_error_naming_the_parameter():
    m = np.zeros((4, 5, 3))
    with pytest.raises(InputError, match="mean_var"):
        F.filter_bank(m, np.zeros((4, 5, 2)))
    with pytest.raises(InputError, match="mean_var.*>= 0"):
        F.filter_bank(m, np.full(m.shape, -1.0))
    bad = m.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(InputError, match="`mean` holds 1 NaN"):
        F.filter_bank(bad, np.zeros_like(m))
    bad = np.zeros_like(m)
    bad[0, 0, 1] = np.inf
    with pytest.raises(InputError, match="`mean_var` holds 0 NaN and 1 Inf"):
        F.filter_bank(m, bad)
    with pytest.raises(InputError, match="sigma"):
        F.gaussian_kernel_1d(-1.0)
    with pytest.raises(InputError, match="sigmas"):
        F.filter_bank(m, m, [1.0, np.nan])
    with pytest.raises(InputError, match="truncate"):
        F.gaussian_kernel_1d(1.0, truncate=0)
    with pytest.raises(InputError, match="dimensions"):
        F.filter_bank(np.zeros(5), np.zeros(5))


# -------------------------------------------------------------------------- compilation
_FILTER_COMPILES = r"""
import numpy as np
from numba.core.registry import CPUDispatcher
from statmc import _filter_kernels as K, gem
m = np.random.default_rng(0).uniform(0.1, 1.0, (40, 36, 3))
gem.reconstruct(m, np.full_like(m, 0.01))
print({name: [str(next(a.dtype for a in s if hasattr(a, "ndim"))) for s in d.signatures] for name, d in vars(K).items()
       if isinstance(d, CPUDispatcher) and d.signatures and name in
       ("_filter_tasks", "_block", "_vpass", "_hpass", "_sep_filter_jobs")})
print(K._filter_tasks.targetoptions.get("parallel", False))
"""


def test_the_filter_passes_compile_into_one_serial_function_per_dtype():
    """A float64 ``gem.reconstruct`` filters in float64 (the bank) and float32 (the
    stopping maps).  The filter passes were compiled into a numba parallel kernel, whose
    parallel lowering compiles the loop body as a function of its own and links it, with
    the passes, into the kernel: ~10 s CPU per dtype on a cold cache (6 s now, in one
    serial function run by ``_filter_kernels.run_tasks``).  Checked in a fresh process,
    where the compiled (or cache-loaded) signatures are those of this one call."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", _FILTER_COMPILES], capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    sigs, parallel = p.stdout.strip().splitlines()
    sigs = eval(sigs)
    assert sigs["_filter_tasks"] == ["float64", "float32"], sigs
    assert "_sep_filter_jobs" not in sigs, sigs      # no parallel filter kernel
    assert parallel == "False"


def _sep_filter_reference(x, C, w, sy, sx):
    """NumPy reference of one job of ``sep_filter_many``: (H, W*C) rows filtered with the
    symmetric taps ``w`` (zero padding) on both axes, times ``sy[y] sx[x]``, in float64."""
    from scipy.ndimage import correlate1d

    h = x.shape[0]
    a = x.astype(np.float64).reshape(h, -1, C)
    w = w.astype(np.float64)
    a = correlate1d(correlate1d(a, w, axis=0, mode="constant"), w, axis=1, mode="constant")
    return (a * sy.astype(np.float64)[:, None, None] * sx.astype(np.float64)[None, :, None]).reshape(h, -1)


@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_filter_jobs_split_over_any_number_of_threads_give_the_same_bits(dt):
    """``sep_filter_many`` runs the row blocks of all its jobs split into one range per
    thread (``_filter_kernels.run_tasks``): the result is the same to the bit for 1 to
    NUMBA_NUM_THREADS threads, with fewer tasks than threads and rows not a multiple of
    the row block, and equals the NumPy reference (values with the taps, variances with
    the squared taps and factors)."""
    import numba

    from statmc import _filter_kernels as K

    rng = np.random.default_rng(5)
    tol = dict(rtol=2e-5, atol=2e-5) if dt == np.float32 else dict(rtol=1e-12, atol=1e-12)
    for h, w, C, Cv in ((1, 7, 3, 1), (33, 5, 1, 1), (70, 9, 3, 3), (130, 4, 2, 1)):
        lens = [1, 27, 9, 5]
        nk = len(lens)
        x = rng.standard_normal((2, h, w * C)).astype(dt)
        v = rng.random((2, h, w * Cv)).astype(dt)
        src = np.array([1, 0, 1, 0], np.int64)
        taps = np.zeros((nk, max(lens)), dt)
        for k, n in enumerate(lens):
            t = rng.random(n) + 0.1
            taps[k, :n] = t + t[::-1]               # symmetric, as the kernel assumes
        sy, sx = (rng.random((nk, h)) + 0.5).astype(dt), (rng.random((nk, w)) + 0.5).astype(dt)
        outs = []
        before = numba.get_num_threads()
        try:
            for t in range(1, numba.config.NUMBA_NUM_THREADS + 1):
                numba.set_num_threads(t)
                ox, ov = np.empty((nk, h, w * C), dt), np.empty((nk, h, w * Cv), dt)
                K.sep_filter_many(x, C, v, Cv, src, taps, np.array(lens, np.int64), sy, sx, ox, ov)
                outs.append((ox, ov))
        finally:
            numba.set_num_threads(before)
        for ox, ov in outs[1:]:
            np.testing.assert_array_equal(ox, outs[0][0])
            np.testing.assert_array_equal(ov, outs[0][1])
        ox, ov = outs[0]
        for k in range(nk):
            tk = taps[k, :lens[k]]
            np.testing.assert_allclose(ox[k], _sep_filter_reference(x[src[k]], C, tk, sy[k], sx[k]), **tol)
            np.testing.assert_allclose(ov[k], _sep_filter_reference(v[src[k]], Cv, tk * tk, sy[k] ** 2,
                                                                    sx[k] ** 2), **tol)
    seen = []
    K.run_tasks(lambda t0, t1: seen.append((t0, t1)), 0)
    assert seen == []
    K.run_tasks(lambda t0, t1: seen.append((t0, t1)), 1)
    assert seen == [(0, 1)]
