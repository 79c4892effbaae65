"""Child processes that do not outlive the process that started them."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from collections.abc import Callable

__all__ = ["die_with_parent"]

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


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
        if prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:  # subprocess raises in the parent
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        if os.getppid() != parent:  # the parent died before prctl took effect
            os._exit(128 + int(sig))

    return preexec
