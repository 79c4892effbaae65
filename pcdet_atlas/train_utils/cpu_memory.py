"""Keep freed CPU memory in the process for reuse (glibc ``mallopt``).

A CPU training step of the pillar models allocates and frees tensors of hundreds of MB (per-point
features of ~2.4 M points for a CP-4f batch of 4). glibc serves such blocks with ``mmap`` and
returns them with ``munmap`` on free, so every step faults all of that memory in again page by
page (~1.1 M minor page faults per CP-4f step) and the kernel zeroes each page; on a 2-core CPU
this cost more than the arithmetic (measured in ``docs/benchmarks.md``, "Training step").
Serving large blocks from the heap (``M_MMAP_MAX = 0``) and not trimming it
(``M_TRIM_THRESHOLD`` = 2 GiB - 1) lets the allocator reuse the pages of the previous step.
Nothing computed changes; the process keeps its peak heap resident (a few GB for CP-4f).
The same can be had without code through the environment
(``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=2147483647``), or with jemalloc / tcmalloc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["retain_freed_cpu_memory", "trim_cpu_memory"]

# glibc <malloc.h> parameter numbers
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
INT_MAX = 2**31 - 1


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def retain_freed_cpu_memory() -> bool:
    """Tell glibc's malloc to keep freed memory for reuse (process-wide, irreversible here).

    Call it once, early, in a training process (forked loader workers inherit it). Returns
    True if the settings were applied, False where there is no glibc ``mallopt`` (other
    platforms / C libraries), in which case nothing changes.
    """
    mallopt = getattr(_libc(), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, INT_MAX) == 1


def trim_cpu_memory() -> bool:
    """Give the free memory of the heap back to the OS now (glibc ``malloc_trim(0)``).

    With :func:`retain_freed_cpu_memory` the heap keeps what it once held, and steps of varying
    sizes fragment it over a long run; the trainer calls this every ``--trim_every`` steps and at
    each epoch's end, each time one step's worth of page faults. Returns False where there is no
    ``malloc_trim``.
    """
    malloc_trim = getattr(_libc(), "malloc_trim", None)
    if malloc_trim is None:
        return False
    malloc_trim.argtypes = [ctypes.c_size_t]
    malloc_trim(0)
    return True
