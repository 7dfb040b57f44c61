"""End-to-end time of statmc's commands on realistic files, each next to its peer.

Writes statistics EXRs the way statmc does (the toy renderer's ``toy:mixed`` at 4 spp,
``write_exr``: mean, variance, channel covariances, SampleCount, albedo, normal, depth), then
times ``python -m statmc COMMAND`` as a user runs it (a fresh interpreter: imports, numba's
cache load, EXR read, the work, EXR write, PNG preview; wall clock and the child's peak RSS).
The peer of each command is the least a script would do for the same output, measured in
the same run: interpreter start with numpy + OpenEXR imported, ``OpenEXR.File`` reading the
input channels, the computation through the Python API on those arrays (warm: imports and
numba compiles done once beforehand, as in ``make bench``), and ``OpenEXR.File`` writing
the output's channels with statmc's compression (ZIP; the peer on OpenEXR's default of no
worker threads, the command on its thread pool sized to the CPUs, which helps only when a
CPU is idle: on a loaded machine the two read alike).  ``ratio`` = command / peer: what
the command line costs beyond its work.  OIDN's peer is ``pyoidn`` called directly (imported, as statmc does, with passive
OpenMP waits: a plain ``import pyoidn`` loads torch's spinning runtime, which made the
peer's numba kernels after it up to 2x slower).

    python bench/bench_cli.py [--size 960x540] [--repeat 1] [--heavy]

``--heavy`` adds ``reconstruct --method oidn+combine`` (~25 s at 960x540).  Wall clocks on
a shared machine are noisy: the load average is printed with the table; repeat and compare
the ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _load() -> str:
    return "load average %.2f %.2f %.2f" % os.getloadavg()


def run_cli(argv, env) -> tuple[float, float]:
    """Wall seconds and peak RSS (MiB) of one ``python -m statmc ARGV`` (os.wait4: this
    child's own rusage)."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "statmc", *argv], env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read().decode()
    p.stderr.close()
    if p.returncode:
        raise SystemExit(f"statmc {' '.join(argv)} failed ({p.returncode}): {err}")
    return wall, ru.ru_maxrss / 1024.0


def startup(env, repeat=3) -> float:
    """A fresh interpreter importing numpy and OpenEXR (the floor of any script)."""
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import numpy, OpenEXR"], env=env, check=True)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


# The peer worker runs in its own interpreter so that its imports (torch through pyoidn,
# FLIP) and memory do not touch this process.  It prints one JSON object.
PEER = r'''
import json, sys, time, statistics
import numpy as np, OpenEXR
d = sys.argv[1]; heavy = sys.argv[2] == "1"; rep = int(sys.argv[3])
Y, Z, REF = f"{d}/y.exr", f"{d}/z.exr", f"{d}/ref.exr"

def med(fn, k=rep):
    ts = []
    for _ in range(k):
        t0 = time.perf_counter(); out = fn(); ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out

def read(p):
    with OpenEXR.File(p, separate_channels=True) as f:
        return {k: np.array(v.pixels) for k, v in f.channels().items()}

def write(p, chans):
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(hdr, {k: np.ascontiguousarray(v, np.float32) for k, v in chans.items()}) as f:
        f.write(p)

def rgb(ch, pre=""):
    return np.stack([ch[pre + c] for c in "RGB"], -1).astype(np.float32)

def out_chans(img, **maps):
    o = {c: img[..., i] for i, c in enumerate("RGB")}
    o.update(maps)
    return o

res = {}
t_read, ch = med(lambda: read(Y))
tz, chz = med(lambda: read(Z))
tr, chr_ = med(lambda: read(REF))
n = ch["SampleCount"].astype(np.int64)
mean = rgb(ch); var = rgb(ch, "Variance.") / np.maximum(n, 1)[..., None]
albedo, normal = rgb(ch, "Albedo."), np.stack([ch["N." + c] for c in "XYZ"], -1).astype(np.float32)

# info: the read and a NaN/Inf count per channel
t, _ = med(lambda: {k: int((~np.isfinite(v)).sum()) for k, v in ch.items()})
res["info"] = {"read": t_read, "compute": t, "write": 0.0}

import statmc.gem as gem
gem.reconstruct(mean, var, n=n)                                  # compile / cache, warm
t, img = med(lambda: gem.reconstruct(mean, var, n=n, extra_output=True))
tw, _ = med(lambda: write(f"{d}/peer.exr", out_chans(img[0], s=img[1]["scales"], g=img[1]["scales"])))
res["reconstruct gem"] = {"read": t_read, "compute": t, "write": tw}

from statmc._threads import import_passively
pyoidn = import_passively("pyoidn")   # as statmc does: torch's spinning OpenMP slowed numba 2x
dev = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU); dev.commit()
out = np.zeros_like(mean)
def oidn():
    f = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT)
    fmt = pyoidn.OIDN_FORMAT_FLOAT3
    f.set_image(pyoidn.OIDN_IMAGE_COLOR, np.ascontiguousarray(mean), fmt)
    f.set_image(pyoidn.OIDN_IMAGE_ALBEDO, np.ascontiguousarray(albedo), fmt)
    f.set_image(pyoidn.OIDN_IMAGE_NORMAL, np.ascontiguousarray(normal), fmt)
    f.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, fmt)
    f.set_bool("hdr", True); f.set_int("quality", pyoidn.OIDN_QUALITY_HIGH)
    f.commit(); f.execute(); f.release()
    return out
oidn()
t, den = med(oidn)
tw, _ = med(lambda: write(f"{d}/peer.exr", out_chans(den)))
res["denoise oidn"] = {"read": t_read, "compute": t, "write": tw}

from statmc.metrics import all_metrics
ref = rgb(chr_)
all_metrics(mean[:64, :64], ref[:64, :64])                       # FLIP imported
t, _ = med(lambda: all_metrics(mean, ref))
res["metrics"] = {"read": t_read + tr, "compute": t, "write": 0.0}

from statmc.stats import PixelStats
from statmc.pipeline import reconstruct_stats
m2 = rgb(ch, "Variance.").astype(np.float64) * np.maximum(n - 1, 0)[..., None]
st = PixelStats(n, mean.astype(np.float64), m2, albedo=albedo, normal=normal)
reconstruct_stats(st, "progressive")
t, pr = med(lambda: reconstruct_stats(st, "progressive"))
tw, _ = med(lambda: write(f"{d}/peer.exr", out_chans(pr[0], a=pr[1]["alpha"])))
res["progressive"] = {"read": t_read, "compute": t, "write": tw}

from statmc import combine as cb
nz = chz["SampleCount"].astype(np.int64)
z = rgb(chz); varz = rgb(chz, "Variance.") / np.maximum(nz, 1)[..., None]
def comb():
    w = cb.statistical_weights(mean, z, var, varz, 15)
    return cb.combine(mean, z, w)
comb()
t, co = med(comb)
tw, _ = med(lambda: write(f"{d}/peer.exr", out_chans(co)))
res["combine statistical"] = {"read": t_read + tz, "compute": t, "write": tw}

if heavy:
    t, oc = med(lambda: reconstruct_stats(st, "oidn+combine"), 1)
    tw, _ = med(lambda: write(f"{d}/peer.exr", out_chans(oc[0], m=oc[1]["mix"])))
    res["reconstruct oidn+combine"] = {"read": t_read, "compute": t, "write": tw}
print(json.dumps(res))
'''


def make_inputs(d, width, height) -> None:
    import numpy as np

    from statmc.exr import write_exr
    from statmc.renderers import make_renderer

    r = make_renderer("toy:mixed", width=width, height=height)
    counts = np.full((height, width), 4, np.int64)
    for name, seed in (("y", 0), ("z", 1), ("ref", 2)):
        write_exr(os.path.join(d, f"{name}.exr"), r.render(counts, seed=seed))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="960x540", help="WxH of the files (default 960x540)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each command (median)")
    ap.add_argument("--heavy", action="store_true", help="also reconstruct --method oidn+combine")
    ap.add_argument("--make-inputs", metavar="DIR", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.make_inputs:
        w, h = map(int, args.size.lower().split("x"))
        make_inputs(args.make_inputs, w, h)
        return 0
    width, height = map(int, args.size.lower().split("x"))
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", os.path.join(ROOT, ".cache", "numba"))
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_cli_") as d:
        # in a child: a forked child's peak RSS starts at its parent's, so keep this one small
        subprocess.run([sys.executable, __file__, "--make-inputs", d, "--size", args.size], env=env,
                       check=True)
        y, z, ref, o = (os.path.join(d, f) for f in ("y.exr", "z.exr", "ref.exr", "out.exr"))
        print(f"# {width}x{height} toy:mixed 4 spp, {os.path.getsize(y) / 2 ** 20:.1f} MB per "
              f"file; {_load()}", flush=True)
        base = startup(env)
        peers = json.loads(subprocess.run(
            [sys.executable, "-c", PEER, d, "1" if args.heavy else "0", str(args.repeat)],
            env=env, check=True, capture_output=True, text=True).stdout)
        commands = {
            "info": ["info", y],
            "reconstruct gem": ["reconstruct", y, "--out", o, "-q"],
            "denoise oidn": ["denoise", y, "--denoiser", "oidn", "--out", o, "-q"],
            "metrics": ["metrics", y, ref],
            "progressive": ["progressive", y, "--out", o, "-q"],
            "combine statistical": ["combine", y, z, "--weights", "statistical", "--out", o,
                                    "-q"],
        }
        if args.heavy:
            commands["reconstruct oidn+combine"] = ["reconstruct", y, "--method", "oidn+combine",
                                                    "--out", o, "-q"]
        print(f"{'command':26s} {'statmc s':>9s} {'peer s':>7s} {'ratio':>6s} {'RSS MiB':>8s}"
              f"   peer = start {base:.2f} + read + compute + write")
        for name, argv in commands.items():
            runs = [run_cli(argv, env) for _ in range(args.repeat)]
            wall = statistics.median(r[0] for r in runs)
            rss = max(r[1] for r in runs)
            p = peers[name]
            peer = base + p["read"] + p["compute"] + p["write"]
            print(f"{name:26s} {wall:9.2f} {peer:7.2f} {wall / peer:6.2f} {rss:8.0f}"
                  f"   {p['read']:.2f} + {p['compute']:.2f} + {p['write']:.2f}", flush=True)
    print(f"# {_load()}; bench took {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
