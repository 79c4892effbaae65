"""Proposal trajectories over a history of per-frame proposal sets (PTT's association).

All boxes are ``(R, 9)`` ``[x, y, z, dx, dy, dz, heading, vx, vy]`` in the current vehicle
frame (history proposals moved there with their poses:
:func:`pcdet_atlas.datasets.proposal_history.history_to_current`), velocity in m/s. A
trajectory starts at a current proposal and walks back one frame at a time: the box of frame ``i``
is predicted from frame ``i - 1``'s by moving it ``-0.1 v`` (its velocity turned into
the backward displacement of one frame); the proposal of frame ``i`` with the highest 3D IoU
with the prediction (the first of equals) replaces it when that IoU reaches ``iou_thresh``
(0.5), else the prediction is kept. Frames before the start of the sequence are padding:
``valid`` False, and their boxes continue the prediction (so features computed from them stay
finite; the model masks them).

The walk is computed without a step per frame. A trajectory's box at frame ``i`` is always the
last proposal it took (or the current one), moved back once per frame since: a *candidate*
(any proposal of any frame) and a step count. So every candidate's moved boxes are computed at
once, the 3D IoUs of each of them with the proposals of each later frame in one grouped call,
and from those a table per frame of where each candidate leads (itself, or the proposal it
takes there). A trajectory's candidate at frame ``i`` is then the composition of the tables of
frames ``1 .. i``, applied to its current proposal: an inclusive scan by doubling
(``ceil(log2 H)`` gathers). The moved boxes repeat the one-frame move step by step (one
subtraction per frame over all candidates), so every box is the same float as the walk's.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from pcdet_atlas.datasets.multiframe import SECONDS_PER_FRAME
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d_grouped

__all__ = ["associate_trajectories", "future_boxes"]


def associate_trajectories(
    current: torch.Tensor,
    history: Sequence[torch.Tensor | None],
    iou_thresh: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Follow each current proposal back through ``history`` (module docstring).

    Args:
        current: ``(R, 9)`` the current frame's proposals (finite).
        history: for frames ``t-1, t-2, ...``: that frame's proposals ``(R_i, 9)`` in the current
            vehicle frame (finite, one dtype for all frames), or ``None`` for a frame before the
            start of the sequence (it and every older frame are padding).
        iou_thresh: the 3D IoU a proposal needs with the prediction to be taken.
    Returns:
        ``boxes`` ``(1 + H, R, 9)`` (frame 0 = ``current``), ``matched`` ``(1 + H, R)`` bool (a
        proposal of that frame was taken; frame 0 True), ``valid`` ``(1 + H, R)`` bool (False on
        padding frames).
    Raises:
        ValueError: a proposal set of another width or dtype than ``current``'s, or a
            non-finite box.
    """
    num, width = current.shape
    device, dtype = current.device, current.dtype
    horizon = len(history)
    real = next((i for i, props in enumerate(history) if props is None), horizon)
    props = list(history[:real])  # the frames that exist: t-1 .. t-real
    for i, frame in enumerate(props, start=1):
        if frame.dim() != 2 or frame.shape[1] != width or frame.dtype != dtype:
            raise ValueError(
                f"associate_trajectories: history frame t-{i} has {frame.dtype} proposals of "
                f"shape {tuple(frame.shape)}, expected {dtype} (R_i, {width}) like the current"
            )
    frame_valid = torch.arange(1 + horizon, device=device) <= real  # (1 + H,)
    if num == 0:
        empty = current.new_zeros(1 + horizon, 0, width)
        none = torch.zeros(1 + horizon, 0, dtype=torch.bool, device=device)
        return empty, none, none.clone()
    sizes = torch.tensor([num] + [p.shape[0] for p in props], device=device)  # (1 + real,)
    cand = torch.cat([current, *(p.to(device) for p in props)])  # (C, 9) every candidate
    if not bool(torch.isfinite(cand).all()):
        raise ValueError("associate_trajectories: a current or history proposal is not finite")
    count = cand.shape[0]
    source = torch.repeat_interleave(torch.arange(1 + real, device=device), sizes)  # (C,) frame
    offset = torch.cumsum(sizes, 0) - sizes  # (1 + real,) first candidate of each frame

    # every candidate moved back 0 .. H frames, one subtraction per frame as the walk does
    step = SECONDS_PER_FRAME * cand[:, 7:9]  # (C, 2)
    moved = cand.new_empty(1 + horizon, count, 2)
    moved[0] = cand[:, 0:2]
    for k in range(1, 1 + horizon):
        torch.sub(moved[k - 1], step, out=moved[k])

    # where each candidate leads: the frame and the proposal it takes first, found for the gaps
    # 1, 2-3, 4-7, ... in turn, each round for the candidates that have taken none yet
    taken_at = torch.full_like(source, 1 + horizon)  # (C,) frame of its first take (none: H+1)
    target = torch.arange(count, device=device)  # (C,) the candidate it takes there
    lo = 1
    while lo <= real:
        hi = 2 * lo - 1
        still_open = taken_at > horizon  # (C,) candidates that have taken none
        gaps = (torch.clamp(real - source, max=hi) - lo + 1).clamp(min=0) * still_open  # (C,)
        q_cand = torch.repeat_interleave(torch.arange(count, device=device), gaps)  # (Q,)
        lo, first_gap = 2 * lo, lo
        if q_cand.numel() == 0:
            continue
        q_gap = (
            torch.arange(q_cand.shape[0], device=device)
            - (torch.cumsum(gaps, 0) - gaps)[q_cand]
            + first_gap
        )  # (Q,) ascending within a candidate
        q_frame = source[q_cand] + q_gap
        q_box = torch.cat([moved[q_gap, q_cand], cand[q_cand, 2:7]], dim=1)  # (Q, 7)
        q_index, p_index, iou = boxes_iou3d_grouped(
            q_box, q_frame, cand[num:, :7], source[num:], min_iou=iou_thresh
        )
        # the walk's max over the frame's proposals: IoU 0 for the pairs not returned, and the
        # first proposal among equals (the frame's first when nothing overlaps)
        best = iou.new_zeros(q_cand.shape[0]).scatter_reduce(
            0, q_index, iou, "amax", include_self=True
        )  # (Q,)
        first = torch.where(iou == best[q_index], num + p_index, count)
        first = torch.full_like(q_cand, count).scatter_reduce(
            0, q_index, first, "amin", include_self=True
        )
        first = torch.where(best > 0, first, offset[q_frame])  # (Q,) a candidate
        hit = ((best >= iou_thresh) & (sizes[q_frame] > 0)).nonzero()[:, 0]  # (Q_hit,)
        # each candidate's first hit: its smallest query index (queries ascend by gap)
        earliest = torch.full_like(source, q_cand.shape[0]).scatter_reduce(
            0, q_cand[hit], hit, "amin", include_self=True
        )  # (C,)
        found = (earliest < q_cand.shape[0]).nonzero()[:, 0]
        taken_at[found] = q_frame[earliest[found]]
        target[found] = first[earliest[found]]

    # per frame, where each candidate is after it; then an inclusive scan by doubling: after it,
    # table[i - 1] is frames 1 .. i composed
    table = torch.arange(count, device=device).repeat(max(real, 1), 1)  # (real, C): c -> c
    took = (taken_at <= real).nonzero()[:, 0]
    table[taken_at[took] - 1, took] = target[took]
    shift = 1
    while shift < real:
        table = torch.cat([table[:shift], torch.gather(table[shift:], 1, table[:-shift])])
        shift *= 2

    # each trajectory's candidate per frame; padding frames keep the last real one
    frames = torch.arange(1 + horizon, device=device)
    last = torch.clamp(frames, max=real) - 1  # (1 + H,) -1: frame 0
    state = torch.where(
        last[:, None] >= 0, table[last.clamp(min=0), :num], torch.arange(num, device=device)
    )  # (1 + H, R)
    steps = frames[:, None] - source[state]  # (1 + H, R) frames moved since taken
    boxes = torch.cat([moved[steps, state], cand[state, 2:]], dim=-1)  # (1 + H, R, 9)
    matched = steps == 0
    valid = frame_valid[:, None].repeat(1, num)
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
