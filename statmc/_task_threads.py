"""Serial numba kernels run over a range of tasks on several threads.

A numba parallel loop (``prange``) costs compile time beyond its body: numba's parallel
lowering compiles the loop body as a function of its own and links it, with every
function it calls, into the kernel, and LLVM optimises the linked code once more at each
level.  For the filter passes that was about 10 s CPU per dtype on a cold cache against
5 s for the same passes in one serial function (the combination weights: 7 s).
:func:`run_chunks` instead calls a serial ``nogil`` kernel on contiguous chunks of its
range from a few Python threads; the kernel releases the GIL, so they run in parallel.
:func:`run_tasks` and :func:`run_rows` are its two calling forms; every statmc kernel
module uses this one pool.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import numba

from ._threads import thread_count

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


#: Chunks per thread of a :func:`run_chunks` call: a thread that finishes early (its core
#: was free, its rows were cheap) takes the next chunk instead of waiting for the others.
CHUNKS_PER_THREAD = 4


def run_chunks(call, start, stop):
    """``call(lo, hi)`` for contiguous chunks ``lo .. hi − 1`` covering ``start .. stop − 1``.

    On :func:`statmc._threads.thread_count` threads (1, on the calling thread alone,
    inside :func:`statmc._threads.serial_when_small` / ``serial_below``, with
    ``NUMBA_NUM_THREADS=1`` or after ``numba.set_num_threads(1)``; found without starting
    numba's own thread pool, which statmc does not use): the calling thread and the pool's,
    each taking the next of about :data:`CHUNKS_PER_THREAD` chunks per thread when it is
    done with one.  ``call`` runs a serial ``nogil`` numba kernel whose chunks write
    disjoint outputs, so the result does not depend on the chunking or on which thread ran
    a chunk: it equals the one-thread result to the bit.  An exception in a chunk, or one raised in the calling
    thread while it waits (KeyboardInterrupt), stops the chunks not yet started and is
    raised here once every chunk started has finished: no output is written after this
    returns.  The pool's threads wait passively (on a queue) and start at first use; a
    forked child starts its own.  Several callers at once share the pool: each caller's
    own thread works through its chunks, and a caller whose pool submissions are still
    queued behind another caller's when its chunks are all done drops them instead of
    waiting for them, so none waits on another's.
    """
    start, stop = int(start), int(stop)
    n = stop - start
    p = min(thread_count(), n)
    if p <= 1:
        if n > 0:
            call(start, stop)
        return
    nchunk = min(n, p * CHUNKS_PER_THREAD)
    bounds = [start + (i * n) // nchunk for i in range(nchunk + 1)]
    todo = iter(range(nchunk))
    lock = threading.Lock()
    errors = []

    def work():
        while not errors:
            with lock:
                i = next(todo, None)
            if i is None:
                return
            try:
                call(bounds[i], bounds[i + 1])
            except BaseException as exc:        # noqa: BLE001 - raised below, in the caller
                errors.append(exc)

    pool = _task_pool()
    futures = [pool.submit(work) for _ in range(p - 1)]
    try:
        work()
    except BaseException as exc:                # outside a chunk (KeyboardInterrupt)
        errors.append(exc)
    # Every chunk is taken (or an error stops them): a submission still queued, behind
    # another caller's, has nothing left to do and is dropped rather than waited for.
    running = [f for f in futures if not f.cancel()]
    while running:
        try:
            wait(running)
            running = []
        except BaseException as exc:            # noqa: BLE001 - KeyboardInterrupt while
            errors.append(exc)                  # waiting: stop the chunks not yet started
            running = [f for f in running if not f.done()]   # and wait for the others
    if errors:
        raise errors[0]


def run_tasks(kernel, n, *args):
    """:func:`run_chunks` of ``kernel(t0, t1, *args)`` over tasks ``0 .. n − 1``: the form
    of the filter, GEM, analytic and gate kernels (their task range first)."""
    run_chunks(lambda t0, t1: kernel(t0, t1, *args), 0, n)


def run_rows(kernel, start, stop, *args):
    """:func:`run_chunks` of ``kernel(*args, lo, hi)`` over ``start .. stop − 1``: the form of
    the combination kernels (their range last)."""
    run_chunks(lambda lo, hi: kernel(*args, lo, hi), start, stop)
