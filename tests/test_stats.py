"""PixelStats: exact merging (Chan et al.) against single-pass NumPy, and bad input."""

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
