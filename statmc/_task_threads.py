"""Serial numba kernels run over a range of tasks on several threads.

A numba parallel loop (``prange``) costs compile time beyond its body: numba's parallel
lowering compiles the loop body as a function of its own and links it, with every
function it calls, into the kernel, and LLVM optimises the linked code once more at each
level.  For the filter passes that was about 10 s CPU per dtype on a cold cache against
5 s for the same passes in one serial function.  :func:`run_tasks` instead calls a
serial ``nogil`` kernel ``kernel(t0, t1, *args)`` on contiguous task ranges from a few
Python threads; the kernel releases the GIL, so they run in parallel.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba

_POOL = None
_POOL_LOCK = threading.Lock()


def _forget_pool():
    """In a forked child: the parent's worker threads do not exist there."""
    global _POOL, _POOL_LOCK
    _POOL = None
    _POOL_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def _task_pool():
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max(numba.config.NUMBA_NUM_THREADS - 1, 1),
                                       thread_name_prefix="statmc-kernel")
        return _POOL


def run_tasks(kernel, n, *args):
    """``kernel(t0, t1, *args)`` over tasks ``0 .. n − 1`` split into one contiguous range
    per thread, as numba's ``prange`` splits a loop: ``numba.get_num_threads()`` ranges
    (1, on the calling thread, inside :func:`statmc._threads.serial_when_small`), the first
    on the calling thread and the others on a pool of Python threads.  ``kernel`` is a
    serial ``nogil`` numba function whose tasks write disjoint outputs, so the result does
    not depend on the split.  The pool's threads wait passively (on a queue) and start
    at first use; a forked child starts its own.
    """
    p = min(numba.get_num_threads(), n)
    if p <= 1:
        if n > 0:
            kernel(0, n, *args)
        return
    bounds = [(i * n) // p for i in range(p + 1)]
    pool = _task_pool()
    futures = [pool.submit(kernel, bounds[i], bounds[i + 1], *args) for i in range(1, p)]
    try:
        kernel(bounds[0], bounds[1], *args)
    finally:
        for f in futures:
            f.result()
