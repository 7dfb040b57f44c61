"""PixelStats: exact merging (Chan et al.) against single-pass NumPy, and bad input."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from statmc import InputError, PixelStats
from statmc.stats import replace_nonfinite

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(data=st.data(), s=st.integers(2, 12), h=st.integers(1, 4), w=st.integers(1, 4),
       c=st.integers(1, 3))
def test_merge_of_any_split_equals_single_pass(data, s, h, w, c):
    x = data.draw(arrays(np.float64, (s, h, w, c), elements=finite))
    cuts = sorted(data.draw(st.lists(st.integers(0, s), min_size=1, max_size=4)))
    bounds = [0, *cuts, s]
    acc = PixelStats.empty(h, w, c)
    for a, b in zip(bounds[:-1], bounds[1:]):
        acc = acc.merge(PixelStats.from_samples(x[a:b]))
    assert np.array_equal(acc.n, np.full((h, w), s))
    scale = 1.0 + np.abs(x).max()
    np.testing.assert_allclose(acc.mean, x.mean(axis=0), rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(acc.sample_var, x.var(axis=0, ddof=1), rtol=1e-9,
                               atol=1e-9 * scale**2)
    np.testing.assert_allclose(acc.mean_var, x.var(axis=0, ddof=1) / s, rtol=1e-9,
                               atol=1e-9 * scale**2)


@settings(max_examples=40, deadline=None)
@given(data=st.data(), h=st.integers(1, 4), w=st.integers(1, 4))
def test_variable_counts_from_pixel_samples_match_per_pixel_numpy(data, h, w):
    counts = data.draw(arrays(np.int64, (h, w), elements=st.integers(0, 6)))
    idx = np.repeat(np.arange(h * w), counts.ravel())
    vals = data.draw(arrays(np.float64, (idx.size, 2), elements=finite))
    perm = np.random.default_rng(0).permutation(idx.size)
    stats = PixelStats.from_pixel_samples(idx[perm], vals[perm], (h, w))
    assert np.array_equal(stats.n, counts)
    for p in range(h * w):
        v = vals[idx == p]
        i, j = divmod(p, w)
        if v.shape[0] == 0:
            assert np.all(stats.mean[i, j] == 0) and np.all(stats.m2[i, j] == 0)
            continue
        np.testing.assert_allclose(stats.mean[i, j], v.mean(0), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(stats.m2[i, j], ((v - v.mean(0)) ** 2).sum(0), rtol=1e-9,
                                   atol=1e-6)


def test_split_by_pixel_samples_merges_exactly():
    rng = np.random.default_rng(1)
    h, w = 5, 7
    idx = rng.integers(0, h * w, 2000)
    vals = rng.gamma(0.5, 3.0, size=(2000, 3))
    whole = PixelStats.from_pixel_samples(idx, vals, (h, w))
    parts = PixelStats.from_pixel_samples(idx[:700], vals[:700], (h, w)).merge(
        PixelStats.from_pixel_samples(idx[700:], vals[700:], (h, w)))
    np.testing.assert_array_equal(parts.n, whole.n)
    np.testing.assert_allclose(parts.mean, whole.mean, rtol=1e-12)
    np.testing.assert_allclose(parts.m2, whole.m2, rtol=1e-10)


def test_from_sums_and_from_mean_var_agree_with_samples():
    rng = np.random.default_rng(2)
    x = rng.normal(3.0, 0.5, size=(16, 3, 4, 3))
    ref = PixelStats.from_samples(x)
    s = PixelStats.from_sums(np.full((3, 4), 16), x.sum(0), (x**2).sum(0))
    np.testing.assert_allclose(s.mean, ref.mean, rtol=1e-12)
    np.testing.assert_allclose(s.sample_var, ref.sample_var, rtol=1e-8)
    m = PixelStats.from_mean_var(ref.mean, ref.sample_var, ref.n)
    np.testing.assert_allclose(m.m2, ref.m2, rtol=1e-12)


def test_mean_var_is_sample_var_over_n_and_unbiased():
    # Over many independent 8-sample pixels, mean_var estimates the variance of the mean.
    rng = np.random.default_rng(3)
    x = rng.exponential(2.0, size=(8, 200, 200, 1))       # per-sample variance 4
    st_ = PixelStats.from_samples(x)
    v = st_.mean_var.ravel()
    se = v.std(ddof=1) / np.sqrt(v.size)
    assert abs(v.mean() - 4.0 / 8) < 4 * se
    # The pixel means are Gamma(8, 1/4): variance 0.5, excess kurtosis 6/8, so the sample
    # variance over N pixels has standard error 0.5 * sqrt(2/(N-1) + 0.75/N).
    emp = st_.mean.ravel().var(ddof=1)
    n_pix = v.size
    assert abs(emp - 0.5) < 4 * 0.5 * np.sqrt(2 / (n_pix - 1) + 0.75 / n_pix)


def test_single_and_zero_sample_pixels_give_zero_variance_not_nan():
    st_ = PixelStats.from_pixel_samples(np.array([0, 1, 1]), np.array([[1.0], [2.0], [4.0]]), (1, 3))
    assert np.array_equal(st_.n, [[1, 2, 0]])
    assert np.all(np.isfinite(st_.sample_var)) and np.all(np.isfinite(st_.mean_var))
    assert st_.sample_var[0, 0, 0] == 0 and st_.sample_var[0, 2, 0] == 0
    assert st_.sample_var[0, 1, 0] == pytest.approx(2.0)


@pytest.mark.parametrize("kwargs, match", [
    (dict(n=-np.ones((2, 2)), mean=np.zeros((2, 2, 3)), m2=np.zeros((2, 2, 3))), "`n` must be >= 0"),
    (dict(n=np.full((2, 2), 1.5), mean=np.zeros((2, 2, 3)), m2=np.zeros((2, 2, 3))), "whole sample"),
    (dict(n=np.full((2, 2), np.nan), mean=np.zeros((2, 2, 3)), m2=np.zeros((2, 2, 3))), "NaN"),
    (dict(n=np.ones((2, 2)), mean=np.zeros((2, 3, 3)), m2=np.zeros((2, 3, 3))), "`mean`"),
    (dict(n=np.ones((2, 2)), mean=np.zeros((2, 2, 3)), m2=np.zeros((2, 2, 1))), "`m2`"),
    (dict(n=np.ones((2, 2)), mean=np.full((2, 2, 3), np.inf), m2=np.zeros((2, 2, 3))), "Inf"),
    (dict(n=np.ones((2, 2)), mean=np.zeros((2, 2, 3)), m2=-np.ones((2, 2, 3))), "`m2` must be >= 0"),
    (dict(n=np.ones(4), mean=np.zeros((2, 2, 3)), m2=np.zeros((2, 2, 3))), r"\(H, W\)"),
])
def test_bad_input_is_named(kwargs, match):
    with pytest.raises(InputError, match=match):
        PixelStats(**kwargs)


def test_merge_sums_the_render_counters_of_meta():
    """A merge kept the first side's meta, so an adaptive render's merged passes (and
    report.json's renderer_info) gave the first pass's samples, seconds and chunks; they
    are the totals now, samples_per_second their ratio, and the rest as before: the union,
    the first side winning (seed, features' seconds), nothing summed unless both are
    numbers."""
    rng = np.random.default_rng(3)

    def stats(s, **meta):
        out = PixelStats.from_samples(rng.normal(size=(s, 2, 2, 3)))
        out.meta.update(meta)
        return out

    a, b = stats(3), stats(5)
    a.meta.update(renderer="mitsuba", seed=1, samples=12, seconds=2.0, samples_per_second=6.0,
                  chunks=3, nonfinite_samples=1, feature_seconds=0.5)
    b.meta.update(renderer="mitsuba", seed=2, samples=20, seconds=0.5, samples_per_second=40.0,
                  chunks=5, nonfinite_samples=0, passes=1)
    m = a.merge(b).meta
    assert m == dict(renderer="mitsuba", seed=1, samples=32, seconds=2.5,
                     samples_per_second=32 / 2.5, chunks=8, nonfinite_samples=1,
                     feature_seconds=0.5, passes=1)
    assert m["samples"] == a.merge(b).total_samples
    assert (b + a).meta["seed"] == 2 and (b + a).meta["samples"] == 32
    assert a.meta["samples"] == 12 and b.meta["samples"] == 20          # inputs untouched
    # one side without a counter, or a non-number: the union as before, nothing summed
    c = stats(2, samples="many")
    assert a.merge(c).meta["samples"] == 12 and c.merge(a).meta["samples"] == "many"
    d = stats(2, seconds=True)
    assert a.merge(d).meta["seconds"] == 2.0
    e = stats(2, renderer="toy")
    assert a.merge(e).meta == a.meta and e.merge(a).meta == {**a.meta, "renderer": "toy"}
    # no time measured: the rate is NaN, as a renderer writes it
    z = dict(samples=4, seconds=0.0, samples_per_second=float("nan"))
    f = stats(2, **z)
    g = stats(2, **z)
    assert np.isnan(f.merge(g).meta["samples_per_second"]) and f.merge(g).meta["samples"] == 8


@pytest.mark.parametrize("make,name", [
    (lambda x: PixelStats.from_samples(x[:, None, None, :] * 1e300), "samples"),
    (lambda x: PixelStats.from_pixel_samples(np.zeros(4, int), x * 1e300, (1, 1)), "values"),
    (lambda x: PixelStats.from_mean_var(np.ones((1, 1, 3)), np.full((1, 1, 3), 1e300),
                                        np.full((1, 1), 2 ** 62)), "sample_var"),
    (lambda x: PixelStats.from_mean_var(np.full((1, 1, 3), 1e300), np.ones((1, 1, 3)),
                                        np.full((1, 1), 4)).merge(
        PixelStats.from_mean_var(np.full((1, 1, 3), -1e300), np.ones((1, 1, 3)),
                                 np.full((1, 1), 4))), "other"),
], ids=["from_samples", "from_pixel_samples", "from_mean_var", "merge"])
def test_statistics_that_overflow_float64_name_their_input(make, name):
    """Samples whose squared deviations pass float64 (1e300 apart), a sample variance
    times 2**62 samples, or two passes whose means are 2e300 apart gave an inf M2, which
    PixelStats refused as "`m2` holds 0 NaN and 3 Inf values ... replace them first" (an
    array the caller never passed, and no NaN/Inf to replace) after a RuntimeWarning."""
    x = np.array([[1.0, -2.0, 0.5], [-1.0, 2.0, 0.25], [0.5, 0.0, -1.0], [2.0, 1.0, 3.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=rf"^`{name}` must give statistics within float64; "
                                             r"got 1 pixels where .* overflows"):
            make(x)


def test_replace_nonfinite_writes_only_what_the_array_holds():
    """A value beyond float32 (1e300) was written as the Inf it replaced, with an
    'overflow encountered in cast' warning; NaN as the value into an integer array raised
    NumPy's 'cannot convert float NaN to integer' (with nothing to replace); a string
    array or value raised NumPy's errors."""
    with pytest.raises(InputError, match=r"`value` must be finite in the array's dtype float32"):
        replace_nonfinite(np.array([1.0, np.nan], np.float32), 1e300)
    for bad in (np.nan, "x", None):
        with pytest.raises(InputError, match=r"`value` must be a finite number"):
            replace_nonfinite(np.array([1.0, np.inf]), bad)
    with pytest.raises(InputError, match=r"`a` must be a numeric array; got dtype <U3"):
        replace_nonfinite(np.array(["abc"]), 0.0)
    y, k = replace_nonfinite(np.array([1, 2]), 5.0)
    assert y.dtype.kind == "i" and k == 0 and y.tolist() == [1, 2]
    y, k = replace_nonfinite(np.array([1.0, np.nan], np.float32), 3e38)
    assert y.dtype == np.float32 and k == 1 and y[1] == np.float32(3e38)


def test_merge_shape_mismatch_and_bad_features():
    a = PixelStats.empty(2, 2)
    with pytest.raises(InputError, match="cannot merge"):
        a.merge(PixelStats.empty(2, 3))
    with pytest.raises(InputError, match="albedo"):
        a.with_features(albedo=np.zeros((3, 3, 3)))
    with pytest.raises(InputError, match="unknown feature"):
        a.with_features(colour=np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match="pixel_index"):
        PixelStats.from_pixel_samples(np.array([0, 9]), np.zeros((2, 1)), (2, 2))
    with pytest.raises(InputError, match="NaN"):
        PixelStats.from_samples(np.full((2, 1, 1, 1), np.nan))


def test_features_travel_through_merge():
    alb = np.full((2, 2, 3), 0.5, np.float32)
    a = PixelStats.empty(2, 2).with_features(albedo=alb)
    b = PixelStats.from_samples(np.ones((3, 2, 2, 3)))
    assert np.array_equal(b.merge(a).albedo, alb) and np.array_equal(a.merge(b).albedo, alb)


def test_replace_nonfinite_counts():
    x = np.array([1.0, np.nan, np.inf, -np.inf])
    y, k = replace_nonfinite(x, 0.0)
    assert k == 3 and np.array_equal(y, [1, 0, 0, 0]) and np.isnan(x[1])


# ----------------------------------------------------------------------------- channel covariance
def _np_cov(x):
    """Per-pixel sample covariance of ``x`` (S, H, W, C) with plain NumPy (reference)."""
    s, h, w, c = x.shape
    out = np.zeros((h, w, c, c))
    for i in range(h):
        for j in range(w):
            out[i, j] = np.cov(x[:, i, j, :], rowvar=False, ddof=1).reshape(c, c)
    return out


@settings(max_examples=40, deadline=None)
@given(data=st.data(), s=st.integers(2, 10), h=st.integers(1, 3), w=st.integers(1, 3),
       c=st.integers(1, 4))
def test_channel_covariance_merges_exactly_and_matches_numpy(data, s, h, w, c):
    x = data.draw(arrays(np.float64, (s, h, w, c), elements=finite))
    cuts = sorted(data.draw(st.lists(st.integers(0, s), min_size=1, max_size=4)))
    bounds = [0, *cuts, s]
    acc = PixelStats.empty(h, w, c)
    acc = PixelStats(acc.n, acc.mean, acc.m2, m2_cross=np.zeros((h, w, c, c)))
    for a, b in zip(bounds[:-1], bounds[1:]):
        acc = acc.merge(PixelStats.from_samples(x[a:b]))
    ref = _np_cov(x)
    scale = (1.0 + np.abs(x).max()) ** 2
    np.testing.assert_allclose(acc.sample_cov, ref, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(PixelStats.from_samples(x).sample_cov, ref, rtol=1e-9,
                               atol=1e-9 * scale)
    np.testing.assert_allclose(acc.mean_cov, ref / s, rtol=1e-9, atol=1e-9 * scale)
    k = np.arange(c)
    assert np.array_equal(acc.sample_cov[..., k, k], acc.sample_var)
    assert np.array_equal(acc.m2_cross, np.swapaxes(acc.m2_cross, -1, -2))


def test_channel_covariance_from_pixel_samples_and_sums():
    rng = np.random.default_rng(11)
    h, w, c = 3, 4, 3
    counts = rng.integers(0, 7, (h, w))
    idx = np.repeat(np.arange(h * w), counts.ravel())
    vals = rng.normal(size=(idx.size, c)) @ np.array([[1, .5, .2], [0, 1, -.3], [0, 0, 1.]])
    perm = rng.permutation(idx.size)
    st_ = PixelStats.from_pixel_samples(idx[perm], vals[perm], (h, w))
    for p in range(h * w):
        v = vals[idx == p]
        m2c = (v - v.mean(0)).T @ (v - v.mean(0)) if len(v) else np.zeros((c, c))
        np.testing.assert_allclose(st_.m2_cross.reshape(-1, c, c)[p], m2c, atol=1e-12)
    # from_sums: full cross-sum matrix or the (RG, RB, GB) pairs give the same statistics
    sx = np.stack([np.bincount(idx, vals[:, a], minlength=h * w) for a in range(c)], 1)
    sxy = np.stack([np.stack([np.bincount(idx, vals[:, a] * vals[:, b], minlength=h * w)
                              for b in range(c)], 1) for a in range(c)], 1)
    sx, sxy = sx.reshape(h, w, c), sxy.reshape(h, w, c, c)
    sx2 = np.diagonal(sxy, axis1=2, axis2=3)
    full = PixelStats.from_sums(counts, sx, sx2, sxy)
    pairs = PixelStats.from_sums(counts, sx, sx2, sxy[..., [0, 0, 1], [1, 2, 2]])
    assert np.array_equal(full.m2_cross, pairs.m2_cross)
    np.testing.assert_allclose(full.m2_cross, st_.m2_cross, atol=1e-10)
    assert PixelStats.from_sums(counts, sx, sx2).m2_cross is None
    # from_mean_var with a sample covariance (the EXR path)
    back = PixelStats.from_mean_var(st_.mean, st_.sample_var, st_.n,
                                    sample_cov=st_.sample_cov[..., [0, 0, 1], [1, 2, 2]])
    np.testing.assert_allclose(back.m2_cross, st_.m2_cross, rtol=1e-12, atol=1e-12)
    assert np.array_equal(back.m2, PixelStats.from_mean_var(st_.mean, st_.sample_var, st_.n).m2)


def test_sample_cov_is_unbiased_for_correlated_channels():
    """E[s_ab] = Σ_ab; for normal samples Var[s_ab] = (Σ_aa Σ_bb + Σ_ab²)/(n−1) (Wishart),
    so the pixel average is tested entrywise by z (Bonferroni over the 6 entries).  Power:
    a covariance computed with 1/n instead of 1/(n−1) is rejected."""
    from scipy import stats as sps
    rng = np.random.default_rng(12)
    L = np.array([[1.0, 0, 0], [0.8, 0.6, 0], [0.5, -0.4, 0.7]])
    sigma = L @ L.T
    n, h, w = 4, 100, 100
    x = rng.normal(size=(n, h, w, 3)) @ L.T
    st_ = PixelStats.from_samples(x)
    iu = np.triu_indices(3)
    se = np.sqrt((np.outer(np.diag(sigma), np.diag(sigma)) + sigma ** 2) / (n - 1) / (h * w))
    crit = sps.norm.ppf(1 - 1e-3 / (2 * iu[0].size))
    for est, ok in ((st_.sample_cov, True), (st_.m2_cross / n, False)):
        z = (est.mean(axis=(0, 1)) - sigma)[iu] / se[iu]
        assert (np.abs(z).max() < crit) == ok, f"z = {np.round(z, 2)}"


def test_channel_covariance_is_never_invented():
    rng = np.random.default_rng(13)
    x = rng.normal(size=(5, 2, 2, 3))
    with_cov = PixelStats.from_samples(x)
    without = PixelStats(with_cov.n, with_cov.mean, with_cov.m2)
    assert not without.has_cov and with_cov.has_cov
    assert with_cov.merge(without).m2_cross is None
    assert without.merge(with_cov).m2_cross is None
    with pytest.raises(InputError, match="no channel covariance"):
        _ = without.mean_cov
    c = with_cov.copy()
    assert c.m2_cross is not with_cov.m2_cross and np.array_equal(c.m2_cross, with_cov.m2_cross)
    assert with_cov.with_features(depth=np.ones((2, 2))).has_cov


def test_bad_channel_covariance_is_named():
    x = np.random.default_rng(14).normal(size=(5, 2, 2, 3))
    s = PixelStats.from_samples(x)
    bad = s.m2_cross.copy()
    bad[0, 0, 0, 1] += 1.0
    with pytest.raises(InputError, match="symmetric"):
        PixelStats(s.n, s.mean, s.m2, m2_cross=bad)
    bad = s.m2_cross.copy()
    bad[0, 0, 1, 1] *= 2
    with pytest.raises(InputError, match="diagonal of `m2_cross`"):
        PixelStats(s.n, s.mean, s.m2, m2_cross=bad)
    with pytest.raises(InputError, match="m2_cross"):
        PixelStats(s.n, s.mean, s.m2, m2_cross=s.m2_cross[..., :2, :2])
    with pytest.raises(InputError, match="sum_xy"):
        PixelStats.from_sums(s.n, s.mean, s.m2, np.zeros((2, 2, 2)))
    with pytest.raises(InputError, match="sample_cov"):
        PixelStats.from_mean_var(s.mean, s.sample_var, s.n, sample_cov=np.zeros((2, 2, 3, 2)))
    # rounding-level asymmetry is accepted and symmetrised exactly
    tiny = s.m2_cross.copy()
    tiny[..., 0, 1] *= 1 + 1e-12
    t = PixelStats(s.n, s.mean, s.m2, m2_cross=tiny)
    assert np.array_equal(t.m2_cross, np.swapaxes(t.m2_cross, -1, -2))


def test_as_number_accepts_finite_reals_and_names_the_parameter():
    from statmc.errors import as_number
    assert as_number("a", 2) == 2.0 and as_number("a", np.float32(0.5)) == 0.5
    assert as_number("a", 0.0, lo=0.0) == 0.0
    for bad, kw in ((True, {}), ("1", {}), (float("nan"), {}), (np.inf, {}),
                    (-1.0, {"lo": 0.0}), (0.0, {"lo": 0.0, "lo_open": True})):
        with pytest.raises(InputError, match="`a` must be"):
            as_number("a", bad, **kw)


def test_as_int_accepts_integers_only_and_names_the_parameter():
    from statmc.errors import as_int
    assert as_int("k", 3) == 3 and type(as_int("k", np.int64(3))) is int
    assert as_int("k", 0, lo=0) == 0
    for bad, kw, what in ((True, {}, "positive"), (2.0, {}, "positive"), ("2", {}, "positive"),
                          (0, {}, "positive"), (-1, {"lo": 0}, "non-negative"),
                          (2, {"lo": 3}, ">= 3")):
        with pytest.raises(InputError, match=f"`k` must be .*{what}"):
            as_int("k", bad, **kw)


def test_require_variance_names_the_pixels_without_two_samples():
    """mean_var is 0 where n < 2; require_variance refuses such statistics, counting them."""
    from statmc.errors import InputError
    st = PixelStats.from_mean_var(np.ones((3, 4, 3)), np.ones((3, 4, 3)), np.full((3, 4), 5))
    st.require_variance()
    n = st.n.copy()
    n[0, 0], n[2, 3] = 0, 1
    holed = PixelStats(n, st.mean, st.m2)
    with pytest.raises(InputError, match=r"`x` must have >= 2 samples in every pixel \(why\); "
                                         r"got 2 pixels with fewer than 2 samples\. Hint\."):
        holed.require_variance("x", why="why", hint=" Hint.")


def test_as_float_array_half_extended_and_complex():
    """float16 became a numba NotImplementedError in the kernels and complex lost its
    imaginary part with a warning: now float16 -> float32, extended -> float64, complex
    refused."""
    from statmc.errors import as_float_array
    assert as_float_array("a", np.ones(3, np.float16)).dtype == np.float32
    assert as_float_array("a", np.ones(3, np.longdouble)).dtype == np.float64
    assert as_float_array("a", np.ones(3, np.float32)).dtype == np.float32
    with pytest.raises(InputError, match="`a` must be a real numeric array; got dtype complex128"):
        as_float_array("a", np.ones(3, complex))


def test_constructors_refuse_mismatched_counts_and_negative_sums():
    """from_mean_var with an n of another size was a NumPy broadcasting ValueError; from_sums
    clipped a negative sum of squares to M2 = 0 (a silently noise-free pixel)."""
    mean, var, n = np.ones((4, 5, 3)), np.full((4, 5, 3), 0.5), np.full((4, 5), 3)
    with pytest.raises(InputError, match=r"`n` must have the shape .* \(4, 5\); got \(3, 5\)"):
        PixelStats.from_mean_var(mean, var, n[:-1])
    s2 = 3 * (mean ** 2 + var)
    s2[1, 2, 0] = -1.0
    with pytest.raises(InputError, match="`sum_x2` must be >= 0; got 1 negative"):
        PixelStats.from_sums(n, 3 * mean, s2)


def test_sizes_are_checked():
    """PixelStats.empty(-1, 2) was NumPy's "negative dimensions" ValueError and a negative
    `shape` of from_pixel_samples was reported as an index range [0, -5)."""
    with pytest.raises(InputError, match="`height` must be a non-negative integer; got -1"):
        PixelStats.empty(-1, 2)
    with pytest.raises(InputError, match=r"`shape\[0\]` must be a non-negative integer"):
        PixelStats.from_pixel_samples(np.array([0]), np.ones((1, 3)), (-1, 5))
    with pytest.raises(InputError, match=r"`shape` must be \(H, W\)"):
        PixelStats.from_pixel_samples(np.array([0]), np.ones((1, 3)), (2,))


def test_rng_arguments_refuse_what_numpy_cannot_seed():
    """``rng=``/``seed=`` take None, a non-negative int, a SeedSequence or a Generator; a
    string, a float or a negative seed is an InputError naming the argument, not NumPy's
    TypeError/ValueError (errors.as_rng, used by every public function with an rng)."""
    from statmc.errors import as_rng
    from statmc.gem import sampling_map
    from statmc.sampling import counts_from_density
    from statmc.sure import mc_sure
    from statmc.toy import ToyRenderer

    g = np.random.default_rng(1)
    assert as_rng(g) is g
    assert as_rng(5).random() == np.random.default_rng(5).random()
    for bad in ("x", 2.5, -1, [1.5], True, False, np.True_):   # a bool seeded with 0/1
        with pytest.raises(InputError, match="`rng` must be"):
            as_rng(bad)
    with pytest.raises(InputError, match="`rng` must be"):
        counts_from_density(np.ones((4, 4)), 32, rng="x")
    m = np.ones((8, 8, 3))
    with pytest.raises(InputError, match="`rng` must be"):
        sampling_map(m, 0.1 * m, np.full((8, 8), 4), 256, rng="x")
    with pytest.raises(InputError, match="`rng` must be"):
        mc_sure(lambda x: x, m, 0.1 * m, rng=-3)
    with pytest.raises(InputError, match="`seed` must be"):
        ToyRenderer("mixed", width=4, height=4).render(np.ones((4, 4), np.int64), seed="x")
    with pytest.raises(InputError, match="`seed` must be"):
        ToyRenderer("mixed", width=4, height=4).render(np.ones((4, 4), np.int64), seed=True)


# ----------------------------------------------------------------------------- audit (session 8)
def test_from_sums_clips_rounding_below_zero_for_constant_pixels():
    """M2 = Σx² − (Σx)²/n of identical samples is 0 but rounds to ±1e-13: the negative
    residues are clipped to 0 (not refused as a negative M2), the rest stay at rounding."""
    rng = np.random.default_rng(41)
    v = rng.uniform(0, 10, (4, 5, 3))
    n = 7
    s1 = sum(v for _ in range(n))                          # running sums, as a renderer's
    s2 = sum(v * v for _ in range(n))
    raw = s2 - s1 * (s1 / n)
    assert np.any(raw < 0)                                 # the case being tested occurs
    st_ = PixelStats.from_sums(np.full((4, 5), n), s1, s2)
    assert np.all(st_.m2[raw <= 0] == 0)
    assert np.all(st_.m2 <= 1e-14 * s2)
    np.testing.assert_allclose(st_.mean, v, rtol=1e-15)


def test_from_mean_var_pixels_with_fewer_than_two_samples_carry_no_spread():
    """EXR files may hold a non-zero variance where n <= 1 (a renderer's garbage or a
    default): M2 = s²·max(n − 1, 0) and M2_cross likewise are 0 there, not negative."""
    n = np.array([[0, 1, 2, 5]])
    mean = np.ones((1, 4, 3))
    var = np.full((1, 4, 3), 0.5)
    cov = np.full((1, 4, 3), 0.2)                           # pairs RG, RB, GB
    st_ = PixelStats.from_mean_var(mean, var, n, sample_cov=cov)
    np.testing.assert_array_equal(st_.m2[0, :, 0], [0, 0, 0.5, 2.0])
    np.testing.assert_array_equal(st_.m2_cross[0, :, 0, 1], [0, 0, 0.2, 0.8])
    np.testing.assert_array_equal(st_.sample_var[0, :, 0], [0, 0, 0.5, 0.5])


def test_merge_keeps_self_features_and_meta_when_both_have_them():
    """Features come from ``self`` when present (``other`` only fills gaps); ``meta`` is the
    union with ``self``'s entries winning."""
    a = PixelStats.from_samples(np.ones((2, 2, 2, 3))).with_features(
        albedo=np.full((2, 2, 3), 0.25), depth=np.full((2, 2), 3.0))
    a.meta = {"seed": 1, "scene": "a"}
    b = PixelStats.from_samples(np.zeros((3, 2, 2, 3))).with_features(
        albedo=np.full((2, 2, 3), 0.75), normal=np.ones((2, 2, 3)))
    b.meta = {"seed": 2, "spp": 3}
    m = a.merge(b)
    assert np.all(m.albedo == 0.25) and np.all(m.depth == 3.0) and np.all(m.normal == 1.0)
    assert m.meta == {"seed": 1, "scene": "a", "spp": 3}
    assert np.all(b.merge(a).albedo == 0.75) and b.merge(a).meta["seed"] == 2


def test_from_sums_names_the_nonfinite_sum():
    """A NaN in `sum_x` was reported as "`mean` holds 12 NaN" and an Inf in `sum_x2` as
    "`m2` holds ... Inf" (names the caller never passed)."""
    n, s1 = np.full((2, 2), 3), np.ones((2, 2, 3))
    with pytest.raises(InputError, match="`sum_x` holds 12 NaN"):
        PixelStats.from_sums(n, s1 * np.nan, s1)
    with pytest.raises(InputError, match="`sum_x2` holds 0 NaN and 12 Inf"):
        PixelStats.from_sums(n, s1, s1 * np.inf)


def test_constructors_that_build_m2_cross_equal_the_checked_path():
    """from_mean_var, from_sums and from_pixel_samples build ``m2_cross`` exactly symmetric
    with the diagonal ``m2`` and skip the public constructor's check and rebuild
    (``_with_built_cross``; session 11: 0.5 s at 1080p): their matrix is, byte for byte, the
    one ``PixelStats(..., m2_cross=)`` returns, for C = 1, 2, 3 and 5; a non-finite one is
    still refused by name."""
    from statmc.stats import _full_from_pairs
    rng = np.random.default_rng(11)
    h, w = 7, 5
    n = rng.integers(0, 6, (h, w))
    for c in (1, 2, 3, 5):
        p = c * (c - 1) // 2
        mean, var = rng.normal(size=(h, w, c)), rng.exponential(size=(h, w, c))
        cov = rng.normal(size=(h, w, p)) * 0.3
        sx = rng.normal(size=(h, w, c)) * n[..., None]
        sx2 = sx ** 2 + rng.exponential(size=(h, w, c)) * n[..., None]
        idx = rng.integers(0, h * w, 120)
        built = [PixelStats.from_mean_var(mean, var, n, sample_cov=cov),
                 PixelStats.from_sums(n, sx, sx2, rng.normal(size=(h, w, p)) * n[..., None]),
                 PixelStats.from_pixel_samples(idx, rng.normal(size=(120, c)), (h, w))]
        for s in built:
            checked = PixelStats(s.n, s.mean, s.m2, m2_cross=s.m2_cross.copy())
            assert s.m2_cross.dtype == np.float64 and s.m2_cross.shape == (h, w, c, c)
            assert s.m2_cross.tobytes() == checked.m2_cross.tobytes()
        # the slice-assigned matrix is the fancy-indexed one
        iu, k = np.triu_indices(c, 1), np.arange(c)
        ref = np.zeros((h, w, c, c))
        ref[..., iu[0], iu[1]] = ref[..., iu[1], iu[0]] = cov
        ref[..., k, k] = var
        assert _full_from_pairs("x", cov, var).tobytes() == ref.tobytes()
    # sums no samples can have, whose (Σx)²/n overflows although Σx² is finite: refused
    # naming the caller's sums, without a RuntimeWarning on the way (session 17: m2 became 0
    # silently and the pairs' overflow was refused as `m2_cross`)
    big = np.full((1, 1, 3), 1e200)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"`sum_x` and `sum_x2` must be sums of the same "
                                             r"samples.* in 1 pixels \(`sum_x` up to 1e\+200"):
            PixelStats.from_sums(np.full((1, 1), 2), big, np.ones((1, 1, 3)),
                                 np.zeros((1, 1, 3)))


# --------------------------------------------------------------- properties on any samples
@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2 ** 31), h=st.integers(1, 5), w=st.integers(1, 5), c=st.integers(1, 3),
       offset=st.sampled_from([0.0, 1e-20, 1.0, -1e15]), spread=st.sampled_from([0.0, 1e-20, 1.0, 1e15]),
       dtype=st.sampled_from([np.float32, np.float64]), nmax=st.sampled_from([0, 1, 3, 9]),
       parts=st.integers(1, 4))
def test_merge_of_split_pixel_samples_equals_all_samples_on_any_values(seed, h, w, c, offset,
                                                                       spread, dtype, nmax,
                                                                       parts):
    # Chan's update is exact: merging the statistics of any split (pixels with 0, 1 or many
    # samples in each part, float32 or float64 values from 1e-20 to 1e15, constant ones)
    # gives the counts, means and M2 of all samples at once, up to rounding of the
    # means; M2, sample and mean variances are >= 0 (rounding-small for constant samples);
    # merging no samples changes nothing.
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, nmax + 1, size=h * w)
    idx = rng.permutation(np.repeat(np.arange(h * w), counts))
    vals = (offset + spread * rng.standard_normal((idx.size, c))).astype(dtype)
    whole = PixelStats.from_pixel_samples(idx, vals, (h, w))
    cuts = np.sort(rng.integers(0, idx.size + 1, size=parts - 1))
    acc = PixelStats.empty(h, w, c)
    for a, b in zip([0, *cuts], [*cuts, idx.size]):
        acc = acc.merge(PixelStats.from_pixel_samples(idx[a:b], vals[a:b], (h, w)))
    assert np.array_equal(acc.n, counts.reshape(h, w))
    big = float(np.abs(vals.astype(np.float64)).max(initial=0.0))
    ulp = np.finfo(np.float64).eps * big
    np.testing.assert_allclose(acc.mean, whole.mean, rtol=1e-12, atol=8 * ulp)
    tol = 64 * max(1, int(counts.max(initial=0))) * ulp ** 2
    np.testing.assert_allclose(acc.m2, whole.m2, rtol=1e-9, atol=tol)
    for s in (acc, whole):
        assert s.m2.min() >= 0 and np.isfinite(s.m2).all()
        sv = s.sample_var
        assert np.isfinite(sv).all() and sv.min() >= 0 and s.mean_var.min() >= 0
    if spread == 0.0:                 # constant samples: only the rounding of their mean
        assert whole.m2.max(initial=0) <= tol and acc.m2.max(initial=0) <= tol
    same = acc.merge(PixelStats.empty(h, w, c))
    assert np.array_equal(same.n, acc.n) and np.array_equal(same.mean, acc.mean)
    assert np.array_equal(same.m2, acc.m2)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2 ** 31), h=st.integers(1, 4), w=st.integers(1, 4), c=st.integers(1, 3),
       offset=st.sampled_from([0.0, 1e-20, 1.0, 1e15]), spread=st.sampled_from([0.0, 1e-20, 1.0]),
       nmax=st.sampled_from([1, 2, 50]))
def test_from_sums_and_from_mean_var_agree_with_the_samples_on_any_values(seed, h, w, c, offset,
                                                                         spread, nmax):
    # M2 = Σx² − (Σx)²/n cancels catastrophically for a large offset; it is clipped at 0,
    # so the variances stay >= 0 and within rounding of the two-pass M2, and
    # from_mean_var(mean, sample_var, n) gives back the same statistics.
    rng = np.random.default_rng(seed)
    s = nmax
    x = offset + spread * rng.standard_normal((s, h, w, c))
    ref = PixelStats.from_samples(x)
    st_ = PixelStats.from_sums(np.full((h, w), s), x.sum(0), (x * x).sum(0))
    assert st_.m2.min() >= 0 and np.isfinite(st_.sample_var).all() and st_.sample_var.min() >= 0
    ulp = np.finfo(np.float64).eps * float(np.abs(x).max())
    np.testing.assert_allclose(st_.mean, ref.mean, rtol=1e-12, atol=4 * s * ulp)
    np.testing.assert_allclose(st_.m2, ref.m2, rtol=1e-6, atol=16 * s * ulp * float(np.abs(x).max()))
    back = PixelStats.from_mean_var(ref.mean, ref.sample_var, ref.n)
    np.testing.assert_array_equal(back.n, ref.n)
    np.testing.assert_array_equal(back.mean, ref.mean)
    np.testing.assert_allclose(back.m2, ref.m2, rtol=1e-12, atol=0)
    assert back.sample_var.min() >= 0
