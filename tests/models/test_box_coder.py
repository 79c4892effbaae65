"""The residual box coder and the canonical ROI frame of two-stage heads."""

import math

import pytest
import torch

from pcdet_atlas.models.model_utils.box_coder import (
    ResidualCoder,
    decode_roi_boxes,
    encode_roi_targets,
)


def random_boxes(n, code_size, seed):
    g = torch.Generator().manual_seed(seed)
    boxes = torch.rand(n, code_size, generator=g, dtype=torch.float64)
    boxes[:, 0:3] = boxes[:, 0:3] * 80 - 40
    boxes[:, 3:6] = boxes[:, 3:6] * 5 + 0.3
    boxes[:, 6] = boxes[:, 6] * 2 * math.pi - math.pi
    if code_size > 7:
        boxes[:, 7:] = boxes[:, 7:] * 20 - 10
    return boxes


def test_residual_code_by_hand():
    anchor = torch.tensor([[1.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.1]], dtype=torch.float64)
    box = torch.tensor([[4.0, 6.0, 1.5, 8.0, 2.0, 3.0, 0.3]], dtype=torch.float64)
    code = ResidualCoder().encode(box, anchor)[0]
    d = math.sqrt(20.0)
    want = [3 / d, 4 / d, 1 / 1.5, math.log(2), 0.0, math.log(2), 0.2]
    assert torch.allclose(code, torch.tensor(want, dtype=torch.float64))


@pytest.mark.parametrize("code_size", [7, 9])
def test_residual_coder_round_trip(code_size):
    coder = ResidualCoder(code_size)
    boxes, anchors = random_boxes(200, code_size, 0), random_boxes(200, code_size, 1)
    back = coder.decode(coder.encode(boxes, anchors), anchors)
    assert torch.allclose(back, boxes, atol=1e-9)
    with pytest.raises(ValueError, match=rf"codes must be \(N, {code_size}\)"):
        coder.decode(torch.zeros(3, code_size + 1), anchors[:3])


def test_roi_target_is_the_box_seen_from_its_roi():
    """A box 1 m ahead of a rotated ROI along the ROI's heading, turned by 0.3 rad further:
    target x = 1 / diagonal, y = 0, heading 0.3, computed directly in the ROI's frame."""
    coder = ResidualCoder()
    theta = 2.0
    roi = torch.tensor([[10.0, -5.0, 1.0, 4.0, 2.0, 1.6, theta]], dtype=torch.float64)
    gt = roi.clone()
    gt[0, 0] += math.cos(theta)
    gt[0, 1] += math.sin(theta)
    gt[0, 6] = theta + 0.3
    code = encode_roi_targets(gt, roi, coder)[0]
    assert code[0].item() == pytest.approx(1 / math.sqrt(20.0))
    assert abs(code[1].item()) < 1e-12 and code[6].item() == pytest.approx(0.3)
    # a box facing the other way is the same box: its target heading is flipped by pi
    gt[0, 6] = theta + math.pi + 0.3
    assert encode_roi_targets(gt, roi, coder)[0, 6].item() == pytest.approx(0.3)


@pytest.mark.parametrize("code_size", [7, 9])
def test_decode_inverts_encode_up_to_the_heading_flip(code_size):
    coder = ResidualCoder(code_size)
    gt, rois = random_boxes(300, code_size, 2), random_boxes(300, code_size, 3)
    codes = encode_roi_targets(gt, rois, coder)
    assert bool((codes[:, 6].abs() <= math.pi / 2 + 1e-12).all())
    back = decode_roi_boxes(codes, rois, coder)
    assert torch.allclose(back[:, :6], gt[:, :6], atol=1e-9)
    diff = torch.remainder(back[:, 6] - gt[:, 6], math.pi)  # 0 or pi apart
    assert bool(((diff < 1e-9) | (diff > math.pi - 1e-9)).all())
    if code_size == 9:  # velocity rotates into the ROI frame and back
        assert torch.allclose(back[:, 7:9], gt[:, 7:9], atol=1e-9)
    same = torch.remainder(gt[:, 6] - rois[:, 6] + math.pi / 2, 2 * math.pi) < math.pi - 1e-6
    assert torch.allclose(torch.cos(back[same, 6] - gt[same, 6]), torch.ones(int(same.sum()),
                          dtype=torch.float64))  # fmt: skip
