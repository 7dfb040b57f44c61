"""Thread control for the numba kernels: small problems run on the calling thread."""

from __future__ import annotations

from contextlib import contextmanager

import numba


@contextmanager
def serial_below(work: int, threshold: int):
    """Run the block on one numba thread when ``work < threshold`` (restored after).

    Waking numba's worker threads costs milliseconds on a busy machine, more than a
    small kernel takes serially; each kernel module sets its own ``threshold``.
    """
    if work >= threshold:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)
