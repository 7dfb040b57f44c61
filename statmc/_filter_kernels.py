"""Private numba kernels for the Gaussian filter bank and GEM scale selection.

Only :mod:`statmc.filters` and :mod:`statmc.gem` call these; the public wrappers validate
input, fix dtypes and contiguity and allocate outputs.  Each kernel has a plain NumPy
reference in the calling module that the tests compare against.

Layout: an ``(H, W, C)`` image is seen as ``(H, W*C)`` rows, so both passes of a
separable filter run over contiguous memory and vectorise; the channel count ``C`` is the
stride of the horizontal pass.  Inner loops index views from 0 so that LLVM can prove
indices non-negative (numba's negative-index wraparound otherwise blocks vectorisation).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Output rows per parallel task; the vertical pass walks the task's rows strip by strip
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
def _block(src, C, w, sy, sxr, y0, y1, out, T, acc):  # pragma: no cover - compiled
    """Both passes for output rows y0..y1; ``T`` holds the vertically filtered rows."""
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
            for j in range(j1 - j0):
                o[j] = acc[j] * (s * f[j])


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def sep_filter(x, C, v, Cv, w, sy, sx, out_x, out_v):  # pragma: no cover - compiled
    """Separable filter of ``x`` with taps ``w`` and of ``v`` with the squared taps.

    x : (H, W*C) rows; v : (H, W*Cv) rows, or (H, 0) to skip the variance.
    w : (2r+1,) 1-D taps; taps outside the image are dropped (zero padding).
    sy, sx : (H,), (W,) per-output factors; ``1 / (sum of the in-image taps)`` gives the
        border-renormalised filter, ones the plain zero-padded one.
    out_x = Σ_q (sy w)(sx w) x_q ;  out_v = Σ_q (sy w)² (sx w)² v_q — the variance of
        ``out_x`` when the ``x_q`` are uncorrelated with variances ``v_q`` (Eq. 2 of
        Rousselle et al. 2011).
    """
    H = x.shape[0]
    Lx = x.shape[1]
    Lv = v.shape[1]
    do_var = Lv > 0
    K = w.shape[0]
    r = K // 2
    w2 = w * w
    sy2 = sy * sy
    W = Lx // C
    sxx = np.empty(Lx, x.dtype)
    for i in range(W):
        for c in range(C):
            sxx[i * C + c] = sx[i]
    sxv = np.empty(Lv, x.dtype)
    if do_var:
        for i in range(W):
            for c in range(Cv):
                sxv[i * Cv + c] = sx[i] * sx[i]
    nblk = (H + _ROW_BLOCK - 1) // _ROW_BLOCK
    for b in prange(nblk):
        y0 = b * _ROW_BLOCK
        y1 = min(H, y0 + _ROW_BLOCK)
        acc = np.empty(_STRIP, x.dtype)
        T = np.zeros((y1 - y0, Lx + 2 * r * C), x.dtype)
        _block(x, C, w, sy, sxx, y0, y1, out_x, T, acc)
        if do_var:
            Tv = np.zeros((y1 - y0, Lv + 2 * r * Cv), x.dtype)
            _block(v, Cv, w2, sy2, sxv, y0, y1, out_v, Tv, acc)


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def stop_pair(f0, f1, v0, v1, C, Cv, fk, weight, out):  # pragma: no cover - compiled
    """Binary stopping map of one scale pair (Eq. 1 of Rousselle et al. 2011).

    f0, f1 : (H, W*C) fine and coarse filtered values; v0, v1 : (H, W*Cv) their
    variances (``Cv`` = C per channel, or 1 if already summed over channels).
    fk : bias factor (r_c² + r_f²)/(r_c² − r_f²); weight : (H, W) ``ρ·z(γ)`` (§4.3).
    out : (H, W) float32, 1 where ``S = weight·fk·Σ_c (c − f)² + Σ_c (Var c − Var f) > 0``
    (stop at the fine scale), else 0.
    """
    H, Lx = f0.shape
    W = Lx // C
    for y in prange(H):
        a = f0[y]
        b = f1[y]
        va = v0[y]
        vb = v1[y]
        g = weight[y]
        o = out[y]
        s = np.empty(W, f0.dtype)
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


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def finish_stop_map(filt, raw, wc, sy, sx, coarser_only, out):  # pragma: no cover
    """Centre-excluded filtered stopping map, rounded (§4.4 and §6 of Rousselle et al. 2011).

    filt : (H, W) the 0/1 map ``raw`` filtered with a border-renormalised Gaussian (centre
    included); ``wc`` the centre tap of its 1-D kernel, ``sy``/``sx`` its renormalisation
    factors, so the centre's normalised 2-D weight is ``w0 = (wc·sy)(wc·sx)``.  Removing it
    gives ``m = (filt − w0·raw)/(1 − w0)``; the result is 1 where ``m >= 1/2`` (ties keep
    the finer scale).  With ``coarser_only`` a 0 stays 0 (final reconstruction, §6).
    """
    H, W = filt.shape
    for y in prange(H):
        a = wc * sy[y]
        fr = filt[y]
        rr = raw[y]
        o = out[y]
        for i in range(W):
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


@njit(parallel=True, cache=True, nogil=True)
def first_stop(maps, out):  # pragma: no cover - compiled
    """Selected scale = finest scale whose stopping map is 1, the coarsest if none (§4.4)."""
    Km1, H, W = maps.shape
    for y in prange(H):
        o = out[y]
        for i in range(W):
            o[i] = Km1
        for k in range(Km1 - 1, -1, -1):
            row = maps[k, y]
            for i in range(W):
                if row[i] > 0.5:
                    o[i] = k


@njit(parallel=True, cache=True, nogil=True)  # no fastmath: it would assume away NaN
def scan_inputs(x, v, C, vsum):  # pragma: no cover - compiled
    """One pass over the inputs: count non-finite ``x``, non-finite ``v``, negative ``v``,
    and write ``vsum`` (H, W), the channel sum of ``v`` (H, W*C)."""
    H, L = x.shape
    W = L // C
    bad_x = np.zeros(H, np.int64)
    bad_v = np.zeros(H, np.int64)
    neg_v = np.zeros(H, np.int64)
    for y in prange(H):
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
        bad_x[y] = nx
        bad_v[y] = nv
        neg_v[y] = ng
    return bad_x.sum(), bad_v.sum(), neg_v.sum()


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def gather(vals, C, scales, out):  # pragma: no cover - compiled
    """``out[y, x, c] = vals[scales[y, x], y, x, c]`` on (K, H, W*C) rows."""
    K, H, Lx = vals.shape
    W = Lx // C
    for y in prange(H):
        s_row = scales[y]
        o = out[y]
        for i in range(W):
            s = s_row[i]
            src = vals[s, y]
            for c in range(C):
                o[i * C + c] = src[i * C + c]


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def estimate_mse(vals, vars_, C, frac, scales, out):  # pragma: no cover - compiled
    """Estimated MSE of the selected scale per channel (§5 of Rousselle et al. 2011).

    ``Var[s] + Σ_{k<s} frac_k (v_{k+1} − v_k)²``: the variance of the finest scale plus the
    accumulated unweighted ΔMSE estimates of Eq. 1 up to the selected scale ``s`` (the
    variance terms telescope, so only the bias terms accumulate).
    """
    K, H, Lx = vals.shape
    W = Lx // C
    for y in prange(H):
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


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def relative_gain(image, est, C, eps, n, batch, rel, gain):  # pragma: no cover - compiled
    """Relative MSE and the gain of ``batch`` more samples (§5 of Rousselle et al. 2011).

    ``rel = mean_c est_c / (image_c² + eps)``, ``gain = rel · batch / (n + batch)``.
    """
    H, L = image.shape
    W = L // C
    for y in prange(H):
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


@njit(parallel=True, cache=True, nogil=True)
def split_by_scale(amount, scales, parts):  # pragma: no cover - compiled
    """``parts[s, y, x] = amount[y, x]`` where ``scales[y, x] == s``, else 0."""
    K, H, W = parts.shape
    for y in prange(H):
        for k in range(K):
            row = parts[k, y]
            for i in range(W):
                row[i] = 0.0
        a = amount[y]
        s = scales[y]
        for i in range(W):
            parts[s[i], y, i] = a[i]


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def estimate_mse_debiased(vals, vars_, dvar, C, frac, scales, out):  # pragma: no cover
    """Estimated MSE of the selected scale with noise-corrected bias terms.

    ``Var[s] + max(0, Σ_{k<s} frac_k ((v_{k+1} − v_k)² − Var(v_{k+1} − v_k)))``: each
    squared difference of §5 of Rousselle et al. 2011 has expectation
    ``bias-difference² + Var(difference)``; subtracting the known variance leaves an
    unbiased estimate of the bias part, clamped at 0 after accumulation.
    """
    K, H, Lx = vals.shape
    W = Lx // C
    for y in prange(H):
        s_row = scales[y]
        o = out[y]
        for i in range(W):
            s = s_row[i]
            for c in range(C):
                j = i * C + c
                acc = 0.0
                for k in range(s):
                    d = vals[k + 1, y, j] - vals[k, y, j]
                    acc += frac[k] * (d * d - dvar[k, y, j])
                o[j] = vars_[s, y, j] + max(acc, 0.0)
