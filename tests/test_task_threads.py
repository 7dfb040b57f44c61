"""statmc._task_threads.run_chunks with several callers at once and an interrupted caller.

Regressions (session 15 review): a caller whose pool submission was queued behind another
caller's chunks waited for those chunks after doing all of its own; a KeyboardInterrupt
while the caller waited for the pool left the pool's chunk writing after the call had
returned.
"""

from __future__ import annotations

import signal
import sys
import threading
import time

import pytest

from statmc import _task_threads as tt


def _in_pool():
    return threading.current_thread().name.startswith("statmc-kernel")


def test_a_caller_does_not_wait_behind_another_callers_chunks(monkeypatch):
    """Caller B's chunks hold every pool thread; caller A does all its chunks itself and
    returns at once instead of waiting for its own queued (now pointless) submission."""
    pool = tt._task_pool()
    workers = pool._max_workers
    monkeypatch.setattr(tt, "thread_count", lambda: workers + 1)
    release, held = threading.Event(), threading.Semaphore(0)

    def blocked(lo, hi):
        # B's own thread holds its first chunk too: otherwise it could run every chunk
        # before the pool's threads woke (a fresh pool, a busy machine), and none would
        # be held
        if _in_pool():
            held.release()
        release.wait(30)

    b = threading.Thread(target=tt.run_chunks, args=(blocked, 0, 1000))
    b.start()
    try:
        for _ in range(workers):
            assert held.acquire(timeout=10), "B's chunks did not reach the pool threads"
        hits = []
        a = threading.Thread(target=tt.run_chunks,
                             args=(lambda lo, hi: hits.extend(range(lo, hi)), 0, 100))
        t0 = time.monotonic()
        a.start()
        a.join(5)
        assert not a.is_alive(), "caller A waited for caller B's chunks"
        assert sorted(hits) == list(range(100)) and time.monotonic() - t0 < 5
    finally:
        release.set()
        b.join(30)
    assert not b.is_alive()


class _Interrupt(BaseException):
    pass


@pytest.mark.skipif(sys.platform == "win32", reason="setitimer")
def test_an_interrupt_while_waiting_returns_after_the_started_chunks(monkeypatch):
    """An exception raised in the calling thread while it waits for the pool (a
    KeyboardInterrupt; here a signal handler's) is raised after the chunk the pool thread
    runs has finished, so no output changes after the call returned."""
    monkeypatch.setattr(tt, "thread_count", lambda: 2)
    started, done = threading.Event(), []

    def chunk(lo, hi):
        if _in_pool():
            started.set()
            time.sleep(0.6)
        else:
            started.wait(10)          # the pool thread has its chunk before the rest go
        done.append((lo, hi))

    def interrupt(signum, frame):
        raise _Interrupt()

    old = signal.signal(signal.SIGALRM, interrupt)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.25)
        with pytest.raises(_Interrupt):
            tt.run_chunks(chunk, 0, 8)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    at_return = list(done)
    time.sleep(0.8)
    assert done == at_return, "a chunk was still writing after run_chunks returned"
    assert sorted(at_return) == sorted(set(at_return))
