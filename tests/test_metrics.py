"""Metrics: closed forms on tiny arrays, symmetry, zero on equality, scaling, bad input."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest
from _omp_display import PRINT_BEGIN, PRINT_END, libgomp_settings

from statmc.errors import InputError
from statmc.metrics import (METRICS, _flip_module, all_metrics, flip, logloss, mse,
                            one_minus_ssim, relmse, rmse, smape, ssim_map)


@pytest.fixture
def pair():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.05, 2.0, size=(24, 20, 3))
    x = np.abs(ref + 0.2 * rng.standard_normal(ref.shape))
    return x, ref


# ---------------------------------------------------------------------------- closed forms
def test_relmse_closed_form():
    x = np.array([[[2.0, 0.0]], [[1.0, 3.0]]])          # (2, 1, 2)
    r = np.array([[[1.0, 0.0]], [[1.0, 1.0]]])
    eps = 0.01
    terms = [1 / (1 + eps), 0 / eps, 0 / (1 + eps), 4 / (1 + eps)]
    assert relmse(x, r, eps) == pytest.approx(np.mean(terms), rel=1e-15)
    m = relmse(x, r, eps, per_pixel=True)
    assert m.shape == (2, 1)
    np.testing.assert_allclose(m[:, 0], [np.mean(terms[:2]), np.mean(terms[2:])], rtol=1e-15)


def test_relmse_of_values_whose_squares_overflow_keeps_eps():
    """``(x − r)²/(r² + ε)`` where ``x²`` overflows float64 but the ratio does not: the
    rescaled branch must keep ε in the denominator (``hypot(r/s, √ε/s)``).  Closed form
    ``(x/√(r² + ε))²``, evaluated without overflow; with r = 1 and ε = 0.01 ε is 1% of the
    denominator, and with ε = 0 the value is ``(x/r)²``."""
    x = 1.345e154                                  # x² = 1.809e308 overflows, x²/1.01 does not
    for r, eps in ((1.0, 0.01), (3.0, 1.0), (2.0, 0.0)):
        want = (x / math.sqrt(r * r + eps)) ** 2 if eps else (x / r) ** 2
        assert math.isfinite(want)
        got = relmse(np.array([[x]]), np.array([[r]]), eps=eps)
        assert got == pytest.approx(want, rel=1e-12), (r, eps)
        assert relmse(np.array([[-x]]), np.array([[-r]]), eps=eps) == pytest.approx(want, rel=1e-12)


def test_mse_rmse_closed_form():
    x = np.array([[1.0, 2.0], [3.0, 4.0]])
    r = np.array([[1.0, 0.0], [0.0, 0.0]])
    assert mse(x, r) == pytest.approx((0 + 4 + 9 + 16) / 4)
    assert rmse(x, r) == pytest.approx(math.sqrt(29 / 4))
    np.testing.assert_allclose(rmse(x, r, per_pixel=True), [[0, 2], [3, 4]])


def test_smape_closed_form():
    x = np.array([[3.0, 0.0]])
    r = np.array([[1.0, 2.0]])
    eps = 0.01
    want = np.mean([2 / (4 + eps), 2 / (2 + eps)])
    assert smape(x, r, eps) == pytest.approx(want, rel=1e-15)


def test_logloss_constant_images_closed_form():
    a, b, eps = 3.0, 1.0, 0.01
    x, r = np.full((9, 9, 3), a), np.full((9, 9, 3), b)
    want = 0.5 * abs(math.log1p(a) - math.log1p(b)) / (math.log1p(b) + eps)
    assert logloss(x, r, eps) == pytest.approx(want, rel=1e-12)


def test_logloss_edge_term_vanishes_for_constant_log_offset():
    # LoG is linear and annihilates constants, so with log1p(x) = log1p(r) + c only the
    # first term of Salehi Eq. 12 remains: 0.5 mean(|c| / (r' + eps)).
    rng = np.random.default_rng(2)
    r = rng.uniform(0, 3, size=(16, 12, 2))
    c = 0.3
    x = np.expm1(np.log1p(r) + c)
    want = np.mean(0.5 * c / (np.log1p(r) + 0.01))
    assert logloss(x, r) == pytest.approx(want, rel=1e-10)


def test_logloss_edge_term_matches_definition():
    # Eq. 12 written out with an explicitly sampled, normalised LoG kernel at an interior pixel.
    rng = np.random.default_rng(3)
    r = rng.uniform(0, 2, size=(15, 15, 1))
    x = rng.uniform(0, 2, size=(15, 15, 1))
    sigma, eps = 1.0, 0.01
    rad = int(4 * sigma + 0.5)                                # scipy's default truncation
    t = np.arange(-rad, rad + 1)
    g = np.exp(-t ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    g2 = g * (t ** 2 - sigma ** 2) / sigma ** 4               # d²/dt² of the Gaussian
    g2 -= g2.sum() * g                                       # zero sum: constants map to 0
    kernel = np.outer(g2, g) + np.outer(g, g2)
    xl, rl = np.log1p(x[..., 0]), np.log1p(r[..., 0])
    i = j = 7
    win = np.s_[i - rad:i + rad + 1, j - rad:j + rad + 1]
    lx, lr = (kernel * xl[win]).sum(), (kernel * rl[win]).sum()
    want = 0.5 * abs(xl[i, j] - rl[i, j]) / (rl[i, j] + eps) + 0.5 * abs(lx - lr) / (rl[i, j] + eps)
    got = logloss(x, r, eps, sigma=sigma, per_pixel=True)[i, j]
    assert got == pytest.approx(want, rel=1e-9)


def test_ssim_constant_images_closed_form():
    # Constant images: no structure, SSIM reduces to the luminance term (Wang 2004 Eq. 6).
    a, b, L = 0.3, 0.7, 1.0
    c1 = (0.01 * L) ** 2
    want = (2 * a * b + c1) / (a * a + b * b + c1)
    got = ssim_map(np.full((12, 12, 1), a), np.full((12, 12, 1), b), data_range=L)
    np.testing.assert_allclose(got, want, rtol=1e-10)


def test_ssim_interior_pixel_by_hand():
    rng = np.random.default_rng(4)
    x = rng.random((21, 21))
    y = 0.6 * x + 0.2 * rng.random((21, 21))
    sigma, L = 1.5, 1.0
    rad = int(3.5 * sigma + 0.5)                              # 11 x 11 window (Wang §III.C)
    t = np.arange(-rad, rad + 1)
    g = np.exp(-t ** 2 / (2 * sigma ** 2))
    w = np.outer(g, g)
    w /= w.sum()
    i, j = 10, 9
    xs, ys = x[i - rad:i + rad + 1, j - rad:j + rad + 1], y[i - rad:i + rad + 1, j - rad:j + rad + 1]
    mx, my = (w * xs).sum(), (w * ys).sum()
    vx, vy = (w * (xs - mx) ** 2).sum(), (w * (ys - my) ** 2).sum()
    cxy = (w * (xs - mx) * (ys - my)).sum()
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    want = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    got = ssim_map(x, y, sigma=sigma, data_range=L)[i, j, 0]
    assert got == pytest.approx(want, rel=1e-10)
    assert 0 < one_minus_ssim(x, y) < 1


# ---------------------------------------------------------------------------- properties
@pytest.mark.parametrize("name", list(METRICS))
def test_zero_on_equality(name, pair):
    x, _ = pair
    assert METRICS[name](x, x) == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.abs(METRICS[name](x, x, per_pixel=True)) <= 1e-12)


@pytest.mark.parametrize("name", ["mse", "rmse", "smape", "one_minus_ssim"])
def test_symmetric(name, pair):
    x, r = pair
    assert METRICS[name](x, r) == pytest.approx(METRICS[name](r, x), rel=1e-12)


@pytest.mark.parametrize("name", list(METRICS))
def test_positive_on_difference_and_map_mean(name, pair):
    x, r = pair
    v = METRICS[name](x, r)
    m = METRICS[name](x, r, per_pixel=True)
    assert v > 0
    assert m.shape == x.shape[:2]
    if name != "rmse":                                        # rmse = sqrt(mean), not mean(sqrt)
        assert np.mean(m) == pytest.approx(v, rel=1e-6)
    else:
        assert np.sqrt(np.mean(m ** 2)) == pytest.approx(v, rel=1e-12)


def test_relmse_scale_invariant_without_eps(pair):
    x, r = pair
    for c in (1e-3, 7.0, 1e4):
        assert relmse(c * x, c * r, eps=0.0) == pytest.approx(relmse(x, r, eps=0.0), rel=1e-12)
    # with eps > 0 dark images are down-weighted: scaling down lowers relMSE
    assert relmse(1e-3 * x, 1e-3 * r) < relmse(x, r)


def test_smape_scale_invariant_without_eps_and_bounded(pair):
    x, r = pair
    assert smape(5 * x, 5 * r, eps=0.0) == pytest.approx(smape(x, r, eps=0.0), rel=1e-12)
    assert 0 <= smape(x, -x, eps=0.0) <= 1


def test_mse_scales_quadratically(pair):
    x, r = pair
    assert mse(3 * x, 3 * r) == pytest.approx(9 * mse(x, r), rel=1e-12)


def test_flip_identical_zero_and_black_images():
    rng = np.random.default_rng(5)
    img = rng.random((16, 16, 3))
    assert flip(img, img) == 0.0
    black = np.zeros((16, 16, 3))
    assert flip(black, black) == 0.0
    # flip_evaluator ends the process on an all-black reference: we must not
    assert flip(img, black) > 0.5


def test_flip_scale_invariant_incl_near_black_reference():
    rng = np.random.default_rng(6)
    r = np.full((24, 24, 3), 0.5)
    x = np.abs(r + 0.2 * rng.standard_normal(r.shape))
    base = flip(x, r)
    assert 0 < base < 1
    for c in (1e-3, 1e-9):                                  # 1e-9: below FLIP's epsilon clamp
        assert flip(c * x, c * r) == pytest.approx(base, rel=1e-5)


def test_flip_clips_negative_values_to_zero():
    rng = np.random.default_rng(9)
    r = rng.random((16, 16, 3))
    x = r - 0.3
    assert flip(x, r) == flip(np.maximum(x, 0), r)
    assert flip(r - 1e-16 * (r < 0.5), r, per_pixel=True).max() == 0.0


def test_flip_grey_channel_and_map():
    rng = np.random.default_rng(7)
    r = rng.random((16, 16))
    x = r * 1.2
    assert flip(x, r) == pytest.approx(flip(np.repeat(x[..., None], 3, 2), np.repeat(r[..., None], 3, 2)))
    assert flip(x, r, per_pixel=True).shape == (16, 16)


def test_all_metrics_keys_and_include(pair):
    x, r = pair
    out = all_metrics(x, r)
    assert list(out) == list(METRICS)
    assert all(isinstance(v, float) for v in out.values())
    assert out["relmse"] == relmse(x, r)
    assert list(all_metrics(x, r, include=["mse", "flip"])) == ["mse", "flip"]
    maps = all_metrics(x, r, per_pixel=True, include=["smape"])
    assert maps["smape"].shape == (24, 20)


def test_all_metrics_leaves_out_logloss_outside_its_domain(pair):
    """A reference with negative values (a noisy render as the reference) stops logLoss
    only: it is None with a warning naming the cause, and the other metrics are the
    direct calls' values; ``logloss`` itself still raises."""
    x, r = pair
    r = r.copy()
    r[0, 0] = -5.55e-17                                   # rounding residue, 3 channels
    with pytest.warns(RuntimeWarning, match="3 negative values"):
        out = all_metrics(x, r)
    assert out["logloss"] is None
    assert out["relmse"] == relmse(x, r) and out["mse"] == mse(x, r)
    assert all(isinstance(v, float) for k, v in out.items() if k != "logloss")
    with pytest.raises(InputError, match=">= 0"):
        logloss(x, r)
    with pytest.warns(RuntimeWarning, match="<= -1"):
        assert all_metrics(np.full_like(x, -1.0), pair[1], include=["logloss"]) == {"logloss": None}


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("name", list(METRICS))
def test_shape_mismatch_names_both_shapes(name):
    with pytest.raises(InputError, match=r"x \(4, 5, 3\) and ref \(4, 6, 3\)"):
        METRICS[name](np.ones((4, 5, 3)), np.ones((4, 6, 3)))


@pytest.mark.parametrize("name", list(METRICS))
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_rejected(name, bad):
    x = np.ones((8, 8, 3))
    r = x.copy()
    r[2, 3, 1] = bad
    with pytest.raises(InputError, match="`ref` holds"):
        METRICS[name](x, r)
    with pytest.raises(InputError, match="`x` holds"):
        METRICS[name](r, x)


def test_other_bad_inputs():
    x = np.ones((8, 8, 3))
    with pytest.raises(InputError, match="`x` must have 2 or 3 dimensions"):
        relmse(np.ones(5), np.ones(5))
    with pytest.raises(InputError, match="`eps` must be a finite number >= 0"):
        relmse(x, x, eps=-1)
    with pytest.raises(InputError, match="reference without zeros"):
        relmse(x, 0 * x, eps=0.0)
    with pytest.raises(InputError, match="must be >= 0 for HDR-FLIP"):
        flip(-x, x, negative="error")
    with pytest.raises(InputError, match="`negative`"):
        flip(x, x, negative="abs")
    with pytest.raises(InputError, match="1 or 3 channels"):
        flip(np.ones((8, 8, 2)), np.ones((8, 8, 2)))
    with pytest.raises(InputError, match="`tonemapper`"):
        flip(x, x, tonemapper="filmic")
    with pytest.raises(InputError, match="`ppd`"):
        flip(x, x, ppd=0)
    with pytest.raises(InputError, match=r"`x` must be > -1"):
        logloss(-2 * x, x)
    with pytest.raises(InputError, match="`ref` must be >= 0"):
        logloss(x, -x)
    with pytest.raises(InputError, match="`data_range`"):
        one_minus_ssim(x, x, data_range=0)
    with pytest.raises(InputError, match=r"`include` must name metrics from .*; got unknown "
                       r"\[.psnr.\]"):
        all_metrics(x, x, include=["psnr"])
    with pytest.raises(InputError, match="numeric"):
        mse(np.array([["a"]]), np.array([["b"]]))


def test_ssim_map_covers_whole_image():
    # reflecting borders: the map covers every pixel (no cropping)
    x = np.random.default_rng(8).random((6, 7, 2))
    assert ssim_map(x, 0.5 * x).shape == (6, 7, 2)


# ---------------------------------------------------------------------------- audit (session 8)
def _explicit_windows(a, rad):
    """All ``(2 rad + 1)²`` windows of ``a`` (H, W, C), borders mirrored half-sample
    (``np.pad`` "symmetric" = ``scipy.ndimage`` "reflect"): (H, W, C, k, k)."""
    p = np.pad(a, ((rad, rad), (rad, rad), (0, 0)), mode="symmetric")
    return np.lib.stride_tricks.sliding_window_view(p, (2 * rad + 1, 2 * rad + 1), axis=(0, 1))


@pytest.mark.parametrize("sigma, L, k1, k2", [(1.5, 1.0, 0.01, 0.03), (1.0, 4.0, 0.01, 0.03),
                                              (1.5, 2.0, 0.05, 0.2)])
def test_ssim_map_equals_explicit_window_implementation(sigma, L, k1, k2):
    """Wang et al. 2004 Eq. 13 with the weighted moments of Eqs. 14-16 (Gaussian window of
    sigma truncated at 3.5 sigma: 11 x 11 for sigma = 1.5, §III.C), written out window by
    window over the whole map, borders included (scikit-image is not installed).  Kills
    C2 built from k1, a `sigma` or `data_range` that does not reach the window/constants."""
    rng = np.random.default_rng(21)
    x = L * rng.random((13, 15, 2))
    y = np.clip(0.7 * x + 0.3 * L * rng.random(x.shape), 0, L)
    rad = int(3.5 * sigma + 0.5)
    t = np.arange(-rad, rad + 1)
    g = np.exp(-t ** 2 / (2 * sigma ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    xw, yw = _explicit_windows(x, rad), _explicit_windows(y, rad)
    mx, my = (w * xw).sum((-2, -1)), (w * yw).sum((-2, -1))
    dx, dy = xw - mx[..., None, None], yw - my[..., None, None]
    vx, vy = (w * dx * dx).sum((-2, -1)), (w * dy * dy).sum((-2, -1))
    cxy = (w * dx * dy).sum((-2, -1))
    c1, c2 = (k1 * L) ** 2, (k2 * L) ** 2
    want = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    got = ssim_map(x, y, data_range=L, sigma=sigma, k1=k1, k2=k2)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    if (k1, k2) == (0.01, 0.03):
        assert one_minus_ssim(x, y, data_range=L, sigma=sigma) == pytest.approx(
            float(np.mean(1 - want)), rel=1e-10)


@pytest.mark.parametrize("sigma, eps", [(1.0, 0.01), (1.7, 0.1)])
def test_logloss_map_equals_explicit_eq12(sigma, eps):
    """Salehi 2022 Eq. 12 over the whole map with x' = log(1 + x), an explicitly sampled
    zero-sum LoG window (radius int(4 sigma + 0.5)) and mirrored borders: kills a `sigma`
    that does not reach the LoG, a dropped log1p, a denominator in linear units."""
    rng = np.random.default_rng(22)
    r = rng.uniform(0, 3, size=(14, 17, 2))
    x = np.abs(r + 0.5 * rng.standard_normal(r.shape))
    rad = int(4 * sigma + 0.5)
    t = np.arange(-rad, rad + 1)
    g = np.exp(-t ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    g2 = g * (t ** 2 - sigma ** 2) / sigma ** 4
    g2 -= g2.sum() * g
    kernel = np.outer(g2, g) + np.outer(g, g2)
    xl, rl = np.log1p(x), np.log1p(r)
    lx = (kernel * _explicit_windows(xl, rad)).sum((-2, -1))
    lr = (kernel * _explicit_windows(rl, rad)).sum((-2, -1))
    ell = 0.5 * np.abs(xl - rl) / (rl + eps) + 0.5 * np.abs(lx - lr) / (rl + eps)
    np.testing.assert_allclose(logloss(x, r, eps, sigma=sigma, per_pixel=True), ell.mean(2),
                               rtol=1e-9, atol=1e-12)
    assert logloss(x, r, eps, sigma=sigma) == pytest.approx(float(ell.mean()), rel=1e-10)


def _flip_direct(x, r, params):
    flip_evaluator = _flip_module()        # the same module; a plain import first would skip
    m, e, _ = flip_evaluator.evaluate(np.ascontiguousarray(r, np.float32),
                                      np.ascontiguousarray(x, np.float32), "HDR",
                                      applyMagma=False, parameters=params)
    return np.asarray(m, np.float64).reshape(r.shape[:2]), float(e)


def test_flip_passes_reference_tonemapper_and_ppd_to_flip_evaluator():
    """flip(x, ref) is flip_evaluator.evaluate(reference=ref, test=x) with our tonemapper
    and ppd.  flip_evaluator silently falls back to ACES on a name it does not know
    ("Hable" instead of "hable"), so the three tone curves must also give three values."""
    rng = np.random.default_rng(23)
    r = 3 * rng.random((12, 16, 3))
    x = np.abs(r + 0.4 * rng.standard_normal(r.shape))
    x[3, 4] = 40.0                                        # test != ref roles matter
    vals = []
    for tm, ppd in (("aces", None), ("hable", None), ("reinhard", None), ("aces", 25.0)):
        params = {"tonemapper": tm} if ppd is None else {"tonemapper": tm, "ppd": ppd}
        m, e = _flip_direct(x, r, params)
        assert flip(x, r, tonemapper=tm, ppd=ppd) == e
        np.testing.assert_array_equal(flip(x, r, tonemapper=tm, ppd=ppd, per_pixel=True), m)
        vals.append(e)
    assert len(set(vals)) == len(vals), vals
    assert flip(x, r) != flip(r, x)                       # the reference sets the exposures


@pytest.mark.parametrize("tm", ["aces", "hable", "reinhard"])
def test_flip_near_black_exposures_equal_flip_evaluators_own(tm):
    """For a (near-)black reference we compute HDR-FLIP's exposure range ourselves
    (_flip_exposures).  Scaled into that regime (Y_max = 2 float32 eps, median above the
    eps clamp), our start/stop shifted back by log2(scale) must equal the range
    flip_evaluator picks for the unscaled reference: this pins the tone-curve
    coefficients and the median (FLIP takes the upper middle element, not the mean of
    the two middle ones), which FLIP's scale invariance needs."""
    from statmc.metrics import _FLT_EPS, _flip_exposures
    flip_evaluator = _flip_module()
    rng = np.random.default_rng(24)
    r = rng.uniform(0.6, 1.0, (16, 16, 3))                 # even pixel count: median matters
    x = np.abs(r + 0.2 * rng.standard_normal(r.shape))
    _, _, p = flip_evaluator.evaluate(r.astype(np.float32), x.astype(np.float32), "HDR",
                                      applyMagma=False, parameters={"tonemapper": tm})
    s = 2 * _FLT_EPS / float((r @ np.array([0.2126, 0.7152, 0.0722])).max())
    start, stop = _flip_exposures(s * r, s * x, tm)
    assert start + np.log2(s) == pytest.approx(p["startExposure"], abs=2e-6)
    assert stop + np.log2(s) == pytest.approx(p["stopExposure"], abs=2e-6)


def test_defaults_are_the_papers_constants(pair):
    """relMSE ε = 0.01 (Rousselle 2011 §7), SMAPE ε = 0.01 (Vogels 2018), logLoss ε = 0.01
    (Salehi 2022 Eq. 12) with our 1-px LoG, SSIM K1 = 0.01, K2 = 0.03, σ = 1.5 (11 × 11,
    Wang 2004 §III.C) at L = 1, and HDR-FLIP with flip_evaluator's own defaults (ACES,
    67 ppd).  The closed-form tests pass these explicitly, so the defaults are pinned here."""
    x, r = pair
    assert relmse(x, r) == relmse(x, r, 0.01)
    assert relmse(x, r) != relmse(x, r, 0.001)
    assert smape(x, r) == smape(x, r, 0.01)
    assert logloss(x, r) == logloss(x, r, 0.01, sigma=1.0)
    explicit = ssim_map(x, r, data_range=1.0, sigma=1.5, k1=0.01, k2=0.03)
    np.testing.assert_array_equal(ssim_map(x, r), explicit)
    assert one_minus_ssim(x, r) == float(np.mean(1.0 - explicit))
    assert flip(x, r) == _flip_direct(x, r, {})[1]


# ------------------------------------------------------------ FLIP's bundled OpenMP runtime
_FLIP_CONCURRENT_IMPORT = """
import sys, threading, time
sys.path.insert(0, sys.argv[1])          # a slow stand-in package named flip_evaluator
from statmc.metrics import _flip_module
first = threading.Thread(target=_flip_module)
first.start()
while "flip_evaluator" not in sys.modules:   # the first import has begun, not finished
    time.sleep(0.001)
mod = _flip_module()
print(getattr(mod, "evaluate", "half-initialised"))
first.join()
"""


def test_flip_module_waits_for_an_import_running_in_another_thread(tmp_path):
    """Regression (session 9 review): while one thread imports flip_evaluator,
    ``sys.modules`` already holds the half-initialised package; ``_flip_module`` returned
    it to a second thread (which then failed on a missing ``evaluate``).  Now it waits for
    the import, as a plain ``import`` does.  A stand-in package that takes 0.5 s to load
    makes the window wide; the old code printed 'half-initialised'."""
    pkg = tmp_path / "flip_evaluator"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("import time\ntime.sleep(0.5)\nevaluate = 'complete'\n")
    p = subprocess.run([sys.executable, "-c", _FLIP_CONCURRENT_IMPORT, str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "complete", p.stdout + p.stderr


_FLIP_OMP_PROBE = f"""
import os, sys
import numpy as np
from statmc.metrics import _flip_module, flip
{PRINT_BEGIN}
_flip_module()
{PRINT_END}
v = flip(np.full((8, 8, 3), 0.3), np.full((8, 8, 3), 0.5))
print(repr(os.environ.get("OMP_WAIT_POLICY")), v, file=sys.stderr)
"""


def _bundled_libgomp():
    """flip_evaluator's own libgomp copy (``flip_evaluator.libs/libgomp*``), or None."""
    import glob
    import importlib.util
    spec = importlib.util.find_spec("flip_evaluator")
    if spec is None or spec.origin is None:
        return None
    site = os.path.dirname(os.path.dirname(spec.origin))
    found = sorted(glob.glob(os.path.join(site, "flip_evaluator.libs", "libgomp*")))
    return found[0] if found else None


def _omp_settings_seen_by_flip(**env_extra):
    """Run flip in a fresh interpreter with OMP_DISPLAY_ENV=VERBOSE (tests/_omp_display.py):
    FLIP's runtime prints while ``_flip_module`` imports flip_evaluator (between the probe's
    two markers; runtimes loaded with numpy or statmc print before).  Returns ([(spin count,
    wait policy) of each libgomp block], env after, FLIP value)."""
    gomp, lines = libgomp_settings(_FLIP_OMP_PROBE, **env_extra)
    assert gomp, "no libgomp printout while flip_evaluator was imported:\n" + "\n".join(lines)
    after, value = lines[-1].rsplit(" ", 1)
    return gomp, after, float(value)


def test_flip_runtime_waits_passively_and_environment_is_restored():
    """Regression (session 8): flip_evaluator's bundled libgomp spin-waits by default
    (GOMP_SPINCOUNT 300000); under load one 16x16 call took ~210 ms instead of ~0.6 ms
    (bench/bench_flip_load.py).  statmc imports it with OMP_WAIT_POLICY=PASSIVE (spin
    count 0) set for the import only: the old code (plain ``import flip_evaluator``) loaded
    it with spin count 300000 (and policy 'PASSIVE' all the same: the spin count is what
    tells).  The user's environment is unchanged afterwards.  Only the libgomp runtime(s)
    loaded by the import are read (see _omp_settings_seen_by_flip), so other OpenMP
    runtimes in the process do not matter; skipped where the wheel bundles no libgomp."""
    if _bundled_libgomp() is None:
        pytest.skip("this flip_evaluator has no bundled flip_evaluator.libs/libgomp*")
    gomp, after, value = _omp_settings_seen_by_flip()
    assert gomp == [("0", "PASSIVE")] * len(gomp) and after == "None", gomp
    # a wait policy the user chose is theirs: statmc keeps out
    gomp_u, after_u, value_u = _omp_settings_seen_by_flip(OMP_WAIT_POLICY="ACTIVE")
    assert all(policy == "ACTIVE" and spin != "0" for spin, policy in gomp_u), gomp_u
    assert after_u == "'ACTIVE'"
    assert value_u == value                                # the wait policy never changes FLIP


# ---------------------------------------------------------------------------- wide windows (session 11)
def _wide_pair(shape=(16, 16, 3), seed=31):
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.05, 2.0, size=shape)
    return np.abs(r + 0.3 * rng.standard_normal(shape)), r


def test_logloss_and_ssim_with_an_absurd_sigma_stay_small():
    """Regression (session 11): logloss(sigma=1e6) on 16x16 built 2·int(4σ+0.5)+1 = 8e6
    taps and ran them through correlate1d (28 s, 244 MiB); ssim_map's gaussian_filter the
    same with 3.5σ.  The kernels are now folded onto the 32-pixel period of the reflected
    image.  Both also have closed forms there: a window flat over the period blurs the
    reflected image to its global mean (SSIM of the global moments), and the LoG of a
    flat window is ~0 (logLoss = its first term); the taps differ from flat by
    ~(32/σ)² ~ 1e-9."""
    import tracemalloc
    x, r = _wide_pair()
    tracemalloc.start()
    try:
        ll = logloss(x, r, sigma=1e6)
        s = ssim_map(x, r, sigma=1e6)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2 ** 20, f"peak {peak / 2 ** 20:.1f} MiB"
    xl, rl = np.log1p(x), np.log1p(r)
    assert ll == pytest.approx(np.mean(0.5 * np.abs(xl - rl) / (rl + 0.01)), rel=1e-7)
    mx, my = x.mean((0, 1)), r.mean((0, 1))
    vx, vy = x.var((0, 1)), r.var((0, 1))
    cxy = ((x - mx) * (r - my)).mean((0, 1))
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    want = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    np.testing.assert_allclose(s, np.broadcast_to(want, s.shape), rtol=1e-7)


@pytest.mark.parametrize("shape", [(16, 12, 3), (1, 7, 2), (5, 1, 1), (33, 20, 1)])
def test_folded_kernels_equal_the_whole_ones(shape, monkeypatch):
    """The folded path (taps summed modulo the reflection's period 2n, per axis) gives
    what the whole kernel gives through scipy's reflect mode, up to rounding, for σ
    below, near and far beyond the image size (forced on by a limit of 0 taps)."""
    import statmc.metrics as m
    x, r = _wide_pair(shape, seed=32)
    for sigma in (0.6, 2.5, 7.0, 40.0):
        ll, s = logloss(x, r, sigma=sigma, per_pixel=True), ssim_map(x, r, sigma=sigma)
        monkeypatch.setattr(m, "_MAX_FULL_RADIUS", 0)
        ll_f, s_f = logloss(x, r, sigma=sigma, per_pixel=True), ssim_map(x, r, sigma=sigma)
        monkeypatch.undo()
        np.testing.assert_allclose(ll_f, ll, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(s_f, s, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("sigma", [4.3e6, 1e300])
def test_sigma_past_the_fold_limit_is_refused(sigma):
    x, r = _wide_pair((4, 4, 1))
    with pytest.raises(InputError, match=r"`sigma` must be at most 4.194e\+06 pixels for the "
                                         r"logLoss LoG.*got"):
        logloss(x, r, sigma=sigma)
    with pytest.raises(InputError, match=r"`sigma` must be at most 4.793e\+06 pixels for "
                                         r"SSIM's window.*got"):
        one_minus_ssim(x, r, sigma=max(sigma, 4.8e6))


# --------------------------------------------------------------- properties on any image
from hypothesis import given, settings, strategies as st  # noqa: E402


def _any_pair(seed, h, w, c, dtype, scale, same_frac):
    """A non-negative reference of magnitude up to ``scale`` (a flat block, all black when
    ``scale`` is 0) and a test image equal to it on a fraction ``same_frac`` of pixels;
    ``c = 0`` gives (H, W) images."""
    rng = np.random.default_rng(seed)
    shp = (h, w) if c == 0 else (h, w, c)
    ref = np.abs(rng.normal(size=shp)) * scale * rng.gamma(0.5, 1, size=shp)
    ref[: h // 2, : w // 2] = ref[0, 0]
    x = np.abs(ref + scale * rng.normal(size=shp))
    same = rng.uniform(size=(h, w)) < same_frac
    x[same] = ref[same]
    return x.astype(dtype), ref.astype(dtype)


_PAIRS = dict(seed=st.integers(0, 2 ** 31), h=st.integers(1, 12), w=st.integers(1, 12),
              c=st.integers(0, 3), dtype=st.sampled_from([np.float32, np.float64]),
              scale=st.sampled_from([0.0, 1e-20, 1.0, 1e15]),
              same_frac=st.sampled_from([0.0, 0.5, 1.0]))


@settings(max_examples=60, deadline=None)
@given(eps=st.sampled_from([0.01, 1e-30, 1.0]), **_PAIRS)
def test_error_metrics_are_non_negative_and_zero_for_identical_images_on_any_image(
        seed, h, w, c, dtype, scale, same_frac, eps):
    # relMSE, SMAPE, logLoss and MSE are means of non-negative per-pixel terms, each 0 where
    # x = ref; SMAPE lies in [0, 1) and is symmetric; the scalar is the mean of the map.
    x, ref = _any_pair(seed, h, w, c, dtype, scale, same_frac)
    for fn, kw in ((relmse, dict(eps=eps)), (smape, dict(eps=eps)), (logloss, dict(eps=eps)),
                   (mse, {})):
        v = fn(x, ref, **kw)
        m = fn(x, ref, per_pixel=True, **kw)
        assert isinstance(v, float) and math.isfinite(v) and v >= 0, fn.__name__
        assert m.shape == (h, w) and np.isfinite(m).all() and m.min() >= 0, fn.__name__
        assert v == pytest.approx(m.mean(), rel=1e-9, abs=1e-300), fn.__name__
        if same_frac == 1.0:
            assert v == 0.0 and fn(ref, ref, **kw) == 0.0, fn.__name__
    s = smape(x, ref, eps=eps, per_pixel=True)
    assert s.max() < 1.0
    np.testing.assert_allclose(s, smape(ref, x, eps=eps, per_pixel=True), rtol=1e-15)


@settings(max_examples=50, deadline=None)
@given(sigma=st.sampled_from([0.5, 1.5, 40.0]), **_PAIRS)
def test_ssim_is_one_for_identical_images_and_within_minus_one_one_on_any_image(
        seed, h, w, c, dtype, scale, same_frac, sigma):
    # Eq. 13 of Wang 2004 is a product of two factors in [−1, 1] (2ab <= a² + b² and
    # Cauchy–Schwarz for the window moments), and 1 for identical images; the data range
    # is the span of the images (>= 1), as the docstring asks for HDR values.
    x, ref = _any_pair(seed, h, w, c, dtype, scale, same_frac)
    L = max(1.0, float(np.max(ref)), float(np.max(x)))
    s = ssim_map(x, ref, data_range=L, sigma=sigma)
    assert s.shape == (h, w, max(c, 1)) and np.isfinite(s).all()
    assert (np.abs(s) <= 1 + 1e-9).all()
    np.testing.assert_allclose(ssim_map(ref, ref, data_range=L, sigma=sigma), 1.0, rtol=1e-12)
    d = one_minus_ssim(x, ref, data_range=L, sigma=sigma)
    assert 0 <= d + 1e-9 and d <= 2 + 1e-9
    if same_frac == 1.0:
        assert d == pytest.approx(0.0, abs=1e-12)
