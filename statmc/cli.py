"""The ``statmc`` command line.

Every command validates its input and exits non-zero with one line naming what is wrong
(``--debug`` shows the traceback).  Outputs are written atomically and never onto an input.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import numbers
import os
import re
import shutil
import sys
import tempfile
import time
import warnings

import numpy as np

from . import __version__
from .errors import FileFormatError, InputError

#: GEM's default error rate γ, as ``statmc.gem.DEFAULT_GAMMA`` (a test checks; the CLI does
#: not import statmc.gem before it needs it).
DEFAULT_GAMMA = 0.2

DESCRIPTION = "statmc: statistics of Monte Carlo rendering (render, reconstruct, denoise, combine)."
EXIT_USAGE = 2
INITIAL_SPP, ITERATIONS = 4, 8  # the adaptive samplers' uniform pilot pass, then passes


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
    """``value`` as a positive int; whole floats such as ``4.0`` are refused like on the
    command line (a sample count is an integer)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise InputError(f"{name} must be a positive integer; got {value!r}.")
    return int(value)


# argparse types: a bad number is refused while parsing, with a message naming what was
# expected (argparse prefixes "argument --NAME: ").
def _int_type(lo: int, what: str):
    def parse(text: str) -> int:
        try:
            v = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}; got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"expected {what}; got {text!r}")
        return v
    parse.__name__ = what  # argparse names the type in some messages
    return parse


POSITIVE_INT = _int_type(1, "a positive integer")
SEED = _int_type(0, "a non-negative integer seed")


def _float_type(what: str, *, positive: bool = False):
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}; got {text!r}") from None
        if not np.isfinite(v) or (positive and v <= 0):
            raise argparse.ArgumentTypeError(f"expected {what}; got {text!r}")
        return v
    parse.__name__ = what
    return parse


FINITE = _float_type("a finite number")
POSITIVE = _float_type("a finite number > 0", positive=True)


def _gamma_type(text: str) -> float:
    from .gem import error_rate_weight
    v = FINITE(text)
    try:
        error_rate_weight(v)  # the range check of GEM's error rate
    except InputError as e:
        raise argparse.ArgumentTypeError(str(e).replace("`gamma`", "GEM's error rate").rstrip(".")) from None
    return v


def _odd_int(text: str) -> int:
    v = _int_type(1, "an odd positive integer")(text)
    if v % 2 == 0:
        raise argparse.ArgumentTypeError(f"expected an odd positive integer (a window width); got {text!r}")
    return v


def _nearest_existing(path: str) -> str:
    d = os.path.abspath(path)
    while not os.path.lexists(d):
        d = os.path.dirname(d)
    return d


def _check_writable_dir(directory: str, out: str) -> None:
    """Refuse ``--out out`` before any work when ``directory`` (created if missing) cannot be."""
    d = _nearest_existing(directory)
    if not os.path.isdir(d):
        raise InputError(f"cannot write --out {out!r}: {d!r} is not a directory.")
    try:
        fd, probe = tempfile.mkstemp(prefix=".statmc-probe-", dir=d)
        os.close(fd)
        os.remove(probe)
    except OSError as e:
        raise InputError(f"cannot write --out {out!r}: cannot create a file in {d!r} "
                         f"({e.strerror}).") from None


def _check_out_file(path: str, inputs=()) -> None:
    """Refuse, before any work, an output EXR path that is not ``*.exr`` (its PNG preview
    would replace it), is a directory, names an input, or cannot be written."""
    from ._atomic import check_not_input
    if os.path.isdir(path):
        raise InputError(f"--out {path!r} is a directory; expected an .exr file path.")
    if not path.lower().endswith(".exr"):
        raise InputError(f"--out must name an .exr file (a .png preview is written beside it); "
                         f"got {path!r}.")
    png = os.path.splitext(path)[0] + ".png"
    if os.path.isdir(png):
        raise InputError(f"the preview {png!r} of --out {path!r} is a directory; choose another --out.")
    check_not_input(path, inputs)
    check_not_input(png, inputs)
    _check_writable_dir(os.path.dirname(os.path.abspath(path)), path)


RENDER_OUTPUTS = ("render.exr", "render.png", "counts.exr", "counts.png", "reconstruction.exr",
                  "reconstruction.png", "scales.exr", "scales.png", "bins.exr", "report.json")


#: Extensions that name a file, not the directory `render --out` writes (a directory of
#: that name that already exists is still taken).
_FILE_EXTENSIONS = (".exr", ".png", ".jpg", ".jpeg", ".hdr", ".tif", ".tiff", ".npy", ".npz",
                    ".json", ".txt", ".pfm")


def _check_scene_arg(scene: str) -> None:
    """Refuse, in the command line's terms (SCENE, not the library's `scene`), a SCENE that
    is neither a built-in scene nor an existing file, a directory, or a file that is not a
    scene (Mitsuba reported an EXR image as an XML parse error, a directory as `scene`)."""
    from .renderers import check_scene, scene_expected
    check_scene(scene, "SCENE")
    if not os.path.exists(scene):                     # a built-in name
        return
    if os.path.isdir(scene):
        raise InputError(f"SCENE {scene!r} is a directory; expected {scene_expected()}.")
    try:
        with open(scene, "rb") as f:
            head = f.read(16)
    except OSError as e:
        raise InputError(f"cannot read SCENE {scene!r}: {e.strerror or e}.") from None
    if not head:
        raise InputError(f"SCENE {scene!r} is an empty file; expected {scene_expected()}.")
    from .exr import format_of
    kind = format_of(head)
    if kind:
        article = "an" if kind[0] in "AEIOU" else "a"
        raise InputError(f"SCENE {scene!r} is {article} {kind} file, not a scene file; "
                         f"expected {scene_expected()}.")


def _check_out_dir(path: str, inputs=()) -> None:
    """Refuse, before rendering, an output directory that is a file, cannot be written, or
    would receive a file onto one of ``inputs``."""
    from ._atomic import check_not_input
    # an input that does not exist is reported missing by its reader, not as an input
    # that an output would overwrite
    inputs = [p for p in inputs if p and os.path.exists(p)]
    if os.path.lexists(path) and not os.path.isdir(path):
        raise InputError(f"--out {path!r} exists and is not a directory; render writes a "
                         f"directory of files ({', '.join(RENDER_OUTPUTS[:3])}, ...).")
    ext = os.path.splitext(os.path.normpath(path))[1]
    said_directory = path.endswith(os.sep) or (os.altsep and path.endswith(os.altsep))
    if not os.path.lexists(path) and ext.lower() in _FILE_EXTENSIONS and not said_directory:
        # `render --out cb16.exr` would make a directory cb16.exr/ holding render.exr;
        # `--out cb16.exr/` says it is a directory
        raise InputError(f"--out {path!r} ends in {ext!r} like a file, but render writes a "
                         f"directory of files ({', '.join(RENDER_OUTPUTS[:3])}, ...); name a "
                         f"directory, e.g. {os.path.splitext(os.path.normpath(path))[0]!r}.")
    for name in RENDER_OUTPUTS:
        check_not_input(os.path.join(path, name), inputs)
        if os.path.isdir(os.path.join(path, name)):
            raise InputError(f"--out {path!r} holds a directory named {name}, which render writes "
                             "as a file; choose another --out.")
    _check_writable_dir(path, path)


def load_sample_map(path: str) -> np.ndarray:
    """A per-pixel sample map ``(H, W)`` from a ``.npy`` file or a one-channel EXR."""
    if not os.path.exists(path):
        raise InputError(f"sample map {path} does not exist.")
    if path.lower().endswith(".npy"):
        try:
            m = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:  # EOFError: an empty file
            if "Object arrays cannot be loaded" in str(e):   # np.save of Python objects
                raise InputError(f"sample map {path} holds Python objects (dtype object, saved "
                                 "with pickle); expected one (H, W) array of numbers saved with "
                                 "numpy.save.") from None
            why = ("not a NumPy .npy array file" if "pickle" in str(e) or isinstance(e, EOFError)
                   else str(e))
            raise InputError(f"cannot read sample map {path}: {why}.") from None
        if not isinstance(m, np.ndarray):  # a .npz archive renamed .npy
            m.close()
            raise InputError(f"sample map {path} is a .npz archive of arrays {sorted(m.files)}; "
                             "expected one (H, W) array saved with numpy.save.")
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
    if m.ndim != 2 or not (np.issubdtype(m.dtype, np.integer) or np.issubdtype(m.dtype, np.floating)):
        raise InputError(f"sample map {path} must be a real-valued (H, W) array of integers or "
                         f"floats; got {m.dtype} {m.shape}.")
    m = m.astype(np.float64)
    bad = ~np.isfinite(m)
    if bad.any():
        raise InputError(f"sample map {path} holds {int(bad.sum())} NaN/Inf values; expected "
                         "finite numbers >= 0 (per-pixel counts or a density).")
    if (m < 0).any():
        raise InputError(f"sample map {path} holds {int((m < 0).sum())} negative values; "
                         "expected finite numbers >= 0 (per-pixel counts or a density).")
    return m


MAX_COUNT = 2**32 - 1  # the largest sample count an EXR SampleCount channel holds (statmc.exr)


def _check_count_range(what: str, largest) -> None:
    if largest > MAX_COUNT:
        raise InputError(f"{what} asks for up to {largest:.4g} samples per pixel; at most "
                         f"{MAX_COUNT} fit the SampleCount channel of the output.")


def counts_for_render(height, width, *, spp=None, sample_map=None, seed=0) -> np.ndarray:
    """The integer count map a render uses: uniform ``spp``, or a sample map.

    A map of whole numbers is used as counts; a real-valued map is a density scaled to
    the budget ``spp × H × W`` (exact total, unbiased rounding).
    """
    from .sampling import counts_from_density
    if sample_map is None:
        if spp is None:
            raise InputError("give --spp (samples per pixel) or --sample-map.")
        spp = _positive_int("--spp", spp)
        _check_count_range("--spp", spp)
        return np.full((height, width), spp, np.int64)
    if sample_map.shape != (height, width):
        raise InputError(f"sample map is {sample_map.shape[1]}x{sample_map.shape[0]} (WxH) but the "
                         f"render is {width}x{height}; pass a matching --size.")
    if np.all(sample_map == np.round(sample_map)) and spp is None:
        if not sample_map.any():
            raise InputError("the sample map holds only zeros; give at least one sample.")
        _check_count_range("the sample map", sample_map.max())
        return sample_map.astype(np.int64)
    if spp is None:
        raise InputError("a real-valued sample map needs --spp to set the budget.")
    return counts_from_density(sample_map, _positive_int("--spp", spp) * height * width, rng=seed)


def _need_variance(stats, path: str, what: str) -> None:
    """Refuse a file with pixels of fewer than the 2 samples a variance estimate needs (a
    1-spp render, or holes of a sample map): ``what`` would silently treat them as
    noise-free (an empty pixel as an exact black)."""
    few = int((stats.n < 2).sum())
    if few:
        which = ("every pixel" if few == stats.n.size
                 else f"{few} of its {stats.n.size} pixels")
        source = stats.meta.get("sample_count_source")
        n = int(stats.n.min())
        count = (f"SampleCount min {n}" if source not in ("header", "spp") else
                 f"{n} sample{'s' if n != 1 else ''} per pixel, "
                 + ("its samplesPerPixel header attribute" if source == "header" else "--spp"))
        raise InputError(f"{what} needs a variance in every pixel, but {which} of {path} "
                         f"{'has' if few == stats.n.size else 'have'} fewer than 2 samples "
                         f"({count}); render at least 2 samples in every pixel.")


def _need_rgb(stats, path: str, what: str, instead: str) -> None:
    """Refuse a one-channel (``Y``) file where OIDN, a colour denoiser, would run on it."""
    if stats.mean.shape[2] != 3:
        raise InputError(f"{path} is a one-channel (Y) image, but {what} runs OIDN, which "
                         f"denoises R, G, B images; {instead}, or write the luminance into "
                         "R, G and B.")


def _write_json(path, obj, protect=()):
    from ._atomic import write_text
    write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n", protect=protect)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


@contextlib.contextmanager
def _staged_outputs(directory, inputs=()):
    """Write a command's files as one set: yield ``stage(path)``, which names a file in a
    hidden staging directory inside ``directory`` (created if missing) to write instead of
    ``path``.  When the block ends without an error every staged file is renamed onto its
    path (keeping the permissions of a file it replaces); on any error or Ctrl-C none is,
    the staging directory (and ``directory`` if this call made it) is removed, so earlier
    outputs stay as they were, never a mix of old and new files."""
    import re

    from ._atomic import check_not_input, missing_directories, remove_made_directories
    made = missing_directories(os.path.abspath(directory))
    try:
        os.makedirs(directory, exist_ok=True)
        tmpdir = tempfile.mkdtemp(prefix=".statmc-", dir=directory)
    except OSError:          # e.g. a name too long after makedirs made its parents
        remove_made_directories(made)
        raise
    staged = {}

    def stage(path):
        tmp = os.path.join(tmpdir, f"{len(staged)}-{os.path.basename(path)}")
        staged[tmp] = os.fspath(path)
        return tmp

    done = False
    try:
        try:
            yield stage
        except (OSError, FileFormatError) as e:   # e.g. a full disk: name the output, not the temp
            target = next(reversed(staged.values()), directory)
            msg = re.sub(r"""['"]?[^'" ]*\.statmc-[^'" ]*['"]?""", repr(target),
                         e.strerror if isinstance(e, OSError) and e.strerror else str(e))
            if target not in msg:
                msg = f"could not write {target!r}: {msg}"
            raise type(e)(f"{msg.rstrip('.')}; nothing was written (earlier outputs are "
                          "unchanged).") from None
        for tmp, path in staged.items():
            check_not_input(path, inputs)
        for tmp, path in staged.items():
            with contextlib.suppress(OSError):
                os.chmod(tmp, os.stat(path).st_mode & 0o7777)
            os.replace(tmp, path)
        done = True
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
        if not done:
            remove_made_directories(made)     # innermost first; only if still empty


def _placement(path, layer=None, part=0) -> dict:
    """What an output keeps of its input ``path`` (its ``part``), read (and checked) before
    the work: its data and display windows (a crop stays where it was), ``chromaticities``
    (an ACEScg render stays ACEScg) and alpha channel ``A`` (``<layer>.A`` with ``layer``;
    None if it has none), as denoisers pass alpha through for a compositor.  An alpha with
    NaN/Inf, which the output would carry, is refused."""
    from .exr import _header_summary, read_channels
    info = _header_summary(path, part)
    keep = {k: info[k] for k in ("data_window", "display_window", "chromaticities")}
    name = "A" if layer is None else f"{layer}.A"
    keep["alpha"] = None
    if name in info["channels"]:
        a = np.asarray(read_channels(path, [name], part=part)[name], np.float32)
        bad = int((~np.isfinite(a)).sum())
        if bad:
            raise InputError(f"{path}: its alpha channel {name} holds {bad} NaN/Inf values, "
                             "which the output would carry over; expected finite values "
                             "(`statmc info FILE` counts them).")
        keep["alpha"] = a
    return keep


def _file_layers(args, first: str, second: str) -> tuple:
    """The layers of a two-file command's files: ``--<first>-layer`` and ``--<second>-layer``
    where given, else ``--layer`` (both files)."""
    return _per_file(args, "layer", first, second, None)


def _file_parts(args, first: str, second: str) -> tuple:
    """The parts of a two-file command's files: ``--<first>-part`` and ``--<second>-part``
    where given, else ``--part`` (both files), else part 0."""
    return _per_file(args, "part", first, second, 0)


def _per_file(args, option: str, first: str, second: str, default) -> tuple:
    both = getattr(args, option)
    both = default if both is None else both
    return tuple(both if getattr(args, f"{which}_{option}") is None
                 else getattr(args, f"{which}_{option}") for which in (first, second))


def _part(args):
    """The part of a one-file command's input: ``--part``, else 0."""
    return 0 if args.part is None else args.part


# The library's hint of a file whose colour is only in a layer ("..., or, in Python, read them
# with statmc.exr.read_exr/read_image(path, layer='X')"); group 1 the quoted layer name.
_LAYER_HINT = re.compile(r", or, in Python, read them with statmc\.exr\.read_exr/read_image\("
                         r"path, layer=('[^']*'|\"[^\"]*\")\)")


@contextlib.contextmanager
def _layer_hint_for(option: str, which: str):
    """Within the block, a file read refused for want of a layer (or of a channel that
    another part holds) names the per-file option of the file it read (``--reference-layer
    'X' for REFERENCE alone``, ``--reference-part``) beside ``--layer`` (``--part``; both
    files), instead of the library's Python hint."""
    try:
        yield
    except FileFormatError as e:
        from .exr import _PART_HINT
        message = _LAYER_HINT.sub(rf", or give {option} \1 for {which} alone, or give --layer \1",
                                  str(e))
        part_option = option.replace("-layer", "-part")
        message = message.replace(_PART_HINT, f"give {part_option} INDEX|NAME for {which} "
                                  "alone, or --part INDEX|NAME, to read another")
        if message == str(e):
            raise
        raise FileFormatError(message) from None


def _write_result(path, data, image, *, inputs, extra=None, quiet=False, place=None) -> None:
    """Write ``data`` (statistics or an image) to ``path`` and a PNG preview of ``image``
    beside it, both or neither, never onto one of ``inputs``.  ``place``: what the output
    keeps of its input (:func:`_placement`): windows, chromaticities and alpha."""
    from .exr import write_exr, write_png_preview
    keep = {}
    if place is not None:
        keep = {k: place[k] for k in ("data_window", "display_window", "chromaticities")}
        if place["alpha"] is not None:
            extra = dict(extra or {}, A=place["alpha"])
    with _staged_outputs(os.path.dirname(os.path.abspath(path)), inputs) as stage:
        write_exr(stage(path), data, protect=inputs, extra=extra, **keep)
        write_png_preview(stage(os.path.splitext(path)[0] + ".png"), image, protect=inputs)
    if not quiet:
        print(f"wrote {path}")


# ---------------------------------------------------------------------------- commands
def _define(text: str) -> tuple[str, str]:
    """``-D NAME=VALUE``: a value for the ``$NAME`` parameter of an XML scene."""
    name, eq, value = text.partition("=")
    if not eq or not name.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE (a value for $NAME in the scene "
                                         f"file, e.g. -D spp=64); got {text!r}")
    return name.strip(), value


def _add_define_option(parser) -> None:
    parser.add_argument("-D", "--define", type=_define, action="append", default=None,
                        metavar="NAME=VALUE",
                        help="value of the parameter $NAME of a Mitsuba XML scene (repeatable), "
                             "as `mitsuba -D`")
    parser.add_argument("--sensor", type=_int_type(0, "a sensor index >= 0"), default=None,
                        metavar="INDEX", help="render sensor INDEX of a Mitsuba scene, "
                                              "counted from 0 in the file's order (default 0)")


def _scene_options(args) -> dict:
    """Keyword options of ``make_renderer`` from ``-D`` and ``--sensor`` (none when not
    given)."""
    from .renderers import TOY_PREFIX
    from .scenes import BUILTIN_SCENES
    opts = {}
    if args.define:
        if args.scene.startswith(TOY_PREFIX) or args.scene in BUILTIN_SCENES:
            raise InputError(f"-D sets $NAME parameters of a Mitsuba XML scene file; "
                             f"{args.scene} is a built-in scene: leave -D out.")
        opts["params"] = dict(args.define)
    if args.sensor is not None:
        if args.scene.startswith(TOY_PREFIX):
            raise InputError(f"--sensor picks a camera of a Mitsuba scene; {args.scene} has "
                             "none: leave --sensor out.")
        opts["sensor"] = args.sensor
    return opts


def cmd_render(args) -> int:
    from .exr import read_image, write_exr, write_png_preview
    from .metrics import all_metrics
    from .pipeline import (BIN_RECONSTRUCTIONS, DENOISER_SAMPLERS, merge_bins, reconstruct_bins,
                           reconstruct_stats, render_bins, render_with_sampler)
    from .plots import write_map_png
    from .renderers import make_renderer

    _check_scene_arg(args.scene)
    width, height = _parse_size(args.size)
    inputs = [p for p in (args.sample_map, args.reference) if p]
    _check_out_dir(args.out, inputs)
    sample_map = load_sample_map(args.sample_map) if args.sample_map else None
    if sample_map is not None and width is None:
        height, width = sample_map.shape
    if sample_map is not None and args.sampler != "uniform":
        raise InputError(f"--sample-map fixes the counts; it cannot be combined with --sampler {args.sampler}.")
    ref = read_image(args.reference) if args.reference else None
    renderer = make_renderer(args.scene, width=width, height=height, **_scene_options(args))
    if args.spp is None and sample_map is None and os.path.isfile(args.scene):
        raise InputError(f"give --spp (samples per pixel) or --sample-map; the sample_count "
                         f"({getattr(renderer, 'scene_sample_count', '?')}) of {args.scene}'s "
                         "sampler is not used: statmc draws the counts it is given.")
    if args.spp is not None:
        _check_count_range("--spp", args.spp)
    counts = None
    if args.sampler == "uniform":
        counts = counts_for_render(renderer.height, renderer.width, spp=args.spp,
                                   sample_map=sample_map, seed=args.seed)
    if (counts is not None and args.reconstruct in ("gem", "progressive", "oidn+combine")
            and counts.min() < 2):
        raise InputError(f"--reconstruct {args.reconstruct} needs at least 2 samples in every pixel "
                         f"(a variance needs two); the counts have {int((counts < 2).sum())} "
                         "pixels with fewer (raise --spp or the sample map's minimum).")
    if args.stencil is not None and not args.crn:
        raise InputError("--stencil is the width of --crn's covariance stencil; it needs --crn.")
    if (args.denoiser is not None and args.reconstruct != "progressive"
            and args.sampler not in DENOISER_SAMPLERS):
        raise InputError(f"--denoiser chooses the denoiser of --sampler denoising-aware / "
                         f"expected-error and of --reconstruct progressive; it has no effect on "
                         f"--sampler {args.sampler} with --reconstruct {args.reconstruct}.")
    _render_gem_defaults(args)
    binned = args.reconstruct in BIN_RECONSTRUCTIONS
    if args.bins is not None and not binned:
        raise InputError(f"--bins is the number of sample bins of --reconstruct "
                         f"{' / '.join(BIN_RECONSTRUCTIONS)}; it needs one of them.")
    if binned:
        args.bins = args.bins or 4
        if args.sampler != "uniform" or sample_map is not None:
            raise InputError(f"--reconstruct {args.reconstruct} splits a uniform render into "
                             "equal bins; it cannot be combined with an adaptive --sampler or "
                             "a --sample-map.")
        if args.bins < 2:
            raise InputError(f"--bins must be at least 2; got {args.bins}.")
        if args.spp is None or args.spp % args.bins or args.spp < 2 * args.bins:
            raise InputError(f"--reconstruct {args.reconstruct} needs --spp to be a multiple of "
                             f"--bins {args.bins} with at least 2 samples per bin; got --spp "
                             f"{args.spp}.")
    if args.crn:
        args.stencil = args.stencil or 15
        if args.sampler != "uniform" or sample_map is not None:
            raise InputError("--crn renders the same --spp in every pixel; it cannot be combined "
                             "with an adaptive --sampler or a --sample-map.")
        if args.spp is None or args.spp < 2:
            raise InputError(f"--crn needs --spp >= 2 (the covariance stencil needs two samples); "
                             f"got {args.spp}.")
        if not hasattr(renderer, "render_crn"):
            raise InputError(f"--crn needs a Mitsuba scene; {args.scene} is rendered by "
                             f"{type(renderer).__name__}, which has no common random numbers.")
        if args.reconstruct != "none":
            raise InputError(f"--crn cannot be combined with --reconstruct {args.reconstruct}: the "
                             "reconstructions assume independent pixel errors, and most of a "
                             "common-random-number render's correlated noise survives them; "
                             "render without --crn to reconstruct, or use the --crn render as "
                             "Z in `statmc combine`.")
    if args.sampler != "uniform" and (args.spp is None or args.spp <= INITIAL_SPP):
        raise InputError(f"--sampler {args.sampler} needs an --spp budget above {INITIAL_SPP} "
                         f"(a {INITIAL_SPP}-spp pilot pass, then {ITERATIONS} adaptive passes "
                         f"share the rest; at {INITIAL_SPP} spp the pilot would be the whole, "
                         f"uniform, render); got {args.spp}.")
    if ref is not None and ref.shape != (renderer.height, renderer.width, 3):
        raise InputError(f"reference {args.reference} is {ref.shape[1]}x{ref.shape[0]} with "
                         f"{ref.shape[2]} channel(s) but the render is {renderer.width}x"
                         f"{renderer.height} R,G,B.")
    if ref is not None:
        from .exr import _describe_colour_space, _header_summary, _same_colour_space
        ref_header = _header_summary(args.reference)
        ref_window = ref_header["data_window"]
        if ref_window[:2] != [0, 0]:
            raise InputError(f"reference {args.reference} has the data window {ref_window} "
                             f"([x0, y0, x1, y1]) but the render lies at the origin, [0, 0, "
                             f"{renderer.width - 1}, {renderer.height - 1}]: pixel by pixel "
                             "they would pair different pixels; expected a reference whose "
                             "data window starts at 0, 0 (`statmc info` shows it).")
        if not _same_colour_space(ref_header["chromaticities"], None):
            raise InputError(f"reference {args.reference} has "
                             f"{_describe_colour_space(ref_header['chromaticities'])} but "
                             "statmc renders linear Rec. 709/sRGB (no chromaticities): pixel "
                             "by pixel they would pair different colours; expected a Rec. "
                             "709/sRGB reference (convert it first).")
    t0 = time.perf_counter()
    extra = {}
    bins = None
    if args.crn:
        from .exr import spatial_covariance_channels

        stats, cov = renderer.render_crn(args.spp, seed=args.seed, stencil=args.stencil,
                                         progress=not args.quiet)
        extra = spatial_covariance_channels(cov, stats.n)
        del cov
    elif binned:
        bins = render_bins(renderer, args.spp, args.bins, seed=args.seed,
                           progress=not args.quiet)
        stats = merge_bins(bins)
    else:
        stats = render_with_sampler(renderer, args.spp, sampler=args.sampler, counts=counts,
                                    seed=args.seed, progress=not args.quiet, gamma=args.gamma,
                                    # --denoiser may be the reconstruction's alone
                                    denoiser=args.denoiser
                                    if args.sampler in DENOISER_SAMPLERS else None,
                                    gem_bias=args.gem_bias,
                                    initial_spp=INITIAL_SPP, iterations=ITERATIONS)
    seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    bin_data = None
    if binned:
        from .exr import bin_channels

        image, maps, (ys, zs) = reconstruct_bins(bins, args.reconstruct, gamma=args.gamma,
                                                 seed=args.seed, gem_bias=args.gem_bias,
                                                 return_bins=True)
        bin_data = bin_channels(ys, zs)
        del bins, ys, zs
    else:
        image, maps = reconstruct_stats(stats, args.reconstruct, gamma=args.gamma,
                                        denoiser=args.denoiser or "oidn", seed=args.seed,
                                        gem_bias=args.gem_bias)
    seconds_rec = time.perf_counter() - t0
    # Everything is computed before the first file is written: a failure writes nothing.
    n = stats.n
    total = int(n.sum())
    report = {
        "scene": args.scene, "scene_params": dict(args.define or ()),
        "renderer": type(renderer).__name__,
        "width": renderer.width, "height": renderer.height, "seed": args.seed,
        # a --sample-map render is not uniform: name the map and how it was read
        "sampler": "sample-map" if sample_map is not None else args.sampler,
        "sample_map": None if sample_map is None else {
            "path": args.sample_map, "used_as": "counts" if args.spp is None else "density"},
        "reconstruct": args.reconstruct, "gamma": args.gamma,
        "gem_bias": args.gem_bias, "crn": bool(args.crn), "bins": args.bins,
        "stencil": args.stencil if args.crn else None,
        "spp": total / n.size, "total_samples": total,
        "spp_min": int(n.min()), "spp_max": int(n.max()),
        "seconds": seconds, "samples_per_second": total / max(seconds, 1e-12),
        "seconds_reconstruct": seconds_rec,
        "renderer_info": {k: v for k, v in stats.meta.items() if np.isscalar(v) or isinstance(v, str)},
    }
    if hasattr(renderer, "nonfinite_samples"):  # the renderer's count of all its passes
        report["renderer_info"]["nonfinite_samples"] = renderer.nonfinite_samples
    if ref is not None:
        report["reference"] = args.reference
        report["metrics"] = all_metrics(stats.mean.astype(np.float32), ref)
        if args.reconstruct != "none":
            report["metrics_reconstruction"] = all_metrics(image, ref)
    written = [f for f in RENDER_OUTPUTS if f.startswith(("render.", "counts.", "report."))
               or (f.startswith("reconstruction.") and args.reconstruct != "none")
               or (f.startswith("scales.") and "scale" in maps)
               or (f == "bins.exr" and bin_data is not None)]
    report["files"] = written
    stale = [f for f in RENDER_OUTPUTS if f not in written and os.path.exists(os.path.join(args.out, f))]
    with _staged_outputs(args.out, inputs) as stage:  # all files, or none on a failure
        out = lambda name: stage(os.path.join(args.out, name))  # noqa: E731
        write_exr(out("render.exr"), stats, protect=inputs, extra=extra)
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
            if bin_data is not None:
                write_exr(out("bins.exr"), stats.mean.astype(np.float32), protect=inputs,
                          extra=bin_data)
        _write_json(out("report.json"), report, protect=inputs)
    if not args.quiet:
        msg = f"wrote {args.out}/ ({total} samples, {seconds:.2f} s"
        msg += f", {report['samples_per_second'] / 1e6:.2f} M samples/s)"
        if ref is not None:
            msg += f"; relMSE raw {report['metrics']['relmse']:.4g}"
            if args.reconstruct != "none":
                msg += f", {args.reconstruct} {report['metrics_reconstruction']['relmse']:.4g}"
        print(msg)
    if stale:
        print(f"statmc render: note: {', '.join(stale)} in {args.out} are from an earlier render "
              "(this one did not write them).", file=sys.stderr)
    return 0


_ASSUMES_INDEPENDENT = ("assumes independent pixel errors and leaves most of its noise; use "
                        "it as Z in `statmc combine`")


def _is_crn(stats) -> bool:
    """Whether a file read by ``read_exr`` is a common-random-number render: it has the
    ``SpatialCovariance.*`` channels of ``statmc render --crn``."""
    from .exr import SPATIAL_COVARIANCE
    return any(c.startswith(SPATIAL_COVARIANCE + ".") for c in stats.meta.get("extra_channels", ()))


def _refuse_crn(stats, path, what: str) -> None:
    """Refuse a common-random-number render where independent pixel errors are assumed
    (Back 2020 §3.1)."""
    if _is_crn(stats):
        raise InputError(f"{path} is a common-random-number render (it has SpatialCovariance.* "
                         f"channels): its pixel errors are correlated, but {what}.")


def cmd_reconstruct(args) -> int:
    from .exr import _reading_once, read_exr
    from .pipeline import reconstruct_stats
    _check_out_file(args.out, [args.input])
    # no method reads the channel covariance (m2_cross): not built (1080p: 0.3-0.5 s, 143 MiB)
    with _reading_once(args.input):            # an alpha channel: from the same decoding
        stats = read_exr(args.input, spp=args.spp, layer=args.layer, part=_part(args),
                         covariance=False, **_features(args, args.method == "oidn+combine",
                                                       f"on --method {args.method}"))
        place = _placement(args.input, args.layer, _part(args))
    _refuse_crn(stats, args.input, f"statmc reconstruct {_ASSUMES_INDEPENDENT}")
    if args.method != "gem":
        _refuse_unused(args, ["gamma", "gem_bias"], f"on --method {args.method} (they are "
                       "options of --method gem's scale selection)")
        _need_variance(stats, args.input, f"--method {args.method}")
        _need_rgb(stats, args.input, f"--method {args.method}", "use --method gem")
    else:
        _refuse_pooled_gamma(args, "on --method gem")
    _fill_gem_defaults(args)
    image, maps = reconstruct_stats(stats, args.method, gamma=args.gamma, gem_bias=args.gem_bias)
    _write_result(args.out, image, image, inputs=[args.input], quiet=args.quiet,
                  extra={f"{args.method}.{k}": v for k, v in maps.items()},
                  place=place)
    return 0


def _add_gem_options(parser, gem_use: str, always: str = "", *, refuse_unused=False) -> None:
    """``--gamma`` and ``--gem-bias``: the GEM selector's error rate and bias estimate.
    ``gem_use`` names the command's GEM final selections, ``always`` what uses γ in any
    case (with a trailing ", and ").  ``refuse_unused``: default None, so that the command
    can refuse them when it has no GEM (it then fills in the defaults, :func:`_gem_defaults`)."""
    parser.add_argument("--gamma", type=_gamma_type,
                        default=None if refuse_unused else DEFAULT_GAMMA,
                        help=f"GEM error-rate parameter γ in (0, 0.526), default 0.2 (Rousselle "
                             f"2011 §4.3): used {always}by {gem_use} only with --gem-bias paper; "
                             "refused where nothing reads it")
    parser.add_argument("--gem-bias", choices=["pooled", "paper"],
                        default=None if refuse_unused else "pooled",
                        help=f"bias estimate of the scale selection of {gem_use}: pooled "
                             "(default, docs/gem.md §5d) or the paper's per-pixel Eq. 1")


def _make_denoiser(name, stats, *, gamma=0.2, sigma=1.0, gem_bias=None):
    """A denoiser bound to ``stats``' features (OIDN) or variance (GEM)."""
    from .pipeline import _denoiser_options
    from .progressive import bind_denoiser
    return bind_denoiser(name, stats, **_denoiser_options(name, gamma, sigma, gem_bias))


def _refuse_unused(args, names, why: str) -> None:
    """Refuse options the user gave that this command would ignore (their argparse
    default is None, so only given values are not None)."""
    given = ["--" + n.replace("_", "-") for n in names if getattr(args, n, None) is not None]
    if given:
        raise InputError(f"{' and '.join(given)} {'has' if len(given) == 1 else 'have'} no "
                         f"effect {why}.")


def _features(args, oidn: bool, where: str) -> dict:
    """``read_exr``'s ``albedo=`` and ``normal=`` of a command's input: ``--albedo-layer``
    and ``--normal-layer`` (None: statmc's own channels, else the layers recognised) where
    OIDN runs; elsewhere statmc's own channels only (False), and the options are refused."""
    if not oidn:
        _refuse_unused(args, ["albedo_layer", "normal_layer"], f"{where} (they name the layers "
                       "of OIDN's albedo and normal, and no OIDN runs)")
        return {"albedo": False, "normal": False}
    return {"albedo": args.albedo_layer, "normal": args.normal_layer}


_GAMMA_READ = ("it is read only with --gem-bias paper (Rousselle 2011 Eq. 1) or by `statmc render "
               "--sampler gem|expected-error`")


def _refuse_pooled_gamma(args, where: str) -> None:
    """Refuse --gamma where the only reader is a GEM final selection with the pooled bias
    estimate, which does not use the error rate (docs/gem.md §5d): the output would be
    byte-identical without it."""
    if args.gamma is not None and args.gem_bias in (None, "pooled"):
        bias = "--gem-bias pooled" if args.gem_bias else "--gem-bias pooled (the default)"
        raise InputError(f"--gamma has no effect {where} under {bias}: the pooled bias estimate "
                         f"does not use GEM's error rate; {_GAMMA_READ}.")


def _fill_gem_defaults(args) -> None:
    """--gamma / --gem-bias not given (None, with ``refuse_unused``) take their defaults."""
    args.gamma = DEFAULT_GAMMA if args.gamma is None else args.gamma
    args.gem_bias = "pooled" if args.gem_bias is None else args.gem_bias


def _gem_defaults(args) -> None:
    """Refuse --gamma / --gem-bias given with another --denoiser than gem, then fill in
    their defaults (``denoise`` and ``progressive``)."""
    if args.denoiser != "gem":
        _refuse_unused(args, ["gamma", "gem_bias"], f"on --denoiser {args.denoiser} (they "
                       "are options of --denoiser gem's scale selection)")
    _refuse_pooled_gamma(args, "on --denoiser gem")
    _fill_gem_defaults(args)


def _render_gem_defaults(args) -> None:
    """Refuse render's --gamma / --gem-bias when no part of the render reads them, then fill
    in their defaults.  γ drives the adaptive --sampler gem, the GEM pilot kernels of
    --sampler expected-error, and the GEM final selections (--reconstruct gem / gem+bins,
    a --denoiser gem of --sampler denoising-aware or --reconstruct progressive) with
    --gem-bias paper only; the bias estimate only the final selections."""
    gem_denoiser = args.denoiser == "gem" and (args.sampler == "denoising-aware"
                                               or args.reconstruct == "progressive")
    final = args.reconstruct in ("gem", "gem+bins") or gem_denoiser
    sampler_gamma = args.sampler == "gem" or (args.sampler == "expected-error"
                                              and args.denoiser in (None, "gem"))
    uses_gamma = final or sampler_gamma
    where = f"on --sampler {args.sampler} with --reconstruct {args.reconstruct}" + (
        f" and --denoiser {args.denoiser}" if args.denoiser else "")
    gem_den_where = "--sampler denoising-aware or --reconstruct progressive"
    if not uses_gamma:
        _refuse_unused(args, ["gamma", "gem_bias"], f"{where} (--gamma and --gem-bias are "
                       "read by GEM only: --sampler gem or expected-error, --reconstruct gem or "
                       f"gem+bins, --denoiser gem with {gem_den_where})")
    elif not final:
        _refuse_unused(args, ["gem_bias"], f"{where} (--gem-bias is read by GEM's final "
                       f"selection only: --reconstruct gem or gem+bins, --denoiser gem with "
                       f"{gem_den_where}; --sampler {args.sampler} reads --gamma only)")
    elif not sampler_gamma:
        _refuse_pooled_gamma(args, where)
    _fill_gem_defaults(args)


def _read_statistics(path, spp, why: str, layer=None, *, part=0, covariance: bool = False,
                     albedo=False, normal=False):
    """``read_exr(path, spp=spp)``; a file without ``Variance.*`` or ``SampleCount`` is
    refused with ``why`` (what reads them, what would take a plain image) appended.
    ``covariance``: build the channel covariance ``m2_cross`` (only denoise --variance
    with OIDN reads it).  ``albedo``, ``normal``: as ``read_exr``'s (statmc's own channels
    only unless given)."""
    from .exr import read_exr
    try:
        return read_exr(path, spp=spp, layer=layer, part=part, covariance=covariance,
                        albedo=albedo, normal=normal)
    except FileFormatError as e:
        if not any(f"has no {c}" in str(e) for c in ("Variance.", "SampleCount")):
            raise
        raise FileFormatError(f"{str(e).rstrip('.')}. {why}") from None


def _read_colour(path, layer=None, part=0, *, albedo=False, normal=False):
    """A file read for its colour and features only, as statistics (its channels listed in
    ``meta``): a plain RGB image needs neither ``Variance.*`` nor ``SampleCount`` (``n = 1``
    where it has none), and its channel covariance is not built."""
    from .exr import read_exr
    return read_exr(path, spp=1, spp_if_missing=True, require_variance=False, layer=layer,
                    part=part, covariance=False, albedo=albedo, normal=normal)


def cmd_denoise(args) -> int:
    from .exr import _reading_once
    from .stats import PixelStats
    _check_out_file(args.out, [args.input])
    features = _features(args, args.denoiser == "oidn", f"with --denoiser {args.denoiser}")
    with _reading_once(args.input):            # an alpha channel: from the same decoding
        if args.variance or args.denoiser == "gem":
            what = "--variance" if args.variance else "--denoiser gem"
            stats = _read_statistics(args.input, args.spp, f"{what} reads the file's "
                                     "statistics; --denoiser oidn or gaussian without --variance "
                                     "denoises a plain image.", layer=args.layer,
                                     part=_part(args), **features,
                                     covariance=bool(args.variance and args.denoiser == "oidn"))
        else:
            _refuse_unused(args, ["spp"], f"on --denoiser {args.denoiser} without --variance (it "
                           "is the sample count of a file without SampleCount, which only "
                           "--variance and --denoiser gem read)")
            # plain denoising reads the colour and OIDN's features (albedo, normal) only
            stats = _read_colour(args.input, args.layer, _part(args), **features)
        place = _placement(args.input, args.layer, _part(args))
    if not np.any(stats.n > 0):
        raise InputError(f"{args.input!r} holds no samples (its sample count is 0 in every "
                         "pixel); expected a render with samples.")
    _refuse_crn(stats, args.input, f"statmc denoise {_ASSUMES_INDEPENDENT}")
    _gem_defaults(args)
    if args.denoiser != "gaussian":
        _refuse_unused(args, ["sigma"], f"on --denoiser {args.denoiser} (it is the width of "
                       "--denoiser gaussian)")
    if not (args.variance and args.denoiser == "oidn"):
        _refuse_unused(args, ["seed"], "without --variance and --denoiser oidn (it seeds the "
                       "random probes of OIDN's variance; the other variances are exact)")
    args.sigma = 1.0 if args.sigma is None else args.sigma
    args.seed = 0 if args.seed is None else args.seed
    if args.variance or args.denoiser == "gem":
        _need_variance(stats, args.input, "--variance" if args.variance else "--denoiser gem")
    if args.denoiser == "oidn":
        _need_rgb(stats, args.input, "--denoiser oidn", "use --denoiser gem or gaussian")
    den = _make_denoiser(args.denoiser, stats, gamma=args.gamma, sigma=args.sigma,
                         gem_bias=args.gem_bias)
    x = stats.mean.astype(np.float32)
    out = np.asarray(den(x), np.float32)
    result = out
    if args.variance:
        # Store the denoised output as statistics whose variance of the mean is the
        # first-order variance of the output (Firmino 2023), with the input's counts.
        from .denoisers import GEMDenoiser
        from .sure import output_variance
        if hasattr(den, "kernels"):  # linear filters: exactly Σ_j w_ij² σ_j²
            var = output_variance(den, x, stats.mean_var.astype(np.float32), method="exact")
        elif isinstance(den, GEMDenoiser):  # the selected filter's, given the selection
            var, _ = den.output_variance(x)
        else:  # first order; the channel covariance when the file has it (OIDN mixes channels)
            cov = stats.mean_cov if stats.has_cov else stats.mean_var
            var = output_variance(den, x, cov.astype(np.float32), method="fd", rng=args.seed)
        n = stats.n.astype(np.float64)[..., None]
        result = PixelStats(stats.n, out, np.maximum(var, 0) * n * np.maximum(n - 1, 0),
                            albedo=stats.albedo, normal=stats.normal, depth=stats.depth)
    _write_result(args.out, result, out, inputs=[args.input], quiet=args.quiet,
                  place=place)
    return 0


def cmd_progressive(args) -> int:
    from .exr import _reading_once, read_exr
    from .pipeline import reconstruct_stats
    _check_out_file(args.out, [args.input])
    with _reading_once(args.input):            # an alpha channel: from the same decoding
        stats = read_exr(args.input, spp=args.spp, layer=args.layer, part=_part(args),
                         covariance=False, **_features(args, args.denoiser == "oidn",
                                                       f"with --denoiser {args.denoiser}"))
        place = _placement(args.input, args.layer, _part(args))
    _refuse_crn(stats, args.input, f"statmc progressive {_ASSUMES_INDEPENDENT}")
    _gem_defaults(args)
    _need_variance(stats, args.input, "progressive denoising")
    if args.denoiser == "oidn":
        _need_rgb(stats, args.input, "--denoiser oidn (the default)",
                  "use --denoiser gem or gaussian")
    image, maps = reconstruct_stats(stats, "progressive", denoiser=args.denoiser, gamma=args.gamma,
                                    seed=args.seed, gem_bias=args.gem_bias)
    _write_result(args.out, image, image, inputs=[args.input], quiet=args.quiet,
                  extra={f"progressive.{k}": v for k, v in maps.items()},
                  place=place)
    return 0


DEFAULT_COMBINE_SIZE = 15  # combine's window width when --size is not given


def _window_size(args, h: int, w: int, path: str) -> int:
    """combine's window width for an ``h × w`` image: the default 15 when --size is not
    given (on any image: on a small one its outside taps get no weight), else the --size
    given, refused when wider than the image can use.

    A tap more than ``max(h, w) − 1`` pixels from the centre is outside the image for every
    pixel and gets no weight, so ``2·max(h, w) − 1`` is the largest useful width; a wider
    --size only costs memory (the weights are ``H·W·size²`` floats: --size 99999 asked for
    hundreds of TiB).  The default is not narrowed to it: ``gaussian_weights`` normalise
    over the whole window, so a narrower one changes the output in the last bit.  For the
    same reason a --size up to the default is always taken (``--size 15`` typed out does
    what leaving it out does)."""
    if args.size is None:
        return DEFAULT_COMBINE_SIZE
    largest = 2 * max(h, w) - 1
    if args.size > max(largest, DEFAULT_COMBINE_SIZE):
        raise InputError(f"--size {args.size} is wider than a {w}x{h} image can use ({path}): "
                         f"taps more than {max(h, w) - 1} pixels from the centre are outside "
                         f"the image for every pixel and get no weight; the largest useful "
                         f"--size is {largest}.")
    return args.size


def _combine_bins_file(args) -> int:
    """`statmc combine BINS.exr`: Eq. 14 on the file's bins and their denoised images."""
    from . import combine as cb
    from .exr import _reading_once, read_bins

    _check_out_file(args.out, [args.y])
    given = [f"--{o}" for o in ("layer", "y-layer", "z-layer", "part", "y-part", "z-part")
             if getattr(args, o.replace("-", "_")) is not None]
    if given:
        what = "a layer" if given[0].endswith("layer") else "a part"
        whose = {"--y": "Y", "--z": "Z"}.get(given[0][:3], "Y and Z")
        raise InputError(f"{given[0]} selects {what} of {whose}; a sample-bins file ({args.y}, "
                         f"without Z) is statmc's own single-part, unlayered file: leave "
                         f"{given[0]} out.")
    with _reading_once(args.y):                # an alpha channel: from the same decoding
        bins = read_bins(args.y)
        place = _placement(args.y)
    if bins is None or bins[1] is None:
        what = "no sample bins" if bins is None else "bins but no Bin<b>.Denoised.* channels"
        raise InputError(f"{args.y} has {what}; give the correlated image as Z, or pass the "
                         "bins.exr of `statmc render --reconstruct gem+bins|oidn+bins`.")
    if args.spp is not None:
        raise InputError(f"--spp is the sample count of a Y file without SampleCount; {args.y} "
                         "holds sample bins, which the combination uses without counts: leave "
                         "--spp out.")
    ys, zs = bins
    B, h, w, _ = ys.shape
    args.size = _window_size(args, h, w, args.y)
    if B < 2:
        raise InputError(f"{args.y} holds {B} sample bin; Eq. 14 needs at least 2.")
    if args.weights == "statistical":
        out = cb.combine_bin_images(ys, zs, size=args.size)
    else:
        weights = (cb.uniform_weights(h, w, B, args.size) if args.weights == "uniform"
                   else cb.gaussian_weights(h, w, B, args.size, args.sigma))
        out = cb.combine_multi(ys, zs, weights)
    _write_result(args.out, out, out, inputs=[args.y], quiet=args.quiet,
                  place=place)
    return 0


def _has_bins(stats) -> bool:
    """Whether a file read by ``read_exr`` holds sample bins (``Bin<b>.R/G/B`` channels)."""
    from .exr import _BIN_CHANNEL
    return any(_BIN_CHANNEL.match(c) for c in stats.meta.get("extra_channels", ()))


def _refuse_bins_as_y(path) -> None:
    """Refuse a sample-bins file as combine's Y beside a Z (it is combined alone)."""
    from .exr import read_bins
    if read_bins(path) is not None:
        raise InputError(f"{path} is a sample-bins file (Bin<b>.* channels); combine it "
                         "alone, without Z: `statmc combine BINS.exr --out OUT.exr`.")


def cmd_combine(args) -> int:
    from . import combine as cb
    from .exr import _reading_once, read_image
    if args.weights != "gaussian":
        _refuse_unused(args, ["sigma"], f"with --weights {args.weights} (it is the width of "
                       "--weights gaussian)")
    args.sigma = 3.0 if args.sigma is None else args.sigma
    if args.z is None:
        return _combine_bins_file(args)
    _check_out_file(args.out, [args.y, args.z])
    from ._atomic import same_file
    # a missing file is reported by the read ("does not exist"), not as the same file
    if os.path.exists(args.y) and os.path.exists(args.z) and same_file(args.y, args.z):
        raise InputError(f"Y and Z are the same file ({args.y!r} and {args.z!r}); combine an "
                         "independent render Y with a correlated image Z of the same scene, "
                         "e.g. a `statmc render --crn` render.")
    statistical = args.weights == "statistical"
    y_layer, z_layer = _file_layers(args, "y", "z")
    y_part, z_part = _file_parts(args, "y", "z")
    if not statistical:
        _refuse_unused(args, ["spp"], f"with --weights {args.weights} (it is the sample count "
                       "of a Y without SampleCount, which only --weights statistical reads)")
    # Y's alpha (and a bins file's channels) from the same decoding as its colour
    with _reading_once(args.y):
        try:
            with _layer_hint_for("--y-layer", "Y"):
                if statistical:
                    y_stats = _read_statistics(args.y, args.spp, "--weights statistical reads "
                                               "Y's statistics; --weights uniform or gaussian "
                                               "combine a plain image.", layer=y_layer,
                                               part=y_part)
                else:
                    # Fixed weights read Y's colour only.  Read as statistics all the same, so
                    # that a --crn render (SpatialCovariance.*) or a bins file is still
                    # recognised by its channels.
                    y_stats = _read_colour(args.y, y_layer, y_part)
        except FileFormatError:
            _refuse_bins_as_y(args.y)
            raise
        if _has_bins(y_stats):
            _refuse_bins_as_y(args.y)
        place = _placement(args.y, y_layer, y_part)
    _refuse_crn(y_stats, args.y, "Y must be an independent render (Back 2020 §3.1, Eq. 11); "
                "pass the --crn render as Z")
    y = y_stats.mean.astype(np.float32)
    h, w, _ = y.shape
    size_given = args.size is not None
    args.size = _window_size(args, h, w, args.y)
    if statistical:
        from .exr import _read_exr_and_stencil
        try:
            # --spp (for a Y without SampleCount) applies to Z only if Z has none either;
            # a --crn Z's stencil comes from the same read of the file (below)
            with _layer_hint_for("--z-layer", "Z"):
                z_stats, z_stencil = _read_exr_and_stencil(
                    args.z, spp=args.spp, spp_if_missing=True, layer=z_layer, part=z_part,
                    covariance=False, albedo=False, normal=False)
        except FileFormatError as e:
            if "Variance" not in str(e):
                raise
            raise FileFormatError(f"{e} --weights statistical needs Z's variance: write Z with "
                                  "`statmc denoise --variance`, or use --weights uniform or "
                                  "gaussian.") from None
        z = z_stats.mean.astype(np.float32)
        for st, path in ((y_stats, args.y), (z_stats, args.z)):
            _need_variance(st, path, "--weights statistical")
    else:
        with _layer_hint_for("--z-layer", "Z"):
            z = read_image(args.z, layer=z_layer, part=z_part)
    if z.shape != y.shape:
        raise InputError(f"{args.z} is {z.shape[1]}x{z.shape[0]}x{z.shape[2]} but {args.y} is "
                         f"{w}x{h}x{y.shape[2]}; Y and Z must have the same size.")
    _same_frame(args.y, args.z, "Y", "Z", (y_part, z_part))
    if args.weights == "uniform":
        weights = cb.uniform_weights(h, w, 1, args.size)
    elif args.weights == "gaussian":
        weights = cb.gaussian_weights(h, w, 1, args.size, args.sigma)
    else:
        cov_z = z_stats.mean_var.astype(np.float32)
        if _is_crn(z_stats):                       # a CRN render's stencil
            cov_z = z_stencil()
        z_stencil = None                           # Z's channels freed
        if cov_z.ndim == 5 and not size_given:
            # the default window, no wider than the stencil (render --crn --stencil 5 at 1080p)
            args.size = min(args.size, cov_z.shape[2])
        if cov_z.ndim == 5 and cov_z.shape[2] < args.size:
            got = f"{args.size}" if size_given else f"the default {args.size}"
            raise InputError(f"{args.z} holds a {cov_z.shape[2]}x{cov_z.shape[2]} covariance "
                             f"stencil; --size must be at most {cov_z.shape[2]} (got {got}).")
        weights = cb.statistical_weights(y, z, y_stats.mean_var.astype(np.float32), cov_z,
                                         args.size)
    out = cb.combine(y, z, weights)
    _write_result(args.out, out, out, inputs=[args.y, args.z], quiet=args.quiet,
                  place=place)
    return 0


def _same_frame(a, b, name_a: str, name_b: str, parts=(0, 0)) -> None:
    """Refuse two files of one size that are not the same pixels in the same colours: data
    windows in different places (say a crop and the full frame's corner) would pair
    different pixels, different ``chromaticities`` (an ACEScg render and a Rec. 709
    reference) different colours."""
    from .exr import _describe_colour_space, _header_summary, _same_colour_space
    ha, hb = _header_summary(a, parts[0]), _header_summary(b, parts[1])
    wa, wb = ha["data_window"], hb["data_window"]
    if wa != wb:
        raise InputError(f"{name_a} {a} has the data window {wa} but {name_b} {b} has {wb} "
                         "([x0, y0, x1, y1]): the same size in different places, so pixel by "
                         "pixel they pair different pixels; expected the same data window "
                         "(`statmc info` shows it; statmc outputs keep their input's, and "
                         "statmc.exr.write_exr(..., data_window=) places an image).")
    ca, cb = ha["chromaticities"], hb["chromaticities"]
    if not _same_colour_space(ca, cb):
        raise InputError(f"{name_a} {a} has {_describe_colour_space(ca)} but {name_b} {b} has "
                         f"{_describe_colour_space(cb)}: their R, G, B are in different colour "
                         "spaces, so pixel by pixel they pair different colours; expected the "
                         "same primaries and white point (convert one file into the other's "
                         "colour space first).")


def cmd_reference(args) -> int:
    from .demo import render_reference
    from .renderers import make_renderer

    _check_scene_arg(args.scene)
    width, height = _parse_size(args.size)
    spp = _positive_int("--spp", args.spp)
    _check_count_range("--spp", spp)
    per_pass = min(spp, _positive_int("--pass-spp", args.pass_spp))
    _check_out_file(args.out)
    renderer = make_renderer(args.scene, width=width, height=height, **_scene_options(args))
    stats = render_reference(renderer, spp, pass_spp=per_pass, seed=args.seed,
                             progress=not args.quiet, features=True)
    _write_result(args.out, stats, stats.mean, inputs=(), quiet=True)
    if not args.quiet:
        passes = -(-spp // per_pass)
        print(f"wrote {args.out} ({spp} spp in {passes} pass{'' if passes == 1 else 'es'})")
    return 0


def cmd_metrics(args) -> int:
    from .exr import read_image
    from .metrics import all_metrics
    opts = {} if args.replace_nonfinite is None else {"nonfinite": "replace",
                                                      "replace_value": args.replace_nonfinite}
    image_layer, reference_layer = _file_layers(args, "image", "reference")
    image_part, reference_part = _file_parts(args, "image", "reference")
    with _layer_hint_for("--image-layer", "IMAGE"):
        img = read_image(args.image, layer=image_layer, part=image_part, **opts)
    with _layer_hint_for("--reference-layer", "REFERENCE"):
        ref = read_image(args.reference, layer=reference_layer, part=reference_part, **opts)
    if img.shape != ref.shape:
        raise InputError(f"{args.image} is {img.shape[1]}x{img.shape[0]}x{img.shape[2]} but "
                         f"{args.reference} is {ref.shape[1]}x{ref.shape[0]}x{ref.shape[2]}.")
    _same_frame(args.image, args.reference, "IMAGE", "REFERENCE", (image_part, reference_part))
    print(json.dumps(all_metrics(img, ref), indent=2, default=_json_default))
    return 0


def cmd_info(args) -> int:
    from .exr import exr_info
    print(json.dumps(exr_info(args.file, families=True, part=_part(args)), indent=2,
                     default=_json_default))
    return 0


def cmd_scenes(args) -> int:
    from .renderers import list_scenes
    for name, desc in list_scenes().items():
        print(f"{name:24s} {desc}")
    return 0


# ---------------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse with the commands' one-line errors (exit status 2) instead of the usage block."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


LAYER_HELP = ("read the channels of this EXR layer as if unprefixed, e.g. ViewLayer.Combined "
              "for Blender's ViewLayer.Combined.R,G,B (and its Variance.*, SampleCount if any)")


#: The commands with --layer (the others read statmc's own files, or a --reference).
_LAYER_COMMANDS = ("reconstruct", "denoise", "progressive", "combine", "metrics")


def _layer_type(text: str) -> str:
    """``--layer`` and ``--<file>-layer``: a layer name, refused while parsing (naming the
    option given) when empty or ending in a dot, as ``read_exr(layer=)`` would refuse it."""
    if not text or text.endswith("."):
        raise argparse.ArgumentTypeError("expected a layer name such as 'ViewLayer.Combined' "
                                         f"(without the channel's last part); got {text!r}")
    return text


def _add_layer_option(parser, what: str = "the input") -> None:
    parser.add_argument("--layer", type=_layer_type, default=None, metavar="NAME",
                        help=LAYER_HELP.replace("EXR layer", f"layer of {what}"))
    parser.add_argument("--part", type=_part_type, default=None, metavar="INDEX|NAME",
                        help=f"the part of a multi-part EXR to read, of {what}: its index (from "
                             "0) or its name (default: part 0)")


#: The commands with --part: those with --layer, and info.
_PART_COMMANDS = _LAYER_COMMANDS + ("info",)


def _part_type(text: str):
    """``--part``: an index (digits) or a part's name."""
    if text.isdigit():
        return int(text)
    if not text:
        raise argparse.ArgumentTypeError("expected a part's index (0, 1, ...) or its name; got ''")
    return text


def _add_feature_options(parser) -> None:
    """``--albedo-layer`` and ``--normal-layer``: where OIDN's features come from."""
    parser.add_argument("--albedo-layer", default=None, metavar="NAME",
                        help="the layer whose .R,.G,.B is OIDN's albedo, e.g. 'ViewLayer.Denoising "
                             "Albedo' (default: the file's Albedo.*, else Blender's Denoising "
                             "Albedo beside the colour or a top-level Mitsuba AOV 'albedo')")
    parser.add_argument("--normal-layer", default=None, metavar="NAME",
                        help="the layer whose .X,.Y,.Z (or .R,.G,.B) is OIDN's normal, e.g. 'nn' "
                             "(default: the file's N.*, else Blender's Denoising Normal beside "
                             "the colour or a top-level AOV 'normal', 'normals' or 'sh_normal')")


def _add_file_layer_options(parser, *files: str) -> None:
    """``--<file>-layer`` for each of a two-file command's files: its layer, in place of
    ``--layer``'s (which names both files' layer)."""
    for which in files:
        upper = which.upper()
        parser.add_argument(f"--{which}-layer", type=_layer_type, default=None, metavar="NAME",
                            help=f"the layer of {upper} alone, in place of --layer's (say "
                                 f"ViewLayer.Combined for a Blender render beside an "
                                 f"unlayered file)")
        parser.add_argument(f"--{which}-part", type=_part_type, default=None,
                            metavar="INDEX|NAME",
                            help=f"the part of {upper} alone, in place of --part's")


SPP_HELP = ("samples per pixel of a file without SampleCount (a positive integer; pbrt-v4 "
            "files give theirs in the samplesPerPixel header attribute)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="statmc", description=DESCRIPTION)
    p.add_argument("--version", action="version", version=f"statmc {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("render", help="render a scene with uniform or mapped per-pixel sample counts")
    r.add_argument("scene", metavar="SCENE", help="built-in scene name (see `statmc scenes`), toy:NAME, or Mitsuba XML path")
    r.add_argument("--spp", type=POSITIVE_INT,
                   help="samples per pixel, a positive integer; with an adaptive --sampler the "
                        "average budget, with --sample-map the budget the map (then a density, "
                        "whole numbers or not) is scaled to")
    r.add_argument("--out", required=True, help="output directory (created if missing)")
    r.add_argument("--size", help="WIDTHxHEIGHT (default: the scene's own size)")
    _add_define_option(r)
    r.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
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
                                             "oidn+combine", "gem+bins", "oidn+bins"],
                   default="none",
                   help="reconstruction written beside the raw render; gem+bins / oidn+bins "
                        "render --bins sample bins and combine them with their per-bin "
                        "denoised images (Back 2020 Eq. 14; GEM's full-sample kernel shared "
                        "by the bins, or OIDN on each bin)")
    r.add_argument("--bins", type=POSITIVE_INT, default=None,
                   help="number of sample bins of --reconstruct gem+bins / oidn+bins (default "
                        "4, the paper's; --spp must be a multiple of it)")
    _add_gem_options(r, "--reconstruct gem or gem+bins and --denoiser gem",
                     "by the adaptive --sampler gem and the pilot kernels of --sampler "
                     "expected-error always, and ", refuse_unused=True)
    r.add_argument("--crn", action="store_true",
                   help="common-random-number render (Mitsuba scenes, uniform --spp >= 2): sample "
                        "j of every pixel uses the same random sequence, so neighbouring errors "
                        "are correlated; render.exr gets the covariance stencil "
                        "(SpatialCovariance.* channels), a correlated Z for `statmc combine`")
    r.add_argument("--stencil", type=_odd_int, default=None,
                   help="odd width of --crn's covariance stencil (default 15; combine's --size "
                        "must not exceed it)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary line")
    r.set_defaults(func=cmd_render)

    rc = sub.add_parser("reconstruct", help="reconstruct an image from a statistics EXR (any renderer)")
    rc.add_argument("input", help="EXR with R,G,B, Variance.* and SampleCount (or pbrt-v4's "
                    "samplesPerPixel attribute, or --spp)")
    rc.add_argument("--method", choices=["gem", "oidn+combine"], default="gem",
                    help="gem (default; Rousselle 2011) or oidn+combine (OIDN improved by Back "
                         "2020's combination kernel: covariances probed through OIDN, a SURE "
                         "mix; needs R,G,B and 2 samples in every pixel; docs/combine.md)")
    rc.add_argument("--out", required=True, help="output .exr (a .png preview goes beside it)")
    rc.add_argument("--spp", type=POSITIVE_INT, help=SPP_HELP)
    _add_layer_option(rc, "the input")
    _add_feature_options(rc)
    _add_gem_options(rc, "--method gem", refuse_unused=True)
    rc.add_argument("-q", "--quiet", action="store_true", help="no summary line")
    rc.set_defaults(func=cmd_reconstruct)

    ref = sub.add_parser("reference", help="render a high-spp reference in passes")
    ref.add_argument("scene", metavar="SCENE", help="as for `statmc render`")
    ref.add_argument("--spp", type=POSITIVE_INT, required=True, help="total samples per pixel")
    ref.add_argument("--out", required=True, help="output .exr (a .png preview goes beside it)")
    ref.add_argument("--size", help="WIDTHxHEIGHT (default: the scene's own size)")
    _add_define_option(ref)
    ref.add_argument("--seed", type=SEED, default=1_000_003,
                     help="random seed of the first pass; pass k uses seed + 7919 k (default "
                          "1000003, far from the renders' default 0)")
    ref.add_argument("--pass-spp", type=POSITIVE_INT, default=256,
                     help="samples per pixel per pass (default 256)")
    ref.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary line")
    ref.set_defaults(func=cmd_reference)

    m = sub.add_parser("metrics", help="error metrics of an image against a reference (JSON)")
    m.add_argument("image", help="EXR image (R,G,B or Y)")
    m.add_argument("reference", help="EXR of the same size")
    _add_layer_option(m, "both files")
    _add_file_layer_options(m, "image", "reference")
    m.add_argument("--replace-nonfinite", type=FINITE, metavar="VALUE",
                   help="replace NaN/Inf pixels by VALUE (default: refuse such files)")
    m.set_defaults(func=cmd_metrics)

    i = sub.add_parser("info", help="channels, size, sample counts and NaN/Inf counts of an EXR")
    i.add_argument("file", help="EXR file")
    i.add_argument("--part", type=_part_type, default=None, metavar="INDEX|NAME",
                   help="the part of a multi-part EXR to describe: its index (from 0) or its "
                        "name (default: part 0; the others are listed under other_parts)")
    i.set_defaults(func=cmd_info)

    d = sub.add_parser("denoise", help="denoise an EXR (OIDN uses its albedo/normal)")
    d.add_argument("input", help="EXR with R,G,B; --variance and --denoiser gem need its "
                                 "statistics (Variance.*, and SampleCount or --spp)")
    d.add_argument("--denoiser", choices=["oidn", "gem", "gaussian"], default="oidn",
                   help="default oidn")
    d.add_argument("--out", required=True, help="output .exr (a .png preview goes beside it)")
    d.add_argument("--spp", type=POSITIVE_INT,
                   help=SPP_HELP + "; read by --variance and --denoiser gem only")
    d.add_argument("--variance", action="store_true",
                   help="also store the output's first-order variance (Firmino 2023) as Variance.*")
    _add_layer_option(d, "the input")
    _add_feature_options(d)
    _add_gem_options(d, "--denoiser gem", refuse_unused=True)
    d.add_argument("--sigma", type=POSITIVE, default=None,
                   help="standard deviation of --denoiser gaussian in pixels (default 1)")
    d.add_argument("--seed", type=SEED, default=None,
                   help="seed of the random probes of --variance with --denoiser oidn (default 0)")
    d.add_argument("-q", "--quiet", action="store_true", help="no summary line")
    d.set_defaults(func=cmd_denoise)

    pg = sub.add_parser("progressive", help="progressive denoising (Firmino 2022): the render mixed "
                                            "with a denoiser's output by a Student-t gated α")
    pg.add_argument("input", help="statistics EXR (R,G,B, Variance.*, SampleCount or --spp)")
    pg.add_argument("--denoiser", choices=["oidn", "gem", "gaussian"], default="oidn",
                    help="default oidn")
    pg.add_argument("--out", required=True, help="output .exr (a .png preview goes beside it)")
    pg.add_argument("--spp", type=POSITIVE_INT, help=SPP_HELP)
    _add_layer_option(pg, "the input")
    _add_feature_options(pg)
    _add_gem_options(pg, "--denoiser gem", refuse_unused=True)
    pg.add_argument("--seed", type=SEED, default=0,
                    help="seed of MC-SURE's random probes (default 0)")
    pg.add_argument("-q", "--quiet", action="store_true", help="no summary line")
    pg.set_defaults(func=cmd_progressive)

    c = sub.add_parser("combine", help="combine an independent Y and a correlated Z (Back 2020 "
                                        "Eq. 8), or sample bins with their denoised images (Eq. 14)")
    c.add_argument("y", help="EXR of the independent render (its statistics for --weights "
                             "statistical: Variance.*, and SampleCount or --spp; R,G,B alone "
                             "for uniform and gaussian), or a bins.exr of `statmc render "
                             "--reconstruct gem+bins|oidn+bins` (then without Z)")
    c.add_argument("z", nargs="?", default=None,
                   help="correlated image whose noise is independent of Y's, e.g. a "
                        "`statmc render --crn` render (with --weights statistical its covariance "
                        "stencil is used); other files need Variance.* for --weights "
                        "statistical (statmc denoise --variance). Cov[Y, Z] is taken as zero: "
                        "for Z = Y denoised it is not, and the result can be worse than Z; use "
                        "`statmc reconstruct Y.exr --method oidn+combine` for that. Left out "
                        "when Y holds sample bins (Bin<b>.* and Bin<b>.Denoised.* channels)")
    _add_layer_option(c, "Y and Z")
    _add_file_layer_options(c, "y", "z")
    c.add_argument("--weights", choices=["uniform", "gaussian", "statistical"], default="statistical",
                   help="default statistical")
    c.add_argument("--size", type=_odd_int, default=None,
                   help="odd window width (default 15 on any image, or a --crn Z's narrower "
                        "stencil width); a given --size must be at most max(15, 2·max(H, W) − 1) "
                        "for an H×W image")
    c.add_argument("--sigma", type=POSITIVE, default=None,
                   help="spatial σ of --weights gaussian in pixels (default 3)")
    c.add_argument("--spp", type=POSITIVE_INT,
                   help=SPP_HELP + "; read by --weights statistical only")
    c.add_argument("--out", required=True, help="output .exr (a .png preview goes beside it)")
    c.add_argument("-q", "--quiet", action="store_true", help="no summary line")
    c.set_defaults(func=cmd_combine)

    s = sub.add_parser("scenes", help="list built-in scenes")
    s.set_defaults(func=cmd_scenes)
    return p


# Library messages name keyword arguments; on the command line the same things are options.
_CLI_WORDING = (
    ("pass the render's uniform spp=.", "pass the render's uniform samples per pixel as --spp N."),
    ("omit spp= to use the file's counts", "omit --spp to use the file's counts"),
    (" Pass require_variance=False to read it with zero variance, or use read_image().", ""),
    ("`spp`", "--spp"),
    ("`stencil`", "--stencil"),
    ("leave `width`/`height` unset", "omit --size"),
    ("give it a value with `params` (`-D ", "give it a value with `-D "),
    ("=VALUE` on the command line) or add <default", "=VALUE` or add <default"),
    ("`params`", "-D"),
    ("`sensor`", "--sensor"),
    ("`layer` must be a layer name", "--layer must be a layer name"),
    ("pass albedo='NAME' (one of them)", "give --albedo-layer NAME (one of them)"),
    ("pass normal='NAME' (one of them)", "give --normal-layer NAME (one of them)"),
    ("`albedo` must be the name", "--albedo-layer must be the name"),
    ("`normal` must be the name", "--normal-layer must be the name"),
    ("; None: recognised, False: statmc's own Albedo.* only", ""),
    ("; None: recognised, False: statmc's own N.* only", ""),
    ("`n` must be >= 2 in every pixel", "the sample count must be >= 2 in every pixel"),
    ("`color` must be an (H, W, 3) image", "the denoiser needs an R,G,B image"),
)
_NONFINITE_HINT = "pass nonfinite='replace' to replace them by `replace_value`."


def _cli_message(message: str, command: str) -> str:
    """``message`` with the library's keyword hints replaced by the command's options."""
    for old, new in _CLI_WORDING:
        message = message.replace(old, new)
    fix = ("give --replace-nonfinite VALUE to replace them." if command == "metrics" else
           "expected finite values (`statmc info FILE` counts them per channel).")
    message = message.replace(_NONFINITE_HINT, fix)
    # the library's layer= is the command's --layer, where it has one
    from .exr import _PART_HINT
    message = message.replace(f" — {_PART_HINT}", " — give --part INDEX|NAME to read "
                              "another" if command in _PART_COMMANDS else "")
    message = message.replace("`part`", "--part")
    return _LAYER_HINT.sub(r", or give --layer \1" if command in _LAYER_COMMANDS else "", message)


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version (0) and argument errors (2, one line printed)
        return e.code if isinstance(e.code, int) else EXIT_USAGE
    return run_command(functools.partial(args.func, args), prog="statmc",
                       label=f"statmc {args.command}", debug=args.debug,
                       wording=functools.partial(_cli_message, command=args.command))


_MEMORY_HINT = "use a smaller --size, --spp, --stencil or input image."


def run_command(call, *, prog: str, label: str | None = None, debug: bool = False,
                wording=None, memory_hint: str = _MEMORY_HINT) -> int:
    """Run ``call()`` as a command-line program and return its exit status (``call``'s
    return value, None meaning 0): the error handling of every ``statmc`` command, shared
    with ``python -m statmc.demo``.

    Bad input — :class:`InputError`, :class:`FileFormatError` (both ``ValueError``), other
    ``ValueError``, ``OSError`` and ``MemoryError`` (with ``memory_hint``) — prints one line
    ``LABEL: error: MESSAGE`` on stderr (``wording`` may rewrite the message) and gives 2;
    Ctrl-C prints ``PROG: interrupted`` (130), SIGTERM ``PROG: terminated`` (143, after
    ``finally`` blocks ran, as for Ctrl-C); a reader that left the pipe gives 141 silently.
    Warnings print as one line ``LABEL: warning: ...``.  With ``debug`` errors propagate
    (the traceback) and warnings keep Python's format.  ``label`` defaults to ``prog``."""
    label = label or prog
    previous = _on_sigterm(_terminate)
    try:
        from .exr import capturing_openexr_output, using_io_threads
        # one-line errors; EXR files decoded and encoded on all CPUs (OpenEXR: one thread)
        with warnings.catch_warnings(), capturing_openexr_output(), using_io_threads():
            if not debug:  # one line per warning, without the source file and line
                warnings.showwarning = functools.partial(_show_warning, label)
            return int(call() or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except _Terminated:  # `kill`, `timeout`: clean up (staged outputs) as on Ctrl-C
        print(f"{prog}: terminated", file=sys.stderr)
        return 143  # 128 + SIGTERM
    except BrokenPipeError:  # `statmc metrics ... | head`: the reader left; stop quietly
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):  # no real stdout (in-process callers)
            pass
        return 141  # 128 + SIGPIPE, as a shell reports a process killed by it
    except (ValueError, OSError, MemoryError) as e:  # InputError and FileFormatError are ValueErrors
        if debug:
            raise
        msg = wording(str(e)) if wording else str(e)
        if isinstance(e, MemoryError):
            msg = (f"out of memory ({msg or 'MemoryError'}); expected inputs that fit in memory: "
                   f"{memory_hint}")
        print(f"{label}: error: {msg}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        _on_sigterm(previous)


def _show_warning(label, message, category, filename, lineno, file=None, line=None):
    """``warnings.showwarning`` of the command line: ``statmc CMD: warning: ...`` on stderr
    (``label`` is ``statmc CMD``)."""
    text = str(message)
    text = text[len("statmc: "):] if text.startswith("statmc: ") else text
    print(f"{label}: warning: {text}", file=sys.stderr)


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that ``finally`` blocks (and the removal of
    staged outputs) run, as for Ctrl-C."""


def _terminate(signum, frame):
    raise _Terminated()


def _on_sigterm(handler):
    """Install ``handler`` for SIGTERM and return the previous one (None, and nothing done,
    outside the main thread or where it cannot be set)."""
    import signal
    if handler is None:
        return None
    try:
        return signal.signal(signal.SIGTERM, handler)
    except (ValueError, OSError):  # not the main thread
        return None


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
