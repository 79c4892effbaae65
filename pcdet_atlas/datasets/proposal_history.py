"""A frame's proposal history: the RPN proposals of its previous frames, moved into its own
vehicle frame (the input of PTT; docs/model_zoo.md, "PTT").

Proposals are float32 rows ``[x, y, z, dx, dy, dz, heading, vx, vy, score, label]`` (``(R, 11)``,
label 1-based) in the vehicle frame of the frame they were predicted on, as the proposal cache
and the proposal bank hold them. The history of frame ``t`` stacks, for ``k = 1 .. H``, frame
``t - k``'s proposals moved by the relative pose ``pose_t^-1 pose_{t-k}`` (centre by the pose,
heading plus the poses' yaw difference, velocity rotated) with ``k`` appended as a 12th column.
Frames before the start of the sequence do not exist: the history then holds
``min(H, t)`` frames and the model masks the rest.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pcdet_atlas.ops.boxes import transform_boxes

__all__ = [
    "HISTORY_COLUMNS", "PROPOSAL_COLUMNS", "PROPOSAL_KEYS", "gather_history", "history_to_current",
]  # fmt: skip

#: the sample keys of two-stage training proposals (world augmentations move them with the boxes)
PROPOSAL_KEYS = ("roi_boxes", "roi_history")
#: columns of a proposal row: box (9), score, label
PROPOSAL_COLUMNS = 11
#: columns of a history row: a proposal row plus the number of frames back (1 .. H)
HISTORY_COLUMNS = 12


def history_to_current(boxes, pose_then, pose_now) -> np.ndarray:
    """Boxes ``(R, 9)`` of an earlier frame, in that frame's vehicle frame (pose ``pose_then``,
    vehicle -> world ``(4, 4)``), moved into the vehicle frame of pose ``pose_now``: centre by the
    relative pose, heading plus the poses' yaw difference (wrapped), velocity rotated. Computed
    in float64, returned in the input's dtype."""
    boxes = np.asarray(boxes)
    then = np.asarray(pose_then, dtype=np.float64).reshape(4, 4)
    now = np.asarray(pose_now, dtype=np.float64).reshape(4, 4)
    moved = transform_boxes(boxes.astype(np.float64), np.linalg.inv(now) @ then)
    return moved.astype(boxes.dtype)


def gather_history(
    lookup: Callable[[int], np.ndarray],
    pose_of: Callable[[int], np.ndarray],
    sample_idx: int,
    num_history: int,
) -> tuple[np.ndarray, int]:
    """The proposal history of frame ``sample_idx`` (module docstring).

    Args:
        lookup: frame index -> that frame's proposals ``(R, 11)`` in its own vehicle frame.
        pose_of: frame index -> its vehicle -> world ``(4, 4)`` pose.
        sample_idx: the current frame; num_history: ``H``, how many previous frames to take.
    Returns:
        ``(rows (N, 12) float64, count)``: the rows of frames ``t-1 .. t-count`` (newest first),
        ``count = min(H, sample_idx)``.
    """
    if num_history < 0:
        raise ValueError(f"num_history must be >= 0, got {num_history}")
    count = min(int(num_history), int(sample_idx))
    now = pose_of(sample_idx)
    parts = []
    for back in range(1, count + 1):
        props = np.asarray(lookup(sample_idx - back))
        if props.ndim != 2 or props.shape[1] != PROPOSAL_COLUMNS:
            raise ValueError(
                f"proposals of frame {sample_idx - back} must be (R, {PROPOSAL_COLUMNS}), got "
                f"{props.shape}"
            )
        rows = np.empty((len(props), HISTORY_COLUMNS), dtype=np.float64)
        rows[:, :9] = history_to_current(
            props[:, :9].astype(np.float64), pose_of(sample_idx - back), now
        )
        rows[:, 9:11] = props[:, 9:11]
        rows[:, 11] = back
        parts.append(rows)
    if not parts:
        return np.zeros((0, HISTORY_COLUMNS), dtype=np.float64), count
    return np.concatenate(parts, axis=0), count
