"""An analytic toy renderer whose per-pixel sample distribution is known exactly.

Every pixel ``(i, j)`` draws independent samples of the form

.. math::

    X_c = \\mu_c \\, S + \\sigma_c \\, Z_c, \\qquad c = 1, \\dots, C,

where ``S`` is one scalar "path throughput" per sample with ``E[S] = 1`` (shared by all
channels, so the channels are correlated like a colour times a scalar throughput, the
same device Salehi et al. 2022 §4.3 use to correlate the RGB channels of synthetic
samples), and ``Z_c`` are independent standard normals (independent per-channel noise,
off in most regions; samples can be negative only in ``gaussian`` pixels).  The law of
``S`` is one of :data:`FAMILIES`, chosen per pixel:

============  ==================================  ===================  =====================
family        ``S``                               ``Var[S]``           ``E[(S-1)^4]``
============  ==================================  ===================  =====================
``const``     ``1``                               ``0``                ``0``
``gaussian``  ``1 + τ N(0, 1)``                   ``τ²``               ``3 τ⁴``
``uniform``   ``U(1 − w, 1 + w)``                 ``w²/3``             ``w⁴/5``
``gamma``     ``Gamma(shape k, scale 1/k)``       ``1/k``              ``3 (k + 2)/k³``
``firefly``   ``1/p`` with prob. ``p``, else 0    ``(1 − p)/p``        ``(1−p)((1−p)³/p³ + 1)``
============  ==================================  ===================  =====================

So the truth is available in closed form: the pixel mean is ``μ_c`` (``>= 0``, a
radiance), the per-sample variance ``μ_c² Var[S] + σ_c²``, the channel covariance
``μ_c μ_d Var[S] + δ_cd σ_c²`` and the higher central moments follow from those of ``S``
(:func:`throughput_central_moments`).  A firefly pixel of mean ``v`` thus returns
``v/p`` with probability ``p`` and 0 otherwise: mean ``v``, per-sample variance
``v² (1 − p)/p``.  These are textbook identities (moments of the normal, uniform, gamma
and two-point laws), not equations of the papers in ``papers/``.

Scenes (:meth:`ToyRenderer.scenes`) are procedural images with noise-free feature
buffers (albedo, shading normal, depth) whose edges coincide with the image's edges, so
feature-guided reconstructions get a useful signal.  The noise is scaled so that
4 spp is very noisy and 4096 spp nearly converged (relative standard deviation of one
sample about 0.5–1 outside the firefly region).
"""

from __future__ import annotations


import numpy as np

from .errors import InputError, as_float_array, as_int, as_rng, check_finite, check_nonnegative
from .stats import PixelStats

__all__ = ["ToyRenderer", "FAMILIES", "throughput_central_moments", "sample_throughput",
           "DEFAULT_CHUNK"]

#: Names of the per-pixel laws of the scalar throughput ``S``; a pixel's family code is
#: the index into this tuple.
FAMILIES = ("const", "gaussian", "uniform", "gamma", "firefly")
CONST, GAUSSIAN, UNIFORM, GAMMA, FIREFLY = range(len(FAMILIES))

#: Samples drawn per chunk by :meth:`ToyRenderer.render` (peak memory about 0.2 GB).
DEFAULT_CHUNK = 1 << 21
#: Samples per pixel a render takes, at most (exclusive), as the Mitsuba backend.
MAX_COUNT = 2 ** 31

_SCENES = {
    "mixed": "four quadrants: sharp-edged shapes (exponential noise), a smooth shaded "
             "gradient (Gaussian noise), a fine texture (uniform noise), fireflies",
    "constant": "flat grey image with independent Gaussian noise (error-rate tests)",
    "edges": "checkerboard and a tilted disc, piecewise constant, exponential/gamma noise",
    "gradient": "smoothly shaded cylinder with a colour ramp, uniform noise",
    "texture": "high-frequency wavy stripes (period ~4 px), uniform noise",
    "fireflies": "smooth diffuse surface of firefly pixels, p from 0.01 to 0.2",
}


# ---------------------------------------------------------------------------- families
def _family_arrays(family, param):
    fam = np.asarray(family)
    if fam.dtype.kind not in "iu":
        raise InputError(f"`family` must hold integer family codes 0..{len(FAMILIES) - 1}; "
                         f"got dtype {fam.dtype}.")
    par = as_float_array("param", param, dtype=np.float64)
    try:
        fam, par = np.broadcast_arrays(fam, par)
    except ValueError:
        raise InputError(f"`family` {fam.shape} and `param` {par.shape} must broadcast.") from None
    if fam.size and (fam.min() < 0 or fam.max() >= len(FAMILIES)):
        raise InputError(f"`family` codes must lie in [0, {len(FAMILIES)}); "
                         f"got [{fam.min()}, {fam.max()}].")
    check_finite("param", par)
    bad = ((fam == GAUSSIAN) & (par < 0)) | ((fam == UNIFORM) & (par < 0)) \
        | ((fam == GAMMA) & (par <= 0)) | ((fam == FIREFLY) & ((par <= 0) | (par > 1)))
    if bad.any():
        raise InputError(f"`param` out of range for {int(bad.sum())} entries: need τ >= 0 "
                         "(gaussian), w >= 0 (uniform), k > 0 (gamma), 0 < p <= 1 (firefly).")
    return fam, par


def throughput_central_moments(family, param):
    """Variance, third and fourth central moments of the throughput ``S`` (``E[S] = 1``).

    Parameters
    ----------
    family : int ndarray
        Family codes, indices into :data:`FAMILIES`.
    param : ndarray
        The family's parameter (broadcast against ``family``): ignored for ``const``,
        ``τ`` for ``gaussian``, half-width ``w`` for ``uniform``, shape ``k`` for
        ``gamma``, probability ``p`` for ``firefly``.

    Returns
    -------
    var, m3, m4 : ndarray
        ``E[(S−1)²]``, ``E[(S−1)³]``, ``E[(S−1)⁴]``.

    Notes
    -----
    Textbook closed forms (no paper equation): normal ``(τ², 0, 3τ⁴)``; uniform on
    ``[1−w, 1+w]`` ``(w²/3, 0, w⁴/5)``; gamma with shape ``k`` and scale ``θ = 1/k``
    ``(kθ², 2kθ³, 3k(k+2)θ⁴)``; the firefly two-point law (``1/p`` with probability
    ``p``, else 0), whose deviations are ``1/p − 1`` and ``−1``:
    ``((1−p)/p, (1−p)(1−2p)/p², (1−p)((1−p)³/p³ + 1))``.

    Examples
    --------
    >>> v, m3, m4 = throughput_central_moments(np.array([4]), 0.25)   # firefly, p = 1/4
    >>> float(v[0]), float(m3[0]), float(m4[0])
    (3.0, 6.0, 21.0)
    """
    fam, par = _family_arrays(family, param)
    var = np.zeros(fam.shape)
    m3 = np.zeros(fam.shape)
    m4 = np.zeros(fam.shape)
    m = fam == GAUSSIAN
    t = par[m]
    var[m], m4[m] = t ** 2, 3 * t ** 4
    m = fam == UNIFORM
    w = par[m]
    var[m], m4[m] = w ** 2 / 3, w ** 4 / 5
    m = fam == GAMMA
    k = par[m]
    var[m], m3[m], m4[m] = 1 / k, 2 / k ** 2, 3 * (k + 2) / k ** 3
    m = fam == FIREFLY
    p = par[m]
    q = 1 - p
    var[m], m3[m], m4[m] = q / p, q * (1 - 2 * p) / p ** 2, q * (q ** 3 / p ** 3 + 1)
    return var, m3, m4


def sample_throughput(family, param, rng) -> np.ndarray:
    """One draw of the throughput ``S`` per entry of ``family`` (laws in :data:`FAMILIES`).

    Parameters
    ----------
    family : (N,) int ndarray
        Family code of each sample.
    param : (N,) ndarray
        Family parameter of each sample (see :func:`throughput_central_moments`).
    rng : numpy.random.Generator or int
        Source of randomness.

    Returns
    -------
    s : (N,) float64 ndarray with ``E[s] = 1``; ``s >= 0`` except in the ``gaussian``
    family, and for ``uniform`` with ``w > 1``.
    """
    fam, par = _family_arrays(family, param)
    rng = as_rng(rng)
    return _sample_throughput(fam.ravel(), par.ravel(), rng).reshape(fam.shape)


def _sample_throughput(fam, par, rng):
    """Unchecked kernel of :func:`sample_throughput` on flat arrays."""
    s = np.ones(fam.shape[0])
    present = np.bincount(fam, minlength=len(FAMILIES)) if fam.size else np.zeros(len(FAMILIES))
    for code in range(1, len(FAMILIES)):
        if not present[code]:
            continue
        m = fam == code
        if m.all():
            p = par
        else:
            p = par[m]
        if code == GAUSSIAN:
            d = 1.0 + p * rng.standard_normal(p.shape[0])
        elif code == UNIFORM:
            d = 1.0 + p * (2.0 * rng.random(p.shape[0]) - 1.0)
        elif code == GAMMA:
            d = rng.gamma(p, 1.0 / p)
        else:  # FIREFLY
            d = (rng.random(p.shape[0]) < p) / p
        if m.all():
            s = d
        else:
            s[m] = d
    return s


# ---------------------------------------------------------------------------- scenes
_LUMA = np.array([0.2126, 0.7152, 0.0722])
_LIGHT = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _shade(normal):
    """Ambient plus clamped-cosine shading in [0.2, 1]."""
    return 0.2 + 0.8 * np.clip(normal @ _LIGHT, 0.0, None)


def _lerp(a, b, t):
    return np.asarray(a) * (1 - t[..., None]) + np.asarray(b) * t[..., None]


def _const_maps(shape, *, mean=0.5, sigma=0.5):
    h, w = shape
    return dict(
        albedo=np.full((h, w, 3), mean), normal=np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3)).copy(),
        depth=np.ones((h, w)), mu=np.full((h, w, 3), mean), sigma=np.full((h, w, 3), sigma),
        family=np.full((h, w), CONST), param=np.zeros((h, w)),
    )


def _edges_maps(x, y, ii, jj):
    h, w = x.shape
    cell = (np.floor(4 * x) + np.floor(4 * y)).astype(int) % 2
    albedo = np.where(cell[..., None] == 1, [0.85, 0.3, 0.2], [0.2, 0.45, 0.85])
    normal = np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3)).copy()
    depth = np.full((h, w), 2.0)
    param = np.ones((h, w))  # exponential: relative std of one sample = 1
    disc = (x - 0.62) ** 2 + (y - 0.42) ** 2 < 0.22 ** 2
    albedo[disc] = [0.95, 0.8, 0.25]
    normal[disc] = _unit([0.35, -0.25, 0.9])
    depth[disc] = 1.2
    param[disc] = 3.0
    return dict(albedo=albedo, normal=normal, depth=depth, mu=albedo * _shade(normal)[..., None],
                sigma=np.zeros((h, w, 3)), family=np.full((h, w), GAMMA), param=param)


def _gradient_maps(x, y, ii, jj, *, gaussian=False):
    h, w = x.shape
    theta = (x - 0.5) * 2.6
    normal = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1)
    albedo = _lerp([0.85, 0.55, 0.25], [0.25, 0.55, 0.85], y)
    mu = albedo * _shade(normal)[..., None]
    out = dict(albedo=albedo, normal=normal, depth=1.5 - 0.5 * np.cos(theta), mu=mu)
    if gaussian:  # X_c = μ_c (1 + 0.5 N) + 0.1 μ_c N_c: Gaussian, relative std ≈ 0.51
        out.update(sigma=0.1 * mu, family=np.full((h, w), GAUSSIAN), param=np.full((h, w), 0.5))
    else:  # S ~ U(0, 2): relative std 1/sqrt(3)
        out.update(sigma=np.zeros((h, w, 3)), family=np.full((h, w), UNIFORM),
                   param=np.ones((h, w)))
    return out


def _texture_maps(x, y, ii, jj):
    h, w = x.shape
    # wavy stripes in *pixel* units (period 3.7 px across, wobbling with period 17 px)
    t = 0.5 + 0.5 * np.sin(2 * np.pi * (jj / 3.7 + 0.6 * np.sin(2 * np.pi * ii / 17.0)))
    albedo = _lerp([0.12, 0.1, 0.08], [0.9, 0.85, 0.7], t)
    normal = np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3)).copy()
    return dict(albedo=albedo, normal=normal, depth=np.full((h, w), 1.8),
                mu=albedo * _shade(normal)[..., None], sigma=np.zeros((h, w, 3)),
                family=np.full((h, w), UNIFORM), param=np.ones((h, w)))


def _firefly_maps(x, y, ii, jj):
    h, w = x.shape
    albedo = np.broadcast_to([0.55, 0.5, 0.6], (h, w, 3)).copy()
    normal = np.broadcast_to(_unit([-0.3, 0.25, 0.92]), (h, w, 3)).copy()
    # p from 0.01 (left/top) to 0.2 (right/bottom), log-linearly
    p = np.exp(np.log(0.01) + (np.log(0.2) - np.log(0.01)) * (x + y) / 2)
    return dict(albedo=albedo, normal=normal, depth=np.full((h, w), 1.0),
                mu=albedo * _shade(normal)[..., None] * (0.8 + 0.4 * y[..., None]),
                sigma=np.zeros((h, w, 3)), family=np.full((h, w), FIREFLY), param=p)


def _scene_maps(name, h, w):
    ii, jj = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64),
                         indexing="ij")
    y, x = (ii + 0.5) / h, (jj + 0.5) / w
    if name == "constant":
        return _const_maps((h, w))
    if name == "edges":
        return _edges_maps(x, y, ii, jj)
    if name == "gradient":
        return _gradient_maps(x, y, ii, jj)
    if name == "texture":
        return _texture_maps(x, y, ii, jj)
    if name == "fireflies":
        return _firefly_maps(x, y, ii, jj)
    # mixed: quadrants, each with local coordinates in [0, 1)
    xl, yl = (2 * x) % 1.0, (2 * y) % 1.0
    parts = [_edges_maps(xl, yl, ii, jj), _gradient_maps(xl, yl, ii, jj, gaussian=True),
             _texture_maps(xl, yl, ii, jj), _firefly_maps(xl, yl, ii, jj)]
    quad = (y >= 0.5).astype(int) * 2 + (x >= 0.5).astype(int)
    out = {}
    for key in parts[0]:
        out[key] = np.choose(quad[..., None] if parts[0][key].ndim == 3 else quad,
                             [p[key] for p in parts])
    return out


def _to_channels(rgb, c):
    """Map an RGB parameter image to ``c`` channels (luminance for 1, interpolation otherwise)."""
    if c == 3:
        return np.array(rgb, np.float64)
    if c == 1:
        return (rgb @ _LUMA)[..., None]
    t = np.linspace(0.0, 2.0, c)
    lo = np.minimum(np.floor(t).astype(int), 1)
    f = t - lo
    return rgb[..., lo] * (1 - f) + rgb[..., lo + 1] * f


# ---------------------------------------------------------------------------- renderer
class ToyRenderer:
    """Procedural images with exactly known per-pixel sample distributions.

    Parameters
    ----------
    scene : str
        One of :meth:`scenes` (default ``"mixed"``).
    width, height : int
        Image size in pixels.
    channels : int
        Channels ``C`` of the image (3 = RGB; 1 = luminance; others interpolate RGB).

    Attributes
    ----------
    height, width, channels : int
    name : str
        ``"toy:<scene>"``.
    scene : str

    Notes
    -----
    Samples are ``X_c = μ_c S + σ_c Z_c`` with a shared unit-mean throughput ``S`` per
    sample (law per pixel, see :data:`FAMILIES`) and independent normals ``Z_c``; see the
    module docstring for the closed-form moments.

    Examples
    --------
    >>> r = ToyRenderer("constant", width=8, height=4)
    >>> stats = r.render_uniform(16, seed=1)
    >>> stats.n.shape, stats.mean.shape, int(stats.total_samples)
    ((4, 8), (4, 8, 3), 512)
    >>> bool(np.allclose(r.true_var(), 0.25))
    True
    """

    def __init__(self, scene: str = "mixed", *, width: int = 64, height: int = 64,
                 channels: int = 3):
        if not isinstance(scene, str) or scene not in _SCENES:
            raise InputError(f"`scene` must be one of {', '.join(_SCENES)}; got {scene!r}.")
        self.width = as_int("width", width)
        self.height = as_int("height", height)
        self.channels = as_int("channels", channels)
        self.scene = scene
        self.name = f"toy:{scene}"
        maps = _scene_maps(scene, self.height, self.width)
        c = self.channels
        self._mu = np.ascontiguousarray(_to_channels(maps["mu"], c))
        self._sigma = np.ascontiguousarray(_to_channels(maps["sigma"], c))
        self._family = np.ascontiguousarray(maps["family"], dtype=np.int8)
        self._param = np.ascontiguousarray(maps["param"], dtype=np.float64)
        self._albedo = np.asarray(maps["albedo"], np.float32)
        self._normal = _unit(maps["normal"]).astype(np.float32)
        self._depth = np.asarray(maps["depth"], np.float32)
        _family_arrays(self._family, self._param)  # parameters in range (internal check)
        hw = self.height * self.width
        self._mu_flat = self._mu.reshape(hw, c)
        self._sigma_flat = self._sigma.reshape(hw, c)
        self._fam_flat = self._family.ravel()
        self._par_flat = self._param.ravel()
        self._noisy_flat = (self._sigma_flat > 0).any(axis=1)
        self._mu_t = np.ascontiguousarray(self._mu_flat.T)  # (C, H*W) for fast gathers
        self._sigma_t = np.ascontiguousarray(self._sigma_flat.T)
        self._var_s, self._m3_s, self._m4_s = throughput_central_moments(self._family, self._param)

    def __repr__(self):
        return (f"ToyRenderer({self.scene!r}, width={self.width}, height={self.height}, "
                f"channels={self.channels})")

    @staticmethod
    def scenes() -> dict[str, str]:
        """Scene names with one-line descriptions (iterating gives the names)."""
        return dict(_SCENES)

    # ------------------------------------------------------------------ truth
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(H, W, C)``."""
        return (self.height, self.width, self.channels)

    @property
    def family(self) -> np.ndarray:
        """``(H, W)`` family code of each pixel (index into :data:`FAMILIES`)."""
        return self._family.copy()

    @property
    def family_param(self) -> np.ndarray:
        """``(H, W)`` family parameter of each pixel (τ, w, k or p)."""
        return self._param.copy()

    def true_mean(self) -> np.ndarray:
        """Exact pixel mean ``E[X] = μ`` (``>= 0``), ``(H, W, C)`` float64."""
        return self._mu.copy()

    def true_var(self) -> np.ndarray:
        """Exact per-SAMPLE variance ``μ² Var[S] + σ²``, ``(H, W, C)`` float64.

        The variance of an ``n``-sample pixel mean is this divided by ``n``.
        """
        return self._mu ** 2 * self._var_s[..., None] + self._sigma ** 2

    def true_cov(self) -> np.ndarray:
        """Exact per-sample channel covariance ``μ_c μ_d Var[S] + δ_cd σ_c²``, ``(H, W, C, C)``."""
        cov = self._mu[..., :, None] * self._mu[..., None, :] * self._var_s[..., None, None]
        idx = np.arange(self.channels)
        cov[..., idx, idx] += self._sigma ** 2
        return cov

    def true_central_moment(self, order: int) -> np.ndarray:
        """Exact per-sample central moment ``E[(X − μ)^order]`` for order 2, 3 or 4.

        With ``A = S − 1`` and ``Z`` independent standard normal (odd moments of ``Z``
        vanish): ``E[(μA + σZ)³] = μ³ E[A³]`` and
        ``E[(μA + σZ)⁴] = μ⁴ E[A⁴] + 6 μ² σ² Var[S] + 3 σ⁴``.
        """
        mu, sg = self._mu, self._sigma
        if order == 2:
            return self.true_var()
        if order == 3:
            return mu ** 3 * self._m3_s[..., None]
        if order == 4:
            v = self._var_s[..., None]
            return mu ** 4 * self._m4_s[..., None] + 6 * mu ** 2 * sg ** 2 * v + 3 * sg ** 4
        raise InputError(f"`order` must be 2, 3 or 4; got {order!r}.")

    def features(self) -> dict[str, np.ndarray]:
        """Noise-free feature buffers: ``albedo`` and unit ``normal`` (H, W, 3), ``depth`` (H, W)."""
        return dict(albedo=self._albedo.copy(), normal=self._normal.copy(),
                    depth=self._depth.copy())

    # ------------------------------------------------------------------ sampling
    def sample_values(self, pixel_index, rng) -> np.ndarray:
        """Draw one sample per entry of ``pixel_index`` (the raw per-sample values).

        Parameters
        ----------
        pixel_index : (N,) int ndarray
            Flat row-major pixel index ``i * width + j`` of each sample.
        rng : numpy.random.Generator or int
            Source of randomness (an int seeds a new generator).

        Returns
        -------
        values : (N, C) float64 ndarray
            ``μ_c S + σ_c Z_c`` for each sample (independent across entries).
        """
        idx = np.asarray(pixel_index)
        if idx.ndim != 1 or not (np.issubdtype(idx.dtype, np.integer) or idx.size == 0):
            raise InputError("`pixel_index` must be a 1-D integer array of flat pixel indices; "
                             f"got dtype {idx.dtype}, shape {idx.shape}.")
        idx = idx.astype(np.intp, copy=False)
        hw = self.height * self.width
        if idx.size and (idx.min() < 0 or idx.max() >= hw):
            raise InputError(f"`pixel_index` must lie in [0, {hw}); got [{idx.min()}, {idx.max()}].")
        return self._draw(idx, as_rng(rng))

    def _draw(self, idx, rng):
        """Samples ``(N, C)``: the true mean plus :meth:`_draw_dev`."""
        dev = self._draw_dev(idx, rng)
        dev += np.take(self._mu_t, idx, axis=1)
        return np.ascontiguousarray(dev.T)

    def _draw_dev(self, idx, rng):
        """Deviations ``X − μ = μ (S − 1) + σ Z`` of one sample per index, ``(C, N)``."""
        s = _sample_throughput(self._fam_flat[idx], self._par_flat[idx], rng)
        s -= 1.0
        dev = np.take(self._mu_t, idx, axis=1)
        dev *= s
        noisy = self._noisy_flat[idx]
        if noisy.any():
            sub = idx if noisy.all() else idx[noisy]
            z = rng.standard_normal((self.channels, sub.shape[0]))
            z *= np.take(self._sigma_t, sub, axis=1)
            if noisy.all():
                dev += z
            else:
                dev[:, noisy] += z
        return dev

    def check_counts(self, counts) -> np.ndarray:
        """``counts`` as an ``(H, W)`` int64 map, or :class:`InputError` saying what is wrong."""
        a = as_float_array("counts", counts, ndim=2, dtype=np.float64)
        if a.shape != (self.height, self.width):
            raise InputError(f"`counts` must have the renderer's shape (H, W) = "
                             f"{(self.height, self.width)}; got {a.shape}.")
        check_finite("counts", a)
        check_nonnegative("counts", a)
        frac = a != np.round(a)
        if frac.any():
            raise InputError(f"`counts` must hold whole sample numbers; got {int(frac.sum())} "
                             "fractional values (round them, e.g. `statmc.sampling.counts_from_density`).")
        if a.size and a.max() >= MAX_COUNT:
            # the Mitsuba backend's bound; it also keeps the running sample totals (int64)
            # and the float64 counts exact.  2**40 samples per pixel were taken and drawn
            # for hours.
            raise InputError(f"`counts` must stay below 2**31 samples per pixel; got max "
                             f"{int(a.max())}.")
        return a.astype(np.int64)

    def render(self, counts, *, seed=0, progress: bool = False, features: bool = True,
               chunk_size: int = DEFAULT_CHUNK) -> PixelStats:
        """Draw exactly ``counts[i, j]`` samples in pixel ``(i, j)``.

        Parameters
        ----------
        counts : (H, W) array of non-negative whole numbers
            Samples per pixel (zeros allowed: those pixels get ``n = 0``, mean 0).
        seed : int, numpy SeedSequence or Generator, optional
            Seed of :func:`numpy.random.default_rng`; different seeds give independent
            renders, the same seed an identical one.
        progress : bool, optional
            Show a ``tqdm`` progress bar over samples.
        features : bool, optional
            Attach the noise-free ``albedo``, ``normal`` and ``depth`` buffers.
        chunk_size : int, optional
            Samples drawn at once; chunk statistics are merged exactly
            (:meth:`PixelStats.merge`), so this bounds memory without changing the law.

        Returns
        -------
        PixelStats
            With ``n == counts``, the channel co-moment ``m2_cross`` (so ``mean_cov`` is
            available) and ``meta`` holding ``renderer``, ``scene`` and ``seed``.
        """
        n = self.check_counts(counts)
        chunk = as_int("chunk_size", chunk_size)
        rng = as_rng(seed, "seed")
        h, w, c = self.shape
        flat = n.ravel()
        cum_end = np.cumsum(flat)
        cum_start = cum_end - flat
        total = int(cum_end[-1]) if flat.size else 0
        stats = PixelStats.empty(h, w, c)
        stats = PixelStats(stats.n, stats.mean, stats.m2, m2_cross=np.zeros((h, w, c, c)))
        bar = None
        if progress:
            from tqdm.auto import tqdm
            bar = tqdm(total=total, unit="sample", unit_scale=True, desc=self.name)
        try:
            for a in range(0, total, chunk):
                b = min(a + chunk, total)
                p0 = int(np.searchsorted(cum_end, a, side="right"))
                p1 = int(np.searchsorted(cum_start, b, side="left"))
                sub = np.clip(cum_end[p0:p1], a, b) - np.clip(cum_start[p0:p1], a, b)
                idx = np.repeat(np.arange(p0, p1, dtype=np.intp), sub)
                part = _stats_from_deviations(idx, self._draw_dev(idx, rng), self._mu_flat, (h, w))
                # Chan's merge keeps each mean between the two merged ones and a flat
                # channel exactly flat (see _stats_from_deviations' Notes), so the
                # per-chunk range guarantee carries over without tracking the ranges
                stats = part if a == 0 else stats.merge(part)
                if bar is not None:
                    bar.update(b - a)
        finally:
            if bar is not None:
                bar.close()
        feats = self.features() if features else {}
        meta = {"renderer": "toy", "scene": self.scene,
                "seed": seed if isinstance(seed, (int, np.integer)) or seed is None else repr(seed)}
        return PixelStats(stats.n, stats.mean, stats.m2, meta=meta, m2_cross=stats.m2_cross,
                          **feats)

    def render_uniform(self, spp: int, *, seed=0, progress: bool = False,
                       features: bool = True, chunk_size: int = DEFAULT_CHUNK) -> PixelStats:
        """:meth:`render` with ``spp`` samples in every pixel."""
        counts = np.full((self.height, self.width), as_int("spp", spp, lo=0), np.int64)
        return self.render(counts, seed=seed, progress=progress, features=features,
                           chunk_size=chunk_size)


def _stats_from_deviations(idx, dev, mu, shape):
    """PixelStats of samples given as deviations from the known pixel means.

    Parameters
    ----------
    idx : (N,) int ndarray
        Sorted flat pixel index of each sample (one run per pixel).
    dev : (C, N) float64 ndarray
        ``x − μ[idx]`` per sample; overwritten.
    mu : (H*W, C) ndarray
        The shift ``μ`` (here the exact pixel means).
    shape : (H, W)

    Returns
    -------
    PixelStats
        With ``m2_cross``.

    Notes
    -----
    Shifted sums: with ``d = x − μ``, ``mean = μ + Σd/n`` and ``M2 = Σd² − (Σd)²/n``; the
    channel co-moment likewise, ``M2_ab = Σ d_a d_b − Σd_a Σd_b / n``.
    Because the shift is the true mean, ``(Σd)²/n`` is only ``O(1/n)`` of ``Σd²``, so
    there is no catastrophic cancellation (unlike unshifted ``Σx² − (Σx)²/n``).  The
    plain two-pass reference is :meth:`PixelStats.from_pixel_samples`; the tests
    compare the two.  The samples are ``x = fl(μ + d)`` (as :meth:`ToyRenderer.sample_values`
    returns them), so their extremes are ``fl(μ + min d)`` and ``fl(μ + max d)`` (rounding
    is monotone).  Each mean is clipped to that range (the mean of real numbers lies in it;
    the shifted sum does only up to rounding), so a run whose samples are all equal in a
    channel gets exactly their value, and ``M2 = 0`` exactly in that channel and in its
    cross terms.

    Both guarantees survive :meth:`PixelStats.merge` of chunks, so :meth:`ToyRenderer.render`
    needs no correction after merging.  With ``a < b`` the merged mean is
    ``fl(a + fl(fl(b − a)·t))``, ``t = fl(n_b/n) ≤ (1 − 1/n)(1 + u)``: the increment is
    ``≥ 0`` and below ``(b − a)(1 − 1/n + u)(1 + u)² < b − a`` while ``n < 1/(3u) ≈ 3·10¹⁵``
    (``u = 2⁻⁵³``), so the sum lies in ``[a, b]`` before rounding and, ``a`` and ``b``
    being floats, after it (``t = 1`` only when ``n_a = 0``, where ``a = 0`` and the result
    is ``b`` exactly); the union's range contains ``[a, b]``.  A channel flat over the
    union is flat at one value in both parts, so ``δ = 0`` and its ``M2`` and cross terms
    stay exactly 0.  tests/test_toy.py checks the merge on adversarial pairs and chunked
    renders down to one sample per chunk.
    """
    h, w = shape
    c = dev.shape[0]
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    pix = idx[starts]
    counts = np.diff(np.r_[starts, idx.shape[0]])
    s1 = np.add.reduceat(dev, starts, axis=1)
    mu_run = mu[pix].T
    lo_run = mu_run + np.minimum.reduceat(dev, starts, axis=1)   # smallest sample x
    hi_run = mu_run + np.maximum.reduceat(dev, starts, axis=1)   # largest sample x
    flat = lo_run == hi_run  # all samples equal (e.g. a firefly pixel without a hit)
    ia, ib = np.triu_indices(c, 1)
    s_ab = np.empty((ia.size, starts.size))
    for p, (a, b) in enumerate(zip(ia, ib)):
        s_ab[p] = np.add.reduceat(dev[a] * dev[b], starts)
    dev *= dev
    s2 = np.add.reduceat(dev, starts, axis=1)
    n = np.zeros(h * w, np.int64)
    mean = np.zeros((h * w, c))
    m2 = np.zeros((h * w, c))
    n[pix] = counts
    mean[pix] = np.clip(mu_run + s1 / counts, lo_run, hi_run).T
    m2[pix] = np.where(flat, 0.0, np.maximum(s2 - s1 * s1 / counts, 0.0)).T
    cross = np.zeros((h * w, c, c))
    cross[pix[:, None], ia, ib] = np.where(flat[ia] | flat[ib], 0.0, s_ab - s1[ia] * s1[ib] / counts).T
    cross[:, ib, ia] = cross[:, ia, ib]
    k = np.arange(c)
    cross[:, k, k] = m2
    return PixelStats(n.reshape(h, w), mean.reshape(h, w, c), m2.reshape(h, w, c),
                      m2_cross=cross.reshape(h, w, c, c))
