"""Scoring, losses and post-processing shared by the two-stage heads (MSF, PTT).

* :func:`soft_iou_label`: the IoU-based soft classification target of a proposal.
* :func:`fuse_scores`: the refined score ``sigmoid(cls)^w * roi_score^(1 - w)``, ``w`` per class.
* :func:`corner_loss`: smooth-L1 of the corner distances to the ground truth or its pi-turn.
* :func:`select_detections`: score threshold, then rotated BEV NMS, except for the classes
  (vehicles, in MSF and PTT) whose proposals are all kept.

Boxes follow docs/conventions.md; labels are 1-based indices into the model's class names.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from pcdet_atlas.ops.boxes import boxes_to_corners_3d
from pcdet_atlas.ops.iou3d_nms import nms_bev

__all__ = ["corner_loss", "fuse_scores", "select_detections", "soft_iou_label"]


def soft_iou_label(iou: torch.Tensor, fg_thresh: float = 0.75, bg_thresh: float = 0.25):
    """``(N,)`` targets in ``[0, 1]``: 0 at or below ``bg_thresh``, 1 at or above ``fg_thresh``,
    linear between."""
    if not 0.0 <= bg_thresh < fg_thresh <= 1.0:
        raise ValueError(f"need 0 <= bg_thresh < fg_thresh <= 1, got {bg_thresh}, {fg_thresh}")
    return ((iou - bg_thresh) / (fg_thresh - bg_thresh)).clamp(0.0, 1.0)


def fuse_scores(
    cls_logits: torch.Tensor,
    roi_scores: torch.Tensor,
    labels: torch.Tensor,
    iou_weights: Sequence[float],
) -> torch.Tensor:
    """``(N,)`` final scores ``sigmoid(cls_logits)^w * roi_scores^(1 - w)``.

    Args:
        cls_logits: ``(N,)`` the head's confidence logits. roi_scores: ``(N,)`` proposal scores
            in ``[0, 1]``. labels: ``(N,)`` long, 1-based class of each proposal.
        iou_weights: ``w`` per class, in class order (MSF: Vehicle 0.5, Pedestrian and Cyclist
            0.4).
    """
    weights = torch.as_tensor(list(iou_weights), dtype=cls_logits.dtype, device=cls_logits.device)
    if labels.numel() and (int(labels.min()) < 1 or int(labels.max()) > weights.numel()):
        raise ValueError(f"labels must be in [1, {weights.numel()}] (one iou_weight per class)")
    w = weights[labels.long() - 1] if labels.numel() else weights[:0]
    return torch.sigmoid(cls_logits) ** w * roi_scores.clamp_min(0.0) ** (1.0 - w)


def corner_loss(pred_boxes: torch.Tensor, gt_boxes: torch.Tensor, beta: float = 1.0):
    """``(N,)`` mean over the 8 corners of the smooth-L1 (``beta``) distance between each
    predicted corner and the ground truth's, taking for each corner the nearer of the ground
    truth and the ground truth turned by pi (a box and its turn are the same box)."""
    flipped = gt_boxes.clone()
    flipped[:, 6] = flipped[:, 6] + math.pi
    pred_c = boxes_to_corners_3d(pred_boxes[:, :7])  # (N, 8, 3)
    dist = torch.minimum(
        torch.linalg.vector_norm(pred_c - boxes_to_corners_3d(gt_boxes[:, :7]), dim=2),
        torch.linalg.vector_norm(pred_c - boxes_to_corners_3d(flipped[:, :7]), dim=2),
    )  # (N, 8)
    return F.smooth_l1_loss(dist, torch.zeros_like(dist), beta=beta, reduction="none").mean(1)


def select_detections(
    boxes: torch.Tensor,
    scores: torch.Tensor,
    labels: torch.Tensor,
    *,
    score_thresh: float = 0.1,
    nms_thresh: float = 0.7,
    pre_max_size: int | None = 4096,
    post_max_size: int | None = 500,
    no_nms_labels: Sequence[int] = (),
) -> torch.Tensor:
    """Indices ``(K,)`` of the detections kept from one frame's refined proposals.

    Proposals scoring ``<= score_thresh`` go. Those whose label is in ``no_nms_labels`` are all
    kept (MSF's and PTT's vehicles: each proposal tracks its own object); the rest go through
    class-agnostic rotated BEV NMS (``nms_thresh``, ``pre_max_size`` / ``post_max_size``).
    Returned in descending score order within each group, the kept no-NMS group first.
    """
    above = scores > score_thresh
    no_nms = torch.isin(labels, torch.as_tensor(list(no_nms_labels), device=labels.device))
    keep_all = torch.nonzero(above & no_nms).squeeze(1)
    keep_all = keep_all[torch.sort(scores[keep_all], descending=True, stable=True).indices]
    rest = torch.nonzero(above & ~no_nms).squeeze(1)
    kept = rest[nms_bev(boxes[rest], scores[rest], nms_thresh, pre_max_size, post_max_size)]
    return torch.cat([keep_all, kept])
