"""Small exact box geometry used by the augmentations and the GT database (numpy, CPU).

* :func:`boxes_bev_overlap`: do two rotated BEV rectangles share a positive area? This is the
  ``BEV IoU > 0`` test of OpenPCDet's GT sampler, done exactly with the separating-axis theorem
  (two convex polygons are disjoint iff their projections are disjoint on one of their edge
  normals), so touching boxes do not collide and no IoU has to be computed.
* :func:`box_index_of_points`: the first box that contains each point (closed faces, as
  :func:`pcdet_atlas.utils.box_utils.points_in_boxes_mask`), scanning only the points near each
  box so it stays cheap for 10^5-10^6 points.
"""

from __future__ import annotations

import numpy as np

from pcdet_atlas.utils.box_utils import points_in_boxes_mask

__all__ = ["bev_corners", "boxes_bev_overlap", "box_index_of_points", "enlarge_boxes"]

# Overlap depth (m) below which two projections count as touching, not overlapping.
_TOUCH_TOL_M = 1e-6


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """``(N, 7+)`` boxes -> ``(N, 4, 2)`` BEV corners (float64), counter-clockwise."""
    boxes = np.asarray(boxes, dtype=np.float64)
    half = boxes[:, 3:5] / 2  # (N, 2)
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)  # (4, 2)
    local = signs[None] * half[:, None]  # (N, 4, 2)
    cos, sin = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = local[..., 0] * cos - local[..., 1] * sin
    y = local[..., 0] * sin + local[..., 1] * cos
    return np.stack([x, y], axis=-1) + boxes[:, None, 0:2]


def boxes_bev_overlap(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """``(N, M)`` bool: box ``a[n]`` and box ``b[m]`` overlap with positive BEV area.

    Equivalent to ``boxes_iou_bev(a, b) > 0`` (z is ignored). Boxes of zero length or width
    have no area and never overlap.

    Args:
        boxes_a: ``(N, 7+)`` ``[x, y, z, dx, dy, dz, heading, ...]``.
        boxes_b: ``(M, 7+)``.
    """
    boxes_a = np.asarray(boxes_a, dtype=np.float64).reshape(-1, np.shape(boxes_a)[-1])
    boxes_b = np.asarray(boxes_b, dtype=np.float64).reshape(-1, np.shape(boxes_b)[-1])
    n, m = boxes_a.shape[0], boxes_b.shape[0]
    if n == 0 or m == 0:
        return np.zeros((n, m), dtype=bool)
    ca, cb = bev_corners(boxes_a), bev_corners(boxes_b)  # (N, 4, 2), (M, 4, 2)

    def axes(boxes: np.ndarray) -> np.ndarray:  # (K, 2, 2): the two edge directions
        cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
        return np.stack([np.stack([cos, sin], -1), np.stack([-sin, cos], -1)], axis=1)

    all_axes = np.concatenate(
        [
            np.broadcast_to(axes(boxes_a)[:, None], (n, m, 2, 2)),
            np.broadcast_to(axes(boxes_b)[None], (n, m, 2, 2)),
        ],
        axis=2,
    )  # (N, M, 4, 2)
    proj_a = np.einsum("nmkd,ncd->nmkc", all_axes, ca)  # (N, M, 4 axes, 4 corners)
    proj_b = np.einsum("nmkd,mcd->nmkc", all_axes, cb)
    depth = np.minimum(proj_a.max(-1), proj_b.max(-1)) - np.maximum(proj_a.min(-1), proj_b.min(-1))
    overlap = (depth > _TOUCH_TOL_M).all(axis=-1)  # (N, M)
    area_a = boxes_a[:, 3] * boxes_a[:, 4] > 0
    area_b = boxes_b[:, 3] * boxes_b[:, 4] > 0
    return overlap & area_a[:, None] & area_b[None, :]


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
    # Candidate points of a box come from an x-sorted view (a binary search per box), so the
    # cost follows the points near the boxes, not boxes x all points.
    order = np.argsort(xyz[:, 0])
    xs = xyz[order, 0]
    # Walk boxes in reverse so that the lowest index wins where boxes overlap.
    for i in range(boxes.shape[0] - 1, -1, -1):
        box = boxes[i]
        # Cheap superset (bounding circle, z slab; a hair wider than the box so that points
        # on a corner survive rounding); the exact closed-face test decides.
        radius_sq = (box[3] ** 2 + box[4] ** 2) / 4 * (1 + 1e-9) + 1e-12
        radius = np.sqrt(radius_sq)
        lo, hi = np.searchsorted(xs, [box[0] - radius, box[0] + radius], side="left")
        strip = order[lo : hi + 1] if hi < len(order) else order[lo:]
        near = ((xyz[strip, 0] - box[0]) ** 2 + (xyz[strip, 1] - box[1]) ** 2 <= radius_sq) & (
            np.abs(xyz[strip, 2] - box[2]) <= box[5] / 2 + 1e-9
        )
        cand = strip[near]
        if cand.size == 0:
            continue
        inside = points_in_boxes_mask(xyz[cand], box[None, :7])[0]
        out[cand[inside]] = i
    return out
