"""Progressive denoising: a per-pixel mix of a render and its denoised image that converges.

Firmino, Frisvad and Jensen (2022) [1]_ mix a Monte Carlo render ``x`` (unbiased, variance
of the mean ``σ²``) with its denoised counterpart ``y = f(x)`` (biased),
``z = x + α (y − x)``, and bound ``α`` with a confidence test — a t-statistic (Eq. 17)
through a shifted standard normal CDF (Eq. 18), two-sided, with no Student-t quantile or
degrees of freedom — so that ``z → μ`` as samples accumulate.  This module is the
classical part:

* :func:`mixing_weights` — the mixing parameter that minimises the expected squared error
  of ``z`` (Eq. 8), Eq. 9 (and Eq. 10, ``β = 1 − α``), from locally smoothed estimates of
  ``σ²``, ``SURE(y)`` and the divergence ``σ² f'(x)``; :func:`mix_error` is Eq. 8 itself;
  :func:`as_mix_inputs` checks and converts the five maps of Eq. 8–10 (what a network
  predicting ``α`` gets, :func:`statmc.nn.mix_features`);
* :func:`confidence_gate` — the t-statistic gating of Eq. 12–18 (11×11 neighbourhood,
  max-variance neighbour, ``σ_s``, ``S`` = normal CDF, ``c = 4.2``, ``a = 2``), which
  also takes a network-predicted ``α`` (:mod:`statmc.nn`) unchanged;
* :func:`progressive_denoise` — the pipeline: denoise, MC-SURE (:func:`statmc.sure.mc_sure`),
  Eq. 9, gate, ``x + α'(y − x)``.

References
----------
.. [1] A. Firmino, J. R. Frisvad, H. W. Jensen. "Progressive Denoising of Monte Carlo
   Rendered Images". Computer Graphics Forum 41(2), 2022.
   https://doi.org/10.1111/cgf.14454
"""

from __future__ import annotations

import numbers

import numpy as np

from .errors import (InputError, _scalar, as_bool, as_broadcast_arrays, as_float_array,
                     as_number, check_finite, check_nonempty, check_nonnegative)
from .stats import PixelStats, check_stats

__all__ = ["mixing_weights", "mix_error", "confidence_gate", "progressive_denoise",
           "bind_denoiser", "auto_sigma_s", "DEFAULT_SMOOTH", "DEFAULT_RELATIVE_EPS",
           "DEFAULT_SHRINK", "DEFAULT_WINDOW", "DEFAULT_C", "DEFAULT_CHANNELS",
           "DEFAULT_A", "DEFAULT_EPS_T", "outlier_alpha", "DEFAULT_OUTLIER", "as_mix_inputs"]

#: Standard deviation (pixels) of the Gaussian that smooths σ², SURE and the divergence
#: before Eq. 9: their per-pixel estimates are far too noisy to use directly (§4.1 and
#: Fig. 3 of [1]).  Chosen on the toy and Mitsuba scenes (docs/progressive.md).
DEFAULT_SMOOTH = 4.0
#: z of the significance shrinkage of β in :func:`mixing_weights`: 2 (a ~95 % two-sided
#: test); 1 (the James–Stein plug-in) leaked visibly more noise at 4–16 spp in the bench.
DEFAULT_SHRINK = 2.0
#: ε of the relative weights 1/(y² + ε) in :func:`mixing_weights`: 0.01, the ε of relMSE
#: (Rousselle et al. 2011 §7) and of the sampling map of Firmino et al. 2023 (Eq. 3).
DEFAULT_RELATIVE_EPS = 0.01
#: Side of the neighbourhood N_p of Eq. 12–16: 11×11 (§4.2 and §7 of [1]).
DEFAULT_WINDOW = 11
#: A pixel whose channel-summed variance of the mean exceeds this factor times its σ = 2 px
#: Gaussian neighbourhood average is a variance outlier (a caught firefly) and gets the
#: per-pixel α of :func:`outlier_alpha`: a departure from [1] (docs/quality.md, last section).
DEFAULT_OUTLIER = 8.0
#: Shift c and strength a of the gate, Eq. 18: c = 4.2, a = 2 (§4.2 of [1]).
DEFAULT_C = 4.2
DEFAULT_A = 2.0
#: One t-statistic per channel in the gate: the shared sum of Eq. 13 over channels treats
#: correlated colour noise as independent and fires on noise (see :func:`confidence_gate`).
DEFAULT_CHANNELS = "separate"
#: ε of Eq. 17: 1e-6, the value of the authors' code (the paper gives none).
DEFAULT_EPS_T = 1e-6
#: σ_s = min(√(mean Var[x]), 1)·100 (§4.2 of [1]; the authors' code takes the image mean
#: of the per-pixel variance of the mean and floors σ_s at 1e-3).
_SIGMA_S_SCALE = 100.0
_SIGMA_S_FLOOR = 1e-3
#: Smallest ``sigma_s`` accepted: below ~1e-38 pixels ``σ_s`` and the centre weight
#: ``κ = 1/(σ_s √(2π))`` leave float32's range (single-precision work gave an all-NaN
#: gate), and ``κ²`` of Eq. 13 overflows float64 below ~1e-150.  1e-6 keeps ``κ² ≈ 1.6e11``
#: with room for variances up to ~1e27 in float32.
_SIGMA_S_MIN = 1e-6


# =========================================================================== checks
def _image(name, a, dtype=np.float64):
    arr = as_float_array(name, a, ndim=3, dtype=dtype)
    check_nonempty(name, arr)
    check_finite(name, arr)
    return arr


def _like(name, a, shape, *, nonneg=False, allow_2d=False, dtype=np.float64, check=True):
    arr = as_float_array(name, a, ndim=(2, 3) if allow_2d else 3, dtype=dtype)
    if allow_2d and arr.ndim == 2:
        if arr.shape != tuple(shape[:2]):
            raise InputError(f"`{name}` must have the shape {tuple(shape)} of `x` (or "
                             f"{tuple(shape[:2])}); got {arr.shape}.")
        arr = np.repeat(arr[..., None], shape[2], axis=2)
    if arr.shape != tuple(shape):
        raise InputError(f"`{name}` must have the shape of `x` {tuple(shape)}; got {arr.shape}.")
    if check:
        check_finite(name, arr)
        if nonneg:
            check_nonnegative(name, arr)
    return arr


def _variance(mean_var, shape, dtype=np.float64, check=True):
    """σ² of ``x``: an (H, W, C) variance of the mean, or the diagonal of (H, W, C, C)."""
    v = as_float_array("mean_var", mean_var, ndim=(3, 4), dtype=dtype)
    if v.ndim == 4:
        if v.shape != tuple(shape) + (shape[2],):
            raise InputError(f"`mean_var` must be the variance of the mean with the shape of `x` "
                             f"{tuple(shape)} (or a covariance {tuple(shape) + (shape[2],)}); "
                             f"got {v.shape}.")
        v = np.ascontiguousarray(np.diagonal(v, axis1=-2, axis2=-1))
    elif v.shape != tuple(shape):
        raise InputError(f"`mean_var` must be the variance of the mean with the shape of `x` "
                         f"{tuple(shape)}; got {v.shape}.")
    if check:
        check_finite("mean_var", v)
        check_nonnegative("mean_var", v)
    return v


def as_mix_inputs(x, y, mean_var, sure_y, divergence):
    """The five per-pixel maps of Eq. 8–10 of [1]_, checked as :func:`mixing_weights`
    checks them, as ``(H, W, C)`` float64 arrays.

    These are the maps that :func:`progressive_denoise` hands to a callable ``alpha`` (its
    dict ``x``, ``y``, ``mean_var``, ``sure``, ``divergence``), and the inputs of the
    mixing network of §4.3 of [1]_ (:func:`statmc.nn.mix_features` calls this).

    Parameters
    ----------
    x : (H, W, C) array_like
        The render (pixel means); non-empty.
    y : (H, W, C) array_like
        The denoised image ``f(x)``.
    mean_var : (H, W, C) or (H, W, C, C) array_like
        ``σ²``, the **variance of the mean** of ``x``, or a per-pixel channel covariance
        of the mean, of which only the diagonal is returned; ``>= 0`` on the diagonal
        (a covariance must be finite everywhere, as :func:`mixing_weights` requires).
    sure_y : (H, W, C) array_like
        Per-pixel SURE of ``y`` (Eq. 1, or Eq. 2 for MC-SURE); may be negative.
    divergence : (H, W, C) array_like
        ``σ² f'(x) = (J_f Σ)_ii`` (may be negative).

    Returns
    -------
    x, y, mean_var, sure_y, divergence : (H, W, C) float64 ndarrays
        New arrays or the inputs themselves (when already float64); ``mean_var`` is the
        diagonal of a covariance.

    Raises
    ------
    InputError
        Naming the map: not 3-d (``mean_var``: 3-d or 4-d), not the shape of ``x``, empty
        ``x``, NaN or Inf anywhere, or a negative variance.

    Examples
    --------
    >>> x = np.ones((2, 2, 3)); v = np.full((2, 2, 3), 0.01)
    >>> _, _, s2, _, _ = as_mix_inputs(x, x, v[..., None] * np.eye(3), v, 0 * v)
    >>> bool(np.array_equal(s2, v))            # a covariance's diagonal
    True
    >>> as_mix_inputs(x, x[:1], v, v, v)
    Traceback (most recent call last):
    ...
    statmc.errors.InputError: `y` must have the shape of `x` (2, 2, 3); got (1, 2, 3).
    """
    return _mix_inputs(x, y, mean_var, sure_y, divergence)[:5]


def _mix_inputs(x, y, mean_var, sure_y, divergence):
    """:func:`as_mix_inputs` and, last, a covariance ``mean_var`` as float64 (else None),
    converted once: a float32 (H, W, C, C) covariance was converted to float64 for its
    diagonal, again to check it whole and a third time by :func:`mixing_weights` (150 MB
    each at 1080p)."""
    xx = _image("x", x)
    shape = xx.shape
    yy = _like("y", y, shape)
    cov = None
    if np.ndim(mean_var) == 4:
        cov = as_float_array("mean_var", mean_var, ndim=(3, 4), dtype=np.float64)
        s2 = _variance(cov, shape)
        check_finite("mean_var", cov)       # off the diagonal too: mixing_weights uses it whole
    else:
        s2 = _variance(mean_var, shape)
    return (xx, yy, s2, _like("sure_y", sure_y, shape),
            _like("divergence", divergence, shape), cov)


def _smooth(a, sigma):
    if sigma == 0.0:
        return a
    from .filters import gaussian_filter

    return gaussian_filter(a, sigma)


# =========================================================================== Eq. 8, 9, 10
def mix_error(alpha, mean_var, sure_y, divergence):
    """Expected squared error of ``z = x + α (y − x)``, Eq. 8 of [1]_.

    Parameters
    ----------
    alpha : float or ndarray
        Mixing parameter(s), broadcast against the maps.
    mean_var : ndarray
        ``σ² = E[(x − μ)²]``, the **variance of the mean** of ``x``.
    sure_y : ndarray
        ``E[SURE(y)] = E[(y − μ)²]``, the squared error of the denoised image.
    divergence : ndarray
        ``σ² E[f'(x)]`` (per pixel: ``(J_f Σ)_ii``), which by Stein's lemma equals the
        covariance ``E[(x − μ)(y − μ)]`` (Eq. 6).

    Returns
    -------
    ndarray
        ``σ²(1 + α² − 2α) + α² E[SURE] + 2(α − α²) σ² E[f'(x)]`` (Eq. 8): exact when the
        three inputs are exact moments, whatever ``f``, as long as ``x`` is normal (for
        Stein's lemma) or ``f`` is linear.

    Examples
    --------
    >>> float(mix_error(0.0, 2.0, 1.0, 0.5)), float(mix_error(1.0, 2.0, 1.0, 0.5))
    (2.0, 1.0)
    """
    a, s2, sy, d = as_broadcast_arrays({"alpha": alpha, "mean_var": mean_var, "sure_y": sure_y,
                                        "divergence": divergence}, nonnegative=("mean_var",))
    return s2 * (1.0 + a * a - 2.0 * a) + a * a * sy + 2.0 * (a - a * a) * d


def mixing_weights(x, y, mean_var, sure_y, divergence, *, smooth: float = DEFAULT_SMOOTH,
                   relative_eps=DEFAULT_RELATIVE_EPS, shrink: float = DEFAULT_SHRINK,
                   per_channel: bool = False, channel_noise: str = "correlated", n=None,
                   extra_output: bool = False):
    """The mixing parameter ``α`` of Eq. 9 (``1 − β``, Eq. 10) of [1]_ from smoothed estimates.

    Parameters
    ----------
    x : (H, W, C) ndarray
        The render (pixel means).
    y : (H, W, C) ndarray
        Its denoised counterpart ``f(x)``.
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        **Variance of the mean** ``σ²`` of ``x`` (of a covariance only the diagonal is used).
    sure_y : (H, W, C) ndarray
        Per-pixel SURE of ``y`` (:func:`statmc.sure.mc_sure` or :func:`statmc.sure.sure`),
        or any unbiased per-pixel estimate of ``E[(y − μ)²]``.
    divergence : (H, W, C) ndarray
        Per-pixel divergence term ``D = σ² f'(x) = (J_f Σ)_ii`` (``extra_output["divergence"]``
        of those functions).
    smooth : float
        Standard deviation in pixels of the Gaussian (border-renormalised,
        :func:`statmc.filters.gaussian_filter`) that averages the per-pixel terms of
        Eq. 9/10 before dividing; ``0`` uses them raw (the literal per-pixel Eq. 9).
    relative_eps : float or None
        Weight each pixel's terms by ``1/(y² + relative_eps)`` inside the average, so that
        ``α`` minimises the local *relative* squared error (relMSE, ε = 0.01) rather than
        the absolute one, in which bright pixels dominate; ``None``: unweighted.
    shrink : float
        ``z >= 0``: shrink the estimated ``β`` towards 0 (``α`` towards 1, the denoised
        image) by the factor ``(1 − z² se²/b²)₊``, ``b`` the averaged numerator of Eq. 10
        and ``se`` its standard error (see Notes): ``β`` is kept only where the bias of
        ``y`` is significant at about ``z`` standard errors.  ``0`` disables it; ``1`` is
        the positive-part James–Stein plug-in; the default 2 a ~95 % two-sided test
        (under a normal null β survives in 5.7 % of pixels at the defaults, 4.9–7.4 %
        over n and ``smooth``, against 4.55 %: the local-spread standard error is noisy;
        ``shrink=2.11`` gives the nominal size; docs/progressive.md).
        Needs ``smooth > 0``.
    per_channel : bool
        ``False`` (default): one ``α`` per pixel from the sums over channels (the pixel's
        total error); ``True``: one per channel.
    channel_noise : {"correlated", "independent"}
        How the normal noise model of ``shrink`` treats the channels of a pixel when it
        sums them (``per_channel=False``; see Notes).  ``"correlated"`` (default): the
        Cauchy–Schwarz bound, exact when the channels' noise is perfectly correlated
        (white light, grey materials: the rule in renders); with a covariance
        ``mean_var`` its off-diagonal terms are used instead.  ``"independent"``: channels
        as independent (understates ``se`` up to √C on correlated colour noise).
    n : (H, W) ndarray, optional
        Samples per pixel, for the noise of ``σ̂²`` in the standard error of ``shrink``.
    extra_output : bool
        Also return a dict with ``beta`` (Eq. 10 from the averaged terms, before
        shrinking and clipping), ``numerator`` and ``denominator`` of Eq. 9 (averaged
        ``w(σ² − D)`` and ``w(SURE + σ² − 2D)``), ``shrink`` (the factor, 1 without),
        ``bias_z`` (``b/se``) and the two standard errors ``se_model`` and ``se_spread``
        (see Notes; NaN without shrinking).

    Returns
    -------
    alpha : (H, W, C) float64 ndarray in [0, 1]

    Notes
    -----
    Eq. 8 is the quadratic ``L(α) = σ² − 2α(σ² − D) + α² A``, ``A = SURE + σ² − 2D``.
    Where ``A > 0`` its minimiser over [0, 1] is Eq. 9, ``α = (σ² − D)/A`` clipped, and
    Eq. 10, ``β = (SURE − D)/A``, equals ``1 − α`` (mixing from ``y`` towards ``x`` gives
    the same ``z``).  Where the averaged estimates make ``A <= 0`` the minimum is at an
    end point: ``α = 1`` if ``L(1) = SURE < σ² = L(0)``, else 0.  As ``SURE = (y − x)²
    + 2D − σ²`` per pixel, ``A`` averaged with the same weights is the averaged
    ``(y − x)²``, the right-hand form of Eq. 9.

    Per-pixel estimates are far too noisy to use directly (§4.1, Fig. 3 of [1]_): we
    minimise the weighted local loss ``Σ_q k_pq w_q L_q(α)`` instead, with ``k`` the
    smoothing kernel and ``w_q = 1/(y_q² + ε)``, whose minimiser is the ratio of the
    averaged terms (numerator and denominator stay unbiased; only their ratio is not).

    Even so, ``β`` is a ratio of noisy averages, and where ``y`` is much better than
    ``x`` the loss is steep in ``α`` (curvature ``A ≈ σ²``): a small random ``β`` then
    leaks a large part of the render's noise into ``z``.  ``shrink`` treats the averaged
    numerator ``b = Σ_q k_pq e_q``, ``e = w (SURE − D)``, as an estimate with standard
    error ``se`` and multiplies ``β`` by ``(1 − z² se²/b²)₊``.  With ``z = 1`` this is the
    plug-in estimate of the optimal shrinkage ``b²/(b² + se²)`` — Eq. 9's own logic
    applied to ``β`` with the fixed target 0; ``z = 2`` keeps ``β`` only where ``|b|``
    exceeds about two standard errors, a soft significance test for the bias of ``y``.

    ``se² = Σ_q k_pq² Var[e_q]`` (pixels independent) is the smaller of two estimates,
    each of which errs upwards in a known case:

    * the local spread ``Var_k[e]`` (weighted by ``k``) — model-free, and calibrated on
      the Mitsuba scenes (checked against the difference of two independent renders,
      ``docs/progressive.md``), but it counts the spatial variation of the bias as
      noise: on a fine texture it kept ``se ≈ |b|`` at every sample count, and the
      output stopped converging (1.5× the render's relMSE at 4096 spp);
    * a normal noise model, ``Var[e_q] = w_q² Σ_c (4 b̂² σ̂² + 2σ̂⁴ + 2σ̂⁴/(n − 1))`` with
      the local bias ``b̂² = max(G[(y − x)² − σ̂²], 0)``: the variance of ``(y − x)²``
      when ``y − x ~ N(b, σ²)`` (the noise of ``y − x`` taken as that of ``x``, which a
      smoothing denoiser leaves almost intact) plus that of the sample variance of ``n``
      normal samples (that term only with ``n``); the Monte Carlo noise of ``D`` is
      ignored.  Summed over channels, ``Var[Σ_c e_c] = Σ_cc' w_c w_c' (2(1 + 1/(n − 1))
      C_cc'² + 4 b_c b_c' C_cc')`` for a channel covariance ``C`` of the noise of ``x``
      (``Cov[X², Y²] = 2 Cov[X, Y]²`` and ``4 b_c b_c' Cov[X, Y]`` for normal ``X, Y``
      with means ``b``); with ``|b̂|`` for ``b`` and, without ``C``, ``C_cc' = σ_c σ_c'``
      (perfect correlation, the upper bound by Cauchy–Schwarz for ``|b̂|``):
      ``2(1 + 1/(n − 1)) (Σ_c w_c σ̂_c²)² + 4 (Σ_c w_c |b̂_c| σ̂_c)²``.  Summing the
      channel variances as if independent understated ``se`` by up to √3 on colour
      noise and let noise through at 4 spp (``toy:mixed``: 1.12× OIDN's relMSE against
      1.00× with the bound, mean of three renders; ``docs/progressive.md``).  It falls
      like ``1/√n`` wherever ``y`` is biased, so the factor tends to 1, but heavy-tailed
      pixels inflate ``σ̂⁴`` far more than they move ``e``: on the Cornell box it
      overstated ``se`` 2–6×.

    Where the bias is significant (e.g. at high sample counts) the factor is ~1, Eq. 9
    itself tends to 0, and the confidence gate bounds the rest.

    Examples
    --------
    >>> x = np.full((4, 4, 3), 1.0); y = np.full((4, 4, 3), 1.1)
    >>> var = np.full((4, 4, 3), 0.01)
    >>> a = mixing_weights(x, y, var, sure_y=(y - x) ** 2 - var, divergence=0 * var,
    ...                    smooth=0, relative_eps=None, shrink=0)
    >>> bool(np.allclose(a, 1.0))   # σ² = (y − x)²: all of y
    True
    """
    xx, yy, s2, sy, d, cov = _mix_inputs(x, y, mean_var, sure_y, divergence)
    shape = xx.shape
    if channel_noise not in ("correlated", "independent"):
        raise InputError(f"`channel_noise` must be 'correlated' or 'independent'; got "
                         f"{channel_noise!r}.")
    cn = channel_noise
    sm = as_number("smooth", smooth, lo=0.0)
    if relative_eps is not None:
        relative_eps = as_number("relative_eps", relative_eps, lo=0.0, lo_open=True)
    z = as_number("shrink", shrink, lo=0.0)
    if n is not None:
        nn = as_float_array("n", n, ndim=2, dtype=np.float64)
        if nn.shape != shape[:2]:
            raise InputError(f"`n` must be an (H, W) count map {shape[:2]}; got {nn.shape}.")
        check_finite("n", nn)
        check_nonnegative("n", nn)
    per_channel = as_bool("per_channel", per_channel)
    extra_output = as_bool("extra_output", extra_output)
    if z > 0 and sm == 0.0:
        raise InputError(f"`shrink`={shrink!r} needs `smooth` > 0 (the standard error comes from "
                         "the local spread); got smooth=0. Pass shrink=0 for the raw Eq. 9.")
    w = 1.0 if relative_eps is None else 1.0 / (yy * yy + relative_eps)
    terms = [w * (s2 - d), w * (sy - d), w * s2, w * sy]   # numerator, b, L(0), L(1)
    if not per_channel:
        terms = [t.sum(axis=2, keepdims=True) for t in terms]
    num, b, l0, l1 = (_smooth(t, sm) for t in terms)
    den = num + b
    pos = den > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.where(pos, b / np.where(pos, den, 1.0), np.nan)
    lam = np.ones_like(b)
    bias_z = se_model = se_spread = np.full_like(b, np.nan)
    if z > 0:
        b2 = np.clip(_smooth((yy - xx) ** 2 - s2, sm), 0.0, None)   # local bias² of y
        # 2σ⁴ (1 + 1/(n − 1)): (y − x)² and the sample variance; the latter only with n
        f2 = 2.0 if n is None else 2.0 + 2.0 / np.maximum(nn - 1.0, 1.0)[..., None]
        ww = np.ones_like(s2) if relative_eps is None else w
        if per_channel or cn == "independent":
            vq = (ww * ww) * (4.0 * b2 * s2 + f2 * s2 * s2)
            if not per_channel:
                vq = vq.sum(axis=2, keepdims=True)
        elif cov is not None:      # Σ_cc' w_c w_c' (2(1 + 1/(n−1)) C_cc'² + 4 |b_c||b_c'| C_cc')
            wb = ww * np.sqrt(b2)
            vq = f2 * np.einsum("hwc,hwd,hwcd->hw", ww, ww, cov * cov)[..., None]
            vq = vq + 4.0 * np.einsum("hwc,hwd,hwcd->hw", wb, wb, cov)[..., None]
        else:                      # perfectly correlated channels: the Cauchy–Schwarz bound
            sd = np.sqrt(s2)
            vq = f2 * (ww * s2).sum(axis=2, keepdims=True) ** 2 \
                + 4.0 * (ww * np.sqrt(b2) * sd).sum(axis=2, keepdims=True) ** 2
        e = terms[1]
        spread = np.clip(_smooth(e * e, sm) - b * b, 0.0, None) * _smooth_k2(np.ones_like(e), sm)
        se_model = np.sqrt(_smooth_k2(vq, sm))
        se_spread = np.sqrt(spread)
        se = np.minimum(se_model, se_spread)
        with np.errstate(divide="ignore", invalid="ignore"):
            bias_z = np.where(se > 0, b / np.where(se > 0, se, 1.0), np.inf * np.sign(b))
        se2 = se * se * (z * z)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.where(b * b > 0, np.clip(1.0 - se2 / (b * b), 0.0, 1.0), 0.0)
    alpha = np.where(pos, 1.0 - np.clip(lam * np.nan_to_num(beta), 0.0, 1.0),
                     (l1 < l0).astype(np.float64))
    alpha = np.broadcast_to(alpha, shape).copy()
    if not extra_output:
        return alpha
    info = {"beta": np.broadcast_to(beta, shape).copy(),
            "numerator": np.broadcast_to(num, shape).copy(),
            "denominator": np.broadcast_to(den, shape).copy(),
            "shrink": np.broadcast_to(lam, shape).copy(),
            "bias_z": np.broadcast_to(bias_z, shape).copy(),
            "se_model": np.broadcast_to(se_model, shape).copy(),
            "se_spread": np.broadcast_to(se_spread, shape).copy()}
    return alpha, info


def _smooth_k2(a, sigma):
    """``Σ_q k_pq² a_q`` for the border-renormalised Gaussian weights ``k`` of :func:`_smooth`."""
    from scipy.ndimage import correlate1d

    from .filters import DEFAULT_TRUNCATE, _taps, border_scale

    g = _taps(sigma, DEFAULT_TRUNCATE, max(a.shape[:2]))   # _smooth's taps, cut to the image
    out = correlate1d(a, g * g, axis=0, mode="constant", cval=0.0)
    out = correlate1d(out, g * g, axis=1, mode="constant", cval=0.0)
    sy = border_scale(a.shape[0], g)
    sx = border_scale(a.shape[1], g)
    return out * (sy * sy)[:, None, None] * (sx * sx)[None, :, None]


# =========================================================================== Eq. 12-18
def auto_sigma_s(mean_var) -> float:
    """``σ_s = min(√Var[x̄], 1)·10²`` of §4.2 of [1]_.

    ``Var[x̄]`` is taken, as in the authors' code, as the image mean of the per-pixel
    variance of the mean, and ``σ_s`` is floored at ``1e-3``.  It depends on the absolute
    radiance scale and the noise level: with ``mean Var[x] = 0.16`` it is 40 (the 11×11
    weights then vary by < 2 %, a nearly flat window), 100 at ``mean Var[x] >= 1``, and it
    shrinks like ``1/√n`` once ``mean Var[x] < 1``.
    """
    v = as_float_array("mean_var", mean_var, ndim=(2, 3, 4), dtype=np.float64)
    if v.ndim == 4:
        if v.shape[2] != v.shape[3]:
            raise InputError(f"`mean_var` must be (H, W, C), or a covariance (H, W, C, C); "
                             f"got {v.shape}.")
        v = np.diagonal(v, axis1=-2, axis2=-1)
    check_finite("mean_var", v)
    check_nonnegative("mean_var", v)
    return _auto_sigma_s_from_mean(float(v.mean()) if v.size else 0.0)


def _auto_sigma_s_from_mean(m):
    return max(_SIGMA_S_SCALE * min(float(np.sqrt(max(m, 0.0))), 1.0), _SIGMA_S_FLOOR)


def confidence_gate(x, y, mean_var, alpha, *, window: int = DEFAULT_WINDOW, sigma_s="auto",
                    c: float = DEFAULT_C, a: float = DEFAULT_A, eps: float = DEFAULT_EPS_T,
                    channels: str = DEFAULT_CHANNELS, cdf: str = "normal",
                    precision: str = "single",
                    extra_output: bool = False):
    """Scale ``α`` down where the mix departs significantly from the render, Eq. 12–18 of [1]_.

    Parameters
    ----------
    x : (H, W, C) ndarray
        The render (unbiased pixel means).
    y : (H, W, C) ndarray
        The denoised image.
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        **Variance of the mean** ``Var[x_q]`` (diagonal of a covariance).
    alpha : (H, W, C) or (H, W) ndarray
        Mixing parameter before gating (:func:`mixing_weights`, or a network's).
    window : int
        Side of the square neighbourhood ``N_p`` (odd; 11 in [1]_).
    sigma_s : float or "auto"
        ``σ_s`` of the weights ``κ`` (Eq. 15), in pixels, ``>= 1e-6``; ``"auto"``:
        :func:`auto_sigma_s`.
    c, a : float
        Shift and strength of Eq. 18 (4.2 and 2 in [1]_).
    eps : float
        ``ε`` of Eq. 17 (``>= 0``).  Where ``√Var[x̄_p] + ε = 0`` (``ε = 0`` on a window of
        zero variance, e.g. all-black pixels) ``t_p`` is the limit ``ε → 0⁺``: 0 if
        ``z̄_p = x̄_p``, else ``±∞`` (then ``α' = 0``: an exact render is kept).
    channels : {"separate", "shared"}
        ``"separate"`` (default): one t-statistic per channel, each from its own Eq.
        12–14; ``"shared"``: one per pixel from the sums of Eq. 12–14 over channels (as
        the authors' code, except that it weighs the ``M_p`` terms by 1/3 in that sum).
        The sum of Eq. 13 treats the channels as independent, so on correlated colour
        noise the shared ``t`` has a standard deviation up to ``√(1 + 2ρ)`` (≈ 1.7) under
        the null instead of 1, and the gate fires on noise (``toy:mixed`` at 256 spp:
        1.19× OIDN's relMSE shared, 0.83× separate).
    cdf : {"normal", "logistic"}
        ``S`` of Eq. 18: the standard normal CDF (default) or the logistic function, which
        [1]_ reports to work equally well.
    precision : {"single", "double"}
        Working precision of Eq. 12–17 (the output dtype follows ``x`` either way).
        ``"single"`` (default): ``u = α(y − x)`` is formed in the input's precision, then
        ``u`` and ``Var[x]`` are rounded once to float32 and the window sums run in
        float32 (see Notes); values beyond ``1e30`` switch to double automatically.
        ``"double"``: float64 throughout (float32 input is upcast).
    extra_output : bool
        Also return a dict with ``t`` (Eq. 17), ``scale`` (``1 − S[a(|t| − c)]``),
        ``sigma_s``, ``difference`` (``z̄ − x̄``) and ``variance`` (``Var[x̄]``, Eq. 13).

    Returns
    -------
    alpha_gated : (H, W, C) ndarray
        ``α' = (1 − S[a(|t_p| − c)]) α_p`` (Eq. 18), same dtype as ``x`` (float32 stays
        float32, other types become float64).

    Notes
    -----
    Eq. 12–14 as printed, per channel:

    ``x̄_p = x_{M_p} + Σ_{q∈N_p} κ_pq x_q``,
    ``Var[x̄_p] = Var[x_{M_p}] + Σ_q κ_pq² Var[x_q]``,
    ``z̄_p = z_{M_p} + Σ_q κ_pq (x_q + α_q (y_q − x_q))``,

    with ``κ_pq = exp(−‖p − q‖²/(2σ_s²))/(σ_s√(2π))`` (Eq. 15), ``M_p`` the neighbour of
    largest ``Var[x_q]`` (Eq. 16; first in row-major order on ties) and
    ``t_p = (z̄_p − x̄_p)/(√Var[x̄_p] + ε)`` (Eq. 17).  The "average" is not normalised:
    ``M_p`` carries weight 1 besides its ``κ`` and the others ``κ`` (DESIGN.md erratum).
    A common factor of all weights cancels in ``t``; their ratio does not, which is why
    ``σ_s`` and ``window`` matter.  As printed, Eq. 13 omits the cross term
    ``2κ_{pM} Var[x_M]`` of the weight ``1 + κ_{pM}`` that ``M_p`` really carries; kept.
    Only ``z̄ − x̄ = α_M d_M + Σ κ α_q d_q`` (``d = y − x``) is formed, never the two sums.
    Outside taps are dropped (no renormalisation).  As ``n → ∞`` the denominator falls
    like ``1/√n`` while a biased ``y`` keeps ``z̄ − x̄`` finite, so ``|t| → ∞`` and
    ``α' → 0``: the output converges to the render, hence to ``μ``.

    Cost: ``O(window)`` per pixel and channel (separable sums and window argmax) in a
    numba kernel, :mod:`statmc._progressive_kernels`, which has a NumPy reference.  A
    window wider than ``2·max(H, W) − 1`` is the whole image: its half-width is cut to
    ``max(H, W) − 1`` (bit for bit the same, the offsets cut never meet the image).

    Precision.  The inputs are noisy estimates and ``t`` is a test statistic of unit
    standard deviation under the null, so float32 suffices, and it halves the memory
    traffic and doubles the SIMD width (float64 input: 2–3× faster).  With unit roundoff
    ``u = 2⁻²⁴`` and ``m = 2(window + 1) + 4`` rounded operations per sum (the input
    rounding, two separable passes of ``window`` products and sums, the ``M_p`` term),
    each sum of Eq. 14 − 12 is off by at most ``γ_m (|u_M| + Σ_q κ_pq |u_q|)``,
    ``γ_m = m u/(1 − m u)`` (≈ 1.7e-6 for 11×11), and Eq. 13 (positive terms) by
    ``γ_m`` relative.  As ``|dS/ds| <= 1/√(2π)``, ``|Δα'| <= (a/√(2π)) α |Δt|`` with
    ``|Δt| <= γ_m (Σ|·| + |t| √Var[x̄])/(√Var[x̄] + ε)`` (channel sums add ``C`` to ``m``):
    a few 1e-6 at most, against a sampling spread of ``t`` of about 1.  Rounding is
    monotone, so ``M_p`` can only change between variances equal to float32 precision
    (ties go to the first, as in double).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> x = 0.5 + 0.01 * rng.standard_normal((16, 16, 3))
    >>> var = np.full_like(x, 1e-4)
    >>> a0 = np.ones_like(x)
    >>> bool(np.all(confidence_gate(x, x, var, a0) > 0.99))     # y = x: nothing to gate
    True
    >>> bool(np.all(confidence_gate(x, x + 0.2, var, a0) < 1e-6))  # strong bias: α' → 0
    True
    """
    from . import _progressive_kernels as _pk

    xx = as_float_array("x", x, ndim=3)
    check_nonempty("x", xx)
    if xx.dtype != np.float32:
        xx = xx.astype(np.float64)
    dt = xx.dtype
    shape = xx.shape
    if precision not in ("single", "double"):
        raise InputError(f"`precision` must be 'single' or 'double'; got {precision!r}.")
    extra_output = as_bool("extra_output", extra_output)
    yy = _like("y", y, shape, dtype=dt, check=False)
    v = _variance(mean_var, shape, dtype=dt, check=False)
    al = _like("alpha", alpha, shape, allow_2d=True, dtype=dt, check=False)
    work = np.float32 if precision == "single" else np.float64
    if work != dt and dt == np.float32:          # float32 input, double precision asked
        xx, yy, v = (q.astype(np.float64) for q in (xx, yy, v))
    # One parallel pass: u = α(y − x) in the input's precision, stored in the working one;
    # finiteness of every input, signs and sum of Var[x]; values float32 cannot hold.
    u, vw, bad, v_sum = _pk.prepare(xx, yy, v, al, work)
    for name, arr, n_bad in (("x", xx, bad[0]), ("y", yy, bad[1]), ("mean_var", v, bad[2]),
                             ("alpha", al, bad[4])):
        if n_bad:
            check_finite(name, arr)
    if bad[3]:
        check_nonnegative("mean_var", v)
    if bad[5]:                                   # beyond float32's safe range: work in double
        u, vw, _, _ = _pk.prepare(xx, yy, v, al, np.float64)
    window = _scalar(window)                     # a 0-d array is its number
    if isinstance(window, bool) or not isinstance(window, numbers.Integral) or window < 1 \
            or window % 2 == 0:
        raise InputError(f"`window` must be an odd positive integer; got {window!r}.")
    if isinstance(sigma_s, str):
        if sigma_s != "auto":
            raise InputError(f"`sigma_s` must be a number > 0 or 'auto'; got {sigma_s!r}.")
        ss = _auto_sigma_s_from_mean(v_sum / v.size if v.size else 0.0)
    else:
        ss = as_number("sigma_s", sigma_s, lo=_SIGMA_S_MIN)
    cc = as_number("c", c)
    aa = as_number("a", a, lo=0.0, lo_open=True)
    ee = as_number("eps", eps, lo=0.0)
    if channels not in ("shared", "separate"):
        raise InputError(f"`channels` must be 'shared' or 'separate'; got {channels!r}.")
    if cdf not in ("normal", "logistic"):
        raise InputError(f"`cdf` must be 'normal' or 'logistic'; got {cdf!r}.")
    # a window offset of max(H, W) or more never meets the image (the kernel skips it):
    # half-widths past that are cut, bit for bit the same; window = 1e9 + 1 built 30 GB
    # of taps before, and the taps of 1e30 + 1 no array could hold
    half = min(int(window) // 2, max(xx.shape[0], xx.shape[1], 1) - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        num, var, t, out = _pk.gate(u, vw, al, half, ss,
                                    shared=(channels == "shared"), a=aa, c=cc, eps=ee,
                                    logistic=(cdf == "logistic"), keep=bool(extra_output))
    if not extra_output:
        return out
    from scipy.special import expit, ndtr

    num, var, t = (q.astype(dt, copy=False) for q in (num, var, t))
    s = aa * (np.abs(t) - cc)
    scale = 1.0 - (expit(s) if cdf == "logistic" else ndtr(s))
    info = {"t": t, "scale": scale.astype(dt), "sigma_s": ss, "difference": num, "variance": var}
    return out, info


# =========================================================================== pipeline
def bind_denoiser(denoiser, stats: PixelStats, **options):
    """A denoiser ``f(color) -> color`` bound to the inputs it needs from ``stats``.

    Parameters
    ----------
    denoiser : str or callable
        ``"oidn"`` (with ``stats.albedo`` and ``stats.normal`` when present), ``"gem"``
        (with ``stats.mean_var`` and ``stats.n``), ``"gaussian"``, ``"none"``; or a
        factory ``factory(stats, **options) -> denoiser``, called as is.
    stats : PixelStats
    **options
        Passed to the factory (``gamma=`` for GEM, ``sigma=`` for Gaussian, ``quality=``
        for OIDN, …).
    """
    from . import denoisers as _d

    check_stats(stats)
    if isinstance(denoiser, str):
        name = denoiser.lower()
        if name == "oidn":
            # OIDN takes albedo in [0, 1] and normals in [-1, 1]; renderers' AOVs can
            # exceed them (emitters, interpolated normals), so clip rather than refuse.
            alb = None if stats.albedo is None else np.clip(stats.albedo, 0.0, 1.0)
            nrm = stats.normal
            nrm = None if (nrm is None or alb is None) else np.clip(nrm, -1.0, 1.0)
            return _d.oidn(albedo=alb, normal=nrm, **options)
        if name == "gem":
            n = np.maximum(stats.n, 2)
            return _d.gem(stats.mean_var, n=n, **options)
        if name in ("gaussian", "none", "identity"):
            return _d.get(name, **options)
        raise InputError(f"`denoiser` must be one of oidn, gem, gaussian, none or a callable; "
                         f"got {denoiser!r}.")
    if callable(denoiser):
        return denoiser(stats, **options)
    raise InputError(f"`denoiser` must be a name or a callable factory(stats); got "
                     f"{type(denoiser).__name__}.")


def outlier_alpha(alpha, x, y, mean_var, *, factor: float = DEFAULT_OUTLIER,
                  sigma: float = 2.0) -> np.ndarray:
    """Raise the smoothed α at variance outliers to their own per-pixel estimate.

    **A departure from [1]_** (docs/quality.md, last section).  Eq. 9 is formed from
    σ², SURE and the divergence smoothed over σ = 4 px, so one pixel whose render caught a
    firefly gets the α of its neighbourhood: where that α is small (e.g. 0.23 in a caustic
    at 1024 spp, where the denoiser's bias shows), most of the firefly passes into
    ``x + α(y − x)``.  At pixels whose channel-summed σ² exceeds ``factor`` times its
    Gaussian (``sigma``) neighbourhood average, this returns

    ``α'_p = max(α_p, min(1, σ²_p / (y_p − x_p)²))``  (per channel),

    the single-pixel plug-in of the minimiser of Eq. 8, ``α* = E[(x − μ)(x − y)] /
    E[(x − y)²] ≈ σ²/E[(y − x)²]`` for a denoised ``y`` much less noisy than ``x``, with
    ``E[(y − x)²]`` estimated by the pixel's own squared difference.  Elsewhere α is
    unchanged.  As samples accumulate σ²_p → 0 and ``α'_p → α_p``, so convergence is that
    of the gated α.  The confidence gate is applied afterwards, as to any α.

    Parameters
    ----------
    alpha : (H, W, C) or (H, W) ndarray
        Mixing weights (e.g. :func:`mixing_weights`).
    x, y : (H, W, C) ndarray
        The render and its denoised image.
    mean_var : (H, W, C) ndarray
        σ², the variance of the mean of ``x``.
    factor : float
        Outlier threshold (> 1).
    sigma : float
        σ (pixels) of the neighbourhood average (> 0).

    Returns
    -------
    alpha : (H, W, C) float64 ndarray
    """
    factor = as_number("factor", factor, lo=1.0, lo_open=True)
    sigma = as_number("sigma", sigma, lo=0.0, lo_open=True)
    xa = as_float_array("x", x, ndim=3)
    check_nonempty("x", xa)
    check_finite("x", xa)
    ya = _like("y", y, xa.shape)
    s2 = _variance(mean_var, xa.shape)
    al = _like("alpha", alpha, xa.shape, allow_2d=True)
    return _outlier_alpha(al, xa, ya, s2, factor, sigma)


def _outlier_alpha(al, xa, ya, s2, factor, sigma=2.0):
    """:func:`outlier_alpha` on checked (H, W, C) float64 arrays."""
    from .filters import gaussian_filter
    v = s2.sum(axis=2)
    hot = v > factor * gaussian_filter(v, sigma)
    if not hot.any():
        return al
    d2 = (ya[hot] - xa[hot]) ** 2
    own = np.where(d2 > 0, np.minimum(s2[hot] / np.where(d2 > 0, d2, 1.0), 1.0), 1.0)
    out = al.copy()
    out[hot] = np.maximum(al[hot], own)
    return out


def progressive_denoise(stats: PixelStats, denoiser, *, alpha=None, mean_var=None,
                        smooth: float = DEFAULT_SMOOTH, relative_eps=DEFAULT_RELATIVE_EPS,
                        shrink: float = DEFAULT_SHRINK, per_channel: bool = False, k: int = 4,
                        eps: float = 1e-4, rng=None, gate: bool = True,
                        window: int = DEFAULT_WINDOW, sigma_s="auto", c: float = DEFAULT_C,
                        a: float = DEFAULT_A, channels: str = DEFAULT_CHANNELS,
                        cdf: str = "normal", channel_noise: str = "correlated",
                        outlier=DEFAULT_OUTLIER, extra_output: bool = False):
    """Progressively denoised image ``x + α'(y − x)`` (§4 of [1]_, classical α).

    Parameters
    ----------
    stats : PixelStats
        The render: ``x = stats.mean``, ``σ² = stats.mean_var`` (variance of the mean).
    denoiser : callable ``f(color) -> color`` or str
        A ready denoiser (:mod:`statmc.denoisers`), or a name bound to ``stats`` by
        :func:`bind_denoiser` (``"oidn"`` with the feature buffers, ``"gem"`` with the
        variance).
    alpha : ndarray or callable, optional
        A mixing parameter to gate instead of Eq. 9 — e.g. a network's (``(H, W, C)`` or
        ``(H, W)``), or ``alpha(inputs) -> array`` called with a dict of ``x``, ``y``,
        ``mean_var``, ``sure``, ``divergence``.  The gate is applied to it unchanged.
    mean_var : (H, W, C) or (H, W, C, C) ndarray, optional
        Overrides ``stats.mean_var`` for MC-SURE and the gate — e.g. a per-pixel channel
        covariance, which removes the bias of a diagonal one for denoisers that mix
        channels (``docs/error-estimates.md``).
    smooth, relative_eps, shrink, per_channel, channel_noise
        Of :func:`mixing_weights` (which gets ``mean_var`` as given, so a covariance
        there also enters the standard error of ``shrink``).
    outlier : float or None
        ``factor`` of :func:`outlier_alpha`, applied to the classical α (not to a given
        ``alpha``): variance outliers (caught fireflies) get their per-pixel α.  ``None``
        gives Eq. 9 alone, as in [1]_.
    k, eps, rng
        Of :func:`statmc.sure.mc_sure` (``k + 1`` denoiser calls in all).
    gate : bool
        Apply :func:`confidence_gate` (default); ``False`` returns the ungated mix, which
        does not converge in general.
    window, sigma_s, c, a, channels, cdf
        Of :func:`confidence_gate`.
    extra_output : bool
        Also return a dict with ``denoised`` (``y``), ``sure``, ``divergence``, ``alpha``
        (before gating), ``alpha_gated``, ``t`` and ``sigma_s``.

    Returns
    -------
    image : (H, W, C) float64 ndarray

    Examples
    --------
    >>> from statmc.toy import ToyRenderer
    >>> from statmc import denoisers
    >>> st = ToyRenderer("gradient", width=24, height=24).render_uniform(16, seed=1)
    >>> z = progressive_denoise(st, denoisers.gaussian(2.0), rng=0)
    >>> z.shape
    (24, 24, 3)
    """
    from .sure import mc_sure

    check_stats(stats)
    gate = as_bool("gate", gate)
    extra_output = as_bool("extra_output", extra_output)
    if outlier is not None:
        outlier = as_number("outlier", outlier, lo=1.0, lo_open=True)
    if mean_var is None:
        stats.require_variance(why="for its variance of the mean, σ² of Eq. 1, 9 and 12–18",
                               hint=" Pass `mean_var` to supply the variances.")
    x = stats.mean
    mv = stats.mean_var if mean_var is None else mean_var
    s2 = _variance(mv, x.shape)
    f = bind_denoiser(denoiser, stats) if isinstance(denoiser, str) else denoiser
    sure_map, info = mc_sure(f, x, mv, eps=eps, k=k, rng=rng, extra_output=True)
    y = info["denoised"]
    div = info["divergence"]
    if alpha is None:
        al = mixing_weights(x, y, mv, sure_map, div, smooth=smooth, relative_eps=relative_eps,
                            shrink=shrink, per_channel=per_channel,
                            channel_noise=channel_noise, n=stats.n)
        if outlier is not None:
            al = _outlier_alpha(al, x, y, s2, outlier)
    else:
        if callable(alpha):
            alpha = alpha({"x": x, "y": y, "mean_var": s2, "sure": sure_map, "divergence": div})
        al = _like("alpha", alpha, x.shape, allow_2d=True)
    if gate:
        ag, ginfo = confidence_gate(x, y, s2, al, window=window, sigma_s=sigma_s, c=c, a=a,
                                    channels=channels, cdf=cdf, extra_output=True)
    else:
        ag, ginfo = al, {"t": None, "sigma_s": None}
    z = x + ag * (y - x)
    if extra_output:
        return z, {"denoised": y, "sure": sure_map, "divergence": div, "alpha": al,
                   "alpha_gated": ag, "t": ginfo["t"], "sigma_s": ginfo["sigma_s"],
                   "calls": info["calls"]}
    return z
