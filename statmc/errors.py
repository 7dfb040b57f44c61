"""Exception types and shared input checks.

Every check raises :class:`InputError` (a ``ValueError``) whose message names the
parameter, what was expected, what was given, and how to fix it, so the CLI can print
it as one line.
"""

from __future__ import annotations

import math
import numbers

import numpy as np


class InputError(ValueError):
    """A caller's input is wrong: bad shape, NaN/Inf, negative counts or variances."""


class FileFormatError(InputError):
    """A file is unreadable, corrupt, or lacks channels that are needed."""


def as_float_array(name: str, a, *, ndim: int | tuple[int, ...] | None = None,
                   dtype=None) -> np.ndarray:
    """Return ``a`` as a float ndarray (ints become ``float64``; float32 stays float32).

    float16 becomes float32 and extended precision float64: the compiled kernels and most
    of SciPy have neither (float16 raised numba's ``NotImplementedError``).  A non-native
    byte order (big-endian ``'>f4'``) becomes native: numba cannot type it.
    Raises :class:`InputError` when it is not numeric (complex included), cannot be
    converted (a ragged list, a torch tensor that requires grad), is a masked array with
    masked entries, or has the wrong number of dims.
    """
    if isinstance(a, np.ma.MaskedArray) and np.ma.getmaskarray(a).any():
        raise InputError(f"`{name}` is a masked array with {int(np.ma.getmaskarray(a).sum())} "
                         "masked entries, whose values would be used as they are; fill them "
                         "first (`a.filled(value)`).")
    try:
        arr = np.asarray(a)
    except (ValueError, TypeError, RuntimeError) as exc:   # ragged lists; torch grad tensors
        raise InputError(f"`{name}` must be an array of real numbers; could not convert the "
                         f"{type(a).__name__} given ({str(exc).splitlines()[0]}).") from None
    if arr.dtype == object or np.iscomplexobj(arr) \
            or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise InputError(f"`{name}` must be a real numeric array; got dtype {arr.dtype}.")
    if dtype is not None:
        arr = arr.astype(dtype, copy=False)
    elif arr.dtype == np.float16:
        arr = arr.astype(np.float32)
    elif not np.issubdtype(arr.dtype, np.floating) or arr.dtype.itemsize > 8:
        arr = arr.astype(np.float64)
    if not arr.dtype.isnative:                  # '>f4' from a file: numba cannot type it
        arr = arr.astype(arr.dtype.newbyteorder("="))
    if ndim is not None:
        dims = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in dims:
            want = " or ".join(str(d) for d in dims)
            hint = (f" For a grey image add a channel axis: `{name}[..., None]`."
                    if arr.ndim == 2 and 3 in dims and 2 not in dims else "")
            raise InputError(f"`{name}` must have {want} dimensions; got shape {arr.shape}.{hint}")
    return arr


def check_finite(name: str, a: np.ndarray) -> None:
    """Raise :class:`InputError` when ``a`` holds NaN or Inf, saying how many."""
    bad = ~np.isfinite(a)
    if bad.any():
        n_nan = int(np.isnan(a).sum())
        n_inf = int(bad.sum()) - n_nan
        raise InputError(
            f"`{name}` holds {n_nan} NaN and {n_inf} Inf values; expected finite numbers "
            "(replace them first, e.g. `statmc.stats.replace_nonfinite`)."
        )


def check_nonnegative(name: str, a: np.ndarray) -> None:
    """Raise :class:`InputError` when ``a`` has negative entries."""
    if a.size and np.nanmin(a) < 0:
        n = int((a < 0).sum())
        raise InputError(f"`{name}` must be >= 0; got {n} negative values (min {np.nanmin(a):.4g}).")


def check_nonempty(name: str, a: np.ndarray, what: str = "(H, W, C) image") -> None:
    """Raise :class:`InputError` when ``a`` has a zero-length axis (no pixels or no
    channels): per-image statistics (means, sums over pixels, budgets) are undefined then."""
    if a.size == 0:
        raise InputError(f"`{name}` must be a non-empty {what}; got shape {a.shape}.")


def check_same_shape(name: str, a: np.ndarray, ref_name: str, ref_shape: tuple) -> None:
    """Raise :class:`InputError` unless ``a.shape == ref_shape``."""
    if a.shape != tuple(ref_shape):
        raise InputError(
            f"`{name}` must have the shape of `{ref_name}` {tuple(ref_shape)}; got {a.shape}."
        )


def _scalar(value):
    """A 0-d array (``np.array(2.0)``, ``a.sum(keepdims=False)[()]``...) as its NumPy
    scalar, so the number checks below see a number; anything else unchanged."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return value[()]
    return value


def real_or_nan(value) -> float:
    """``value`` as a float if it is a real number (a 0-d array too; not a bool), else NaN,
    for checks with their own message: a string "1" was parsed silently by ``float`` and
    None was its TypeError."""
    value = _scalar(value)
    ok = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    return float(value) if ok else math.nan


def as_number(name: str, value, *, lo: float | None = None, lo_open: bool = False) -> float:
    """``value`` as a finite float, optionally ``>= lo`` (``> lo`` with ``lo_open``).

    Booleans and non-numbers are refused with an :class:`InputError` naming ``name``; a
    0-d array is read as its number.
    """
    value = _scalar(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real) \
            or not np.isfinite(float(value)):
        raise InputError(f"`{name}` must be a finite number; got {value!r}.")
    f = float(value)
    if lo is not None and (f < lo or (lo_open and f == lo)):
        rel = ">" if lo_open else ">="
        raise InputError(f"`{name}` must be {rel} {lo}; got {value!r}.")
    return f


def as_int(name: str, value, *, lo: int = 1) -> int:
    """``value`` as a Python int ``>= lo`` (default: a positive integer).

    Booleans, floats and non-numbers are refused with an :class:`InputError` naming ``name``.
    """
    value = _scalar(value)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < lo:
        what = {0: "a non-negative integer", 1: "a positive integer"}.get(lo, f"an integer >= {lo}")
        raise InputError(f"`{name}` must be {what}; got {value!r}.")
    return int(value)


def as_bool(name: str, value, *, why: str | None = None) -> bool:
    """``value`` of a True/False option as a Python bool; anything but a bool or NumPy
    bool (``"no"`` was taken as True, None as False) is an :class:`InputError`:
    "`name` must be True or False; got 'no'.".  ``why``, if given, says what the option
    means, in parentheses: "`per_channel` must be True or False (one α per pixel and
    channel); got 'yes'."."""
    if not isinstance(value, (bool, np.bool_)):
        hint = f" ({why})" if why else ""
        raise InputError(f"`{name}` must be True or False{hint}; got {value!r}.")
    return bool(value)


#: Largest sample budget accepted: counts are placed through float64 targets, exact up to
#: 2**53 (a budget of 2**56 came back 6 samples off, 2**63 overflowed the kernels).
MAX_BUDGET = 2 ** 53


def as_whole(name: str, value, *, lo: int = 0, what: str = "number",
             hi: int | None = None) -> int:
    """``value`` as a Python int ``>= lo`` (and ``<= hi`` if given): integers and
    whole-valued finite floats (``12.0``, e.g. a budget computed in floating point).  A
    fraction, a bool, a string or a non-finite number is an :class:`InputError`:
    "`name` must be a whole ``what`` >= ``lo``"."""
    value = _scalar(value)
    ok = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    if ok and not isinstance(value, numbers.Integral):
        ok = bool(np.isfinite(value)) and float(value) == np.floor(value)
    if not ok or value < lo:
        raise InputError(f"`{name}` must be a whole {what} >= {lo}; got {value!r}.")
    if hi is not None and value > hi:
        raise InputError(f"`{name}` must be a whole {what} <= {hi}; got {value!r}.")
    return int(value)


def as_rng(value, name: str = "rng") -> np.random.Generator:
    """``np.random.default_rng(value)``: None, a non-negative int seed, a SeedSequence or
    a Generator (returned as it is); anything else is an :class:`InputError` naming
    ``name``.  A bool is refused: ``default_rng(True)`` would seed with 1."""
    if isinstance(value, (bool, np.bool_)):
        raise InputError(f"`{name}` must be None, a non-negative int seed or a numpy "
                         f"Generator; got {value!r}.")
    try:
        return np.random.default_rng(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"`{name}` must be None, a non-negative int seed or a numpy "
                         f"Generator; got {value!r}.") from exc


def as_broadcast_arrays(arrays: dict, *, nonnegative=()) -> list:
    """The values of ``arrays`` (``{name: array or number}``) as finite float64 arrays that
    broadcast together, those named in ``nonnegative`` also ``>= 0`` (for element-wise
    formulas that take scalars or maps); any failure is an :class:`InputError` naming the
    argument."""
    out = []
    for name, a in arrays.items():
        arr = as_float_array(name, a, dtype=np.float64)
        check_finite(name, arr)
        if name in nonnegative:
            check_nonnegative(name, arr)
        out.append(arr)
    try:
        np.broadcast_shapes(*(a.shape for a in out))
    except ValueError:
        shapes = ", ".join(f"`{n}` {a.shape}" for n, a in zip(arrays, out))
        raise InputError(f"the arrays must have shapes that broadcast together (e.g. all the "
                         f"same); got {shapes}.") from None
    return out


def _largest(a) -> float:
    """Largest magnitude in ``a`` (for messages; NaN if ``a`` is empty)."""
    a = np.asarray(a, dtype=np.float64)
    return float(max(a.max(), -a.min())) if a.size else math.nan   # 0, not -0, for zeros


def check_overflow(result, what: str, given: dict, expected: str) -> None:
    """Raise :class:`InputError` when ``result``, computed from finite (already checked)
    input, holds NaN or Inf: the float64 arithmetic overflowed (a square of a value
    beyond ~1.3e154, a product or sum beyond ~1.8e308) where a caller would otherwise get
    Inf/NaN back silently.

    One pass and no temporary when all is well (a sum: NaN/Inf propagate into it; a sum
    that overflows although every entry is finite is then checked entry by entry).  The
    message says what overflowed, the largest magnitude of each array in ``given``
    (``{name: array}``, the inputs that bound it; or a function returning that dict, called
    only when the check fails, for inputs that are costly to form) and the range
    ``expected``.
    """
    a = np.asarray(result)
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.sum(a)):
            return
    n_bad = int(a.size - np.count_nonzero(np.isfinite(a)))
    if n_bad == 0:                          # only the sum overflowed
        return
    where = f" in {n_bad} of {a.size} entries" if a.ndim else ""
    if callable(given):
        given = given()
    parts = ", ".join(f"`{name}` up to {_largest(v):.3g}" for name, v in given.items())
    raise InputError(
        f"{what} left float64's range (largest finite {np.finfo(np.float64).max:.3g}){where} "
        f"for the finite input given ({parts} in magnitude); expected {expected}. Rescale "
        "the input (e.g. divide the images by their largest value and variances by its "
        "square).")
