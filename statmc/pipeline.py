"""Glue shared by the CLI, the demo and the benchmarks: render with a named sampler,
then reconstruct with a named method."""

from __future__ import annotations

import sys

import numpy as np

from .errors import InputError, as_int
from .stats import PixelStats, check_stats

__all__ = ["RECONSTRUCTIONS", "BIN_RECONSTRUCTIONS", "reconstruct_stats", "render_with_sampler",
           "render_bins", "merge_bins", "reconstruct_bins", "bin_seed"]

RECONSTRUCTIONS = ("none", "gem", "gaussian", "oidn", "progressive", "oidn+combine", "combine")
#: Reconstructions from ``B`` sample bins (:func:`reconstruct_bins`): the multi-buffer
#: combination kernel (Back 2020 Eq. 14) with GEM's full-sample kernel shared by the bins,
#: or OIDN applied to each bin.
BIN_RECONSTRUCTIONS = ("gem+bins", "oidn+bins")
#: Salt of the bin seeds: a bin's seed is a hash of ``(seed, b, salt)``, so the bins of
#: seed ``s`` do not reuse the numbers of ``render(seed=s)`` (a hashed seed may still equal
#: some other plain seed, with probability ~2⁻³¹ per pair).
_SALT_BINS = 0xB1B5
#: The samplers of :func:`render_with_sampler` that take a ``denoiser``.
DENOISER_SAMPLERS = ("denoising-aware", "expected-error")


def _check_renderer(renderer) -> None:
    """Refuse what is not a renderer (``height``, ``width``, ``render``) by name: None was
    "'NoneType' object has no attribute 'height'"."""
    if not all(hasattr(renderer, a) for a in ("height", "width", "render")):
        raise InputError(f"`renderer` must be a renderer (statmc.renderers.make_renderer: with "
                         f"height, width and render(counts, seed=...)); got "
                         f"{type(renderer).__name__}.")


def _check_gem_bias(gem_bias) -> None:
    """``gem_bias`` by its own name (gem's message said `bias`, which this module's
    callers never typed)."""
    from .gem import BIAS_MODES
    if gem_bias is not None and gem_bias not in BIAS_MODES:
        raise InputError(f"`gem_bias` must be one of {BIAS_MODES} or None (pooled); got "
                         f"{gem_bias!r}.")


def _denoiser_options(name, gamma, sigma, gem_bias=None) -> dict:
    """Options of :func:`statmc.progressive.bind_denoiser` for the denoiser ``name``."""
    if name == "gem":
        return {"gamma": gamma, "bias": gem_bias}
    return {"sigma": sigma} if name == "gaussian" else {}


def reconstruct_stats(stats: PixelStats, method: str = "gem", *, gamma: float = 0.2,
                      sigma: float = 1.0, denoiser: str = "oidn", seed: int = 0,
                      gem_bias: str | None = None):
    """Reconstruct an image from pixel statistics.

    ``method``: ``"none"`` (the pixel means), ``"gem"`` (Rousselle 2011), ``"gaussian"``
    (σ = ``sigma``), ``"oidn"``, ``"progressive"`` (Firmino 2022 with ``denoiser``),
    ``"oidn+combine"`` (OIDN improved by the combination kernel of Back 2020 with
    classical statistical weights and a SURE mix, :func:`statmc.combine.combine_denoised`),
    or ``"combine"`` (the same with ``denoiser``).
    ``gem_bias`` selects GEM's bias estimate (:func:`statmc.gem.reconstruct`'s ``bias``):
    ``None``/``"pooled"``, the default, or ``"paper"`` (Eq. 1 of Rousselle 2011, the only
    mode in which ``gamma`` changes the final reconstruction).
    Returns ``(image (H, W, C) float32, maps)`` where ``maps`` holds per-pixel diagnostics
    (for GEM: ``"scale"``, the selected scale index, and ``"sigma"``, its Gaussian σ with
    0 for the pixel filter; for progressive: ``"alpha"``, the gated mixing weight; for the
    combiner: ``"mix"``, the total weight Σλ given to the combined images, 0 = the
    denoiser's output).
    """
    check_stats(stats)
    if method not in RECONSTRUCTIONS:
        raise InputError(f"`method` must be one of {RECONSTRUCTIONS}; got {method!r}, an unknown "
                         "reconstruction.")
    _check_gem_bias(gem_bias)
    if method == "none":
        return stats.mean.astype(np.float32), {}
    if method == "gem":
        from .gem import reconstruct
        img, info = reconstruct(stats.mean.astype(np.float32), stats.mean_var.astype(np.float32),
                                gamma=gamma, n=stats.n, extra_output=True, bias=gem_bias)
        scales = np.asarray(info["scales"])
        sigma = np.asarray(info["sigmas"], np.float32)[scales]
        return img, {"scale": scales.astype(np.float32), "sigma": sigma}
    if method in ("gaussian", "oidn"):
        from .progressive import bind_denoiser
        f = bind_denoiser(method, stats, **({"sigma": sigma} if method == "gaussian" else {}))
        return np.asarray(f(stats.mean.astype(np.float32)), np.float32), {}
    if method == "progressive":
        # Firmino 2022: x + α'(y − x) with the classical α and the Student-t gate.
        from .progressive import bind_denoiser, progressive_denoise
        opts = _denoiser_options(denoiser, gamma, sigma, gem_bias)
        img, info = progressive_denoise(stats, bind_denoiser(denoiser, stats, **opts), rng=seed,
                                        extra_output=True)
        alpha = np.asarray(info["alpha_gated"], np.float32)  # (H, W, C): report its channel mean
        return img.astype(np.float32), {"alpha": alpha.mean(axis=-1)}
    if method in ("oidn+combine", "combine"):
        # Back 2020 Eq. 8 with statistical weights (Eq. 10/11) and a SURE mix with z.
        stats.require_variance(why=f"{method!r} needs a variance of the mean in every pixel "
                                   "for Eq. 10/11 and SURE")
        from .combine import combine_denoised
        from .progressive import bind_denoiser
        name = "oidn" if method == "oidn+combine" else denoiser
        if name == "gem":
            # GEM exposes its kernel: select once on the render, then combine with that
            # fixed linear filter (exact moments; Back 2020 §4.4 "Network Input").
            f = _gem_kernel(stats, gamma, gem_bias)
        else:
            f = bind_denoiser(name, stats, **_denoiser_options(name, gamma, sigma, gem_bias))
        # extra_output for the mix λ only: without sure_terms the per-pixel SURE terms
        # (2 J H W C float64, 0.2 GB at 1080p) are never allocated
        img, info = combine_denoised(stats.mean, stats.mean_var, f, rng=seed, extra_output=True)
        lam = np.asarray(info["mix"], np.float32)
        return img.astype(np.float32), {"mix": lam.sum(axis=-1)}
    raise AssertionError(method)       # every name of RECONSTRUCTIONS is handled above


def _gem_kernel(stats, gamma, gem_bias):
    """GEM's selection on ``stats`` (>= 2 samples in every pixel, checked by the callers)
    as a fixed linear filter (:class:`statmc.gem.SelectedFilter`)."""
    from .gem import selected_filter
    _, f = selected_filter(stats.mean.astype(np.float32), stats.mean_var.astype(np.float32),
                           gamma=gamma, n=stats.n, bias=gem_bias)
    return f


def bin_seed(seed: int, b: int) -> int:
    """Seed of sample bin ``b`` of a binned render with ``seed`` (distinct per bin)."""
    ss = np.random.SeedSequence([as_int("seed", seed, lo=0), as_int("b", b, lo=0), _SALT_BINS])
    return int(ss.generate_state(1, np.uint32)[0] >> 1)


def render_bins(renderer, spp: int, bins: int = 4, *, seed: int = 0,
                progress: bool = False) -> list[PixelStats]:
    """``bins`` independent uniform renders of ``spp // bins`` samples each: the sample
    bins of Back 2020 §4.4 (each pixel's samples split into disjoint subsets).

    ``spp`` must be a multiple of ``bins``.  Merge them (:func:`merge_bins`) for the
    full render.  With a renderer whose ``render`` takes ``first_sample`` (the Mitsuba
    backend), bin ``b`` holds samples ``b·m … (b+1)·m − 1`` (``m = spp // bins``) of every
    pixel's sequence of ``seed``, so the merged bins are the very samples of
    ``renderer.render(spp, seed=seed)``.  Otherwise bin ``b`` is a render with
    :func:`bin_seed` ``(seed, b)``.
    """
    from .adaptive import _takes_first_sample
    _check_renderer(renderer)
    spp = as_int("spp", spp, lo=1)
    bins = as_int("bins", bins, lo=2)
    seed = as_int("seed", seed, lo=0)
    if spp % bins:
        raise InputError(f"`spp` must be a multiple of `bins` (every bin gets the same number "
                         f"of samples); got spp={spp}, bins={bins}.")
    counts = np.full((renderer.height, renderer.width), spp // bins, np.int64)
    slices = _takes_first_sample(renderer)
    out = []
    for b in range(bins):
        if progress:
            print(f"  bin {b + 1}/{bins}: {spp // bins} spp", file=sys.stderr, flush=True)
        if slices:   # one seed: the bins' feature passes would be equal, render one
            out.append(renderer.render(counts, seed=seed, progress=progress,
                                       first_sample=b * counts, features=b == 0))
        else:
            out.append(renderer.render(counts, seed=bin_seed(seed, b), progress=progress))
    return out


def merge_bins(bins) -> PixelStats:
    """The full render of sample bins: their exact merge (``PixelStats.merge``), after
    checking that they are ``B >= 2`` :class:`PixelStats` with equal counts (equal-count
    subsets of every pixel's samples, Back 2020 §4.4)."""
    try:
        bins = list(bins)
    except TypeError:
        raise InputError(f"`bins` must be a list of at least 2 PixelStats; got "
                         f"{type(bins).__name__}.") from None
    if len(bins) < 2 or not all(isinstance(b, PixelStats) for b in bins):
        got = ", ".join(type(b).__name__ for b in bins[:3]) + (", ..." if len(bins) > 3 else "")
        raise InputError(f"`bins` must be a list of at least 2 PixelStats; got {len(bins)} "
                         f"item(s): {got or 'none'}.")
    for i, b in enumerate(bins[1:], 1):
        if b.shape != bins[0].shape or not np.array_equal(b.n, bins[0].n):
            raise InputError(f"bin {i} has other sample counts or shape than bin 0; the bins "
                             "must be equal-count subsets of every pixel's samples.")
    full = bins[0]
    for b in bins[1:]:
        full = full.merge(b)
    return full


def reconstruct_bins(bins, method: str = "gem+bins", *, gamma: float = 0.2, seed: int = 0,
                     gem_bias: str | None = None, mix: str | None = "local",
                     return_bins: bool = False):
    """Reconstruct from sample bins (a list of ``B >= 2`` :class:`PixelStats` with equal
    counts, e.g. :func:`render_bins`) by :func:`statmc.combine.combine_bins`.

    ``"gem+bins"``: GEM selects its kernels on the merged render and the kernel is shared
    by the bins (Back 2020 §4.4); ``"oidn+bins"``: OIDN (with the merged render's albedo
    and normal) applied to each bin.  ``mix``: the SURE mix of the result with the
    denoiser's output on the merged render (``combine_bins``' ``mix``; ``"local"``, the
    default, ``"global"`` or None).  Returns ``(image (H, W, C) float32, maps)`` as
    :func:`reconstruct_stats` (``"gem+bins"``: the selected ``"scale"`` and ``"sigma"``;
    with a mix, ``"mix"``: the weight λ of the combination, 0 = the denoiser's output);
    with ``return_bins`` also ``(ys, zs)``, the bin means and their denoised images
    ``(B, H, W, C)``.
    """
    from .combine import (DEFAULT_MIX_SIGMA, DEFAULT_MOMENT_SMOOTH, DEFAULT_PROBES,
                          DEFAULT_SIZE, DEFAULT_STENCIL, _combine_bins)
    if method not in BIN_RECONSTRUCTIONS:
        raise InputError(f"`method` must be one of {BIN_RECONSTRUCTIONS}; got {method!r}, an "
                         "unknown bin reconstruction.")
    _check_gem_bias(gem_bias)
    bins = list(bins)
    full = merge_bins(bins)
    full.require_variance("bins", why="merged, for the variance of the mean that the weights "
                                       "use")
    ys = np.stack([b.mean for b in bins])
    maps = {}
    if method == "gem+bins":
        f = _gem_kernel(full, gamma, gem_bias)
        sig = np.asarray(f.sigmas, np.float32)
        maps = {"scale": f.scales.astype(np.float32), "sigma": sig[f.scales]}
    else:
        from .progressive import bind_denoiser
        f = bind_denoiser("oidn", full)
    img, info = _combine_bins(ys, full.mean_var, f, size=DEFAULT_SIZE, stencil=DEFAULT_STENCIL,
                              probes=DEFAULT_PROBES, smooth=DEFAULT_MOMENT_SMOOTH, patch=2,
                              mix=mix, mix_sigma=DEFAULT_MIX_SIGMA, rng=seed, whole=False)
    zs = info["denoised"]
    if mix is not None:         # Σλ per pixel, 0 = the denoiser's output on the merged render
        lam = np.asarray(info["mix"], np.float32).sum(axis=-1)
        maps["mix"] = np.broadcast_to(lam, ys.shape[1:3]).copy()
    if return_bins:
        return img.astype(np.float32), maps, (ys, zs)
    return img.astype(np.float32), maps


def render_with_sampler(renderer, spp, *, sampler: str = "uniform", counts=None, seed: int = 0,
                        progress: bool = False, gamma: float = 0.2, initial_spp: int = 4,
                        iterations: int = 8, denoiser: str | None = None,
                        gem_bias: str | None = None, sigma: float = 1.0) -> PixelStats:
    """One render: fixed ``counts`` (uniform or a user map) or an adaptive ``sampler``.

    ``denoiser`` is the one the sampler optimises for: ``"oidn"`` (default), ``"gem"`` or
    ``"gaussian"`` for ``"denoising-aware"``; ``"gem"`` (default: GEM kernels chosen on the
    pilot pass and held fixed) or ``"gaussian"`` (a fixed σ = 1 Gaussian) for
    ``"expected-error"``.  ``gamma`` drives the ``"gem"`` sampler and the GEM pilot
    kernels of ``"expected-error"``; the denoising-aware sampler's GEM denoiser gets
    ``gamma`` and ``gem_bias`` (``None``/``"pooled"`` or ``"paper"``, as in
    :func:`reconstruct_stats`), its Gaussian ``sigma``.
    """
    from .adaptive import SAMPLERS
    _check_renderer(renderer)
    if not isinstance(sampler, str) or sampler not in SAMPLERS:
        raise InputError(f"`sampler` must be one of {sorted(SAMPLERS)}; got {sampler!r}, an "
                         "unknown sampler.")
    _check_gem_bias(gem_bias)
    if denoiser is not None and sampler not in DENOISER_SAMPLERS:
        raise InputError(f"`denoiser` is the denoiser of the 'denoising-aware' and "
                         f"'expected-error' samplers; sampler={sampler!r} does not use it: "
                         "leave it None.")
    if sampler == "uniform":
        if counts is None:  # 2.5 used to become 2 spp without a word
            counts = np.full((renderer.height, renderer.width), as_int("spp", spp), np.int64)
        return renderer.render(counts, seed=seed, progress=progress)
    if counts is not None:
        raise InputError(f"`counts` (a sample map) fixes the sample counts, which an adaptive "
                         f"`sampler` chooses; got counts with sampler={sampler!r}: pass "
                         "counts=None or sampler='uniform'.")
    from .adaptive import adaptive_render
    opts = {"gamma": gamma} if sampler == "gem" else {}
    if sampler == "denoising-aware":
        name = denoiser or "oidn"
        dopts = _denoiser_options(name, gamma, sigma, gem_bias)
        if dopts:  # rebuilt from the current statistics at every iteration, with the options
            from .progressive import bind_denoiser
            opts = {"denoiser": lambda st: bind_denoiser(name, st, **dopts)}
        else:
            opts = {"denoiser": name}
    elif sampler == "expected-error":
        if denoiser not in (None, "gem", "gaussian"):
            raise InputError(f"`denoiser` must be a kernel denoiser, 'gem' or 'gaussian' (or "
                             f"None: 'gem'), for the expected-error sampler; got {denoiser!r}.")
        opts = {"kernels": "gem", "gem_options": {"gamma": gamma}} if denoiser in (None, "gem") else {}
    res = adaptive_render(renderer, spp, sampler=sampler, initial_spp=initial_spp,
                          iterations=iterations, seed=seed, progress=progress, **opts)
    res.stats.meta.update(seconds_sampler=res.seconds_sampler, seconds_render=res.seconds_render,
                          passes=len(res.counts))
    return res.stats
