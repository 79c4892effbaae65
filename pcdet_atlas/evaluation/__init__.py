"""Evaluation: exact 3D IoU, the Waymo L1/L2 AP/APH metric, attack success rate and analyses."""

from pcdet_atlas.evaluation.iou3d import (
    boxes_aligned_iou3d,
    boxes_aligned_iou_bev,
    boxes_iou3d,
    boxes_iou_bev,
    boxes_overlap_bev,
    nms_bev,
)
from pcdet_atlas.evaluation.waymo_metric import (
    WAYMO_IOU_THRESHOLDS,
    WAYMO_SCORE_CUTOFFS,
    compute_waymo_curves,
    summarize_waymo_curves,
    waymo_average_precision,
    waymo_evaluate,
    waymo_heading_accuracy,
)

__all__ = [
    "WAYMO_IOU_THRESHOLDS",
    "WAYMO_SCORE_CUTOFFS",
    "boxes_aligned_iou3d",
    "boxes_aligned_iou_bev",
    "boxes_iou3d",
    "boxes_iou_bev",
    "boxes_overlap_bev",
    "compute_waymo_curves",
    "nms_bev",
    "summarize_waymo_curves",
    "waymo_average_precision",
    "waymo_evaluate",
    "waymo_heading_accuracy",
]
