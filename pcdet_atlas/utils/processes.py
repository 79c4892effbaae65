"""Child processes that do not outlive the process that started them."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from collections.abc import Callable

__all__ = ["die_with_parent", "tie_to_parent"]

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def tie_to_parent(sig: int = signal.SIGKILL) -> None:
    """Have the kernel send this process ``sig`` when its parent dies, even by SIGKILL (Linux
    ``prctl(PR_SET_PDEATHSIG)``; nothing elsewhere): for a child that was forked, not started by
    ``subprocess``, such as a data loader worker. A worker whose parent is killed while it hands
    over a batch can otherwise block for ever on the pipe nobody reads, holding the files and
    the output folder's lock it inherited. If the parent died already, this process ends now.

    Raises:
        OSError: the kernel refused the call.
    """
    if not sys.platform.startswith("linux"):
        return
    _set_death_signal(ctypes.CDLL(None, use_errno=True).prctl, sig, os.getppid())


def _set_death_signal(prctl, sig: int, parent: int) -> None:
    if prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:  # subprocess raises in the parent
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if parent == 1 or os.getppid() != parent:  # orphaned before prctl took effect
        os._exit(128 + int(sig))


def die_with_parent(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A ``preexec_fn`` for ``subprocess`` that has the kernel send the child ``sig`` when its
    parent dies, even by SIGKILL (Linux ``prctl(PR_SET_PDEATHSIG)``), so a killed tool leaves no
    orphan writing its outputs. The signal follows the death of the parent's *thread* that
    started the child: start it from a thread that waits for it (``subprocess.run``).

    Returns None off Linux, where no such kernel call exists (``preexec_fn=None``: the child
    is not tied to its parent there).
    """
    if not sys.platform.startswith("linux"):
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here: the child only calls it
    parent = os.getpid()

    def preexec() -> None:
        _set_death_signal(prctl, sig, parent)

    return preexec
