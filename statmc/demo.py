"""``make demo``: sampling and reconstruction methods on a built-in scene, at equal budgets.

Renders ``cornell-box`` (128×128) at 4, 16 and 64 spp with uniform sampling + box filter,
uniform sampling + GEM reconstruction, and adaptive GEM sampling + GEM reconstruction
(Rousselle et al. 2011), each against a cached 4096-spp reference.  Writes EXR/PNG images,
the adaptive sampling-density maps, a log-log convergence plot and ``results.json`` to
``out/demo/``, and prints the table.  :func:`compare` is reused by the quality benchmarks.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time

import numpy as np

from .errors import FileFormatError, as_int

# name -> (sampler, reconstruction)
METHODS = {
    "uniform+box": ("uniform", "none"),
    "uniform+GEM": ("uniform", "gem"),
    "adaptive GEM": ("gem", "gem"),
}


def render_reference(renderer, spp: int, *, pass_spp: int = 256, seed: int = 1_000_003,
                     progress: bool = True, features: bool = False):
    """``spp`` samples per pixel of ``renderer`` as merged passes of ``pass_spp`` (the last
    one holding the remainder); pass ``k`` has the seed ``seed + 7919 k`` and the first
    pass renders the features when ``features``.  Returns the merged :class:`PixelStats`."""
    from tqdm import tqdm

    spp, pass_spp = as_int("spp", spp), as_int("pass_spp", pass_spp)
    seed = as_int("seed", seed, lo=0)          # True would run as seed 1
    per = min(spp, pass_spp)
    sizes = [per] * (spp // per) + ([spp % per] if spp % per else [])
    stats = None
    for k, size in enumerate(tqdm(sizes, desc=f"reference {renderer.name} {spp} spp",
                                  unit="pass", disable=not progress)):
        counts = np.full((renderer.height, renderer.width), size, np.int64)
        part = renderer.render(counts, seed=seed + 7919 * k, features=features and k == 0)
        stats = part if stats is None else stats.merge(part)
    return stats


def cached_reference(renderer, spp: int, cache_dir: str, *, seed: int = 1_000_003,
                     pass_spp: int = 256):
    """Reference mean image of ``renderer`` at ``spp``, rendered once
    (:func:`render_reference`) and cached as EXR."""
    from .exr import read_image, write_exr, write_png_preview
    name = f"{renderer.name}-{renderer.width}x{renderer.height}-{spp}spp"
    # another camera, or other $name values of a scene file, is another image
    sensor = getattr(renderer, "sensor", 0)
    params = getattr(renderer, "params", None)
    if sensor:
        name += f"-sensor{sensor}"
    if params:
        digest = hashlib.sha1(repr(sorted((str(k), str(v)) for k, v in params.items()))
                              .encode()).hexdigest()[:10]
        name += f"-params{digest}"
    name += ".exr"
    path = os.path.join(cache_dir, name.replace("/", "_").replace(":", "_"))
    if os.path.exists(path):
        try:
            return read_image(path), path
        except FileFormatError as e:  # say, a render interrupted by a full disk
            raise FileFormatError(f"{str(e).rstrip('.')}; it is a cached reference: delete it "
                                  "to render it again.") from None
    stats = render_reference(renderer, spp, pass_spp=pass_spp, seed=seed)
    write_exr(path, stats)
    write_png_preview(path[:-4] + ".png", stats.mean)
    return read_image(path), path


def compare(renderer, ref, spps, methods=METHODS, *, seed: int = 0, out: str | None = None,
            gamma: float = 0.2, quiet: bool = False) -> list[dict]:
    """Every method at every spp against ``ref``; one row of metrics per (method, spp).

    With ``out``, writes each result's reconstruction (EXR + PNG) and, for adaptive
    samplers, the sample-count map (PNG).
    """
    from .exr import write_exr, write_png_preview
    from .metrics import all_metrics
    from .pipeline import reconstruct_stats, render_with_sampler
    from .plots import write_map_png

    seed = as_int("seed", seed, lo=0)          # True would run as seed 1
    rows = []
    for spp in spps:
        for name, (sampler, rec) in methods.items():
            t0 = time.perf_counter()
            # below 8 spp a 2-spp pilot, so that an adaptive run has samples to place
            stats = render_with_sampler(renderer, spp, sampler=sampler, seed=seed + spp,
                                        gamma=gamma, initial_spp=2 if spp < 8 else 4)
            t1 = time.perf_counter()
            image, _ = reconstruct_stats(stats, rec, gamma=gamma)
            t2 = time.perf_counter()
            m = all_metrics(image, ref)
            rows.append({"scene": renderer.name, "spp": spp, "method": name,
                         "total_samples": int(stats.n.sum()), "seconds_render": t1 - t0,
                         "seconds_reconstruct": t2 - t1, **m})
            if out:
                tag = name.replace(" ", "-").replace("+", "-").lower()
                base = os.path.join(out, f"{renderer.name.replace(':', '_')}-{spp}spp-{tag}")
                write_exr(base + ".exr", image)
                write_png_preview(base + ".png", image)
                if sampler != "uniform":
                    write_map_png(base + "-counts.png", stats.n, label="samples per pixel")
            if not quiet:
                r = rows[-1]
                print(f"  {renderer.name:16s} {spp:>5} spp  {name:<14s} relMSE {r['relmse']:.4g}",
                      flush=True)
    return rows


def print_table(rows, methods) -> None:
    spps = sorted({r["spp"] for r in rows})
    by = {(r["spp"], r["method"]): r for r in rows}
    head = f"{'spp':>6} " + " ".join(f"{m:>14s}" for m in methods)
    print("relMSE\n" + head)
    for s in spps:
        print(f"{s:>6} " + " ".join(f"{by[(s, m)]['relmse']:>14.4g}" for m in methods))


def run(out: str, *, scene: str = "cornell-box", size=(128, 128), spps=(4, 16, 64),
        ref_spp: int = 4096, seed: int = 0) -> list[dict]:
    from .plots import write_convergence_plot
    from .renderers import make_renderer

    from .cli import _check_writable_dir
    # bad input is refused before anything is written (an unknown scene made an empty --out)
    renderer = make_renderer(scene, width=size[0], height=size[1])
    _check_writable_dir(out, out)
    cache = os.path.join(os.path.dirname(os.path.abspath(out)), "cache")
    ref, ref_path = cached_reference(renderer, ref_spp, cache)
    os.makedirs(out, exist_ok=True)
    rows = compare(renderer, ref, spps, seed=seed, out=out)
    series = {m: ([r["spp"] for r in rows if r["method"] == m],
                  [r["relmse"] for r in rows if r["method"] == m]) for m in METHODS}
    plot = os.path.join(out, "convergence.png")
    write_convergence_plot(plot, series, title=f"{scene} {renderer.width}x{renderer.height}, "
                           f"reference {ref_spp} spp")
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump({"reference": ref_path, "rows": rows}, f, indent=2)
    print(f"\n{scene} {renderer.width}x{renderer.height}, reference {ref_spp} spp")
    print_table(rows, METHODS)
    print(f"\nimages, sampling-density maps, convergence.png and results.json in {out}/")
    return rows


def main(argv=None) -> int:
    """The ``python -m statmc.demo`` entry: its exit status.  Bad input (an unknown
    ``--scene``, an ``--out`` that cannot be written, ...) prints one line and gives 2, as
    the ``statmc`` commands do (:func:`statmc.cli.run_command`); ``--debug`` shows the
    traceback."""
    from .cli import POSITIVE_INT, _Parser, run_command
    p = _Parser(prog="python -m statmc.demo",
                description=__doc__.splitlines()[0].replace("``", "`"))
    p.add_argument("--out", default="out/demo",
                   help="output directory (default out/demo); the reference is cached in "
                        "cache/ beside it (out/cache)")
    p.add_argument("--scene", default="cornell-box",
                   help="scene rendered at 128x128: a built-in name (`statmc scenes`), "
                        "toy:NAME or a Mitsuba XML path (default cornell-box)")
    p.add_argument("--ref-spp", type=POSITIVE_INT, default=4096,
                   help="samples per pixel of the reference, a positive integer (default 4096)")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    a = p.parse_args(argv)

    def demo():
        from .renderers import check_scene
        run(a.out, scene=check_scene(a.scene, "--scene"), ref_spp=a.ref_spp)

    return run_command(demo, prog=p.prog, debug=a.debug,
                       memory_hint="use a smaller --ref-spp or another --scene.")


if __name__ == "__main__":
    sys.exit(main())
