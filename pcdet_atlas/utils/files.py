"""Writing files at fixed names inside folders a user may have received from someone else.

An output, evaluation or report folder can come from a collaborator, and a name in it can be a
planted symlink (``report.md -> ~/.bashrc``). A write that opens such a name follows the link and
overwrites its target, outside the folder. So a whole file is written by :func:`write_atomic`: a
temporary file of the folder renamed over the name, which replaces a link instead of following
it; a file that is kept open and written in place (a lock, a log) is opened by
:func:`open_regular_file`, which refuses a symlink or anything else than a regular file there.
This module imports nothing of the package, so that every layer (``config`` included) can use it.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["NotARegularFileError", "open_regular_file", "write_atomic"]

_UMASK = os.umask(0)
os.umask(_UMASK)


class NotARegularFileError(OSError):
    """A path the project writes in place that is a symlink, a FIFO, a device or a folder."""


def write_atomic(
    path: str | Path, write: Callable[[BinaryIO], object], *, sync: bool = True
) -> Path:
    """Write ``path`` by ``write(file)`` into a temporary file of its folder (created if
    needed), renamed into place: an interrupted write never leaves a truncated file, and
    processes writing the same path at once each rename a whole file of their own. ``sync``:
    flush the file to disk before the rename (off for bulk data that is cheap to regenerate).
    A symlink at ``path`` is replaced by the file, never written through."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp's 0600 -> what open() would have made
        with os.fdopen(fd, "wb") as f:
            write(f)
            if sync:  # the rename never publishes an unwritten file
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def open_regular_file(path: str | Path, flags: int, what: str) -> int:
    """``os.open(path, flags | O_CREAT)`` (mode 0666 less the umask) that refuses, with a
    :class:`NotARegularFileError` naming ``path`` and ``what`` it is, a symlink at ``path``
    (``O_NOFOLLOW``) or anything but a regular file there (checked on the opened file; a FIFO
    without a reader is refused, not waited on). Returns the descriptor (close-on-exec); ``flags``
    hold the access mode and e.g. ``O_APPEND`` or ``O_TRUNC`` (applied once the file is known to
    be a regular one)."""
    path = Path(path)
    truncate = bool(flags & os.O_TRUNC)
    flags = (flags & ~os.O_TRUNC) | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK
    try:
        fd = os.open(path, flags, 0o666)
    except OSError:
        if not (path.is_symlink() or _special(path)):
            raise
        raise NotARegularFileError(_refusal(path, what)) from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise NotARegularFileError(_refusal(path, what))
        os.set_blocking(fd, True)
        if truncate:
            os.ftruncate(fd, 0)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _special(path: Path) -> bool:
    """Whether ``path`` is there and is not a regular file (not following a symlink)."""
    try:
        return not stat.S_ISREG(os.lstat(path).st_mode)
    except FileNotFoundError:
        return False


def _refusal(path: Path, what: str) -> str:
    try:
        mode = os.lstat(path).st_mode
        found = (f"a symlink to {os.readlink(path)}" if stat.S_ISLNK(mode)
                 else f"not a regular file ({stat.filemode(mode)})")  # fmt: skip
    except OSError:  # replaced meanwhile
        found = "not a regular file"
    return (
        f"{path}: {found}, expected {what} as a regular file; a link or special file at that "
        "name is never written through: remove it"
    )
