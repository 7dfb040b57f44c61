"""Analytic future renders and the bias-variance theorem for kernel denoisers.

What happens to a render when ``s`` more samples are added to a pixel that already holds
``s_bar`` samples with mean ``x_t``?  With the true per-pixel mean ``x_g`` and the true
**sample variance** ``var_g`` (variance of *one* sample) the answer is analytic
(Salehi et al. 2022 [1]_, §3.2–3.3):

* :func:`future_moments` — mean (Eq. 6) and variance of the future render, conditional on
  ``x_t`` (``s·var_g/(s_bar+s)²``, Eq. 19) or averaged over ``x_t`` too (Eq. 7);
* :func:`sample_future` — one synthetic future render (Eq. 8): the mean of the ``s`` new
  samples is drawn in one go from a moment-matched gamma (Eq. 9), log-normal, truncated
  or clipped normal, with one random stream shared by the channels;
* :func:`kernel_bias_variance` / :func:`expected_kernel_loss` — the exact expected MSE or
  relMSE (MRSE) after adding ``s`` samples, for any per-pixel kernel denoiser whose
  weights do not depend on the new samples (Lemma A.1, Theorem 1), with its gradient;
* :func:`optimal_sample_map` / :func:`optimal_sample_counts` — a classical (non-neural)
  sampler that minimises that expected loss under a budget (not in the paper);
* :func:`expected_error_sampler` / :class:`PilotKernelSampler` — that sampler with
  estimated statistics, for a fixed Gaussian or GEM's selection on a pilot render
  (:func:`gem_kernels`, :func:`scale_kernels`), held fixed so Lemma A.1 applies.

Kernel convention (also :func:`apply_kernels`): kernels are ``(H, W, k, k)`` with odd
``k`` and ``r = k // 2``; the denoised pixel is

``D[y, x, c] = Σ_{dy,dx} K[y, x, dy, dx] · img[y + dy − r, x + dx − r, c]``,

the same weights for every channel.  Taps outside the image contribute nothing (zero
weight); weights are used exactly as given, never renormalised.

References
----------
.. [1] F. Salehi, M. Manzi, G. Roethlin, R. Weber, C. Schroers, M. Papas. "Deep Adaptive
   Sampling and Reconstruction using Analytic Distributions". ACM Trans. Graph. 41(6),
   259, 2022. https://doi.org/10.1145/3550454.3555515
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy import special

from . import _analytic_kernels as _ak
from .errors import (MAX_BUDGET, InputError, _scalar, as_bool, as_broadcast_arrays,
                     as_float_array, as_number, as_rng, as_whole, check_finite, check_nonempty,
                     check_nonnegative, check_overflow)
from .sampling import counts_from_density
from .stats import check_stats

__all__ = [
    "DISTRIBUTIONS", "RELMSE_EPS", "future_moments", "gamma_parameters", "sample_future",
    "apply_kernels",
    "kernel_bias_variance", "expected_kernel_loss", "optimal_sample_map",
    "optimal_sample_counts", "pooled_sample_variance", "expected_error_sampler",
    "POOL_SIGMA", "WEIGHT_SIGMA", "scale_kernels", "gem_kernels", "PilotKernelSampler",
]

#: Values accepted by ``sample_future(dist=...)``.
DISTRIBUTIONS = ("gamma", "lognormal", "truncnorm", "clipped_normal")

#: ε in relMSE ``(x − r)²/(r² + ε)``: 0.01 as in DESIGN.md (Rousselle 2011 §7).  Salehi
#: Eq. 20 divides by ``X_g²`` alone, which is ``eps=0``.
RELMSE_EPS = 0.01

_LOSSES = ("mse", "mrse", "relmse")


# =========================================================================== validation
def _image(name, a):
    arr = as_float_array(name, a, ndim=(2, 3), dtype=np.float64)
    check_nonempty(name, arr)
    check_finite(name, arr)
    return arr


def _like(name, a, ref_name, ref):
    arr = as_float_array(name, a, dtype=np.float64)
    if arr.shape != ref.shape:
        raise InputError(f"`{name}` must have the shape of `{ref_name}` {ref.shape}; got {arr.shape}.")
    check_finite(name, arr)
    return arr


def _count_map(name, a, hw):
    arr = as_float_array(name, a, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(hw, float(arr))
    if arr.shape != tuple(hw):
        raise InputError(
            f"`{name}` must be an (H, W) sample-count map with (H, W) = {tuple(hw)} (or a "
            f"scalar); got shape {arr.shape}.")
    check_finite(name, arr)
    check_nonnegative(name, arr)
    return arr


def _prepare(x_t, s_bar, s, x_g, var_g, mean_var_t=None, *, names=("x_t", "s_bar", "s", "x_g", "var_g")):
    """Validate and return float64 ``(H, W, C)`` images, ``(H, W)`` maps, and the input ndim."""
    nx, nsb, ns, nxg, nv = names
    xt = _image(nx, x_t)
    ndim = xt.ndim
    xg = _like(nxg, x_g, nx, xt)
    vg = _like(nv, var_g, nx, xt)
    check_nonnegative(nv, vg)
    hw = xt.shape[:2]
    sb = _count_map(nsb, s_bar, hw)
    sm = _count_map(ns, s, hw)
    mvt = None
    if mean_var_t is not None:
        mvt = _like("mean_var_t", mean_var_t, nx, xt)
        check_nonnegative("mean_var_t", mvt)
    if ndim == 2:
        xt, xg, vg = xt[..., None], xg[..., None], vg[..., None]
        mvt = None if mvt is None else mvt[..., None]
    _check_tiny_counts(sb, sm, nsb, ns, 2)
    return xt, sb, sm, xg, vg, mvt, ndim


def _check_tiny_counts(sb, sm, nsb, ns, power):
    """``InputError`` where ``0 < s_bar + s`` but ``(s_bar + s)**power`` is 0 in float64
    (below about 2.2e-162 for the square that divides Eq. 19's variance, 1.7e-108 for the
    cube in its derivative): that gave NaN/Inf or a bare ZeroDivisionError from the
    compiled kernels."""
    n = sb + sm
    if not n.size or float(n.min()) ** power > 0:    # the usual case: two passes
        return
    tiny = (n > 0) & (n ** power == 0)
    if tiny.any():
        lim = float(np.finfo(np.float64).smallest_subnormal) ** (1.0 / power)
        what = {2: "its square divides the variance (Eq. 19)",
                3: "its cube divides the gradient of the variance"}[power]
        raise InputError(
            f"`{nsb}` + `{ns}` (samples per pixel once added) must be 0 or at least "
            f"{lim:.2g} ({what} and is 0 in float64 below that); got {int(tiny.sum())} "
            f"pixel(s) with 0 < {nsb} + {ns} < {lim:.2g}, e.g. {float(n[tiny][0]):.3g}.")


def _numeric_kernels(kernels) -> np.ndarray:
    """``kernels`` as an array, refused unless numeric (a kernel denoiser given in place of
    its ``kernels(shape)`` is named)."""
    K = np.asarray(kernels)
    if np.iscomplexobj(K):          # was taken as its real part (a ComplexWarning only)
        raise InputError(f"`kernels` must be a real numeric array; got dtype {K.dtype}.")
    if K.dtype == object or not np.issubdtype(K.dtype, np.number):
        hint = (" (for a kernel denoiser pass its `kernels(shape)`)"
                if callable(getattr(kernels, "kernels", None)) else "")
        raise InputError(f"`kernels` must be a numeric (H, W, k, k) array; got "
                         f"{type(kernels).__name__ if K.ndim == 0 else K.dtype}{hint}.")
    return K


def _check_kernels(kernels, hw):
    K = _numeric_kernels(kernels)
    if K.dtype not in (np.float32, np.float64):
        K = K.astype(np.float64)
    if K.ndim != 4 or K.shape[2] != K.shape[3]:
        raise InputError(f"`kernels` must have shape (H, W, k, k); got {K.shape}.")
    if K.shape[:2] != tuple(hw):
        raise InputError(
            f"`kernels` must have one k x k kernel per pixel, shape {tuple(hw)} + (k, k); "
            f"got {K.shape}.")
    if K.shape[2] % 2 == 0:
        raise InputError(f"`kernels` must have an odd size k (centred taps); got k = {K.shape[2]}.")
    # One cheap pass instead of an (H, W, k, k) boolean temporary: a NaN/Inf makes the sum non-finite.
    if not np.isfinite(np.sum(K, dtype=np.float64)):
        check_finite("kernels", K)
        raise InputError("`kernels` must hold finite values whose sum is finite; got an overflow.")
    return K


def _check_loss(loss, eps):
    if not isinstance(loss, str) or loss.lower() not in _LOSSES:
        raise InputError(f"`loss` must be one of 'mse', 'mrse' (alias 'relmse'); got {loss!r}.")
    eps = as_number("eps", eps, lo=0.0)
    return "mse" if loss.lower() == "mse" else "mrse", eps


def _check_rel_denominator(loss, eps, xg):
    if loss == "mrse" and eps == 0 and np.any(xg == 0):
        raise InputError(
            f"relMSE with `eps`=0 divides by x_g² = 0 in {int((xg == 0).sum())} entries; "
            "use eps > 0 (e.g. the default 0.01).")


def _rng(rng):
    return as_rng(rng)


# =========================================================================== moments
_moments = _ak.moments_numpy


def future_moments(x_t, s_bar, s, x_g, var_g, *, mean_var_t=None):
    """Mean and variance of a pixel's future render after adding ``s`` samples.

    Parameters
    ----------
    x_t : (H, W, C) or (H, W) ndarray
        Current render (mean of ``s_bar`` samples per pixel).
    s_bar : (H, W) ndarray or scalar
        Samples accumulated so far (real values allowed).
    s : (H, W) ndarray or scalar
        Samples to add.
    x_g : like ``x_t``
        True pixel mean.
    var_g : like ``x_t``
        True **sample variance** (variance of one sample), ``>= 0``.
    mean_var_t : like ``x_t``, optional
        Variance of the current mean ``x_t`` (e.g. ``PixelStats.mean_var``).  When given,
        ``x_t`` is treated as random and both moments are averaged over it.

    Returns
    -------
    mean, var : ndarray like ``x_t`` (float64)

    Notes
    -----
    With ``n = s_bar + s`` and conditional on ``x_t`` (the setting of Fig. 5 of [1]_):

    * ``mean = (s_bar x_t + s x_g) / n`` — Eq. 6 of [1]_;
    * ``var = s var_g / n²`` — Eq. 19 of [1]_ (only the ``s`` new samples are random).

    With ``mean_var_t`` (``x_t`` unbiased with variance ``mean_var_t``):

    * ``var = (s_bar² mean_var_t + s var_g) / n²`` — Eq. 7 of [1]_; by the law of total
      variance this is the *unconditional* variance, so
    * ``mean = x_g`` — Eq. 6 with ``x_t`` replaced by its expectation ``x_g``.  Pairing
      Eq. 7 with the conditional Eq. 6 would mix two different distributions.

    Where ``n = 0`` the pixel receives no samples at all: ``mean = x_t``, ``var = 0``.

    Examples
    --------
    The pixel of Fig. 5 of [1]_ (``X_g = 0.38``, ``V = 0.9``, ``X_t = 0.78`` at 16 spp):

    >>> m, v = future_moments([[[0.78]]], 16, 16, [[[0.38]]], [[[0.9]]])
    >>> round(float(m[0, 0, 0]), 4), round(float(v[0, 0, 0]), 7)   # 16*0.9/32**2
    (0.58, 0.0140625)
    """
    xt, sb, sm, xg, vg, mvt, ndim = _prepare(x_t, s_bar, s, x_g, var_g, mean_var_t)
    with np.errstate(over="ignore", invalid="ignore"):     # checked just below
        mean, var = _moments(xt, sb, sm, xg, vg, mvt)
    _check_moments_overflow((mean, var), xt, sb, sm, xg, vg, mvt)
    if ndim == 2:
        mean, var = mean[..., 0], var[..., 0]
    return mean, var


#: The range that :func:`_check_moments_overflow` names (the products of Eq. 6, 7, 19).
_MOMENTS_RANGE = ("products s_bar·x_t, s·x_g, s·var_g and s_bar²·mean_var_t (and their "
                  "sums) below 1.8e308, e.g. |x_t|, |x_g| and var_g below 1e300 at up to "
                  "1e7 samples")

_KBV_RANGE = ("the sums Σ K·E[Y] − x_g and Σ K²·Var[Y] below 1.8e308 (Var[Y] as in "
              "future_moments)")
_LOSS_RANGE = ("squared errors (Σ K·E[Y] − x_g)² + Σ K²·Var[Y] below 1.8e308, i.e. "
               "|x_t|, |x_g| (times the kernel weights) below about 1e154 and var_g below "
               "about 1e308; for loss='mrse' also x_g² + eps below 1.8e308 (|x_g| below "
               "1.3e154)")


def _check_moments_overflow(results, xt, sb, sm, xg, vg, mvt, what="the future moments",
                            expected=_MOMENTS_RANGE, K=None):
    """:func:`check_overflow` of each array in ``results`` (None skipped), naming the
    moment inputs (and the kernels ``K`` if given)."""
    given = {} if K is None else {"kernels": K}
    given.update({"x_t": xt, "s_bar": sb, "s": sm, "x_g": xg, "var_g": vg})
    if mvt is not None:
        given["mean_var_t"] = mvt
    for r in results:
        if r is not None:
            check_overflow(r, what, given, expected)


# =========================================================================== sampling
def gamma_parameters(x_g, var_g, s):
    """Shape and rate of the gamma law of the mean of ``s`` samples (Eq. 9 of [1]_).

    ``α = x_g² s / var_g``, ``β = x_g s / var_g``, so the mean is ``α/β = x_g`` and the
    variance ``α/β² = var_g / s``.  Arrays broadcast, and an ``(H, W)`` count map ``s``
    goes with ``(H, W, C)`` images as in :func:`future_moments`; undefined (NaN) where
    ``x_g·s·var_g = 0`` — those pixels are point masses at ``x_g``.  ``x_g`` must be
    ``>= 0``: a gamma law has a positive mean (a negative ``x_g`` would give a negative
    rate ``β``).  Where ``x_g²`` or a product leaves float64's range but ``α`` and ``β`` do
    not, they are computed exactly from mantissas and exponents; an ``α`` or ``β`` above
    1.8e308 is an :class:`~statmc.errors.InputError`, one below 5e-324 is 0 (rounded as
    float64 arithmetic rounds it).
    """
    if np.ndim(s) == 2 and np.ndim(x_g) == 3 and np.shape(s) == np.shape(x_g)[:2]:
        s = np.asarray(s)[..., None]                    # per-pixel counts, all channels
    xg, v, s = as_broadcast_arrays({"x_g": x_g, "var_g": var_g, "s": s},
                                   nonnegative=("x_g", "var_g", "s"))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        ok = (xg != 0) & (v > 0) & (s > 0)
        alpha = np.where(ok, xg * xg * s / np.where(ok, v, 1.0), np.nan)
        beta = np.where(ok, xg * s / np.where(ok, v, 1.0), np.nan)
        # Where ok, both are > 0 and finite unless an intermediate left float64's range
        # (x_g² beyond 1.8e308, or below the smallest float): redo those entries exactly.
        # fmin/fmax skip the NaN of the undefined entries; one pass each, no temporary.
        if not all(np.fmin.reduce(a, axis=None) > 0 and np.fmax.reduce(a, axis=None) < np.inf
                   for a in (alpha, beta) if a.size):
            alpha, beta = _gamma_rescaled(xg, v, s, ok, alpha, beta)
    return alpha, beta


def _gamma_rescaled(xg, v, s, ok, alpha, beta):
    """:func:`gamma_parameters` where the plain products over- or underflowed: the same
    products of the mantissas (``np.frexp``), scaled back by the summed exponents with
    ``np.ldexp`` — scaling by powers of two is exact, so an entry comes out as the plain
    formula would give it with an unlimited exponent range (rounded to a subnormal or 0
    below 5e-324).  A result above 1.8e308 is an :class:`InputError`."""
    alpha, beta = np.array(alpha, dtype=np.float64), np.array(beta, dtype=np.float64)
    bad = ok & ~((alpha > 0) & (alpha < np.inf) & (beta > 0) & (beta < np.inf))
    xb, sb, vb = (np.broadcast_to(a, alpha.shape)[bad] for a in (xg, s, v))
    (mx, ex), (ms, es), (mv, ev) = np.frexp(xb), np.frexp(sb), np.frexp(vb)
    a = np.ldexp(mx * mx * ms / mv, 2 * ex + es - ev)
    b = np.ldexp(mx * ms / mv, ex + es - ev)
    # Below the smallest float, ldexp rounds to a subnormal or 0, as the plain formula
    # did (x_g = 1e-200, var_g = s = 1 gave α = 0 before and must not be refused);
    # only a value beyond 1.8e308 has no float64 to round to.
    out = (a == np.inf) | (b == np.inf)
    if out.any():
        i = int(np.argmax(out))
        x0, s0, v0 = float(xb[i]), float(sb[i]), float(vb[i])
        lb = np.log10(x0) + np.log10(s0) - np.log10(v0)
        raise InputError(
            f"`x_g`, `var_g` and `s` must give a gamma shape α = x_g² s / var_g and rate "
            f"β = x_g s / var_g within float64's range (below 1.8e308); got "
            f"{int(out.sum())} entries outside it, e.g. x_g = {x0:.3g}, var_g = {v0:.3g}, "
            f"s = {s0:.3g} (α ≈ 1e{lb + np.log10(x0):.0f}, β ≈ 1e{lb:.0f}).  Scaling x_g by "
            "c and var_g by c² divides β by c and leaves α (the squared signal-to-noise "
            "ratio) as it is.")
    alpha[bad], beta[bad] = a, b
    return alpha, beta


_TINY = float(np.finfo(np.float64).tiny)       # smallest normal float64, 2.2e-308


def _draw_mean(dist, mu, var_mean, u, z, bounds):
    """Mean of the new samples with mean ``mu`` and variance ``var_mean`` (non-degenerate)."""
    if dist == "gamma":
        alpha = mu * mu / var_mean                      # Eq. 9 with var_mean = var_g / s
        rate = mu / var_mean
        q = special.gammaincinv(alpha, u)
        # A shape below float64's smallest normal (x_g² underflowed: x_g = 1e-200) gave
        # NaN; the quantile u**(1/α)-like is 0 there for every u < 1, as scipy gives it
        # from α = 2.2e-308 up.
        small = alpha < _TINY
        if small.any():
            q[small] = 0.0
        return q / rate
    if dist == "lognormal":
        mm = mu * mu
        with np.errstate(divide="ignore"):              # mm = 0: redone just below
            r = var_mean / mm
        low = mm < _TINY                                # x_g² underflowed: divide twice
        if low.any():
            r[low] = var_mean[low] / mu[low] / mu[low]
        s2 = np.log1p(r)
        return np.exp(np.log(mu) - 0.5 * s2 + np.sqrt(s2) * z)
    sd = np.sqrt(var_mean)
    if dist == "truncnorm":                              # N(mu, sd²) restricted to [0, ∞)
        lo = special.ndtr(-mu / sd)
        q = lo + u * (1.0 - lo)
        return np.maximum(mu + sd * special.ndtri(np.minimum(q, np.nextafter(1.0, 0.0))), 0.0)
    return np.clip(mu + sd * z, bounds[0], bounds[1])   # clipped_normal


def sample_future(x_t, s_bar, s, x_g, var_g, *, dist="gamma", rng=None, shared_stream=True,
                  bounds=(-1.0, 1.0)):
    """One synthetic future render after adding ``s`` samples (Eq. 8 of [1]_).

    Parameters
    ----------
    x_t, s_bar, s, x_g, var_g
        As in :func:`future_moments` (``var_g`` is the sample variance of one sample).
    dist : {"gamma", "lognormal", "truncnorm", "clipped_normal"}
        Law of the mean ``Ȳ_s`` of the ``s`` new samples:

        * ``"gamma"`` — moment matched, shape/rate of Eq. 9 of [1]_: mean ``x_g``,
          variance ``var_g/s`` exactly (the mean of ``s`` i.i.d. gamma samples is gamma);
        * ``"lognormal"`` — moment matched, ``σ² = log(1 + var_g/(s x_g²))``,
          ``μ = log x_g − σ²/2``;
        * ``"truncnorm"`` — ``N(x_g, var_g/s)`` truncated to ``[0, ∞)``.  Not moment
          matched: its mean exceeds ``x_g`` at low ``s`` (the bias §5.4 of [1]_ reports);
        * ``"clipped_normal"`` — ``N(x_g, var_g/s)`` clipped to ``bounds``: for normals
          (§4.3 of [1]_), whose values may be negative.

        The first three need ``x_g >= 0``.
    rng : numpy Generator or int, optional
    shared_stream : bool
        One uniform (or standard normal) per pixel drives every channel through the
        quantile function, so channels are perfectly rank-correlated — the paper's "same
        seed for each channel" (§4.3 of [1]_).  ``False`` draws channels independently.
    bounds : (float, float)
        Clip range for ``"clipped_normal"``.

    Returns
    -------
    y : ndarray like ``x_t``
        ``(s_bar x_t + s Ȳ_s)/(s_bar + s)`` (Eq. 8 of [1]_), float32 if ``x_t`` is float32.

    Notes
    -----
    Degenerate pixels are exact point masses, never NaN: ``Ȳ_s = x_g`` where ``s = 0`` or
    ``var_g = 0`` (``clip(x_g, *bounds)`` for ``"clipped_normal"``, the limit of its law
    as ``var_g → 0``), and (for the three non-negative laws) where ``x_g = 0`` — a
    non-negative variable with mean 0 is 0.  Where ``s_bar + s = 0`` the result is
    ``x_t``.  Only the ``s`` new samples are random: the result has the conditional
    moments of :func:`future_moments` (for the moment-matched laws).

    The shared-stream gamma uses the inverse regularised incomplete gamma function
    (about 0.7 µs per value); ``shared_stream=False`` uses NumPy's faster sampler.

    Examples
    --------
    >>> y = sample_future(np.full((2, 2, 3), 0.5), 16, 16, np.full((2, 2, 3), 0.4),
    ...                   np.full((2, 2, 3), 0.9), rng=1)
    >>> y.shape
    (2, 2, 3)
    """
    if dist not in DISTRIBUTIONS:
        raise InputError(f"`dist` must be one of {DISTRIBUTIONS}; got {dist!r}.")
    out_dtype = np.float32 if np.asarray(x_t).dtype == np.float32 else np.float64
    xt, sb, sm, xg, vg, _, ndim = _prepare(x_t, s_bar, s, x_g, var_g)
    positive = dist != "clipped_normal"
    if positive and np.any(xg < 0):
        raise InputError(
            f"`x_g` must be >= 0 for dist={dist!r} (a law on [0, ∞)); got "
            f"{int((xg < 0).sum())} negative values (min {xg.min():.4g}). Use "
            "dist='clipped_normal' for signed features such as normals.")
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError):             # None, a scalar, three numbers, strings
        raise InputError(f"`bounds` must be (low, high), two numbers; got {bounds!r}.") from None
    if not lo <= hi:
        raise InputError(f"`bounds` must be (low, high) with low <= high; got {bounds!r}.")
    gen = _rng(rng)
    shared_stream = as_bool("shared_stream", shared_stream)
    shape = xt.shape[:2] + ((1,) if shared_stream else (xt.shape[2],))
    s3 = np.broadcast_to(sm[..., None], xt.shape)
    degenerate = (s3 == 0) | (vg == 0)
    if positive:
        degenerate |= xg == 0
    ok = ~degenerate
    u = z = None
    if dist in ("gamma", "truncnorm"):
        u = np.broadcast_to(gen.random(shape), xt.shape)[ok]
    else:
        z = np.broadcast_to(gen.standard_normal(shape), xt.shape)[ok]
    # Point masses: N(x_g, 0) clipped to `bounds` is clip(x_g), the limit var_g -> 0.
    ybar = np.clip(xg, lo, hi) if dist == "clipped_normal" else xg.copy()
    with np.errstate(over="ignore", invalid="ignore"):    # the result is checked below
        if ok.any():
            mu = xg[ok]
            var_mean = vg[ok] / s3[ok]
            if dist == "gamma" and not shared_stream:
                # NumPy's sampler refuses a NaN or Inf shape: say which input caused it
                shape_ = mu * mu / var_mean
                # the sum also overflows for finite shapes (1000 entries of 1e306): count
                n_inf = 0 if np.isfinite(np.sum(shape_)) else int(shape_.size - np.count_nonzero(
                    np.isfinite(shape_)))
                if n_inf:
                    raise InputError(
                        f"`x_g`, `var_g` and `s` must give a gamma shape s·x_g²/var_g below "
                        f"1.8e308 for dist='gamma'; got {n_inf} "
                        f"entries beyond it (`x_g` up to {float(np.max(mu)):.3g}).  The shape "
                        "does not change when x_g is scaled by c and var_g by c²; such a law "
                        "is a point mass at x_g to float64 precision (var_g = 0 gives it).")
                ybar[ok] = gen.gamma(shape_, var_mean / mu)
            else:
                ybar[ok] = _draw_mean(dist, mu, var_mean, u, z, (lo, hi))
        n = (sb + sm)[..., None]
        has = n > 0
        y = np.where(has, (sb[..., None] * xt + sm[..., None] * ybar) / np.where(has, n, 1.0), xt)
        if ndim == 2:
            y = y[..., 0]
        y = y.astype(out_dtype, copy=False)
    _check_moments_overflow(
        (y,), xt, sb, sm, xg, vg, None, "the future render",
        _MOMENTS_RANGE + (", and the gamma shape x_g² s/var_g below 1.8e308"
                          if dist == "gamma" else "")
        + (" (a float32 `x_t` gives a float32 render: below 3.4e38)"
           if out_dtype == np.float32 else ""))
    return y


# =========================================================================== kernels
def _evaluate(K, xt, sb, sm, xg, vg, mvt, loss, eps, want_grad, engine="numba"):
    """``(loss, grad or None, bias, var)`` on validated float64 inputs."""
    fn = _ak.evaluate_numba if engine == "numba" else _ak.evaluate_numpy
    return fn(K, xt, sb, sm, xg, vg, mvt, loss == "mrse", float(eps), want_grad)


def apply_kernels(kernels, image):
    """Apply per-pixel kernels to an image or a stack of images.

    Parameters
    ----------
    kernels : (H, W, k, k) ndarray
        One kernel per output pixel, odd ``k``.  Any float dtype and strides, so a fixed
        kernel may be passed as ``np.broadcast_to(g, (H, W, k, k))``.
    image : (H, W), (H, W, C) or (N, H, W, C) ndarray

    Returns
    -------
    out : ndarray like ``image``
        ``out[y, x, c] = Σ K[y, x, dy, dx] · image[y + dy − r, x + dx − r, c]``, taps
        outside the image dropped (zero weight, no renormalisation); the kernel
        denoiser ``D(X)_p = Σ_q K_pq X_q`` of §A.1 of [1]_.
    """
    img = as_float_array("image", image, ndim=(2, 3, 4))
    check_nonempty("image", img)
    check_finite("image", img)
    out_dtype = img.dtype if img.dtype in (np.float32, np.float64) else np.float64
    stack = {2: img[None, ..., None], 3: img[None], 4: img}[img.ndim]
    K = _check_kernels(kernels, stack.shape[1:3])
    out = np.empty(stack.shape)
    _ak.apply_numba(K, np.ascontiguousarray(stack, dtype=np.float64), out)
    out = {2: out[0, ..., 0], 3: out[0], 4: out}[img.ndim]
    return out.astype(out_dtype, copy=False)


def scale_kernels(scales, sigmas, *, truncate=None, dtype=np.float32):
    """Per-pixel kernels of a per-pixel choice among border-renormalised Gaussians.

    Parameters
    ----------
    scales : (H, W) int ndarray
        Index into ``sigmas`` of the filter each pixel uses (the ``scales`` entry of
        ``statmc.gem.reconstruct(..., extra_output=True)``'s dict).
    sigmas : sequence of float
        Standard deviations (pixels) of the bank; 0 is the pixel filter (the ``sigmas``
        entry of the same dict, e.g. :data:`statmc.filters.ADAPTIVE_SIGMAS`).
    truncate : float, optional
        Cut-off in standard deviations (default :data:`statmc.filters.DEFAULT_TRUNCATE`,
        the one GEM uses).
    dtype : float32 or float64
        Of the result; float32 halves the memory.

    Returns
    -------
    kernels : (H, W, k, k) ndarray
        ``K[y, x] = g_s ⊗ g_s / (N_y(y) N_x(x))`` with ``s = scales[y, x]``, the
        separable taps of :func:`statmc.filters.gaussian_kernel_1d` and the border
        renormalisation of :func:`statmc.filters.gaussian_filter` (taps outside the image
        are 0), zero-padded to the largest *selected* scale's size ``k``.  So
        ``apply_kernels(K, x)`` is the bank's filtered value at each pixel's scale —
        GEM's reconstruction (Rousselle et al. 2011, §4 and §6) for the selection given.
        Memory ``H·W·k²`` entries: ``k = 49`` for σ = 8 (the adaptive bank), 83 for
        σ = 13.6 (the default final bank, ``bias="pooled"``), 97 for σ = 16 (§6's final
        bank, ``bias="paper"``).  A kernel of more than 4096 taps a side is cut to the
        ``2·(max(H, W) − 1) + 1`` taps that can reach the image (exact: the taps cut fall
        outside it for every pixel), so ``k <= 2·max(H, W) − 1`` for ``σ`` above
        ``4096/truncate`` whatever σ.

    Notes
    -----
    Held fixed, the selection makes GEM a linear kernel denoiser to which Lemma A.1 of
    [1]_ applies exactly; re-selected from the noisy data it reacts to the new samples
    and does not.

    Examples
    --------
    >>> k = scale_kernels(np.array([[0, 1], [1, 0]]), (0.0, 1.0))
    >>> k.shape, bool(np.allclose(k.sum(axis=(2, 3)), 1.0))
    ((2, 2, 7, 7), True)
    """
    from .filters import DEFAULT_TRUNCATE, _check_truncate, _taps, border_scale
    sc = np.asarray(scales)
    if sc.ndim != 2 or not np.issubdtype(sc.dtype, np.integer):
        raise InputError(f"`scales` must be an (H, W) integer map of scale indices; got "
                         f"shape {sc.shape}, dtype {sc.dtype}.")
    try:
        sig = [float(v) for v in np.asarray(sigmas, dtype=np.float64).ravel()]
    except (TypeError, ValueError) as exc:
        raise InputError(f"`sigmas` must be a sequence of standard deviations >= 0; "
                         f"got {sigmas!r}.") from exc
    if not sig or any(not np.isfinite(v) or v < 0 for v in sig):
        raise InputError(f"`sigmas` must be a non-empty sequence of finite numbers >= 0; "
                         f"got {sigmas!r}.")
    if sc.size and (sc.min() < 0 or sc.max() >= len(sig)):
        raise InputError(f"`scales` must lie in [0, {len(sig) - 1}] (indices into `sigmas`); "
                         f"got [{sc.min()}, {sc.max()}].")
    if np.dtype(dtype) not in (np.float32, np.float64):
        raise InputError(f"`dtype` must be float32 or float64; got {dtype!r}.")
    t = _check_truncate(DEFAULT_TRUNCATE if truncate is None else truncate)
    h, w = sc.shape
    used = np.unique(sc)
    # the bank's taps on this image (statmc.filters._taps): a kernel of more than 4096
    # taps a side is cut to the 2·(max(H, W) − 1) + 1 that can reach it; σ = 1e6 asked
    # for an (H, W, 6e6, 6e6) array before (MemoryError)
    taps = {int(i): _taps(sig[int(i)], t, max(h, w)) for i in used}
    k = max((g.size for g in taps.values()), default=1)
    r = k // 2
    out = np.zeros((h, w, k, k), dtype)
    for i, g in taps.items():
        ys, xs = np.nonzero(sc == i)
        rs = g.size // 2
        off = np.arange(-rs, rs + 1)
        ky = g[None, :] * ((ys[:, None] + off >= 0) & (ys[:, None] + off < h))
        kx = g[None, :] * ((xs[:, None] + off >= 0) & (xs[:, None] + off < w))
        ky *= border_scale(h, g)[ys][:, None]
        kx *= border_scale(w, g)[xs][:, None]
        out[ys, xs, r - rs:r + rs + 1, r - rs:r + rs + 1] = ky[:, :, None] * kx[:, None, :]
    return out


def gem_kernels(mean, mean_var, *, n=None, gamma=None, final=False, dtype=np.float32):
    """Kernels of GEM's per-pixel scale selection on ``mean`` (Rousselle et al. 2011).

    Runs ``statmc.gem.reconstruct(mean, mean_var, gamma=gamma, final=final, n=n,
    extra_output=True)`` and turns its ``scales`` and ``sigmas`` into per-pixel kernels
    with :func:`scale_kernels`.  ``apply_kernels(kernels, mean)`` equals GEM's image.

    Parameters
    ----------
    mean, mean_var : (H, W, C) ndarray
        Pixel estimates and their **variance of the mean** (e.g. of a pilot render).
    n : (H, W) ndarray, optional
        Samples per pixel (>= 2), GEM's low-count correction.
    gamma : float, optional
        GEM's error-rate parameter (default ``statmc.gem.DEFAULT_GAMMA``).
    final : bool
        GEM's final-reconstruction bank (the default pooled selector's σ up to 13.6:
        ``k = 83``, ``H·W·83²`` entries; §6's σ up to 16 would give ``k = 97``) or, by
        default, the adaptive bank (σ = 0, 1, 2, 4, 8: ``k <= 49``).
    dtype : float32 or float64

    Returns
    -------
    kernels : (H, W, k, k) ndarray
        Fixed from then on: see :class:`PilotKernelSampler` for the use that keeps
        Lemma A.1 of [1]_ exact.
    """
    from . import gem as _gem
    g = _gem.DEFAULT_GAMMA if gamma is None else gamma
    final = as_bool("final", final)
    _, info = _gem.reconstruct(mean, mean_var, gamma=g, final=final, n=n, extra_output=True)
    return scale_kernels(info["scales"], info["sigmas"], dtype=dtype)


def kernel_bias_variance(kernels, x_t, s_bar, s, x_g, var_g, *, mean_var_t=None):
    """Per-pixel bias and variance of a kernel denoiser's output (Lemma A.1 of [1]_).

    Parameters
    ----------
    kernels : (H, W, k, k) ndarray
        Denoising kernels, fixed with respect to the new samples (see
        :func:`apply_kernels` for the convention).
    x_t, s_bar, s, x_g, var_g, mean_var_t
        As in :func:`future_moments`.

    Returns
    -------
    bias, var : ndarray like ``x_t`` (float64)
        ``bias_p = Σ_q K_pq E[Y_q] − x_g,p`` and ``var_p = Σ_q K_pq² Var[Y_q]`` with the
        moments of :func:`future_moments`, i.e. the two terms of Eq. 15 of [1]_ with the
        variance factor ``s/(s_bar + s)²`` of Eq. 19 (Eq. 15 prints ``s/(s_bar + s)``, an
        erratum).  ``E[(D(Y)_p − x_g,p)²] = bias_p² + var_p`` because pixels are
        independent.
    """
    xt, sb, sm, xg, vg, mvt, ndim = _prepare(x_t, s_bar, s, x_g, var_g, mean_var_t)
    K = _check_kernels(kernels, xt.shape[:2])
    _, _, bias, v = _evaluate(K, xt, sb, sm, xg, vg, mvt, "mse", 0.0, False)
    bias, v = np.ascontiguousarray(bias), np.ascontiguousarray(v)
    _check_moments_overflow((bias, v), xt, sb, sm, xg, vg, mvt, "the bias and variance",
                            _KBV_RANGE, K)
    if ndim == 2:
        bias, v = bias[..., 0], v[..., 0]
    return bias, v


def expected_kernel_loss(kernels, x_t, s_bar, s, x_g, var_g, *, loss="mse", eps=RELMSE_EPS,
                         mean_var_t=None, return_grad=False):
    """Expected MSE or relMSE of a kernel denoiser after adding ``s`` samples.

    Parameters
    ----------
    kernels : (H, W, k, k) ndarray
        Per-pixel kernels (convention of :func:`apply_kernels`) whose weights do **not**
        depend on the new samples (they may depend on ``x_t``, ``s_bar``, ``s``, features).
    x_t, s_bar, s, x_g, var_g, mean_var_t
        As in :func:`future_moments`.  Without ``mean_var_t`` the expectation is over the
        new samples only (conditional on ``x_t``, as in [1]_); with it, over ``x_t`` too.
    loss : {"mse", "mrse"}
        ``"mrse"`` (alias ``"relmse"``) weights each entry by ``1/(x_g² + eps)``.
    eps : float
        relMSE ε, default 0.01 (DESIGN.md); ``eps=0`` is Eq. 20 of [1]_ exactly.
    return_grad : bool
        Also return the gradient with respect to ``s``.

    Returns
    -------
    loss : float
        ``mean_{p,c} w_pc (bias_pc² + var_pc)`` with the terms of
        :func:`kernel_bias_variance` — Lemma A.1 / Eq. 15 (MSE) and Eq. 20 (MRSE) of [1]_,
        averaged instead of summed over pixels and channels.  By Theorem 1 of [1]_ any
        future-render law with the moments of :func:`future_moments` gives this value.
    grad : (H, W) ndarray, only if ``return_grad``
        ``∂loss/∂s_q = Σ_c ∂m_qc/∂s_q (Kᵀ 2wb)_qc + ∂v_qc/∂s_q ((K²)ᵀ w)_qc / (HWC)``, with
        ``∂m/∂s = (x_g − m)/n`` and ``∂v/∂s = var_g (s_bar − s)/n³`` (conditional).
        Where ``s_bar + s = 0`` the loss jumps (no samples → some samples) and the entry
        is reported as 0.

    Notes
    -----
    Conditional on ``x_t`` the variance term ``s var_g/(s_bar+s)²`` *grows* with ``s`` up to
    ``s = s_bar``: new samples add noise around a fixed current value, while the bias
    term pays for moving ``x_t`` towards ``x_g``.  Averaged over ``x_t``
    (``mean_var_t = var_g/s_bar``) the variance is ``var_g/(s_bar+s)`` and the bias the
    denoiser's own.

    A loss or gradient beyond float64's range (errors above ~1e154 squared) is an
    :class:`~statmc.errors.InputError` naming the inputs, not Inf/NaN.

    The compiled kernel runs in parallel over rows; a 1920×1080×3 image with 7×7
    kernels takes 0.4–0.6 s on 2 busy cores (``bench/bench_analytic.py``).
    """
    loss, eps = _check_loss(loss, eps)
    return_grad = as_bool("return_grad", return_grad)
    xt, sb, sm, xg, vg, mvt, _ = _prepare(x_t, s_bar, s, x_g, var_g, mean_var_t)
    if return_grad:
        _check_tiny_counts(sb, sm, "s_bar", "s", 3)
    K = _check_kernels(kernels, xt.shape[:2])
    _check_rel_denominator(loss, eps, xg)
    value, grad, _, _ = _evaluate(K, xt, sb, sm, xg, vg, mvt, loss, eps, return_grad)
    what = f"the expected {loss.upper()}" + (" or its gradient" if return_grad else "")
    _check_moments_overflow((value, grad), xt, sb, sm, xg, vg, mvt, what, _LOSS_RANGE, K)
    return (value, grad) if return_grad else value


# =========================================================================== sampler
def _project(y, budget, upper):
    """Euclidean projection of ``y`` onto ``{0 <= s <= upper, Σ s = budget}``.

    ``s = clip(y − τ, 0, upper)`` with ``τ`` found by safeguarded Newton steps on the
    piecewise-linear, decreasing ``φ(τ) = Σ clip(y − τ, 0, upper)``.
    """
    hi_cap = np.inf if upper is None else upper

    def phi(t):
        x = np.clip(y - t, 0.0, hi_cap)
        return x.sum(), x

    big = budget if upper is None else max(budget, float(np.max(upper)))
    lo, hi = float(np.min(y)) - big - 1.0, float(np.max(y))   # φ(lo) >= budget >= φ(hi) = 0
    t = 0.5 * (lo + hi)
    x = None
    for _ in range(200):
        total, x = phi(t)
        err = total - budget
        if abs(err) <= 1e-12 * max(budget, 1.0):
            break
        if err > 0:
            lo = t
        else:
            hi = t
        free = np.count_nonzero((x > 0) & (x < hi_cap))
        t_new = t + err / free if free else 0.5 * (lo + hi)
        t = t_new if lo < t_new < hi else 0.5 * (lo + hi)
        if hi - lo <= 1e-15 * max(1.0, abs(t)):
            break
    # Exact budget: put the last rounding residue on the free entries.
    resid = budget - x.sum()
    free = (x > 0) & (x < hi_cap)
    if resid != 0 and free.any():
        x[free] += resid / np.count_nonzero(free)
        np.clip(x, 0.0, hi_cap, out=x)
    return x


def _water_fill(a, sb, budget, upper):
    """Minimiser of ``Σ a_q / (sb_q + s_q)`` on the budget set: ``sb + s = sqrt(a/λ)``."""
    hi_cap = np.inf if upper is None else upper
    root = np.sqrt(np.maximum(a, 0.0))
    if not np.any(root > 0):
        return None

    def alloc(inv_sqrt_lam):
        return np.clip(root * inv_sqrt_lam - sb, 0.0, hi_cap)

    lo, hi = 0.0, 1.0
    while alloc(hi).sum() < budget:
        hi *= 2.0
        if hi > 1e300:
            return None
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if alloc(mid).sum() < budget:
            lo = mid
        else:
            hi = mid
    return _project(alloc(hi), budget, upper)


def _check_budget(budget, n_pix, upper):
    value = _scalar(budget)         # a string "300" was parsed by float(), True was 1 sample
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise InputError(f"`budget` must be a number of samples; got {budget!r}.")
    b = float(value)
    if not np.isfinite(b) or b < 0:
        raise InputError(f"`budget` must be a finite number >= 0; got {budget!r}.")
    if upper is not None and b > upper.sum() * (1 + 1e-12):
        raise InputError(
            f"`budget` = {b:g} is not reachable: `max_count` allows at most "
            f"{upper.sum():g} samples over the {n_pix} pixels.")
    return b


def optimal_sample_map(kernels, x_t, s_bar, x_g_est, var_g_est, budget, *, loss="mse",
                       eps=RELMSE_EPS, mean_var_t=None, max_count=None, max_iter=1000,
                       rtol=1e-9, return_info=False):
    """Real-valued sampling map minimising the expected denoising loss under a budget.

    Solves ``min_s expected_kernel_loss(kernels, x_t, s_bar, s, x_g_est, var_g_est)``
    subject to ``Σ s = budget`` and ``0 <= s (<= max_count)`` — Eq. 1–2 of [1]_ with the
    closed form of Lemma A.1 in place of a trained network (a classical sampler; not in
    the paper).

    Parameters
    ----------
    kernels : (H, W, k, k) ndarray
        The denoiser's kernels, fixed for the next pass (a GEM selection, a fixed
        Gaussian, kernels exported by a network...).
    x_t : (H, W, C) ndarray
        Current render.
    s_bar : (H, W) ndarray
        Samples so far; must be ``> 0`` in every pixel (the model needs a current value).
    x_g_est, var_g_est : like ``x_t``
        Estimates (or, on synthetic data, the truth) of the pixel mean and of the
        **sample variance** of one sample.
    budget : float
        Samples to distribute, ``>= 0``.
    loss, eps, mean_var_t
        As in :func:`expected_kernel_loss`.  With estimated ``x_g`` the unconditional
        objective (``mean_var_t = var_g_est / s_bar``) is the safer choice: conditional
        on ``x_t`` it can only see errors of ``x_t`` that ``x_g_est`` reveals.
    max_count : (H, W) ndarray, optional
        Per-pixel cap on the new samples.
    max_iter, rtol
        Iteration cap and relative objective decrease that stops the solver.
    return_info : bool
        Also return a dict of diagnostics (objective at uniform, start and end,
        iterations, whether ``rtol`` was met).

    Returns
    -------
    s : (H, W) float64 ndarray
        ``s >= 0``, ``s.sum() == budget`` (to rounding).
    info : dict, only if ``return_info``

    Notes
    -----
    Spectral projected gradient (Barzilai–Borwein steps, Armijo backtracking, Euclidean
    projection onto the capped simplex), started from the better of the uniform map and
    the water-filling map ``s_bar + s ∝ sqrt(Σ_c var_g (K²)ᵀw)``, which is the exact
    optimum of the unconditional objective with ``mean_var_t = var_g/s_bar``.  Each step
    decreases the objective, so the result is never worse than uniform sampling.  The
    conditional objective is not convex (see :func:`expected_kernel_loss`): the result
    is a local optimum.
    """
    loss, eps = _check_loss(loss, eps)
    return_info = as_bool("return_info", return_info)
    xt, sb, _, xg, vg, mvt, _ = _prepare(x_t, s_bar, 0.0, x_g_est, var_g_est, mean_var_t,
                                         names=("x_t", "s_bar", "s", "x_g_est", "var_g_est"))
    hw = xt.shape[:2]
    K = _check_kernels(kernels, hw)
    if np.any(sb <= 0):
        raise InputError(
            f"`s_bar` must be > 0 in every pixel for optimal_sample_map (the analytic model "
            f"needs a current estimate); got {int((sb <= 0).sum())} pixels with 0 samples. "
            "Render at least one sample per pixel first.")
    _check_tiny_counts(sb, 0.0, "s_bar", "s", 3)     # the gradient's n³, n >= s_bar
    upper = None if max_count is None else _count_map("max_count", max_count, hw)
    b = _check_budget(budget, sb.size, upper)
    max_iter = as_whole("max_iter", max_iter, lo=1, what="number of iterations")
    rtol = as_number("rtol", rtol, lo=0.0)
    _check_rel_denominator(loss, eps, xg)

    def f(sv, grad=False):
        return _evaluate(K, xt, sb, sv, xg, vg, mvt, loss, eps, grad)[:2]

    uniform = _project(np.full(hw, b / sb.size), b, upper)
    f_uniform = f(uniform)[0]
    _check_moments_overflow((f_uniform,), xt, sb, uniform, xg, vg, mvt,
                            f"the expected {loss.upper()} at uniform sampling", _LOSS_RANGE, K)
    info = {"objective_uniform": f_uniform, "iterations": 0, "converged": b == 0}
    if b == 0:
        info.update(objective_start=f_uniform, objective=f_uniform, start="uniform")
        return (uniform, info) if return_info else uniform
    # water-filling start: a_q = Σ_c var_g (K²)ᵀ w / (HWC)
    wgt = 1.0 / (xg * xg + eps) if loss == "mrse" else np.ones_like(xg)
    a = _ak.column_weights_numba(K, wgt / xg.size, vg)
    x, start = uniform, "uniform"
    wf = _water_fill(a, sb, b, upper)
    fx = f_uniform
    if wf is not None:
        f_wf = f(wf)[0]
        if f_wf < fx:
            x, fx, start = wf, f_wf, "water-filling"
    info.update(objective_start=fx, start=start)
    fx, g = f(x, True)
    _check_moments_overflow((g,), xt, sb, x, xg, vg, mvt,
                            f"the gradient of the expected {loss.upper()}", _LOSS_RANGE, K)
    pg = _project(x - (g - g.mean()), b, upper) - x
    alpha = 1.0 / max(np.max(np.abs(pg)), 1e-300)
    # BB steps live in the units of s²/loss.  The projection ignores a constant added to
    # its argument, so step along g minus its mean; and a step longer than ~ the feasible
    # set's diameter (<= 2b per entry) over the gradient's spread only lands on a vertex.
    # Without both, x − αg reached 1e20 near the optimum (g almost constant, α huge) and
    # the projection lost the budget to rounding (an all-zero map came back once).
    scale = 4.0 * (b + float(np.max(x)))
    a_min = 1e-30
    stall = 0
    it = 0
    for it in range(1, max_iter + 1):
        gc = g - g.mean()
        alpha = min(alpha, scale / max(float(np.ptp(gc)), 1e-300))
        d = _project(x - alpha * gc, b, upper) - x
        gd = float(np.sum(g * d))
        if gd >= 0 or not np.any(d):
            info["converged"] = True
            break
        t = 1.0
        while True:
            xn = x + t * d
            fn = f(xn)[0]
            if fn <= fx + 1e-4 * t * gd or t < 1e-12:
                break
            t *= 0.5
        if fn > fx:
            info["converged"] = True
            break
        fn, gn = f(xn, True)
        sk, yk = xn - x, gn - g
        sy = float(np.sum(sk * yk))
        alpha = max(float(np.sum(sk * sk)) / sy, a_min) if sy > 0 else np.inf
        rel = (fx - fn) / max(abs(fx), 1e-300)
        x, fx, g = xn, fn, gn
        stall = stall + 1 if rel <= rtol else 0
        if stall >= 3:
            info["converged"] = True
            break
    x_final = _project(np.maximum(x, 0.0), b, upper)
    f_final = f(x_final)[0]
    if not f_final <= fx * (1 + 1e-12) + 1e-300:   # never worse than the accepted iterate
        x_final, f_final = x, fx
    info.update(iterations=it, objective=f_final)
    return (x_final, info) if return_info else x_final


def optimal_sample_counts(kernels, x_t, s_bar, x_g_est, var_g_est, budget, *, rng=None,
                          **options):
    """Integer version of :func:`optimal_sample_map` with an exact budget.

    The real map is rounded by :func:`statmc.sampling.counts_from_density` (systematic,
    unbiased rounding): ``counts.sum() == budget`` exactly and ``E[counts]`` equals the
    real map.  ``budget`` must be a whole number; ``options`` are passed on
    (``loss``, ``eps``, ``mean_var_t``, ``max_count``, ``max_iter``, ``rtol``,
    ``return_info``).  With a non-integer ``max_count`` a count may exceed it by < 1.

    Returns
    -------
    counts : (H, W) int64 ndarray (and the info dict if ``return_info=True``)
    """
    b = _whole_budget(budget)
    res = optimal_sample_map(kernels, x_t, s_bar, x_g_est, var_g_est, b, **options)
    smap, info = res if options.get("return_info") else (res, None)
    counts = counts_from_density(smap, int(b), rng=rng)
    return (counts, info) if info is not None else counts


#: Window of :func:`pooled_sample_variance` used by :func:`expected_error_sampler`:
#: σ = 2 px pools ~50 pixels.  Chosen once on the toy scenes among a few candidates
#: (docs/analytic.md); the Mitsuba scenes were held out.
POOL_SIGMA = 2.0


def pooled_sample_variance(sample_var, n, *, sigma=POOL_SIGMA, prior_dof=None):
    """Per-pixel sample variance shrunk towards its neighbourhood (empirical Bayes).

    Parameters
    ----------
    sample_var : (H, W, C) or (H, W) ndarray
        **Sample variance** ``s²`` of one sample per pixel (``PixelStats.sample_var``).
    n : (H, W) ndarray
        Samples per pixel; ``n − 1`` are the degrees of freedom of ``s²``.
    sigma : float
        Standard deviation (pixels) of the Gaussian window that pools the neighbours;
        0 pools nothing.
    prior_dof : float or None
        ``ν0``, the weight of the pooled value in degrees of freedom; 0 returns ``s²``.
        ``None`` (default) gives the pool as many as the pixel's own, ``ν0 = n − 1``:
        the plain average of ``s²`` and ``v_pool``.

    Returns
    -------
    var : ndarray like ``sample_var`` (float64)
        ``(ν0 v_pool + (n − 1) s²) / (ν0 + n − 1)`` with the pooled variance
        ``v_pool = G_σ∗((n − 1) s²) / G_σ∗(n − 1)`` (degree-of-freedom weighted,
        border-renormalised Gaussian window).  This is the scale of the conjugate
        posterior of a normal variance under a scaled-inverse-χ²(ν0, v_pool) prior
        (Gelman et al., *Bayesian Data Analysis*, 3rd ed., §2.6; the "moderated"
        variance of Smyth 2004, Eq. 2, with a local instead of a global prior).  Not in
        the rendering papers.  Where ``ν0 + n − 1 = 0`` the result is ``v_pool`` (0 if the
        window has no degree of freedom either).

    Notes
    -----
    Why: from 4–16 samples, ``s²`` of a heavy-tailed pixel is mostly 0 (no firefly hit yet)
    and occasionally huge.  A sampler that trusts it starves the first kind of pixel
    forever (``s² = 0`` asks for no samples) and its allocation is correlated with the
    pixel's own mean error.  The pooled value fixes both; the pixel's own ``s²`` takes
    over as its degrees of freedom grow past ``ν0``.

    Examples
    --------
    >>> v = np.zeros((5, 5)); v[2, 2] = 1.0
    >>> out = pooled_sample_variance(v, np.full((5, 5), 4), sigma=1.0, prior_dof=3.0)
    >>> bool(out[0, 0] > 0), bool(out[2, 2] < 1.0)
    (True, True)
    """
    sv = as_float_array("sample_var", sample_var, ndim=(2, 3), dtype=np.float64)
    check_finite("sample_var", sv)
    check_nonnegative("sample_var", sv)
    cnt = _count_map("n", n, sv.shape[:2])
    # as_number: float() parsed a string "2" and took True for 1 here before
    sigma = as_number("sigma", sigma, lo=0.0)
    nu0 = 0.0 if prior_dof is None else as_number("prior_dof", prior_dof, lo=0.0)
    from .filters import gaussian_filter
    dof = np.maximum(cnt - 1.0, 0.0)
    dof_c = dof if sv.ndim == 2 else dof[..., None]
    with np.errstate(over="ignore"):
        num = dof_c * sv
    # checked here: gaussian_filter named its own `image` when handed the Inf
    pooled_range = "(n − 1)·sample_var, and its Gaussian-weighted sums, below 1.8e308"
    check_overflow(num, "the weighted sample variance (n − 1)·sample_var",
                   {"sample_var": sv, "n": cnt}, pooled_range)
    num = gaussian_filter(num, sigma) if sigma > 0 else num
    den = gaussian_filter(dof, sigma) if sigma > 0 else dof
    den_c = den if sv.ndim == 2 else den[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        pool = np.where(den_c > 0, num / np.where(den_c > 0, den_c, 1.0), 0.0)
        nu = dof_c if prior_dof is None else nu0
        tot = nu + dof_c
        out = np.where(tot > 0, (nu * pool + dof_c * sv) / np.where(tot > 0, tot, 1.0), pool)
    check_overflow(out, "the pooled sample variance", {"sample_var": sv, "n": cnt}, pooled_range)
    return np.maximum(out, 0.0)


def _reference_estimate(kernels, mean, mean_var):
    """``sqrt(max(D² − Var[D], 0))`` with ``D = K x_t``: the relMSE denominator's estimate.

    ``E[D²] = (K x_g)² + Var[D]`` with ``Var[D]_p = Σ_q K_pq² mean_var_q`` (independent
    pixels), so ``D² − Var[D]`` is unbiased for ``(K x_g)²``; the raw ``x_t²`` would add
    ``mean_var`` and ``(K x_t)²`` the smaller ``Var[D]``.
    """
    d = apply_kernels(kernels, mean)
    vd = apply_kernels(np.square(kernels), mean_var)
    return np.sqrt(np.maximum(d * d - vd, 0.0))


def _smooth_reference_estimate(mean, mean_var, sigma):
    """:func:`_reference_estimate` for a border-renormalised Gaussian of ``sigma`` px.

    ``D = G_σ x_t`` by :func:`statmc.filters.gaussian_filter`; ``Var[D]_p = Σ_q G_pq²
    mean_var_q`` with the separable squared taps ``g²`` and the squared border factors
    (the same weights as ``gaussian(σ).kernels``, without the ``(H, W, k, k)`` array).
    """
    from scipy.ndimage import correlate1d

    from .filters import DEFAULT_TRUNCATE, _taps, border_scale, gaussian_filter
    sig = as_number("weight_sigma", sigma, lo=0.0)
    m = np.asarray(mean, np.float64)
    mv = np.asarray(mean_var, np.float64)
    if sig == 0:
        d, vd = m, mv
    else:   # gaussian_filter's taps, cut to the image (σ = 1e6: 6e6 taps, 13 s before)
        g = _taps(sig, DEFAULT_TRUNCATE, max(m.shape[:2]))
        d = gaussian_filter(m, sig)
        vd = correlate1d(correlate1d(mv, g * g, axis=0, mode="constant"), g * g, axis=1,
                         mode="constant")
        sy, sx = border_scale(m.shape[0], g) ** 2, border_scale(m.shape[1], g) ** 2
        shape = (-1, 1) + (1,) * (m.ndim - 2)
        vd = vd * sy.reshape(shape) * sx.reshape((1, -1) + (1,) * (m.ndim - 2))
    return np.sqrt(np.maximum(d * d - vd, 0.0))


#: Default ``weight_sigma`` of :func:`expected_error_sampler`: the relMSE weights
#: ``1/(x̂² + ε)`` take ``x̂`` from a σ = 2 px Gaussian of the current render rather than
#: from the denoiser's own kernels.  Chosen on the toy scenes (docs/analytic.md); with
#: GEM's kernels, whose pixel filter makes ``x̂`` the pixel's own 4-spp value, weights
#: from the kernels made the adaptive render 1.4-4x *worse* than uniform.
WEIGHT_SIGMA = 2.0

_OBJECTIVES = ("unconditional", "conditional")


def expected_error_sampler(stats, budget: int, rng=None, *, sigma: float = 1.0,
                           kernels=None, mix: float = 0.0,
                           weight_sigma=WEIGHT_SIGMA,
                           loss: str = "mrse", objective: str = "unconditional",
                           pool_sigma: float = POOL_SIGMA, prior_dof=None,
                           eps: float = RELMSE_EPS) -> np.ndarray:
    """One iteration of the ``expected-error`` adaptive sampler (a classical sampler).

    Integer counts minimising the closed-form expected loss (Lemma A.1 of [1]_) of a
    fixed kernel denoiser (by default a Gaussian of standard deviation ``sigma``) after
    adding ``budget`` samples, with the true statistics replaced by estimates from
    ``stats``.

    Parameters
    ----------
    stats : PixelStats
        Statistics so far.  Pixels with ``n <= 1`` have no variance of their own and
        take the pooled variance of their neighbourhood (:func:`pooled_sample_variance`);
        an empty pixel (``n = 0``) is filled up like its neighbours (tested;
        ``objective="conditional"`` refuses it: it needs a current estimate).
    budget : int
        Samples to add; the counts sum to it exactly.
    rng : numpy Generator or int, optional
        For the unbiased rounding of the real-valued map.
    sigma : float
        The denoiser when ``kernels`` is None: ``statmc.denoisers.gaussian(sigma)``.
    kernels : (H, W, k, k) ndarray, "gem" or an object with ``.kernels(shape)``, optional
        The denoiser's kernels for the next pass: an array (e.g. :func:`gem_kernels` of a
        pilot render, or kernels exported by a network), a linear denoiser such as
        ``statmc.denoisers.gaussian(2.0)``, or ``"gem"`` — GEM's selection
        (:func:`gem_kernels`) on ``stats`` *of this call*.  Lemma A.1 needs kernels that
        do not react to the samples being placed: over one pass any of these qualifies,
        but the final denoiser equals the optimised one only if the kernels are held
        fixed over all passes — use :class:`PilotKernelSampler` for that.
    mix : float
        Defensive mixture ``λ`` in [0, 1]: the real-valued map is
        ``(1 − λ) s_opt + λ · budget/(H W)`` before rounding, so every pixel keeps at
        least the share ``λ`` of a uniform pass whatever the estimates say (a bound of
        ``1/(1 − λ)`` on how much worse than uniform the variance term can get for a
        pixel the optimiser starved).  Default 0 (docs/analytic.md measures 0.25, 0.5).
    loss : {"mrse", "mse"}
    objective : {"unconditional", "conditional"}
        ``"unconditional"`` (default) averages the loss over the current render too
        (``mean_var_t = var_est / n``, Eq. 7 of [1]_): the frequentist risk, which is what
        the mean of measured relMSE over seeds estimates.  Its bias term does not depend
        on the new samples, so the optimum is the water-filling map
        ``n_q ∝ sqrt(var_est_q Σ_p w_p K_pq²)`` and the mean estimate only enters the
        relMSE weights ``w_p = 1/(x̂_p² + eps)``.  ``"conditional"`` is the paper's form
        (conditional on the current render, Eq. 6 and 19) with ``x_g`` estimated by the
        current mean; it then sees no current error and charges new samples for their
        noise, which made it worse than uniform sampling (docs/analytic.md).
    weight_sigma : float or None
        The relMSE weights ``1/(x̂² + eps)`` take ``x̂`` from a Gaussian of this many
        pixels (default :data:`WEIGHT_SIGMA` = 2); ``None`` takes it from ``kernels``.
    pool_sigma, prior_dof
        Variance estimate: :func:`pooled_sample_variance` of ``stats.sample_var``.
    eps : float
        relMSE ε.

    Returns
    -------
    counts : (H, W) int64 ndarray

    Notes
    -----
    Estimates: ``var_est`` = :func:`pooled_sample_variance`; the relMSE reference is
    ``x̂ = sqrt(max((G x_t)² − Var[G x_t], 0))`` with ``G`` the σ = ``weight_sigma``
    Gaussian (or ``K``), an unbiased estimate of ``(G x_g)²`` under the root (the noisy
    ``x_t²`` overstates dark pixels' brightness by their variance).  A weight computed
    from the render is correlated with its current error: too-dark pixels get more
    samples and are corrected, too-bright ones are left, so the adaptive render is biased
    upwards.  Wide kernels keep that bias while removing the noise; with GEM's kernels
    (whose pixel filter makes ``K x_t`` the pixel's own value) weights from the kernels
    made the result 1.4–4× worse than uniform, the σ = 2 Gaussian fixed it
    (docs/analytic.md).

    The unconditional optimum is the water-filling map, computed directly.  Measured
    against uniform sampling on toy and Mitsuba scenes, with the Gaussian and with fixed
    pilot-GEM kernels, in ``bench/bench_quality_expected_error.py``.
    """
    check_stats(stats)
    if not isinstance(objective, str) or objective not in _OBJECTIVES:
        raise InputError(f"`objective` must be one of {_OBJECTIVES}; got {objective!r}.")
    lam = _check_mix(mix)
    kernels = _resolve_kernels(kernels, sigma, stats)
    var_est = pooled_sample_variance(stats.sample_var, stats.n, sigma=pool_sigma,
                                     prior_dof=prior_dof)
    n = np.asarray(stats.n, np.float64)
    n_c = n[..., None] if var_est.ndim == 3 else n
    b = _whole_budget(budget)
    if objective == "conditional":
        if np.any(n <= 0):
            raise InputError(f"`stats` must have >= 1 sample in every pixel for "
                             f"objective='conditional' (its model needs a current estimate); "
                             f"got {int((n <= 0).sum())} empty pixels. Render a first pass, "
                             "or use objective='unconditional' (the default), which fills "
                             "them like their neighbours.")
        smap = optimal_sample_map(kernels, stats.mean, n, stats.mean, var_est, b,
                                  loss=loss, eps=eps)
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            mean_var = np.where(n_c > 0, var_est / np.where(n_c > 0, n_c, 1.0), 0.0)
        if weight_sigma is None:
            x_ref = _reference_estimate(kernels, stats.mean, mean_var)
        else:
            x_ref = _smooth_reference_estimate(stats.mean, mean_var, weight_sigma)
        smap = _unconditional_map(kernels, n, x_ref, var_est, b, loss, eps)
    if lam > 0:
        smap = (1.0 - lam) * smap + lam * (b / smap.size)
    return counts_from_density(smap, int(b), rng=rng)


def _unconditional_map(kernels, n, x_ref, var_est, budget, loss, eps):
    """Exact minimiser of the unconditional objective: the water-filling map.

    With ``mean_var_t = var/n`` the objective is ``const + Σ_q a_q/(n_q + s_q)``,
    ``a_q = Σ_c var_qc ((K²)ᵀ w)_qc / (HWC)``, minimised by ``n + s ∝ sqrt(a)`` clipped at
    ``s >= 0`` — what :func:`optimal_sample_map` starts from; its gradient steps only
    polish rounding (``test_expected_error_sampler_water_filling_equals_solver``).
    """
    loss, eps = _check_loss(loss, eps)
    xg = x_ref if x_ref.ndim == 3 else x_ref[..., None]
    vg = var_est if var_est.ndim == 3 else var_est[..., None]
    K = _check_kernels(kernels, xg.shape[:2])
    wgt = 1.0 / (xg * xg + eps) if loss == "mrse" else np.ones_like(xg)
    a = _ak.column_weights_numba(K, np.ascontiguousarray(wgt / xg.size),
                                 np.ascontiguousarray(vg, dtype=np.float64))
    uniform = np.full(n.shape, budget / n.size)
    if budget == 0:
        return uniform
    wf = _water_fill(a, n, budget, None)
    return uniform if wf is None else wf


def _check_mix(mix):
    lam = as_number("mix", mix, lo=0.0)
    if lam > 1.0:
        raise InputError(f"`mix` must be a number in [0, 1] (weight of uniform sampling); "
                         f"got {mix!r}.")
    return lam


def _whole_budget(budget):
    # hi: checked here on the budget given, else counts_from_density printed float(budget)
    # rounded back to an int (10**30 came back as 1000000000000000019884624838656)
    return float(as_whole("budget", budget, what="number of samples", hi=MAX_BUDGET))


def _resolve_kernels(kernels, sigma, stats):
    """The ``(H, W, k, k)`` kernels named by ``expected_error_sampler(kernels=...)``."""
    shape = stats.mean.shape
    if kernels is None:
        from .denoisers import gaussian
        return gaussian(sigma).kernels(shape)
    if isinstance(kernels, str):
        if kernels != "gem":
            raise InputError(f"`kernels` must be an (H, W, k, k) array, a linear denoiser "
                             f"with .kernels(shape), or 'gem'; got {kernels!r}.")
        return gem_kernels(stats.mean, stats.mean_var, n=stats.n)
    if hasattr(kernels, "kernels") and callable(kernels.kernels):
        return kernels.kernels(shape)
    return _check_kernels(kernels, shape[:2])


class PilotKernelSampler:
    """``expected-error`` sampler for kernels chosen once, from the pilot, then held fixed.

    A sampler for :func:`statmc.adaptive.adaptive_render`.  On its first call (the
    statistics of the first, uniform pass) it fixes the denoiser's kernels; every call
    then places samples by :func:`expected_error_sampler` for those kernels, and
    :attr:`kernels` is the denoiser to apply to the final render
    (``apply_kernels(sampler.kernels, result.stats.mean)``).  Because the kernels never
    see the samples being placed, Lemma A.1 of [1]_ holds for the final denoised image —
    which is not true of GEM re-selected on the final render.

    Parameters
    ----------
    kernels : "gem", (H, W, k, k) ndarray, or a callable ``stats -> (H, W, k, k)``
        ``"gem"`` (default): :func:`gem_kernels` of the pilot (``gem_options`` passed on).
    gem_options : dict, optional
        ``gamma``, ``final``, ``dtype`` for :func:`gem_kernels`.
    **options
        Passed to :func:`expected_error_sampler` (``mix``, ``loss``, ``objective``, ...).

    Notes
    -----
    One instance per render: it keeps the first render's kernels.  ``reset()`` forgets
    them.

    Examples
    --------
    >>> from statmc.adaptive import adaptive_render
    >>> from statmc.toy import ToyRenderer
    >>> s = PilotKernelSampler("gem")
    >>> res = adaptive_render(ToyRenderer("mixed", width=16, height=16), 8, sampler=s)
    >>> s.kernels.shape[:2], int(res.stats.n.sum())
    ((16, 16), 2048)
    """

    def __init__(self, kernels="gem", *, gem_options=None, **options):
        if isinstance(kernels, str) and kernels != "gem":
            raise InputError(f"`kernels` must be 'gem', an (H, W, k, k) array or a callable "
                             f"stats -> kernels; got {kernels!r}.")
        self.source = kernels
        self.gem_options = dict(gem_options or {})
        self.options = options
        self.kernels = None

    def reset(self):
        """Forget the kernels (the next call selects them again)."""
        self.kernels = None

    def select(self, stats):
        """Fix the kernels from ``stats`` (done automatically on the first call)."""
        check_stats(stats)
        if isinstance(self.source, str):
            K = gem_kernels(stats.mean, stats.mean_var, n=stats.n, **self.gem_options)
        elif callable(self.source):
            K = self.source(stats)
        else:
            K = self.source
        self.kernels = _check_kernels(K, stats.mean.shape[:2])
        return self.kernels

    def __call__(self, stats, budget, rng=None):
        if self.kernels is None:
            self.select(stats)
        return expected_error_sampler(stats, budget, rng, kernels=self.kernels, **self.options)

    def __repr__(self):
        src = self.source if isinstance(self.source, str) else type(self.source).__name__
        return f"PilotKernelSampler({src!r}, options={self.options})"
