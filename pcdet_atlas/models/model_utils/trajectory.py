"""Proposal trajectories over a history of per-frame proposal sets (PTT's association).

All boxes are ``(R, 9)`` ``[x, y, z, dx, dy, dz, heading, vx, vy]`` in the current vehicle
frame (history proposals moved there with their poses:
:func:`pcdet_atlas.datasets.proposal_history.history_to_current`), velocity in m/s. A
trajectory starts at a current proposal and walks back one frame at a time: the box of frame ``i``
is predicted from frame ``i - 1``'s by moving it ``-0.1 v`` (its velocity turned into
the backward displacement of one frame); the proposal of frame ``i`` with the highest 3D IoU
with the prediction replaces it when that IoU reaches ``iou_thresh`` (0.5), else the prediction is
kept. Frames before the start of the sequence are padding: ``valid`` False, and their boxes
continue the prediction (so features computed from them stay finite; the model masks them).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from pcdet_atlas.datasets.multiframe import SECONDS_PER_FRAME
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d

__all__ = ["associate_trajectories", "future_boxes"]


def associate_trajectories(
    current: torch.Tensor,
    history: Sequence[torch.Tensor | None],
    iou_thresh: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Follow each current proposal back through ``history`` (module docstring).

    Args:
        current: ``(R, 9)`` the current frame's proposals.
        history: for frames ``t-1, t-2, ...``: that frame's proposals ``(R_i, 9)`` in the current
            vehicle frame, or ``None`` for a frame before the start of the sequence (it and every
            older frame are padding).
        iou_thresh: the 3D IoU a proposal needs with the prediction to be taken.
    Returns:
        ``boxes`` ``(1 + H, R, 9)`` (frame 0 = ``current``), ``matched`` ``(1 + H, R)`` bool (a
        proposal of that frame was taken; frame 0 True), ``valid`` ``(1 + H, R)`` bool (False on
        padding frames).
    """
    num = current.shape[0]
    frames = 1 + len(history)
    boxes = current.new_zeros(frames, num, current.shape[1])
    matched = torch.zeros(frames, num, dtype=torch.bool, device=current.device)
    valid = torch.zeros(frames, num, dtype=torch.bool, device=current.device)
    boxes[0], matched[0], valid[0] = current, True, True
    started = True
    for i, props in enumerate(history, start=1):
        pred = boxes[i - 1].clone()
        pred[:, 0:2] = pred[:, 0:2] - SECONDS_PER_FRAME * pred[:, 7:9]
        boxes[i] = pred
        started = started and props is not None  # padding from the sequence start on
        valid[i] = started
        if not started or props.shape[0] == 0 or num == 0:
            continue
        iou, index = boxes_iou3d(pred[:, :7], props[:, :7]).max(dim=1)
        hit = iou >= iou_thresh
        boxes[i, hit] = props[index[hit]].to(boxes.dtype)
        matched[i] = hit
    return boxes, matched, valid


def future_boxes(current: torch.Tensor, count: int) -> torch.Tensor:
    """``(count, R, 9)`` boxes of frames ``t + count, ..., t + 1`` (farthest first, PTT's order):
    the current boxes moved ``+0.1 k v``."""
    steps = torch.arange(count, 0, -1, dtype=current.dtype, device=current.device)
    out = current[None].repeat(count, 1, 1)
    out[:, :, 0:2] = (
        current[None, :, 0:2] + SECONDS_PER_FRAME * steps[:, None, None] * (current[None, :, 7:9])
    )
    return out
