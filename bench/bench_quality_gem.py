"""Quality at equal budget on the built-in Mitsuba scenes (issue 3's acceptance table).

For each scene at its default size: uniform+box, uniform+GEM and adaptive GEM at 16, 32
and 64 spp against a cached 4096-spp reference (out/cache/).  Prints a Markdown table with
relMSE and the ratios the issue asks for (uniform+GEM / uniform+box <= 0.5; adaptive GEM /
uniform+GEM <= 0.9) and writes it to out/bench/quality_gem.md.
"""

import argparse
import os
import sys

import numpy as np

from statmc.demo import METHODS, cached_reference, compare
from statmc.renderers import make_renderer
from statmc.scenes import BUILTIN_SCENES

# The caustic of a tiny bright light converges slowly: two independent 4096-spp references
# differ by relMSE 0.079 there (1e-4..3e-4 for the other scenes), more than the errors
# being compared, so that scene gets a reference with 8x the samples.
REF_SPP = {"glass-caustic": 32768}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="*", default=list(BUILTIN_SCENES))
    p.add_argument("--spp", nargs="*", type=int, default=[16, 32, 64])
    p.add_argument("--ref-spp", type=int, default=4096, help="reference spp (see REF_SPP)")
    p.add_argument("--gamma", type=float, default=0.2)
    p.add_argument("--seeds", type=int, default=2, help="independent repeats averaged per cell")
    p.add_argument("--out", default="out/bench")
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    lines = ["| scene | spp | uniform+box | uniform+GEM | adaptive GEM | GEM/box (≤0.5) | adaptive/uniform GEM (≤0.9) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    ok = True
    for scene in a.scenes:
        r = make_renderer(scene)
        ref, _ = cached_reference(r, max(a.ref_spp, REF_SPP.get(scene, 0)), "out/cache")
        rows = []
        for s in range(a.seeds):
            rows += compare(r, ref, a.spp, METHODS, seed=1000 * s, gamma=a.gamma, quiet=True)
        for spp in a.spp:
            v = {m: np.mean([x["relmse"] for x in rows if x["spp"] == spp and x["method"] == m])
                 for m in METHODS}
            r1 = v["uniform+GEM"] / v["uniform+box"]
            r2 = v["adaptive GEM"] / v["uniform+GEM"]
            ok &= (r1 <= 0.5) and (r2 <= 0.9)
            lines.append(f"| {scene} | {spp} | {v['uniform+box']:.4g} | {v['uniform+GEM']:.4g} | "
                         f"{v['adaptive GEM']:.4g} | {r1:.3f} {'PASS' if r1 <= 0.5 else 'NOT REACHED'} | "
                         f"{r2:.3f} {'PASS' if r2 <= 0.9 else 'NOT REACHED'} |")
            print(lines[-1], flush=True)
    table = "\n".join(lines)
    with open(os.path.join(a.out, "quality_gem.md"), "w") as f:
        f.write(f"relMSE (ε = 0.01), mean of {a.seeds} seeds, γ = {a.gamma}, reference {a.ref_spp} spp "
                f"({', '.join(f'{k}: {v}' for k, v in REF_SPP.items())})\n\n")
        f.write(table + "\n")
    print("\n" + table)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
