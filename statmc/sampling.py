"""Turning real-valued sampling maps into integer per-pixel counts.

A sampling map says where samples should go; a renderer needs whole numbers.  The counts
produced here always sum to the budget exactly, and are unbiased: ``E[counts] = map``
scaled to the budget.
"""

from __future__ import annotations

import numpy as np

from .errors import (MAX_BUDGET, InputError, as_float_array, as_rng, as_whole, check_finite,
                     check_nonnegative)

__all__ = ["counts_from_density"]


def counts_from_density(density, budget: int, *, min_count: int = 0, rng=None) -> np.ndarray:
    """Integer counts proportional to ``density`` summing exactly to ``budget``.

    Parameters
    ----------
    density : (H, W) ndarray
        Non-negative, finite sampling density (any scale).  An all-zero map is uniform.
    budget : int
        Total number of samples to hand out (``0 <= budget <= 2**53``, where float64
        targets stay exact; a whole-valued float is accepted, a fractional one is an
        :class:`~statmc.errors.InputError`).
    min_count : int, optional
        Samples every pixel gets first (taken out of the budget), ``>= 0``.
    rng : numpy Generator or int, optional
        Randomness of the rounding.

    Returns
    -------
    counts : (H, W) int64 ndarray with ``counts.sum() == budget``.

    Notes
    -----
    Systematic rounding: each pixel gets ``floor(t_i)`` of its target ``t_i`` and the
    remaining samples go to pixels picked by one stratified sweep over the cumulative
    fractional parts, so pixel ``i`` gets one more with probability ``t_i − floor(t_i)``.
    """
    d = as_float_array("density", density, ndim=2, dtype=np.float64)
    check_finite("density", d)
    check_nonnegative("density", d)
    budget = as_whole("budget", budget, what="number of samples", hi=MAX_BUDGET)
    min_count = as_whole("min_count", min_count, what="number of samples")
    if d.size == 0:
        if budget:
            raise InputError(f"`density` must have pixels to place `budget`={budget} samples "
                             f"in; got shape {d.shape}.")
        return np.zeros(d.shape, np.int64)
    base_total = min_count * d.size
    if base_total > budget:
        raise InputError(f"`budget` must be at least `min_count` × pixels = {min_count} × "
                         f"{d.size} = {base_total} samples; got {budget}.")
    with np.errstate(over="ignore"):
        total = d.sum()
    if not np.isfinite(total):      # values near float64's maximum: only the sum overflows
        d = d / d.max()             # (it was a ZeroDivisionError); any scale is the same map
    return _systematic_round(d, budget - base_total, min_count, as_rng(rng))


def _systematic_round(d, rest, min_count, rng):
    """Checked inputs -> counts: two compiled sweeps (``_filter_kernels.round_targets``,
    ``place_points``); NumPy reference :func:`_systematic_round_reference`."""
    from ._filter_kernels import place_points, round_targets
    flat = np.ascontiguousarray(d).ravel()
    counts = np.empty(flat.size, np.int64)
    cum = np.empty(flat.size)
    # d.sum() in NumPy (pairwise), exactly as in the reference
    r = int(round_targets(flat, float(flat.sum()), int(rest), int(min_count), counts, cum))
    if r > 0:
        place_points(cum, r, float(rng.uniform()), counts)
    return counts.reshape(d.shape)


def _systematic_round_reference(d, rest, min_count, rng):
    """NumPy reference of :func:`_systematic_round`."""
    total = d.sum()
    # d / total first: rest / total overflows for subnormal totals
    target = (np.full(d.shape, rest / d.size) if total <= 0 else (d / total) * rest).ravel()
    base = np.floor(target)
    frac = target - base
    r = rest - int(base.sum())
    counts = base.astype(np.int64) + int(min_count)
    if r > 0:
        cum = np.cumsum(frac)
        cum *= r / cum[-1]  # guard against rounding drift: exactly r points fit
        points = rng.uniform() + np.arange(r)
        hit = np.searchsorted(cum, points, side="right")
        counts += np.bincount(np.minimum(hit, d.size - 1), minlength=d.size)
    return counts.reshape(d.shape)
