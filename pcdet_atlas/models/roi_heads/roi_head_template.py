"""What the second stages of the temporal two-stage detectors (MSF, PTT) share: the config of
their ROI targets and loss, target assignment with MSF's ROI and trajectory jitter, the loss
(soft-label BCE, smooth-L1 on residual box codes, corner loss) and decoding.

A head built on :class:`TemporalRoIHead` writes ``rcnn_cls`` (a list of ``(B, R)`` logits, one
per refinement block; the loss averages them), ``rcnn_reg`` ``(B, R, 7)`` (the refined box's
residual code), ``traj_reg`` ``(B, R, 7)`` (an auxiliary code from the box-sequence branch) and
``aux_reg`` (a list, possibly empty, of further auxiliary ``(B, R, 7)`` codes).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.config_values import as_lists, fields_of, section, setting
from pcdet_atlas.models.model_utils.box_coder import (
    ResidualCoder,
    decode_roi_boxes,
    encode_roi_targets,
)
from pcdet_atlas.models.model_utils.roi_sampler import RoiSamplerConfig, sample_rois
from pcdet_atlas.models.model_utils.roi_utils import corner_loss, soft_iou_label
from pcdet_atlas.models.stage_config import StageConfig
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d

__all__ = ["RoiHeadConfig", "TemporalRoIHead", "augment_boxes", "SMOOTH_L1_BETA"]

#: OpenPCDet's two-stage regression loss: smooth-L1 with beta 1/9.
SMOOTH_L1_BETA = 1.0 / 9.0

_R = RoiSamplerConfig


@dataclass(frozen=True, kw_only=True)
class TrajAugConfig:
    """``TARGET_CONFIG.USE_TRAJ_AUG``."""

    enabled: bool = setting(True, doc="jitter the trajectories too")
    threshold: float = setting(0.8, ge=0, le=1, doc="IoU the jittered trajectory keeps")


@dataclass(frozen=True, kw_only=True)
class RoiTargetConfig:
    """``MODEL.ROI_HEAD.TARGET_CONFIG``: OpenPCDet's ROI sampler keys and MSF's augmentation."""

    roi_per_image: int = setting(_R.roi_per_image, ge=1, doc="proposals sampled per frame")
    fg_ratio: float = setting(_R.fg_ratio, ge=0, le=1, doc="share of foreground samples")
    reg_fg_thresh: float = setting(_R.reg_fg_thresh, ge=0, le=1, doc="IoU for regression")
    cls_fg_thresh: float = setting(_R.cls_fg_thresh, ge=0, le=1, doc="IoU of a positive")
    cls_bg_thresh: float = setting(_R.cls_bg_thresh, ge=0, le=1, doc="IoU of a negative")
    cls_bg_thresh_lo: float = setting(_R.cls_bg_thresh_lo, ge=0, le=1, doc="hard negatives")
    hard_bg_ratio: float = setting(_R.hard_bg_ratio, ge=0, le=1, doc="share of hard negatives")
    by_class: bool = setting(_R.by_class, key="SAMPLE_ROI_BY_EACH_CLASS", doc="per class")
    use_roi_aug: bool = setting(True, doc="jitter the sampled proposals")
    roi_fg_aug_times: int = setting(10, ge=1, doc="jitter tries")
    ratio: float = setting(0.2, ge=0, le=1, doc="share of proposals kept unjittered")
    use_traj_aug: TrajAugConfig = section(TrajAugConfig)

    def sampler(self) -> RoiSamplerConfig:
        return RoiSamplerConfig(**{f: getattr(self, f) for f in _R.__dataclass_fields__})

    def roi_aug(self) -> dict:
        """The head's ``roi_aug`` argument."""
        return {
            "ENABLED": self.use_roi_aug,
            "TRIES": self.roi_fg_aug_times,
            "KEEP_RATIO": self.ratio,
            "TRAJ_ENABLED": self.use_traj_aug.enabled,
            "TRAJ_THRESH": self.use_traj_aug.threshold,
        }


@dataclass(frozen=True, kw_only=True)
class RoiLossWeightsConfig:
    """``MODEL.ROI_HEAD.LOSS_CONFIG.LOSS_WEIGHTS`` (absent: the head's default)."""

    rcnn_cls_weight: float | None = setting(None, key="rcnn_cls_weight", ge=0, doc="score loss")
    rcnn_reg_weight: float | None = setting(None, key="rcnn_reg_weight", ge=0, doc="box loss")
    rcnn_corner_weight: float | None = setting(
        None, key="rcnn_corner_weight", ge=0, doc="corner loss"
    )
    traj_reg_weight: tuple[float, ...] | None = setting(
        None, key="traj_reg_weight", ge=0, doc="trajectory losses (3)"
    )
    code_weights: tuple[float, ...] | None = setting(
        None, key="code_weights", ge=0, doc="weight per box code (7)"
    )


@dataclass(frozen=True, kw_only=True)
class RoiLossConfig:
    loss_weights: RoiLossWeightsConfig = section(RoiLossWeightsConfig)


@dataclass(frozen=True, kw_only=True)
class RoiHeadConfig(StageConfig):
    """The ``MODEL.ROI_HEAD`` keys of every temporal ROI head (a head adds its own)."""

    iou_weight: tuple[float, ...] | None = setting(
        None, ge=0, doc="IoU weight of the score per class (default 0.5, then 0.4)"
    )
    target_config: RoiTargetConfig = section(RoiTargetConfig)
    loss_config: RoiLossConfig = section(RoiLossConfig)


#: a trajectory function: (sample index, its chosen proposals ``(S, 9)``) -> boxes per frame
#: ``(T, S, D >= 7)`` (frame 0: the proposals themselves) and their validity ``(T, S)`` or None
TrajectoryFn = Callable[[int, torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]]


def augment_boxes(
    boxes: torch.Tensor,
    references: torch.Tensor,
    base_iou: torch.Tensor,
    *,
    tries: int,
    keep_ratio: float,
    iou_thresh: float,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """MSF's ROI jitter: per box up to ``tries`` draws, each the box itself with probability
    ``keep_ratio`` or the box shifted by U(-0.5, 0.5) m per axis, sized by U(0.85, 1.15) per
    axis and turned by U(-pi/12, pi/12); the first draw whose 3D IoU with its reference reaches
    ``iou_thresh`` is taken, else the last. Columns past the 7th (velocity) are kept. Returns the
    boxes and their IoU (``base_iou`` where the box itself was taken)."""
    num = boxes.shape[0]
    if num == 0:
        return boxes.clone(), base_iou.clone()
    u = torch.rand(tries, num, 8, generator=generator, dtype=torch.float64).to(boxes)
    keep = u[..., 7] <= keep_ratio
    cand = boxes[None].repeat(tries, 1, 1)
    cand[..., 0:3] = cand[..., 0:3] + (u[..., 0:3] - 0.5)
    cand[..., 3:6] = cand[..., 3:6] * (1.0 + (u[..., 3:6] - 0.5) * 0.3)
    cand[..., 6] = cand[..., 6] + (u[..., 6] - 0.5) * (math.pi / 6)
    cand = torch.where(keep[..., None], boxes[None], cand)
    iou = boxes_aligned_iou3d(
        cand.reshape(-1, cand.shape[-1])[:, :7], references[None].expand(tries, -1, -1)
        .reshape(-1, references.shape[-1])[:, :7],
    ).reshape(tries, num).to(boxes.dtype)  # fmt: skip
    iou = torch.where(keep, base_iou[None].to(boxes.dtype), iou)
    ok = iou >= iou_thresh
    first = torch.where(ok.any(0), ok.float().argmax(0), torch.full_like(ok[0], tries - 1).long())
    cols = torch.arange(num, device=boxes.device)
    return cand[first, cols], iou[first, cols]


class TemporalRoIHead(nn.Module):
    """Targets, loss and decoding of a temporal ROI head (module docstring).

    ``num_point_features`` counts the point columns with the time lag (last). Config keys read by
    :meth:`common_config`: ``IOU_WEIGHT`` (per class, the weight of the
    refined confidence in the fused score), ``TARGET_CONFIG`` (OpenPCDet's ROI sampler keys
    plus MSF's ``USE_ROI_AUG``, ``ROI_FG_AUG_TIMES``, ``RATIO``, ``USE_TRAJ_AUG``) and
    ``LOSS_CONFIG.LOSS_WEIGHTS``.
    """

    def __init__(
        self,
        *,
        num_class: int,
        num_point_features: int,
        iou_weight: Sequence[float],
        sampler_cfg: RoiSamplerConfig | None = None,
        roi_aug: Mapping | None = None,
        loss_weights: Mapping | None = None,
    ):
        super().__init__()
        if num_point_features < 6:
            raise ValueError(
                f"{type(self).__name__} needs points [x, y, z, intensity, elongation, ..., time "
                f"lag], got {num_point_features} columns"
            )
        #: point columns the head reads: x, y, z, intensity, elongation, ... (not the time lag)
        self.point_feature_dim = num_point_features - 1
        if len(iou_weight) != num_class:
            raise ValueError(
                f"IOU_WEIGHT needs one weight per class ({num_class}), got {iou_weight}"
            )
        self.num_class = num_class
        self.iou_weight = [float(w) for w in iou_weight]
        self.sampler_cfg = sampler_cfg or RoiSamplerConfig()
        self.roi_aug = dict(roi_aug or RoiTargetConfig().roi_aug())
        self.loss_weights = dict(loss_weights or {})
        for key, size in (("traj_reg_weight", 3), ("code_weights", 7)):
            value = self.loss_weights.get(key)
            if value is not None and (
                isinstance(value, str) or not isinstance(value, Sequence) or len(value) != size
            ):
                raise ValueError(
                    f"LOSS_CONFIG.LOSS_WEIGHTS.{key} needs {size} weights, got {value!r}"
                )
        self.box_coder = ResidualCoder(7)

    @staticmethod
    def common_config(settings: RoiHeadConfig, class_names: Sequence[str]) -> dict:
        """The keyword arguments of :class:`TemporalRoIHead` from a read ``MODEL.ROI_HEAD``."""
        target = settings.target_config
        weights = settings.loss_config.loss_weights
        iou_weight = settings.iou_weight
        if iou_weight is None:
            iou_weight = [0.5] + [0.4] * (len(class_names) - 1)
        return {
            "num_class": len(class_names),
            "iou_weight": list(iou_weight),
            "sampler_cfg": target.sampler(),
            "roi_aug": target.roi_aug(),
            "loss_weights": {
                f: as_lists(v) for f, v in fields_of(weights).items() if v is not None
            },
        }

    # ------------------------------------------------------------------ training
    def default_trajectories(
        self, sample: int, chosen: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The head's :data:`TrajectoryFn` when :meth:`assign_targets` is given none."""
        raise NotImplementedError(f"{type(self).__name__} needs a trajectory_fn")

    def assign_targets(
        self,
        rois: torch.Tensor,
        roi_labels: torch.Tensor,
        roi_valid: torch.Tensor,
        gt_boxes: torch.Tensor,
        generators: Sequence[torch.Generator],
        trajectory_fn: TrajectoryFn | None = None,
    ) -> dict:
        """Sample ``ROI_PER_IMAGE`` proposals per frame, jitter them (MSF's ROI and trajectory
        augmentation) and match them to the ground truth.

        Args:
            rois: ``(B, R, 9)`` proposals with velocity; roi_labels ``(B, R)`` 1-based;
                roi_valid ``(B, R)`` bool (False: padding).
            gt_boxes: ``(B, M, 8|10)`` with the 1-based class last (all-zero rows: padding).
            generators: one per sample.
            trajectory_fn: the boxes of each chosen proposal over the head's frames, computed
                from the unjittered proposal (:data:`TrajectoryFn`; default: the head's
                :meth:`default_trajectories`).
        Returns:
            ``rois`` ``(B, S, 9)``, ``trajectories`` ``(B, T, S, D)`` (frame 0: the jittered
            ROI), ``trajectory_valid`` ``(B, T, S)``, ``roi_valid`` ``(B, S)`` (False for every
            row of a frame without proposals), ``gt_of_rois`` ``(B, S, 7)``, ``reg_valid``
            ``(B, S)`` bool, ``cls_label`` ``(B, S)``, ``roi_labels`` ``(B, S)``.
        """
        trajectory_fn = trajectory_fn or self.default_trajectories
        cfg, aug = self.sampler_cfg, self.roi_aug
        count, batch, device = cfg.roi_per_image, len(generators), rois.device
        out = {
            "rois": rois.new_zeros(batch, count, rois.shape[-1]),
            "roi_valid": torch.zeros(batch, count, dtype=torch.bool, device=device),
            "gt_of_rois": rois.new_zeros(batch, count, 7),
            "reg_valid": torch.zeros(batch, count, dtype=torch.bool, device=device),
            "cls_label": rois.new_zeros(batch, count),
            "roi_labels": torch.zeros(batch, count, dtype=torch.long, device=device),
        }
        trajectories: list[torch.Tensor | None] = [None] * batch
        traj_valid: list[torch.Tensor | None] = [None] * batch
        fg_thresh = min(cfg.reg_fg_thresh, cfg.cls_fg_thresh)
        for b, gen in enumerate(generators):
            keep = roi_valid[b]
            if not bool(keep.any()):
                continue  # a frame without proposals trains nothing (its rows stay invalid)
            cur, labels = rois[b][keep], roi_labels[b][keep]
            gt = gt_boxes[b][gt_boxes[b, :, :7].abs().sum(1) > 0]
            draw = sample_rois(cur, labels, gt[:, :7], gt[:, -1].long(), cfg, gen)
            chosen = cur[draw.roi_index].clone()
            iou = draw.iou.to(chosen.dtype)
            matched = gt[draw.gt_index.clamp_min(0), :7] if gt.shape[0] else chosen[:, :7] * 0
            traj, valid = trajectory_fn(b, chosen)  # from the unjittered proposal
            traj = traj.clone()
            fg = iou >= fg_thresh
            if aug["ENABLED"] and bool(fg.any()):
                boxes, new_iou = augment_boxes(
                    chosen[fg, :7], matched[fg], iou[fg], tries=aug["TRIES"],
                    keep_ratio=aug["KEEP_RATIO"], iou_thresh=fg_thresh, generator=gen,
                )  # fmt: skip
                chosen[fg, :7], iou[fg] = boxes, new_iou
                if aug["TRAJ_ENABLED"]:
                    for frame in range(1, traj.shape[0]):
                        ref = traj[frame][fg]
                        traj[frame][fg] = augment_boxes(
                            ref, ref, torch.ones_like(new_iou), tries=aug["TRIES"],
                            keep_ratio=aug["KEEP_RATIO"], iou_thresh=aug["TRAJ_THRESH"],
                            generator=gen,
                        )[0]  # fmt: skip
            traj[0, :, :7] = chosen[:, :7]
            trajectories[b] = traj
            traj_valid[b] = (
                valid if valid is not None else torch.ones(traj.shape[:2], dtype=torch.bool,
                                                           device=device)
            )  # fmt: skip
            out["rois"][b] = chosen
            out["roi_valid"][b] = True
            out["gt_of_rois"][b] = matched
            out["reg_valid"][b] = (iou > cfg.reg_fg_thresh) & (draw.gt_index >= 0)
            out["cls_label"][b] = soft_iou_label(iou, cfg.cls_fg_thresh, cfg.cls_bg_thresh)
            out["roi_labels"][b] = labels[draw.roi_index]
        template = next((t for t in trajectories if t is not None), None)
        if template is None:  # no sample has proposals: shapes from an empty call
            template, _ = trajectory_fn(0, rois.new_zeros(0, rois.shape[-1]))
        shape = (template.shape[0], count, template.shape[-1])
        out["trajectories"] = torch.stack(
            [t if t is not None else rois.new_zeros(shape) for t in trajectories]
        )
        out["trajectory_valid"] = torch.stack([
            v if v is not None else torch.zeros(shape[:2], dtype=torch.bool, device=device)
            for v in traj_valid
        ])  # fmt: skip
        return out

    def loss(self, outputs: Mapping, targets: Mapping) -> dict[str, torch.Tensor]:
        """Soft-label BCE on every block's confidence, smooth-L1 (beta 1/9) on the refined box,
        the box-sequence branch's and the auxiliary codes, and the corner loss of the refined
        box (weights: ``LOSS_CONFIG.LOSS_WEIGHTS``; ``traj_reg_weight`` = the weights of the
        refined, box-sequence and auxiliary codes, default 2 each)."""
        w = self.loss_weights
        traj_w = list(w.get("traj_reg_weight", [2.0, 2.0, 2.0]))
        code_w = torch.as_tensor(
            w.get("code_weights", [1.0] * 7), dtype=outputs["rcnn_reg"].dtype,
            device=outputs["rcnn_reg"].device,
        )  # fmt: skip
        valid = targets["roi_valid"]
        reg_valid = targets["reg_valid"] & valid
        rois = targets["rois"][..., :7]
        goal = encode_roi_targets(
            targets["gt_of_rois"].reshape(-1, 7), rois.reshape(-1, 7), self.box_coder
        ).reshape(rois.shape)
        num_valid = valid.sum().clamp_min(1)
        num_fg = reg_valid.sum().clamp_min(1)

        def reg_loss(codes: torch.Tensor) -> torch.Tensor:
            per = F.smooth_l1_loss(codes, goal, beta=SMOOTH_L1_BETA, reduction="none") * code_w
            return (per.sum(-1) * reg_valid).sum() / num_fg

        cls = torch.stack([
            (F.binary_cross_entropy_with_logits(
                logits, targets["cls_label"], reduction="none") * valid).sum() / num_valid
            for logits in outputs["rcnn_cls"]
        ]).mean() * w.get("rcnn_cls_weight", 1.0)  # fmt: skip
        reg = reg_loss(outputs["rcnn_reg"]) * w.get("rcnn_reg_weight", 1.0) * traj_w[0]
        traj = reg_loss(outputs["traj_reg"]) * traj_w[1]
        losses = {"rcnn_loss_cls": cls, "rcnn_loss_reg": reg, "rcnn_loss_traj": traj}
        if outputs["aux_reg"]:
            aux = torch.stack([reg_loss(c) for c in outputs["aux_reg"]]).mean() * traj_w[2]
            losses["rcnn_loss_aux"] = aux
        fg_rois, fg_codes = rois[reg_valid], outputs["rcnn_reg"][reg_valid]
        if fg_rois.shape[0]:
            boxes = decode_roi_boxes(fg_codes, fg_rois, self.box_coder)
            corner = corner_loss(boxes, targets["gt_of_rois"][reg_valid]).mean()
        else:
            corner = outputs["rcnn_reg"].sum() * 0.0
        losses["rcnn_loss_corner"] = corner * w.get("rcnn_corner_weight", 2.0)
        return {"loss": sum(losses.values()), **losses}

    # ------------------------------------------------------------------ inference
    def decode(self, outputs: Mapping, rois: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, R, 7)`` refined boxes and ``(B, R)`` confidence logits (last block)."""
        shape = rois.shape[:2]
        boxes = decode_roi_boxes(
            outputs["rcnn_reg"].reshape(-1, 7), rois[..., :7].reshape(-1, 7), self.box_coder
        )
        return boxes.reshape(*shape, 7), outputs["rcnn_cls"][-1]
