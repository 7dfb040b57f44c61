"""numba's thread pool starts with passive OpenMP waits (statmc._threads).

Regression (session 10): numba ran statmc's parallel kernels on the system's libgomp with
its default spin-wait (spin count 300000).  On a machine whose cores are busy with other
work, waiting threads held the cores their partners needed: ``gem.reconstruct`` of a
64x64 image took a median 116 ms instead of 11 ms with two busy loops on the two cores,
512x512 1.6 s instead of 0.17 s (``bench/bench_numba_load.py``).  The runtime's settings
are read from its own printout (tests/_omp_display.py).
"""

from __future__ import annotations

import subprocess
import sys
import threading

import numba
import numpy as np
import pytest
from _omp_display import PRINT_BEGIN, PRINT_END, libgomp_settings

_PROBE = f"""
import os, sys
import numpy as np
import numba
import statmc.gem
from numba.np.ufunc import parallel
started_at_import = parallel._is_initialized
{PRINT_BEGIN}
statmc.gem.reconstruct(np.ones((16, 16, 3)), np.full((16, 16, 3), 0.01))
numba.get_num_threads()            # the user's own numba code starts numba's pool
{PRINT_END}
print(repr(os.environ.get("OMP_WAIT_POLICY")), numba.threading_layer(), started_at_import,
      file=sys.stderr)
"""


def _run(**env):
    gomp, lines = libgomp_settings(_PROBE, **env)
    after, layer, started_at_import = lines[-1].rsplit(" ", 2)
    if layer != "omp":
        pytest.skip(f"numba runs on its {layer!r} threading layer here, not libgomp")
    return gomp, after, started_at_import


def test_numba_pool_starts_on_a_passive_runtime_when_the_users_code_starts_it():
    """The old code loaded libgomp with spin count 300000 at the first kernel call (this
    failed on ``gomp``).  statmc's kernels no longer start numba's pool (see
    test_statmc_calls_leave_numbas_pool_and_torchs_thread_count_alone); the user's own
    numba code, run after statmc's import, still starts it passively.  The pool is not
    started by the import (see the fork test), and the user's environment is the same
    afterwards."""
    gomp, after, started_at_import = _run()
    assert gomp == [("0", "PASSIVE")], gomp
    assert after == "None" and started_at_import == "False"


def test_a_wait_policy_the_user_chose_is_kept():
    gomp, after, _ = _run(OMP_WAIT_POLICY="ACTIVE")
    assert gomp and all(policy == "ACTIVE" and spin != "0" for spin, policy in gomp), gomp
    assert after == "'ACTIVE'"
    gomp, _, _ = _run(GOMP_SPINCOUNT="300000")
    assert gomp == [("300000", gomp[0][1])], gomp


_FORK = """
import multiprocessing as mp
import numpy as np
import statmc.gem as gem

def f(i):
    m = np.random.default_rng(i).random((24, 24, 3))
    return float(gem.reconstruct(m, 0.01 * m).mean())

if __name__ == "__main__":
    with mp.get_context("fork").Pool(2) as p:
        print(len(p.map(f, range(4))))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_fork_after_import_still_works():
    """A process that imports statmc and forks workers before its first kernel call must
    keep working: GNU OpenMP aborts a forked child once the parent started its pool, so
    statmc must not start numba's pool at import (a first version of the change above did,
    and the workers died with 'fork() called from a process already using GNU OpenMP')."""
    if numba.config.THREADING_LAYER not in ("default", "safe", "omp"):
        pytest.skip("numba is configured for a threading layer other than omp")
    p = subprocess.run([sys.executable, "-c", _FORK], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0 and p.stdout.strip() == "4", p.stdout + p.stderr


def test_small_gem_and_filter_calls_run_on_one_thread(monkeypatch):
    """Below ``_threads.SERIAL_VALUES`` a decorated call runs on one thread (each parallel
    region would pay a sleeping worker's wake-up), also when the user chose an OpenMP wait
    policy (statmc's threads never spin; until session 16 such calls stayed parallel);
    statmc's thread count (``_threads.thread_count``) is restored after, also when
    the call raises, and in a nested block."""
    from statmc import _threads

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread only")
    seen = []

    @_threads.serial_when_small(100)
    def probe(x, fail=False):
        seen.append(_threads.thread_count())
        if fail:
            raise ValueError("refused")

    for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):
        monkeypatch.delenv(k, raising=False)
    before = _threads.thread_count()
    probe(np.zeros(99))
    probe(np.zeros(100))
    with pytest.raises(ValueError):
        probe(np.zeros(5), fail=True)
    monkeypatch.setenv("GOMP_SPINCOUNT", "300000")   # no spinning pool to keep busy any more
    probe(np.zeros(99))
    assert seen == [1, before, 1, 1]
    monkeypatch.delenv("GOMP_SPINCOUNT")
    with _threads.serial_below(1, 2):
        with _threads.serial_below(1, 2):
            seen.append(_threads.thread_count())
        seen.append(_threads.thread_count())
        with _threads.serial_below(2, 2):           # not small: no change
            seen.append(_threads.thread_count())
        other = []                                  # another thread: its own count
        t = threading.Thread(target=lambda: other.append(_threads.thread_count()))
        t.start()
        t.join()
    assert seen[4:] == [1, 1, 1] and other == [before]
    assert _threads.thread_count() == before


def _first_stop_threads(monkeypatch):
    """A list that gets ``_threads.thread_count()`` at each call of
    ``_filter_kernels.first_stop`` (every select/reconstruct/sampling_map calls it once)."""
    from statmc import _filter_kernels, _threads

    threads = []
    first_stop = _filter_kernels.first_stop

    def spy(*args):
        threads.append(_threads.thread_count())
        return first_stop(*args)

    monkeypatch.setattr(_filter_kernels, "first_stop", spy)
    return threads


def test_gem_calls_with_the_fused_selection_go_parallel_from_a_smaller_size(monkeypatch):
    """``threshold_of`` picks the threshold per call: gem.select/reconstruct/selected_filter
    with the pooled selection (bias="pooled", or the default of final=True), whose stages
    run fused, use the pool from ``gem.FUSED_SERIAL_VALUES`` values; the paper's selection
    (final=False) keeps ``SERIAL_VALUES``."""
    from statmc import _threads, gem

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread only")
    for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):
        monkeypatch.delenv(k, raising=False)
    seen = []

    @_threads.serial_when_small(10, threshold_of=lambda kw: kw.get("limit", 10))
    def probe(x, limit=10):
        seen.append(_threads.thread_count())

    before = _threads.thread_count()
    probe(np.zeros(50), limit=100)
    probe(np.zeros(50))
    assert seen == [1, before]

    threads = _first_stop_threads(monkeypatch)
    h = w = 240                                       # 172,800 values: between the thresholds
    assert gem.FUSED_SERIAL_VALUES < h * w * 3 < _threads.SERIAL_VALUES
    m = np.random.default_rng(1).random((h, w, 3))
    v = np.full_like(m, 0.01)
    gem.reconstruct(m, v)
    gem.select(m, v, bias="pooled", final=False)
    gem.reconstruct(m, v, final=False)
    gem.reconstruct(m[:200, :200], v[:200, :200])      # 120,000 values: below both
    gem.selected_filter(m, v)                         # the same _core, the same thresholds
    gem.selected_filter(m, v, final=False)
    assert threads == [before, before, 1, 1, before, 1]
    assert _threads.thread_count() == before


def test_pooled_reconstruct_of_a_small_image_runs_on_one_thread(monkeypatch):
    """Regression (session 16): a 136x136 and a 192x192 RGB final reconstruction ran on two
    task threads (the fused threshold was 50,000 values, tuned for numba's OpenMP pool) and
    took 1.4-1.8x as long as on one thread at load 2; below ``gem.FUSED_SERIAL_VALUES``
    they now run on the calling thread, and a 256x256 one still on every thread."""
    from statmc import _threads, gem

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread only")
    for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):
        monkeypatch.delenv(k, raising=False)
    threads = _first_stop_threads(monkeypatch)
    before = _threads.thread_count()
    rng = np.random.default_rng(2)
    for side in (136, 192, 256):
        m = rng.random((side, side, 3)).astype(np.float32)
        gem.reconstruct(m, np.full_like(m, 0.01))
    assert threads == [1, 1, before]
    assert _threads.thread_count() == before


def test_unfused_calls_of_a_256_image_use_every_thread(monkeypatch):
    """Session 17 (docs/gem.md §7): on an idle 2-core machine two task threads won from
    about 224x224 RGB for the paper selection, ``sampling_map`` and the filter bank, so
    ``_threads.SERIAL_VALUES`` is 180,000 (was 300,000): a 240x240 image still runs on
    the calling thread, a 256x256 one on every thread."""
    from statmc import _threads, gem

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread only")
    threads = _first_stop_threads(monkeypatch)
    before = _threads.thread_count()
    rng = np.random.default_rng(3)
    for side in (240, 256):
        m = rng.random((side, side, 3)).astype(np.float32)
        gem.reconstruct(m, np.full_like(m, 0.01), final=False)
        gem.sampling_map(m, np.full_like(m, 0.01), np.full((side, side), 4), side * side, rng=0)
    assert threads == [1, 1, before, before]
    assert _threads.thread_count() == before


_TORCH_PROBE = """
import torch
torch.set_num_threads(1)
assert torch.get_num_threads() == 1
import numba
import numpy as np
from numba.np.ufunc import parallel
import statmc.combine as C
import statmc.gem as gem
from statmc import _task_threads
run_chunks, chunks = _task_threads.run_chunks, []


def counted(call, start, stop):          # how many chunks each kernel pass ran in
    n = [0]
    def one(lo, hi):
        n[0] += 1
        call(lo, hi)
    run_chunks(one, start, stop)
    chunks.append(n[0])


_task_threads.run_chunks = counted
rng = np.random.default_rng(0)
most = []
for side in (24, 300):          # 300x300 RGB: above every serial threshold
    m = rng.random((side, side, 3))
    gem.reconstruct(m, 0.01 * m)
    most.append(max(chunks))
y = rng.random((256, 256, 3)).astype(np.float32)
C.combine(y, y + 0.01, C.gaussian_weights(256, 256, 1, 15, 3.0)[:, :, 0])
print(torch.get_num_threads(), parallel._is_initialized, *most, numba.config.NUMBA_NUM_THREADS)
"""


def test_statmc_calls_leave_numbas_pool_and_torchs_thread_count_alone():
    """Regression (session 16, docs review): statmc asked ``numba.get_num_threads()`` (and
    set it for small calls), which starts numba's OpenMP pool; with torch imported first
    that is torch's libgomp, and after ``torch.set_num_threads(1)`` and a
    ``torch.get_num_threads()`` call its start reset torch to one thread per core (a 32x32
    ``unfold`` then took 8-16 ms instead of 0.12-0.22 ms).  statmc's kernels never use
    numba's pool: GEM of a small and a 300x300 image (several task threads) and a combine
    must leave it unstarted and torch at its one thread."""
    pytest.importorskip("torch")
    p = subprocess.run([sys.executable, "-c", _TORCH_PROBE], capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    torch_threads, started, small, large, cores = p.stdout.split()
    assert (torch_threads, started) == ("1", "False"), p.stdout
    assert small == "1", p.stdout                        # one chunk: the calling thread
    assert int(large) > 1 or cores == "1", p.stdout      # several task threads


def test_numba_set_num_threads_still_limits_statmc():
    """The user's ``numba.set_num_threads(n)`` (tests and docs use it) still sets how many
    threads statmc's runner uses: 1 runs every chunk inline on the calling thread."""
    from statmc import _task_threads, _threads

    before = numba.get_num_threads()
    calls = []
    try:
        for n in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(n)
            calls.clear()
            _task_threads.run_chunks(
                lambda lo, hi: calls.append((lo, hi, threading.current_thread().name)), 0, 100)
            assert _threads.thread_count() == n
            if n == 1:
                assert calls == [(0, 100, threading.current_thread().name)]
            else:
                assert len(calls) == min(100, n * _task_threads.CHUNKS_PER_THREAD)
    finally:
        numba.set_num_threads(before)


_OIDN_PROBE = f"""
import os, sys
import numpy as np
import statmc.denoisers as D
d = D.oidn()
{PRINT_BEGIN}
d(np.full((8, 8, 3), 0.5, np.float32))
{PRINT_END}
print(repr(os.environ.get("OMP_WAIT_POLICY")), "torch" in sys.modules, file=sys.stderr)
"""


def test_oidn_loads_torchs_openmp_runtime_with_passive_waits():
    """pyoidn imports torch, and numba's kernels then share torch's bundled libgomp.  The
    old code imported pyoidn plainly (spin count 300000: this failed on ``gomp``); two
    statmc jobs that had run OIDN first then took 4.5-6.8 s each for six 512x512
    reconstructions against 0.55 s.  Skipped where pyoidn does not bring torch along."""
    pytest.importorskip("pyoidn")
    gomp, lines = libgomp_settings(_OIDN_PROBE)
    after, torch_loaded = lines[-1].rsplit(" ", 1)
    if torch_loaded != "True" or not gomp:
        pytest.skip("pyoidn loads no libgomp here")
    assert gomp == [("0", "PASSIVE")] * len(gomp), gomp
    assert after == "None"


@pytest.mark.parametrize("dt", [np.float32, np.float64])
@pytest.mark.parametrize("C,Cv", [(3, 1), (3, 3), (1, 1), (2, 2)])
def test_fused_kernels_equal_the_single_kernels_job_by_job(dt, C, Cv):
    """The ``*_many`` kernels of ``statmc._filter_kernels`` run several calls of one
    kernel in one parallel region (each region wakes the passively waiting pool); their
    reference is the single kernel called job by job, which they must equal bit for bit
    (rows not a multiple of the row block, taps of 1 to 27 values, padded tap rows).

    ``sep_filter`` is itself one job of ``sep_filter_many`` (one compiled filter), so here
    the jobs run together on all threads (``run_tasks`` splits their row blocks) and one
    by one on a single thread; ``test_filters`` compares both with a NumPy reference."""
    from statmc import _filter_kernels as K

    rng = np.random.default_rng(7 + C + Cv)
    H, W, nk = 45, 23, 4
    x = rng.standard_normal((2, H, W * C)).astype(dt)
    v = rng.random((2, H, W * Cv)).astype(dt)
    src = np.array([1, 0, 1, 0], np.int64)
    lens = [1, 27, 9, 5]
    taps = np.zeros((nk, max(lens)), dt)
    for k, n in enumerate(lens):
        taps[k, :n] = rng.random(n) + 0.1
    sy, sx = (rng.random((nk, H)) + 0.5).astype(dt), (rng.random((nk, W)) + 0.5).astype(dt)
    out_x, out_v = np.empty((nk, H, W * C), dt), np.empty((nk, H, W * Cv), dt)
    K.sep_filter_many(x, C, v, Cv, src, taps, np.array(lens, np.int64), sy, sx, out_x, out_v)
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        for k in range(nk):
            ex, ev = np.empty_like(out_x[k]), np.empty_like(out_v[k])
            K.sep_filter(x[src[k]], C, v[src[k]], Cv, taps[k, :lens[k]].copy(), sy[k].copy(),
                         sx[k].copy(), ex, ev)
            np.testing.assert_array_equal(out_x[k], ex)
            np.testing.assert_array_equal(out_v[k], ev)
        none = np.empty((nk, H, 0), dt)
        numba.set_num_threads(before)
        K.sep_filter_many(x, C, np.empty((2, H, 0), dt), 1, src, taps, np.array(lens, np.int64),
                          sy, sx, out_x, none)                     # values only
        numba.set_num_threads(1)
        K.sep_filter(x[0], C, none[0], 1, taps[1].copy(), sy[1].copy(), sx[1].copy(), ex, none[0])
        np.testing.assert_array_equal(out_x[1], ex)
    finally:
        numba.set_num_threads(before)

    f = rng.standard_normal((nk, H, W * C)).astype(dt)
    fv = rng.random((nk, H, W * Cv)).astype(dt)
    cov = (0.3 * rng.random((nk - 1, H, W))).astype(dt)
    d = np.empty((nk - 1, H, W), dt)
    K.pooled_bias_input_many(f, fv, cov, C, Cv, d)
    fk = rng.random(nk - 1) + 0.5
    stop = np.empty((nk - 1, H, W), np.float32)
    K.stop_pooled_many(d, fv, Cv, fk, 1.0, stop)
    for k in range(nk - 1):
        e = np.empty((H, W), dt)
        K.pooled_bias_input(f[k], f[k + 1], fv[k], fv[k + 1], cov[k], C, Cv, e)
        np.testing.assert_array_equal(d[k], e)
        s = np.empty((H, W), np.float32)
        K.stop_pooled(d[k], fv[k], fv[k + 1], Cv, float(fk[k]), 1.0, s)
        np.testing.assert_array_equal(stop[k], s)
    assert 0 < stop.mean() < 1                                     # both decisions occur

    raw = (rng.random((nk, H, W)) < 0.5).astype(np.float32)
    filt = rng.random((nk, H, W)).astype(np.float32)
    wc = (0.2 + 0.5 * rng.random(nk)).astype(np.float32)
    fy, fx = (rng.random((nk, H)) + 0.9).astype(np.float32), (rng.random((nk, W)) + 0.9).astype(np.float32)
    for coarser_only in (False, True):
        out = np.empty_like(raw)
        K.finish_stop_map_many(filt, raw, wc, fy, fx, coarser_only, out)
        for k in range(nk):
            e = np.empty((H, W), np.float32)
            K.finish_stop_map(filt[k], raw[k], wc[k], fy[k].copy(), fx[k].copy(), coarser_only, e)
            np.testing.assert_array_equal(out[k], e)


_METRICS_PROBE = """
import sys
import numpy as np
from statmc.cli import main
from statmc.exr import write_exr
d = sys.argv[1]
rng = np.random.default_rng(0)
for name in ("a", "b"):
    write_exr(f"{d}/{name}.exr", rng.random((8, 8, 3)).astype(np.float32))
assert "numba" not in sys.modules, "numba imported before the command"
code = main(["metrics", f"{d}/a.exr", f"{d}/b.exr"])
print(code, "numba" in sys.modules, "flip_evaluator" in sys.modules)
"""


def test_metrics_does_not_import_numba(tmp_path):
    """`statmc metrics` runs no numba kernel: _threads imports numba where it uses it
    (serial_below, wait_passively_in_numba), so importing _threads for FLIP's passive
    import no longer costs numba's import (0.1 s of the command).  Fails before: _threads
    imported numba at its top."""
    p = subprocess.run([sys.executable, "-c", _METRICS_PROBE, str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split()[-3:] == ["0", "False", "True"], p.stdout + p.stderr
