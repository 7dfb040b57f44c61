"""The networks' per-pixel inputs: :func:`pixel_features` (from a :class:`statmc.PixelStats`)
and :func:`mix_features` (the mixing network's, Firmino 2022 §4.3).

:func:`pixel_features` is the input builder of :mod:`statmc.nn.nets`; every network takes
its ``(1, F, H, W)`` output, with ``F = feature_channels(...)``, except
``MixNet(inputs="mix")``, which reads :func:`mix_features` (the inputs of Firmino 2022
§4.3: HDR, VAR, DEN, SURE, ``σ² f'(x)``, ``‖y − x‖²``, ordered so that the paper's random
swap is the plane permutation :func:`swap_mix_planes`).  The planes of
:func:`pixel_features`, in order (``x = stats.mean``, ``σ² = stats.mean_var``, the
**variance of the mean**, ``C`` channels):

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

from statmc.errors import (MAX_BUDGET, InputError, as_bool, as_float_array, as_int, as_number,
                           as_whole, check_finite)
from statmc.progressive import as_mix_inputs, bind_denoiser
from statmc.stats import PixelStats, check_stats

__all__ = ["pixel_features", "feature_channels", "REL_EPS", "VAR_FLOOR", "DIST_EPS",
           "mix_features", "mix_features_of", "mix_feature_channels", "mix_inputs",
           "swap_mix_planes", "MIX_PLANES", "MIX_SWAP", "MIX_REL_EPS", "MIX_GAIN"]

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
    channels, extra = as_int("channels", channels, lo=0), as_int("extra", extra, lo=0)
    budget = as_bool("budget", budget, why="whether pixel_features gets a budget")
    return 2 * channels + 6 + 2 * channels * extra + 2 * budget


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
        Eq. 11 feeds it, and the current sampling map, to the sampler): a whole number in
        ``[0, 2**53]``, as :func:`statmc.sampling.counts_from_density` takes.
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
    for name in ("albedo", "normal"):
        feat = getattr(stats, name)
        if feat is None:
            planes.append(np.zeros((H, W, 3)))
            continue
        feat = np.asarray(feat, np.float64)
        check_finite(f"stats.{name}", feat)       # named here, not as the `features` below
        planes.append(feat)
    if extra is not None:
        for e in _extra(extra, x.shape):
            planes += [np.log1p(np.maximum(e, 0.0)), np.abs(e - x) / (np.abs(x) + DIST_EPS)]
    if budget is not None:     # 2**70 was taken here, and refused by SamplingNet.counts
        budget = as_whole("budget", budget, what="number of samples", hi=MAX_BUDGET)
        planes += [np.log1p(np.asarray(stats.n, np.float64))[..., None],
                   np.full((H, W, 1), np.log1p(budget / (H * W)))]
    a = np.concatenate(planes, axis=2)
    check_finite("features", a)
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)[None])).to(dtype)


# =========================================================================== mixing network
#: Names of the six plane groups of :func:`mix_features` (``C`` planes each), in order:
#: Firmino 2022 §4.3's HDR, VAR, DEN, SURE, then the two by-products of SURE,
#: ``σ² f'(x)`` (DIV) and ``‖y − x‖²`` (DIST).
MIX_PLANES = ("HDR", "VAR", "DEN", "SURE", "DIV", "DIST")
#: The random swap of Firmino 2022 §4.3 as a permutation of the groups of
#: :data:`MIX_PLANES`: (HDR, VAR) ↔ (DEN, SURE); DIV and DIST stay (see :func:`mix_features`).
MIX_SWAP = (2, 3, 0, 1, 4, 5)
#: ε of the relative normalisation ``(x² + y²)/2 + ε`` of :func:`mix_features`: 0.01, the ε
#: of relMSE (Rousselle 2011 §7).
MIX_REL_EPS = 0.01
#: Gain before the arctan of :func:`mix_features` (``relative=True``).  Measured on 32×32
#: OIDN-denoised toy renders ("mixed", "edges", "texture"; session 12): the relative VAR,
#: SURE, DIV and DIST have medians 3e-4 to 6e-2 and 95th percentiles 2e-3 to 1.7 from 512
#: to 8 spp, so a gain of 100 puts typical values in arctan's responsive range (|·| ≲ 1.5)
#: instead of next to 0, where the first layer could barely see them.
MIX_GAIN = 100.0


def mix_feature_channels(channels: int = 3) -> int:
    """Number of planes ``F = 6C`` that :func:`mix_features` returns for ``C`` channels."""
    return 6 * as_int("channels", channels, lo=1)


def _check_mix_options(relative=True, gain=MIX_GAIN):
    """``(relative, gain)`` of :func:`mix_features` checked: ``relative`` a bool, ``gain``
    a finite number > 0 (``InputError`` otherwise); returns them (``gain`` as a float)."""
    relative = as_bool("relative", relative,
                       why="whether mix_features divides by (x² + y²)/2 + 0.01 before the arctan")
    return relative, as_number("gain", gain, lo=0.0, lo_open=True)


def mix_features(x, mean_var, y, sure_y, divergence, *, relative: bool = True,
                 gain: float = MIX_GAIN, dtype=torch.float32) -> torch.Tensor:
    """The inputs of the mixing network of Firmino 2022 §4.3, in swappable order.

    Parameters
    ----------
    x : (H, W, C) ndarray
        The render (pixel means), "HDR".
    mean_var : (H, W, C) or (H, W, C, C) ndarray
        ``σ²``, the **variance of the mean** of ``x`` ("VAR", the estimate of the squared
        error of ``x``; of a covariance only the diagonal is used).
    y : (H, W, C) ndarray
        The denoised image ``f(x)``, "DEN".
    sure_y : (H, W, C) ndarray
        Per-pixel SURE of ``y`` (:func:`statmc.sure.mc_sure` or :func:`statmc.sure.sure`),
        the estimate of its squared error; may be negative.
    divergence : (H, W, C) ndarray
        ``σ² f'(x) = (J_f Σ)_ii``, the divergence term computed with SURE
        (``extra_output["divergence"]`` of those functions).
    relative : bool
        ``True`` (default): divide the four non-radiance quantities by
        ``(x² + y²)/2 + 0.01`` before the arctan (a departure from the paper, see Notes).
        ``False``: the paper's literal ``arctan(gain · q)``.
    gain : float
        Factor inside the arctan (> 0; default :data:`MIX_GAIN` = 100).  ``relative=False,
        gain=1`` is the paper's transform.
    dtype : torch.float32 or torch.float64

    Returns
    -------
    (1, 6C, H, W) tensor
        Six groups of ``C`` planes, in the order of :data:`MIX_PLANES`:
        ``log(1 + max(x, 0))``, ``arctan(g σ²/s)``, ``log(1 + max(y, 0))``,
        ``arctan(g SURE/s)``, ``arctan(g D/s)``, ``arctan(g (y − x)²/s)``, with
        ``s = (x² + y²)/2 + 0.01`` (``s = 1`` when ``relative=False``) and ``g = gain``.

    Notes
    -----
    §4.3 of Firmino 2022 feeds HDR, DEN, VAR, SURE, ``σ² f'(x)`` and ``‖y − x‖²``;
    radiances go through ``log(1 + x)`` and "the non-radiance quantities are transformed
    by ``arctan(x)``, rather than ``log(1 + x)`` as x may be negative" (SURE and the
    divergence can be).  The order makes the paper's random swap of (HDR, VAR) with
    (DEN, SURE) an exact permutation of planes, :func:`swap_mix_planes`.

    **The divergence under a swap** (the paper is silent).  It stays where it is.  In
    Eq. 8 ``σ² E[f'(x)]`` enters as the covariance ``E[(x − μ)(y − μ)]`` of the two
    estimates' errors (Eq. 6, Stein's lemma), which is symmetric in ``x`` and ``y``: the
    expected error of the swapped mix ``y + β(x − y)`` is Eq. 8 with ``σ²`` and SURE
    exchanged and the same cross term, and its minimiser is Eq. 10, ``β = (SURE − σ²
    f'(x))/‖y − x‖²`` — Eq. 9 with ``σ² ↔ SURE`` and the same ``σ² f'(x)`` and
    ``‖y − x‖²``.  So a network that learns Eq. 9 on the unswapped planes computes Eq. 10
    on the swapped ones.  ``‖y − x‖²`` is symmetric too, and so is the normaliser ``s``,
    so the swap stays an exact permutation with ``relative=True``.

    **Relative, with a gain** (departure).  The paper applies ``arctan`` to the absolute
    quantities.  Here they are divided by the symmetric ``s`` (the ε of relMSE) and
    multiplied by :data:`MIX_GAIN`: the ratios of Eq. 9 and 10 do not change under a common
    per-pixel factor, inputs of renders of any brightness land on one scale, and at 64–512
    spp the absolute (and relative) values are so close to 0 that ``arctan`` leaves them
    about 1e-4 to 1e-2 (measurements at :data:`MIX_GAIN`).

    References
    ----------
    A. Firmino, J. R. Frisvad, H. W. Jensen. "Progressive Denoising of Monte Carlo Rendered
    Images". Computer Graphics Forum 41(2), 2022. https://doi.org/10.1111/cgf.14454
    """
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"`dtype` must be torch.float32 or torch.float64; got {dtype!r}.")
    relative, gain = _check_mix_options(relative, gain)
    # the checks of statmc.progressive, whose progressive_denoise hands these to `alpha`
    xx, yy, v, sy, d = as_mix_inputs(x, y, mean_var, sure_y, divergence)
    scale = gain / ((xx * xx + yy * yy) / 2.0 + MIX_REL_EPS) if relative else gain
    planes = [np.log1p(np.maximum(xx, 0.0)), np.arctan(scale * v),
              np.log1p(np.maximum(yy, 0.0)), np.arctan(scale * sy),
              np.arctan(scale * d), np.arctan(scale * (yy - xx) ** 2)]
    a = np.concatenate(planes, axis=2)
    check_finite("features", a)
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)[None])).to(dtype)


def swap_mix_planes(features: torch.Tensor) -> torch.Tensor:
    """The random swap of Firmino 2022 §4.3 on :func:`mix_features` planes: (HDR, VAR) ↔
    (DEN, SURE), DIV and DIST in place (:data:`MIX_SWAP`; an involution).

    ``features`` is ``(N, 6C, H, W)`` (or ``(6C, H, W)``); the result is the same planes
    permuted, exactly the features of the swapped inputs (``mix_features(y, SURE, x, σ²,
    D)`` where SURE ≥ 0 — that call refuses a negative variance, the permutation has no such
    limit; see :func:`mix_features` for why the divergence ``D`` stays).  The VAR slot of a
    swapped sample is negative wherever SURE is, which an unswapped one never is: a network
    can tell the two orientations apart, as the paper's can.
    """
    if not isinstance(features, torch.Tensor) or features.ndim not in (3, 4) \
            or features.shape[-3] % 6 != 0 or features.shape[-3] == 0:
        got = tuple(features.shape) if isinstance(features, torch.Tensor) else type(features).__name__
        raise InputError(f"`features` must be an (N, 6C, H, W) tensor of mix_features planes; "
                         f"got {got}.")
    groups = features.unflatten(-3, (6, features.shape[-3] // 6))
    return groups[..., list(MIX_SWAP), :, :, :].flatten(-4, -3)


def mix_inputs(stats: PixelStats, denoiser, *, mean_var=None, k: int = 4, eps: float = 1e-4,
               rng=None) -> dict:
    """Denoise a render and compute its MC-SURE: the inputs of :func:`mix_features`.

    Returns the dict that :func:`statmc.progressive.progressive_denoise` hands to a callable
    ``alpha`` (given the same ``mean_var``, ``k``, ``eps`` and ``rng``): ``x``
    (``stats.mean``), ``y`` (the denoised image), ``mean_var`` (σ², the variance of the
    mean), ``sure`` (per-pixel MC-SURE of ``y``, Eq. 1 with Eq. 2 of Firmino 2022) and
    ``divergence`` (``σ² f'(x)``), from :func:`statmc.sure.mc_sure` with ``k``, ``eps``,
    ``rng``.  ``denoiser`` is a callable or a name bound to ``stats`` by
    :func:`statmc.progressive.bind_denoiser` (e.g. ``"oidn"``).

    ``mean_var`` ((H, W, C) variance of the mean or (H, W, C, C) per-pixel channel
    covariance), as in ``progressive_denoise``, replaces ``stats.mean_var`` for MC-SURE and
    VAR (the dict then holds its diagonal), so a network trained on these inputs sees what
    ``progressive_denoise(..., mean_var=...)`` gives its ``alpha``.  Without it every pixel
    needs ``n >= 2`` (``InputError`` otherwise).
    """
    from statmc.sure import mc_sure

    check_stats(stats)
    if mean_var is None:
        stats.require_variance(why="for VAR and MC-SURE of the mixing network's inputs",
                               hint=" Render a uniform pass of >= 2 spp first, or pass "
                                    "`mean_var`.")
    mv = stats.mean_var if mean_var is None else mean_var
    x = np.asarray(stats.mean, np.float64)
    _, _, s2, _, _ = as_mix_inputs(x, x, mv, x, x)       # σ², or a covariance's diagonal
    f = bind_denoiser(denoiser, stats) if isinstance(denoiser, str) else denoiser
    s, info = mc_sure(f, stats.mean, mv, k=k, eps=eps, rng=rng, extra_output=True)
    return {"x": x, "y": info["denoised"], "mean_var": s2, "sure": s,
            "divergence": info["divergence"]}


def mix_features_of(inputs: dict, **options) -> torch.Tensor:
    """:func:`mix_features` of a :func:`mix_inputs` dict (the ``alpha`` callable's dict of
    :func:`statmc.progressive.progressive_denoise`); ``options`` as there."""
    if not isinstance(inputs, dict) or not {"x", "y", "mean_var", "sure", "divergence"} <= set(inputs):
        raise InputError("`inputs` must be a dict with x, y, mean_var, sure and divergence "
                         f"(statmc.nn.mix_inputs); got {type(inputs).__name__}"
                         + (f" with keys {sorted(inputs)}" if isinstance(inputs, dict) else "") + ".")
    return mix_features(inputs["x"], inputs["mean_var"], inputs["y"], inputs["sure"],
                        inputs["divergence"], **options)
