"""Mitsuba 3 renderer backend with exact per-pixel sample counts.

Mitsuba 3 renders the same number of samples in every pixel.  :class:`MitsubaRenderer`
renders any integer count map instead, as a wavefront: pixel indices are repeated by their
counts (in chunks of about two million samples, so memory stays bounded), each sample is
jittered inside its pixel, traced with ``sensor.sample_ray_differential`` and
``integrator.sample``, and summed per pixel with ``dr.scatter_reduce`` into ``float64``
Dr.Jit arrays (sums, sums of squares and the cross sums ``Σ x_a x_b`` of the channel
pairs RG, RB, GB, which give the channel covariance).  The sums are copied to NumPy once,
at the end,
and become :class:`statmc.stats.PixelStats`.  Keeping the accumulators inside Dr.Jit is
what makes this as fast as ``mi.render`` (see ``bench/bench_render.py``).

A sample belongs to the pixel it was drawn in: the reconstruction filter is a box, whatever
filter the scene's film declares.  The scene's sampler is replaced by an ``independent``
sampler.  Every sample has its own random stream, a function of the render's seed, its
pixel and its index in that pixel only (:func:`_sample_seeds`): sample ``j`` of pixel ``p``
is the same whatever the counts of the other pixels, and ``render(..., first_sample=)``
continues a pixel's sequence where an earlier pass stopped.  So an adaptive render and a
uniform render with the same seed share the first samples of every pixel (common random
numbers between samplers), and moving one sample leaves every other pixel as it was.
A stream is set by one 32-bit word, a keyed bijection of ``j · P + p`` (P pixels), so no
two samples of a render share a stream while ``j < 2**32 / P`` (beyond that the words wrap
and ``render`` warns).  Renders whose seeds differ are independent, but renders with the
same seed are not: give a reference and the renders it scores different seeds.

Mitsuba's fast ``llvm_ad_rgb`` variant needs LLVM >= 16 at run time
(:func:`find_libllvm`, :func:`setup_mitsuba`).  Without it the backend falls back to
``scalar_rgb``, which renders per-pixel counts as one-sample passes of ``mi.render``,
pass ``j`` giving sample ``j`` of every pixel (correct, much slower; a render continuing
sequences with ``first_sample`` needs ``max(first + counts) − min(first)`` passes, about
3× ``max(counts)`` for an adaptive GEM pass).

Mitsuba is imported here only, and only when a function of this module is called.
"""

from __future__ import annotations

import glob
import math
import numbers
import os
import re
import sys
import time
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .errors import (FileFormatError, InputError, as_bool, as_float_array, check_finite,
                     check_nonnegative)
from .scenes import BUILTIN_SCENES, _check_size, load_scene_dict
from .stats import PixelStats

__all__ = ["find_libllvm", "setup_mitsuba", "current_mitsuba", "MitsubaRenderer",
           "MIN_LLVM_VERSION", "LLVM_SEARCH_PATTERNS"]

#: Oldest LLVM that Dr.Jit's LLVM backend runs with (14 and 15 fail with
#: "Cannot select ... fminimum").
MIN_LLVM_VERSION = 16

#: Glob patterns searched, in order, for a shared libLLVM (after ``DRJIT_LIBLLVM_PATH``).
LLVM_SEARCH_PATTERNS: tuple[str, ...] = (
    "/usr/lib/*-linux-gnu/libLLVM-[0-9]*.so*",
    "/usr/lib/*-linux-gnu/libLLVM.so.[0-9]*",
    "/usr/lib/llvm-[0-9]*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM-[0-9]*.so*",
    "/usr/lib64/libLLVM.so.[0-9]*",
    "/usr/local/lib/libLLVM-[0-9]*.so*",
    "/usr/local/lib/libLLVM.so.[0-9]*",
)

_VERSION_PATTERNS = (
    re.compile(r"libLLVM-(\d+)"),          # libLLVM-19.so, libLLVM-19.so.1
    re.compile(r"llvm-(\d+)[/\\]"),        # /usr/lib/llvm-19/lib/libLLVM.so.1
    re.compile(r"libLLVM\.so\.(\d+)"),     # libLLVM.so.19.1
)

_LLVM_HINT = ("install LLVM >= 16 (on Debian/Ubuntu: `apt-get install libllvm19`) or point "
              "DRJIT_LIBLLVM_PATH at libLLVM-16 or newer")

# The variant chosen by setup_mitsuba(None), remembered for the life of the process.
_AUTO: dict[str, str] = {}

# Salts separating the random streams of the passes of one render.
_SALT_MAIN = 0x5EED
_SALT_FEATURES = 0xFEA7
_SALT_CRN = 0xC0CA

#: Largest memory :meth:`MitsubaRenderer.render_crn` may take for its stencil arrays.
CRN_MAX_BYTES = 4 * 2 ** 30
_PAIRS = ((0, 1), (0, 2), (1, 2))   # channel pairs RG, RB, GB (PixelStats.from_sums order)


def _llvm_version(path: str) -> int | None:
    """Major LLVM version in a library path, or None when the name does not say."""
    for pat in _VERSION_PATTERNS:
        m = pat.search(path)
        if m:
            return int(m.group(1))
    return None


def find_libllvm() -> str | None:
    """Path of a shared libLLVM >= 16 for Dr.Jit's LLVM backend, or None.

    ``DRJIT_LIBLLVM_PATH`` is used first when it names an existing file whose version is
    >= 16 or cannot be read from its name.  Otherwise :data:`LLVM_SEARCH_PATTERNS` are
    searched and the newest version found wins (the shortest name among equals).

    Returns
    -------
    str or None
    """
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.isfile(env):
        v = _llvm_version(env)
        if v is None or v >= MIN_LLVM_VERSION:
            return env
    best = None
    for pattern in LLVM_SEARCH_PATTERNS:
        for path in glob.glob(pattern):
            v = _llvm_version(path)
            if v is None or v < MIN_LLVM_VERSION or not os.path.isfile(path):
                continue
            key = (v, -len(path), path)
            if best is None or key > best[0]:
                best = (key, path)
    return None if best is None else best[1]


def _import_mitsuba():
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - mitsuba is a dependency
        raise InputError(f"the Mitsuba backend needs the `mitsuba` package ({e}); "
                         "`pip install mitsuba`.") from None
    return mi


def _choose_auto_variant() -> str:
    path = find_libllvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path   # before drjit starts its LLVM backend
    mi = _import_mitsuba()
    if path is None:
        warnings.warn(f"statmc: no libLLVM >= {MIN_LLVM_VERSION} found, so Mitsuba uses the slow "
                      f"`scalar_rgb` variant; {_LLVM_HINT}.", RuntimeWarning, stacklevel=3)
        return "scalar_rgb"
    try:
        mi.set_variant("llvm_ad_rgb")
    except Exception as e:  # noqa: BLE001 - any failure to start LLVM means: fall back
        warnings.warn(f"statmc: Mitsuba's `llvm_ad_rgb` variant did not start with {path} ({e}); "
                      f"using the slow `scalar_rgb` variant; {_LLVM_HINT}.",
                      RuntimeWarning, stacklevel=3)
        return "scalar_rgb"
    return "llvm_ad_rgb"


def setup_mitsuba(variant: str | None = None):
    """Import Mitsuba 3 and set its variant, finding LLVM first.

    Parameters
    ----------
    variant : str, optional
        An RGB variant (``llvm_ad_rgb``, ``scalar_rgb``, ``cuda_ad_rgb``).  By default
        ``llvm_ad_rgb`` when :func:`find_libllvm` finds LLVM >= 16 (``DRJIT_LIBLLVM_PATH``
        is set to it before Dr.Jit is imported), else ``scalar_rgb`` with a
        ``RuntimeWarning`` saying how to install LLVM.

    Returns
    -------
    mi : module
        The ``mitsuba`` module with the variant set.
    variant : str
    """
    if variant is None:
        if "auto" not in _AUTO:
            _AUTO["auto"] = _choose_auto_variant()
        variant = _AUTO["auto"]
    else:
        if not isinstance(variant, str) or not variant.endswith("_rgb"):
            raise InputError(f"`variant` must be a Mitsuba RGB variant such as 'llvm_ad_rgb' or "
                             f"'scalar_rgb'; got {variant!r}.")
        if variant.startswith("llvm"):
            path = find_libllvm()
            if path is None:
                raise InputError(f"`variant` {variant!r} needs libLLVM >= {MIN_LLVM_VERSION}, "
                                 f"which was not found; {_LLVM_HINT}, or use 'scalar_rgb'.")
            os.environ["DRJIT_LIBLLVM_PATH"] = path
    mi = _import_mitsuba()
    if variant not in mi.variants():
        raise InputError(f"`variant` {variant!r} is not in this Mitsuba build; "
                         f"available: {', '.join(mi.variants())}.")
    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as e:  # noqa: BLE001
            raise InputError(f"Mitsuba could not start variant {variant!r} ({e}); {_LLVM_HINT}, "
                             "or use 'scalar_rgb'.") from None
    return mi, variant


def current_mitsuba():
    """The ``mitsuba`` module with its current variant, set up by :func:`setup_mitsuba` if unset."""
    mi = sys.modules.get("mitsuba")
    if mi is not None and mi.variant() is not None:
        return mi
    return setup_mitsuba()[0]


# ---------------------------------------------------------------------------- helpers
def _check_int(name: str, value, *, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise InputError(f"`{name}` must be an integer >= {minimum}; got {value!r}.")
    return int(value)


def _check_flags(**flags) -> None:
    """Refuse a True/False option given as anything else (``progress="no"`` showed the bar)."""
    for name, value in flags.items():
        as_bool(name, value)


def _chunk_seed(seed: int, salt: int, chunk: int) -> int:
    """A 32-bit sampler seed for one chunk, distinct streams for distinct (seed, salt, chunk)."""
    return int(np.random.SeedSequence([seed, salt, chunk]).generate_state(1, np.uint32)[0])


#: (shifts, multipliers) of two xor-shift-multiply mixes: SplitMix64's output function on
#: 64-bit words and MurmurHash3's 32-bit finaliser.  Both are bijections of their words.
_SPLITMIX64 = ((30, 27, 31), (0xBF58476D1CE4E5B9, 0x94D049BB133111EB))
_FMIX32 = ((16, 13, 16), (0x85EBCA6B, 0xC2B2AE35))


def _xorshift_multiply(x, constants, word):
    """``x ^= x >> s1; x *= m1; x ^= x >> s2; x *= m2; x ^= x >> s3`` on an array of
    unsigned words (products wrap); ``word`` is the word type (``np.uint64``,
    ``np.uint32`` or a Dr.Jit ``UInt32``), so NumPy and Dr.Jit share this code."""
    (s1, s2, s3), (m1, m2) = constants
    x = x ^ (x >> word(s1))
    x = x * word(m1)
    x = x ^ (x >> word(s2))
    x = x * word(m2)
    return x ^ (x >> word(s3))


def _fmix32(h: np.ndarray) -> np.ndarray:
    """MurmurHash3's 32-bit finaliser of a ``uint32`` array."""
    return _xorshift_multiply(h, _FMIX32, np.uint32)


def _seed_keys(seed: int, salt: int) -> tuple[int, int]:
    """Two 32-bit keys ``(k1, k2)`` of a render seed (and a salt)."""
    k = np.random.SeedSequence([seed, salt]).generate_state(2, np.uint32)
    return int(k[0]), int(k[1])


def _sample_seeds(keys, pixels: int, pix: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Sampler seed of sample ``index`` of pixel ``pix`` (of ``pixels``):
    ``fmix32(index · pixels + pix + k1) ^ k2``, a keyed bijection of the word
    ``index · pixels + pix`` (modulo 2**32).

    So within one render no two samples share a stream while every index stays below
    ``2**32 / pixels`` (2048 samples per pixel at 1920×1080, 349,525 at 128×96); beyond
    that the words wrap around (:meth:`MitsubaRenderer.render` warns).  (NumPy reference
    of the seeds that :meth:`MitsubaRenderer._render_jit` forms inside Dr.Jit.)
    """
    k1, k2 = keys
    w = (index.astype(np.uint64) * np.uint64(pixels) + pix.astype(np.uint64) + np.uint64(k1))
    with np.errstate(over="ignore"):
        return _fmix32((w % np.uint64(1 << 32)).astype(np.uint32)) ^ np.uint32(k2)


def _warn_if_words_wrap(first: np.ndarray, counts: np.ndarray) -> bool:
    """Warn (and return True) when a sample's word ``index · P + pixel`` of
    :func:`_sample_seeds` reaches 2**32: it then wraps around onto the word, hence the
    random stream, of another sample of the same seed (sample 0 of pixel 0 for the word
    2**32), so the render is no longer made of independent samples."""
    used = counts.ravel() > 0
    if not used.any():
        return False
    P = counts.size
    last = (first.ravel()[used] + counts.ravel()[used] - 1) * P + np.flatnonzero(used)
    top = int(last.max())                     # < 2**31 · P, exact in int64
    if top < 2 ** 32:
        return False
    warnings.warn(f"statmc: this render uses sample indices up to {top // P} with {P} pixels; "
                  f"from index {2 ** 32 // P} on (2**32 / pixels) the 32-bit seed words wrap "
                  "around, so some samples repeat the random stream of others with the same "
                  "seed and are not independent.  Render fewer samples per pixel per seed, or "
                  "merge renders with different seeds.", RuntimeWarning, stacklevel=3)
    return True


def _chunk_pixels(counts_flat: np.ndarray, chunk: int):
    """Yield the flat pixel index of every sample, ``chunk`` samples at a time.

    The concatenation of the chunks equals ``np.repeat(arange(P), counts_flat)`` (samples
    of a pixel are consecutive) without building that array whole.
    """
    cum = np.cumsum(counts_flat)
    total = int(cum[-1]) if cum.size else 0
    start = cum - counts_flat
    for a in range(0, total, chunk):
        b = min(a + chunk, total)
        p0 = int(np.searchsorted(cum, a, side="right"))
        p1 = int(np.searchsorted(cum, b - 1, side="right"))
        local = np.minimum(cum[p0:p1 + 1], b) - np.maximum(start[p0:p1 + 1], a)
        yield np.repeat(np.arange(p0, p1 + 1, dtype=np.uint32), local)


def _chunk_samples(counts_flat: np.ndarray, first_flat: np.ndarray, chunk: int):
    """Like :func:`_chunk_pixels`, yielding ``(pixel, index)``: the pixel of every sample
    and its index in that pixel's sequence, ``first_flat[pixel] + (its rank in this
    render)``."""
    start = np.cumsum(counts_flat) - counts_flat
    a = 0
    for pix in _chunk_pixels(counts_flat, chunk):
        rank = np.arange(a, a + pix.size, dtype=np.int64) - start[pix]
        yield pix, first_flat[pix] + rank
        a += pix.size


def _seed_bases(k1: int, counts_flat: np.ndarray, first_flat: np.ndarray) -> np.ndarray:
    """``(first[p] − start[p]) · P + p + k1`` modulo 2**32 per pixel, where ``start[p]``
    is the position of pixel p's first sample in the render's sample order and ``P`` the
    number of pixels: the sample at position ``g`` (in pixel p, index ``first[p] + g −
    start[p]``) then has the word ``base[p] + g · P`` of :func:`_sample_seeds`."""
    P = counts_flat.size
    start = np.cumsum(counts_flat) - counts_flat
    d = ((first_flat - start) % (1 << 32)).astype(np.uint64)        # < 2**32
    w = d * np.uint64(P) + np.arange(P, dtype=np.uint64) + np.uint64(k1)   # < 2**64
    return (w % np.uint64(1 << 32)).astype(np.uint32)


def _fmix32_drjit(mi, h):
    """:func:`_fmix32` on a Dr.Jit ``UInt32`` array."""
    return _xorshift_multiply(h, _FMIX32, mi.UInt32)


_PARAM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def _check_params(params) -> dict:
    """``params`` of :class:`MitsubaRenderer`: a mapping of ``$name`` values, as strings."""
    if params is None:
        return {}
    if not hasattr(params, "items"):
        raise InputError(f"`params` must be a mapping of scene parameter names to values "
                         f"(the $name substitutions of the XML file); got {type(params).__name__}.")
    out = {}
    for k, v in params.items():
        if (not isinstance(k, str) or not _PARAM_NAME.match(k)
                or k in ("parallel", "optimize", "update_scene")):
            # the last three are options of Mitsuba's loader (update_scene: older versions)
            raise InputError(f"`params` names must be XML parameter names (letters, digits, "
                             f"'_', as in $spp), not 'parallel' or 'optimize' (options of "
                             f"Mitsuba's loader: rename such a $name in the file); got {k!r}.")
        if isinstance(v, bool):
            v = "true" if v else "false"
        if not isinstance(v, (str, numbers.Real)):
            raise InputError(f"`params` value of {k!r} must be a string or a number; "
                             f"got {type(v).__name__}.")
        out[k] = str(v)
    return out


def _mitsuba_message(path: Path, e: Exception) -> str:
    """Mitsuba's loader error on one line, without its C++ source locations, with a hint
    for an undefined ``$name``."""
    msg = re.sub(r"\[[\w./]+\.(?:cpp|h):\d+\] ", "", str(e)).strip().rstrip(".!")
    msg = re.sub(r"\s*\n\s*", " ", msg)
    m = re.search(r"undefined parameter: \$(\w+)", msg)
    if m:
        name = m.group(1)
        msg += (f"; give it a value with `params` (`-D {name}=VALUE` on the command line) or "
                f"add <default name=\"{name}\" value=\"...\"/> to the file")
    return f"Mitsuba could not load scene file {str(path)!r}: {msg}."


def _attribute_text(root) -> str:
    """All attribute values of an XML tree, where Mitsuba substitutes ``$name``."""
    return "\n".join(v for el in root.iter() for v in el.attrib.values())


def _load_string(mi, root, path: Path, params: dict):
    """Load the XML tree ``root`` of file ``path``, finding relative file names beside
    ``path`` (as ``mi.load_file`` does), without leaving that folder in Mitsuba's global
    file resolver for later scenes."""
    resolver = mi.file_resolver()
    saved = [str(resolver[i]) for i in range(len(resolver))]
    resolver.prepend(str(path.resolve().parent))
    try:
        return mi.load_string(ET.tostring(root, encoding="unicode"), **params)
    finally:
        resolver.clear()
        for folder in saved:
            resolver.append(folder)


def _no_such_sensor(sensor: int, count: int, where: str) -> InputError:
    """The refusal of a ``sensor`` index beyond the ``count`` sensors of ``where``."""
    return InputError(f"`sensor` must be the index of one of the {count} sensors of {where} "
                      f"(0 to {count - 1}); got {sensor}.")


def _file_sensor(mi, root, path: Path, params: dict, sensor: int):
    """The ``<sensor>`` element of the XML tree ``root`` (of file ``path``) that becomes
    the scene's sensor number ``sensor``."""
    sensors = root.findall("sensor")        # the file's own, not a batch's parts
    if root.find("include") is None and root.find(".//shape/sensor") is None:
        if sensor < len(sensors):           # the scene's sensors are these, in this order
            return sensors[sensor]
        if not sensors:
            raise InputError(f"scene file {str(path)!r} has no <sensor> element, so its film "
                             "size cannot be set; add a <sensor> with a <film> to it or leave "
                             "`width`/`height` unset.")
        raise _no_such_sensor(sensor, len(sensors), f"scene file {str(path)!r}")
    # <include>d files and shapes add sensors where they stand: tag the file's own and
    # see which one the scene's sensor is
    tags = {}
    for k, el in enumerate(sensors):
        if not el.get("id"):
            el.set("id", f"__statmc_sensor_{k}")
        tags[el.get("id")] = el
    found = _load_string(mi, root, path, params).sensors()
    if sensor >= len(found):
        raise _no_such_sensor(sensor, len(found), f"scene file {str(path)!r}")
    element = tags.get(found[sensor].id())
    if element is None:
        raise InputError(f"sensor {sensor} of scene file {str(path)!r} is not a <sensor> "
                         "written in the file itself (it comes from an <include>d file or a "
                         "shape), so its film cannot be resized; leave `width`/`height` unset "
                         "and set the size where that sensor is written.")
    return element


def _load_xml(mi, path: Path, width: int | None, height: int | None, force_box: bool,
              params: dict | None = None, sensor: int = 0):
    """Load a Mitsuba XML scene (``params``: values of its ``$name`` parameters),
    overriding the film size of sensor number ``sensor`` when asked; ``force_box``: a box
    filter and an RGB film for it (what the scalar fallback's one-sample ``mi.render``
    images need)."""
    params = params or {}
    try:
        if width is None and height is None and not force_box:
            return mi.load_file(str(path), **params)
        try:
            root = ET.parse(path).getroot()
        except ET.ParseError as e:
            raise FileFormatError(f"scene file {str(path)!r} is not valid XML: {e}.") from None
        before = _attribute_text(root)
        element = _file_sensor(mi, root, path, params, sensor)
        film = element.find("film")
        if film is None:
            raise InputError(f"scene file {str(path)!r} has no <film> in the <sensor> of sensor "
                             f"{sensor}, so its size cannot be set; add one or leave "
                             "`width`/`height` unset.")
        crop = [el.get("name") for el in film if str(el.get("name", "")).startswith("crop_")]
        if (width is not None or height is not None) and crop:
            # a new size is refused, the crop window's own size is no change
            scene = mi.load_file(str(path), **params)
            cw, ch = (int(v) for v in scene.sensors()[sensor].film().crop_size())
            if (width or cw, height or ch) != (cw, ch):
                raise InputError(f"scene file {str(path)!r} has a film with a crop window "
                                 f"({', '.join(crop)}) of {cw}x{ch}, which a new film size "
                                 f"{width or cw}x{height or ch} would not resize; make the "
                                 f"size the crop window's, {cw}x{ch}, or leave `width`/`height` "
                                 "unset, or remove the crop window from the film.")
            if not force_box:
                return scene
            width = height = None
        for name, value in (("width", width), ("height", height)):
            if value is None:
                continue
            el = film.find(f"integer[@name='{name}']")
            if el is None:
                el = ET.SubElement(film, "integer", name=name)
            el.set("value", str(value))
        if force_box:
            for el in film.findall("rfilter") + film.findall("string[@name='pixel_format']"):
                film.remove(el)
            ET.SubElement(film, "rfilter", type="box")
            ET.SubElement(film, "string", name="pixel_format", value="rgb")
        # a $name used only in a setting replaced above has no use left (the size given
        # wins): leave it out, as Mitsuba refuses unused parameters
        after = _attribute_text(root)
        params = {k: v for k, v in params.items() if f"${k}" in after or f"${k}" not in before}
        return _load_string(mi, root, path, params)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - Mitsuba's parser raises plain exceptions
        raise FileFormatError(_mitsuba_message(path, e)) from None


def _check_integrator(mi, integrator, name: str) -> None:
    """Refuse an integrator whose ``sample`` is not one sample of the pixel it was drawn in."""
    supported = ("MitsubaRenderer supports Mitsuba's C++ sampling integrators (e.g. 'path', "
                 "'volpath', 'direct')")
    if integrator is None:
        raise InputError(f"scene {name!r} has no integrator; {supported}: add one.")
    if hasattr(integrator, "sample_rays"):
        # Python (differentiable) integrators have no C++ `sample` taking one ray
        raise InputError(f"scene {name!r} uses {type(integrator).__name__}, a Python "
                         f"integrator (such as 'prb'); {supported}: change the scene's "
                         "<integrator>.")
    kind = integrator.class_name()
    if not isinstance(integrator, mi.SamplingIntegrator):
        # ptracer: a light path lands in whatever pixel it reaches, not the one drawn for
        raise InputError(f"scene {name!r} uses Mitsuba's {kind}, a light-tracing integrator "
                         "(such as 'ptracer') that splats paths into whatever pixels they "
                         "reach, so a sample does not belong to one pixel and per-pixel counts "
                         f"cannot steer it; {supported}: change the scene's <integrator>.")
    if kind == "AOVIntegrator" and re.search(r"integrators = \[\s*\]", str(integrator)):
        raise InputError(f"scene {name!r} uses an 'aov' integrator without a nested integrator, "
                         "so it renders no colour (every sample is black); nest one inside it, "
                         "e.g. <integrator type=\"aov\">...<integrator type=\"path\"/></integrator>.")


def _scalar_ready(film) -> bool:
    """Whether one-sample ``mi.render`` images of ``film`` are the samples of its pixels
    with R, G, B first: a box filter and an ``rgb``/``rgba`` pixel format (not ``xyz``,
    which has three channels too; the film's description is the one place that says)."""
    fmt = re.search(r"pixel_format = (\w+)", str(film))
    return (film.rfilter().is_box_filter() and fmt is not None
            and fmt.group(1).lower() in ("rgb", "rgba"))


def _warn_filter(film, name: str) -> None:
    """Say that a film's reconstruction filter other than a box is not used."""
    rfilter = film.rfilter()
    if rfilter.is_box_filter():
        return
    warnings.warn(f"statmc: scene {name!r}: its film's {rfilter.class_name()} is not used: a "
                  "sample counts only in the pixel it was drawn in (a box filter), so the image "
                  "is a little sharper than mi.render's; give the film <rfilter type=\"box\"/> "
                  "to match it.", RuntimeWarning, stacklevel=3)


# ---------------------------------------------------------------------------- renderer
class MitsubaRenderer:
    """Render a Mitsuba 3 scene with any number of samples in each pixel.

    Parameters
    ----------
    scene : str, path or mitsuba.Scene
        A built-in scene name (:data:`statmc.scenes.BUILTIN_SCENES`), a path to a
        Mitsuba XML file, or an already loaded scene.
    width, height : int, optional
        Image size; default: the scene's own (for an XML file whose film has a crop
        window, only the window's size: a new one would not resize the window).
    variant : str, optional
        Mitsuba variant (see :func:`setup_mitsuba`); default ``llvm_ad_rgb`` when LLVM
        >= 16 is found, else ``scalar_rgb``.
    chunk_samples : int, optional
        Samples traced per wavefront (bounds memory: a few hundred bytes per sample).
    sensor : int, optional
        Index of the sensor to render, in the order of the scene file (default 0, as
        ``mi.render``); ``width``/``height`` resize its film.
    params : mapping, optional
        Values of the ``$name`` parameters of an XML scene file (``{"spp": 64}``, as
        ``mitsuba -D spp=64``); they override the file's ``<default>`` values, and a
        parameter the file does not use is an error (Mitsuba's); one used only for the
        film's size gives way to ``width``/``height``.

    Attributes
    ----------
    height, width : int
    sensor : int
    params : dict
        The ``params`` given, as strings (what the file's ``$name`` parameters were set to).
    scene_sample_count : int
        The ``sample_count`` of the sensor's sampler in the scene, which is not used.
    nonfinite_samples : int
        NaN/Inf samples (counted as zeros) of all renders of this renderer so far, every
        pass of every render; an adaptive render's merged ``meta["nonfinite_samples"]``
        holds the sum over its own passes (``PixelStats.merge`` adds the counters of
        :data:`statmc.stats.MERGED_META_SUMS`).
    channels : int
        Always 3 (RGB).
    name : str
        Scene name or file path.
    variant : str

    Notes
    -----
    The reconstruction filter is a box: a sample counts in the pixel it was drawn in (a
    film's other filter, Gaussian by default, is not used: a ``RuntimeWarning`` says so).
    The scene's sampler and its ``sample_count`` are not used either: the counts passed to
    :meth:`render` are the samples, each with an independent random stream.  The image is
    ``sensor``'s, in RGB whatever the film's ``pixel_format``; camera rays start in
    the sensor's medium, as in ``mi.render``.  Only C++ sampling integrators (``path``,
    ``volpath``, ``direct``, ``aov`` with a nested integrator, ...) are supported: light
    tracing (``ptracer``) is refused.  A scene without emitters warns (it renders black).
    Ray differentials are scaled by ``1/sqrt(counts[i, j])``, as ``mi.render`` does for a
    uniform count (this only changes filtered bitmap texture look-ups).

    Examples
    --------
    >>> r = MitsubaRenderer("cornell-box", width=32, height=32)
    >>> stats = r.render(np.full((32, 32), 16), seed=1)
    >>> int(stats.n.sum()), stats.mean.shape
    (16384, (32, 32, 3))
    """

    channels = 3

    def __init__(self, scene, *, width: int | None = None, height: int | None = None,
                 variant: str | None = None, chunk_samples: int = 2 ** 21, params=None,
                 sensor: int = 0):
        self.chunk_samples = _check_int("chunk_samples", chunk_samples, minimum=1)
        params = _check_params(params)
        self.params = dict(params)
        self.sensor = _check_int("sensor", sensor, minimum=0)
        if self.chunk_samples > 2 ** 31:
            raise InputError(f"`chunk_samples` must be <= 2**31; got {chunk_samples}.")
        if width is not None:
            width = _check_size("width", width, 0)
        if height is not None:
            height = _check_size("height", height, 0)
        mi, self.variant = setup_mitsuba(variant)
        self._mi = mi
        import drjit as dr
        self._dr = dr
        self._jit = not self.variant.startswith("scalar")

        xml = (isinstance(scene, (str, os.PathLike)) and os.fspath(scene) not in BUILTIN_SCENES)
        if params and not xml:
            raise InputError("`params` gives values to the $name parameters of an XML scene "
                             "file; this `scene` is not one, so leave `params` unset.")
        if hasattr(scene, "sensors") and hasattr(scene, "integrator"):
            if width is not None or height is not None:
                raise InputError("`width`/`height` cannot be changed for an already loaded "
                                 "`scene`; set them in the scene description.")
            self._scene, self.name = scene, "custom"
        elif isinstance(scene, (str, os.PathLike)):
            key = os.fspath(scene)
            if isinstance(key, str) and key in BUILTIN_SCENES:
                self._scene = mi.load_dict(load_scene_dict(key, width, height))
                self.name = key
            else:
                path = Path(key)
                if not path.is_file():
                    raise InputError(
                        f"`scene` must be a built-in Mitsuba scene name "
                        f"({', '.join(sorted(BUILTIN_SCENES))}) or the path of an existing "
                        f"Mitsuba XML file; got {key!r}, which is neither.")
                self._scene = _load_xml(mi, path, width, height, False, params, sensor)
                sensors = self._scene.sensors()
                if (not self._jit and sensor < len(sensors)
                        and not _scalar_ready(sensors[sensor].film())):
                    # the scalar fallback reads one-sample mi.render images: needs a box
                    # filter and R, G, B first
                    _warn_filter(sensors[sensor].film(), str(path))
                    self._scene = _load_xml(mi, path, width, height, True, params, sensor)
                self.name = str(path)
        else:
            raise InputError(f"`scene` must be a scene name, an XML path or a mitsuba.Scene; "
                             f"got {type(scene).__name__}.")

        n_sensors = len(self._scene.sensors())
        if not n_sensors:
            raise InputError(f"scene {self.name!r} has no sensor.")
        if sensor >= n_sensors:
            raise _no_such_sensor(sensor, n_sensors, f"scene {self.name!r}")
        self._sensor = self._scene.sensors()[sensor]
        # not used (the counts passed to render are), kept to tell users so
        self.scene_sample_count = int(self._sensor.sampler().sample_count())
        film = self._sensor.film()
        self.width, self.height = (int(v) for v in film.crop_size())
        self._integrator = self._scene.integrator()
        _check_integrator(mi, self._integrator, self.name)
        if self._jit:
            _warn_filter(film, self.name)
        elif not _scalar_ready(film):
            raise InputError(f"the {self.variant!r} fallback renders through mi.render, so the "
                             "film of an already loaded `scene` needs a box filter and an RGB "
                             "pixel_format; load it with <rfilter type=\"box\"/> and "
                             "pixel_format 'rgb', or pass the XML file's path.")
        if not self._scene.emitters() and self._integrator.class_name() != "DepthIntegrator":
            warnings.warn(f"statmc: scene {self.name!r} has no emitter, so every pixel renders "
                          "black; add one (e.g. <emitter type=\"constant\"/>).",
                          RuntimeWarning, stacklevel=2)
        self._aov_integrator = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal"})
        self._sampler = mi.load_dict({"type": "independent"})
        self._warned_nonfinite = False
        self.nonfinite_samples = 0

    def __repr__(self) -> str:
        return (f"MitsubaRenderer({self.name!r}, width={self.width}, height={self.height}, "
                f"variant={self.variant!r})")

    # ------------------------------------------------------------------ public
    def render(self, counts, *, seed: int = 0, progress: bool = False, features: bool = True,
               feature_spp: int = 16, cross: bool = True, first_sample=None) -> PixelStats:
        """Render exactly ``counts[i, j]`` samples in pixel ``(i, j)``.

        Parameters
        ----------
        counts : (H, W) array of non-negative integers
            Samples per pixel; zeros allowed.
        seed : int, optional
            Seed of the random numbers; different seeds give independent renders.  Sample
            ``j`` of pixel ``p`` depends on ``(seed, p, j)`` only, so two renders with the
            same seed share the first ``min`` of their counts in every pixel.
        progress : bool, optional
            Show a tqdm progress bar over the chunks.
        features : bool, optional
            Also render ``albedo`` and ``normal`` buffers, ``(H, W, 3)``, in a separate pass
            of ``feature_spp`` samples per pixel (Mitsuba's ``aov`` integrator, shading
            normals in world space), so they do not slow down the main pass.
        feature_spp : int, optional
        cross : bool, optional
            Also accumulate the channel cross sums (default), so the result carries the
            channel co-moment ``m2_cross`` (``sample_cov``, ``mean_cov``); ``False`` skips
            them (``m2_cross`` is None).
        first_sample : (H, W) array of non-negative integers, optional
            Index of the first sample of each pixel in its sequence (default 0): a pass
            that continues an earlier one with the same seed passes the counts rendered so
            far, and the two passes merged equal one render of the summed counts (up to
            the order of the float64 sums).  ``counts + first_sample`` must stay below
            2**31.

        Returns
        -------
        PixelStats
            ``n == counts``; ``mean``, ``m2`` and (with ``cross``) ``m2_cross`` (float64)
            of the RGB samples; ``meta``
            holds ``seconds``, ``samples``, ``samples_per_second`` (main pass),
            ``feature_seconds``, ``variant``, ``scene``, ``seed``, ``chunks`` and
            ``nonfinite_samples`` (NaN/Inf samples, counted as zeros; the first render
            that meets any warns).
        """
        counts = self._check_counts(counts)
        first = self._check_first(first_sample, counts)
        _warn_if_words_wrap(first, counts)
        seed = _check_int("seed", seed, minimum=0)
        feature_spp = _check_int("feature_spp", feature_spp, minimum=1)
        _check_flags(progress=progress, features=features, cross=cross)
        if self._mi.variant() != self.variant:
            self._mi.set_variant(self.variant)
        render = self._render_jit if self._jit else self._render_scalar
        t0 = time.perf_counter()
        s1, s2, sxy, n_bad, n_chunks = render(counts, first, seed, progress, bool(cross))
        seconds = time.perf_counter() - t0
        stats = PixelStats.from_sums(counts, s1, s2, sxy)
        total = int(counts.sum())
        self._warn_nonfinite(n_bad, total)
        stats.meta.update({
            "renderer": "mitsuba", "scene": self.name, "sensor": self.sensor,
            "variant": self.variant, "seed": seed,
            "samples": total, "seconds": seconds,
            "samples_per_second": total / seconds if seconds > 0 else float("nan"),
            "chunks": n_chunks, "nonfinite_samples": n_bad,
        })
        if features:
            t0 = time.perf_counter()
            albedo, normal = self._render_features(seed, feature_spp)
            stats.albedo, stats.normal = albedo, normal
            stats.meta["feature_seconds"] = time.perf_counter() - t0
            stats.meta["feature_spp"] = feature_spp
        return stats

    def render_uniform(self, spp: int, *, seed: int = 0, progress: bool = False,
                       features: bool = True, feature_spp: int = 16,
                       cross: bool = True) -> PixelStats:
        """:meth:`render` with ``spp`` samples in every pixel."""
        spp = _check_int("spp", spp, minimum=0)
        return self.render(np.full((self.height, self.width), spp, np.int64), seed=seed,
                           progress=progress, features=features, feature_spp=feature_spp,
                           cross=cross)

    def render_crn(self, spp: int, *, seed: int = 0, stencil: int = 5, progress: bool = False,
                   features: bool = True, feature_spp: int = 16):
        """A common-random-number (CRN) render and the covariance of its neighbouring pixels.

        Sample ``j`` of every pixel uses the same random sequence ``j`` (one sampler stream
        shared by all pixels: the same sub-pixel jitter, lens position and path decisions,
        until paths part ways), and the ``spp`` sequences are independent.  Each pixel is
        still an unbiased estimate with independent samples, but the errors of
        neighbouring pixels are positively correlated: a *correlated* estimate ``z`` in
        the sense of Back et al. 2020 (§1, §3: correlated pixel estimates such as CRN
        renders), to combine with an independent render ``y`` by
        :func:`statmc.combine.statistical_weights` and :func:`statmc.combine.combine`.

        Parameters
        ----------
        spp : int
            Samples in every pixel (>= 1; >= 2 for a variance).
        seed : int, optional
            Seed; a CRN render is independent of :meth:`render` with the same seed.
        stencil : int, optional
            Odd width ``m`` of the neighbourhood whose covariances are returned.
        progress, features, feature_spp
            As in :meth:`render`.

        Returns
        -------
        stats : PixelStats
            Per-pixel statistics as :meth:`render` (``meta["crn"] = True``).
        cov_z : (H, W, m, m, 3) float64 ndarray
            Covariance of the pixel means, ``cov_z[p, R + v] = cov(z_p, z_{p+v})``
            (``R = m // 2``; the convention of :func:`statmc.combine.combine_bias_variance`),
            estimated without bias from the ``spp`` paired samples:
            ``Σ_j (x_pj − z_p)(x_qj − z_q) / ((spp − 1) spp)``; 0 outside the image and
            where ``spp < 2``.  The centre ``cov_z[p, R, R]`` equals ``stats.mean_var``.

        Notes
        -----
        Needs a JIT variant (``llvm_ad_rgb``): the scalar fallback renders through
        ``mi.render``, which seeds every pixel differently.  Costs ``spp`` wavefronts of
        ``H·W`` samples; the sums are kept in NumPy, the neighbour products formed by the
        compiled kernel of :mod:`statmc._stencil_kernels`.  Memory: two ``(H, W, m, m, 3)``
        float64 arrays; more than :data:`CRN_MAX_BYTES` is refused (at 1920x1080, m <= 5).
        """
        spp = _check_int("spp", spp, minimum=1)
        seed = _check_int("seed", seed, minimum=0)
        feature_spp = _check_int("feature_spp", feature_spp, minimum=1)
        _check_flags(progress=progress, features=features)
        m = _check_int("stencil", stencil, minimum=1)
        if m % 2 == 0:
            raise InputError(f"`stencil` must be an odd width; got {stencil}.")
        need = 2 * self.height * self.width * m * m * 3 * 8      # products + covariance
        if need > CRN_MAX_BYTES:
            raise InputError(f"a {m}x{m} covariance stencil at {self.width}x{self.height} needs "
                             f"{need / 2 ** 30:.1f} GiB (limit {CRN_MAX_BYTES / 2 ** 30:.0f} GiB); "
                             f"use a smaller `stencil`.")
        if not self._jit:
            raise InputError(f"common-random-number renders need a JIT Mitsuba variant "
                             f"(llvm_ad_rgb); this renderer runs {self.variant!r} ({_LLVM_HINT}).")
        if self._mi.variant() != self.variant:
            self._mi.set_variant(self.variant)
        from ._stencil_kernels import add_neighbour_products

        mi = self._mi
        H, W, R = self.height, self.width, m // 2
        pix = np.arange(H * W, dtype=np.uint32)
        s1 = np.zeros((H, W, 3))
        s2 = np.zeros((H, W, 3, 3))
        prod = np.zeros((H, W, m, m, 3))
        n_bad = 0
        t0 = time.perf_counter()
        with _progress(spp * H * W, progress, f"mitsuba {self.name} (CRN)") as bar:
            for j in range(spp):
                _, L, _ = self._trace(self._integrator, pix, _chunk_seed(seed, _SALT_CRN, j),
                                      mi.Float(1.0 / math.sqrt(spp)), shared=True)
                x = np.stack([np.asarray(L[c], np.float64) for c in range(3)], -1).reshape(H, W, 3)
                ok = np.isfinite(x).all(-1, keepdims=True)
                n_bad += int((~ok).sum())
                x = np.where(ok, x, 0.0)
                s1 += x
                s2 += x[..., :, None] * x[..., None, :]
                x = np.ascontiguousarray(x)
                add_neighbour_products(prod, x, x, R)
                bar.update(H * W)
        seconds = time.perf_counter() - t0
        self._warn_nonfinite(n_bad, spp * H * W)
        counts = np.full((H, W), spp, np.int64)
        stats = PixelStats.from_sums(counts, s1, np.einsum("hwcc->hwc", s2), s2)
        stats.meta.update({
            "renderer": "mitsuba", "scene": self.name, "sensor": self.sensor,
            "variant": self.variant, "seed": seed,
            "samples": spp * H * W, "seconds": seconds, "crn": True,
            "samples_per_second": spp * H * W / seconds if seconds > 0 else float("nan"),
            "chunks": spp, "nonfinite_samples": n_bad,
        })
        if features:
            t0 = time.perf_counter()
            stats.albedo, stats.normal = self._render_features(seed, feature_spp)
            stats.meta["feature_seconds"] = time.perf_counter() - t0
            stats.meta["feature_spp"] = feature_spp
        # in place: peak memory stays at the two arrays counted above (prod and a gather)
        cov = prod
        if spp >= 2:
            mean = s1 / spp
            nb = _neighbours(mean, R)
            nb *= spp * mean[:, :, None, None, :]
            cov -= nb
            del nb
            cov /= (spp - 1) * spp          # 0 outside the image: prod and nb are 0 there
            cov[:, :, R, R] = stats.mean_var                  # the centre: M2 clipped at 0
        else:
            cov.fill(0.0)
        return stats, cov

    # ------------------------------------------------------------------ internals
    def _warn_nonfinite(self, n_bad: int, total: int) -> None:
        """Count a render's NaN/Inf samples (counted as zeros) in :attr:`nonfinite_samples`
        and warn, once per renderer, when there are any."""
        self.nonfinite_samples += n_bad
        if n_bad and not self._warned_nonfinite:
            self._warned_nonfinite = True
            warnings.warn(f"statmc: {n_bad} of {total} samples of scene {self.name!r} were NaN "
                          "or Inf and were counted as zeros, which biases their pixels; check "
                          "the scene (an infinite radiance, a degenerate shape).  Later renders "
                          "count them in meta['nonfinite_samples'] without warning again.",
                          RuntimeWarning, stacklevel=3)

    def _whole_map(self, name: str, value, whole: str) -> np.ndarray:
        """An (H, W) float map of whole numbers >= 0 (``whole`` names what they count)."""
        a = as_float_array(name, value, ndim=2)
        if a.shape != (self.height, self.width):
            raise InputError(f"`{name}` must have the image shape (H, W) = "
                             f"{(self.height, self.width)}; got {a.shape}.")
        check_finite(name, a)
        check_nonnegative(name, a)
        if np.any(a != np.floor(a)):
            raise InputError(f"`{name}` must hold {whole}; got fractional values.")
        return a

    def _check_counts(self, counts) -> np.ndarray:
        return self._whole_map("counts", counts, "whole numbers of samples").astype(np.int64)

    def _check_first(self, first_sample, counts) -> np.ndarray:
        if first_sample is None:
            # the bound first_sample + counts had; without first_sample, 2**40 samples per
            # pixel were not refused and the render ran for hours
            if counts.size and int(counts.max()) >= 2 ** 31:
                raise InputError(f"`counts` must stay below 2**31 samples per pixel; got max "
                                 f"{int(counts.max())}.")
            return np.zeros_like(counts)
        a = self._whole_map("first_sample", first_sample, "whole sample indices")
        if np.any(a + counts >= 2 ** 31):
            raise InputError(f"`first_sample + counts` must stay below 2**31 samples per pixel; "
                             f"got max {int((a + counts).max())}.")
        return a.astype(np.int64)

    def _reduce_mode(self, arrays: int):
        dr = self._dr
        if self.variant.startswith("llvm"):
            # Expand: one private copy of the accumulators per thread, no atomics
            nbytes = self.width * self.height * dr.thread_count() * 8 * arrays
            if nbytes <= 2 ** 30:
                return dr.ReduceMode.Expand
        return dr.ReduceMode.Auto

    def _trace(self, integrator, pix: np.ndarray, seed, diff_scale, shared: bool = False):
        """Trace one wavefront: samples in pixels ``pix``; returns (idx, L, aovs).

        ``seed``: an int seeds the wavefront's sampler (Mitsuba derives one stream per
        lane from it and the lane's index); a callable ``seed(idx)`` returning a
        ``UInt32`` array gives every lane its own stream, independent of its position in
        the wavefront (:func:`_sample_seeds`).
        ``shared`` (with an int): one random stream for the whole wavefront (a sampler
        seeded for a wavefront of 1, broadcast to every lane): common random numbers.
        """
        mi, dr = self._mi, self._dr
        sensor, sampler = self._sensor, self._sampler
        idx = mi.UInt32(pix)
        if callable(seed):
            # per-lane seeds and a wavefront of 1: lane i's stream is TEA(seed(idx)[i], 0)
            sampler.seed(seed(idx), 1)
        else:
            sampler.seed(dr.opaque(mi.UInt32, seed), 1 if shared else int(pix.size))
        y = idx // self.width
        x = idx - y * self.width
        jitter = sampler.next_2d()
        # film-relative position in [0, 1]^2, as in mi.render
        pos = mi.Point2f((mi.Float(x) + jitter.x) * (1.0 / self.width),
                         (mi.Float(y) + jitter.y) * (1.0 / self.height))
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        t = sensor.shutter_open()
        if sensor.shutter_open_time() > 0:
            t = t + sampler.next_1d() * sensor.shutter_open_time()
        ray, weight = sensor.sample_ray_differential(t, 0.0, pos, aperture)
        if callable(diff_scale):
            diff_scale = diff_scale(idx)
        ray.scale_differential(diff_scale)
        # the medium the sensor sits in, as mi.render passes it (None: in vacuum)
        L, _valid, aovs = integrator.sample(self._scene, sampler, ray, sensor.get_medium(), True)
        return idx, L * weight, aovs

    def _render_jit(self, counts: np.ndarray, first: np.ndarray, seed: int, progress: bool,
                    cross: bool):
        mi, dr = self._mi, self._dr
        hw = self.height * self.width
        flat = counts.ravel()
        # per-sample seeds fmix32(base[p] + g·P) ^ k2 (_sample_seeds), formed inside the
        # traced kernel (forming them in NumPy cost about 12 % of the render's time)
        k1, k2 = _seed_keys(seed, _SALT_MAIN)
        base = mi.UInt32(_seed_bases(k1, flat, first.ravel()))
        s1 = [dr.zeros(mi.Float64, hw) for _ in range(3)]
        s2 = [dr.zeros(mi.Float64, hw) for _ in range(3)]
        s3 = [dr.zeros(mi.Float64, hw) for _ in _PAIRS] if cross else []
        bad = dr.zeros(mi.UInt32, hw)
        mode = self._reduce_mode(6 + len(s3))
        rsqrt_n = mi.Float(1.0 / np.sqrt(np.maximum(flat, 1)).astype(np.float32))

        def scale(idx):
            return dr.gather(mi.Float, rsqrt_n, idx)

        n_chunks = 0
        with _progress(int(flat.sum()), progress, f"mitsuba {self.name}") as bar:
            pos = 0                     # position of the chunk's first sample in the render
            for pix in _chunk_pixels(flat, self.chunk_samples):
                def seeds(idx, pos=pos, size=pix.size):
                    g = (dr.arange(mi.UInt32, size) + mi.UInt32(pos % (1 << 32))) * mi.UInt32(hw)
                    word = dr.gather(mi.UInt32, base, idx) + g
                    return _fmix32_drjit(mi, word) ^ mi.UInt32(k2)
                idx, L, _ = self._trace(self._integrator, pix, seeds, scale)
                pos += pix.size
                ok = dr.isfinite(L.x) & dr.isfinite(L.y) & dr.isfinite(L.z)
                vs = [mi.Float64(dr.select(ok, L[c], 0.0)) for c in range(3)]
                for c, v in enumerate(vs):
                    dr.scatter_reduce(dr.ReduceOp.Add, s1[c], v, idx, mode=mode)
                    dr.scatter_reduce(dr.ReduceOp.Add, s2[c], v * v, idx, mode=mode)
                for acc, (a, b) in zip(s3, _PAIRS):
                    dr.scatter_reduce(dr.ReduceOp.Add, acc, vs[a] * vs[b], idx, mode=mode)
                dr.scatter_reduce(dr.ReduceOp.Add, bad, mi.UInt32(1), idx, active=~ok,
                                  mode=dr.ReduceMode.Direct)
                dr.eval(s1, s2, s3, bad)
                _release_chunk(dr)
                n_chunks += 1
                bar.update(int(pix.size))
        shape = (self.height, self.width, 3)
        sum_x = np.stack([np.asarray(a) for a in s1], axis=-1).reshape(shape)
        sum_x2 = np.stack([np.asarray(a) for a in s2], axis=-1).reshape(shape)
        sum_xy = (np.stack([np.asarray(a) for a in s3], axis=-1).reshape(shape) if cross
                  else None)
        return sum_x, sum_x2, sum_xy, int(np.asarray(bad).sum()), n_chunks

    def _render_scalar(self, counts: np.ndarray, first: np.ndarray, seed: int, progress: bool,
                       cross: bool):
        """Fallback: one-sample passes of ``mi.render`` (box filter), pass ``j`` giving
        sample ``j`` of every pixel whose sequence ``[first, first + counts)`` holds it:
        ``max(first + counts) - min(first)`` passes."""
        mi = self._mi
        shape = (self.height, self.width, 3)
        s1, s2, s3 = np.zeros(shape), np.zeros(shape), np.zeros(shape)
        n_bad = 0
        live = counts > 0
        j0 = int(first[live].min()) if live.any() else 0
        j1 = int((first + counts)[live].max()) if live.any() else 0
        passes = j1 - j0
        with _progress(passes, progress, f"mitsuba {self.name} (scalar)", "pass") as bar:
            for k in range(j0, j1):
                img = np.asarray(mi.render(self._scene, sensor=self._sensor, spp=1,
                                           seed=_chunk_seed(seed, _SALT_MAIN, k)), np.float64)
                img = img[..., :3]
                active = ((first <= k) & (k < first + counts))[..., None]
                ok = np.isfinite(img)
                n_bad += int((~ok.all(axis=-1) & active[..., 0]).sum())
                img = np.where(ok & active, img, 0.0)
                s1 += img
                s2 += img * img
                if cross:
                    for p, (a, b) in enumerate(_PAIRS):
                        s3[..., p] += img[..., a] * img[..., b]
                bar.update(1)
        return s1, s2, (s3 if cross else None), n_bad, passes

    def _render_features(self, seed: int, spp: int):
        """Albedo and shading normal, ``spp`` samples per pixel, averaged (box filter)."""
        mi, dr = self._mi, self._dr
        if not self._jit:
            img = np.asarray(mi.render(self._scene, sensor=self._sensor,
                                       integrator=self._aov_integrator, spp=spp,
                                       seed=_chunk_seed(seed, _SALT_FEATURES, 0)), np.float32)
            img = np.where(np.isfinite(img), img, 0.0)
            return img[..., :3].copy(), img[..., 3:6].copy()
        hw = self.height * self.width
        acc = [dr.zeros(mi.Float, hw) for _ in range(6)]
        mode = self._reduce_mode(6)
        flat = np.full(hw, spp, np.int64)
        for k, pix in enumerate(_chunk_pixels(flat, self.chunk_samples)):
            idx, _, aovs = self._trace(self._aov_integrator, pix,
                                       _chunk_seed(seed, _SALT_FEATURES, k), 1.0 / math.sqrt(spp))
            for c in range(6):
                v = aovs[c]
                dr.scatter_reduce(dr.ReduceOp.Add, acc[c], dr.select(dr.isfinite(v), v, 0.0),
                                  idx, mode=mode)
            dr.eval(acc)
            _release_chunk(dr)
        out = np.stack([np.asarray(a) for a in acc], axis=-1).reshape(self.height, self.width, 6)
        out = (out / spp).astype(np.float32)
        return out[..., :3].copy(), out[..., 3:6].copy()


def _release_chunk(dr) -> None:
    """Hand the memory of a finished chunk back (``drjit.flush_malloc_cache``).

    Without it Dr.Jit's allocation cache kept about 8 MB per 2**21-sample chunk until the
    render ended: a 32x32 cornell-box at 32768 spp (16 chunks) peaked at 280 MB of
    resident memory instead of 168 MB, 131072 spp at 691 MB, and a long render filled the
    machine's memory and then took minutes to exit while the cache was freed.  The flush
    costs nothing measurable next to a chunk's tracing (20.6 / 20.4 s CPU without it,
    20.7 / 20.1 s with it, 32x32 at 16384 spp).
    """
    dr.flush_malloc_cache()


def _neighbours(a: np.ndarray, R: int) -> np.ndarray:
    """``out[y, x, R + dy, R + dx] = a[y + dy, x + dx]`` (0 outside), ``(H, W, m, m, C)``."""
    from ._stencil_kernels import shift_slices

    H, W = a.shape[:2]
    m = 2 * R + 1
    out = np.zeros((H, W, m, m) + a.shape[2:], a.dtype)
    for dy in range(-R, R + 1):
        for dx in range(-R, R + 1):
            dst, src = shift_slices(H, W, dy, dx)
            out[dst + (R + dy, R + dx)] = a[src]
    return out


class _NoBar:
    def update(self, n):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _progress(total: int, show: bool, desc: str, unit: str = "sample"):
    if not show:
        return _NoBar()
    from tqdm.auto import tqdm
    return tqdm(total=total, desc=desc, unit=unit, unit_scale=unit == "sample", leave=False)
