"""Greedy Error Minimisation: per-pixel filter-scale selection and sample distribution.

Rousselle, Knaus and Zwicker (2011) [1]_ reconstruct a Monte Carlo image by choosing, at
each pixel, one filter from a fine-to-coarse bank (the pixel estimate, then Gaussians,
:mod:`statmc.filters`) so as to minimise the pixel's MSE, and place new samples where the
relative MSE of the chosen filter falls fastest.  This module implements:

* the scale selector ``S`` of Eq. 1 (§4.1–4.2) with the bias factor derived correctly,
  ``(r_c² + r_f²)/(r_c² − r_f²)`` (the paper prints ``(r_f² + r_c²)/(r_f² − r_c²)``,
  which is negative; see ``docs/gem.md``), weighted by ``ρ·z(γ)`` (§4.3);
* stopping-map post-processing (§4.4, §6) and selection of the finest scale that stops;
* the estimated MSE of the selected filter and the greedy sample distribution (§5);
* :func:`reconstruct` (final reconstruction, §6) and :func:`sampling_map`
  (one adaptive iteration: integer counts that sum exactly to the budget);
* a departure, the default of the final reconstruction (``bias="pooled"``,
  :func:`pooled_selector`): each squared difference minus its known noise variance,
  pooled over a σ = 1 Gaussian, in the plain MSE comparison, on a bank starting at
  σ = 0.6.  On the built-in scenes it halves the error of the literal rule where that
  rule stays above half the box filter's (``docs/gem.md`` §5d); ``bias="paper"`` keeps
  the paper's Eq. 1 and §6.

Inputs are ``mean`` ``(H, W, C)`` (pixel estimates), ``mean_var`` ``(H, W, C)`` — the
**variance of the mean** of each pixel (sample variance / n) — and ``n`` ``(H, W)``
sample counts.  float32 in gives float32 out.

References
----------
.. [1] F. Rousselle, C. Knaus, M. Zwicker. Adaptive sampling and reconstruction using
   greedy error minimization. ACM TOG 30(6), 159 (2011). doi:10.1145/2070781.2024193
"""

from __future__ import annotations

import math

import numpy as np

from . import _filter_kernels as _k
from ._threads import SERIAL_VALUES, serial_when_small, thread_count
from .errors import (MAX_BUDGET, InputError, as_bool, as_float_array, as_number, as_rng,
                     as_whole, check_finite, check_nonnegative, real_or_nan)
from .filters import (ADAPTIVE_SIGMAS, DEFAULT_TRUNCATE, FINAL_SIGMAS, _as_sigmas, _check_pair,
                      _border_scale, _rows, _run, _taps, _weight_matrix, gaussian_kernel_1d,
                      kernel_moment2)

__all__ = [
    "error_rate_weight", "bias_factor", "bias_term", "selector", "postprocess_stop_maps",
    "estimate_mse", "difference_variance", "pooled_selector", "select", "select_scales",
    "reconstruct", "sampling_map", "SelectedFilter", "selected_filter",
    "DEFAULT_GAMMA", "RELMSE_EPS", "BIAS_MODES", "POOLED_FINAL_SIGMAS", "BIAS_POOL_SIGMA",
]

#: Default error-rate parameter γ (the paper's Fig. 8 uses 0.2; §7 results use 0.1).
DEFAULT_GAMMA = 0.2
#: ε of the relative MSE that ranks pixels for new samples (§5 of [1]).
RELMSE_EPS = 1e-3
#: z(γ) = −log(1 − (1.9 γ)^(1/√2)) is finite only for γ < 1/1.9.
_GAMMA_MAX = 1.0 / 1.9
#: Bias estimates of the scale selector: ``"paper"`` (Eq. 1 of [1] with ρ·z(γ)) and
#: ``"pooled"`` (statmc's departure: noise-corrected, Gaussian-pooled; docs/gem.md §5d).
BIAS_MODES = ("paper", "pooled")
#: Final-reconstruction scales with ``bias="pooled"``: the pixel estimate and ten
#: Gaussians ×√2 from σ = 0.6 to 13.6 (§6 of [1]: eight from √2 to 16).  Finest σ
#: measured on the Mitsuba scenes (docs/gem.md §5d): uniform+GEM / box on textured-dof
#: at 64 spp was 0.77 (√2), 0.65 (1), 0.50 (1/√2), 0.44 (0.6), 0.44 (0.5), but σ = 0.5
#: kept fireflies on glass-caustic (2 of 16 renders > 1× box at 16 spp).
POOLED_FINAL_SIGMAS: tuple[float, ...] = (0.0,) + tuple(0.6 * 2.0 ** (k / 2) for k in range(10))
#: σ (pixels) of the Gaussian that pools the noise-corrected squared differences
#: (``bias="pooled"``); of 0.7, 1, 1.5 and 2 measured on the Mitsuba scenes, 1 was best
#: or within 0.01 of it (docs/gem.md §5d).
BIAS_POOL_SIGMA = 1.0
#: Images of at most this many pixels run each stage of the pooled selection and of the
#: stopping-map post-processing for all scales in one parallel region (the ``*_many``
#: kernels of :mod:`statmc._filter_kernels`): numba's pool waits passively, so each region
#: pays for waking it, and per scale a ``reconstruct`` ran 73 regions (11 fused).  Larger
#: images keep the scale-by-scale loop, which holds two scales' variances instead of all
#: (fused, 1080p took twice as long; 512x512 beside another job 1.07-1.18x).  Results are
#: bit for bit the same either way (docs/gem.md §7).
FUSED_PIXELS = 1 << 18
#: ``select``/``reconstruct``/``selected_filter`` calls with the pooled selection run on
#: the task threads (:mod:`statmc._task_threads`) from this many values (about 224x224
#: RGB) instead of ``_threads.SERIAL_VALUES`` (about 245x245): fused, they run 11 parallel
#: regions instead of 73.  It was 50,000 (about 128x128), measured for numba's OpenMP pool
#: (session 11); the Python task threads lose more when the cores are busy.  On 2026-11-23
#: at load 2.1-2.3, two threads against one took 1.5-1.8x as long at 136x136 and
#: 1.4-1.6x at 192x192 (59b4b59's OpenMP pool: 0.9-1.6x and 0.8-1.0x); docs/gem.md §7.
FUSED_SERIAL_VALUES = 150_000


# ---------------------------------------------------------------------------------------
# Formulas
# ---------------------------------------------------------------------------------------

def error_rate_weight(gamma: float) -> float:
    """Weight ``z(γ) = −log(1 − (1.9 γ)^(1/√2))`` of the bias term (§4.3 of [1]).

    Chosen empirically by the authors so that ``γ`` is roughly the rate of wrong "stop"
    decisions on constant noisy input; stated valid for ``0 < γ < 0.4``.  Finite for
    ``0 < γ < 1/1.9``.  Larger ``γ`` weights the bias more, so the selector stops earlier
    (sharper, noisier).

    Examples
    --------
    >>> round(error_rate_weight(0.2), 4)
    0.7022
    """
    g = real_or_nan(gamma)                   # None, "0.2": refused; np.array(0.2) read
    if not (0.0 < g < _GAMMA_MAX) or not math.isfinite(g):
        raise InputError(f"`gamma` must be in (0, {_GAMMA_MAX:.4f}) (error rate of the scale "
                         f"selector; the paper uses 0.1-0.3); got {gamma!r}.")
    return -math.log1p(-((1.9 * g) ** (1.0 / math.sqrt(2.0))))


def bias_factor(r2_fine, r2_coarse):
    """``(r_c² + r_f²)/(r_c² − r_f²)``: the bias-term factor of §4.2 of [1], derived.

    If the image is locally quadratic and the filters have vanishing first moments,
    ``Bias[c] = k·Bias[f]`` with ``k = r_c²/r_f²``.  With ``c − f = (k − 1)·Bias[f]``,
    ``Bias[c]² − Bias[f]² = (k² − 1)·Bias[f]² = (k + 1)/(k − 1)·(c − f)²``; ``(k+1)/(k−1)``
    is this factor.  The paper prints the fraction upside down (negative).  For the pixel
    filter (``r_f² = 0``, unbiased by definition) it is 1: the bias term is ``(c − f)²``
    (§6 of [1]).  ``r²`` is the kernel's second moment per axis (:func:`kernel_moment2`).
    """
    rf = as_float_array("r2_fine", r2_fine).astype(np.float64, copy=False)
    rc = as_float_array("r2_coarse", r2_coarse).astype(np.float64, copy=False)
    if np.any(rc <= rf) or np.any(rf < 0) or not (np.all(np.isfinite(rf))
                                                   and np.all(np.isfinite(rc))):
        raise InputError(f"`r2_coarse` must exceed `r2_fine` >= 0, both finite; got {r2_coarse!r} "
                         f"and {r2_fine!r}.")
    out = (rc + rf) / (rc - rf)
    return float(out) if out.ndim == 0 else out


def bias_term(fine, coarse, r2_fine: float, r2_coarse: float):
    """Approximate ``Bias[c]² − Bias[f]²`` from filtered values (§4.2 of [1], derived).

    ``(r_c² + r_f²)/(r_c² − r_f²) · (c − f)²``; exact where the image is quadratic over
    both supports (see :func:`bias_factor`).
    """
    d = np.asarray(coarse) - np.asarray(fine)
    return bias_factor(r2_fine, r2_coarse) * d * d


def _moments(sigmas, truncate):
    return np.array([kernel_moment2(s, truncate=truncate) for s in sigmas])


def _pair_factors(sigmas, truncate):
    """Kernel second moments of the (checked, increasing) ``sigmas`` and their pair
    factors; an :class:`InputError` naming ``sigmas`` when the moments are not finite
    and strictly increasing (σ above ~1e154, whose ``r² ≈ σ²`` overflows, or two scales
    a rounding error apart)."""
    r2 = _moments(sigmas, truncate)
    if not (np.all(np.isfinite(r2)) and np.all(np.diff(r2) > 0)):
        raise InputError(f"`sigmas` must give finite, strictly increasing kernel second "
                         f"moments r² (statmc.filters.kernel_moment2; σ up to ~1e154, "
                         f"scales more than a rounding error apart, σ > 0 above ~0.03, "
                         f"below which the Gaussian is the pixel filter); got sigmas "
                         f"{sigmas} with r² {r2.tolist()}.")
    return r2, bias_factor(r2[:-1], r2[1:])


def _channel_sum(name, a, shape, channels, ref):
    """``a`` as float64 of ``shape``, summed over channels if given per channel."""
    arr = as_float_array(name, a, ndim=(3, 4)).astype(np.float64, copy=False)
    check_finite(name, arr)
    if arr.shape == shape + (channels,):
        return arr.sum(axis=3)
    if arr.shape != shape:
        raise InputError(f"`{name}` must be {shape + (channels,)} (per channel) or {shape} "
                         f"(summed over channels) to match {ref}; got {arr.shape}.")
    return arr


def _selector_inputs(values, variances, r2, weight, diff_variances=None):
    """Coerce and check the inputs of :func:`selector` and :func:`pooled_selector`.

    Returns ``values`` as (K, H, W, C) float64 (a (K, H, W) array is one channel),
    ``variances`` and ``diff_variances`` summed over channels ((K, H, W), (K−1, H, W)),
    the pair bias factors (K−1,) of :func:`bias_factor` and ``weight`` as a float64
    scalar or (H, W) array.
    """
    v = as_float_array("values", values, ndim=(3, 4)).astype(np.float64, copy=False)
    check_finite("values", v)
    if v.ndim == 3:
        v = v[..., None]
    k, h, w, c = v.shape
    if k < 2:
        raise InputError(f"`values` must hold K >= 2 scales (K, H, W, C); got shape {v.shape}.")
    ref = f"`values` {v.shape}"
    var = _channel_sum("variances", variances, (k, h, w), c, ref)
    check_nonnegative("variances", var)   # as `mean_var`: < 0 was taken, flipping decisions
    dv = None
    if diff_variances is not None:
        dv = _channel_sum("diff_variances", diff_variances, (k - 1, h, w), c, ref)
    r = _check_r2(r2, k, ref)
    wt = as_float_array("weight", weight).astype(np.float64, copy=False)
    if wt.shape not in ((), (h, w)):
        raise InputError(f"`weight` must be a number or an (H, W) = {(h, w)} map; got shape "
                         f"{wt.shape}.")
    check_finite("weight", wt)                      # NaN: every decision silently 'go on'
    check_nonnegative("weight", wt)                 # < 0 turns the bias term around
    return v, var, dv, bias_factor(r[:-1], r[1:]), wt


def _check_r2(r2, k, ref):
    """``r2`` as a (K,) float64 array of finite, increasing second moments >= 0."""
    r = as_float_array("r2", r2, ndim=1).astype(np.float64, copy=False)
    if r.shape != (k,):
        raise InputError(f"`r2` must hold one second moment per scale, shape ({k},) to match "
                         f"{ref}; got {r.shape}.")
    if not (np.all(np.isfinite(r)) and r[0] >= 0 and np.all(np.diff(r) > 0)):
        raise InputError(f"`r2` must be increasing second moments >= 0, fine to coarse "
                         f"(statmc.filters.kernel_moment2); got {r.tolist()}.")
    return r


def selector(values, variances, r2, *, weight=1.0) -> np.ndarray:
    """Scale selector ``S`` of Eq. 1 of [1] for every consecutive pair, summed over channels.

    ``S_k = weight · (r_{k+1}² + r_k²)/(r_{k+1}² − r_k²) · Σ_c (v_{k+1} − v_k)²
    + Σ_c (Var_{k+1} − Var_k)``; ``S_k > 0`` means stop at the finer scale ``k``.

    Parameters
    ----------
    values : (K, H, W, C) ndarray
        Filtered values, fine to coarse (:func:`statmc.filters.filter_bank`).
    variances : (K, H, W, C) or (K, H, W) ndarray
        Their variances (per channel or already summed over channels).
    r2 : (K,) array
        Second moments of the kernels (0 for the pixel filter).
    weight : float or (H, W) array
        ``ρ·z(γ)`` (§4.3); 1 gives the unweighted ΔMSE estimate.

    Returns
    -------
    S : (K-1, H, W) float64 ndarray
    """
    v, var, _, frac, wt = _selector_inputs(values, variances, r2, weight)
    bias = ((v[1:] - v[:-1]) ** 2).sum(axis=3)
    return wt * np.reshape(frac, (-1, 1, 1)) * bias + (var[1:] - var[:-1])


def pooled_selector(values, variances, diff_variances, r2, *, pool_sigma: float = BIAS_POOL_SIGMA,
                    weight=1.0, truncate: float = DEFAULT_TRUNCATE) -> np.ndarray:
    """Scale selector with a pooled, noise-corrected bias estimate (``bias="pooled"``).

    **A departure from [1]** (docs/gem.md §5d).  Eq. 1 estimates the bias term of each
    pixel from its own squared difference ``(c − f)²``, whose expectation is
    ``(Bias[c] − Bias[f])² + Var(c − f)``.  At moderate sample counts the noise part
    dominates, and the selector stops at fine scales wherever the noise happens to be
    large (the paper compensates with ρ·z(γ), calibrated on raw squares).  Here the noise
    part is subtracted and the result is averaged over a small Gaussian window, then
    clamped at 0:

    ``B_k = max(G_pool * [Σ_c (v_{k+1} − v_k)² − Σ_c Var(v_{k+1} − v_k)], 0)``,

    ``S_k = weight · (r_{k+1}² + r_k²)/(r_{k+1}² − r_k²) · B_k + Σ_c (Var_{k+1} − Var_k)``.

    Before the clamp, ``B_k`` is an unbiased estimate of the pooled squared bias
    difference (``E[(c − f)²] − Var(c − f)``), so with ``weight = 1`` ``S_k`` estimates
    the ΔMSE of §4.2 itself and ``S_k > 0`` (stop at the finer scale) is the plain MSE
    comparison; no error-rate weight z(γ) is involved.  On a locally quadratic image the
    bias term is exact, as in Eq. 1.  NumPy reference of the compiled selection
    (:func:`statmc._filter_kernels.pooled_bias_input`, ``stop_pooled``).

    Parameters
    ----------
    values : (K, H, W, C) ndarray
        Filtered values, fine to coarse (:func:`statmc.filters.filter_bank`).
    variances : (K, H, W, C) or (K, H, W) ndarray
        Their variances (per channel or summed over channels).
    diff_variances : (K-1, H, W, C) or (K-1, H, W) ndarray
        ``Var(v_{k+1} − v_k)`` (:func:`difference_variance`).
    r2 : (K,) array
        Second moments of the kernels (0 for the pixel filter).
    pool_sigma : float
        σ (pixels, finite, >= 0) of the border-renormalised pooling Gaussian
        (0: no pooling).
    weight : float or (H, W) array
        Weight of the bias term (1: the MSE comparison).
    truncate : float
        The pooling Gaussian is cut at ``ceil(truncate · pool_sigma)`` pixels from its
        centre (:func:`statmc.filters.gaussian_kernel_1d`); default
        :data:`~statmc.filters.DEFAULT_TRUNCATE` = 3, as in the bank.

    Returns
    -------
    S : (K-1, H, W) float64 ndarray
    """
    from .filters import _check_truncate, gaussian_filter
    v, var, dv, frac, wt = _selector_inputs(values, variances, r2, weight, diff_variances)
    pool_sigma = as_number("pool_sigma", pool_sigma, lo=0.0)
    truncate = _check_truncate(truncate)
    d = ((v[1:] - v[:-1]) ** 2).sum(axis=3) - dv
    if pool_sigma > 0:
        d = np.stack([gaussian_filter(x, pool_sigma, truncate=truncate) for x in d])
    bias = np.maximum(d, 0.0)
    return wt * np.reshape(frac, (-1, 1, 1)) * bias + (var[1:] - var[:-1])


# ---------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------

def _check_inputs(mean, mean_var, n=None):
    """Validate the inputs; returns mean, mean_var, their channel-summed variance (H, W)
    and the counts as float64 (or None)."""
    m, v, vsum = _check_pair(mean, mean_var)
    nn = None
    if n is not None:
        nn = np.asarray(n)
        if nn.shape != m.shape[:2]:
            raise InputError(f"`n` must be an (H, W) count map of shape {m.shape[:2]}; got {nn.shape}.")
        if nn.dtype.kind not in "iuf":     # not bool, complex, or timedelta (an integer to NumPy)
            raise InputError(f"`n` must hold sample counts (integers); got dtype {nn.dtype}.")
        counts = nn.astype(_count_dtype(nn.dtype), copy=False)
        nn = np.empty(nn.shape)
        bad, frac, low = _k.scan_counts(counts, nn)     # converts and counts in one pass
        if bad:
            check_finite("n", nn)
        if frac:
            raise InputError("`n` must hold whole sample counts; got non-integer values.")
        if low:
            raise InputError(f"`n` must be >= 2 in every pixel (a variance needs two samples; "
                             f"render at least 2 spp first); got {low} pixels with fewer "
                             f"(min {int(nn.min())}).")
    return m, v, vsum, nn


def _count_dtype(dt):
    """The dtype a count map of dtype ``dt`` reaches the count scan in: int64 for
    integers that int64 holds exactly, else float64 (both in native byte order).

    Each dtype the scan sees compiles it once more (4 s on a cold cache): '>i8', int32 or
    float32 counts were each a variant of their own, with the same float64 counts out.
    uint64 goes to float64 (NumPy's conversion, correctly rounded as the scan's own).
    """
    if dt.kind == "i" or (dt.kind == "u" and dt.itemsize < 8):
        return np.dtype(np.int64)
    return np.dtype(np.float64)


def _check_sigmas(sigmas):
    sig = [float(s) for s in _as_sigmas(sigmas)]
    if len(sig) < 2 or any(not math.isfinite(s) or s < 0 for s in sig) or \
            any(b <= a for a, b in zip(sig, sig[1:])):
        raise InputError(f"`sigmas` must be >= 2 increasing scales >= 0; got {sigmas!r}.")
    return sig


def _check_bias(bias):
    """``bias`` if it is ``None`` or one of :data:`BIAS_MODES`, else an :class:`InputError`."""
    if bias is not None and (not isinstance(bias, str) or bias not in BIAS_MODES):
        raise InputError(f"`bias` must be one of {BIAS_MODES} (the paper's per-pixel Eq. 1, or "
                         f"the pooled noise-corrected estimate) or None; got {bias!r}.")
    return bias


def _default_bias(bias, final):
    """``bias``, or its default when None: ``"pooled"`` for the final reconstruction,
    ``"paper"`` for the adaptive iterations."""
    if bias is None:
        return "pooled" if final else "paper"
    return bias


def _resolve_mode(final, bias, sigmas, map_scale):
    """Bias mode, scales and outlier-filter factor from the arguments, checked.

    ``bias=None`` is ``"pooled"`` for the final reconstruction and ``"paper"`` for the
    adaptive iterations; ``sigmas=None`` then takes that mode's default scales
    (:data:`POOLED_FINAL_SIGMAS` for the pooled final reconstruction, §6 of [1]
    otherwise).  ``map_scale=None`` is §6's factor in every mode (2 when ``final``,
    else 1).  Returns ``(bias, sigmas, map_scale)`` with ``map_scale`` that factor as a
    float.
    """
    final = as_bool("final", final)     # "no" was taken as True
    bias = _default_bias(_check_bias(bias), final)
    pooled_final = bias == "pooled" and final
    if sigmas is None:
        sigmas = POOLED_FINAL_SIGMAS if pooled_final else (FINAL_SIGMAS if final else ADAPTIVE_SIGMAS)
    sig = _check_sigmas(sigmas)
    return bias, sig, _map_scale(final, map_scale)


def _weight_map(n, gamma, shape, dtype):
    """ρ·z(γ) per pixel, ρ = 1 − 1/|P| (§4.3 of [1]); ρ = 1 when counts are unknown."""
    z = error_rate_weight(gamma)
    if n is None:
        return np.full(shape, z, dtype)
    out = np.empty(shape, dtype)
    _k.weight_map(n, z, out)
    return out


# ---------------------------------------------------------------------------------------
# Post-processing and selection
# ---------------------------------------------------------------------------------------

def _map_sigmas(sigmas, final, map_scale=None):
    """Outlier-removal filter of pair k: the coarse scale's Gaussian, doubled in the final
    reconstruction (§4.4 and §6 of [1]); ``map_scale`` overrides the factor."""
    f = _map_scale(final, map_scale)
    out = [sigmas[k + 1] * f for k in range(len(sigmas) - 1)]
    if not math.isfinite(out[-1]):      # 1e308 · 16: was "`sigma` must be a finite number"
        raise InputError(f"`map_scale` times the coarsest scale must be a finite σ (the "
                         f"outlier filter of the last pair); got map_scale {f!r} × σ "
                         f"{sigmas[-1]!r}.")
    return out


def _map_scale(final, map_scale):
    if map_scale is None:
        return 2.0 if final else 1.0
    return as_number("map_scale", map_scale, lo=0.0, lo_open=True)


def postprocess_stop_maps(stop, sigmas, *, final: bool, truncate: float = DEFAULT_TRUNCATE,
                          map_scale=None):
    """Remove outliers from binary stopping maps (§4.4 and §6 of [1]).

    Map ``k`` (pair ``σ_k → σ_{k+1}``) is filtered with a border-renormalised Gaussian of
    the coarse scale ``σ_{k+1}`` (``2σ_{k+1}`` when ``final``) whose centre pixel is left
    out, and rounded (ties, value exactly 1/2, give 1: keep the finer scale).  With
    ``final`` only switches 1 → 0 (towards the coarser scale) are accepted.

    Parameters
    ----------
    stop : (K-1, H, W) array of 0/1 (bool or float)
    sigmas : (K,) scales of the bank
    final : bool
    map_scale : float, optional
        Outlier filter of pair k = ``map_scale · σ_{k+1}`` (default 2 when ``final``,
        else 1, as in §6).

    Returns
    -------
    (K-1, H, W) bool ndarray
    """
    final = as_bool("final", final)
    raw = np.ascontiguousarray(as_float_array("stop", stop, dtype=np.float32))
    check_finite("stop", raw)                       # NaN: silently a 'go on' decision
    sig = _check_sigmas(sigmas)
    if raw.ndim != 3 or raw.shape[0] != len(sig) - 1:
        raise InputError(f"`stop` must be (K-1, H, W) = ({len(sig) - 1}, H, W); got {raw.shape}.")
    return _postprocess(raw, sig, final, truncate, map_scale) > 0.5


def _filter_many(x, c, v, cv, src, taps, sy, sx, out_x, out_v=None):
    """:func:`statmc.filters._run`'s filter for several jobs in one region: job k filters
    ``x[src[k]]`` (and ``v[src[k]]``) with the 1-D taps ``taps[k]`` and per-output factors
    ``sy[k]``, ``sx[k]`` into ``out_x[k]`` (``out_v[k]``)
    (:func:`statmc._filter_kernels.sep_filter_many`)."""
    dt = x.dtype
    h = x.shape[1]
    tt = np.zeros((len(taps), max(len(t) for t in taps)), dt)
    for k, t in enumerate(taps):
        tt[k, :len(t)] = t.astype(dt)
    if v is None:
        v, cv, out_v = np.empty((x.shape[0], h, 0), dt), 1, np.empty((len(taps), h, 0), dt)
    _k.sep_filter_many(x, c, v, cv, np.asarray(src, np.int64), tt,
                       np.array([len(t) for t in taps], np.int64),
                       np.stack(sy).astype(dt), np.stack(sx).astype(dt), out_x, out_v)


def _postprocess(raw, sig, final, truncate, map_scale=None):
    km1, h, w = raw.shape
    out = np.empty_like(raw)
    if h * w <= FUSED_PIXELS:                     # all maps in two regions
        taps = [_taps(s, truncate, max(h, w)) for s in _map_sigmas(sig, final, map_scale)]
        sy = [_border_scale(h, t) for t in taps]
        sx = [_border_scale(w, t) for t in taps]
        filt = np.empty_like(raw)
        _filter_many(raw, 1, None, 0, np.arange(km1), taps, sy, sx, filt)
        _k.finish_stop_map_many(filt, raw, np.array([t[len(t) // 2] for t in taps], np.float32),
                                np.stack(sy).astype(np.float32),
                                np.stack(sx).astype(np.float32), bool(final), out)
        return out
    filt = np.empty((h, w), np.float32)
    for k, s in enumerate(_map_sigmas(sig, final, map_scale)):
        wk = _taps(s, truncate, max(h, w))        # the kernel _run applies
        _run(raw[k], 1, None, 0, s, truncate, out_x=filt)
        r = len(wk) // 2
        _k.finish_stop_map(filt, raw[k], np.float32(wk[r]),
                           _border_scale(h, wk).astype(np.float32),
                           _border_scale(w, wk).astype(np.float32), bool(final), out[k])
    return out


def _postprocess_reference(raw, sig, final, truncate, map_scale=None, *, margins=False):
    """NumPy reference of the post-processing (dense weight matrices, float64).

    With ``margins=True`` also returns ``|m − ½|``, the distance of each pixel's
    centre-excluded mean from the rounding threshold (``inf`` where no neighbour counts).
    """
    out = np.empty(raw.shape, bool)
    dist = np.full(raw.shape, np.inf)
    h, w = raw.shape[1:]
    for k, s in enumerate(_map_sigmas(sig, final, map_scale)):
        ay = _weight_matrix(h, s, truncate)
        ax = _weight_matrix(w, s, truncate)
        b = raw[k].astype(np.float64)
        w0 = np.outer(np.diag(ay), np.diag(ax))
        with np.errstate(invalid="ignore", divide="ignore"):
            m = (ay @ b @ ax.T - w0 * b) / (1.0 - w0)
        alone = 1.0 - w0 <= 1e-6
        keep = np.where(alone, b > 0.5, m >= 0.5)
        out[k] = keep & (b > 0.5) if final else keep
        dist[k] = np.where(alone, np.inf, np.abs(m - 0.5))
    return (out, dist) if margins else out


def _first_stop_reference(maps):
    """NumPy reference of :func:`statmc._filter_kernels.first_stop`."""
    km1 = maps.shape[0]
    stop = np.asarray(maps) > 0.5
    return np.where(stop.any(axis=0), stop.argmax(axis=0), km1)


def estimate_mse(values, variances, r2, scales) -> np.ndarray:
    """Estimated MSE of the selected scale, per channel (§5 of [1]).

    ``MSE[s] = Var[0] + Σ_{k<s} ΔMSE_k`` with the unweighted ΔMSE of Eq. 1; the variance
    terms telescope to ``Var[s]``, leaving ``Var[s] + Σ_{k<s} frac_k (v_{k+1} − v_k)²``.
    The pixel filter (k = 0) is unbiased, so its MSE is its variance.

    Parameters
    ----------
    values, variances : (K, H, W, C) ndarrays of the bank
    r2 : (K,) kernel second moments
    scales : (H, W) int selected scale indices

    Returns
    -------
    (H, W, C) ndarray, >= 0
    """
    v = as_float_array("values", values)          # float16, big-endian: numba types neither
    var = as_float_array("variances", variances, dtype=v.dtype)
    s = np.asarray(scales)
    if v.ndim != 4 or var.shape != v.shape or s.shape != v.shape[1:3]:
        raise InputError(f"`values`, `variances` must be (K, H, W, C) and `scales` (H, W); "
                         f"got {v.shape}, {var.shape}, {s.shape}.")
    if not np.issubdtype(s.dtype, np.integer):      # 0.5 and True were read as index 0
        raise InputError(f"`scales` must be an (H, W) integer array of scale indices; got "
                         f"dtype {s.dtype}.")
    if s.size and (s.min() < 0 or s.max() >= v.shape[0]):
        raise InputError(f"`scales` must lie in [0, {v.shape[0] - 1}]; got [{s.min()}, {s.max()}].")
    k, h, w, c = v.shape
    check_finite("values", v)
    check_finite("variances", var)
    r = _check_r2(r2, k, f"`values` {v.shape}")   # short: the kernel read past its end
    frac = np.asarray(bias_factor(r[:-1], r[1:]), dtype=v.dtype)
    if v.size == 0:                          # no pixels or channels (C = 0 divided the kernel)
        return np.zeros((h, w, c), v.dtype)
    out = np.empty((h, w * c), v.dtype)
    _k.estimate_mse(np.ascontiguousarray(v).reshape(k, h, w * c),
                    np.ascontiguousarray(var).reshape(k, h, w * c), c, frac,
                    np.ascontiguousarray(s, dtype=np.intp), out)
    return out.reshape(h, w, c)


def _estimate_mse_reference(values, variances, r2, scales):
    frac = bias_factor(np.asarray(r2)[:-1], np.asarray(r2)[1:])
    v = np.asarray(values, np.float64)
    inc = np.reshape(frac, (-1, 1, 1, 1)) * (v[1:] - v[:-1]) ** 2
    cum = np.concatenate([np.zeros_like(v[:1]), np.cumsum(inc, axis=0)])
    s = np.asarray(scales)[None, :, :, None]
    return (np.take_along_axis(cum, s, 0) + np.take_along_axis(np.asarray(variances, np.float64), s, 0))[0]


def _product_taps(sa, sb, truncate, n):
    """1-D taps ``g_a(k)·g_b(k)``, ``σ_a < σ_b``, on the support of the narrower kernel
    (outside it the product is 0); ``g`` the bank's taps on an image of longer side ``n``
    (:func:`statmc.filters._taps`), returned too."""
    ga, gb = _taps(sa, truncate, n), _taps(sb, truncate, n)
    return _taps_product(ga, gb), ga, gb


def _taps_product(ga, gb):
    """:func:`_product_taps` of the taps ``ga``, ``gb`` themselves."""
    r = min(len(ga), len(gb)) // 2
    return ga[len(ga) // 2 - r:len(ga) // 2 + r + 1] * gb[len(gb) // 2 - r:len(gb) // 2 + r + 1]


def _pair_covariance_rows(vr, cv, sa, sb, truncate, out=None):
    """``Cov(f_a, f_b)(p) = Σ_q w_a(p, q) w_b(p, q) mean_var(q)`` on (H, W·C) rows.

    The product of two border-renormalised separable Gaussians is separable, with taps
    ``g_a g_b`` and per-output factors ``1/(N_a N_b)``: one filter pass.
    """
    h, L = vr.shape
    wd = L // cv
    dt = vr.dtype
    if out is None:
        out = np.empty_like(vr)
    if sa == 0.0:  # pixel filter: w_a(p, q) = [p = q], so Cov = w_b(p, p) mean_var(p)
        gb = _taps(sb, truncate, max(h, wd))
        g0 = gb[len(gb) // 2]
        _k.scale_rows(vr, cv, (g0 * _border_scale(h, gb)).astype(dt),
                      (g0 * _border_scale(wd, gb)).astype(dt), out)
        return out
    taps, ga, gb = _product_taps(sa, sb, truncate, max(h, wd))
    sy = _border_scale(h, ga) * _border_scale(h, gb)
    sx = _border_scale(wd, ga) * _border_scale(wd, gb)
    _k.sep_filter(vr, cv, np.empty((h, 0), dt), 1, taps.astype(dt), sy.astype(dt),
                  sx.astype(dt), out, np.empty((h, 0), dt))
    return out


def _pair_covariances(vr, cv, sig, truncate):
    """(K−1, H, L) covariances of consecutive bank scales, :func:`_pair_covariance_rows`."""
    cov = np.empty((len(sig) - 1,) + vr.shape, vr.dtype)
    for k in range(len(sig) - 1):
        _pair_covariance_rows(vr, cv, sig[k], sig[k + 1], truncate, out=cov[k])
    return cov


def _difference_variance_rows(vr, cv, bank_vars, sig, truncate):
    """``Var(v_{k+1} − v_k) = Var_{k+1} + Var_k − 2 Cov_k``, clamped at 0, (K−1, H, L)."""
    cov = _pair_covariances(vr, cv, sig, truncate)
    _k.difference_variance(bank_vars, cov, cov)     # in place: row k read before written
    return cov


def difference_variance(mean_var, sigmas=ADAPTIVE_SIGMAS, *,
                        truncate: float = DEFAULT_TRUNCATE) -> np.ndarray:
    """Variance of the difference of consecutive bank scales, ``Var(v_{k+1} − v_k)``.

    With pixel estimates uncorrelated (as in Eq. 2 of [1]_),
    ``Var(c − f)(p) = Σ_q (w_c(p, q) − w_f(p, q))² mean_var(q)
    = Var[c] + Var[f] − 2 Σ_q w_c(p, q) w_f(p, q) mean_var(q)``.
    ``E[(c − f)²] = (Bias[c] − Bias[f])² + Var(c − f)``, so this is the noise part of the
    squared differences that §5 accumulates into the estimated MSE; ``sampling_map(...,
    debias=True)`` subtracts it.

    Parameters
    ----------
    mean_var : (H, W, C) ndarray
        Variance of the mean of each pixel estimate (>= 0).
    sigmas : sequence of float
        Increasing scales (0 = pixel filter), default the adaptive set.

    Returns
    -------
    (K − 1, H, W, C) ndarray, >= 0
    """
    v = as_float_array("mean_var", mean_var, ndim=(2, 3))
    check_finite("mean_var", v)
    check_nonnegative("mean_var", v)
    sig = _check_sigmas(sigmas)
    if v.size == 0:                                   # no pixels or no channels
        return np.zeros((len(sig) - 1,) + v.shape, v.dtype)
    vr, cv = _rows(v)
    bank = np.empty((len(sig),) + vr.shape, vr.dtype)
    for k, s in enumerate(sig):
        if s == 0.0:
            bank[k] = vr
        else:
            _run(vr, cv, vr, cv, s, truncate, out_v=bank[k])
    out = _difference_variance_rows(vr, cv, bank, sig, truncate)
    return out.reshape((len(sig) - 1,) + v.shape)


def _difference_variance_reference(mean_var, sigmas, truncate=DEFAULT_TRUNCATE):
    """Dense NumPy reference of :func:`difference_variance`."""
    v = np.asarray(mean_var, np.float64)
    h, w = v.shape[:2]
    mats = [(np.eye(h), np.eye(w)) if s == 0 else
            (_weight_matrix(h, s, truncate), _weight_matrix(w, s, truncate)) for s in sigmas]
    out = []
    for (ay, ax), (by, bx) in zip(mats[:-1], mats[1:]):
        out.append(np.einsum("ip,jq,pqc->ijc", by ** 2, bx ** 2, v)
                   + np.einsum("ip,jq,pqc->ijc", ay ** 2, ax ** 2, v)
                   - 2 * np.einsum("ip,jq,pqc->ijc", ay * by, ax * bx, v))
    return np.maximum(np.array(out), 0.0)


def _variance_prior(v, nn, weight, sigma, truncate=DEFAULT_TRUNCATE):
    """Pooled-prior (shrunk) variance of the mean for the sampler; see :func:`sampling_map`.

    ``s̃² = ((n − 1) s² + k s̄²) / (n − 1 + k)`` with ``s² = n·mean_var`` the pixel's
    sample variance and ``s̄²`` its Gaussian-pooled neighbourhood average: the posterior
    mean of σ² under a scaled-inverse-χ² prior of ``k`` pseudo-degrees of freedom centred
    on the neighbourhood (conjugate for Gaussian samples).  Returns ``s̃² / n``.
    Two elementwise kernels around one filter pass; NumPy reference
    :func:`_variance_prior_reference`.
    """
    dt = v.dtype.type
    nb = np.ascontiguousarray(nn, dtype=v.dtype)
    x, c = _rows(v)
    s2 = _k.prior_scale(x, nb, c, np.empty_like(x))
    pooled = _run(s2, c, None, 0, sigma, truncate)[0]
    _k.prior_shrink(s2, pooled, nb, c, dt(weight), dt(1), s2)   # in place, elementwise
    return s2.reshape(v.shape)


def _variance_prior_reference(v, nn, weight, sigma, truncate=DEFAULT_TRUNCATE):
    """NumPy reference of :func:`_variance_prior`."""
    nb = nn.reshape(nn.shape + (1,) * (v.ndim - 2)).astype(v.dtype)
    s2 = v * nb
    x, c = _rows(s2)
    pooled = _run(x, c, None, 0, sigma, truncate)[0].reshape(s2.shape)
    k = v.dtype.type(weight)
    return np.ascontiguousarray(((nb - 1) * s2 + k * pooled) / ((nb - 1 + k) * nb))


def _pooled_stops_fused(x, c, vr, cv, vsum, sig, fr, truncate, vals, vars_, raw):
    """The bank and the pooled stopping maps of :func:`_core`, stage by stage for all
    scales (one parallel region per stage): ``vals``, ``vars_`` (every scale's
    variances) and ``raw`` are written."""
    h, w = vsum.shape
    nsc = len(sig)
    dt = x.dtype
    p0 = 1 if sig[0] == 0.0 else 0                # the pixel filter (increasing: only sig[0])
    if p0:
        vals[0] = x
        vars_[0] = vr
    # the bank: one input, every σ; taps[j] and its border scales are those of sig[p0 + j]
    taps = [_taps(s, truncate, max(h, w)) for s in sig[p0:]]
    by = [_border_scale(h, t) for t in taps]
    bx = [_border_scale(w, t) for t in taps]
    _filter_many(x[None], c, vr[None], cv, np.zeros(nsc - p0), taps, by, bx,
                 vals[p0:], vars_[p0:])
    cov = np.empty((nsc - 1, h, w), dt)           # pair covariances of the summed variance
    if p0:
        _pair_covariance_rows(vsum, 1, sig[0], sig[1], truncate, out=cov[0])
    if nsc - 1 > p0:                              # pair (k, k + 1) = bank taps (j, j + 1)
        pairs = range(nsc - 1 - p0)
        _filter_many(vsum[None], 1, None, 0, np.zeros(len(pairs)),
                     [_taps_product(taps[j], taps[j + 1]) for j in pairs],
                     [by[j] * by[j + 1] for j in pairs], [bx[j] * bx[j + 1] for j in pairs],
                     cov[p0:])
    d = np.empty((nsc - 1, h, w), dt)
    _k.pooled_bias_input_many(vals, vars_, cov, c, cv, d)
    pool = _taps(BIAS_POOL_SIGMA, truncate, max(h, w))
    _filter_many(d, 1, None, 0, np.arange(nsc - 1), [pool] * (nsc - 1),
                 [_border_scale(h, pool)] * (nsc - 1), [_border_scale(w, pool)] * (nsc - 1),
                 cov)                             # the pooled D, over the covariances
    _k.stop_pooled_many(cov, vars_, cv, fr[:nsc - 1].astype(np.float64), 1.0, raw)


def _core(m, v, vsum, n, gamma, sig, final, postprocess, truncate, *, keep_bank,
          debias=False, map_scale=None, bias="paper"):
    """Bank → stopping maps → post-processing → selection → image.

    With ``keep_bank`` the per-channel variances of every scale are kept and the
    estimated MSE is computed; without it only the channel-summed variance is filtered
    (all the selector needs) and two scales of it are held at a time.  ``bias="pooled"``
    forms the stopping maps with :func:`pooled_selector` (compiled): per pair, the
    covariance of the two scales (one filter pass over the channel-summed variance), the
    noise-corrected squared difference, its pooling over :data:`BIAS_POOL_SIGMA` (one
    filter pass), the decision.  ``gamma`` is validated in every mode but only enters
    ``bias="paper"``.
    """
    final, postprocess = as_bool("final", final), as_bool("postprocess", postprocess)
    debias = as_bool("debias", debias)
    h, w = m.shape[:2]
    x, c = _rows(m)
    if keep_bank:
        vr, cv = _rows(v)
    else:
        vr, cv = vsum, 1
    nsc = len(sig)
    r2, frac = _pair_factors(sig, truncate)
    dt = x.dtype
    fr = frac.astype(dt)
    pooled = bias == "pooled"
    fused = pooled and h * w <= FUSED_PIXELS      # every stage over all scales at once
    if pooled:
        error_rate_weight(gamma)                      # validates γ; unused by this mode
        if not fused:
            work = np.empty((3, h, w), dt)            # covariance, D, pooled D
    else:
        weight = _weight_map(n, gamma, (h, w), dt)
    vals = np.empty((nsc,) + x.shape, dt)
    raw = np.empty((nsc - 1, h, w), np.float32)
    if keep_bank or fused:                            # every scale's variance is held
        vars_ = np.empty((nsc,) + vr.shape, dt)
        slots = [vars_[k] for k in range(nsc)]
    else:                                             # two scales of it at a time
        vars_ = None
        spare = [np.empty_like(vr), np.empty_like(vr)]
        slots = [spare[k % 2] for k in range(nsc)]
    if fused:
        _pooled_stops_fused(x, c, vr, cv, vsum, sig, fr, truncate, vals, vars_, raw)
        if not keep_bank:
            vars_ = None
    prev = None
    for k, s in enumerate(sig if not fused else ()):
        if s == 0.0:
            vals[k] = x
            if keep_bank:
                slots[k][...] = vr
            else:
                slots[k] = vr
        else:
            _run(x, c, vr, cv, s, truncate, out_x=vals[k], out_v=slots[k])
        if k and pooled:
            _pair_covariance_rows(vsum, 1, sig[k - 1], s, truncate, out=work[0])
            _k.pooled_bias_input(vals[k - 1], vals[k], prev, slots[k], work[0], c, cv, work[1])
            _run(work[1], 1, None, 0, BIAS_POOL_SIGMA, truncate, out_x=work[2])
            _k.stop_pooled(work[2], prev, slots[k], cv, float(fr[k - 1]), 1.0, raw[k - 1])
        elif k:
            _k.stop_pair(vals[k - 1], vals[k], prev, slots[k], c, cv, fr[k - 1], weight, raw[k - 1])
        prev = slots[k]
    maps = _postprocess(raw, sig, final, truncate, map_scale) if postprocess else raw
    scales = np.empty((h, w), np.intp)
    _k.first_stop(maps, scales)
    image = np.empty((h, w * c), dt)
    _k.gather(vals, c, scales, image)
    out = {"image": image.reshape(m.shape), "scales": scales, "sigmas": tuple(sig), "r2": r2,
           "bias_factors": frac, "raw": raw, "maps": maps, "bias": bias}
    if keep_bank:
        est = np.empty((h, w * c), dt)
        if debias:
            p0 = sig[0] == 0.0      # pixel-filter pair: its covariance is formed inline
            cov = np.empty((nsc - 1 - p0,) + vr.shape, dt)
            for k in range(p0, nsc - 1):
                _pair_covariance_rows(vr, cv, sig[k], sig[k + 1], truncate, out=cov[k - p0])
            if p0:
                g1 = _taps(sig[1], truncate, max(h, w))
                fy0 = (g1[len(g1) // 2] * _border_scale(h, g1)).astype(dt)
                fx0 = (g1[len(g1) // 2] * _border_scale(w, g1)).astype(dt)
            else:
                fy0 = fx0 = np.empty(0, dt)
            _k.estimate_mse_debiased(vals, vars_, cov, c, fr, scales, fy0, fx0, est)
        else:
            _k.estimate_mse(vals, vars_, c, fr, scales, est)
        shape = (nsc,) + m.shape
        out.update(values=vals.reshape(shape), variances=vars_.reshape(shape),
                   est_mse=est.reshape(m.shape))
    return out


# ---------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------

def _serial_threshold(kwargs) -> int:
    """:func:`serial_when_small`'s threshold of a ``select``/``reconstruct``/
    ``selected_filter`` call: :data:`FUSED_SERIAL_VALUES` when its selection is the pooled
    one (``bias="pooled"``, or the default of ``final=True``), whose stages run fused; else
    ``SERIAL_VALUES``."""
    bias = kwargs.get("bias")
    try:
        pooled = isinstance(bias, (str, type(None))) and \
            _default_bias(bias, kwargs.get("final", True)) == "pooled"
    except Exception:                          # an odd `final`: the call will say why
        pooled = False
    return FUSED_SERIAL_VALUES if pooled else SERIAL_VALUES


@serial_when_small(threshold_of=_serial_threshold)
def select(mean, mean_var, *, gamma: float = DEFAULT_GAMMA, final: bool = True, n=None,
           sigmas=None, postprocess: bool = True, truncate: float = DEFAULT_TRUNCATE,
           map_scale=None, bias=None) -> dict:
    """Select a filter scale per pixel and return everything that went into the choice.

    Parameters
    ----------
    mean : (H, W, C) ndarray
        Pixel estimates.
    mean_var : (H, W, C) ndarray
        Variance of the mean of each pixel estimate (>= 0).
    gamma : float
        Error-rate parameter γ of §4.3 of [1] (rate of wrong stops on constant input).
        Used by ``bias="paper"`` only; unused (but validated) with ``bias="pooled"``.
    final : bool
        Final-reconstruction settings (map filters of twice the coarse scale, only
        switches to coarser scales, §6) with the scales :data:`POOLED_FINAL_SIGMAS` and
        ``bias="pooled"`` by default, or §6's :data:`~statmc.filters.FINAL_SIGMAS` with
        ``bias="paper"``; ``False`` gives the adaptive settings
        (:data:`~statmc.filters.ADAPTIVE_SIGMAS`, coarse-scale map filters,
        ``bias="paper"``).
    n : (H, W) int array, optional
        Samples per pixel (>= 2), for the low-count correction ``ρ = 1 − 1/n`` (§4.3) of
        ``bias="paper"``; ``ρ = 1`` when not given.  Unused (but validated) with
        ``bias="pooled"``.
    sigmas : sequence of float, optional
        Override the scales (increasing; 0 = pixel filter).
    postprocess : bool
        Apply the outlier removal of §4.4 (default) or use the raw selector decisions.
    truncate : float
        Cut-off in σ of every Gaussian involved (the bank, its second moments ``r2``, the
        outlier filters, the pooling of ``bias="pooled"``); default 3
        (:data:`~statmc.filters.DEFAULT_TRUNCATE`).  Kernels longer than the image are cut
        to it without changing the result (``docs/gem.md`` §1).
    map_scale : float, optional
        Outlier filter of pair k = ``map_scale · σ_{k+1}``; default 2 when ``final``, else 1
        (§6).
    bias : {"pooled", "paper"}, optional
        How the selector estimates the bias term.  ``"paper"``: Eq. 1 of [1], each pixel's
        own squared difference weighted by ``ρ·z(γ)``.  ``"pooled"`` (**a departure**, see
        :func:`pooled_selector` and ``docs/gem.md`` §5d): the squared difference minus its
        known noise variance, averaged over a Gaussian of σ = :data:`BIAS_POOL_SIGMA` and
        clamped at 0, in the plain MSE comparison (weight 1; ``gamma`` and ``n`` do not
        enter).  Default: ``"pooled"`` when ``final`` (with the scales
        :data:`POOLED_FINAL_SIGMAS` unless given), ``"paper"`` otherwise.
        ``bias="paper"`` with ``final`` is the literal §6.

    Returns
    -------
    dict with
        ``image`` (H, W, C) the reconstruction; ``scales`` (H, W) selected index into
        ``sigmas``; ``sigmas``; ``r2`` kernel second moments; ``bias_factors``;
        ``values``, ``variances`` (K, H, W, C) the bank; ``stop_raw``, ``stop``
        (K-1, H, W) bool stopping maps before/after post-processing; ``est_mse``
        (H, W, C) estimated MSE of the selected filter (§5, from the raw squared
        differences whatever ``bias``); ``bias`` the mode used.
    """
    m, v, vsum, nn = _check_inputs(mean, mean_var, n)
    bias, sig, map_scale = _resolve_mode(final, bias, sigmas, map_scale)
    out = _core(m, v, vsum, nn, gamma, sig, final, postprocess, truncate, keep_bank=True,
                map_scale=map_scale, bias=bias)
    out["stop_raw"] = out.pop("raw") > 0.5
    out["stop"] = out.pop("maps") > 0.5
    return out


def select_scales(mean, mean_var, *, gamma: float = DEFAULT_GAMMA, final: bool = True, n=None,
                  sigmas=None, postprocess: bool = True, map_scale=None, bias=None) -> np.ndarray:
    """Selected scale index per pixel, ``(H, W)``; see :func:`select`.

    As there, ``gamma`` and ``n`` only enter with ``bias="paper"`` (the default when not
    ``final``); with ``bias="pooled"`` (the default when ``final``) they are validated
    and unused.
    """
    m, v, vsum, nn = _check_inputs(mean, mean_var, n)
    bias, sig, map_scale = _resolve_mode(final, bias, sigmas, map_scale)
    return _core(m, v, vsum, nn, gamma, sig, final, postprocess, DEFAULT_TRUNCATE,
                 keep_bank=False, map_scale=map_scale, bias=bias)["scales"]


@serial_when_small(threshold_of=_serial_threshold)
def reconstruct(mean, mean_var, *, gamma: float = DEFAULT_GAMMA, final: bool = True, n=None,
                extra_output: bool = False, sigmas=None, map_scale=None, bias=None):
    """GEM reconstruction: each pixel takes the filter scale that minimises its MSE.

    Parameters
    ----------
    mean : (H, W, C) ndarray
        Pixel estimates (the finest scale).
    mean_var : (H, W, C) ndarray
        **Variance of the mean** per pixel and channel (sample variance / n), >= 0.
    gamma : float
        Error-rate parameter γ (§4.3 of [1]), in (0, 0.526); 0.1–0.3 is sensible.  Used by
        ``bias="paper"`` only; unused (but validated) with ``bias="pooled"``.
    final : bool
        Final reconstruction (§6: only switches to coarser scales in the outlier removal;
        by default with the pooled bias estimate, see ``bias``); ``False`` gives the
        adaptive-iteration settings of the paper (σ = 1, 2, 4, 8, outlier filters of the
        coarse scale, ``bias="paper"``).
    n : (H, W) ndarray, optional
        Samples per pixel (>= 2) for the low-count correction ``ρ = 1 − 1/n`` of
        ``bias="paper"``; without it ``ρ = 1``.  Unused (but validated) with
        ``bias="pooled"``.
    extra_output : bool
        Also return the dictionary of :func:`select` (scales, bank, maps, est. MSE).
    sigmas, map_scale : optional
        Override the scales and the outlier-filter factor (see :func:`select`).
    bias : {"pooled", "paper"}, optional
        Bias estimate of the selector (see :func:`select`).  The default for ``final`` is
        ``"pooled"`` — **a departure from the paper** — with the scales
        :data:`POOLED_FINAL_SIGMAS` (σ = 0.6 … 13.6; §6's outlier removal unchanged).
        On the four built-in Mitsuba scenes at 16–64 spp uniform+GEM then had at most
        0.46× the relMSE of the box filter (textured-dof: 0.31/0.39/0.46 at 16/32/64
        spp), against 0.71–0.93× on textured-dof for the literal §6 (``bias="paper"``);
        ``docs/gem.md`` §5b, §5d.

    Returns
    -------
    image : (H, W, C) ndarray (same dtype as ``mean``)
    info : dict, only with ``extra_output``

    Notes
    -----
    Decisions combine channels by summing their ΔMSE (the selector minimises the total
    squared error of the pixel).  Borders use renormalised filters; there, the kernels
    are one-sided and the quadratic bias relation is only approximate.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> truth = np.full((32, 32, 3), 0.5, np.float32)
    >>> noisy = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
    >>> out = reconstruct(noisy, np.full_like(noisy, 0.01))
    >>> out.dtype, bool(np.mean((out - truth) ** 2) < 0.1 * np.mean((noisy - truth) ** 2))
    (dtype('float32'), True)
    """
    if as_bool("extra_output", extra_output):
        info = select(mean, mean_var, gamma=gamma, final=final, n=n, sigmas=sigmas,
                      map_scale=map_scale, bias=bias)
        return info["image"], info
    m, v, vsum, nn = _check_inputs(mean, mean_var, n)
    bias, sig, map_scale = _resolve_mode(final, bias, sigmas, map_scale)
    return _core(m, v, vsum, nn, gamma, sig, final, True, DEFAULT_TRUNCATE,
                 keep_bank=False, map_scale=map_scale, bias=bias)["image"]


class SelectedFilter:
    """GEM's reconstruction as a fixed linear filter: the kernel it selected, exposed.

    Pixel ``p`` of the output is the border-renormalised Gaussian of σ =
    ``sigmas[scales[p]]`` (the pixel itself for σ = 0) applied to the input — the
    per-pixel filter that :func:`select` chose from the full sample (Rousselle et al.
    2011 [1]_, §4, §6: the output is the selected scale of the filter bank).  Applied to
    the render it reproduces :func:`reconstruct`; applied to anything else (a sample bin,
    a probe vector) it is a *linear* map that does not select again.  This is what
    Back et al. 2020 (§4.4, "Network Input") do for denoisers that expose their weights:
    compute the kernel from all samples, then share it among the ``B`` bins,
    ``z_{c,b} = Σ_i w̄_i y_{i,b}``; :func:`statmc.combine.combine_bins` uses it so.  Its
    linearity also makes the moments of :func:`statmc.combine.denoiser_moments` exact
    in expectation (first order is exact).

    Parameters
    ----------
    scales : (H, W) int array
        Selected index into ``sigmas`` per pixel (``select(...)["scales"]``).
    sigmas : sequence of float
        The bank's Gaussian σ (0 = the pixel filter), increasing.
    truncate : float
        Kernel cut-off in σ (the bank's).
    """

    def __init__(self, scales, sigmas, *, truncate: float = DEFAULT_TRUNCATE):
        sig = _check_sigmas(sigmas)
        sc = np.asarray(scales)
        if sc.ndim != 2 or not np.issubdtype(sc.dtype, np.integer):
            raise InputError(f"`scales` must be an (H, W) integer array; got shape {sc.shape} "
                             f"of {sc.dtype}.")
        if sc.size and (sc.min() < 0 or sc.max() >= len(sig)):
            raise InputError(f"`scales` must index `sigmas` (0 … {len(sig) - 1}); got values "
                             f"{int(sc.min())} … {int(sc.max())}.")
        # an own read-only copy: neither the caller's array nor ``f.scales`` may change
        # after the range check
        self.scales = np.array(sc, dtype=np.intp, order="C", copy=True)
        self.scales.flags.writeable = False
        self.sigmas = tuple(sig)
        self.truncate = float(as_number("truncate", truncate, lo=0.0, lo_open=True))
        # the scales in use, and each pixel's index among them: a call filters only those
        # (the compiled gather indexes the stack by ``_slot`` unchecked)
        self._used, slot = np.unique(self.scales, return_inverse=True)
        self._slot = np.ascontiguousarray(slot.reshape(self.scales.shape), dtype=np.intp)

    @property
    def shape(self) -> tuple[int, int]:
        return self.scales.shape

    def __call__(self, image) -> np.ndarray:
        """Filter ``image`` ``(H, W, C)`` or ``(H, W)`` with the selected kernels (same
        dtype for float32/float64 input)."""
        a = np.asarray(image)
        dt = a.dtype if a.dtype in (np.float32, np.float64) else np.float64
        x3 = as_float_array("image", a, ndim=(2, 3), dtype=dt)
        check_finite("image", x3)
        if x3.shape[:2] != self.scales.shape:
            raise InputError(f"`image` has {x3.shape[0]}x{x3.shape[1]} pixels but the filter "
                             f"was selected on {self.scales.shape[0]}x{self.scales.shape[1]}.")
        if x3.size == 0:                    # no channels (or pixels): ZeroDivisionError
            return x3.copy()
        x, c = _rows(x3)
        vals = np.empty((len(self._used),) + x.shape, dt)
        for j, k in enumerate(self._used):
            if self.sigmas[k] == 0.0:
                vals[j] = x
            else:
                _run(x, c, None, 0, self.sigmas[k], self.truncate, out_x=vals[j])
        out = np.empty_like(x)
        _k.gather(vals, c, self._slot, out)
        return out.reshape(x3.shape)

    def reference(self, image) -> np.ndarray:
        """Plain NumPy/SciPy version of ``__call__`` (tests compare the two): each scale
        by :func:`scipy.ndimage.correlate1d` with the border-renormalised kernel."""
        from scipy.ndimage import correlate1d

        x = np.asarray(image, np.float64)
        h, w = x.shape[:2]
        out = np.empty_like(x)
        for k, s in enumerate(self.sigmas):
            sel = self.scales == k
            if not sel.any():
                continue
            if s == 0.0:
                out[sel] = x[sel]
                continue
            g = gaussian_kernel_1d(s, truncate=self.truncate)
            f = correlate1d(correlate1d(x, g, axis=0, mode="constant"), g, axis=1,
                            mode="constant")
            norm = np.outer(correlate1d(np.ones(h), g, mode="constant"),
                            correlate1d(np.ones(w), g, mode="constant"))
            f = f / norm.reshape(norm.shape + (1,) * (x.ndim - 2))
            out[sel] = f[sel]
        return out


@serial_when_small(threshold_of=_serial_threshold)
def selected_filter(mean, mean_var, **options):
    """GEM on the render and the kernel it selected: ``(image, SelectedFilter)``.

    ``options`` are those of :func:`select` (``gamma``, ``final``, ``n``, ``sigmas``,
    ``map_scale``, ``bias``).  ``filter(mean)`` equals ``image`` (Rousselle et al.
    2011 §6: the output is the selected scale of the bank).
    """
    m, v, vsum, nn = _check_inputs(mean, mean_var, options.pop("n", None))
    gamma = options.pop("gamma", DEFAULT_GAMMA)
    final = options.pop("final", True)
    bias, sig, map_scale = _resolve_mode(final, options.pop("bias", None),
                                         options.pop("sigmas", None),
                                         options.pop("map_scale", None))
    if options:
        raise InputError(f"unknown option(s) {sorted(options)}; expected gamma, final, n, "
                         "sigmas, map_scale, bias.")
    out = _core(m, v, vsum, nn, gamma, sig, final, True, DEFAULT_TRUNCATE, keep_bank=False,
                map_scale=map_scale, bias=bias)
    return out["image"], SelectedFilter(out["scales"], sig)


def _allocate(gain, budget, batch):
    """Samples per pixel before spreading: the best pixels get ``batch`` each (§5).

    NumPy reference of one round of :func:`statmc._filter_kernels.allocate_rounds`.
    ``budget // batch`` batches go to the pixels of largest gain (everyone gets
    ``budget // (batch·size)`` batches first if there are more batches than pixels) and
    the remainder ``budget % batch`` to the next pixel in that order.  Equal gains are
    ordered by pixel index (lower first), so the result is deterministic.
    """
    g = gain.ravel()
    size = g.size
    amount = np.zeros(size)
    if budget == 0:
        return amount.reshape(gain.shape)
    if not np.any(g > 0):  # nothing to gain anywhere (e.g. noise-free input): uniform
        amount[:] = budget / size
        return amount.reshape(gain.shape)
    m, rem = divmod(budget, batch)
    rounds, m = divmod(m, size)
    amount += rounds * batch
    if m or rem:
        q = m if rem else m - 1                        # last rank that gets samples
        t = np.partition(g, size - 1 - q)[size - 1 - q]   # value at rank q (descending)
        above = np.flatnonzero(g > t)
        ties = np.flatnonzero(g == t)[:q + 1 - above.size]
        amount[above] += batch
        if rem:
            amount[ties[:-1]] += batch
            amount[ties[-1]] += rem
        else:
            amount[ties] += batch
    return amount.reshape(gain.shape)


def _allocate_rounds(rel, n, budget, batch, rounds):
    """Greedy allocation in ``rounds`` rounds, updating the gains analytically in between.

    Each round hands out its share of ``budget`` with :func:`_allocate`; a pixel that
    received ``a`` samples then has ``rel ← rel·n/(n + a)`` and ``n ← n + a`` (§5 of [1]:
    relative MSE is inversely proportional to the samples), so its next gain is
    ``rel·batch/(n + batch)`` at its new count.  ``rounds = 1`` is the paper's single step.
    NumPy reference of :func:`_allocate_rounds_fast`.
    """
    if rounds == 1:
        return _allocate(rel * batch / (n + batch), budget, batch)
    amount = np.zeros(rel.shape)
    r = rel.astype(np.float64, copy=True)
    nn = n.astype(np.float64, copy=True)
    for i in range(rounds):
        part = budget // rounds + (1 if i < budget % rounds else 0)
        a = _allocate(r * batch / (nn + batch), part, batch)
        amount += a
        r *= nn / (nn + a)
        nn += a
    return amount


def _allocate_rounds_fast(rel, n, budget, batch, rounds):
    """:func:`_allocate_rounds` in one compiled kernel (radix selection per round)."""
    amount = np.empty(rel.shape)
    work = np.empty((3, rel.size))                    # r, n, gain (NumPy: huge pages)
    _k.allocate_rounds(np.ascontiguousarray(rel, np.float64).ravel(),
                       np.ascontiguousarray(n, np.float64).ravel(), int(budget), int(batch),
                       int(rounds), amount.reshape(-1), work[0], work[1], work[2],
                       np.empty((2 * thread_count(), 1 << _k._DIGIT), np.int64))
    return amount


def _spread(amount, scales, sig, truncate=DEFAULT_TRUNCATE):
    """Spread each pixel's amount over the support of its selected filter (§5 of [1]).

    ``density(q) = Σ_p w_{s(p)}(p, q) amount(p)``: per scale, the adjoint of the
    border-renormalised filter (:func:`statmc.filters.gaussian_spread`) of the amounts of
    the pixels that selected it.  ``sig[0]`` must be 0 (the pixel filter).
    """
    h, w = amount.shape
    fy = np.ones((len(sig) - 1, h))
    fx = np.ones((len(sig) - 1, w))
    taps = [_taps(sigma, truncate, max(h, w)) for sigma in sig[1:]]   # the bank's kernels
    for s, wk in enumerate(taps):
        fy[s], fx[s] = _border_scale(h, wk), _border_scale(w, wk)
    density = np.empty((h, w))
    parts = np.empty((len(sig) - 1, h, w))
    per_scale = _k.spread_parts(amount, scales, fy, fx, density, parts)
    ones_h, ones_w = np.ones(h), np.ones(w)
    for s, wk in enumerate(taps):
        if per_scale[s + 1] > 0:   # density += unnormalised filter of the pre-scaled part
            _k.sep_filter_add(parts[s], wk, ones_h, ones_w, density)
    return density


def _spread_reference(amount, scales, sig, truncate=DEFAULT_TRUNCATE):
    """NumPy reference of :func:`_spread` (dense weight matrices)."""
    h, w = amount.shape
    density = np.where(scales == 0, amount, 0.0)
    for s, sigma in enumerate(sig):
        if s == 0:
            continue
        a = np.where(scales == s, amount, 0.0)
        density += _weight_matrix(h, sigma, truncate).T @ a @ _weight_matrix(w, sigma, truncate)
    return density


@serial_when_small()
def sampling_map(mean, mean_var, n, budget: int, *, gamma: float = DEFAULT_GAMMA,
                 batch: int | None = None, eps: float = RELMSE_EPS, rng=None,
                 rounds: int = 4, var_prior: float = 2.0, var_prior_sigma: float = 1.0,
                 debias: bool = True, extra_output: bool = False):
    """Integer sample counts for one adaptive GEM iteration (§5 of [1]).

    Selects scales with the adaptive settings (:data:`~statmc.filters.ADAPTIVE_SIGMAS`),
    estimates each pixel's MSE under its selected filter (:func:`estimate_mse`), its
    relative MSE ``mean_c MSE_c / (value_c² + ε)`` and the gain of ``batch`` more samples,
    ``relMSE · batch / (n + batch)``.  The ``budget // batch`` pixels of largest gain
    each receive ``batch`` samples (one more pixel gets the remainder), spread over the
    support of their selected filter in proportion to its weights; the expected counts are
    then rounded without bias to integers that sum to ``budget`` exactly.

    Parameters
    ----------
    mean, mean_var : (H, W, C) ndarrays
        Current pixel estimates and their variances of the mean.
    n : (H, W) ndarray
        Current samples per pixel (>= 2).
    budget : int
        Samples to hand out in this iteration.
    gamma : float
        Error-rate parameter of the scale selector.
    batch : int, optional
        Samples per selected pixel (the paper's per-pixel ``n``).  Default
        ``ceil(8 · budget / (H·W))``, which selects about an eighth of the pixels per call
        as in §6 (``m = N/n`` pixels with ``N = M(n − 4)/8``).  At most 2**53, as
        ``budget``.
    eps : float
        ε of the relative MSE (0.001 in §5).
    rng : numpy Generator or int, optional
        Randomness of the integer rounding (:func:`statmc.sampling.counts_from_density`).
    rounds : int
        Greedy rounds within the call (default 4; the paper: 1).  Each hands out
        ``budget/rounds``; between rounds a pixel that received ``a`` samples has its
        relative MSE scaled by ``n/(n + a)`` and ``n ← n + a`` (§5's model), so gains are
        re-evaluated without re-rendering.  The default ``batch`` is per round.  More
        rounds than ``budget`` act as ``budget`` rounds of one sample (those past it would
        hand out nothing).
    var_prior : float
        Pseudo-degrees of freedom ``k`` of a pooled prior on each pixel's sample variance
        (default 2; the paper: 0).  The sampler uses the posterior mean
        ``((n − 1) s² + k s̄²)/(n − 1 + k)``, ``s̄²`` the Gaussian (σ = ``var_prior_sigma``)
        neighbourhood average of ``s²``, so ``n`` equal samples (``s² = 0``, e.g. all
        zeros in a firefly region) no longer mean "noise-free, never sample again".
    var_prior_sigma : float
        σ of the pooling Gaussian (default 1).
    debias : bool
        Subtract the known noise ``Var(v_{k+1} − v_k)`` (:func:`difference_variance`)
        from every squared difference accumulated into the estimated MSE, clamping the
        accumulated bias² at 0 (default True; the paper: False).  ``E[(c − f)²] =
        bias-difference² + Var(c − f)``, so the raw sum overstates the MSE of filtered
        pixels by their noise.
    extra_output : bool
        Also return a dict with ``density`` (the real-valued map that is rounded to
        ``counts``), ``gain`` and ``rel_mse`` (§5's per-pixel terms, first round),
        ``scales`` (selected scale per pixel, an index into ``sigmas``), ``est_mse``
        (estimated MSE of the selected filter), ``amount`` (samples handed to each
        pixel before they are spread over its filter support), ``batch`` (the
        per-pixel batch used) and ``sigmas`` (the adaptive bank's scales).

    Returns
    -------
    counts : (H, W) int64 ndarray, ``counts.sum() == budget``
    info : dict, only with ``extra_output``

    Notes
    -----
    The paper's literal sampler is ``rounds=1, var_prior=0, debias=False``; the defaults
    depart from it in three ways measured on toy scenes (``docs/gem.md`` §5a).  None of
    them touches :func:`reconstruct`.  Choices where the paper is silent: the expected share of each selected pixel's batch
    is spread deterministically over its filter support (the paper draws the pixels at
    random by the weights; the expectation is the same) and only the final rounding is
    random; ``n`` in the gain is the pixel's own count, as in the paper; if no pixel can
    gain (noise-free input), the budget is spread uniformly.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> m = rng.uniform(0.2, 1.0, (24, 32, 3)).astype(np.float32)
    >>> counts = sampling_map(m, np.full_like(m, 0.01), np.full((24, 32), 4), 1000, rng=0)
    >>> int(counts.sum()), counts.dtype
    (1000, dtype('int64'))
    """
    from .sampling import _systematic_round
    if n is None:
        raise InputError("`n` (samples per pixel, (H, W)) is required by `sampling_map`.")
    m, v, vsum, nn = _check_inputs(mean, mean_var, n)
    budget = as_whole("budget", budget, hi=MAX_BUDGET)
    debias, extra_output = as_bool("debias", debias), as_bool("extra_output", extra_output)
    given = eps, var_prior, var_prior_sigma          # '0.1', True, [1, 2]: float() took
    eps, var_prior, var_prior_sigma = map(real_or_nan, given)   # or raised TypeError
    if not eps > 0 or not math.isfinite(eps):
        raise InputError(f"`eps` must be a finite number > 0; got {given[0]!r}.")
    h, w = m.shape[:2]
    # rounds past the budget hand out nothing (each of the first ``budget`` rounds gets one
    # sample either way): the same counts, but 1e18 rounds ran for years and 2**70 reached
    # the kernel as a number too large for it
    rounds = min(as_whole("rounds", rounds, lo=1), max(budget, 1))
    if not (var_prior >= 0 and math.isfinite(var_prior)):
        raise InputError(f"`var_prior` must be a finite number >= 0 (pseudo-samples); got "
                         f"{given[1]!r}.")
    if not (var_prior_sigma > 0 and math.isfinite(var_prior_sigma)):
        raise InputError(f"`var_prior_sigma` must be a finite number > 0; got {given[2]!r}.")
    if batch is None:
        batch = max(1, math.ceil(8 * math.ceil(budget / rounds) / (h * w)))
    batch = as_whole("batch", batch, lo=1, hi=MAX_BUDGET)   # 2**63: the kernel's SystemError
    sig = list(ADAPTIVE_SIGMAS)
    if var_prior > 0:
        v = _variance_prior(v, nn, var_prior, var_prior_sigma)   # (vsum unused below)
    sel = _core(m, v, vsum, nn, gamma, sig, False, True, DEFAULT_TRUNCATE, keep_bank=True,
                debias=debias)
    c = 1 if m.ndim == 2 else m.shape[2]
    rel = np.empty((h, w))
    gain = np.empty((h, w))
    _k.relative_gain(sel["image"].reshape(h, w * c), sel["est_mse"].reshape(h, w * c), c,
                     eps, nn, float(batch), rel, gain)
    amount = _allocate_rounds_fast(rel, nn, budget, batch, rounds)
    scales = sel["scales"]
    density = _spread(amount, scales, sig)
    # density is finite and >= 0 by construction (non-negative weights and amounts):
    # straight to the rounding of counts_from_density, without its input checks
    counts = _systematic_round(density, budget, 0, as_rng(rng))
    if extra_output:
        return counts, {"density": density, "gain": gain, "rel_mse": rel, "scales": scales,
                        "est_mse": sel["est_mse"], "amount": amount, "batch": batch,
                        "sigmas": tuple(sig)}
    return counts
