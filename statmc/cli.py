"""The ``statmc`` command line.

Every command validates its input and exits non-zero with one line naming what is wrong
(``--debug`` shows the traceback).  Outputs are written atomically and never onto an input.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from . import __version__
from .errors import InputError

EXIT_USAGE = 2


# ---------------------------------------------------------------------------- helpers
def _parse_size(text: str | None):
    if text is None:
        return None, None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like WIDTHxHEIGHT (e.g. 128x96); got {text!r}.") from None
    if w <= 0 or h <= 0:
        raise InputError(f"--size must be positive; got {text!r}.")
    return w, h


def _positive_int(name: str, value) -> int:
    if value is None or int(value) != value or value < 0:
        raise InputError(f"{name} must be a non-negative integer; got {value!r}.")
    return int(value)


def load_sample_map(path: str) -> np.ndarray:
    """A per-pixel sample map ``(H, W)`` from a ``.npy`` file or a one-channel EXR."""
    if not os.path.exists(path):
        raise InputError(f"sample map {path} does not exist.")
    if path.lower().endswith(".npy"):
        try:
            m = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise InputError(f"cannot read sample map {path} as .npy: {e}") from None
    elif path.lower().endswith(".exr"):
        from .exr import read_channels
        ch = read_channels(path)
        for name in ("SampleCount", "Y", "A", "R"):
            if name in ch:
                m = ch[name]
                break
        else:
            if len(ch) != 1:
                raise InputError(f"sample map {path} has channels {sorted(ch)}; expected "
                                 "'SampleCount' or a single channel.")
            m = next(iter(ch.values()))
    else:
        raise InputError(f"sample map {path} must be a .npy or .exr file.")
    m = np.asarray(m)
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[..., 0]
    if m.ndim != 2 or not np.issubdtype(m.dtype, np.number):
        raise InputError(f"sample map {path} must be a numeric (H, W) array; got {m.dtype} {m.shape}.")
    m = m.astype(np.float64)
    bad = ~np.isfinite(m)
    if bad.any():
        raise InputError(f"sample map {path} holds {int(bad.sum())} NaN/Inf values.")
    if (m < 0).any():
        raise InputError(f"sample map {path} holds {int((m < 0).sum())} negative values.")
    return m


def counts_for_render(height, width, *, spp=None, sample_map=None, seed=0) -> np.ndarray:
    """The integer count map a render uses: uniform ``spp``, or a sample map.

    A map of whole numbers is used as counts; a real-valued map is a density scaled to
    the budget ``spp × H × W`` (exact total, unbiased rounding).
    """
    from .sampling import counts_from_density
    if sample_map is None:
        if spp is None:
            raise InputError("give --spp (samples per pixel) or --sample-map.")
        return np.full((height, width), _positive_int("--spp", spp), np.int64)
    if sample_map.shape != (height, width):
        raise InputError(f"sample map is {sample_map.shape[1]}x{sample_map.shape[0]} (WxH) but the "
                         f"render is {width}x{height}; pass a matching --size.")
    if np.all(sample_map == np.round(sample_map)) and spp is None:
        return sample_map.astype(np.int64)
    if spp is None:
        raise InputError("a real-valued sample map needs --spp to set the budget.")
    return counts_from_density(sample_map, _positive_int("--spp", spp) * height * width, rng=seed)


def _write_json(path, obj, protect=()):
    from ._atomic import write_text
    write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n", protect=protect)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _write_result(path, data, image, *, inputs, extra=None, quiet=False) -> None:
    """Write ``data`` (statistics or an image) to ``path`` and a PNG preview of ``image``
    beside it, never onto one of ``inputs``."""
    from .exr import write_exr, write_png_preview
    write_exr(path, data, protect=inputs, extra=extra)
    write_png_preview(os.path.splitext(path)[0] + ".png", image, protect=inputs)
    if not quiet:
        print(f"wrote {path}")


# ---------------------------------------------------------------------------- commands
def cmd_render(args) -> int:
    from .exr import read_image, write_exr, write_png_preview
    from .metrics import all_metrics
    from .pipeline import reconstruct_stats, render_with_sampler
    from .plots import write_map_png
    from .renderers import make_renderer

    width, height = _parse_size(args.size)
    sample_map = load_sample_map(args.sample_map) if args.sample_map else None
    if sample_map is not None and width is None:
        height, width = sample_map.shape
    if sample_map is not None and args.sampler != "uniform":
        raise InputError(f"--sample-map fixes the counts; it cannot be combined with --sampler {args.sampler}.")
    ref = read_image(args.reference) if args.reference else None
    renderer = make_renderer(args.scene, width=width, height=height)
    counts = None
    if args.sampler == "uniform":
        counts = counts_for_render(renderer.height, renderer.width, spp=args.spp,
                                   sample_map=sample_map, seed=args.seed)
    elif args.spp is None or args.spp <= 0:
        raise InputError(f"--sampler {args.sampler} needs a positive --spp budget; got {args.spp}.")
    if ref is not None and ref.shape[:2] != (renderer.height, renderer.width):
        raise InputError(f"reference {args.reference} is {ref.shape[1]}x{ref.shape[0]} but the render "
                         f"is {renderer.width}x{renderer.height}.")
    inputs = [p for p in (args.sample_map, args.reference) if p]
    t0 = time.perf_counter()
    stats = render_with_sampler(renderer, args.spp, sampler=args.sampler, counts=counts,
                                seed=args.seed, progress=not args.quiet, gamma=args.gamma,
                                denoiser=args.denoiser)
    seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    image, maps = reconstruct_stats(stats, args.reconstruct, gamma=args.gamma,
                                    denoiser=args.denoiser or "oidn", seed=args.seed,
                                    gem_bias=args.gem_bias)
    seconds_rec = time.perf_counter() - t0
    os.makedirs(args.out, exist_ok=True)
    out = lambda name: os.path.join(args.out, name)  # noqa: E731
    write_exr(out("render.exr"), stats, protect=inputs)
    write_png_preview(out("render.png"), stats.mean, protect=inputs)
    write_exr(out("counts.exr"), stats.n[..., None].astype(np.float32), protect=inputs)
    write_map_png(out("counts.png"), stats.n, label="samples per pixel", protect=inputs)
    if args.reconstruct != "none":
        write_exr(out("reconstruction.exr"), image, protect=inputs,
                  extra={f"{args.reconstruct}.{k}": v for k, v in maps.items()})
        write_png_preview(out("reconstruction.png"), image, protect=inputs)
        if "scale" in maps:
            write_exr(out("scales.exr"), maps["scale"][..., None], protect=inputs)
            write_map_png(out("scales.png"), maps["scale"], cmap="magma",
                          label="selected scale (0 = pixel filter)", protect=inputs)
    n = stats.n
    total = int(n.sum())
    report = {
        "scene": args.scene, "renderer": type(renderer).__name__,
        "width": renderer.width, "height": renderer.height, "seed": args.seed,
        "sampler": args.sampler, "reconstruct": args.reconstruct, "gamma": args.gamma,
        "gem_bias": args.gem_bias,
        "spp": total / n.size, "total_samples": total,
        "spp_min": int(n.min()), "spp_max": int(n.max()),
        "seconds": seconds, "samples_per_second": total / max(seconds, 1e-12),
        "seconds_reconstruct": seconds_rec,
        "renderer_info": {k: v for k, v in stats.meta.items() if np.isscalar(v) or isinstance(v, str)},
    }
    if ref is not None:
        report["reference"] = args.reference
        report["metrics"] = all_metrics(stats.mean.astype(np.float32), ref)
        if args.reconstruct != "none":
            report["metrics_reconstruction"] = all_metrics(image, ref)
    _write_json(out("report.json"), report, protect=inputs)
    if not args.quiet:
        msg = f"wrote {args.out}/ ({total} samples, {seconds:.2f} s"
        msg += f", {report['samples_per_second'] / 1e6:.2f} M samples/s)"
        if ref is not None:
            msg += f"; relMSE raw {report['metrics']['relmse']:.4g}"
            if args.reconstruct != "none":
                msg += f", {args.reconstruct} {report['metrics_reconstruction']['relmse']:.4g}"
        print(msg)
    return 0


def cmd_reconstruct(args) -> int:
    from .exr import read_exr
    from .pipeline import reconstruct_stats
    stats = read_exr(args.input, spp=args.spp)
    image, maps = reconstruct_stats(stats, args.method, gamma=args.gamma, gem_bias=args.gem_bias)
    _write_result(args.out, image, image, inputs=[args.input], quiet=args.quiet,
                  extra={f"{args.method}.{k}": v for k, v in maps.items()})
    return 0


def _add_gem_options(parser, gamma_use: str = "") -> None:
    """``--gamma`` and ``--gem-bias``: the GEM selector's error rate and bias estimate."""
    parser.add_argument("--gamma", type=float, default=0.2,
                        help=f"GEM error-rate parameter γ (Rousselle 2011 §4.3): used by {gamma_use}"
                             "by the final GEM reconstruction only with --gem-bias paper")
    parser.add_argument("--gem-bias", choices=["pooled", "paper"], default="pooled",
                        help="bias estimate of GEM's final scale selection: pooled (default, "
                             "docs/gem.md §5d) or the paper's per-pixel Eq. 1")


def _make_denoiser(name, stats, *, gamma=0.2, sigma=1.0, gem_bias=None):
    """A denoiser bound to ``stats``' features (OIDN) or variance (GEM)."""
    from .pipeline import _denoiser_options
    from .progressive import bind_denoiser
    return bind_denoiser(name, stats, **_denoiser_options(name, gamma, sigma, gem_bias))


def cmd_denoise(args) -> int:
    from .exr import read_exr
    from .stats import PixelStats
    stats = read_exr(args.input, spp=args.spp)
    den = _make_denoiser(args.denoiser, stats, gamma=args.gamma, sigma=args.sigma,
                         gem_bias=args.gem_bias)
    x = stats.mean.astype(np.float32)
    out = np.asarray(den(x), np.float32)
    result = out
    if args.variance:
        # Store the denoised output as statistics whose variance of the mean is the
        # first-order variance of the output (Firmino 2023), with the input's counts.
        from .sure import output_variance
        if hasattr(den, "kernels"):  # linear filters: exactly Σ_j w_ij² σ_j²
            var = output_variance(den, x, stats.mean_var.astype(np.float32), method="exact")
        else:  # first order; the channel covariance when the file has it (OIDN mixes channels)
            cov = stats.mean_cov if stats.has_cov else stats.mean_var
            var = output_variance(den, x, cov.astype(np.float32), method="fd", rng=args.seed)
        n = stats.n.astype(np.float64)[..., None]
        result = PixelStats(stats.n, out, np.maximum(var, 0) * n * np.maximum(n - 1, 0),
                            albedo=stats.albedo, normal=stats.normal, depth=stats.depth)
    _write_result(args.out, result, out, inputs=[args.input], quiet=args.quiet)
    return 0


def cmd_progressive(args) -> int:
    from .exr import read_exr
    from .pipeline import reconstruct_stats
    stats = read_exr(args.input, spp=args.spp)
    image, maps = reconstruct_stats(stats, "progressive", denoiser=args.denoiser, gamma=args.gamma,
                                    seed=args.seed, gem_bias=args.gem_bias)
    _write_result(args.out, image, image, inputs=[args.input], quiet=args.quiet,
                  extra={f"progressive.{k}": v for k, v in maps.items()})
    return 0


def cmd_combine(args) -> int:
    from . import combine as cb
    from .exr import read_exr, read_image
    y_stats = read_exr(args.y, spp=args.spp)
    y = y_stats.mean.astype(np.float32)
    h, w, _ = y.shape
    if args.weights == "statistical":
        z_stats = read_exr(args.z, spp=args.spp)  # needs Variance.* (e.g. `statmc denoise --variance`)
        z = z_stats.mean.astype(np.float32)
    else:
        z = read_image(args.z)
    if z.shape != y.shape:
        raise InputError(f"{args.z} is {z.shape[1]}x{z.shape[0]}x{z.shape[2]} but {args.y} is "
                         f"{w}x{h}x{y.shape[2]}; Y and Z must have the same size.")
    if args.size < 1 or args.size % 2 == 0:
        raise InputError(f"--size must be an odd window width; got {args.size}.")
    if args.weights == "uniform":
        weights = cb.uniform_weights(h, w, 1, args.size)
    elif args.weights == "gaussian":
        weights = cb.gaussian_weights(h, w, 1, args.size, args.sigma)
    else:
        weights = cb.statistical_weights(y, z, y_stats.mean_var.astype(np.float32),
                                         z_stats.mean_var.astype(np.float32), args.size)
    out = cb.combine(y, z, weights)
    _write_result(args.out, out, out, inputs=[args.y, args.z], quiet=args.quiet)
    return 0


def cmd_reference(args) -> int:
    from tqdm import tqdm

    from .exr import write_exr, write_png_preview
    from .renderers import make_renderer

    width, height = _parse_size(args.size)
    spp = _positive_int("--spp", args.spp)
    if spp == 0:
        raise InputError("--spp must be positive for a reference.")
    renderer = make_renderer(args.scene, width=width, height=height)
    per_pass = min(spp, args.pass_spp)
    passes = [per_pass] * (spp // per_pass) + ([spp % per_pass] if spp % per_pass else [])
    stats = None
    for k, s in enumerate(tqdm(passes, desc="reference passes", unit="pass", disable=args.quiet)):
        counts = np.full((renderer.height, renderer.width), s, np.int64)
        part = renderer.render(counts, seed=args.seed + 7919 * k, features=(k == 0))
        stats = part if stats is None else stats.merge(part)
    write_exr(args.out, stats)
    write_png_preview(os.path.splitext(args.out)[0] + ".png", stats.mean)
    if not args.quiet:
        print(f"wrote {args.out} ({spp} spp in {len(passes)} passes)")
    return 0


def cmd_metrics(args) -> int:
    from .exr import read_image
    from .metrics import all_metrics
    opts = {} if args.replace_nonfinite is None else {"nonfinite": "replace",
                                                      "replace_value": args.replace_nonfinite}
    img = read_image(args.image, **opts)
    ref = read_image(args.reference, **opts)
    if img.shape != ref.shape:
        raise InputError(f"{args.image} is {img.shape[1]}x{img.shape[0]}x{img.shape[2]} but "
                         f"{args.reference} is {ref.shape[1]}x{ref.shape[0]}x{ref.shape[2]}.")
    print(json.dumps(all_metrics(img, ref), indent=2, default=_json_default))
    return 0


def cmd_info(args) -> int:
    from .exr import exr_info
    print(json.dumps(exr_info(args.file), indent=2, default=_json_default))
    return 0


def cmd_scenes(args) -> int:
    from .renderers import list_scenes
    for name, desc in list_scenes().items():
        print(f"{name:24s} {desc}")
    return 0


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="statmc", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"statmc {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("render", help="render a scene with uniform or mapped per-pixel sample counts")
    r.add_argument("scene", help="built-in scene name (see `statmc scenes`), toy:NAME, or Mitsuba XML path")
    r.add_argument("--spp", type=int, help="samples per pixel (the budget for a real-valued --sample-map)")
    r.add_argument("--out", required=True, help="output directory")
    r.add_argument("--size", help="WIDTHxHEIGHT (default: the scene's own size)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--sample-map", help=".npy or .exr per-pixel counts (whole numbers) or densities")
    r.add_argument("--reference", help="reference EXR: metrics go into report.json")
    r.add_argument("--sampler", choices=["uniform", "gem", "expected-error", "denoising-aware"],
                   default="uniform",
                   help="uniform counts, or adaptive sampling (4 spp, then 8 iterations): GEM "
                        "(Rousselle 2011), minimum expected error of a fixed kernel denoiser "
                        "(Salehi 2022 Lemma A.1; --denoiser gem: GEM kernels of the pilot pass, "
                        "or gaussian), or denoising-aware (Firmino 2023) for --denoiser")
    r.add_argument("--denoiser", choices=["oidn", "gem", "gaussian"], default=None,
                   help="denoiser of --sampler denoising-aware and --reconstruct progressive "
                        "(default oidn), of --sampler expected-error (default gem)")
    r.add_argument("--reconstruct", choices=["none", "gem", "gaussian", "oidn", "progressive",
                                             "oidn+combine"],
                   default="none",
                   help="reconstruction written beside the raw render")
    _add_gem_options(r, "the adaptive --sampler gem always; ")
    r.add_argument("-q", "--quiet", action="store_true")
    r.set_defaults(func=cmd_render)

    rc = sub.add_parser("reconstruct", help="reconstruct an image from a statistics EXR (any renderer)")
    rc.add_argument("input", help="EXR with R,G,B, Variance.* and SampleCount (or --spp)")
    rc.add_argument("--method", choices=["gem"], default="gem")
    rc.add_argument("--out", required=True, help="output EXR (a PNG preview goes beside it)")
    rc.add_argument("--spp", type=int, help="uniform sample count for files without SampleCount")
    _add_gem_options(rc)
    rc.add_argument("-q", "--quiet", action="store_true")
    rc.set_defaults(func=cmd_reconstruct)

    ref = sub.add_parser("reference", help="render a high-spp reference in passes")
    ref.add_argument("scene")
    ref.add_argument("--spp", type=int, required=True)
    ref.add_argument("--out", required=True, help="output EXR path")
    ref.add_argument("--size")
    ref.add_argument("--seed", type=int, default=1_000_003)
    ref.add_argument("--pass-spp", type=int, default=256, help="samples per pixel per pass")
    ref.add_argument("-q", "--quiet", action="store_true")
    ref.set_defaults(func=cmd_reference)

    m = sub.add_parser("metrics", help="error metrics of an image against a reference (JSON)")
    m.add_argument("image")
    m.add_argument("reference")
    m.add_argument("--replace-nonfinite", type=float, metavar="VALUE",
                   help="replace NaN/Inf pixels by VALUE (default: refuse such files)")
    m.set_defaults(func=cmd_metrics)

    i = sub.add_parser("info", help="channels, size, sample counts and NaN/Inf counts of an EXR")
    i.add_argument("file")
    i.set_defaults(func=cmd_info)

    d = sub.add_parser("denoise", help="denoise a statistics EXR (OIDN uses its albedo/normal)")
    d.add_argument("input")
    d.add_argument("--denoiser", choices=["oidn", "gem", "gaussian"], default="oidn")
    d.add_argument("--out", required=True)
    d.add_argument("--spp", type=int, help="uniform sample count for files without SampleCount")
    d.add_argument("--variance", action="store_true",
                   help="also store the output's first-order variance (Firmino 2023) as Variance.*")
    _add_gem_options(d)
    d.add_argument("--sigma", type=float, default=1.0, help="Gaussian standard deviation (pixels)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("-q", "--quiet", action="store_true")
    d.set_defaults(func=cmd_denoise)

    pg = sub.add_parser("progressive", help="progressive denoising (Firmino 2022): the render mixed "
                                            "with a denoiser's output by a Student-t gated α")
    pg.add_argument("input", help="statistics EXR (R,G,B, Variance.*, SampleCount or --spp)")
    pg.add_argument("--denoiser", choices=["oidn", "gem", "gaussian"], default="oidn")
    pg.add_argument("--out", required=True)
    pg.add_argument("--spp", type=int)
    _add_gem_options(pg)
    pg.add_argument("--seed", type=int, default=0, help="seed of MC-SURE's random probes")
    pg.add_argument("-q", "--quiet", action="store_true")
    pg.set_defaults(func=cmd_progressive)

    c = sub.add_parser("combine", help="combine an independent Y and a correlated Z (Back 2020 Eq. 8)")
    c.add_argument("y", help="statistics EXR of the independent render")
    c.add_argument("z", help="correlated image (e.g. its denoised version); with --weights "
                             "statistical it needs Variance.* too (statmc denoise --variance)")
    c.add_argument("--weights", choices=["uniform", "gaussian", "statistical"], default="statistical")
    c.add_argument("--size", type=int, default=15, help="odd window width")
    c.add_argument("--sigma", type=float, default=3.0, help="spatial σ of --weights gaussian")
    c.add_argument("--spp", type=int)
    c.add_argument("--out", required=True)
    c.add_argument("-q", "--quiet", action="store_true")
    c.set_defaults(func=cmd_combine)

    s = sub.add_parser("scenes", help="list built-in scenes")
    s.set_defaults(func=cmd_scenes)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("statmc: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, MemoryError) as e:  # InputError and FileFormatError are ValueErrors
        if args.debug:
            raise
        print(f"statmc {args.command}: error: {e}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
