"""ROI sampling of two-stage heads: quotas, replacement, classes, soft labels, determinism."""

import pytest
import torch

from pcdet_atlas.models.model_utils.roi_sampler import RoiSamplerConfig, sample_rois

GT = [10.0, 0.0, 1.0, 4.0, 2.0, 1.5, 0.0]


def rois_at(shifts, label=1):
    """ROIs like GT moved by ``dx`` along x: 3D IoU (4 - dx) / (4 + dx) for dx < 4."""
    boxes = torch.tensor([GT] * len(shifts), dtype=torch.float64)
    boxes[:, 0] += torch.tensor(shifts, dtype=torch.float64)
    return boxes, torch.full((len(shifts),), label)


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def sample(rois, labels, gt=(GT,), gt_labels=(1,), seed=0, **cfg):
    gt = torch.tensor(list(gt), dtype=torch.float64).reshape(-1, 7)
    return sample_rois(rois, labels, gt, torch.tensor(list(gt_labels)), RoiSamplerConfig(**cfg),
                       gen(seed))  # fmt: skip


def test_quotas_of_foreground_hard_and_easy_background():
    # 30 foreground (IoU 0.9), 50 hard (IoU 1/3), 50 easy (far away)
    rois, labels = rois_at([0.2] * 30 + [2.0] * 50 + [50.0] * 50)
    s = sample(rois, labels)
    assert s.roi_index.numel() == 96
    fg, bg = s.roi_index[:30], s.roi_index[30:]
    assert sorted(fg.tolist()) == list(range(30))  # fewer than the 48 quota: all, once each
    hard = ((bg >= 30) & (bg < 80)).sum().item()
    easy = (bg >= 80).sum().item()
    assert (hard, easy) == (50, 16)  # int(66 * 0.8) = 52 hard wanted, 50 exist
    assert torch.allclose(s.iou[:30], torch.full((30,), 3.8 / 4.2, dtype=torch.float64))
    assert s.reg_valid.tolist() == [True] * 30 + [False] * 66
    assert s.cls_label[:30].tolist() == [1.0] * 30
    assert torch.allclose(s.cls_label[30:][(bg >= 30) & (bg < 80)],
                          torch.tensor((1 / 3 - 0.25) / 0.5, dtype=torch.float64))  # fmt: skip
    assert s.gt_index[:30].tolist() == [0] * 30 and bool((s.gt_index[30:][bg >= 80] == -1).all())


def test_foreground_only_and_no_ground_truth_draw_with_replacement():
    rois, labels = rois_at([0.1, 0.2, 0.3])
    s = sample(rois, labels)
    assert s.roi_index.numel() == 96 and set(s.roi_index.tolist()) == {0, 1, 2}
    s = sample(rois, labels, gt=(), gt_labels=())
    assert s.roi_index.numel() == 96 and bool((s.iou == 0).all()) and not s.reg_valid.any()


def test_iou_counts_only_the_same_class_by_default():
    rois, labels = rois_at([0.2, 0.2], label=2)  # pedestrian proposals on a vehicle
    assert bool((sample(rois, labels).iou == 0).all())
    assert bool((sample(rois, labels, by_class=False).iou > 0.9).all())


def test_draws_follow_the_generator():
    rois, labels = rois_at([0.2] * 60 + [2.0] * 60 + [50.0] * 60)
    a, b, c = (
        sample(rois, labels, seed=1),
        sample(rois, labels, seed=1),
        sample(rois, labels, seed=2),
    )
    assert torch.equal(a.roi_index, b.roi_index) and not torch.equal(a.roi_index, c.roi_index)
    assert (a.roi_index < 60).sum().item() == 48  # the foreground quota, without replacement
    with pytest.raises(ValueError, match="no ROI"):
        sample(rois[:0], labels[:0])
