"""Compiled kernels against plain NumPy references where no other test compares them,
and on the inputs the other comparisons leave out: single-pixel, single-row and
single-column images (every tap a border tap), zero-variance pixels.

An audit of every numba kernel of ``statmc/`` found these with no NumPy comparison:
``_filter_kernels.scan_inputs``, ``relative_gain`` (formula checked only through
``sampling_map`` on one float64 image) and ``_combine_kernels._solve_small`` (checked
only through the weights); the others are compared in the test file of their module
(``test_analytic`` and ``test_progressive`` take the degenerate shapes in their own
parametrisations).

Tolerances: an exact comparison where both sides do the same float operations in the same
order; otherwise a bound from the arithmetic, given at each assertion.
"""

from __future__ import annotations

import numpy as np
import pytest

from statmc import _combine_kernels as ck
from statmc import _filter_kernels as fk
from statmc import _progressive_kernels as pk
from statmc import _stencil_kernels as sk
from statmc import filters as F
from statmc import gem
from statmc.analytic import apply_kernels
from statmc.combine import combine_multi, filter_covariance, statistical_weights

EPS64 = np.finfo(np.float64).eps

# (H, W): single pixel, single row, single column, and a small image with an interior
DEGENERATE = [(1, 1), (1, 9), (8, 1), (6, 7)]


# --------------------------------------------------------------------------- _filter_kernels
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("hw", DEGENERATE)
@pytest.mark.parametrize("C", [1, 3])
def test_scan_inputs_equals_numpy(dtype, hw, C):
    """``scan_inputs`` (the one-pass input check of ``filter_bank``/GEM) counts what NumPy
    counts and its ``vsum`` is the channel sum.  Exact: the counts are integers and the sum
    adds the channels in order, as the reference below does (no fastmath in this kernel)."""
    H, W = hw
    rng = np.random.default_rng(H * 31 + W * 7 + C)
    x = rng.normal(size=(H, W, C)).astype(dtype)
    v = rng.uniform(0, 2, (H, W, C)).astype(dtype)
    v[rng.random((H, W, C)) < 0.3] = 0.0                      # zero-variance entries
    for arr, vals in ((x, (np.nan, np.inf, -np.inf)), (v, (np.nan, np.inf, -1.0, -0.0))):
        idx = rng.integers(0, arr.size, size=min(arr.size, 3))
        arr.ravel()[idx] = np.array(vals[:idx.size], dtype)
    vsum = np.empty((H, W), dtype)
    got = fk.scan_inputs(x.reshape(H, W * C), v.reshape(H, W * C), C, vsum)
    with np.errstate(invalid="ignore"):
        want = (int((~np.isfinite(x)).sum()), int((~np.isfinite(v)).sum()), int((v < 0).sum()))
    assert tuple(int(a) for a in got) == want
    ref = v[..., 0].copy()
    with np.errstate(invalid="ignore", over="ignore"):
        for c in range(1, C):
            ref = ref + v[..., c]
    np.testing.assert_array_equal(vsum, ref)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("hw", DEGENERATE)
@pytest.mark.parametrize("C", [1, 3])
def test_relative_gain_equals_numpy(dtype, hw, C):
    """``relative_gain``: ``rel = mean_c est / (image² + eps)``, ``gain = rel · b / (n + b)``
    (§5 of Rousselle et al. 2011), in float64 from float32 or float64 rows; zero estimated
    MSE and a zero image included.  rtol 8 eps: the same float64 operations, but the kernel
    is compiled with fastmath, which may reorder the channel sum and fuse or replace a
    division by a reciprocal (a few roundings of relative size eps each)."""
    H, W = hw
    rng = np.random.default_rng(H * 13 + W + C)
    img = rng.normal(size=(H, W, C)).astype(dtype)
    est = rng.uniform(0, 1, (H, W, C)).astype(dtype)
    est[rng.random((H, W, C)) < 0.3] = 0.0                    # zero estimated MSE
    img.ravel()[0] = 0.0
    n = rng.integers(1, 50, (H, W)).astype(np.float64)
    eps, batch = 1e-3, 4.0
    rel = np.empty((H, W))
    gain = np.empty((H, W))
    fk.relative_gain(img.reshape(H, W * C), est.reshape(H, W * C), C, eps, n, batch, rel, gain)
    i64 = img.astype(np.float64)
    ref = (est.astype(np.float64) / (i64 * i64 + eps)).mean(axis=-1)
    np.testing.assert_allclose(rel, ref, rtol=8 * EPS64, atol=0)
    np.testing.assert_allclose(gain, ref * batch / (n + batch), rtol=8 * EPS64, atol=0)


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 9, 3), (8, 1, 3)])
def test_filter_bank_float32_on_degenerate_images(shape):
    """``sep_filter`` in float32 (the float64 degenerate shapes are in ``test_filters``)
    against the dense float64 reference, zero variances included.  Tolerances those of
    ``test_filters.test_bank_float32_matches_reference_and_keeps_dtype``: atol 2e-6 on
    values of size ~1 (float32 sums of normalised weights, ~16 ulp), rtol 1e-5 on the
    variances."""
    rng = np.random.default_rng(sum(shape))
    m = rng.normal(size=shape).astype(np.float32)
    v = rng.uniform(0, 1, size=shape).astype(np.float32)
    v[rng.random(shape[:2]) < 0.3] = 0.0
    vals, vars_ = F.filter_bank(m, v, F.FINAL_SIGMAS)
    assert vals.dtype == vars_.dtype == np.float32
    rv, rvar = F.filter_bank_reference(m, v, F.FINAL_SIGMAS)
    np.testing.assert_allclose(vals, rv, rtol=0, atol=2e-6)
    np.testing.assert_allclose(vars_, rvar, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("hw", DEGENERATE)
def test_greedy_allocation_on_degenerate_images(hw):
    """``allocate_rounds`` (with ``_rank_key``, ``_start_chunks``, ``_assign_chunks``) equals
    ``gem._allocate_rounds`` on single-pixel/row/column maps with zero gains (ties) and
    budgets below, at and far above the pixel count.  Exact: both hand out whole samples
    by the same (gain, index) order."""
    H, W = hw
    rng = np.random.default_rng(H * 5 + W)
    rel = np.where(rng.random((H, W)) < 0.4, 0.0, rng.lognormal(-2, 1, (H, W)))
    n = rng.integers(2, 20, (H, W)).astype(float)
    for budget in (0, 1, H * W, 7 * H * W + 3):
        for batch, rounds in ((1, 1), (3, 4)):
            ref = gem._allocate_rounds(rel, n, budget, batch, rounds)
            got = gem._allocate_rounds_fast(rel, n, budget, batch, rounds)
            np.testing.assert_array_equal(got, ref)
            assert got.sum() == budget


# --------------------------------------------------------------------------- GEM on degenerate images
def _noisy(truth, n, sd, rng):
    x = truth[None] + rng.normal(0.0, sd, (n,) + truth.shape)
    return x.mean(0), x.var(0, ddof=1) / n


@pytest.mark.parametrize("hw", DEGENERATE)
@pytest.mark.parametrize("bias", ["paper", "pooled"])
def test_gem_selection_kernels_on_degenerate_images(hw, bias):
    """The GEM kernels (``sep_filter``, ``stop_pair``/``pooled_bias_input``+``stop_pooled``,
    ``finish_stop_map``, ``first_stop``, ``gather``, ``estimate_mse``) against their NumPy
    references, as ``test_gem.test_selection_kernels_equal_numpy_reference`` does on a
    40x50 image, here on images where every pixel is a border pixel, with a third of the
    pixels at zero variance.  Decisions are compared away from ``S = 0`` (rtol 1e-9 of the
    variance scale: both sides are float64 sums of the same terms in another order);
    the first stop is exact (integer logic on the same maps); the estimated MSE rtol 1e-12
    as in ``test_gem``."""
    H, W = hw
    rng = np.random.default_rng(H * 3 + W)
    truth = np.where(np.arange(W)[None, :, None] < W // 2, 0.2, 0.9) * np.ones((H, W, 3))
    m, mv = _noisy(truth, 6, 0.4, rng)
    mv[rng.random((H, W)) < 0.3] = 0.0
    n = rng.integers(2, 20, (H, W))
    info = gem.select(m, mv, n=n, gamma=0.2, bias=bias)
    if bias == "paper":
        S = gem.selector(info["values"], info["variances"], info["r2"],
                         weight=gem.error_rate_weight(0.2) * (1 - 1 / n))
    else:
        S = gem.pooled_selector(info["values"], info["variances"],
                                gem._difference_variance_reference(mv, info["sigmas"]),
                                info["r2"])
    sure = np.abs(S) > 1e-9 * (np.abs(info["variances"]).sum(-1)[1:] + 1e-300)
    np.testing.assert_array_equal((S > 0)[sure], info["stop_raw"][sure])
    ref = gem._postprocess_reference(info["stop_raw"].astype(np.float32), list(info["sigmas"]),
                                     True, F.DEFAULT_TRUNCATE)
    if sure.all():                                  # post-processing of the same raw maps
        np.testing.assert_array_equal(info["stop"] > 0.5, ref)
    np.testing.assert_array_equal(gem._first_stop_reference(info["stop"]), info["scales"])
    np.testing.assert_allclose(
        info["est_mse"],
        gem._estimate_mse_reference(info["values"], info["variances"], info["r2"], info["scales"]),
        rtol=1e-12, atol=1e-15)
    pick = np.take_along_axis(info["values"], info["scales"][None, :, :, None], 0)[0]
    np.testing.assert_array_equal(info["image"], pick)


@pytest.mark.parametrize("final", [False, True])
def test_stop_map_ties_keep_the_finer_scale(final, monkeypatch):
    """A centre-excluded mean of exactly 1/2 rounds to 1 (keep the finer scale, as
    ``postprocess_stop_maps`` documents) in ``finish_stop_map`` and in its NumPy reference.
    Gaussian taps never give an exact tie, so both get dyadic weights: a 1x3 map with the
    1-D kernel [1/4, 1/2, 1/4] (border-renormalised), whose middle pixel has one neighbour
    at 1 and one at 0, all sums exact in float32.  The middle pixel's raw decision ``b``
    is 0 or 1; with ``final`` a 0 must stay 0 (only switches to the coarser scale)."""
    taps = np.array([0.25, 0.5, 0.25])
    wc = np.float32(0.5)
    sy = np.array([2.0], np.float32)                  # one row: only the centre tap
    sx = np.array([4 / 3, 1.0, 4 / 3], np.float32)    # end columns lose one quarter tap

    def dyadic(n, sigma, truncate):                     # the same weights, densely
        a = np.zeros((n, n))
        for i in range(n):
            for d, t in zip((-1, 0, 1), taps):
                if 0 <= i + d < n:
                    a[i, i + d] = t
        return a / a.sum(1, keepdims=True)

    monkeypatch.setattr(gem, "_weight_matrix", dyadic)
    for b in (0.0, 1.0):
        raw = np.array([[1.0, b, 0.0]], np.float32)
        filt = (dyadic(1, 0, 0) @ raw @ dyadic(3, 0, 0).T).astype(np.float32)
        out = np.empty_like(raw)
        fk.finish_stop_map(filt, raw, wc, sy, sx, final, out)
        ref = gem._postprocess_reference(raw[None], [1.0, 2.0], final, F.DEFAULT_TRUNCATE)[0]
        want = 0.0 if (final and b == 0.0) else 1.0     # the tie itself gives 1
        assert out[0, 1] == want and ref[0, 1] == want, (b, out, ref)
        # just below the tie gives 0 (towards the coarser scale)
        filt[0, 1] = np.nextafter(filt[0, 1], np.float32(0.0))
        fk.finish_stop_map(filt, raw, wc, sy, sx, final, out)
        assert out[0, 1] == 0.0


@pytest.mark.parametrize("hw", DEGENERATE)
def test_gem_variance_kernels_on_degenerate_images(hw):
    """``difference_variance`` (``scale_rows`` + ``sep_filter`` + ``difference_variance``),
    the variance prior (``prior_scale``, ``prior_shrink``) and the spreading of samples
    (``spread_parts`` + ``sep_filter_add``) against their dense NumPy references on
    single-pixel/row/column images with zero variances.  Tolerances as in ``test_gem``:
    rtol 1e-10 for the separable vs dense filter (sums in another order), exact for the
    prior (same operations in the same order), rtol 1e-12 for the spread."""
    H, W = hw
    rng = np.random.default_rng(H * 11 + W)
    v = rng.uniform(0.0, 2.0, (H, W, 3))
    v[rng.random((H, W)) < 0.3] = 0.0
    sig = F.ADAPTIVE_SIGMAS
    np.testing.assert_allclose(gem.difference_variance(v, sig),
                               gem._difference_variance_reference(v, sig),
                               rtol=1e-10, atol=1e-13)
    nn = rng.integers(2, 30, (H, W)).astype(float)
    np.testing.assert_array_equal(gem._variance_prior(v, nn, 2.0, 1.0),
                                  gem._variance_prior_reference(v, nn, 2.0, 1.0))
    amount = np.where(rng.random((H, W)) < 0.5, rng.integers(1, 9, (H, W)), 0).astype(float)
    scales = rng.integers(0, len(sig), (H, W))
    got = gem._spread(amount, scales, list(sig))
    np.testing.assert_allclose(got, gem._spread_reference(amount, scales, list(sig)),
                               rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- _combine_kernels
def _spd_system(rng, C, big):
    """``G = I + Σ d_i U_i U_iᵀ`` as the weight kernel forms it (``d_i`` in (0, 1],
    ``|U|`` up to ``big``) and a right-hand side ``Σ d_i U_i``."""
    n = 9
    d = rng.uniform(0.01, 1.0, n)
    U = rng.normal(size=(n, C)) * big
    G = np.eye(C) + np.einsum("n,nc,nd->cd", d, U, U)
    return G, (d[:, None] * U).sum(axis=0)


@pytest.mark.parametrize("C", [1, 2, 3, 4, 6])
def test_solve_small_equals_numpy_solve(C):
    """``_solve_small`` (Gaussian elimination with partial pivoting, the ``C x C`` solve of
    the "coherent" weights) against ``np.linalg.solve`` on the systems the kernel forms,
    up to ``|U| ~ 1e3`` (condition numbers to ~1e7).  Both are backward stable, so the
    solutions agree to ``cond(G) · eps`` times a small factor (64, for the order of the
    eliminations); a singular system gives a non-finite solution, the trigger of the
    weights' documented fallback."""
    rng = np.random.default_rng(C)
    for big in (1e-3, 1.0, 30.0, 1e3):
        for _ in range(5):
            G, rhs = _spd_system(rng, C, big)
            sol = np.empty(C)
            ck._solve_small(G.copy(), rhs.copy(), sol)
            ref = np.linalg.solve(G, rhs)
            tol = 64 * np.linalg.cond(G) * EPS64
            np.testing.assert_allclose(sol, ref, rtol=tol, atol=tol * np.abs(ref).max())
    sol = np.empty(C)
    ck._solve_small(np.zeros((C, C)), np.ones(C), sol)
    assert not np.isfinite(sol).all()


@pytest.mark.parametrize("hw", DEGENERATE)
@pytest.mark.parametrize("B", [1, 2])
@pytest.mark.parametrize("zero_var", ["none", "part", "all"])
def test_statistical_weights_kernel_on_degenerate_images(hw, B, zero_var):
    """The compiled weights (``_bias_planes``, ``_weights_band``, ``_solve_small``,
    ``_drop_tap``) against the NumPy path on single-pixel/row/column images, with no, some
    or only zero-variance pixels (then every tap's variance is the relative floor and the
    biases dominate), for both methods, the three bias modes and leave-centre-out.
    rtol 1e-5, atol 1e-7 as ``test_combine``: float32 weights formed from float64 sums in
    another order may land one float32 ulp (6e-8 at 1) apart."""
    H, W = hw
    C, k = 3, 5
    rng = np.random.default_rng(H * 17 + W + B)
    K = rng.random((H, W, 3, 3))
    K /= K.sum(axis=(2, 3), keepdims=True)
    var = rng.gamma(2.0, 0.5, (H, W, C))
    if zero_var == "all":
        var[:] = 0.0
    elif zero_var == "part":
        var[rng.random((H, W)) < 0.5] = 0.0
    ys = rng.gamma(2.0, 0.5, (B, H, W, C))
    zs = np.stack([apply_kernels(K, a) for a in ys])
    cz, cyz = filter_covariance(K, var, cross=True)
    y, z = (ys, zs) if B > 1 else (ys[0], zs[0])
    for method in ("coherent", "diagonal"):
        for bias in ("estimate", "zero", "array"):
            for loo in (False, True):
                zb = rng.normal(size=(H, W, C)) if bias == "array" else bias
                kw = dict(method=method, z_bias=zb, cov_yz=cyz, leave_centre_out=loo)
                fast = statistical_weights(y, z, var, cz, k, **kw)
                ref = statistical_weights(y, z, var, cz, k, _reference=True, **kw)
                assert np.isfinite(fast).all()
                np.testing.assert_allclose(fast.sum(axis=(2, 3, 4)), 1.0, rtol=1e-5)
                np.testing.assert_allclose(fast, ref, rtol=1e-5, atol=1e-7,
                                           err_msg=f"{method} {bias} loo={loo}")


@pytest.mark.parametrize("hw", DEGENERATE)
@pytest.mark.parametrize("k", [1, 3, 7])
def test_combine_kernel_on_degenerate_images(hw, k):
    """Eq. 14 (``_prepare_group``, ``_combine_group``, ``_pixel``) against ``combine_numpy``
    on single-pixel/row/column images, window wider than the image included, 4 channels
    (groups 3 + 1).  rtol 1e-12: float64 sums of at most B k² terms of size ~1 in another
    order (the kernel uses the boosting form Eq. 15 and fused multiply-adds)."""
    H, W = hw
    B, C = 2, 4
    rng = np.random.default_rng(H * 7 + W * 3 + k)
    ys = rng.normal(1.0, 1.0, (B, H, W, C))
    zs = rng.normal(1.0, 0.5, (B, H, W, C))
    w = rng.uniform(0.1, 1.0, (H, W, B, k, k))
    np.testing.assert_allclose(combine_multi(ys, zs, w), ck.combine_numpy(w, ys, zs),
                               rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------- _stencil_kernels
@pytest.mark.parametrize("hw", [(1, 6), (6, 1), (1, 1)])
@pytest.mark.parametrize("R", [0, 2])
def test_neighbour_products_on_single_rows_and_columns(hw, R):
    """``add_neighbour_products_sum`` against its NumPy reference on single rows/columns,
    where most offsets fall outside.  Exact: one multiply and one add per element in the
    same order on both sides (the module's contract)."""
    H, W = hw
    rng = np.random.default_rng(H + 10 * W + R)
    a = rng.normal(size=(3, H, W, 2))
    b = rng.normal(size=(3, H, W, 2))
    use = np.array([True, False, True])
    start = rng.normal(size=(H, W, 2 * R + 1, 2 * R + 1, 2))
    got, ref = start.copy(), start.copy()
    sk.add_neighbour_products_sum(got, a, b, R, use)
    sk.add_neighbour_products_sum_numpy(ref, a, b, R, use)
    np.testing.assert_array_equal(got, ref)


# --------------------------------------------------------------------------- _progressive_kernels
@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 9, 3), (9, 1, 2)])
def test_prepare_kernel_on_degenerate_images(shape):
    """``_prepare`` (``u = α (y − x)``, the variances, the bad-input counts) against NumPy
    on single-pixel/row/column images.  Exact: one subtraction and one multiplication in
    the input precision, as the reference; the variance sum to rtol 1e-12 (another
    order)."""
    rng = np.random.default_rng(sum(shape) + 1)
    x, y, v, a = (rng.standard_normal(shape) for _ in range(4))
    v = np.abs(v)
    v.ravel()[0] = 0.0
    u, vw, bad, vsum = pk.prepare(x, y, v, a, np.float64)
    np.testing.assert_array_equal(u, a * (y - x))
    np.testing.assert_array_equal(vw, v)
    assert list(bad) == [0] * len(bad)
    np.testing.assert_allclose(vsum, v.sum(), rtol=1e-12)


# --------------------------------------------------------------------------- the last parallel loops
def _on_threads(call):
    """``call()`` on 1, 2, ... ``NUMBA_NUM_THREADS`` numba threads (``run_tasks`` splits its
    range into about four chunks per thread), the results of each."""
    import numba
    before = numba.get_num_threads()
    out = []
    try:
        for t in range(1, numba.config.NUMBA_NUM_THREADS + 1):
            numba.set_num_threads(t)
            out.append((t, call()))
    finally:
        numba.set_num_threads(before)
    return out


@pytest.mark.parametrize("hw", DEGENERATE + [(37, 5)])
def test_former_parallel_loops_equal_numpy_on_any_thread_count(hw):
    """The count scan, the spread of samples, the greedy rounds and the gate's input pass
    (``scan_counts``, ``spread_parts``, ``allocate_rounds``, ``_progressive_kernels.prepare``;
    numba parallel loops until session 16, now serial kernels over chunks of rows or pixels
    on ``run_tasks``) against NumPy on every thread count and, for the rounds, 1 to 64
    chunks of pixels.  Exact: each chunk writes its own rows (pixels), and the sums are
    of integers or of multiples of 1/4 far below 2**53, the same in any order."""
    H, W = hw
    rng = np.random.default_rng(7 * H + W)
    # count scan: float64 copy; numbers of non-finite, non-integer, < 2 entries
    n = rng.integers(0, 9, (H, W)).astype(float)
    n.ravel()[:3] = [np.nan, np.inf, 2.5][:n.size]
    fin = np.isfinite(n)
    ref_n = (int((~fin).sum()), int((np.floor(n[fin]) != n[fin]).sum()), int((n < 2).sum()))
    for t, (counts, out) in _on_threads(lambda: (fk.scan_counts(n, o := np.empty(n.shape)), o)):
        assert counts == ref_n, t
        np.testing.assert_array_equal(out, n)
    # spread: pixel-filter amounts, the pre-scaled parts per coarser scale, amount per scale
    K1 = len(F.ADAPTIVE_SIGMAS) - 1
    amount = rng.integers(0, 40, (H, W)) / 4.0
    scales = rng.integers(0, K1 + 1, (H, W))
    fy, fx = rng.uniform(1, 2, (K1, H)), rng.uniform(1, 2, (K1, W))
    ref_d = np.where(scales == 0, amount, 0.0)
    ref_p = np.stack([np.where(scales == s + 1, (amount * fy[s][:, None]) * fx[s][None, :], 0.0)
                      for s in range(K1)])
    ref_t = np.array([amount[scales == s].sum() for s in range(K1 + 1)])

    def spread():
        d, p = np.full((H, W), np.nan), np.full((K1, H, W), np.nan)
        return fk.spread_parts(amount, scales, fy, fx, d, p), d, p

    for t, got in _on_threads(spread):
        for g, r in zip(got, (ref_t, ref_d, ref_p)):
            np.testing.assert_array_equal(g, r, err_msg=f"{t} threads")
    # greedy rounds, with ties and zero gains
    rel = np.where(rng.random((H, W)) < 0.3, 0.0, rng.integers(1, 4, (H, W)) * 0.25)
    nn = rng.integers(2, 20, (H, W)).astype(float)
    for budget, batch, rounds in ((0, 2, 3), (1, 1, 1), (H * W, 3, 4), (9 * H * W + 5, 2, 7)):
        ref = gem._allocate_rounds(rel, nn, budget, batch, rounds)
        for chunks in (1, 2, 5, 64):
            def rounds_():
                out, work = np.empty(H * W), np.empty((3, H * W))
                fk.allocate_rounds(rel.ravel(), nn.ravel(), budget, batch, rounds, out, *work,
                                   np.empty((chunks, 1 << fk._DIGIT), np.int64))
                return out
            for t, got in _on_threads(rounds_):
                np.testing.assert_array_equal(got.reshape(H, W), ref,
                                              err_msg=f"{t} threads, {chunks} chunks")
    # the gate's input pass: u = α(y − x), the bad-input counts, Σ v
    x, y, a = (rng.integers(-8, 8, (H, W, 3)) / 4.0 for _ in range(3))
    v = rng.integers(0, 8, (H, W, 3)) / 4.0
    v.ravel()[0] = -0.25
    x.ravel()[-1] = np.inf
    with np.errstate(invalid="ignore"):
        ref_u = a * (y - x)
    for t, (u, vw, bad, vsum) in _on_threads(lambda: pk.prepare(x, y, v, a, np.float64)):
        np.testing.assert_array_equal(u, ref_u, err_msg=f"{t} threads")
        np.testing.assert_array_equal(vw, v)
        assert list(bad) == [1, 0, 0, 1, 0, 0] and vsum == v.sum(), t
