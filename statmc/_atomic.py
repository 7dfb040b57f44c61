"""Atomic file output: write to a temporary file beside the target, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile

from .errors import InputError


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_not_input(path, protect=()) -> None:
    """Raise :class:`InputError` when ``path`` is one of the files in ``protect``."""
    for q in protect:
        if q is not None and os.path.exists(path) and _same_file(str(path), str(q)):
            raise InputError(f"refusing to overwrite the input file {q}; choose another output path.")


@contextlib.contextmanager
def atomic_path(path, *, protect=(), suffix=None):
    """Yield a temporary path in ``path``'s directory; rename it onto ``path`` on success.

    On any exception the temporary file is removed and an existing ``path`` is untouched.
    ``protect`` lists input files that ``path`` must not be.
    """
    path = os.fspath(path)
    check_not_input(path, protect)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    suffix = suffix if suffix is not None else os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=".statmc-", suffix=suffix, dir=directory)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def write_text(path, text: str, *, protect=()) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path, protect=protect) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
