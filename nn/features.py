"""The networks' per-pixel inputs, built from :class:`statmc.PixelStats` by one function.

:func:`pixel_features` is the only input builder of :mod:`statmc.nn.nets`; every network
takes its ``(1, F, H, W)`` output, with ``F = feature_channels(...)``.  The planes, in
order (``x = stats.mean``, ``σ² = stats.mean_var``, the **variance of the mean**, ``C``
channels):

======================================  ======  ===================================================
plane                                   count   why
======================================  ======  ===================================================
``log(1 + max(x, 0))``                  C       radiance, compressed (HDR values span decades)
``log(σ²/(x² + ε) + 1e-4) / 10``        C       relative variance of the mean; ε = 0.01, the ε of
                                                relMSE (Rousselle 2011 §7); roughly in [−1, 1]
``albedo``                              3       feature buffer (zeros when ``stats.albedo`` is None)
``normal``                              3       feature buffer (zeros when ``stats.normal`` is None)
per ``extra`` image ``e``:
``log(1 + max(e, 0))``                  C       e.g. the denoised ``y`` (Firmino 2022 §4.3 "DEN"),
                                                the correlated ``z`` or the bins (Back 2020 §4.4)
``|e − x| / (|x| + 0.1)``               C       its relative distance to the render
                                                (Firmino 2022 §4.3 feeds ``‖y − x‖²``)
with ``budget``:
``log(1 + n)``                          1       the accumulated sampling map ``S̄_t`` (Salehi 2022
                                                Eq. 11)
``log(1 + budget / (H·W))``             1       the mean per-pixel budget ``B̄_{t+1}`` (Eq. 11)
======================================  ======  ===================================================

The transforms are fixed (no statistics of a data set), so a render of any size or
brightness gives inputs on the same scale.
"""

from __future__ import annotations

import numpy as np
import torch

from statmc.errors import InputError, as_float_array, check_finite
from statmc.stats import PixelStats, check_stats

__all__ = ["pixel_features", "feature_channels", "REL_EPS", "VAR_FLOOR", "DIST_EPS"]

#: ε of the relative variance ``σ²/(x² + ε)``: 0.01, the ε of relMSE (Rousselle 2011 §7).
REL_EPS = 0.01
#: Floor inside the log of the relative variance (a noise-free pixel gives log(1e-4)/10 ≈ −0.92).
VAR_FLOOR = 1e-4
#: Offset of the relative distance ``|e − x| / (|x| + 0.1)`` (keeps black pixels finite).
DIST_EPS = 0.1


def feature_channels(channels: int = 3, *, extra: int = 0, budget: bool = False) -> int:
    """Number of planes ``F`` that :func:`pixel_features` returns.

    Parameters
    ----------
    channels : int
        ``C`` of the render.
    extra : int
        Number of extra images (``E`` of ``extra=``).
    budget : bool
        Whether ``budget=`` is given.

    Returns
    -------
    int
        ``2C + 6 + 2C·extra + 2·budget``.
    """
    for name, v in (("channels", channels), ("extra", extra)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise InputError(f"`{name}` must be a non-negative int; got {v!r}.")
    if not isinstance(budget, (bool, np.bool_)):
        raise InputError(f"`budget` must be a bool (whether pixel_features gets a budget); "
                         f"got {budget!r}.")
    return 2 * channels + 6 + 2 * channels * int(extra) + 2 * bool(budget)


def _extra(extra, shape):
    e = as_float_array("extra", extra, ndim=(3, 4), dtype=np.float64)
    if e.ndim == 3:
        e = e[None]
    if e.shape[1:] != shape:
        raise InputError(f"`extra` must be an (H, W, C) image or an (E, H, W, C) stack with "
                         f"(H, W, C) = {shape} of `stats.mean`; got shape {np.shape(extra)}.")
    check_finite("extra", e)
    return e


def pixel_features(stats: PixelStats, *, extra=None, budget=None,
                   dtype=torch.float32) -> torch.Tensor:
    """Per-pixel network inputs from a render's statistics (table in the module docstring).

    Parameters
    ----------
    stats : PixelStats
        The render: mean, variance of the mean, albedo and normal (zeros when absent),
        and ``n`` when ``budget`` is given.  Every pixel needs ``n >= 2`` (a variance
        estimate; ``InputError`` otherwise, as :meth:`PixelStats.require_variance`).
    extra : (H, W, C) or (E, H, W, C) ndarray, optional
        Further images of the same picture: the denoised image for :class:`MixNet`, the
        correlated image(s) and bins for :class:`CombinerNet`.
    budget : int, optional
        The next iteration's total sample budget, for :class:`SamplingNet` (Salehi 2022
        Eq. 11 feeds it, and the current sampling map, to the sampler).
    dtype : torch.float32 or torch.float64

    Returns
    -------
    (1, F, H, W) tensor
        ``F = feature_channels(C, extra=E, budget=budget is not None)``.
    """
    check_stats(stats)
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"`dtype` must be torch.float32 or torch.float64; got {dtype!r}.")
    # mean_var is 0 where n < 2: such a pixel would look noise-free (the floor of plane 2)
    stats.require_variance(why="for the relative-variance planes of pixel_features: mean_var "
                               "is 0 where n < 2, which the networks would read as noise-free",
                           hint=" Render a uniform pass of >= 2 spp first.")
    x = np.asarray(stats.mean, np.float64)
    H, W, C = x.shape
    xp = np.maximum(x, 0.0)
    planes = [np.log1p(xp),
              np.log(stats.mean_var / (x * x + REL_EPS) + VAR_FLOOR) / 10.0]
    for feat in (stats.albedo, stats.normal):
        planes.append(np.zeros((H, W, 3)) if feat is None else np.asarray(feat, np.float64))
    if extra is not None:
        for e in _extra(extra, x.shape):
            planes += [np.log1p(np.maximum(e, 0.0)), np.abs(e - x) / (np.abs(x) + DIST_EPS)]
    if budget is not None:
        if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 0:
            raise InputError(f"`budget` must be a non-negative int (total samples of the next "
                             f"iteration); got {budget!r}.")
        planes += [np.log1p(np.asarray(stats.n, np.float64))[..., None],
                   np.full((H, W, 1), np.log1p(budget / (H * W)))]
    a = np.concatenate(planes, axis=2)
    check_finite("features", a)
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)[None])).to(dtype)
