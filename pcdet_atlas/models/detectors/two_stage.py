"""Two-stage temporal detectors (MSF, PTT): a frozen proposal network (RPN) and a refining head.

The RPN is a complete detector of this project (CP-4f), built from its own config file and
loaded from its checkpoint (``MODEL.RPN: {CFG, CHECKPOINT}``). It is frozen: its parameters
are not parameters of the two-stage model (no optimizer sees them, ``state_dict`` leaves them
out), it always runs in eval mode, and it moves with the model (``.to``, ``.cuda``). What a
two-stage checkpoint was trained with is recorded in it (``model_info``: the RPN checkpoint's
SHA-256) and checked when it is loaded, so second-stage weights never meet another RPN.

Proposals at test time always come from the RPN run on the batch's own points (attacked points
under an attack): :meth:`TwoStageDetector.propose`. Training reads proposals precomputed on
clean data from the batch (``roi_boxes``; :mod:`pcdet_atlas.train_utils.proposals`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch

from pcdet_atlas.config import ConfigError, cfg_from_yaml_file, resolve_repo_path
from pcdet_atlas.config_values import read_section, section, setting, unsupported
from pcdet_atlas.models.build import build_network_from_config, num_point_features_of
from pcdet_atlas.models.detectors.detector3d_template import (
    CheckpointMismatchError,
    Detector3DTemplate,
    DetectorConfig,
    PostProcessingConfig,
)
from pcdet_atlas.models.model_utils.motion_sampler import frame_of_points
from pcdet_atlas.models.model_utils.roi_utils import fuse_scores, select_detections
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.seeding import torch_generator

__all__ = [
    "RPNConfig",
    "TwoStageConfig",
    "TwoStageDetector",
    "TwoStageNMSConfig",
    "TwoStagePostProcessing",
    "load_rpn",
]


def _given(value: str) -> bool:
    return bool(value)


@dataclass(frozen=True, kw_only=True)
class RPNConfig:
    """``MODEL.RPN``: the frozen proposal network."""

    cfg: str = setting(check=_given, expected="a config file", doc="the RPN's config file")
    checkpoint: str = setting(
        check=_given, expected="a checkpoint file", doc="the RPN's trained checkpoint"
    )
    cache_dir: str | None = setting(None, doc="folder of precomputed training proposals")


@dataclass(frozen=True, kw_only=True)
class TwoStageNMSConfig:
    """``MODEL.POST_PROCESSING.NMS_CONFIG``: class-agnostic rotated BEV NMS (the one that runs;
    ``NMS_TYPE`` and ``MULTI_CLASSES_NMS`` only with its values)."""

    nms_thresh: float = setting(0.7, gt=0, le=1, doc="BEV IoU above which a box is suppressed")
    nms_pre_maxsize: int = setting(4096, ge=1, doc="highest-scoring boxes entering NMS")
    nms_post_maxsize: int = setting(500, ge=1, doc="boxes kept after NMS")
    nms_type: str = setting(
        "nms_gpu", choices=("nms_gpu", "nms_bev"),
        expected="'nms_gpu' or 'nms_bev': only rotated BEV NMS is implemented",
        doc="nms_gpu or nms_bev (the same rotated BEV NMS)",
    )  # fmt: skip
    multi_classes_nms: bool = unsupported("only class-agnostic NMS is implemented")


@dataclass(frozen=True, kw_only=True)
class TwoStagePostProcessing(PostProcessingConfig):
    """``MODEL.POST_PROCESSING`` of a two-stage detector (read by
    :meth:`TwoStageDetector.detections`)."""

    score_thresh: float = setting(0.1, ge=0, doc="refined detections below it are dropped")
    not_apply_nms_for_vel: bool = setting(True, doc="no NMS for vehicles (as MSF and PTT)")
    nms_config: TwoStageNMSConfig = section(TwoStageNMSConfig)


@dataclass(frozen=True, kw_only=True)
class TwoStageConfig(DetectorConfig):
    """``MODEL`` of a two-stage detector: the detector's keys and its RPN."""

    rpn: RPNConfig = setting(doc="the frozen proposal network (CFG and CHECKPOINT)")
    post_processing: TwoStagePostProcessing = section(TwoStagePostProcessing)


def rpn_window(rpn_cfg: Mapping) -> int:
    """Frames of points the RPN reads (its ``SEQUENCE_CONFIG.SAMPLE_OFFSET`` span; 1 without)."""
    seq = rpn_cfg.DATA_CONFIG.get("SEQUENCE_CONFIG") or {}
    if not seq.get("ENABLED", False):
        return 1
    low, high = seq["SAMPLE_OFFSET"]
    return int(high) - int(low) + 1


def load_rpn(rpn_section: Mapping) -> tuple[Detector3DTemplate, dict]:
    """Build and load the RPN of a ``MODEL.RPN`` section; returns it (eval mode, gradients off)
    and its identity ``{'cfg', 'checkpoint', 'sha256', 'window', 'cfg_dict'}``."""
    settings = read_section(RPNConfig, rpn_section, "MODEL.RPN")
    cfg_path = resolve_repo_path(settings.cfg)
    ckpt_path = resolve_repo_path(settings.checkpoint)
    if not cfg_path.is_file():
        raise FileNotFoundError(f"MODEL.RPN.CFG: {cfg_path} not found")
    if not ckpt_path.is_file():
        raise FileNotFoundError(
            f"MODEL.RPN.CHECKPOINT: {ckpt_path} not found (train the RPN with tools/train.py "
            f"--cfg {settings.cfg}; docs/getting_started.md, two-stage models)"
        )
    rpn_cfg = cfg_from_yaml_file(cfg_path)
    rpn = build_network_from_config(rpn_cfg)
    num_point_features = num_point_features_of(rpn_cfg.DATA_CONFIG)
    rpn.load_params_from_file(ckpt_path)
    rpn.eval()
    for param in rpn.parameters():
        param.requires_grad_(False)
    info = {
        "cfg": settings.cfg,
        "checkpoint": settings.checkpoint,
        "sha256": file_sha256(ckpt_path),
        "window": rpn_window(rpn_cfg),
        "num_point_features": num_point_features,
        "cache_dir": settings.cache_dir,
        "cfg_dict": rpn_cfg,
    }
    return rpn, info


class TwoStageDetector(Detector3DTemplate):
    """A frozen RPN plus stages of its own (module docstring)."""

    CONFIG = TwoStageConfig

    def __init__(self, *, class_names, rpn: Detector3DTemplate, rpn_info: Mapping,
                 post_processing: TwoStagePostProcessing | None = None, **stages):  # fmt: skip
        super().__init__(class_names=class_names, **stages)
        object.__setattr__(self, "rpn", rpn)  # not a submodule: frozen, not in state_dict
        self.rpn_info = {k: v for k, v in rpn_info.items() if k != "cfg_dict"}
        self.post_processing = post_processing or TwoStagePostProcessing()

    @classmethod
    def from_config(cls, model_cfg: Mapping, **kwargs) -> TwoStageDetector:
        settings = cls.read_config(model_cfg)
        rpn, info = load_rpn(model_cfg["RPN"])
        rpn_points = info["num_point_features"]
        if rpn_points != kwargs["num_point_features"]:
            raise ConfigError(
                f"MODEL.RPN.CFG {info['cfg']} reads {rpn_points} point columns, this model's "
                f"data {kwargs['num_point_features']}: both need x, y, z, intensity, "
                "elongation and the time lag"
            )
        return super().from_config(
            model_cfg, rpn=rpn, rpn_info=info, post_processing=settings.post_processing,
            **kwargs,
        )  # fmt: skip

    @property
    def proposal_history(self) -> int:
        """How many previous frames' proposals the model reads besides the current frame's (0:
        only the current frame's, which :meth:`propose` computes from the batch)."""
        return 0

    # ------------------------------------------------------------------ the frozen RPN
    def _apply(self, fn, recurse=True):
        super()._apply(fn, recurse)
        self.rpn._apply(fn, recurse)
        return self

    def train(self, mode: bool = True):
        super().train(mode)
        self.rpn.eval()  # frozen: batch-norm statistics and dropout never change
        return self

    @torch.no_grad()
    def propose(self, batch_dict: Mapping) -> list[dict[str, torch.Tensor]]:
        """The RPN's detections on the batch's own points: the points of its ``window`` newest
        frames (time lag < 0.1 * window s); through the RPN's ``prediction_store`` if set."""
        points = batch_dict["points"]
        keep = frame_of_points(points[:, -1], self.rpn_info["window"]) >= 0
        return self.rpn.stored_predict({**batch_dict, "points": points[keep]})

    # ------------------------------------------------------------------ training
    def second_stage_loss(
        self, batch_dict: Mapping, purpose: str, trajectory_fn=None
    ) -> dict[str, torch.Tensor]:
        """The head's loss on the batch's training proposals ``roi_boxes`` ``(B, R, 11)``:
        ROI sampling and jitter (``<purpose>_targets`` draws), trajectories of the sampled
        proposals by ``trajectory_fn`` (default: the head's), the head on them
        (``<purpose>_points`` draws)."""
        head = self.roi_head
        rois, _, labels, valid = roi_boxes_to_padded(batch_dict["roi_boxes"])
        targets = head.assign_targets(
            rois, labels, valid, batch_dict["gt_boxes"],
            self.sample_generators(batch_dict, f"{purpose}_targets"), trajectory_fn,
        )  # fmt: skip
        out = head({
            **batch_dict, "rois": targets["rois"], "roi_valid": targets["roi_valid"],
            "trajectories": targets["trajectories"],
            "trajectory_valid": targets["trajectory_valid"],
            "generators": self.sample_generators(batch_dict, f"{purpose}_points"),
        })  # fmt: skip
        return head.loss(out, targets)

    # ------------------------------------------------------------------ detections
    def detections(
        self,
        proposals: list[Mapping],
        boxes: torch.Tensor,
        logits: torch.Tensor,
        scores: torch.Tensor,
        labels: torch.Tensor,
    ) -> list[dict[str, torch.Tensor]]:
        """Per sample: the refined boxes ``(B, R, 7)`` of its proposals with their confidence
        ``logits`` fused with the proposal ``scores`` (``IOU_WEIGHT`` per class), then the score
        threshold and class-agnostic NMS (none for vehicles with ``NOT_APPLY_NMS_FOR_VEL``, as
        MSF and PTT). ``proposals`` (the RPN's per-sample outputs) are returned as ``rois``,
        ``roi_scores``, ``roi_labels``."""
        post = self.post_processing
        nms = post.nms_config
        no_nms = [1 + self.class_names.index("Vehicle")] if (
            post.not_apply_nms_for_vel and "Vehicle" in self.class_names
        ) else []  # fmt: skip
        results = []
        for b, proposal in enumerate(proposals):
            n = len(proposal["pred_scores"])
            fused = fuse_scores(
                logits[b, :n], scores[b, :n], labels[b, :n], self.roi_head.iou_weight
            )
            keep = select_detections(
                boxes[b, :n], fused, labels[b, :n],
                score_thresh=post.score_thresh,
                nms_thresh=nms.nms_thresh,
                pre_max_size=nms.nms_pre_maxsize,
                post_max_size=nms.nms_post_maxsize,
                no_nms_labels=no_nms,
            )  # fmt: skip
            results.append({
                "pred_boxes": boxes[b, keep], "pred_scores": fused[keep],
                "pred_labels": labels[b, keep], "rois": proposal["pred_boxes"],
                "roi_scores": proposal["pred_scores"], "roi_labels": proposal["pred_labels"],
            })  # fmt: skip
        return results

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_info(self) -> dict:
        """What a checkpoint of this model records besides its weights."""
        return {"rpn": dict(self.rpn_info)}

    def load_params_from_file(self, filename, *, strict: bool = True, map_location: str = "cpu"):
        ckpt = super().load_params_from_file(filename, strict=strict, map_location=map_location)
        self.check_checkpoint_info(ckpt, filename)
        return ckpt

    def check_checkpoint_info(self, ckpt: Mapping, source) -> None:
        """Refuse a checkpoint trained on the proposals of another RPN checkpoint."""
        recorded = (ckpt.get("model_info") or {}).get("rpn", {}).get("sha256")
        if recorded != self.rpn_info["sha256"]:
            raise CheckpointMismatchError(
                f"checkpoint {source} was trained on the proposals of an RPN with checkpoint "
                f"SHA-256 {recorded}; MODEL.RPN.CHECKPOINT {self.rpn_info['checkpoint']} has "
                f"{self.rpn_info['sha256']}: use the RPN it was trained with, or retrain"
            )

    # ------------------------------------------------------------------ randomness
    @staticmethod
    def sample_generators(batch_dict: Mapping, purpose: str) -> list[torch.Generator]:
        """One CPU generator per sample, keyed by the sample's ``frame_seed`` (set by the
        dataset from its seed, epoch, sequence and frame) and ``purpose``."""
        if "frame_seed" not in batch_dict:
            raise KeyError(
                "two-stage models need batch_dict['frame_seed'] (one int per sample, as the "
                "datasets' collate_batch provides)"
            )
        return [torch_generator(int(s), purpose) for s in batch_dict["frame_seed"]]


def proposals_to_padded(
    proposals: list[Mapping], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-sample RPN outputs -> ``boxes (B, R, 9)``, ``scores (B, R)``, ``labels (B, R)`` long,
    ``valid (B, R)`` bool (``R``: the largest count, at least 1)."""
    count = max([1] + [len(p["pred_scores"]) for p in proposals])
    batch = len(proposals)
    boxes = torch.zeros(batch, count, 9, device=device)
    scores = torch.zeros(batch, count, device=device)
    labels = torch.zeros(batch, count, dtype=torch.long, device=device)
    valid = torch.zeros(batch, count, dtype=torch.bool, device=device)
    for b, p in enumerate(proposals):
        n = len(p["pred_scores"])
        width = p["pred_boxes"].shape[1] if n else 9
        if n and width < 9:
            raise ValueError(f"RPN boxes need velocity columns (9), got {width}")
        boxes[b, :n] = p["pred_boxes"][:, :9].to(device)
        scores[b, :n] = p["pred_scores"].to(device)
        labels[b, :n] = p["pred_labels"].to(device).long()
        valid[b, :n] = True
    return boxes, scores, labels, valid


def roi_boxes_to_padded(roi_boxes: torch.Tensor):
    """A batch's collated ``roi_boxes`` ``(B, R, 11)`` ``[box 9, score, label]`` (label 0:
    padding) -> ``boxes``, ``scores``, ``labels``, ``valid`` as :func:`proposals_to_padded`."""
    labels = roi_boxes[..., 10].round().long()
    return roi_boxes[..., :9], roi_boxes[..., 9], labels, labels > 0
