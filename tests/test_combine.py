"""Tests for statmc.combine (Back et al. 2020, Eq. 6-15).

Theorems are checked against independent computations: Eq. 8/14 against a least-squares
solver on Eq. 6/13, Eq. 15 against Eq. 8, Eq. 11 against dense linear algebra and, with
the toy renderer, Eq. 10/11 against Monte Carlo bias and variance (chi-square tests on
pixels far enough apart to be independent).  The compiled kernel is compared with the
NumPy reference on random inputs including borders.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from _images import any_image, image_args
from _memory import traced_peak
from statmc import _combine_kernels as ck
from statmc import denoisers
from statmc.analytic import apply_kernels
from statmc.combine import (buffer_moments, combine, combine_bias_variance, combine_bin_images,
                            combine_bins, combine_boosting,
                            combine_denoised, combine_multi, denoiser_moments,
                            filter_covariance, gaussian_weights, statistical_weights,
                            uniform_weights)
from statmc.errors import InputError
from statmc.stats import PixelStats
from statmc.toy import ToyRenderer

ALPHA = 1e-3   # family-wise level of the statistical tests in this file


# --------------------------------------------------------------------------- helpers
def _window_pixels(H, W, k, y, x):
    """``[(dy, dx, yy, xx)]`` of the taps of pixel (y, x) inside the image."""
    r = k // 2
    return [(dy, dx, y + dy - r, x + dx - r) for dy in range(k) for dx in range(k)
            if 0 <= y + dy - r < H and 0 <= x + dx - r < W]


def _lstsq_beta_c(ys, zs, w, y, x):
    """Minimise Eq. 13 (Eq. 6 for B = 1) of pixel (y, x) with a generic solver.

    Unknowns: beta_c and one beta_i per neighbour inside the image.  Rows are the
    weighted residuals sqrt(w_c/2)(y_c - beta_c), sqrt(w_i)(y_i - beta_i) and
    sqrt(w_i)((z_c - z_i) - (beta_c - beta_i)), per bin and channel.
    """
    B, H, W, C = ys.shape
    k = w.shape[3]
    r = k // 2
    taps = [t for t in _window_pixels(H, W, k, y, x) if (t[0], t[1]) != (r, r)]
    n = 1 + len(taps)
    out = np.empty(C)
    for c in range(C):
        rows, rhs = [], []
        for b in range(B):
            s = np.sqrt(w[y, x, b, r, r] / 2.0)
            row = np.zeros(n)
            row[0] = s
            rows.append(row)
            rhs.append(s * ys[b, y, x, c])
            for j, (dy, dx, yy, xx) in enumerate(taps, start=1):
                s = np.sqrt(w[y, x, b, dy, dx])
                row = np.zeros(n)
                row[j] = s
                rows.append(row)
                rhs.append(s * ys[b, yy, xx, c])
                row = np.zeros(n)
                row[0], row[j] = s, -s
                rows.append(row)
                rhs.append(s * (zs[b, y, x, c] - zs[b, yy, xx, c]))
        sol, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
        out[c] = sol[0]
    return out


def _renormalised_gaussian(H, W, k, sigma):
    """Per-pixel Gaussian kernels, renormalised over the taps inside the image."""
    g = np.array(gaussian_weights(H, W, 1, k, sigma)[:, :, 0], dtype=np.float64)
    r = k // 2
    for dy in range(k):
        for dx in range(k):
            yy = np.arange(H)[:, None] + dy - r
            xx = np.arange(W)[None, :] + dx - r
            g[:, :, dy, dx] *= (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
    return g / g.sum(axis=(2, 3), keepdims=True)


def _dense_operator(K, H, W):
    """The (HW x HW) matrix of ``apply_kernels(K, .)`` (zero outside)."""
    k = K.shape[2]
    A = np.zeros((H * W, H * W))
    for y in range(H):
        for x in range(W):
            for dy, dx, yy, xx in _window_pixels(H, W, k, y, x):
                A[y * W + x, yy * W + xx] += K[y, x, dy, dx]
    return A


def _chi2_pvalue(zscores):
    z = np.asarray(zscores).ravel()
    return stats.chi2.sf(float(np.sum(z * z)), z.size)


# --------------------------------------------------------------------------- Eq. 6 -> Eq. 8
@pytest.mark.parametrize("B,k", [(1, 3), (1, 5), (3, 3)])
def test_eq8_and_eq14_are_the_least_squares_minimisers(B, k):
    rng = np.random.default_rng(10 + B + k)
    H, W, C = 7, 9, 2
    ys = rng.normal(size=(B, H, W, C))
    zs = rng.normal(size=(B, H, W, C))
    w = rng.uniform(0.05, 2.0, size=(H, W, B, k, k))
    out = combine_multi(ys, zs, w) if B > 1 else combine(ys[0], zs[0], w[:, :, 0])
    for (y, x) in [(3, 4), (0, 0), (0, 5), (6, 8), (1, 1), (6, 0)]:
        ref = _lstsq_beta_c(ys, zs, w, y, x)
        np.testing.assert_allclose(out[y, x], ref, rtol=1e-10, atol=1e-12)


def test_eq7_printed_gradients_are_minus_and_half_the_true_ones():
    """Erratum: Eq. 7 prints -dJ/dbeta_c and dJ/dbeta_i / 2; Eq. 8 is unaffected."""
    rng = np.random.default_rng(1)
    n = 6                                         # neighbours i
    yc, zc, wc = rng.normal(), rng.normal(), rng.uniform(0.1, 2)
    yi, zi, wi = rng.normal(size=n), rng.normal(size=n), rng.uniform(0.1, 2, n)
    bc, bi = rng.normal(), rng.normal(size=n)     # an arbitrary point, not the optimum

    def J(bc, bi):   # Eq. 6
        return (0.5 * wc * (yc - bc) ** 2 + np.sum(wi * (yi - bi) ** 2)
                + np.sum(wi * ((zc - zi) - (bc - bi)) ** 2))

    h = 1e-5         # J is quadratic: central differences are exact up to rounding
    g_c = (J(bc + h, bi) - J(bc - h, bi)) / (2 * h)
    g_i = np.array([(J(bc, bi + h * e) - J(bc, bi - h * e)) / (2 * h) for e in np.eye(n)])
    printed_c = wc * (yc - bc) + 2 * np.sum(wi * ((zc - zi) - (bc - bi)))
    printed_i = -wi * (yi - bi) + wi * ((zc - zi) - (bc - bi))
    np.testing.assert_allclose(printed_c, -g_c, rtol=1e-7)
    np.testing.assert_allclose(printed_i, g_i / 2, rtol=1e-7)
    assert not np.isclose(printed_c, g_c)
    # Eq. 8 zeroes the true gradient once beta_i = (y_i - z_c + z_i + beta_c) / 2.
    b8 = (wc * yc + np.sum(wi * yi) + np.sum(wi * (zc - zi))) / (wc + wi.sum())
    bi8 = 0.5 * (yi - zc + zi + b8)
    for j in range(n + 1):
        e = np.zeros(n + 1)
        e[j] = h
        g = (J(b8 + e[0], bi8 + e[1:]) - J(b8 - e[0], bi8 - e[1:])) / (2 * h)
        assert abs(g) < 1e-8


# --------------------------------------------------------------------------- Eq. 15, conventions
@pytest.mark.parametrize("shape,k", [((8, 11, 3), 5), ((4, 3, 1), 7), ((16, 9, 4), 3)])
def test_eq15_boosting_form_equals_eq8(shape, k):
    rng = np.random.default_rng(sum(shape) + k)
    y = rng.normal(size=shape)
    z = rng.normal(size=shape)
    w = rng.uniform(0.01, 1.0, size=shape[:2] + (k, k))
    np.testing.assert_allclose(combine_boosting(y, z, w), combine(y, z, w), rtol=1e-12, atol=1e-13)


def test_window_convention_matches_apply_kernels():
    rng = np.random.default_rng(5)
    H, W, C, k = 10, 13, 3, 5
    y, z = rng.normal(size=(2, H, W, C))
    w = rng.uniform(0.1, 1.0, size=(H, W, k, k))
    expected = z + apply_kernels(w, y - z) / apply_kernels(w, np.ones((H, W)))[..., None]
    np.testing.assert_allclose(combine(y, z, w), expected, rtol=1e-12, atol=1e-13)
    # outside taps are never read: poisoning them changes nothing
    wp = w.copy()
    wp[0, 0, 0, :] = np.nan
    wp[-1, -1, -1, -1] = np.inf
    np.testing.assert_array_equal(combine(y, z, wp), combine(y, z, w))
    np.testing.assert_allclose(combine_boosting(y, z, wp), combine(y, z, w), rtol=1e-12, atol=1e-13)


def test_invariances_and_special_cases():
    rng = np.random.default_rng(6)
    H, W, C, k = 9, 10, 3, 5
    y, z = rng.normal(size=(2, H, W, C))
    w = rng.uniform(0.1, 1.0, size=(H, W, k, k))
    out = combine(y, z, w)
    np.testing.assert_allclose(combine(y, z + 7.5, w), out, atol=1e-12)        # z offset cancels
    np.testing.assert_allclose(combine(y + 2.0, z + 2.0, w), out + 2.0, atol=1e-12)
    np.testing.assert_allclose(combine(y, z, 3.0 * w), out, atol=1e-12)          # scale-free
    np.testing.assert_allclose(combine(y, y, w), y, atol=1e-12)                  # z = y -> y
    np.testing.assert_allclose(combine(z, z + 1.0, w), z, atol=1e-12)
    cw = np.zeros((H, W, k, k))
    cw[:, :, k // 2, k // 2] = 1.0                                               # centre only
    np.testing.assert_allclose(combine(y, z, cw), y, atol=1e-14)
    # a single buffer through combine_multi is combine
    np.testing.assert_allclose(combine_multi(y[None], z[None], w[:, :, None]), out, atol=1e-14)
    # (H, W) images
    np.testing.assert_allclose(combine(y[..., 1], z[..., 1], w), out[..., 1], atol=1e-14)
    # Eq. 14 with identical bins is Eq. 8
    np.testing.assert_allclose(combine_multi(np.stack([y] * 4), np.stack([z] * 4),
                                             np.stack([w] * 4, axis=2)), out, atol=1e-12)


def test_dtype_policy():
    rng = np.random.default_rng(7)
    y, z = rng.random((2, 6, 7, 3), dtype=np.float32)
    w = rng.random((6, 7, 3, 3), dtype=np.float32)
    assert combine(y, z, w).dtype == np.float32
    assert combine(y.astype(np.float64), z, w).dtype == np.float64
    assert combine(y.astype(np.int32), z.astype(np.int32), w).dtype == np.float64
    assert combine_boosting(y, z, w).dtype == np.float32


# --------------------------------------------------------------------------- numba vs NumPy
@pytest.mark.parametrize("B,H,W,C,k,dtype", [
    (4, 23, 37, 3, 15, np.float32),   # the target configuration, window larger than the image rows
    (4, 40, 41, 3, 5, np.float32),
    (1, 17, 19, 3, 3, np.float64),
    (2, 9, 30, 1, 7, np.float64),
    (3, 12, 14, 4, 5, np.float32),    # channel groups 3 + 1
    (1, 5, 6, 2, 9, np.float64),      # image smaller than the window
    (2, 1, 1, 5, 3, np.float64),
    (1, 8, 8, 3, 1, np.float32),
])
def test_numba_kernel_matches_numpy_reference(B, H, W, C, k, dtype):
    rng = np.random.default_rng(B * 1000 + H * 10 + k)
    ys = rng.normal(1.0, 1.0, size=(B, H, W, C)).astype(dtype)
    zs = rng.normal(1.0, 0.5, size=(B, H, W, C)).astype(dtype)
    w = rng.uniform(0.0, 1.0, size=(H, W, B, k, k)).astype(dtype)
    ref = ck.combine_numpy(w, ys, zs)
    out = combine_multi(ys, zs, w)
    assert out.dtype == dtype
    if dtype == np.float64:
        np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)
    else:   # float64 accumulation, one rounding to float32 at the end
        np.testing.assert_allclose(out, ref, rtol=2 ** -23, atol=2 ** -23 * np.abs(ref).max())


def test_numba_kernel_with_broadcast_and_strided_inputs():
    rng = np.random.default_rng(8)
    B, H, W, C, k = 4, 20, 33, 3, 7
    ys = rng.normal(size=(B, H, W + 5, C))[:, :, 2:-3]           # non-contiguous
    zs = rng.normal(size=(B, W, H, C)).transpose(0, 2, 1, 3)    # transposed
    w = gaussian_weights(H, W, B, k, 2.0)                       # broadcast, read-only
    ref = ck.combine_numpy(np.asarray(w), ys, zs)
    np.testing.assert_allclose(combine_multi(ys, zs, w), ref, rtol=1e-12, atol=1e-12)
    signed = rng.normal(size=(H, W, B, k, k))
    signed[:, :, 0, k // 2, k // 2] = 50.0                      # keep W_c away from 0
    np.testing.assert_allclose(combine_multi(ys, zs, signed), ck.combine_numpy(signed, ys, zs),
                               rtol=1e-10, atol=1e-10)


# --------------------------------------------------------------------------- Eq. 10 / 11 exact
@pytest.mark.parametrize("correlated", [False, True])
def test_eq11_matches_dense_linear_algebra(correlated):
    """Var of the linear map beta = A y + (I - A) z with z = F x, against Eq. 11."""
    rng = np.random.default_rng(11 + correlated)
    H, W, C, k, kf = 7, 8, 2, 3, 5
    N = H * W
    F = rng.random((H, W, kf, kf))
    w = rng.random((H, W, k, k))
    vx = rng.random((H, W, C)) + 0.1
    vy = rng.random((H, W, C)) + 0.1
    Fm, Wm = _dense_operator(F, H, W), _dense_operator(w, H, W)
    A = Wm / Wm.sum(axis=1, keepdims=True)
    Bz = np.eye(N) - A
    cov_z, cross = filter_covariance(F, vx, size=2 * k - 1, cross=True)
    if correlated:   # y = x, z = F y: the cross-covariance term is needed
        _, var = combine_bias_variance(w, vx, cov_z, cov_yz=cross)
    else:
        _, var = combine_bias_variance(w, vy, cov_z)
    for c in range(C):
        Sx = np.diag(vx[..., c].ravel())
        Sz = Fm @ Sx @ Fm.T
        if correlated:
            Sy, Syz = Sx, Sx @ Fm.T
        else:
            Sy, Syz = np.diag(vy[..., c].ravel()), np.zeros((N, N))
        V = A @ Sy @ A.T + Bz @ Sz @ Bz.T + A @ Syz @ Bz.T + Bz @ Syz.T @ A.T
        np.testing.assert_allclose(var[..., c], np.diag(V).reshape(H, W), rtol=1e-10, atol=1e-13)
    # the stencil itself: every entry of F diag(v) F^T
    Sz = Fm @ np.diag(vx[..., 0].ravel()) @ Fm.T
    full, _ = filter_covariance(F, vx, cross=True)
    R = full.shape[2] // 2
    for p in range(N):
        py, px = divmod(p, W)
        for q in range(N):
            qy, qx = divmod(q, W)
            v = (qy - py, qx - px)
            got = full[py, px, R + v[0], R + v[1], 0] if max(map(abs, v)) <= R else 0.0
            assert abs(got - Sz[p, q]) < 1e-12


def test_tap_moments_of_the_weights_match_dense_linear_algebra():
    """The per-tap moments behind statistical_weights, with ``z = F x`` computed from
    ``y = x`` (so ``cov_yz`` matters): ``Cov(e_t, e_s)`` of ``e_t = y_t + z_c − z_t``
    (``_Moments.pair``, Eq. 11's matrix, used by "full" and on its diagonal by "coherent"
    and "diagonal") and ``Var(δ_t)`` of ``δ_t = (z_c − z_t) − (y_c − y_t)`` (``_delta_var``,
    subtracted from the tap-bias estimate), against the rows of the dense linear maps of
    ``x``, at interior and border pixels.  Catches a wrong sign, factor or offset in any
    of their cross terms (the kernel-vs-reference tests cannot: both share the formula)."""
    from statmc.combine import _delta_var, _Moments, _offsets

    rng = np.random.default_rng(13)
    H, W, C, k, kf = 7, 8, 2, 3, 3
    N = H * W
    F = rng.random((H, W, kf, kf))                  # asymmetric, so offsets' signs matter
    vx = rng.random((H, W, C)) + 0.1
    cov_z, cross = filter_covariance(F, vx, size=2 * k - 1, cross=True)
    mom = _Moments(vx[None], cov_z[None], cross[None])
    Fm = _dense_operator(F, H, W)
    E = np.eye(N)
    offs = _offsets(k)
    pair = {(t, s): mom.pair(0, t, s) for t in offs for s in offs}
    dvar = {t: _delta_var(mom, 0, t) for t in offs if t != (0, 0)}    # no δ for the centre
    without = _Moments(vx[None], cov_z[None], None)     # printed Eq. 11: no cross terms
    differs = False
    for (py, px) in [(3, 4), (0, 0), (0, 7), (6, 3), (2, 1)]:
        c = py * W + px
        taps = {t: (py + t[0]) * W + px + t[1] for t in offs
                if 0 <= py + t[0] < H and 0 <= px + t[1] < W}
        # rows of e_t and δ_t as linear maps of x
        rows = {t: E[q] + Fm[c] - Fm[q] for t, q in taps.items()}
        for ch in range(C):
            S = np.diag(vx[..., ch].ravel())
            for t, rt in rows.items():
                if t != (0, 0):
                    dt = Fm[c] - Fm[taps[t]] - E[c] + E[taps[t]]
                    np.testing.assert_allclose(dvar[t][py, px, ch], dt @ S @ dt, rtol=1e-10,
                                               atol=1e-13)
                for s, rs in rows.items():
                    want = rt @ S @ rs
                    np.testing.assert_allclose(pair[t, s][py, px, ch], want, rtol=1e-10,
                                               atol=1e-13)
                    differs |= abs(without.pair(0, t, s)[py, px, ch] - want) > 1e-3 * abs(want)
    assert differs                                  # the cross terms are exercised


def test_eq10_bias_is_exact_for_fixed_weights():
    rng = np.random.default_rng(12)
    H, W, C, k = 8, 9, 3, 5
    w = rng.random((H, W, k, k))
    mu = rng.random((H, W, C))
    zb = rng.normal(size=(H, W, C))
    # expectation of Eq. 8 with E[y] = mu and E[z] = mu + zb is Eq. 8 applied to them
    expect = combine(mu, mu + zb, w)
    bias, _ = combine_bias_variance(w, np.zeros((H, W, C)), np.zeros((H, W, C)), z_bias=zb)
    np.testing.assert_allclose(bias, expect - mu, atol=1e-12)
    # a constant bias of z cancels (Eq. 10 depends on differences only)
    bias0, _ = combine_bias_variance(w, np.zeros((H, W, C)), np.zeros((H, W, C)),
                                     z_bias=np.full((H, W, C), 3.0))
    np.testing.assert_allclose(bias0, 0.0, atol=1e-12)


# --------------------------------------------------------------------------- Eq. 10 / 11 by MC
def _mc_setup(H=45, k=5, kf=5, sigma_f=1.0, seed=0):
    rng = np.random.default_rng(seed)
    w = np.array(gaussian_weights(H, H, 1, k, 1.5)[:, :, 0]) * rng.uniform(0.5, 1.5, (H, H, k, k))
    F = _renormalised_gaussian(H, H, kf, sigma_f)
    return w, F


def _chi2_bias_var(samples, mu, bias, var, grid):
    """p-values of the bias and variance of per-rep estimates at independent pixels."""
    R, C = samples.shape[0], samples.shape[-1]
    s = samples[:, grid[0], grid[1]].reshape(R, -1, C)          # (R, n, C)
    mu, bias, var = (a[grid].reshape(-1, C) for a in (mu, bias, var))
    m = s.mean(axis=0)
    z_bias = (m - mu - bias) / np.sqrt(var / R)
    u = (s - m) ** 2
    s2 = u.sum(axis=0) / (R - 1)
    z_var = (s2 - var) / (u.std(axis=0, ddof=1) / np.sqrt(R))
    # one chi-square per channel (the channels of a pixel share the throughput S)
    return ([_chi2_pvalue(z_bias[:, c]) for c in range(C)],
            [_chi2_pvalue(z_var[:, c]) for c in range(C)])


def test_eq10_eq11_match_monte_carlo_independent_z():
    """y: 8-spp render; z: a Gaussian filter of an independent 8-spp render (Eq. 11's
    assumptions hold).  Bias and variance of Eq. 8 over 1500 renders vs Eq. 10 / 11."""
    H, spp, R = 45, 8, 1500
    w, F = _mc_setup(H)
    r = ToyRenderer("edges", width=H, height=H)
    mu, v1 = r.true_mean(), r.true_var() / spp
    out = np.empty((R, H, H, 3))
    for i in range(R):
        y = r.render_uniform(spp, seed=2 * i, features=False).mean
        x = r.render_uniform(spp, seed=2 * i + 1, features=False).mean
        out[i] = combine(y, apply_kernels(F, x), w)
    cov_z = filter_covariance(F, v1, size=9)
    z_bias = apply_kernels(F, mu) - mu
    bias, var = combine_bias_variance(w, v1, cov_z, z_bias=z_bias)
    # pixels 9 apart depend on disjoint samples (window radius 2 + filter radius 2)
    grid = np.ix_(np.arange(4, H, 9), np.arange(4, H, 9))
    p_bias, p_var = _chi2_bias_var(out, mu, bias, var, grid)
    n_tests = 2 * 3 * 3          # (bias, var) x channels, and the power checks below
    assert min(p_bias + p_var) > ALPHA / n_tests, (p_bias, p_var)
    # power: the bias is visible at these pixels, and z's covariances matter
    p_nobias, _ = _chi2_bias_var(out, mu, 0 * bias, var, grid)
    _, var_uncorr = combine_bias_variance(w, v1, v1 * np.sum(F ** 2, axis=(2, 3))[..., None],
                                          z_bias=z_bias)
    _, p_uncorr = _chi2_bias_var(out, mu, bias, var_uncorr, grid)
    assert max(p_nobias) < ALPHA / n_tests and max(p_uncorr) < ALPHA / n_tests


def test_eq10_eq11_match_monte_carlo_multibuffer_z_from_y():
    """Two bins of 4 spp, z_b = F(y_b) (a 'denoised' bin, correlated with y_b): Eq. 14's
    bias and variance match with the cross-covariance term; printed Eq. 11, which assumes
    y independent of z, underestimates the variance (by ~30% here) and is rejected."""
    H, spp, R, B = 45, 4, 1500, 2
    w1, F = _mc_setup(H, seed=3)
    w = np.stack([w1, w1[::-1]], axis=2)               # different weights per bin
    r = ToyRenderer("edges", width=H, height=H)
    mu, v1 = r.true_mean(), r.true_var() / spp
    out = np.empty((R, H, H, 3))
    for i in range(R):
        ys = np.stack([r.render_uniform(spp, seed=(i, b), features=False).mean for b in range(B)])
        zs = np.stack([apply_kernels(F, yb) for yb in ys])
        out[i] = combine_multi(ys, zs, w)
    cov_z, cross = filter_covariance(F, v1, size=9, cross=True)
    z_bias = apply_kernels(F, mu) - mu
    bias, var = combine_bias_variance(w, v1, cov_z, z_bias=z_bias, cov_yz=cross)
    grid = np.ix_(np.arange(4, H, 9), np.arange(4, H, 9))
    p_bias, p_var = _chi2_bias_var(out, mu, bias, var, grid)
    n_tests = 2 * 3 + 3
    assert min(p_bias + p_var) > ALPHA / n_tests, (p_bias, p_var)
    _, var_printed = combine_bias_variance(w, v1, cov_z, z_bias=z_bias)   # no cross term
    _, p_printed = _chi2_bias_var(out, mu, bias, var_printed, grid)
    assert max(p_printed) < ALPHA / n_tests
    assert np.mean(var_printed / var) < 0.8      # printed Eq. 11 underestimates it here


# --------------------------------------------------------------------------- statistical weights
def _oracle_problem(H=14, C=3, k=3, kf=3, seed=20):
    rng = np.random.default_rng(seed)
    F = rng.random((H, H, kf, kf))
    F /= F.sum(axis=(2, 3), keepdims=True)
    vx = rng.random((H, H, C)) + 0.1
    vy = rng.random((H, H, C)) + 0.1
    cov_z = filter_covariance(F, vx, size=2 * k - 1)
    zb = 0.3 * rng.normal(size=(H, H, C))
    return rng, vy, cov_z, zb


def _mse(w, vy, cov_z, zb, cov_yz=None):
    b, v = combine_bias_variance(w, vy, cov_z, z_bias=zb, cov_yz=cov_yz)
    return (b * b + v).mean(axis=-1)


def test_full_statistical_weights_minimise_eq10_eq11():
    rng, vy, cov_z, zb = _oracle_problem()
    H, k = vy.shape[0], 3
    y, z = rng.normal(size=(2, H, H, 3))               # unused by oracle moments
    wf = statistical_weights(y, z, vy, cov_z, k, method="full", z_bias=zb, ridge=0)
    wd = statistical_weights(y, z, vy, cov_z, k, method="diagonal", z_bias=zb)
    assert wf.shape == wd.shape == (H, H, 1, k, k)
    np.testing.assert_allclose(wf.sum(axis=(2, 3, 4)), 1.0, rtol=1e-5)
    base = _mse(wf.astype(np.float64), vy, cov_z, zb)
    for i in range(10):   # no perturbation (renormalised by Eq. 8) improves any pixel
        d = rng.normal(scale=0.05, size=wf.shape)
        assert (_mse(wf + d, vy, cov_z, zb) >= base - 1e-9 * base).all()
    m_diag = _mse(wd, vy, cov_z, zb)
    m_coh = _mse(statistical_weights(y, z, vy, cov_z, k, z_bias=zb), vy, cov_z, zb)
    m_uni = _mse(uniform_weights(H, H, 1, k), vy, cov_z, zb)
    assert (base <= m_diag * (1 + 1e-6)).all() and (base <= m_coh * (1 + 1e-6)).all()
    assert max(m_diag.mean(), m_coh.mean()) < m_uni.mean() and base.mean() < vy.mean()
    # the diagonal weights are positive, and exactly inverse-MSE with uncorrelated errors
    assert (wd >= 0).all()


def test_diagonal_weights_are_exact_for_uncorrelated_estimates():
    """With z = 0 deterministic and y independent, e_t = y_t are uncorrelated with bias
    mu_t - mu_c; inverse-MSE weights are then the exact minimiser, equal to 'full'."""
    rng = np.random.default_rng(21)
    H, C, k = 10, 2, 3
    vy = rng.random((H, H, C)) + 0.1
    y, z = rng.normal(size=(2, H, H, C))
    zero = np.zeros((H, H, C))
    wd = statistical_weights(y, z, vy, zero, k, method="diagonal", z_bias="zero")
    wf = statistical_weights(y, z, vy, zero, k, method="full", z_bias="zero", ridge=0)
    np.testing.assert_allclose(wd, wf, rtol=1e-4, atol=1e-6)
    # centre weight 1/var_y(c): ratios of weights are inverse variance ratios
    r = k // 2
    ratio = wd[5, 5, 0, r, r + 1] / wd[5, 5, 0, r, r]
    np.testing.assert_allclose(ratio, vy[5, 5].mean() / vy[5, 6].mean(), rtol=1e-5)


def test_coherent_weights_solve_their_quadratic_programme():
    """'coherent' minimises a^T (D + |b||b|^T) a over the simplex; compare with SLSQP.

    D_t = Var(e_t) and b_t = bias of e_t come from Eq. 10/11 with one-hot weights (an
    independent computation of the per-tap moments)."""
    from scipy.optimize import minimize

    rng, vy, cov_z, zb = _oracle_problem(H=6, C=2, k=3, kf=3, seed=22)
    H, k = vy.shape[0], 3
    y, z = rng.normal(size=(2, H, H, 2))
    w = statistical_weights(y, z, vy, cov_z, k, method="coherent", z_bias=zb)
    assert (w >= 0).all()
    D, Bt = np.zeros((H, H, k * k)), np.zeros((H, H, 2, k * k))
    with np.errstate(divide="ignore", invalid="ignore"):
        for t in range(k * k):
            onehot = np.zeros((H, H, k, k))
            onehot.reshape(H, H, -1)[..., t] = 1.0
            b, v = combine_bias_variance(onehot, vy, cov_z, z_bias=zb)
            D[..., t], Bt[..., t] = v.mean(axis=-1), np.abs(b)
    for (py, px) in [(2, 3), (0, 0), (5, 2), (3, 3)]:
        ok = np.isfinite(D[py, px])
        d, bt = D[py, px][ok], Bt[py, px][:, ok]

        def f(a):
            return float(a @ (d * a) + np.mean((bt @ a) ** 2))

        res = minimize(f, np.full(d.size, 1.0 / d.size), method="SLSQP", bounds=[(0, 1)] * d.size,
                       constraints=[{"type": "eq", "fun": lambda a: a.sum() - 1.0}],
                       options={"ftol": 1e-14, "maxiter": 500})
        mine = w[py, px, 0].reshape(-1)[ok].astype(np.float64)
        assert f(mine) <= res.fun * (1 + 1e-5), (f(mine), res.fun)
        np.testing.assert_allclose(mine, res.x, atol=2e-4)


def test_coherent_equals_full_when_the_model_is_exact():
    """z deterministic (var 0) and a bias peak at one pixel: Cov(e) is diagonal and all
    biases of that pixel's taps share a sign, so 'coherent' is the exact optimum."""
    rng = np.random.default_rng(23)
    H, C, k = 5, 2, 3
    vy = rng.random((H, H, C)) + 0.1
    zb = np.zeros((H, H, C))
    zb[2, 2] = [0.4, 0.7]
    y, z = rng.normal(size=(2, H, H, C))
    zero = np.zeros((H, H, C))
    wc = statistical_weights(y, z, vy, zero, k, method="coherent", z_bias=zb)
    wf = statistical_weights(y, z, vy, zero, k, method="full", z_bias=zb, ridge=0)
    np.testing.assert_allclose(wc[2, 2], wf[2, 2], rtol=1e-5, atol=1e-7)
    assert wc[2, 2, 0, 1, 1] > 3 * wc[2, 2, 0, 0, 0]     # biased taps are held back


def test_statistical_weights_reduce_measured_error():
    """Weights from moments estimated without the truth (4 bins of 4 spp, buffer_moments,
    bias estimated from the data) for z = a sigma-2 Gaussian filter of each bin: Eq. 14
    beats y, z, uniform weights and the inverse-MSE rule on a scene with edges."""
    H, B, spp, reps, k = 32, 4, 4, 12, 5
    r = ToyRenderer("edges", width=H, height=H)
    mu = r.true_mean()
    F = _renormalised_gaussian(H, H, 9, 2.0)
    G = _renormalised_gaussian(H, H, 5, 1.5)
    err = {name: [] for name in ("y", "z", "uniform", "diagonal", "coherent")}
    for i in range(reps):
        ys = np.stack([r.render_uniform(spp, seed=(7, i, b), features=False).mean for b in range(B)])
        zs = np.stack([apply_kernels(F, yb) for yb in ys])
        var_y, cov_z, cov_yz = buffer_moments(ys, zs, size=k)
        # smooth the 3-dof estimates over a few pixels
        var_y = apply_kernels(G, var_y)
        cov_z = apply_kernels(G, cov_z.reshape(H, H, -1)).reshape(cov_z.shape)
        cov_yz = apply_kernels(G, cov_yz.reshape(H, H, -1)).reshape(cov_yz.shape)
        est = {"y": ys.mean(axis=0), "z": zs.mean(axis=0),
               "uniform": combine_multi(ys, zs, uniform_weights(H, H, B, k))}
        for method in ("diagonal", "coherent"):
            w = statistical_weights(ys, zs, var_y, cov_z, k, cov_yz=cov_yz, method=method)
            est[method] = combine_multi(ys, zs, w)
        for name, e in est.items():
            err[name].append(((e - mu) ** 2).mean())
    err = {name: np.array(v) for name, v in err.items()}
    for other in ("y", "z", "uniform", "diagonal"):   # paired one-sided t-tests
        t = stats.ttest_1samp(np.log(err["coherent"] / err[other]), 0.0, alternative="less")
        assert t.pvalue < ALPHA / 4, (other, err["coherent"].mean(), err[other].mean())
    assert err["coherent"].mean() < 0.6 * min(err["y"].mean(), err["z"].mean())


@pytest.mark.parametrize("B, H, W, C, k, kf, bias, method, cross", [
    (1, 9, 11, 3, 3, 3, "estimate", "coherent", False),
    (2, 10, 7, 3, 5, 3, "estimate", "coherent", True),
    (1, 12, 13, 1, 5, 3, "zero", "coherent", True),
    (3, 8, 9, 2, 3, 5, "estimate", "diagonal", True),
    (2, 9, 9, 3, 3, 3, "array", "coherent", True),
    (1, 7, 6, 3, 7, 3, "array", "diagonal", False),     # window wider than the image
    (2, 10, 7, 3, 5, 3, "pairs", "coherent", True),
    (3, 8, 9, 2, 3, 5, "pairs", "diagonal", False),
])
def test_statistical_weights_numba_matches_numpy_reference(B, H, W, C, k, kf, bias, method,
                                                           cross):
    """The compiled "coherent"/"diagonal" weights equal the NumPy path on consistent
    (positive semi-definite) moments of a filtered image, borders included."""
    rng = np.random.default_rng(31 + B + k)
    K = rng.random((H, W, kf, kf))
    K /= K.sum(axis=(2, 3), keepdims=True)
    var = rng.gamma(2.0, 0.5, (H, W, C))
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = np.stack([apply_kernels(K, yb) for yb in ys])
    cov_z, cov_yz = filter_covariance(K, var, cross=True)
    zb = rng.normal(size=(H, W, C)) if bias == "array" else bias
    y, z = (ys, zs) if B > 1 else (ys[0], zs[0])
    kw = dict(method=method, z_bias=zb, cov_yz=cov_yz if cross else None)
    fast = statistical_weights(y, z, var, cov_z, k, **kw)
    ref = statistical_weights(y, z, var, cov_z, k, _reference=True, **kw)
    assert fast.shape == ref.shape == (H, W, B, k, k) and fast.dtype == np.float32
    np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("loo", [False, True])
def test_pairs_tap_bias_is_the_mean_over_distinct_bins_in_both_paths(loo):
    """``z_bias="pairs"``: the squared bias of tap ``t`` at a centre is the mean of
    ``δ_b δ_b'`` over ordered pairs of distinct bins (``E = β_t²`` for independent bins,
    whatever their noise), box-averaged and clamped at 0 as "estimate"; written here as
    the explicit double loop at ``patch = 0`` (no box).  The compiled kernel equals the
    NumPy path on an image wider than a column tile, with and without leaving the centre
    out, and one buffer is refused."""
    import statmc.combine as cbm

    rng = np.random.default_rng(17)
    B, H, W, C, k = 3, 7, ck.BIAS_TILE + 6, 2, 5
    K = rng.random((H, W, 3, 3))
    K /= K.sum(axis=(2, 3), keepdims=True)
    var = rng.gamma(2.0, 0.5, (H, W, C))
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = np.stack([apply_kernels(K, yb) for yb in ys])
    cov_z, cov_yz = filter_covariance(K, var, cross=True)
    mom = cbm._Moments(*(np.broadcast_to(a, (B,) + a.shape) for a in (var, cov_z, cov_yz)))
    _, sq = cbm._bias_vectors(ys, zs, mom, None, "pairs", k, 0)
    for o in [(0, 1), (-2, 1), (1, -1)]:
        d = np.stack([(zs[b] - cbm._shift(zs[b], *o)) - (ys[b] - cbm._shift(ys[b], *o))
                      for b in range(B)])
        want = sum(d[a] * d[b] for a in range(B) for b in range(B) if a != b) / (B * (B - 1))
        inside = cbm._valid(H, W, *o)[..., None] > 0
        np.testing.assert_allclose(sq[o][0], np.where(inside, np.maximum(want, 0.0), 0.0),
                                   rtol=1e-12, atol=1e-15)
    kw = dict(cov_yz=cov_yz, z_bias="pairs", leave_centre_out=loo)
    fast = statistical_weights(ys, zs, var, cov_z, k, **kw)
    np.testing.assert_allclose(fast, statistical_weights(ys, zs, var, cov_z, k, _reference=True,
                                                         **kw), rtol=1e-5, atol=1e-7)
    assert not np.allclose(fast, statistical_weights(ys, zs, var, cov_z, k, cov_yz=cov_yz,
                                                     leave_centre_out=loo))
    with pytest.raises(InputError, match="needs B >= 2 bins"):
        statistical_weights(ys[0], zs[0], var, cov_z, k, z_bias="pairs")


def test_statistical_weights_numba_bands_match_one_band():
    """Row bands of the squared-bias planes (memory bound at 1080p) change nothing."""
    rng = np.random.default_rng(5)
    H, W, C, k = 13, 10, 3, 5
    y = rng.gamma(2.0, 0.5, (1, H, W, C))
    z = 0.5 * y + 0.1 * rng.random((1, H, W, C))
    vy = rng.random((1, H, W, C)) + 0.1
    cz = np.ascontiguousarray(np.broadcast_to(0.05, (1, H, W, 1, 1, C)))
    out = {}
    for band in (1 << 40, k * k * W * C * 8 * 3):      # one band; bands of 3 rows
        o = np.empty((H, W, 1, k, k), np.float32)
        ck.statistical_weights_numba(y, z, vy, cz, None, None, ck.BIAS_ESTIMATE,
                                     ck.METHOD_COHERENT, k, 2, o, band_bytes=band)
        out[band] = o
    a, b = out.values()
    np.testing.assert_array_equal(a, b)



def test_combination_kernels_compile_no_parallel_loops():
    """The combination's compiled kernels are serial functions run on several threads in
    chunks of rows or tasks (``_task_threads.run_rows``), not ``prange`` loops.
    numba links a function's callees into it and optimises and compiles them again there:
    a parallel loop calling the weights' row function compiled it twice more (into the
    loop's gufunc and the wrapper), 7 s of CPU time for ``_weights_band`` and 6 s for
    ``_bias_planes`` on a cold cache (session 15), more than the row functions themselves.
    Fails before: ``_weights_band``, ``_bias_planes``, ``_combine_group``,
    ``_prepare_group``, ``running_rows`` and ``_add_neighbour_products_sum`` were parallel."""
    from numba.core.registry import CPUDispatcher

    from statmc import _stencil_kernels as sk
    parallel = [f"{m.__name__}.{n}" for m in (ck, sk) for n, d in vars(m).items()
                if isinstance(d, CPUDispatcher) and d.targetoptions.get("parallel")]
    assert not parallel, parallel


def test_bias_planes_compile_only_the_mode_used():
    """``z_bias="pairs"`` and the other modes reach ``_bias_tasks`` with ``None`` for what
    they do not read (``P`` and the pairs flag), so numba drops the other mode's branch
    when it compiles: ``combine_bins`` (pairs) compiled the kernel in 2.3–3.3 s of CPU
    instead of 3.9–5.7 s on a cold cache (session 17).  The weights stay those of the
    NumPy path.  Fails before: the kernel took an array ``P`` and a bool flag in every
    mode (one signature holding both branches)."""
    from numba import types

    rng = np.random.default_rng(5)
    B, H, W, C, k = 3, 9, 11, 3, 5
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = ys + rng.normal(0.0, 0.1, ys.shape)
    vy = rng.gamma(2.0, 0.05, (B, H, W, C))
    cz = rng.normal(0.0, 0.01, (H, W, 3, 3, C))
    cz[:, :, 1, 1] = 0.05
    for zb in ("estimate", "pairs"):
        fast = statistical_weights(ys, zs, vy, cz, k, z_bias=zb, leave_centre_out=True)
        ref = statistical_weights(ys, zs, vy, cz, k, z_bias=zb, leave_centre_out=True,
                                  _reference=True)
        np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-7, err_msg=zb)
    sigs = ck._bias_tasks.signatures
    P_none = [s[2] == types.none for s in sigs]
    flag_none = [s[12] == types.none for s in sigs]
    assert any(P_none) and any(flag_none), sigs
    assert all(p != f for p, f in zip(P_none, flag_none)), sigs


def test_threaded_chunks_equal_one_thread_and_honour_the_thread_count():
    """``run_rows`` gives the one-thread result to the bit (weights, Eq. 14, moment
    stencils, the running box sums), runs on no more threads than
    ``numba.get_num_threads()`` (the calling one among them; one with
    ``set_num_threads(1)``, as ``serial_below`` sets for small calls), covers every index
    once, and raises a chunk's exception."""
    import threading

    import numba

    from statmc import _stencil_kernels as sk
    from statmc._task_threads import run_rows

    rng = np.random.default_rng(21)
    B, H, W, C, k = 2, 23, ck.BIAS_TILE + 5, 3, 5
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = ys + rng.normal(0.0, 0.1, ys.shape)
    vy = rng.gamma(2.0, 0.05, (B, H, W, C))
    cz = rng.normal(0.0, 0.01, (H, W, 3, 3, C))
    cz[:, :, 1, 1] = 0.05
    w = rng.uniform(0.1, 1.0, (H, W, B, 7, 7)).astype(np.float32)
    a = rng.normal(size=(3, H, W, C))
    x = rng.normal(size=(9, 2 * ck.RUN_TILE + 3))
    add, sub = rng.integers(0, 9, 12), rng.integers(0, 9, 12)

    def run():
        prod = np.zeros((H, W, 5, 5, C))
        sk.add_neighbour_products_sum(prod, a, a[::-1], 2, np.ones(3, bool))
        t, o = np.ones(x.shape[1]), np.empty((12, x.shape[1]))
        ck.running_rows(x, add, sub, 5, t, o)
        return [statistical_weights(ys, zs, vy, cz, k, z_bias=zb, leave_centre_out=True)
                for zb in ("estimate", "pairs")] + [combine_multi(ys, zs, w), prod, o, t]

    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = run()
        numba.set_num_threads(before)
        many = run()
        seen, hits = set(), np.zeros(1000, int)

        def kernel(lo, hi):
            seen.add(threading.get_ident())
            hits[lo:hi] += 1

        for n in (1, 2):
            numba.set_num_threads(n)
            seen.clear()
            hits[:] = 0
            run_rows(kernel, 3, 1000)
            assert 1 <= len(seen) <= n and (hits[3:] == 1).all() and (hits[:3] == 0).all()
    finally:
        numba.set_num_threads(before)
    for p, q in zip(one, many):
        assert p.dtype == q.dtype
        np.testing.assert_array_equal(p, q)

    def fail(lo, hi):
        if lo <= 500 < hi:
            raise ZeroDivisionError("chunk")

    with pytest.raises(ZeroDivisionError, match="chunk"):
        run_rows(fail, 0, 1000)

@pytest.mark.parametrize("loo", [False, True])
def test_statistical_weights_rows_match_all_rows(loo):
    """``rows=(r0, r1)`` (the banded combinations skip their margin rows) computes those
    rows to the bit as on all rows, leaves ``out`` elsewhere untouched, and
    ``_statistical_weights(rows=...)`` gives the other rows the identity; the NumPy
    reference path agrees on the rows computed."""
    import statmc.combine as cbm

    rng = np.random.default_rng(9)
    H, W, C, k = 17, 11, 3, 5
    K = rng.random((H, W, 3, 3))
    K /= K.sum(axis=(2, 3), keepdims=True)
    vy = rng.gamma(2.0, 0.5, (1, H, W, C))
    y = rng.gamma(2.0, 0.5, (1, H, W, C))
    z = apply_kernels(K, y[0])[None]
    cz, cyz = (np.ascontiguousarray(a[None]) for a in filter_covariance(K, vy[0], cross=True))
    full = np.empty((H, W, 1, k, k), np.float32)
    ck.statistical_weights_numba(y, z, vy, cz, cyz, None, ck.BIAS_ESTIMATE,
                                 ck.METHOD_COHERENT, k, 2, full, loo=loo)
    for r0, r1, band in ((4, 9, 1 << 40), (0, 6, k * k * W * C * 8 * 2), (12, 17, 1 << 40)):
        o = np.full((H, W, 1, k, k), -7.0, np.float32)
        ck.statistical_weights_numba(y, z, vy, cz, cyz, None, ck.BIAS_ESTIMATE,
                                     ck.METHOD_COHERENT, k, 2, o, loo=loo, band_bytes=band,
                                     rows=(r0, r1))
        np.testing.assert_array_equal(o[r0:r1], full[r0:r1])
        assert (np.delete(o, np.s_[r0:r1], axis=0) == -7.0).all()
        w = cbm._statistical_weights(y[0], z[0], vy[0], cz[0], k, cov_yz=cyz[0], patch=2,
                                     leave_centre_out=loo, rows=(r0, r1))
        np.testing.assert_array_equal(w[r0:r1], full[r0:r1])
        ident = np.zeros((k, k), np.float32)
        ident[k // 2, k // 2] = 1.0
        assert (np.delete(w, np.s_[r0:r1], axis=0) == ident).all()
        ref = cbm.statistical_weights(y[0], z[0], vy[0], cz[0], k, cov_yz=cyz[0], patch=2,
                                      leave_centre_out=loo, _reference=True)
        np.testing.assert_allclose(w[r0:r1], ref[r0:r1], rtol=1e-5, atol=1e-7)



@pytest.mark.parametrize("loo", [False, True])
def test_statistical_weights_numba_column_tiles_match_numpy_reference(loo):
    """The squared-bias planes are computed in tiles of ``BIAS_TILE`` columns: an image
    wider than one tile (a tile edge inside the box filter) equals the NumPy path."""
    rng = np.random.default_rng(11)
    H, W, C, k, kf = 6, ck.BIAS_TILE + 9, 3, 5, 3
    K = rng.random((H, W, kf, kf))
    K /= K.sum(axis=(2, 3), keepdims=True)
    var = rng.gamma(2.0, 0.5, (H, W, C))
    y = rng.gamma(2.0, 0.5, (H, W, C))
    z = apply_kernels(K, y)
    cov_z, cov_yz = filter_covariance(K, var, cross=True)
    kw = dict(cov_yz=cov_yz, leave_centre_out=loo)
    fast = statistical_weights(y, z, var, cov_z, k, **kw)
    ref = statistical_weights(y, z, var, cov_z, k, _reference=True, **kw)
    np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-7)

# --------------------------------------------------------------------------- magnitude limits, fallback
def _extreme_inputs(seed=41, H=9, W=10, C=3, k=5):
    """Inputs that push every term of the weights to its bound: ``|y| = |z| <= 1`` with
    random signs and ``z = −y`` on 30 % of the pixels (``|δ|`` up to 4), variances from 1e-3 up to 1e10 (the
    largest moment that fits ``MOMENT_LIMIT`` after the scaling of
    :func:`test_statistical_weights_are_scale_free_up_to_the_limits`), a stencil of a
    filter of them, and a ``z_bias`` array with ``|z_bias| <= 1``."""
    rng = np.random.default_rng(seed)
    y = rng.choice([-1.0, 1.0], (H, W, C)) * rng.uniform(0.5, 1.0, (H, W, C))
    y[0, 0] = 1.0                                      # the bounds reached exactly
    z = np.where(rng.random((H, W, 1)) < 0.3, -y, y)  # flipped pixels: |δ| up to 4
    var = rng.gamma(2.0, 0.5, (H, W, C)) * 1e-3
    var[rng.random((H, W)) < 0.1] = 1e10
    K = rng.random((H, W, 3, 3))
    K /= K.sum(axis=(2, 3), keepdims=True)
    cov_z, cov_yz = filter_covariance(K, var, cross=True)
    zb = rng.uniform(-1.0, 1.0, (H, W, C))
    return y, z, var, cov_z, cov_yz, zb, k


@pytest.mark.parametrize("method, bias", [("coherent", "estimate"), ("diagonal", "estimate"),
                                          ("coherent", "array")])
def test_statistical_weights_are_scale_free_up_to_the_limits(method, bias):
    """Scaling ``y, z, z_bias`` by ``s = 2**465`` (values up to 9.5e139 < ``VALUE_LIMIT``)
    and the moments by ``s²`` (up to 9.1e289 < ``MOMENT_LIMIT``) leaves the weights equal
    to the bit in both paths: every square and sum stays finite up to the limits (an
    overflow would put Inf into the bias planes and change or drop the weights, as it
    did at 1e170), and the compiled weights still equal the NumPy reference."""
    from statmc.combine import MOMENT_LIMIT, VALUE_LIMIT

    y, z, var, cov_z, cov_yz, zb, k = _extreme_inputs()
    s = 2.0 ** 465
    assert 0.9 * VALUE_LIMIT < s < VALUE_LIMIT and 0.9 * MOMENT_LIMIT < var.max() * s * s < MOMENT_LIMIT
    out = {}
    for scale in (1.0, s):
        kw = dict(method=method, cov_yz=cov_yz * scale ** 2,
                  z_bias=zb * scale if bias == "array" else bias)
        with np.errstate(all="raise"):                # no overflow in the NumPy path either
            out[scale] = [statistical_weights(y * scale, z * scale, var * scale ** 2,
                                              cov_z * scale ** 2, k, _reference=ref, **kw)
                          for ref in (False, True)]
    (fast, ref), (fast_s, ref_s) = out[1.0], out[s]
    np.testing.assert_array_equal(fast_s, fast)
    np.testing.assert_array_equal(ref_s, ref)
    assert np.isfinite(fast).all()
    np.testing.assert_allclose(fast.sum(axis=(2, 3, 4)), 1.0, rtol=1e-5)
    # not degenerate (the fallback, or all weight on the centres): most pixels average
    assert (fast[:, :, 0, k // 2, k // 2] < 0.99).mean() > 0.5
    np.testing.assert_allclose(fast_s, ref_s, rtol=1e-5, atol=1e-7)   # as the tests above


def test_statistical_weights_refuse_magnitudes_beyond_the_limits():
    """Regression: with ``y`` at 1e170 the squares of the bias estimate overflowed; the
    compiled weights became all zeros (Eq. 8 then 0/0) while the NumPy reference dropped
    the bias (up to 0.84 apart, measured).  Now both paths refuse such input with an
    ``InputError`` naming the argument and the limit, just above each limit, and accept
    it at the limit."""
    from statmc.combine import MOMENT_LIMIT, VALUE_LIMIT

    rng = np.random.default_rng(3)
    H, W, C = 5, 6, 3
    y = rng.gamma(2.0, 0.5, (H, W, C))
    base = dict(y=y, z=0.9 * y, var_y=0.1 * y, cov_z=0.1 * y, size=3, cov_yz=0.01 * y,
                z_bias=np.zeros((H, W, C)))
    for name, limit in (("y", VALUE_LIMIT), ("z", VALUE_LIMIT), ("z_bias", VALUE_LIMIT),
                        ("var_y", MOMENT_LIMIT), ("cov_z", MOMENT_LIMIT),
                        ("cov_yz", MOMENT_LIMIT)):
        for ref in (False, True):
            kw = dict(base, _reference=ref)
            a = np.array(kw[name], dtype=np.float64)
            a[2, 3, 1] = limit * (1 if name == "var_y" else -1)     # the sign does not matter
            kw[name] = a
            w = statistical_weights(**kw)                # at the limit: accepted
            assert np.isfinite(w).all()
            kw[name] = a = a.copy()
            a[2, 3, 1] *= 1.01
            with pytest.raises(InputError, match=rf"`{name}` holds values up to 1.01e\+{int(np.log10(limit))}"
                                                 rf".* at most 1e\+140 in `y`, `z` and `z_bias` and "
                                                 r"1e\+290 in the moments .* rescale"):
                statistical_weights(**kw)
    for ref in (False, True):                              # the case that was seen
        with pytest.raises(InputError, match=r"`y` holds values up to .*e\+170"):
            statistical_weights(y * 1e170, 0.9 * y * 1e170, y, y, 3, _reference=ref)
    with pytest.raises(InputError, match="NaN"):         # non-finite keeps its own message
        statistical_weights(np.full((H, W, C), np.nan), y, y, y, 3)


def test_combination_pipelines_refuse_magnitudes_before_the_denoiser_runs():
    """``combine_denoised``, ``combine_bins`` and ``combine_bin_images`` check the limits of
    the statistical weights on their input first (not after the denoiser's probes, and
    not in some band of rows, under the name of an internal moment)."""
    from statmc.combine import combine_bin_images, combine_bins

    def denoiser(c):
        raise AssertionError("the denoiser ran")

    y = np.ones((6, 7, 3))
    with pytest.raises(InputError, match=r"`y` holds values up to 2e\+150"):
        combine_denoised(2e150 * y, y, denoiser)
    with pytest.raises(InputError, match=r"`mean_var` holds values up to 2e\+300"):
        combine_denoised(y, 2e300 * y, denoiser)
    with pytest.raises(InputError, match=r"`ys` holds values up to 2e\+150"):
        combine_bins(2e150 * np.stack([y, y]), y, denoiser)
    with pytest.raises(InputError, match=r"`mean_var` holds values up to 2e\+300"):
        combine_bins(np.stack([y, y]), 2e300 * y, denoiser)
    with pytest.raises(InputError, match=r"`zs` holds values up to 2e\+150"):
        combine_bin_images(np.stack([y, y]), 2e150 * np.stack([y, y]))


def test_denoiser_pipelines_refuse_images_beyond_float32_before_the_denoiser_runs():
    """Regression: the denoiser is called on float32 copies, so ``|y|`` above float32's
    3.4e38 (but within ``VALUE_LIMIT``) reached it as Inf, and after the denoiser's calls
    the error blamed "`denoiser output` holds ... Inf values".  Now ``combine_denoised`` and
    ``combine_bins`` name the input and float32's range up front; at 3e38 they run."""
    from statmc.combine import combine_bins

    def denoiser(c):
        raise AssertionError("the denoiser ran")

    mv = np.ones((6, 7, 3))
    y = mv.copy()
    y[2, 3, 1] = -1.0
    with pytest.raises(InputError, match=r"`y` holds values up to 2e\+50 .*float32.* 3\.4e\+38"):
        combine_denoised(-2e50 * y, mv, denoiser)
    with pytest.raises(InputError, match=r"`ys` holds values up to 2e\+50 .*float32"):
        combine_bins(np.stack([y, 2e50 * y]), mv, denoiser)
    halve = lambda c: 0.5 * np.asarray(c)  # noqa: E731
    assert np.isfinite(combine_denoised(3e38 * y, mv, halve, rng=0)).all()
    assert np.isfinite(combine_bins(np.stack([y, 3e38 * y]), mv, halve, rng=0)).all()


@pytest.mark.parametrize("method", ["coherent", "diagonal"])
@pytest.mark.parametrize("B", [1, 2])
def test_weight_fallback_is_the_centre_tap_in_both_paths(method, B):
    """The documented fallback, engineered: a non-finite squared bias (here Inf and NaN in
    a ``z_bias`` array, which the public function refuses, so the private paths are
    called) makes exactly the pixels whose window holds the bad pixel fall back to ``1/B``
    on each bin's centre tap, in the compiled kernel and in the NumPy reference alike; every
    other pixel keeps, to the bit, the weights of the same input without the bad values.
    Without the fallback the compiled kernel gave all-zero weights there, the reference
    NaN."""
    import statmc.combine as cbm

    rng = np.random.default_rng(17 + B)
    H, W, C, k = 9, 11, 3, 3
    r = k // 2
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = 0.8 * ys + 0.1
    var = rng.gamma(2.0, 0.5, (B, H, W, C))
    cz = np.ascontiguousarray(np.broadcast_to(0.05 * var[..., None, None, :], (B, H, W, 3, 3, C)))
    zb = rng.normal(size=(B, H, W, C))
    bad_px = [(1, 2, np.inf), (6, 7, np.nan), (8, 0, -np.inf)]
    zb_bad = zb.copy()
    for yy, xx, val in bad_px:
        zb_bad[B - 1, yy, xx, 1] = val
    code = ck.METHOD_COHERENT if method == "coherent" else ck.METHOD_DIAGONAL
    ref_fn = cbm._coherent_weights if method == "coherent" else cbm._diagonal_weights

    def both(zbias):
        fast = np.full((H, W, B, k, k), -7.0, np.float32)
        ck.statistical_weights_numba(ys, zs, var, cz, None, zbias, ck.BIAS_ARRAY, code, k, 2,
                                     fast)
        mom = cbm._Moments(var, cz, None)
        with np.errstate(invalid="ignore", over="ignore"):
            _, sq = cbm._bias_vectors(ys, zs, mom, zbias, zbias, k, 2)
            ref = ref_fn(mom, sq, k, B, H, W)
        return fast, ref

    fast, ref = both(zb_bad)
    clean, clean_ref = both(zb)
    hit = np.zeros((H, W), bool)
    for yy, xx, _ in bad_px:
        hit[max(0, yy - r):yy + r + 1, max(0, xx - r):xx + r + 1] = True
    ident = np.zeros((B, k, k), np.float32)
    ident[:, r, r] = np.float32(1.0 / B)
    for w in (fast, ref):
        assert (w[hit] == ident).all()
        np.testing.assert_array_equal(w[~hit], (clean if w is fast else clean_ref)[~hit])
    np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-7)
    assert not np.array_equal(clean[hit], fast[hit])      # the fallback did change them
    # Eq. 14 with the fallback weights returns the mean of the bins' y there
    out = combine_multi(ys, zs, fast)
    np.testing.assert_allclose(out[hit], ys.mean(axis=0)[hit], rtol=1e-12)


# --------------------------------------------------------------------------- moment helpers
def test_buffer_moments_are_unbiased():
    """E over renders of the bin-spread covariance estimates equals the exact moments."""
    H, B, spp, reps, m = 12, 4, 4, 400, 3
    r = ToyRenderer("gradient", width=H, height=H, channels=1)
    F = _renormalised_gaussian(H, H, 3, 1.0)
    v1 = r.true_var() / spp
    exact_z, exact_yz = filter_covariance(F, v1, size=m, cross=True)
    acc = [np.zeros((H, H, 1)), np.zeros(exact_z.shape), np.zeros(exact_z.shape)]
    sq = [np.zeros((H, H, 1)), np.zeros(exact_z.shape), np.zeros(exact_z.shape)]
    for i in range(reps):
        ys = np.stack([r.render_uniform(spp, seed=(9, i, b), features=False).mean for b in range(B)])
        zs = np.stack([apply_kernels(F, yb) for yb in ys])
        for j, est in enumerate(buffer_moments(ys, zs, size=m)):
            acc[j] += est
            sq[j] += est * est
    pvals = []
    for j, exact in enumerate((v1, exact_z, exact_yz)):
        mean = acc[j] / reps
        se = np.sqrt(np.maximum(sq[j] / reps - mean ** 2, 1e-300) / (reps - 1))
        # one statistic per quantity at independent pixels (3 px apart > 2 * (1 + 1))
        sel = (slice(1, None, 5), slice(1, None, 5))
        zsc = ((mean - exact) / se)[sel]
        zsc = zsc[np.isfinite(zsc) & (se[sel] > 0)]
        pvals.append(_chi2_pvalue(zsc))
    assert min(pvals) > ALPHA / 3, pvals


# --------------------------------------------------------------------------- weight builders
def test_weight_builders():
    u = uniform_weights(4, 5, 2, 3)
    assert u.shape == (4, 5, 2, 3, 3) and u.dtype == np.float32 and not u.flags.writeable
    g = gaussian_weights(4, 5, 2, 5, 1.0)
    np.testing.assert_allclose(g[0, 0].sum(), 1.0, rtol=1e-6)
    assert g[0, 0, 0, 2, 2] == g.max() and g[0, 0, 0, 0, 0] == g.min()
    np.testing.assert_allclose(g[1, 2, 1, 2, 3] / g[1, 2, 1, 2, 2], np.exp(-0.5), rtol=1e-6)


# --------------------------------------------------------------------------- bad input
def test_bad_input_messages_name_the_shapes():
    y = np.zeros((6, 7, 3))
    w = np.ones((6, 7, 3, 3))
    with pytest.raises(InputError, match=r"`z` must have the shape of `y` \(6, 7, 3\); got \(6, 8, 3\)"):
        combine(y, np.zeros((6, 8, 3)), w)
    with pytest.raises(InputError, match=r"B = 2 buffers on axis 2 to match the 2 buffers of `ys`/`zs`; got weights of shape \(6, 7, 4, 3, 3\)"):
        combine_multi(np.zeros((2, 6, 7, 3)), np.zeros((2, 6, 7, 3)), np.ones((6, 7, 4, 3, 3)))
    with pytest.raises(InputError, match=r"B = 4 buffers .* use `combine_multi"):
        combine(y, y, np.ones((6, 7, 4, 3, 3)))
    with pytest.raises(InputError, match=r"leading shape \(H, W\) = \(6, 7\); got \(7, 6, 3, 3\)"):
        combine(y, y, np.ones((7, 6, 3, 3)))
    with pytest.raises(InputError, match="odd window size"):
        combine(y, y, np.ones((6, 7, 4, 4)))
    with pytest.raises(InputError, match=r"shape \(H, W, k, k\)"):
        combine(y, y, np.ones((6, 7, 3, 5)))
    with pytest.raises(InputError, match="NaN"):
        combine(np.full((6, 7, 3), np.nan), y, w)
    bad = w.copy()
    bad[2, 3] = 0.0
    with pytest.raises(InputError, match=r"1 pixel\(s\) fail, the first at \(row 2, column 3\)"):
        combine(y, y, bad)
    bad = w.copy()
    bad[4, 1, 1, 1] = np.nan
    with pytest.raises(InputError, match=r"row 4, column 1"):
        combine(y, y, bad)
    with pytest.raises(InputError, match="numeric"):
        combine(y, y, np.full((6, 7, 3, 3), "a"))


def test_bad_moments_messages():
    y = np.zeros((6, 7, 3))
    w = np.ones((6, 7, 3, 3))
    with pytest.raises(InputError, match="`var_y` is missing"):
        combine_bias_variance(w, None, y)
    with pytest.raises(InputError, match="`cov_z` is missing"):
        combine_bias_variance(w, y, None)
    with pytest.raises(InputError, match="`var_y` is missing"):
        statistical_weights(y, y, None, y, 3)
    with pytest.raises(InputError, match="`cov_z` is missing"):
        statistical_weights(y, y, y, None, 3)
    with pytest.raises(InputError, match=r"`var_y` must have shape \(6, 7, 3\) or \(2, 6, 7, 3\).*got \(3, 6, 7, 3\)"):
        combine_bias_variance(np.ones((6, 7, 2, 3, 3)), np.zeros((3, 6, 7, 3)), y)
    with pytest.raises(InputError, match=r"`cov_z` must be a covariance stencil .*got \(6, 7, 4, 4, 3\)"):
        combine_bias_variance(w, y, np.zeros((6, 7, 4, 4, 3)))
    with pytest.raises(InputError, match=">= 0"):
        combine_bias_variance(w, -np.ones((6, 7, 3)), y)
    with pytest.raises(InputError, match="`method`"):
        statistical_weights(y, y, y, y, 3, method="nnls")
    with pytest.raises(InputError, match="`z_bias`"):
        statistical_weights(y, y, y, y, 3, z_bias="guess")
    with pytest.raises(InputError, match="`size`"):
        statistical_weights(y, y, y, y, 4)
    with pytest.raises(InputError, match="B >= 2"):
        buffer_moments(y[None], y[None], size=3)
    with pytest.raises(InputError, match=r"`var` must have shape \(6, 7, C\)"):
        filter_covariance(w, np.zeros((5, 7, 3)))
    with pytest.raises(InputError, match="`sigma`"):
        gaussian_weights(2, 2, 1, 3, 0.0)
    with pytest.raises(InputError, match="`buffers`"):
        uniform_weights(2, 2, 0, 3)


# --------------------------------------------------------------------------- denoiser + combiner
def test_denoiser_moments_match_exact_moments_of_a_linear_denoiser():
    """First-order probe moments of a Gaussian filter equal ``filter_covariance`` (exact for
    a linear denoiser) in expectation: z-scores of the probe means, Bonferroni over entries."""
    from statmc import denoisers

    H, W, C, m, K = 9, 10, 2, 3, 400
    rng = np.random.default_rng(41)
    x = rng.gamma(2.0, 0.5, (H, W, C))
    mv = rng.gamma(2.0, 0.05, (H, W, C))
    f = denoisers.gaussian(1.0)
    exact_z, exact_yz = filter_covariance(f.kernels((H, W, C)), mv, size=m, cross=True)
    z, cz, cyz, V, JV = denoiser_moments(f, x, mv, size=m, probes=K, rng=3, extra_output=True)
    np.testing.assert_allclose(z, f(x.astype(np.float32)), rtol=1e-6)
    assert V.shape == JV.shape == (K, H, W, C)
    R = m // 2
    for est, exact, left in ((cz, exact_z, JV), (cyz, exact_yz, V)):
        # per-probe products give i.i.d. samples; their spread is the standard error
        prods = np.stack([left[i][:, :, None, None] * np.stack(
            [np.stack([np.roll(np.roll(JV[i], -vy, 0), -vx, 1) for vx in range(-R, R + 1)], 2)
             for vy in range(-R, R + 1)], 2) for i in range(K)])
        se = prods.std(axis=0, ddof=1) / np.sqrt(K)
        inside = (np.abs(exact) > 0) & (se > 0)      # offsets inside the image (no wrap)
        # the stencil is the mean of the K per-probe products (÷ K, not K − 1: v has a
        # known zero mean; a 400/399 slip is invisible to the z-test below)
        np.testing.assert_allclose(est[inside], prods.mean(axis=0)[inside], rtol=1e-9)
        zs = (est - exact)[inside] / se[inside]
        p = 2 * stats.norm.sf(np.abs(zs)).min() * zs.size
        assert p > ALPHA, (np.abs(zs).max(), zs.size)


def test_mix_gain_is_unbiased_for_a_linear_denoiser():
    """Stein: with weights independent of y, E[r ρ − a_c σ² + Σ a_t cov(y_c, z_t)] equals
    −E[(z − μ) ρ] (the quantity the SURE mix needs).  Over 300 toy renders, the image-summed
    difference of estimate and truth has mean zero (t-test), and the naive r·ρ does not."""
    from statmc import denoisers
    from statmc.combine import _mix_gain

    H, spp, reps, k = 24, 16, 300, 7
    r = ToyRenderer("edges", width=H, height=H)
    mu = r.true_mean()
    f = denoisers.gaussian(1.5)
    w = np.ascontiguousarray(gaussian_weights(H, H, 1, k, 2.0))
    mv = r.true_var() / spp
    diffs, naive = [], []
    for i in range(reps):
        y = r.render_uniform(spp, seed=(11, i), features=False).mean
        z, _, _, V, JV = denoiser_moments(f, y, mv, size=1, probes=4, rng=i, extra_output=True)
        beta = combine(y, z, w)
        truth = -(z - mu) * (beta - z)
        diffs.append((_mix_gain(y, z, beta, mv, w, V, JV) - truth).sum())
        naive.append(((y - z) * (beta - z) - truth).sum())
    t = stats.ttest_1samp(diffs, 0.0)
    assert t.pvalue > ALPHA, (np.mean(diffs), np.std(diffs))
    assert stats.ttest_1samp(naive, 0.0).pvalue < ALPHA       # the Stein terms matter


def test_simplex_mix_minimises_its_quadratic():
    from scipy.optimize import minimize
    from statmc.combine import _simplex_mix

    rng = np.random.default_rng(8)
    for J in (1, 2, 3):
        A = rng.normal(size=(20, J, J + 2))
        G = A @ np.swapaxes(A, 1, 2)
        b = rng.normal(size=(20, J)) * 2.0
        lam = _simplex_mix(G, b)
        assert (lam >= -1e-12).all() and (lam.sum(-1) <= 1 + 1e-9).all()
        for g, bb, mine in zip(G, b, lam):
            def q(x):
                return float(x @ g @ x - 2 * bb @ x)
            res = minimize(q, np.full(J, 0.1), method="SLSQP", bounds=[(0, 1)] * J,
                           constraints=[{"type": "ineq", "fun": lambda x: 1 - x.sum()}],
                           options={"ftol": 1e-14, "maxiter": 500})
            assert q(mine) <= res.fun + 1e-7 * (1 + abs(res.fun))


def test_combine_denoised_improves_a_blurring_denoiser():
    """A σ = 2 Gaussian blur is biased at the edges of the toy 'edges' scene; the combiner
    with its SURE mix lowers the relMSE in every one of 8 renders at 64 spp (sign test),
    and the leave-centre-out weights are what make the combination itself help."""
    from statmc import denoisers
    from statmc.metrics import relmse

    H, spp, reps = 40, 64, 8
    r = ToyRenderer("edges", width=H, height=H)
    mu = r.true_mean()
    f = denoisers.gaussian(2.0)
    better = 0
    for i in range(reps):
        st = r.render_uniform(spp, seed=(12, i), features=False)
        out, info = combine_denoised(st.mean, st.mean_var, f, rng=i, extra_output=True)
        assert info["combined"].shape == (2, H, H, 3) and info["mix"].shape == (H, H, 2)
        better += relmse(out, mu) < relmse(info["denoised"], mu)
    assert stats.binomtest(better, reps, 0.5, alternative="greater").pvalue < 0.01


def test_reconstruct_stats_combine_methods():
    from statmc.pipeline import RECONSTRUCTIONS, reconstruct_stats

    assert "oidn+combine" in RECONSTRUCTIONS and "combine" in RECONSTRUCTIONS
    st = ToyRenderer("edges", width=24, height=20).render_uniform(16, seed=1)
    img, maps = reconstruct_stats(st, "combine", denoiser="gaussian", sigma=1.5)
    assert img.shape == (20, 24, 3) and img.dtype == np.float32 and np.isfinite(img).all()
    assert maps["mix"].shape == (20, 24) and (maps["mix"] >= 0).all() and (maps["mix"] <= 1 + 1e-6).all()


def test_combine_denoised_bad_input():
    from statmc import denoisers

    y = np.ones((8, 9, 3))
    f = denoisers.gaussian(1.0)
    with pytest.raises(InputError, match="mean_var"):
        combine_denoised(y, np.ones((8, 8, 3)), f)
    with pytest.raises(InputError, match="`var`"):
        combine_denoised(y, y, f, var="median")
    with pytest.raises(InputError, match="`mix`"):
        combine_denoised(y, y, f, mix="median")
    with pytest.raises(InputError, match="shape"):
        combine_denoised(y, y, lambda c: c[:4])
    with pytest.raises(InputError, match="probes"):
        denoiser_moments(f, y, y, probes=0)
    with pytest.raises(InputError, match="denoiser"):
        denoiser_moments("oidn", y, y)


def test_neighbour_products_sum_kernel_equals_numpy_reference_to_the_bit():
    """``add_neighbour_products_sum`` (``denoiser_moments``' probes in one pass) equals its
    NumPy reference and K calls of ``add_neighbour_products`` exactly, skipped probes and
    borders included."""
    from statmc import _stencil_kernels as sk

    rng = np.random.default_rng(12)
    for K, h, w, R in ((4, 7, 5, 2), (3, 6, 9, 3), (1, 3, 4, 4), (5, 1, 1, 1)):
        a = rng.normal(size=(K, h, w, 3))
        b = rng.normal(size=(K, h, w, 3))
        use = rng.random(K) < 0.7
        use[0] = True
        start = rng.normal(size=(h, w, 2 * R + 1, 2 * R + 1, 3))
        fast = start.copy()
        sk.add_neighbour_products_sum(fast, a, b, R, use)
        ref = sk.add_neighbour_products_sum_numpy(start.copy(), a, b, R, use)
        np.testing.assert_array_equal(fast, ref)
        calls = start.copy()
        for i in np.flatnonzero(use):
            sk.add_neighbour_products(calls, a[i], b[i], R)
        np.testing.assert_array_equal(fast, calls)


def test_neighbour_products_kernel_equals_numpy_reference_to_the_bit():
    """``statmc._stencil_kernels``: the compiled ``prod[p, R+v] += a_p · b_{p+v}`` equals the
    NumPy reference exactly (same operations, no fused multiply-add), borders and offsets
    wider than the image included, for a = b (CRN renders) and a ≠ b (denoiser_moments)."""
    from statmc import _stencil_kernels as sk

    rng = np.random.default_rng(11)
    for h, w, R in ((7, 5, 0), (7, 5, 2), (6, 9, 3), (3, 4, 4), (1, 1, 1)):
        a = rng.normal(size=(h, w, 3))
        b = rng.normal(size=(h, w, 3))
        start = rng.normal(size=(h, w, 2 * R + 1, 2 * R + 1, 3))
        for x, y in ((a, a), (a, b)):
            fast = start.copy()
            sk.add_neighbour_products(fast, x, y, R)
            ref = sk.add_neighbour_products_numpy(start.copy(), x, y, R)
            np.testing.assert_array_equal(fast, ref)
            # and by the definition, one element at a time
            for yy, xx, dy, dx in ((0, 0, R, R), (h - 1, w - 1, -R, -R), (h // 2, w // 2, 0, R)):
                inside = 0 <= yy + dy < h and 0 <= xx + dx < w
                want = start[yy, xx, R + dy, R + dx] + (x[yy, xx] * y[yy + dy, xx + dx]
                                                        if inside else 0.0)
                np.testing.assert_array_equal(fast[yy, xx, R + dy, R + dx], want)


# --------------------------------------------------------------------------- sample bins
def _bins_and_kernel(seed=0, B=4, spp=16, scene="edges"):
    """``B`` bins of a toy render, the merged render and GEM's full-sample kernel."""
    from statmc import gem
    from statmc.pipeline import merge_bins
    r = ToyRenderer(scene, width=40, height=32)
    bins = [r.render_uniform(spp // B, seed=100 * seed + b) for b in range(B)]
    full = merge_bins(bins)
    _, f = gem.selected_filter(full.mean.astype(np.float32), full.mean_var.astype(np.float32))
    return bins, full, f


def test_combine_bins_with_a_shared_linear_kernel_is_eq8_on_the_bin_means():
    """Back 2020 §4.4 shares the full-sample kernel among the bins, z_b = K y_b.  The
    classical weights give every bin the same moments and the same (bin-averaged) tap
    biases, so they are equal across bins, and then Eq. 14 is Eq. 8 on the bin means:
    Σ_b w (y_b + z_{c,b} − z_{i,b}) = B w (ȳ + (Kȳ)_c − (Kȳ)_i).  Fails if combine_bins
    let the weights differ between bins or did not share the kernel."""
    from statmc.combine import combine_bins
    bins, full, f = _bins_and_kernel()
    ys = np.stack([b.mean for b in bins])
    out, info = combine_bins(ys, full.mean_var, f, size=7, rng=0, mix=None, extra_output=True)
    w = info["weights"]
    for b in range(1, len(bins)):
        np.testing.assert_array_equal(w[:, :, b], w[:, :, 0])
    ybar = ys.mean(axis=0)
    np.testing.assert_allclose(info["denoised"].mean(axis=0), f(ybar.astype(np.float32)),
                               rtol=1e-5, atol=1e-6)
    # each bin its own image under the shared kernel (z_b = K ȳ for every b would pass
    # the two checks above and the Eq. 8 identity below)
    for b in range(len(bins)):
        np.testing.assert_allclose(info["denoised"][b], f(ys[b].astype(np.float32)),
                                   rtol=1e-5, atol=1e-6)
    want = combine(ybar, f(ybar.astype(np.float32)).astype(np.float64), w[:, :, 0])
    np.testing.assert_allclose(out, want, rtol=1e-4, atol=1e-5)
    assert np.max(np.abs(out - ybar)) > 1e-3 and np.max(np.abs(out - want)) < 1e-4


def test_combine_bins_gives_the_weights_per_bin_moments(monkeypatch):
    """The moments of one bin are B times those of the full-sample mean: var(y_b) =
    B·mean_var (box-smoothed), cov(z_b) = B·cov(Kȳ) — checked against the exact
    covariance of the linear kernel, A diag(B·mean_var) Aᵀ with A from unit impulses."""
    import statmc.combine as cbm
    bins, full, f = _bins_and_kernel(seed=1)
    B = len(bins)
    ys = np.stack([b.mean for b in bins])
    seen = {}
    real = cbm._statistical_weights        # the banded path's (statistical_weights + rows)

    def spy(y, z, var_y, cov_z, size, **kw):
        seen.update(var_y=var_y, cov_z=cov_z, cov_yz=kw["cov_yz"])
        return real(y, z, var_y, cov_z, size, **kw)

    monkeypatch.setattr(cbm, "_statistical_weights", spy)
    cbm.combine_bins(ys, full.mean_var, f, size=3, stencil=3, probes=400, smooth=0, rng=2)
    np.testing.assert_allclose(seen["var_y"], B * cbm._box(full.mean_var, 2), rtol=1e-12)
    H, W, C = full.mean.shape
    A = np.zeros((H * W, H * W))
    for q in range(H * W):
        e = np.zeros((H, W), np.float32)
        e.flat[q] = 1.0
        A[:, q] = f(e).ravel()
    c = 1
    S = A @ np.diag(B * full.mean_var[..., c].ravel()) @ A.T
    # horizontal neighbour covariance of z_b at interior pixels, probe estimate vs exact
    pix = [(y, x) for y in range(4, H - 4, 5) for x in range(4, W - 4, 5)]
    est = np.array([seen["cov_z"][y, x, 1, 2, c] for y, x in pix])
    exact = np.array([S[y * W + x, y * W + x + 1] for y, x in pix])
    var0 = np.array([S[y * W + x, y * W + x] for y, x in pix])
    # 400 ±σ probes: relative error of a covariance entry ~ sqrt(2/400) of the variance
    assert np.all(np.abs(est - exact) < 5 * np.sqrt(2 / 400) * var0 + 1e-12)
    assert np.corrcoef(est, exact)[0, 1] > 0.9
    # without the factor B the estimate would sit at 1/4 of the exact values
    assert np.median(est / np.where(exact != 0, exact, np.nan)) == pytest.approx(1, abs=0.25)
    # cov(y_b at p, z_b at p + (0, 1)) = A[p+1, p] · B mean_var_p, the same factor B
    est = np.array([seen["cov_yz"][y, x, 1, 2, c] for y, x in pix])
    exact = np.array([A[y * W + x + 1, y * W + x] * B * full.mean_var[y, x, c] for y, x in pix])
    sd = np.array([np.sqrt(B * full.mean_var[y, x, c] * S[y * W + x + 1, y * W + x + 1])
                   for y, x in pix])
    assert np.all(np.abs(est - exact) < 5 * sd / np.sqrt(400) + 1e-12)
    assert np.count_nonzero(exact) >= len(pix) // 2
    assert np.nanmedian(est / np.where(exact != 0, exact, np.nan)) == pytest.approx(1, abs=0.25)


def test_combine_bins_refuses_bad_input():
    from statmc.combine import combine_bins
    bins, full, f = _bins_and_kernel(seed=2)
    ys = np.stack([b.mean for b in bins])
    with pytest.raises(InputError, match="B >= 2"):
        combine_bins(ys[:1], full.mean_var, f)
    with pytest.raises(InputError, match="shape of one bin"):
        combine_bins(ys, full.mean_var[:-1], f)
    with pytest.raises(InputError, match="callable"):
        combine_bins(ys, full.mean_var, None)
    bad = ys.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(InputError, match="ys"):
        combine_bins(bad, full.mean_var, f)
    with pytest.raises(InputError, match="mean_var"):
        combine_bins(ys, -full.mean_var - 1, f)


def test_pipeline_combine_with_gem_uses_gems_exposed_kernel():
    """`reconstruct_stats(..., "combine", denoiser="gem")` selects GEM's kernels once on
    the render and combines with that fixed linear filter (its moments are then exact),
    not with GEM as a black box that selects again on every probe."""
    from statmc import gem
    from statmc.pipeline import reconstruct_stats
    from statmc.progressive import bind_denoiser
    stats = ToyRenderer("edges", width=40, height=32).render_uniform(8, seed=4)
    img, _ = reconstruct_stats(stats, "combine", denoiser="gem", seed=5)
    _, f = gem.selected_filter(stats.mean.astype(np.float32), stats.mean_var.astype(np.float32),
                               n=stats.n)
    want = combine_denoised(stats.mean, stats.mean_var, f, rng=5)
    np.testing.assert_allclose(img, want, rtol=1e-5, atol=1e-6)
    black_box = combine_denoised(stats.mean, stats.mean_var, bind_denoiser("gem", stats), rng=5)
    assert np.max(np.abs(black_box - want)) > 1e-4


def test_render_bins_and_reconstruct_bins_check_their_input():
    from statmc.pipeline import bin_seed, reconstruct_bins, render_bins
    r = ToyRenderer("edges", width=16, height=12)
    assert len({bin_seed(s, b) for s in range(4) for b in range(4)}) == 16
    with pytest.raises(InputError, match="multiple of `bins`"):
        render_bins(r, 6, 4)
    bins = render_bins(r, 8, 4, seed=1)
    assert [int(b.n.max()) for b in bins] == [2] * 4
    assert not np.array_equal(bins[0].mean, bins[1].mean)
    with pytest.raises(InputError, match="other sample counts"):
        reconstruct_bins([bins[0], bins[1].merge(bins[2])])
    with pytest.raises(InputError, match="at least 2"):
        reconstruct_bins(bins[:1])
    with pytest.raises(InputError, match="unknown bin reconstruction"):
        reconstruct_bins(bins, "gem")


def test_bin_seeds_refuse_negative_seeds_with_an_input_error():
    """A negative seed gave NumPy's bare ValueError from SeedSequence, not an InputError
    naming the parameter."""
    from statmc.pipeline import bin_seed, render_bins
    with pytest.raises(InputError, match="`seed`"):
        bin_seed(-1, 0)
    with pytest.raises(InputError, match="`seed`"):
        render_bins(ToyRenderer("edges", width=8, height=6), 4, 2, seed=-1)


def _band_bytes(rows, W, B, k, margin, m=5, C=3):
    """A ``BAND_BYTES`` giving bands of ``rows`` output rows (when ``rows >= 2 margin``
    and the image splits evenly): weights and two smoothed stencils per row."""
    return (rows + 2 * margin) * (W * B * k * k * 4 + 2 * W * m * m * C * 8)


def test_combine_bins_in_bands_of_rows_equals_one_piece(monkeypatch):
    """The weights and moment stencils of a large image are formed in bands of rows with a
    margin of k // 2 + patch rows: the output must be what the whole image at once gives,
    to the bit, and the unbanded pipeline assembled by hand (denoiser_moments at the bin
    mean, B x the 5x5 box of the stencils, weights, Eq. 14).  A margin one row short
    changes the output (the test can see a wrong margin)."""
    import statmc.combine as cbm
    bins, full, f = _bins_and_kernel(seed=3)
    ys = np.stack([b.mean for b in bins])
    whole, info = cbm.combine_bins(ys, full.mean_var, f, size=7, patch=2, rng=1, mix=None,
                                   extra_output=True)
    B, H, W, _ = ys.shape
    _, cz, cyz = denoiser_moments(f, ys.mean(axis=0), full.mean_var, size=5, rng=1)
    var_y = B * np.maximum(cbm._box(full.mean_var, 2), 0.0)
    w = statistical_weights(ys, info["denoised"], var_y, B * cbm._box(cz, 2), 7,
                            cov_yz=B * cbm._box(cyz, 2), patch=2)
    np.testing.assert_array_equal(w, info["weights"])
    np.testing.assert_array_equal(whole, combine_multi(ys, info["denoised"], w))
    for rows in (1, 10, 13):
        monkeypatch.setattr(cbm, "BAND_BYTES", _band_bytes(rows, W, B, 7, 5))
        banded = cbm.combine_bins(ys, full.mean_var, f, size=7, patch=2, rng=1, mix=None)
        np.testing.assert_array_equal(banded, whole)
    monkeypatch.setattr(cbm, "_band_margin", lambda k, patch: k // 2 + patch - 1)
    assert not np.array_equal(cbm.combine_bins(ys, full.mean_var, f, size=7, patch=2, rng=1,
                                               mix=None), whole)


def test_combine_bins_return_denoised_keeps_the_bands(monkeypatch):
    """``return_denoised`` gives the denoised bins without forming the whole image's
    weights (reconstruct_bins used extra_output, which needs 7.5 GB of weights at 1080p)."""
    import statmc.combine as cbm
    from statmc.pipeline import reconstruct_bins
    bins, full, f = _bins_and_kernel(seed=4)
    ys = np.stack([b.mean for b in bins])
    whole, info = cbm.combine_bins(ys, full.mean_var, f, size=7, patch=2, rng=1,
                                   extra_output=True)
    B, H, W, _ = ys.shape
    monkeypatch.setattr(cbm, "BAND_BYTES", _band_bytes(10, W, B, 7, 5))
    seen = []
    real = cbm._statistical_weights        # the banded path's (statistical_weights + rows)
    monkeypatch.setattr(cbm, "_statistical_weights",
                        lambda ys, *a, **k: seen.append(ys.shape[1]) or real(ys, *a, **k))
    out, zs = cbm.combine_bins(ys, full.mean_var, f, size=7, patch=2, rng=1,
                               return_denoised=True)
    np.testing.assert_array_equal(out, whole)
    np.testing.assert_array_equal(zs, info["denoised"])
    assert len(seen) > 1 and max(seen) < H          # banded
    seen.clear()
    img, _, (ys2, zs2) = reconstruct_bins(bins, "gem+bins", return_bins=True)
    assert len(seen) > 1 and max(seen) < H
    np.testing.assert_array_equal(ys2, ys)


def test_combine_bin_images_is_eq14_with_moments_from_the_bin_spread(monkeypatch):
    """Bins made elsewhere: buffer_moments over the bins (smoothed), coherent statistical
    weights and Eq. 14 — the same numbers assembled by hand, in one piece and in bands."""
    import statmc.combine as cbm
    from scipy.ndimage import uniform_filter
    from statmc.filters import gaussian_filter
    r = ToyRenderer("edges", width=36, height=28)
    ys = np.stack([r.render_uniform(4, seed=60 + b).mean for b in range(4)])
    zs = np.stack([gaussian_filter(y, 2.0) for y in ys])      # z_b from bin b alone: i.i.d.
    var_y, cov_z, cov_yz = buffer_moments(ys, zs, size=3)
    box = lambda a: uniform_filter(a, (5, 5) + (1,) * (a.ndim - 2), mode="reflect")  # noqa: E731
    w = statistical_weights(ys, zs, box(var_y), box(cov_z), 7, cov_yz=box(cov_yz))
    want = combine_multi(ys, zs, w)
    got = cbm.combine_bin_images(ys, zs, size=7, stencil=3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    for rows in (10, 13):
        monkeypatch.setattr(cbm, "BAND_BYTES", _band_bytes(rows, 36, 4, 7, 5, m=3))
        np.testing.assert_array_equal(cbm.combine_bin_images(ys, zs, size=7, stencil=3), got)
    with pytest.raises(InputError, match="patch"):
        cbm.combine_bin_images(ys, zs, patch=-1)
    with pytest.raises(InputError):
        cbm.combine_bin_images(ys[:1], zs[:1])


def test_combine_bin_images_survives_box_filter_rounding_below_zero():
    """Zero spread next to a wildly varying region: the box filter's running sums leave
    smoothed variances of about -1e-13, which statistical_weights would refuse."""
    from scipy.ndimage import uniform_filter
    from statmc.combine import combine_bin_images
    rng = np.random.default_rng(0)
    ys = np.full((4, 20, 20, 3), 0.25)
    ys[:, :, :6] = rng.gamma(0.3, 50, (4, 20, 6, 3))
    var_y = buffer_moments(ys, ys, size=3)[0]
    assert uniform_filter(var_y, (5, 5, 1), mode="reflect").min() < 0      # the trap is set
    out = combine_bin_images(ys, ys, size=5)
    np.testing.assert_allclose(out[:, 9:], 0.25, atol=1e-9)   # z = y: flat region stays flat


def test_combine_bin_images_names_stencil_and_keeps_channel_less_bins_channel_less():
    """A bad `stencil` is named as such (it was reported as `size`, and combine_bins
    reported it only after denoising every bin); (B, H, W) bins give an (H, W) image as
    combine_multi does (it was (H, W, 1))."""
    import statmc.combine as cbm
    rng = np.random.default_rng(4)
    ys = rng.gamma(2.0, 0.5, (3, 10, 12))
    zs = 0.5 * (ys + ys.mean())                     # a shrinkage "denoiser" per bin
    out = cbm.combine_bin_images(ys, zs, size=5)
    assert out.shape == (10, 12)
    np.testing.assert_array_equal(out, cbm.combine_bin_images(ys[..., None], zs[..., None],
                                                              size=5)[..., 0])
    with pytest.raises(InputError, match="`stencil`"):
        cbm.combine_bin_images(ys, zs, stencil=4)
    calls = []

    def den(x):
        calls.append(1)
        return x
    with pytest.raises(InputError, match="`stencil`"):
        cbm.combine_bins(ys[..., None], ys.var(axis=0)[..., None] / 3, den, stencil=4)
    assert not calls


def test_pipeline_combine_refuses_pixels_without_a_variance():
    """A hole (0 samples) has variance 0 in mean_var: the combiner would take it as exact."""
    from statmc.pipeline import reconstruct_stats
    st = ToyRenderer("edges", width=16, height=12).render_uniform(8, seed=1)
    n = st.n.copy()
    n[1, 1] = 0
    holed = PixelStats(n, st.mean, st.m2)
    for method, den in (("combine", "gaussian"), ("combine", "gem"), ("oidn+combine", "oidn")):
        with pytest.raises(InputError, match="1 pixels with fewer than 2"):
            reconstruct_stats(holed, method, denoiser=den)


def test_reconstruct_bins_refuses_pixels_without_a_variance():
    """Bins whose merge leaves pixels with fewer than 2 samples: their zero mean_var would
    count as exact in the weights (as in reconstruct_stats' combiners)."""
    from statmc.pipeline import reconstruct_bins
    r = ToyRenderer("edges", width=16, height=12)
    counts = np.full((12, 16), 2)
    counts[4, 5] = 0
    bins = [r.render(counts, seed=70 + b) for b in range(2)]
    for method in ("gem+bins", "oidn+bins"):
        with pytest.raises(InputError, match="1 pixels with fewer than 2 samples"):
            reconstruct_bins(bins, method)


# --------------------------------------------------------------------------- banded moments
def test_running_rows_kernel_equals_numpy_reference_to_the_bit():
    """``_combine_kernels.running_rows`` (the rows pass of _SmoothedRows) equals its NumPy
    reference exactly: the same update ``t += x[a] − x[b]``, ``out = t / n`` per row, over
    several column tiles and with repeated (reflected) rows."""
    rng = np.random.default_rng(13)
    for rows, L, n in ((9, 5, 5), (12, 2 * ck.RUN_TILE + 37, 3), (1, 1, 1)):
        x = rng.normal(size=(rows, L)) * 10.0 ** rng.integers(-3, 3, size=(rows, L))
        add = rng.integers(0, rows, 2 * rows).astype(np.int64)
        sub = rng.integers(0, rows, 2 * rows).astype(np.int64)
        t0 = rng.normal(size=L)
        t1, t2 = t0.copy(), t0.copy()
        o1, o2 = np.empty((2 * rows, L)), np.empty((2 * rows, L))
        ck.running_rows(x, add, sub, n, t1, o1)
        ck.running_rows_numpy(x, add, sub, n, t2, o2)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(t1, t2)


def test_smoothed_rows_equal_scipys_box_of_the_whole_image_to_the_bit():
    """_SmoothedRows hands out box-smoothed stencils band after band, carrying the
    running sums of the rows pass from band to band: whatever the bands (overlapping as in
    the band loops), borders included and images shorter than the box (reflected more than
    once), they are bit for bit the one-piece result, which is ``scale · _box(stencil,
    radius)`` of the whole image.  With SciPy 1.17 that is also to the bit, because the rows
    pass runs SciPy's sums in SciPy's order; the library needs only bands == one piece, so
    against SciPy the test allows the rounding of a running sum (another SciPy may sum
    differently).  Restarting the box on each band (without the carried sums) is *not* bit
    for bit, which is why they are carried."""
    from scipy.ndimage import uniform_filter

    import statmc.combine as cbm
    rng = np.random.default_rng(21)
    eps = np.finfo(np.float64).eps
    for H, W, radius, scale in ((23, 6, 2, None), (23, 6, 3, 4), (9, 5, 0, 2), (1, 4, 2, None),
                                (2, 3, 2, None), (3, 7, 4, None)):
        x = rng.normal(size=(H, W, 3, 3, 2)) * 10.0 ** rng.integers(-4, 4, (H, W, 3, 3, 2))
        y = 2 * x
        f = 1.0 if scale is None else scale
        scipy_box = [f * cbm._box(a, radius) for a in (x, y)]
        want = cbm._SmoothedRows(lambda r0, r1: (x[r0:r1].copy(), y[r0:r1].copy()), H, radius,
                                 scale=scale).rows(0, H)
        for w_, b_, a in zip(want, scipy_box, (x, y)):
            # a running sum over H + 2 radius + 1 rows: each step rounds at most the sum's size
            np.testing.assert_allclose(w_, b_, rtol=0,
                                       atol=4 * (H + 2 * radius + 1) * eps * f * np.abs(a).max())
        for rows, margin in ((H, 0), (1, 0), (4, 2), (5, 3), (7, 1)):
            sr = cbm._SmoothedRows(lambda r0, r1: (x[r0:r1].copy(), y[r0:r1].copy()), H,
                                   radius, scale=scale)
            for a in range(0, H, rows):
                b = min(H, a + rows)
                lo, hi = max(0, a - margin), min(H, b + margin)
                got = sr.rows(lo, hi)
                for g, wnt in zip(got, want):
                    np.testing.assert_array_equal(g, wnt[lo:hi])
    x = rng.normal(size=(40, 8, 1, 1, 3))
    band = uniform_filter(x[20:], (5, 5, 1, 1, 1), mode="reflect")[2:]
    assert not np.array_equal(band, cbm._box(x, 2)[22:])
    sr = cbm._SmoothedRows(lambda r0, r1: (x[r0:r1],), 40, 2)
    sr.rows(0, 12)
    with pytest.raises(ValueError, match="move down"):
        sr.rows(0, 10)


def test_probe_stencil_rows_equal_the_whole_image_stencils_to_the_bit():
    """Rows r0 .. r1 of the probe stencils, from a slab with m // 2 rows of margin, are
    those of ``denoiser_moments`` on the whole image (borders, a band of one row, bands
    wider than the image's rows, a skipped probe of a black image)."""
    import statmc.combine as cbm
    from statmc import denoisers
    rng = np.random.default_rng(22)
    f = denoisers.gaussian(1.5)
    for H, W, C, m in ((17, 9, 3, 5), (17, 9, 1, 3), (2, 5, 3, 5)):
        x = rng.gamma(2.0, 0.5, (H, W, C))
        mv = rng.gamma(2.0, 0.02, (H, W, C))
        z, cz, cyz, V, JV = denoiser_moments(f, x, mv, size=m, probes=3, rng=4,
                                             extra_output=True)
        pr = cbm._probe_vectors(f, x, mv, 3, 4, 1e-3)
        np.testing.assert_array_equal(np.stack([pr.v(i) for i in range(3)]), V)
        for r0, r1 in ((0, H), (0, 1), (H - 1, H), (H // 2, H // 2 + 1), (1, H - 1)):
            if r1 <= r0:
                continue
            a, b = pr.stencils(m, r0, r1)
            np.testing.assert_array_equal(a, cz[r0:r1])
            np.testing.assert_array_equal(b, cyz[r0:r1])
    zero = np.zeros((5, 4, 3))
    z, cz, cyz, V, JV = denoiser_moments(f, zero, np.ones_like(zero), size=3, probes=2,
                                         extra_output=True)
    assert not cz.any() and not cyz.any() and not V.any() and not JV.any()


@pytest.mark.parametrize("H, W, C", [(31, 12, 3), (37, 12, 1), (3, 5, 3)])
def test_combine_denoised_in_bands_of_rows_equals_one_piece(monkeypatch, H, W, C):
    """combine_denoised forms the probe stencils, the weights, β̂ and the SURE terms in
    bands of rows (the stencils and weights of a 1080p image took 5 GB at once): bit for
    bit the output, β̂ and mix of one band, for any band size (31 rows in bands of 10: a
    last band inside the previous one's margin), one channel, an image shorter than a
    band's margin; equal to the unbanded pipeline assembled by hand
    (mix=None); a margin one row short changes the output."""
    import statmc.combine as cbm
    from statmc import denoisers
    rng = np.random.default_rng(23 + C)
    y = rng.gamma(2.0, 0.5, (H, W, C))
    mv = rng.gamma(2.0, 0.01, (H, W, C))
    f = denoisers.gaussian(1.5)
    kw = dict(size=7, patch=2, rng=3, extra_output=True)
    whole = {mix: cbm.combine_denoised(y, mv, f, mix=mix, **kw)
             for mix in ("local", "global", None)}
    # mix=None, var="smooth" by hand: the moments, box, weights and Eq. 8 of the old code
    z, cz, cyz = denoiser_moments(f, y, mv, size=5, probes=8, rng=3)
    sm = np.maximum(cbm._box(mv, 2), 0.0)
    w = statistical_weights(y, z, sm, cbm._box(cz, 2), 7, cov_yz=cbm._box(cyz, 2), patch=2,
                            leave_centre_out=True)
    np.testing.assert_array_equal(whole[None][0], combine(y, z, w))
    for rows in (10, 11, 17):
        monkeypatch.setattr(cbm, "BAND_BYTES", _band_bytes(rows, W, 1, 7, 5, C=C))
        for mix, (out, info) in whole.items():
            got, ginfo = cbm.combine_denoised(y, mv, f, mix=mix, **kw)
            np.testing.assert_array_equal(got, out)
            np.testing.assert_array_equal(ginfo["combined"], info["combined"])
            if mix is not None:
                np.testing.assert_array_equal(ginfo["mix"], info["mix"])
    if H > 2 * 5:
        monkeypatch.setattr(cbm, "_band_margin", lambda k, patch: k // 2 + patch - 1)
        short = cbm.combine_denoised(y, mv, f, mix=None, **kw)[0]
        assert not np.array_equal(short, whole[None][0])


# ----------------------------------------------------- combine_bins' SURE mix with f(ȳ)
def _gauss_blur(sigma):
    """A linear denoiser (shared by the bins when applied to each), fast on small images."""
    from scipy.ndimage import gaussian_filter
    return lambda x: gaussian_filter(x, (sigma, sigma, 0), mode="nearest")


def _draw_bins(r, spp, B, seed):
    from statmc.pipeline import merge_bins
    bins = [r.render_uniform(spp // B, seed=(seed, b), features=False) for b in range(B)]
    full = merge_bins(bins)
    return np.stack([b.mean for b in bins]), full


def test_combine_bins_mix_falls_back_to_an_exact_denoiser():
    """A 'denoiser' returning the noise-free truth: z = f(ȳ) is exact, so any ρ = β̂ − z
    only adds error and b = −E[(z − μ) ρ] = 0.  The mix must go to z: small λ and an
    output far closer to the truth than β̂ (without the mix, or with SURE terms that
    overrate β̂, the output would be β̂).  The estimate of b is unbiased, so λ, its
    positive part over ``ρᵀρ``, is noise around 0: over 20 draws its mean is small
    (0.03 here) and every output stays 10x closer to the truth than β̂ (the worst draw of
    40 had λ = 0.26 and 0.066x)."""
    from statmc.combine import combine_bins
    from statmc.metrics import relmse
    r = ToyRenderer("edges", width=24, height=24)
    mu = r.true_mean()
    lam = {"local": [], "global": []}
    for i in range(20):
        ys, full = _draw_bins(r, 16, 4, (30, i))
        for mix in ("local", "global"):
            out, info = combine_bins(ys, full.mean_var, lambda x: mu.astype(np.float32),
                                     size=7, mix=mix, rng=i, extra_output=True)
            np.testing.assert_array_equal(info["full_denoised"], mu.astype(np.float32))
            lam[mix].append(info["mix"].mean())
            assert relmse(out, mu) < 0.1 * relmse(info["combined"], mu), (i, mix)
    assert max(np.mean(v) for v in lam.values()) < 0.1, lam


def test_combine_bins_mix_keeps_a_combination_that_is_clearly_better():
    """A σ = 3 blur of toy 'edges' at 64 spp: z is far off at the edges, Eq. 14 on the
    bins corrects it (relMSE ~ 60x lower).  The mix must keep β̂ (λ near 1): its output
    within 10 % of β̂ and far below z, and no worse than without the mix by more than
    that."""
    from statmc.combine import combine_bins
    from statmc.metrics import relmse
    r = ToyRenderer("edges", width=32, height=32)
    mu = r.true_mean()
    f = _gauss_blur(3.0)
    for i in range(3):
        ys, full = _draw_bins(r, 64, 4, (31, i))
        out, info = combine_bins(ys, full.mean_var, f, size=7, mix="local", rng=i,
                                 extra_output=True)
        plain = combine_bins(ys, full.mean_var, f, size=7, rng=i)
        assert info["mix"].min() > 0.9
        e, eb, ez = relmse(out, mu), relmse(info["combined"], mu), relmse(info["full_denoised"], mu)
        assert e < 1.1 * eb and e < 1.1 * relmse(plain, mu) and e < 0.05 * ez, (e, eb, ez)


@pytest.mark.parametrize("bin_probes", [0, None])
def test_combine_bins_mix_sure_term_matches_the_true_error_over_bin_draws(bin_probes):
    """The Stein estimate of b = −E[(z − μ) ρ] (ρ = β̂ − z, z = f(ȳ)) that the mix uses:
    over 80 independent draws of B = 4 bins (toy 'edges', 16 spp, a linear blur applied to
    each bin and to ȳ), the image sum of (estimate − truth) has mean zero (t-test); the
    naive (ȳ − z) ρ, and the Stein correction with the per-bin variance B σ² in place of
    the full-sample σ² (Stein over the bins: Σ_b (B σ²) E[∂ρ/∂y_b] with ∂ȳ/∂y_b = 1/B),
    are rejected.  Both with the Jacobian from the probes at ȳ (``bin_probes=0``) and from
    2 probes per bin (the default for a black box such as this callable)."""
    from statmc.combine import combine_bins
    r = ToyRenderer("edges", width=16, height=16)
    mu = r.true_mean()
    f = _gauss_blur(1.5)
    B, d, naive, per_bin = 4, [], [], []
    for i in range(80):
        ys, full = _draw_bins(r, 16, B, (32, i))
        _, info = combine_bins(ys, full.mean_var, f, size=7, probes=4, mix="local", rng=i,
                               bin_probes=bin_probes, extra_output=True)
        z = info["full_denoised"]
        rho = info["combined"] - z
        truth = -(z - mu) * rho
        rr = (full.mean - z) * rho
        d.append((info["gain"] - truth).sum())
        naive.append((rr - truth).sum())
        per_bin.append((rr + B * (info["gain"] - rr) - truth).sum())
    assert stats.ttest_1samp(d, 0.0).pvalue > ALPHA, (np.mean(d), np.std(d))
    assert stats.ttest_1samp(naive, 0.0).pvalue < ALPHA
    assert stats.ttest_1samp(per_bin, 0.0).pvalue < ALPHA


def test_combine_bins_mix_sure_term_is_unbiased_with_heavy_tailed_pixels(monkeypatch):
    """The same check on toy 'mixed' (a quadrant of exponential fireflies: a pixel's mean
    and its sample variance rise together), 24x24, 80 draws, the linear blur with the
    exact Jacobian (``bin_probes=0``): the Stein estimate of b has mean zero.  With the
    tap biases of "estimate" (``δ² − Var δ``, whose ``Var δ`` of the centres near ``c``
    holds the smoothed ``mean_var`` of ``c`` itself, so the weights of ``c`` move with
    ``y_c``'s noise) it was biased low (p = 5e-5; −15 % of b at 32x32), the mix
    conservative; the weights of the mix therefore use ``z_bias="pairs"``."""
    import statmc.combine as cbm
    r = ToyRenderer("mixed", width=24, height=24)
    mu = r.true_mean()
    f = _gauss_blur(1.5)
    draws = [_draw_bins(r, 16, 4, (33, i)) for i in range(80)]
    p = {}
    for mode in ("default", "estimate"):         # the default is "pairs"
        if mode == "estimate":
            monkeypatch.setattr(cbm, "_MIX_Z_BIAS", mode)
        d = []
        for i, (ys, full) in enumerate(draws):
            _, info = cbm.combine_bins(ys, full.mean_var, f, size=7, probes=4, mix="local",
                                       rng=i, bin_probes=0, extra_output=True)
            z = info["full_denoised"]
            d.append((info["gain"] + (z - mu) * (info["combined"] - z)).sum())
        p[mode] = stats.ttest_1samp(d, 0.0).pvalue
    assert p["default"] > ALPHA and p["estimate"] < ALPHA, p


def test_bin_probes_have_one_bins_variance():
    """The per-bin probes of a black box are ``v = ±√(B σ²)`` (σ² = ``mean_var`` of the
    merged render, so ``B σ²`` is one bin's variance of the mean), and ``J_b v`` their
    finite-difference Jacobian products: for ``f(x) = x / 2`` (``J = I / 2``) every
    ``v_c (J_b v)_c`` is ``B σ_c² / 2`` exactly (up to the float32 denoiser copies), the
    term the Stein estimate of the mix divides by ``B``.  (A probe of ``±σ`` would make the
    Stein terms ``B`` times too small, a slip the statistical test of the mix over 80 draws
    of a blur does not see: its Jacobian terms are small next to ``a_c σ²``.)"""
    from statmc.combine import _bin_probe_vectors
    rng = np.random.default_rng(3)
    B, H, W, C = 4, 6, 7, 3
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = 0.5 * ys
    mv = rng.gamma(2.0, 0.01, (H, W, C))
    jac = _bin_probe_vectors(lambda x: 0.5 * x, ys, zs, mv, 3, np.random.default_rng(0), 1e-3)
    assert jac.K == 3 * B and jac.used.all()
    for i in range(jac.K):
        np.testing.assert_allclose(jac.v(i) ** 2, B * mv, rtol=1e-12)
        np.testing.assert_allclose(jac.v(i) * jac.jv[i], 0.5 * B * mv, rtol=2e-3)


def test_combine_bins_mix_in_bands_of_rows_equals_one_piece(monkeypatch):
    """With the mix the weights, Eq. 14 and the SURE terms are formed in bands (margin
    k // 2 + patch): output, λ, β̂ and the SURE terms (kept in bands with ``sure_terms``)
    equal the one-piece ones to the bit;
    a margin one row short changes them.  mix=None stays the output of before (the
    unmixed Eq. 14, not the leave-centre-out β̂ of the mix)."""
    import statmc.combine as cbm
    bins, full, f = _bins_and_kernel(seed=5)
    ys = np.stack([b.mean for b in bins])
    B, H, W, _ = ys.shape
    kw = dict(size=7, patch=2, rng=1, extra_output=True, sure_terms=True)
    whole = {mix: cbm.combine_bins(ys, full.mean_var, f, mix=mix, **kw)
             for mix in ("local", "global")}
    plain = cbm.combine_bins(ys, full.mean_var, f, size=7, patch=2, rng=1)
    assert not np.array_equal(whole["local"][1]["combined"], plain)     # LOO weights
    seen = []
    real = cbm._statistical_weights
    monkeypatch.setattr(cbm, "_statistical_weights",
                        lambda ys, *a, **k: seen.append(ys.shape[1]) or real(ys, *a, **k))
    for rows, mix in ((10, "local"), (13, "global")):
        # the mix holds the bin-summed weights too: one more "bin" of weights per row
        monkeypatch.setattr(cbm, "BAND_BYTES", _band_bytes(rows, W, B + 1, 7, 5))
        out, info = whole[mix]
        seen.clear()
        got, ginfo = cbm._combine_bins(ys, full.mean_var, f, size=7, stencil=5, probes=8,
                                       smooth=2, patch=2, mix=mix, mix_sigma=16.0, rng=1,
                                       whole=False, sure_terms=True)
        assert len(seen) > 2 and max(seen) < H                         # banded
        np.testing.assert_array_equal(got, out)
        for key in ("combined", "mix", "gain", "weighted_gain", "rel", "full_denoised"):
            np.testing.assert_array_equal(ginfo[key], info[key])
        # the banded path without sure_terms (reconstruct_bins) keeps no per-pixel SURE terms
        got2, ginfo2 = cbm._combine_bins(ys, full.mean_var, f, size=7, stencil=5, probes=8,
                                         smooth=2, patch=2, mix=mix, mix_sigma=16.0, rng=1,
                                         whole=False)
        np.testing.assert_array_equal(got2, out)
        assert ginfo2["gain"] is None and ginfo2.get("weighted_gain") is None
    # a black box (the same kernel behind a plain callable): probes at each bin too
    box = lambda x: f(x)                                               # noqa: E731
    kw = dict(size=7, stencil=5, probes=8, smooth=2, patch=2, mix="local", mix_sigma=16.0,
              rng=1)
    monkeypatch.setattr(cbm, "BAND_BYTES", 1 << 40)
    one, oinfo = cbm._combine_bins(ys, full.mean_var, box, whole=True, **kw)
    monkeypatch.setattr(cbm, "BAND_BYTES", _band_bytes(10, W, B + 1, 7, 5))
    seen.clear()
    got, ginfo = cbm._combine_bins(ys, full.mean_var, box, whole=False, sure_terms=True, **kw)
    assert len(seen) > 2 and max(seen) < H
    np.testing.assert_array_equal(got, one)
    np.testing.assert_array_equal(ginfo["gain"], oinfo["gain"])
    assert not np.array_equal(oinfo["gain"], whole["local"][1]["gain"])   # other Stein terms
    monkeypatch.setattr(cbm, "_band_margin", lambda k, patch: k // 2 + patch - 1)
    short = cbm.combine_bins(ys, full.mean_var, f, mix="local", size=7, patch=2, rng=1)
    assert not np.array_equal(short, whole["local"][0])


def test_reconstruct_bins_mix_map_and_bad_mix():
    from statmc.combine import combine_bins
    from statmc.pipeline import reconstruct_bins
    bins, full, f = _bins_and_kernel(seed=6)
    img, maps = reconstruct_bins(bins, "gem+bins", mix="local")
    assert maps["mix"].shape == full.n.shape and 0 <= maps["mix"].min() <= maps["mix"].max() <= 1
    assert set(maps) == {"scale", "sigma", "mix"}
    ys = np.stack([b.mean for b in bins])
    with pytest.raises(InputError, match="`mix`"):
        combine_bins(ys, full.mean_var, f, mix="yes")
    with pytest.raises(InputError, match="`mix_sigma`"):
        combine_bins(ys, full.mean_var, f, mix="local", mix_sigma=0)
    with pytest.raises(InputError, match="`bin_probes`"):
        combine_bins(ys, full.mean_var, f, bin_probes=-1)


def test_combine_bins_probes_each_bin_of_a_black_box_only():
    """GEM's shared kernel has the same Jacobian at every bin: no per-bin probes (B bins +
    probes + 1 calls, as without the mix); a black box gets 2 probes per bin by default
    (B more calls each); mix=None makes none."""
    from statmc.combine import combine_bins
    bins, full, f = _bins_and_kernel(seed=7)
    ys = np.stack([b.mean for b in bins])
    B = len(bins)
    calls = []

    def counted(x):
        calls.append(1)
        return f(x)

    for mix, probes, want in (("local", None, 0), ("local", 3, 3), (None, None, 0)):
        calls.clear()
        combine_bins(ys, full.mean_var, counted, size=5, probes=4, mix=mix, bin_probes=probes,
                     rng=0)
        extra = 2 if (mix is not None and probes is None) else want
        assert len(calls) == B + 4 + 1 + B * extra, (mix, probes, len(calls))
    # GEM's SelectedFilter itself: the default is bin_probes=0
    out0 = combine_bins(ys, full.mean_var, f, size=5, probes=4, rng=0, bin_probes=0)
    np.testing.assert_array_equal(combine_bins(ys, full.mean_var, f, size=5, probes=4, rng=0),
                                  out0)


def test_combine_without_the_mix_is_scale_equivariant():
    """Eq. 8 and the statistical weights are scale-free: without the mix, a render ×2¹⁰
    (variance ×2²⁰, a scale-equivariant denoiser) is combined to 2¹⁰ × the output, by
    ``combine_denoised`` and by ``combine_bins``.  The SURE mix is not: it minimises
    relMSE with the metric's absolute ε = 0.01, so λ, and the output, change with the
    scale (documented in both docstrings)."""
    from statmc import denoisers
    from statmc.combine import combine_bins

    r = ToyRenderer("mixed", width=24, height=20)
    st = r.render_uniform(16, seed=5, features=False)
    ys, full = _draw_bins(r, 16, 4, 6)
    f = denoisers.gaussian(1.5)
    a = 2.0 ** 10
    for fn, y, v in ((combine_denoised, st.mean, st.mean_var), (combine_bins, ys, full.mean_var)):
        for mix in (None, "local"):
            base = fn(y, v, f, size=7, mix=mix, rng=1)
            big = fn(y * a, v * a * a, f, size=7, mix=mix, rng=1)
            if mix is None:
                np.testing.assert_allclose(big / a, base, rtol=1e-9, atol=1e-12)
            else:   # not equivariant: fails the tolerance the unmixed output meets
                assert not np.allclose(big / a, base, rtol=1e-9, atol=1e-12), fn.__name__


def test_combine_denoised_sure_terms_hold_the_pooled_sure_terms():
    """``extra_output=True, sure_terms=True`` of ``combine_denoised`` returns the per-pixel
    Stein estimates ``gain`` of ``b_j = −E[(z − μ) ρ_j]`` and ``weighted_gain`` =
    ``gain / (z² + 0.01)``, the terms the mix pools: the global λ recomputed from them is
    the returned one; ``extra_output`` alone returns the same output, ``z``, ``β̂`` and λ to
    the bit without those keys; without a mix they are None and the output is unchanged."""
    import statmc.combine as cbm
    from statmc import denoisers

    st = ToyRenderer("edges", width=20, height=18).render_uniform(16, seed=4, features=False)
    f = denoisers.gaussian(1.5)
    out, info = combine_denoised(st.mean, st.mean_var, f, size=7, probes=4, mix="global",
                                 rng=3, extra_output=True, sure_terms=True)
    z, betas = info["denoised"], info["combined"]
    assert info["gain"].shape == info["weighted_gain"].shape == betas.shape
    np.testing.assert_array_equal(info["rel"], 1.0 / (z * z + 0.01))
    np.testing.assert_array_equal(info["weighted_gain"], info["gain"] * (1.0 / (z * z + 0.01)))
    short_out, short = combine_denoised(st.mean, st.mean_var, f, size=7, probes=4,
                                        mix="global", rng=3, extra_output=True)
    assert set(short) == {"denoised", "combined", "mix"}
    np.testing.assert_array_equal(short_out, out)
    for key in short:
        np.testing.assert_array_equal(short[key], info[key])
    rho = betas - z[None]
    G = np.einsum("jhwc,khwc,hwc->jk", rho, rho, 1.0 / (z * z + 0.01))
    lam = cbm._simplex_mix(G, info["weighted_gain"].sum(axis=(1, 2, 3)))
    np.testing.assert_allclose(lam, info["mix"], atol=1e-9)
    np.testing.assert_allclose(out, z + np.einsum("jhwc,j->hwc", rho, info["mix"]), atol=1e-12)
    plain, pinfo = combine_denoised(st.mean, st.mean_var, f, size=7, probes=4, mix=None,
                                    rng=3, extra_output=True, sure_terms=True)
    assert pinfo["gain"] is None and pinfo["weighted_gain"] is None and pinfo["rel"] is None
    np.testing.assert_array_equal(plain, combine_denoised(st.mean, st.mean_var, f, size=7,
                                                          probes=4, mix=None, rng=3))


def test_relmse_weights_from_z_bias_the_stein_estimate_with_heavy_tailed_pixels():
    """Session 9 finding behind docs/combine.md "Is the mix of combine_denoised biased?":
    with weights and a blur that do not depend on the data, the Stein estimate of
    ``b = −E[(z − μ) ρ]`` is unbiased (``test_mix_gain_is_unbiased_for_a_linear_denoiser``),
    but the mix pools it weighted by ``1 / (z² + 0.01)``, which moves with ``y_c`` through
    ``z_c``; on toy 'mixed' (exponential fireflies, 200 renders) that weighted estimate is
    biased (t-test rejects), while the same with weights from ``ỹ``, the 5x5 mean of ``y``
    leaving ``c`` out (independent of ``y_c``; the "loo" weights of
    bench/analysis_denoised_mix.py, computed here), is not."""
    from scipy.ndimage import uniform_filter

    from statmc import denoisers
    from statmc.combine import _mix_gain, _mix_rel

    def rel_loo(y):         # 1 / (ỹ² + 0.01), ỹ_c the 5x5 mean of y without c (inside the image)
        num = uniform_filter(y, (5, 5, 1), mode="constant") * 25 - y
        den = uniform_filter(np.ones(y.shape[:2]), 5, mode="constant") * 25 - 1.0
        yl = num / np.maximum(den, 1.0)[..., None]
        return 1.0 / (yl * yl + 0.01)

    H, spp, reps, k = 24, 16, 200, 7
    r = ToyRenderer("mixed", width=H, height=H)
    mu = r.true_mean()
    f = denoisers.gaussian(1.5)
    w = np.ascontiguousarray(gaussian_weights(H, H, 1, k, 2.0))
    d = {"z": [], "loo": []}
    for i in range(reps):
        st = r.render_uniform(spp, seed=(11, i), features=False)
        y, mv = st.mean, st.mean_var
        z, _, _, V, JV = denoiser_moments(f, y, mv, size=1, probes=4, rng=i, extra_output=True)
        beta = combine(y, z, w)
        err = _mix_gain(y, z, beta, mv, w, V, JV) + (z - mu) * (beta - z)
        d["z"].append((err * _mix_rel(y, z, None, mv)).sum())     # the library's weights
        d["loo"].append((err * rel_loo(y)).sum())
    p = {mode: stats.ttest_1samp(v, 0.0).pvalue for mode, v in d.items()}
    assert p["z"] < ALPHA and p["loo"] > ALPHA, (p, {m: np.mean(v) for m, v in d.items()})


def test_combine_denoised_keeps_the_sure_terms_only_when_asked():
    """The per-pixel SURE terms (``gain``, ``weighted_gain``: two ``(J, H, W, C)`` float64
    arrays, 0.2 GB at 1080p) are allocated only with ``sure_terms=True``: with it the
    traced peak memory rises by their size (within 5 %) over ``extra_output`` alone, which
    the CLI path (``reconstruct_stats(..., "oidn+combine" | "combine")``) uses for the mix.
    Before ``sure_terms`` existed, ``extra_output=True`` always allocated them.  One numba
    thread: the parallel kernels' traced temporaries vary by ±0.4 MB with the scheduling
    (measured), one thread makes the peak repeat to within 0.2 kB."""
    import gc

    import numba

    from statmc import denoisers

    H, W = 48, 40
    st = ToyRenderer("edges", width=W, height=H).render_uniform(8, seed=4, features=False)
    f = denoisers.gaussian(1.5)

    def peak(**kw):
        gc.collect()
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            out, top = traced_peak(combine_denoised, st.mean, st.mean_var, f, size=5,
                                   probes=2, stencil=3, rng=1, extra_output=True, **kw)
            return top, out
        finally:
            numba.set_num_threads(threads)

    peak()                                                   # compile the kernels first
    short, (o1, i1) = peak()
    full, (o2, i2) = peak(sure_terms=True)
    terms = 2 * 2 * H * W * 3 * 8                            # J = 2 models ("smooth", "max")
    assert not {"gain", "weighted_gain", "rel"} & set(i1)
    assert i2["gain"].nbytes + i2["weighted_gain"].nbytes == terms
    assert abs((full - short) - terms) < 0.05 * terms, (short, full, terms)
    np.testing.assert_array_equal(o1, o2)


def test_sure_terms_needs_extra_output():
    """``sure_terms`` adds keys to the dict of ``extra_output``: without it, or given a
    non-bool, it is refused up front (the denoiser never runs)."""
    from statmc.combine import combine_bins

    y = np.ones((6, 6, 3))

    def never(x):
        raise AssertionError("the denoiser ran")

    for fn, data in ((combine_denoised, y), (combine_bins, np.stack([y, y]))):
        with pytest.raises(InputError, match="pass extra_output=True"):
            fn(data, np.ones((6, 6, 3)), never, size=3, sure_terms=True)
        with pytest.raises(InputError, match="`sure_terms` must be True or False; got 'yes'"):
            fn(data, np.ones((6, 6, 3)), never, size=3, extra_output=True, sure_terms="yes")


def test_combine_bins_sure_terms_add_the_weighted_gain():
    """``combine_bins``' ``extra_output`` returns ``gain`` as before; ``sure_terms=True``
    adds ``weighted_gain`` = ``gain / (z² + 0.01)`` and ``rel``; the rest, and the output,
    are the same to the bit."""
    from statmc import denoisers
    from statmc.combine import combine_bins
    from statmc.pipeline import merge_bins

    r = ToyRenderer("mixed", width=20, height=18)
    bins = [r.render_uniform(4, seed=(5, b), features=False) for b in range(4)]
    ys = np.stack([b.mean for b in bins])
    mv = merge_bins(bins).mean_var
    f = denoisers.gaussian(1.5)
    o1, i1 = combine_bins(ys, mv, f, size=7, probes=3, rng=2, extra_output=True)
    o2, i2 = combine_bins(ys, mv, f, size=7, probes=3, rng=2, extra_output=True, sure_terms=True)
    assert "gain" in i1 and not {"weighted_gain", "rel"} & set(i1)
    assert set(i2) == set(i1) | {"weighted_gain", "rel"}
    np.testing.assert_array_equal(o1, o2)
    for key in i1:
        np.testing.assert_array_equal(i1[key], i2[key])
    z = i2["full_denoised"]
    np.testing.assert_array_equal(i2["rel"], 1.0 / (z * z + 0.01))
    np.testing.assert_array_equal(i2["weighted_gain"], i2["gain"] * i2["rel"])


def test_reconstruct_stats_combine_reads_the_mix_without_the_sure_terms(monkeypatch):
    """The CLI path (``render --reconstruct oidn+combine``, ``reconstruct --method
    oidn+combine``: ``reconstruct_stats``) asks ``combine_denoised`` for the mix only, so the
    per-pixel SURE terms are never allocated there; its ``"mix"`` map is Σλ."""
    import statmc.combine as cbm
    from statmc.pipeline import reconstruct_stats

    seen = []
    real = cbm.combine_denoised

    def spy(*args, **kw):
        res = real(*args, **kw)
        seen.append((kw, res[1]))
        return res

    monkeypatch.setattr(cbm, "combine_denoised", spy)
    st = ToyRenderer("edges", width=20, height=16).render_uniform(8, seed=2)
    img, maps = reconstruct_stats(st, "combine", denoiser="gaussian", seed=1)
    assert len(seen) == 1
    kw, info = seen[0]
    assert not kw.get("sure_terms", False) and not {"gain", "weighted_gain", "rel"} & set(info)
    np.testing.assert_array_equal(maps["mix"], np.asarray(info["mix"], np.float32).sum(axis=-1))


# --------------------------------------------------------------- properties on any image
from hypothesis import given, settings, strategies as st  # noqa: E402



def _any_weights(seed, h, w, k, wscale, dtype, b=None):
    """Non-negative window weights, a third of the taps exactly 0, the centre > 0."""
    rng = np.random.default_rng(seed + 1)
    lead = (h, w) if b is None else (h, w, b)
    wt = rng.gamma(0.5, 1, size=lead + (k, k)) * (rng.uniform(size=lead + (k, k)) > 0.33)
    wt[..., k // 2, k // 2] += 0.1
    return (wt * wscale).astype(dtype)


_IMAGES = image_args(12, dtype=True)


def _in_range(out, lo, hi, dtype):
    slack = 16 * np.finfo(dtype).eps * np.maximum(np.abs(lo), np.abs(hi))
    return bool((out >= lo - slack).all() and (out <= hi + slack).all())


@settings(max_examples=50, deadline=None)
@given(k=st.sampled_from([1, 3, 5]), wscale=st.sampled_from([1e-20, 1.0, 1e15]),
       zconst=st.sampled_from([0.0, 1.0, -3e7]), **_IMAGES)
def test_combine_with_a_flat_z_is_a_convex_average_of_y_on_any_image(seed, h, w, c, dtype,
                                                                     scale, zero_frac, k,
                                                                     wscale, zconst):
    # With z constant every per-tap estimate e_t = y_t + z_c − z_t of Eq. 8 is y_t, and
    # non-negative weights normalised by W_c make a convex average: each output lies
    # between the channel's smallest and largest y, for Eq. 8 (combine), Eq. 14 with one
    # bin (combine_multi) and Eq. 15 (combine_boosting) alike.
    y, _ = any_image(seed, h, w, c, scale, zero_frac, dtype=dtype)
    z = np.full_like(y, zconst)
    wt = _any_weights(seed, h, w, k, wscale, dtype)
    lo, hi = y.min(axis=(0, 1)), y.max(axis=(0, 1))
    for out in (combine(y, z, wt), combine_multi(y[None], z[None], wt[:, :, None]),
                combine_boosting(y, z, wt)):
        assert out.shape == y.shape and out.dtype == y.dtype
        assert np.isfinite(out).all()
        # Eq. 15 computes z + filter(y − z): its rounding is that of |y − z|
        tol_lo, tol_hi = lo - 16 * np.finfo(dtype).eps * abs(zconst), hi + 16 * np.finfo(dtype).eps * abs(zconst)
        assert _in_range(out, tol_lo, tol_hi, dtype)
        if scale == 0.0 and zconst == 0.0:
            assert not out.any()


@settings(max_examples=40, deadline=None)
@given(k=st.sampled_from([1, 3, 5]), wscale=st.sampled_from([1e-20, 1.0, 1e15]), **_IMAGES)
def test_combine_of_an_image_with_itself_returns_it_on_any_image(seed, h, w, c, dtype, scale,
                                                                zero_frac, k, wscale):
    # z = y makes every e_t = y_t + y_c − y_t = y_c (Eq. 8), so β̂_c = y_c whatever the
    # (normalised, non-negative) weights: up to the rounding of y_t + y_c − y_t.
    y, _ = any_image(seed, h, w, c, scale, zero_frac, dtype=dtype)
    wt = _any_weights(seed, h, w, k, wscale, dtype)
    tol = 16 * np.finfo(dtype).eps * np.abs(y).max(axis=(0, 1))
    for out in (combine(y, y, wt), combine_boosting(y, y, wt)):
        assert out.shape == y.shape and out.dtype == y.dtype
        assert (np.abs(out - y) <= tol).all()


@settings(max_examples=40, deadline=None)
@given(k=st.sampled_from([1, 3]), b=st.integers(1, 3), method=st.sampled_from(["coherent", "diagonal"]),
       z_bias=st.sampled_from(["estimate", "zero", "pairs"]), **_IMAGES)
def test_statistical_weights_are_normalised_and_non_negative_on_any_image(seed, h, w, c, dtype,
                                                                         scale, zero_frac, k,
                                                                         b, method, z_bias):
    # "coherent" minimises over a >= 0 and "diagonal" takes inverse MSEs, then both are
    # normalised over the taps inside the image: finite, >= 0, zero outside the image,
    # summing to 1 per pixel — with zero variances, flat regions and 1-pixel images, and
    # the combination with them a convex average of the per-tap estimates.
    if z_bias == "pairs" and b < 2:
        b = 2
    y, v = any_image(seed, h, w, c, scale, zero_frac, dtype=dtype, bins=b)
    z = np.roll(y, 1, axis=-2) * 0.5 + 0.5 * y                 # a blurred-like z
    wt = statistical_weights(y, z, np.broadcast_to(v, y.shape), v, k, method=method,
                             z_bias=z_bias)
    assert wt.shape == (h, w, b, k, k) and wt.dtype == np.float32
    assert np.isfinite(wt).all() and wt.min() >= 0
    r = k // 2
    inside = np.zeros((h, w, k, k), bool)
    for dy in range(k):
        for dx in range(k):
            inside[max(0, r - dy):h - max(0, dy - r), max(0, r - dx):w - max(0, dx - r), dy, dx] = True
    assert not wt[~np.broadcast_to(inside[:, :, None], wt.shape)].any()
    np.testing.assert_allclose(wt.sum(axis=(2, 3, 4)), 1.0, rtol=1e-5)
    out = combine_multi(y, z, wt)
    assert out.shape == (h, w, c) and np.isfinite(out).all()


@settings(max_examples=40, deadline=None)
@given(k=st.sampled_from([1, 3, 5]), wscale=st.sampled_from([1e-20, 1.0, 1e15]),
       b=st.integers(1, 2), zb=st.sampled_from([0.0, 2.5, -1e10]), yb=st.sampled_from([0.0, 0.5]),
       **_IMAGES)
def test_combine_bias_variance_of_constant_biases_and_non_negative_variance(seed, h, w, c, dtype,
                                                                            scale, zero_frac,
                                                                            k, wscale, b, zb,
                                                                            yb):
    # Eq. 10: a constant z bias cancels in z_c − z_t and a constant y bias is averaged by
    # normalised weights, so bias = y_bias exactly; Eq. 11 with uncorrelated pixels is a
    # sum of w² var terms / W², hence >= 0, and 0 where every variance is 0.
    _, v = any_image(seed, h, w, c, scale, zero_frac, dtype=dtype)
    wt = _any_weights(seed, h, w, k, wscale, dtype, b=b)
    bias, var = combine_bias_variance(wt, v, v, z_bias=np.full_like(v, zb),
                                      y_bias=np.full_like(v, yb))
    assert bias.shape == var.shape == (h, w, c) and bias.dtype == var.dtype == np.float64
    assert np.isfinite(bias).all() and np.isfinite(var).all()
    np.testing.assert_allclose(bias, yb, rtol=1e-12, atol=1e-12 * (1 + abs(zb)))
    assert var.min() >= 0
    if zero_frac == 1.0:
        assert not var.any()


@settings(max_examples=30, deadline=None)
@given(k=st.sampled_from([1, 3]), z_bias=st.sampled_from(["estimate", "zero"]),
       ridge=st.sampled_from([0.0, 1e-9]), **_IMAGES)
def test_full_statistical_weights_are_finite_and_normalised_on_any_image(seed, h, w, c, dtype,
                                                                        scale, zero_frac, k,
                                                                        z_bias, ridge):
    # "full" solves M a ∝ 1 with signs free (ridge-regularised, a singular M falls back to
    # the centre tap): finite, zero outside the image, summing to 1 per pixel, also when
    # every variance is 0 (M is then the bias term alone, or 0).
    y, v = any_image(seed, h, w, c, scale, zero_frac, dtype=dtype)
    z = np.roll(y, 1, axis=1) * 0.5 + 0.5 * y
    wt = statistical_weights(y, z, v, v, k, method="full", z_bias=z_bias, ridge=ridge)
    assert wt.shape == (h, w, 1, k, k) and np.isfinite(wt).all()
    r = k // 2
    for dy in range(k):
        for dx in range(k):
            ys = slice(max(0, r - dy), h - max(0, dy - r))
            xs = slice(max(0, r - dx), w - max(0, dx - r))
            outside = np.ones((h, w), bool)
            outside[ys, xs] = False
            assert not wt[outside, 0, dy, dx].any()
    np.testing.assert_allclose(wt.sum(axis=(2, 3, 4)), 1.0, rtol=1e-4)


def test_full_statistical_weights_with_ridge_0_on_a_singular_system_do_not_raise_linalgerror():
    # Regression (found by property testing): method="full" with ridge=0 (allowed, >= 0)
    # and zero variances gives M = 0 in flat pixels; np.linalg.solve raised a raw
    # LinAlgError("Singular matrix"). Such pixels now take the documented fallback, weight
    # 1/B on each bin's centre tap; pixels with a regular M are solved as before.
    y = np.ones((3, 4, 1))
    v = np.zeros_like(y)
    for zb in ("zero", "estimate"):
        wt = statistical_weights(y, y, v, v, 3, method="full", ridge=0.0, z_bias=zb)
        centre = np.zeros((3, 4, 1, 3, 3), np.float32)
        centre[..., 1, 1] = 1.0
        np.testing.assert_array_equal(wt, centre)
    wt2 = statistical_weights(np.stack([y, y]), np.stack([y, y]), v, v, 3, method="full",
                              ridge=0.0, z_bias="zero")
    assert np.isfinite(wt2).all() and (wt2[..., 1, 1] == np.float32(0.5)).all()
    rng = np.random.default_rng(3)
    y = rng.random((4, 5, 2))
    v = 0.01 + rng.random((4, 5, 2))
    wt3 = statistical_weights(y, y + 0.1, v, v, 3, method="full", ridge=0.0)
    assert np.isfinite(wt3).all() and np.abs(wt3[:, :, 0, 0, 0]).max() > 0   # solved
    np.testing.assert_allclose(wt3.sum(axis=(2, 3, 4)), 1.0, rtol=1e-5)



@settings(max_examples=25, deadline=None)
@given(mix=st.sampled_from(["local", "global", None]), size=st.sampled_from([1, 3]),
       denoiser=st.sampled_from(["gaussian", "gem"]), **_IMAGES)
def test_combined_denoisers_stay_within_the_per_tap_estimates_on_any_image(seed, h, w, c, dtype,
                                                                          scale, zero_frac, mix,
                                                                          size, denoiser):
    # Each β̂ averages the per-tap estimates e_t = y_t + z_c − z_t with normalised weights
    # >= 0, and the mix takes a convex combination of z and the β̂: with z = a filtered y
    # (a Gaussian or GEM, inside y's range) the output is finite and within
    # [min y − span, max y + span] per channel, span = max y − min y, for combine_denoised,
    # combine_bins and combine_bin_images alike.
    y, v = any_image(seed, h, w, c, scale, zero_frac, dtype=np.float64)
    f = denoisers.gaussian(1.0) if denoiser == "gaussian" else denoisers.gem(v)
    lo, hi = y.min(axis=(0, 1)), y.max(axis=(0, 1))
    span = hi - lo
    # the denoiser is called on float32 (the protocol): z carries float32 rounding of y
    slack = 8 * np.finfo(np.float32).eps * np.abs(y).max(axis=(0, 1)) + 1e-300

    def check(out, ref_lo, ref_hi, sp):
        assert out.shape == (h, w, c) and np.isfinite(out).all()
        assert (out >= ref_lo - sp - slack).all() and (out <= ref_hi + sp + slack).all()

    check(combine_denoised(y, v, f, size=size, mix=mix, rng=seed), lo, hi, span)
    ys = np.stack([y, np.roll(y, 1, axis=0)])
    check(combine_bins(ys, 2 * v, f, size=size, mix=mix, rng=seed), lo, hi, span)
    zs = np.stack([f(b) for b in ys])
    check(combine_bin_images(ys, zs, size=size), lo, hi, span)
