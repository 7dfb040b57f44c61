"""Awkward but valid images for the property tests (hypothesis) of several test files:
signed or non-negative means at magnitudes from 0 to 1e15, a flat block (all black at
magnitude 0), heavy-tailed variances with a share of exact zeros, shapes down to 1x1."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

#: Magnitudes of the means: all black, tiny, ordinary, huge.
SCALES = (0.0, 1e-20, 1.0, 1e15)


def any_image(seed, h, w, c, scale, zero_frac, *, dtype=None, nonneg=False, bins=None):
    """``(mean, var)`` of shape ``(h, w, c)``: means of magnitude up to ``scale`` (signed
    unless ``nonneg``; ``bins`` gives them a leading axis of that length) with the top-left
    quarter flat, and heavy-tailed (gamma 0.3) variances, a fraction ``zero_frac`` of the
    pixels exactly 0.  ``dtype`` casts both (default: float64)."""
    rng = np.random.default_rng(seed)
    lead = () if bins is None else (bins,)
    m = rng.normal(size=lead + (h, w, c)) * scale * rng.gamma(0.5, 1, size=(h, w, 1))
    if nonneg:
        m = np.abs(m)
    v = rng.gamma(0.3, 1, size=(h, w, c)) * (scale ** 2 + 1e-30)
    v[rng.uniform(size=(h, w)) < zero_frac] = 0.0
    m[..., : h // 2, : w // 2, :] = m[..., :1, :1, :]          # a flat region
    if dtype is not None:
        m, v = m.astype(dtype), v.astype(dtype)
    return m, v


def image_args(max_side, *, dtype=False, scales=SCALES):
    """Hypothesis strategies for :func:`any_image`'s arguments (``seed, h, w, c, scale,
    zero_frac``, and ``dtype`` float32/float64 when asked), sides 1 to ``max_side``."""
    args = dict(seed=st.integers(0, 2 ** 31), h=st.integers(1, max_side),
                w=st.integers(1, max_side), c=st.integers(1, 3),
                scale=st.sampled_from(list(scales)),
                zero_frac=st.sampled_from([0.0, 0.3, 1.0]))
    if dtype:
        args["dtype"] = st.sampled_from([np.float32, np.float64])
    return args
