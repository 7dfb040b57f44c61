"""Image error metrics against a reference: relMSE, MSE, RMSE, SMAPE, logLoss, 1−SSIM, FLIP.

All take the test image ``x`` first and the reference ``ref`` second, both ``(H, W, C)``
(or ``(H, W)``, read as one channel) of the same shape and finite.  Each returns the
mean over pixels and channels as a Python ``float``; ``per_pixel=True`` returns instead
the ``(H, W)`` map averaged over channels (for RMSE the root of the per-pixel MSE).
Computations run in float64.

References
----------
.. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and Reconstruction using
   Greedy Error Minimization", ACM TOG 30(6), 2011. doi:10.1145/2070781.2024193
.. [2] F. Salehi, M. Manzi, G. Roethlin, R. Weber, C. Schroers, M. Papas, "Deep Adaptive
   Sampling and Reconstruction using Analytic Distributions", ACM TOG 41(6), 2022.
   doi:10.1145/3550454.3555515
.. [3] Z. Wang, A. C. Bovik, H. R. Sheikh, E. P. Simoncelli, "Image Quality Assessment:
   From Error Visibility to Structural Similarity", IEEE TIP 13(4), 2004.
   doi:10.1109/TIP.2003.819861
.. [4] P. Andersson, J. Nilsson, T. Akenine-Möller, M. Oskarsson, K. Åström,
   M. D. Fairchild, "FLIP: A Difference Evaluator for Alternating Images", Proc. ACM
   Comput. Graph. Interact. Tech. 3(2), 2020. doi:10.1145/3406183
.. [5] T. Vogels, F. Rousselle, B. McWilliams, G. Röthlin, A. Harvill, D. Adler, M. Meyer,
   J. Novák, "Denoising with Kernel Prediction and Asymmetric Loss Functions", ACM TOG
   37(4), 2018. doi:10.1145/3197517.3201388
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage

from .errors import InputError, as_bool, as_float_array, check_finite, real_or_nan

__all__ = ["relmse", "mse", "rmse", "smape", "logloss", "one_minus_ssim", "ssim_map", "flip",
           "all_metrics", "METRICS"]

_FLT_EPS = float(np.finfo(np.float32).eps)
# Tone-curve coefficients FLIP uses to pick its exposure range (flip_evaluator, HDR-FLIP [4] §4).
_FLIP_TONEMAP = {
    "aces": (0.6 * 0.6 * 2.51, 0.6 * 0.03, 0.0, 0.6 * 0.6 * 2.43, 0.6 * 0.59, 0.14),
    "hable": (0.231683, 0.013791, 0.0, 0.18, 0.3, 0.018),
    "reinhard": (0.0, 1.0, 0.0, 0.0, 1.0, 1.0),
}


# flip_evaluator's wheel bundles its own libgomp, which reads its settings from the
# environment once, when it is loaded.  Its default wait policy spins at every barrier of
# FLIP's many short parallel regions; on a busy machine a spinning thread holds a core the
# thread it waits for needs: with two nice-10 busy loops on the two cores a 16x16 call took
# ~210 ms instead of ~0.6 ms, a 256x256 one ~350 ms instead of ~170 ms
# (bench/bench_flip_load.py).  "PASSIVE" makes waiting threads sleep instead; the thread
# count stays, and the values are the same bit for bit (checked there and in the tests).
def _flip_module():
    """``flip_evaluator``, imported with its bundled OpenMP runtime set to wait passively
    (:func:`statmc._threads.import_passively`: the user's environment is unchanged
    afterwards, a wait policy the user set is kept, an earlier import is returned as is,
    and an import still running in another thread is waited for)."""
    from ._threads import import_passively

    return import_passively("flip_evaluator")


def _pair(x, ref):
    """Validate a test/reference pair; return float64 (H, W, C) copies."""
    xa = as_float_array("x", x, ndim=(2, 3))
    ra = as_float_array("ref", ref, ndim=(2, 3))
    if xa.shape != ra.shape:
        raise InputError(f"`x` and `ref` must have the same shape; got x {xa.shape} and ref {ra.shape}.")
    if xa.size == 0:
        raise InputError(f"`x` and `ref` must not be empty; got shape {xa.shape}.")
    check_finite("x", xa)
    check_finite("ref", ra)
    if xa.ndim == 2:
        xa, ra = xa[..., None], ra[..., None]
    return xa.astype(np.float64), ra.astype(np.float64)


def _eps(eps, name="eps"):
    e = real_or_nan(eps)                  # a string or None is refused below, not parsed
    if not np.isfinite(e) or e < 0:
        raise InputError(f"`{name}` must be a finite number >= 0; got {eps!r}.")
    return e


def _positive(name, value, what="a positive number") -> float:
    """``value`` as a float > 0, else an :class:`InputError` naming ``name`` (a string,
    None or NaN was a TypeError of ``np.isfinite`` or passed on to the arithmetic)."""
    v = real_or_nan(value)
    if not np.isfinite(v) or v <= 0:
        raise InputError(f"`{name}` must be {what}; got {value!r}.")
    return v


def _constant(name, value, usual) -> float:
    """An SSIM stabilising constant: a finite float >= 0 (``k1 = k2 = 0`` is Wang and
    Bovik's universal quality index, 2002), else an :class:`InputError` naming ``name``."""
    v = real_or_nan(value)
    if not np.isfinite(v) or v < 0:
        raise InputError(f"`{name}` must be a constant >= 0 ({usual}); got {value!r}.")
    return v


def _reduce(err, per_pixel):
    """Mean over channels per pixel (map) or over everything (float)."""
    return err.mean(axis=2) if as_bool("per_pixel", per_pixel) else float(err.mean())


def relmse(x, ref, eps: float = 0.01, *, per_pixel: bool = False):
    """Relative mean squared error ``mean((x − r)² / (r² + ε))`` (relMSE, also called MRSE).

    Parameters
    ----------
    x, ref : (H, W, C) or (H, W) ndarray
        Test image and reference.
    eps : float, default 0.01
        ``ε`` of §7 of [1]_, which keeps dark pixels from dominating.  ``eps = 0`` needs a
        reference without zeros.
    per_pixel : bool, default False
        Return the ``(H, W)`` map (mean over channels) instead of the mean.

    Notes
    -----
    Relative pixel MSE ``(img − ref)²/(ref² + ε)`` averaged over the image, ε = 0.01
    (§7 "Results" of Rousselle et al. [1]_).

    Examples
    --------
    >>> relmse(np.array([[2.0]]), np.array([[1.0]]), eps=0.0)
    1.0
    """
    xa, ra = _pair(x, ref)
    e = _eps(eps)
    with np.errstate(over="ignore"):
        den = ra * ra + e
    if e == 0 and np.any(den == 0):
        raise InputError("`eps` = 0 needs a reference without zeros; got "
                         f"{int((den == 0).sum())} zero values in `ref`. Use eps > 0.")
    with np.errstate(over="ignore", invalid="ignore"):
        err = (xa - ra) ** 2 / den
        out = _reduce(err, per_pixel)
    if np.isfinite(out).all():      # every entry is >= 0: a NaN or inf one reaches its mean
        return out
    bad = ~np.isfinite(err)         # |x|, |r| beyond ~1e154: the squares overflow (inf/inf),
    xb, rb = xa[bad], ra[bad]       # not the ratio
    s = np.maximum(np.abs(xb), np.abs(rb))
    with np.errstate(divide="ignore", under="ignore", over="ignore"):   # inf if it is
        err[bad] = ((xb / s - rb / s) / np.hypot(rb / s, np.sqrt(e) / s)) ** 2
        return _reduce(err, per_pixel)


def mse(x, ref, *, per_pixel: bool = False):
    """Mean squared error ``mean((x − r)²)``."""
    xa, ra = _pair(x, ref)
    return _reduce((xa - ra) ** 2, per_pixel)


def rmse(x, ref, *, per_pixel: bool = False):
    """Root mean squared error ``sqrt(mean((x − r)²))``; per pixel the root of the pixel's MSE."""
    m = mse(x, ref, per_pixel=per_pixel)
    return np.sqrt(m) if per_pixel else float(np.sqrt(m))


def smape(x, ref, eps: float = 0.01, *, per_pixel: bool = False):
    """Symmetric mean absolute percentage error ``mean(|x − r| / (|x| + |r| + ε))``.

    SMAPE as used for denoiser training by Vogels et al. [5]_ and for evaluation by
    Firmino et al. (2022); ``ε = 0.01`` avoids division by zero on black pixels.  It is
    symmetric in ``x`` and ``ref`` and lies in ``[0, 1)``.

    Examples
    --------
    >>> round(smape(np.array([[3.0]]), np.array([[1.0]]), eps=0.0), 12)
    0.5
    """
    xa, ra = _pair(x, ref)
    e = _eps(eps)
    den = np.abs(xa) + np.abs(ra) + e
    if e == 0 and np.any(den == 0):
        raise InputError("`eps` = 0 needs no pixel where both `x` and `ref` are 0; use eps > 0.")
    return _reduce(np.abs(xa - ra) / den, per_pixel)


#: Kernels up to this many taps a side are applied as they are (bit for bit as always);
#: longer ones are folded onto the image's reflection (:func:`_folded_taps`).  The number
#: of :func:`statmc.filters._taps`.
_MAX_FULL_RADIUS = 4096
#: The longest kernel folded (taps a side): folding visits every tap once, in chunks, ~0.5 s
#: here at this length; a σ whose kernel is longer (~4.2e6 px for the LoG, ~4.8e6 for SSIM)
#: is refused rather than left to run for minutes or hours.
_MAX_FOLD_RADIUS = 2 ** 24
_FOLD_CHUNK = 2 ** 16


def _kernel_radius(sigma, truncate, what):
    """``int(truncate σ + 0.5)`` taps a side (scipy's), refused past :data:`_MAX_FOLD_RADIUS`."""
    rad = truncate * sigma + 0.5
    if rad > _MAX_FOLD_RADIUS:
        most = (_MAX_FOLD_RADIUS - 0.5) / truncate
        raise InputError(f"`sigma` must be at most {most:.4g} pixels for {what} (its kernel of "
                         f"2·int({truncate:g}σ + 0.5) + 1 taps is folded onto the image, one "
                         f"tap at a time); got {sigma!r}. A σ far wider than the image already "
                         "blurs it to nearly its mean: a few times max(H, W) gives nearly the "
                         "same result.")
    return int(rad)


def _folded_taps(sigma, rad, n, second=False):
    """Gaussian taps ``exp(−t²/2σ²)`` on ``t = −rad … rad`` (and with ``second`` the
    ``(t² − σ²)/σ⁴`` weighted ones) folded onto ``2n`` offsets ``−n … n − 1`` for a line
    of ``n`` pixels, with the sums of all taps.

    With ``mode="reflect"`` the line is extended as ``… d c b a | a b c d | d c b a …``,
    which repeats every ``2n`` pixels, so taps whose offsets are equal modulo ``2n`` always
    meet the same pixel: summing them (folding) gives a ``2n``-tap kernel whose
    correlation is the same as the long kernel's up to rounding, at a cost and size that
    no longer grow with σ.  Offset ``m`` lands at index ``m + n`` (the centre of an
    even-length ``correlate1d`` kernel).  Returns ``(g, sum g, g2, sum g2)`` unnormalised
    (``g2`` None without ``second``).
    """
    period = 2 * n
    g = np.zeros(period)
    g2 = np.zeros(period) if second else None
    sg = sg2 = 0.0
    for lo in range(-rad, rad + 1, _FOLD_CHUNK):
        t = np.arange(lo, min(lo + _FOLD_CHUNK, rad + 1), dtype=np.float64)
        e = np.exp(-0.5 * t * t / (sigma * sigma))
        idx = (t.astype(np.int64) + n) % period
        g += np.bincount(idx, weights=e, minlength=period)
        sg += float(e.sum())
        if second:
            e2 = (t * t - sigma * sigma) / sigma ** 4 * e
            g2 += np.bincount(idx, weights=e2, minlength=period)
            sg2 += float(e2.sum())
    return g, sg, g2, sg2


def _laplacian_of_gaussian(a, sigma):
    """Laplacian of Gaussian of each channel of ``a`` (H, W, C), reflecting at borders.

    Separable: ``g'' ⊗ g + g ⊗ g''`` with ``g`` the normalised Gaussian sampled on
    ``[−4σ, 4σ]`` and ``g''(t) = (t² − σ²)/σ⁴ · g(t)``, made zero-sum by subtracting
    ``(Σ g'') g`` so that constants map to 0 as for the continuous operator (the plain
    sampled kernel of ``scipy.ndimage.gaussian_laplace`` leaves a ~1e-4 residue).

    A kernel longer than :data:`_MAX_FULL_RADIUS` taps a side is folded onto the
    reflection's period, per axis (:func:`_folded_taps`): the same result up to rounding,
    in memory and time that do not grow with σ (σ = 1e6 on 16×16 took 28 s and 244 MiB).
    σ beyond :data:`_MAX_FOLD_RADIUS` taps is refused.
    """
    rad = _kernel_radius(sigma, 4.0, "the logLoss LoG")

    def sep(a, k0, k1):
        return ndimage.correlate1d(ndimage.correlate1d(a, k0, axis=0, mode="reflect"),
                                   k1, axis=1, mode="reflect")

    if rad > _MAX_FULL_RADIUS:
        kern = {}
        for n in {a.shape[0], a.shape[1]}:
            g, sg, g2, sg2 = _folded_taps(sigma, rad, n, second=True)
            g /= sg
            kern[n] = (g, g2 / sg - (sg2 / sg) * g)      # zero-sum, as below
        (g0, d0), (g1, d1) = kern[a.shape[0]], kern[a.shape[1]]
        return sep(a, d0, g1) + sep(a, g0, d1)
    t = np.arange(-rad, rad + 1, dtype=np.float64)
    g = np.exp(-0.5 * t * t / (sigma * sigma))
    g /= g.sum()
    g2 = (t * t - sigma * sigma) / sigma ** 4 * g
    g2 -= g2.sum() * g
    return sep(a, g2, g) + sep(a, g, g2)


def logloss(x, ref, eps: float = 0.01, *, sigma: float = 1.0, per_pixel: bool = False):
    """logLoss of Eq. 12 of Salehi et al. [2]_ (after Kuznetsov et al. 2018).

    With ``x' = log(1 + x)`` and ``r' = log(1 + ref)``::

        ℓ = 0.5 |x' − r'| / (r' + ε) + 0.5 |L(x') − L(r')| / (r' + ε)

    where ``L`` is the Laplacian-of-Gaussian operator, applied per channel; the loss is
    the mean of ``ℓ`` over pixels and channels ("the mean of the logLoss over all image
    pixels", §4.5 of [2]_).

    Parameters
    ----------
    x, ref : (H, W, C) or (H, W) ndarray
        Test image (values > −1) and reference (values >= 0).
    eps : float, default 0.01
        ``ε`` of Eq. 12 of [2]_.
    sigma : float, default 1.0
        Standard deviation (pixels) of the LoG.  [2]_ does not state it; 1 px is our
        choice.  See :func:`_laplacian_of_gaussian` for the discrete kernel.
    per_pixel : bool, default False
        Return the ``(H, W)`` map of ``ℓ`` averaged over channels.
    """
    xa, ra = _pair(x, ref)
    e = _eps(eps)
    sigma = _positive("sigma", sigma, "a positive number of pixels")
    if xa.min() <= -1:
        raise InputError(f"`x` must be > -1 for log(1 + x); got min {xa.min():.4g}.")
    if ra.min() < 0:
        raise InputError(f"`ref` must be >= 0 (radiance) for logLoss; got min {ra.min():.4g}.")
    xl, rl = np.log1p(xa), np.log1p(ra)
    den = rl + e
    if e == 0 and np.any(den == 0):
        raise InputError("`eps` = 0 needs a reference without zeros; use eps > 0.")
    lap = _laplacian_of_gaussian(xl - rl, sigma)           # L is linear: L(x') − L(r')
    err = 0.5 * np.abs(xl - rl) / den + 0.5 * np.abs(lap) / den
    return _reduce(err, per_pixel)


def ssim_map(x, ref, *, data_range: float = 1.0, sigma: float = 1.5, k1: float = 0.01,
             k2: float = 0.03) -> np.ndarray:
    """Per-pixel, per-channel SSIM index (Eq. 13 of Wang et al. [3]_), ``(H, W, C)``.

    ``SSIM = (2 μx μy + C1)(2 σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2))`` with
    ``C1 = (k1 L)²``, ``C2 = (k2 L)²``, ``L = data_range``, and local moments weighted by
    a Gaussian window of standard deviation ``sigma`` (1.5 px, truncated at 3.5σ: the
    11×11 window of §III.C of [3]_), normalised, without the ``N/(N−1)`` correction.
    Borders use reflection, so the map covers the whole image.  A window longer than
    :data:`_MAX_FULL_RADIUS` taps a side is folded onto the reflection's period (the same
    up to rounding, :func:`_folded_taps`); σ past :data:`_MAX_FOLD_RADIUS` taps is refused.
    """
    xa, ra = _pair(x, ref)
    data_range = _positive("data_range", data_range)
    sigma = _positive("sigma", sigma, "a positive number of pixels")
    k1 = _constant("k1", k1, "0.01 in Wang et al. 2004")
    k2 = _constant("k2", k2, "0.03 in Wang et al. 2004")
    # SSIM is unchanged when x, ref and L are scaled together: work in units of L, so that
    # HDR values and ranges beyond ~1e154 do not overflow the squares (exact for L = 1)
    if data_range != 1.0:
        xa, ra = xa / data_range, ra / data_range
    c1, c2 = k1 ** 2, k2 ** 2

    rad = _kernel_radius(sigma, 3.5, "SSIM's window")
    if rad > _MAX_FULL_RADIUS:   # fold the window onto the reflection (see _folded_taps)
        kern = {}
        for n in {xa.shape[0], xa.shape[1]}:
            g, sg, _, _ = _folded_taps(sigma, rad, n)
            kern[n] = g / sg

        def blur(a):
            b = ndimage.correlate1d(a, kern[a.shape[0]], axis=0, mode="reflect")
            return ndimage.correlate1d(b, kern[a.shape[1]], axis=1, mode="reflect")
    else:
        def blur(a):
            return ndimage.gaussian_filter(a, sigma=(sigma, sigma, 0), mode="reflect",
                                           truncate=3.5)

    with np.errstate(over="ignore", invalid="ignore"):
        mx, my = blur(xa), blur(ra)
        vx = blur(xa * xa) - mx * mx
        vy = blur(ra * ra) - my * my
        cxy = blur(xa * ra) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    if not np.isfinite(s).all():
        if c1 == 0 or c2 == 0:
            zero = " and ".join(f"`{k}`" for k, c in (("k1", c1), ("k2", c2)) if c == 0)
            raise InputError(f"SSIM with {zero} = 0 is 0/0 in a window where both images are "
                             "constant (or both black); use positive constants, or images "
                             "without such windows.")
        big = max(float(np.abs(xa).max()), float(np.abs(ra).max())) * data_range
        raise InputError(f"`x` and `ref` are too large for SSIM at `data_range`={data_range!r} "
                         f"(max |value| {big:.3g}, whose square overflows); pass the range "
                         "they span as `data_range`, or tone-map them first.")
    return s


def one_minus_ssim(x, ref, *, data_range: float = 1.0, sigma: float = 1.5,
                   per_pixel: bool = False):
    """``1 − SSIM`` (Wang et al. [3]_), mean over pixels and channels; see :func:`ssim_map`.

    ``data_range`` is the dynamic range ``L`` (1 for display-referred images in [0, 1]);
    for linear HDR radiance tone-map first (e.g. :func:`statmc.exr.to_display`) or pass
    the range you compare at.
    """
    s = ssim_map(x, ref, data_range=data_range, sigma=sigma)
    return _reduce(1.0 - s, per_pixel)


def _flip_exposures(ref_rgb, test_rgb, tonemapper):
    """FLIP's exposure range for a (near-)black reference, or None to let FLIP choose.

    HDR-FLIP ([4]_, flip_evaluator) starts at ``log2(x_max / Y_max)`` and stops at
    ``log2(x_max / Y_median)`` of the reference luminance, the median (FLIP's: the
    element of rank ``⌊N/2⌋`` of the sorted values, the upper middle one for even ``N``)
    clamped at float32 epsilon, ``x_max`` being where the tone curve reaches 0.85.  When
    ``Y_max`` is below that epsilon the start exceeds the stop (or is infinite) and
    flip_evaluator ends the process.  We then keep FLIP's start, anchored at the test
    image's maximum when the reference is all black, and raise the stop to the start;
    FLIP's scale invariance (``FLIP(c x, c r) = FLIP(x, r)``) is kept.  Returns
    ``"zero"`` when both images are black.
    """
    w = np.array([0.2126, 0.7152, 0.0722])               # linear sRGB luminance, as FLIP
    y_ref = ref_rgb @ w
    y_max = float(y_ref.max())
    if y_max > 4 * _FLT_EPS:
        return None
    anchor = y_max if y_max > 0 else float((test_rgb @ w).max())
    if anchor <= 0:
        return "zero"
    a0, b0, c0, d0, e0, f0 = _FLIP_TONEMAP[tonemapper]
    t = 0.85
    a, b, c = a0 - t * d0, b0 - t * e0, c0 - t * f0
    xmax = -c / b if a == 0 else float(max(np.roots([a, b, c]).real))
    start = float(np.log2(xmax / anchor))
    flat = y_ref.ravel()
    med = float(np.partition(flat, flat.size // 2)[flat.size // 2])   # FLIP's "median"
    stop = max(start, float(np.log2(xmax / max(med, _FLT_EPS))))
    return start, stop


def flip(x, ref, *, tonemapper: str = "aces", ppd: float | None = None,
         negative: str = "clip", per_pixel: bool = False):
    """HDR-FLIP error of ``x`` against ``ref`` (Andersson et al. [4]_), via ``flip_evaluator``.

    Parameters
    ----------
    x, ref : (H, W, 3) or (H, W) / (H, W, 1) ndarray
        Linear radiance; one channel is repeated to grey RGB.
    tonemapper : {"aces", "hable", "reinhard"}
        Tone curve HDR-FLIP assumes.
    ppd : float, optional
        Pixels per degree of visual angle (FLIP's default, about 67, when None).
    negative : {"clip", "error"}, default "clip"
        HDR-FLIP needs non-negative input: negative values (rounding residue such as
        −1e-16, or signed estimators) are clipped to 0 (no light), or raise InputError.
    per_pixel : bool
        Return FLIP's ``(H, W)`` error map instead of its mean.

    Notes
    -----
    The parameters are validated here because flip_evaluator ends the process
    (``sys.exit``) on invalid ones, and an all-black reference (which it cannot handle)
    gets an explicit exposure range (see ``_flip_exposures``).

    flip_evaluator runs on its own bundled OpenMP runtime.  statmc imports it with that
    runtime's ``OMP_WAIT_POLICY`` set to ``PASSIVE`` (for the import only, the environment
    is restored): its default spin-waiting made a small call take ~200 ms instead of
    ~1 ms on a busy machine.  A wait policy set by the user (``OMP_WAIT_POLICY`` or
    ``GOMP_SPINCOUNT`` in the environment), or an earlier ``import flip_evaluator``, is
    left as it is.  The values do not change.
    """
    flip_evaluator = _flip_module()

    xa, ra = _pair(x, ref)
    per_pixel = as_bool("per_pixel", per_pixel)
    if xa.shape[2] == 1:
        xa, ra = np.repeat(xa, 3, axis=2), np.repeat(ra, 3, axis=2)
    if xa.shape[2] != 3:
        raise InputError(f"`x` and `ref` must have 1 or 3 channels for FLIP; got {xa.shape}.")
    if negative not in ("clip", "error"):
        raise InputError(f"`negative` must be 'clip' or 'error'; got {negative!r}.")
    for name, a in (("x", xa), ("ref", ra)):
        if negative == "error" and a.min() < 0:
            raise InputError(f"`{name}` must be >= 0 for HDR-FLIP (linear radiance); got "
                             f"{int((a < 0).sum())} negative values (min {a.min():.4g}); "
                             "clip them first, e.g. np.maximum(x, 0), or pass negative='clip'.")
    xa, ra = np.maximum(xa, 0.0), np.maximum(ra, 0.0)
    if tonemapper not in _FLIP_TONEMAP:
        raise InputError(f"`tonemapper` must be one of {sorted(_FLIP_TONEMAP)}; got {tonemapper!r}.")
    params = {"tonemapper": tonemapper}
    if ppd is not None:
        params["ppd"] = _positive("ppd", ppd, "a positive number of pixels per degree")
    exposures = _flip_exposures(ra, xa, tonemapper)
    if isinstance(exposures, str):                       # both images black: no difference
        return np.zeros(xa.shape[:2]) if per_pixel else 0.0
    if exposures is not None:
        params["startExposure"], params["stopExposure"] = exposures
    xf = np.ascontiguousarray(xa, dtype=np.float32)
    rf = np.ascontiguousarray(ra, dtype=np.float32)
    check_finite("x (as float32)", xf)
    check_finite("ref (as float32)", rf)
    err_map, mean_err, _ = flip_evaluator.evaluate(rf, xf, "HDR", applyMagma=False,
                                                   computeMeanError=True, parameters=params)
    err_map = np.asarray(err_map, dtype=np.float64).reshape(xa.shape[:2])
    return err_map if per_pixel else float(mean_err)


METRICS = {
    "relmse": relmse,
    "mse": mse,
    "rmse": rmse,
    "smape": smape,
    "logloss": logloss,
    "one_minus_ssim": one_minus_ssim,
    "flip": flip,
}


def all_metrics(x, ref, *, per_pixel: bool = False, include=None) -> dict:
    """All metrics of ``x`` against ``ref`` with their default parameters.

    Parameters
    ----------
    x, ref : (H, W, C) or (H, W) ndarray
    per_pixel : bool
        Maps ``(H, W)`` instead of floats.
    include : str or iterable of str, optional
        Names from :data:`METRICS` to compute (all by default; one name may be given
        alone).  FLIP needs 1- or
        3-channel images (and clips negative values to 0); leave it out otherwise.

    Returns
    -------
    dict
        ``{name: value}`` in the order of :data:`METRICS`.  ``"logloss"`` is None, with a
        ``RuntimeWarning`` saying why, when the images are outside its domain (a
        reference with negative values, such as a noisy render with rounding residue, or
        a test image <= −1), so that it does not stop the other metrics; call
        :func:`logloss` directly to get the error instead.
    """
    if isinstance(include, str):               # one name: not its letters
        include = [include]
    names = list(METRICS) if include is None else list(include)
    unknown = [n for n in names if n not in METRICS]
    if unknown:
        raise InputError(f"`include` must name metrics from {list(METRICS)}; got unknown "
                         f"{unknown}.")
    xa, ra = _pair(x, ref)             # validate once with a clear message
    as_bool("per_pixel", per_pixel)
    out = {}
    for n in METRICS:
        if n not in names:
            continue
        why = _logloss_domain(xa, ra) if n == "logloss" else None
        if why:
            warnings.warn(f"statmc: logloss left out (null): {why}", RuntimeWarning, stacklevel=2)
            out[n] = None
        else:
            out[n] = METRICS[n](x, ref, per_pixel=per_pixel)
    return out


def _logloss_domain(xa, ra) -> str | None:
    """Why :func:`logloss` cannot score ``xa`` against ``ra`` (None if it can)."""
    if ra.min() < 0:
        return (f"the reference has {int((ra < 0).sum())} negative values (min {ra.min():.4g}); "
                "logLoss needs a reference >= 0.")
    if xa.min() <= -1:
        return f"the image has values <= -1 (min {xa.min():.4g}); logLoss needs x > -1."
    return None
