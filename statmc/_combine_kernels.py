"""Compiled kernels for :mod:`statmc.combine` (private; never exported).

The callers in ``combine.py`` validate; here arrays are assumed well-formed:
weights ``w`` are ``(H, W, B, k, k)`` float32 or float64 with odd ``k`` (any strides, e.g.
a broadcast fixed kernel), buffers ``ys``/``zs`` are ``(B, H, W, C)``.

Window convention (the one of :func:`statmc.analytic.apply_kernels`)::

    tap (dy, dx) of pixel (y, x) reads pixel (y + dy - r, x + dx - r),  r = k // 2

Taps outside the image are dropped, and the normalisation ``W_c`` of Eq. 8/14 of Back et
al. 2020 sums the weights of the taps *inside* the image only, so a border pixel gets
exactly Eq. 14 over its clipped neighbourhood.  Weights of outside taps are never read.

The compiled kernel evaluates Eq. 14 in its boosting form (Eq. 15)::

    out_c = ( sum_b [ s_b * z_{c,b} + sum_t w_{t,b} (y_{t,b} - z_{t,b}) ] ) / sum_b s_b,
    s_b   = sum_t w_{t,b},

with ``d = y - z`` formed once in float64.  The reference :func:`combine_numpy` evaluates
the printed Eq. 14 term by term, so comparing the two also checks Eq. 14 == Eq. 15.

Speed: the kernel is bound by floating-point latency and issue width, not memory, even
for 7.5 GB of 1080p 15x15x4 weights.  Two devices make it ~1.8x faster than the plain
loop (measured on 1920x68 rows, one thread: 0.19 s -> 0.106 s of CPU time):

* four output pixels per iteration, i.e. 16 independent accumulator chains instead of 4
  (the plain loop waits on the 4-cycle latency of each add);
* ``llvm.fmuladd``: an explicit fused multiply-add where the target has one (a plain
  multiply and add otherwise).  It is an IEEE operation with one rounding, not a
  fast-math licence: the kernels keep ``fastmath=False``.
"""

from __future__ import annotations


import numpy as np

from ._kernel_inputs import readonly, readonly_strided
from ._task_threads import run_rows
from ._stencil_kernels import shift_slices as _shift_slices
from ._threads import serial_below, wait_passively_in_numba
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

wait_passively_in_numba()

#: Below this many multiply-adds a parallel region costs more than it saves: waking the
#: worker threads took ~3 ms per call on a busy 2-core machine (a 45x45, B = 2, 5x5
#: combination: 7 ms parallel, 0.1 ms serial); 4 M multiply-adds take ~2 ms serially.
SERIAL_WORK = 1 << 22
GROUP = 3  # channels per kernel pass (kept in scalar registers)


def _threads_for(work):
    """Run small problems on the calling thread only (see :func:`statmc._threads.serial_below`)."""
    return serial_below(work, SERIAL_WORK)


@intrinsic
def _fmuladd(typingctx, a, b, c):
    """``a * b + c`` through ``llvm.fmuladd`` (fused where the CPU has FMA)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        dbl = ir.DoubleType()
        fnty = ir.FunctionType(dbl, [dbl] * 3)
        fn = builder.module.declare_intrinsic("llvm.fmuladd", [dbl], fnty)
        return builder.call(fn, args)

    return sig, codegen


# =========================================================================== NumPy reference
def combine_numpy(w, ys, zs):
    """Reference: Eq. 14 of Back et al. 2020 term by term, ``(H, W, C)`` float64.

    ``num_c = sum_b sum_t w_{t,b} (y_{t,b} + z_{c,b} - z_{t,b})`` and
    ``W_c = sum_b sum_t w_{t,b}`` over the taps inside the image; returns ``num / W``
    (``nan`` where ``W_c = 0``).
    """
    B, H, W, C = ys.shape
    k = w.shape[3]
    r = k // 2
    y64 = ys.astype(np.float64)
    z64 = zs.astype(np.float64)
    num = np.zeros((H, W, C))
    den = np.zeros((H, W))
    for b in range(B):
        for dy in range(k):
            for dx in range(k):
                dst, src = _shift_slices(H, W, dy - r, dx - r)
                wt = w[dst[0], dst[1], b, dy, dx].astype(np.float64)
                est = y64[b][src] + z64[b][dst] - z64[b][src]   # y_t + z_c - z_t
                num[dst] += wt[..., None] * est
                den[dst] += wt
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / den[..., None]


# =========================================================================== numba
@njit(cache=True, fastmath=False, nogil=True, inline="always", error_model="numpy")
def _pixel(w, d, zs, y, x, dy0, dy1, r, k, c0, nc, out):  # pragma: no cover - compiled
    """One output pixel (any position): returns ``W_c``."""
    B = d.shape[0]
    c1 = c0 + min(1, nc - 1)
    c2 = c0 + min(2, nc - 1)
    Wd = d.shape[2]
    dx0 = max(0, r - x)
    dx1 = min(k, Wd - x + r)
    tot = 0.0
    n0 = 0.0
    n1 = 0.0
    n2 = 0.0
    for b in range(B):
        s = 0.0
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for dy in range(dy0, dy1):
            yy = y + dy - r
            for dx in range(dx0, dx1):
                xx = x + dx - r
                wt = np.float64(w[y, x, b, dy, dx])
                s += wt
                a0 = _fmuladd(wt, d[b, yy, xx, 0], a0)
                a1 = _fmuladd(wt, d[b, yy, xx, 1], a1)
                a2 = _fmuladd(wt, d[b, yy, xx, 2], a2)
        tot += s
        n0 += a0 + s * zs[b, y, x, c0]
        n1 += a1 + s * zs[b, y, x, c1]
        n2 += a2 + s * zs[b, y, x, c2]
    out[y, x, c0] = n0 / tot
    if nc > 1:
        out[y, x, c0 + 1] = n1 / tot
    if nc > 2:
        out[y, x, c0 + 2] = n2 / tot
    return tot


@njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _combine_group(w, d, zs, c0, nc, out, bad, ya, yb):  # pragma: no cover - compiled
    """Eq. 14/15 for one group of (up to) three channels ``c0 .. c0 + nc - 1``, rows
    ``ya .. yb - 1`` (:func:`combine_numba` runs chunks of rows on several threads).

    ``d = y - z`` is ``(B, H, W, 3)`` float64 from :func:`_prepare_group`; ``zs`` the
    ``(B, H, W, C)`` correlated buffers (read at the centre pixel only).  Writes those
    channels of ``out``; ``bad[y]`` counts the pixels of row ``y`` whose ``W_c`` is 0 or
    not finite (their output is ``nan``/``inf``).
    """
    B, H, Wd, _ = d.shape
    k = w.shape[3]
    r = k // 2
    acc = np.zeros((4, 3))
    tt = np.zeros(4)
    for y in range(ya, yb):
        c1 = c0 + min(1, nc - 1)   # missing channels of a short group repeat the last one;
        c2 = c0 + min(2, nc - 1)   # their results are never written
        dy0 = max(0, r - y)
        dy1 = min(k, H - y + r)
        nbad = np.int64(0)         # typed, not literal 0 (see _weights_rows)
        x = np.int64(0)
        while x < Wd:
            if x >= r and x + 3 + r < Wd:
                # Four interior pixels x .. x+3 at once: 16 independent accumulator chains.
                acc[:, :] = 0.0
                tt[:] = 0.0
                for b in range(B):
                    s0 = 0.0
                    s1 = 0.0
                    s2 = 0.0
                    s3 = 0.0
                    a0 = 0.0
                    a1 = 0.0
                    a2 = 0.0
                    a3 = 0.0
                    e0 = 0.0
                    e1 = 0.0
                    e2 = 0.0
                    e3 = 0.0
                    g0 = 0.0
                    g1 = 0.0
                    g2 = 0.0
                    g3 = 0.0
                    for dy in range(dy0, dy1):
                        w0 = w[y, x, b, dy]
                        w1 = w[y, x + 1, b, dy]
                        w2 = w[y, x + 2, b, dy]
                        w3 = w[y, x + 3, b, dy]
                        row = d[b, y + dy - r, x - r:]
                        for dx in range(k):
                            v0 = np.float64(w0[dx])
                            v1 = np.float64(w1[dx])
                            v2 = np.float64(w2[dx])
                            v3 = np.float64(w3[dx])
                            s0 += v0
                            s1 += v1
                            s2 += v2
                            s3 += v3
                            a0 = _fmuladd(v0, row[dx, 0], a0)
                            a1 = _fmuladd(v1, row[dx + 1, 0], a1)
                            a2 = _fmuladd(v2, row[dx + 2, 0], a2)
                            a3 = _fmuladd(v3, row[dx + 3, 0], a3)
                            e0 = _fmuladd(v0, row[dx, 1], e0)
                            e1 = _fmuladd(v1, row[dx + 1, 1], e1)
                            e2 = _fmuladd(v2, row[dx + 2, 1], e2)
                            e3 = _fmuladd(v3, row[dx + 3, 1], e3)
                            g0 = _fmuladd(v0, row[dx, 2], g0)
                            g1 = _fmuladd(v1, row[dx + 1, 2], g1)
                            g2 = _fmuladd(v2, row[dx + 2, 2], g2)
                            g3 = _fmuladd(v3, row[dx + 3, 2], g3)
                    tt[0] += s0
                    tt[1] += s1
                    tt[2] += s2
                    tt[3] += s3
                    acc[0, 0] += a0 + s0 * zs[b, y, x, c0]
                    acc[0, 1] += e0 + s0 * zs[b, y, x, c1]
                    acc[0, 2] += g0 + s0 * zs[b, y, x, c2]
                    acc[1, 0] += a1 + s1 * zs[b, y, x + 1, c0]
                    acc[1, 1] += e1 + s1 * zs[b, y, x + 1, c1]
                    acc[1, 2] += g1 + s1 * zs[b, y, x + 1, c2]
                    acc[2, 0] += a2 + s2 * zs[b, y, x + 2, c0]
                    acc[2, 1] += e2 + s2 * zs[b, y, x + 2, c1]
                    acc[2, 2] += g2 + s2 * zs[b, y, x + 2, c2]
                    acc[3, 0] += a3 + s3 * zs[b, y, x + 3, c0]
                    acc[3, 1] += e3 + s3 * zs[b, y, x + 3, c1]
                    acc[3, 2] += g3 + s3 * zs[b, y, x + 3, c2]
                for j in range(4):
                    t = tt[j]
                    if t == 0.0 or not np.isfinite(t):
                        nbad += 1
                    out[y, x + j, c0] = acc[j, 0] / t
                    if nc > 1:
                        out[y, x + j, c0 + 1] = acc[j, 1] / t
                    if nc > 2:
                        out[y, x + j, c0 + 2] = acc[j, 2] / t
                x += 4
            else:
                t = _pixel(w, d, zs, y, x, dy0, dy1, r, k, c0, nc, out)
                if t == 0.0 or not np.isfinite(t):
                    nbad += 1
                x += 1
        bad[y] = nbad


@njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _prepare_group(ys, zs, c0, nc, d, ta, tb):  # pragma: no cover - compiled
    """``d[b, y, x, j] = y - z`` in float64 for channel ``c0 + min(j, nc - 1)``, for the
    rows ``t = b H + y`` in ``ta .. tb - 1``."""
    B, H, W, _ = ys.shape
    for t in range(ta, tb):
        b = t // H
        y = t % H
        for x in range(W):
            for j in range(GROUP):
                c = c0 + min(j, nc - 1)
                d[b, y, x, j] = np.float64(ys[b, y, x, c]) - np.float64(zs[b, y, x, c])


def combine_numba(w, ys, zs, out):
    """Compiled Eq. 14 into ``out`` ``(H, W, C)``; returns the per-row bad-pixel counts.

    A pixel is bad when ``W_c`` is 0 or not finite (a NaN/Inf weight inside the image
    makes it so); its output is then ``nan`` or ``inf``.
    """
    B, H, W, C = ys.shape
    # one compiled variant per dtype: read-only C inputs, weights C or strided views
    w, ys, zs = readonly_strided(w), readonly(ys), readonly(zs)
    bad = np.zeros(H, np.int64)
    d = np.empty((B, H, W, GROUP))
    for c0 in range(0, C, GROUP):
        nc = min(GROUP, C - c0)
        with _threads_for(d.size * 8):      # a subtraction is cheap, threads are not
            run_rows(_prepare_group, 0, B * H, ys, zs, c0, nc, d)
        with _threads_for(d.size * w.shape[3] ** 2):
            run_rows(_combine_group, 0, H, w, d, zs, c0, nc, out, bad)
    return bad


# =========================================================================== statistical weights
# Compiled :func:`statmc.combine.statistical_weights` ("coherent" and "diagonal"): the same
# estimator as the NumPy path in ``combine.py`` (which stays the reference), computed per
# pixel from O(1) stencil look-ups instead of image-sized temporaries per tap, and in bands
# of rows so the per-tap squared-bias planes of ``z_bias="estimate"`` fit in memory at 1080p.
#
# Arrays: ``ys, zs`` (B, H, W, C) float64; ``var_y`` (By, H, W, C) with By in {1, B};
# ``cov_z`` (Bz, H, W, m, m, C); ``cov_yz`` (Bx, H, W, m', m', C) (``has_yz`` False: a dummy);
# ``zb`` (Bb, H, W, C) (bias mode 2 only).  Bias modes: 0 "estimate", 1 "zero", 2 array.
# Methods: 0 "coherent", 1 "diagonal".  Output ``out`` (H, W, B, k, k) float32.

BIAS_ESTIMATE, BIAS_ZERO, BIAS_ARRAY = 0, 1, 2
METHOD_COHERENT, METHOD_DIAGONAL = 0, 1
MAX_ACTIVE_SET_ITER = 20   # the NumPy path's ``max_iter``
BIAS_TILE = 128            # columns per task of :func:`_bias_planes` (inputs stay in L2)


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _im(A, b, y, x, c):  # pragma: no cover - compiled
    """``A[b, y, x, c]`` (shared over bins when ``A.shape[0] == 1``), 0 outside the image."""
    if y < 0 or y >= A.shape[1] or x < 0 or x >= A.shape[2]:
        return 0.0
    return A[b if A.shape[0] > 1 else 0, y, x, c]


@njit(cache=True, fastmath=False, nogil=True)
def _bias_tasks(ys, zs, P, cov_z, cov_yz, has_yz, k, patch, loo, y0, y1, s2, pairs,
                ta, tb):  # pragma: no cover - compiled
    """Tasks ``ta .. tb - 1`` (task ``t``: a tile of columns and a tap) of
    :func:`_bias_planes`.  ``pairs`` is None except with ``z_bias="pairs"``, where ``P``
    is None instead: numba compiles only the branch of the mode it is called for."""
    B, H, W, C = ys.shape
    r = k // 2
    kk = k * k
    Rz = cov_z.shape[3] // 2
    Rx = cov_yz.shape[3] // 2
    q0 = max(0, y0 - patch)
    q1 = min(H, y1 + patch)
    nq = q1 - q0
    pc = patch * C
    for t in range(ta, tb):
        tile = t // kk
        j = t % kk
        oy = j // k - r
        ox = j % k - r
        c0 = tile * BIAS_TILE                 # output columns c0 .. c1 - 1
        c1 = min(W, c0 + BIAS_TILE)
        if oy == 0 and ox == 0:
            s2[j, :, c0:c1] = 0.0
            continue
        e0 = c0 - patch                  # q columns e0 .. e1 - 1 (zero outside the image)
        e1 = c1 + patch
        ne = e1 - e0
        inz = abs(oy) <= Rz and abs(ox) <= Rz
        inx = has_yz and abs(oy) <= Rx and abs(ox) <= Rx
        ya = max(0, -oy)
        yb = min(H, H - oy)
        xa = max(0, -ox, e0)             # valid centres inside the q columns
        xb = min(W, W - ox, e1)
        sh = ox * C
        q = np.empty((nq, ne * C))
        hq = np.empty((nq, (c1 - c0) * C))
        dvr = np.empty(ne * C)
        sr = np.empty(ne * C)            # pairs: Σ_b δ_b of the row
        for yy in range(q0, q1):
            qf = q[yy - q0]
            qf[:] = 0.0
            if yy < ya or yy >= yb or xa >= xb:
                continue
            ty = yy + oy
            lo = xa * C
            hi = xb * C
            qo = -e0 * C                 # q index of image index i is i + qo
            if pairs is not None:        # None unless z_bias="pairs" (then P is None)
                sr[:] = 0.0
                a_s = sr[lo + qo:hi + qo]
                a_q = qf[lo + qo:hi + qo]
                for b in range(B):
                    zc = zs[b, yy].reshape(W * C)
                    zt = zs[b, ty].reshape(W * C)
                    yc = ys[b, yy].reshape(W * C)
                    yt = ys[b, ty].reshape(W * C)
                    a_zc = zc[lo:hi]
                    a_zt = zt[lo + sh:hi + sh]
                    a_yc = yc[lo:hi]
                    a_yt = yt[lo + sh:hi + sh]
                    for i in range(hi - lo):
                        d = (a_zc[i] - a_zt[i]) - (a_yc[i] - a_yt[i])
                        a_s[i] += d
                        a_q[i] += d * d
                fp = np.float64(B) * np.float64(B - 1)
                for i in range(hi - lo):
                    a_q[i] = (a_s[i] * a_s[i] - a_q[i]) / fp
                continue
            if P is None:                # numba drops the branch a None flag rules out
                continue                 # when it compiles (see _bias_planes)
            for b in range(B):
                bp = b if P.shape[0] > 1 else 0
                Pc = P[bp, yy].reshape(W * C)
                Pt = P[bp, ty].reshape(W * C)
                zc = zs[b, yy].reshape(W * C)
                zt = zs[b, ty].reshape(W * C)
                yc = ys[b, yy].reshape(W * C)
                yt = ys[b, ty].reshape(W * C)
                if inz or inx:
                    # stencil rows (a valid dummy view where the offset is beyond it)
                    bz = b if cov_z.shape[0] > 1 else 0
                    bx = b if cov_yz.shape[0] > 1 else 0
                    czr = cov_z[bz, yy, :, Rz + oy, Rz + ox, :] if inz else cov_z[0, 0, :, 0, 0, :]
                    cxc = cov_yz[bx, yy, :, Rx + oy, Rx + ox, :] if inx else cov_yz[0, 0, :, 0, 0, :]
                    cxt = cov_yz[bx, ty, :, Rx - oy, Rx - ox, :] if inx else cov_yz[0, 0, :, 0, 0, :]
                    for xx in range(xa, xb):
                        tx = xx + ox
                        for c in range(C):
                            dv = Pc[xx * C + c] + Pt[tx * C + c]
                            if inz:
                                dv -= 2.0 * czr[xx, c]
                            if inx:
                                dv += 2.0 * (cxc[xx, c] + cxt[tx, c])
                            dvr[(xx - e0) * C + c] = dv
                n = hi - lo
                a_zc = zc[lo:hi]
                a_zt = zt[lo + sh:hi + sh]
                a_yc = yc[lo:hi]
                a_yt = yt[lo + sh:hi + sh]
                a_q = qf[lo + qo:hi + qo]
                if inz or inx:
                    a_dv = dvr[lo + qo:hi + qo]
                    for i in range(n):
                        d = (a_zc[i] - a_zt[i]) - (a_yc[i] - a_yt[i])
                        a_q[i] += d * d - a_dv[i]
                else:
                    a_pc = Pc[lo:hi]
                    a_pt = Pt[lo + sh:hi + sh]
                    for i in range(n):
                        d = (a_zc[i] - a_zt[i]) - (a_yc[i] - a_yt[i])
                        a_q[i] += d * d - (a_pc[i] + a_pt[i])
            a_q = qf[lo + qo:hi + qo]
            fb = np.float64(B)
            for i in range(hi - lo):
                a_q[i] /= fb
        nc = (c1 - c0) * C
        for yy in range(nq):
            qf = q[yy]
            hf = hq[yy]
            hf[:] = 0.0
            for u in range(2 * patch + 1):
                a_q = qf[u * C:u * C + nc]
                for i in range(nc):
                    hf[i] += a_q[i]
        num = np.empty(nc)
        for yy in range(y0, y1):
            ua = max(q0, yy - patch)
            ub = min(q1, yy + patch + 1)
            num[:] = 0.0
            for u in range(ua, ub):
                hf = hq[u - q0]
                for i in range(nc):
                    num[i] += hf[i]
            ny = max(0, min(yb, yy + patch + 1) - max(ya, yy - patch))
            rowok = ya <= yy < yb
            py = yy - oy
            inby = loo and abs(oy) <= patch and abs(ox) <= patch and 0 <= py < H
            out = s2[j, yy - y0].reshape(W * C)[c0 * C:c1 * C]
            qc = q[yy - q0][pc:pc + nc]
            qp = q[py - q0] if inby else q[yy - q0]
            xa0 = max(0, -ox)
            xb0 = min(W, W - ox)
            for xi in range(c1 - c0):
                xx = c0 + xi
                nx = max(0, min(xb0, xx + patch + 1) - max(xa0, xx - patch))
                den = np.float64(ny * nx)
                if loo:
                    px = xx - ox
                    inb = inby and 0 <= px < W
                    dl = (1.0 if rowok and xa0 <= xx < xb0 else 0.0) + (1.0 if inb else 0.0)
                    dd = den - dl
                    for c in range(C):
                        nm = num[xi * C + c]
                        nm -= qc[xi * C + c] + (qp[(px - e0) * C + c] if inb else 0.0)
                        m = nm / dd if dd > 0.0 else 0.0
                        out[xi * C + c] = m if m > 0.0 else 0.0
                else:
                    dd = den - 0.0
                    for c in range(C):
                        m = num[xi * C + c] / dd if dd > 0.0 else 0.0
                        out[xi * C + c] = m if m > 0.0 else 0.0


def _bias_planes(ys, zs, P, cov_z, cov_yz, has_yz, k, patch, loo, y0, y1, s2, pairs=False):
    """Squared-bias estimates ``s2[j, y − y0, x, c]`` for tap ``j`` and rows ``y0 .. y1 − 1``.

    ``max(box_mean(mean_b((δ² − Var δ)·valid), valid), 0)`` over the ``(2 patch + 1)²``
    box of centre pixels, counting only centres whose tap is inside the image (the
    ``z_bias="estimate"`` of :func:`statmc.combine.statistical_weights`).  With ``loo``
    the two centres whose ``δ`` contains ``y_c`` itself (``c`` and ``c − o``) are left out.
    ``Var δ = P_c + P_t − 2 cov(z_c, z_t) + 2 cov(y_c, z_t) + 2 cov(y_t, z_c)`` with the
    per-pixel ``P = var_y + var_z − 2 cov(y, z)`` (:func:`_self_term`), the NumPy
    ``_delta_var`` regrouped.  With ``pairs`` (``z_bias="pairs"``, ``B >= 2``) the
    per-centre term is ``((Σ_b δ_b)² − Σ_b δ_b²) / (B (B − 1))`` instead (the mean of
    ``δ_b δ_b'`` over distinct bins; no ``Var δ``).

    One task per (tile of ``BIAS_TILE`` columns, tap), so a task's input rows stay in
    cache; chunks of tasks run on several threads (:func:`statmc._task_threads.run_rows`).
    The inner loops run over contiguous ``(x, c)`` rows (1-D views indexed from 0, which
    LLVM vectorises); the stencil terms of the taps within the stencil are formed
    first, in the same order.  The box counts are products of the row and column counts
    of valid centres (sums of ones before).  Every sum keeps its order, so the planes are
    bit for bit those of the plain per-pixel loop.

    Finite input within ``statmc.combine.VALUE_LIMIT`` / ``MOMENT_LIMIT`` keeps every plane
    finite.  Beyond them (refused by the callers) an overflowed ``δ²`` would stay Inf here
    while the NumPy ``_box_mean`` sets non-finite box means to 0, so the two would differ.
    """
    nt = (ys.shape[2] + BIAS_TILE - 1) // BIAS_TILE
    # Each mode passes None for what it does not read ("pairs": P; the others: the flag),
    # so numba compiles only that mode's branch, once per mode used: on a cold cache the
    # pairs kernel of combine_bins compiled in 2.3-3.3 s of CPU instead of 3.9-5.7 s, the
    # "estimate" one of combine_denoised in 3.6-4.6 s instead of 4.4-5.5 s (session 17;
    # both in one process: 6.8-8.0 s, docs/combine.md "First call").
    P, flag = (None, True) if pairs else (P, None)
    run_rows(_bias_tasks, 0, nt * k * k, ys, zs, P, cov_z, cov_yz, bool(has_yz), int(k),
             int(patch), bool(loo), int(y0), int(y1), s2, flag)


@njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _solve_small(G, rhs, sol):  # pragma: no cover - compiled
    """``G sol = rhs`` for a small dense system (Gaussian elimination, partial pivoting).

    A zero pivot gives Inf/NaN (``error_model="numpy"``: IEEE division, no
    ``ZeroDivisionError``), which sends the pixel to the weights' fallback."""
    n = G.shape[0]
    for i in range(n):
        p = i
        for j in range(i + 1, n):
            if abs(G[j, i]) > abs(G[p, i]):
                p = j
        if p != i:
            for j in range(n):
                G[i, j], G[p, j] = G[p, j], G[i, j]
            rhs[i], rhs[p] = rhs[p], rhs[i]
        for j in range(i + 1, n):
            f = G[j, i] / G[i, i]
            for l in range(i, n):
                G[j, l] -= f * G[i, l]
            rhs[j] -= f * rhs[i]
    for i in range(n - 1, -1, -1):
        s = rhs[i]
        for j in range(i + 1, n):
            s -= G[i, j] * sol[j]
        sol[i] = s / G[i, i]


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _drop_tap(U, di, i, C, rhs0, G0):  # pragma: no cover - compiled
    """Remove tap ``i``'s terms ``U_i d_i`` from the active-set sums ``rhs0``, ``G0``."""
    for c in range(C):
        ud = U[i, c] * di[i]
        rhs0[c] -= ud
        for d in range(C):
            G0[c, d] -= ud * U[i, d]


@njit(cache=True, fastmath=False, nogil=True, inline="always")
def _identity(out, y, x, B, k):  # pragma: no cover - compiled
    """The fallback weights of pixel ``(y, x)``: ``1 / B`` on each bin's centre tap."""
    r = k // 2
    wc = np.float32(1.0 / B)
    for b in range(B):
        for dy in range(k):
            for dx in range(k):
                out[y, x, b, dy, dx] = wc if (dy == r and dx == r) else np.float32(0.0)


@njit(cache=True, fastmath=False, nogil=True)
def _weights_rows(var_y, P, cov_z, cov_yz, has_yz, zb, bias_mode, s2, method, k, B, y0, out,
                  ya, yb):  # pragma: no cover - compiled
    """Rows ``ya .. yb - 1`` of :func:`_weights_band`."""
    H = out.shape[0]
    W = out.shape[1]
    C = var_y.shape[3]
    r = k // 2
    kk = k * k
    n = B * kk
    Rz = cov_z.shape[3] // 2
    Rx = cov_yz.shape[3] // 2
    v = np.empty(n)
    di = np.empty(n)
    b2 = np.empty((n, C))
    valid = np.zeros(n, np.bool_)
    act = np.zeros(n, np.bool_)
    nzu = np.zeros(n, np.bool_)
    lst = np.empty(n, np.int64)
    a = np.zeros(n)
    U = np.empty((n, C))
    G = np.empty((C, C))
    G0 = np.empty((C, C))
    rhs = np.empty(C)
    rhs0 = np.empty(C)
    sol = np.empty(C)
    cz0 = np.empty(C)
    for y in range(ya, yb):
        for x in range(W):
            top = 0.0
            # typed initial values, not literals (False, 0): numba's type inference runs
            # over the whole function once more for each literal it has to widen
            bad = np.bool_(False)     # a tap's Var(e_t) or squared bias is not finite
            for b in range(B):
                bv = b if var_y.shape[0] > 1 else 0
                bp = b if P.shape[0] > 1 else 0
                bz = b if cov_z.shape[0] > 1 else 0
                bx = b if cov_yz.shape[0] > 1 else 0
                for c in range(C):
                    cz0[c] = cov_z[bz, y, x, Rz, Rz, c]
                for dy in range(k):
                    oy = dy - r
                    ty = y + oy
                    rowok = 0 <= ty < H
                    for dx in range(k):
                        j = dy * k + dx
                        i = b * kk + j
                        ox = dx - r
                        tx = x + ox
                        ok = rowok and 0 <= tx < W
                        valid[i] = ok
                        if not ok:
                            continue
                        centre = oy == 0 and ox == 0
                        inz = abs(oy) <= Rz and abs(ox) <= Rz
                        inx = has_yz and abs(oy) <= Rx and abs(ox) <= Rx
                        vm = 0.0
                        bm = 0.0
                        for c in range(C):
                            if centre:
                                q = var_y[bv, y, x, c]
                            else:
                                q = P[bp, ty, tx, c] + cz0[c]
                                if inz:
                                    q -= 2.0 * cov_z[bz, y, x, Rz + oy, Rz + ox, c]
                                if inx:
                                    q += 2.0 * cov_yz[bx, ty, tx, Rx - oy, Rx - ox, c]
                            vm += q
                            if bias_mode == 0:
                                e2 = s2[j, y - y0, x, c]
                            elif bias_mode == 1 or centre:
                                e2 = 0.0
                            else:
                                e = _im(zb, b, y, x, c) - _im(zb, b, ty, tx, c)
                                e2 = e * e
                            b2[i, c] = e2
                            bm += e2
                        v[i] = vm / C
                        t = v[i] + bm / C
                        if t > top:
                            top = t
                        if not np.isfinite(t):
                            bad = True
            if bad:
                _identity(out, y, x, B, k)
                continue
            floor = max(1e-12 * top, 1e-300)
            vmin = np.inf
            for i in range(n):
                if valid[i]:
                    if v[i] < floor:
                        v[i] = floor
                    if v[i] < vmin:
                        vmin = v[i]
            if method == 1:
                # diagonal: inverse-MSE weights, scaled by the smallest MSE
                mmin = np.inf
                for i in range(n):
                    a[i] = 0.0
                    if valid[i]:
                        s = 0.0
                        for c in range(C):
                            s += b2[i, c]
                        a[i] = v[i] + s / C
                        if a[i] < mmin:
                            mmin = a[i]
                for i in range(n):
                    a[i] = mmin / a[i] if valid[i] else 0.0
                    act[i] = valid[i]
            else:
                # coherent: min aᵀ(D + U Uᵀ)a, Σa = 1, a ≥ 0 (Woodbury + active set);
                # G = I + Σ_active d_i U_i U_iᵀ and rhs = Σ_active d_i U_i are updated by
                # removing the dropped taps instead of being summed again.  Taps without
                # bias (U_i = 0, most of them) skip the sqrt and the updates, which would
                # add exact zeros, and get a_i = d_i (1 − 0) = d_i: bit for bit the same.
                for c in range(C):
                    rhs0[c] = 0.0
                    for d in range(C):
                        G0[c, d] = 1.0 if c == d else 0.0
                cv = C * vmin
                # C = 3: the sums in registers (the same additions in the same order)
                g00, g01, g02, g10, g11, g12, g20, g21, g22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, \
                    0.0, 0.0, 1.0
                q0 = q1 = q2 = 0.0
                for i in range(n):
                    act[i] = valid[i]
                    nzu[i] = False
                    if valid[i]:
                        di[i] = vmin / v[i]
                        for c in range(C):
                            e2 = b2[i, c]
                            if e2 != 0.0:
                                U[i, c] = np.sqrt(e2 / cv)
                                nzu[i] = True
                            else:
                                U[i, c] = 0.0
                        if nzu[i] and C == 3:
                            u0 = U[i, 0]
                            u1 = U[i, 1]
                            u2 = U[i, 2]
                            ud = u0 * di[i]
                            q0 += ud
                            g00 += ud * u0
                            g01 += ud * u1
                            g02 += ud * u2
                            ud = u1 * di[i]
                            q1 += ud
                            g10 += ud * u0
                            g11 += ud * u1
                            g12 += ud * u2
                            ud = u2 * di[i]
                            q2 += ud
                            g20 += ud * u0
                            g21 += ud * u1
                            g22 += ud * u2
                        elif nzu[i]:
                            for c in range(C):
                                ud = U[i, c] * di[i]
                                rhs0[c] += ud
                                for d in range(C):
                                    G0[c, d] += ud * U[i, d]
                if C == 3:
                    rhs0[0], rhs0[1], rhs0[2] = q0, q1, q2
                    G0[0, 0], G0[0, 1], G0[0, 2] = g00, g01, g02
                    G0[1, 0], G0[1, 1], G0[1, 2] = g10, g11, g12
                    G0[2, 0], G0[2, 1], G0[2, 2] = g20, g21, g22
                # The active taps with U_i != 0 in ascending order (``lst[:nl]``): with a
                # finite solution only they can change or turn negative; the others keep
                # a_i = d_i (> 0).  (``a`` of inactive taps is never read.)  Each dropped
                # tap's update of G0, rhs0 comes in ascending order after its a_i, from
                # the same solution, as when all a are formed first: bit for bit the same.
                nl = np.int64(0)
                for i in range(n):
                    if act[i]:
                        a[i] = di[i]
                        if nzu[i]:
                            lst[nl] = i
                            nl += 1
                for it in range(MAX_ACTIVE_SET_ITER):
                    for c in range(C):
                        rhs[c] = rhs0[c]
                        for d in range(C):
                            G[c, d] = G0[c, d]
                    _solve_small(G, rhs, sol)
                    for c in range(C):
                        bad = bad or not np.isfinite(sol[c])
                    if bad:
                        # G = I + Σ d_i U_i U_iᵀ is positive definite, so only a numerically
                        # singular elimination gets here: the pixel falls back (below)
                        break
                    neg = np.bool_(False)
                    m = np.int64(0)
                    for li in range(nl):
                        i = lst[li]
                        s = 0.0
                        for c in range(C):
                            s += U[i, c] * sol[c]
                        a[i] = di[i] * (1.0 - s)
                        if a[i] < 0.0:
                            act[i] = False
                            neg = True
                            _drop_tap(U, di, i, C, rhs0, G0)
                        else:
                            lst[m] = i
                            m += 1
                    nl = m
                    if not neg:
                        break
            tot = 0.0
            for i in range(n):
                if act[i] and a[i] > 0.0:
                    tot += a[i]
            if bad or not (0.0 < tot < np.inf):
                _identity(out, y, x, B, k)
                continue
            for b in range(B):
                for dy in range(k):
                    for dx in range(k):
                        i = b * kk + dy * k + dx
                        w = a[i] / tot if (act[i] and a[i] > 0.0) else 0.0
                        out[y, x, b, dy, dx] = np.float32(w)


def _weights_band(var_y, P, cov_z, cov_yz, has_yz, zb, bias_mode, s2, method, k, B, y0, y1, out):
    """Weights of rows ``y0 .. y1 − 1`` into ``out`` (see :func:`statistical_weights_numba`).

    ``Var(e_t)`` of ``e_t = y_t + z_c − z_t`` is ``var_y(c)`` for the centre and
    ``P_t + var_z(c) − 2 cov(z_c, z_t) + 2 cov(y_t, z_c)`` otherwise (the NumPy
    ``_Moments.pair`` regrouped with ``P = var_y + var_z − 2 cov(y, z)``).

    Fallback (as the NumPy ``_to_weights``): a pixel gets :func:`_identity` (``1 / B`` on
    each bin's centre tap) when a tap inside the image has a non-finite ``Var(e_t)`` or
    squared bias, when the ``C x C`` solve of "coherent" is not finite, or when the weights
    do not sum to a positive finite number.  Inputs within the limits that
    :func:`statmc.combine.statistical_weights` enforces keep every moment finite, so
    there only a numerically singular solve could get here.
    """
    run_rows(_weights_rows, y0, y1, var_y, P, cov_z, cov_yz, bool(has_yz), zb,
             int(bias_mode), s2, int(method), int(k), int(B), int(y0), out)


def _self_term(var_y, cov_z, cov_yz, has_yz):
    """``P = var_y + var_z − 2 cov(y, z)`` per pixel, ``(B', H, W, C)`` (B' = 1 or B)."""
    Rz = cov_z.shape[3] // 2
    P = var_y + cov_z[:, :, :, Rz, Rz, :]
    if has_yz:
        Rx = cov_yz.shape[3] // 2
        P = P - 2.0 * cov_yz[:, :, :, Rx, Rx, :]
    return np.ascontiguousarray(P)


def statistical_weights_numba(ys, zs, var_y, cov_z, cov_yz, zb, bias_mode, method, k, patch,
                              out, *, loo=False, band_bytes=1 << 28, rows=None, pairs=False):
    """Compiled "coherent"/"diagonal" statistical weights into ``out`` ``(H, W, B, k, k)``.

    ``pairs`` (with ``bias_mode`` 0, ``B >= 2``): the squared biases from products of
    distinct bins (``z_bias="pairs"``, see :func:`_bias_planes`).

    Rows are processed in bands so that the squared-bias planes ``(k², rows, W, C)`` of
    ``bias_mode`` 0 stay under ``band_bytes``.  ``rows = (r0, r1)``: only the weights of
    rows ``r0 .. r1 − 1`` are computed (the others of ``out`` are left as they are); each
    row's weights are those of the whole computation to the bit (a row's bias planes and
    weights read the inputs, never other rows' results).
    """
    B, H, W, C = ys.shape
    r0, r1 = (0, H) if rows is None else (max(0, int(rows[0])), min(H, int(rows[1])))
    has_yz = cov_yz is not None
    if not has_yz:
        cov_yz = np.zeros((1, 1, 1, 1, 1, C))
    if zb is None:
        zb = np.zeros((1, 1, 1, C))
    # the inputs read-only and C-contiguous: one compiled variant, whatever the caller's
    # arrays (a read-only var_y compiled the ~20 s kernels anew)
    ys, zs, var_y, cov_z, cov_yz, zb = (readonly(a, np.float64)
                                        for a in (ys, zs, var_y, cov_z, cov_yz, zb))
    n = max(1, r1 - r0)
    rows = n if bias_mode != BIAS_ESTIMATE else max(1, min(n, band_bytes // (k * k * W * C * 8)))
    s2 = np.zeros((k * k, rows, W, C) if bias_mode == BIAS_ESTIMATE else (1, 1, 1, C))
    P = _self_term(var_y, cov_z, cov_yz, has_yz)
    for y0 in range(r0, r1, rows):
        y1 = min(r1, y0 + rows)
        if bias_mode == BIAS_ESTIMATE:
            _bias_planes(ys, zs, P, cov_z, cov_yz, has_yz, k, patch, loo, y0, y1, s2,
                         bool(pairs))
        _weights_band(var_y, P, cov_z, cov_yz, has_yz, zb, bias_mode, s2, method, k, B, y0, y1,
                      out)
    return out


# =========================================================================== moment smoothing
RUN_TILE = 2048            # columns per task of :func:`running_rows` (the sums stay in L1)


def running_rows(x, add, sub, n, t, out):
    """The rows pass of a box mean of width ``n`` as a running sum, continued from ``t``.

    ``x`` ``(rows, L)``, ``t`` ``(L,)`` the running sums so far (updated), ``out``
    ``(len(add), L)``: for ``j = 0, 1, ...`` in order, ``t += x[add[j]] − x[sub[j]]`` and
    ``out[j] = t / n`` (:class:`statmc.combine._SmoothedRows`, SciPy's ``uniform_filter1d``
    update).  Each element does the same subtraction, addition and division in the same
    order as :func:`running_rows_numpy`, so the two agree to the bit.  Tiles of
    ``RUN_TILE`` columns run on several threads (:func:`_running_tiles`).
    """
    L = t.shape[0]
    run_rows(_running_tiles, 0, (L + RUN_TILE - 1) // RUN_TILE, x, add, sub, n, t, out)


@njit(cache=True, fastmath=False, nogil=True)
def _running_tiles(x, add, sub, n, t, out, ta, tb):  # pragma: no cover - compiled
    """Column tiles ``ta .. tb - 1`` of :func:`running_rows`."""
    L = t.shape[0]
    nr = add.shape[0]
    for tile in range(ta, tb):
        j0 = tile * RUN_TILE
        j1 = min(L, j0 + RUN_TILE)
        for r in range(nr):
            xa = x[add[r]]
            xb = x[sub[r]]
            o = out[r]
            for j in range(j0, j1):
                t[j] += xa[j] - xb[j]
                o[j] = t[j] / n


def running_rows_numpy(x, add, sub, n, t, out):
    """NumPy reference of :func:`running_rows` (one row at a time)."""
    for r in range(len(add)):
        t += x[add[r]] - x[sub[r]]
        np.divide(t, n, out=out[r])
    return out

