"""Atomic file output: write to a temporary file beside the target, then rename.

Every file statmc writes goes through :func:`atomic_path`, so a failed write never
leaves a half-written file and never replaces an existing one, and no output can land
on one of the command's input files.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile

from .errors import InputError


def _as_tuple(protect):
    if protect is None:
        return ()
    if isinstance(protect, (str, bytes, os.PathLike)):
        return (protect,)
    return tuple(protect)


def same_file(a, b) -> bool:
    """Whether the paths ``a`` and ``b`` name one file: :func:`os.path.samefile` when both
    exist (hard links, symlinks, ``dir/link/..`` through a symlinked directory), else the
    equality of their :func:`os.path.realpath` (a file not written yet)."""
    a, b = os.fspath(a), os.fspath(b)
    if os.path.exists(a) and os.path.exists(b):
        with contextlib.suppress(OSError):
            return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def check_not_input(path, protect=()) -> None:
    """Raise :class:`InputError` when ``path`` names the same file as any of ``protect``."""
    path = os.fspath(path)
    for q in _as_tuple(protect):
        if q is None:
            continue
        q = os.fspath(q)
        if same_file(path, q):
            raise InputError(f"refusing to write {path!r}: it is the input file {q!r}; "
                             "choose another output path (statmc never overwrites an input).")


def _final_mode(path: str) -> int:
    """Permissions for the output: those of the file it replaces, else 0o666 & ~umask."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        mask = os.umask(0)
        os.umask(mask)
        return 0o666 & ~mask


def _cannot_write(path: str, directory: str, e: OSError) -> OSError:
    """``e`` (of the same class and errno) saying which output could not be created where."""
    d = directory
    while d and not os.path.lexists(d):
        d = os.path.dirname(d)
    if d and not os.path.isdir(d):
        return NotADirectoryError(errno.ENOTDIR, f"cannot write {path!r}: {d!r} is not a "
                                  "directory")
    return type(e)(e.errno, f"cannot write {path!r}: cannot create a file in {directory!r} "
                            f"({e.strerror or e})")


@contextlib.contextmanager
def atomic_path(path, *, protect=(), overwrite: bool = True, suffix=None):
    """Yield a temporary path in ``path``'s directory; rename it onto ``path`` on success.

    On any exception the temporary file is removed and an existing ``path`` is untouched.
    ``protect`` (a path or several) lists input files that ``path`` must not be;
    ``overwrite=False`` refuses an existing ``path``.  The result gets the permissions of
    the file it replaces (or the umask's), and is flushed to disk before the rename.
    """
    path = os.fspath(path)
    check_not_input(path, protect)
    if os.path.isdir(path):
        raise InputError(f"cannot write {path!r}: it is a directory.")
    if not overwrite and os.path.lexists(path):
        raise InputError(f"{path!r} exists and overwrite=False; choose another path or allow overwriting.")
    directory = os.path.dirname(os.path.abspath(path))
    mode = _final_mode(path)
    suffix = suffix if suffix is not None else os.path.splitext(path)[1]
    made = missing_directories(directory)
    try:
        os.makedirs(directory, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".statmc-", suffix=suffix, dir=directory)
    except OSError as e:
        remove_made_directories(made)
        # name the target and the directory, not the hidden temporary file or a bare errno
        raise _cannot_write(path, directory, e) from None
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, mode)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        remove_made_directories(made)
        raise


def missing_directories(directory: str) -> list:
    """The components of ``directory`` that do not exist yet, deepest first (what
    ``os.makedirs`` will create)."""
    made = []
    d = directory
    while d and not os.path.lexists(d):
        made.append(d)
        parent = os.path.dirname(d)
        if parent == d:
            break
        d = parent
    return made


def remove_made_directories(made) -> None:
    """Remove the directories a failed write created (deepest first), if still empty.

    Every one is tried: a deeper one that is missing (``os.makedirs`` failed before making
    it, e.g. on a name too long, after making its parents) does not stop the parents'
    removal; a non-empty one stays, and so do its parents (``os.rmdir`` removes only
    empty directories)."""
    for d in made:
        with contextlib.suppress(OSError):
            os.rmdir(d)


def write_text(path, text: str, *, protect=()) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path, protect=protect) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
