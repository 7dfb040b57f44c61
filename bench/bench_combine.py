"""Benchmark for :mod:`statmc.combine`.

1. Speed of the multi-buffer combination kernel (Eq. 14).  Target (issue 5):
   1920x1080x3, B = 4 buffers, 15x15 windows, per-pixel float32 weights (7 GiB, as a
   kernel-predicting network would export them) in at most 1.5 s on 2 cores.  Peer: the
   plain NumPy reference (``_combine_kernels.combine_numpy``) on a crop of full width,
   scaled to 1080 rows, measured in the same run.

The machine is shared: the script prints the load average and the CPU time of the timed
call beside its wall time (CPU time / wall time close to 2 means both cores were ours).

2. Quality of the classical weights: MSE of Eq. 14 with ``statistical_weights``
   ("diagonal", "coherent") against ``y`` and ``z`` on toy scenes, moments estimated
   without the truth (``buffer_moments``); the table in ``docs/combine.md``.

3. Speed of ``statistical_weights`` ("coherent", the numba kernel) against its NumPy
   reference path in the same run (256x256, B = 4, 7x7, bin moments; 128x128, B = 1,
   15x15, the setting of ``combine_denoised``), and its time at 1920x1080 (B = 1, 15x15,
   5x5 covariance stencils), plus one ``combine_denoised`` call with OIDN at 1080p.

4. Quality of OIDN + combiner (``combine_denoised``, ``reconstruct_stats(...,
   "oidn+combine")``): relMSE of the raw render, OIDN and OIDN + combiner on the toy
   ``mixed`` scene and the four built-in Mitsuba scenes at 4-1024 spp against the cached
   references, with the issue's check (combiner < min(OIDN, raw) at >= 64 spp, <= 1.05
   OIDN below); the table in ``docs/combine.md``.

5. Memory (``--part memory``): peak RSS above the inputs, wall and CPU time of one
   ``combine_denoised`` and one ``combine_bins`` (B = 4) call at 1920x1080x3 (defaults,
   GEM's ``SelectedFilter``, a synthetic smooth image plus Gaussian noise), each in its own
   subprocess (``--memory-child``; the peak is ``VmHWM`` after a reset through
   ``/proc/self/clear_refs``).  Before the moment stencils were banded: 5.34 and 4.87 GiB
   above 0.64 GiB of inputs; now 1.89 GiB each (docs/combine.md, "Memory").
   ``--memory-child denoised --save out.npy`` keeps the output, to compare versions;
   ``--part memory --baseline DIR [--which denoised]`` runs an older checkout
   (``git archive <commit> statmc bench | tar -x -C DIR``) first in the same session and
   prints both times, their ratio and whether the outputs are equal to the bit.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_combine.py [--part
kernel|weights|memory|quality|all] [--seeds 0 1 2] [--height 1080 --width 1920]``
"""

from __future__ import annotations

import os
import time

import numba
import numpy as np
from numba import njit, prange

from statmc import _combine_kernels as ck
from statmc.analytic import apply_kernels
from statmc.combine import buffer_moments, combine_multi, statistical_weights
from statmc.toy import ToyRenderer

H, W, C, B, K = 1080, 1920, 3, 4, 15
TARGET_S = 1.5
CROP_ROWS = 24


@njit(parallel=True, cache=True)
def _fill_weights(w, seed):  # pragma: no cover - compiled
    """Distinct pseudo-random weights in (0, 1] per pixel and tap (xorshift), in parallel."""
    H, W, B, k, _ = w.shape
    for y in prange(H):
        s = np.uint64(seed) ^ (np.uint64(y + 1) * np.uint64(0x9E3779B97F4A7C15))
        for x in range(W):
            for b in range(B):
                for i in range(k):
                    for j in range(k):
                        s ^= s << np.uint64(13)
                        s ^= s >> np.uint64(7)
                        s ^= s << np.uint64(17)
                        u = np.float32((s >> np.uint64(40)) + np.uint64(1))
                        w[y, x, b, i, j] = u * np.float32(2.0 ** -24)


def _available_gib():
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2 ** 20
    except OSError:
        pass
    return float("inf")


from _timing import best_wall_cpu as _timed  # noqa: E402


def main():
    rows = H
    need = H * W * B * K * K * 4 / 2 ** 30
    if _available_gib() < need + 3.0:
        rows = 270
        print(f"only {_available_gib():.1f} GiB available (< {need + 3:.1f}): timing a "
              f"{W}x{rows} band and scaling to {H} rows")
    rng = np.random.default_rng(0)
    ys = rng.gamma(2.0, 0.5, size=(B, rows, W, C)).astype(np.float32)
    zs = (0.5 * ys + 0.25 * rng.random((B, rows, W, C))).astype(np.float32)
    t0 = time.perf_counter()
    w = np.empty((rows, W, B, K, K), np.float32)
    _fill_weights(w, 12345)
    print(f"generated {w.nbytes / 2 ** 30:.2f} GiB of per-pixel float32 weights in "
          f"{time.perf_counter() - t0:.1f} s")
    combine_multi(ys[:, :16, :16], zs[:, :16, :16], np.ascontiguousarray(w[:16, :16]))  # compile

    scale = H / rows
    wall, cpu = _timed(lambda: combine_multi(ys, zs, w), 3)
    wall, cpu = wall * scale, cpu * scale

    crop = slice(0, CROP_ROWS)
    t0 = time.perf_counter()
    ref = ck.combine_numpy(w[crop], ys[:, crop], zs[:, crop])
    t_ref = (time.perf_counter() - t0) * H / CROP_ROWS
    fast = combine_multi(ys[:, crop], zs[:, crop], w[crop])
    err = float(np.max(np.abs(fast - ref) / np.maximum(np.abs(ref), 1e-6)))

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"combine_multi {W}x{H}x{C}, B = {B}, {K}x{K} per-pixel float32 weights "
          f"({numba.get_num_threads()} numba threads, load average {load:.2f}):")
    print(f"  numba  {wall:7.3f} s wall  ({cpu:.3f} s CPU)   target <= {TARGET_S} s   "
          f"{'OK' if wall <= TARGET_S else 'MISSED'}")
    print(f"         {cpu / 2:7.3f} s = CPU time / 2: the wall time if both cores were free")
    print(f"  numpy  {t_ref:7.3f} s wall  (reference on {W}x{CROP_ROWS}, "
          f"scaled x{H / CROP_ROWS:.0f})")
    print(f"  speed-up x{t_ref / wall:.1f}; max relative difference on the crop {err:.1e}")


def _renormalised_gaussian(h, w, k, sigma):
    r = k // 2
    ax = np.arange(k) - r
    g = np.exp(-(ax[:, None] ** 2 + ax[None, :] ** 2) / (2 * sigma ** 2))
    K = np.broadcast_to(g, (h, w, k, k)).copy()
    for dy in range(k):
        for dx in range(k):
            yy = np.arange(h)[:, None] + dy - r
            xx = np.arange(w)[None, :] + dx - r
            K[:, :, dy, dx] *= (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
    return K / K.sum(axis=(2, 3), keepdims=True)


def quality(size=32, bins=4, spp=4, reps=4, k=5, sigma=2.0):
    """MSE x 1e4 of y, z and Eq. 14 with estimated statistical weights."""
    F = _renormalised_gaussian(size, size, 2 * int(np.ceil(2 * sigma)) + 1, sigma)
    G = _renormalised_gaussian(size, size, 5, 1.5)
    print(f"\nstatistical_weights on {size}x{size} toy scenes: {bins} bins of {spp} spp, "
          f"z_b = Gaussian(sigma {sigma}) of y_b, {k}x{k} windows, moments from buffer_moments "
          f"(smoothed 5x5), bias estimated from the data; MSE x 1e4 over {reps} renders:")
    print(f"  {'scene':10s} {'y':>8s} {'z':>8s} {'diagonal':>9s} {'coherent':>9s}")
    for scene in ("edges", "texture", "gradient"):
        r = ToyRenderer(scene, width=size, height=size)
        mu = r.true_mean()
        err = {name: [] for name in ("y", "z", "diagonal", "coherent")}
        for i in range(reps):
            ys = np.stack([r.render_uniform(spp, seed=(7, i, b), features=False).mean
                           for b in range(bins)])
            zs = np.stack([apply_kernels(F, yb) for yb in ys])
            var_y, cov_z, cov_yz = buffer_moments(ys, zs, size=k)
            var_y = apply_kernels(G, var_y)
            cov_z = apply_kernels(G, cov_z.reshape(size, size, -1)).reshape(cov_z.shape)
            cov_yz = apply_kernels(G, cov_yz.reshape(size, size, -1)).reshape(cov_yz.shape)
            err["y"].append(((ys.mean(axis=0) - mu) ** 2).mean())
            err["z"].append(((zs.mean(axis=0) - mu) ** 2).mean())
            for method in ("diagonal", "coherent"):
                wts = statistical_weights(ys, zs, var_y, cov_z, k, cov_yz=cov_yz, method=method)
                err[method].append(((combine_multi(ys, zs, wts) - mu) ** 2).mean())
        row = " ".join(f"{1e4 * np.mean(v):8.1f} " for v in err.values())
        print(f"  {scene:10s} {row}")


def _load():
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def weights_speed():
    """``statistical_weights`` numba vs its NumPy reference, and at 1080p."""
    from statmc.analytic import apply_kernels as ak
    from statmc.combine import filter_covariance

    print(f"\nstatistical_weights (coherent, z_bias='estimate'), load average {_load():.2f}:")
    rng = np.random.default_rng(3)
    cases = [("256x256, B = 4, 7x7, buffer_moments", 256, 4, 7, "bins"),
             ("128x128, B = 1, 15x15, 5x5 stencils", 128, 1, 15, "stencil")]
    for label, n, b, k, kind in cases:
        ys = rng.gamma(2.0, 0.5, (b if b > 1 else 2, n, n, C))
        F = _renormalised_gaussian(n, n, 5, 1.0)
        zs = np.stack([ak(F, yb) for yb in ys])
        if kind == "bins":
            var_y, cov_z, cov_yz = buffer_moments(ys, zs, size=k)
            y, z = ys, zs
        else:
            var_y = np.full((n, n, C), 0.1)
            cov_z, cov_yz = filter_covariance(F, var_y, size=5, cross=True)
            y, z = ys[0], zs[0]
        statistical_weights(y[..., :8, :8, :], z[..., :8, :8, :], var_y[:8, :8], cov_z[:8, :8], k,
                            cov_yz=cov_yz[:8, :8])                       # compile
        t_fast, c_fast = _timed(lambda: statistical_weights(y, z, var_y, cov_z, k, cov_yz=cov_yz), 2)
        t0 = time.perf_counter()
        ref = statistical_weights(y, z, var_y, cov_z, k, cov_yz=cov_yz, _reference=True)
        t_ref = time.perf_counter() - t0
        fast = statistical_weights(y, z, var_y, cov_z, k, cov_yz=cov_yz)
        err = float(np.abs(fast - ref).max())
        print(f"  {label:40s} numba {t_fast:6.2f} s ({c_fast:.2f} s CPU)  numpy {t_ref:6.2f} s  "
              f"x{t_ref / t_fast:5.1f}   max |difference| {err:.1e}")
    # 1080p, B = 1, 15x15, 5x5 stencils (the setting of combine_denoised)
    y = rng.gamma(2.0, 0.5, (H, W, C))
    z = 0.8 * y + 0.2 * y.mean()
    var_y = np.full((H, W, C), 0.1)
    cov_z = np.ascontiguousarray(np.broadcast_to(
        np.exp(-np.add.outer(np.arange(-2, 3) ** 2, np.arange(-2, 3) ** 2) / 4.0)[..., None] * 0.01,
        (H, W, 5, 5, C)))
    cov_yz = 0.5 * cov_z
    c0, t0 = time.process_time(), time.perf_counter()
    w = statistical_weights(y, z, var_y, cov_z, 15, cov_yz=cov_yz)
    t, c = time.perf_counter() - t0, time.process_time() - c0
    print(f"  {'1920x1080, B = 1, 15x15, 5x5 stencils':40s} numba {t:6.2f} s ({c:.2f} s CPU), "
          f"weights {w.nbytes / 2 ** 30:.2f} GiB; load average {_load():.2f}")
    w = cov_z = cov_yz = None                            # free 3.6 GB before OIDN
    try:
        from statmc import denoisers
        from statmc.combine import combine_denoised
        f = denoisers.oidn()
        y32 = y.astype(np.float32)
        t0 = time.perf_counter()
        f(y32)
        t_oidn = time.perf_counter() - t0
        t0 = time.perf_counter()
        combine_denoised(y32, var_y, f, rng=0)
        t_all = time.perf_counter() - t0
        print(f"  combine_denoised with OIDN at 1920x1080: {t_all:.1f} s (one OIDN call {t_oidn:.2f} s; "
              f"9 calls for 8 probes); load average {_load():.2f}")
    except ImportError as e:                         # pragma: no cover - OIDN missing
        print(f"  (OIDN unavailable: {e})")


# --------------------------------------------------------------------------- memory
def _status_kib(field):
    """``VmRSS`` / ``VmHWM`` of this process from ``/proc/self/status``, in KiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return -1


def _synthetic_render(h, w, c=3, bins=4, seed=0):
    """Bins of a smooth image plus Gaussian noise: ``(ys (B, h, w, c), mean_var)`` with
    ``mean_var`` the variance of the mean of ``ys.mean(0)`` (the bins' noise / B)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    base = 0.5 + 0.3 * np.sin(9 * xx)[..., None] * np.cos(7 * yy)[..., None] * np.arange(1, c + 1) / c
    base[:, w // 3:w // 2] += 0.4                          # an edge GEM must not blur over
    mean_var = (0.002 + 0.01 * base * base) / 4.0           # per-bin variance 4·mean_var
    ys = base + np.sqrt(bins * mean_var) * rng.standard_normal((bins, h, w, c))
    return ys, mean_var


def memory_child(which, h=H, w=W, save=None):
    """One ``combine_denoised`` (``which="denoised"``) or ``combine_bins`` (``"bins"``) call
    at ``h x w x 3`` with GEM's ``SelectedFilter``; prints a JSON line with the RSS after the
    inputs, the peak RSS of the call (``VmHWM`` reset by ``/proc/self/clear_refs``), its
    wall and CPU time.  ``save``: write the output to that ``.npy`` (to compare versions)."""
    import json

    from statmc import gem
    from statmc.combine import combine_bins, combine_denoised

    ys, mv = _synthetic_render(h, w)
    y = ys.mean(axis=0)
    _, f = gem.selected_filter(y.astype(np.float32), mv.astype(np.float32))
    small_ys, small_mv = _synthetic_render(24, 20, seed=1)
    _, fs = gem.selected_filter(small_ys.mean(0).astype(np.float32), small_mv.astype(np.float32))
    combine_denoised(small_ys.mean(0), small_mv, fs, rng=0)        # compile / load kernels
    combine_bins(small_ys, small_mv, fs, rng=0)
    try:
        with open("/proc/self/clear_refs", "w") as fh:             # reset VmHWM to VmRSS
            fh.write("5")
    except OSError:                  # pragma: no cover - not Linux: the peak includes setup
        print("warning: could not reset the peak RSS; it includes the setup", flush=True)
    base = _status_kib("VmRSS")
    c0, t0 = time.process_time(), time.perf_counter()
    if which == "denoised":
        out = combine_denoised(y, mv, f, rng=0)
    else:
        out = combine_bins(ys, mv, f, rng=0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = _status_kib("VmHWM")
    if save:
        np.save(save, out)
    print(json.dumps({"which": which, "base_mib": base / 1024, "peak_mib": peak / 1024,
                      "wall_s": wall, "cpu_s": cpu}), flush=True)


def _memory_run(which, h, w, root=None, save=None):
    """One ``--memory-child`` subprocess; ``root``: a checkout whose ``statmc`` (and this
    script) to run instead of the current one.  Returns its JSON record."""
    import json
    import subprocess
    import sys

    script, env = __file__, None
    if root is not None:
        script = os.path.join(root, "bench", "bench_combine.py")
        env = dict(os.environ, PYTHONPATH=os.path.abspath(root))
    cmd = [sys.executable, script, "--memory-child", which, "--height", str(h),
           "--width", str(w)] + (["--save", save] if save else [])
    res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
    return json.loads(res.stdout.strip().splitlines()[-1])


def memory(h=H, w=W, baseline=None, which=("denoised", "bins")):
    """Peak RSS above the inputs of ``combine_denoised`` and ``combine_bins`` at ``h x w``
    (GEM's SelectedFilter; each in its own subprocess, so one does not inherit the other's
    peak), with wall time and load average.  ``baseline``: a checkout of an older version
    (``git archive <commit> statmc bench | tar -x -C DIR``), run first in the same session;
    prints both, the time ratio and whether the outputs are equal to the bit."""
    import tempfile

    print(f"\nmemory of combine_denoised / combine_bins (B = 4) at {w}x{h}x3, 15x15 windows, "
          f"5x5 stencils, GEM's SelectedFilter, synthetic render; load average {_load():.2f}:")
    with tempfile.TemporaryDirectory() as tmp:
        for name in which:
            runs = [("baseline", baseline), ("current", None)] if baseline else [("", None)]
            rec = {}
            for label, root in runs:
                load0 = _load()
                save = os.path.join(tmp, f"{name}-{label}.npy") if baseline else None
                r = rec[label] = _memory_run(name, h, w, root, save)
                print(f"  combine_{name:8s} {label:8s} peak RSS {r['peak_mib'] / 1024:5.2f} GiB "
                      f"= inputs {r['base_mib'] / 1024:4.2f} GiB + "
                      f"{(r['peak_mib'] - r['base_mib']) / 1024:4.2f} GiB; {r['wall_s']:6.1f} s "
                      f"wall ({r['cpu_s']:.1f} s CPU); load average {load0:.2f} -> {_load():.2f}",
                      flush=True)
            if baseline:
                a, b = (np.load(os.path.join(tmp, f"{name}-{x}.npy"))
                        for x in ("baseline", "current"))
                print(f"  combine_{name:8s} current / baseline: wall "
                      f"{rec['current']['wall_s'] / rec['baseline']['wall_s']:.3f}, CPU "
                      f"{rec['current']['cpu_s'] / rec['baseline']['cpu_s']:.3f}; outputs equal "
                      f"to the bit: {np.array_equal(a, b)} (max |diff| {np.abs(a - b).max():.3g})",
                      flush=True)


QUALITY_SCENES = ("toy:mixed", "cornell-box", "glossy-spheres", "glass-caustic", "textured-dof")
QUALITY_SPPS = (4, 16, 64, 256, 1024)


def _scene(scene):
    from statmc.renderers import make_renderer
    from statmc.scenes import DEFAULT_SIZES

    from _scenes import scene_reference

    if scene.startswith("toy:"):
        r = ToyRenderer(scene[4:], width=128, height=128)
        return r, r.true_mean()
    w, h = DEFAULT_SIZES[scene]
    r, ref = scene_reference(scene, make_renderer(scene, width=w, height=h))
    return r, ref.mean


def quality_table(seeds=(0,), out="out/combine/quality.md"):
    """relMSE of raw, OIDN and OIDN + combiner; the issue's check per row."""
    from statmc.metrics import relmse
    from statmc.pipeline import reconstruct_stats

    lines = ["| scene | spp | raw | OIDN | OIDN+combiner | comb/OIDN | comb/raw | renders comb < OIDN "
             "| mix | check |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    print(f"\nOIDN + combiner (reconstruct_stats 'oidn+combine'), relMSE, mean over seeds {seeds}; "
          f"load average {_load():.2f}")
    print("  " + lines[0])
    for scene in QUALITY_SCENES:
        r, ref = _scene(scene)
        for spp in QUALITY_SPPS:
            e = {"raw": [], "oidn": [], "comb": [], "mix": [], "t": []}
            for seed in seeds:
                st = r.render(np.full((r.height, r.width), spp, np.int64), seed=seed * 7919 + spp)
                z, _ = reconstruct_stats(st, "oidn")
                t0 = time.perf_counter()
                x, maps = reconstruct_stats(st, "oidn+combine", seed=seed)
                e["t"].append(time.perf_counter() - t0)
                e["raw"].append(relmse(st.mean, ref))
                e["oidn"].append(relmse(z, ref))
                e["comb"].append(relmse(x, ref))
                e["mix"].append(float(np.mean(maps["mix"])))
            raw, oidn, comb = (float(np.mean(e[n])) for n in ("raw", "oidn", "comb"))
            if spp >= 64:
                ok = comb < min(oidn, raw)
                check = "met" if ok else "**not met**"
            else:
                ok = comb <= 1.05 * oidn
                check = "met (<= 1.05 OIDN)" if ok else "**not met** (> 1.05 OIDN)"
            wins = sum(c < o for c, o in zip(e["comb"], e["oidn"]))
            row = (f"| {scene} | {spp} | {raw:.5f} | {oidn:.5f} | {comb:.5f} | {comb / oidn:.3f} | "
                   f"{comb / raw:.3f} | {wins}/{len(seeds)} | {np.mean(e['mix']):.2f} | {check} |")
            lines.append(row)
            print(f"  {row}   [{np.mean(e['t']):.1f} s per call]", flush=True)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"written {out}")


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=["kernel", "weights", "memory", "quality", "all"],
                    default="all")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--memory-child", choices=["denoised", "bins"], help=argparse.SUPPRESS)
    ap.add_argument("--height", type=int, default=H)
    ap.add_argument("--width", type=int, default=W)
    ap.add_argument("--save", help="--memory-child: save the output to this .npy")
    ap.add_argument("--baseline", help="--part memory: also run this older checkout "
                    "(a directory holding its statmc/ and bench/) first, and compare")
    ap.add_argument("--which", nargs="+", choices=["denoised", "bins"],
                    default=["denoised", "bins"], help="--part memory: the calls to run")
    args = ap.parse_args()
    if args.memory_child:
        memory_child(args.memory_child, args.height, args.width, args.save)
        raise SystemExit
    if args.part in ("kernel", "all"):
        main()
        quality()
    if args.part in ("weights", "all"):
        weights_speed()
    if args.part in ("memory", "all"):
        memory(args.height, args.width, args.baseline, tuple(args.which))
    if args.part in ("quality", "all"):
        quality_table(tuple(args.seeds))
