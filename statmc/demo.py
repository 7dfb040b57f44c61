"""``make demo``: render a built-in scene at several sample counts and measure the error.

Renders ``cornell-box`` (small) at 4, 16 and 64 spp against a cached high-spp reference,
writes EXR and PNG previews to ``out/demo/`` and prints relMSE per spp.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def cached_reference(renderer, spp: int, cache_dir: str, *, seed: int = 1_000_003,
                     pass_spp: int = 256):
    """Reference mean image of ``renderer`` at ``spp``, rendered once and cached as EXR."""
    from tqdm import tqdm

    from .exr import read_image, write_exr, write_png_preview
    name = f"{renderer.name}-{renderer.width}x{renderer.height}-{spp}spp.exr"
    path = os.path.join(cache_dir, name.replace("/", "_").replace(":", "_"))
    if os.path.exists(path):
        return read_image(path), path
    stats = None
    passes = max(1, spp // pass_spp)
    for k in tqdm(range(passes), desc=f"reference {spp} spp", unit="pass"):
        counts = np.full((renderer.height, renderer.width), min(spp, pass_spp), np.int64)
        part = renderer.render(counts, seed=seed + 7919 * k, features=False)
        stats = part if stats is None else stats.merge(part)
    write_exr(path, stats)
    write_png_preview(path[:-4] + ".png", stats.mean)
    return read_image(path), path


def run(out: str, *, scene: str = "cornell-box", size=(128, 128), spps=(4, 16, 64),
        ref_spp: int = 4096, seed: int = 0) -> list[dict]:
    from .exr import write_exr, write_png_preview
    from .metrics import all_metrics
    from .renderers import make_renderer

    os.makedirs(out, exist_ok=True)
    renderer = make_renderer(scene, width=size[0], height=size[1])
    ref, ref_path = cached_reference(renderer, ref_spp, os.path.join(os.path.dirname(out.rstrip("/")) or ".", "cache"))
    rows = []
    for spp in spps:
        counts = np.full((renderer.height, renderer.width), spp, np.int64)
        t0 = time.perf_counter()
        stats = renderer.render(counts, seed=seed + spp)
        secs = time.perf_counter() - t0
        base = os.path.join(out, f"{scene}-{spp}spp-uniform-box")
        write_exr(base + ".exr", stats)
        write_png_preview(base + ".png", stats.mean)
        m = all_metrics(stats.mean.astype(np.float32), ref)
        rows.append({"scene": scene, "spp": spp, "method": "uniform+box", "seconds": secs, **m})
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump({"reference": ref_path, "rows": rows}, f, indent=2)
    print(f"\n{scene} {renderer.width}x{renderer.height}, reference {ref_spp} spp")
    print(f"{'spp':>6} {'method':<16} {'relMSE':>10} {'SMAPE':>8} {'FLIP':>7} {'time/s':>7}")
    for r in rows:
        print(f"{r['spp']:>6} {r['method']:<16} {r['relmse']:>10.4g} {r['smape']:>8.4f} "
              f"{r['flip']:>7.4f} {r['seconds']:>7.2f}")
    print(f"\nimages and results.json in {out}/")
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="out/demo")
    p.add_argument("--scene", default="cornell-box")
    p.add_argument("--ref-spp", type=int, default=4096)
    a = p.parse_args(argv)
    run(a.out, scene=a.scene, ref_spp=a.ref_spp)


if __name__ == "__main__":
    main()
