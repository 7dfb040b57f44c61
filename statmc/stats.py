"""Per-pixel sufficient statistics of Monte Carlo samples, merged exactly.

A render is summarised per pixel by the sample count ``n``, the mean and ``M2`` (the sum
of squared deviations from the mean).  Two names for variance are used throughout, never
mixed up:

* **sample variance** ``s² = M2 / (n − 1)``: the variance of *one* sample
  (:attr:`PixelStats.sample_var`; pbrt-v4's ``Variance.*`` channels);
* **variance of the mean** ``s² / n``: the variance of the pixel estimate
  (:attr:`PixelStats.mean_var`).

Optionally the full per-pixel channel co-moment ``M2_cross[a, b] = Σ (x_a − mean_a)(x_b −
mean_b)`` is kept too (:attr:`PixelStats.m2_cross`, diagonal equal to ``M2``), giving the
**sample covariance** ``M2_cross / (n − 1)`` and the **covariance of the mean** (divided by
``n`` again).  Render noise is correlated across colour channels (one path throughput
scales R, G and B), and estimators such as MC-SURE for channel-mixing denoisers need it.

Passes are combined with the parallel update of Chan, Golub and LeVeque (1979), which is
exact: merging any split of the samples gives the single-pass statistics up to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import (InputError, as_float_array, as_int, as_number, check_finite,
                     check_nonnegative, check_same_shape)

__all__ = ["PixelStats", "replace_nonfinite", "MERGED_META_SUMS"]


def _pair_index(c):
    """Upper-triangle channel pairs ``(a, b)``, ``a < b``, in row-major order (RG, RB, GB)."""
    return np.triu_indices(c, 1)


def _full_from_pairs(name, pairs, diag):
    """``(H, W, C, C)`` symmetric matrix from upper-triangle ``pairs`` (H, W, P) and ``diag``."""
    h, w, c = diag.shape
    iu = _pair_index(c)
    if pairs.shape != (h, w, iu[0].size):
        raise InputError(f"`{name}` must be (H, W, C, C) = {(h, w, c, c)} or the channel pairs "
                         f"(H, W, C(C-1)/2) = {(h, w, iu[0].size)}; got {pairs.shape}.")
    # every entry written once by a slice assignment: faster than np.zeros + fancy indexing
    full = np.empty((h, w, c, c))
    for p, (a, b) in enumerate(zip(*iu)):
        full[..., a, b] = pairs[..., p]
        full[..., b, a] = pairs[..., p]
    for k in range(c):
        full[..., k, k] = diag[..., k]
    return full


def _as_pairs(name, a, mean_shape):
    """``a`` given as a full ``(H, W, C, C)`` matrix or as pairs ``(H, W, C(C-1)/2)``,
    returned as the float64 pairs ``a < b`` (row-major: RG, RB, GB)."""
    h, w, c = mean_shape
    iu = _pair_index(c)
    arr = as_float_array(name, a, ndim=(3, 4), dtype=np.float64)
    if arr.ndim == 4 and arr.shape == (h, w, c, c):
        arr = arr[..., iu[0], iu[1]]
    if arr.shape != (h, w, iu[0].size):
        raise InputError(f"`{name}` must be (H, W, C, C) = {(h, w, c, c)} or the channel pairs "
                         f"(H, W, C(C-1)/2) = {(h, w, iu[0].size)}; got {arr.shape}.")
    check_finite(name, arr)
    return arr


def _check_cross(m2_cross, m2):
    """Validate a full ``(H, W, C, C)`` co-moment against ``m2``; return it exactly symmetric
    with its diagonal set to ``m2`` (the two agree up to rounding when computed apart)."""
    a = as_float_array("m2_cross", m2_cross, ndim=4, dtype=np.float64)
    h, w, c = m2.shape
    if a.shape != (h, w, c, c):
        raise InputError(f"`m2_cross` must be (H, W, C, C) = {(h, w, c, c)}; got {a.shape}.")
    check_finite("m2_cross", a)
    k = np.arange(c)
    ia, ib = _pair_index(c)
    # rounding allowance: relative to the Cauchy-Schwarz bound sqrt(M2_a M2_b) per pair
    floor = 1e-15 * m2.max(initial=0.0) + 1e-300
    upper, lower = a[..., ia, ib], a[..., ib, ia]
    tol = 1e-6 * np.sqrt(m2[..., ia] * m2[..., ib]) + floor
    if np.any(np.abs(upper - lower) > tol):
        raise InputError(f"`m2_cross` must be symmetric in its last two axes; largest "
                         f"asymmetry {np.abs(upper - lower).max():.3g}.")
    diag = a[..., k, k]
    if np.any(np.abs(diag - m2) > 1e-6 * m2 + floor):
        raise InputError("the diagonal of `m2_cross` must equal `m2` (the per-channel M2); largest "
                         f"difference {np.abs(diag - m2).max():.3g}.")
    return _full_from_pairs("m2_cross", 0.5 * (upper + lower), m2)


_INT64_MAX = int(np.iinfo(np.int64).max)


def _as_counts(n: np.ndarray) -> np.ndarray:
    """A 2-D count map as int64: integers exactly (not through float64, which rounds
    counts above 2**53), whole-valued floats and bools converted; negative, fractional,
    non-finite and int64-overflowing counts are an :class:`InputError`."""
    if n.dtype.kind in "iu":
        check_nonnegative("n", n)
        if n.size and int(n.max()) > _INT64_MAX:
            raise InputError(f"`n` must fit in int64 (< 2**63); got max {int(n.max())}.")
        return n.astype(np.int64)
    n_f = as_float_array("n", n)
    check_finite("n", n_f)
    check_nonnegative("n", n_f)
    if np.any(n_f != np.round(n_f)):
        raise InputError("`n` must hold whole sample counts; got fractional values.")
    if n_f.size and n_f.max() >= 2.0 ** 63:
        raise InputError(f"`n` must fit in int64 (< 2**63); got max {n_f.max():.4g}.")
    return n_f.astype(np.int64)


def _check_feature(name, a, hw):
    """A feature buffer as float32: ``albedo`` and ``normal`` ``(H, W, 3)``, ``depth``
    ``(H, W)`` (or ``(H, W, 1)``), the shapes every consumer reads (OIDN, the networks'
    :func:`statmc.nn.pixel_features`, the EXR writer); an ``(H, W)`` albedo failed in
    ``pixel_features`` with NumPy's concatenate error, an ``(H, W, 1)`` one gave it two
    planes too few."""
    if a is None:
        return None
    arr = as_float_array(name, a, ndim=(2, 3)).astype(np.float32, copy=False)
    if arr.shape[:2] != tuple(hw):
        raise InputError(f"feature `{name}` must be {tuple(hw)} in height and width; got {arr.shape}.")
    if name == "depth" and arr.ndim == 3 and arr.shape[2] != 1:
        raise InputError(f"feature `depth` must be an (H, W) map; got shape {arr.shape}.")
    if name != "depth" and (arr.ndim != 3 or arr.shape[2] != 3):
        raise InputError(f"feature `{name}` must be an (H, W, 3) image; got shape {arr.shape}.")
    return arr


@dataclass(eq=False)
class PixelStats:
    """Sample count, mean and M2 per pixel, plus optional feature buffers.

    Parameters
    ----------
    n : (H, W) ndarray
        Samples in each pixel (non-negative integers, stored as ``int64``).
    mean : (H, W, C) ndarray
        Mean of the samples in each pixel (``float64``).
    m2 : (H, W, C) ndarray
        Sum of squared deviations from the mean (``float64``, ``>= 0``).
    albedo, normal : (H, W, 3) ndarray, optional
        Feature buffers (``float32``), carried along unchanged by merges.
    depth : (H, W) ndarray, optional
        Depth buffer (``float32``).
    meta : dict, optional
        Free-form provenance (renderer, scene, seed, ...).
    m2_cross : (H, W, C, C) ndarray, optional
        Channel co-moment ``Σ (x_a − mean_a)(x_b − mean_b)`` (``float64``), symmetric with
        diagonal ``m2``; ``None`` (default) when only per-channel statistics are known.
        Gives :attr:`sample_cov` and :attr:`mean_cov`.

    Notes
    -----
    Pixels with ``n == 0`` have mean and M2 equal to 0.  :attr:`sample_var` is 0 where
    ``n < 2`` (no spread can be measured from one sample): check :attr:`n` before trusting it.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = rng.normal(size=(8, 2, 3, 1))          # 8 samples of a 2x3 image
    >>> a = PixelStats.from_samples(x[:3]).merge(PixelStats.from_samples(x[3:]))
    >>> bool(np.allclose(a.sample_var, x.var(axis=0, ddof=1)))
    True
    """

    n: np.ndarray
    mean: np.ndarray
    m2: np.ndarray
    albedo: np.ndarray | None = None
    normal: np.ndarray | None = None
    depth: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    m2_cross: np.ndarray | None = None

    def __post_init__(self):
        n = np.asarray(self.n)
        if n.ndim != 2:
            raise InputError(f"`n` must be an (H, W) count map; got shape {n.shape}.")
        self.n = _as_counts(n)
        self.mean = as_float_array("mean", self.mean, ndim=3, dtype=np.float64)
        if self.mean.shape[:2] != self.n.shape:
            raise InputError(f"`mean` must be (H, W, C) with (H, W) = {self.n.shape}; got {self.mean.shape}.")
        self.m2 = as_float_array("m2", self.m2, ndim=3, dtype=np.float64)
        check_same_shape("m2", self.m2, "mean", self.mean.shape)
        check_finite("mean", self.mean)
        check_finite("m2", self.m2)
        check_nonnegative("m2", self.m2)
        if self.m2_cross is not None:
            self.m2_cross = _check_cross(self.m2_cross, self.m2)
        hw = self.n.shape
        self.albedo = _check_feature("albedo", self.albedo, hw)
        self.normal = _check_feature("normal", self.normal, hw)
        self.depth = _check_feature("depth", self.depth, hw)

    @classmethod
    def _with_built_cross(cls, n, mean, m2, cross, **features) -> "PixelStats":
        """``cls(n, mean, m2, m2_cross=cross, **features)`` for a ``cross`` that
        :func:`_full_from_pairs` built from pairs with the diagonal ``m2`` (this module's
        constructors): exactly symmetric with that diagonal already, so
        :func:`_check_cross` would return it unchanged (``0.5 (p + p) = p``) after a
        symmetry check, a diagonal check and a rebuild (0.5 s and two more ``(H, W, C, C)``
        arrays at 1920x1080).  Only finiteness is checked, with the same message.  Private:
        ``PixelStats(...)`` given an ``m2_cross`` checks it all."""
        stats = cls(n, mean, m2, **features)
        if cross is not None:
            check_finite("m2_cross", cross)
            stats.m2_cross = cross
        return stats

    # ------------------------------------------------------------------ constructors
    @classmethod
    def empty(cls, height: int, width: int, channels: int = 3) -> "PixelStats":
        """Statistics of no samples at all (``n = 0`` everywhere)."""
        height, width = as_int("height", height, lo=0), as_int("width", width, lo=0)
        channels = as_int("channels", channels)
        return cls(np.zeros((height, width), np.int64), np.zeros((height, width, channels)),
                   np.zeros((height, width, channels)))

    @classmethod
    def from_samples(cls, samples) -> "PixelStats":
        """Statistics of ``S`` samples in every pixel, ``samples`` of shape ``(S, H, W, C)``.

        Two passes (mean, then deviations), including the channel co-moment ``m2_cross``.
        """
        x = as_float_array("samples", samples, ndim=4, dtype=np.float64)
        check_finite("samples", x)
        s = x.shape[0]
        with np.errstate(over="ignore", invalid="ignore"):   # refused below by name
            mean = x.mean(axis=0) if s else np.zeros(x.shape[1:])
            d = x - mean
            cross = np.einsum("shwa,shwb->hwab", d, d)
            m2 = (d * d).sum(axis=0)
        try:
            return cls(np.full(x.shape[1:3], s, np.int64), mean, m2, m2_cross=cross)
        except InputError:
            _refuse_overflow("samples", mean, m2, "their mean or their squared deviations "
                             "from it (beyond ~1e154)")
            raise

    @classmethod
    def from_pixel_samples(cls, pixel_index, values, shape: tuple[int, int]) -> "PixelStats":
        """Statistics of samples with any number per pixel.

        Parameters
        ----------
        pixel_index : (N,) int ndarray
            Flat (row-major) pixel index of each sample, in ``[0, H*W)``.
        values : (N, C) ndarray
            The samples.
        shape : (H, W)
            Image size.

        Notes
        -----
        Two passes (means first, then products of deviations), so no cancellation;
        the channel co-moment ``m2_cross`` is computed too.
        """
        try:
            h, w = (as_int(f"shape[{k}]", v, lo=0) for k, v in enumerate(shape))
        except (TypeError, ValueError) as e:   # not a pair (InputError is a ValueError)
            if isinstance(e, InputError):
                raise
            raise InputError(f"`shape` must be (H, W), two integers >= 0; got {shape!r}.") from None
        idx = np.asarray(pixel_index)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
            raise InputError(f"`pixel_index` must be a 1-D integer array; got {idx.dtype} {idx.shape}.")
        vals = as_float_array("values", values, ndim=2, dtype=np.float64)
        if vals.shape[0] != idx.shape[0]:
            raise InputError(f"`values` must have one row per index ({idx.shape[0]}); got {vals.shape}.")
        if idx.size and (idx.min() < 0 or idx.max() >= h * w):
            raise InputError(f"`pixel_index` must lie in [0, {h * w}); got [{idx.min()}, {idx.max()}].")
        check_finite("values", vals)
        c = vals.shape[1]
        n = np.bincount(idx, minlength=h * w)
        safe = np.maximum(n, 1)[:, None]
        with np.errstate(over="ignore", invalid="ignore"):   # refused below by name
            mean = np.stack([np.bincount(idx, vals[:, k], minlength=h * w)
                             for k in range(c)], 1) / safe
            d = vals - mean[idx]
            m2 = np.stack([np.bincount(idx, d[:, k] * d[:, k], minlength=h * w)
                           for k in range(c)], 1)
            ia, ib = _pair_index(c)
            pairs = np.zeros((h * w, ia.size))
            for p, (a, b) in enumerate(zip(ia, ib)):
                pairs[:, p] = np.bincount(idx, d[:, a] * d[:, b], minlength=h * w)
        m2 = m2.reshape(h, w, c)
        mean = mean.reshape(h, w, c)
        _refuse_overflow("values", mean, m2, "their mean or their squared deviations from it "
                         "(beyond ~1e154)")            # before the pairs' own message
        cross = _full_from_pairs("m2_cross", pairs.reshape(h, w, -1), m2)
        return cls._with_built_cross(n.reshape(h, w), mean, m2, cross)

    @classmethod
    def from_sums(cls, n, sum_x, sum_x2, sum_xy=None) -> "PixelStats":
        """Statistics from per-pixel sums ``Σx`` and ``Σx²`` (e.g. one render pass).

        ``M2 = Σx² − (Σx)²/n``, clipped at 0.  Pass float64 sums: in float32 this
        difference cancels catastrophically at high sample counts.  Sums no samples can
        have, whose ``(Σx)²/n`` overflows float64 although ``Σx²`` is finite (it is at most
        ``Σx²``), are an :class:`~statmc.errors.InputError`.

        Parameters
        ----------
        n : (H, W) ndarray
        sum_x, sum_x2 : (H, W, C) ndarray
        sum_xy : (H, W, C, C) or (H, W, C(C-1)/2) ndarray, optional
            Cross sums ``Σ x_a x_b``: the full matrix (its diagonal is ignored, ``sum_x2``
            gives it) or the pairs ``a < b`` in row-major order (RG, RB, GB for RGB).
            Gives ``m2_cross[a, b] = Σ x_a x_b − Σx_a Σx_b / n`` (not clipped: covariances
            may be negative).
        """
        n_a = as_float_array("n", n, ndim=2, dtype=np.float64)
        s1 = as_float_array("sum_x", sum_x, ndim=3, dtype=np.float64)
        s2 = as_float_array("sum_x2", sum_x2, ndim=3, dtype=np.float64)
        check_same_shape("sum_x2", s2, "sum_x", s1.shape)
        check_finite("sum_x", s1)
        check_finite("sum_x2", s2)
        check_nonnegative("sum_x2", s2)                  # a sum of squares
        if s1.shape[:2] != n_a.shape:
            raise InputError(f"`sum_x` must be (H, W, C) with (H, W) = {n_a.shape}; got {s1.shape}.")
        empty = (n_a == 0)[..., None] & ((s1 != 0) | (s2 != 0))
        if empty.any():       # the mean was taken as sum_x / 1: contradictory input
            raise InputError(f"`sum_x` and `sum_x2` must be 0 where `n` = 0 (no samples); got "
                             f"nonzero sums in {int(empty.any(axis=2).sum())} pixels.")
        safe = np.maximum(n_a, 1)[..., None]
        mean = s1 / safe
        with np.errstate(over="ignore", invalid="ignore"):
            sq = s1 * mean                                   # (Σx)² / n
        if not np.isfinite(np.sum(sq)):
            # (Σx)²/n <= Σx² for any samples (Cauchy-Schwarz), so with a finite Σx² this
            # overflows only for sums no samples can have; it gave m2 = 0 silently and a
            # refusal of `m2_cross`, a name the caller never gave
            bad = int(np.count_nonzero(~np.isfinite(sq).all(axis=2)))
            raise InputError(
                f"`sum_x` and `sum_x2` must be sums of the same samples, (Σx)²/n <= Σx² "
                f"(finite); got (Σx)²/n beyond float64's range in {bad} pixels (`sum_x` up "
                f"to {float(np.max(np.abs(s1))):.3g}, `sum_x2` up to {float(np.max(s2)):.3g}).")
        m2 = np.maximum(s2 - sq, 0.0)
        cross = None
        if sum_xy is not None:
            ia, ib = _pair_index(s1.shape[2])
            sxy = _as_pairs("sum_xy", sum_xy, s1.shape)
            pairs = np.where((n_a > 0)[..., None], sxy - s1[..., ia] * mean[..., ib], 0.0)
            cross = _full_from_pairs("sum_xy", pairs, m2)
        return cls._with_built_cross(n if np.asarray(n).dtype.kind in "iu" else n_a, mean, m2,
                                     cross)

    @classmethod
    def from_mean_var(cls, mean, sample_var, n, *, sample_cov=None, **features) -> "PixelStats":
        """Statistics from a mean image, its *sample* variance and the counts (EXR files).

        ``sample_cov`` (optional): the per-pixel channel **sample covariance**, full
        ``(H, W, C, C)`` (its diagonal is ignored, ``sample_var`` gives it) or the pairs
        ``a < b`` ``(H, W, C(C-1)/2)`` (RG, RB, GB); then ``m2_cross = sample_cov (n − 1)``.
        """
        mean = as_float_array("mean", mean, ndim=3, dtype=np.float64)
        check_finite("mean", mean)      # before M2, whose overflow check would blame sample_var
        var = as_float_array("sample_var", sample_var, ndim=3, dtype=np.float64)
        check_same_shape("sample_var", var, "mean", mean.shape)
        check_finite("sample_var", var)
        check_nonnegative("sample_var", var)
        n_a = as_float_array("n", n, ndim=2, dtype=np.float64)
        check_same_shape("n", n_a, "mean[..., 0]", mean.shape[:2])
        check_finite("n", n_a)
        check_nonnegative("n", n_a)
        with np.errstate(over="ignore"):                       # refused below by name
            m2 = var * np.maximum(n_a - 1, 0)[..., None]
        try:
            cross = None
            if sample_cov is not None:
                pairs = _as_pairs("sample_cov", sample_cov, mean.shape)
                cross = _full_from_pairs("sample_cov", pairs * np.maximum(n_a - 1, 0)[..., None],
                                         m2)
            return cls._with_built_cross(n if np.asarray(n).dtype.kind in "iu" else n_a, mean,
                                         m2, cross, **features)
        except InputError:
            _refuse_overflow("sample_var", mean, m2, "M2 = sample_var · (n − 1) (beyond ~1.8e308)")
            raise

    # ------------------------------------------------------------------ shape
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(H, W, C)``."""
        return self.mean.shape

    @property
    def total_samples(self) -> int:
        """``n.sum()`` as an exact Python int (int64 sums overflow past 2**63)."""
        hi, lo = self.n >> 32, self.n & 0xFFFFFFFF        # each sum fits while H·W < 2**31
        return (int(hi.sum()) << 32) + int(lo.sum())

    # ------------------------------------------------------------------ variances
    @property
    def sample_var(self) -> np.ndarray:
        """Sample variance ``M2/(n−1)`` of one sample, ``(H, W, C)``; 0 where ``n < 2``."""
        return self.m2 / np.maximum(self.n - 1, 1)[..., None]

    @property
    def mean_var(self) -> np.ndarray:
        """Variance of the mean ``sample_var / n``, ``(H, W, C)``; 0 where ``n < 2``."""
        return self.sample_var / np.maximum(self.n, 1)[..., None]

    def require_variance(self, name: str = "stats", *, why: str = "for its variance of the mean",
                         hint: str = "") -> None:
        """Raise :class:`InputError` unless every pixel has the 2 samples a variance
        estimate needs (:attr:`mean_var` is 0 where ``n < 2``, which a method that uses it
        would take as exact); the message names ``name``, ``why`` and the pixel count,
        then ``hint``."""
        few = int((self.n < 2).sum())
        if few:
            raise InputError(f"`{name}` must have >= 2 samples in every pixel ({why}); got "
                             f"{few} pixels with fewer than 2 samples.{hint}")

    @property
    def has_cov(self) -> bool:
        """Whether the channel co-moment :attr:`m2_cross` is known."""
        return self.m2_cross is not None

    @property
    def sample_cov(self) -> np.ndarray:
        """Sample covariance ``M2_cross/(n−1)`` of one sample, ``(H, W, C, C)``; 0 where ``n < 2``.

        Raises :class:`~statmc.errors.InputError` when :attr:`m2_cross` is ``None``.
        """
        if self.m2_cross is None:
            raise InputError("these statistics carry no channel covariance (`m2_cross` is None): "
                             "render them with a backend that records it, or use the diagonal "
                             "`sample_var`/`mean_var`.")
        return self.m2_cross / np.maximum(self.n - 1, 1)[..., None, None]

    @property
    def mean_cov(self) -> np.ndarray:
        """Covariance of the mean ``sample_cov / n``, ``(H, W, C, C)``; 0 where ``n < 2``.

        Its diagonal is :attr:`mean_var`.  This is the ``Σ`` that SURE/MC-SURE
        (Firmino 2022 Eq. 1, 2) need for channel-mixing denoisers.
        """
        return self.sample_cov / np.maximum(self.n, 1)[..., None, None]

    # ------------------------------------------------------------------ merging
    def merge(self, other: "PixelStats") -> "PixelStats":
        """Exact union of two independent sets of samples (Chan et al. 1979).

        ``δ = mean_b − mean_a``, ``n = n_a + n_b``,
        ``mean = mean_a + δ n_b/n``, ``M2 = M2_a + M2_b + δ² n_a n_b / n``; the channel
        co-moment likewise, ``M2_cross = M2_cross_a + M2_cross_b + δ δᵀ n_a n_b / n``
        (Chan, Golub and LeVeque 1979, Eq. 2.1b; the outer-product form is the
        multivariate version), kept only when both sides have it (never invented).
        Features are taken from ``self`` when present, else from ``other``; ``meta`` is the
        union of both, ``self``'s entries winning, except the counters of a render
        (:data:`MERGED_META_SUMS`: ``samples``, ``seconds``, ``chunks``,
        ``nonfinite_samples``), which are added up when both sides have them as numbers,
        and ``samples_per_second``, then recomputed as ``samples / seconds``: the merge of
        an adaptive render's passes reports their totals, not the first pass's.
        """
        if not isinstance(other, PixelStats):
            raise InputError(f"`other` must be a statmc.PixelStats to merge; got "
                             f"{type(other).__name__}.")
        if other.shape != self.shape:
            raise InputError(f"`other` must have the shape of the statistics it is merged into, "
                             f"(H, W, C) = {self.shape}; cannot merge {other.shape} into it.")
        over = other.n > _INT64_MAX - self.n
        if np.any(over):
            raise InputError(f"`other` must add to the sample counts `n` without overflowing "
                             f"int64 (a merged count < 2**63); got {int(np.sum(over))} pixels "
                             f"whose summed counts overflow int64 (largest `n`: "
                             f"{int(self.n.max())} here and {int(other.n.max())} in `other`).")
        na = self.n.astype(np.float64)[..., None]
        nb = other.n.astype(np.float64)[..., None]
        n = na + nb
        safe = np.where(n > 0, n, 1.0)
        with np.errstate(over="ignore", invalid="ignore"):     # refused below by name
            delta = other.mean - self.mean
            mean = self.mean + delta * (nb / safe)
            wgt = na * nb / safe
            m2 = self.m2 + other.m2 + delta * delta * wgt
            cross = None
            if self.m2_cross is not None and other.m2_cross is not None:
                cross = (self.m2_cross + other.m2_cross
                         + delta[..., :, None] * delta[..., None, :] * wgt[..., None])
                k = np.arange(m2.shape[2])
                cross[..., k, k] = m2
        try:
            return PixelStats(
                self.n + other.n, mean, m2,
                albedo=self.albedo if self.albedo is not None else other.albedo,
                normal=self.normal if self.normal is not None else other.normal,
                depth=self.depth if self.depth is not None else other.depth,
                meta=_merged_meta(self.meta, other.meta),
                m2_cross=cross,
            )
        except InputError:
            _refuse_overflow("other", mean, m2, "the merged M2 = M2_a + M2_b + δ² n_a n_b / n "
                             "(means far apart, δ beyond ~1e154, or huge spreads)")
            raise

    __add__ = merge

    def with_features(self, **features) -> "PixelStats":
        """A copy with feature buffers (``albedo``, ``normal``, ``depth``) set or replaced."""
        unknown = set(features) - {"albedo", "normal", "depth"}
        if unknown:
            raise InputError(f"unknown feature buffers {sorted(unknown)}; expected albedo, normal, depth.")
        return replace(self, **features)

    def copy(self) -> "PixelStats":
        return PixelStats(self.n.copy(), self.mean.copy(), self.m2.copy(),
                          albedo=None if self.albedo is None else self.albedo.copy(),
                          normal=None if self.normal is None else self.normal.copy(),
                          depth=None if self.depth is None else self.depth.copy(),
                          meta=dict(self.meta),
                          m2_cross=None if self.m2_cross is None else self.m2_cross.copy())


#: ``meta`` entries that count what a render did, added up by :meth:`PixelStats.merge`
#: (the renderers write them: :mod:`statmc.mitsuba_backend`); ``samples_per_second`` is
#: recomputed from the sums.
MERGED_META_SUMS = ("samples", "seconds", "chunks", "nonfinite_samples")


def _merged_meta(a: dict, b: dict) -> dict:
    """``meta`` of ``a`` merged with ``b``: the union (``a`` winning) with the entries of
    :data:`MERGED_META_SUMS` summed where both are numbers (not bools)."""
    out = {**b, **a}
    summed = set()
    for key in MERGED_META_SUMS:
        x, y = a.get(key), b.get(key)
        if all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
               for v in (x, y)):
            out[key] = x + y
            summed.add(key)
    if "samples_per_second" in out and {"samples", "seconds"} <= summed:
        out["samples_per_second"] = (out["samples"] / out["seconds"] if out["seconds"] > 0
                                     else float("nan"))
    return out


def _refuse_overflow(name, mean, m2, what):
    """:class:`InputError` naming ``name`` when the ``mean`` or ``m2`` computed from it
    overflowed float64 (``PixelStats`` then refused them as "`m2` holds ... Inf values;
    replace them first", naming an array the caller never passed)."""
    bad = (~(np.isfinite(mean) & np.isfinite(m2))).any(axis=-1)
    if bad.any():
        raise InputError(f"`{name}` must give statistics within float64; got {int(bad.sum())} "
                         f"pixels where {what} overflows. Rescale the data first (e.g. divide "
                         f"by a power of 2).") from None


def check_stats(stats, name: str = "stats") -> None:
    """Raise :class:`InputError` unless ``stats`` is a :class:`PixelStats` (an image passed
    instead failed deep inside: an ndarray's ``mean`` is a method)."""
    if not isinstance(stats, PixelStats):
        raise InputError(f"`{name}` must be a statmc.PixelStats; got {type(stats).__name__}.")


def replace_nonfinite(a, value: float = 0.0):
    """Return ``(copy of a with NaN/Inf replaced by value, number replaced)``.

    ``value`` must be a finite number that ``a``'s dtype holds (1e300 in a float32 array
    was written as the Inf it replaced); integer arrays are copied as they are.
    """
    v = as_number("value", value)
    arr = np.array(a, copy=True)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise InputError(f"`a` must be a numeric array; got dtype {arr.dtype}.")
    if not np.issubdtype(arr.dtype, np.inexact):     # nothing non-finite in integers
        return arr, 0
    with np.errstate(over="ignore"):
        if not np.isfinite(arr.dtype.type(v)):
            raise InputError(f"`value` must be finite in the array's dtype {arr.dtype}; got "
                             f"{value!r}.")
    bad = ~np.isfinite(arr)
    arr[bad] = v
    return arr, int(bad.sum())
