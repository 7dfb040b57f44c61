"""Progressive denoising with and without the variance-outlier rule (``outlier_alpha``).

For every (scene, spp, seed) cell: one uniform render, OIDN, and ``progressive_denoise`` with
the default ``outlier=8`` ("new") and with ``outlier=None`` (Eq. 9 alone, "old"); relMSE
against the cached high-spp reference (toy scenes: the exact mean).  Prints each cell and
the number of cells the rule changes (docs/progressive.md, docs/quality.md).

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/analysis_progressive_outliers.py``
(about 10 minutes on 2 cores).
"""

import time

import numpy as np

from statmc import metrics
from statmc.demo import cached_reference
from statmc.progressive import bind_denoiser, progressive_denoise
from statmc.renderers import make_renderer

SCENES = ["toy:mixed", "toy:texture", "cornell-box", "textured-dof", "glossy-spheres", "glass-caustic"]


def main():
    rows = []
    for scene in SCENES:
        if scene.startswith("toy"):
            r = make_renderer(scene, width=64, height=64)
            ref = r.true_mean()
        else:
            r = make_renderer(scene)
            ref, _ = cached_reference(r, 32768 if scene == "glass-caustic" else 65536, "out/cache")
        for spp in (4, 16, 64, 256, 1024, 4096):
            for seed in range(3):
                t = time.time()
                st = r.render(np.full((r.height, r.width), spp, np.int64), seed=seed * 7919 + spp)
                f = bind_denoiser("oidn", st)
                y = np.asarray(f(st.mean.astype(np.float32)), np.float64)
                new = progressive_denoise(st, f, rng=seed)
                old = progressive_denoise(st, f, rng=seed, outlier=None)
                e = [metrics.relmse(v, ref) for v in (st.mean, y, old, new)]
                rows.append((scene, spp, seed, *e))
                print(f"{scene:15s} {spp:5d} s{seed} raw {e[0]:.4g} oidn {e[1]:.4g} old/min {e[2]/min(e[0],e[1]):.4f} new/min {e[3]/min(e[0],e[1]):.4f} new/old {e[3]/e[2]:.4f} new/raw {e[3]/e[0]:.4f} ({time.time()-t:.1f}s)", flush=True)
    a = np.array([r[3:] for r in rows])
    print("changed cells:", int((np.abs(a[:, 3] / a[:, 2] - 1) > 1e-9).sum()), "of", len(rows))
    print("new/old range", (a[:, 3] / a[:, 2]).min(), (a[:, 3] / a[:, 2]).max())


if __name__ == "__main__":
    main()
