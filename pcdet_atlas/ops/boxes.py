"""Box and rigid-transform geometry in the conventions of docs/conventions.md.

Boxes are ``(N, 7)`` ``[x, y, z, dx, dy, dz, heading]`` with z at the box centre, heading CCW from
+x in radians, or ``(N, 9)`` with ``[vx, vy]`` (m/s) appended. Poses are 4x4 vehicle -> global.
Every function takes numpy arrays or torch tensors and returns the same kind, except
:func:`boxes_bev_overlap` (numpy). Exact rotated IoU and NMS:
:mod:`pcdet_atlas.ops.iou3d_nms`.
"""

from __future__ import annotations

import numpy as np
import torch

from pcdet_atlas.utils.common import limit_period

# Overlap depth (m) below which two projections count as touching, not overlapping.
_TOUCH_TOL_M = 1e-6

__all__ = [
    "boxes_bev_overlap",
    "boxes_to_corners_3d",
    "boxes_to_corners_bev",
    "points_in_boxes_mask",
    "transform_points",
    "transform_boxes",
    "yaw_of_pose",
]


def _as_tensor(x) -> tuple[torch.Tensor, bool]:
    if isinstance(x, torch.Tensor):
        return x, False
    return torch.as_tensor(np.asarray(x)), True


def _back(x: torch.Tensor, was_numpy: bool):
    return x.numpy() if was_numpy else x


def boxes_to_corners_3d(boxes):
    """Corners of ``(N, 7+)`` boxes as ``(N, 8, 3)``: bottom face (from +x+y), then top."""
    b, was_np = _as_tensor(boxes)
    template = b.new_tensor(
        [[1, 1, -1], [1, -1, -1], [-1, -1, -1], [-1, 1, -1],
         [1, 1, 1], [1, -1, 1], [-1, -1, 1], [-1, 1, 1]]
    ) / 2  # fmt: skip
    corners = b[:, None, 3:6] * template[None]  # (N, 8, 3)
    cos, sin = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    x = corners[..., 0] * cos[:, None] - corners[..., 1] * sin[:, None]
    y = corners[..., 0] * sin[:, None] + corners[..., 1] * cos[:, None]
    out = torch.stack([x, y, corners[..., 2]], dim=-1) + b[:, None, 0:3]
    return _back(out, was_np)


def boxes_to_corners_bev(boxes):
    """BEV corners of ``(N, 7+)`` boxes as ``(N, 4, 2)`` (the bottom face of
    :func:`boxes_to_corners_3d`, clockwise from +x+y)."""
    return boxes_to_corners_3d(boxes)[:, :4, :2]


def boxes_bev_overlap(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """``(N, M)`` bool: box ``a[n]`` and box ``b[m]`` overlap with positive BEV area.

    Equivalent to ``boxes_iou_bev(a, b) > 0`` (z is ignored). Boxes with a length or width
    ``<= 0`` have no area and never overlap.

    Args:
        boxes_a: ``(N, 7+)`` ``[x, y, z, dx, dy, dz, heading, ...]``.
        boxes_b: ``(M, 7+)``.
    """
    boxes_a = np.asarray(boxes_a, dtype=np.float64).reshape(-1, np.shape(boxes_a)[-1])
    boxes_b = np.asarray(boxes_b, dtype=np.float64).reshape(-1, np.shape(boxes_b)[-1])
    n, m = boxes_a.shape[0], boxes_b.shape[0]
    if n == 0 or m == 0:
        return np.zeros((n, m), dtype=bool)
    ca, cb = boxes_to_corners_bev(boxes_a), boxes_to_corners_bev(boxes_b)  # (N, 4, 2), (M, 4, 2)

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
    # both dimensions positive, as in boxes_iou_bev (a product test would pass two negatives)
    area_a = (boxes_a[:, 3] > 0) & (boxes_a[:, 4] > 0)
    area_b = (boxes_b[:, 3] > 0) & (boxes_b[:, 4] > 0)
    return overlap & area_a[:, None] & area_b[None, :]


def points_in_boxes_mask(points_xyz, boxes):
    """``(M, N)`` bool: point n lies in box m (closed faces).

    Args:
        points_xyz: ``(N, 3+)`` points; only the first 3 columns are used.
        boxes: ``(M, 7+)`` boxes.
    """
    p, was_np = _as_tensor(points_xyz)
    b, _ = _as_tensor(boxes)
    b = b.to(p.dtype if p.is_floating_point() else torch.float64)
    p = p[:, :3].to(b.dtype)
    if b.shape[0] == 0 or p.shape[0] == 0:
        return _back(torch.zeros((b.shape[0], p.shape[0]), dtype=torch.bool), was_np)
    rel = p[None, :, :] - b[:, None, 0:3]  # (M, N, 3)
    cos, sin = torch.cos(b[:, 6])[:, None], torch.sin(b[:, 6])[:, None]
    local_x = rel[..., 0] * cos + rel[..., 1] * sin
    local_y = -rel[..., 0] * sin + rel[..., 1] * cos
    inside = (
        (local_x.abs() <= b[:, None, 3] / 2)
        & (local_y.abs() <= b[:, None, 4] / 2)
        & (rel[..., 2].abs() <= b[:, None, 5] / 2)
    )
    return _back(inside, was_np)


def transform_points(points_xyz, pose):
    """Apply a 4x4 rigid transform to ``(N, 3)`` points; returns ``(N, 3)``."""
    p, was_np = _as_tensor(points_xyz)
    t, _ = _as_tensor(pose)
    t = t.to(p.dtype)
    out = p[:, :3] @ t[:3, :3].T + t[:3, 3]
    return _back(out, was_np)


def yaw_of_pose(pose) -> float:
    """Rotation about z of a 4x4 pose (radians), ``atan2(R[1, 0], R[0, 0])``."""
    t, _ = _as_tensor(pose)
    return float(torch.atan2(t[1, 0], t[0, 0]))


def transform_boxes(boxes, pose):
    """Rigidly move ``(N, 7)`` or ``(N, 9)`` boxes by a 4x4 transform.

    The centre is transformed, the heading gains the transform's yaw (wrapped to [-pi, pi)), and
    the velocity ``[vx, vy, 0]`` is rotated (not translated). Assumes the transform keeps z up,
    as vehicle poses do.
    """
    b, was_np = _as_tensor(boxes)
    t, _ = _as_tensor(pose)
    t = t.to(b.dtype)
    out = b.clone()
    out[:, 0:3] = b[:, 0:3] @ t[:3, :3].T + t[:3, 3]
    out[:, 6] = limit_period(b[:, 6] + torch.atan2(t[1, 0], t[0, 0]))
    if b.shape[1] >= 9:
        vel = torch.cat([b[:, 7:9], b.new_zeros((b.shape[0], 1))], dim=1)
        out[:, 7:9] = (vel @ t[:3, :3].T)[:, :2]
    return _back(out, was_np)
