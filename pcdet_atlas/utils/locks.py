"""One writer per output folder: an exclusive lock a run holds while it writes there.

The lock is ``flock`` on ``.<folder name>.lock`` beside the folder (inside it, ``--overwrite``
would delete it with the folder's files). The kernel releases a ``flock`` when its holder dies, so
a killed run leaves no lock to clear by hand; the file records the holder's PID, host and start
time for the message of a second run, and is removed when the holder releases it. A symlink or
anything but a regular file at the lock's name (planted in a folder received from someone else)
is refused, never followed: the lock file is truncated and rewritten by its holder.
"""

from __future__ import annotations

import datetime
import fcntl
import json
import os
import socket
from pathlib import Path

from pcdet_atlas.utils.files import open_regular_file

__all__ = ["FolderLock", "FolderLockedError", "lock_path"]


class FolderLockedError(RuntimeError):
    """The folder's lock is held by another run (or by another lock of this process)."""


def lock_path(folder: str | Path) -> Path:
    """The lock file of ``folder`` (symlinks resolved, so two names of a folder share one)."""
    real = Path(folder).resolve()
    if real == real.parent:
        raise ValueError(f"{folder}: a file system root cannot be locked as an output folder")
    return real.parent / f".{real.name}.lock"


class FolderLock:
    """An exclusive lock on ``folder`` for one run (``purpose``: what it writes there, for the
    message a second run gets). ``with FolderLock(folder, "training"):`` or
    :meth:`acquire` / :meth:`release`; a lock already held raises :class:`FolderLockedError`
    at once, naming the folder and the holder's PID, host and start time; a lock path that is a
    symlink or not a regular file, a :class:`~pcdet_atlas.utils.files.NotARegularFileError`
    naming it."""

    def __init__(self, folder: str | Path, purpose: str):
        self.folder = Path(folder)
        self.purpose = purpose
        self.path = lock_path(folder)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> FolderLock:
        if self._fd is not None:
            raise RuntimeError(f"{self.path}: this FolderLock is held already")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = open_regular_file(self.path, os.O_RDWR, f"the lock file of {self.folder}")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _describe_holder(fd)
                os.close(fd)
                raise FolderLockedError(
                    f"{self.folder} is in use: {holder} holds its lock {self.path}; wait for that "
                    "run to end, or write into another folder"
                ) from None
            except BaseException:
                os.close(fd)
                raise
            # a holder releasing meanwhile unlinks the file we opened: lock the one at the path
            if _same_file(fd, self.path):
                break
            os.close(fd)
        record = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "purpose": self.purpose,
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Remove the lock file and unlock (also for processes forked meanwhile that share the
        open file, such as data loader workers). Releasing a lock not held does nothing."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if _same_file(fd, self.path):  # not a file someone put there after deleting ours
                self.path.unlink()
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` itself (not a symlink's target) is the file open as ``fd``."""
    try:
        return os.path.samestat(os.fstat(fd), os.lstat(path))
    except FileNotFoundError:
        return False


def _describe_holder(fd: int) -> str:
    """``'training by PID 123 on host, started 2026-...'`` from the lock file's record."""
    text = os.pread(fd, 4096, 0).decode(errors="replace")
    try:
        record = json.loads(text)
        holder = (
            f"{record['purpose']} by PID {record['pid']} on {record['host']}, started "
            f"{record['started']}"
        )
        pid, host = int(record["pid"]), record["host"]
    except (ValueError, TypeError, KeyError):
        return f"a run that has not recorded itself yet (lock file content {text[:200]!r})"
    if host == socket.gethostname() and not _alive(pid):
        holder += (
            " (gone; a process it forked, such as a data loader worker, holds it until it ends)"
        )
    return holder


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
