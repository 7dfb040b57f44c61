"""Compiled kernels for :mod:`statmc.analytic` (private; never exported).

The callers in ``analytic.py`` validate; here arrays are assumed well-formed.  ``K`` is
``(H, W, k, k)`` with odd ``k`` (float32 or float64, any strides, e.g. a broadcast fixed
kernel); per-pixel inputs are C-contiguous float64, images ``(H, W, C)``, maps ``(H, W)``.
Intermediate images are *planar* ``(C, H, W)`` so a kernel can keep three channels in
scalar registers (3x faster than a per-channel accumulator array).

Convention (shared by every function here and documented in ``docs/analytic.md``)::

    out[y, x, c] = sum_{dy, dx} K[y, x, dy, dx] * img[y + dy - r, x + dx - r, c],  r = k // 2

taps outside the image contribute nothing (zero weight, no renormalisation).

Each numba path has a plain NumPy reference: :func:`evaluate_numpy` beside
:func:`evaluate_numba`, :func:`apply_numpy` beside :func:`apply_numba`; the tests
compare them.
"""

from __future__ import annotations


import numpy as np

from ._kernel_inputs import readonly, readonly_strided
from ._task_threads import run_tasks
from ._threads import serial_below, wait_passively_in_numba
from numba import njit

wait_passively_in_numba()

GROUP = 3  # channels handled per pass of the convolution kernels
# Below this many multiply-adds a parallel region costs more than it saves: waking the
# worker threads took ~40 ms per call on a busy 2-core machine, against ~10 µs serially.
SERIAL_WORK = 1 << 18


def _threads_for(work):
    """Run small problems on the calling thread only (see :func:`statmc._threads.serial_below`)."""
    return serial_below(work, SERIAL_WORK)


# =========================================================================== NumPy reference
def moments_numpy(xt, sb, sm, xg, vg, mvt):
    """Future mean and variance (Eq. 6 with Eq. 19, or Eq. 7 of Salehi 2022), ``(H, W, C)``."""
    n = (sb + sm)[..., None]
    has = n > 0
    safe = np.where(has, n, 1.0)
    s3 = sm[..., None]
    if mvt is None:
        mean = np.where(has, (sb[..., None] * xt + s3 * xg) / safe, xt)
        var = s3 * vg / (safe * safe)
    else:
        mean = np.where(has, xg, xt)
        var = ((sb * sb)[..., None] * mvt + s3 * vg) / (safe * safe)
    return mean, var


def moment_derivs_numpy(xt, sb, sm, xg, vg, mvt):
    """``∂mean/∂s`` and ``∂var/∂s``, ``(H, W, C)``; 0 where ``s_bar + s = 0``."""
    mean, _ = moments_numpy(xt, sb, sm, xg, vg, mvt)
    n = (sb + sm)[..., None]
    has = n > 0
    safe = np.where(has, n, 1.0)
    if mvt is None:
        dm = np.where(has, (xg - mean) / safe, 0.0)
        dv = np.where(has, vg * (sb - sm)[..., None] / safe ** 3, 0.0)
    else:
        dm = np.zeros_like(mean)
        tot = (sb * sb)[..., None] * mvt + sm[..., None] * vg
        dv = np.where(has, vg / safe ** 2 - 2.0 * tot / safe ** 3, 0.0)
    return dm, dv


def _shifts(H, W, k):
    """``(dy, dx, out_y, out_x, src_y, src_x)`` slices for every kernel tap."""
    r = k // 2
    for dy in range(k):
        oy = dy - r
        ys, yd = slice(max(0, -oy), min(H, H - oy)), slice(max(0, oy), min(H, H + oy))
        for dx in range(k):
            ox = dx - r
            xs, xd = slice(max(0, -ox), min(W, W - ox)), slice(max(0, ox), min(W, W + ox))
            yield dy, dx, ys, xs, yd, xd


def evaluate_numpy(K, xt, sb, sm, xg, vg, mvt, rel, eps, want_grad):
    """Reference: ``(loss, grad or None, bias, var)`` of Lemma A.1 (Salehi 2022).

    ``loss = mean w (bias² + var)``, ``w = 1/(x_g² + eps)`` if ``rel`` else 1;
    ``grad_q = Σ_c dm_qc (Kᵀ 2wb/N)_qc + dv_qc ((K²)ᵀ w/N)_qc`` with ``N = H W C``.
    """
    H, W, k, _ = K.shape
    mean, var = moments_numpy(xt, sb, sm, xg, vg, mvt)
    acc_m = np.zeros(mean.shape)
    acc_v = np.zeros(var.shape)
    for dy, dx, ys, xs, yd, xd in _shifts(H, W, k):
        w = K[ys, xs, dy, dx].astype(np.float64)[..., None]
        acc_m[ys, xs] += w * mean[yd, xd]
        acc_v[ys, xs] += (w * w) * var[yd, xd]
    bias = acc_m - xg
    wgt = 1.0 / (xg * xg + eps) if rel else np.ones_like(xg)
    scale = 1.0 / bias.size
    loss = float(np.sum(wgt * (bias * bias + acc_v)) * scale)
    if not want_grad:
        return loss, None, bias, acc_v
    A = 2.0 * scale * wgt * bias
    B = scale * wgt
    acc_a = np.zeros(A.shape)
    acc_b = np.zeros(B.shape)
    for dy, dx, ys, xs, yd, xd in _shifts(H, W, k):
        w = K[ys, xs, dy, dx].astype(np.float64)[..., None]
        acc_a[yd, xd] += w * A[ys, xs]          # scatter p -> q = p + o - r
        acc_b[yd, xd] += (w * w) * B[ys, xs]
    dm, dv = moment_derivs_numpy(xt, sb, sm, xg, vg, mvt)
    return loss, (dm * acc_a + dv * acc_b).sum(axis=-1), bias, acc_v


def column_weights_numpy(K, wv, fq):
    """``a_q = Σ_c fq_qc ((K²)ᵀ wv)_qc`` for ``(H, W, C)`` ``wv`` and ``fq``.

    Reference of :func:`column_weights_numba`.
    """
    H, W, k, _ = K.shape
    acc = np.zeros(wv.shape)
    for dy, dx, ys, xs, yd, xd in _shifts(H, W, k):
        w = K[ys, xs, dy, dx].astype(np.float64)[..., None]
        acc[yd, xd] += (w * w) * wv[ys, xs]
    return (acc * fq).sum(axis=-1)


def apply_numpy(K, img, out):
    """Reference of :func:`apply_numba`: ``out = K * img`` for a stack ``(N, H, W, C)``."""
    _, H, W, _ = img.shape
    acc = np.zeros(img.shape)
    for dy, dx, ys, xs, yd, xd in _shifts(H, W, K.shape[2]):
        acc[:, ys, xs] += K[ys, xs, dy, dx].astype(np.float64)[None, ..., None] * img[:, yd, xd]
    out[...] = acc


# =========================================================================== numba
@njit(cache=True, nogil=True)
def _moments_planar_row(xt, sb, sm, xg, vg, mvt, use_mvt, m, v, y):  # pragma: no cover - compiled
    """One row of :func:`_moments_planar`.

    The kernels here are serial functions over a range of rows, run on several threads by
    :func:`statmc._task_threads.run_tasks`: as numba parallel loops (``prange``) they
    compiled in 5.4 s (``kernel_bias_variance``) and 6.9 s (``optimal_sample_map``) CPU
    on a cold cache, the loop bodies' calls linked and optimised again per level of the
    parallel lowering."""
    H, W, C = xt.shape
    for x in range(W):
        a = sb[y, x]
        b = sm[y, x]
        n = a + b
        for c in range(C):
            if n <= 0.0:
                m[c, y, x] = xt[y, x, c]
                v[c, y, x] = 0.0
            elif use_mvt:
                m[c, y, x] = xg[y, x, c]
                v[c, y, x] = (a * a * mvt[y, x, c] + b * vg[y, x, c]) / (n * n)
            else:
                m[c, y, x] = (a * xt[y, x, c] + b * xg[y, x, c]) / n
                v[c, y, x] = b * vg[y, x, c] / (n * n)


@njit(cache=True, nogil=True)
def _moments_planar(y0, y1, xt, sb, sm, xg, vg, mvt, use_mvt, m, v):  # pragma: no cover - compiled
    """Rows ``y0 .. y1 − 1`` (tasks of :func:`run_tasks`)."""
    for y in range(y0, y1):
        _moments_planar_row(xt, sb, sm, xg, vg, mvt, use_mvt, m, v, y)


@njit(inline="always")
def _weight(g, rel, eps):  # pragma: no cover - compiled
    return 1.0 / (g * g + eps) if rel else 1.0


@njit(cache=True, nogil=True)
def _bias_var_group_row(K, m, v, xg, c0, nc, rel, eps, bias, var, rows, y):  # pragma: no cover
    """A row of :func:`_bias_var_group` (see :func:`_moments_planar_row`)."""
    H, W, k, _ = K.shape
    r = k // 2
    c1 = c0 + min(1, nc - 1)
    c2 = c0 + min(2, nc - 1)
    tot = 0.0
    dy0 = max(0, r - y)
    dy1 = min(k, H - y + r)
    for x in range(W):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        dx0 = max(0, r - x)
        dx1 = min(k, W - x + r)
        for dy in range(dy0, dy1):
            yy = y + dy - r
            for dx in range(dx0, dx1):
                xx = x + dx - r
                w = np.float64(K[y, x, dy, dx])
                w2 = w * w
                a0 += w * m[c0, yy, xx]
                a1 += w * m[c1, yy, xx]
                a2 += w * m[c2, yy, xx]
                b0 += w2 * v[c0, yy, xx]
                b1 += w2 * v[c1, yy, xx]
                b2 += w2 * v[c2, yy, xx]
        e = a0 - xg[y, x, c0]
        bias[c0, y, x] = e
        var[c0, y, x] = b0
        tot += _weight(xg[y, x, c0], rel, eps) * (e * e + b0)
        if nc > 1:
            e = a1 - xg[y, x, c1]
            bias[c1, y, x] = e
            var[c1, y, x] = b1
            tot += _weight(xg[y, x, c1], rel, eps) * (e * e + b1)
        if nc > 2:
            e = a2 - xg[y, x, c2]
            bias[c2, y, x] = e
            var[c2, y, x] = b2
            tot += _weight(xg[y, x, c2], rel, eps) * (e * e + b2)
    rows[y] += tot


@njit(cache=True, nogil=True)
def _bias_var_group(y0, y1, K, m, v, xg, c0, nc, rel, eps, bias, var, rows):  # pragma: no cover
    """Channels ``c0 .. c0+nc-1`` (``nc <= 3``): bias, var and per-row loss sums, rows
    ``y0 .. y1 − 1``."""
    for y in range(y0, y1):
        _bias_var_group_row(K, m, v, xg, c0, nc, rel, eps, bias, var, rows, y)


@njit(cache=True, nogil=True)
def _adjoint_weights_row(bias, xg, rel, eps, scale, wb, wn, y):  # pragma: no cover - compiled
    """A row of :func:`_adjoint_weights` (see :func:`_moments_planar_row`)."""
    C, H, W = bias.shape
    for x in range(W):
        for c in range(C):
            wt = scale * _weight(xg[y, x, c], rel, eps)
            wn[c, y, x] = wt
            wb[c, y, x] = 2.0 * wt * bias[c, y, x]


@njit(cache=True, nogil=True)
def _adjoint_weights(y0, y1, bias, xg, rel, eps, scale, wb, wn):  # pragma: no cover - compiled
    for y in range(y0, y1):
        _adjoint_weights_row(bias, xg, rel, eps, scale, wb, wn, y)


@njit(inline="always")
def _derivs(xt, sb, sm, xg, vg, mvt, use_mvt, y, x, c):  # pragma: no cover - compiled
    a = sb[y, x]
    b = sm[y, x]
    n = a + b
    if n <= 0.0:
        return 0.0, 0.0
    if use_mvt:
        tot = a * a * mvt[y, x, c] + b * vg[y, x, c]
        return 0.0, vg[y, x, c] / (n * n) - 2.0 * tot / (n * n * n)
    mean = (a * xt[y, x, c] + b * xg[y, x, c]) / n
    return (xg[y, x, c] - mean) / n, vg[y, x, c] * (a - b) / (n * n * n)


@njit(cache=True, nogil=True)
def _adjoint_group_row(K, wb, wn, xt, sb, sm, xg, vg, mvt, use_mvt, c0, nc, grad,
                       qy):  # pragma: no cover - compiled
    """A row of :func:`_adjoint_group` (see :func:`_moments_planar_row`)."""
    H, W, k, _ = K.shape
    r = k // 2
    c1 = c0 + min(1, nc - 1)
    c2 = c0 + min(2, nc - 1)
    dy0 = max(0, qy + r - H + 1)
    dy1 = min(k, qy + r + 1)
    for qx in range(W):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        dx0 = max(0, qx + r - W + 1)
        dx1 = min(k, qx + r + 1)
        for dy in range(dy0, dy1):
            py = qy + r - dy
            for dx in range(dx0, dx1):
                px = qx + r - dx
                w = np.float64(K[py, px, dy, dx])
                w2 = w * w
                a0 += w * wb[c0, py, px]
                a1 += w * wb[c1, py, px]
                a2 += w * wb[c2, py, px]
                b0 += w2 * wn[c0, py, px]
                b1 += w2 * wn[c1, py, px]
                b2 += w2 * wn[c2, py, px]
        dm, dv = _derivs(xt, sb, sm, xg, vg, mvt, use_mvt, qy, qx, c0)
        g = dm * a0 + dv * b0
        if nc > 1:
            dm, dv = _derivs(xt, sb, sm, xg, vg, mvt, use_mvt, qy, qx, c1)
            g += dm * a1 + dv * b1
        if nc > 2:
            dm, dv = _derivs(xt, sb, sm, xg, vg, mvt, use_mvt, qy, qx, c2)
            g += dm * a2 + dv * b2
        grad[qy, qx] += g


@njit(cache=True, nogil=True)
def _adjoint_group(y0, y1, K, wb, wn, xt, sb, sm, xg, vg, mvt, use_mvt, c0, nc, grad):  # pragma: no cover
    """``grad[q] += Σ_c dm_qc Σ_o K[p,o] wb[c,p] + dv_qc Σ_o K[p,o]² wn[c,p]``, ``p = q + r − o``,
    rows ``y0 .. y1 − 1`` of ``q``."""
    for qy in range(y0, y1):
        _adjoint_group_row(K, wb, wn, xt, sb, sm, xg, vg, mvt, use_mvt, c0, nc, grad, qy)


@njit(cache=True, nogil=True)
def _column_weights_group_row(K, wv, fq, c0, nc, out, qy):  # pragma: no cover - compiled
    """A row of :func:`_column_weights_group` (see :func:`_moments_planar_row`)."""
    H, W, k, _ = K.shape
    r = k // 2
    c1 = c0 + min(1, nc - 1)
    c2 = c0 + min(2, nc - 1)
    dy0 = max(0, qy + r - H + 1)
    dy1 = min(k, qy + r + 1)
    for qx in range(W):
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        dx0 = max(0, qx + r - W + 1)
        dx1 = min(k, qx + r + 1)
        for dy in range(dy0, dy1):
            py = qy + r - dy
            for dx in range(dx0, dx1):
                px = qx + r - dx
                w = np.float64(K[py, px, dy, dx])
                w2 = w * w
                b0 += w2 * wv[c0, py, px]
                b1 += w2 * wv[c1, py, px]
                b2 += w2 * wv[c2, py, px]
        tot = fq[c0, qy, qx] * b0
        if nc > 1:
            tot += fq[c1, qy, qx] * b1
        if nc > 2:
            tot += fq[c2, qy, qx] * b2
        out[qy, qx] += tot


@njit(cache=True, nogil=True)
def _column_weights_group(y0, y1, K, wv, fq, c0, nc, out):  # pragma: no cover - compiled
    """``out[q] += Σ_{c in group} fq[c,q] Σ_o K[p,o]² wv[c,p]``, ``p = q + r − o``, rows
    ``y0 .. y1 − 1`` of ``q``."""
    for qy in range(y0, y1):
        _column_weights_group_row(K, wv, fq, c0, nc, out, qy)


def _groups(C):
    for c0 in range(0, C, GROUP):
        yield c0, min(GROUP, C - c0)


def evaluate_numba(K, xt, sb, sm, xg, vg, mvt, rel, eps, want_grad):
    """Compiled :func:`evaluate_numpy`: ``(loss, grad or None, bias, var)``.

    ``bias`` and ``var`` are returned as ``(H, W, C)`` views of planar buffers.
    """
    H, W, C = xt.shape
    # one compiled variant per dtype of K: read-only C inputs, K C or a strided view
    K = readonly_strided(K)
    xt, sb, sm, xg, vg = (readonly(a) for a in (xt, sb, sm, xg, vg))
    mvt = None if mvt is None else readonly(mvt)
    with _threads_for(H * W * C * K.shape[2] ** 2):
        return _evaluate_numba(K, xt, sb, sm, xg, vg, mvt, rel, eps, want_grad)


def _evaluate_numba(K, xt, sb, sm, xg, vg, mvt, rel, eps, want_grad):
    H, W, C = xt.shape
    use_mvt = mvt is not None
    mv = mvt if use_mvt else xt
    m = np.empty((C, H, W))
    v = np.empty((C, H, W))
    run_tasks(_moments_planar, H, xt, sb, sm, xg, vg, mv, use_mvt, m, v)
    bias = np.empty((C, H, W))
    var = np.empty((C, H, W))
    rows = np.zeros(H)
    for c0, nc in _groups(C):
        run_tasks(_bias_var_group, H, K, m, v, xg, c0, nc, rel, eps, bias, var, rows)
    scale = 1.0 / (H * W * C)
    loss = float(rows.sum() * scale)
    grad = None
    if want_grad:
        wb, wn = m, v                     # reuse the buffers
        run_tasks(_adjoint_weights, H, bias, xg, rel, eps, scale, wb, wn)
        grad = np.zeros((H, W))
        for c0, nc in _groups(C):
            run_tasks(_adjoint_group, H, K, wb, wn, xt, sb, sm, xg, vg, mv, use_mvt, c0, nc, grad)
    return loss, grad, bias.transpose(1, 2, 0), var.transpose(1, 2, 0)


def column_weights_numba(K, wv, fq):
    """``a_q = Σ_c fq_qc Σ_p K_pq² wv_pc`` (the variance weight of pixel q's samples)."""
    H, W, C = wv.shape
    K = readonly_strided(K)
    planar = readonly(wv.transpose(2, 0, 1))
    fplanar = readonly(fq.transpose(2, 0, 1))
    out = np.zeros((H, W))
    with _threads_for(H * W * C * K.shape[2] ** 2):
        for c0, nc in _groups(C):
            run_tasks(_column_weights_group, H, K, planar, fplanar, c0, nc, out)
    return out


def apply_numba(K, img, out):
    """``out = K * img`` for a stack ``img`` of shape ``(N, H, W, C)``."""
    K, img = readonly_strided(K), readonly(img)
    with _threads_for(img.size * K.shape[2] ** 2):
        run_tasks(_apply, img.shape[0] * img.shape[1], K, img, out)


@njit(cache=True, nogil=True)
def _apply_row(K, img, out, t):  # pragma: no cover - compiled
    """One task of :func:`_apply`, compiled on its own (see :func:`_moments_planar_row`)."""
    N, H, W, C = img.shape
    k = K.shape[2]
    r = k // 2
    n = t // H
    y = t % H
    acc = np.empty(C)
    dy0 = max(0, r - y)
    dy1 = min(k, H - y + r)
    for x in range(W):
        for c in range(C):
            acc[c] = 0.0
        dx0 = max(0, r - x)
        dx1 = min(k, W - x + r)
        for dy in range(dy0, dy1):
            yy = y + dy - r
            for dx in range(dx0, dx1):
                w = np.float64(K[y, x, dy, dx])
                xx = x + dx - r
                for c in range(C):
                    acc[c] += w * img[n, yy, xx, c]
        for c in range(C):
            out[n, y, x, c] = acc[c]


@njit(cache=True, nogil=True)
def _apply(t0, t1, K, img, out):  # pragma: no cover - compiled
    """Tasks ``t0 .. t1 − 1``: task ``t`` is row ``t % H`` of image ``t // H``."""
    for t in range(t0, t1):
        _apply_row(K, img, out, t)

