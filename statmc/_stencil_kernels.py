"""Private numba kernel for common-random-number renders: neighbour products of one pass.

Only :meth:`statmc.mitsuba_backend.MitsubaRenderer.render_crn` calls it; the caller owns
the arrays (float64, C-contiguous).  :func:`add_neighbour_products_numpy` is the plain
NumPy reference the tests compare against.

``prod[y, x, R + dy, R + dx, c] += img[y, x, c] · img[y + dy, x + dx, c]`` for every
offset ``|dy|, |dx| <= R`` whose neighbour lies inside the image (the others are left
as they are): the sums behind the covariance stencil of a CRN render.
"""

from __future__ import annotations

from numba import njit, prange


@njit(parallel=True, cache=True, fastmath={"nsz", "contract"})
def add_neighbour_products(prod, img, R):
    """Compiled; rows of the output in parallel (each row writes only its own slots)."""
    H, W, C = img.shape
    for y in prange(H):
        for dy in range(-R, R + 1):
            yy = y + dy
            if yy < 0 or yy >= H:
                continue
            for x in range(W):
                lo = max(-R, -x)
                hi = min(R, W - 1 - x)
                for dx in range(lo, hi + 1):
                    for c in range(C):
                        prod[y, x, R + dy, R + dx, c] += img[y, x, c] * img[yy, x + dx, c]


def offset_slices(n: int, d: int):
    """``(dst, src)`` slices of the indices ``i`` with ``0 <= i + d < n`` and of ``i + d``
    (empty when ``|d| >= n``)."""
    lo, hi = max(0, -d), max(0, min(n, n - d))
    hi = max(hi, lo)
    return slice(lo, hi), slice(lo + d, hi + d)


def add_neighbour_products_numpy(prod, img, R):
    """NumPy reference of :func:`add_neighbour_products` (shifted slices per offset)."""
    H, W = img.shape[:2]
    for dy in range(-R, R + 1):
        yd, ys = offset_slices(H, dy)
        for dx in range(-R, R + 1):
            xd, xs = offset_slices(W, dx)
            prod[yd, xd, R + dy, R + dx] += img[yd, xd] * img[ys, xs]
    return prod


__all__ = ["add_neighbour_products", "add_neighbour_products_numpy", "offset_slices"]
