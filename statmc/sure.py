"""Error and variance estimates for denoised Monte Carlo renders.

Given a render ``x`` (pixel means, ``(H, W, C)``) whose per-pixel **variance of the
mean** ``Σ`` is known or estimated (``stats.mean_var``), and a denoiser ``f`` (any
callable ``f(color) -> color``, see :mod:`statmc.denoisers`), this module estimates,
without the ground truth ``μ``:

* the squared error of ``f(x)`` per pixel and over the image with Stein's unbiased risk
  estimate — exactly for kernel (linear) denoisers, :func:`sure`, and by Monte Carlo
  finite differences for black boxes such as OIDN, :func:`mc_sure` (Eq. 1 and 2 of
  Firmino et al. 2022 [1]_, after Ramani et al. 2008 [2]_);
* the variance of ``f(x)`` per pixel to first order, ``Σ_j (∂f_i/∂x_j)² σ_j²``, from
  Jacobian-vector products with random ``±σ`` vectors (Firmino et al. 2023 [3]_), by
  forward-mode autodiff for torch modules or finite differences for black boxes, and
  exactly for kernels, :func:`output_variance`, :func:`kernel_variance`;
* from two independent half renders, the double-buffer variance and error estimates
  of [3]_, :func:`double_buffer_estimates`.

``mean_var`` is either ``(H, W, C)`` — independent channels, a diagonal ``Σ`` as in §3.2
of [1]_ — or ``(H, W, C, C)``, a per-pixel channel covariance (pixels independent), which
renderers with a shared path throughput per sample produce.  MC-SURE and the variance
estimators draw their random vectors with exactly that covariance.

References
----------
.. [1] A. Firmino, J. R. Frisvad, H. W. Jensen. "Progressive Denoising of Monte Carlo
   Rendered Images". Computer Graphics Forum 41(2), 2022.
   https://doi.org/10.1111/cgf.14454
.. [2] S. Ramani, T. Blu, M. Unser. "Monte-Carlo SURE: A black-box optimization of
   regularization parameters for general denoising algorithms". IEEE TIP 17(9),
   1540–1554, 2008. https://doi.org/10.1109/TIP.2008.2001404
.. [3] A. Firmino, J. R. Frisvad, H. W. Jensen. "Denoising-Aware Adaptive Sampling for
   Monte Carlo Ray Tracing". SIGGRAPH 2023 Conference Proceedings.
   https://doi.org/10.1145/3588432.3591537
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .analytic import _numeric_kernels, apply_kernels
from .errors import (InputError, as_bool, as_float_array, as_int, as_number, as_rng,
                     check_finite, check_nonempty, check_nonnegative, check_overflow)
from .stats import check_stats

__all__ = ["sure", "mc_sure", "kernel_variance", "output_variance", "double_buffer_estimates",
           "DoubleBufferEstimates", "METHODS", "DEFAULT_EPS", "DEFAULT_VARIANCE_EPS", "DEFAULT_K"]

#: Finite-difference step ε of MC-SURE and of ``output_variance(method="fd")``: 1e-4 as in
#: Firmino 2022 §3.2 and Firmino 2023 ("AS with MC-SURE").  Relative to the image scale
#: by default (see :func:`mc_sure`).
DEFAULT_EPS = 1e-4
#: Finite-difference step of ``output_variance(method="fd")``: 1e-3 relative to the image
#: scale.  The variance squares the difference, so float32 rounding of the probe adds a
#: positive bias ``∝ 1/h²`` (measured on OIDN: +0.3–1.5 % at 1e-4, negligible at 1e-3, while
#: the first-order value changes by < 1 % between 1e-4 and 3e-3; ``bench/bench_sure.py``).
DEFAULT_VARIANCE_EPS = 1e-3
#: Monte Carlo iterations K of MC-SURE: 4 (Firmino 2023; Firmino 2022 uses 1 or 4).
DEFAULT_K = 4
#: Methods of :func:`output_variance`.
METHODS = ("fd", "jvp", "exact")


# =========================================================================== validation
def _image(x):
    arr = as_float_array("x", x, ndim=3, dtype=np.float64)
    check_nonempty("x", arr)
    check_finite("x", arr)
    return arr


_F32_MAX = float(np.finfo(np.float32).max)

#: The range named when a result overflows (:func:`statmc.errors.check_overflow`).
_SURE_RANGE = ("the squared residuals (f(x) − x)² and 2·(J Σ)_ii below 1.8e308, i.e. "
               "|x| below about 1e154 and `mean_var` below about 1e308")
_VARIANCE_RANGE = ("(J v)² below 1.8e308 for the ±σ probes v, i.e. `mean_var` below "
                   "about 1e308 (times the denoiser's gain squared)")


def _mean(a) -> float:
    """``float(a.mean())``, also where the sum overflows although the mean does not
    (entries near 1.8e308): then the mean of ``a·2⁻⁶⁴`` times ``2⁶⁴`` (scaling by a power
    of two is exact).  Unchanged, to the bit, wherever the plain mean is finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        m = float(np.mean(a))
    if not np.isfinite(m):
        with np.errstate(over="ignore", invalid="ignore"):
            m = float(np.ldexp(np.mean(np.ldexp(a, -64)), 64))
    return m


def _check_float32(name, x):
    """The denoiser protocol passes float32 images: larger values became Inf on the way
    (reported as a non-finite `color`), so say what the caller can do."""
    m = float(np.abs(x).max())
    if m > _F32_MAX:
        raise InputError(f"`{name}` holds values up to {m:.3g} in magnitude, beyond float32's "
                         f"range ({_F32_MAX:.3g}); denoisers are called on float32 images. "
                         f"Rescale `{name}` (and its variance by the square of the factor).")


def _probe(x, h, b, eps):
    """The float32 probe ``x + h b``, refused naming ``eps`` where the step throws it out
    of float32's range (the denoiser would see Inf and blame its `color`)."""
    p = x + h * b
    m = float(np.abs(p).max())
    if m > _F32_MAX:
        raise InputError(f"`eps`={eps!r} moves the probe x + h·b to {m:.3g}, beyond float32's "
                         f"range ({_F32_MAX:.3g}) in which denoisers are called; use a small "
                         f"step such as the default ({DEFAULT_EPS:g} for mc_sure, "
                         f"{DEFAULT_VARIANCE_EPS:g} for output_variance).")
    return p.astype(np.float32)


class _Noise:
    """The covariance of ``x``: diagonal ``(H, W, C)`` or per-pixel ``(H, W, C, C)``."""

    def __init__(self, mean_var, shape):
        v = as_float_array("mean_var", mean_var, ndim=(3, 4), dtype=np.float64)
        check_nonempty("mean_var", v)
        cov_shape = tuple(shape) + (shape[2],)
        if v.shape not in (tuple(shape), cov_shape):
            raise InputError(
                f"`mean_var` must be the variance of the mean with the shape of `x` {tuple(shape)} "
                f"(or a per-pixel channel covariance {cov_shape}); got {v.shape}.")
        check_finite("mean_var", v)
        if v.ndim == 3:
            check_nonnegative("mean_var", v)
            self.diag, self.root = v, None
            self._sd = np.sqrt(v)
            return
        if not np.allclose(v, np.swapaxes(v, -1, -2), rtol=1e-6, atol=0.0):
            raise InputError("`mean_var` given as a covariance (H, W, C, C) must be symmetric in "
                             "its last two axes; got an asymmetric one.")
        lam, q = np.linalg.eigh(v)
        # Per pixel, relative to its largest eigenvalue: covariances estimated from samples
        # and stored as float32 (EXR) are PSD only up to float32 rounding (~1e-7 relative),
        # whatever dtype they are handed over in.
        tol = 1e-5 * np.abs(lam).max(axis=-1, keepdims=True) + np.finfo(float).tiny
        if (lam < -tol).any():
            n = int((lam < -tol).any(axis=-1).sum())
            raise InputError(f"`mean_var` given as a covariance must be positive semi-definite; "
                             f"{n} pixels have negative eigenvalues (min {lam.min():.4g}).")
        self.diag = np.ascontiguousarray(np.diagonal(v, axis1=-2, axis2=-1))
        self.root = q * np.sqrt(np.clip(lam, 0.0, None))[..., None, :]   # Σ = R Rᵀ
        self._sd = None

    def apply(self, z):
        """``R z`` per pixel: turns unit-covariance ``z`` into covariance ``Σ``."""
        if self.root is None:
            return self._sd * z
        return np.einsum("hwij,hwj->hwi", self.root, z)

    @property
    def rms(self) -> float:
        return float(np.sqrt(_mean(self.diag)))


def _call(denoiser, x32):
    """``denoiser(x32)`` as float64, checked to be a finite image shaped like the input."""
    return _checked_output(denoiser(x32), x32.shape)


def _checked_output(out, shape):
    try:
        arr = np.asarray(out, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"`denoiser` must return a numeric (H, W, C) array; got "
                         f"{type(out).__name__}.") from exc
    if arr.shape != shape:
        raise InputError(f"`denoiser` must return an image shaped like its input {shape}; "
                         f"got {arr.shape}.")
    if not np.isfinite(arr).all():
        raise InputError(f"`denoiser` returned {int((~np.isfinite(arr)).sum())} NaN/Inf values "
                         "for a finite input.")
    return arr


def _check_denoiser(denoiser):
    from .denoisers import as_denoiser

    return as_denoiser(denoiser)


def _step(eps, relative, x, noise):
    """Finite-difference step ``h`` so that the perturbation ``h·b`` is as documented."""
    s_b = noise.rms
    if s_b == 0.0:
        return None
    if not relative:
        return eps
    s_x = float(np.sqrt(np.mean(x * x)))
    return eps * (s_x if s_x > 0 else s_b) / s_b


def _kernels_of(kernels, shape):
    if hasattr(kernels, "kernels") and callable(kernels.kernels):
        return kernels.kernels(shape)
    if callable(kernels) and not isinstance(kernels, np.ndarray):
        # a GEM, OIDN or user denoiser: not a fixed linear filter (was "dtype object")
        raise InputError(f"`kernels` must be an (H, W, k, k) array or a kernel denoiser with a "
                         f"`kernels(shape)` method (e.g. statmc.denoisers.gaussian); got "
                         f"{type(kernels).__name__}. For any other denoiser use mc_sure / "
                         "output_variance.")
    return kernels


# =========================================================================== SURE
def sure(kernels, x, mean_var, *, extra_output: bool = False):
    """Exact per-pixel SURE of a kernel (linear) denoiser, Eq. 1 of [1]_.

    Parameters
    ----------
    kernels : (H, W, k, k) ndarray, or a denoiser with a ``kernels(shape)`` method
        Per-pixel kernels in the convention of :func:`statmc.analytic.apply_kernels`
        (``f(x)_i = Σ_q K[i, q] x_{i+q−r}``, same weights for every channel), fixed
        independently of ``x`` (e.g. :func:`statmc.denoisers.gaussian`).
    x : (H, W, C) ndarray
        Noisy pixel means.
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        **Variance of the mean** ``σ_i²`` of ``x`` (or the per-pixel channel covariance,
        of which only the diagonal matters here because the kernels act per channel).
    extra_output : bool
        Also return a dict with ``denoised`` (``f(x)``), ``divergence``
        (``(J Σ)_ii = K[i, r, r]·σ_i²``) and ``mse`` (the image-level SURE, Eq. 1).

    Returns
    -------
    sure_map : (H, W, C) float64 ndarray
        ``(f(x)_i − x_i)² + 2 K[i, r, r] σ_i² − σ_i²``: the terms of Eq. 1 of [1]_ per
        pixel and channel, whose expectation is the pixel's MSE ``E[(f(x)_i − μ_i)²]``
        when ``x`` is normal with covariance ``Σ``; its mean over all entries is
        Eq. 1 itself (``(1/d)(‖f(x) − x‖² + 2 tr(J Σ) − tr(Σ))``).

    Notes
    -----
    For ``f(x) = K x`` the Jacobian is ``K`` itself, so ``(J Σ)_ii`` is the centre weight
    of pixel ``i``'s kernel times ``σ_i²`` — no Monte Carlo needed.  Unbiased for any
    noise law with the given variance, not only the normal one, because ``f`` is linear
    (``E[(x_i − μ_i) f(x)_i] = K_ii σ_i²``).

    Terms beyond float64's range (``|x|`` above ~1e154) raise
    :class:`~statmc.errors.InputError` instead of coming back as Inf/NaN; ``mse`` is
    exact also where the sum of the terms would overflow.

    Examples
    --------
    >>> from statmc.denoisers import gaussian
    >>> rng = np.random.default_rng(0)
    >>> mu = np.full((16, 16, 3), 0.5)
    >>> var = np.full_like(mu, 0.01)
    >>> x = mu + rng.normal(0, 0.1, mu.shape)
    >>> s = sure(gaussian(sigma=1.0), x, var)
    >>> s.shape
    (16, 16, 3)
    """
    extra_output = as_bool("extra_output", extra_output)
    xx = _image(x)
    noise = _Noise(mean_var, xx.shape)
    K = _kernels_of(kernels, xx.shape)
    fx = apply_kernels(K, xx)   # validates the kernels and their shape
    K = np.asarray(K)
    r = K.shape[2] // 2
    with np.errstate(over="ignore", invalid="ignore"):     # checked just below
        div = K[:, :, r, r].astype(np.float64)[..., None] * noise.diag
        out = (fx - xx) ** 2 + 2.0 * div - noise.diag
    check_overflow(out, "the SURE map", {"kernels": K, "x": xx, "mean_var": noise.diag},
                   _SURE_RANGE)
    if extra_output:
        return out, {"denoised": fx, "divergence": div, "mse": _mean(out)}
    return out


def mc_sure(denoiser, x, mean_var, *, eps: float = DEFAULT_EPS, k: int = DEFAULT_K, rng=None,
            relative: bool = True, extra_output: bool = False):
    """Per-pixel Monte Carlo SURE of any (black-box) denoiser, Eq. 1 with Eq. 2 of [1]_.

    Parameters
    ----------
    denoiser : callable ``f(color) -> color``
        Deterministic; called on ``(H, W, C)`` float32 arrays exactly ``k + 1`` times
        (once on ``x``, once per probe).  A name or torch module is accepted too
        (:func:`statmc.denoisers.as_denoiser`).
    x : (H, W, C) ndarray
        Noisy pixel means.
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        **Variance of the mean** of ``x`` (diagonal ``Σ``), or the per-pixel channel
        covariance.
    eps : float
        Finite-difference step ε (default 1e-4, as in [1]_ §3.2).
    k : int
        Monte Carlo iterations K (default 4).
    rng : numpy Generator or seed, optional
    relative : bool
        ``True`` (default): ε is relative to the image scale — the probe ``x + h b_k``
        uses ``h = ε·rms(x)/rms(σ)``, so the perturbation's RMS is ``ε·rms(x)`` whatever
        the noise level.  ``False``: the literal ``x + ε b_k`` of Eq. 2.
    extra_output : bool
        Also return a dict with ``denoised`` (``f(x)``, float64), ``divergence`` (the
        per-pixel estimate of ``(J Σ)_ii``), ``mse`` (image-level SURE, Eq. 1), ``step``
        (``h``) and ``calls`` (denoiser calls made).

    Returns
    -------
    sure_map : (H, W, C) float64 ndarray
        ``(f(x)_i − x_i)² + 2 D_i − σ_i²`` with the Monte Carlo divergence
        ``D_i = (1/(h K)) Σ_k b_{k,i} (f(x + h b_k) − f(x))_i``, ``b_k ~ N(0, Σ)``: the
        per-pixel terms of Eq. 1 with the trace replaced by Eq. 2 of [1]_ (the per-pixel
        form of the 2023 paper's "AS with MC-SURE").  ``E[D_i] = (J Σ)_ii`` to first order
        in ``h``, so the map is an unbiased estimate of each pixel's MSE, and its mean
        over the image of the image's MSE, when ``x`` is normal with covariance ``Σ``.

    Notes
    -----
    Cost: ``k + 1`` denoiser calls plus ``O(pixels)`` NumPy work.  Per-pixel values are
    very noisy (Fig. 3 of [1]_): average them locally or over the image.

    Choice of ε.  The divergence only needs ``f(x + h b) − f(x) ≈ h J b``: ``h`` must be
    small against the scale on which ``f`` bends but large against float32 rounding of
    the probe (the protocol passes float32 images; one ulp is ``6e-8`` relative).  With
    the literal ``ε b_k`` the perturbation is ``ε σ``, which shrinks with the noise: at
    high sample counts it falls to a few ulps and the estimate drowns in rounding.  The
    default therefore scales it to the image, ``ε·rms(x) = 1e-4·rms(x)`` (about 800 ulps
    at the RMS level).  For OIDN (HDR, nonlinear) the divergence measured on a 32×32 toy
    render is flat within its Monte Carlo noise for relative steps from 1e-2 to 1e-5 and
    noisy at 1e-6 (``bench/bench_sure.py`` repeats the scan), so 1e-4 sits well inside.
    Pixels so bright, relative to their own noise, that ``h σ_i`` falls below one ulp of
    ``x_i`` cannot be probed in float32; their ``σ_i²`` is tiny, so their SURE is
    essentially the data term.

    Covariance.  With a diagonal ``mean_var`` SURE ignores channel correlation, like
    [1]_ §3.2 ("no impact at high sample counts"); a denoiser that mixes channels (OIDN
    does) then gets a biased divergence when the channels are correlated.  Pass the
    per-pixel channel covariance to remove that bias.

    Examples
    --------
    >>> from statmc.denoisers import gaussian
    >>> rng = np.random.default_rng(0)
    >>> x = 0.5 + rng.normal(0, 0.1, (16, 16, 3))
    >>> var = np.full_like(x, 0.01)
    >>> s = mc_sure(gaussian(sigma=1.0), x, var, rng=1)
    >>> bool(abs(s.mean() - sure(gaussian(sigma=1.0), x, var).mean()) < 2e-3)
    True
    """
    xx = _image(x)
    noise = _Noise(mean_var, xx.shape)
    eps = as_number("eps", eps, lo=0.0, lo_open=True)
    relative = as_bool("relative", relative)
    k = as_int("k", k)
    extra_output = as_bool("extra_output", extra_output)
    f = _check_denoiser(denoiser)
    gen = as_rng(rng)
    _check_float32("x", xx)
    fx = _call(f, xx.astype(np.float32))
    calls = 1
    h = _step(eps, relative, xx, noise)
    div = np.zeros_like(xx)
    if h is not None:
        for _ in range(k):
            b = noise.apply(gen.standard_normal(xx.shape))
            fp = _call(f, _probe(xx, h, b, eps))
            calls += 1
            fp -= fx
            fp *= b
            div += fp
        div /= h * k
    with np.errstate(over="ignore", invalid="ignore"):     # checked just below
        out = (fx - xx) ** 2 + 2.0 * div - noise.diag
    check_overflow(out, "the MC-SURE map", {"x": xx, "mean_var": noise.diag}, _SURE_RANGE)
    if extra_output:
        return out, {"denoised": fx, "divergence": div, "mse": _mean(out),
                     "step": h, "calls": calls}
    return out


# =========================================================================== variance
def kernel_variance(kernels, mean_var):
    """Exact variance of a kernel denoiser's output: ``Var[f(x)_i] = Σ_j K_ij² σ_j²``.

    Parameters
    ----------
    kernels : (H, W, k, k) ndarray, or a denoiser with a ``kernels(shape)`` method
        Per-pixel kernels (convention of :func:`statmc.analytic.apply_kernels`).
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        **Variance of the mean** of the input (covariance: only its diagonal matters,
        the kernels act per channel).

    Returns
    -------
    var : (H, W, C) float64 ndarray
        The first-order formula of Firmino et al. 2023 [3]_ (§"Deep NN Variance
        Estimate", ``Σ_j |∂f_i/∂x_j|² σ_j²``), exact here because ``f`` is linear and the
        pixels are independent (also Lemma A.1 of Salehi et al. 2022).
    """
    mv = as_float_array("mean_var", mean_var, ndim=(3, 4), dtype=np.float64)
    shape = mv.shape[:3]
    noise = _Noise(mv, shape)
    # complex (np.square kept it complex) and string kernels raised numpy's UFuncTypeError
    K = _numeric_kernels(_kernels_of(kernels, shape))
    if K.ndim != 4:
        raise InputError(f"`kernels` must have shape (H, W, k, k); got {K.shape}.")
    return apply_kernels(np.square(K, dtype=np.float64), noise.diag)


def output_variance(denoiser, x, mean_var, *, k: int = 16, method: str = "fd", rng=None,
                    eps: float = DEFAULT_VARIANCE_EPS, relative: bool = True,
                    extra_output: bool = False):
    """Per-pixel variance of ``denoiser(x)`` to first order (Firmino et al. 2023 [3]_).

    Parameters
    ----------
    denoiser : callable ``f(color) -> color``, torch module, or name
        See :mod:`statmc.denoisers`.
    x : (H, W, C) ndarray
        Noisy pixel means at which ``f`` is linearised.
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        **Variance of the mean** of ``x`` (or the per-pixel channel covariance).
    k : int
        Random vectors (default 16); ``fd`` costs ``k + 1`` denoiser calls, ``jvp``
        ``k`` forward-mode passes.
    method : {"fd", "jvp", "exact"}
        ``"fd"``: forward finite differences ``(f(x + h v) − f(x))/h`` (any black box);
        ``"jvp"``: ``J v`` by forward-mode autodiff (torch modules, via
        :meth:`statmc.denoisers.TorchDenoiser.jvp`); ``"exact"``: a denoiser with
        ``kernels(shape)`` (:func:`kernel_variance`).
    rng : numpy Generator or seed, optional
    eps, relative : float, bool
        Finite-difference step as in :func:`mc_sure` (``fd`` only), by default
        :data:`DEFAULT_VARIANCE_EPS` = 1e-3 relative to the image scale: unlike the
        divergence of MC-SURE, which is linear in ``f(x + h v) − f(x)`` so that rounding
        only adds noise, the variance squares it, so rounding adds a positive bias
        ``∝ 1/h²`` that a larger step keeps negligible.
    extra_output : bool
        Also return a dict with ``denoised`` (``f(x)``), ``std_error`` (per-pixel standard
        error of the ``k``-vector mean), ``step`` and ``calls``.

    Returns
    -------
    var : (H, W, C) float64 ndarray
        ``(1/k) Σ_k ((J v_k)_i)²`` with ``v_{k,j} = ±σ_j`` independent fair signs
        (per-pixel ``v = R s``, ``R Rᵀ = Σ``, for a channel covariance).  Its expectation
        is ``Σ_j (∂f_i/∂x_j)² σ_j²`` (``(J Σ Jᵀ)_ii`` with covariance), the first-order
        variance of ``f_i(x)`` — the derivation of §"Deep NN Variance Estimate" of [3]_.

    Notes
    -----
    First order: exact for linear denoisers, and accurate for nonlinear ones while the
    noise is small against the scale on which ``f`` bends.  ``J`` is taken at the noisy
    ``x``, not at the unknown mean.  For OIDN on the toy renderer the first-order value
    exceeds the empirical variance of the output over renders by about 20 %: its
    response flattens over the noise scale.  A central difference does not change that
    (1.203 against 1.205 at the same step: it is not a truncation error); ``eps=1,
    relative=False`` (forward steps of exactly ``±σ``, a secant rather than a tangent)
    matched the empirical variance (0.99 at 16 spp, z = −0.4; 1.00 at 64 spp); see
    ``docs/error-estimates.md``.
    """
    if method not in METHODS:
        raise InputError(f"`method` must be one of {', '.join(METHODS)}; got {method!r}.")
    xx = _image(x)
    noise = _Noise(mean_var, xx.shape)
    k = as_int("k", k)
    relative = as_bool("relative", relative)
    extra_output = as_bool("extra_output", extra_output)
    f = _check_denoiser(denoiser)
    if method == "exact":
        if not callable(getattr(f, "kernels", None)):
            raise InputError("`method`='exact' needs a kernel denoiser with a `kernels(shape)` "
                             f"method (e.g. statmc.denoisers.gaussian); got {f!r}.")
        var = kernel_variance(f.kernels(xx.shape), noise.diag)
        if extra_output:
            return var, {"denoised": None, "std_error": np.zeros_like(var), "step": None, "calls": 0}
        return var
    if method == "jvp" and not callable(getattr(f, "jvp", None)):
        raise InputError("`method`='jvp' needs a torch module or statmc.denoisers.torch_module(...) "
                         f"(a denoiser with a `jvp(color, tangent)` method); got {f!r}.")
    gen = as_rng(rng)
    _check_float32("x", xx)
    x32 = xx.astype(np.float32)
    acc = np.zeros_like(xx)
    acc2 = np.zeros_like(xx)
    h = None
    fx = None
    calls = 0
    if method == "fd":
        fx = _call(f, x32)
        calls = 1
        h = _step(as_number("eps", eps, lo=0.0, lo_open=True), relative, xx, noise)
    if noise.rms > 0.0 and (method == "jvp" or h is not None):
        # The standard error squares (J v)² once more: beyond σ ~ 1e77 that overflowed
        # (and the sum of k values (J v)² beyond 1.8e308/k).  When the σ are that large,
        # accumulate (J v)²·c² instead, c a power of two (exact scaling).
        top = float(np.sqrt(np.max(noise.diag)))
        c2 = np.ldexp(1.0, -2 * int(np.frexp(top)[1])) if top > 2.0 ** 128 else 1.0
        for _ in range(k):
            v = noise.apply(gen.integers(0, 2, xx.shape) * 2.0 - 1.0)
            if method == "fd":
                jv = (_call(f, _probe(xx, h, v, eps)) - fx) / h
            else:
                y, jv = f.jvp(x32, v.astype(np.float32))
                jv = _checked_output(jv, xx.shape)
                if fx is None:
                    fx = _checked_output(y, xx.shape)
            calls += 1
            jv *= jv
            if c2 != 1.0:
                jv *= c2
            acc += jv
            acc2 += jv * jv
        var = acc / k
        se = np.sqrt(np.clip(acc2 / k - var * var, 0.0, None) / max(k - 1, 1))
        if c2 != 1.0:
            var /= c2
            se /= c2
        given = {"x": xx, "mean_var": noise.diag}
        check_overflow(var, "the output variance", given, _VARIANCE_RANGE)
        check_overflow(se, "the standard error of the output variance", given, _VARIANCE_RANGE)
    else:
        var = np.zeros_like(xx)
        se = np.zeros_like(xx)
        if fx is None:
            fx = _call(f, x32)
            calls += 1
    if extra_output:
        return var, {"denoised": fx, "std_error": se, "step": h, "calls": calls}
    return var


# =========================================================================== double buffer
@dataclass(frozen=True)
class DoubleBufferEstimates:
    """Estimates from two independent half renders ``a`` and ``b`` (Firmino et al. 2023).

    All arrays are ``(H, W, C)`` float64.

    Attributes
    ----------
    mean : merged render ``x = (n_a x_a + n_b x_b)/(n_a + n_b)``.
    mean_var : **variance of the mean** of ``x`` from the buffer difference,
        ``(x_a − x_b)² n_a n_b/(n_a + n_b)²`` (``¼ (x_a − x_b)²`` for equal halves);
        unbiased when both halves sample the same per-sample law.
    denoised_a, denoised_b : ``f(x_a)`` and ``f(x_b)``.
    denoised_var : ``½ (f(x_a) − f(x_b))²``, the double-buffer variance estimate of
        ``Var[f(x_half)]`` — the variance of the denoiser applied to *one half* — unbiased
        when the halves are identically distributed (equal sample counts).
    denoised_mse_a : ``(f(x_a) − x_b)² − σ̂_b²`` estimates ``E[(f(x_a) − μ)²]``.
    denoised_mse_b : ``(f(x_b) − x_a)² − σ̂_a²`` estimates ``E[(f(x_b) − μ)²]``.
    denoised_mse : ``½ (denoised_mse_a + denoised_mse_b)``, the double-buffer error
        estimate, unbiased for the mean of the two half-buffer MSEs.
    """

    mean: np.ndarray
    mean_var: np.ndarray
    denoised_a: np.ndarray
    denoised_b: np.ndarray
    denoised_var: np.ndarray
    denoised_mse_a: np.ndarray
    denoised_mse_b: np.ndarray
    denoised_mse: np.ndarray


def double_buffer_estimates(stats_a, stats_b, denoiser) -> DoubleBufferEstimates:
    """Double-buffer variance and error estimates of a denoiser (Firmino et al. 2023 [3]_).

    Parameters
    ----------
    stats_a, stats_b : PixelStats
        Two **independent** renders of the same image (e.g. two seeds), each with at
        least 2 samples in every pixel (for the within-buffer variance of the mean
        ``σ̂² = stats.mean_var``).
    denoiser : callable ``f(color) -> color``, or a pair ``(f_a, f_b)``
        Applied to ``x_a = stats_a.mean`` and ``x_b = stats_b.mean``.  Give a pair when
        the denoiser binds buffer-specific inputs, e.g. GEM with each half's
        ``mean_var``: ``(denoisers.gem(a.mean_var), denoisers.gem(b.mean_var))``.

    Returns
    -------
    DoubleBufferEstimates

    Notes
    -----
    §"Double-Buffer" of [3]_: ``Var[f_i(x)] = ½ E[(f_i(x_a) − f_i(x_b))²]`` and
    ``E[(f_i(x) − μ_i)²] = E[½((f_i(x_a) − x_{b,i})² − σ̂_{b,i}² + (f_i(x_b) − x_{a,i})²
    − σ̂_{a,i}²)]``, where ``x`` stands for a half buffer.  The error identity only needs
    ``x_b`` unbiased and independent of ``x_a`` (``E[(f(x_a) − x_b)²] = E[(f(x_a) − μ)²]
    + Var[x_b]``), so it holds for any denoiser and any noise law; neither estimate says
    anything directly about ``f`` of the merged buffer.
    """
    for name, s in (("stats_a", stats_a), ("stats_b", stats_b)):
        check_stats(s, name)
    if stats_a.mean.shape != stats_b.mean.shape:
        raise InputError(f"`stats_b` must have the shape of `stats_a` {stats_a.mean.shape}; "
                         f"got {stats_b.mean.shape}.")
    for name, s in (("stats_a", stats_a), ("stats_b", stats_b)):
        s.require_variance(name)
    if isinstance(denoiser, (tuple, list)):
        if len(denoiser) != 2:
            raise InputError(f"`denoiser` must be a callable or a pair (f_a, f_b); got "
                             f"{len(denoiser)} items.")
        f_a, f_b = (_check_denoiser(d) for d in denoiser)
    else:
        f_a = f_b = _check_denoiser(denoiser)
    xa, xb = stats_a.mean, stats_b.mean
    va, vb = stats_a.mean_var, stats_b.mean_var
    na = stats_a.n[..., None].astype(np.float64)
    nb = stats_b.n[..., None].astype(np.float64)
    n = na + nb
    _check_float32("stats_a.mean", xa)
    _check_float32("stats_b.mean", xb)
    fa = _call(f_a, xa.astype(np.float32))
    fb = _call(f_b, xb.astype(np.float32))
    mse_a = (fa - xb) ** 2 - vb
    mse_b = (fb - xa) ** 2 - va
    return DoubleBufferEstimates(
        mean=(na * xa + nb * xb) / n,
        mean_var=(xa - xb) ** 2 * na * nb / (n * n),
        denoised_a=fa, denoised_b=fb,
        denoised_var=0.5 * (fa - fb) ** 2,
        denoised_mse_a=mse_a, denoised_mse_b=mse_b,
        denoised_mse=0.5 * (mse_a + mse_b),
    )
