"""The temporal spoofing schedule and the lifecycle positions (docs/attacks.md, docs/evaluation.md).

Frame ``i`` of a sequence is spoofed iff ``floor(i / W) mod 2 = 1`` (``s_0 = 0`` always), with the
window ``W = 32`` by default. A *run* is a maximal block of spoofed frames: frames 32-63, 96-127
and 160-191 of a 198-frame Waymo sequence. A run that reaches the end of a short sequence is
truncated there (a 50-frame sequence has the single run 32-49).

Lifecycle positions (docs/evaluation.md), relative to run ``r`` starting at frame ``start``:
``k = i - start + 1``, i.e. ``k = 0`` for the last clean frame before onset, ``k = 1..W`` for
the spoofed frames and ``k = W+1..2W`` for the W clean frames after a full run. Because the gap
between two runs is exactly ``W`` frames, frame ``start_{r+1} - 1`` is both ``k = 2W`` of run
``r`` and ``k = 0`` of run ``r+1``; :func:`lifecycle_positions` returns both memberships, and
:func:`lifecycle_of_frame` picks one by a documented rule (the upcoming run's onset wins).

Everything here is pure integer arithmetic on frame indices; no frame data is touched.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "DEFAULT_WINDOW",
    "is_spoofed",
    "spoof_schedule",
    "schedule_runs",
    "num_runs",
    "run_bounds",
    "run_of_frame",
    "lifecycle_positions",
    "lifecycle_of_frame",
    "lifecycle_frames",
]

#: Frames per spoofed/clean window (ATLAS: 32 frames = 3.2 s at 10 Hz).
DEFAULT_WINDOW = 32


def _check_window(window: int) -> int:
    if isinstance(window, bool) or int(window) != window or int(window) < 1:
        raise ValueError(f"schedule window must be a positive integer, got {window!r}")
    return int(window)


def _check_num_frames(num_frames: int) -> int:
    if isinstance(num_frames, bool) or int(num_frames) != num_frames or int(num_frames) < 0:
        raise ValueError(f"num_frames must be a non-negative integer, got {num_frames!r}")
    return int(num_frames)


def _check_frame(frame_idx: int, num_frames: int) -> int:
    if isinstance(frame_idx, bool) or int(frame_idx) != frame_idx:
        raise ValueError(f"frame index must be an integer, got {frame_idx!r}")
    if not 0 <= int(frame_idx) < num_frames:
        raise ValueError(f"frame index {frame_idx} outside a sequence of {num_frames} frames")
    return int(frame_idx)


def is_spoofed(frame_idx: int, window: int = DEFAULT_WINDOW) -> bool:
    """``s_i = 1[floor(i / W) mod 2 = 1]`` for one frame index ``i >= 0`` (``s_0 = 0``)."""
    window = _check_window(window)
    if isinstance(frame_idx, bool) or int(frame_idx) != frame_idx or int(frame_idx) < 0:
        raise ValueError(f"frame index must be a non-negative integer, got {frame_idx!r}")
    return (int(frame_idx) // window) % 2 == 1


def spoof_schedule(num_frames: int, window: int = DEFAULT_WINDOW) -> np.ndarray:
    """The schedule of a sequence.

    Returns:
        ``(num_frames,)`` bool ndarray, ``True`` where the frame is spoofed.
    """
    num_frames = _check_num_frames(num_frames)
    window = _check_window(window)
    return (np.arange(num_frames) // window) % 2 == 1


def schedule_runs(schedule) -> list[tuple[int, int]]:
    """Maximal blocks of spoofed frames of any bool schedule (ndarray, tensor or list).

    Returns:
        ``[(start, end_inclusive), ...]`` in frame order.
    """
    s = np.asarray(schedule, dtype=bool).reshape(-1)
    if s.size == 0:
        return []
    padded = np.concatenate([[False], s, [False]]).astype(np.int8)
    edges = np.diff(padded)
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def num_runs(num_frames: int, window: int = DEFAULT_WINDOW) -> int:
    """Number of runs of the formula schedule in a ``num_frames`` sequence."""
    num_frames = _check_num_frames(num_frames)
    window = _check_window(window)
    # run r starts at (2r + 1) W; it exists iff that frame is in the sequence
    return (num_frames + window - 1) // (2 * window)


def run_bounds(run_id: int, num_frames: int, window: int = DEFAULT_WINDOW) -> tuple[int, int]:
    """``(start, end_inclusive)`` of run ``run_id`` (truncated at the end of the sequence)."""
    num_frames = _check_num_frames(num_frames)
    window = _check_window(window)
    n = num_runs(num_frames, window)
    if isinstance(run_id, bool) or int(run_id) != run_id or not 0 <= int(run_id) < n:
        raise ValueError(f"run_id {run_id!r} outside [0, {n}) for {num_frames} frames, W={window}")
    start = (2 * int(run_id) + 1) * window
    return start, min(start + window, num_frames) - 1


def run_of_frame(frame_idx: int, num_frames: int, window: int = DEFAULT_WINDOW) -> tuple[int, int]:
    """Run id and 0-based position within the run of a frame; ``(-1, -1)`` for a clean frame."""
    num_frames = _check_num_frames(num_frames)
    window = _check_window(window)
    i = _check_frame(frame_idx, num_frames)
    block = i // window
    if block % 2 == 0:
        return -1, -1
    return (block - 1) // 2, i - block * window


def lifecycle_positions(
    frame_idx: int, num_frames: int, window: int = DEFAULT_WINDOW
) -> list[tuple[int, int]]:
    """Every lifecycle membership ``(run_id, k)`` of a frame, sorted by run id.

    ``k = frame_idx - start + 1`` in ``0..2W`` for each run whose lifecycle (the frame before
    onset, the run, and the ``W`` frames after it) contains the frame. Frames after a truncated
    final run do not exist, so such a run has no ``k > W`` frames. A frame is in at most two
    lifecycles (``k = 2W`` of run ``r`` and ``k = 0`` of run ``r + 1``).
    """
    num_frames = _check_num_frames(num_frames)
    window = _check_window(window)
    i = _check_frame(frame_idx, num_frames)
    out = []
    # run r covers frames start_r - 1 .. start_r + 2W - 1, start_r = (2r + 1) W
    r_lo = max(0, (i - window) // (2 * window))
    r_hi = (i + 1 - window) // (2 * window)
    for r in range(r_lo, r_hi + 1):
        start = (2 * r + 1) * window
        if start >= num_frames:
            continue
        k = i - start + 1
        if 0 <= k <= 2 * window:
            out.append((r, k))
    return out


def lifecycle_of_frame(
    frame_idx: int, num_frames: int, window: int = DEFAULT_WINDOW
) -> tuple[int, int]:
    """The one lifecycle position ``(run_id, k)`` recorded for a frame; ``(-1, -1)`` if none.

    Where a frame belongs to two lifecycles (``k = 2W`` of run ``r`` and ``k = 0`` of run
    ``r + 1``), the upcoming run's onset ``(r + 1, 0)`` is returned: the clean frame just before
    onset is every run's reference point, whereas ``k = 2W`` is the last frame of a decay tail.
    Use :func:`lifecycle_positions` to get both.
    """
    pos = lifecycle_positions(frame_idx, num_frames, window)
    if not pos:
        return -1, -1
    return pos[-1]


def lifecycle_frames(
    run_id: int, num_frames: int, window: int = DEFAULT_WINDOW
) -> list[tuple[int, int]]:
    """``[(frame_idx, k), ...]`` of one run's lifecycle that exist in the sequence, by frame."""
    start, _ = run_bounds(run_id, num_frames, window)
    window = int(window)
    first, last = start - 1, min(start + 2 * window - 1, num_frames - 1)
    return [(i, i - start + 1) for i in range(max(first, 0), last + 1)]
