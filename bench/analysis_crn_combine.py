"""Combining an independent render with a common-random-number (CRN) render (issue 5).

Back et al. 2020 (§1, §3) combine independent pixel estimates ``y`` with *correlated* ones
``z``; a CRN render (every pixel's ``j``-th sample uses the same random sequence,
:meth:`statmc.mitsuba_backend.MitsubaRenderer.render_crn`) is one of their examples.  Its
pixels are unbiased but their errors are correlated, so the differences ``z_c − z_t``
that Eq. 8 adds to the neighbours' ``y_t`` are far less noisy than ``z`` itself.

Per scene, spp and seed: ``y`` = an independent render of ``spp`` samples, ``z`` = a CRN
render of ``spp`` samples (independent of ``y``), the covariance stencil of ``z`` from
its own samples, weights :func:`statmc.combine.statistical_weights` (``"coherent"``,
``k×k``, ``z_bias="estimate"`` and ``"zero"``), output Eq. 8 (:func:`statmc.combine.combine`).
Printed: relMSE (ε = 0.01, cached high-spp reference) of ``y``, ``z``, the plain average
of the two renders, an independent render of ``2 spp`` (the same budget as ``y`` + ``z``)
and the combinations; ratios to the ``2 spp`` render, mean over seeds with the per-seed
range; and the time of the CRN render and of the weights.

Run: ``NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/analysis_crn_combine.py``
(``--scenes``, ``--spp``, ``--seeds``, ``--size`` for the window ``k``, ``--json``).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from statmc import combine as cb
from statmc import metrics

from _scenes import scene_reference  # noqa: E402  (bench/ is the script's directory)

SCENES = ("cornell-box", "glossy-spheres", "textured-dof", "glass-caustic")


def cell(r, ref, spp, seed, k):
    """relMSE of every method for one (scene, spp, seed), and the timings."""
    y = r.render_uniform(spp, seed=5000 + seed, features=False)
    t0 = time.perf_counter()
    z, cov = r.render_crn(spp, seed=5000 + seed, stencil=k, features=False)
    t_crn = time.perf_counter() - t0
    y2 = r.render_uniform(2 * spp, seed=6000 + seed, features=False)
    out = {"y": metrics.relmse(y.mean, ref), "z (CRN)": metrics.relmse(z.mean, ref),
           "average of y, z": metrics.relmse(y.merge(z).mean, ref),
           "y at 2 spp": metrics.relmse(y2.mean, ref)}
    t0 = time.perf_counter()
    for zb in ("estimate", "zero"):
        w = cb.statistical_weights(y.mean, z.mean, y.mean_var, cov, k, z_bias=zb)
        out[f"combined ({zb})"] = metrics.relmse(cb.combine(y.mean, z.mean, w), ref)
    t_w = (time.perf_counter() - t0) / 2
    return out, t_crn, t_w


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--spp", type=int, nargs="*", default=[16, 64])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--size", type=int, default=15, help="window k (the stencil is k wide)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    rows = []
    for scene in a.scenes:
        r, ref = scene_reference(scene)
        ref = ref.mean
        for spp in a.spp:
            res, tc, tw = {}, [], []
            for s in range(a.seeds):
                out, t_crn, t_w = cell(r, ref, spp, s, a.size)
                for key, v in out.items():
                    res.setdefault(key, []).append(v)
                tc.append(t_crn)
                tw.append(t_w)
            base = np.array(res["y at 2 spp"])
            print(f"\n{scene} {r.width}x{r.height}, {spp} + {spp} spp, k = {a.size}, "
                  f"{a.seeds} seeds (CRN render {np.mean(tc):.2f} s, weights {np.mean(tw):.2f} s)")
            print(f"  {'method':20s} {'relMSE':>10s} {'/ y at 2 spp':>13s}  per-seed range")
            for key, v in res.items():
                ratio = np.array(v) / base
                print(f"  {key:20s} {np.mean(v):10.4g} {np.mean(v) / base.mean():13.3f}  "
                      f"[{ratio.min():.3f}, {ratio.max():.3f}]")
            rows.append({"scene": scene, "spp": spp, "k": a.size, "relmse": res,
                         "seconds_crn": tc, "seconds_weights": tw})
    if a.json:
        os.makedirs(os.path.dirname(a.json) or ".", exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
