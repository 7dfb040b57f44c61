"""Denoising-aware adaptive sampling (Firmino, Frisvad and Jensen 2023 [1]_).

Samples go where they most reduce the error of the *denoised* image.  Each iteration of
the adaptive loop denoises the current render ``x`` with ``f``, estimates per pixel the
variance of ``f(x)`` (first order, from Jacobian-vector products with random ``±σ``
vectors, :func:`statmc.sure.output_variance`) — or its error by MC-SURE — and samples in
proportion to the map (Eq. 3 of the notes)

``m_i = Var[f_i(x)] / ((N_i + 1)(f_i(x)² + ε))``,  ε = 0.01,

clamped to ``>= 0``, blurred by a 5×5 Gaussian of σ = 0.5 (17×17, σ = 4 for the noisier
MC-SURE numerator), and normalised to the iteration's budget
(:func:`statmc.sampling.counts_from_density`, exact budget).  ``Var[f_i]/(N_i + 1)`` is
what one more sample in pixel ``i`` removes from ``Var[f_i]``; dividing by ``f_i² + ε``
makes it relative (relMSE).

Variants:

* ``variant="mc-sure"``: the per-pixel MC-SURE of ``f(x)`` (Eq. 1, 2 of Firmino 2022) in
  place of ``Var[f]`` (§"AS with MC-SURE" of [1]_);
* ``output="progressive"``: the variance (or error) of the progressively denoised image
  ``z = x + α'(y − x)`` (:mod:`statmc.progressive`) in place of ``f``'s, by the
  NJS-style formula of [1]_ (:func:`mix_variance`, :func:`njs_variance`);
* ``tonemap="aces"`` or ``"reinhard"``: the map of the tone-mapped output
  ``T(f(x))`` by the chain rule, ``Var[T(f_i)] ≈ T'(f_i)² Var[f_i]``, without the
  relative normalisation (the output is bounded).

:func:`sampler` has the signature of the adaptive loop (:func:`statmc.adaptive.adaptive_render`),
``sampler(stats, budget, rng, *, denoiser="oidn", ...) -> counts``; the denoiser is rebuilt
each iteration from the current statistics (OIDN with the feature buffers, GEM with the
current variance).

Reproducibility: with a seed the whole loop is deterministic to the bit, in any process
and on any number of numba or OIDN threads.  It is also chaotic.  A change to the map at
the level of float rounding can move one sample in the first adaptive pass, and the
renderer then draws different random numbers for the passes that follow, so it produces
another render.  That happened with the gate's float32 normal CDF: glass-caustic 256 spp went
from 0.547 to 0.761 × OIDN+progressive (docs/quality.md).  Compare adaptive renders across
code versions by means over seeds.

References
----------
.. [1] A. Firmino, J. R. Frisvad, H. W. Jensen. "Denoising-Aware Adaptive Sampling for
   Monte Carlo Ray Tracing". SIGGRAPH 2023 Conference Proceedings.
   https://doi.org/10.1145/3588432.3591537
   (``shared/papers/firmino2023-denoising-aware-adaptive-sampling-notes.md``)
.. [2] K. Narkowicz. "ACES Filmic Tone Mapping Curve", 2016.
   https://knarkowicz.wordpress.com/2016/01/06/aces-filmic-tone-mapping-curve/
.. [3] E. Reinhard, M. Stark, P. Shirley, J. Ferwerda. "Photographic tone reproduction
   for digital images". ACM TOG 21(3), 2002. https://doi.org/10.1145/566654.566575
"""

from __future__ import annotations

import numbers

import numpy as np

from .errors import (MAX_BUDGET, InputError, _scalar, as_bool, as_broadcast_arrays,
                     as_float_array, as_rng, as_whole, check_finite)
from .stats import PixelStats, check_stats

__all__ = ["denoising_aware_density", "denoising_aware_map", "denoising_aware_sampler",
           "sampler", "mix_variance", "njs_variance", "tonemap", "tonemap_derivative",
           "VARIANTS", "OUTPUTS", "TONEMAPS", "BLUR", "DEFAULT_EPS", "DEFAULT_K"]

#: Numerators of the map: the first-order variance of the output, or its MC-SURE error.
VARIANTS = ("variance", "mc-sure")
#: Which image the map is about: ``f(x)``, or the progressive mix ``x + α'(f(x) − x)``.
OUTPUTS = ("denoised", "progressive")
#: Tone-mapping curves (per channel): ACES (Narkowicz's fit [2]_) and Reinhard ``x/(1+x)``.
TONEMAPS = ("aces", "reinhard")
#: Blur of the map per variant as (σ, radius): 5×5 σ = 0.5 for the variance, 17×17
#: σ = 4 for MC-SURE, whose per-pixel values are noisier (Firmino 2023, notes).
BLUR = {"variance": (0.5, 2), "mc-sure": (4.0, 8)}
#: ε of the relative map (Eq. 3 of the notes): 0.01.
DEFAULT_EPS = 0.01
#: Random probes per iteration for Var[f] (``output_variance``) and for MC-SURE (K = 4,
#: Firmino 2023 "AS with MC-SURE").
DEFAULT_K = 4

_NAMES = ("oidn", "gem", "gaussian", "none", "identity")

# ACES fit of Narkowicz [2]: T(x) = x(a x + b) / (x(c x + d) + e), clamped to [0, 1].
_ACES = (2.51, 0.03, 2.43, 0.59, 0.14)
#: The ACES fit reaches 1 at x ≈ 7.24 and is clamped there, so capping ``x`` at 8 changes
#: neither the curve nor its derivative (0) and keeps ``x²`` finite for huge radiance
#: (float32 1e20 gave inf/inf = NaN).
_ACES_CAP = 8.0


# =========================================================================== tone mapping
def _tm_name(name):
    if name not in TONEMAPS:
        raise InputError(f"`tonemap` must be one of {', '.join(TONEMAPS)}; got {name!r}.")
    return name


def _exposure(exposure):
    exposure = _scalar(exposure)                 # a 0-d array is its number
    if isinstance(exposure, bool) or not isinstance(exposure, numbers.Real) \
            or not np.isfinite(float(exposure)) or float(exposure) <= 0:
        raise InputError(f"`exposure` must be a finite number > 0; got {exposure!r}.")
    return float(exposure)


def _aces_input(xr, ex):
    """``e·max(x, 0)`` capped at :data:`_ACES_CAP`; the cap ``8/e`` in the image's dtype
    (beyond float32's range for ``e`` < ~2.4e-38, where np.minimum warned of an overflowing
    cast; the dtype's maximum caps nothing there either)."""
    cap = min(_ACES_CAP / ex, float(np.finfo(xr.dtype).max))
    return np.minimum(np.maximum(xr, 0.0), cap) * ex


def tonemap(image, name: str = "aces", *, exposure: float = 1.0) -> np.ndarray:
    """Per-channel tone mapping ``T(e·x)`` into [0, 1].

    Parameters
    ----------
    image : ndarray
        Linear radiance (any shape); negative values map to 0.
    name : {"aces", "reinhard"}
        ``"aces"``: Narkowicz's fit ``x(2.51x + 0.03)/(x(2.43x + 0.59) + 0.14)`` clamped
        to [0, 1] [2]_; ``"reinhard"``: ``x/(1 + x)`` [3]_.
    exposure : float
        Scale ``e`` applied before the curve.

    Examples
    --------
    >>> float(tonemap(np.array(1.0), "reinhard"))
    0.5
    """
    xr = as_float_array("image", image)
    check_finite("image", xr)
    ex = _exposure(exposure)
    if ex > float(np.finfo(xr.dtype).max):   # e in float32 would be inf, and T(0·inf) NaN
        return tonemap(xr.astype(np.float64), _tm_name(name), exposure=ex).astype(xr.dtype)
    if _tm_name(name) == "reinhard":
        with np.errstate(over="ignore"):
            x = np.maximum(xr, 0.0) * ex
        # e·x beyond the dtype (inf): the largest finite value instead, whose T is exactly 1
        # (1 + max rounds to max); finite values pass unchanged, in one pass
        x = np.minimum(x, np.finfo(x.dtype).max)
        return x / (1.0 + x)
    x = _aces_input(xr, ex)
    a, b, c, d, e = _ACES
    return np.clip(x * (a * x + b) / (x * (c * x + d) + e), 0.0, 1.0)


def tonemap_derivative(image, name: str = "aces", *, exposure: float = 1.0) -> np.ndarray:
    """``d/dx T(e·x)`` of :func:`tonemap`, per element (0 where clamped).

    In the image's dtype; a slope beyond its range (``e·T'(0)`` for an exposure near the
    float32 maximum) is ``inf``.
    """
    xr = as_float_array("image", image)
    check_finite("image", xr)
    ex = _exposure(exposure)
    if ex > float(np.finfo(xr.dtype).max):   # e in float32 would be inf, and 0·inf NaN
        out = tonemap_derivative(xr.astype(np.float64), _tm_name(name), exposure=ex)
        with np.errstate(over="ignore"):
            return out.astype(xr.dtype)
    if _tm_name(name) == "reinhard":
        with np.errstate(over="ignore"):            # 1 + e·x = inf: the derivative is 0
            g = 1.0 + np.maximum(xr, 0.0) * ex
            out = ex / g / g                         # not e/g²: g² overflows first
    else:
        x = _aces_input(xr, ex)
        a, b, c, d, e = _ACES
        num = x * (a * x + b)
        den = x * (c * x + d) + e
        # e·(…/den²), not (e·…)/den²: the product overflowed for e > ~1e36 in float32
        out = ex * (((2 * a * x + b) * den - num * (2 * c * x + d)) / (den * den))
        out = np.where(num / den >= 1.0, 0.0, out)
    return np.where(xr < 0, 0.0, out)


# =========================================================================== variance of mixes
def mix_variance(alpha, var_x, var_y, *, cov_xy=None) -> np.ndarray:
    """Variance of ``z = x + α (y − x) = (1 − α) x + α y`` for a fixed ``α``.

    Parameters
    ----------
    alpha : ndarray or float
        Mixing parameter (e.g. the gated ``α'`` of :func:`statmc.progressive.progressive_denoise`).
    var_x : ndarray
        ``Var[x]``, the **variance of the mean** of the render.
    var_y : ndarray
        ``Var[y]`` of the denoised image (:func:`statmc.sure.output_variance`).
    cov_xy : ndarray, optional
        ``Cov[x_i, y_i]``; to first order it is the divergence term ``(J_f Σ)_ii`` of
        MC-SURE (Stein's lemma, Eq. 6 of Firmino 2022).  ``None`` drops it, the NJS-style
        approximation of Firmino 2023 that treats the inputs of the mix as uncorrelated.

    Returns
    -------
    ndarray
        ``(1 − α)² Var[x] + α² Var[y] + 2α(1 − α) Cov[x, y]`` — with ``ρ = α`` and a single
        denoised image, the formula ``ρ²(…) + (1 − ρ)² Var[x]`` of the notes plus the
        covariance it omits.  ``α`` is treated as fixed (its own randomness is ignored, as
        in [1]_).  With an estimated ``cov_xy`` (the MC-SURE divergence is noisy) the result
        is negative where ``|Cov| > √(Var[x] Var[y])``; it is returned as computed, not
        clipped (:func:`denoising_aware_density` clamps its map at 0, as the notes do).
    """
    named = {"alpha": alpha, "var_x": var_x, "var_y": var_y}
    if cov_xy is not None:
        named["cov_xy"] = cov_xy
    a, vx, vy, *cov = as_broadcast_arrays(named, nonnegative=("var_x", "var_y"))
    out = (1.0 - a) ** 2 * vx + a * a * vy
    if cov:
        out = out + 2.0 * a * (1.0 - a) * cov[0]
    return out


def njs_variance(rho, alpha, var_fa, var_fb, var_x) -> np.ndarray:
    """Variance of the Neural James–Stein combination, Firmino 2023 (§"Denoising with
    Post-Correction" of the notes).

    ``ρ (α f(x_a) + (1 − α) f(x_b)) + (1 − ρ) x`` has, with ``ρ`` and ``α`` fixed and the
    three terms uncorrelated,

    ``Var = ρ² (α² Var[f(x_a)] + (1 − α)² Var[f(x_b)]) + (1 − ρ)² Var[x]``.

    The notes state it so; the terms are in fact correlated (``x = (x_a + x_b)/2`` feeds
    both denoised buffers), which :func:`mix_variance` can include for the two-term mix.
    """
    r, a, va, vb, vx = as_broadcast_arrays(
        {"rho": rho, "alpha": alpha, "var_fa": var_fa, "var_fb": var_fb, "var_x": var_x},
        nonnegative=("var_fa", "var_fb", "var_x"))
    return r * r * (a * a * va + (1.0 - a) ** 2 * vb) + (1.0 - r) ** 2 * vx


# =========================================================================== the map
def _check_stats(stats):
    check_stats(stats)
    stats.require_variance(hint=" Render an initial uniform pass of >= 2 spp first.")


def _blur(m, variant, blur):
    from .filters import gaussian_filter

    if blur is None:
        sigma, radius = BLUR[variant]
    else:
        try:
            sigma, radius = float(blur[0]), int(blur[1])
        except (TypeError, ValueError, IndexError) as exc:
            raise InputError(f"`blur` must be None or (sigma, radius); got {blur!r}.") from exc
        if not np.isfinite(sigma) or sigma < 0 or radius < 0:
            raise InputError(f"`blur` must have sigma >= 0 and radius >= 0; got {blur!r}.")
    if sigma == 0 or radius == 0:
        return m
    return gaussian_filter(m, sigma, truncate=radius / sigma)


def _output_variance(f, x, s2, k, method, gen):
    """``(Var[f(x)], f(x))``: first order by :func:`statmc.sure.output_variance`, except for
    GEM, whose output is the selected filter's (exact given the selection)."""
    from .denoisers import GEMDenoiser
    from .sure import output_variance

    if isinstance(f, GEMDenoiser) and method != "jvp":
        return f.output_variance(x)
    var, info = output_variance(f, x, s2, k=k, method=method, rng=gen, extra_output=True)
    out = info["denoised"]
    if out is None:
        out = np.asarray(f(x.astype(np.float32)), np.float64)
    return var, out


def denoising_aware_density(stats: PixelStats, denoiser, *, variant: str = "variance",
                            output: str = "denoised", tonemap: str | None = None,
                            exposure: float = 1.0, eps: float = DEFAULT_EPS, k: int = DEFAULT_K,
                            method: str = "fd", covariance: bool = True, blur=None, rng=None,
                            progressive_options: dict | None = None,
                            extra_output: bool = False):
    """The real-valued sampling map of denoising-aware adaptive sampling, ``(H, W)``.

    Parameters
    ----------
    stats : PixelStats
        Current statistics (``>= 2`` samples per pixel): ``x = stats.mean``, ``σ² =
        stats.mean_var`` (variance of the mean), ``N = stats.n``.
    denoiser : callable ``f(color) -> color`` or str
        A ready denoiser bound to these statistics, or a name (``"oidn"``, ``"gem"``,
        ``"gaussian"``) bound by :func:`statmc.progressive.bind_denoiser`.
    variant : {"variance", "mc-sure"}
        Numerator: the first-order variance of the output (:func:`statmc.sure.output_variance`,
        ``k`` probes) or its per-pixel MC-SURE error (:func:`statmc.sure.mc_sure`, ``k``
        probes, ε = 1e-4).
    output : {"denoised", "progressive"}
        ``"progressive"``: the map of ``z = x + α'(y − x)``
        (:func:`statmc.progressive.progressive_denoise`, with ``progressive_options``, any
        of its options but ``mean_var``; ``outlier=None`` unless given there):
        ``Var[z]`` by :func:`mix_variance` (with ``Cov[x, y] ≈`` the MC-SURE divergence when
        ``covariance``), or its error by Eq. 8 of Firmino 2022
        (:func:`statmc.progressive.mix_error`).
    tonemap : {"aces", "reinhard"} or None
        Map of the tone-mapped output ``T(f)`` by the chain rule (numerator times
        ``T'(f)²``), without the relative normalisation.
    exposure : float
        Exposure applied before the tone curve.
    eps : float
        ε of the relative normalisation (0.01).
    k : int
        Random probes.
    method : {"fd", "jvp", "exact"}
        How :func:`statmc.sure.output_variance` gets ``J v`` (``variant="variance"``).
        GEM (:class:`statmc.denoisers.GEMDenoiser`) is the exception: it switches filters
        discontinuously, and finite differences across a switch measure the jump divided by
        the step, not the noise (in the bench this piled up to 18 000 samples in single
        pixels at 64 spp), so its variance is that of the selected filter, from its filter
        bank — exact given the selection.
    covariance : bool
        Include ``Cov[x, y]`` in the variance of the progressive mix (``False``: the
        NJS-style formula).
    blur : (sigma, radius) or None
        Override :data:`BLUR` (``None``: 5×5 σ = 0.5 for the variance, 17×17 σ = 4 for
        MC-SURE).
    rng : numpy Generator or seed, optional
    extra_output : bool
        Also return a dict with ``output`` (the image the map is about), ``numerator``
        (per pixel and channel, before normalisation) and ``raw`` (the map before
        clamping and blurring).

    Returns
    -------
    density : (H, W) float64 ndarray, ``>= 0``
        ``blur(max(mean_c num_c / ((N + 1)(f_c² + ε)), 0))`` — Eq. 3 of the notes — or
        ``blur(max(mean_c T'(f_c)² num_c / (N + 1), 0))`` with a tone map.
    """
    from .progressive import bind_denoiser
    from .sure import mc_sure

    _check_stats(stats)
    if variant not in VARIANTS:
        raise InputError(f"`variant` must be one of {', '.join(VARIANTS)}; got {variant!r}.")
    if output not in OUTPUTS:
        raise InputError(f"`output` must be one of {', '.join(OUTPUTS)}; got {output!r}.")
    if tonemap is not None:
        _tm_name(tonemap)
    _exposure(exposure)
    eps, k = _scalar(eps), _scalar(k)            # 0-d arrays are their numbers
    if isinstance(eps, bool) or not isinstance(eps, numbers.Real) or not np.isfinite(eps) \
            or eps <= 0:
        raise InputError(f"`eps` must be a finite number > 0; got {eps!r}.")
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 1:
        raise InputError(f"`k` must be a positive integer; got {k!r}.")
    for flag, value in (("covariance", covariance), ("extra_output", extra_output)):
        as_bool(flag, value)                       # None or "no" were taken as False / True
    if progressive_options is not None and not isinstance(progressive_options, dict):
        raise InputError(f"`progressive_options` must be a dict or None; got "
                         f"{type(progressive_options).__name__}.")
    if progressive_options and "mean_var" in progressive_options:
        # one variance for the whole map: Eq. 3's σ², Var[x] in mix_variance and the gate's
        raise InputError("`progressive_options` must not set 'mean_var': the map takes σ² from "
                         "`stats.mean_var` everywhere. Pass stats with the variance you want "
                         "(PixelStats.from_mean_var).")
    if progressive_options:
        import inspect

        from .progressive import progressive_denoise
        known = set(inspect.signature(progressive_denoise).parameters) - {
            "stats", "denoiser", "rng", "extra_output"}
        unknown = sorted(set(progressive_options) - known)
        if unknown:          # a TypeError from progressive_denoise, or silently unused
            raise InputError(f"unknown `progressive_options` {unknown}; expected options of "
                             f"progressive_denoise: {sorted(known)}.")
    gen = as_rng(rng)
    f = bind_denoiser(denoiser, stats) if isinstance(denoiser, str) else denoiser
    x = stats.mean
    s2 = stats.mean_var
    if output == "denoised":
        if variant == "variance":
            num, out = _output_variance(f, x, s2, k, method, gen)
        else:
            num, info = mc_sure(f, x, s2, k=k, rng=gen, extra_output=True)
            out = info["denoised"]
    else:
        from .progressive import mix_error, progressive_denoise

        opts = dict(progressive_options or {})
        opts.setdefault("k", k)
        # The map keeps Eq. 9's α: the outlier rule of the final image (``outlier_alpha``)
        # fired on the noisy variances of a 2-spp pilot and made the 4-spp toy:mixed map 5 %
        # worse over 4 renders (docs/quality.md).
        opts.setdefault("outlier", None)
        out, pinfo = progressive_denoise(stats, f, rng=gen, extra_output=True, **opts)
        ag = pinfo["alpha_gated"]
        if variant == "variance":
            var_y, _ = _output_variance(f, x, s2, k, method, gen)
            num = mix_variance(ag, s2, var_y, cov_xy=pinfo["divergence"] if covariance else None)
        else:
            num = mix_error(ag, s2, pinfo["sure"], pinfo["divergence"])
    n1 = (stats.n.astype(np.float64) + 1.0)[..., None]
    if tonemap is None:
        per = num / (n1 * (out * out + float(eps)))
    else:
        per = tonemap_derivative(out, tonemap, exposure=exposure) ** 2 * num / n1
    raw = per.mean(axis=2)
    check_finite("density", raw)
    density = np.clip(_blur(np.maximum(raw, 0.0), variant, blur), 0.0, None)
    if extra_output:
        return density, {"output": out, "numerator": num, "raw": raw}
    return density


def denoising_aware_map(stats: PixelStats, denoiser, budget: int, *, rng=None, **options):
    """Integer per-pixel counts summing exactly to ``budget`` from :func:`denoising_aware_density`.

    Parameters
    ----------
    stats, denoiser
        As in :func:`denoising_aware_density`.
    budget : int
        Samples to distribute in this iteration.
    rng : numpy Generator or seed, optional
        Drives both the probes and the rounding.
    **options
        Of :func:`denoising_aware_density` (``variant``, ``output``, ``tonemap``, ``k``, …).

    Returns
    -------
    counts : (H, W) int64 ndarray with ``counts.sum() == budget``

    Examples
    --------
    >>> from statmc.toy import ToyRenderer
    >>> st = ToyRenderer("mixed", width=16, height=16).render_uniform(4, seed=0)
    >>> c = denoising_aware_map(st, "gaussian", 1000, rng=1)
    >>> int(c.sum())
    1000
    """
    from .sampling import counts_from_density

    # a whole float (spp·H·W computed in floating point) is a budget, as in the other samplers
    budget = as_whole("budget", budget, what="number of samples", hi=MAX_BUDGET)
    gen = as_rng(rng)
    density = denoising_aware_density(stats, denoiser, rng=gen, **options)
    return counts_from_density(density, budget, rng=gen)


def sampler(stats: PixelStats, budget: int, rng, *, denoiser="oidn", **options):
    """Adaptive-loop sampler: ``sampler(stats, budget, rng, *, denoiser=..., **options) -> counts``.

    ``denoiser`` is a name (``"oidn"``, ``"gem"``, ``"gaussian"``) or a factory
    ``factory(stats) -> denoiser``, rebuilt from the current ``stats`` at every call (OIDN
    with the feature buffers, GEM with the current variance).  ``options`` go to
    :func:`denoising_aware_density`.  Register it as ``SAMPLERS["denoising-aware"]``.
    """
    from .progressive import bind_denoiser

    _check_stats(stats)
    if not isinstance(denoiser, str) and not callable(denoiser):
        raise InputError(f"`denoiser` must be a name (oidn, gem, gaussian) or a factory(stats); "
                         f"got {type(denoiser).__name__}.")
    f = bind_denoiser(denoiser, stats)
    try:
        return denoising_aware_map(stats, f, budget, rng=rng, **options)
    finally:
        close = getattr(f, "close", None)
        if callable(close):
            close()


def denoising_aware_sampler(denoiser_factory="oidn", **options):
    """A sampler ``(stats, budget, rng) -> counts`` for :func:`statmc.adaptive.adaptive_render`.

    Parameters
    ----------
    denoiser_factory : str or callable
        ``"oidn"``, ``"gem"``, ``"gaussian"`` or ``factory(stats) -> denoiser``; rebuilt
        from the current statistics at every iteration.
    **options
        Of :func:`denoising_aware_density`.

    Examples
    --------
    >>> from statmc.adaptive import adaptive_render
    >>> from statmc.toy import ToyRenderer
    >>> r = ToyRenderer("mixed", width=16, height=16)
    >>> res = adaptive_render(r, 8, sampler=denoising_aware_sampler("gaussian"), iterations=2)
    >>> int(res.stats.n.sum())
    2048
    """
    if not isinstance(denoiser_factory, str) and not callable(denoiser_factory):
        raise InputError(f"`denoiser_factory` must be a name or a callable factory(stats); got "
                         f"{type(denoiser_factory).__name__}.")
    if isinstance(denoiser_factory, str) and denoiser_factory.lower() not in _NAMES:
        raise InputError(f"`denoiser_factory` must be one of {', '.join(_NAMES)} or a callable "
                         f"factory(stats); got {denoiser_factory!r}.")

    def _sampler(stats, budget, rng):
        return sampler(stats, budget, rng, denoiser=denoiser_factory, **options)

    return _sampler
