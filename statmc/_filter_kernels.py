"""Private numba kernels for the Gaussian filter bank and GEM scale selection.

Only :mod:`statmc.filters` and :mod:`statmc.gem` call these; the public wrappers validate
input, fix dtypes and contiguity and allocate outputs.  Each kernel has a plain NumPy
reference in the calling module that the tests compare against.

Layout: an ``(H, W, C)`` image is seen as ``(H, W*C)`` rows, so both passes of a
separable filter run over contiguous memory and vectorise; the channel count ``C`` is the
stride of the horizontal pass.  Inner loops index views from 0 so that LLVM can prove
indices non-negative (numba's negative-index wraparound otherwise blocks vectorisation).

Parallelism: the kernels that run on several threads are a public Python function that
hands a serial compiled ``_*_rows(t0, t1, ...)`` function to
:func:`statmc._task_threads.run_tasks`, which runs contiguous ranges of rows (tasks) on a
few threads.  As numba parallel loops (``prange``) each cost about 1 s more CPU to compile
on a cold cache, the filter passes about 4 s more per dtype and the greedy rounds and the
spread of samples several seconds each: numba's parallel lowering links the loop body,
with everything it calls, into a function of its own and that into the kernel, optimising
it again at each level.  No kernel here is a parallel loop (the count scan, the spread
and the greedy rounds were the last, until session 16).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._kernel_inputs import writable
from ._task_threads import run_tasks
from ._threads import wait_passively_in_numba

wait_passively_in_numba()

# Output rows per task; the vertical pass walks the task's rows strip by strip
# (_STRIP values wide) so the 2r+1 input rows of a strip stay in cache.
_ROW_BLOCK = 32
_STRIP = 256


@njit(fastmath=True, nogil=True, cache=True)
def _vpass(src, trow, y, k0, k1, w, r, j0, j1):  # pragma: no cover - compiled
    """trow[j0:j1] = Σ_{k=k0..k1} w[k+r] src[y+k, j0:j1].

    With the full window (k0 = −r, k1 = r) the symmetric taps are folded,
    ``w[r+k]·(src[y−k] + src[y+k])``, four pairs per sweep; at the borders four taps per
    sweep.
    """
    n = j1 - j0
    t = trow[j0:j1]
    if k0 == -r and k1 == r:
        c0 = src[y, j0:j1]
        a = w[r]
        for j in range(n):
            t[j] = a * c0[j]
        k = 1
        while k + 3 <= r:
            a0 = w[r + k]
            a1 = w[r + k + 1]
            a2 = w[r + k + 2]
            a3 = w[r + k + 3]
            p0 = src[y + k, j0:j1]
            p1 = src[y + k + 1, j0:j1]
            p2 = src[y + k + 2, j0:j1]
            p3 = src[y + k + 3, j0:j1]
            m0 = src[y - k, j0:j1]
            m1 = src[y - k - 1, j0:j1]
            m2 = src[y - k - 2, j0:j1]
            m3 = src[y - k - 3, j0:j1]
            for j in range(n):
                t[j] += (a0 * (p0[j] + m0[j]) + a1 * (p1[j] + m1[j])
                         + a2 * (p2[j] + m2[j]) + a3 * (p3[j] + m3[j]))
            k += 4
        while k <= r:
            a0 = w[r + k]
            p0 = src[y + k, j0:j1]
            m0 = src[y - k, j0:j1]
            for j in range(n):
                t[j] += a0 * (p0[j] + m0[j])
            k += 1
        return
    for j in range(n):
        t[j] = 0.0
    k = k0
    while k + 3 <= k1:
        a0 = w[k + r]
        a1 = w[k + r + 1]
        a2 = w[k + r + 2]
        a3 = w[k + r + 3]
        s0 = src[y + k, j0:j1]
        s1 = src[y + k + 1, j0:j1]
        s2 = src[y + k + 2, j0:j1]
        s3 = src[y + k + 3, j0:j1]
        for j in range(n):
            t[j] += a0 * s0[j] + a1 * s1[j] + a2 * s2[j] + a3 * s3[j]
        k += 4
    while k <= k1:
        a0 = w[k + r]
        s0 = src[y + k, j0:j1]
        for j in range(n):
            t[j] += a0 * s0[j]
        k += 1


@njit(fastmath=True, nogil=True, cache=True)
def _hpass(trow, acc, w, C, j0, j1):  # pragma: no cover - compiled
    """acc[:n] = Σ_k w[k] trow[j0 + k*C : j1 + k*C] (``trow`` padded by r*C zeros).

    Symmetric taps folded: ``w[r+k]·(trow[.. + (r+k)C] + trow[.. + (r−k)C])``.
    """
    K = w.shape[0]
    r = K // 2
    n = j1 - j0
    c0 = trow[j0 + r * C:j1 + r * C]
    a = w[r]
    for j in range(n):
        acc[j] = a * c0[j]
    k = 1
    while k + 3 <= r:
        a0 = w[r + k]
        a1 = w[r + k + 1]
        a2 = w[r + k + 2]
        a3 = w[r + k + 3]
        o = j0 + (r + k) * C
        q = j0 + (r - k) * C
        p0 = trow[o:o + n]
        p1 = trow[o + C:o + C + n]
        p2 = trow[o + 2 * C:o + 2 * C + n]
        p3 = trow[o + 3 * C:o + 3 * C + n]
        m0 = trow[q:q + n]
        m1 = trow[q - C:q - C + n]
        m2 = trow[q - 2 * C:q - 2 * C + n]
        m3 = trow[q - 3 * C:q - 3 * C + n]
        for j in range(n):
            acc[j] += (a0 * (p0[j] + m0[j]) + a1 * (p1[j] + m1[j])
                       + a2 * (p2[j] + m2[j]) + a3 * (p3[j] + m3[j]))
        k += 4
    while k <= r:
        a0 = w[r + k]
        o = j0 + (r + k) * C
        q = j0 + (r - k) * C
        p0 = trow[o:o + n]
        m0 = trow[q:q + n]
        for j in range(n):
            acc[j] += a0 * (p0[j] + m0[j])
        k += 1


@njit(fastmath=True, nogil=True, cache=True)
def _block(src, C, w, sy, sxr, y0, y1, out, T, acc, add):  # pragma: no cover - compiled
    """Both passes for output rows y0..y1; ``T`` holds the vertically filtered rows.
    With ``add`` the result is added to ``out`` instead of written."""
    H, L = src.shape
    r = w.shape[0] // 2
    pad = r * C
    for j0 in range(0, L, _STRIP):
        j1 = min(L, j0 + _STRIP)
        for y in range(y0, y1):
            _vpass(src, T[y - y0, pad:pad + L], y, max(-r, -y), min(r, H - 1 - y), w, r, j0, j1)
    for y in range(y0, y1):
        s = sy[y]
        trow = T[y - y0]
        orow = out[y]
        for j0 in range(0, L, _STRIP):
            j1 = min(L, j0 + _STRIP)
            _hpass(trow, acc, w, C, j0, j1)
            o = orow[j0:j1]
            f = sxr[j0:j1]
            if add:
                for j in range(j1 - j0):
                    o[j] += acc[j] * (s * f[j])
            else:
                for j in range(j1 - j0):
                    o[j] = acc[j] * (s * f[j])


def sep_filter(x, C, v, Cv, w, sy, sx, out_x, out_v):
    """Separable filter of ``x`` with taps ``w`` and of ``v`` with the squared taps.

    x : (H, W*C) rows; v : (H, W*Cv) rows, or (H, 0) to skip the variance.
    w : (2r+1,) 1-D taps; taps outside the image are dropped (zero padding).
    sy, sx : (H,), (W,) per-output factors; ``1 / (sum of the in-image taps)`` gives the
        border-renormalised filter, ones the plain zero-padded one.
    out_x = Σ_q (sy w)(sx w) x_q ;  out_v = Σ_q (sy w)² (sx w)² v_q — the variance of
        ``out_x`` when the ``x_q`` are uncorrelated with variances ``v_q`` (Eq. 2 of
        Rousselle et al. 2011).

    One job of :func:`sep_filter_many` (the one compiled filter kernel: a kernel of its
    own compiled the filter passes again, 3-4 s per dtype on a cold cache).
    """
    _sep_filter_jobs(x[None], C, v[None], Cv, np.zeros(1, np.int64), w[None], np.array([w.shape[0]]),
                     sy[None], sx[None], out_x[None], out_v[None], False)


def sep_filter_add(x, w, sy, sx, out):
    """``out += Σ_q (sy w)(sx w) x_q`` for one-channel (H, W) ``x`` (see
    :func:`sep_filter`): accumulates several filtered maps without a temporary.
    One job of :func:`sep_filter_many`, adding."""
    none = np.empty((1, x.shape[0], 0), x.dtype)
    _sep_filter_jobs(x[None], 1, none, 1, np.zeros(1, np.int64), w[None], np.array([w.shape[0]]),
                     sy[None], sx[None], out[None], none, True)


@njit(nogil=True, cache=True)
def _padded_rows(n, L, pad, dtype):  # pragma: no cover - compiled
    """(n, L + 2 pad) work rows whose pads are 0; the middle is left for the caller to
    fill (zeroing the whole buffer per block cost as much as a small filter)."""
    T = np.empty((n, L + 2 * pad), dtype)
    for i in range(n):
        for j in range(pad):
            T[i, j] = 0
            T[i, L + pad + j] = 0
    return T


def stop_pair(f0, f1, v0, v1, C, Cv, fk, weight, out):
    """Binary stopping map of one scale pair (Eq. 1 of Rousselle et al. 2011).

    f0, f1 : (H, W*C) fine and coarse filtered values; v0, v1 : (H, W*Cv) their
    variances (``Cv`` = C per channel, or 1 if already summed over channels).
    fk : bias factor (r_c² + r_f²)/(r_c² − r_f²); weight : (H, W) ``ρ·z(γ)`` (§4.3).
    out : (H, W) float32, 1 where ``S = weight·fk·Σ_c (c − f)² + Σ_c (Var c − Var f) > 0``
    (stop at the fine scale), else 0.
    """
    run_tasks(_stop_pair_rows, f0.shape[0], f0, f1, v0, v1, C, Cv, fk, weight, out)


@njit(cache=True, fastmath=True, nogil=True)
def _stop_pair_rows(t0, t1, f0, f1, v0, v1, C, Cv, fk, weight, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`stop_pair`, run by :func:`run_tasks`."""
    for y in range(t0, t1):
        _stop_pair_row(f0[y], f1[y], v0[y], v1[y], weight[y], C, Cv, fk, out[y])


@njit(fastmath=True, nogil=True, cache=True)
def _stop_pair_row(a, b, va, vb, g, C, Cv, fk, o):  # pragma: no cover - compiled
    """One row of :func:`stop_pair`."""
    W = o.shape[0]
    s = np.empty(W, a.dtype)
    if Cv == 1:
        for i in range(W):
            s[i] = vb[i] - va[i]
    elif Cv == 3:
        for i in range(W):
            s[i] = ((vb[3 * i] - va[3 * i]) + (vb[3 * i + 1] - va[3 * i + 1])
                    + (vb[3 * i + 2] - va[3 * i + 2]))
    else:
        for i in range(W):
            s[i] = 0.0
        for i in range(W):
            for c in range(Cv):
                s[i] += vb[i * Cv + c] - va[i * Cv + c]
    if C == 3:  # the common case, unrolled so that LLVM vectorises it
        for i in range(W):
            d0 = b[3 * i] - a[3 * i]
            d1 = b[3 * i + 1] - a[3 * i + 1]
            d2 = b[3 * i + 2] - a[3 * i + 2]
            s[i] += g[i] * fk * (d0 * d0 + d1 * d1 + d2 * d2)
    else:
        for i in range(W):
            acc = s[i] - s[i]
            for c in range(C):
                d = b[i * C + c] - a[i * C + c]
                acc += d * d
            s[i] += g[i] * fk * acc
    for i in range(W):
        o[i] = 1.0 if s[i] > 0.0 else 0.0


def pooled_bias_input(f0, f1, v0, v1, cov, C, Cv, out):
    """Noise-corrected squared difference of one scale pair, summed over channels.

    ``out = Σ_c (f1 − f0)² − max(Σ_c (v0 + v1) − 2 cov, 0)``: the squared difference of
    Eq. 1 of Rousselle et al. 2011 minus its noise part ``Var(f1 − f0) = Var[f1] + Var[f0]
    − 2 Cov(f0, f1)`` (statmc's ``bias="pooled"`` departure; unbiased for the squared
    bias difference).  f0, f1 : (H, W*C) values; v0, v1 : (H, W*Cv) their variances
    (``Cv`` = C per channel or 1 if summed); cov : (H, W) covariance of the two scales of
    the channel-summed variance; out : (H, W).  Accumulates in float64.
    NumPy reference: ``statmc.gem.pooled_selector``.
    """
    run_tasks(_pooled_bias_input_rows, f0.shape[0], f0, f1, v0, v1, cov, C, Cv, out)


@njit(cache=True, fastmath=True, nogil=True)
def _pooled_bias_input_rows(t0, t1, f0, f1, v0, v1, cov, C, Cv, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`pooled_bias_input`, run by :func:`run_tasks`."""
    for y in range(t0, t1):
        _pooled_bias_row(f0[y], f1[y], v0[y], v1[y], cov[y], C, Cv, out[y])


@njit(fastmath=True, nogil=True, cache=True)
def _pooled_bias_row(a, b, va, vb, cv, C, Cv, o):  # pragma: no cover - compiled
    """One row of :func:`pooled_bias_input` (and of its fused form)."""
    W = o.shape[0]
    if C == 3 and Cv == 1:  # the fast path of reconstruct, unrolled so that it vectorises
        for i in range(W):
            d0 = np.float64(b[3 * i]) - np.float64(a[3 * i])
            d1 = np.float64(b[3 * i + 1]) - np.float64(a[3 * i + 1])
            d2 = np.float64(b[3 * i + 2]) - np.float64(a[3 * i + 2])
            vs = np.float64(va[i]) + np.float64(vb[i]) - 2.0 * np.float64(cv[i])
            o[i] = d0 * d0 + d1 * d1 + d2 * d2 - max(vs, 0.0)
        return
    for i in range(W):
        d2 = 0.0
        for c in range(C):
            d = np.float64(b[i * C + c]) - np.float64(a[i * C + c])
            d2 += d * d
        vs = 0.0
        for c in range(Cv):
            vs += np.float64(va[i * Cv + c]) + np.float64(vb[i * Cv + c])
        o[i] = d2 - max(vs - 2.0 * np.float64(cv[i]), 0.0)


def stop_pooled(pooled, v0, v1, Cv, fk, weight, out):
    """Binary stopping map from a pooled bias estimate (``bias="pooled"``).

    ``S = weight · fk · max(pooled, 0) + Σ_c (v1 − v0)``, 1 where ``S > 0`` (stop at the
    finer scale): Eq. 1 of Rousselle et al. 2011 with the squared difference replaced by
    the pooled, noise-corrected estimate of :func:`pooled_bias_input` (clamped at 0 after
    pooling).  pooled : (H, W); v0, v1 : (H, W*Cv); out : (H, W) float32.
    NumPy reference: ``statmc.gem.pooled_selector``.
    """
    run_tasks(_stop_pooled_rows, pooled.shape[0], pooled, v0, v1, Cv, fk, weight, out)


@njit(cache=True, fastmath=True, nogil=True)
def _stop_pooled_rows(t0, t1, pooled, v0, v1, Cv, fk, weight, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`stop_pooled`, run by :func:`run_tasks`."""
    for y in range(t0, t1):
        _stop_pooled_row(pooled[y], v0[y], v1[y], Cv, fk, weight, out[y])


@njit(fastmath=True, nogil=True, cache=True)
def _stop_pooled_row(p, va, vb, Cv, fk, weight, o):  # pragma: no cover - compiled
    """One row of :func:`stop_pooled` (and of its fused form)."""
    W = o.shape[0]
    if Cv == 1:  # reconstruct's case, written out so that it vectorises (3x faster)
        for i in range(W):
            s = weight * fk * max(np.float64(p[i]), 0.0)
            s += np.float64(vb[i]) - np.float64(va[i])
            o[i] = 1.0 if s > 0.0 else 0.0
        return
    for i in range(W):
        s = weight * fk * max(np.float64(p[i]), 0.0)
        for c in range(Cv):
            s += np.float64(vb[i * Cv + c]) - np.float64(va[i * Cv + c])
        o[i] = 1.0 if s > 0.0 else 0.0


def finish_stop_map(filt, raw, wc, sy, sx, coarser_only, out):
    """Centre-excluded filtered stopping map, rounded (§4.4 and §6 of Rousselle et al. 2011).

    filt : (H, W) the 0/1 map ``raw`` filtered with a border-renormalised Gaussian (centre
    included); ``wc`` the centre tap of its 1-D kernel, ``sy``/``sx`` its renormalisation
    factors, so the centre's normalised 2-D weight is ``w0 = (wc·sy)(wc·sx)``.  Removing it
    gives ``m = (filt − w0·raw)/(1 − w0)``; the result is 1 where ``m >= 1/2`` (ties keep
    the finer scale).  With ``coarser_only`` a 0 stays 0 (final reconstruction, §6).
    """
    run_tasks(_finish_stop_map_rows, filt.shape[0], filt, raw, wc, sy, sx, coarser_only, out)


@njit(cache=True, fastmath=True, nogil=True)
def _finish_stop_map_rows(t0, t1, filt, raw, wc, sy, sx, coarser_only, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`finish_stop_map`, run by :func:`run_tasks`."""
    for y in range(t0, t1):
        _finish_stop_row(filt[y], raw[y], wc, sy[y], sx, coarser_only, out[y])


@njit(fastmath=True, nogil=True, cache=True)
def _finish_stop_row(fr, rr, wc, sy, sx, coarser_only, o):  # pragma: no cover - compiled
    """One row of :func:`finish_stop_map` (and of its fused form); ``sy`` is the row's factor."""
    a = wc * sy
    for i in range(o.shape[0]):
        w0 = a * wc * sx[i]
        b = rr[i]
        den = 1.0 - w0
        if den <= 1e-6:  # no neighbours (1x1 image): keep the raw decision
            m = b
        else:
            m = 1.0 if (fr[i] - w0 * b) >= 0.5 * den else 0.0
        if coarser_only and m > b:
            m = b
        o[i] = m


def first_stop(maps, out):
    """Selected scale = finest scale whose stopping map is 1, the coarsest if none (§4.4)."""
    run_tasks(_first_stop_rows, maps.shape[1], maps, out)


@njit(cache=True, nogil=True)
def _first_stop_rows(t0, t1, maps, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`first_stop`, run by :func:`run_tasks`."""
    Km1, H, W = maps.shape
    for y in range(t0, t1):
        o = out[y]
        for i in range(W):
            o[i] = Km1
        for k in range(Km1 - 1, -1, -1):
            row = maps[k, y]
            for i in range(W):
                if row[i] > 0.5:
                    o[i] = k


def scan_inputs(x, v, C, vsum):
    """One pass over the inputs: count non-finite ``x``, non-finite ``v``, negative ``v``,
    and write ``vsum`` (H, W), the channel sum of ``v`` (H, W*C)."""
    H = x.shape[0]
    counts = np.empty((H, 3), np.int64)          # every row writes its counts
    run_tasks(_scan_inputs_rows, H, x, v, C, vsum, counts)
    tx, tv, tg = (int(t) for t in counts.sum(axis=0))
    return tx, tv, tg


@njit(cache=True, nogil=True)  # no fastmath: it would assume away NaN
def _scan_inputs_rows(t0, t1, x, v, C, vsum, counts):  # pragma: no cover - compiled
    """Rows ``t0 .. t1 − 1`` of :func:`scan_inputs`; ``counts[y]`` gets row y's counts."""
    L = x.shape[1]
    W = L // C
    for y in range(t0, t1):
        xr = x[y]
        vr = v[y]
        o = vsum[y]
        nx = 0
        nv = 0
        ng = 0
        for j in range(L):
            a = xr[j]
            b = vr[j]
            nx += 0 if (a - a) == 0.0 else 1      # inf - inf and nan are nan
            nv += 0 if (b - b) == 0.0 else 1
            ng += 1 if b < 0.0 else 0
        for i in range(W):
            acc = vr[i * C]
            for c in range(1, C):
                acc += vr[i * C + c]
            o[i] = acc
        counts[y, 0] = nx
        counts[y, 1] = nv
        counts[y, 2] = ng


def gather(vals, C, scales, out):
    """``out[y, x, c] = vals[scales[y, x], y, x, c]`` on (K, H, W*C) rows."""
    run_tasks(_gather_rows, vals.shape[1], vals, C, scales, out)


@njit(cache=True, fastmath=True, nogil=True)
def _gather_rows(t0, t1, vals, C, scales, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`gather`, run by :func:`run_tasks`."""
    K, H, Lx = vals.shape
    W = Lx // C
    for y in range(t0, t1):
        s_row = scales[y]
        o = out[y]
        for i in range(W):
            s = s_row[i]
            src = vals[s, y]
            for c in range(C):
                o[i * C + c] = src[i * C + c]


def estimate_mse(vals, vars_, C, frac, scales, out):
    """Estimated MSE of the selected scale per channel (§5 of Rousselle et al. 2011).

    ``Var[s] + Σ_{k<s} frac_k (v_{k+1} − v_k)²``: the variance of the finest scale plus the
    accumulated unweighted ΔMSE estimates of Eq. 1 up to the selected scale ``s`` (the
    variance terms telescope, so only the bias terms accumulate).
    """
    run_tasks(_estimate_mse_rows, vals.shape[1], vals, vars_, C, frac, scales, out)


@njit(cache=True, fastmath=True, nogil=True)
def _estimate_mse_rows(t0, t1, vals, vars_, C, frac, scales, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`estimate_mse`, run by :func:`run_tasks`."""
    K, H, Lx = vals.shape
    W = Lx // C
    for y in range(t0, t1):
        s_row = scales[y]
        o = out[y]
        for i in range(W):
            s = s_row[i]
            for c in range(C):
                j = i * C + c
                acc = vars_[s, y, j]
                for k in range(s):
                    d = vals[k + 1, y, j] - vals[k, y, j]
                    acc += frac[k] * d * d
                o[j] = acc


def relative_gain(image, est, C, eps, n, batch, rel, gain):
    """Relative MSE and the gain of ``batch`` more samples (§5 of Rousselle et al. 2011).

    ``rel = mean_c est_c / (image_c² + eps)``, ``gain = rel · batch / (n + batch)``.
    """
    run_tasks(_relative_gain_rows, image.shape[0], image, est, C, eps, n, batch, rel, gain)


@njit(cache=True, fastmath=True, nogil=True)
def _relative_gain_rows(t0, t1, image, est, C, eps, n, batch, rel, gain):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`relative_gain`, run by :func:`run_tasks`."""
    H, L = image.shape
    W = L // C
    for y in range(t0, t1):
        im = image[y]
        es = est[y]
        nr = n[y]
        rr = rel[y]
        gr = gain[y]
        for i in range(W):
            acc = 0.0
            for c in range(C):
                v = np.float64(im[i * C + c])
                acc += es[i * C + c] / (v * v + eps)
            acc /= C
            rr[i] = acc
            gr[i] = acc * batch / (nr[i] + batch)


def estimate_mse_debiased(vals, vars_, cov, C, frac, scales, fy0, fx0, out):
    """Estimated MSE of the selected scale with noise-corrected bias terms.

    ``Var[s] + max(0, Σ_{k<s} frac_k ((v_{k+1} − v_k)² − Var(v_{k+1} − v_k)))``: each
    squared difference of §5 of Rousselle et al. 2011 has expectation
    ``bias-difference² + Var(difference)``; subtracting the known variance leaves an
    unbiased estimate of the bias part, clamped at 0 after accumulation.  The variance of
    the difference is formed here, ``max(Var_k + Var_{k+1} − 2 Cov_k, 0)`` (as
    :func:`difference_variance`), from the bank variances and the pair covariances
    ``cov``.  If ``fy0`` is non-empty, scale 0 is the pixel filter and its covariance with
    scale 1 is ``(Var_0 · fy0[y]) · fx0[x]`` (``cov`` then starts at pair 1).

    Works on whole rows, pair by pair, adding each pair's term where ``k < s`` (a
    branch-free select that vectorises), in float64.
    """
    run_tasks(_estimate_mse_debiased_rows, vals.shape[1], vals, vars_, cov, C, frac, scales,
              fy0, fx0, out)


@njit(cache=True, fastmath=True, nogil=True)
def _estimate_mse_debiased_rows(t0, t1, vals, vars_, cov, C, frac, scales, fy0, fx0,
                                out):  # pragma: no cover - compiled
    """Rows ``t0 .. t1 − 1`` of :func:`estimate_mse_debiased`, run by :func:`run_tasks`."""
    K, H, Lx = vals.shape
    W = Lx // C
    off = 1 if fy0.shape[0] > 0 else 0
    fxl = np.empty(Lx if off else 0, vals.dtype)
    if off:
        for i in range(W):
            for c in range(C):
                fxl[i * C + c] = fx0[i]
    for y in range(t0, t1):
        s_row = scales[y]
        sl = np.empty(Lx, np.int64)
        for i in range(W):
            for c in range(C):
                sl[i * C + c] = s_row[i]
        acc = np.zeros(Lx)
        for k in range(K - 1):
            a = vals[k, y]
            b = vals[k + 1, y]
            va = vars_[k, y]
            vb = vars_[k + 1, y]
            fk = frac[k]
            if k < off:
                g = fy0[y]
                for j in range(Lx):
                    d = b[j] - a[j]
                    dv = max(va[j] + vb[j] - 2 * ((va[j] * g) * fxl[j]), 0.0)
                    acc[j] += fk * (d * d - dv) if k < sl[j] else 0.0
            else:
                cv = cov[k - off, y]
                for j in range(Lx):
                    d = b[j] - a[j]
                    dv = max(va[j] + vb[j] - 2 * cv[j], 0.0)
                    acc[j] += fk * (d * d - dv) if k < sl[j] else 0.0
        o = out[y]
        for j in range(Lx):
            o[j] = vars_[sl[j], y, j] + max(acc[j], 0.0)


@njit(cache=True, nogil=True)  # no fastmath: it would assume away NaN
def _scan_count_row(nr, o, tally):  # pragma: no cover - compiled
    tally[0] = 0
    tally[1] = 0
    tally[2] = 0
    for i in range(nr.shape[0]):
        a = np.float64(nr[i])
        o[i] = a
        if (a - a) != 0.0:              # inf - inf and nan are nan
            tally[0] += 1
        elif np.floor(a) != a:
            tally[1] += 1
        if a < 2.0:
            tally[2] += 1


def scan_counts(n, out):
    """``out = float64(n)``; returns the numbers of non-finite, non-integer and < 2
    entries (the sample-count checks of ``gem._check_inputs``) in one pass.

    ``n`` reaches the kernel C-contiguous and writable (a read-only, strided or Fortran
    count map is copied, 16 MB at 1080p), so each dtype compiles one variant.  Each row
    writes its own three counts, summed here (integers: the same whatever the chunks)."""
    H = n.shape[0]
    tally = np.empty((H, 3), np.int64)      # every row writes its counts
    run_tasks(_scan_counts, H, writable(n), out, tally)
    bad, frac, low = tally.sum(axis=0).tolist()
    return bad, frac, low


@njit(cache=True, nogil=True)
def _scan_counts(t0, t1, n, out, tally):  # pragma: no cover - compiled
    """Rows ``t0 .. t1 − 1`` of :func:`scan_counts`, run by :func:`run_tasks`."""
    for y in range(t0, t1):
        _scan_count_row(n[y], out[y], tally[y])


def weight_map(n, z, out):
    """``out = z·(1 − 1/n)``: the selector weight ``ρ·z(γ)`` of §4.3 of Rousselle 2011."""
    run_tasks(_weight_map_rows, n.shape[0], n, z, out)


@njit(cache=True, nogil=True)
def _weight_map_rows(t0, t1, n, z, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`weight_map`, run by :func:`run_tasks`."""
    H, W = n.shape
    for y in range(t0, t1):
        nr = n[y]
        o = out[y]
        for i in range(W):
            o[i] = z * (1.0 - 1.0 / nr[i])


# ---------------------------------------------------------------------------------------
# Sampler kernels (gem.sampling_map).  No fastmath where results must equal the NumPy
# reference bit for bit (greedy allocation, integer rounding, variance prior).
# ---------------------------------------------------------------------------------------

def prior_scale(v, nb, C, s2):
    """``s2 = v · n`` (sample variance from the variance of the mean) on (H, W*C) rows."""
    run_tasks(_prior_scale_rows, v.shape[0], v, nb, C, s2)
    return s2


@njit(cache=True, nogil=True)
def _prior_scale_rows(t0, t1, v, nb, C, s2):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`prior_scale`, run by :func:`run_tasks`."""
    H, L = v.shape
    W = L // C
    for y in range(t0, t1):
        vr = v[y]
        nr = nb[y]
        o = s2[y]
        for i in range(W):
            a = nr[i]
            for c in range(C):
                o[i * C + c] = vr[i * C + c] * a


def prior_shrink(s2, pooled, nb, C, k, one, out):
    """``out = ((n − 1) s2 + k pooled) / ((n − 1 + k) n)`` on (H, W*C) rows.

    The posterior-mean sample variance under a pooled scaled-inverse-χ² prior, divided by
    ``n`` (see ``gem._variance_prior``); ``k`` and ``one`` carry the array dtype.
    """
    run_tasks(_prior_shrink_rows, s2.shape[0], s2, pooled, nb, C, k, one, out)


@njit(cache=True, nogil=True)
def _prior_shrink_rows(t0, t1, s2, pooled, nb, C, k, one, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`prior_shrink`, run by :func:`run_tasks`."""
    H, L = s2.shape
    W = L // C
    for y in range(t0, t1):
        sr = s2[y]
        pr = pooled[y]
        nr = nb[y]
        o = out[y]
        for i in range(W):
            a = nr[i]
            nm1 = a - one
            den = (nm1 + k) * a
            for c in range(C):
                j = i * C + c
                o[j] = (nm1 * sr[j] + k * pr[j]) / den


def scale_rows(v, C, fy, fx, out):
    """``out[y, x, c] = v[y, x, c] · fy[y] · fx[x]`` on (H, W*C) rows."""
    run_tasks(_scale_rows_rows, v.shape[0], v, C, fy, fx, out)


@njit(cache=True, fastmath=True, nogil=True)
def _scale_rows_rows(t0, t1, v, C, fy, fx, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`scale_rows`, run by :func:`run_tasks`."""
    H, L = v.shape
    W = L // C
    for y in range(t0, t1):
        vr = v[y]
        o = out[y]
        a = fy[y]
        for i in range(W):
            b = fx[i]
            for c in range(C):
                o[i * C + c] = (vr[i * C + c] * a) * b


def difference_variance(vars_, cov, out):
    """``out[k] = max(vars_[k] + vars_[k+1] − 2 cov[k], 0)`` on (K, H, L) stacks."""
    run_tasks(_difference_variance_rows, cov.shape[1], vars_, cov, out)


@njit(cache=True, fastmath=True, nogil=True)
def _difference_variance_rows(t0, t1, vars_, cov, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`difference_variance`, run by :func:`run_tasks`."""
    Km1, H, L = cov.shape
    for y in range(t0, t1):
        for k in range(Km1):
            a = vars_[k, y]
            b = vars_[k + 1, y]
            cv = cov[k, y]
            o = out[k, y]
            for j in range(L):
                o[j] = max(a[j] + b[j] - 2 * cv[j], 0.0)


def spread_parts(amount, scales, fy, fx, density, parts):
    """Split ``amount`` by selected scale and pre-scale it for the spreading filters.

    ``density = amount`` where scale 0 (the pixel filter) is selected, else 0;
    ``parts[s − 1] = (amount · fy[s − 1, y]) · fx[s − 1, x]`` where scale ``s >= 1`` is
    selected, else 0 (``fy``, ``fx`` the border renormalisation factors of scale ``s``:
    the spread is the adjoint of the renormalised filter).  Returns the amount per scale
    (each row's sums, added row after row).
    """
    Km1, H, W = parts.shape
    tot = np.zeros((H, Km1 + 1))
    run_tasks(_spread_parts_rows, H, amount, scales, fy, fx, density, parts, tot)
    return tot.sum(axis=0)


@njit(cache=True, nogil=True)
def _spread_parts_rows(t0, t1, amount, scales, fy, fx, density, parts, tot):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`spread_parts`, run by :func:`run_tasks`; ``tot[y]``
    the amount per scale of row ``y``."""
    Km1, H, W = parts.shape
    for y in range(t0, t1):
        for k in range(Km1):
            row = parts[k, y]
            for i in range(W):
                row[i] = 0.0
        a = amount[y]
        s = scales[y]
        d = density[y]
        for i in range(W):
            si = s[i]
            ai = a[i]
            tot[y, si] += ai
            if si == 0:
                d[i] = ai
            else:
                d[i] = 0.0
                parts[si - 1, y, i] = (ai * fy[si - 1, y]) * fx[si - 1, i]


_DIGIT = 16                      # radix selection: bits per level
_TOP = np.uint64(64 - _DIGIT)    # shift of the first (most significant) digit


@njit(cache=True, nogil=True)
def _rank_key(keys, hist, q):  # pragma: no cover - compiled
    """Key at 0-based rank ``q`` in descending order, the number of keys above it and
    the number of keys equal to it.

    Radix selection, 16 bits per level from the top: ``hist`` (the counts of the keys'
    first digit, filled by the caller during its own pass) finds the bucket holding rank
    ``q``; only that bucket's keys go on to the next digit.  The keys are the bit
    patterns of non-negative float64 values, whose order as unsigned integers is their
    order as numbers.
    """
    nb = 1 << _DIGIT
    mask = np.uint64(nb - 1)
    cand = keys
    above = 0
    for level in range(4):
        sh = np.uint64(64 - _DIGIT * (level + 1))
        if level > 0:
            hist[:] = 0
            for i in range(cand.size):
                hist[(cand[i] >> sh) & mask] += 1
        b = nb - 1
        acc = 0
        while acc + hist[b] <= q:
            acc += hist[b]
            b -= 1
        q -= acc
        above += acc
        nxt = np.empty(hist[b], np.uint64)
        j = 0
        bb = np.uint64(b)
        for i in range(cand.size):
            if (cand[i] >> sh) & mask == bb:
                nxt[j] = cand[i]
                j += 1
        cand = nxt
        if cand.size <= 64:
            break
    # the key at rank q of the few left (at most 64, or all equal after the last digit):
    # the candidate with fewer than q + 1 keys above it and at least q + 1 at or above it
    # (counted, not sorted: np.sort compiled a quicksort for these few, 2-3 s cold)
    for i in range(cand.size):
        key = cand[i]
        j = 0
        ties = 0
        for c in range(cand.size):
            if cand[c] > key:
                j += 1
            elif cand[c] == key:
                ties += 1
        if j <= q < j + ties:
            return key, above + j, ties
    return cand[0], above, 0            # not reached: 0 <= q < cand.size


@njit(cache=True, nogil=True)
def _gain(r, nn, fb):  # pragma: no cover - compiled
    x = r * fb / (nn + fb)
    return x if x > 0.0 else 0.0        # -0.0 -> 0.0: keys order like the values


@njit(cache=True, nogil=True)
def _start_chunks(c0, c1, step, rel, n, fb, amount, r, nn, g, hists,
                  npos_c):  # pragma: no cover - compiled
    """Chunks ``c0 .. c1 − 1`` of :func:`allocate_rounds`' start, run by :func:`run_tasks`:
    chunk ``p`` (pixels ``p·step .. (p + 1)·step − 1``) copies ``rel`` and ``n`` to ``r``
    and ``nn``, zeroes ``amount``, forms the gains, counts their first radix digit into
    ``hists[p]`` and the pixels that can gain into ``npos_c[p]``."""
    size = rel.size
    keys = g.view(np.uint64)
    for p in range(c0, c1):
        i0 = min(size, p * step)
        i1 = min(size, (p + 1) * step)
        hist = hists[p]
        hist[:] = 0
        npos = 0
        for i in range(i0, i1):
            r[i] = rel[i]
            nn[i] = n[i]
            amount[i] = 0.0
            x = _gain(r[i], nn[i], fb)
            g[i] = x
            npos += x > 0.0
            hist[keys[i] >> _TOP] += 1
        npos_c[p] = npos


@njit(cache=True, nogil=True)
def _assign_chunks(c0, c1, step, base, t, need, cut, extra, fb, amount, r, nn, g, hists,
                   npos_c):  # pragma: no cover - compiled
    """Chunks ``c0 .. c1 − 1`` of one round of :func:`allocate_rounds`, run by
    :func:`run_tasks`.  On the pixels of chunk ``p``: ``base`` each, ``fb`` more above the
    threshold ``t`` and for the ties taken (all of them if ``cut < 0``, else those up to
    index ``cut``, which gets ``extra``); update the gains and count their first digit
    into ``hists[p]``, the pixels that can still gain into ``npos_c[p]``."""
    size = g.size
    keys = g.view(np.uint64)
    for p in range(c0, c1):
        i0 = min(size, p * step)
        i1 = min(size, (p + 1) * step)
        hist = hists[p]
        hist[:] = 0
        npos = 0
        for i in range(i0, i1):
            gi = g[i]
            ai = base
            if gi > t:
                ai += fb
            elif gi == t and need > 0:
                if cut < 0 or i == cut:
                    ai += extra
                elif i < cut:
                    ai += fb
            if ai != 0.0:
                amount[i] += ai
                r[i] *= nn[i] / (nn[i] + ai)
                nn[i] += ai
                gi = _gain(r[i], nn[i], fb)
                g[i] = gi
            npos += gi > 0.0
            hist[keys[i] >> _TOP] += 1
        npos_c[p] = npos


def allocate_rounds(rel, n, budget, batch, rounds, amount, r, nn, g, hists):
    """Greedy allocation of ``budget`` samples in ``rounds`` rounds (§5 of Rousselle 2011).

    Fast version of ``gem._allocate_rounds`` (the NumPy reference) on flat float64
    arrays.  Each round hands out its share: ``full = m // size`` batches to everyone
    when the share exceeds one batch per pixel, then one ``batch`` to each of the ``m``
    pixels of largest gain ``rel·batch/(n + batch)`` and the remainder to the next one;
    equal gains are ranked by pixel index (lower first).  If no pixel can gain, the
    share is spread uniformly.  After a round, a pixel that received ``a`` samples has
    ``rel ← rel·n/(n + a)``, ``n ← n + a``.  ``amount`` (out) gets the total per pixel.

    ``r``, ``nn``, ``g`` (size,) float64 and ``hists`` (P, 2**16) int64 are work space
    (P chunks of pixels).  One pass per round (:func:`_assign_chunks`, the chunks on
    :func:`run_tasks`' threads) assigns the samples, updates the gains and counts the
    first radix digit of the new gains for the next round's selection; between the
    passes :func:`_round_plan` finds the round's threshold (:func:`_rank_key`).  Each
    chunk writes only its own pixels, histogram and count, and the plan adds the
    chunks' integer counts, so the result does not depend on the number of chunks or
    threads.  The rounds loop is Python: as one numba parallel kernel (``prange`` over
    the chunks inside it) the allocation cost about 6 s CPU to compile on a cold cache.
    """
    size = rel.size
    P = hists.shape[0]
    step = (size + P - 1) // P
    fb = float(batch)
    npos_c = np.empty(P, np.int64)      # every chunk writes its count
    run_tasks(_start_chunks, P, step, rel, n, fb, amount, r, nn, g, hists, npos_c)
    keys = g.view(np.uint64)
    for it in range(rounds):
        part = budget // rounds + (1 if it < budget % rounds else 0)
        if part == 0:
            continue
        base, t, need, cut, extra = _round_plan(part, size, batch, fb, npos_c, keys, hists, g)
        run_tasks(_assign_chunks, P, step, base, t, need, cut, extra, fb, amount, r, nn, g,
                  hists, npos_c)


@njit(cache=True, nogil=True)
def _round_plan(part, size, batch, fb, npos_c, keys, hists, g):  # pragma: no cover - compiled
    """What one round of :func:`allocate_rounds` hands out: ``(base, t, need, cut,
    extra)`` for :func:`_assign_chunks`, from the ``part`` samples of the round, the
    chunks' counts of pixels that can gain (``npos_c``) and first-digit histograms.

    Serial, between the chunk passes (inside the former parallel kernel its array sums
    and allocations were parallel loops of their own, each compiled for nothing).
    """
    t = np.inf                      # nobody above: only the base amount
    need = 0
    cut = -1
    extra = fb
    npos = 0
    for p in range(npos_c.shape[0]):
        npos += npos_c[p]
    if npos == 0:                   # nothing to gain anywhere: uniform
        base = part / size
    else:
        m = part // batch
        rem = part - m * batch
        full = m // size
        m -= full * size
        base = float(full * batch)
        if m > 0 or rem > 0:
            q = m if rem > 0 else m - 1            # last rank that gets samples
            hist = np.zeros(hists.shape[1], np.int64)  # not hists.sum(axis=0): the
            for p in range(hists.shape[0]):              # generic axis sum compiled too
                for b in range(hists.shape[1]):
                    hist[b] += hists[p, b]
            tkey = np.empty(1, np.uint64)
            tkey[0], above, ties = _rank_key(keys, hist, q)
            t = tkey.view(np.float64)[0]
            need = q + 1 - above                   # ties at t taken, by index
            if rem > 0:
                extra = float(rem)                 # for the last one taken
            if ties > 1:
                k = 0
                for i in range(size):
                    if g[i] == t:
                        k += 1
                        if k == need:
                            cut = i
                            break
    return base, t, need, cut, extra


@njit(cache=True, nogil=True)
def round_targets(d, total, rest, min_count, counts, cum):  # pragma: no cover - compiled
    """First pass of systematic rounding (``statmc.sampling.counts_from_density``).

    Targets ``t = (d/total)·rest`` (``rest/size`` each if ``total <= 0``); ``counts =
    floor(t) + min_count``, ``cum`` the running sum of the fractional parts.  Returns the
    number of samples still to place, ``rest − Σ floor(t)``.
    """
    size = d.size
    acc = 0.0
    placed = 0
    uni = rest / size
    for i in range(size):
        t = uni if total <= 0 else (d[i] / total) * rest
        b = np.floor(t)
        acc += t - b
        cum[i] = acc
        placed += np.int64(b)
        counts[i] = np.int64(b) + min_count
    return rest - placed


@njit(cache=True, nogil=True)
def place_points(cum, r, u, counts):  # pragma: no cover - compiled
    """Second pass: ``r`` points ``u, u + 1, …`` on the cumulative fractional parts
    scaled to total ``r``; pixel ``i`` gets the points in ``[cum_{i−1}, cum_i)`` (the
    last pixel any beyond the end, from rounding)."""
    size = cum.size
    s = r / cum[size - 1]
    j = 0
    p = u
    for i in range(size):
        c = cum[i] * s
        while j < r and p < c:
            counts[i] += 1
            j += 1
            p = u + j
    counts[size - 1] += r - j


# ---------------------------------------------------------------------------------------
# Fused forms: several calls of one kernel in one parallel region (one run_tasks call).
# The worker threads wait passively (statmc._threads, statmc._task_threads), so every
# parallel region pays for waking them, ~0.1-0.2 ms on the 2-core machine this was
# measured on (with numba's pool); a gem.reconstruct that
# calls the per-scale kernels above scale by scale runs 73 regions.  Each job of a fused
# kernel does exactly what the single kernel does on that job's arrays (the same compiled
# helpers, or the same expressions), so the results are bit for bit the single kernels'.
# NumPy reference of each: the single kernel called job by job (tests/test_threads.py).
# ---------------------------------------------------------------------------------------

def sep_filter_many(x, C, v, Cv, src, taps, ntaps, sy, sx, out_x, out_v):
    """:func:`sep_filter` for K jobs in one region: job k filters ``x[src[k]]`` (and
    ``v[src[k]]``) with the taps ``taps[k, :ntaps[k]]`` and factors ``sy[k]``, ``sx[k]``
    into ``out_x[k]`` (``out_v[k]``).

    x : (S, H, W*C) inputs; v : (S, H, W*Cv), or (S, H, 0) to skip the variance;
    src : (K,) int64; taps : (K, T) padded taps, ntaps : (K,) their odd lengths;
    sy : (K, H); sx : (K, W); out_x : (K, H, W*C); out_v : (K, H, W*Cv) or (K, H, 0).
    """
    _sep_filter_jobs(x, C, v, Cv, src, taps, ntaps, sy, sx, out_x, out_v, False)


def _sep_filter_jobs(x, C, v, Cv, src, taps, ntaps, sy, sx, out_x, out_v, add):
    """:func:`sep_filter_many`; with ``add`` the results are added to ``out_x`` (and
    ``out_v``) instead of written (:func:`sep_filter_add`).  ``add`` is a run-time flag,
    not a literal, so the filter passes are compiled once per dtype, into
    :func:`_filter_tasks` only.

    The tasks (row blocks of every job) run on :func:`run_tasks`' threads, not in a numba
    parallel loop: numba compiles a parallel loop's body as a function of its own and
    links it, with everything it calls, into the kernel, optimising the filter passes
    once per level (about 10 s CPU per dtype on a cold cache, against 5 s for the same
    passes in one serial function).
    """
    K = src.shape[0]
    H = x.shape[1]
    sxx = np.repeat(sx, C, axis=1)          # per value of a row: x's factor, x² for v
    sxv = np.repeat(sx * sx, Cv, axis=1) if v.shape[2] > 0 else np.empty((K, 0), x.dtype)
    nblk = (H + _ROW_BLOCK - 1) // _ROW_BLOCK
    run_tasks(_filter_tasks, K * nblk, x, C, v, Cv, src, taps, ntaps, sy, sxx, sxv, out_x,
              out_v, add)


@njit(cache=True, fastmath=True, nogil=True)
def _filter_tasks(t0, t1, x, C, v, Cv, src, taps, ntaps, sy, sxx, sxv, out_x, out_v,
                  add):  # pragma: no cover - compiled
    """Tasks ``t0 .. t1 − 1`` of :func:`_sep_filter_jobs`: task ``t`` filters row block
    ``t // K`` of job ``t % K`` (jobs round-robin, so that a contiguous range of tasks
    holds each job's share: the coarse scales' long taps cost far more than the fine
    ones').  ``sxx``, ``sxv``: ``sx`` (and ``sx²``) repeated per value of a row."""
    K = src.shape[0]
    H = x.shape[1]
    Lx = x.shape[2]
    Lv = v.shape[2]
    for t in range(t0, t1):
        b = t // K
        k = t - b * K
        w = taps[k, :ntaps[k]].copy()
        r = w.shape[0] // 2
        syk = sy[k].copy()
        y0 = b * _ROW_BLOCK
        y1 = min(H, y0 + _ROW_BLOCK)
        acc = np.empty(_STRIP, x.dtype)
        T = _padded_rows(y1 - y0, Lx, r * C, x.dtype)
        _block(x[src[k]], C, w, syk, sxx[k], y0, y1, out_x[k], T, acc, add)
        if Lv > 0:
            w2 = w * w
            sy2 = syk * syk
            Tv = _padded_rows(y1 - y0, Lv, r * Cv, x.dtype)
            _block(v[src[k]], Cv, w2, sy2, sxv[k], y0, y1, out_v[k], Tv, acc, add)


def pooled_bias_input_many(f, v, cov, C, Cv, out):
    """:func:`pooled_bias_input` of every consecutive pair in one region: job k reads
    ``f[k], f[k+1], v[k], v[k+1], cov[k]`` and writes ``out[k]``.

    f : (K, H, W*C); v : (K, H, W*Cv); cov, out : (K−1, H, W).
    """
    run_tasks(_pooled_bias_input_many_rows, out.shape[0] * out.shape[1], f, v, cov, C, Cv, out)


@njit(cache=True, fastmath=True, nogil=True)
def _pooled_bias_input_many_rows(t0, t1, f, v, cov, C, Cv, out):  # pragma: no cover
    """Tasks ``t0 .. t1 − 1`` of :func:`pooled_bias_input_many`, run by :func:`run_tasks`."""
    H = out.shape[1]
    for t in range(t0, t1):
        k = t // H
        y = t - k * H
        _pooled_bias_row(f[k, y], f[k + 1, y], v[k, y], v[k + 1, y], cov[k, y], C, Cv,
                         out[k, y])


def stop_pooled_many(pooled, v, Cv, fk, weight, out):
    """:func:`stop_pooled` of every consecutive pair in one region: job k reads
    ``pooled[k], v[k], v[k+1]`` with factor ``fk[k]`` and writes ``out[k]``.

    pooled : (K−1, H, W); v : (K, H, W*Cv); fk : (K−1,) float64; out : (K−1, H, W).
    """
    run_tasks(_stop_pooled_many_rows, out.shape[0] * out.shape[1], pooled, v, Cv, fk, weight, out)


@njit(cache=True, fastmath=True, nogil=True)
def _stop_pooled_many_rows(t0, t1, pooled, v, Cv, fk, weight, out):  # pragma: no cover
    """Rows ``t0 .. t1 − 1`` of :func:`stop_pooled_many`, run by :func:`run_tasks`."""
    H = out.shape[1]
    for t in range(t0, t1):
        k = t // H
        y = t - k * H
        _stop_pooled_row(pooled[k, y], v[k, y], v[k + 1, y], Cv, fk[k], weight, out[k, y])


def finish_stop_map_many(filt, raw, wc, sy, sx, coarser_only, out):
    """:func:`finish_stop_map` of K maps in one region: job k uses ``filt[k], raw[k]``,
    centre tap ``wc[k]`` and factors ``sy[k]``, ``sx[k]``, and writes ``out[k]``.

    filt, raw, out : (K, H, W); wc : (K,); sy : (K, H); sx : (K, W).
    """
    run_tasks(_finish_stop_map_many_rows, out.shape[0] * out.shape[1], filt, raw, wc, sy, sx,
              coarser_only, out)


@njit(cache=True, fastmath=True, nogil=True)
def _finish_stop_map_many_rows(t0, t1, filt, raw, wc, sy, sx, coarser_only,
                               out):  # pragma: no cover - compiled
    """Rows ``t0 .. t1 − 1`` of :func:`finish_stop_map_many`, run by :func:`run_tasks`."""
    H = out.shape[1]
    for t in range(t0, t1):
        k = t // H
        y = t - k * H
        _finish_stop_row(filt[k, y], raw[k, y], wc[k], sy[k, y], sx[k], coarser_only,
                         out[k, y])
