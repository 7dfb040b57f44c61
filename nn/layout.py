"""Layout conversions at the boundary between statmc (NumPy, channel-last) and torch (NCHW).

statmc's arrays are channel-last: images ``(H, W, C)``, per-pixel kernels ``(H, W, k, k)``
(:func:`statmc.analytic.apply_kernels`), combination weights ``(H, W, B, k, k)``
(:func:`statmc.combine.combine_multi`), maps ``(H, W)``.  Inside torch everything is
``(N, C, H, W)``; a ``k x k`` window is ``k·k`` channels in row-major tap order, tap
``t = dy·k + dx`` (the order of :func:`torch.nn.functional.unfold`).  These functions are
the only place the two layouts meet; each ``*_to_numpy`` is the inverse of its
``*_from_numpy`` (for ``N = 1``).
"""

from __future__ import annotations

import numpy as np
import torch

from statmc.errors import InputError, as_float_array, check_finite

from .ops import kernel_size

__all__ = ["image_to_tensor", "tensor_to_image", "kernels_from_numpy", "kernels_to_numpy",
           "weights_from_numpy", "weights_to_numpy"]


def _tensor(name, t, ndim):
    if not isinstance(t, torch.Tensor):
        raise InputError(f"`{name}` must be a torch.Tensor; got {type(t).__name__}.")
    if t.ndim != ndim:
        raise InputError(f"`{name}` must have {ndim} dimensions; got shape {tuple(t.shape)}.")
    if t.shape[0] != 1:
        raise InputError(f"`{name}` must hold one image (leading N = 1) to become a statmc "
                         f"array; got shape {tuple(t.shape)}.  Convert `{name}[i:i+1]` per image.")
    if t.is_complex():   # lost its imaginary part with only a ComplexWarning before
        raise InputError(f"`{name}` must be a real tensor; got {t.dtype}.")
    if t.is_meta:        # NotImplementedError "Cannot copy out of meta tensor" before
        raise InputError(f"`{name}` is on the meta device, which holds no values.")
    # float64 in torch: NumPy has no bfloat16 (`.numpy()` raised TypeError "Got unsupported
    # ScalarType BFloat16"); exact for the other real dtypes (then copied, as before)
    return t.detach().cpu().to(torch.float64)


def _dtype(dtype):
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"`dtype` must be torch.float32 or torch.float64; got {dtype!r}.")
    return dtype


def _to_tensor(name, a, dtype):
    """The finite float64 array ``a`` as a tensor of ``dtype``, refused if a value overflows
    it (1e300 became Inf in float32 silently)."""
    t = torch.from_numpy(np.ascontiguousarray(a)).to(_dtype(dtype))
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"`{name}` holds values beyond the range of {dtype} (largest "
                         f"magnitude {float(np.abs(a).max()):.3g}); use dtype=torch.float64, "
                         "or rescale it.")
    return t


def image_to_tensor(image, *, dtype=torch.float32) -> torch.Tensor:
    """``(H, W, C)`` or ``(H, W)`` array -> ``(1, C, H, W)`` tensor (``C = 1`` for a map).

    Parameters
    ----------
    image : (H, W, C) or (H, W) ndarray
        Finite values.
    dtype : torch.float32 or torch.float64
        Of the tensor (float32 for the networks, float64 for exact comparisons).
    """
    a = as_float_array("image", image, ndim=(2, 3), dtype=np.float64)
    check_finite("image", a)
    if a.ndim == 2:
        a = a[..., None]
    return _to_tensor("image", a.transpose(2, 0, 1)[None], dtype)


def tensor_to_image(t) -> np.ndarray:
    """``(1, C, H, W)`` tensor -> ``(H, W, C)`` float64 array (inverse of :func:`image_to_tensor`)."""
    a = _tensor("t", t, 4)
    return a[0].permute(1, 2, 0).numpy().astype(np.float64)


def kernels_from_numpy(kernels, *, dtype=torch.float32) -> torch.Tensor:
    """statmc kernels ``(H, W, k, k)`` -> ``(1, k·k, H, W)`` tensor, tap ``dy·k + dx``."""
    K = as_float_array("kernels", kernels, ndim=4, dtype=np.float64)
    H, W, k, k2 = K.shape
    if k != k2 or k % 2 == 0:
        raise InputError(f"`kernels` must have shape (H, W, k, k) with odd k; got {K.shape}.")
    check_finite("kernels", K)
    return _to_tensor("kernels", K.reshape(H, W, k * k).transpose(2, 0, 1)[None], dtype)


def kernels_to_numpy(t) -> np.ndarray:
    """``(1, k·k, H, W)`` tensor -> statmc kernels ``(H, W, k, k)`` float64."""
    a = _tensor("t", t, 4)
    _, taps, H, W = a.shape
    k = kernel_size(taps, "t")
    return a[0].permute(1, 2, 0).reshape(H, W, k, k).numpy().astype(np.float64)


def weights_from_numpy(weights, *, dtype=torch.float32) -> torch.Tensor:
    """statmc combination weights ``(H, W, B, k, k)`` -> ``(1, B, k·k, H, W)`` tensor."""
    w = as_float_array("weights", weights, ndim=5, dtype=np.float64)
    H, W, B, k, k2 = w.shape
    if k != k2 or k % 2 == 0:
        raise InputError(f"`weights` must have shape (H, W, B, k, k) with odd k; got {w.shape}.")
    check_finite("weights", w)
    return _to_tensor("weights", w.reshape(H, W, B, k * k).transpose(2, 3, 0, 1)[None], dtype)


def weights_to_numpy(t) -> np.ndarray:
    """``(1, B, k·k, H, W)`` tensor -> statmc combination weights ``(H, W, B, k, k)`` float64."""
    a = _tensor("t", t, 5)
    _, B, taps, H, W = a.shape
    k = kernel_size(taps, "t")
    return a[0].permute(2, 3, 0, 1).reshape(H, W, B, k, k).numpy().astype(np.float64)
