"""Evaluation: exact 3D IoU, the Waymo L1/L2 AP/APH metric, attack success rate and analyses."""

from pcdet_atlas.evaluation.iou3d import (
    boxes_aligned_iou3d,
    boxes_aligned_iou_bev,
    boxes_iou3d,
    boxes_iou_bev,
    boxes_overlap_bev,
    nms_bev,
)

__all__ = [
    "boxes_aligned_iou3d",
    "boxes_aligned_iou_bev",
    "boxes_iou3d",
    "boxes_iou_bev",
    "boxes_overlap_bev",
    "nms_bev",
]
