"""One array type per kernel argument: inputs normalised before they reach a numba kernel.

numba compiles a kernel once per combination of argument types, and an array's type holds
its dtype, its layout (``'C'``, ``'F'`` or ``'A'`` for any strides) and whether it is
read-only.  A read-only, Fortran-ordered, strided or foreign-byte-order input therefore
cost a fresh compilation of the whole kernel (tens of seconds for the combination
weights) with numbers identical to the usual case.  The functions below give each input
the one type the kernel is compiled for, copying only where a view cannot.
"""

from __future__ import annotations

import numpy as np


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a`` itself when it is read-only, else a read-only view of it (no copy)."""
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


def _native_c(a, dtype):
    a = np.ascontiguousarray(a, dtype=dtype)
    if not a.dtype.isnative:                 # ascontiguousarray keeps '>f8'
        a = a.astype(a.dtype.newbyteorder("="))
    return a


def readonly(a, dtype=None) -> np.ndarray:
    """``a`` as a C-contiguous, native-byte-order, read-only array of ``dtype``.

    A view when ``a`` is already C-contiguous, native and of that dtype; otherwise one
    copy (the size of ``a``); a broadcast array is materialised (use
    :func:`readonly_strided` where the kernel reads it through its strides).
    """
    return _frozen(_native_c(a, dtype))


def readonly_strided(a) -> np.ndarray:
    """``a`` as a read-only array for a kernel that reads it through its strides (numba's
    ``'A'`` layout), without copying a large non-contiguous one: a C-contiguous array stays
    ``'C'``; a broadcast (``np.broadcast_to``, e.g. one fixed kernel for every pixel) or
    strided view (e.g. permuted network output) stays a view, typed ``'A'``; only a
    Fortran-ordered or foreign-byte-order array is copied to C (:func:`readonly`).  So a
    kernel sees two layouts at most.
    """
    a = np.asarray(a)
    if a.dtype.isnative and (a.flags.c_contiguous or not a.flags.f_contiguous):
        return _frozen(a)
    return readonly(a)


def writable(a, dtype=None) -> np.ndarray:
    """``a`` as a C-contiguous, native-byte-order, writable array of ``dtype``: ``a``
    itself when it is one, else a copy.  For kernels that also receive arrays the library
    allocates (writable), so a read-only caller's array does not add a second type."""
    a = _native_c(a, dtype)
    return a if a.flags.writeable else a.copy()
