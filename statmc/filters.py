"""Gaussian filter bank with border renormalisation and exact variance propagation.

The filters of Greedy Error Minimisation (Rousselle, Knaus and Zwicker 2011, §4 and §6):
the finest scale is the pixel estimate itself (the renderer's box pixel filter, ``σ = 0``
here); the coarser scales are isotropic Gaussians of the pixel estimates.  Alongside each
filtered value the bank returns its variance, obtained by filtering the per-pixel
*variance of the mean* with the squared weights (Eq. 2 and §6 of [1]_; valid because
pixel estimates use disjoint samples and are uncorrelated).

Borders are renormalised: a filter that hangs over the image edge drops the outside taps
and rescales the inside ones to sum to one, so a constant image stays constant up to the
edge (no energy leaks in or out, no ghost values from padding).  Because the Gaussian is
separable and the renormalisation factors per axis multiply, the renormalised 2-D kernel
is still separable, and so are its squares.

Kernels are truncated at ``truncate · σ`` (default 3, radius ``ceil(3σ)``) and
normalised to sum to one.  The bias formula of GEM uses each kernel's *actual* second
moment ``r² = Σ_k w_k k²`` (:func:`kernel_moment2`), not the nominal ``σ²``, so the
quadratic-image identity of §4.2 holds exactly for the discrete kernels.

References
----------
.. [1] F. Rousselle, C. Knaus, M. Zwicker. Adaptive sampling and reconstruction using
   greedy error minimization. ACM TOG 30(6), 159 (2011). doi:10.1145/2070781.2024193
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ._kernel_inputs import writable
from ._threads import LazyModule, serial_when_small
from .errors import (InputError, as_bool, as_float_array, as_int, check_finite,
                     check_nonnegative, check_same_shape, real_or_nan)

# the compiled kernels (numba) load at the first filter pass, not with this module:
# statmc.denoisers imports it, and `statmc denoise --denoiser oidn` runs no kernel
_k = LazyModule("statmc._filter_kernels")

__all__ = [
    "ADAPTIVE_SIGMAS", "FINAL_SIGMAS", "DEFAULT_TRUNCATE",
    "gaussian_kernel_1d", "kernel_moment2", "border_scale",
    "gaussian_filter", "gaussian_spread", "filter_bank", "filter_bank_reference",
]

#: Scales used during the adaptive iterations (§6 of [1]): the pixel estimate (σ = 0) and
#: four Gaussians at dyadic scales starting at σ = 1.
ADAPTIVE_SIGMAS: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 8.0)
#: Scales of the final reconstruction (§6 of [1]): the pixel estimate and eight Gaussians
#: related by √2, the finest of σ = √2 (so σ = √2 … 16).
FINAL_SIGMAS: tuple[float, ...] = (0.0,) + tuple(2.0 ** (k / 2) for k in range(1, 9))
#: Kernels are cut at ``ceil(DEFAULT_TRUNCATE · σ)`` pixels from the centre.
DEFAULT_TRUNCATE = 3.0


def _check_sigma(sigma) -> float:
    s = real_or_nan(sigma)
    if not np.isfinite(s) or s < 0:
        raise InputError(f"`sigma` must be a finite number >= 0; got {sigma!r}.")
    return s


def _check_truncate(truncate) -> float:
    t = real_or_nan(truncate)
    if not np.isfinite(t) or t <= 0:
        raise InputError(f"`truncate` must be a finite number > 0; got {truncate!r}.")
    return t


def gaussian_kernel_1d(sigma: float, *, truncate: float = DEFAULT_TRUNCATE) -> np.ndarray:
    """Normalised 1-D Gaussian taps ``w_k ∝ exp(−k²/(2σ²))``, ``|k| <= ceil(truncate·σ)``.

    Parameters
    ----------
    sigma : float
        Standard deviation in pixels; ``0`` gives the identity ``[1.0]`` (the pixel filter).
    truncate : float, optional
        Cut-off in standard deviations.

    Returns
    -------
    w : (2r+1,) float64 ndarray summing to 1.

    Examples
    --------
    >>> w = gaussian_kernel_1d(1.0)
    >>> len(w), round(float(w.sum()), 12)
    (7, 1.0)
    """
    s = _check_sigma(sigma)
    t = _check_truncate(truncate)
    if s == 0.0:
        return np.ones(1)
    r = _radius(s, t)
    if r > _MAX_TAPS_A_SIDE:                # NumPy's 'Maximum allowed size exceeded'
        raise InputError(f"`sigma` · `truncate` must be below {_MAX_TAPS_A_SIDE:.3g} taps a "
                         f"side for a kernel array; got {s!r} · {t!r}. The filters take such "
                         f"a σ as it is (they cut the kernel to the image).")
    return _gauss(s, r)


#: More taps a side than any array can hold (2r + 1 elements past the index range).
_MAX_TAPS_A_SIDE = (np.iinfo(np.intp).max - 1) // 2


def _radius(s: float, t: float) -> int:
    """Taps a side of :func:`gaussian_kernel_1d` for checked ``σ > 0`` and ``truncate``.

    ``truncate·σ`` beyond float64's range (``σ = 1e308``) counts as its largest finite
    value: no image and no memory reaches that far either way.
    """
    x = min(t * s, _FLOAT_MAX)
    return max(1, int(math.ceil(x - 1e-9)))      # 3·2.0 -> 6, not 7 after rounding noise


_FLOAT_MAX = float(np.finfo(np.float64).max)
#: ``exp(−k²/(2σ²))`` is exactly 0 in float64 once ``|k| >= 40σ`` (``exp(−800)``
#: underflows; the last subnormal is near ``38.6σ``).
_ZERO_BEYOND = 40.0


def _reach(s: float, r: int) -> int:
    """Taps a side of the ``r``-tap Gaussian of ``σ = s`` that can be non-zero in float64:
    the ones beyond ``40σ`` are exactly 0, so dropping them changes no sum or product."""
    cap = _ZERO_BEYOND * s
    return r if cap >= r else max(1, int(math.ceil(cap)))


#: Kernels and border factors up to this many values are kept (:func:`_gauss`,
#: :func:`_border_scale`): a 136x136 ``gem.reconstruct`` asked for 32 kernels and 44 border
#: factors, the same ones at every call, 1.6 ms of Python in its 8.5 ms (session 16).
_CACHE_VALUES = 1 << 14


def _cached(compute):
    """``compute(*key)`` kept for keys whose result holds at most :data:`_CACHE_VALUES`
    values; each call gets its own writable array (a copy of the kept one: a caller may
    scale it in place), a larger result is computed afresh at each call."""
    keep = functools.lru_cache(maxsize=256)(compute)

    def get(*key, size):
        return keep(*key).copy() if size <= _CACHE_VALUES else compute(*key)
    get.cache_clear = keep.cache_clear
    return get


def _gauss(s: float, r: int) -> np.ndarray:
    """The ``2r + 1`` central taps ``exp(−k²/(2σ²))``, normalised to sum 1."""
    return _gauss_kept(float(s), int(r), size=2 * int(r) + 1)


@_cached
def _gauss_kept(s: float, r: int) -> np.ndarray:
    k = np.arange(-r, r + 1, dtype=np.float64)
    with np.errstate(over="ignore"):             # σ ~ 1e-300: (k/σ)² = inf, weight 0
        w = np.exp(-0.5 * (k / s) ** 2)
    return w / w.sum()


def kernel_moment2(sigma: float, *, truncate: float = DEFAULT_TRUNCATE) -> float:
    """Second central moment ``r² = Σ_k w_k k²`` of :func:`gaussian_kernel_1d` (per axis).

    For an image that is locally quadratic, ``f(x, y) = a x² + b y² + (lower order)``,
    the interior bias of the filter is ``(a + b)·r²`` (the moment relation used in §4.2 of
    [1], after Silverman 1986).  ``r² = 0`` for the pixel filter; ``r² → σ²`` as the
    truncation grows (at the default 3σ cut: 0.975–0.999 σ² for σ = 1 to 16, → 0.973 σ²
    for large σ).

    This is the moment of the whole kernel, whatever image it is applied to: the filters
    cut kernels longer than the image (:func:`_taps`) but renormalise over the in-image
    taps, so every pixel gets the same weights as from the whole kernel.  A long kernel is
    not built: beyond :data:`_MAX_FULL_RADIUS` taps a side the taps past ``40σ`` (exactly
    0) are skipped, and beyond :data:`_MAX_SUM_RADIUS` non-zero taps a side both sums
    take their Euler–Maclaurin form (:func:`_moment2_closed`, within a few ulp).
    """
    s = _check_sigma(sigma)
    t = _check_truncate(truncate)
    if s == 0.0:
        return 0.0
    r = _radius(s, t)
    if r > _MAX_FULL_RADIUS:
        r = _reach(s, r)
        if r > _MAX_SUM_RADIUS:
            return _moment2_closed(s, r)
    w = _gauss(s, r)
    k = np.arange(-r, r + 1, dtype=np.float64)
    return float(np.sum(w * k * k))


#: Beyond this many non-zero taps a side :func:`kernel_moment2` uses the closed form
#: (then ``σ > 2^16/40 ≈ 1638``, where the omitted Euler–Maclaurin terms are ~σ⁻⁷).
_MAX_SUM_RADIUS = 1 << 16


def _moment2_closed(s: float, r: int) -> float:
    """``Σ_{|k|<=r} k² g(k) / Σ_{|k|<=r} g(k)``, ``g(k) = exp(−k²/(2σ²))``, closed form.

    Euler–Maclaurin summation of an even ``f`` over the integers ``−r … r``:
    ``Σ f(k) = ∫_{−r}^{r} f + f(r) + 2 Σ_{j=1}^{3} B_{2j}/(2j)! f^{(2j−1)}(r) + R``, with
    ``B_2/2! = 1/12``, ``B_4/4! = −1/720``, ``B_6/6! = 1/30240`` and ``R`` of order
    ``σ⁻⁷`` relative to the sum.  With ``y = r/σ`` and ``E = exp(−y²/2)``:

    * ``f = g``: ``∫ = σ√(2π) P(1/2, y²/2)`` (``P`` the regularised lower incomplete
      gamma function; ``P(1/2, y²/2) = erf(y/√2)``) and ``σ^m g^(m)(r) = (−1)^m He_m(y) E``
      with the Hermite polynomials ``He_1 = y``, ``He_3 = y³ − 3y``,
      ``He_5 = y⁵ − 10y³ + 15y``;
    * ``f = k² g``: ``∫ = σ³√(2π) P(3/2, y²/2)`` (no cancellation at small ``y``, unlike
      ``σ²(∫g − 2rE)``) and, by Leibniz's rule, ``f' = σ y E (2 − y²)``,
      ``σ f^(3) = E (−y⁵ + 9y³ − 12y)``, ``σ³ f^(5) = E (−y⁷ + 20y⁵ − 95y³ + 90y)``.

    The sums are divided by ``σ`` and ``σ³`` before the ratio, so only the result
    ``≈ σ²`` can overflow (to inf, for ``σ`` above ~1e154).  Agrees with the summed taps
    within 1e-14 relative (tests/test_filters.py).
    """
    from scipy.special import gammainc

    y = min(r / s, _ZERO_BEYOND + 1.0)            # past 40σ every term is 0
    e = math.exp(-0.5 * y * y)
    q = 0.5 * y * y
    root = math.sqrt(2.0 * math.pi)
    b2, b4, b6 = 1.0 / 12.0, -1.0 / 720.0, 1.0 / 30240.0
    u = 1.0 / s
    s0 = (root * float(gammainc(0.5, q)) + e * u                     # Σ g / σ
          - 2.0 * e * u * u * (b2 * y + b4 * (y ** 3 - 3 * y) * u * u
                               + b6 * (y ** 5 - 10 * y ** 3 + 15 * y) * u ** 4))
    s2 = (root * float(gammainc(1.5, q)) + y * y * e * u             # Σ k² g / σ³
          + 2.0 * e * u * u * (b2 * y * (2 - y * y)
                               + b4 * (-y ** 5 + 9 * y ** 3 - 12 * y) * u * u
                               + b6 * (-y ** 7 + 20 * y ** 5 - 95 * y ** 3 + 90 * y) * u ** 4))
    with np.errstate(over="ignore"):
        return float(np.float64(s) * s * (s2 / s0))


def border_scale(n: int, w: np.ndarray) -> np.ndarray:
    """Renormalisation factors ``1 / Σ_{k in image} w_k`` for each of ``n`` positions.

    Equal to 1 away from the border, where the taps sum to one.  ``w`` is a centred 1-D
    kernel of odd length (:func:`gaussian_kernel_1d`).
    """
    n = as_int("n", n, lo=0)
    w = as_float_array("w", w, ndim=1)
    if len(w) % 2 == 0:
        raise InputError(f"`w` must be a centred kernel of odd length; got length {len(w)}.")
    return _border_scale(n, w)


def _border_scale(n: int, w: np.ndarray) -> np.ndarray:
    """:func:`border_scale` without its checks, for this package's callers, which pass an
    image side and taps of :func:`_taps` (a ``gem.reconstruct`` makes ~80 such calls, the
    same ones at every call of a size: kept, :func:`_cached`)."""
    w = np.ascontiguousarray(w)
    return _border_scale_kept(int(n), w.dtype.str, w.tobytes(), size=int(n) + w.size)


@_cached
def _border_scale_kept(n: int, dtype: str, taps: bytes) -> np.ndarray:
    w = np.frombuffer(taps, dtype)
    r = len(w) // 2
    c = np.concatenate([[0.0], np.cumsum(w)])
    pos = np.arange(n)
    # np.maximum/np.minimum, not np.clip: the same integers, 15 µs less a call (a 136x136
    # reconstruct makes 44 of these calls)
    lo = np.maximum(pos - r, 0) - (pos - r)             # first tap index in the image
    hi = np.minimum(pos + r, n - 1) - (pos - r) + 1     # one past the last one
    return 1.0 / (c[hi] - c[lo])


#: Kernels with more taps on a side than this are cut to the taps that can reach the image.
_MAX_FULL_RADIUS = 4096


def _taps(sigma, truncate, n):
    """:func:`gaussian_kernel_1d` for an image whose longer side has ``n`` pixels.

    A tap farther than ``n − 1`` pixels from the centre only ever meets the zero padding,
    so when the kernel is much longer than the image (``σ`` of 1e6 took 41 s on 64×64 and
    1e9 a 45 GiB kernel) it is cut to the ``2(n − 1) + 1`` central taps and renormalised.
    Every use renormalises over the in-image taps (border scale), so the result is the
    same up to rounding; kernels up to :data:`_MAX_FULL_RADIUS` taps a side are unchanged.
    Longer ones also lose their taps past ``40σ``, which are exactly 0 (a huge
    ``truncate`` on a large image).

    The one source of taps for everything that applies, spreads or describes a bank
    filter on an image (the bank, :func:`gaussian_spread`, and in :mod:`statmc.gem` the
    stopping-map filters and their centre taps, the pair covariances, the spread of
    samples): pass ``max(H, W)`` of that image.
    """
    s = _check_sigma(sigma)
    t = _check_truncate(truncate)
    if s == 0.0:
        return np.ones(1)
    r = _radius(s, t)
    if r <= _MAX_FULL_RADIUS:
        return _gauss(s, r)
    return _gauss(s, min(_reach(s, r), max(n - 1, 0)))


def _as_image(name, a, dtype=None):
    arr = as_float_array(name, a, ndim=(2, 3), dtype=dtype)
    check_finite(name, arr)
    return arr


def _rows(img):
    """(H, W) or (H, W, C) -> contiguous, writable (H, W*C) view and C.

    A read-only image is copied: the kernels are compiled for the writable arrays the
    library allocates itself, and a read-only one compiled each of them anew.
    """
    c = 1 if img.ndim == 2 else img.shape[2]
    return writable(img).reshape(img.shape[0], img.shape[1] * c), c


def _run(x, c, v, cv, sigma, truncate, *, normalize=True, out_x=None, out_v=None):
    """One scale through the kernel on (H, W*C) rows; returns (value, variance-or-None)."""
    h, L = x.shape
    wd = L // c
    w = _taps(sigma, truncate, max(h, wd))
    if normalize:
        sy, sx = _border_scale(h, w), _border_scale(wd, w)
    else:
        sy, sx = np.ones(h), np.ones(wd)
    dt = x.dtype
    if out_x is None:
        out_x = np.empty_like(x)
    if v is None:
        v, cv = np.empty((h, 0), dt), 1
        out_v = v
    elif out_v is None:
        out_v = np.empty_like(v)
    _k.sep_filter(x, c, v, cv, w.astype(dt), sy.astype(dt), sx.astype(dt), out_x, out_v)
    return out_x, (out_v if out_v.shape[1] else None)


@serial_when_small()
def gaussian_filter(image, sigma: float, *, truncate: float = DEFAULT_TRUNCATE) -> np.ndarray:
    """Border-renormalised Gaussian filter of an ``(H, W)`` or ``(H, W, C)`` image.

    ``out(p) = Σ_q w(p, q) image(q)`` with separable weights ``w(p, q) = g(p_y − q_y)
    g(p_x − q_x) / N(p)``, ``N(p)`` the sum of the in-image taps.  float32 stays float32.

    Examples
    --------
    >>> img = np.full((5, 6, 3), 2.0, np.float32)
    >>> out = gaussian_filter(img, 2.0)
    >>> out.dtype, bool(np.allclose(out, 2.0))
    (dtype('float32'), True)
    """
    img = _as_image("image", image)
    s = _check_sigma(sigma)
    _check_truncate(truncate)               # also for σ = 0, which does not use it
    if s == 0.0 or img.size == 0:           # no pixels or no channels: nothing to filter
        return img.copy()
    x, c = _rows(img)
    out, _ = _run(x, c, None, 0, s, truncate)
    return out.reshape(img.shape)


@serial_when_small()
def gaussian_spread(amount, sigma: float, *, truncate: float = DEFAULT_TRUNCATE) -> np.ndarray:
    """Adjoint of :func:`gaussian_filter`: spread ``amount(p)`` over p's filter support.

    ``out(q) = Σ_p w(p, q) amount(p)`` with the border-renormalised weights of
    :func:`gaussian_filter`, so ``out.sum() == amount.sum()`` (up to rounding): each
    pixel's amount is split over its neighbours in proportion to its own filter's weights.
    Used to distribute a pixel's new samples over the support of its selected filter
    (§5 of [1]).
    """
    a = _as_image("amount", amount)
    s = _check_sigma(sigma)
    _check_truncate(truncate)
    if s == 0.0 or a.size == 0:
        return a.copy()
    x, c = _rows(a)
    h, wd = a.shape[:2]
    w = _taps(s, truncate, max(h, wd))          # the kernel _run uses below
    pre = (_border_scale(h, w)[:, None] * _border_scale(wd, w)[None, :]).astype(x.dtype)
    x = (x.reshape(h, wd, c) * pre[:, :, None]).reshape(h, wd * c)
    out, _ = _run(x, c, None, 0, s, truncate, normalize=False)
    return out.reshape(a.shape)


def _check_pair(mean, mean_var):
    """Check ``mean`` and ``mean_var`` in one parallel pass; also return the channel sum
    of ``mean_var`` as (H, W) (what the GEM selector needs)."""
    m = as_float_array("mean", mean, ndim=(2, 3))
    v = as_float_array("mean_var", mean_var, ndim=(2, 3), dtype=m.dtype)
    check_same_shape("mean_var", v, "mean", m.shape)
    if m.size == 0:
        raise InputError(f"`mean` must be a non-empty (H, W, C) image; got shape {m.shape}.")
    x, c = _rows(m)
    vr, _ = _rows(v)
    vsum = np.empty(m.shape[:2], m.dtype)
    bad_x, bad_v, neg_v = _k.scan_inputs(x, vr, c, vsum)
    if bad_x:
        check_finite("mean", m)
    if bad_v:
        check_finite("mean_var", v)
    if neg_v:
        check_nonnegative("mean_var", v)
    return m, v, vsum


def _as_sigmas(sigmas) -> np.ndarray:
    """``sigmas`` as a flat float64 array; an :class:`InputError` naming ``sigmas`` when it
    is not real numbers (a string, a ragged list and complex values raised NumPy's
    ValueError/TypeError)."""
    return as_float_array("sigmas", sigmas).astype(np.float64, copy=False).ravel()


def _check_bank_input(mean, mean_var, sigmas, truncate):
    m, v, _ = _check_pair(mean, mean_var)
    sig = _as_sigmas(sigmas)
    if sig.size < 1 or not np.all(np.isfinite(sig)) or np.any(sig < 0):
        raise InputError(f"`sigmas` must be a non-empty sequence of finite numbers >= 0; got {sigmas!r}.")
    _check_truncate(truncate)
    return m, v, [float(s) for s in sig]


@serial_when_small()
def filter_bank(mean, mean_var, sigmas=ADAPTIVE_SIGMAS, *, truncate: float = DEFAULT_TRUNCATE,
                sum_channels: bool = False):
    """Filter the pixel estimates at every scale and propagate their variances.

    Parameters
    ----------
    mean : (H, W, C) or (H, W) ndarray
        Pixel estimates (the finest scale).
    mean_var : same shape as ``mean``
        **Variance of the mean** of each pixel estimate (sample variance / n), >= 0.
    sigmas : sequence of float
        Gaussian standard deviations in pixels; ``0`` is the pixel estimate itself.
        Defaults to :data:`ADAPTIVE_SIGMAS`; see also :data:`FINAL_SIGMAS`.
    truncate : float, optional
        Kernel cut-off in standard deviations.
    sum_channels : bool, optional
        Return the variances summed over channels, ``(K, H, W)``: one filtered plane
        instead of ``C`` (the GEM selector only needs the sum).

    Returns
    -------
    values : (K, H, W, C) ndarray
        ``Σ_q w(p, q) mean(q)`` for each scale, border-renormalised weights.
    variances : (K, H, W, C) ndarray (``(K, H, W)`` with ``sum_channels``)
        ``Σ_q w(p, q)² mean_var(q)``: Eq. 2 of [1] applied to the per-pixel variances of
        the mean (§6 of [1]); exact when pixel estimates are uncorrelated.

    Notes
    -----
    ``mean_var`` is cast to ``mean``'s dtype; float32 stays float32.  2-D input gives
    ``(K, H, W)`` arrays.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> m = rng.normal(size=(16, 16, 3)).astype(np.float32)
    >>> vals, vars_ = filter_bank(m, np.ones_like(m), [0.0, 2.0])
    >>> vals.shape, vals.dtype
    ((2, 16, 16, 3), dtype('float32'))
    >>> bool(abs(vars_[1, 8, 8, 0] - 1 / (4 * np.pi * kernel_moment2(2.0))) < 0.01)
    True
    """
    sum_channels = as_bool("sum_channels", sum_channels)   # "no" was taken as True
    m, v, sig = _check_bank_input(mean, mean_var, sigmas, truncate)
    vals, vars_ = _bank_rows(m, v, sig, truncate, sum_channels=sum_channels)
    h, w = m.shape[:2]
    vshape = (len(sig), h, w) if (sum_channels or m.ndim == 2) else (len(sig),) + m.shape
    return vals.reshape((len(sig),) + m.shape), vars_.reshape(vshape)


def _bank_rows(m, v, sig, truncate, *, sum_channels=False):
    """Filter bank on checked arrays; returns (K, H, W*C) values and (K, H, W*Cv) variances."""
    x, c = _rows(m)
    if sum_channels and m.ndim == 3:
        vr, cv = np.ascontiguousarray(v.sum(axis=2, dtype=v.dtype)), 1
    else:
        vr, cv = _rows(v)
    vals = np.empty((len(sig),) + x.shape, x.dtype)
    vars_ = np.empty((len(sig),) + vr.shape, x.dtype)
    for i, s in enumerate(sig):
        if s == 0.0:
            vals[i] = x
            vars_[i] = vr
        else:
            _run(x, c, vr, cv, s, truncate, out_x=vals[i], out_v=vars_[i])
    return vals, vars_


def _weight_matrix(n: int, sigma: float, truncate: float) -> np.ndarray:
    """(n, n) matrix of border-renormalised 1-D weights ``A[p, q]`` (reference only)."""
    w = gaussian_kernel_1d(sigma, truncate=truncate)
    r = len(w) // 2
    a = np.zeros((n, n))
    for p in range(n):
        for q in range(max(0, p - r), min(n, p + r + 1)):
            a[p, q] = w[q - p + r]
    return a / a.sum(axis=1, keepdims=True)


def filter_bank_reference(mean, mean_var, sigmas=ADAPTIVE_SIGMAS, *,
                          truncate: float = DEFAULT_TRUNCATE):
    """Plain NumPy reference of :func:`filter_bank` (dense weight matrices, float64).

    Builds the renormalised weight matrices ``A_y (H×H)`` and ``A_x (W×W)`` explicitly and
    returns ``A_y · mean · A_xᵀ`` and ``A_y∘A_y · mean_var · (A_x∘A_x)ᵀ`` per channel.
    Slow (O(H² W + H W²)); for tests and small images.
    """
    m, v, sig = _check_bank_input(mean, mean_var, sigmas, truncate)
    m64 = m.astype(np.float64).reshape(m.shape[0], m.shape[1], -1)
    v64 = v.astype(np.float64).reshape(m64.shape)
    vals, vars_ = [], []
    for s in sig:
        if s == 0.0:
            vals.append(m64)
            vars_.append(v64)
            continue
        ay = _weight_matrix(m.shape[0], s, truncate)
        ax = _weight_matrix(m.shape[1], s, truncate)
        vals.append(np.einsum("yq,qxc,px->ypc", ay, m64, ax))
        vars_.append(np.einsum("yq,qxc,px->ypc", ay ** 2, v64, ax ** 2))
    shape = (len(sig),) + m.shape
    return np.stack(vals).reshape(shape), np.stack(vars_).reshape(shape)
