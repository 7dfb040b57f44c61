"""Glue shared by the CLI, the demo and the benchmarks: render with a named sampler,
then reconstruct with a named method."""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .stats import PixelStats

__all__ = ["RECONSTRUCTIONS", "reconstruct_stats", "render_with_sampler"]

RECONSTRUCTIONS = ("none", "gem", "gaussian")


def reconstruct_stats(stats: PixelStats, method: str = "gem", *, gamma: float = 0.2,
                      sigma: float = 1.0):
    """Reconstruct an image from pixel statistics.

    Returns ``(image (H, W, C) float32, maps)`` where ``maps`` holds per-pixel diagnostics
    (for GEM: ``"scale"``, the selected scale index, and ``"sigma"``, its Gaussian σ with
    0 for the pixel filter).
    """
    if method == "none":
        return stats.mean.astype(np.float32), {}
    if method == "gem":
        from .gem import reconstruct
        img, info = reconstruct(stats.mean.astype(np.float32), stats.mean_var.astype(np.float32),
                                gamma=gamma, n=stats.n, extra_output=True)
        scales = np.asarray(info["scales"])
        sigma = np.asarray(info["sigmas"], np.float32)[scales]
        return img, {"scale": scales.astype(np.float32), "sigma": sigma}
    if method == "gaussian":
        from .denoisers import gaussian
        return gaussian(sigma)(stats.mean.astype(np.float32)), {}
    raise InputError(f"unknown reconstruction {method!r}; expected one of {RECONSTRUCTIONS}.")


def render_with_sampler(renderer, spp, *, sampler: str = "uniform", counts=None, seed: int = 0,
                        progress: bool = False, gamma: float = 0.2, initial_spp: int = 4,
                        iterations: int = 8) -> PixelStats:
    """One render: fixed ``counts`` (uniform or a user map) or an adaptive ``sampler``."""
    if sampler == "uniform":
        if counts is None:
            counts = np.full((renderer.height, renderer.width), int(spp), np.int64)
        return renderer.render(counts, seed=seed, progress=progress)
    if counts is not None:
        raise InputError(f"a sample map fixes the counts; it cannot be combined with --sampler {sampler}.")
    from .adaptive import adaptive_render
    opts = {"gamma": gamma} if sampler == "gem" else {}
    res = adaptive_render(renderer, spp, sampler=sampler, initial_spp=initial_spp,
                          iterations=iterations, seed=seed, progress=progress, **opts)
    res.stats.meta.update(seconds_sampler=res.seconds_sampler, seconds_render=res.seconds_render,
                          passes=len(res.counts))
    return res.stats
