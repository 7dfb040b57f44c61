"""Tiny convolutional networks whose outputs plug into statmc's statistical kernels.

All four share one body — 3×3 conv, ReLU, 3×3 conv, ReLU, 1×1 conv, ``width`` features
(a few thousand parameters at the default ``width=16``) — and differ in the head that
turns its output into something a statmc kernel accepts:

=====================  ==========================  ==================================================
network                output (torch, NCHW)        plugs into (NumPy, channel-last)
=====================  ==========================  ==================================================
:class:`KernelNet`     ``(N, k·k, H, W)`` softmax   :func:`statmc.analytic.apply_kernels`,
                       kernels                      :func:`statmc.analytic.expected_kernel_loss`
                                                    (``(H, W, k, k)``; Salehi 2022 §A.1)
:class:`CombinerNet`   ``(N, B, k·k, H, W)``        :func:`statmc.combine.combine` /
                       positive weights             :func:`~statmc.combine.combine_multi`
                                                    (``(H, W, B, k, k)``; Back 2020 Eq. 8, 14, §4.2)
:class:`MixNet`        ``(N, 1, H, W)`` α ∈ [0, 1]  :func:`statmc.progressive.progressive_denoise`
                       (``(N, C, H, W)`` with       ``(alpha=...)`` (``(H, W)`` or ``(H, W, C)``;
                       ``per_channel=True``)        Firmino 2022 §4.3; ``inputs="mix"``:
                                                    :func:`~statmc.nn.mix_features`)
:class:`SamplingNet`   ``(N, 1, H, W)`` logits      :func:`statmc.sampling.counts_from_density`
                                                    (``(H, W)`` counts; Salehi 2022 Eq. 11)
=====================  ==========================  ==================================================

Every network reads the planes of :func:`statmc.nn.features.pixel_features` (``MixNet(inputs="mix")``
those of :func:`statmc.nn.features.mix_features` instead; its
``channels`` argument is the ``C`` of the render), so ``net(pixel_features(stats, ...))``
is the torch path used in training, and one method per network (``kernels``, ``weights``,
``alpha``, ``counts``) is the NumPy path that hands statmc a channel-last array.

These are untrained plumbing: the architectures are far smaller than the papers' (Back
2020: six 5×5 layers of 100 features; Firmino 2022: six layers of 48 features with residual
blocks; Salehi 2022: a 5-scale U-net with a global summary module), and nothing here
claims that a learned version beats the classical one (docs/nn.md).
"""

from __future__ import annotations

import numpy as np
import torch

from statmc.errors import (MAX_BUDGET, InputError, as_bool, as_float_array, as_int, as_number,
                           as_whole, check_finite)
from statmc.sampling import counts_from_density
from statmc.stats import check_stats

from .features import (_check_mix_options, feature_channels, mix_feature_channels, mix_features_of,
                       pixel_features, swap_mix_planes)
from .layout import kernels_to_numpy, weights_to_numpy
from .ops import _finite_result, apply_kernels, check_finite_tensor, check_tensor, torch_seed

__all__ = ["KernelNet", "CombinerNet", "MixNet", "SamplingNet", "F_ACT_EPS",
           "F_ACT_INIT_BIAS", "F_ACT_INIT_SCALE"]

#: ε of f_act (Eq. 19 of Firmino 2022): 1e-6, "to avoid the singularity" (§4.3).
F_ACT_EPS = 1e-6
#: Initial biases of f_act's outputs ``(x1, x2, x3)``: α starts at (1 − 0) / 2 = 0.5 with
#: ``x3`` far above ε.  Not from the paper (which gives no initialisation): with torch's
#: default one, ``x3 < ε`` at nearly every pixel for 7 of 10 seeds (seed 0 among them), so
#: ``(x1 − x2)/ε`` was clamped to 0 or 1 everywhere and no gradient flowed (session 10).
F_ACT_INIT_BIAS = (1.0, 0.0, 2.0)
#: Factor on the default initial weights of f_act's output layer, so that ``x3`` stays
#: near its bias (above 0.5) and α near 0.5 at every pixel of a fresh network.
F_ACT_INIT_SCALE = 0.1


def _int(name, v, lo, odd=False):
    v = as_int(name, v, lo=lo)
    if odd and v % 2 == 0:
        raise InputError(f"`{name}` must be an odd integer (a window side); got {v!r}.")
    return v


def _images(name, a, stats, count=None):
    """``a`` as a float64 ``(E, H, W, C)`` stack of images shaped like ``stats.mean``:
    ``count=None`` takes one ``(H, W, C)`` image (or a stack of one), else exactly ``count``."""
    check_stats(stats)
    shape = stats.mean.shape
    arr = as_float_array(name, a, ndim=(3, 4) if count is None else 4, dtype=np.float64)
    stack = arr if arr.ndim == 4 else arr[None]
    want = (1 if count is None else count,) + shape
    if stack.shape != want:
        what = "an (H, W, C) image" if count is None else f"a ({count}, H, W, C) stack"
        raise InputError(f"`{name}` must be {what} with (H, W, C) = {tuple(shape)} of "
                         f"`stats.mean`; got shape {np.shape(a)}.")
    check_finite(name, stack)
    return stack


class _Net(torch.nn.Module):
    """The shared body; ``seed`` makes the initial weights reproducible without touching
    torch's global random state."""

    def __init__(self, channels, in_channels, out_channels, width, seed):
        super().__init__()
        width = _int("width", width, 1)
        if seed is not None:
            seed = torch_seed("seed", seed)
        self.channels = channels            # C of the render, checked by the NumPy methods
        self.in_channels = in_channels
        with torch.random.fork_rng(devices=[]):
            if seed is not None:
                torch.manual_seed(seed)
            self.body = torch.nn.Sequential(
                torch.nn.Conv2d(in_channels, width, 3, padding=1), torch.nn.ReLU(),
                torch.nn.Conv2d(width, width, 3, padding=1), torch.nn.ReLU(),
                torch.nn.Conv2d(width, out_channels, 1))

    def _body(self, features):
        if not isinstance(features, torch.Tensor) or features.ndim != 4 \
                or features.shape[1] != self.in_channels:
            got = tuple(features.shape) if isinstance(features, torch.Tensor) else type(features).__name__
            builder = "mix_features" if getattr(self, "inputs", None) == "mix" else "pixel_features"
            raise InputError(f"`features` must be an (N, {self.in_channels}, H, W) tensor "
                             f"(statmc.nn.{builder} with this network's settings); got {got}.")
        if features.device != self._device:
            raise InputError(f"`features` is on device {features.device} but the network is on "
                             f"{self._device}; move one of them (`features.to(net_device)`).")
        if not features.is_floating_point():     # complex lost its imaginary part in the cast
            raise InputError(f"`features` must be a floating-point tensor; got {features.dtype}.")
        if features.shape[2] == 0 or features.shape[3] == 0:     # a conv RuntimeError
            raise InputError(f"`features` must have at least one row and column; got shape "
                             f"{tuple(features.shape)}.")
        check_finite_tensor("features", features)
        return self.body(features.to(self._dtype))

    def _image(self, name, t, like=None):
        """An ``(N, C, H, W)`` image tensor for this network: its dtype, on its device."""
        check_tensor(name, t, 4, "(N, C, H, W)")
        if t.device != self._device:
            raise InputError(f"`{name}` is on device {t.device} but the network is on "
                             f"{self._device}; move it (`{name}.to(net_device)`).")
        if like is not None and t.shape != like.shape:
            raise InputError(f"`{name}` must have the shape of `x` {tuple(like.shape)}; got "
                             f"{tuple(t.shape)}.")
        return t.to(self._dtype)

    def _features(self, stats, **kw):
        """:func:`pixel_features` in this network's dtype, on its device (the NumPy methods)."""
        self._check_stats(stats)
        return pixel_features(stats, dtype=self._dtype, **kw).to(self._device)

    def _check_stats(self, stats):
        """``InputError`` unless ``stats`` is a render of the ``C`` this network was built for
        (the refusal named `features`, which the caller of a NumPy method never gave)."""
        check_stats(stats)
        C = stats.mean.shape[2]
        if C != self.channels:
            raise InputError(f"`stats` has C = {C} channels, but this network was built for "
                             f"channels={self.channels}; build it with channels={C}.")

    @property
    def _dtype(self):
        return next(self.parameters()).dtype

    @property
    def _device(self):
        return next(self.parameters()).device

    def n_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)


class KernelNet(_Net):
    """Per-pixel normalised ``k x k`` kernels (a kernel-predicting network).

    Parameters
    ----------
    channels : int
        ``C`` of the render (inputs: ``pixel_features(stats)``, ``2C + 6`` planes).
    k : int
        Odd kernel side (default 5).
    width : int
        Features of the hidden layers.
    seed : int or None
        Seed of the initial weights (default 0).

    Notes
    -----
    The output is the linear kernel denoiser ``D(X)_p = Σ_q K_pq X_q`` of §A.1 of Salehi
    et al. 2022 with positive weights summing to 1 (a softmax over the taps) — GEM's
    per-pixel choice among Gaussians (Rousselle 2011) is a classical kernel of the same
    kind.  Kernels predicted from a pilot render and then frozen satisfy Lemma A.1, so
    :func:`statmc.analytic.expected_kernel_loss` gives their exact expected error after
    more samples.  Taps outside the image are dropped, not renormalised (the convention of
    :func:`statmc.analytic.apply_kernels`), so border pixels lose the weight of their
    outside taps.
    """

    def __init__(self, channels: int = 3, *, k: int = 5, width: int = 16, seed=0):
        self.k = _int("k", k, 1, odd=True)
        C = _int("channels", channels, 1)
        super().__init__(C, feature_channels(C), self.k * self.k, width, seed)

    def forward(self, features):
        """``(N, 2C + 6, H, W)`` features -> ``(N, k·k, H, W)`` kernels, softmax over taps.

        The weights ``K_pq`` of the kernel denoiser ``D(X)_p = Σ_q K_pq X_q`` (Salehi 2022
        §A.1, Lemma A.1), for :func:`statmc.nn.apply_kernels` /
        :func:`statmc.analytic.apply_kernels`.
        """
        return torch.softmax(self._body(features), dim=1)

    def denoise(self, features, image):
        """``apply_kernels(self(features), image)`` on ``(N, C, H, W)`` images (differentiable):
        the kernel denoiser ``D(X)_p = Σ_q K_pq X_q`` of Salehi 2022 §A.1."""
        return apply_kernels(self(features), self._image("image", image))

    def kernels(self, stats) -> np.ndarray:
        """The kernels for a render as statmc's ``(H, W, k, k)`` float64 array."""
        with torch.no_grad():
            return kernels_to_numpy(self(self._features(stats)))


class CombinerNet(_Net):
    """Weights of the combination kernel of Back et al. 2020 (Eq. 8, Eq. 14), as in their §4.2.

    Parameters
    ----------
    channels : int
        ``C`` of the render.
    buffers : int
        ``B``: 1 for Eq. 8 (inputs ``pixel_features(stats, extra=z)``, ``4C + 6`` planes),
        ``B > 1`` for Eq. 14 on sample bins (inputs ``pixel_features(stats,
        extra=concatenate([ys, zs]))``, ``2C + 6 + 4BC`` planes: the paper feeds the ``B``
        pairs ``(y_b, z_b)`` and the G-buffers, §4.2, §4.4).
    k : int
        Odd window side (default 5; the paper uses 15).
    width : int
    seed : int or None

    Notes
    -----
    The last layer emits ``B·k·k`` values per pixel (the paper's ``B × (|Ω_c| + 1)``,
    §4.4); a softmax over all of them gives positive weights, so every pixel's ``W_c``
    over the taps inside the image is positive, as :func:`statmc.combine.combine` needs.
    Eq. 8 and Eq. 14 are invariant to a common scale of a pixel's weights, so the
    normalisation costs nothing; taking it jointly over the bins lets a bin be
    down-weighted as a whole (an outlier bin, §4.4).
    """

    def __init__(self, channels: int = 3, *, buffers: int = 1, k: int = 5, width: int = 16,
                 seed=0):
        self.k = _int("k", k, 1, odd=True)
        self.buffers = _int("buffers", buffers, 1)
        extra = 1 if self.buffers == 1 else 2 * self.buffers
        C = _int("channels", channels, 1)
        super().__init__(C, feature_channels(C, extra=extra), self.buffers * self.k * self.k,
                         width, seed)

    def forward(self, features):
        """Features -> ``(N, B, k·k, H, W)`` positive weights (softmax over ``B·k·k``).

        The ``w_{i,b}`` of Back 2020 Eq. 14 (``w_c``, ``w_i`` of Eq. 8 when ``B = 1``),
        for :func:`statmc.nn.combine_multi` / :func:`statmc.combine.combine_multi`.
        """
        out = torch.softmax(self._body(features), dim=1)
        N, _, H, W = out.shape
        return out.view(N, self.buffers, self.k * self.k, H, W)

    def features(self, stats, zs, ys=None) -> torch.Tensor:
        """This network's inputs: ``z`` for ``B = 1``; ``ys`` and ``zs`` ``(B, H, W, C)`` for ``B > 1``."""
        self._check_stats(stats)
        if self.buffers == 1:
            if ys is not None:
                raise InputError("`ys` is for B > 1 bins; with buffers=1 the independent "
                                 "image is `stats.mean` and only `zs` (z) is given.")
            if np.ndim(zs) == 4 and np.shape(zs)[0] != 1:
                raise InputError(f"`zs` must be one (H, W, C) image z for buffers=1; got shape "
                                 f"{np.shape(zs)}.  For bins use CombinerNet(buffers=B) with "
                                 "`ys` and `zs` of shape (B, H, W, C).")
            return self._features(stats, extra=_images("zs", zs, stats))
        if ys is None:
            raise InputError(f"`ys` must be given for buffers={self.buffers}: the "
                             f"({self.buffers}, H, W, C) bins whose correlated estimates are `zs`.")
        ys, zs = (_images(n, a, stats, self.buffers) for n, a in (("ys", ys), ("zs", zs)))
        return self._features(stats, extra=np.concatenate([ys, zs]))

    def weights(self, stats, zs, ys=None) -> np.ndarray:
        """The weights as statmc's ``(H, W, B, k, k)`` float64 array (see :meth:`features`)."""
        with torch.no_grad():
            return weights_to_numpy(self(self.features(stats, zs, ys)))


class MixNet(_Net):
    """Per-pixel mixing parameter α for progressive denoising (Firmino et al. 2022, §4.3).

    Parameters
    ----------
    channels : int
        ``C`` of the render (inputs ``pixel_features(stats, extra=y)``, ``4C + 6`` planes,
        ``y`` the denoised image).
    width : int
    activation : {"sigmoid", "f_act"}
        ``"sigmoid"``: one output per pixel, ``α = sigmoid(o)``.  ``"f_act"``: three
        outputs ``(x1, x2, x3)`` and ``α = clamp((x1 − x2) / max(x3, ε), 0, 1)``, Eq. 19
        of Firmino 2022 (ε = 1e-6; the paper does not clamp, but the gate and
        ``z = x + α(y − x)`` are meant for α in [0, 1], and the clamp makes that so; its
        gradient is 0 outside).  The output layer starts with biases
        :data:`F_ACT_INIT_BIAS` and weights scaled by :data:`F_ACT_INIT_SCALE`, so a fresh
        network gives α ≈ 0.5 with ``x3`` well above ε at every pixel (with torch's default
        initialisation most seeds start clamped everywhere, with no gradient at all).
    inputs : {"pixel", "mix"}
        ``"pixel"`` (default): ``pixel_features(stats, extra=y)``.  ``"mix"``: the inputs
        of Firmino 2022 §4.3, :func:`statmc.nn.mix_features` (HDR, VAR, DEN, SURE,
        ``σ² f'(x)``, ``‖y − x‖²``; ``6C`` planes), whose swap (HDR, VAR) ↔ (DEN, SURE) is
        a permutation of planes, for training with the paper's random swapping
        (:func:`statmc.nn.swap_mix_loss`).
    mix_options : dict, optional
        ``relative`` and ``gain`` of :func:`statmc.nn.mix_features`, used by the NumPy
        methods (:meth:`alpha`, :meth:`alpha_from`); build training features with the same.
    per_channel : bool
        ``False`` (default): one α per pixel, shared by the channels, ``(N, 1, H, W)``.
        ``True``: one α per pixel and channel, ``(N, C, H, W)`` — the paper's network
        "outputs three values (x1, x2, x3) per pixel and per channel" (Firmino 2022 §4.3),
        so with ``activation="f_act"`` the head has ``3C`` outputs, ``x1`` of channel ``c``
        at ``c``, ``x2`` at ``C + c``, ``x3`` at ``2C + c``, and Eq. 19 is applied per
        channel.  The NumPy methods then return ``(H, W, C)``, which
        :func:`statmc.progressive.progressive_denoise` and its gate take as they are.
    seed : int or None

    Notes
    -----
    The swap turns the pair round: on swapped inputs the network's output is the β of
    ``y + β(x − y)`` (Eq. 10), per channel with ``per_channel=True`` (the swap exchanges
    all channels' planes at once); a swap-consistent network has ``α(x, y) = 1 − α(y, x)``
    (:meth:`swap_consistency`).
    ``z = x + α (y − x)`` (§4 of Firmino 2022; the network is their ``h`` of Eq. 3).  Pass the α of :meth:`alpha` to
    :func:`statmc.progressive.progressive_denoise` ``(alpha=...)``: it goes through the
    same Student-t confidence gate (Eq. 12–18) as the classical α of Eq. 9, which keeps
    the mix convergent whatever the network predicts.
    """

    _ACTIVATIONS = ("sigmoid", "f_act")
    _INPUTS = ("pixel", "mix")

    def __init__(self, channels: int = 3, *, width: int = 16, activation: str = "sigmoid",
                 inputs: str = "pixel", mix_options=None, per_channel: bool = False, seed=0):
        if activation not in self._ACTIVATIONS:
            raise InputError(f"`activation` must be 'sigmoid' or 'f_act'; got {activation!r}.")
        if inputs not in self._INPUTS:
            raise InputError(f"`inputs` must be 'pixel' (pixel_features(stats, extra=y)) or "
                             f"'mix' (mix_features, Firmino 2022 §4.3); got {inputs!r}.")
        if mix_options is not None and (inputs != "mix" or not isinstance(mix_options, dict)
                                        or not set(mix_options) <= {"relative", "gain"}):
            raise InputError(f"`mix_options` must be None or, with inputs='mix', a dict of "
                             f"mix_features options (relative, gain); got {mix_options!r}.")
        if mix_options:                    # refused here, not at the first alpha_from
            _check_mix_options(**mix_options)
        per_channel = as_bool("per_channel", per_channel, why="one α per pixel and channel")
        self.activation = activation
        self.inputs = inputs
        self.mix_options = dict(mix_options or {})
        C = _int("channels", channels, 1)
        self.per_channel = per_channel
        K = C if self.per_channel else 1   # α maps: one per channel, or one shared
        F = feature_channels(C, extra=1) if inputs == "pixel" else mix_feature_channels(C)
        super().__init__(C, F, K if activation == "sigmoid" else 3 * K, width, seed)
        if activation == "f_act":          # start inside the clamp, x3 > ε (F_ACT_INIT_BIAS)
            head = self.body[-1]
            with torch.no_grad():
                head.weight.mul_(F_ACT_INIT_SCALE)
                head.bias.copy_(torch.tensor(F_ACT_INIT_BIAS, dtype=head.bias.dtype)
                                .repeat_interleave(K))

    def forward(self, features):
        """Features -> ``(N, 1, H, W)`` α in [0, 1] (``(N, C, H, W)`` with ``per_channel``).

        The α of ``z = x + α (y − x)`` (Firmino 2022 §4; the network is ``h`` of Eq. 3,
        with ``f_act`` of Eq. 19 when ``activation="f_act"``), gated by
        :func:`statmc.progressive.confidence_gate` (Eq. 12–18) in
        :func:`statmc.progressive.progressive_denoise`.
        """
        o = self._body(features)
        if self.activation == "sigmoid":
            return torch.sigmoid(o)
        K = o.shape[1] // 3
        x1, x2, x3 = o[:, :K], o[:, K:2 * K], o[:, 2 * K:]
        return torch.clamp((x1 - x2) / torch.clamp(x3, min=F_ACT_EPS), 0.0, 1.0)

    def mix(self, features, x, y):
        """``z = x + α (y − x)`` on ``(N, C, H, W)`` tensors (Firmino 2022 §4, Eq. 11;
        differentiable; ungated)."""
        x = self._image("x", x)
        y = self._image("y", y, like=x)
        a = self(features)
        if (a.shape[0], *a.shape[2:]) != (x.shape[0], *x.shape[2:]):
            raise InputError(f"`x` has shape {tuple(x.shape)}, but the images must have the "
                             f"batch size and (H, W) of `features` {tuple(features.shape)}.")
        if a.shape[1] != 1 and a.shape[1] != x.shape[1]:
            raise InputError(f"`x` must have the {a.shape[1]} channels of this per-channel "
                             f"network's α; got shape {tuple(x.shape)}.")
        # NaN/Inf in x or y reaches the result (it was returned silently): checked there
        return _finite_result(x + a * (y - x), (("x", x), ("y", y)))

    def alpha(self, stats, y, *, sure=None, divergence=None) -> np.ndarray:
        """α for a render and its denoised image ``y`` ``(H, W, C)``, as an ``(H, W)`` float64
        map (``(H, W, C)`` with ``per_channel``).

        With ``inputs="mix"``, ``sure`` and ``divergence`` (``(H, W, C)``, from
        :func:`statmc.sure.mc_sure`) are needed too; :meth:`alpha_from` takes them in a
        :func:`statmc.nn.mix_inputs` dict.
        """
        self._check_stats(stats)
        if self.inputs == "pixel":
            if sure is not None or divergence is not None:
                raise InputError("`sure` and `divergence` are inputs of MixNet(inputs='mix'); "
                                 "this network reads pixel_features(stats, extra=y) only.")
            with torch.no_grad():
                return self._alpha_map(self(self._features(stats, extra=_images("y", y, stats))))
        if sure is None or divergence is None:
            raise InputError("MixNet(inputs='mix') needs `sure` and `divergence` of `y` "
                             "(statmc.sure.mc_sure(..., extra_output=True)); got None.")
        # as pixel_features and mix_inputs: mean_var is 0 where n < 2, which reads as noise-free
        stats.require_variance(why="for the VAR plane of the mixing network's inputs",
                               hint=" Render a uniform pass of >= 2 spp first.")
        return self.alpha_from({"x": stats.mean, "y": y, "mean_var": stats.mean_var,
                                "sure": sure, "divergence": divergence})

    def alpha_from(self, inputs) -> np.ndarray:
        """α ``(H, W)`` (``(H, W, C)`` with ``per_channel``) from a dict of ``x``, ``y``,
        ``mean_var``, ``sure``, ``divergence`` (``inputs="mix"``): pass
        ``alpha=net.alpha_from`` to :func:`statmc.progressive.progressive_denoise`, which
        calls it with exactly that dict, so the network sees the ``y`` and MC-SURE that the
        gate and the mix use."""
        if self.inputs != "mix":
            raise InputError("`alpha_from` is for MixNet(inputs='mix'); use alpha(stats, y).")
        with torch.no_grad():
            f = mix_features_of(inputs, dtype=self._dtype, **self.mix_options).to(self._device)
            return self._alpha_map(self(f))

    def _alpha_map(self, a):
        """The first sample's α as statmc's float64 ``(H, W)`` or, per channel, ``(H, W, C)``."""
        a = a[0].permute(1, 2, 0) if self.per_channel else a[0, 0]
        return a.cpu().numpy().astype(np.float64)

    def swap_consistency(self, features) -> torch.Tensor:
        """``α(x, y) + α(y, x) − 1`` per pixel, and per channel with ``per_channel``
        (``inputs="mix"``; 0 for a swap-consistent network, Firmino 2022 §4.3: swapping the
        inputs should turn α into β = 1 − α)."""
        if self.inputs != "mix":
            raise InputError("`swap_consistency` is for MixNet(inputs='mix').")
        return self(features) + self(swap_mix_planes(features)) - 1.0


class SamplingNet(_Net):
    """Per-pixel sampling logits whose softmax is a sampling density (Salehi et al. 2022 Eq. 11).

    Parameters
    ----------
    channels : int
        ``C`` of the render (inputs ``pixel_features(stats, budget=budget)``, ``2C + 8``
        planes, with the current counts and the mean budget per pixel).
    width : int
    seed : int or None

    Notes
    -----
    Eq. 11: ``S = B_{t+1} · softmax(Φ(X_t, S̄_t, B̄_{t+1}))``, the softmax over the pixels
    of the image.  :meth:`sample_map` is that real-valued map (differentiable; the paper
    trains through it with analytic future renders); :meth:`counts` rounds it to integer
    counts that sum to the budget exactly with :func:`statmc.sampling.counts_from_density`
    (systematic rounding, unbiased).  The paper's global summary module is not included.
    """

    def __init__(self, channels: int = 3, *, width: int = 16, seed=0):
        C = _int("channels", channels, 1)
        super().__init__(C, feature_channels(C, budget=True), 1, width, seed)

    def forward(self, features):
        """Features -> ``(N, 1, H, W)`` logits ``Φ`` of Salehi 2022 Eq. 11
        (``S = B · softmax(Φ)``, see :meth:`sample_map`, :meth:`counts`)."""
        return self._body(features)

    def density(self, features):
        """``softmax(Φ)`` over each image's pixels (Salehi 2022 Eq. 11 without the budget):
        ``(N, 1, H, W)``, each image sums to 1."""
        logits = self(features)
        N, _, H, W = logits.shape
        return torch.softmax(logits.reshape(N, H * W), dim=1).view(N, 1, H, W)

    def sample_map(self, features, budget):
        """Eq. 11: ``budget · softmax(Φ)``, real-valued ``(N, 1, H, W)`` (differentiable)."""
        if isinstance(budget, torch.Tensor) and budget.numel() == 1:
            budget = budget.item()
        return as_number("budget", budget, lo=0.0) * self.density(features)

    def counts(self, stats, budget: int, *, rng=None) -> np.ndarray:
        """Integer ``(H, W)`` counts, summing to ``budget`` exactly, for the next iteration.

        Parameters
        ----------
        stats : PixelStats
            The render so far (``X_t``, and ``S̄_t = stats.n``).
        budget : int
            ``B_{t+1}``, the total samples to hand out.
        rng : numpy Generator or int, optional
            Randomness of the rounding (:func:`statmc.sampling.counts_from_density`).
        """
        # checked first: budget=None built features without the budget planes, refused
        # as the wrong `features`
        budget = as_whole("budget", budget, what="number of samples", hi=MAX_BUDGET)
        with torch.no_grad():
            d = self.density(self._features(stats, budget=budget))
        return counts_from_density(d[0, 0].cpu().numpy().astype(np.float64), budget, rng=rng)
