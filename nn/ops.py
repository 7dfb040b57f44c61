"""Differentiable torch twins of the statmc kernels the networks feed.

Each function equals its statmc counterpart on the same numbers (tests/test_nn.py checks
this in float64 on random inputs, borders included, and runs ``torch.autograd.gradcheck``):

=====================  ===========================================  ==========================
function               statmc counterpart                            formula
=====================  ===========================================  ==========================
:func:`apply_kernels`  :func:`statmc.analytic.apply_kernels`          ``D(X)_p = Σ_q K_pq X_q``
                                                                     (§A.1 of Salehi 2022 [2]_)
:func:`combine`        :func:`statmc.combine.combine`                Eq. 8 of Back 2020 [1]_
:func:`combine_multi`  :func:`statmc.combine.combine_multi`          Eq. 14 of Back 2020 [1]_
=====================  ===========================================  ==========================

Layout (see :mod:`statmc.nn.layout` for the conversions): images ``(N, C, H, W)``;
kernels ``(N, k·k, H, W)`` with tap ``t = dy·k + dx`` reading the neighbour
``(y + dy − r, x + dx − r)``, ``r = k // 2``, odd ``k``; combination weights
``(N, B, k·k, H, W)``; sample bins ``(N, B, C, H, W)``.  Taps outside the image are dropped
(they read zeros), exactly as in statmc: :func:`apply_kernels` does not renormalise, the
combination kernels divide by ``W_c``, the sum of the weights of the taps *inside* the
image (the border renormalisation of docs/combine.md).  Weights must be finite everywhere,
outside taps included (``0 · inf`` is NaN in torch); :mod:`statmc.nn.nets` produces
softmax weights, which are.

Input checks (:class:`~statmc.errors.InputError` naming the parameter): tensors of the
documented rank, floating point, of **one dtype on one device** (torch would silently
promote float32 to float64, or fail deep inside on a device mismatch) and non-empty
images, before any arithmetic; finite values, and for the combination kernels a finite,
nonzero ``W_c`` at every pixel (statmc refuses the same; torch would return Inf/NaN),
before the result is returned.  A NaN or Inf in any input always reaches the result, so
the result is checked and the inputs are searched only when it is not finite.  The value
checks read one boolean each; they are skipped under :func:`torch.func.vmap`, which
cannot branch on values (the ops still work there).

Each function has a thin :class:`torch.nn.Module` (:class:`ApplyKernels`,
:class:`Combine`, :class:`CombineMulti`) whose ``forward`` calls it.

References
----------
.. [1] J. Back, B.-S. Hua, T. Hachisuka, B. Moon. "Deep Combiner for Independent and
   Correlated Pixel Estimates". ACM Trans. Graph. 39(6), 242, 2020.
   https://doi.org/10.1145/3414685.3417847
.. [2] F. Salehi, M. Manzi, G. Roethlin, R. Weber, C. Schroers, M. Papas. "Deep Adaptive
   Sampling and Reconstruction using Analytic Distributions". ACM Trans. Graph. 41(6),
   259, 2022. https://doi.org/10.1145/3550454.3555515
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

import numbers

from statmc.errors import InputError, as_int

__all__ = ["apply_kernels", "combine", "combine_multi", "ApplyKernels", "Combine",
           "CombineMulti", "kernel_size", "check_tensor", "check_finite_tensor", "check_like",
           "torch_seed"]

#: Largest seed :func:`torch.manual_seed` takes (it raised a bare ValueError "Overflow when
#: unpacking long long" beyond).
MAX_TORCH_SEED = 2 ** 64 - 1


def torch_seed(name, seed):
    """``seed`` as an int for :func:`torch.manual_seed`, in ``[0, 2**64 − 1]``
    (``InputError`` naming ``name`` otherwise).  Negative seeds are refused as
    :func:`statmc.errors.as_rng` refuses them (torch would remap them to ``2**64 − 1 + seed``)."""
    seed = as_int(name, seed, lo=0)
    if seed > MAX_TORCH_SEED:
        raise InputError(f"`{name}` must be <= 2**64 - 1 (torch.manual_seed's range); got {seed!r}.")
    return seed


def check_tensor(name, t, ndim, what):
    """``InputError`` unless ``t`` is a floating-point tensor with ``ndim`` dimensions."""
    if not isinstance(t, torch.Tensor):
        raise InputError(f"`{name}` must be a torch.Tensor {what}; got {type(t).__name__}.")
    if t.ndim != ndim:
        raise InputError(f"`{name}` must be {what}; got shape {tuple(t.shape)}.")
    if not t.is_floating_point():
        raise InputError(f"`{name}` must be a floating-point tensor; got {t.dtype}.")


def _readable(cond):
    """``bool(cond)`` of a one-element bool tensor, or None where torch cannot branch on a
    value: under :func:`torch.func.vmap` (data-dependent control flow is refused there)
    and on the ``meta`` device.  The value checks are skipped there, nowhere else."""
    try:
        return bool(cond)
    except RuntimeError:
        return None


def check_finite_tensor(name, t):
    """``InputError`` when ``t`` holds NaN or Inf, saying how many (as
    :func:`statmc.errors.check_finite` does for arrays)."""
    if _readable(torch.isfinite(t).all()) is False:
        n_nan, n_inf = int(torch.isnan(t).sum()), int(torch.isinf(t).sum())
        raise InputError(f"`{name}` holds {n_nan} NaN and {n_inf} Inf values; expected "
                         "finite numbers.")


def check_like(name, t, ref_name, ref):
    """``InputError`` unless ``t`` has the dtype and device of ``ref`` (torch would promote
    the dtype silently, or fail deep inside with a device error)."""
    if t.dtype != ref.dtype:
        raise InputError(f"`{name}` has dtype {t.dtype} but `{ref_name}` has {ref.dtype}; "
                         f"give tensors of one dtype (e.g. `{name}.to({ref_name}.dtype)`).")
    if t.device != ref.device:
        raise InputError(f"`{name}` is on device {t.device} but `{ref_name}` is on "
                         f"{ref.device}; give tensors on one device (e.g. "
                         f"`{name}.to({ref_name}.device)`).")


def _finite_result(out, inputs):
    """``out``, after checking it is finite; if not, name the input that holds NaN or Inf.

    A NaN or Inf anywhere in the inputs always reaches the result (an outside tap
    multiplies its weight by zero, and ``0 · inf`` is NaN), so one pass over the result
    replaces a pass over every input; the inputs are searched only on failure."""
    if _readable(torch.isfinite(out).all()) is False:
        for name, t in inputs:
            check_finite_tensor(name, t)
        n_bad = int((~torch.isfinite(out)).sum())
        raise InputError(
            f"`{inputs[0][0]}`: the result holds {n_bad} non-finite values although every "
            f"input is finite: {out.dtype} overflowed.  Use float32 or float64, or rescale "
            "the inputs.")
    return out


def _finite_weights(wsum, weights):
    """NaN/Inf anywhere in ``weights`` (outside taps included: ``0 · inf`` is NaN) makes
    their sums ``wsum`` non-finite: one pass over the sums, ``weights`` searched on failure."""
    if _readable(torch.isfinite(wsum).all()) is False:
        check_finite_tensor("weights", weights)


def _nonempty(name, t, dims):
    if any(t.shape[i] == 0 for i in dims):
        raise InputError(f"`{name}` is empty: it needs at least one channel, row and column "
                         f"(and bin); got shape {tuple(t.shape)}.")


def _check_weight_sums(wsum):
    """``InputError`` unless every pixel's ``W_c`` (``(N, 1, H, W)``) is finite and nonzero,
    as :func:`statmc.combine.combine` requires (it divides by it)."""
    bad = ~(torch.isfinite(wsum) & (wsum != 0))
    if _readable(bad.any()):
        n, _, y, x = (int(i) for i in bad.nonzero()[0])
        raise InputError(
            f"`weights` must sum to a finite, nonzero W_c over the taps inside the image at "
            f"every pixel; {int(bad.sum())} pixel(s) fail, the first at (image {n}, row {y}, "
            f"column {x}) with W_c = {float(wsum[n, 0, y, x]):.4g}.  Use positive weights "
            "(e.g. a softmax or exp of network outputs).")


def kernel_size(taps: int, name: str = "kernels") -> int:
    """Odd window side ``k`` of a tap axis of length ``k·k`` (``InputError`` otherwise)."""
    ok = isinstance(taps, numbers.Integral) and not isinstance(taps, bool) and taps >= 0
    k = int(round(taps ** 0.5)) if ok else 0     # -9 ** 0.5 is complex, "9" ** 0.5 a TypeError
    if k * k != taps or k % 2 == 0:
        raise InputError(f"`{name}` must hold k·k taps with odd k on its tap axis (9, 25, 49, "
                         f"...); got {taps}.")
    return k


def _same_grid(name, t, ref_name, ref, dims):
    if tuple(t.shape[i] for i in dims) != tuple(ref.shape[i] for i in dims):
        raise InputError(f"`{name}` {tuple(t.shape)} does not match `{ref_name}` "
                         f"{tuple(ref.shape)} on axes {dims} (batch and H, W must agree).")


def _apply(kernels, image, k):
    """``(M, k·k, H, W)`` kernels on ``(M, C, H, W)`` images, zero outside the image."""
    M, C, H, W = image.shape
    patches = F.unfold(image, k, padding=k // 2).view(M, C, k * k, H, W)
    return (patches * kernels[:, None]).sum(dim=2)


def apply_kernels(kernels, image):
    """Apply per-pixel kernels to images (torch twin of :func:`statmc.analytic.apply_kernels`).

    Parameters
    ----------
    kernels : (N, k·k, H, W) tensor
        One ``k x k`` kernel per output pixel, odd ``k``, tap ``dy·k + dx``.
    image : (N, C, H, W) tensor

    Returns
    -------
    out : (N, C, H, W) tensor
        ``out[n, c, y, x] = Σ_{dy,dx} K[n, dy·k+dx, y, x] · image[n, c, y+dy−r, x+dx−r]``,
        taps outside the image dropped, no renormalisation: the kernel denoiser
        ``D(X)_p = Σ_q K_pq X_q`` of §A.1 of [2]_ (Lemma A.1 needs ``K`` independent of
        the samples it is applied to).

    Examples
    --------
    >>> import torch
    >>> K = torch.zeros(1, 9, 2, 3); K[:, 4] = 1.0          # identity: centre tap only
    >>> img = torch.arange(6.0).view(1, 1, 2, 3)
    >>> bool(torch.equal(apply_kernels(K, img), img))
    True
    """
    check_tensor("kernels", kernels, 4, "(N, k·k, H, W)")
    check_tensor("image", image, 4, "(N, C, H, W)")
    check_like("image", image, "kernels", kernels)
    _nonempty("image", image, (1, 2, 3))
    _same_grid("kernels", kernels, "image", image, (0, 2, 3))
    k = kernel_size(kernels.shape[1])
    return _finite_result(_apply(kernels, image, k), (("kernels", kernels), ("image", image)))


def combine(y, z, weights):
    """Combination kernel, Eq. 8 of [1]_ (torch twin of :func:`statmc.combine.combine`).

    Parameters
    ----------
    y : (N, C, H, W) tensor
        Independent pixel estimates (a render).
    z : (N, C, H, W) tensor
        Correlated estimates of the same picture (e.g. the denoised ``y``).
    weights : (N, k·k, H, W) tensor
        Per-pixel window weights, the centre tap ``(r, r)`` is ``w_c``; finite, with a
        nonzero sum over the taps inside the image (positive weights, e.g. a softmax).

    Returns
    -------
    out : (N, C, H, W) tensor
        ``β̂_c = (w_c y_c + Σ_i w_i y_i + Σ_i w_i (z_c − z_i)) / W_c``,
        ``W_c = w_c + Σ_i w_i`` over the taps inside the image, computed in the boosting
        form ``z + apply_kernels(w, y − z) / apply_kernels(w, 1)`` (Eq. 15, algebraically
        Eq. 8).

    Examples
    --------
    >>> import torch
    >>> y = torch.full((1, 3, 4, 5), 2.0); z = y + 1.0      # z off by a constant: cancels
    >>> w = torch.rand(1, 9, 4, 5) + 0.1
    >>> bool(torch.allclose(combine(y, z, w), y))
    True
    """
    check_tensor("y", y, 4, "(N, C, H, W)")
    check_tensor("z", z, 4, "(N, C, H, W)")
    check_tensor("weights", weights, 4, "(N, k·k, H, W)")
    check_like("z", z, "y", y)
    check_like("weights", weights, "y", y)
    if z.shape != y.shape:
        raise InputError(f"`z` must have the shape of `y` {tuple(y.shape)}; got {tuple(z.shape)}.")
    _nonempty("y", y, (1, 2, 3))
    _same_grid("weights", weights, "y", y, (0, 2, 3))
    k = kernel_size(weights.shape[1], "weights")
    wsum = _apply(weights, torch.ones_like(y[:, :1]), k)
    _finite_weights(wsum, weights)
    _check_weight_sums(wsum)
    return _finite_result(z + _apply(weights, y - z, k) / wsum,
                          (("y", y), ("z", z), ("weights", weights)))


def combine_multi(ys, zs, weights):
    """Multi-buffer combination kernel, Eq. 14 of [1]_ (twin of :func:`statmc.combine.combine_multi`).

    Parameters
    ----------
    ys : (N, B, C, H, W) tensor
        Independent estimates per sample bin.
    zs : (N, B, C, H, W) tensor
        Correlated estimates per bin (e.g. ``zs[:, b] = denoise(ys[:, b])``).
    weights : (N, B, k·k, H, W) tensor
        Weights ``w_{i,b}`` per bin and tap, finite.

    Returns
    -------
    out : (N, C, H, W) tensor
        ``β̂_c = Σ_b [w_{c,b} y_{c,b} + Σ_i w_{i,b} y_{i,b} + Σ_i w_{i,b}(z_{c,b} − z_{i,b})] / W_c``,
        ``W_c = Σ_b (w_{c,b} + Σ_i w_{i,b})`` over the taps inside the image; evaluated as
        ``Σ_b [apply(w_b, y_b − z_b) + apply(w_b, 1) z_b] / Σ_b apply(w_b, 1)``.
    """
    check_tensor("ys", ys, 5, "(N, B, C, H, W)")
    check_tensor("zs", zs, 5, "(N, B, C, H, W)")
    check_tensor("weights", weights, 5, "(N, B, k·k, H, W)")
    check_like("zs", zs, "ys", ys)
    check_like("weights", weights, "ys", ys)
    if zs.shape != ys.shape:
        raise InputError(f"`zs` must have the shape of `ys` {tuple(ys.shape)}; got {tuple(zs.shape)}.")
    _nonempty("ys", ys, (1, 2, 3, 4))
    _same_grid("weights", weights, "ys", ys, (0, 1, 3, 4))
    N, B, C, H, W = ys.shape
    k = kernel_size(weights.shape[2], "weights")
    w = weights.reshape(N * B, k * k, H, W)
    wsum = _apply(w, torch.ones_like(ys[:, :, :1]).reshape(N * B, 1, H, W), k).view(N, B, 1, H, W)
    _finite_weights(wsum, weights)
    total = wsum.sum(dim=1)
    _check_weight_sums(total)
    diff = _apply(w, (ys - zs).reshape(N * B, C, H, W), k).view(N, B, C, H, W)
    return _finite_result((diff + wsum * zs).sum(dim=1) / total,
                          (("ys", ys), ("zs", zs), ("weights", weights)))


class ApplyKernels(torch.nn.Module):
    """Module form of :func:`apply_kernels`: ``forward(kernels, image)``."""

    def forward(self, kernels, image):
        return apply_kernels(kernels, image)


class Combine(torch.nn.Module):
    """Module form of :func:`combine` (Eq. 8 of [1]_): ``forward(y, z, weights)``."""

    def forward(self, y, z, weights):
        return combine(y, z, weights)


class CombineMulti(torch.nn.Module):
    """Module form of :func:`combine_multi` (Eq. 14 of [1]_): ``forward(ys, zs, weights)``."""

    def forward(self, ys, zs, weights):
        return combine_multi(ys, zs, weights)
