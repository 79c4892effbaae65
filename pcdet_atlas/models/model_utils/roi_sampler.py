"""Training targets of two-stage heads: which proposals (ROIs) of a frame are trained on, and
their matched ground truth, as OpenPCDet's ``ProposalTargetLayer`` samples them.

Each ROI is matched to the ground-truth box of the highest 3D IoU (among boxes of its own class
with ``by_class``). ``roi_per_image`` ROIs are drawn: foreground (IoU >= ``min(reg_fg_thresh,
cls_fg_thresh)``) up to ``fg_ratio`` of them, the rest background, of which ``hard_bg_ratio``
from the hard band ``[cls_bg_thresh_lo, reg_fg_thresh)`` and the others from below
``cls_bg_thresh_lo``. A set smaller than its quota is drawn with replacement. Every draw comes
from the generator passed in. Regression is trained on ROIs with IoU > ``reg_fg_thresh``;
classification on the soft label of
:func:`~pcdet_atlas.models.model_utils.roi_utils.soft_iou_label`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pcdet_atlas.models.model_utils.roi_utils import soft_iou_label
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d

__all__ = ["RoiSamplerConfig", "RoiSample", "sample_rois"]


@dataclass(frozen=True)
class RoiSamplerConfig:
    """OpenPCDet's ``ROI_SAMPLER_CFG`` (MSF's values by default)."""

    roi_per_image: int = 96
    fg_ratio: float = 0.5
    reg_fg_thresh: float = 0.55
    cls_fg_thresh: float = 0.75
    cls_bg_thresh: float = 0.25
    cls_bg_thresh_lo: float = 0.1
    hard_bg_ratio: float = 0.8
    by_class: bool = True

    def __post_init__(self) -> None:
        problems = []
        if isinstance(self.roi_per_image, bool) or not isinstance(self.roi_per_image, int):
            problems.append(f"ROI_PER_IMAGE must be an integer, got {self.roi_per_image!r}")
        elif self.roi_per_image < 1:
            problems.append(f"ROI_PER_IMAGE must be >= 1, got {self.roi_per_image}")
        for key, value in (
            ("FG_RATIO", self.fg_ratio), ("REG_FG_THRESH", self.reg_fg_thresh),
            ("CLS_FG_THRESH", self.cls_fg_thresh), ("CLS_BG_THRESH", self.cls_bg_thresh),
            ("CLS_BG_THRESH_LO", self.cls_bg_thresh_lo), ("HARD_BG_RATIO", self.hard_bg_ratio),
        ):  # fmt: skip
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (0.0 <= value <= 1.0)
            ):
                problems.append(f"{key} must be a number in [0, 1], got {value!r}")
        if not problems and not self.cls_bg_thresh < self.cls_fg_thresh:
            problems.append(
                f"CLS_BG_THRESH ({self.cls_bg_thresh}) must be below CLS_FG_THRESH "
                f"({self.cls_fg_thresh})"
            )
        if not isinstance(self.by_class, bool):
            problems.append(
                f"SAMPLE_ROI_BY_EACH_CLASS must be True or False, got {self.by_class!r}"
            )
        if problems:
            raise ValueError("ROI sampler (TARGET_CONFIG): " + "; ".join(problems))


@dataclass
class RoiSample:
    """The sampled ROIs of one frame, ``S = roi_per_image`` rows each."""

    roi_index: torch.Tensor  # (S,) long, into the frame's ROIs (repeats where drawn again)
    gt_index: torch.Tensor  # (S,) long, the matched ground-truth box, -1 if none
    iou: torch.Tensor  # (S,) IoU with it (0 without ground truth)
    reg_valid: torch.Tensor  # (S,) bool, IoU > reg_fg_thresh
    cls_label: torch.Tensor  # (S,) soft IoU label in [0, 1]


def sample_rois(
    rois: torch.Tensor,
    roi_labels: torch.Tensor,
    gt_boxes: torch.Tensor,
    gt_labels: torch.Tensor,
    cfg: RoiSamplerConfig,
    generator: torch.Generator,
) -> RoiSample:
    """Draw ``cfg.roi_per_image`` ROIs of one frame and their targets.

    Args:
        rois: ``(R, 7+)`` proposals; roi_labels: ``(R,)`` 1-based classes.
        gt_boxes: ``(G, 7+)``; gt_labels: ``(G,)`` 1-based classes.
        generator: a ``torch.Generator`` on the CPU (the draws are made there).
    Raises:
        ValueError: a frame without ROIs.
    """
    num = rois.shape[0]
    if num == 0:
        raise ValueError("sample_rois: the frame has no ROI to sample from")
    iou = torch.zeros(num, dtype=torch.float64, device=rois.device)
    gt_index = torch.full((num,), -1, dtype=torch.long, device=rois.device)
    if gt_boxes.shape[0]:
        ious = boxes_iou3d(rois[:, :7].double(), gt_boxes[:, :7].double())  # (R, G)
        if cfg.by_class:
            ious = ious.masked_fill(roi_labels[:, None] != gt_labels[None, :], 0.0)
        iou, gt_index = ious.max(dim=1)
        gt_index = torch.where(iou > 0, gt_index, torch.full_like(gt_index, -1))
    fg_thresh = min(cfg.reg_fg_thresh, cfg.cls_fg_thresh)
    fg = torch.nonzero(iou >= fg_thresh).squeeze(1).cpu()
    easy = torch.nonzero(iou < cfg.cls_bg_thresh_lo).squeeze(1).cpu()
    hard = torch.nonzero((iou < cfg.reg_fg_thresh) & (iou >= cfg.cls_bg_thresh_lo))
    hard = hard.squeeze(1).cpu()
    fg_quota = round(cfg.fg_ratio * cfg.roi_per_image)
    num_bg = easy.numel() + hard.numel()
    if fg.numel() and num_bg:
        fg_take = min(fg_quota, fg.numel())
        fg = fg[torch.randperm(fg.numel(), generator=generator)[:fg_take]]
        bg = _background(hard, easy, cfg.roi_per_image - fg_take, cfg.hard_bg_ratio, generator)
    elif fg.numel():
        fg = _with_replacement(fg, cfg.roi_per_image, generator)
        bg = fg[:0]
    else:
        bg = _background(hard, easy, cfg.roi_per_image, cfg.hard_bg_ratio, generator)
    index = torch.cat([fg, bg]).to(rois.device)
    sampled_iou = iou[index]
    return RoiSample(
        roi_index=index,
        gt_index=gt_index[index],
        iou=sampled_iou,
        reg_valid=sampled_iou > cfg.reg_fg_thresh,
        cls_label=soft_iou_label(sampled_iou, cfg.cls_fg_thresh, cfg.cls_bg_thresh),
    )


def _with_replacement(pool: torch.Tensor, count: int, generator: torch.Generator):
    return pool[torch.randint(pool.numel(), (count,), generator=generator)]


def _background(hard, easy, count: int, hard_ratio: float, generator: torch.Generator):
    """``count`` background ROIs: ``hard_ratio`` of them hard when both kinds exist."""
    if hard.numel() and easy.numel():
        num_hard = min(int(count * hard_ratio), hard.numel())
        return torch.cat(
            [
                _with_replacement(hard, num_hard, generator),
                _with_replacement(easy, count - num_hard, generator),
            ]
        )
    return _with_replacement(hard if hard.numel() else easy, count, generator)
