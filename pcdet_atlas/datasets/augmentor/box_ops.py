"""Box helpers of the augmentations and the GT database (numpy, CPU); the box geometry they
build on is :mod:`pcdet_atlas.ops.boxes`.

* :func:`box_index_of_points`: the first box that contains each point (closed faces, as
  :func:`pcdet_atlas.ops.boxes.points_in_boxes_mask`), scanning only the points in the BEV grid
  cells near each box so it stays cheap for 10^5-10^6 points.
"""

from __future__ import annotations

import numpy as np

from pcdet_atlas.ops.boxes import points_in_boxes_mask

__all__ = ["box_index_of_points", "enlarge_boxes"]

#: cells a side of box_index_of_points' grid: 181^2 keys fit int16, which numpy sorts by radix
_GRID_CELLS = 181


def enlarge_boxes(boxes: np.ndarray, extra_width) -> np.ndarray:
    """Copy of ``(N, 7+)`` boxes with ``extra_width`` ``(3,)`` (m) added to ``dx, dy, dz``."""
    out = np.array(boxes, dtype=np.float64, copy=True)
    out[:, 3:6] += np.asarray(extra_width, dtype=np.float64).reshape(1, 3)
    return out


def box_index_of_points(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """``(N,)`` int64: index of the first box containing each point, -1 if none.

    Args:
        points: ``(N, 3+)``; only x, y, z are used.
        boxes: ``(M, 7+)``.
    """
    points = np.asarray(points)
    boxes = np.asarray(boxes, dtype=np.float64)
    out = np.full(points.shape[0], -1, dtype=np.int64)
    if points.shape[0] == 0 or boxes.shape[0] == 0:
        return out
    xyz = points[:, :3].astype(np.float64)
    # Candidate points of a box come from the cells of a coarse BEV grid its bounding circle
    # touches (points grouped by cell with an O(N) radix sort of int16 keys), so the cost follows
    # the points near the boxes, not boxes x all points.
    lo_xy = xyz[:, :2].min(axis=0)
    span = float((xyz[:, :2].max(axis=0) - lo_xy).max())
    cell = max(1.0, span / (_GRID_CELLS - 1))  # at most _GRID_CELLS cells a side
    cells = np.minimum(np.floor((xyz[:, :2] - lo_xy) / cell), _GRID_CELLS - 1).astype(np.int64)
    num_y = int(cells[:, 1].max()) + 1
    num_x = int(cells[:, 0].max()) + 1
    keys = (cells[:, 0] * num_y + cells[:, 1]).astype(np.int16)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    # Walk boxes in reverse so that the lowest index wins where boxes overlap.
    for i in range(boxes.shape[0] - 1, -1, -1):
        box = boxes[i]
        # Cheap superset (bounding circle, z slab; a hair wider than the box so that points
        # on a corner survive rounding); the exact closed-face test decides.
        radius_sq = (box[3] ** 2 + box[4] ** 2) / 4 * (1 + 1e-9) + 1e-12
        radius = np.sqrt(radius_sq)
        first = np.floor((box[:2] - radius - lo_xy) / cell)
        last = np.floor((box[:2] + radius - lo_xy) / cell)
        x0, y0 = int(max(first[0], 0)), int(max(first[1], 0))
        x1, y1 = int(min(last[0], num_x - 1)), int(min(last[1], num_y - 1))
        if x0 > x1 or y0 > y1:
            continue
        rows = np.arange(x0, x1 + 1) * num_y
        starts = np.searchsorted(sorted_keys, rows + y0, side="left")
        ends = np.searchsorted(sorted_keys, rows + y1, side="right")
        strip = np.concatenate([order[a:b] for a, b in zip(starts, ends)])
        near = ((xyz[strip, 0] - box[0]) ** 2 + (xyz[strip, 1] - box[1]) ** 2 <= radius_sq) & (
            np.abs(xyz[strip, 2] - box[2]) <= box[5] / 2 + 1e-9
        )
        cand = strip[near]
        if cand.size == 0:
            continue
        inside = points_in_boxes_mask(xyz[cand], box[None, :7])[0]
        out[cand[inside]] = i
    return out
