"""Memory checks shared by the test files: the peak of the allocations a call makes, and
the comparison of a kernel cut to the image with the whole kernel it replaces."""

from __future__ import annotations

import tracemalloc

import numpy as np


def traced_peak(fn, *args, **options):
    """``(fn(*args, **options), peak)``: ``peak`` is the most memory (bytes) the call held
    at once in allocations tracemalloc sees (NumPy's arrays included)."""
    tracemalloc.start()
    try:
        out = fn(*args, **options)
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def assert_central_part(cut, whole, radii):
    """``cut`` (…, 2c+1, 2c+1) kernels equal the central part of ``whole`` (…, 2r+1, 2r+1)
    to rounding, and every tap of ``whole`` outside that part is exactly 0; ``radii`` is
    the ``(r, c)`` the test expects."""
    r, c = whole.shape[-1] // 2, cut.shape[-1] // 2
    assert (r, c) == tuple(radii)
    np.testing.assert_allclose(cut, whole[..., r - c:r + c + 1, r - c:r + c + 1],
                               rtol=1e-12, atol=0)
    inner = np.zeros(whole.shape[-2:], bool)
    inner[r - c:r + c + 1, r - c:r + c + 1] = True
    assert np.all(whole[..., ~inner] == 0)
