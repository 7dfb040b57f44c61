"""Denoiser adapters behind one small protocol: ``f(color) -> color``.

A *denoiser* is any callable that maps an ``(H, W, C)`` float32 colour image to an
``(H, W, C)`` colour image.  Everything else a denoiser needs — feature buffers (albedo,
normal), the per-pixel variance, a filter width — is bound when the adapter is built, so
the error estimators of :mod:`statmc.sure` can call it on perturbed copies of the colour
alone (MC-SURE, Eq. 2 of Firmino et al. 2022; first-order output variance, Firmino et
al. 2023).

=====================  ========================================  ==========================
factory                denoiser                                  exact kernels / JVP
=====================  ========================================  ==========================
:func:`identity`       the input itself                          ``.kernels(shape)``
:func:`gaussian`       border-renormalised Gaussian              ``.kernels(shape)``
                       (:func:`statmc.filters.gaussian_filter`)
:func:`gem`            GEM reconstruction                        —
                       (:func:`statmc.gem.reconstruct`)
:func:`oidn`           Intel Open Image Denoise via ``pyoidn``   —
:func:`torch_module`   any ``torch.nn.Module`` on ``(1, C, H,    ``.jvp(color, tangent)``
                       W)`` tensors
=====================  ========================================  ==========================

:func:`get` builds one by name (``"oidn"``, ``"gem"``, ``"gaussian"``, ``"none"`` /
``"identity"``), :func:`as_denoiser` accepts a name, a plain callable or a torch module.

Neither this module nor ``import statmc`` imports torch or pyoidn: :func:`oidn` loads
``pyoidn`` (which itself imports torch when it is installed) at its first call, and
:func:`torch_module` uses the module it is given.

Linear adapters expose their per-pixel kernels in the convention of
:func:`statmc.analytic.apply_kernels`, so exact SURE (:func:`statmc.sure.sure`) and the
exact output variance (:func:`statmc.sure.kernel_variance`) apply to them.
"""

from __future__ import annotations

import inspect
import threading
import weakref
from typing import Protocol, runtime_checkable

import numpy as np

from .errors import (InputError, as_bool, as_float_array, check_finite, check_nonempty,
                     check_nonnegative)
from .filters import (DEFAULT_TRUNCATE, _check_sigma, _check_truncate, _taps, border_scale,
                      gaussian_filter)

__all__ = [
    "Denoiser", "identity", "gaussian", "gem", "oidn", "torch_module", "get", "as_denoiser",
    "NAMES", "IdentityDenoiser", "GaussianDenoiser", "GEMDenoiser", "OIDNDenoiser",
    "TorchDenoiser",
]


@runtime_checkable
class Denoiser(Protocol):
    """The denoiser protocol: ``denoiser(color) -> color`` on ``(H, W, C)`` arrays.

    ``color`` is float32 (the estimators of :mod:`statmc.sure` always pass float32);
    the result must have the same shape.  Any bound input (features, variance) is fixed
    at construction; a denoiser used with MC-SURE or finite differences must be
    deterministic (the same input gives the same output).
    """

    def __call__(self, color: np.ndarray) -> np.ndarray: ...


# ----------------------------------------------------------------------------- checks
def _color(name, a, *, channels=None, shape=None):
    arr = as_float_array(name, a, ndim=3)
    check_nonempty(name, arr)
    if channels is not None and arr.shape[2] != channels:
        raise InputError(f"`{name}` must be an (H, W, {channels}) image; got shape {arr.shape}.")
    if shape is not None and arr.shape != tuple(shape):
        raise InputError(f"`{name}` must have the shape {tuple(shape)} of the bound inputs; "
                         f"got {arr.shape}.")
    check_finite(name, arr)
    return arr


def _feature(name, a, *, lo, hi):
    if a is None:
        return None
    arr = as_float_array(name, a, ndim=3, dtype=np.float32)
    if arr.shape[2] != 3:
        raise InputError(f"`{name}` must be an (H, W, 3) image; got shape {arr.shape}.")
    check_finite(name, arr)
    if arr.size and (arr.min() < lo - 1e-4 or arr.max() > hi + 1e-4):
        raise InputError(f"`{name}` must lie in [{lo}, {hi}]; got values in "
                         f"[{arr.min():.4g}, {arr.max():.4g}].")
    return np.ascontiguousarray(arr)


def _shape_hw(shape):
    try:
        shp = tuple(int(s) for s in shape)
    except TypeError as exc:
        raise InputError(f"`shape` must be (H, W) or (H, W, C); got {shape!r}.") from exc
    if len(shp) not in (2, 3) or min(shp) < 1:
        raise InputError(f"`shape` must be (H, W) or (H, W, C) with positive sizes; got {shape!r}.")
    return shp[:2]


# ----------------------------------------------------------------------------- identity
class IdentityDenoiser:
    """The identity ``f(x) = x`` ("no denoising"); see :func:`identity`."""

    name = "identity"

    def __call__(self, color):
        return _color("color", color).copy()

    def kernels(self, shape) -> np.ndarray:
        """``(H, W, 1, 1)`` unit kernels (the convention of :func:`statmc.analytic.apply_kernels`)."""
        return np.ones(_shape_hw(shape) + (1, 1))

    def __repr__(self):
        return "identity()"


def identity() -> IdentityDenoiser:
    """The identity denoiser (``get("none")``): SURE reduces to the variance of the mean."""
    return IdentityDenoiser()


# ----------------------------------------------------------------------------- gaussian
class GaussianDenoiser:
    """Fixed border-renormalised Gaussian filter; see :func:`gaussian`."""

    name = "gaussian"

    def __init__(self, sigma: float = 1.0, *, truncate: float = DEFAULT_TRUNCATE):
        # checked as statmc.filters does; the taps are built for an image in kernels(),
        # cut to what reaches it (σ = 1e6 built 6e6 taps, 137 MiB, here before)
        self.sigma = _check_sigma(sigma)
        self.truncate = _check_truncate(truncate)

    def __call__(self, color):
        return gaussian_filter(_color("color", color), self.sigma, truncate=self.truncate)

    def kernels(self, shape) -> np.ndarray:
        """Per-pixel kernels ``(H, W, k, k)`` of this filter on an image of ``shape``.

        ``K[y, x, dy, dx] = g(dy − r) g(dx − r) / (N_y(y) N_x(x))`` for taps inside the
        image and 0 outside, with ``g`` the normalised 1-D Gaussian and ``N`` the sum of
        the in-image taps (border renormalisation), so that
        ``statmc.analytic.apply_kernels(K, x) == self(x)`` up to rounding.  Memory is
        ``H·W·k²`` float64, ``k = 2·ceil(truncate·σ) + 1``; a kernel of more than 4096
        taps a side is cut to the ``2·(max(H, W) − 1) + 1`` taps that can reach the image
        (the taps of :func:`statmc.filters.gaussian_filter`, exact: the taps cut only ever
        fall outside it), so a huge σ costs what the image does.
        """
        h, w = _shape_hw(shape)
        g = _taps(self.sigma, self.truncate, max(h, w))
        k = g.size
        r = k // 2
        sy, sx = border_scale(h, g), border_scale(w, g)
        off = np.arange(k) - r
        in_y = (np.arange(h)[:, None] + off[None, :] >= 0) & (np.arange(h)[:, None] + off[None, :] < h)
        in_x = (np.arange(w)[:, None] + off[None, :] >= 0) & (np.arange(w)[:, None] + off[None, :] < w)
        ky = np.where(in_y, g[None, :], 0.0) * sy[:, None]   # (H, k)
        kx = np.where(in_x, g[None, :], 0.0) * sx[:, None]   # (W, k)
        return ky[:, None, :, None] * kx[None, :, None, :]

    def __repr__(self):
        return f"gaussian(sigma={self.sigma:g}, truncate={self.truncate:g})"


def gaussian(sigma: float = 1.0, *, truncate: float = DEFAULT_TRUNCATE) -> GaussianDenoiser:
    """A fixed Gaussian filter of standard deviation ``sigma`` pixels as a denoiser.

    Linear, so :meth:`GaussianDenoiser.kernels` gives its exact per-pixel kernels for
    :func:`statmc.sure.sure` and :func:`statmc.sure.kernel_variance`.

    Examples
    --------
    >>> f = gaussian(sigma=1.5)
    >>> x = np.random.default_rng(0).random((6, 7, 3)).astype(np.float32)
    >>> from statmc.analytic import apply_kernels
    >>> bool(np.allclose(f(x), apply_kernels(f.kernels(x.shape), x), atol=1e-6))
    True
    """
    return GaussianDenoiser(sigma, truncate=truncate)


# ----------------------------------------------------------------------------- GEM
class GEMDenoiser:
    """GEM reconstruction with its variance bound; see :func:`gem`."""

    name = "gem"

    def __init__(self, mean_var, *, gamma: float = 0.2, final: bool = True, n=None, bias=None):
        mv = as_float_array("mean_var", mean_var, ndim=3)
        check_finite("mean_var", mv)
        check_nonnegative("mean_var", mv)
        self.mean_var = mv
        self.gamma = gamma
        self.final = as_bool("final", final)   # "no" was taken as True
        self.n = n
        self.bias = bias

    def __call__(self, color):
        from . import gem as _gem  # lazy: statmc.gem is a peer module

        x = _color("color", color, shape=self.mean_var.shape)
        xw, vw = self._working(x)
        out = _gem.reconstruct(xw, vw, gamma=self.gamma, final=self.final, n=self.n,
                               bias=self.bias)
        return out.astype(x.dtype, copy=False)

    def _working(self, x):
        """``(color, mean_var)`` in the colour's dtype, or both in float64 where the
        variance does not fit it (a finite float64 ``mean_var`` beyond float32's 3.4e38 would
        become inf); GEM's output is an average of the colour, so it fits back."""
        if (self.mean_var.dtype.itemsize > x.dtype.itemsize and self.mean_var.size
                and float(self.mean_var.max()) > float(np.finfo(x.dtype).max)):
            return x.astype(np.float64), self.mean_var.astype(np.float64, copy=False)
        return x, self.mean_var.astype(x.dtype, copy=False)

    def output_variance(self, color):
        """``(variance, image)`` of the output on ``color``, both float64: the variance of
        the filter GEM selects on ``color``, given that selection — ``mean_var`` filtered
        with the squared weights of each pixel's selected scale (Rousselle 2011 §4.1).
        Exact for the linear filter the selection defines; finite differences would cross
        the selection's switches (see :func:`gem`'s notes)."""
        from . import gem as _gem

        x, v = self._working(_color("color", color, shape=self.mean_var.shape))
        info = _gem.select(x, v, gamma=self.gamma, final=self.final, n=self.n, bias=self.bias)
        var = np.take_along_axis(info["variances"], info["scales"][None, ..., None], axis=0)[0]
        return np.asarray(var, np.float64), np.asarray(info["image"], np.float64)

    def __repr__(self):
        return (f"gem(mean_var=<{self.mean_var.shape}>, gamma={self.gamma}, final={self.final}, "
                f"bias={self.bias!r})")


def gem(mean_var, *, gamma: float = 0.2, final: bool = True, n=None, bias=None) -> GEMDenoiser:
    """GEM reconstruction (Rousselle et al. 2011) bound to a variance-of-the-mean image.

    Parameters
    ----------
    mean_var : (H, W, C) ndarray
        **Variance of the mean** of the image that will be denoised (``stats.mean_var``).
    gamma, final, n, bias
        As in :func:`statmc.gem.reconstruct`: with ``final=True`` the default ``bias`` is the
        pooled estimate (docs/gem.md §5d), which does not use ``gamma``; ``bias="paper"``
        is Eq. 1 of Rousselle 2011 with the error-rate weight z(γ).

    Notes
    -----
    GEM selects a filter scale per pixel from the data, so it is piecewise linear with
    jumps where the selection switches: SURE assumes weak differentiability, which jumps
    violate, so (MC-)SURE of GEM is approximate.  Finite differences (small steps) see
    the linear pieces.
    """
    from .gem import _check_bias
    return GEMDenoiser(mean_var, gamma=gamma, final=final, n=n, bias=_check_bias(bias))


# ----------------------------------------------------------------------------- OIDN
_QUALITIES = ("high", "balanced", "fast", "default")


def _release(state):
    """Release an OIDN filter then its device (a weakref finalizer, safe to call twice)."""
    flt, dev = state.pop("filter", None), state.pop("device", None)
    if flt is not None:
        flt.release()
    if dev is not None:
        dev.release()


class OIDNDenoiser:
    """Intel Open Image Denoise (``RT`` filter, CPU) with bound features; see :func:`oidn`."""

    name = "oidn"

    def __init__(self, albedo=None, normal=None, *, hdr: bool = True, quality: str = "high",
                 clean_aux: bool = False, num_threads: int | None = None):
        self.albedo = _feature("albedo", albedo, lo=0.0, hi=1.0)
        self.normal = _feature("normal", normal, lo=-1.0, hi=1.0)
        if self.normal is not None and self.albedo is None:
            raise InputError("`normal` needs `albedo` too (OIDN's RT filter takes a normal "
                             "buffer only together with an albedo buffer); got only `normal`.")
        if self.albedo is not None and self.normal is not None and self.albedo.shape != self.normal.shape:
            raise InputError(f"`normal` must have the shape of `albedo` {self.albedo.shape}; "
                             f"got {self.normal.shape}.")
        if not isinstance(hdr, bool) or not isinstance(clean_aux, bool):
            raise InputError(f"`hdr` and `clean_aux` must be bools; got {hdr!r} and {clean_aux!r}.")
        if quality not in _QUALITIES:
            raise InputError(f"`quality` must be one of {', '.join(_QUALITIES)}; got {quality!r}.")
        if num_threads is not None and (isinstance(num_threads, bool) or not isinstance(num_threads, int)
                                        or num_threads < 0):
            raise InputError(f"`num_threads` must be None or an int >= 0; got {num_threads!r}.")
        self.hdr, self.quality, self.clean_aux, self.num_threads = hdr, quality, clean_aux, num_threads
        self._lock = threading.Lock()
        self._state: dict = {}
        self._finalizer = weakref.finalize(self, _release, self._state)

    @property
    def shape(self):
        """``(H, W, 3)`` fixed by the bound features, else ``None``."""
        return None if self.albedo is None else self.albedo.shape

    def _setup(self, shape):
        """Create (once) the device and one filter bound to persistent shared buffers."""
        from ._threads import import_passively

        # pyoidn imports torch (when installed), whose bundled OpenMP runtime numba's
        # kernels then share: load it with passive waits.  Two statmc jobs side by side
        # that had run OIDN first: 512x512 gem.reconstruct x6 took 4.5-6.8 s each with
        # torch's default spin-wait, 0.55 s with this.
        pyoidn = import_passively("pyoidn")

        st = self._state
        if "device" not in st:
            dev = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
            if self.num_threads is not None:
                dev.set_int("numThreads", self.num_threads)
            dev.commit()
            self._raise_error(dev, "device creation")
            st["device"] = dev
        if st.get("shape") == shape:
            return
        if "filter" in st:
            st.pop("filter").release()
        dev = st["device"]
        flt = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT)
        st["filter"] = flt
        st["in"] = np.zeros(shape, np.float32)
        st["out"] = np.zeros(shape, np.float32)
        fmt = pyoidn.OIDN_FORMAT_FLOAT3
        flt.set_image(pyoidn.OIDN_IMAGE_COLOR, st["in"], fmt)
        if self.albedo is not None:
            flt.set_image(pyoidn.OIDN_IMAGE_ALBEDO, self.albedo, fmt)
        if self.normal is not None:
            flt.set_image(pyoidn.OIDN_IMAGE_NORMAL, self.normal, fmt)
        flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, st["out"], fmt)
        flt.set_bool("hdr", self.hdr)
        flt.set_bool("cleanAux", self.clean_aux)
        flt.set_int("quality", {"high": pyoidn.OIDN_QUALITY_HIGH,
                                "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                                "fast": pyoidn.OIDN_QUALITY_FAST,
                                "default": pyoidn.OIDN_QUALITY_DEFAULT}[self.quality])
        flt.commit()
        self._raise_error(dev, "filter setup")
        st["shape"] = shape

    @staticmethod
    def _raise_error(dev, what):
        err = dev.get_error()
        if err is not None:
            raise RuntimeError(f"OIDN {what} failed: {err}")

    def __call__(self, color):
        x = _color("color", color, channels=3, shape=self.shape)
        with self._lock:
            self._setup(x.shape)
            st = self._state
            np.copyto(st["in"], x, casting="unsafe")
            st["filter"].execute()
            self._raise_error(st["device"], "filter execution")
            return st["out"].copy()

    def close(self):
        """Release the OIDN filter and device now (otherwise at garbage collection)."""
        with self._lock:
            self._finalizer()

    def __repr__(self):
        feats = [n for n in ("albedo", "normal") if getattr(self, n) is not None]
        return f"oidn(features={feats}, hdr={self.hdr}, quality={self.quality!r})"


def oidn(albedo=None, normal=None, *, hdr: bool = True, quality: str = "high",
         clean_aux: bool = False, num_threads: int | None = None) -> OIDNDenoiser:
    """Intel Open Image Denoise (``pyoidn``, CPU ``RT`` filter) as a denoiser.

    Parameters
    ----------
    albedo : (H, W, 3) ndarray in [0, 1], optional
        Albedo feature buffer, bound for every call.
    normal : (H, W, 3) ndarray in [-1, 1], optional
        Normal feature buffer (needs ``albedo``).
    hdr : bool
        Colour is HDR (linear radiance ``>= 0``); ``False`` for LDR in [0, 1].
    quality : {"high", "balanced", "fast", "default"}
    clean_aux : bool
        The features are noise-free (e.g. the toy renderer's); OIDN then does not
        prefilter them.
    num_threads : int, optional
        OIDN's ``numThreads`` (0 or ``None``: all cores).

    Notes
    -----
    One OIDN device and one filter, bound to persistent input/output buffers, live as
    long as the adapter (one commit, then one ``execute`` per call): the repeated calls
    of MC-SURE cost only the network.  CPU OIDN is deterministic — the same input gives
    bit-identical output, which finite differences rely on (tested).  The filter is
    rebuilt if an image of another shape arrives (only without bound features).
    """
    return OIDNDenoiser(albedo, normal, hdr=hdr, quality=quality, clean_aux=clean_aux,
                        num_threads=num_threads)


# ----------------------------------------------------------------------------- torch
class TorchDenoiser:
    """A torch module run on ``(1, C, H, W)`` float32 tensors; see :func:`torch_module`."""

    name = "torch"

    def __init__(self, module, *, albedo=None, normal=None, device: str = "cpu"):
        import torch  # only reached when a torch module is given

        if not isinstance(module, torch.nn.Module) and not callable(module):
            raise InputError(f"`module` must be a torch.nn.Module or a callable on tensors; "
                             f"got {type(module).__name__}.")
        self.module = module
        self.device = torch.device(device)
        feats = [f for f in (_feature("albedo", albedo, lo=0.0, hi=1.0),
                             _feature("normal", normal, lo=-1.0, hi=1.0)) if f is not None]
        if len(feats) == 2 and feats[0].shape != feats[1].shape:
            raise InputError(f"`normal` must have the shape of `albedo` {feats[0].shape}; "
                             f"got {feats[1].shape}.")
        self.shape_hw = feats[0].shape[:2] if feats else None
        self._features = (None if not feats else
                          torch.from_numpy(np.concatenate(feats, axis=2).transpose(2, 0, 1)[None].copy())
                          .to(self.device))

    def _to_tensor(self, a):
        import torch

        return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)[None], np.float32)).to(self.device)

    def _input(self, color):
        x = _color("color", color)
        if self.shape_hw is not None and x.shape[:2] != self.shape_hw:
            raise InputError(f"`color` must be (H, W, C) with (H, W) = {self.shape_hw} of the bound "
                             f"features; got {x.shape}.")
        return x

    def _forward(self, t):
        import torch

        if self._features is not None:
            t = torch.cat([t, self._features], dim=1)
        return self.module(t)

    def _to_numpy(self, y, shape):
        import torch

        if y.ndim != 4 or y.shape[0] != 1 or tuple(y.shape[2:]) != shape[:2] or y.shape[1] != shape[2]:
            raise InputError(f"`module` must return a (1, C, H, W) tensor shaped like its colour "
                             f"input (1, {shape[2]}, {shape[0]}, {shape[1]}); got {tuple(y.shape)}.")
        return np.ascontiguousarray(y[0].detach().to("cpu", dtype=torch.float32).numpy().transpose(1, 2, 0))

    def __call__(self, color):
        import torch

        x = self._input(color)
        with torch.no_grad():
            y = self._forward(self._to_tensor(x))
        return self._to_numpy(y, x.shape)

    def jvp(self, color, tangent):
        """Output and Jacobian-vector product ``(f(x), J_f(x) v)`` by forward-mode autodiff.

        The tangent ``v`` perturbs the colour only (bound features are constants).  This is
        the JVP of §"Deep NN Variance Estimate" of Firmino et al. 2023, computed with
        ``torch.func.jvp`` in one forward pass.
        """
        import torch

        x = self._input(color)
        v = as_float_array("tangent", tangent, ndim=3)
        if v.shape != x.shape:
            raise InputError(f"`tangent` must have the shape of `color` {x.shape}; got {v.shape}.")
        with torch.no_grad():
            y, jv = torch.func.jvp(self._forward, (self._to_tensor(x),), (self._to_tensor(v),))
        return self._to_numpy(y, x.shape), self._to_numpy(jv, x.shape)

    def __repr__(self):
        return f"torch_module({type(self.module).__name__})"


def torch_module(module, *, albedo=None, normal=None, device: str = "cpu") -> TorchDenoiser:
    """Any torch module ``(1, C_in, H, W) -> (1, C, H, W)`` as a denoiser.

    The colour ``(H, W, C)`` is converted to a ``(1, C, H, W)`` float32 tensor at the
    boundary (features, when bound, are concatenated after the colour channels:
    ``C_in = C + 3·#features``) and the output back to ``(H, W, C)`` float32.  Calls run
    under ``torch.no_grad()``; :meth:`TorchDenoiser.jvp` gives forward-mode JVPs for
    ``statmc.sure.output_variance(..., method="jvp")``.  Put the module in ``eval()``
    mode yourself if it has dropout or batch-norm layers.
    """
    return TorchDenoiser(module, albedo=albedo, normal=normal, device=device)


# ----------------------------------------------------------------------------- by name
_FACTORIES = {"identity": identity, "none": identity, "gaussian": gaussian, "gem": gem,
              "oidn": oidn}
#: Names accepted by :func:`get`.
NAMES = tuple(_FACTORIES)


def get(name: str, **bound):
    """Build a denoiser by name with its bound inputs.

    Parameters
    ----------
    name : {"oidn", "gem", "gaussian", "none", "identity"}
    **bound
        Keyword arguments of the factory (:func:`oidn`, :func:`gem`, :func:`gaussian`,
        :func:`identity`), e.g. ``get("gem", mean_var=stats.mean_var, gamma=0.2)``.

    Examples
    --------
    >>> get("gaussian", sigma=2.0)
    gaussian(sigma=2, truncate=3)
    """
    key = name.lower() if isinstance(name, str) else name
    if key not in _FACTORIES:
        raise InputError(f"`name` must be one of {', '.join(NAMES)}; got {name!r}.")
    factory = _FACTORIES[key]
    params = inspect.signature(factory).parameters
    unknown = sorted(set(bound) - set(params))
    if unknown:
        raise InputError(f"denoiser {key!r} takes {', '.join(params) or 'no arguments'}; got "
                         f"unexpected {', '.join(unknown)}.")
    missing = [p for p, v in params.items()
               if v.default is inspect.Parameter.empty and p not in bound]
    if missing:
        raise InputError(f"denoiser {key!r} needs {', '.join(missing)} (e.g. "
                         f"`get({key!r}, {missing[0]}=...)`).")
    return factory(**bound)


def as_denoiser(obj, **bound):
    """A denoiser from a name (:func:`get`), a torch module (:func:`torch_module`) or a callable."""
    if isinstance(obj, str):
        return get(obj, **bound)
    if bound:
        raise InputError(f"bound inputs ({', '.join(bound)}) are only accepted with a denoiser name.")
    if _is_torch_module(obj):
        return torch_module(obj)
    if not callable(obj):
        raise InputError(f"`denoiser` must be callable f(color) -> color or a name in "
                         f"{', '.join(NAMES)}; got {type(obj).__name__}.")
    return obj


def _is_torch_module(obj) -> bool:
    """True if ``obj`` is a ``torch.nn.Module`` (without importing torch when it is not loaded)."""
    import sys

    torch = sys.modules.get("torch")
    return torch is not None and isinstance(obj, torch.nn.Module)
