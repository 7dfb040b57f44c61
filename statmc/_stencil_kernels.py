"""Private numba kernel for covariance stencils: neighbour products of two images.

``prod[y, x, R + dy, R + dx, c] += a[y, x, c] · b[y + dy, x + dx, c]`` for every offset
``|dy|, |dx| <= R`` whose neighbour lies inside the image (the others are left as they
are).  Summed over samples or probes, these are the sums behind a covariance stencil
``cov(a_p, b_{p+v})`` in the convention of :func:`statmc.combine.combine_bias_variance`.
Callers: :meth:`statmc.mitsuba_backend.MitsubaRenderer.render_crn` (``a = b`` = one pass
of a common-random-number render) and :func:`statmc.combine.denoiser_moments`
(``J v`` with itself and with the probe ``v``).  Callers own the arrays (float64,
C-contiguous, same shape).  :func:`add_neighbour_products_numpy` is the plain NumPy
reference the tests compare against; both do one multiply and one add per element in the
same order (no fused multiply-add), so they agree to the bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._kernel_inputs import readonly
from ._task_threads import run_rows
from ._threads import wait_passively_in_numba

wait_passively_in_numba()


def add_neighbour_products(prod, a, b, R):
    """Compiled ``prod[y, x, R + dy, R + dx, c] += a[y, x, c] · b[y + dy, x + dx, c]`` for
    ``|dy|, |dx| <= R`` inside the image: :func:`add_neighbour_products_sum` with one pair."""
    add_neighbour_products_sum(prod, a[None], b[None], R, np.ones(1, np.bool_))


def add_neighbour_products_sum(prod, a, b, R, use):
    """Compiled ``add_neighbour_products(prod, a[i], b[i], R)`` for every ``i`` with
    ``use[i]``, in order (``a``, ``b`` ``(K, H, W, C)``): each element of ``prod`` is read
    once, gets its ``K`` products added one by one in the same order, and is written once,
    so the sums are those of the ``K`` calls to the bit (``prod`` makes one trip through
    memory instead of ``K``).

    ``a``, ``b`` and ``use`` reach the kernel read-only, C-contiguous and native
    (:func:`readonly`; a copy of a strided slab such as ``jv[:, s0:s1]`` is ``m²`` times
    smaller than ``prod``), so a slab view does not compile the kernel once more.  Chunks of
    rows run on several threads (:func:`statmc._task_threads.run_rows`: a serial
    kernel, no parallel loop to compile).
    """
    run_rows(_add_neighbour_products_sum, 0, a.shape[1], prod, readonly(a), readonly(b),
             int(R), readonly(use, np.bool_))


@njit(cache=True, nogil=True)
def _add_neighbour_products_sum(prod, a, b, R, use, ya, yb):  # pragma: no cover - compiled
    """Rows ``ya .. yb - 1`` of :func:`add_neighbour_products_sum`."""
    K, H, W, C = a.shape
    for y in range(ya, yb):
        for dy in range(-R, R + 1):
            yy = y + dy
            if yy < 0 or yy >= H:
                continue
            for x in range(W):
                lo = max(-R, -x)
                hi = min(R, W - 1 - x)
                for dx in range(lo, hi + 1):
                    for c in range(C):
                        t = prod[y, x, R + dy, R + dx, c]
                        for i in range(K):
                            if use[i]:
                                t += a[i, y, x, c] * b[i, yy, x + dx, c]
                        prod[y, x, R + dy, R + dx, c] = t


def shift_slices(H, W, oy, ox):
    """Slices ``(dst, src)`` with ``dst[p] <- src[p + (oy, ox)]`` where both are inside an
    ``H x W`` image (empty when the offset is at least the image size)."""
    ny = max(0, H - abs(oy))
    nx = max(0, W - abs(ox))
    y0, x0 = max(0, -oy), max(0, -ox)
    dst = (slice(y0, y0 + ny), slice(x0, x0 + nx))
    src = (slice(y0 + oy, y0 + oy + ny), slice(x0 + ox, x0 + ox + nx))
    return dst, src


def add_neighbour_products_numpy(prod, a, b, R):
    """NumPy reference of :func:`add_neighbour_products` (shifted slices per offset)."""
    H, W = a.shape[:2]
    for dy in range(-R, R + 1):
        for dx in range(-R, R + 1):
            dst, src = shift_slices(H, W, dy, dx)
            prod[dst + (R + dy, R + dx)] += a[dst] * b[src]
    return prod


def add_neighbour_products_sum_numpy(prod, a, b, R, use):
    """NumPy reference of :func:`add_neighbour_products_sum`: the reference above once per
    used ``i``, in order."""
    for i in range(a.shape[0]):
        if use[i]:
            add_neighbour_products_numpy(prod, a[i], b[i], R)
    return prod


__all__ = ["add_neighbour_products", "add_neighbour_products_numpy", "add_neighbour_products_sum",
           "add_neighbour_products_sum_numpy", "shift_slices"]
