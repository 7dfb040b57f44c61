"""Least-squares combination of independent and correlated pixel estimates.

Back, Hua, Hachisuka and Moon 2020 [1]_ combine an image of *independent* pixel
estimates ``y`` (a path-traced render: the pixels use disjoint samples) with an image of
*correlated* estimates ``z`` of the same picture (a denoised image, a gradient-domain
reconstruction, correlated sampling).  For a pixel ``c`` and a neighbour ``i`` the
difference ``z_c − z_i`` is a low-noise estimate of ``μ_c − μ_i``, so
``y_i + z_c − z_i`` is one more estimate of ``μ_c`` (Eq. 3); a weighted average of all of
them is the *combination kernel*:

* :func:`combine` — Eq. 8 (single buffer), the exact minimiser of the weighted least
  squares of Eq. 6;
* :func:`combine_multi` — Eq. 14 for ``B`` sample bins (minimiser of Eq. 13);
* :func:`combine_boosting` — Eq. 15, the same estimator written as boosting:
  ``z_c`` plus a normalised filter of the residual ``y − z``;
* :func:`combine_bias_variance` — its bias (Eq. 10) and variance (Eq. 11) for fixed
  weights, optionally with the cross-covariance of ``y`` and ``z`` that Eq. 11 omits;
* weight builders: :func:`uniform_weights`, :func:`gaussian_weights` and
  :func:`statistical_weights` (classical weights that minimise Eq. 10² + Eq. 11 from
  estimated moments — the paper uses a network instead; this module only needs the
  weights);
* moment helpers: :func:`filter_covariance` (exact covariances of a linear filter of an
  independent image) and :func:`buffer_moments` (covariances estimated from ``B``
  independent sample bins).

Window convention (the one of :func:`statmc.analytic.apply_kernels`).  Weights are
``(H, W, B, k, k)`` with odd ``k``, ``r = k // 2``; tap ``(dy, dx)`` of pixel ``(y, x)``
is the neighbour ``(y + dy − r, x + dx − r)``, the centre tap ``(r, r)`` holds ``w_c``.
Taps outside the image are dropped and ``W_c`` sums the weights of the taps *inside* the
image, i.e. Eq. 8 is applied exactly to the neighbourhood clipped to the image.
Equivalently, for one buffer,

``combine(y, z, w) = z + apply_kernels(w, y − z) / apply_kernels(w, 1)``.

The same weights serve every channel.  Eq. 8 is invariant to a common scale of a
pixel's weights.

References
----------
.. [1] J. Back, B.-S. Hua, T. Hachisuka, B. Moon. "Deep Combiner for Independent and
   Correlated Pixel Estimates". ACM Trans. Graph. 39(6), 242, 2020.
   https://doi.org/10.1145/3414685.3417847
"""

from __future__ import annotations

import numpy as np

from . import _combine_kernels as _ck
from ._stencil_kernels import add_neighbour_products_sum, shift_slices
from .errors import (InputError, as_bool, as_float_array, as_number, as_rng, check_finite,
                     check_nonempty, check_nonnegative, check_overflow)

__all__ = [
    "combine", "combine_multi", "combine_boosting",
    "uniform_weights", "gaussian_weights", "statistical_weights",
    "combine_bias_variance", "filter_covariance", "buffer_moments",
    "denoiser_moments", "combine_denoised", "combine_bins", "combine_bin_images",
]

_BIAS_MODES = ("estimate", "pairs", "zero")
_METHODS = ("coherent", "diagonal", "full")

#: The largest magnitudes :func:`statistical_weights` accepts: ``VALUE_LIMIT`` in the
#: images ``y``, ``z`` and ``z_bias``, ``MOMENT_LIMIT`` in ``var_y``, ``cov_z`` and
#: ``cov_yz``.  The weights square differences of four image values (``δ² <= 16 max|y,
#: z|²``) and add up to 14 moments per term, then sum such terms over the bias box and the
#: channels: below these limits a term stays under 1.4e291, so sums of up to 1e17 terms
#: stay finite in float64 (max 1.8e308).  Above them squares overflowed to Inf and the
#: weights came out wrong (the compiled kernel all zeros, the NumPy reference ignoring
#: the bias), so such input is refused.  A common scale does not change the weights
#: (``y, z, z_bias`` times ``s``, the moments times ``s²``), so rescaling is the fix.
VALUE_LIMIT = 1e140
MOMENT_LIMIT = 1e290


# =========================================================================== validation
def _check_limit(name, a, limit):
    """:func:`check_finite`, and ``|a| <= limit`` (see ``VALUE_LIMIT``), in one min/max pass."""
    if a is None or a.size == 0:
        return
    lo, hi = float(np.min(a)), float(np.max(a))
    if -limit <= lo and hi <= limit:
        return
    check_finite(name, a)
    big = max(-lo, hi)
    moment = limit == MOMENT_LIMIT
    ratio = np.log10(big / limit) / (2.0 if moment else 1.0)
    s = 10.0 ** -np.ceil(ratio + 1e-9)
    raise InputError(
        f"`{name}` holds values up to {big:.3g} in magnitude; the statistical weights accept "
        f"at most {VALUE_LIMIT:.0e} in `y`, `z` and `z_bias` and {MOMENT_LIMIT:.0e} in the "
        "moments `var_y` (`mean_var`), `cov_z` and `cov_yz` (their squares and sums must "
        "stay finite in float64).  The weights do not change when the images are scaled by "
        f"s and the moments by s²: rescale the input (e.g. s = {s:.0e}).")


#: Black-box denoisers get float32 copies of the images (see ``_denoise``).
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _check_float32_range(name, a):
    """``|a|`` within float32's range, for an image whose float32 copy goes to a denoiser
    (larger values would reach it as Inf); ``a`` is finite (:func:`_check_limit` first)."""
    big = max(-float(np.min(a)), float(np.max(a))) if a.size else 0.0
    if big > _FLOAT32_MAX:
        raise InputError(
            f"`{name}` holds values up to {big:.3g} in magnitude; the denoiser is called on "
            f"float32 images, which hold at most {_FLOAT32_MAX:.2g}: rescale the input.")


def _buffers(name, a, *, multi):
    """``a`` as ``(B, H, W, C)`` (float32/float64 kept) and whether a channel axis was added."""
    arr = as_float_array(name, a, ndim=(3, 4) if multi else (2, 3))
    check_nonempty(name, arr, "image (or stack of images)")
    squeeze = arr.ndim == (3 if multi else 2)
    if squeeze:
        arr = arr[..., None]
    if not multi:
        arr = arr[None]
    check_finite(name, arr)
    return np.ascontiguousarray(arr), squeeze


def _pair(y_name, y, z_name, z, *, multi):
    ys, squeeze = _buffers(y_name, y, multi=multi)
    zs, _ = _buffers(z_name, z, multi=multi)
    if zs.shape != ys.shape:
        what = "(B, H, W, C) buffers" if multi else "(H, W, C) images of the same picture"
        raise InputError(f"`{z_name}` must have the shape of `{y_name}` {tuple(np.shape(y))}; "
                         f"got {tuple(np.shape(z))}.  Both are {what}.")
    dtype = np.result_type(ys.dtype, zs.dtype)   # one dtype: fewer compiled variants
    return ys.astype(dtype, copy=False), zs.astype(dtype, copy=False), squeeze


def _weights(weights, B, H, W, *, multi, name="weights"):
    """Weights as ``(H, W, B, k, k)`` float32/float64 (no copy when already so)."""
    w = np.asarray(weights)
    if w.dtype == object or np.iscomplexobj(w) \
            or not (np.issubdtype(w.dtype, np.number) or w.dtype == bool):
        # complex weights lost their imaginary part with only numpy's ComplexWarning
        raise InputError(f"`{name}` must be a real numeric array; got dtype {w.dtype}.")
    if w.dtype not in (np.float32, np.float64):
        w = w.astype(np.float64)
    given = w.shape
    if w.ndim == 4 and not multi:
        w = w[:, :, None]
    want = "(H, W, B, k, k)" if multi else "(H, W, k, k) or (H, W, 1, k, k)"
    if w.ndim != 5 or w.shape[3] != w.shape[4]:
        raise InputError(f"`{name}` must have shape {want} with square k x k windows; "
                         f"got {given}.")
    if w.shape[:2] != (H, W):
        raise InputError(f"`{name}` must have one window per pixel, leading shape (H, W) = "
                         f"{(H, W)}; got {given}.")
    if w.shape[2] != B:
        if multi:
            raise InputError(f"`{name}` must have B = {B} buffers on axis 2 to match the "
                             f"{B} buffers of `ys`/`zs`; got weights of shape {given}.")
        raise InputError(f"`{name}` holds B = {w.shape[2]} buffers (shape {given}) but "
                         "`combine` takes one; use `combine_multi(ys, zs, weights)` with "
                         f"ys, zs of shape ({w.shape[2]}, H, W, C).")
    if w.shape[3] % 2 == 0:
        raise InputError(f"`{name}` must have an odd window size k (a centre tap); got "
                         f"k = {w.shape[3]} (shape {given}).")
    return w


def _weight_sums_row(w, y):
    """``W_c`` of every pixel of row ``y`` (taps inside the image only), float64."""
    H, W, B, k, _ = w.shape
    r = k // 2
    out = np.zeros(W)
    for dy in range(max(0, r - y), min(k, H - y + r)):
        for dx in range(k):
            x0, x1 = max(0, r - dx), min(W, W + r - dx)
            if x1 > x0:
                out[x0:x1] += w[y, x0:x1, :, dy, dx].astype(np.float64).sum(axis=-1)
    return out


def _raise_bad(w, bad):
    n = int(bad.sum())
    y = int(np.flatnonzero(bad)[0])
    sums = _weight_sums_row(w, y)
    x = int(np.flatnonzero(~np.isfinite(sums) | (sums == 0))[0]) if (
        ~np.isfinite(sums) | (sums == 0)).any() else 0
    raise InputError(
        f"`weights` must be finite and sum to a nonzero W_c over the taps inside the image "
        f"at every pixel; {n} pixel(s) fail, the first at (row {y}, column {x}) with "
        f"W_c = {sums[x]:.4g}.  Use positive weights (e.g. a softmax or exp of network "
        "outputs).")


def _run(ys, zs, w, squeeze):
    B, H, W, C = ys.shape
    dtype = np.result_type(ys.dtype, zs.dtype)
    out = np.empty((H, W, C), dtype)
    bad = _ck.combine_numba(w, ys, zs, out)
    if bad.any():
        _raise_bad(w, bad)
    return out[..., 0] if squeeze else out


# =========================================================================== combination
def combine(y, z, weights):
    """Combine independent and correlated pixel estimates (Eq. 8 of [1]_).

    Parameters
    ----------
    y : (H, W, C) or (H, W) ndarray
        Independent pixel estimates (e.g. a path-traced image).
    z : ndarray like ``y``
        Correlated pixel estimates of the same picture (e.g. the denoised ``y``).
    weights : (H, W, k, k) or (H, W, 1, k, k) ndarray
        Per-pixel window weights (odd ``k``), float32 or float64, any strides (a fixed
        window may be ``np.broadcast_to(g, (H, W, k, k))``).  The centre tap is ``w_c``.

    Returns
    -------
    out : ndarray like ``y``
        ``β̂_c = (w_c y_c + Σ_i w_i y_i + Σ_i w_i (z_c − z_i)) / W_c`` with
        ``W_c = w_c + Σ_i w_i`` over the neighbours inside the image (see the module
        docstring for the window convention).  float32 if ``y`` and ``z`` are float32,
        else float64; accumulation is in float64.

    Raises
    ------
    InputError
        If ``z`` and ``y`` differ in shape, the weights do not have one ``k x k`` window
        per pixel (or hold several buffers), or a pixel's weights are non-finite or sum
        to zero.

    Notes
    -----
    Eq. 8 is the exact minimiser of Eq. 6,
    ``J_c = ½ w_c (y_c − β_c)² + Σ_i w_i (y_i − β_i)² + Σ_i w_i ((z_c − z_i) − (β_c − β_i))²``,
    over ``β_c`` and all ``β_i`` (for positive weights ``J_c`` is a convex quadratic).
    Setting ``∂J_c/∂β_i = −2 w_i (y_i − β_i) + 2 w_i ((z_c − z_i) − (β_c − β_i)) = 0``
    gives ``β_i = ½ (y_i − z_c + z_i + β_c)``, hence the residual
    ``(z_c − z_i) − (β_c − β_i) = ½ (y_i + z_c − z_i − β_c)``; then
    ``∂J_c/∂β_c = −w_c (y_c − β_c) − Σ_i w_i (y_i + z_c − z_i − β_c) = 0`` is Eq. 8.
    The gradients printed as Eq. 7 are the negative of ``∂J_c/∂β_c`` and half of
    ``∂J_c/∂β_i``; their zero sets, and so Eq. 8, are unaffected (an erratum checked in
    ``tests/test_combine.py``).  Signed weights are accepted (the combination is still
    the affine estimator of Eq. 4), but the least-squares reading needs ``w ≥ 0``.

    Examples
    --------
    >>> import numpy as np
    >>> from statmc.combine import combine, uniform_weights
    >>> y = np.full((4, 5, 3), 2.0); z = y + 1.0      # z off by a constant: cancels
    >>> np.allclose(combine(y, z, uniform_weights(4, 5, 1, 3)), 2.0)
    True
    """
    ys, zs, squeeze = _pair("y", y, "z", z, multi=False)
    w = _weights(weights, 1, *ys.shape[1:3], multi=False)
    return _run(ys, zs, w, squeeze)


def combine_multi(ys, zs, weights):
    """Multi-buffered combination kernel (Eq. 14 of [1]_).

    Parameters
    ----------
    ys : (B, H, W, C) or (B, H, W) ndarray
        Independent estimates per sample bin: ``ys[b]`` is the mean of the ``b``-th
        disjoint subset of each pixel's samples (sample binning, §4.4 of [1]_).
    zs : ndarray like ``ys``
        Correlated estimates per bin, e.g. ``zs[b] = denoise(ys[b])``.
    weights : (H, W, B, k, k) ndarray
        Weights ``w_{i,b}`` per pixel, bin and tap (float32 or float64, any strides).

    Returns
    -------
    out : (H, W, C) or (H, W) ndarray
        ``β̂_c = Σ_b [w_{c,b} y_{c,b} + Σ_i w_{i,b} y_{i,b} + Σ_i w_{i,b} (z_{c,b} − z_{i,b})] / W_c``
        with ``W_c = Σ_b (w_{c,b} + Σ_i w_{i,b})`` over the taps inside the image: the
        exact minimiser of Eq. 13 (derived as for :func:`combine`, with
        ``β_i = ½ (Σ_b w_{i,b}(y_{i,b} − z_{c,b} + z_{i,b}) / Σ_b w_{i,b} + β_c)``).
        A bin whose centre pixel holds an outlier can be down-weighted as a whole.

    Raises
    ------
    InputError
        If ``zs`` differs from ``ys`` in shape, the weights' ``B`` (axis 2) differs from
        the number of buffers, or a pixel's weights are non-finite or sum to zero.
    """
    ysa, zsa, squeeze = _pair("ys", ys, "zs", zs, multi=True)
    w = _weights(weights, *ysa.shape[:3], multi=True)
    return _run(ysa, zsa, w, squeeze)


def combine_boosting(y, z, weights):
    """The combination kernel in boosting form (Eq. 15 of [1]_).

    ``β̂_c = z_c + (1/W_c) Σ_{i ∈ Ω'_c} w_i (y_i − z_i)``, where ``Ω'_c`` includes ``c``:
    the correlated image plus a normalised filter of its residual ``y − z``.  This is
    algebraically Eq. 8 (the centre term of Eq. 8's difference sum vanishes); it is
    computed here by a separate path (two :func:`statmc.analytic.apply_kernels` passes)
    so the identity can be tested.  Typical boosting uses the denoiser's own kernel as
    ``weights``.

    Parameters and return value as in :func:`combine`; the output is float64 unless
    ``y`` and ``z`` are float32.
    """
    from .analytic import apply_kernels  # the shared kernel convention

    ys, zs, squeeze = _pair("y", y, "z", z, multi=False)
    w = _weights(weights, 1, *ys.shape[1:3], multi=False)[:, :, 0]
    H, W, k = w.shape[0], w.shape[1], w.shape[2]
    inside = np.stack([_valid(H, W, dy - k // 2, dx - k // 2)
                       for dy in range(k) for dx in range(k)], axis=-1).reshape(H, W, k, k)
    w = np.where(inside > 0, w, 0.0)                # outside taps are never used (as in Eq. 8)
    # apply_kernels would name them `kernels`, not the caller's `weights`; zero sums
    # counted too, as _raise_bad names the first pixel that fails either way
    bad = ~np.isfinite(w).all(axis=(2, 3)) | (w.sum(axis=(2, 3)) == 0)
    if bad.any():
        _raise_bad(w[:, :, None], bad.sum(axis=1))
    y64, z64 = ys[0].astype(np.float64), zs[0].astype(np.float64)
    num = apply_kernels(w, y64 - z64)
    den = apply_kernels(w, np.ones(y64.shape[:2]))
    bad = ~np.isfinite(den) | (den == 0)
    if bad.any():
        _raise_bad(w[:, :, None], bad.sum(axis=1))
    out = (z64 + num / den[..., None]).astype(np.result_type(ys.dtype, zs.dtype), copy=False)
    return out[..., 0] if squeeze else out


# =========================================================================== weights
def _check_size(size):
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1 or size % 2 == 0:
        raise InputError(f"`size` (the window width k) must be an odd integer >= 1; got {size!r}.")
    return int(size)


def _check_hwb(height, width, buffers):
    for name, v in (("height", height), ("width", width), ("buffers", buffers)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"`{name}` must be an integer >= 1; got {v!r}.")
    return int(height), int(width), int(buffers)


def uniform_weights(height, width, buffers, size):
    """Uniform weights ``w_{i,b} = 1`` (the baseline of Fig. 3c of [1]_).

    Returns
    -------
    weights : (height, width, buffers, size, size) float32 ndarray
        A read-only broadcast view (no memory per pixel); ``.copy()`` it to edit.
    """
    h, w, b = _check_hwb(height, width, buffers)
    k = _check_size(size)
    return np.broadcast_to(np.ones((b, k, k), np.float32), (h, w, b, k, k))


def gaussian_weights(height, width, buffers, size, sigma):
    """Spatial Gaussian weights ``exp(−(Δy² + Δx²) / (2σ²))`` of the tap offset.

    The same for every pixel and bin, normalised to sum to one over the full window
    (the scale is irrelevant to Eq. 8/14).

    Returns
    -------
    weights : (height, width, buffers, size, size) float32 ndarray
        A read-only broadcast view.
    """
    h, w, b = _check_hwb(height, width, buffers)
    k = _check_size(size)
    s = as_number("sigma", sigma, lo=0.0, lo_open=True)
    ax = np.arange(k) - k // 2
    g = np.exp(-(ax[:, None] ** 2 + ax[None, :] ** 2) / (2.0 * s * s))
    g = np.broadcast_to(g / (b * g.sum()), (b, k, k)).astype(np.float32)
    return np.broadcast_to(g, (h, w, b, k, k))


# =========================================================================== moments
def _shift(a, oy, ox):
    """``out[p] = a[p + (oy, ox)]`` where that pixel exists, else 0 (leading axes H, W)."""
    H, W = a.shape[:2]
    out = np.zeros_like(a)
    dst, src = shift_slices(H, W, oy, ox)
    out[dst] = a[src]
    return out


def _valid(H, W, oy, ox):
    return _shift(np.ones((H, W)), oy, ox)


class _Moments:
    """Second moments of ``(y, z)`` per bin, read through covariance stencils.

    A stencil ``S`` of size ``m`` (``R = m // 2``) stores ``S[p, R + vy, R + vx, c] =
    cov(a_p, b_{p + v})``; offsets beyond ``R`` are uncorrelated (zero).
    """

    def __init__(self, var_y, cov_z, cov_yz):
        self.var_y = var_y        # (B, H, W, C)
        self.cov_z = cov_z        # (B, H, W, m, m, C)
        self.cov_yz = cov_yz      # (B, H, W, m', m', C) or None
        self.B, self.H, self.W, self.C = var_y.shape

    @staticmethod
    def _at(S, b, p, v):
        """``S[b]`` at pixel ``c + p``, offset ``v``, for every pixel ``c`` (zero outside)."""
        R = S.shape[3] // 2
        vy, vx = v
        if abs(vy) > R or abs(vx) > R:
            return None
        plane = S[b, :, :, R + vy, R + vx]
        return plane if p == (0, 0) else _shift(plane, *p)

    def cz(self, b, p, v):
        """``cov(z_{c+p}, z_{c+p+v})`` or None when beyond the stencil."""
        return self._at(self.cov_z, b, p, v)

    def cyz(self, b, p, v):
        """``cov(y_{c+p}, z_{c+p+v})`` or None (no cross-covariance given, or beyond)."""
        return None if self.cov_yz is None else self._at(self.cov_yz, b, p, v)

    def vy(self, b, p):
        return self.var_y[b] if p == (0, 0) else _shift(self.var_y[b], *p)

    def pair(self, b, ot, os_):
        """``Cov(e_t, e_s)`` of the estimates ``e_t = y_t + z_c − z_t`` (t, s offsets)."""
        q = np.zeros((self.H, self.W, self.C))
        if ot == os_:
            q += self.vy(b, ot)
        if ot != (0, 0) and os_ != (0, 0):
            # Cov(z_c − z_t, z_c − z_s) = V_c − C(c,s) − C(c,t) + C(t,s)
            for sign, p, v in ((1, (0, 0), (0, 0)), (-1, (0, 0), os_), (-1, (0, 0), ot),
                               (1, ot, (os_[0] - ot[0], os_[1] - ot[1]))):
                c = self.cz(b, p, v)
                if c is not None:
                    q += sign * c
        # Cov(y_t, z_c − z_s) + Cov(y_s, z_c − z_t)
        for a, o in ((ot, os_), (os_, ot)):
            for sign, v in ((1, (-a[0], -a[1])), (-1, (o[0] - a[0], o[1] - a[1]))):
                c = self.cyz(b, a, v)
                if c is not None:
                    q += sign * c
        return q


def _stencil(name, a, B, H, W, C, *, required=True, limit=None):
    """A covariance stencil as a ``(B, H, W, m, m, C)`` view (``(H, W, C)``: variances only);
    ``limit``: see :func:`_check_limit`."""
    if a is None:
        if not required:
            return None
        raise InputError(f"`{name}` is missing: pass the covariances of the correlated "
                         f"image as a stencil (H, W, m, m, C) = ({H}, {W}, m, m, {C}), e.g. "
                         "from `filter_covariance` or `buffer_moments`, or its variances "
                         f"({H}, {W}, {C}) if its pixels are uncorrelated.")
    arr = as_float_array(name, a, ndim=(3, 5, 6), dtype=np.float64)
    if limit is None:
        check_finite(name, arr)
    else:
        _check_limit(name, arr, limit)
    if arr.ndim == 3:
        arr = arr[:, :, None, None, :]
    if arr.ndim == 5:
        arr = arr[None]
    m = arr.shape[3]
    ok = (arr.shape[0] in (1, B) and arr.shape[1:3] == (H, W) and arr.shape[3] == arr.shape[4]
          and m % 2 == 1 and arr.shape[5] == C)
    if not ok:
        raise InputError(f"`{name}` must be a covariance stencil of shape (H, W, m, m, C) = "
                         f"({H}, {W}, m, m, {C}) with odd m (or ({B}, {H}, {W}, m, m, {C}) "
                         f"per buffer, or ({H}, {W}, {C}) variances); got {np.shape(a)}.")
    return np.broadcast_to(arr, (B,) + arr.shape[1:])


def _image_moment(name, a, B, H, W, C, *, required=True, nonneg=False, limit=None):
    if a is None:
        if not required:
            return None
        raise InputError(f"`{name}` is missing: pass the variance of the mean of each "
                         f"independent pixel estimate, shape ({H}, {W}, {C}) (e.g. "
                         "`PixelStats.mean_var`), or one per buffer "
                         f"({B}, {H}, {W}, {C}).")
    arr = as_float_array(name, a, ndim=(3, 4), dtype=np.float64)
    if limit is None:
        check_finite(name, arr)
    else:
        _check_limit(name, arr, limit)
    if nonneg:
        check_nonnegative(name, arr)
    if arr.ndim == 3:
        arr = arr[None]
    if arr.shape[0] not in (1, B) or arr.shape[1:] != (H, W, C):
        raise InputError(f"`{name}` must have shape ({H}, {W}, {C}) or ({B}, {H}, {W}, {C}) "
                         f"to match the weights and buffers; got {np.shape(a)}.")
    return np.broadcast_to(arr, (B, H, W, C))


def _offsets(k):
    r = k // 2
    return [(dy - r, dx - r) for dy in range(k) for dx in range(k)]


def combine_bias_variance(weights, var_y, cov_z, *, z_bias=None, y_bias=None, cov_yz=None):
    """Bias (Eq. 10) and variance (Eq. 11) of the combined estimate for fixed weights.

    Parameters
    ----------
    weights : (H, W, k, k) or (H, W, B, k, k) ndarray
        The weights given to :func:`combine` / :func:`combine_multi`.
    var_y : (H, W, C) or (B, H, W, C) ndarray
        Variance of each independent estimate ``y_{i,b}`` (the variance of the *mean*:
        ``PixelStats.mean_var`` of that bin); one array is shared by all bins.
    cov_z : (H, W, m, m, C), (B, H, W, m, m, C) or (H, W, C) ndarray
        Covariance stencil of the correlated estimates, ``cov_z[p, R + v] =
        cov(z_p, z_{p+v})`` with ``R = m // 2`` (:func:`filter_covariance`,
        :func:`buffer_moments`); offsets beyond ``R`` count as uncorrelated, so
        ``m = 2k − 1`` is needed for the exact Eq. 11 when ``z`` is correlated that far.
        ``(H, W, C)`` means variances of uncorrelated pixels.
    z_bias : ndarray like ``var_y``, optional
        ``E[z] − μ``; then ``E[ε_ci] = z_bias_c − z_bias_i``.  Default 0.
    y_bias : ndarray like ``var_y``, optional
        ``E[y] − μ`` (the paper assumes 0, the default).
    cov_yz : ndarray like ``cov_z`` (stencil), optional
        ``cov_yz[p, R + v] = cov(y_p, z_{p+v})``.  Eq. 11 assumes ``y`` independent of
        ``z``; that fails when ``z`` is computed from ``y`` (a denoised ``y``), and then
        this term is needed (:func:`filter_covariance` with ``cross=True``).

    Returns
    -------
    bias, var : (H, W, C) float64 ndarrays
        Eq. 10, ``bias_c = (1/W_c) Σ_b Σ_t w_{t,b} (y_bias_t + z_bias_c − z_bias_t)``
        (``= (1/W_c) Σ_i w_i E[ε_ci]`` for unbiased ``y``), and Eq. 11 summed over bins,
        ``var_c = (1/W_c²) Σ_b [Σ_t w_t² var(y_t) + S² var(z_c) + Σ_{i,j≠c} w_i w_j
        cov(z_i, z_j) − 2 S Σ_{i≠c} w_i cov(z_c, z_i) + 2 Σ_t w_t Σ_s w_s (cov(y_t, z_c) −
        cov(y_t, z_s))]`` with ``S = Σ_{i≠c} w_i`` (the last term only with
        ``cov_yz``).  Bins are taken as independent (disjoint samples).

    Notes
    -----
    For weights that do not depend on the data both expressions are exact; the paper's
    "≈" accounts for weights computed from the same data.  The double sum over taps
    costs ``O(k² min(k, m)²)`` image operations per bin, so this is an analysis tool
    for small windows or crops, not a per-frame routine.
    """
    w = np.asarray(weights)
    multi = w.ndim == 5
    if w.ndim not in (4, 5):
        raise InputError(f"`weights` must have shape (H, W, k, k) or (H, W, B, k, k); got {w.shape}.")
    B = w.shape[2] if multi else 1
    H, W = w.shape[:2]
    C = _channels("var_y", var_y)
    w = _weights(w, B, H, W, multi=multi)
    mom = _Moments(_image_moment("var_y", var_y, B, H, W, C, nonneg=True),
                   _stencil("cov_z", cov_z, B, H, W, C),
                   _stencil("cov_yz", cov_yz, B, H, W, C, required=False))
    zb = _image_moment("z_bias", z_bias, B, H, W, C, required=False)
    yb = _image_moment("y_bias", y_bias, B, H, W, C, required=False)
    k = w.shape[3]
    r = k // 2
    offs = _offsets(k)
    Wtot = np.zeros((H, W))
    bias = np.zeros((H, W, C))
    var = np.zeros((H, W, C))
    for b in range(B):
        # taps outside the image are never read (a NaN there stays out of the sums)
        wb = {o: np.where(_valid(H, W, *o) > 0, w[:, :, b, o[0] + r, o[1] + r], 0.0)
              .astype(np.float64) for o in offs}
        bad = np.zeros((H, W), bool)
        for x in wb.values():          # per tap: a sum of huge finite weights overflows
            bad |= ~np.isfinite(x)
        if bad.any():
            py, px = (int(i[0]) for i in np.nonzero(bad))
            raise InputError(f"`weights` must be finite at the taps inside the image; "
                             f"{int(bad.sum())} pixel(s) of buffer {b} fail, the first at "
                             f"(row {py}, column {px}).")
        Wb = sum(wb.values())
        S = Wb - wb[(0, 0)]
        Wtot += Wb
        # Eq. 10 (plus an optional bias of y)
        if zb is not None:
            for o in offs:
                if o != (0, 0):
                    bias += wb[o][..., None] * (zb[b] - _shift(zb[b], *o))
        if yb is not None:
            for o in offs:
                bias += wb[o][..., None] * _shift(yb[b], *o)
        # Eq. 11
        v = np.zeros((H, W, C))
        for o in offs:
            v += (wb[o] ** 2)[..., None] * mom.vy(b, o)
        v += (S ** 2)[..., None] * mom.cz(b, (0, 0), (0, 0))
        for oi in offs:
            if oi == (0, 0):
                continue
            c_ci = mom.cz(b, (0, 0), oi)
            if c_ci is not None:
                v -= 2.0 * (S * wb[oi])[..., None] * c_ci
            for oj in offs:
                if oj == (0, 0):
                    continue
                c_ij = mom.cz(b, oi, (oj[0] - oi[0], oj[1] - oi[1]))
                if c_ij is not None:
                    v += (wb[oi] * wb[oj])[..., None] * c_ij
        # Cross term 2 Cov(Σ_t w_t y_t, Σ_s w_s (z_c − z_s)), absent from Eq. 11.
        if mom.cov_yz is not None:
            for ot in offs:
                for os_ in offs:
                    for sign, vv in ((1, (-ot[0], -ot[1])), (-1, (os_[0] - ot[0], os_[1] - ot[1]))):
                        c = mom.cyz(b, ot, vv)
                        if c is not None:
                            v += 2.0 * sign * (wb[ot] * wb[os_])[..., None] * c
        var += v
    with np.errstate(divide="ignore", invalid="ignore"):
        return bias / Wtot[..., None], var / (Wtot ** 2)[..., None]


def _channels(name, a):
    if a is None:
        raise InputError(f"`{name}` is missing: pass the variance of the mean of each "
                         "independent pixel estimate (e.g. `PixelStats.mean_var`).")
    shape = np.shape(a)
    if len(shape) not in (3, 4):
        raise InputError(f"`{name}` must have shape (H, W, C) or (B, H, W, C); got {shape}.")
    return shape[-1]


def _box_mean(a, valid, radius):
    """Mean of ``a`` over the ``(2 radius + 1)²`` box, counting only ``valid`` pixels."""
    if radius == 0:
        return a
    from scipy.ndimage import uniform_filter

    size = (2 * radius + 1, 2 * radius + 1) + (1,) * (a.ndim - 2)
    num = uniform_filter(a * valid.reshape(valid.shape + (1,) * (a.ndim - 2)), size,
                         mode="constant")
    den = uniform_filter(valid, 2 * radius + 1, mode="constant")
    with np.errstate(divide="ignore", invalid="ignore"):
        out = num / den.reshape(den.shape + (1,) * (a.ndim - 2))
    return np.where(np.isfinite(out), out, 0.0)


def _box_mean_loo(q1, q2, valid, radius, o):
    """:func:`_box_mean` of ``q1`` and ``q2`` leaving out the centres ``c`` and ``c − o``
    (the two whose ``δ`` for tap offset ``o`` contains ``y_c``)."""
    from scipy.ndimage import uniform_filter

    n = 2 * radius + 1
    den = uniform_filter(valid, n, mode="constant") * (n * n) - valid
    nums = [uniform_filter(q, (n, n, 1), mode="constant") * (n * n) - q for q in (q1, q2)]
    if abs(o[0]) <= radius and abs(o[1]) <= radius:
        back = _shift(valid, -o[0], -o[1])
        den = den - back
        nums = [a - _shift(q, -o[0], -o[1]) for a, q in zip(nums, (q1, q2))]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = [a / den[..., None] for a in nums]
    return [np.where(np.isfinite(a) & (den[..., None] > 0.5), a, 0.0) for a in out]


def _delta_var(mom, b, o):
    """``Var(δ)`` of ``δ = (z_c − z_t) − (y_c − y_t)`` for the tap at offset ``o``."""
    z = np.zeros((mom.H, mom.W, mom.C))
    for sign, p, v in ((1, (0, 0), (0, 0)), (1, o, (0, 0)), (-2, (0, 0), o)):
        c = mom.cz(b, p, v)
        if c is not None:
            z += sign * c
    v = mom.vy(b, (0, 0)) + mom.vy(b, o) + z
    # − 2 Cov(z_c − z_t, y_c) + 2 Cov(z_c − z_t, y_t)
    for sign, p, vv in ((-2, (0, 0), (0, 0)), (2, (0, 0), o), (2, o, (-o[0], -o[1])), (-2, o, (0, 0))):
        c = mom.cyz(b, p, vv)
        if c is not None:
            v += sign * c
    return v


def _bias_vectors(ys, zs, mom, zb, z_bias, k, patch, loo=False):
    """Per-tap bias ``E[e_t] − μ_c`` of the estimates, ``{offset: (B, H, W, C)}``, and
    the per-tap squared bias to use, ``{offset: (B, H, W, C)}``."""
    B, H, W, C = ys.shape
    mean, sq = {}, {}
    for o in _offsets(k):
        if o == (0, 0):
            mean[o] = sq[o] = np.zeros((B, H, W, C))
            continue
        if isinstance(z_bias, str) and z_bias == "zero":
            mean[o] = sq[o] = np.zeros((B, H, W, C))
        elif isinstance(z_bias, str):  # "estimate", "pairs"
            valid = _valid(H, W, *o)
            d = np.stack([(zs[b] - _shift(zs[b], *o)) - (ys[b] - _shift(ys[b], *o))
                          for b in range(B)])
            q1 = (d * valid[..., None]).mean(axis=0)
            if z_bias == "pairs":       # mean of δ_b δ_b' over distinct bins b != b'
                sd = d.sum(axis=0)
                q2 = ((sd * sd - (d * d).sum(axis=0)) / (B * (B - 1))) * valid[..., None]
            else:
                dv = np.stack([_delta_var(mom, b, o) for b in range(B)])
                q2 = ((d * d - dv) * valid[..., None]).mean(axis=0)
            if loo:
                m, s2 = _box_mean_loo(q1, q2, valid, patch, o)
            else:
                m = _box_mean(q1, valid, patch)
                s2 = _box_mean(q2, valid, patch)
            mean[o] = np.broadcast_to(m, (B, H, W, C))
            sq[o] = np.broadcast_to(np.maximum(s2, 0.0), (B, H, W, C))
        else:
            e = np.stack([zb[b] - _shift(zb[b], *o) for b in range(B)])
            mean[o] = e
            sq[o] = e * e
    return mean, sq


def _tap_moments(mom, sq, k, B, H, W):
    """Per-tap ``Var(e_t)`` (channel mean), squared biases and validity, tap-major:
    ``(n, H, W)``, ``(n, H, W, C)``, ``(n, H, W)`` with ``n = B k²``, and the pixels that
    fall back (a tap inside the image with a non-finite ``Var(e_t)`` or squared bias;
    their moments are replaced by harmless ones, the weights by :func:`_to_weights`)."""
    offs = _offsets(k)
    n = B * len(offs)
    v = np.empty((n, H, W))
    b2 = np.empty((n, H, W, mom.C))
    valid = np.empty((n, H, W), bool)
    for b in range(B):
        for j, o in enumerate(offs):
            i = b * len(offs) + j
            v[i] = mom.pair(b, o, o).mean(axis=-1)      # Var(y_t + z_c − z_t)
            b2[i] = sq[o][b]
            valid[i] = _valid(H, W, *o) > 0
    with np.errstate(invalid="ignore", over="ignore"):
        t = v + b2.mean(axis=-1)
    bad = (valid & ~np.isfinite(t)).any(axis=0)
    if bad.any():
        v[:, bad], b2[:, bad], t[:, bad] = 1.0, 0.0, 1.0
    # floor: a zero-variance tap must not divide by zero (relative to the largest MSE)
    top = np.where(valid, t, 0.0).max(axis=0)
    v = np.where(valid, np.maximum(v, np.maximum(1e-12 * top, 1e-300)), np.inf)
    return v, b2, valid, bad


def _to_weights(a, valid, k, B, H, W, bad):
    """Normalised weights ``(H, W, B, k, k)``; the fallback where ``bad`` or where the
    weights do not sum to a positive finite number: ``1 / B`` on each bin's centre tap."""
    a = np.where(valid, np.maximum(a, 0.0), 0.0)
    tot = a.sum(axis=0)
    bad = bad | ~(np.isfinite(tot) & (tot > 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        a /= tot
    a = np.moveaxis(a.reshape(B, k, k, H, W), (3, 4), (0, 1)).astype(np.float32)
    a[bad] = 0.0
    a[bad, :, k // 2, k // 2] = np.float32(1.0 / B)
    return a


def _diagonal_weights(mom, sq, k, B, H, W):
    v, b2, valid, bad = _tap_moments(mom, sq, k, B, H, W)
    mse = v + b2.mean(axis=-1)
    # inverse-MSE weights, scaled by the smallest MSE so nothing overflows
    return _to_weights(mse.min(axis=0) / mse, valid, k, B, H, W, bad)


def _solve_or_nan(G, rhs):
    """``G⁻¹ rhs`` per pixel; NaN for a pixel whose ``G`` LAPACK finds singular."""
    try:
        return np.linalg.solve(G, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full(rhs.shape, np.nan)
        for p in np.ndindex(G.shape[:-2]):
            try:
                out[p] = np.linalg.solve(G[p], rhs[p])
            except np.linalg.LinAlgError:
                pass
        return out


def _coherent_weights(mom, sq, k, B, H, W, max_iter=20):
    """Minimise ``aᵀ(D + U Uᵀ)a`` s.t. ``Σa = 1, a ≥ 0``: Woodbury plus an active set.

    ``G = I + Σ d_i U_i U_iᵀ`` is positive definite; a pixel whose solve is nevertheless
    not finite (a numerically singular elimination) falls back (:func:`_to_weights`)."""
    v, b2, valid, bad = _tap_moments(mom, sq, k, B, H, W)
    C = b2.shape[-1]
    vmin = v.min(axis=0)
    d_inv = vmin / v                                     # D⁻¹ up to a per-pixel scale
    U = np.sqrt(b2 / (C * vmin[..., None]))              # (n, H, W, C), same scale
    active = valid.copy()
    eye = np.eye(C)
    for _ in range(max_iter):
        di = np.where(active, d_inv, 0.0)
        G = eye + np.einsum("nhwc,nhw,nhwd->hwcd", U, di, U, optimize=True)
        rhs = np.einsum("nhwc,nhw->hwc", U, di)
        sol = _solve_or_nan(G, rhs)
        fail = ~np.isfinite(sol).all(axis=-1)
        bad |= fail
        sol[fail] = 0.0                                   # the pixel falls back anyway
        a = di * (1.0 - np.einsum("nhwc,hwc->nhw", U, sol))
        neg = active & (a < 0)
        if not neg.any():
            break
        active &= ~neg
    return _to_weights(a, active, k, B, H, W, bad)


def _full_weights(mom, mean, k, B, H, W, ridge):
    offs = _offsets(k)
    n1 = len(offs)
    n = B * n1
    need = H * W * n * n * 8
    if need > 2 ** 30:
        raise InputError(f"`method='full'` needs an (H·W) x n x n system with n = B·k² = {n}, "
                         f"{need / 2 ** 30:.1f} GiB here; use method='diagonal', a smaller "
                         "`size`, or a crop.")
    M = np.zeros((H, W, n, n))
    for b in range(B):
        for i, ot in enumerate(offs):
            for j in range(i, n1):
                q = mom.pair(b, ot, offs[j]).mean(axis=-1)
                M[:, :, b * n1 + i, b * n1 + j] = q
                M[:, :, b * n1 + j, b * n1 + i] = q
    e = np.stack([mean[o][b] for b in range(B) for o in offs], axis=-1)     # (H, W, C, n)
    M += np.einsum("hwci,hwcj->hwij", e, e) / e.shape[2]
    valid = np.tile(np.stack([_valid(H, W, *o) for o in offs], axis=-1), (1, 1, B)) > 0
    eye = np.eye(n, dtype=bool)
    diag = np.einsum("hwii->hwi", M)
    scale = np.where(valid, diag, 0.0).sum(axis=-1) / valid.sum(axis=-1)
    scale = np.where(scale > 0, scale, 1.0)
    both = valid[..., :, None] & valid[..., None, :]
    M = np.where(both, M, 0.0)
    M = M + eye * np.where(valid, ridge * scale[..., None], 1.0)[..., None, :]
    a = _solve_or_nan(M, valid.astype(np.float64))     # NaN where M is singular (ridge 0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        a /= a.sum(axis=-1, keepdims=True)
        w = a.reshape(H, W, B, k, k).astype(np.float32)
    # the documented fallback, as for the other methods: 1 / B on each bin's centre tap
    bad = ~np.isfinite(w).all(axis=(2, 3, 4))
    w[bad] = 0.0
    w[bad, :, k // 2, k // 2] = np.float32(1.0 / B)
    return w


def _unbroadcast(a):
    """A moment broadcast over bins as its stored ``(1, ...)`` block (the kernel's wrapper
    makes it contiguous float64)."""
    if a is None:
        return None
    if a.shape[0] > 1 and a.strides[0] == 0:
        a = a[:1]
    return a


def _statistical_weights_compiled(ys, zs, mom, zb, z_bias, method, k, patch, loo, rows=None):
    """The numba path of :func:`statistical_weights` ("coherent", "diagonal"); ``rows``:
    see :func:`_statistical_weights`."""
    B, H, W, C = ys.shape
    if zb is not None:
        mode = _ck.BIAS_ARRAY
    else:
        mode = _ck.BIAS_ZERO if z_bias == "zero" else _ck.BIAS_ESTIMATE
    out = np.empty((H, W, B, k, k), np.float32)
    if rows is not None:                         # the rows not asked for: the identity
        for part in (out[:max(0, rows[0])], out[max(0, rows[1]):]):
            part[:] = 0.0
            part[:, :, :, k // 2, k // 2] = 1.0
    code = _ck.METHOD_COHERENT if method == "coherent" else _ck.METHOD_DIAGONAL
    _ck.statistical_weights_numba(ys, zs,
                                  _unbroadcast(mom.var_y), _unbroadcast(mom.cov_z),
                                  _unbroadcast(mom.cov_yz), _unbroadcast(zb), mode, code, k,
                                  patch, out, loo=loo, rows=rows,
                                  pairs=isinstance(z_bias, str) and z_bias == "pairs")
    return out


def statistical_weights(y, z, var_y, cov_z, size, *, method="coherent", z_bias="estimate",
                        cov_yz=None, patch=2, leave_centre_out=False, ridge=1e-9,
                        _reference=False):
    """Classical combination weights that minimise Eq. 10² + Eq. 11 of [1]_.

    The estimate Eq. 8/14 averages the per-tap estimates ``e_t = y_t + z_c − z_t``
    (``e_c = y_c``, one per tap and bin) of ``μ_c``.  For normalised weights ``a`` its
    error is ``aᵀ M a`` with ``M = Cov(e) + β βᵀ``: ``β_t`` is the bias of ``e_t`` (the
    ``E[ε_ci]`` of Eq. 10) and ``Cov(e)`` the matrix behind Eq. 11.  The three methods
    minimise models of ``M`` (the weights are then normalised; Eq. 8 is scale-free):

    * ``"coherent"`` (default): ``M ≈ D + |β||β|ᵀ`` with ``D = diag Var(e_t)``,
      ``Var(e_t) = var(y_t) + var(z_c) + var(z_t) − 2 cov(z_c, z_t)`` (``+ 2 cov(y_t,
      z_c) − 2 cov(y_t, z_t)`` with ``cov_yz``), minimised over ``a ≥ 0``.  The biases of
      neighbouring taps are taken to add up (the worst case; they usually share a sign
      near an edge a filter blurred), so biased taps cannot be averaged out.  Closed
      form by the Woodbury identity (a ``C x C`` solve per pixel for ``C`` channels)
      inside an active-set loop that drops taps with negative weight.
    * ``"diagonal"``: ``M ≈ diag(β² + Var(e))``, i.e. inverse-MSE weights
      ``w_t ∝ 1 / (β_t² + Var(e_t))`` — the classical rule for uncorrelated errors; it
      lets many mildly biased taps outvote the unbiased centre.
    * ``"full"``: the exact ``M`` with signed biases, minimised over all affine weights
      (``a = M⁻¹1 / 1ᵀM⁻¹1``, signs free): the exact minimiser of Eq. 10² + Eq. 11 when
      the moments are exact; ``O((B k²)³)`` per pixel, for small windows.  Negative
      weights keep Eq. 8 the affine estimator of Eq. 4.

    In all three a neighbour whose ``z`` is strongly correlated with ``z_c`` (small
    ``Var(z_c − z_t)``) and whose difference ``z_c − z_t`` is unbiased gets a large
    weight, and the centre gets ``1 / var(y_c)``.

    Parameters
    ----------
    y, z : (H, W, C) or (B, H, W, C) ndarray
        Independent and correlated estimates (one buffer, or ``B`` bins).
    var_y : ndarray like ``y`` or (H, W, C)
        Variance of each ``y`` estimate (``PixelStats.mean_var``, per bin).
    cov_z : (H, W, m, m, C), (B, H, W, m, m, C) or (H, W, C) ndarray
        Covariance stencil of ``z`` (see :func:`combine_bias_variance`).  ``m >= size``
        is enough for ``"coherent"``/``"diagonal"``; ``"full"`` uses offsets up to
        ``2 (size − 1)``.
    size : int
        Odd window width ``k``.
    method : {"coherent", "diagonal", "full"}
    z_bias : "estimate", "pairs", "zero" or ndarray like ``var_y``
        Bias of ``z``.  ``"estimate"`` (default) estimates the bias of ``z_c − z_t``
        without the truth from ``δ_t = (z_c − z_t) − (y_c − y_t)``, whose mean is that
        bias: ``β_t² ≈ mean(δ_t²) − Var(δ_t)`` over a ``(2 patch + 1)²`` box of centre
        pixels (and over bins), clamped at 0 — unbiased before the clamp, like the
        variance-cancelled distance of non-local means (``"full"`` uses the signed box
        mean of ``δ_t``).  ``"pairs"`` (``B >= 2`` independent bins): ``β_t²`` from the
        products of distinct bins, ``((Σ_b δ_{t,b})² − Σ_b δ_{t,b}²) / (B (B − 1))``
        (``E[δ_b δ_b'] = β_t²`` for ``b ≠ b'``), box-averaged and clamped the same way:
        unbiased without ``Var(δ_t)``, so neither the moments nor their errors enter the
        biases, and with a smaller spread than ``"estimate"`` (for ``B = 4`` and Gaussian
        ``δ``, a third of its variance when ``β = 0``).  ``"zero"``: unbiased ``z`` (e.g.
        GPT-L2).  An array: ``E[z] − μ`` (oracle or external estimate).
    cov_yz : stencil like ``cov_z``, optional
        Cross-covariance of ``y`` and ``z`` (needed when ``z`` is computed from ``y``).
    patch : int
        Radius of the box for ``z_bias="estimate"`` (default 2, a 5x5 box).
    leave_centre_out : bool
        ``z_bias="estimate"``: leave out of tap ``t``'s box the two centres whose ``δ``
        contains ``y_c`` itself (``c`` and ``c − (t − c)``), so the weights of pixel ``c``
        do not depend on the noise of ``y_c`` (otherwise taps agreeing with the noisy
        centre are favoured, and SURE of the combined image, which assumes
        ``∂a/∂y_c = 0``, is biased; see :func:`combine_denoised`).
    ridge : float
        ``"full"`` only: relative Tikhonov term added to ``M`` (``ridge · mean diag``).

    Returns
    -------
    weights : (H, W, B, size, size) float32 ndarray
        Normalised to sum to one over the taps inside the image (``B = 1`` for a single
        buffer, accepted by :func:`combine`); zero on taps outside the image.

    Raises
    ------
    InputError
        Bad shapes or options, non-finite input, negative ``var_y``, and magnitudes the
        weights cannot handle in float64: ``|y|``, ``|z|``, ``|z_bias|`` above
        ``VALUE_LIMIT = 1e140`` or ``|var_y|``, ``|cov_z|``, ``|cov_yz|`` above
        ``MOMENT_LIMIT = 1e290`` (the weights square differences of the images; beyond these
        the squares and their sums overflow).  The weights are invariant to ``y, z,
        z_bias -> s y, s z, s z_bias`` with the moments times ``s²``, so rescale such input.

    Notes
    -----
    Fallback: a pixel whose weights cannot be formed finitely gets weight ``1 / B`` on
    each bin's centre tap and zero elsewhere (the combination then returns the mean of
    the bins' ``y_c``, the unbiased independent estimate).  That happens when a tap
    inside the window has a non-finite ``Var(e_t)`` or squared bias, when the ``C x C``
    solve of ``"coherent"`` is not finite, or when the weights do not sum to a positive
    finite number.  Input within the limits above keeps every moment finite, so only a
    numerically singular solve of ``G = I + Σ d_i U_i U_iᵀ`` (positive definite, ``>= I``)
    could trigger it; the compiled kernel and the NumPy path apply the same rule.
    ``"full"`` falls back the same way where ``M`` is singular (``ridge=0`` on pixels whose
    taps have no variance and no bias, e.g. flat noiseless regions) or its weights are not
    finite.

    The paper fits the weights with a network because the moments are unknown (§4.3).
    Given estimated moments (``PixelStats.mean_var``, :func:`buffer_moments`,
    :func:`filter_covariance`), these weights are the classical plug-in answer; their
    quality is that of the moments.  Weights computed from the data make Eq. 10/11
    approximate (the paper's "≈").

    ``"coherent"`` and ``"diagonal"`` run in a numba kernel
    (``_combine_kernels.statistical_weights_numba``); ``_reference=True`` runs the plain
    NumPy path instead, which tests compare against (``"full"`` always uses NumPy).
    """
    return _statistical_weights(y, z, var_y, cov_z, size, method=method, z_bias=z_bias,
                                cov_yz=cov_yz, patch=patch, leave_centre_out=leave_centre_out,
                                ridge=ridge, reference=_reference)


def _statistical_weights(y, z, var_y, cov_z, size, *, method="coherent", z_bias="estimate",
                         cov_yz=None, patch=2, leave_centre_out=False, ridge=1e-9,
                         reference=False, rows=None):
    """:func:`statistical_weights`; ``rows = (r0, r1)``: the compiled path computes the
    weights of rows ``r0 .. r1 − 1`` only (each to the bit as on all rows) and gives the
    other rows the identity (centre tap 1), so :func:`combine` still runs on them; for the
    banded callers, whose margin rows' outputs are thrown away."""
    multi = np.ndim(y) == 4
    ys, zs, _ = _pair("y", y, "z", z, multi=multi)
    B, H, W, C = ys.shape
    if np.ndim(y) not in (3, 4):
        raise InputError(f"`y` must have shape (H, W, C) or (B, H, W, C); got {np.shape(y)}.")
    k = _check_size(size)
    if method not in _METHODS:
        raise InputError(f"`method` must be one of {_METHODS}; got {method!r}.")
    if isinstance(patch, bool) or not isinstance(patch, (int, np.integer)) or patch < 0:
        raise InputError(f"`patch` must be an integer >= 0; got {patch!r}.")
    ridge = as_number("ridge", ridge, lo=0.0)
    _check_limit("y", ys, VALUE_LIMIT)
    _check_limit("z", zs, VALUE_LIMIT)
    mom = _Moments(_image_moment("var_y", var_y, B, H, W, C, nonneg=True, limit=MOMENT_LIMIT),
                   _stencil("cov_z", cov_z, B, H, W, C, limit=MOMENT_LIMIT),
                   _stencil("cov_yz", cov_yz, B, H, W, C, required=False, limit=MOMENT_LIMIT))
    zb = None
    if isinstance(z_bias, str):
        if z_bias not in _BIAS_MODES:
            raise InputError(f"`z_bias` must be 'estimate', 'pairs', 'zero' or an array; got "
                             f"{z_bias!r}.")
        if z_bias == "pairs" and B < 2:
            raise InputError("`z_bias='pairs'` estimates the tap biases from products of "
                             "distinct bins and needs B >= 2 bins (y, z of shape (B, H, W, C)); "
                             f"got one image of shape {np.shape(y)}.")
    else:
        zb = _image_moment("z_bias", z_bias, B, H, W, C, limit=VALUE_LIMIT)
    ys64, zs64 = ys.astype(np.float64), zs.astype(np.float64)
    loo = bool(leave_centre_out)
    if method != "full" and not reference:
        return _statistical_weights_compiled(ys64, zs64, mom, zb, z_bias, method, k, int(patch),
                                             loo, rows)
    mean, sq = _bias_vectors(ys64, zs64, mom, zb, z_bias, k, int(patch), loo)
    if method == "coherent":
        return _coherent_weights(mom, sq, k, B, H, W)
    if method == "diagonal":
        return _diagonal_weights(mom, sq, k, B, H, W)
    return _full_weights(mom, mean, k, B, H, W, ridge)


def filter_covariance(kernels, var, *, size=None, cross=False):
    """Covariance stencil of a linear filter of an image with independent pixels.

    For ``z = apply_kernels(kernels, x)`` (the convention of the module docstring, zero
    outside) and independent pixels ``x_q`` with variances ``var_q``,
    ``cov(z_p, z_{p+v}) = Σ_a K_p[a] K_{p+v}[a − v] var_{p+a−r}``.  Textbook
    propagation of covariance, used to give :func:`combine_bias_variance` and
    :func:`statistical_weights` the exact moments of a filtered (denoised-like) ``z``.

    Parameters
    ----------
    kernels : (H, W, kf, kf) ndarray
        Per-pixel filter weights (odd ``kf``).
    var : (H, W, C) ndarray
        Variance of each independent pixel of ``x`` (e.g. ``PixelStats.mean_var``).
    size : int, optional
        Odd stencil width ``m``; default ``2 kf − 1`` (every nonzero covariance).
    cross : bool
        Also return ``cov(x_p, z_{p+v}) = K_{p+v}[r − v] var_p`` (the ``cov_yz`` of
        ``y = x``, ``z = filter(x)``).

    Returns
    -------
    cov : (H, W, m, m, C) float64 ndarray
        ``cov[p, m//2 + vy, m//2 + vx] = cov(z_p, z_{p+v})``; zero where ``p + v`` is
        outside the image.
    cross_cov : (H, W, m, m, C) float64 ndarray
        Only with ``cross=True``.

    Raises
    ------
    InputError
        Besides bad shapes and values: where a covariance leaves float64's range (a
        product ``K·K·var`` or its sum beyond 1.8e308, e.g. ``var`` near 1e308 or
        kernel weights beyond 1e154), naming ``kernels`` and ``var`` with their largest
        magnitudes, instead of returning Inf/NaN.  Checked on the result (one sum
        pass), so every representable result is returned.
    """
    from .analytic import _numeric_kernels
    K = _numeric_kernels(kernels)
    if K.ndim != 4 or K.shape[2] != K.shape[3] or K.shape[2] % 2 == 0:
        raise InputError(f"`kernels` must have shape (H, W, k, k) with odd k; got {K.shape}.")
    K = K.astype(np.float64)
    check_finite("kernels", K)
    H, W, kf, _ = K.shape
    v = as_float_array("var", var, ndim=3, dtype=np.float64)
    check_nonempty("var", v)
    check_finite("var", v)
    check_nonnegative("var", v)
    if v.shape[:2] != (H, W):
        raise InputError(f"`var` must have shape ({H}, {W}, C) to match `kernels` {K.shape}; "
                         f"got {v.shape}.")
    m = 2 * kf - 1 if size is None else _check_size(size)
    R, r = m // 2, kf // 2
    cov = np.zeros((H, W, m, m, v.shape[2]))
    for vy in range(-R, R + 1):
        for vx in range(-R, R + 1):
            acc = cov[:, :, R + vy, R + vx]
            for ay in range(kf):
                by = ay - vy
                if not 0 <= by < kf:
                    continue
                for ax in range(kf):
                    bx = ax - vx
                    if not 0 <= bx < kf:
                        continue
                    kq = _shift(K[:, :, by, bx], vy, vx)
                    with np.errstate(over="ignore", invalid="ignore"):
                        acc += (K[:, :, ay, ax] * kq)[..., None] * _shift(v, ay - r, ax - r)
    given = {"kernels": K, "var": v}
    check_overflow(cov, "the covariance stencil", given, _FILTER_COV_RANGE)
    if not cross:
        return cov
    xc = np.zeros_like(cov)
    for vy in range(-min(R, r), min(R, r) + 1):
        for vx in range(-min(R, r), min(R, r) + 1):
            with np.errstate(over="ignore", invalid="ignore"):
                xc[:, :, R + vy, R + vx] = _shift(K[:, :, r - vy, r - vx], vy, vx)[..., None] * v
    check_overflow(xc, "the cross-covariance stencil", given, _FILTER_COV_RANGE)
    return cov, xc


#: The range named when :func:`filter_covariance` overflows.
_FILTER_COV_RANGE = ("the products K_p[a]·K_q[b]·var and their sums Σ_a below 1.8e308, e.g. "
                     "kernel weights up to 1 and `var` below 1.8e308 / k²")


def buffer_moments(ys, zs, *, size):
    """Moments of one bin's estimates, estimated from ``B >= 2`` independent bins.

    With sample binning (§4.4 of [1]_) the bins of a pixel hold disjoint samples, so
    ``(y_{·,b}, z_{·,b})`` are i.i.d. over ``b`` when every bin has the same sample count
    and ``z_b`` is computed from bin ``b`` alone.  The unbiased sample covariances over
    the bins (``ddof = 1``) then estimate the second moments of *one* bin:

    ``var_y[p] = Σ_b (y_pb − ȳ_p)² / (B − 1)``,
    ``cov_z[p, v] = Σ_b (z_pb − z̄_p)(z_{p+v,b} − z̄_{p+v}) / (B − 1)``,
    ``cov_yz[p, v] = Σ_b (y_pb − ȳ_p)(z_{p+v,b} − z̄_{p+v}) / (B − 1)``.

    With ``B = 4`` they have 3 degrees of freedom and are noisy: smooth them, or use
    them where noise averages out (e.g. over a patch).

    Parameters
    ----------
    ys, zs : (B, H, W, C) ndarray
    size : int
        Odd stencil width ``m``.

    Returns
    -------
    var_y : (H, W, C), cov_z : (H, W, m, m, C), cov_yz : (H, W, m, m, C) float64 ndarrays
        Shared by all bins (pass them as they are to :func:`statistical_weights` or
        :func:`combine_bias_variance` with multi-buffer weights).

    Raises
    ------
    InputError
        Besides bad shapes and values: a moment that leaves float64's range (the
        squared spreads, for ``|ys|`` or ``|zs|`` beyond about 1e154), which came back
        as Inf/NaN before session 17; every representable moment is returned.
        (:func:`statistical_weights` takes images up to ``VALUE_LIMIT`` = 1e140, whose
        moments stay below its ``MOMENT_LIMIT``.)
    """
    ysa, zsa, _ = _pair("ys", ys, "zs", zs, multi=True)
    B, H, W, C = ysa.shape
    if B < 2:
        raise InputError(f"`ys` must hold B >= 2 buffers to estimate moments from their "
                         f"spread; got shape {np.shape(ys)}.")
    m = _check_size(size)
    R = m // 2
    with np.errstate(over="ignore", invalid="ignore"):      # the results are checked below
        dy = ysa.astype(np.float64) - ysa.mean(axis=0, dtype=np.float64)
        dz = zsa.astype(np.float64) - zsa.mean(axis=0, dtype=np.float64)
        var_y = (dy * dy).sum(axis=0) / (B - 1)
        cov_z = np.zeros((H, W, m, m, C))
        cov_yz = np.zeros((H, W, m, m, C))
        for vy in range(-R, R + 1):
            for vx in range(-R, R + 1):
                sz = np.stack([_shift(dz[b], vy, vx) for b in range(B)])
                cov_z[:, :, R + vy, R + vx] = (dz * sz).sum(axis=0) / (B - 1)
                cov_yz[:, :, R + vy, R + vx] = (dy * sz).sum(axis=0) / (B - 1)
    for name, a in (("var_y", var_y), ("cov_z", cov_z), ("cov_yz", cov_yz)):
        check_overflow(a, f"the moment {name}", {"ys": ysa, "zs": zsa},
                       "squared spreads of the bins below 1.8e308, i.e. |ys| and |zs| "
                       "below about 1e154")
    return var_y, cov_z, cov_yz


# =========================================================================== black-box z
#: Defaults of :func:`combine_denoised`, chosen on the toy ``mixed`` scene and the four
#: built-in Mitsuba scenes at 4-1024 spp (``bench/bench_combine.py``, docs/combine.md).
DEFAULT_PROBES = 8        # ±σ probe vectors: 8 extra denoiser calls
DEFAULT_STENCIL = 5       # covariance stencil width m of the first-order moments
DEFAULT_MOMENT_SMOOTH = 2  # box radius smoothing the probe moments (5x5)
DEFAULT_SIZE = 15         # combination window (the paper's 15x15, §5)
DEFAULT_MIX_SIGMA = 16.0  # Gaussian σ (pixels) pooling the SURE terms of the mix
#: Probes per bin of a black-box denoiser for the Stein terms of combine_bins' mix (B x this
#: extra calls): 2 moved oidn+bins with the mix from 0.84 to 0.79x OIDN on cornell-box at
#: 64 spp, 0.99 to 0.98x on textured-dof (bench/analysis_bins_combine.py, docs/combine.md).
DEFAULT_BIN_PROBES = 2
#: Tap-bias estimate of the weights behind combine_bins' mix (:func:`statistical_weights`'s
#: ``z_bias``): "pairs" keeps them independent of the pixel noise model that "estimate"
#: subtracts (docs/combine.md, "The bias of the SURE terms").
_MIX_Z_BIAS = "pairs"
#: Memory of one band of rows (bytes) of the per-pixel weights (float32) and smoothed
#: moment stencils (float64) of :func:`combine_denoised`, :func:`combine_bins` and
#: :func:`combine_bin_images`, margins included (:func:`_band_rows`).
BAND_BYTES = 1 << 30


def _box(a, radius):
    """Box mean over ``(2 radius + 1)²`` pixels (leading axes H, W), reflected borders."""
    if radius <= 0:
        return a
    from scipy.ndimage import uniform_filter

    n = 2 * radius + 1
    return uniform_filter(a, (n, n) + (1,) * (a.ndim - 2), mode="reflect")


def _probe_step(x, v, eps):
    """Finite-difference step: ``eps`` relative to the image's RMS over the probe's RMS
    (each mean exact also where its sum overflows float64, ``sure._mean``: ``mean_var``
    near 1.8e308 made the step 0 and the moments NaN)."""
    from .sure import _mean

    with np.errstate(over="ignore"):       # x*x beyond 1.8e308: an Inf RMS, a 0 step
        sx = float(np.sqrt(_mean(x * x)))
    sv = float(np.sqrt(_mean(v * v)))
    if sx == 0.0 or sv == 0.0:
        return None
    return eps * sx / sv


def _denoise(f, x):
    out = np.asarray(f(np.ascontiguousarray(x, dtype=np.float32)))
    if out.shape != x.shape:
        raise InputError(f"`denoiser` must return an image of the input's shape {x.shape}; "
                         f"got {out.shape}.")
    out = out.astype(np.float64)
    check_finite("denoiser output", out)
    return out


def denoiser_moments(denoiser, x, mean_var, *, size=DEFAULT_STENCIL, probes=DEFAULT_PROBES,
                     rng=None, eps=1e-3, extra_output=False):
    """First-order covariance stencils of a black-box denoiser's output ``z = f(x)``.

    The first-order model ``z(x + ε) ≈ z(x) + J ε`` with independent pixel noise
    ``Cov(ε) = diag(σ²)`` gives ``cov(z_p, z_q) = (J Σ Jᵀ)_pq`` and
    ``cov(y_p, z_q) = J_qp σ_p²``.  Both are estimated from ``K`` random probes ``v`` with
    independent fair signs, ``v_p = ±σ_p`` (so ``E[v vᵀ] = Σ``), and finite-difference
    Jacobian-vector products ``J v ≈ (f(x + h v) − f(x)) / h``:
    ``E[(J v)_p (J v)_q] = (J Σ Jᵀ)_pq`` and ``E[v_p (J v)_q] = J_qp σ_p²``.  This extends
    the variance estimate of Firmino et al. 2023 (§"Deep NN Variance Estimate",
    ``Σ_j (∂f_i/∂x_j)² σ_j²`` from ``±σ`` vectors [3]_; :func:`statmc.sure.output_variance`)
    to the covariances that Eq. 10/11 of Back et al. 2020 [1]_ need when ``z`` is
    computed from ``y`` (the cross term ``cov_yz``, see :func:`combine_bias_variance`).

    Parameters
    ----------
    denoiser : callable ``f(color) -> color``
        E.g. :func:`statmc.denoisers.oidn` with its feature buffers bound.
    x : (H, W, C) ndarray
        The noisy image (``y``), where ``f`` is linearised.
    mean_var : (H, W, C) ndarray
        **Variance of the mean** of each pixel of ``x`` (``PixelStats.mean_var``).
    size : int
        Odd stencil width ``m`` (offsets up to ``m // 2``).
    probes : int
        ``K``, the number of probe vectors (``K + 1`` denoiser calls).
    rng : numpy Generator or seed, optional
    eps : float
        Finite-difference step relative to the image's RMS (1e-3: the value
        :data:`statmc.sure.DEFAULT_VARIANCE_EPS` uses for the same squared differences).
    extra_output : bool
        Also return the probes ``v`` and ``J v`` as ``(K, H, W, C)`` arrays.

    Returns
    -------
    z : (H, W, C) float64 ndarray
        ``f(x)``.
    cov_z, cov_yz : (H, W, m, m, C) float64 ndarrays
        Stencils in the convention of :func:`combine_bias_variance`:
        ``cov_z[p, R + v] = cov(z_p, z_{p+v})``, ``cov_yz[p, R + v] = cov(x_p, z_{p+v})``
        (``R = m // 2``), each the mean over the ``K`` probes (unbiased for the
        first-order model; smooth them before use, ``K`` is small).
    probes_v, probes_jv : (K, H, W, C) float64 ndarrays
        Only with ``extra_output=True``.

    Notes
    -----
    Exact (up to the finite difference) for linear denoisers; for OIDN the first-order
    variance exceeds the empirical one by 16–20 % (``docs/error-estimates.md``).

    References
    ----------
    .. [1] J. Back, B.-S. Hua, T. Hachisuka, B. Moon. "Deep Combiner for Independent and
       Correlated Pixel Estimates". ACM TOG 39(6), 242, 2020.
       https://doi.org/10.1145/3414685.3417847
    .. [3] A. Firmino, J. R. Frisvad, H. W. Jensen. "Denoising-Aware Adaptive Sampling
       for Monte Carlo Ray Tracing". SIGGRAPH 2023. https://doi.org/10.1145/3588432.3591537
    """
    m = _check_size(size)
    extra_output = as_bool("extra_output", extra_output)
    pr = _probe_vectors(denoiser, x, mean_var, probes, rng, eps)
    with np.errstate(over="ignore", invalid="ignore"):      # checked just below
        cov_z, cov_yz = pr.stencils(m, 0, pr.z.shape[0])
    for name, a in (("cov_z", cov_z), ("cov_yz", cov_yz)):
        # σ² for the message is formed only if the check fails (50 MB at 1080p)
        check_overflow(a, f"the stencil {name}", lambda: {"mean_var": pr.sig * pr.sig},
                       "products (J v)_p (J v)_q and v_p (J v)_q of the ±σ probes below "
                       "1.8e308, i.e. `mean_var` below about 1e307 times the denoiser's "
                       "gain squared")
    if extra_output:
        V = np.stack([pr.v(i) for i in range(pr.K)])
        return pr.z, cov_z, cov_yz, V, pr.jv
    return pr.z, cov_z, cov_yz


class _Probes:
    """The probes of :func:`denoiser_moments`: ``z = f(x)``, the ``K`` probe vectors ``v``
    (kept as their random signs, int8, and rebuilt as ``σ · (±1)`` exactly as drawn) and
    ``J v`` (float64); ``used[i]`` is False for a probe skipped (no noise), whose ``v`` and
    ``J v`` are zero."""

    def __init__(self, z, sig, signs, jv, used):
        self.z, self.sig, self.signs, self.jv, self.used = z, sig, signs, jv, used
        self.K = jv.shape[0]

    def v(self, i, lo=0, hi=None):
        """Rows ``lo .. hi − 1`` of probe ``i``."""
        if not self.used[i]:
            return np.zeros(self.jv.shape[1:])[lo:hi]
        return self.sig[lo:hi] * (self.signs[i, lo:hi] * 2.0 - 1.0)

    def stencils(self, m, r0, r1):
        """Rows ``r0 .. r1 − 1`` of the unsmoothed stencils ``cov_z``, ``cov_yz``
        ``(r1 − r0, W, m, m, C)``: products over a slab with ``m // 2`` rows of margin,
        summed over the probes in order and divided by ``K``, so each entry is the one
        of the whole image to the bit."""
        H, W, C = self.z.shape
        R = m // 2
        s0, s1 = max(0, r0 - R), min(H, r1 + R)
        cov_z = np.zeros((s1 - s0, W, m, m, C))
        cov_yz = np.zeros((s1 - s0, W, m, m, C))
        # probe by probe in order, skipping those without noise (zero moments), with each
        # stencil element in a register: the sums of one add_neighbour_products per probe
        jv = self.jv[:, s0:s1]
        V = np.stack([self.v(i, s0, s1) for i in range(self.K)])
        add_neighbour_products_sum(cov_z, jv, jv, R, self.used)   # += (Jv)_p (Jv)_{p+u}
        add_neighbour_products_sum(cov_yz, V, jv, R, self.used)   # += v_p (Jv)_{p+u}
        del V
        out = []
        for a in (cov_z, cov_yz):
            a = a[r0 - s0:r1 - s0]
            a /= self.K
            out.append(a)
        return out


def _probe_vectors(denoiser, x, mean_var, probes, rng, eps, name="x"):
    """Check the input of :func:`denoiser_moments` and run the ``K + 1`` denoiser calls
    (on the whole image: a black box cannot be banded); returns :class:`_Probes`.  ``name``
    is the caller's name of ``x``, used in its messages."""
    xx = as_float_array(name, x, ndim=3, dtype=np.float64)
    check_nonempty(name, xx)
    check_finite(name, xx)
    mv = as_float_array("mean_var", mean_var, ndim=3, dtype=np.float64)
    check_finite("mean_var", mv)
    check_nonnegative("mean_var", mv)
    if mv.shape != xx.shape:
        raise InputError(f"`mean_var` must have the shape of `{name}` {xx.shape} (the variance of "
                         f"the mean of each pixel and channel); got {mv.shape}.")
    if isinstance(probes, bool) or not isinstance(probes, (int, np.integer)) or probes < 1:
        raise InputError(f"`probes` must be an integer >= 1; got {probes!r}.")
    eps = as_number("eps", eps, lo=0.0, lo_open=True)
    if not callable(denoiser):
        raise InputError(f"`denoiser` must be a callable f(color) -> color; got {denoiser!r}.")
    gen = as_rng(rng)
    sig = np.sqrt(mv)
    z = _denoise(denoiser, xx)
    signs = np.zeros((probes,) + xx.shape, np.int8)
    jvs = np.zeros((probes,) + xx.shape)
    used = np.zeros(probes, bool)
    _run_probes(denoiser, xx, z, sig, range(int(probes)), gen, eps, signs, jvs, used)
    return _Probes(z, sig, signs, jvs, used)


def _run_probes(denoiser, x, z, sig, slots, gen, eps, signs, jvs, used):
    """One ±σ probe of ``denoiser`` at ``x`` (whose output is ``z``) per slot ``j`` of
    ``slots``: ``signs[j]`` the draw, ``jvs[j] = (f(x + h v) − z) / h`` with ``v = ±sig``,
    ``used[j]``; a probe without a usable step (no noise, a black image) is left at zero
    moments."""
    for j in slots:
        draw = gen.integers(0, 2, x.shape)
        v = sig * (draw * 2.0 - 1.0)
        h = _probe_step(x, v, eps)
        if h is None:
            continue
        jvs[j] = (_denoise(denoiser, x + h * v) - z) / h
        signs[j], used[j] = draw, True


def _bin_probe_vectors(denoiser, ys, zs, mean_var, count, gen, eps):
    """``count`` ±σ probes of the denoiser at each bin ``ys[b]`` (``B · count`` calls):
    :class:`_Probes` with ``v = ±√(B · mean_var)`` (one bin's variance) and
    ``J_b v ≈ (f(y_b + h v) − z_b) / h`` (float32), bin after bin."""
    B = ys.shape[0]
    sig = np.sqrt(B * mean_var)
    n = B * count
    signs = np.zeros((n,) + ys.shape[1:], np.int8)
    jvs = np.zeros((n,) + ys.shape[1:], np.float32)
    used = np.zeros(n, bool)
    for b in range(B):
        _run_probes(denoiser, ys[b], zs[b], sig, range(b * count, (b + 1) * count), gen, eps,
                    signs, jvs, used)
    return _Probes(None, sig, signs, jvs, used)


def _reflect(i, n):
    """Index ``i`` of a line of ``n`` extended as :mod:`scipy.ndimage`'s ``mode="reflect"``
    (``d c b a | a b c d | d c b a``, repeated for lines shorter than the extension)."""
    p = 2 * n
    i %= p
    return i if i < n else p - 1 - i


class _SmoothedRows:
    """Box-smoothed covariance stencils handed out in bands of rows, to the bit those of
    ``scale · _box(stencil, radius)`` on the whole image, without ever holding it.

    ``raw(r0, r1)`` gives rows ``r0 .. r1 − 1`` of the unsmoothed stencils (a tuple of
    ``(r1 − r0, W, m, m, C)`` arrays).  :func:`scipy.ndimage.uniform_filter` filters the
    rows axis, then the columns axis; along the rows it keeps a running sum from the
    first row (``t_0 = Σ x_{−s..s}``, ``t_y = t_{y−1} + (x_{y+s} − x_{y−s−1})``, output
    ``t_y / n``, reflected borders; SciPy 1.17), so a band's rows depend on the rounding
    of every row above.
    This class runs the same sum with the same operations, row after row over successive
    bands (requests move down the image; a band may overlap the previous one), carrying
    the running sums across bands; the columns pass is SciPy's own on each new row.  What
    the combiners rely on is that any bands give the one-piece result to the bit (they all
    smooth through this class); equality with another SciPy's ``uniform_filter`` is only up
    to the rounding of the running sums.
    """

    def __init__(self, raw, H, radius, scale=None):
        self.raw, self.H, self.s, self.scale = raw, H, int(radius), scale
        self.lo = self.hi = 0          # rows held: lo .. hi - 1
        self.held = None
        self.sums = None               # running sums of the rows pass at row hi - 1

    def rows(self, lo, hi):
        """Smoothed rows ``lo .. hi − 1`` (``lo``, ``hi`` not below the previous call's)."""
        if lo < self.lo or hi < self.hi or lo > self.hi or hi <= lo:
            raise ValueError(f"bands must move down the image: rows {lo}..{hi} after "
                             f"{self.lo}..{self.hi}")
        keep = [] if self.held is None else [a[lo - self.lo:].copy() for a in self.held]
        self.held = None                   # free the previous band before the next
        out = self._smooth(self.hi, hi, keep) if hi > self.hi else keep
        self.lo, self.hi, self.held = lo, hi, out
        return out

    def _smooth(self, n0, n1, keep):
        """Rows ``n0 .. n1 − 1`` appended to the ``keep`` rows (one array per stencil)."""
        s, H = self.s, self.H
        if s <= 0:
            new = list(self.raw(n0, n1))
            if self.scale is not None:
                for o in new:
                    o *= self.scale
            return [np.concatenate([k_, o]) for k_, o in zip(keep, new)] if keep else new
        from scipy.ndimage import uniform_filter1d

        n = 2 * s + 1
        first = n0 - s - 1 if n0 > 0 else -s
        idx = [_reflect(e, H) for e in range(first, n1 + s)]
        r0 = min(idx)
        raw = list(self.raw(r0, max(idx) + 1))
        if self.sums is None:
            self.sums = [None] * len(raw)
        out = []
        for j in range(len(raw)):
            x = raw[j]
            nk = len(keep[j]) if keep else 0
            full = np.empty((nk + n1 - n0,) + x.shape[1:])
            if nk:
                full[:nk] = keep[j]
                keep[j] = None
            o = full[nk:]
            t = self.sums[j]
            y = n0
            if y == 0:
                t = np.zeros(x.shape[1:])
                for e in range(-s, s + 1):
                    t += x[_reflect(e, H) - r0]
                np.divide(t, n, out=o[0])
                y = 1
            if y < n1:                     # t += x[y + s] - x[y - s - 1], o[y] = t / n
                add = np.array([_reflect(e + s, H) - r0 for e in range(y, n1)], np.int64)
                sub = np.array([_reflect(e - s - 1, H) - r0 for e in range(y, n1)], np.int64)
                L = t.size
                _ck.running_rows(np.ascontiguousarray(x).reshape(len(x), L), add, sub, n,
                                 t.reshape(L), o[y - n0:].reshape(n1 - y, L))
            self.sums[j] = t
            raw[j] = x = None              # free each raw stencil once summed
            uniform_filter1d(o, n, axis=1, output=o, mode="reflect")
            if self.scale is not None:
                o *= self.scale
            out.append(full)
        return out


def _band_margin(k, patch):
    """Rows of margin a band of weights needs on either side: a pixel's Eq. 8/14 reads
    its taps ``k // 2`` rows away, whose tap biases are box means over ``patch`` rows."""
    return k // 2 + patch


def _band_rows(H, row_bytes, margin):
    """Output rows of each band: as many as :data:`BAND_BYTES` holds with the ``margin``
    rows on either side (``row_bytes`` per row), split into equal bands, but at least
    ``2 margin`` (so the margins at most double the work)."""
    most = max(1, 2 * margin, BAND_BYTES // max(1, row_bytes) - 2 * margin)
    return max(-(-H // -(-H // most)), min(most, 2 * margin))


def _stencil_row_bytes(W, m, C, count=2):
    """Bytes of one row of ``count`` float64 ``(W, m, m, C)`` stencils."""
    return count * W * m * m * C * 8


def _simplex_mix(G, b):
    """Minimise ``λᵀGλ − 2bᵀλ`` over ``λ ≥ 0, Σλ ≤ 1`` per pixel (``G`` ``(..., J, J)``).

    Enumerates the faces of the simplex (free and ``Σλ = 1`` on every subset of the
    candidates, ``J <= 3``) and keeps the best feasible stationary point; ``λ = 0``
    (objective 0) is always feasible.
    """
    from itertools import combinations

    J = b.shape[-1]
    best = np.zeros(b.shape)
    best_q = np.zeros(b.shape[:-1])
    for n in range(1, J + 1):
        for S in combinations(range(J), n):
            idx = np.array(S)
            Gs = G[..., idx[:, None], idx[None, :]]
            bs = b[..., idx]
            # ridge relative to the diagonal: a candidate equal to another is singular
            tr = np.einsum("...ii->...", Gs)[..., None, None] / n
            Gs = Gs + np.eye(n) * (1e-9 * tr + 1e-300)
            inv1 = np.linalg.solve(Gs, np.ones(bs.shape)[..., None])[..., 0]
            free = np.linalg.solve(Gs, bs[..., None])[..., 0]
            # on Σλ = 1: λ = free + ν inv1 with ν = (1 − Σfree) / Σinv1
            with np.errstate(divide="ignore", invalid="ignore"):
                nu = (1.0 - free.sum(-1)) / inv1.sum(-1)
            tight = free + nu[..., None] * inv1
            for lam_s in (free, tight):
                ok = np.isfinite(lam_s).all(-1) & (lam_s >= 0).all(-1) & (lam_s.sum(-1) <= 1 + 1e-12)
                lam = np.zeros(b.shape)
                lam[..., idx] = np.where(ok[..., None], lam_s, 0.0)
                q = np.einsum("...i,...ij,...j->...", lam, G, lam) - 2 * (lam * b).sum(-1)
                better = ok & (q < best_q)
                best = np.where(better[..., None], lam, best)
                best_q = np.where(better, q, best_q)
    return best


def _mix_gain(y, z, beta, mean_var, w, V, JV):
    """Per pixel and channel, an estimate of ``−E[(z_c − μ_c) ρ_c]``, ``ρ = β̂ − z``.

    ``r_c ρ_c − a_c σ_c² + Σ_t a_t cov(y_c, z_t)`` with ``r = y − z``: Stein's lemma
    ``E[ε_c ρ_c] = σ_c² E[∂ρ_c/∂y_c]`` for ``ρ = A(y − z)`` with weights ``A``
    independent of ``y_c``, where ``σ_c² ∂ρ_c/∂y_c = a_c σ_c² − Σ_t a_t J_tc σ_c²`` and
    ``J_tc σ_c² = cov(y_c, z_t) = E[v_c (J v)_t]`` from the probes ``V``, ``JV``.
    Unbiased when ``z`` is linear in ``y`` (first order otherwise).
    """
    from .analytic import apply_kernels

    k = w.shape[3]
    wk = w[:, :, 0]
    # the centre's share of W_c, the weight sum over the taps inside the image (Eq. 8)
    a_c = (wk[:, :, k // 2, k // 2] / apply_kernels(wk, np.ones(y.shape[:2])))[..., None]
    zero = np.zeros_like(y)
    cross = np.zeros_like(y)
    for i in range(V.shape[0]):
        cross += V[i] * combine(JV[i], zero, w)        # A u = combine(u, 0, w)
    cross /= max(V.shape[0], 1)
    return (y - z) * (beta - z) - a_c * mean_var + cross


def _mix_rel(y, z, pr, mean_var):
    """The relMSE weights ``1 / (z² + 0.01)`` with which the SURE mix of
    :func:`combine_denoised` and :func:`combine_bins` pools ``G`` and ``b`` (ε = 0.01 of
    Rousselle et al. 2011, as the relMSE metric), per pixel and channel, ``(H, W, C)``.

    ``y`` (the render, or the bin mean ``ȳ``), the probes ``pr`` (:class:`_Probes`) and
    ``mean_var`` are not read: they are the arguments of this hook, so that a study can swap
    in other weights without a copy of the mix (``bench/analysis_denoised_mix.py``).
    Stein's lemma needs ``rel_c`` not to move with ``y_c``, and ``1 / (z_c² + 0.01)`` does,
    through ``z_c``; with heavy-tailed pixels that biases the pooled estimate of ``b``.  Two
    weights free of ``y_c`` removed that bias on toy ``mixed`` but made the built-in scenes
    worse (session 9; ``docs/combine.md``, "Is the mix of combine_denoised biased?"), so
    these stay."""
    return 1.0 / (z * z + 0.01)


def _check_sure_terms(sure_terms, extra_output):
    """Check ``sure_terms`` of :func:`combine_denoised` / :func:`combine_bins`."""
    if as_bool("sure_terms", sure_terms) and not extra_output:
        raise InputError("`sure_terms=True` adds the SURE terms to the dict of "
                         "`extra_output`; pass extra_output=True as well (got "
                         f"extra_output={extra_output!r}).")


#: ``mix_sigma`` may be at most this many times the image's longer side (and never less
#: than :data:`DEFAULT_MIX_SIGMA`).  The local mix pools with SciPy's ``gaussian_filter``
#: (mode "reflect"), whose taps cover ``4 mix_sigma`` pixels each side: 1e30 raised SciPy's
#: "Maximum allowed size exceeded", 1e9 asked for 64 GB of taps, and the cost grows with
#: ``mix_sigma`` though the result stops changing: at twice the longer side the pooled
#: values already vary by < 2e-5 relative over the image (measured on 5² to 256² random
#: images), i.e. the pool is the whole image's, which ``mix="global"`` computes directly.
MIX_SIGMA_IMAGES = 4.0


def _check_mix(mix, mix_sigma, hw) -> float:
    """Check the SURE mix options of :func:`combine_denoised` / :func:`combine_bins` for
    an image of height and width ``hw``; returns ``mix_sigma`` as a float.  Its upper
    bound applies to ``mix="local"`` only, the one mix that uses it."""
    if mix not in ("local", "global", None):
        raise InputError(f"`mix` must be 'local', 'global' or None; got {mix!r}.")
    ms = as_number("mix_sigma", mix_sigma, lo=0.0, lo_open=True)
    limit = max(DEFAULT_MIX_SIGMA, MIX_SIGMA_IMAGES * max(hw))
    if mix == "local" and ms > limit:   # the other mixes do not use mix_sigma
        raise InputError(
            f"`mix_sigma` must be at most {limit:g} pixels for a {hw[0]}x{hw[1]} image "
            f"({MIX_SIGMA_IMAGES:g} times its longer side, and never less than "
            f"{DEFAULT_MIX_SIGMA:g}); got {mix_sigma!r}.  A Gaussian that wide pools the "
            "SURE terms evenly over the whole image: pass mix='global' for that.")
    return ms


def _pooled_mix(z, betas, nums, rel, mix, sigma):
    """Step 4 of :func:`combine_denoised` (and the mix of :func:`combine_bins`): ``out =
    z + Σ_j λ_j ρ_j``, ``ρ_j = β̂_j − z``, with ``λ`` minimising the pooled SURE estimate
    ``λᵀ G λ − 2 bᵀ λ`` on the simplex (:func:`_simplex_mix`; Eq. 1 and the optimal α of
    Eq. 9 of Firmino et al. 2022).

    ``betas`` ``(J, H, W, C)``; ``nums`` ``(H, W, J)`` the relMSE-weighted channel sums of
    the per-pixel estimates of ``b_j = −E[(z − μ) ρ_j]`` (:func:`_mix_gain`); ``rel``
    ``(H, W, C)`` the relMSE weights ``1 / (z² + 0.01)``, which also weight
    ``G_ij = Σ_c rel ρ_i ρ_j``.  ``mix="global"`` pools over the image (``λ`` ``(J,)``),
    ``"local"`` with a Gaussian of σ = ``sigma`` pixels (``λ`` ``(H, W, J)``).
    """
    rho = np.stack([b - z for b in betas], axis=-1)                   # (H, W, C, J)
    G = np.einsum("hwci,hwcj,hwc->hwij", rho, rho, rel)
    b = nums
    if mix == "global":
        lam = _simplex_mix(G.sum(axis=(0, 1)), b.sum(axis=(0, 1)))
        out = z + np.einsum("hwcj,j->hwc", rho, lam)
    else:
        from scipy.ndimage import gaussian_filter

        Gs = gaussian_filter(G, (sigma, sigma, 0, 0), mode="reflect")
        bs = gaussian_filter(b, (sigma, sigma, 0), mode="reflect")
        lam = _simplex_mix(Gs, bs)
        out = z + np.einsum("hwcj,hwj->hwc", rho, lam)
    return out, lam


def combine_denoised(y, mean_var, denoiser, *, size=DEFAULT_SIZE, probes=DEFAULT_PROBES,
                     stencil=DEFAULT_STENCIL, smooth=DEFAULT_MOMENT_SMOOTH, patch=2,
                     var=("smooth", "max"), mix="local", mix_sigma=DEFAULT_MIX_SIGMA, rng=None,
                     extra_output=False, sure_terms=False):
    """A black-box denoiser made better by the combination kernel (Back et al. 2020 [1]_).

    ``y`` is the render (independent pixels), ``z = denoiser(y)`` the correlated image.
    The classical pipeline, without a network:

    1. **Moments** of ``z`` to first order from ``probes`` ``±σ`` probe vectors
       (:func:`denoiser_moments`): ``cov(z_c, z_t)`` and ``cov(y_t, z_c)`` on a
       ``stencil``-wide stencil, box-smoothed over ``(2 smooth + 1)²`` pixels.
    2. **Weights** minimising Eq. 10² + Eq. 11 (:func:`statistical_weights`, "coherent",
       with the cross term ``cov_yz`` because ``z`` is computed from ``y``, and the tap
       biases estimated from the data leaving the centre out — see Notes), once per
       entry of ``var``, the variance of ``y`` given to the weights: ``"smooth"``,
       ``mean_var`` box-smoothed over 5x5 (robust where most samples are 0, e.g. dense
       fireflies); ``"max"``, the larger of that and the per-pixel ``mean_var`` (holds
       back isolated outliers, e.g. caustic fireflies); ``"raw"``, per pixel.
    3. **Combination** Eq. 8 for each: ``β̂_j = z + A_j (y − z)`` (:func:`combine`).
    4. **Mix** with ``z``: ``out = z + Σ_j λ_j ρ_j``, ``ρ_j = β̂_j − z``, with ``λ ≥ 0``,
       ``Σ λ_j ≤ 1`` minimising the expected relMSE estimated by Stein's lemma (SURE,
       Eq. 1 of Firmino et al. 2022 [2]_), as their optimal mixing α (Eq. 9 of [2]_) but
       between ``z`` and the ``β̂_j``.  The expected squared error is, up to that of
       ``z``, ``λᵀ G λ − 2 bᵀ λ`` with ``G_ij = E[ρ_i ρ_j]`` and
       ``b_j = −E[(z − μ) ρ_j]``; with ``r = y − z`` and Stein's
       ``E[ε_c ρ_c] = σ_c² E[∂ρ_c/∂y_c]``,
       ``b_j = E[r_c ρ_{j,c} − a_c σ_c² + Σ_t a_t cov(y_c, z_t)]`` (``a`` the normalised
       weights of pixel ``c``, ``a_c`` the centre's; the sum from the same probes,
       ``E[v_c (A J v)_c]``).  ``G`` and ``b`` are pooled with relative weights
       ``1 / (z² + 0.01)`` (relMSE, ε of Rousselle et al. 2011) over the channels and a
       Gaussian neighbourhood of σ = ``mix_sigma`` pixels (``mix="local"``) or the
       whole image (``mix="global"``).  ``mix=None`` returns the first ``β̂``.

    Parameters
    ----------
    y : (H, W, C) ndarray
        The render: pixel means.
    mean_var : (H, W, C) ndarray
        **Variance of the mean** of ``y`` (``PixelStats.mean_var``).
    denoiser : callable ``f(color) -> color``
        Black box (OIDN: :func:`statmc.progressive.bind_denoiser` ``("oidn", stats)``).
    size : int
        Odd combination window ``k`` (default 15, as the paper).
    probes, stencil, smooth : int
        Of the moments (step 1): ``probes + 1`` denoiser calls in all.
    patch : int
        Box radius of the tap-bias estimate (:func:`statistical_weights`).
    var : str or sequence of str
        Variance models for the weights (step 2), at most 3; one combination each.
    mix : {"local", "global", None}
    mix_sigma : float
        σ (pixels) of the Gaussian that pools the SURE terms for ``mix="local"``; ``> 0``
        and at most ``MIX_SIGMA_IMAGES`` (4) times the image's longer side, or 16 if that
        is less (a wider one pools the whole image: use ``mix="global"``).
    rng : numpy Generator or seed, optional
        Seeds the probe vectors.
    extra_output : bool
        Also return a dict with ``denoised`` (``z``), ``combined`` (the ``β̂_j``,
        ``(J, H, W, C)``) and ``mix`` (``λ``, ``(H, W, J)``, or ``(J,)`` for ``"global"``;
        None without a mix).
    sure_terms : bool
        Only with ``extra_output``: the dict also holds the per-pixel SURE terms of the mix,
        ``gain`` (the estimates of ``b_j = −E[(z − μ)(β̂_j − z)]``, ``(J, H, W, C)``),
        ``weighted_gain`` (those of the relMSE-weighted ``−E[rel (z − μ)(β̂_j − z)]`` that
        the mix pools, ``(J, H, W, C)``) and ``rel`` (those relMSE weights,
        ``1 / (z² + 0.01)``, ``(H, W, C)``); all three None without a mix.  Without
        ``sure_terms`` the keys are absent and the two ``(J, H, W, C)`` float64 arrays are
        never allocated (0.2 GB at 1920x1080 with the default two models).  The output is
        the same either way.

    Returns
    -------
    out : (H, W, C) float64 ndarray

    Raises
    ------
    InputError
        Besides bad shapes and options: ``|y|`` above float32's range (3.4e38; the
        denoiser gets float32 copies) or ``mean_var`` above ``MOMENT_LIMIT`` (1e290, a
        limit of :func:`statistical_weights`), checked before the denoiser runs.

    Notes
    -----
    *Why the plain statistical weights failed with OIDN* (toy ``mixed``, 4–64 spp:
    relMSE 0.12–0.27 against OIDN's 0.003–0.011).  (i) Per-pixel sample variances are
    0 in firefly regions wherever no sample hit, so those taps — whose ``y_t`` is 0 —
    got nearly all the weight and the output went dark; the smoothed variance removes
    that.  (ii) The data-driven tap biases keep the taps whose difference
    ``(z_c − z_t) − (y_c − y_t)`` happens to be small, which selects neighbours whose
    noise agrees with ``y_c``: ``β̂`` leans toward the noisy centre, and SURE (which
    takes ``∂a/∂y_c = 0``) overestimated its benefit several-fold (mix 1.86 estimated,
    −0.05 true, glossy-spheres 64 spp).  Leaving out the two centres whose ``δ`` holds
    ``y_c`` (``leave_centre_out=True``) makes the weights of pixel ``c`` independent of
    ``y_c``: ``β̂`` improves and the SURE mix becomes accurate (0.16 estimated, 0.16
    true).  (iii) Eq. 8's weights sum to one, so ``β̂`` always adds a full average of
    residuals ``y − z``; where ``z`` is better than any such average — low spp,
    fireflies — only the mix can keep ``z``.  Quality table: ``docs/combine.md``.

    *Scale.*  Without the mix the output is scale-equivariant: ``y`` ×a with ``mean_var``
    ×a² and a scale-equivariant denoiser gives a× the output.  The mix is not, because it
    minimises relMSE with the metric's absolute ε = 0.01 (``1 / (z² + 0.01)``): it weighs
    errors as MSE where ``|z| ≪ 0.1`` and as relative errors where ``|z| ≫ 0.1``, as the
    quality tables do, which assume display-referred radiance of order 1 (tested).

    *Memory.*  The denoiser sees the whole image (``probes + 1`` calls; the probes are kept,
    ``J v`` as float64 and ``v`` as signs).  Steps 1–3 then run in bands of rows, as in
    :func:`combine_bins` (within :data:`BAND_BYTES`, ``k // 2 + patch`` rows of margin):
    the smoothed stencils and the weights of the whole image would take
    ``H W (2 · 8 m² C + 4 k²)`` bytes, 4.4 GB at 1920x1080.  The output is the one-piece
    output to the bit (tested); at 1920x1080 with the defaults and GEM's kernel the peak
    is the inputs plus 1.9 GiB (5.3 GiB before; ``bench/bench_combine.py --part memory``).

    References
    ----------
    .. [1] J. Back, B.-S. Hua, T. Hachisuka, B. Moon. "Deep Combiner for Independent and
       Correlated Pixel Estimates". ACM TOG 39(6), 242, 2020.
       https://doi.org/10.1145/3414685.3417847
    .. [2] A. Firmino, J. R. Frisvad, H. W. Jensen. "Progressive Denoising of Monte Carlo
       Rendered Images". Computer Graphics Forum 41(2), 2022.
       https://doi.org/10.1111/cgf.14454
    """
    yy = as_float_array("y", y, ndim=3, dtype=np.float64)
    check_nonempty("y", yy)
    _check_limit("y", yy, VALUE_LIMIT)                 # statistical weights: up front
    _check_float32_range("y", yy)                      # the denoiser's float32 copies
    _check_limit("mean_var", as_float_array("mean_var", mean_var, ndim=3, dtype=np.float64),
                 MOMENT_LIMIT)
    try:
        models = (var,) if isinstance(var, str) else tuple(var)
    except TypeError:                              # None, a number: not a sequence of names
        models = None
    if models is None or not 1 <= len(models) <= 3 \
            or any(m not in ("smooth", "raw", "max") for m in models):
        raise InputError(f"`var` must be 'smooth', 'raw', 'max' or a sequence of 1 to 3 of "
                         f"them; got {var!r}.")
    ms = _check_mix(mix, mix_sigma, yy.shape[:2])
    k = _check_window_options(size, stencil, smooth, patch)
    extra_output = as_bool("extra_output", extra_output)
    _check_sure_terms(sure_terms, extra_output)
    pr = _probe_vectors(denoiser, yy, mean_var, probes, rng, 1e-3, name="y")
    z = pr.z
    H, W, C = z.shape
    m = int(stencil)
    mv = np.asarray(mean_var, np.float64)
    sm = np.maximum(_box(mv, 2), 0.0)
    var_w = {"smooth": sm, "raw": mv, "max": np.maximum(mv, sm)}
    rel = _mix_rel(yy, z, pr, mv)
    J = 1 if mix is None else len(models)
    betas = np.empty((J, H, W, C))
    nums = np.empty((H, W, J))
    # the per-pixel SURE terms are kept for sure_terms only (2 J H W C float64: 0.2 GB at 1080p)
    keep = mix is not None and sure_terms
    gains = np.empty((J, H, W, C)) if keep else None
    wgains = np.empty((J, H, W, C)) if keep else None
    # Steps 1-3 in bands of rows (the smoothed stencils and weights of the whole image
    # would take H W (2 m² C 8 + k² 4) bytes, 4.4 GB at 1080p, and the raw stencils 2.5 GB
    # more while smoothing): a band's smoothed stencils need the
    # rows above it (the box's running sums, carried by _SmoothedRows), and its weights,
    # β̂ and SURE terms read k // 2 + patch rows on either side.
    margin = _band_margin(k, int(patch))
    rows = _band_rows(H, W * k * k * 4 + _stencil_row_bytes(W, m, C), margin)
    moments = _SmoothedRows(lambda r0, r1: pr.stencils(m, r0, r1), H, smooth)
    for a in range(0, H, rows):
        b = min(H, a + rows)
        lo, hi = max(0, a - margin), min(H, b + margin)
        cov_z, cov_yz = moments.rows(lo, hi)
        yb, zb = yy[lo:hi], z[lo:hi]
        V = np.stack([pr.v(i, lo, hi) for i in range(pr.K)]) if mix is not None else None
        for j in range(J):
            w = _statistical_weights(yb, zb, var_w[models[j]][lo:hi], cov_z, k,
                                     cov_yz=cov_yz, patch=int(patch), leave_centre_out=True,
                                     rows=(a - lo, b - lo))
            beta = combine(yb, zb, w)
            betas[j, a:b] = beta[a - lo:b - lo]
            if mix is not None:
                gain = _mix_gain(yb, zb, beta, mv[lo:hi], w, V, pr.jv[:, lo:hi])
                wg = gain * rel[lo:hi]
                nums[a:b, :, j] = wg.sum(axis=-1)[a - lo:b - lo]
                if keep:
                    gains[j, a:b] = gain[a - lo:b - lo]
                    wgains[j, a:b] = wg[a - lo:b - lo]
            del w, beta
        del cov_z, cov_yz, V
    del moments
    lam = None
    if mix is None:
        out = betas[0]
    else:
        out, lam = _pooled_mix(z, betas, nums, rel, mix, ms)
    if extra_output:
        info = {"denoised": z, "combined": betas, "mix": lam}
        if sure_terms:
            info.update(gain=gains, weighted_gain=wgains, rel=None if mix is None else rel)
        return out, info
    return out


def combine_bins(ys, mean_var, denoiser, *, size=DEFAULT_SIZE, stencil=DEFAULT_STENCIL,
                 probes=DEFAULT_PROBES, smooth=DEFAULT_MOMENT_SMOOTH, patch=2, mix="local",
                 mix_sigma=DEFAULT_MIX_SIGMA, bin_probes=None, rng=None, extra_output=False,
                 return_denoised=False, sure_terms=False):
    """Multi-buffer combination (Eq. 14 of Back et al. 2020 [1]_) of ``B`` sample bins
    and their per-bin denoised images, with classical statistical weights.

    §4.4 and "Network Input" of [1]_: the samples of each pixel are split into ``B``
    disjoint bins, ``ys[b]`` is the mean of bin ``b`` and ``z_b = denoiser(ys[b])``.  A
    denoiser that exposes its kernel is computed once from *all* samples and the kernel
    is shared by the bins, ``z_{c,b} = Σ_i w̄_i y_{i,b}`` — pass
    :class:`statmc.gem.SelectedFilter` (GEM's selection on the full render,
    :func:`statmc.gem.selected_filter`); any other callable (OIDN) is applied to each
    bin, as the paper does for denoisers without explicit weights.

    1. **Moments** of one bin's ``z_b`` by :func:`denoiser_moments` at the full-sample
       mean ``ȳ`` with per-bin variance ``B · mean_var`` (the bins have equal sample
       counts): ``cov(z_b)``, ``cov(y_b, z_b)`` are ``B`` times those of ``f(ȳ)`` —
       exact in expectation for a linear (shared) kernel, first order at ``ȳ`` for a
       black box.  Box-smoothed over ``(2 smooth + 1)²`` pixels.
    2. **Weights** :func:`statistical_weights` (``"coherent"``, per bin, tap biases
       estimated from the bins' ``δ``) with ``var(y_b) = B ·`` ``mean_var`` box-smoothed
       over 5x5 (zero-variance pixels next to lights otherwise take all the weight).
    3. **Output** Eq. 14, :func:`combine_multi`: ``β̂``.
    4. **Mix** (``mix="local"`` or ``"global"``) with ``z = f(ȳ)``, the denoiser's output
       on the merged render (the base point of the probes, so no extra call):
       ``out = z + λ (β̂ − z)``, ``0 ≤ λ ≤ 1`` minimising a SURE estimate of the relMSE
       (Eq. 1 and the optimal α of Eq. 9 of Firmino et al. 2022 [2]_), pooled as in
       :func:`combine_denoised` (relMSE weights, a Gaussian of σ = ``mix_sigma`` pixels
       or the whole image).  The weights then leave the centre out
       (``leave_centre_out=True`` of :func:`statistical_weights`) and take the tap
       biases from products of distinct bins (``z_bias="pairs"``), as Stein's lemma
       needs; see Notes.  ``mix=None`` returns ``β̂`` of the ordinary weights.

    Parameters
    ----------
    ys : (B, H, W, C) ndarray, ``B >= 2``
        Bin means (equal sample counts per bin).
    mean_var : (H, W, C) ndarray
        Variance of the mean of the full-sample mean ``ys.mean(0)``
        (``PixelStats.mean_var`` of the merged render).
    denoiser : callable ``f(color) -> color``
        Applied to each bin; a :class:`statmc.gem.SelectedFilter` shares GEM's kernel.
    size, stencil, probes, smooth, patch, rng
        As in :func:`combine_denoised`.
    mix : {"local", "global", None}
        The SURE mix with ``f(ȳ)`` (step 4), pooled over a Gaussian of σ = ``mix_sigma``
        pixels (the default: on the four built-in scenes at 16 and 64 spp, 3 seeds, it
        gave 0.95–1.00x GEM and 0.76–1.00x OIDN (session 8; cells up to 1.003x, one seed
        at 1.010x), where Eq. 14 alone gave 0.98–5.5x and 0.94–6.2x, ``docs/combine.md``)
        or the whole image (never better than ``"local"`` in session 7); ``None``: Eq. 14
        alone.
    mix_sigma : float
        As in :func:`combine_denoised` (``> 0``, at most 4x the longer side or 16).
    bin_probes : int or None
        With a mix: ``±σ`` probes of the denoiser at each bin (``B · bin_probes`` extra
        calls) for the Jacobians ``J_b`` in the Stein terms (Notes, (iii)).  None (default):
        0 for a :class:`statmc.gem.SelectedFilter`, whose Jacobian is ``K`` at every bin
        (the probes at ``ȳ`` give it), else :data:`DEFAULT_BIN_PROBES` (2).
    extra_output : bool
        Also return ``{"denoised": (B, H, W, C) z_b, "weights": (H, W, B, k, k)}`` (the
        weights of the whole image at once, whatever their size); with a mix also
        ``"full_denoised"`` (``z = f(ȳ)``), ``"combined"`` (``β̂``), ``"mix"`` (``λ``,
        ``(H, W, 1)``, or ``(1,)`` for ``"global"``) and ``"gain"`` (the per-pixel
        estimate of ``b = −E[(z − μ)(β̂ − z)]``, ``(H, W, C)``).
    return_denoised : bool
        Also return the denoised bins ``(B, H, W, C)``, as ``(out, z_b)``, keeping the
        weights in bands (``extra_output`` forms the weights of the whole image: about
        7.5 GB at 1080p with ``B = 4``).
    sure_terms : bool
        Only with ``extra_output``: with a mix the dict also holds ``"weighted_gain"``
        (``"gain"`` times ``"rel"``, what the mix pools, ``(H, W, C)``) and ``"rel"`` (its
        relMSE weights ``1 / (z² + 0.01)``, ``(H, W, C)``), as :func:`combine_denoised`'s
        ``sure_terms`` (``"gain"`` is returned with ``extra_output`` alone, as before);
        without it these keys are absent.  The output is the same either way.

    Returns
    -------
    out : (H, W, C) float64 ndarray

    Raises
    ------
    InputError
        Besides bad shapes and options: ``|ys|`` above float32's range (3.4e38; the
        denoiser gets float32 copies) or ``mean_var`` above ``MOMENT_LIMIT`` (1e290, a
        limit of :func:`statistical_weights`), checked before the denoiser runs.

    Notes
    -----
    The weights, ``H·W·B·k²`` float32 values (7.5 GB at 1920x1080 with ``B = 4``, 15x15),
    and the smoothed moment stencils, two ``(H, W, m, m, C)`` float64 arrays (2.5 GB with
    ``m = 5``), are formed in bands of rows: as many as :data:`BAND_BYTES` holds (or
    ``2 (k // 2 + patch)``, if more, so the margins cost at most twice the work), in
    equal bands, each with a margin of ``k // 2 + patch`` rows on either side, which is
    everything a pixel's weights and its Eq. 14 read.  A band's stencils come from the
    probes with ``m // 2`` rows of margin, and its box smoothing carries SciPy's running
    sums down from the band above, so the output is the one-piece output to the bit
    (tested).  Only the ``K + 1`` denoiser calls (and each bin's) see the whole image.
    Peak memory at 1920x1080 (``B = 4``, defaults, GEM's kernel): the inputs plus 1.9 GiB
    (4.9 GiB before the stencils were banded; ``bench/bench_combine.py --part memory``;
    1.94 GiB with the mix).  The mix adds the bin-summed weights of a band (counted in the
    band's size) and a few ``(H, W, C)`` float64 images (``z``, ``β̂``, the relMSE weights;
    50 MB each at 1080p; the per-pixel SURE terms are kept only for ``extra_output``); a
    black box's per-bin probes keep ``B · bin_probes`` images of ``J_b v`` (float32) and
    their signs: 2.26 GiB above the inputs at 1080p for the same kernel behind a plain
    callable.  The output equals the one-piece result to the bit (tested).

    *Scale.*  As for :func:`combine_denoised`: without the mix the output is
    scale-equivariant (``ys`` ×a, ``mean_var`` ×a², a scale-equivariant denoiser); the mix
    minimises relMSE with the metric's absolute ε = 0.01, so its λ depends on the scale
    (tested).

    With these moment-based weights every bin gets the same moments, so the weights
    differ between bins only through the tap biases; with a shared *linear* kernel and
    equal weights Eq. 14 is then Eq. 8 on the bin means (``docs/combine.md``, "Sample
    bins").  The paper's gain from bins — down-weighting the one bin whose centre holds
    an outlier — needs per-bin weights; taking them from per-bin sample variances cost
    1.23–1.51x GEM on the Cornell box (a bin that drew few bright samples has a low mean
    *and* a low variance, so inverse-variance weighting is biased low), though it held
    off a firefly render on glass-caustic (``bench/analysis_bins_combine.py``), so it is
    not offered.

    *The mix* (step 4).  Eq. 14's weights sum to one, so ``β̂`` always adds an average of
    residuals and cannot return ``z``; where the denoiser alone is better (fireflies,
    low spp) only a mix can.  It falls back to ``z = f(ȳ)``, not to the mean of the
    per-bin ``z_b``: that is the denoiser's own result on the same samples, the image
    the mix must not lose to (for the shared linear kernel the two are equal, ``Kȳ``;
    OIDN on one ``1/B``-spp bin is worse than on the merged render), and the probes'
    first-order moments are taken there.  With ``ρ = β̂ − z`` the expected squared
    error, less that of ``z``, is ``λ² E[ρ²] − 2λ b`` with ``b = −E[(z − μ) ρ]``.
    Write ``β̂_c = Σ_b Σ_t a_{t,b} (y_{t,b} + z_{c,b} − z_{t,b})`` (``Σ a = 1``) and
    ``ā_t = Σ_b a_{t,b}``.  The bins are independent with ``Var(y_{c,b}) = B σ_c²``
    (``σ² = mean_var``), so Stein's lemma over the bins gives
    ``E[(ȳ_c − μ_c) ρ_c] = Σ_b (1/B)(B σ_c²) E[∂ρ_c/∂y_{c,b}]``, and for weights that do
    not depend on ``y_c`` and ``z_b = K y_b``, ``Σ_b ∂ρ_c/∂y_{c,b} = ā_c − Σ_t ā_t K_tc``.
    Hence ``b = E[(ȳ_c − z_c) ρ_c − ā_c σ_c² + Σ_t ā_t cov(ȳ_c, z_t)]``, the estimate of
    :func:`combine_denoised` at ``(ȳ, f(ȳ))`` with the bin-summed weights ``ā``
    (:func:`_mix_gain`), ``cov(ȳ_c, z_t) = E[v_c (J v)_t]`` from the probes at ``ȳ``.
    Assumptions: (i) the weights of pixel ``c`` do not depend on ``y_c`` — hence the
    leave-centre-out tap biases from products of distinct bins (``z_bias="pairs"``); they
    still see ``y_c`` through ``z_c``, the probe moments and the 5x5 variance of the
    taps, which the estimate ignores, as does :func:`combine_denoised`; (ii) a
    kernel fixed given the data — for GEM's kernel its selection on ``ȳ`` is ignored;
    then ``ρ`` is linear in each ``y_{c,b}`` and the estimate is unbiased for any pixel
    noise, not only Gaussian (tested against the true error over bin draws); (iii) for
    a black box run per bin (OIDN), first order: ``f`` linearised at each bin, with
    Jacobian ``J_b``.  Then ``z_b`` moves with ``y_{c,b}`` by ``J_b``, ``f(ȳ)`` by
    ``J_ȳ / B``, and (the weights being equal across bins)
    ``σ_c² Σ_b ∂ρ_c/∂y_{c,b} = ā_c σ_c² + σ_c² (mean_b (J_b)_cc − (J_ȳ)_cc)
    − mean_b Σ_t ā_t σ_c² (J_b)_tc``, each term from probes:
    ``σ_c² (J_b)_tc = E[v_c (J_b v)_t] / B`` for probes ``v = ±√(B σ²)`` at bin ``b``
    (``bin_probes`` per bin), ``σ_c² (J_ȳ)_cc`` from those at ``ȳ``.  With
    ``bin_probes=0`` every ``J_b`` is taken as ``J_ȳ``, which leaves the shared-kernel
    formula above; for OIDN that is biased (a ``1/B``-spp bin sees a smoother OIDN):
    the estimated optimal global λ was −0.03 to 0.15 where the truth was 0.46–0.49
    (cornell-box, 64 spp, 3 seeds), 0.38–0.45 with 4 probes per bin.  ``z̄ − f(ȳ)``
    itself enters ``ρ`` as observed.  ``E[ρ²]`` is estimated by ``ρ²``.  Until session 8
    the weights of the mix took their tap biases from ``δ² − Var(δ)`` (``"estimate"``);
    ``Var(δ)`` of the centres near ``c`` holds the 5x5-smoothed ``mean_var`` of ``c``,
    which rises with ``y_c`` where pixels are heavy-tailed, so the weights moved with
    ``y_c`` and the estimate of ``b`` was biased low (toy ``mixed``, fixed blur, 32x32,
    200 draws: −15 % of ``b``, p = 2e-36; mean λ 0.69 where the per-draw optimum was
    0.80), the mix conservative.  With ``"pairs"`` (no ``Var(δ)``) the same run gave
    +2.1 % (p = 1e-5 with the relMSE weights, p = 0.06 without), λ 0.89 against 0.87, and
    relMSE 0.064 instead of 0.152 (``docs/combine.md``, "The bias of the SURE terms").

    References
    ----------
    .. [1] J. Back, B.-S. Hua, T. Hachisuka, B. Moon. "Deep Combiner for Independent and
       Correlated Pixel Estimates". ACM TOG 39(6), 242, 2020.
       https://doi.org/10.1145/3414685.3417847
    .. [2] A. Firmino, J. R. Frisvad, H. W. Jensen. "Progressive Denoising of Monte Carlo
       Rendered Images". Computer Graphics Forum 41(2), 2022.
       https://doi.org/10.1111/cgf.14454
    """
    extra_output = as_bool("extra_output", extra_output)
    return_denoised = as_bool("return_denoised", return_denoised)
    _check_sure_terms(sure_terms, extra_output)
    out, info = _combine_bins(ys, mean_var, denoiser, size=size, stencil=stencil,
                              probes=probes, smooth=smooth, patch=patch, mix=mix,
                              mix_sigma=mix_sigma, bin_probes=bin_probes, rng=rng,
                              whole=extra_output, sure_terms=sure_terms)
    if extra_output:
        return out, info
    if return_denoised:
        return out, info["denoised"]
    return out


def _combine_bins(ys, mean_var, denoiser, *, size, stencil, probes, smooth, patch, mix,
                  mix_sigma, rng, whole, bin_probes=None, sure_terms=False):
    """:func:`combine_bins`; returns ``(out, info)``, ``info`` as its ``extra_output``
    (``"weights"`` only with ``whole``, else None: the weights stay in bands; with a mix
    ``"gain"`` only with ``whole`` or ``sure_terms``, else None, and ``"weighted_gain"`` and
    ``"rel"`` with ``sure_terms``)."""
    yb = as_float_array("ys", ys, ndim=4, dtype=np.float64)
    check_nonempty("ys", yb, "(B, H, W, C) stack of bin images")
    _check_limit("ys", yb, VALUE_LIMIT)                # statistical weights: up front
    _check_float32_range("ys", yb)                     # the denoiser's float32 copies
    B = yb.shape[0]
    if B < 2:
        raise InputError(f"`ys` must hold B >= 2 sample bins (B, H, W, C); got B = {B}.")
    mv = as_float_array("mean_var", mean_var, ndim=3, dtype=np.float64)
    if mv.shape != yb.shape[1:]:
        raise InputError(f"`mean_var` must have the shape of one bin {yb.shape[1:]} (the "
                         f"variance of the mean of the full render); got {mv.shape}.")
    _check_limit("mean_var", mv, MOMENT_LIMIT)
    check_nonnegative("mean_var", mv)
    if not callable(denoiser):
        raise InputError(f"`denoiser` must be a callable f(color) -> color; got {denoiser!r}.")
    ms = _check_mix(mix, mix_sigma, yb.shape[1:3])
    k = _check_window_options(size, stencil, smooth, patch)
    if bin_probes is None:
        from .gem import SelectedFilter
        # a shared linear kernel has the same Jacobian K at every bin: the probes at ȳ
        # give it exactly; a black box's Jacobian at a 1/B-spp bin is another
        bin_probes = 0 if isinstance(denoiser, SelectedFilter) else DEFAULT_BIN_PROBES
    if isinstance(bin_probes, bool) or not isinstance(bin_probes, (int, np.integer)) \
            or bin_probes < 0:
        raise InputError(f"`bin_probes` must be None or an integer >= 0; got {bin_probes!r}.")
    gen = as_rng(rng)
    zs = np.stack([_denoise(denoiser, yb[b]) for b in range(B)])
    ybar = yb.mean(axis=0)
    pr = _probe_vectors(denoiser, ybar, mv, probes, gen, 1e-3)
    m = int(stencil)
    H, W, C = ybar.shape
    moments = _SmoothedRows(lambda r0, r1: pr.stencils(m, r0, r1), H, smooth, scale=B)
    var_y = B * np.maximum(_box(mv, 2), 0.0)
    if mix is None:
        out, w = _banded_eq14(yb, zs, var_y, moments, m, k, int(patch), whole=whole)
        return out, {"denoised": zs, "weights": w}
    # The mix: z = f(ȳ) (pr.z, the probes' base point), ρ = β̂ − z, and the Stein estimate
    # of b = −E[(z − μ) ρ] per pixel (_mix_gain at ȳ with the bin-summed normalised weights
    # ā_t = Σ_b w_{t,b} / W_c; see Notes), in the bands of the weights.
    z = pr.z
    rel = _mix_rel(ybar, z, pr, mv)
    nums = np.empty((H, W, 1))
    # the per-pixel SURE terms are kept for extra_output / sure_terms only (50 MB each at 1080p)
    gains = np.empty((H, W, C)) if whole or sure_terms else None
    wgains = np.empty((H, W, C)) if sure_terms else None
    jac, diag = pr, None
    if bin_probes:
        # Per-bin Jacobians J_b (probes at each bin, v ~ ±√(B σ²)): the Stein terms
        # mean_b Σ_t ā_t σ² (J_b)_tc = mean_b E[v_c (A J_b v)_c] / B (through _mix_gain with
        # v / B) and σ² (mean_b (J_b)_cc − (J_ȳ)_cc), the part of ∂ρ_c/∂y_c from z̄ − f(ȳ).
        jac = _bin_probe_vectors(denoiser, yb, zs, mv, int(bin_probes), gen, 1e-3)
        diag = np.zeros((H, W, C))
        for i in range(pr.K):                        # − σ² (J_ȳ)_cc, no (K, H, W, C) copies
            diag -= pr.v(i) * pr.jv[i] / pr.K
        for i in range(jac.K):                       # + σ² mean_b (J_b)_cc
            diag += jac.v(i) * jac.jv[i] / (B * jac.K)

    def band(a, b, lo, hi, w, beta):
        wsum = w.sum(axis=2, keepdims=True)          # (rows, W, 1, k, k), float32
        scale = 1.0 if jac is pr else 1.0 / B
        V = np.stack([jac.v(i, lo, hi) * scale for i in range(jac.K)])
        gain = _mix_gain(ybar[lo:hi], z[lo:hi], beta, mv[lo:hi], wsum, V, jac.jv[:, lo:hi])
        if diag is not None:
            gain -= diag[lo:hi]
        wg = gain * rel[lo:hi]
        nums[a:b, :, 0] = wg.sum(axis=-1)[a - lo:b - lo]
        if gains is not None:
            gains[a:b] = gain[a - lo:b - lo]
        if sure_terms:
            wgains[a:b] = wg[a - lo:b - lo]

    beta, w = _banded_eq14(yb, zs, var_y, moments, m, k, int(patch), whole=whole, loo=True,
                           band=band, extra_row_bytes=W * k * k * 4, z_bias=_MIX_Z_BIAS)
    del moments
    out, lam = _pooled_mix(z, beta[None], nums, rel, mix, ms)
    info = {"denoised": zs, "weights": w, "full_denoised": z, "combined": beta, "mix": lam,
            "gain": gains}
    if sure_terms:
        info.update(weighted_gain=wgains, rel=rel)
    return out, info


def _check_window_options(size, stencil, smooth, patch):
    """The window ``k`` after checking the options of :func:`combine_denoised`,
    :func:`combine_bins` and :func:`combine_bin_images` (before any denoiser call)."""
    k = _check_size(size)
    for name, v in (("smooth", smooth), ("patch", patch)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise InputError(f"`{name}` must be an integer >= 0; got {v!r}.")
    if isinstance(stencil, bool) or not isinstance(stencil, (int, np.integer)) or stencil < 1 \
            or stencil % 2 == 0:
        raise InputError(f"`stencil` (the covariance stencil width m) must be an odd integer "
                         f">= 1; got {stencil!r}.")
    return k


def _banded_eq14(ys, zs, var_y, moments, m, k, patch, *, whole=False, loo=False, band=None,
                 extra_row_bytes=0, z_bias="estimate"):
    """Statistical weights and Eq. 14 in bands of rows (:func:`_band_rows`: weights and
    ``m``-wide stencils within :data:`BAND_BYTES`), each with the ``k // 2 + patch`` rows
    of margin a pixel's weights and its Eq. 14 read; ``moments`` (:class:`_SmoothedRows`)
    gives each band's smoothed ``cov_z``, ``cov_yz`` (``whole``: one band; returns its
    weights too).  ``loo``, ``z_bias``: of the weights (:func:`statistical_weights`).
    ``band(a, b, lo, hi, w, beta)``, if given, sees each band's weights and Eq. 14 on
    rows ``lo .. hi − 1`` (its output rows ``a .. b − 1``), e.g. for the SURE terms of
    the mix; ``extra_row_bytes`` is what it holds per row, counted in the band size."""
    B, H, W, C = ys.shape
    margin = _band_margin(k, patch)
    rows = H if whole else _band_rows(H, W * B * k * k * 4 + _stencil_row_bytes(W, m, C)
                                      + extra_row_bytes, margin)
    out = np.empty(ys.shape[1:])
    w = None
    for a in range(0, H, rows):
        b = min(H, a + rows)
        lo, hi = max(0, a - margin), min(H, b + margin)
        w = None                           # free the previous band's weights first
        cov_z, cov_yz = moments.rows(lo, hi)
        w = _statistical_weights(ys[:, lo:hi], zs[:, lo:hi], var_y[lo:hi], cov_z, k,
                                 cov_yz=cov_yz, patch=patch, leave_centre_out=loo,
                                 z_bias=z_bias, rows=None if whole else (a - lo, b - lo))
        del cov_z, cov_yz
        beta = combine_multi(ys[:, lo:hi], zs[:, lo:hi], w)
        out[a:b] = beta[a - lo:b - lo]
        if band is not None:
            band(a, b, lo, hi, w, beta)
        del beta
    return out, (w if whole else None)


def combine_bin_images(ys, zs, *, size=DEFAULT_SIZE, stencil=DEFAULT_STENCIL,
                       smooth=DEFAULT_MOMENT_SMOOTH, patch=2):
    """Eq. 14 of Back et al. 2020 [1]_ on given bins and per-bin correlated images, with
    statistical weights whose moments come from the spread over the bins.

    For bins made elsewhere — ``bins.exr`` of ``statmc render --reconstruct gem+bins`` with
    the ``Bin<b>.Denoised`` channels replaced by another denoiser's per-bin output, say —
    nothing but the ``B`` pairs ``(y_b, z_b)`` is known.  §4.4 of [1]_ makes the bins
    disjoint sample subsets, so the pairs are i.i.d. over ``b`` when ``z_b`` is computed
    from bin ``b`` (for a kernel shared by the bins, nearly so) and
    :func:`buffer_moments` estimates the moments of one bin from their spread (``B − 1``
    degrees of freedom; ``stencil``-wide, box-smoothed over ``(2 smooth + 1)²`` pixels).
    The weights are :func:`statistical_weights` ("coherent", tap biases from the bins'
    ``δ``).  Moments and weights are formed in bands of rows like :func:`combine_bins`
    (the same output as in one piece, to the bit).

    Parameters
    ----------
    ys, zs : (B, H, W, C) or (B, H, W) ndarray, ``B >= 2``
    size, stencil, smooth, patch : int
        Window, moment stencil (odd), moment smoothing radius, bias-box radius.

    Returns
    -------
    out : (H, W, C) float64 ndarray (``(H, W)`` for ``(B, H, W)`` bins)

    Raises
    ------
    InputError
        Besides bad shapes and options: ``|ys|`` or ``|zs|`` above ``VALUE_LIMIT``
        (1e140), the limit of :func:`statistical_weights`.
    """
    ysa, zsa, squeeze = _pair("ys", ys, "zs", zs, multi=True)
    _check_limit("ys", ysa, VALUE_LIMIT)               # statistical weights: up front
    _check_limit("zs", zsa, VALUE_LIMIT)
    k = _check_window_options(size, stencil, smooth, patch)
    ysa, zsa = ysa.astype(np.float64), zsa.astype(np.float64)
    H, m = ysa.shape[1], int(stencil)
    var_y = buffer_moments(ysa, zsa, size=1)[0]
    var_y = np.maximum(_box(var_y, int(smooth)), 0.0)  # the box's running sums leave -1e-19

    def raw(r0, r1):
        """Stencil rows r0 .. r1 - 1 from a slab with m // 2 rows of margin (the same
        products and sums as on the whole image)."""
        s0, s1 = max(0, r0 - m // 2), min(H, r1 + m // 2)
        _, cz, cyz = buffer_moments(ysa[:, s0:s1], zsa[:, s0:s1], size=m)
        return cz[r0 - s0:r1 - s0], cyz[r0 - s0:r1 - s0]

    moments = _SmoothedRows(raw, H, int(smooth))
    out = _banded_eq14(ysa, zsa, var_y, moments, m, k, int(patch))[0]
    return out[..., 0] if squeeze else out     # (B, H, W) bins give (H, W), as combine_multi
