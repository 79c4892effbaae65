"""Motion-guided point sampling of temporal two-stage heads (MSF; PTT's current-frame pooling).

A proposal of the current frame is propagated backwards along its velocity (MSF: the box of
frame ``t - i`` is the current box moved by ``-0.1 i v``, size, height and heading unchanged).
For each propagated box, up to ``num_sample`` points of that frame are drawn from the vertical
cylinder around its centre of radius ``gamma^(i + 1) * ||(dx / 2, dy / 2)||`` (the paper's radius
growing with the frame's age; ``radius_growth=False`` gives the released code's constant
``gamma * ||(dx / 2, dy / 2)||``).

Which points are drawn: every point of a sample gets one uniform key from the sample's
generator (one ``torch.rand`` over the sample's points, in their order); a box takes the
``num_sample`` points of its cylinder with the smallest keys (a uniform random subset, as the
released code's permutation-then-first-k). Slots left over are zero with ``valid`` False.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from pcdet_atlas.datasets.multiframe import SECONDS_PER_FRAME

__all__ = [
    "frame_of_points",
    "propagate_boxes",
    "sample_batch_points",
    "sample_cylinder_points",
    "sampling_radius",
]

#: A point belongs to frame ``i`` when its time lag is within this of ``0.1 i`` s.
LAG_TOLERANCE_S = 0.25 * SECONDS_PER_FRAME


def propagate_boxes(boxes: torch.Tensor, num_frames: int) -> torch.Tensor:
    """``(T, R, 7)`` boxes of frames ``t, t-1, ..., t-T+1`` from current boxes ``(R, 9)`` with
    velocity ``(vx, vy)`` in m/s: frame ``i`` is moved by ``-0.1 i (vx, vy)``."""
    if boxes.dim() != 2 or boxes.shape[1] < 9:
        raise ValueError(f"propagate_boxes: need (R, 9) boxes with velocity, got {boxes.shape}")
    steps = torch.arange(num_frames, dtype=boxes.dtype, device=boxes.device)
    traj = boxes[None, :, :7].repeat(num_frames, 1, 1)
    traj[:, :, 0:2] = (
        boxes[None, :, 0:2] - SECONDS_PER_FRAME * steps[:, None, None] * boxes[None, :, 7:9]
    )
    return traj


def sampling_radius(boxes: torch.Tensor, frame: int, gamma: float, radius_growth: bool):
    """``(R,)`` cylinder radii of frame ``frame``'s boxes ``(R, 7)`` (module docstring)."""
    factor = gamma ** (frame + 1) if radius_growth else gamma
    return factor * torch.linalg.vector_norm(boxes[:, 3:5] / 2, dim=1)


def frame_of_points(lag_s: torch.Tensor, num_frames: int) -> torch.Tensor:
    """``(N,)`` long frame index ``i`` of points with time lag ``0.1 i`` s; -1 for a lag that is
    none of ``0 .. num_frames - 1`` frames."""
    index = torch.round(lag_s / SECONDS_PER_FRAME)
    ok = ((lag_s - index * SECONDS_PER_FRAME).abs() <= LAG_TOLERANCE_S) & (index >= 0)
    ok &= index < num_frames
    return torch.where(ok, index, torch.full_like(index, -1)).long()


def sample_cylinder_points(
    points: torch.Tensor,
    frame_index: torch.Tensor,
    trajectories: torch.Tensor,
    *,
    num_sample: int,
    gamma: float,
    radius_growth: bool,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw the points of one sample for each box of each frame.

    Args:
        points: ``(N, C)`` the sample's points, ``x, y, z`` first (any further columns are
            carried along).
        frame_index: ``(N,)`` long, the frame of each point (:func:`frame_of_points`; -1 never
            sampled).
        trajectories: ``(T, R, 7)`` boxes per frame (:func:`propagate_boxes`).
        generator: a CPU ``torch.Generator`` (the keys are drawn on the CPU, then moved).
    Returns:
        ``(R, T, num_sample, C)`` points (zero where invalid) and ``(R, T, num_sample)`` bool
        validity.
    """
    num_frames, num_boxes = trajectories.shape[0], trajectories.shape[1]
    keys = torch.rand(points.shape[0], generator=generator, dtype=torch.float64)
    keys = keys.to(points.device)
    out = points.new_zeros(num_boxes, num_frames, num_sample, points.shape[1])
    valid = torch.zeros(num_boxes, num_frames, num_sample, dtype=torch.bool, device=points.device)
    if points.shape[0] == 0 or num_boxes * num_frames == 0:
        return out, valid
    # all frames at once: box slot f * R + r is box r of frame f and pairs with frame f's points
    radius = torch.cat(
        [sampling_radius(trajectories[f], f, gamma, radius_growth) for f in range(num_frames)]
    )
    slot_frame = torch.arange(num_frames, device=points.device).repeat_interleave(num_boxes)
    slot, point_id = cylinder_pairs(
        points[:, 0:2], trajectories[..., 0:2].reshape(-1, 2), radius,
        point_group=frame_index, box_group=slot_frame,
    )  # fmt: skip
    # per slot, its candidates in increasing key order (ties: candidate order); the first
    # num_sample are drawn
    order = _sort_within_slots(slot, keys.index_select(0, point_id), num_frames * num_boxes)
    slot, point_id = slot.index_select(0, order), point_id.index_select(0, order)
    count = torch.bincount(slot, minlength=num_frames * num_boxes)
    first = torch.cumsum(count, 0) - count
    rank = torch.arange(slot.numel(), device=slot.device) - first.index_select(0, slot)
    take = torch.nonzero(rank < num_sample).squeeze(1)
    slot, point_id, rank = (t.index_select(0, take) for t in (slot, point_id, rank))
    frame, box = torch.div(slot, num_boxes, rounding_mode="floor"), slot % num_boxes
    out[box, frame, rank] = points.index_select(0, point_id)
    valid[box, frame, rank] = True
    return out, valid


#: Bits of a sampling key: ``torch.rand`` draws float64 on a ``2^-53`` grid, so ``key * 2^53``
#: is an exact integer below ``2^53``; the slot takes the 10 bits above it in one int64.
_KEY_BITS = 53
_SLOT_BITS = 63 - _KEY_BITS


def _sort_within_slots(slot: torch.Tensor, key: torch.Tensor, num_slots: int) -> torch.Tensor:
    """The permutation of pairs that sorts them by ``(slot, key)``, ties in their given order;
    ``slot`` ``(P,)`` long non-decreasing, ``key`` ``(P,)`` float64 in ``[0, 1)`` on the
    ``2^-53`` grid. One stable sort of ``slot << 53 | key * 2^53`` per run of ``2^10`` slots."""
    key_int = (key * float(2**_KEY_BITS)).long()
    order = torch.empty_like(slot)
    step = 1 << _SLOT_BITS
    bounds = torch.arange(0, num_slots + step, step, device=slot.device).clamp_max(num_slots)
    edges = torch.searchsorted(slot, bounds).tolist()
    for chunk, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        if hi > lo:
            local = (slot[lo:hi] - chunk * step) << _KEY_BITS | key_int[lo:hi]
            order[lo:hi] = torch.sort(local, stable=True).indices + lo
    return order


def cylinder_pairs(
    xy: torch.Tensor,
    centers: torch.Tensor,
    radius: torch.Tensor,
    *,
    point_group: torch.Tensor | None = None,
    box_group: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every (box, point) pair with the point's XY within ``radius`` of the box centre, as two
    ``(P,)`` long index tensors sorted by box.

    ``point_group`` ``(N,)`` / ``box_group`` ``(R,)`` (long, both or neither; boxes' groups
    ``>= 0``): a box pairs only with the points of its own group (MSF: a frame); the points of
    no box's group (-1, say) are not read at all.

    Points are bucketed on a BEV grid whose cell is about half the median radius; a box measures
    only the points of the ``(2k + 1)^2`` cells around its centre, ``k = ceil(radius / cell +
    0.01)`` (the hundredth of a cell keeps a point on the cylinder's edge in its box's window
    whatever the rounding of the cell indices), so its candidates cover about twice its
    cylinder's area whatever the spread of the radii. Candidates of a box come cell by cell,
    each cell's points in index order.

    Gathers are ``index_select`` on contiguous tensors: on the CPU, advanced indexing takes a
    slower path, most of all on a strided view such as the points' XY columns."""
    if (point_group is None) != (box_group is None):
        raise ValueError("cylinder_pairs: pass both point_group and box_group, or neither")
    empty = torch.zeros(0, dtype=torch.long, device=xy.device)
    if xy.shape[0] == 0 or centers.shape[0] == 0:
        return empty, empty
    xy, centers = xy.contiguous(), centers.contiguous()
    num_groups, taken = 1, None  # taken: the points read, when not all of them
    if box_group is not None:
        if bool((box_group < 0).any()):
            raise ValueError("cylinder_pairs: box_group must be >= 0")
        num_groups = int(box_group.max()) + 1
        mine = (point_group >= 0) & (point_group < num_groups)
        if not bool(mine.all()):
            taken = torch.nonzero(mine).squeeze(1)
            xy, point_group = xy.index_select(0, taken), point_group.index_select(0, taken)
            if xy.shape[0] == 0:
                return empty, empty
    low = torch.minimum(xy.min(0).values, centers.min(0).values)
    high = torch.maximum(xy.max(0).values, centers.max(0).values)
    # half the median radius; coarser only to bound the grids (2^24 cells over all groups) and
    # the window of the largest box (64 cells each side)
    cell = max(float(radius.median()) / 2, float(radius.max()) / 64,
               float((high - low).max()) * num_groups**0.5 / 4096, 1e-3)  # fmt: skip
    reach = torch.ceil(radius / cell + 0.01).long().clamp_min(1)  # (R,) cells on each side
    margin = cell * (int(reach.max()) + 1)
    origin = low - margin
    width = int(torch.floor((high + margin - origin) / cell).max()) + 1
    point_cell = torch.floor((xy - origin) / cell).long()
    point_key = point_cell[:, 0] * width + point_cell[:, 1]
    center_cell = torch.floor((centers - origin) / cell).long()
    center_key = center_cell[:, 0] * width + center_cell[:, 1]
    grid = width * width
    if box_group is not None:  # group g's grid follows group g - 1's
        point_key = point_key + point_group * grid
        center_key = center_key + box_group * grid
    # the window of each box, flattened: box b owns side_b^2 consecutive entries
    side = 2 * reach + 1
    cells_per_box = side * side
    cell_box = torch.arange(centers.shape[0], device=xy.device).repeat_interleave(cells_per_box)
    first = torch.cumsum(cells_per_box, 0) - cells_per_box
    local = torch.arange(cell_box.numel(), device=xy.device) - first.index_select(0, cell_box)
    box_side, box_reach = side.index_select(0, cell_box), reach.index_select(0, cell_box)
    dx = torch.div(local, box_side, rounding_mode="floor") - box_reach
    dy = local % box_side - box_reach
    cell_key = center_key.index_select(0, cell_box) + dx * width + dy
    needed = torch.zeros(num_groups * grid, dtype=torch.bool, device=xy.device)
    needed[cell_key] = True
    # points in a cell some box looks at
    near = torch.nonzero(needed.index_select(0, point_key)).squeeze(1)
    sorted_key, order = torch.sort(point_key.index_select(0, near), stable=True)
    sorted_point = near.index_select(0, order)
    start = torch.searchsorted(sorted_key, cell_key, right=False)
    count = torch.searchsorted(sorted_key, cell_key, right=True) - start
    total = int(count.sum())
    if total == 0:
        return empty, empty
    box_id = cell_box.repeat_interleave(count)
    base = torch.cumsum(count, 0) - count
    within = torch.arange(total, device=xy.device) - base.repeat_interleave(count)
    point_id = sorted_point.index_select(0, start.repeat_interleave(count) + within)
    delta = xy.index_select(0, point_id) - centers.index_select(0, box_id)
    inside = (delta * delta).sum(1) <= radius.index_select(0, box_id) ** 2
    inside = torch.nonzero(inside).squeeze(1)
    box_id, point_id = box_id.index_select(0, inside), point_id.index_select(0, inside)
    if taken is not None:
        point_id = taken.index_select(0, point_id)
    return box_id, point_id


def sample_batch_points(
    points: torch.Tensor,
    trajectories: torch.Tensor,
    generators: Sequence[torch.Generator],
    *,
    num_sample: int,
    gamma: float,
    radius_growth: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`sample_cylinder_points` over a batch.

    Args:
        points: ``(N, 1 + C)`` collated points ``[batch_idx, x, y, z, ..., lag_s]`` (time lag
            last); the lag column is dropped from the output.
        trajectories: ``(B, T, R, 7)``; generators: one per sample.
    Returns:
        ``(B, R, T, num_sample, C - 1)`` and ``(B, R, T, num_sample)`` validity.
    """
    batch, num_frames, num_boxes = trajectories.shape[:3]
    features = points.shape[1] - 2
    out = points.new_zeros(batch, num_boxes, num_frames, num_sample, features)
    valid = torch.zeros(
        batch, num_boxes, num_frames, num_sample, dtype=torch.bool, device=points.device
    )
    for b in range(batch):
        rows = points.index_select(0, torch.nonzero(points[:, 0] == b).squeeze(1))
        frame_index = frame_of_points(rows[:, -1], num_frames)
        out[b], valid[b] = sample_cylinder_points(
            rows[:, 1:-1], frame_index, trajectories[b], num_sample=num_sample, gamma=gamma,
            radius_growth=radius_growth, generator=generators[b],
        )  # fmt: skip
    return out, valid
