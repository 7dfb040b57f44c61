"""Thread control for the numba kernels: how many threads statmc's kernel runner uses
(:func:`thread_count`, small problems on the calling thread alone), and the OpenMP wait
policy of numba's thread pool, should the user's own numba code start it."""

from __future__ import annotations

import functools
import importlib
import inspect
import os
import sys
import threading
from contextlib import contextmanager

import numpy as np

# numba is imported where it is used, not here: `statmc metrics` imports this module (FLIP
# through import_passively) and never runs a numba kernel; numba's import took 0.1 s of it.

#: What statmc asks of an OpenMP runtime it loads: waiting threads sleep instead of spinning.
PASSIVE_OMP_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}
#: Variables that mean the user chose a wait policy for every OpenMP runtime: then we keep out.
OMP_USER_CHOICE = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
_ENV_LOCK = threading.RLock()


def _user_chose_policy() -> bool:
    """The user set a wait policy (:data:`OMP_USER_CHOICE`) for every OpenMP runtime."""
    return any(k in os.environ for k in OMP_USER_CHOICE)


@contextmanager
def passive_omp():
    """Put :data:`PASSIVE_OMP_ENV` into the environment for the block, then restore it.

    An OpenMP runtime (libgomp) reads its wait policy once, when it is loaded; loading one
    inside this block configures it, and the user's environment is the same afterwards.
    The environment is process-wide: while the block runs every thread sees the setting
    (an OpenMP runtime another thread loads in that moment, or a subprocess it starts,
    inherits it).  Nothing is changed when the user set ``OMP_WAIT_POLICY`` or
    ``GOMP_SPINCOUNT`` themselves.  The blocks of several threads run one at a time.
    """
    with _ENV_LOCK:
        if _user_chose_policy():
            yield
            return
        added = [k for k in PASSIVE_OMP_ENV if k not in os.environ]
        try:
            for k in added:
                os.environ[k] = PASSIVE_OMP_ENV[k]
            yield
        finally:
            for k in added:
                os.environ.pop(k, None)


def import_passively(name: str):
    """Import module ``name``, any OpenMP runtime it loads set to wait passively.

    The first import runs inside :func:`passive_omp` (its lock makes a second thread wait
    for it); a module imported before, its runtime already configured, is returned as it
    is.  When another thread is still importing it, this waits for that import to finish
    (as a plain ``import`` does) and returns the complete module, not the half-initialised
    one ``sys.modules`` already holds.
    """
    if name not in sys.modules:
        with passive_omp():
            return importlib.import_module(name)
    return importlib.import_module(name)


class LazyModule:
    """Module ``name``, imported at the first use of one of its attributes: a module that
    holds compiled kernels (and so imports numba, about 0.4 s) costs nothing to a caller
    that never runs one, such as ``statmc denoise --denoiser oidn``."""

    def __init__(self, name: str):
        self._name = name

    def __getattr__(self, attr):
        return getattr(importlib.import_module(self._name), attr)

    def __repr__(self) -> str:
        return f"<lazily imported module {self._name!r}>"


def wait_passively_in_numba() -> None:
    """Make numba start its thread pool, when it does, with passive OpenMP waits.

    numba starts its pool (with the ``omp`` threading layer: the system's libgomp) at the
    first parallel kernel call or ``numba.get_num_threads()``/``set_num_threads`` call, and
    libgomp's default wait policy spins at every barrier.  On a machine whose cores are
    busy with other work a spinning thread holds the core the thread it waits for needs:
    with two busy loops on the two cores of the machine this was measured on, when
    statmc's kernels were numba parallel loops, ``gem.reconstruct`` of a 64x64 image took
    a median 116 ms instead of 11 ms, at 512x512 1.6 s instead of 0.17 s
    (``bench/bench_numba_load.py``).  statmc's kernels no longer use the pool and statmc
    does not start it (:func:`thread_count`); the user's own numba code still may.

    numba's pool start (``numba.np.ufunc.parallel._launch_threads``, which numba looks up
    at every use) is wrapped so that it runs inside :func:`passive_omp`: the pool still
    starts when numba starts it, so a process that forks before its first kernel call
    keeps working (GNU OpenMP is not fork-safe once started), and the environment is the
    user's again right after.  Every compiled-kernel module of statmc calls this at import.
    Nothing changes when the pool was already started (by the user's own numba code or
    an earlier call), when the user chose a wait policy, or for an OpenMP runtime another
    library loaded before (torch imported first: numba may then share it, see
    docs/nn.md, "Threads").
    """
    from numba.np.ufunc import parallel

    launch = getattr(parallel, "_launch_threads", None)
    if launch is None or getattr(launch, "_statmc_passive", False) or parallel._is_initialized:
        return

    def launch_passive():
        if parallel._is_initialized:      # numba calls this at every use: keep that cheap
            return launch()
        with passive_omp():
            return launch()

    launch_passive._statmc_passive = True
    launch_passive.__wrapped__ = launch
    parallel._launch_threads = launch_passive


_LOCAL = threading.local()      # .serial: depth of the calling thread's serial_below blocks


def thread_count() -> int:
    """The number of threads statmc's kernel runner (:mod:`statmc._task_threads`) uses for
    a call from the calling thread, found without starting numba's thread pool.

    1 inside :func:`serial_below` on this thread; else ``numba.get_num_threads()`` when
    numba's pool is already started (by the user's ``numba.set_num_threads(n)``, which
    so still limits statmc, or by their own parallel numba code); else
    ``numba.config.NUMBA_NUM_THREADS`` (the ``NUMBA_NUM_THREADS`` environment variable, or
    the number of cores).  statmc's kernels are serial ``nogil`` functions on its own
    Python threads and never need numba's pool, and starting it is not free: with torch
    imported first numba's pool runs on torch's OpenMP runtime, and its start reset
    torch's thread count after ``torch.set_num_threads(1)`` (docs/nn.md, "Threads").
    """
    if getattr(_LOCAL, "serial", 0):
        return 1
    import numba
    from numba.np.ufunc import parallel

    if parallel._is_initialized:
        return numba.get_num_threads()
    return numba.config.NUMBA_NUM_THREADS


@contextmanager
def serial_below(work: int, threshold: int):
    """Run the block's statmc kernels on the calling thread alone when ``work < threshold``.

    Inside the block :func:`thread_count` is 1 on this thread (other threads are not
    affected; nested blocks and exceptions restore the count).  Waking other threads costs
    more than a small kernel takes serially; each kernel module sets its own ``threshold``.
    numba's own thread count is neither read nor changed.
    """
    if work >= threshold:
        yield
        return
    _LOCAL.serial = getattr(_LOCAL, "serial", 0) + 1
    try:
        yield
    finally:
        _LOCAL.serial -= 1


#: Below this many values (about 245x245 RGB) statmc's GEM and filter-bank calls run on
#: the calling thread alone.  Every parallel region of a call pays for handing chunks to
#: the other task threads (:mod:`statmc._task_threads`), so small images are faster on
#: one thread.  It was 300,000 (about 316x316) from session 11, measured for numba's
#: OpenMP pool.  On an idle 2-core machine (session 17, docs/gem.md §7) two task threads
#: won from about 224x224 (150,528 values): the paper-mode ``reconstruct`` 20.4 against
#: 16.4 ms there and 24.3 against 18.6 ms at 256x256, ``filter_bank`` 10.7 against 7.8 ms;
#: at 192x192 the two were even.  With other jobs on the cores one thread won at every size
#: up to 320x320, so the threshold sits above the idle crossover.
SERIAL_VALUES = 180_000


def serial_when_small(threshold: int = SERIAL_VALUES, *, threshold_of=None):
    """Decorator: run the function's kernels on the calling thread alone when its first
    argument (given by position or by name) holds fewer than ``threshold`` values
    (:func:`serial_below`), whatever OpenMP wait policy the user set: statmc's threads are
    Python threads (:mod:`statmc._task_threads`) that never spin, so a user's
    ``OMP_WAIT_POLICY=ACTIVE`` no longer makes small calls cheap in parallel (until
    session 16 it kept them on numba's spinning OpenMP pool).
    ``threshold_of(kwargs)``, if given, picks the threshold from the call's keyword
    arguments (a call that runs fewer parallel regions pays fewer wake-ups, so it is
    parallel from a smaller size)."""
    def wrap(fn):
        first_name = next(iter(inspect.signature(fn).parameters))

        @functools.wraps(fn)
        def run(*args, **kwargs):
            limit = threshold if threshold_of is None else threshold_of(kwargs)
            # The first argument, passed by position or by name (`mean=x`); a call that
            # gives none is left to the function to refuse.
            first = args[0] if args else kwargs.get(first_name)
            try:
                work = int(np.size(first))
            except Exception:                  # ragged input: the function will say why
                work = limit
            with serial_below(work, limit):
                return fn(*args, **kwargs)
        return run
    return wrap
