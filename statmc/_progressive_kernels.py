"""Private numba kernels for the confidence gate of progressive denoising.

Only :mod:`statmc.progressive` calls these; the public wrapper validates input, fixes
dtypes and contiguity and allocates outputs.  :func:`gate_sums_numpy` and
:func:`gate_numpy` are the plain NumPy references the tests compare against.

What is computed (Eq. 12–18 of Firmino et al. 2022, per channel ``c`` and pixel ``p``,
with ``u = α (y − x)``, ``v = Var[x]`` and the window ``N_p`` of ``(2r+1)²`` in-image
pixels):

* ``M_p = argmax_{q ∈ N_p} v_q`` (Eq. 16; ties go to the first in row-major order);
* ``num_p = u_{M_p} + Σ_q κ_pq u_q`` — the difference ``z̄_p − x̄_p`` of Eq. 14 and 12;
* ``var_p = v_{M_p} + Σ_q κ_pq² v_q`` — Eq. 13;
* ``t_p = num_p/(√var_p + ε)`` — Eq. 17, with its limit ε → 0⁺ where ``√var_p + ε = 0``
  (0 if ``num_p = 0``, else ±∞), and ``α'_p = (1 − S[a(|t_p| − c)]) α_p`` — Eq. 18;

with ``κ_pq = g(p_y − q_y) g(p_x − q_x)·norm``, ``g(d) = exp(−d²/(2σ_s²))`` and
``norm = 1/(σ_s √(2π))`` (Eq. 15).  κ is separable, and so is the window argmax (the
maximum over each row segment, then over the rows), so each pixel costs ``O(r)`` work.

Layout: an ``(H, W, C)`` image is seen as ``(H, W*C)`` rows; the horizontal pass strides
by ``C``.  Parallel tasks are bands of output rows (see ``_BAND``).  Inner loops index
slices from 0 so that LLVM can prove indices non-negative.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._kernel_inputs import readonly
from ._task_threads import run_tasks
from ._threads import wait_passively_in_numba

wait_passively_in_numba()

# No NaN reaches the kernels (inputs are checked finite), which lets LLVM turn the
# compare-and-select of the window argmax into vector max/blend instructions; -inf is
# used as the initial maximum, so "ninf" is deliberately not among the flags.
_FLAGS = {"nnan", "nsz", "contract"}


# =========================================================================== numba
#: Output rows per parallel task.  Each task keeps the horizontal-pass rows of its band
#: plus a halo of r rows in small local buffers (instead of image-sized temporaries, whose
#: first touch alone cost ~30 % of the time at 1080p), at (BAND + 2r)/BAND of the
#: horizontal work.
_BAND = 48


@njit(cache=True, nogil=True, inline="always", fastmath=_FLAGS)
def _hrow(src_u, src_v, g, g2, r, c, su, sv, rm, ri):  # pragma: no cover - compiled
    """One row: Σ_dx g u, Σ_dx g² v, and the max of v over the row window and its dx."""
    n = src_u.shape[0]
    w = n // c
    for j in range(n):
        su[j] = 0.0
        sv[j] = 0.0
        rm[j] = -np.inf
        ri[j] = 0
    for k in range(-r, r + 1):
        x0 = max(0, -k)
        x1 = min(w, w - k)
        if x1 <= x0:
            continue
        j0 = x0 * c
        j1 = x1 * c
        off = k * c
        pu = src_u[j0 + off:j1 + off]
        pv = src_v[j0 + off:j1 + off]
        d_su = su[j0:j1]
        d_sv = sv[j0:j1]
        d_rm = rm[j0:j1]
        d_ri = ri[j0:j1]
        wk = g[k + r]
        wk2 = g2[k + r]
        for j in range(j1 - j0):   # branch-free so that LLVM vectorises the argmax
            val = pv[j]
            d_su[j] += wk * pu[j]
            d_sv[j] += wk2 * val
            cur = d_rm[j]
            gt = val > cur
            d_rm[j] = val if gt else cur
            d_ri[j] = k if gt else d_ri[j]


#: Abramowitz & Stegun 7.1.26 (Hastings): erfc(x) ≈ t (a1 + t (a2 + … + t a5)) e^{−x²},
#: t = 1/(1 + p x), x >= 0, absolute error <= 1.5e-7.
_AS_P = 0.3275911
_AS_A = (0.254829592, -0.284496736, 1.421413741, -1.453152027, 1.061405429)
#: Absolute error bound of :func:`_scale` with ``fast``: half that of 7.1.26.
FAST_CDF_ERROR = 0.75e-7


@njit(cache=True, nogil=True, inline="always")
def _scale(s, logistic, fast, inv_sqrt2):  # pragma: no cover - compiled
    """``1 − S(s)``; S is the standard normal CDF or the logistic function.  ``fast``: the
    normal CDF by Abramowitz & Stegun 7.1.26 (one exp, no libm erfc; |error| <= 7.5e-8,
    below float32 resolution of the scale, used with float32 work)."""
    if logistic:
        return 1.0 / (1.0 + math.exp(s)) if s < 700.0 else 0.0
    if fast:
        x = abs(s) * inv_sqrt2
        q = 1.0 / (1.0 + _AS_P * x)
        q = 0.5 * q * (_AS_A[0] + q * (_AS_A[1] + q * (_AS_A[2] + q * (_AS_A[3] + q * _AS_A[4]))))
        q *= math.exp(-x * x)
        return q if s >= 0.0 else 1.0 - q
    if s < -8.3:          # 1 − Φ(s) rounds to 1 in double precision below −8.3
        return 1.0
    return 0.5 * math.erfc(s * inv_sqrt2)


@njit(cache=True, nogil=True, inline="always")
def _tstat(num, var, eps):  # pragma: no cover - compiled
    """Eq. 17, ``num/(√var + ε)``; where ``√var + ε = 0`` (ε = 0 on zero variance) its limit
    ε → 0⁺: 0 if ``num = 0``, else ±∞ (no 0/0, which the no-NaN fast math may not form)."""
    den = math.sqrt(max(var, 0.0)) + eps
    if den > 0.0:
        return num / den
    if num == 0.0:
        return 0.0
    return math.inf if num > 0.0 else -math.inf


@njit(cache=True, nogil=True)
def _gate_bands(b0, b1, u, v, g, g2, r, c, norm, norm2, band, keep, num, var,
                finish, alpha, shared, a, cc, eps, logistic, fast, t_out,
                a_out):  # pragma: no cover
    """Bands ``b0 .. b1 − 1`` of output rows, each by :func:`_gate_band`; run on several
    threads by :func:`statmc._task_threads.run_tasks`.  As a numba parallel loop
    (``prange``) the gate compiled in 9-11 s CPU on a cold cache: the parallel lowering
    links the band function into the loop body's function and that into the kernel,
    optimising it again at each level."""
    for b in range(b0, b1):
        _gate_band(b, u, v, g, g2, r, c, norm, norm2, band, keep, num, var,
                   finish, alpha, shared, a, cc, eps, logistic, fast, t_out, a_out)


@njit(cache=True, nogil=True, fastmath=_FLAGS)
def _gate_band(b, u, v, g, g2, r, c, norm, norm2, band, keep, num, var,
               finish, alpha, shared, a, cc, eps, logistic, fast, t_out,
               a_out):  # pragma: no cover - compiled
    """Band ``b`` of output rows: horizontal pass with halo, vertical sums and argmax, the
    gather of Eq. 13/14, and (``finish``) Eq. 17/18.  ``keep``: write num/var (else row
    scratch)."""
    h, n = u.shape
    w = n // c
    inv_sqrt2 = 1.0 / math.sqrt(2.0)
    y0 = b * band
    y1 = min(h, y0 + band)
    h0 = max(0, y0 - r)
    h1 = min(h, y1 + r)
    m = h1 - h0
    su = np.empty((m, n), u.dtype)
    sv = np.empty((m, n), u.dtype)
    rm = np.empty((m, n), u.dtype)
    ri = np.empty((m, n), np.int32)
    for yy in range(h0, h1):
        i = yy - h0
        _hrow(u[yy], v[yy], g, g2, r, c, su[i], sv[i], rm[i], ri[i])
    best = np.empty(n, u.dtype)
    bdy = np.empty(n, np.int32)
    s_num = np.empty(n, u.dtype)
    s_var = np.empty(n, u.dtype)
    for y in range(y0, y1):
        o_num = num[y] if keep else s_num
        o_var = var[y] if keep else s_var
        for j in range(n):
            o_num[j] = 0.0
            o_var[j] = 0.0
            best[j] = -np.inf
            bdy[j] = 0
        for k in range(-r, r + 1):
            yy = y + k
            if yy < 0 or yy >= h:
                continue
            i = yy - h0
            p_su = su[i]
            p_sv = sv[i]
            p_rm = rm[i]
            wk = g[k + r]
            wk2 = g2[k + r]
            for j in range(n):
                o_num[j] += wk * p_su[j]
                o_var[j] += wk2 * p_sv[j]
                val = p_rm[j]
                cur = best[j]
                gt = val > cur
                best[j] = val if gt else cur
                bdy[j] = k if gt else bdy[j]
        for j in range(n):
            ym = y + bdy[j]
            jm = j + ri[ym - h0, j] * c
            o_num[j] = u[ym, jm] + norm * o_num[j]
            o_var[j] = v[ym, jm] + norm2 * o_var[j]
        if not finish:
            continue
        i_a = alpha[y]
        o_a = a_out[y]
        for x in range(w):
            j0 = x * c
            if shared:
                sn = 0.0
                sw = 0.0
                for k in range(c):
                    sn += o_num[j0 + k]
                    sw += o_var[j0 + k]
                t = _tstat(sn, sw, eps)
                scale = _scale(a * (abs(t) - cc), logistic, fast, inv_sqrt2)
                for k in range(c):
                    if keep:
                        t_out[y, j0 + k] = t
                    o_a[j0 + k] = scale * i_a[j0 + k]
            else:
                for k in range(c):
                    t = _tstat(o_num[j0 + k], o_var[j0 + k], eps)
                    if keep:
                        t_out[y, j0 + k] = t
                    o_a[j0 + k] = _scale(a * (abs(t) - cc), logistic, fast,
                                         inv_sqrt2) * i_a[j0 + k]


def _run(u, v, r, sigma_s, alpha=None, keep=True, **finish):
    """``u`` and ``v`` set the working precision (``v`` is cast to ``u``'s dtype); the gated
    output has ``alpha``'s dtype (float32 or float64; other dtypes give float64), but the
    kernel always gets ``alpha`` as float64 (see below), so one gate is compiled per
    working precision.

    Inputs reach the kernel read-only, C-contiguous and native (:func:`readonly`), so a
    read-only caller's array does not compile the kernel anew; without ``alpha`` the
    unused ``alpha`` and output are the float64 ones of :func:`gate` with float64 ``alpha``
    (one compiled kernel for both).
    """
    h, w, c = u.shape
    u2 = readonly(u).reshape(h, w * c)
    dt = u2.dtype
    v2 = readonly(v, dt).reshape(h, w * c)
    d = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (d / sigma_s) ** 2)
    norm = 1.0 / (sigma_s * math.sqrt(2.0 * math.pi))
    gd, g2d = readonly(g.astype(dt)), readonly((g * g).astype(dt))
    empty = np.empty((h, 0), dt)
    num = np.empty_like(u2) if keep else empty
    var = np.empty_like(u2) if keep else empty
    if alpha is None:
        no_alpha = np.empty((h, 0), np.float64)
        args = (False, readonly(no_alpha), False, 0.0, 0.0, 0.0, False, False, empty, no_alpha)
    else:
        a2 = np.asarray(alpha)
        out_dt = np.float32 if a2.dtype == np.float32 else np.float64
        # float32 α as float64 (exact): the kernel forms scale·α in float64 either way and
        # rounds it to the output's dtype on the store, so a float32 output rounded from
        # the float64 one is the same to the bit, and one gate is compiled, not two
        a2 = readonly(a2, np.float64).reshape(h, w * c)
        t = np.empty_like(u2) if keep else empty
        out = np.empty(a2.shape, np.float64)
        fast = bool(finish.get("fast_cdf", dt == np.float32))
        args = (True, a2, bool(finish["shared"]), float(finish["a"]), float(finish["c"]),
                float(finish["eps"]), bool(finish["logistic"]), fast, t, out)
    run_tasks(_gate_bands, (h + _BAND - 1) // _BAND, u2, v2, gd, g2d, r, c, dt.type(norm),
              dt.type(norm * norm), _BAND, keep, num, var, *args)
    shp = (h, w, c)
    if alpha is None:
        return num.reshape(shp), var.reshape(shp)
    out = out.astype(out_dt, copy=False)
    if not keep:
        return None, None, None, out.reshape(shp)
    return num.reshape(shp), var.reshape(shp), t.reshape(shp), out.reshape(shp)


@njit(cache=True, nogil=True)
def _prepare(i0, i1, x, y, v, al, u, vw, cast, big, bad, vsum):  # pragma: no cover - compiled
    """Rows ``i0 .. i1 − 1`` of :func:`prepare`, run by :func:`run_tasks`.  Per row: u =
    α(y − x) in the inputs' precision, stored in ``u``'s dtype; with ``cast`` also ``vw =
    v`` in ``vw``'s dtype.  Counts of non-finite x, y, v, α, of negative v and of |u| or v
    above ``big`` (values the working dtype cannot hold) into ``bad[i]``; Σ v into
    ``vsum[i]``.  Each row writes its own counts and sum, added by :func:`prepare` (a
    numba parallel loop until session 16, which cost more to compile on a cold cache)."""
    h, n = x.shape
    for i in range(i0, i1):
        b0 = 0
        b1 = 0
        b2 = 0
        b3 = 0
        b4 = 0
        b5 = 0
        s = 0.0
        for j in range(n):
            xv = x[i, j]
            yv = y[i, j]
            vv = v[i, j]
            av = al[i, j]
            b0 += not np.isfinite(xv)
            b1 += not np.isfinite(yv)
            b2 += not np.isfinite(vv)
            b3 += vv < 0
            b4 += not np.isfinite(av)
            s += vv
            uv = av * (yv - xv)
            b5 += (abs(uv) > big) or (vv > big)
            u[i, j] = uv
            if cast:
                vw[i, j] = vv
        bad[i, 0] = b0
        bad[i, 1] = b1
        bad[i, 2] = b2
        bad[i, 3] = b3
        bad[i, 4] = b4
        bad[i, 5] = b5
        vsum[i] = s


#: Largest magnitude of ``u`` or ``v`` worked in float32: sums of Eq. 13 carry the weight
#: κ² ≤ norm² = 1/(2π σ_s²) ≈ 1.6e5 at the floor σ_s = 1e-3 over up to a few hundred
#: taps, so 1e30 leaves them far below float32's maximum 3.4e38.
SINGLE_MAX = 1e30


def prepare(x, y, v, alpha, work=None):
    """``(u, v_work, bad, Σv)`` for the gate.

    ``u = α(y − x)`` ``(H, W, C)`` is formed in the inputs' dtype and stored in ``work``
    (default: the inputs' dtype); ``v_work`` is ``v`` in ``work`` (``v`` itself when the
    dtypes agree).  ``bad`` counts non-finite ``x``, ``y``, ``v``, negative ``v``,
    non-finite ``α`` and (float32 work from float64 input) ``|u|`` or ``v`` above
    :data:`SINGLE_MAX`; ``Σv`` is float64.
    """
    h, w, c = x.shape
    dt = x.dtype.newbyteorder("=")
    work = dt if work is None else np.dtype(work)
    as2 = lambda a: readonly(a, dt).reshape(h, w * c)   # noqa: E731  (one kernel type)
    v2 = as2(v)
    u = np.empty((h, w * c), work)
    cast = work != dt
    vw = np.empty((h, w * c), work) if cast else np.empty((h, 0), work)
    big = SINGLE_MAX if (cast and work == np.float32) else np.inf
    bad = np.zeros((h, 6), np.int64)
    vsum = np.zeros(h, np.float64)
    run_tasks(_prepare, h, as2(x), as2(y), v2, as2(alpha), u, vw, cast, big, bad, vsum)
    v_out = vw if cast else v2
    return u.reshape(h, w, c), v_out.reshape(h, w, c), bad.sum(axis=0), float(vsum.sum())


def gate_sums(u, v, r, sigma_s):
    """``(num, var)`` of the module docstring for ``(H, W, C)`` arrays ``u`` and ``v``."""
    return _run(u, v, r, sigma_s)


def gate(u, v, alpha, r, sigma_s, *, shared, a, c, eps, logistic, keep=True):
    """``(num, var, t, alpha_gated)``: :func:`gate_sums`, then Eq. 17 and 18 row by row.

    ``keep=False`` returns ``(None, None, None, alpha_gated)`` without allocating the
    image-sized diagnostics.  With float32 ``u`` (single-precision work) the normal CDF of
    Eq. 18 is Abramowitz & Stegun 7.1.26 (absolute error <= :data:`FAST_CDF_ERROR`) instead
    of libm's erfc, which cost as much as the window sums with one t per channel.
    """
    return _run(u, v, r, sigma_s, alpha, keep=keep, shared=shared, a=a, c=c, eps=eps,
                logistic=logistic)


# =========================================================================== NumPy reference
def gate_sums_numpy(u, v, r, sigma_s):
    """Plain NumPy reference of :func:`gate_sums`: one shifted view per window offset."""
    h, w, c = u.shape
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    norm = 1.0 / (sigma_s * math.sqrt(2.0 * math.pi))
    up = np.zeros((h + 2 * r, w + 2 * r, c))
    vp = np.full((h + 2 * r, w + 2 * r, c), -np.inf)
    up[r:r + h, r:r + w] = u
    vp[r:r + h, r:r + w] = v
    su = np.zeros((h, w, c))
    sv = np.zeros((h, w, c))
    best = np.full((h, w, c), -np.inf)
    u_at = np.zeros((h, w, c))
    v_at = np.zeros((h, w, c))
    for dy in range(-r, r + 1):          # row-major order: ties keep the first maximum
        for dx in range(-r, r + 1):
            kappa = math.exp(-(dy * dy + dx * dx) / (2.0 * sigma_s ** 2)) * norm
            us = up[r + dy:r + dy + h, r + dx:r + dx + w]
            vs = vp[r + dy:r + dy + h, r + dx:r + dx + w]
            inside = np.isfinite(vs)
            su += kappa * us
            sv += kappa * kappa * np.where(inside, vs, 0.0)
            better = vs > best
            best = np.where(better, vs, best)
            u_at = np.where(better, us, u_at)
            v_at = np.where(better, vs, v_at)
    return u_at + su, v_at + sv


def gate_numpy(u, v, alpha, r, sigma_s, *, shared, a, c, eps, logistic):
    """Plain NumPy reference of :func:`gate`."""
    num, var = gate_sums_numpy(u, v, r, sigma_s)
    return (num, var) + gate_finish_numpy(num, var, alpha, shared=shared, a=a, c=c, eps=eps,
                                          logistic=logistic)


def gate_finish_numpy(num, var, alpha, *, shared, a, c, eps, logistic):
    """Plain NumPy reference of Eq. 17 and 18 given ``num`` and ``var``."""
    from scipy.special import ndtr

    shape = num.shape
    if shared:
        num = num.sum(axis=2, keepdims=True)
        var = var.sum(axis=2, keepdims=True)
    den = np.sqrt(np.clip(var, 0, None)) + eps
    pos = den > 0
    limit = np.where(num > 0, np.inf, np.where(num < 0, -np.inf, 0.0))   # ε → 0⁺ at den = 0
    t = np.broadcast_to(np.where(pos, num / np.where(pos, den, 1.0), limit), shape)
    s = a * (np.abs(t) - c)
    cdf = 1.0 / (1.0 + np.exp(-s)) if logistic else ndtr(s)
    return np.array(t), (1.0 - cdf) * alpha
