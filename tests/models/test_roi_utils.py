"""Soft IoU labels, score fusion, corner loss and detection selection of two-stage heads."""

import math

import pytest
import torch

from pcdet_atlas.models.model_utils.roi_utils import (
    corner_loss,
    fuse_scores,
    select_detections,
    soft_iou_label,
)

CAR = [0.0, 0.0, 1.0, 4.0, 2.0, 1.5, 0.3]


def test_soft_iou_label():
    iou = torch.tensor([0.0, 0.25, 0.5, 0.75, 0.9])
    assert soft_iou_label(iou).tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]
    with pytest.raises(ValueError, match="bg_thresh < fg_thresh"):
        soft_iou_label(iou, fg_thresh=0.2, bg_thresh=0.3)


def test_fuse_scores_by_class_weight():
    logits = torch.tensor([0.0, 0.0, math.log(3.0)])  # sigmoid: 0.5, 0.5, 0.75
    roi = torch.tensor([0.8, 0.8, 0.25])
    labels = torch.tensor([1, 2, 3])
    got = fuse_scores(logits, roi, labels, [0.5, 0.4, 0.4])
    want = [0.5**0.5 * 0.8**0.5, 0.5**0.4 * 0.8**0.6, 0.75**0.4 * 0.25**0.6]
    assert torch.allclose(got, torch.tensor(want))
    with pytest.raises(ValueError, match=r"labels must be in \[1, 2\]"):
        fuse_scores(logits, roi, labels, [0.5, 0.4])


def test_corner_loss_is_zero_for_the_box_and_its_turn_and_grows_with_error():
    gt = torch.tensor([CAR], dtype=torch.float64)
    turned = gt.clone()
    turned[0, 6] += math.pi
    assert corner_loss(gt, gt).item() == 0.0
    assert corner_loss(turned, gt).item() == pytest.approx(0.0, abs=1e-12)
    shifted = gt.clone()
    shifted[0, 0] += 0.5  # every corner 0.5 m off: smooth-L1 0.5 * 0.5^2
    assert corner_loss(shifted, gt).item() == pytest.approx(0.125)
    far = gt.clone()
    far[0, 2] += 3.0  # 3 m up (the turn's corners are farther): beyond beta, |d| - beta / 2
    assert corner_loss(far, gt).item() == pytest.approx(2.5)
    # 3 m along the box: for the rear corners the turned box's corners are nearer
    along = gt.clone()
    along[0, 0] += 3.0 * math.cos(0.3)
    along[0, 1] += 3.0 * math.sin(0.3)
    assert corner_loss(along, gt).item() < 2.5


def test_select_detections_keeps_every_vehicle_and_suppresses_the_rest():
    boxes = torch.tensor(
        [CAR, CAR, CAR, [20.0, 0, 1, 0.8, 0.8, 1.8, 0.0], [20.1, 0, 1, 0.8, 0.8, 1.8, 0.0]],
        dtype=torch.float64,
    )
    scores = torch.tensor([0.9, 0.8, 0.05, 0.7, 0.6])
    labels = torch.tensor([1, 1, 1, 2, 2])
    kept = select_detections(boxes, scores, labels, no_nms_labels=(1,))
    # both overlapping vehicles above 0.1 stay, the 0.05 one goes; one pedestrian survives NMS
    assert kept.tolist() == [0, 1, 3]
    with_nms = select_detections(boxes, scores, labels)
    assert with_nms.tolist() == [0, 3]
