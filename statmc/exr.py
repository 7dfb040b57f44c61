"""OpenEXR files in pbrt-v4's gbuffer-film layout, read and written safely.

The channel layout (``docs/file-format.md`` has the full table):

=====================================  ==============================================
``R, G, B``                            mean radiance of the pixel
``Variance.R, Variance.G, Variance.B`` **sample variance** ``M2/(n-1)`` of *one* sample
``SampleCount``                        samples in the pixel (statmc; pbrt-v4 omits it)
``Covariance.RG, .RB, .GB``            **sample covariance** ``M2_ab/(n-1)`` of *one* sample
                                       between two channels (statmc; optional)
``Albedo.R, Albedo.G, Albedo.B``       albedo feature
``N.X, N.Y, N.Z``                      normal feature
``Z`` (else pbrt-v4's ``P.Z``)         depth feature
``Y``, ``Variance.Y``                  one-channel images instead of ``R, G, B``
=====================================  ==============================================

pbrt-v4's ``gbuffer`` film writes exactly these names (plus ``P.*``, ``dzdx``, ``dzdy``,
``Ns.*``, ``u``, ``v`` and ``RelativeVariance.*``, which are kept as extra channels), so
its output loads directly with :func:`read_exr`; since it stores no ``SampleCount``,
pass the render's uniform ``spp``.

Arrays hold the file's data window (a crop or an overscan region as stored);
:func:`exr_windows` says where it lies, and ``write_exr(..., data_window=, display_window=)``
writes a result back in the same place (a ``PixelStats`` from :func:`read_exr` is written back
where its ``meta`` says, with its ``chromaticities``, unless these arguments are given).

Every failure to read raises :class:`~statmc.errors.FileFormatError` naming the file.
Writes are atomic (temporary file beside the target, then ``os.replace``) and refuse
to overwrite any path listed in ``protect``.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterable, Mapping
import numbers
import os
import re
import sys
import tempfile
import threading

import numpy as np

from .errors import (FileFormatError, InputError, as_bool, as_float_array, as_int,
                     check_finite, real_or_nan)
from .stats import PixelStats

_INT64_MAX = int(np.iinfo(np.int64).max)

__all__ = ["read_exr", "read_image", "read_channels", "exr_info", "exr_windows", "write_exr",
           "write_png_preview", "to_display", "SAMPLE_COUNT", "spatial_covariance_channels",
           "read_spatial_covariance", "SPATIAL_COVARIANCE", "bin_channels", "read_bins", "BIN",
           "capturing_openexr_output"]

SAMPLE_COUNT = "SampleCount"
_RGB = ("R", "G", "B")
_ALBEDO = ("Albedo.R", "Albedo.G", "Albedo.B")
_NORMAL = ("N.X", "N.Y", "N.Z")
_COV = ("Covariance.RG", "Covariance.RB", "Covariance.GB")   # pairs a < b of R, G, B, row-major
_DEPTH = ("Z", "P.Z")            # preference order: our own ``Z``, then pbrt-v4's camera-space P.Z
_MAX_F32_COUNT = 2 ** 24         # integers above this are not all representable in float32
_TONEMAPS = ("srgb", "reinhard", "aces")
#: Prefix of the neighbour-covariance channels ``SpatialCovariance.<dy><dx>.<R|G|B>``.
SPATIAL_COVARIANCE = "SpatialCovariance"
# A neighbour-covariance channel name (read_spatial_covariance, statmc.cli): groups 1, 2
# the offset dy, dx (signed), 3 the colour channel.
_SPATIAL_CHANNEL = re.compile(rf"^{SPATIAL_COVARIANCE}\.([+-]\d+)([+-]\d+)\.([RGB])$")
#: Prefix of the sample-bin channels ``Bin<b>.<C>`` and ``Bin<b>.Denoised.<C>``.
BIN = "Bin"
# A sample-bin channel name, the one definition of the pattern (read_bins, statmc.cli):
# groups 1 the bin number, 2 "Denoised." or None, 3 the colour channel R, G or B.
_BIN_CHANNEL = re.compile(rf"^{BIN}(\d+)\.(Denoised\.)?([RGB])$")


# ---------------------------------------------------------------------------- reading
def _name(path) -> str:
    if isinstance(path, (bytes, bytearray)):
        return path.decode()
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"`path` must be a file path (a str or os.PathLike); got "
                         f"{type(path).__name__} {path!r}.")
    return os.fspath(path)


_EXR_MAGIC = b"\x76\x2f\x31\x01"
_OTHER_FORMATS = ((b"\x89PNG\r\n\x1a\n", "PNG"), (b"\xff\xd8\xff", "JPEG"),
                  (b"#?RADIANCE", "Radiance HDR"), (b"#?RGBE", "Radiance HDR"),
                  (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"), (b"\x93NUMPY", "NumPy .npy"),
                  (b"PK\x03\x04", "ZIP (e.g. .npz)"))


def format_of(head: bytes):
    """The name of the file format whose magic number ``head`` (a file's first bytes)
    starts with: ``"OpenEXR"``, ``"PNG"``, ``"JPEG"``, ... or None when none is known."""
    if head.startswith(_EXR_MAGIC):
        return "OpenEXR"
    return next((name for sig, name in _OTHER_FORMATS if head.startswith(sig)), None)


def _check_magic(p: str) -> None:
    """Refuse an empty file or one without OpenEXR's magic number, naming what it is."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError as e:
        raise FileFormatError(f"cannot read EXR file {p!r}: {e.strerror}.") from None
    if not head:
        raise FileFormatError(f"{p!r} is not a readable OpenEXR file: it is empty (0 bytes).")
    if not head.startswith(_EXR_MAGIC):
        kind = format_of(head)
        what = f"a {kind} file" if kind else "another format"
        raise FileFormatError(f"{p!r} is not a readable OpenEXR file: it is {what} (it does not "
                              "start with OpenEXR's magic number 76 2f 31 01).")


def _flush_c_stdio() -> None:
    """Flush C's stdio buffers (fully buffered when not a terminal)."""
    import ctypes
    with contextlib.suppress(Exception):
        ctypes.CDLL(None).fflush(None)


#: One capture at a time: file descriptors 1 and 2 and ``sys.stdout``/``sys.stderr`` are
#: process-wide, so overlapping captures from threads restored each other's redirections
#: and left them on a deleted temporary file (all later output of the process lost).
_CAPTURE_LOCK = threading.Lock()
#: Whether reads capture OpenEXR's console output (:func:`capturing_openexr_output`).
_capture = False


@contextlib.contextmanager
def capturing_openexr_output():
    """Within this block, reads capture what OpenEXR prints about a corrupt file (a warning
    on ``sys.stdout``, errors on file descriptor 2) and put its diagnosis in the
    :class:`FileFormatError` instead.  The capture redirects the process's stdout and
    stderr while OpenEXR runs, so only the command line, a single-threaded program that
    prints nothing meanwhile, turns it on; library reads leave them alone (OpenEXR's lines
    then reach the console and the error says the file is corrupt)."""
    global _capture
    before, _capture = _capture, True
    try:
        yield
    finally:
        _capture = before


#: OpenEXR's worker threads wanted by :func:`using_io_threads` (0: leave OpenEXR's setting).
_io_threads = 0


def _cpu_count() -> int:
    """The CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def using_io_threads(threads=None):
    """Within this block, EXR files are decoded and encoded by OpenEXR's thread pool of
    ``threads`` workers (default: the CPUs this process may use) instead of OpenEXR's
    default of none (the calling thread alone); the pool's size is restored after it.
    The command line turns it on: at 1920x1080 on 2 CPUs it took a 15-channel ZIP file's
    decoding from 2.8 to 1.2 s.  Pixels and bytes written are the same (ZIP compresses
    each block of 16 scanlines on its own, and the blocks are written in order)."""
    global _io_threads
    if threads is not None:
        threads = as_int("threads", threads, lo=0)
    before, _io_threads = _io_threads, _cpu_count() if threads is None else threads
    try:
        yield
    finally:
        _io_threads = before
        exr = sys.modules.get("OpenEXR")
        if exr is not None and exr.global_thread_count() != before:
            exr.set_global_thread_count(before)


def _import_openexr():
    """``import OpenEXR``, with the thread pool :func:`using_io_threads` asks for."""
    import OpenEXR

    if _io_threads and OpenEXR.global_thread_count() != _io_threads:
        OpenEXR.set_global_thread_count(_io_threads)
    return OpenEXR


@contextlib.contextmanager
def _captured_c_output():
    """Collect what is written to ``sys.stdout``/``sys.stderr`` and to file descriptors
    1 and 2 meanwhile, as one string appended to the yielded list: OpenEXR prints its
    diagnosis of a corrupt file there (a warning on ``sys.stdout``, the core library's
    errors on fd 2), around the one-line error of the command."""
    said = []
    saved = {}
    try:
        for s in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                s.flush()
        _flush_c_stdio()
        for fd in (1, 2):
            saved[fd] = os.dup(fd)
    except OSError:                          # no usable descriptor: capture nothing
        for d in saved.values():
            os.close(d)
        yield said
        return
    py = io.StringIO()                       # the binding's warning goes to sys.stdout
    try:
        with tempfile.TemporaryFile() as tmp:
            for fd in saved:
                os.dup2(tmp.fileno(), fd)
            try:
                with contextlib.redirect_stdout(py), contextlib.redirect_stderr(py):
                    yield said
            finally:
                _flush_c_stdio()
                for fd, d in saved.items():
                    os.dup2(d, fd)
                tmp.seek(0)
                said.append(py.getvalue() + tmp.read().decode("utf-8", "replace"))
    finally:
        for d in saved.values():
            os.close(d)


def _openexr_diagnosis(p: str, text: str) -> str:
    """OpenEXR's first error line in ``text`` (the file name prefix removed), or "".
    Other text it printed is passed on to stderr."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    errors = [ln for ln in lines if "EXR_ERR" in ln or ln.startswith("Warning: Exception")]
    if not errors:
        if text:
            sys.stderr.write(text)
        return ""
    first = next((ln for ln in errors if "EXR_ERR" in ln), errors[0])
    return first.split(": ", 1)[1] if first.startswith(p + ": ") else first


#: The hint of a multi-part file's missing-channel error (the command line names --part).
_PART_HINT = "pass part=INDEX or part='NAME' to read another"


def _part_label(q) -> str:
    """``"part 1 ('variance')"`` (``"part 0"`` for an unnamed part) of a :func:`_parts_summary` entry."""
    return f"part {q['part']}" + (f" ({q['name']!r})" if q["name"] else "")


class _Channels(dict):
    """``{name: (H, W) array}`` of the part read (``read_part``, its index) and of the parts
    read with it (``merged``, :func:`_companions`), with ``parts``: ``{"part", "name",
    "channels"}`` of every part of the file (:func:`_parts_summary`), and ``left``:
    ``{index: why}`` of the other parts, whose channels were not read."""
    parts: list = []
    read_part: int = 0
    merged: tuple = ()
    left: dict = {}
    layer: str | None = None      # the layer these channels were selected from (names inside it)

    def sharing(self, items=()) -> "_Channels":
        """``items`` as channels of the same file read: this one's ``parts``, ``read_part``,
        ``merged`` and ``left`` (``layer`` is the caller's to set)."""
        out = _Channels(items)
        out.parts, out.read_part = self.parts, self.read_part
        out.merged, out.left = self.merged, self.left
        return out

    @property
    def note(self) -> str:
        """``" (only part 0 ('beauty') of this 2-part file is read; part 1 ('variance'):
        [...], not read with it (data window [1, 1, 3, 2], not [0, 0, 2, 1])) — pass
        part=INDEX or part='NAME' to read another"``, appended to the channel list of a
        missing-channel error; "" when no part was left unread."""
        if len(self.parts) < 2 or not self.left:
            return ""
        label = {q["part"]: q for q in self.parts}
        read = _part_label(label[self.read_part])
        if self.merged:
            read += ", with " + ", ".join(_part_label(label[i]) for i in self.merged) + ","
        rest = "; ".join(f"{_part_label(label[i])}: {label[i]['channels']}, not read with "
                         f"it ({why})" for i, why in sorted(self.left.items()))
        return (f" (only {read} of this {len(self.parts)}-part file is read; {rest}) — "
                f"{_PART_HINT}")


def _companions(headers: list, index: int) -> tuple[dict, dict]:
    """The channels other parts add to part ``index`` of a file (``headers``: each part's
    header, with its ``channels`` list), and why the others add none.

    A part is read with part ``index`` when the two are one image split into parts (as
    Nuke writes a layer per part, and OpenEXR suggests for reading a subset of channels
    quickly): it is flat, has the same data window and the same ``view`` (or none), and no
    channel name is held twice among part ``index`` and these parts.  A part that repeats
    names (a second render with its own ``R, G, B``, a stereo file's other view) is another
    image and adds nothing; and then the window holds more than one image, so which one the
    other such parts belong to is not known: none is read with it either.  Returns
    ``({name: part}, {part: why not read})``."""
    def names(h):
        return [str(c.name) for c in h.get("channels", ())]
    base = headers[index]
    window = _windows(base)[0]
    same, left = [], {}
    for j, h in enumerate(headers):
        if j == index:
            continue
        if "deep" in str(h.get("type", "")):
            left[j] = "a deep part"
        elif _windows(h)[0] != window:
            left[j] = f"data window {_windows(h)[0]}, not {window}"
        elif h.get("view") != base.get("view"):
            left[j] = f"view {h.get('view')!r}, not {base.get('view')!r}"
        elif any(c.xSampling != 1 or c.ySampling != 1 for c in h.get("channels", ())):
            left[j] = "subsampled channels"
        else:
            same.append(j)
    held: dict[str, int] = {}
    for j in [index, *same]:
        for n in names(headers[j]):
            held[n] = held.get(n, 0) + 1
    repeats = [j for j in same if any(held[n] > 1 for n in names(headers[j]))]
    take = {}
    for j in same:
        if j in repeats:
            left[j] = "channel names also in another part: another image"
        elif repeats:
            left[j] = (f"part {', '.join(map(str, repeats))} of this window repeat"
                       f"{'s' if len(repeats) == 1 else ''} channel names, so it holds more "
                       "than one image and which one this part belongs to is not known")
        else:
            take.update(dict.fromkeys(names(headers[j]), j))
    return take, left


def _check_part(part):
    """``part`` as given to the readers: an index >= 0 or a part's name."""
    if isinstance(part, (bool, np.bool_)) or not (
            (isinstance(part, (int, np.integer)) and part >= 0) or (isinstance(part, str) and part)):
        raise InputError(f"`part` must be a part's index (0, 1, ...) or its name; got {part!r}.")
    return int(part) if not isinstance(part, str) else part


def _part_index(parts: list, part):
    """The index of ``part`` (an index or a name) among ``parts`` (:func:`_parts_summary`), or
    None when the file has no such part."""
    if isinstance(part, str):
        return next((q["part"] for q in parts if q["name"] == part), None)
    return part if part < len(parts) else None


def _no_part(p: str, parts: list, part) -> FileFormatError:
    """The error of a ``part`` the file ``p`` does not have, naming the parts it has."""
    which = f"part named {part!r}" if isinstance(part, str) else f"part {part}"
    listed = ", ".join(_part_label(q) for q in parts)
    return FileFormatError(f"{p!r} has no {which}; it has {len(parts)} part"
                           f"{'' if len(parts) == 1 else 's'}: {listed} (`part` takes an index "
                           "from 0 or a part's name).")


def _parts_summary(f) -> list:
    """``[{"part": i, "name": name or None, "channels": sorted names}]`` of an open file."""
    out = []
    with contextlib.suppress(Exception):
        for i, q in enumerate(f.parts):
            name = None
            with contextlib.suppress(Exception):
                name = q.name() or None
            out.append({"part": i, "name": name,
                        "channels": sorted(str(c.name) for c in q.header.get("channels", ()))})
    return out


#: OpenEXR's lossy compressions (PXR24 rounds float32 to 24 bits; B44/B44A are lossy for
#: half channels; DWAA/DWAB quantise the DCT of colour-named channels such as ``*.R``).
_LOSSY = ("PXR24", "B44", "B44A", "DWAA", "DWAB")


def _compression_name(header) -> str:
    """The header's compression as OpenEXR names it: ``"ZIP_COMPRESSION"``."""
    return str(header.get("compression", "")).rsplit(".", 1)[-1].split(":")[0]


def _compression(header) -> str:
    """The header's compression without ``_COMPRESSION``: ``"ZIP"``."""
    name = _compression_name(header)
    return name[:-len("_COMPRESSION")] if name.endswith("_COMPRESSION") else name


def _present(arrays) -> str:
    """The channel list of a missing-channel error, with what other parts hold."""
    return f"{sorted(arrays)}{getattr(arrays, 'note', '')}"


def _windows(header) -> tuple[list, list]:
    """``(data_window, display_window)`` of a header, each ``[x0, y0, x1, y1]`` (inclusive)."""
    def box(w):
        (x0, y0), (x1, y1) = (np.asarray(v).tolist() for v in w)
        return [int(x0), int(y0), int(x1), int(y1)]
    data = box(header["dataWindow"])
    return data, box(header.get("displayWindow", header["dataWindow"]))


def _header_spp(header):
    """pbrt-v4's ``samplesPerPixel`` header attribute (the uniform count of the render it
    wrote, partial images included), or None when absent or not a whole number >= 0 (a
    float such as 64.0 is taken)."""
    v = header.get("samplesPerPixel")
    if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
        if np.isfinite(v) and v >= 0 and v == int(v):
            return int(v)
    return None


def _no_header_spp(header) -> str:
    """``"no samplesPerPixel header attribute"``, or what is wrong with the file's."""
    if "samplesPerPixel" in header:
        return (f"its samplesPerPixel header attribute, {header['samplesPerPixel']!r}, is not "
                "a whole number >= 0")
    return "no samplesPerPixel header attribute"


def _chromaticities(header):
    """The ``chromaticities`` attribute as 8 floats (red, green, blue, white x, y), or None."""
    v = header.get("chromaticities")
    with contextlib.suppress(TypeError, ValueError):
        c = tuple(float(x) for x in v)
        if len(c) == 8 and all(np.isfinite(c)):
            return c
    return None


#: OpenEXR's default primaries and white point (Rec. 709/sRGB, D65): what a file without a
#: ``chromaticities`` attribute is in.
_REC709 = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def _same_colour_space(a, b) -> bool:
    """Whether two ``chromaticities`` (8 floats or None, which is Rec. 709) are the same
    primaries and white point: within 1e-3 in x and y, which takes D65 written as
    (0.3127, 0.3290) or (0.31271, 0.32902) alike, while the spaces in use differ by more
    (Rec. 709, P3, Rec. 2020 and ACES primaries by > 0.01, D60 from D65 by 0.009)."""
    return bool(np.allclose(a or _REC709, b or _REC709, rtol=0, atol=1e-3))


def _describe_colour_space(c) -> str:
    """``"the chromaticities (0.713, 0.293, ...)"`` or ``"none (Rec. 709/sRGB)"``."""
    if c is None:
        return "none (Rec. 709/sRGB)"
    return "the chromaticities (" + ", ".join(f"{v:.4g}" for v in c) + ")"


def _header_summary(path, part=0) -> dict:
    """What an output takes from an input, from the header only: ``data_window``,
    ``display_window``, ``chromaticities`` and the ``channels`` names of ``part``."""
    header, _, _ = _open(path, header_only=True, part=part)
    data, display = _windows(header)
    return {"data_window": data, "display_window": display,
            "chromaticities": _chromaticities(header),
            "channels": sorted(str(c.name) for c in header.get("channels", ()))}


def exr_windows(path, *, part=0) -> tuple[list, list]:
    """The data window and display window of an EXR file (its ``part``, an index or a
    name: part 0 unless given), each
    ``[x0, y0, x1, y1]`` with inclusive corners as OpenEXR stores them, read from the header
    only.  Pixel ``(i, j)`` of an array read by :func:`read_exr` or :func:`read_image` is
    pixel ``(x0 + j, y0 + i)`` of the image; pass the windows to :func:`write_exr` to write
    a result in the same place (``statmc reconstruct``, ``denoise``, ``progressive`` and
    ``combine`` do)."""
    info = _header_summary(path, part)
    return info["data_window"], info["display_window"]


# Files already read, by path, that _open takes instead of reading them again (this thread,
# inside _reading_once blocks only).
_OPENED = threading.local()


@contextlib.contextmanager
def _reading_once(path, opened=None, part=0):
    """Inside the block, every :func:`_open` of ``path`` in this thread (``read_exr``,
    ``read_channels``, ...) takes one decoding of the file per ``part`` asked for:
    ``opened`` (an :func:`_open` result of ``part``), or else the block's first read of it.
    Nothing is kept after the block."""
    p = _name(path)
    before = getattr(_OPENED, "files", {})
    _OPENED.files = {**before, p: {} if opened is None else {part: opened}}
    try:
        yield
    finally:
        _OPENED.files = before


def _open(path, *, header_only: bool = False, part=0):
    """Read one part of an EXR file (``part``, an index or a name; checked):
    ``(header dict, {name: (H, W) array}, {name: type})`` (the arrays and types empty with
    ``header_only``).  The header's ``_parts`` is the file's number of parts, ``_part`` the
    index read."""
    p = _name(path)
    part = _check_part(part)
    files = getattr(_OPENED, "files", {})
    if p not in files or header_only:
        return _decode(p, header_only, part)
    if part not in files[p]:
        files[p][part] = _decode(p, False, part)
    header, arrays, types = files[p][part]
    return dict(header), arrays.sharing(arrays), dict(types)


def _decode(p: str, header_only: bool, part=0):
    """:func:`_open` of the file ``p``, read from disk."""
    OpenEXR = _import_openexr()

    if not os.path.exists(p):
        raise FileFormatError(f"EXR file {p!r} does not exist.")
    if os.path.isdir(p):
        raise FileFormatError(f"{p!r} is a directory, not an EXR file.")
    _check_magic(p)
    err = None
    capture = _capture
    with (_CAPTURE_LOCK if capture else contextlib.nullcontext()), \
            (_captured_c_output() if capture else contextlib.nullcontext([])) as said:
        try:
            f = OpenEXR.File(p, separate_channels=True, header_only=header_only)
            n_parts = len(f.parts)
            parts = _parts_summary(f)
            index = _part_index(parts, part) if part else 0
            header = f.header(index or 0)
            take, left = ({}, {}) if index is None else \
                _companions([q.header for q in f.parts], index)
            chans = {} if header_only or index is None else dict(f.channels(index))
            if not header_only:
                for name, j in take.items():
                    chans[name] = f.parts[j].channels[name]
        except Exception as e:  # OpenEXR raises RuntimeError / ValueError for bad files
            err = e
    # OpenEXR reports a corrupt chunk on stdout and stderr (three lines) and then drops the
    # part, so the exception only says "file has 0 parts": give its own diagnosis instead
    # (when captured), or say what "0 parts" means.
    diag = _openexr_diagnosis(p, said[0] if said else "")
    if err is not None and not diag and "0 parts" in str(err):
        diag = ("OpenEXR could not decode its image part (a corrupt or truncated chunk; "
                "OpenEXR printed its diagnosis above)")
    if err is not None or diag:
        raise FileFormatError(f"{p!r} is not a readable OpenEXR file (corrupt, truncated or "
                              f"another format): {diag or err}") from None
    if index is None:
        raise _no_part(p, parts, part)
    storage = str(header.get("type", ""))
    if "deep" in storage:
        raise FileFormatError(f"{p!r} is a deep EXR ({storage}); only flat images are supported.")
    (x0, y0), (x1, y1) = (np.asarray(v) for v in header["dataWindow"])
    hw = (int(y1) - int(y0) + 1, int(x1) - int(x0) + 1)
    arrays, types = _Channels(), {}
    arrays.parts, arrays.read_part = parts, index
    arrays.merged, arrays.left = tuple(sorted(set(take.values()))), left
    for name, ch in chans.items():
        px = np.asarray(ch.pixels)
        if ch.xSampling != 1 or ch.ySampling != 1 or px.shape != hw:
            raise FileFormatError(
                f"{p!r}: channel {name!r} has size {px.shape} (sampling {ch.xSampling}x"
                f"{ch.ySampling}) but the image is {hw[0]}x{hw[1]} (H x W); channels of "
                "inconsistent sizes (subsampled channels) are not supported.")
        # own the data beyond the File object (the binding's arrays own theirs: no copy)
        arrays[name] = px if px.flags.owndata and px.base is None else np.array(px, copy=True)
        types[name] = str(ch.type()).rsplit(".", 1)[-1].lower()
    header = dict(header)
    header["_parts"], header["_part"] = n_parts, index
    header["_merged"] = arrays.merged
    if take:                                          # the channels of the image, all parts
        header["channels"] = list(header.get("channels", ())) + [
            c for j in arrays.merged for c in f.parts[j].header.get("channels", ())
            if take.get(str(c.name)) == j]
    return header, arrays, types


def _group(p, arrays, names, what):
    """Stack channels ``names`` as (H, W, k) float64, None when all are absent."""
    present = [n for n in names if n in arrays]
    if not present:
        return None
    if len(present) != len(names):
        missing = [n for n in names if n not in arrays]
        raise FileFormatError(f"{p!r} has only part of the {what} channels: missing {missing}; "
                              f"channels present: {_present(arrays)}.")
    first = arrays[names[0]]
    out = np.empty(first.shape + (len(names),), np.float64)   # one pass per channel, no
    for k, n in enumerate(names):                              # float64 copy before the stack
        out[..., k] = arrays[n]
    return out


def _color_names(p, arrays):
    if any(n in arrays for n in _RGB):
        if not all(n in arrays for n in _RGB):
            missing = [n for n in _RGB if n not in arrays]
            raise FileFormatError(f"{p!r} lacks colour channel(s) {missing}; expected R, G, B "
                                  f"(or Y). Channels present: {_present(arrays)}.")
        return _RGB
    if "Y" in arrays:
        return ("Y",)
    inside = getattr(arrays, "layer", None)
    where = "" if inside is None else f" in layer {inside!r}"
    raise FileFormatError(f"{p!r} has no colour channels R, G, B (or Y){where}; channels "
                          f"present{' there' if inside else ''}: {_present(arrays)}."
                          f"{_colour_hint(arrays, inside)}")


# Layers whose R, G, B are statmc's or pbrt-v4's own channels, not an image's colour.
_NOT_COLOUR_LAYERS = ("variance", "relativevariance", "albedo", "covariance")
# Last names of the layer that holds a renderer's beauty image (Blender: Combined).
_BEAUTY_LAYERS = ("combined", "beauty", "rgba", "rgb", "color", "colour")


def _colour_hint(arrays, inside=None) -> str:
    """What a file without ``R, G, B`` holds instead: a layer's ``<layer>.R/G/B`` (Blender's
    ``ViewLayer.Combined.R``, a ``diffuse.R`` pass) or lowercase ``r, g, b``; "" if neither.
    ``inside``: the layer ``arrays`` were selected from (their names are inside it); the
    layers are then named in full (``ViewLayer`` + ``Combined``)."""
    import shlex

    # the beauty first (Blender's Combined), then by name
    layers = sorted({n[:-2] for n in arrays if n[-2:] in (".R", ".G", ".B")
                     and all(n[:-2] + "." + c in arrays for c in _RGB)
                     and n[:-2].rsplit(".", 1)[-1].lower() not in _NOT_COLOUR_LAYERS
                     and not _BIN_CHANNEL.match(n)},
                    key=lambda x: (x.rsplit(".", 1)[-1].lower() not in _BEAUTY_LAYERS, x))
    if inside is not None:
        layers = [f"{inside}.{x}" for x in layers]
    if layers:
        which = ", ".join(repr(x) for x in layers[:4]) + (", ..." if len(layers) > 4 else "")
        first = layers[0]
        ch = shlex.quote(",".join(f"{c}={first}.{c}" for c in _RGB))
        return (f" R, G, B are only inside layer(s) {which} (e.g. {first + '.R'!r}): "
                "statmc reads the unprefixed R, G, B (pbrt-v4's layout); write the layer's "
                f"channels as R, G, B (e.g. `oiiotool IN.exr --ch {ch} -o OUT.exr`), or, in "
                f"Python, read them with statmc.exr.read_exr/read_image(path, layer={first!r}).")
    lower = [c for c in ("r", "g", "b") if c in arrays]
    if len(lower) == 3:
        return (" The file has lowercase r, g, b: EXR channel names are case-sensitive and "
                "statmc reads R, G, B; rename them.")
    return ""


def _count_nonfinite(a) -> tuple[int, int]:
    if a is None or not np.issubdtype(a.dtype, np.floating):
        return 0, 0
    finite = np.isfinite(a)
    if finite.all():            # the usual case: one scan, not two and two sums
        return 0, 0
    n_nan = int(np.isnan(a).sum())
    return n_nan, int(a.size - np.count_nonzero(finite)) - n_nan


def _check_policy(nonfinite, replace_value):
    if nonfinite not in ("error", "replace"):
        raise InputError(f"`nonfinite` must be 'error' or 'replace'; got {nonfinite!r}.")
    if not np.isfinite(real_or_nan(replace_value)):
        raise InputError(f"`replace_value` must be a finite number; got {replace_value!r}.")


def _handle_nonfinite(p, groups: dict, nonfinite, replace_value, half=()):
    """Count NaN/Inf per channel group; raise or replace in place. Returns counts.
    ``half``: the groups stored as half floats, whose Inf is most likely an overflow."""
    counts = {}
    for key, a in groups.items():
        n_nan, n_inf = _count_nonfinite(a)
        if n_nan or n_inf:
            counts[key] = {"nan": n_nan, "inf": n_inf}
    if counts and nonfinite == "error":
        detail = "; ".join(f"{k}: {v['nan']} NaN, {v['inf']} Inf" for k, v in counts.items())
        over = [k for k, v in counts.items() if v["inf"] and k in half]
        why = (f" (the Inf of {', '.join(over)} is likely an overflow: half floats end at "
               "65504, and pbrt-v4 writes half floats, clamping R, G, B but not Variance, "
               "unless its film has \"bool savefp16\" false)" if over else "")
        raise FileFormatError(f"{p!r} holds non-finite values ({detail}){why}; pass "
                              "nonfinite='replace' to replace them by `replace_value`.")
    for key in counts:
        a = groups[key]
        a[~np.isfinite(a)] = replace_value
    return counts


def _select_layer(p, arrays, types, layer):
    """The channels of ``layer`` (``"ViewLayer.Combined"``) under their names inside it
    (``"ViewLayer.Combined.R"`` → ``"R"``); others are left out."""
    if layer is None:
        return arrays, types
    if not isinstance(layer, str) or not layer or layer.endswith("."):
        raise InputError(f"`layer` must be a layer name such as 'ViewLayer.Combined' (without "
                         f"the channel's last part); got {layer!r}.")
    prefix = layer + "."
    out, kinds = arrays.sharing(), {}
    out.layer = layer
    for name, a in arrays.items():
        if name.startswith(prefix) and len(name) > len(prefix):
            out[name[len(prefix):]] = a
            kinds[name[len(prefix):]] = types[name]
    if not out:
        layers = sorted({n.rsplit(".", 1)[0] for n in arrays if "." in n})
        raise FileFormatError(f"{p!r} has no channels in layer {layer!r} (named "
                              f"'{prefix}<channel>'); its layers: {layers}{arrays.note}.")
    return out, kinds


# Feature layers of other tools that read_exr takes as albedo and normal (when the file has
# no Albedo.* / N.* of its own): kind -> (channel suffixes, statmc's own channels, last names
# of the layers recognised, case-sensitive).  Blender (Cycles) writes its denoising data
# passes as '<view layer>.Denoising Albedo.R/G/B' and '<view layer>.Denoising Normal.X/Y/Z';
# Mitsuba 3's aov integrator names a layer by the user's AOV name ('albedo:albedo' writes
# albedo.R/G/B, 'sh_normal:sh_normal' sh_normal.X/Y/Z; checked with Mitsuba 3.9.1).
# Blender's plain 'Normal' pass and Mitsuba names such as 'nn' are not guessed at: pass
# normal='ViewLayer.Normal' or normal='nn'.
_FEATURE_KINDS = {
    "albedo": (("R", "G", "B"), _ALBEDO, ("Denoising Albedo", "albedo")),
    "normal": (("X", "Y", "Z"), _NORMAL, ("Denoising Normal", "normal", "normals", "sh_normal")),
}


def _parent(layer) -> str:
    """The layer that holds ``layer`` (``"ViewLayer"`` of ``"ViewLayer.Combined"``; "" at
    the top level or for None)."""
    return layer.rsplit(".", 1)[0] if layer and "." in layer else ""


def _feature_candidates(arrays, kind: str, parent=None) -> list:
    """The layers of ``arrays`` recognised as feature ``kind`` (all three channels present,
    a last name of :data:`_FEATURE_KINDS`), in ``parent`` only unless None; sorted."""
    comps, _, names = _FEATURE_KINDS[kind]
    found = set()
    for n in arrays:
        if n.endswith("." + comps[0]):
            layer = n[:-len(comps[0]) - 1]
            if (layer.rsplit(".", 1)[-1] in names and (parent is None or _parent(layer) == parent)
                    and all(f"{layer}.{c}" in arrays for c in comps)):
                found.add(layer)
    return sorted(found)


def _feature_channels(p, arrays, layer, kind: str, choice):
    """``(channel names, layer)`` of feature ``kind`` (``"albedo"`` or ``"normal"``) among the
    channels ``arrays`` of the part read (prefixes and all): ``choice`` a layer's name, its
    ``.R/.G/.B`` (a normal's ``.X/.Y/.Z``, else ``.R/.G/.B``); None statmc's own ``Albedo.*``
    / ``N.*`` (inside ``layer`` if given), else the one layer of another tool recognised
    beside ``layer`` (:data:`_FEATURE_KINDS`; two are refused); False statmc's own only.
    The layer is None when the file has no such feature (the names are then absent)."""
    comps, own, _ = _FEATURE_KINDS[kind]
    prefix = "" if layer is None else layer + "."
    own_names = tuple(prefix + n for n in own)
    own_layer = prefix + own[0].rsplit(".", 1)[0]
    if choice is None or choice is False:
        if choice is False or any(n in arrays for n in own_names):
            return own_names, (own_layer if any(n in arrays for n in own_names) else None)
        found = _feature_candidates(arrays, kind, _parent(layer))
        if len(found) > 1:
            raise FileFormatError(
                f"{p!r} has {len(found)} layers statmc would read as the {kind}: {found}; it "
                f"does not choose between them: pass {kind}='NAME' (one of them) to read that "
                "one.")
        if not found:
            return own_names, None
        return tuple(f"{found[0]}.{c}" for c in comps), found[0]
    if not isinstance(choice, str) or not choice or choice.endswith("."):
        raise InputError(f"`{kind}` must be the name of the layer holding the {kind} (such as "
                         f"'ViewLayer.Denoising {kind.capitalize()}'; None: recognised, False: "
                         f"statmc's own {own[0].rsplit('.', 1)[0]}.* only); got {choice!r}.")
    for cs in ((comps, ("R", "G", "B")) if kind == "normal" else (comps,)):
        names = tuple(f"{choice}.{c}" for c in cs)
        if all(n in arrays for n in names):
            return names, choice
    want = "', '".join(f"{choice}.{c}" for c in comps)
    layers = sorted({n.rsplit(".", 1)[0] for n in arrays if "." in n
                     and n.rsplit(".", 1)[1] in comps})
    raise FileFormatError(f"{p!r} has no {kind} layer {choice!r} (channels '{want}'"
                          f"{' or .R, .G, .B' if kind == 'normal' else ''}); layers with "
                          f"{', '.join(comps)} channels: {layers}{getattr(arrays, 'note', '')}.")


def read_exr(path, *, spp=None, layer=None, part=0, albedo=None, normal=None,
             require_variance: bool = True,
             nonfinite: str = "error", replace_value: float = 0.0,
             spp_if_missing: bool = False, covariance: bool = True) -> PixelStats:
    """Read per-pixel statistics from an EXR file in pbrt-v4's gbuffer layout.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    spp : int or (H, W) array of int, optional
        Samples per pixel, needed when the file has neither a ``SampleCount`` channel nor
        pbrt-v4's ``samplesPerPixel`` header attribute (which pbrt-v4 writes: its files
        load without ``spp``).  When the file has either, ``spp`` must agree with it or be
        omitted (or ``spp_if_missing`` be set).
    layer : str, optional
        Read the channels of this layer as if they had no prefix: ``layer="ViewLayer.Combined"``
        reads Blender's ``ViewLayer.Combined.R`` as ``R`` (and a layer's ``Variance.R``,
        ``SampleCount``, ...); channels outside the layer are left out.
    part : int or str, default 0
        The part of a multi-part file to read: its index (from 0) or its name (Nuke writes
        one part per layer).  The parts that are the same image split up are read with it:
        flat parts of the same data window and ``view`` whose channel names no other such
        part repeats (``meta["merged_parts"]``).  A part the file does not have raises
        :class:`FileFormatError` naming the parts it has.
    albedo, normal : str, None or False, optional
        Where the albedo and normal features (OIDN's auxiliary images) come from.  A string
        names a layer: ``albedo="ViewLayer.Denoising Albedo"`` reads its ``.R, .G, .B``,
        ``normal="nn"`` its ``.X, .Y, .Z`` (or ``.R, .G, .B``); the name is the whole
        channel prefix, whatever ``layer`` is.  None (the default) takes statmc's (and
        pbrt-v4's) own ``Albedo.*`` and ``N.*`` (inside ``layer``), else the one layer of
        another tool recognised beside the colour: Blender's denoising data passes
        ``<view layer>.Denoising Albedo`` / ``Denoising Normal`` (with
        ``layer="ViewLayer.Combined"``, those of ``ViewLayer``), or the top-level AOV layers
        ``albedo`` and ``normal``, ``normals`` or ``sh_normal`` of Mitsuba 3's ``aov``
        integrator; two such layers raise :class:`FileFormatError` listing them.  False
        reads statmc's own channels only.  Values are passed through as stored (OIDN takes
        normals in any consistent space).
    require_variance : bool, default True
        Raise when the ``Variance.*`` channels are missing.  With ``False`` a file without
        them is read with zero spread (``M2 = 0``); ``meta["has_variance"]`` says so.
    nonfinite : {"error", "replace"}, default "error"
        NaN/Inf pixels raise :class:`FileFormatError` with counts per channel group, or
        are replaced by ``replace_value`` and counted in ``meta["nonfinite_replaced"]``.
    replace_value : float, default 0.0
        Replacement for non-finite values.
    spp_if_missing : bool, default False
        Use ``spp`` only for a file with neither ``SampleCount`` nor ``samplesPerPixel``; a
        file with either keeps its own counts (e.g. the second input of a command whose
        ``--spp`` is for the first).
    covariance : bool, default True
        Build the channel co-moment ``m2_cross`` from the ``Covariance.*`` channels.  With
        ``False`` it is left None (``n``, ``mean``, ``m2``, the features and ``meta`` are the
        same): a caller that never reads the channel covariance saves its ``(H, W, 3, 3)``
        float64 matrix (143 MiB at 1920x1080) and its construction.  The channels are still
        checked as with ``True`` (all three or none, NaN/Inf, ``Variance.*`` beside them).

    Returns
    -------
    PixelStats
        ``n`` from ``SampleCount`` (or ``spp``); ``mean`` from ``R, G, B`` (or ``Y``);
        ``M2 = Variance · (n − 1)`` since ``Variance.*`` holds the *sample* variance;
        with ``Covariance.RG/RB/GB`` (sample covariances, statmc's extension) also the
        channel co-moment ``m2_cross = Covariance · (n − 1)``, else ``m2_cross`` is None;
        albedo, normal and depth when present.  ``meta`` holds ``source``, ``channels``,
        ``extra_channels`` (present but unused), ``has_variance``, ``has_covariance``,
        ``data_window`` and ``display_window`` (``[x0, y0, x1, y1]``: where the pixels lie
        in the frame, :func:`exr_windows`), ``depth_channel``,
        ``chromaticities`` (the header's 8 primaries and white point x, y, or None),
        ``layer``, ``part`` (the index of the part read), ``merged_parts`` (the indices of
        the parts read with it as one image, see ``part``), ``albedo_layer`` and
        ``normal_layer`` (the layer the feature came from, e.g. ``"Albedo"`` or
        ``"ViewLayer.Denoising Albedo"``, or None),
        ``sample_count_source`` (``"file"``: the channel, ``"header"``: the
        ``samplesPerPixel`` attribute, or ``"spp"``), ``nonfinite_replaced`` and
        ``nonfinite_by_group``.

    Raises
    ------
    FileFormatError
        Missing or unreadable file; missing colour, variance (unless allowed) or partial
        feature channels; inconsistent channel sizes; no ``SampleCount``, no
        ``samplesPerPixel`` attribute and no ``spp``;
        NaN/Inf (with ``nonfinite="error"``); negative variance; negative or fractional
        sample counts.

    Notes
    -----
    Pixels with ``n < 2`` keep no spread (``M2 = 0``); pbrt-v4 writes variance 0 there.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> s = PixelStats.from_mean_var(np.ones((2, 3, 3)), np.full((2, 3, 3), 0.25),
    ...                              np.full((2, 3), 4))
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_exr(os.path.join(d, "a.exr"), s)
    ...     t = read_exr(os.path.join(d, "a.exr"))
    >>> float(t.sample_var[0, 0, 0]), int(t.n[0, 0])
    (0.25, 4)
    """
    p = _name(path)
    _check_policy(nonfinite, replace_value)
    for flag, value in (("covariance", covariance), ("require_variance", require_variance),
                        ("spp_if_missing", spp_if_missing)):
        as_bool(flag, value)
    header, arrays, types = _open(p, part=part)
    whole, whole_types = arrays, types
    arrays, types = _select_layer(p, arrays, types, layer)
    color = _color_names(p, arrays)
    albedo_names, albedo_layer = _feature_channels(p, whole, layer, "albedo", albedo)
    normal_names, normal_layer = _feature_channels(p, whole, layer, "normal", normal)
    mean = _group(p, arrays, color, "colour")
    var_names = tuple("Variance." + c for c in color)
    var = _group(p, arrays, var_names, "variance")
    if var is None and require_variance:
        raise FileFormatError(
            f"{p!r} has no {', '.join(var_names)} channels (the sample variance per sample, "
            f"as pbrt-v4's gbuffer film writes). Channels present: {_present(arrays)}. Pass "
            "require_variance=False to read it with zero variance, or use read_image().")
    cov = _group(p, arrays, _COV, "covariance") if color == _RGB else None
    has_cov = cov is not None
    if cov is not None and var is None:
        raise FileFormatError(f"{p!r} has Covariance channels but no {', '.join(var_names)}: a "
                              "channel covariance needs the variances on its diagonal.")
    albedo = _group(p, whole, albedo_names, "albedo")
    normal = _group(p, whole, normal_names, "normal")
    depth_name = next((d for d in _DEPTH if d in arrays), None)
    depth = arrays[depth_name].astype(np.float64) if depth_name else None
    count = arrays[SAMPLE_COUNT].astype(np.float64) if SAMPLE_COUNT in arrays else None
    header_spp = _header_spp(header)
    if count is None and spp is None and header_spp is None:
        raise FileFormatError(
            f"{p!r} has no {SAMPLE_COUNT} channel and {_no_header_spp(header)}, so the "
            f"samples per pixel are unknown: pass the render's uniform spp=. Channels present: "
            f"{_present(arrays)}.")

    groups = {"+".join(color): mean, "Variance": var, "Covariance": cov, "Albedo": albedo,
              "N": normal,
              depth_name or "Z": depth, SAMPLE_COUNT: count}
    groups = {k: v for k, v in groups.items() if v is not None}
    members = {"+".join(color): color, "Variance": var_names, "Covariance": _COV,
               depth_name or "Z": (depth_name,), SAMPLE_COUNT: (SAMPLE_COUNT,)}
    half = {k for k in groups if k in members and all(types.get(c) == "half" for c in members[k])}
    half |= {k for k, names in (("Albedo", albedo_names), ("N", normal_names))
             if k in groups and all(whole_types.get(c) == "half" for c in names)}
    by_group = _handle_nonfinite(p, groups, nonfinite, replace_value, half)
    if not covariance:                 # checked above, not kept
        groups.pop("Covariance", None)
        cov = None

    if var is not None and var.size and var.min() < 0:
        comp = _compression(header)
        why = (f" The file is {comp}-compressed, a lossy codec whose errors turn small "
               "variances negative (and change the others): write statistics with a lossless "
               "compression (ZIP, PIZ, ZIPS, RLE, NONE)." if comp in _LOSSY else "")
        raise FileFormatError(f"{p!r}: Variance channels hold {int((var < 0).sum())} negative "
                              f"values (min {var.min():.4g}); a variance is >= 0.{why}")
    if count is not None:
        _check_counts(p, count)
        if spp is not None and not spp_if_missing:
            want = np.broadcast_to(_spp_map(spp, count.shape), count.shape)
            if np.any(want != count):
                raise InputError(f"`spp` disagrees with the {SAMPLE_COUNT} channel of {p!r} in "
                                 f"{int((want != count).sum())} pixels; omit spp= to use the file's counts.")
        n, source = count, "file"
    elif header_spp is not None:
        if spp is not None and not spp_if_missing:
            want = _spp_map(spp, mean.shape[:2])
            if np.any(want != header_spp):
                raise InputError(f"`spp` disagrees with the samplesPerPixel header attribute "
                                 f"of {p!r}, {header_spp} (the count pbrt-v4 rendered); omit "
                                 "spp= to use the file's counts.")
        n, source = np.full(mean.shape[:2], float(header_spp)), "header"
    else:
        n, source = _spp_map(spp, mean.shape[:2]), "spp"
    if var is None:
        var = np.zeros_like(mean)
    stats = PixelStats.from_mean_var(mean, var, n, sample_cov=cov, albedo=albedo, normal=normal,
                                     depth=depth)
    data_window, display_window = _windows(header)
    # another tool's feature channels read from the layer's own channels (a top-level
    # albedo.R of Mitsuba beside R, G, B) are not extra channels
    prefix = "" if layer is None else layer + "."
    features_read = {n[len(prefix):] for names, got in ((albedo_names, albedo_layer),
                                                        (normal_names, normal_layer))
                     if got is not None for n in names if n.startswith(prefix)}
    stats.meta.update({
        "source": p, "channels": sorted(arrays),
        "extra_channels": sorted(set(arrays) - set(color) - set(var_names) - set(_ALBEDO)
                                 - set(_NORMAL) - {depth_name, SAMPLE_COUNT}
                                 - (set(_COV) if has_cov else set()) - features_read),
        "has_variance": bool(all(v in arrays for v in var_names)),
        "has_covariance": has_cov,
        "data_window": data_window, "display_window": display_window,
        "chromaticities": _chromaticities(header), "layer": layer, "part": header["_part"],
        "merged_parts": list(header["_merged"]),
        "albedo_layer": albedo_layer, "normal_layer": normal_layer,
        "depth_channel": depth_name, "sample_count_source": source,
        "nonfinite_replaced": int(sum(v["nan"] + v["inf"] for v in by_group.values())),
        "nonfinite_by_group": by_group,
    })
    return stats


def _check_counts(p, count):
    if count.size and count.min() < 0:
        raise FileFormatError(f"{p!r}: {SAMPLE_COUNT} holds {int((count < 0).sum())} negative "
                              f"values (min {count.min():.4g}); sample counts are >= 0.")
    frac = count != np.round(count)
    if frac.any():
        raise FileFormatError(f"{p!r}: {SAMPLE_COUNT} holds {int(frac.sum())} non-integer values "
                              f"(e.g. {count[frac].flat[0]:.6g}); sample counts are whole numbers.")


def _spp_map(spp, hw, name="spp"):
    """``spp`` (a count, or an ``(H, W)`` map of counts) as an ``(H, W)`` int64 count map.

    Integers are taken exactly (not through float64, which rounds counts above 2**53: 2**63 - 1
    became 2**63 and was refused), whole-valued floats converted; the accepted range is that
    of :class:`~statmc.stats.PixelStats`' int64 counts, 0 to 2**63 - 1."""
    def refuse(what):
        return InputError(f"`{name}` must be a whole number of samples per pixel from 0 to "
                          f"2**63 - 1, or a {tuple(hw)} map of them; got {what}.")
    if isinstance(spp, numbers.Integral) and not isinstance(spp, (bool, np.bool_)):
        if not 0 <= int(spp) <= _INT64_MAX:          # NumPy would hold a larger one as an object
            raise refuse(spp)
        spp = int(spp)
    a = np.asarray(spp)
    if a.dtype.kind not in "iuf":                    # bool, complex, timedelta, str, object
        raise refuse(f"{spp!r}" if a.ndim == 0 else f"an array of dtype {a.dtype}")
    if a.ndim not in (0, 2) or (a.ndim == 2 and a.shape != tuple(hw)):
        raise refuse(f"shape {a.shape}")
    if a.dtype.kind == "u":
        bad = a > _INT64_MAX
    elif a.dtype.kind == "i":
        bad = a < 0
    else:
        af = a.astype(np.float64)
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(af) | (af < 0) | (af != np.round(af)) | (af >= 2.0 ** 63)
    if np.any(bad):
        raise refuse(f"{spp!r}" if a.ndim == 0 else
                     f"a map with {int(np.sum(bad))} other values (e.g. {a[bad].flat[0]})")
    return np.broadcast_to(a.astype(np.int64), tuple(hw))


def read_image(path, *, layer=None, part=0, nonfinite: str = "error",
               replace_value: float = 0.0) -> np.ndarray:
    """Read the colour of an EXR file as an ``(H, W, 3)`` (or ``(H, W, 1)`` for ``Y``) float32 array.

    For plain images such as references; variance and counts are ignored.  ``layer``
    (``"ViewLayer.Combined"``) reads that layer's ``R, G, B``, ``part`` (an index or a name)
    that part of a multi-part file; NaN/Inf follow ``nonfinite`` as in :func:`read_exr`.
    """
    p = _name(path)
    _check_policy(nonfinite, replace_value)
    _, arrays, types = _open(p, part=part)
    arrays, types = _select_layer(p, arrays, types, layer)
    color = _color_names(p, arrays)
    img = np.stack([arrays[c].astype(np.float32) for c in color], axis=-1)
    key = "+".join(color)
    _handle_nonfinite(p, {key: img}, nonfinite, replace_value,
                      {key} if all(types[c] == "half" for c in color) else ())
    return img


def read_channels(path, names=None, *, part=0) -> dict:
    """Raw channels of an EXR file: ``{name: (H, W) array}`` (all, or those in ``names``) of
    its ``part`` (an index or a name; part 0 unless given).

    Values are returned as stored (float16/float32/uint32), NaN/Inf included.
    """
    p = _name(path)
    _, arrays, _ = _open(p, part=part)
    if names is None:
        return arrays
    names = [names] if isinstance(names, str) else names
    if not isinstance(names, Iterable) or not all(isinstance(n, str) for n in names):
        raise InputError(f"`names` must be a channel name or a list of them; got {names!r}.")
    names = list(names)
    missing = [n for n in names if n not in arrays]
    if missing:
        raise FileFormatError(f"{p!r} lacks channel(s) {missing}; channels present: {_present(arrays)}.")
    return {n: arrays[n] for n in names}


def _group_of(name: str) -> str:
    if name in _RGB:
        return "R+G+B"
    return name.rsplit(".", 1)[0] if "." in name else name


# Channel families that `statmc info` summarises instead of listing one group per member:
# the family's group name -> the family's channel pattern.
_INFO_FAMILIES = {
    "SpatialCovariance.<dy><dx>": "SpatialCovariance.<dy><dx>.<R|G|B>",
    "Bin<b>": "Bin<b>.<R|G|B>",
    "Bin<b>.Denoised": "Bin<b>.Denoised.<R|G|B>",
}


def _info_family(name: str):
    """``(group, match)`` of a channel in one of :data:`_INFO_FAMILIES` (``match.group(1)``
    the bin number, or with ``group(2)`` the stencil offset dy, dx), else None."""
    mt = _SPATIAL_CHANNEL.match(name)
    if mt:
        return "SpatialCovariance.<dy><dx>", mt
    mt = _BIN_CHANNEL.match(name)
    if mt:
        return ("Bin<b>.Denoised" if mt.group(2) else "Bin<b>"), mt
    return None


def _summarise_families(info: dict) -> dict:
    """:func:`exr_info`'s summary with the channel families of statmc's extensions — the
    covariance stencil of ``render --crn`` (3·m² channels) and sample bins — collapsed to
    one entry each, and named in ``layout``: ``covariance`` (``Covariance.RG/RB/GB``),
    ``spatial_covariance`` (``"stencil MxM"``), ``bins`` (their number) and
    ``bins_denoised``."""
    members = {group: [] for group in _INFO_FAMILIES}   # family -> [match]
    channels, family_of = {}, {}
    for name, ptype in info["channels"].items():
        fam = _info_family(name)
        if fam:
            group, mt = fam
            members[group].append(mt)
            family_of[name] = group
            types = channels.setdefault(_INFO_FAMILIES[group], [])
            if ptype not in types:
                types.append(ptype)
        else:
            channels[name] = ptype
    channels = {k: ", ".join(v) if isinstance(v, list) else v for k, v in channels.items()}
    groups, nonfinite = {}, {}
    for g, names in info["groups"].items():
        rest = [n for n in names if n not in family_of]
        for fam in dict.fromkeys(family_of[n] for n in names if n in family_of):
            groups.setdefault(fam, None)                # filled in below, in this position
        if rest:
            groups[g] = rest
        if g in info["nonfinite"]:
            key = g if rest else family_of[names[0]]
            c = nonfinite.setdefault(key, {"nan": 0, "inf": 0})
            for k in ("nan", "inf"):
                c[k] += info["nonfinite"][g][k]
    stencil = None
    if members["SpatialCovariance.<dy><dx>"]:
        offs = {(int(m.group(1)), int(m.group(2))) for m in members["SpatialCovariance.<dy><dx>"]}
        width = 2 * max(max(abs(dy), abs(dx)) for dy, dx in offs) + 1
        k = len(members["SpatialCovariance.<dy><dx>"])
        stencil = f"stencil {width}x{width}" + ("" if k == 3 * width * width else
                                                 f" (partial: {k} of {3 * width * width} channels)")
        groups["SpatialCovariance.<dy><dx>"] = (f"{stencil}: {len(offs)} offsets (dy, dx) x "
                                                f"R,G,B = {k} channels")
    nbins = {}
    for fam in ("Bin<b>", "Bin<b>.Denoised"):
        if members[fam]:
            nbins[fam] = len({int(m.group(1)) for m in members[fam]})
            groups[fam] = f"{nbins[fam]} bins x R,G,B = {len(members[fam])} channels"
    layout = dict(info["layout"])
    layout["covariance"] = all(c in info["channels"] for c in _COV)
    layout["spatial_covariance"] = stencil
    layout["bins"] = nbins.get("Bin<b>")
    layout["bins_denoised"] = "Bin<b>.Denoised" in nbins
    return dict(info, channels=channels, channel_count=len(info["channels"]), groups=groups,
                layout=layout, nonfinite=nonfinite)


def exr_info(path, *, families: bool = False, part=0) -> dict:
    """A JSON-ready summary of an EXR file (for ``statmc info``).

    Keys: ``path``, ``width``, ``height``, ``data_window``, ``display_window``,
    ``compression``, ``lossy_compression`` (PXR24, B44, B44A, DWAA or DWAB), ``parts`` (their
    number), ``part`` (``part`` and ``name`` of the part described: ``part``, an index or a
    name, part 0 unless given), ``other_parts`` (``part``, ``name`` and ``channels`` of each
    other part), ``merged_parts`` (the parts read with it as one image, as by
    :func:`read_exr`; the channels below include theirs), ``samples_per_pixel``
    (pbrt-v4's ``samplesPerPixel`` header attribute or None), ``chromaticities`` (or None),
    ``channels`` (name → pixel type), ``groups`` (group →
    channel names), ``layout`` (which statmc/pbrt-v4 channel groups are present),
    ``features`` (``albedo`` and ``normal``: the layers :func:`read_exr` recognises as
    such, statmc's own ``Albedo`` / ``N`` first, then other tools' layers such as Blender's
    ``ViewLayer.Denoising Albedo`` or Mitsuba's ``albedo``, at any level; ``read_exr`` takes
    its own, else the one beside the colour it reads),
    ``sample_count`` (``min``/``mean``/``max``/``total`` or None) and ``nonfinite``
    (group → NaN and Inf counts, only groups that have any).

    With ``families=True`` (what ``statmc info`` prints) the channel families of statmc's
    extensions are collapsed to one entry each — the covariance stencil of ``render --crn``
    (``SpatialCovariance.<dy><dx>.<R|G|B>``, 3·m² channels) and sample bins
    (``Bin<b>.<R|G|B>``, ``Bin<b>.Denoised.<R|G|B>``) — in ``channels``, ``groups`` and
    ``nonfinite``; ``channel_count`` gives the number of channels, and ``layout`` also
    says ``covariance`` (``Covariance.RG/RB/GB`` present), ``spatial_covariance``
    (``"stencil MxM"`` or None), ``bins`` (their number or None) and ``bins_denoised``.
    """
    p = _name(path)
    as_bool("families", families)
    header, arrays, types = _open(p, part=part)
    data_window, display_window = _windows(header)
    x0, y0, x1, y1 = data_window
    groups: dict[str, list[str]] = {}
    for n in sorted(arrays):
        groups.setdefault(_group_of(n), []).append(n)
    nonfinite = {}
    for g, names in groups.items():
        c = np.array([_count_nonfinite(arrays[n]) for n in names]).sum(axis=0)
        if c.any():
            nonfinite[g] = {"nan": int(c[0]), "inf": int(c[1])}
    sc = None
    if SAMPLE_COUNT in arrays:
        a = arrays[SAMPLE_COUNT].astype(np.float64)
        fin = a[np.isfinite(a)]
        sc = {"min": float(fin.min()), "mean": float(fin.mean()), "max": float(fin.max()),
              "total": float(fin.sum())} if fin.size else None
    info = {
        "path": p, "width": x1 - x0 + 1, "height": y1 - y0 + 1,
        "data_window": data_window, "display_window": display_window,
        "compression": _compression_name(header),
        "lossy_compression": _compression(header) in _LOSSY,
        "samples_per_pixel": _header_spp(header),
        "chromaticities": _chromaticities(header),
        "parts": int(header["_parts"]),
        "part": {"part": arrays.read_part,
                 "name": next((q["name"] for q in arrays.parts if q["part"] == arrays.read_part),
                              None)},
        "other_parts": [q for q in arrays.parts if q["part"] != arrays.read_part],
        "merged_parts": list(arrays.merged),
        "channels": {n: types[n] for n in sorted(arrays)},
        "groups": groups,
        "layout": {
            "color": "R,G,B" if all(c in arrays for c in _RGB) else ("Y" if "Y" in arrays else None),
            "variance": any(n.startswith("Variance.") for n in arrays),
            "sample_count": SAMPLE_COUNT in arrays,
            "albedo": all(c in arrays for c in _ALBEDO),
            "normal": all(c in arrays for c in _NORMAL),
            "depth": next((d for d in _DEPTH if d in arrays), None),
        },
        "features": {kind: ([own[0].rsplit(".", 1)[0]] if all(c in arrays for c in own) else [])
                     + _feature_candidates(arrays, kind)
                     for kind, (_, own, _) in _FEATURE_KINDS.items()},
        "sample_count": sc,
        "nonfinite": nonfinite,
    }
    return _summarise_families(info) if families else info


# ---------------------------------------------------------------------------- writing
def _atomic_write(path, write, *, overwrite: bool, protect) -> None:
    """Call ``write(tmp)`` on a temporary path beside ``path``, then rename it onto ``path``."""
    from ._atomic import atomic_path

    as_bool("overwrite", overwrite)               # "no" overwrote the file
    with atomic_path(_name(path), protect=protect, overwrite=overwrite) as tmp:
        write(tmp)


# Extensions of other formats: a file written under one holds something else than its name
# says (an EXR named .png opens in no PNG viewer).
_EXTENSIONS = {"exr": (".exr",), "png": (".png",)}
_OTHER_EXTENSIONS = (".exr", ".png", ".jpg", ".jpeg", ".hdr", ".tif", ".tiff", ".bmp", ".gif",
                     ".webp", ".npy", ".npz")


def _check_extension(path, what: str, hint: str, protect=()) -> None:
    """Refuse ``path`` whose extension names another image or array format than ``what``
    (after refusing it as one of the inputs ``protect``, the more telling error)."""
    from ._atomic import check_not_input
    check_not_input(_name(path), protect)
    ext = os.path.splitext(_name(path))[1].lower()
    if ext in _OTHER_EXTENSIONS and ext not in _EXTENSIONS[what]:
        raise InputError(f"`path` {_name(path)!r} ends in {ext}, but this writes {what.upper()}; "
                         f"name it {_EXTENSIONS[what][0]} ({hint}).")


def _write_exr_file(tmp: str, channels: dict, windows=None, attrs=None) -> None:
    """Write ``{name: (H, W) float32/uint32 array}`` as a ZIP-compressed scanline EXR, with
    ``windows = (data_window, display_window)`` (``[x0, y0, x1, y1]`` each) when given and
    the header attributes ``attrs``."""
    OpenEXR = _import_openexr()

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attrs or {})
    if windows is not None:
        for key, (x0, y0, x1, y1) in zip(("dataWindow", "displayWindow"), windows):
            header[key] = (np.array([x0, y0], np.int32), np.array([x1, y1], np.int32))
    OpenEXR.File(header, channels).write(tmp)


def _check_window(name: str, box, hw=None) -> list:
    """``box`` as ``[x0, y0, x1, y1]`` ints (x1 >= x0, y1 >= y0, within OpenEXR's int32),
    of the image size ``hw = (H, W)`` when given."""
    try:
        b = [int(v) for v in box]
        ok = len(b) == 4 and all(v == w for v, w in zip(b, box))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"`{name}` must be [x0, y0, x1, y1], four whole numbers (inclusive "
                         f"corners, as exr_windows() returns); got {box!r}.")
    lim = 2 ** 30      # OpenEXR keeps coordinates and sizes in int32
    if b[2] < b[0] or b[3] < b[1] or any(abs(v) > lim for v in b):
        raise InputError(f"`{name}` must have x1 >= x0 and y1 >= y0 within +-2**30; got {b}.")
    if hw is not None and (b[3] - b[1] + 1, b[2] - b[0] + 1) != tuple(hw):
        raise InputError(f"`{name}` {b} is {b[2] - b[0] + 1}x{b[3] - b[1] + 1} (W x H) but the "
                         f"image is {hw[1]}x{hw[0]}; the data window must have the image's size.")
    return b


def _f32(name, a):
    """``a`` as contiguous float32; NaN/Inf in ``a`` (``check_finite``'s error) or values
    beyond float32's range refused.  One scan of the result when all is finite: a NaN/Inf
    of ``a`` stays one in float32."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.ascontiguousarray(a, dtype=np.float32)
    if not np.isfinite(out).all():
        check_finite(name, np.asarray(a))
        raise InputError(f"`{name}` overflows float32 in {int((~np.isfinite(out)).sum())} values "
                         f"(max |value| {np.abs(np.asarray(a)).max():.4g} > 3.4e38).")
    return out


def _image_channels(image, name="data") -> dict:
    """The ``Y`` or ``R, G, B`` channels of a plain image given as ``name`` (write_exr's
    ``data``, which it names: the messages said `image`, a parameter it does not have)."""
    img = as_float_array(name, image, ndim=(2, 3))
    if img.ndim == 2:
        img = img[..., None]
    c = img.shape[2]
    if c not in (1, 3):
        raise InputError(f"`{name}` must be a PixelStats or an image with 1 or 3 channels (Y "
                         f"or R, G, B); got shape {img.shape}.")
    names = ("Y",) if c == 1 else _RGB
    return {n: _f32(name, img[..., k]) for k, n in enumerate(names)}


def _stats_channels(stats: PixelStats) -> dict:
    c = stats.shape[2]
    if c not in (1, 3):
        raise InputError(f"PixelStats to write must have 1 or 3 channels (Y or R, G, B); got {stats.shape}.")
    color = ("Y",) if c == 1 else _RGB
    var = stats.sample_var
    out = {}
    for k, n in enumerate(color):
        out[n] = _f32("mean", stats.mean[..., k])
        out["Variance." + n] = _f32("sample_var", var[..., k])
    if stats.m2_cross is not None and c == 3:
        cov = stats.sample_cov
        for name, (a, b) in zip(_COV, ((0, 1), (0, 2), (1, 2))):
            out[name] = _f32("sample_cov", cov[..., a, b])
    nmax = int(stats.n.max()) if stats.n.size else 0
    if nmax <= _MAX_F32_COUNT:
        out[SAMPLE_COUNT] = stats.n.astype(np.float32)
    elif nmax <= np.iinfo(np.uint32).max:
        out[SAMPLE_COUNT] = stats.n.astype(np.uint32)   # exact beyond float32's 2**24
    else:
        raise InputError(f"sample counts up to {nmax} do not fit an EXR channel (max 2**32 - 1).")
    for feat, names in (("albedo", _ALBEDO), ("normal", _NORMAL)):
        a = getattr(stats, feat)
        if a is not None:
            if a.ndim != 3 or a.shape[2] != 3:
                raise InputError(f"feature `{feat}` must be (H, W, 3) to be written; got {a.shape}.")
            for k, n in enumerate(names):
                out[n] = _f32(feat, a[..., k])
    if stats.depth is not None:
        d = stats.depth
        if d.ndim == 3 and d.shape[2] == 1:
            d = d[..., 0]
        if d.ndim != 2:
            raise InputError(f"feature `depth` must be (H, W) to be written; got {d.shape}.")
        out["Z"] = _f32("depth", d)
    return out


def write_exr(path, data, *, extra=None, data_window=None, display_window=None,
              chromaticities=None, overwrite: bool = True, protect=()) -> None:
    """Write per-pixel statistics or a plain image as an EXR file, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    data : PixelStats or (H, W, 3) / (H, W) ndarray
        Statistics are written with all channels of the layout (float32, with the
        *sample* variance in ``Variance.*``, the sample covariances in
        ``Covariance.RG/RB/GB`` when ``m2_cross`` is known (RGB only), and ``SampleCount``
        as float32, or uint32 beyond 2**24 samples); a plain image as ``R, G, B`` (or
        ``Y``) only.
    extra : dict of str to (H, W) ndarray, optional
        Further channels, e.g. selected filter scales; names must not clash with the layout.
    data_window, display_window : [x0, y0, x1, y1], optional
        Where the pixels lie (OpenEXR's inclusive corners, as :func:`exr_windows` and
        ``read_exr(...).meta`` give them): the data window must have the image's size; the
        display window, the frame the image belongs to, defaults to the data window.  Left
        out (both), a ``PixelStats`` is written where its ``meta["data_window"]`` and
        ``meta["display_window"]`` say (``read_exr`` sets them, so a read crop is written
        back as a crop; a meta window of another size than the image is refused), and a
        plain image, or statistics without them, at the origin, ``[0, 0, W - 1, H - 1]``.
        Given, they win over ``meta``: pass an input's windows to write a result in the
        input's place.
    chromaticities : sequence of 8 floats, optional
        The RGB primaries and white point ``(rx, ry, gx, gy, bx, by, wx, wy)`` of the
        data (OpenEXR's ``chromaticities`` attribute; ``read_exr(...).meta`` gives an
        input's).  Left out, a ``PixelStats``'s ``meta["chromaticities"]`` is written if
        it has one, else none, which readers take as Rec. 709/sRGB; given, it wins: pass
        an input's to keep, say, an ACEScg render's colours in a result computed from it.
        (Set a ``meta`` entry to None to write statistics without it.)
    overwrite : bool, default True
        With ``False``, an existing ``path`` raises :class:`InputError`.
    protect : path or sequence of paths
        Files that must never be overwritten (the command's inputs): writing onto any of
        them (same path, symlink or hard link) raises :class:`InputError`.

    Notes
    -----
    The file is first written beside ``path`` under a temporary name and then renamed
    onto it (``os.replace``), so readers see the old or the new file, never a partial one;
    on failure the temporary file is removed and an existing file stays as it was.
    Values are stored as float32: float32-representable data round-trips bit-exactly.
    A ``path`` ending in another format's extension (``.png``, ``.jpg``, ``.hdr``, ``.tif``,
    ``.npy``, ...) is refused: the file would not be what its name says.
    """
    _check_extension(path, "exr", "write_png_preview writes an 8-bit PNG preview", protect)
    chroma_name, window_names = "chromaticities", None     # None: the caller's windows
    if isinstance(data, PixelStats):
        channels = _stats_channels(data)
        meta = data.meta if isinstance(data.meta, dict) else {}
        if chromaticities is None:
            chromaticities = meta.get("chromaticities")
            chroma_name = "data.meta['chromaticities']"
        if data_window is None and display_window is None:
            data_window, display_window = meta.get("data_window"), meta.get("display_window")
            window_names = ("data.meta['data_window']", "data.meta['display_window']")
    else:
        channels = _image_channels(data)
    hw = next(iter(channels.values())).shape
    if 0 in hw:             # OpenEXR said "Invalid display window in image header"
        raise InputError(f"`data` must have pixels; got an image of (H, W) = {hw}.")
    if extra is not None and not isinstance(extra, Mapping):
        raise InputError(f"`extra` must be a dict of channel name to (H, W) array; got "
                         f"{type(extra).__name__}.")
    for name, a in (extra or {}).items():
        if not isinstance(name, str) or not name or name in channels:
            raise InputError(f"`extra` channel names must be new non-empty strings; got {name!r} "
                             f"(already used: {sorted(channels)}).")
        arr = as_float_array(f"extra[{name!r}]", a, ndim=2)
        if arr.shape != hw:
            raise InputError(f"`extra[{name!r}]` must have the image size {hw}; got {arr.shape}.")
        channels[name] = _f32(f"extra[{name!r}]", arr)
    attrs = {}
    if chromaticities is not None:
        try:
            c = tuple(float(x) for x in chromaticities)
        except (TypeError, ValueError):
            c = ()
        if len(c) != 8 or not all(np.isfinite(c)):
            raise InputError(f"`{chroma_name}` must be 8 finite numbers (rx, ry, gx, gy, bx, by, "
                             f"wx, wy); got {chromaticities!r}.")
        attrs["chromaticities"] = c
    windows = None
    if data_window is not None or display_window is not None:
        names = window_names or ("data_window", "display_window")
        try:
            box = _check_window(names[0], data_window if data_window is not None
                                else [0, 0, hw[1] - 1, hw[0] - 1], hw)
            windows = (box, box if display_window is None
                       else _check_window(names[1], display_window))
        except InputError as e:
            if window_names is None:
                raise
            raise InputError(f"{str(e).rstrip('.')}; pass data_window= (and display_window=) "
                             "for where the image lies, or set these meta entries to None for "
                             "the origin.") from None

    def write(tmp):
        try:
            _write_exr_file(tmp, channels, windows, attrs)
        except OSError:
            raise
        except Exception as e:
            raise FileFormatError(f"could not write EXR file {_name(path)!r}: {e}") from e

    _atomic_write(path, write, overwrite=overwrite, protect=protect)


# ------------------------------------------------------------- spatial covariance
def _spatial_name(dy: int, dx: int, c: str) -> str:
    return f"{SPATIAL_COVARIANCE}.{dy:+d}{dx:+d}.{c}"


def spatial_covariance_channels(cov, n) -> dict:
    """Channels holding a neighbour-covariance stencil, for ``write_exr(..., extra=)``.

    ``cov`` is the covariance of the pixel *means*, ``(H, W, m, m, 3)`` with
    ``cov[p, R + dy, R + dx] = cov(z_p, z_{p + (dy, dx)})`` (e.g. the second output of
    :meth:`statmc.mitsuba_backend.MitsubaRenderer.render_crn`).  Like ``Variance.*`` the
    file stores the covariance of *one* sample pair, ``n · cov`` (uniform ``n``), in
    channels ``SpatialCovariance.<dy><dx>.<R|G|B>`` with signed offsets, e.g.
    ``SpatialCovariance.-1+2.G``; the centre ``+0+0`` equals ``Variance.*``.
    """
    a = as_float_array("cov", cov, ndim=5, dtype=np.float64)
    check_finite("cov", a)
    H, W, m, m2, C = a.shape
    if m != m2 or m % 2 == 0 or C != 3:
        raise InputError(f"`cov` must be (H, W, m, m, 3) with odd m; got {a.shape}.")
    nn = as_float_array("n", n, ndim=2, dtype=np.float64)
    if nn.shape != (H, W):
        raise InputError(f"`n` must be (H, W) = {(H, W)}; got {nn.shape}.")
    R = m // 2
    return {_spatial_name(dy, dx, c): a[:, :, R + dy, R + dx, k] * nn
            for dy in range(-R, R + 1) for dx in range(-R, R + 1) for k, c in enumerate(_RGB)}


def read_spatial_covariance(path, n=None, *, part=0):
    """The neighbour-covariance stencil of an EXR file (its ``part``, an index or a name), or
    ``None`` if it has none.

    Returns the covariance of the pixel means, ``(H, W, m, m, 3)`` float64 (the stored
    one-sample covariance divided by ``n``: ``SampleCount`` unless ``n`` is given).  A
    partial stencil (a missing offset or channel) raises
    :class:`~statmc.errors.FileFormatError` naming what is missing.
    """
    p = _name(path)
    _, arrays, _ = _open(p, part=part)
    found = {}
    for name in arrays:
        mt = _SPATIAL_CHANNEL.match(name)
        if mt:
            found[(int(mt.group(1)), int(mt.group(2)), mt.group(3))] = name
    if not found:
        return None
    R = max(max(abs(dy), abs(dx)) for dy, dx, _ in found)
    want = [_spatial_name(dy, dx, c) for dy in range(-R, R + 1) for dx in range(-R, R + 1)
            for c in _RGB]
    missing = [w for w in want if w not in arrays]
    if missing:
        raise FileFormatError(f"{p!r} has a partial {SPATIAL_COVARIANCE} stencil ({2 * R + 1}x"
                              f"{2 * R + 1}); missing {len(missing)} channel(s), e.g. {missing[:3]}.")
    H, W = arrays[want[0]].shape
    if n is None:
        if SAMPLE_COUNT not in arrays:
            raise FileFormatError(f"{p!r} has {SPATIAL_COVARIANCE} channels but no {SAMPLE_COUNT}; "
                                  f"pass the samples per pixel.")
        nn = arrays[SAMPLE_COUNT].astype(np.float64)
    else:
        nn = _spp_map(n, (H, W), "n")
    m = 2 * R + 1
    out = np.empty((H, W, m, m, 3))
    for dy in range(-R, R + 1):
        for dx in range(-R, R + 1):
            for k, c in enumerate(_RGB):
                out[:, :, R + dy, R + dx, k] = arrays[_spatial_name(dy, dx, c)]
    if not np.all(np.isfinite(out)):
        raise FileFormatError(f"{p!r}: {SPATIAL_COVARIANCE} channels hold NaN or Inf.")
    return out / np.maximum(nn, 1.0)[:, :, None, None, None]


def _read_exr_and_stencil(path, **read_options):
    """``read_exr(path, **read_options)`` and the file's neighbour-covariance stencil,
    ``read_spatial_covariance(path, n)`` of that read's counts (None without
    ``SpatialCovariance.*`` channels), from one read of the file instead of two: a
    ``statmc render --crn`` file with a 5x5 stencil is 317 MB at 1920x1080, ~2 s a read.

    Returns ``(stats, stencil)``, ``stencil()`` the stencil, computed when called: until
    then, and the errors of the stencil (a partial one) with it, the file's channels stay
    in memory; drop ``stencil`` to free them.
    """
    p = _name(path)
    part = _check_part(read_options.get("part", 0))
    opened = _open(p, part=part)

    def reading_opened(fn, *args, **kwargs):
        with _reading_once(p, opened, part):
            return fn(*args, **kwargs)

    stats = reading_opened(read_exr, p, **read_options)
    return stats, lambda: reading_opened(read_spatial_covariance, p, stats.n, part=part)


# ------------------------------------------------------------------ sample bins
def _bin_name(b: int, c: str, denoised: bool) -> str:
    return f"{BIN}{b}.{'Denoised.' if denoised else ''}{c}"


def bin_channels(ys, zs=None) -> dict:
    """Channels holding ``B`` sample bins (Back et al. 2020 §4.4), for
    ``write_exr(..., extra=)``: ``Bin<b>.<R|G|B>`` the mean of bin ``b``'s samples and,
    with ``zs``, ``Bin<b>.Denoised.<R|G|B>`` its correlated (denoised) image — the
    inputs ``ys``, ``zs`` ``(B, H, W, 3)`` of :func:`statmc.combine.combine_multi`."""
    y = as_float_array("ys", ys, ndim=4)
    check_finite("ys", y)
    if y.shape[0] < 1 or y.shape[3] != 3:
        raise InputError(f"`ys` must be (B, H, W, 3); got {y.shape}.")
    out = {_bin_name(b, c, False): y[b, :, :, k] for b in range(y.shape[0])
           for k, c in enumerate(_RGB)}
    if zs is not None:
        z = as_float_array("zs", zs, ndim=4)
        check_finite("zs", z)
        if z.shape != y.shape:
            raise InputError(f"`zs` must have the shape of `ys` {y.shape}; got {z.shape}.")
        out.update({_bin_name(b, c, True): z[b, :, :, k] for b in range(z.shape[0])
                    for k, c in enumerate(_RGB)})
    return out


def read_bins(path):
    """The sample bins of an EXR file written with :func:`bin_channels`:
    ``(ys, zs)``, each ``(B, H, W, 3)`` float32 (``zs`` is ``None`` without
    ``Bin<b>.Denoised.*`` channels), or ``None`` if the file has no bins.  A gap in the
    bin numbers or a missing channel raises :class:`~statmc.errors.FileFormatError`."""
    p = _name(path)
    _, arrays, _ = _open(p)
    found = set()
    for name in arrays:
        mt = _BIN_CHANNEL.match(name)
        if mt:
            found.add((int(mt.group(1)), bool(mt.group(2))))
    if not found:
        return None
    nums = {b for b, _ in found}
    B = max(nums) + 1
    if len(nums) != B:
        # a gap (or a corrupt huge index): name it without listing every missing channel
        gap = min(set(range(len(nums) + 1)) - nums)
        raise FileFormatError(f"{p!r} has {BIN}* channels for bins up to {B - 1} but none for "
                              f"bin {gap} (e.g. {_bin_name(gap, 'R', False)!r}).")
    has_z = any(d for _, d in found)
    want = [_bin_name(b, c, d) for d in ((False, True) if has_z else (False,))
            for b in range(B) for c in _RGB]
    missing = [w for w in want if w not in arrays]
    if missing:
        raise FileFormatError(f"{p!r} has {BIN}* channels for {B} bins but misses "
                              f"{len(missing)}, e.g. {missing[:3]}.")

    def stack(d):
        a = np.stack([np.stack([arrays[_bin_name(b, c, d)] for c in _RGB], axis=-1)
                      for b in range(B)]).astype(np.float32)
        if not np.all(np.isfinite(a)):
            raise FileFormatError(f"{p!r}: {BIN}* channels hold NaN or Inf.")
        return a

    return stack(False), (stack(True) if has_z else None)


# ---------------------------------------------------------------------------- previews
#: zlib level of the PNG previews (:func:`write_png_preview`).
_PNG_LEVEL = 1

def _srgb_encode(x):
    """sRGB transfer function (IEC 61966-2-1) of linear values clamped to [0, 1]:
    ``12.92 x`` up to 0.0031308, else ``1.055 x^(1/2.4) − 0.055``.  ``x`` (float64, the
    caller's own temporary) is clamped in place; the curve is computed in place in one
    array (1920x1080: 80 -> 47 ms against ``np.where`` of both branches, bit for bit the
    same)."""
    x = np.clip(x, 0.0, 1.0, out=x)
    out = np.power(x, 1 / 2.4)
    out *= 1.055
    out -= 0.055
    np.multiply(x, 12.92, out=out, where=x <= 0.0031308)
    return out


def to_display(image, *, exposure: float = 0.0, tonemap: str = "srgb") -> np.ndarray:
    """Linear radiance to display values in [0, 1]: exposure, tone curve, sRGB encoding.

    Parameters
    ----------
    image : (H, W, C) or (H, W) ndarray or PixelStats (its mean)
    exposure : float
        Stops: the image is scaled by ``2**exposure`` first.
    tonemap : {"srgb", "reinhard", "aces"}
        ``"srgb"`` clamps to [0, 1]; ``"reinhard"`` applies ``x / (1 + x)`` per channel
        (Reinhard et al. 2002, Eq. 3); ``"aces"`` applies Narkowicz's (2015) fit
        ``x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14)`` of the ACES curve.  The sRGB
        transfer function follows in all cases.
    """
    if isinstance(image, PixelStats):
        image = image.mean
    x = as_float_array("image", image, ndim=(2, 3))
    check_finite("image", x)
    if not np.isfinite(real_or_nan(exposure)):
        raise InputError(f"`exposure` must be a finite number of stops; got {exposure!r}.")
    if tonemap not in _TONEMAPS:
        raise InputError(f"`tonemap` must be one of {_TONEMAPS}; got {tonemap!r}.")
    try:
        scale = 2.0 ** real_or_nan(exposure)
    except OverflowError:                   # 2**1100: every positive value shows white
        scale = None
    if scale is None:
        x = np.where(x > 0, np.inf, 0.0)
    else:
        # one float64 temporary, changed in place from here on (the same values as
        # ``np.maximum(x * scale, 0.0)``; 1920x1080: three 50 MB copies fewer)
        x = x.astype(np.float64)
        if scale != 1.0:
            with np.errstate(over="ignore"):    # 1e300 · 2**100: inf, white
                x *= scale
        np.maximum(x, 0.0, out=x)
    # Above 1e150 every curve is at its limit to float64's precision (x/(1+x) = 1, ACES
    # 2.51/2.43); capping there keeps x² finite and inf/inf from making NaN.
    np.minimum(x, 1e150, out=x)
    if tonemap == "reinhard":
        x = x / (1.0 + x)
    elif tonemap == "aces":
        x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    return _srgb_encode(x)


def write_png_preview(path, image, *, exposure: float = 0.0, tonemap: str = "srgb",
                      overwrite: bool = True, protect=()) -> None:
    """Write an 8-bit sRGB PNG preview of a linear image, atomically (see :func:`to_display`).

    ``image`` is ``(H, W, 3)``, ``(H, W, 1)``, ``(H, W)`` or a :class:`PixelStats`.
    ``overwrite`` and ``protect`` behave as in :func:`write_exr`; a ``path`` ending in another
    format's extension (``.exr``, ``.jpg``, ...) is refused.
    """
    from PIL import Image

    _check_extension(path, "png", "write_exr writes the linear image as OpenEXR", protect)
    disp = to_display(image, exposure=exposure, tonemap=tonemap)
    if disp.size == 0:
        raise InputError(f"`image` must have pixels for a PNG preview; got shape {disp.shape}.")
    if disp.ndim == 3 and disp.shape[2] == 1:
        disp = disp[..., 0]
    if disp.ndim == 3 and disp.shape[2] != 3:
        raise InputError(f"`image` must have 1 or 3 channels for a PNG preview; got {disp.shape}.")
    disp *= 255.0                     # to_display's own array: rounded in place
    u8 = np.round(disp, out=disp).astype(np.uint8)

    def write(tmp):
        # zlib level 1, not Pillow's default 6: lossless all the same; at 1920x1080 2-3x
        # faster (0.16-0.28 against 0.39-0.54 s) for a file 7 % smaller to 8 % larger
        Image.fromarray(u8).save(tmp, format="PNG", compress_level=_PNG_LEVEL)

    _atomic_write(path, write, overwrite=overwrite, protect=protect)
