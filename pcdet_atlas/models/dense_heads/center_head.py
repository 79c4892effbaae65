"""CenterHead: CenterPoint's BEV heatmap + box regression head, with optional velocity.

One head for all classes (OpenPCDet's Waymo setting): a shared 3x3 conv, then one small conv
branch per output (``center`` 2, ``center_z`` 1, ``dim`` 3, ``rot`` 2, optionally ``vel`` 2, and
``hm`` one channel per class). Training targets, losses and decoding are in
:mod:`pcdet_atlas.models.model_utils.centernet_utils`; boxes are de-duplicated by rotated BEV NMS
from :mod:`pcdet_atlas.ops.iou3d_nms`, over all classes or per class (``class_specific_nms``).

DSVT's Waymo head adds an ``iou`` branch (HEAD_DICT ``iou``) trained to the 3D IoU of the
predicted box with its GT box (mapped to [-1, 1]), a DIoU regression loss on the decoded boxes
(``IOU_REG_LOSS``), and at test time rectifies each score with the predicted IoU,
``score ** (1 - r) * iou ** r`` with ``r`` per class (``IOU_RECTIFIER``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import as_lists, section, setting, unsupported
from pcdet_atlas.models.dense_heads.center_config import (
    CenterTargetConfig,
    LossConfig,
    LossWeightsConfig,
    SeparateHeadConfig,
    branch_num_convs,
    check_one_head,
)
from pcdet_atlas.models.model_utils import centernet_utils as cu
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d, nms_bev, nms_bev_per_class
from pcdet_atlas.registry import MODEL_STAGES

REG_HEADS = {"center": 2, "center_z": 1, "dim": 3, "rot": 2, "vel": 2, "iou": 1}
NMS_TYPES = ("nms_gpu", "nms_bev", "class_specific_nms")


class SeparateHead(nn.Module):
    """One conv branch per output map: ``num_conv - 1`` x (conv3x3-BN-ReLU), then conv3x3."""

    def __init__(
        self,
        in_channels: int,
        heads: Mapping[str, tuple[int, int]],
        init_bias: float,
        use_bias: bool,
        bn_eps: float = 1e-5,
        bn_momentum: float = 0.1,
    ):
        """heads: ``name -> (out_channels, num_conv)``; the ``hm`` bias starts at ``init_bias``."""
        super().__init__()
        self.branches = nn.ModuleDict()
        for name, (out_ch, num_conv) in heads.items():
            layers: list[nn.Module] = []
            for _ in range(num_conv - 1):
                layers += [
                    nn.Conv2d(in_channels, in_channels, 3, padding=1, bias=use_bias),
                    nn.BatchNorm2d(in_channels, eps=bn_eps, momentum=bn_momentum),
                    nn.ReLU(),
                ]
            layers.append(nn.Conv2d(in_channels, out_ch, 3, padding=1, bias=True))
            branch = nn.Sequential(*layers)
            if name == "hm":  # default init, final bias = init_bias (prior ~0.1)
                nn.init.constant_(branch[-1].bias, init_bias)
            else:
                for m in branch.modules():
                    if isinstance(m, nn.Conv2d):
                        nn.init.kaiming_normal_(m.weight)
                        if m.bias is not None:
                            nn.init.zeros_(m.bias)
            self.branches[name] = branch

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {name: branch(x) for name, branch in self.branches.items()}


SECTION = "MODEL.DENSE_HEAD"
_BOX_CODES = (("center", "center_z", "dim", "rot"), ("center", "center_z", "dim", "rot", "vel"))


@dataclass(frozen=True, kw_only=True)
class CenterSeparateHeadConfig(SeparateHeadConfig):
    head_order: tuple[str, ...] = setting(
        _BOX_CODES[0],
        check=lambda order: order in _BOX_CODES,
        expected="[center, center_z, dim, rot] with optional vel",
        doc="branches of the box code, in order",
    )


@dataclass(frozen=True, kw_only=True)
class CenterNmsConfig:
    """``POST_PROCESSING.NMS_CONFIG``."""

    nms_type: str = setting(
        "nms_gpu",
        choices=NMS_TYPES,
        expected=f"one of {', '.join(NMS_TYPES)} (rotated BEV NMS)",
        doc="over all classes, or class_specific_nms",
    )
    nms_thresh: float | tuple[float, ...] = setting(0.7, doc="IoU threshold (per class)")
    nms_pre_maxsize: int | tuple[int, ...] = setting(4096, doc="boxes before NMS (per class)")
    nms_post_maxsize: int | tuple[int, ...] = setting(500, doc="boxes after NMS (per class)")


@dataclass(frozen=True, kw_only=True)
class CenterPostConfig:
    """``POST_PROCESSING`` of the head."""

    score_thresh: float = setting(0.1, doc="boxes scoring below are dropped")
    post_center_limit_range: tuple[float, float, float, float, float, float] | None = setting(
        None, doc="box centres outside are dropped, m"
    )
    max_obj_per_sample: int = setting(500, ge=1, doc="top-K heatmap peaks")
    nms_config: CenterNmsConfig = section(CenterNmsConfig)
    use_iou_to_rectify_score: bool = setting(False, doc="scores ** (1 - r) * iou ** r")
    iou_rectifier: tuple[float, ...] | None = setting(None, doc="r per class")


@dataclass(frozen=True, kw_only=True)
class CenterHeadConfig(StageConfig):
    """``MODEL.DENSE_HEAD`` of CenterHead (OpenPCDet's keys)."""

    class_agnostic: bool = unsupported("one class-aware head")
    class_names_each_head: tuple[tuple[str, ...], ...] | None = setting(
        None, doc="one head over all CLASS_NAMES"
    )
    shared_conv_channel: int = setting(64, ge=1, doc="width of the shared conv")
    use_bias_before_norm: bool = setting(False, doc="conv bias before BatchNorm")
    num_hm_conv: int = setting(2, ge=1, doc="convs of the heatmap branch")
    separate_head_cfg: CenterSeparateHeadConfig = section(CenterSeparateHeadConfig)
    target_assigner_config: CenterTargetConfig = section(CenterTargetConfig)
    loss_config: LossConfig = section(LossConfig)
    post_processing: CenterPostConfig = section(CenterPostConfig)
    iou_reg_loss: bool = setting(False, doc="DIoU loss of the decoded boxes")
    bn_eps: float = setting(1e-5, gt=0, doc="BatchNorm eps")
    bn_momentum: float = setting(0.1, key="BN_MOM", gt=0, le=1, doc="BatchNorm momentum")


@MODEL_STAGES.register()
class CenterHead(nn.Module):
    """Reads ``spatial_features_2d`` (B, C, H, W); writes ``head_outputs``: a dict of maps
    ``hm`` (B, num_class, H, W) logits, ``center`` (B, 2, H, W), ``center_z`` (B, 1, H, W),
    ``dim`` (B, 3, H, W) log-sizes, ``rot`` (B, 2, H, W) ``[cos, sin]``, optionally ``vel``
    (B, 2, H, W) m/s and ``iou`` (B, 1, H, W) in [-1, 1]."""

    CONFIG = CenterHeadConfig

    def __init__(
        self,
        *,
        input_channels: int,
        num_class: int,
        point_cloud_range: Sequence[float],
        voxel_size: Sequence[float],
        grid_size: Sequence[int],
        feature_map_stride: int = 1,
        with_velocity: bool = False,
        shared_conv_channel: int = CenterHeadConfig.shared_conv_channel,
        use_bias_before_norm: bool = CenterHeadConfig.use_bias_before_norm,
        num_hm_conv: int = CenterHeadConfig.num_hm_conv,
        reg_num_conv: int | Mapping[str, int] = 2,
        init_bias: float = -2.19,
        num_max_objs: int = CenterTargetConfig.num_max_objs,
        gaussian_overlap: float = CenterTargetConfig.gaussian_overlap,
        min_radius: int = CenterTargetConfig.min_radius,
        cls_weight: float = LossWeightsConfig.cls_weight,
        loc_weight: float = LossWeightsConfig.loc_weight,
        code_weights: Sequence[float] | None = None,
        score_thresh: float = CenterPostConfig.score_thresh,
        post_center_limit_range: Sequence[float] | None = None,
        max_obj_per_sample: int = CenterPostConfig.max_obj_per_sample,
        nms_thresh: float | Sequence[float] = CenterNmsConfig.nms_thresh,
        nms_pre_maxsize: int | Sequence[int] = CenterNmsConfig.nms_pre_maxsize,
        nms_post_maxsize: int | Sequence[int] = CenterNmsConfig.nms_post_maxsize,
        nms_type: str = CenterNmsConfig.nms_type,
        with_iou: bool = False,
        iou_reg_loss: bool = CenterHeadConfig.iou_reg_loss,
        iou_rectifier: Sequence[float] | None = None,
        bn_eps: float = CenterHeadConfig.bn_eps,
        bn_momentum: float = CenterHeadConfig.bn_momentum,
    ):
        """
        Args:
            input_channels: width of ``spatial_features_2d``.
            num_class: heatmap channels (classes are 1-based in ``gt_boxes`` and predictions).
            point_cloud_range, voxel_size, grid_size: the VFE's grid (metres / cells).
            feature_map_stride: voxels per head cell along x and y.
            with_velocity: regress ``[vx, vy]`` (multi-frame input; GT must have 10 columns).
            reg_num_conv: convs per regression branch (an int, or per head name).
            code_weights: L1 weight per regression channel (8, or 10 with velocity).
            nms_thresh / nms_pre_maxsize / nms_post_maxsize: rotated BEV NMS over all classes
                (``nms_type`` ``'nms_gpu'``), or one value per class (``'class_specific_nms'``).
            with_iou: add the ``iou`` branch (its L1 loss to the boxes' 3D IoU in training).
            iou_reg_loss: add the DIoU loss of the decoded boxes (weighted by ``loc_weight``).
            iou_rectifier: per class ``r``: scores become ``score ** (1 - r) * iou ** r`` (needs
                ``with_iou``); None keeps the heatmap scores.
            bn_eps / bn_momentum: the head's BatchNorm settings (OpenPCDet's BN_EPS / BN_MOM).
        """
        super().__init__()
        self.num_class = num_class
        self.point_cloud_range = tuple(float(v) for v in point_cloud_range)
        self.voxel_size = tuple(float(v) for v in voxel_size)
        self.feature_map_stride = int(feature_map_stride)
        self.feature_map_size = cu.head_map_size(grid_size, feature_map_stride, "CenterHead")
        self.with_velocity = with_velocity
        self.code_size = 10 if with_velocity else 8
        if code_weights is None:
            code_weights = [1.0] * 8 + ([0.2, 0.2] if with_velocity else [])
        if len(code_weights) != self.code_size:
            raise ValueError(
                f"CenterHead: code_weights needs {self.code_size} values "
                f"(center 2, center_z 1, dim 3, rot 2{', vel 2' if with_velocity else ''}), "
                f"got {len(code_weights)}"
            )
        self.register_buffer("code_weights", torch.tensor(code_weights, dtype=torch.float32))
        self.num_max_objs = num_max_objs
        self.gaussian_overlap = gaussian_overlap
        self.min_radius = min_radius
        self.cls_weight = cls_weight
        self.loc_weight = loc_weight
        self.score_thresh = score_thresh
        self.post_center_limit_range = (
            None if post_center_limit_range is None else tuple(map(float, post_center_limit_range))
        )
        self.max_obj_per_sample = max_obj_per_sample
        if nms_type not in NMS_TYPES:
            raise ValueError(f"CenterHead: nms_type must be one of {NMS_TYPES}, got {nms_type!r}")
        per_class = nms_type == "class_specific_nms"
        for name, value in (("nms_thresh", nms_thresh), ("nms_pre_maxsize", nms_pre_maxsize),
                            ("nms_post_maxsize", nms_post_maxsize)):  # fmt: skip
            if per_class != isinstance(value, Sequence) or (per_class and len(value) != num_class):
                raise ValueError(
                    f"CenterHead: {name} {value!r}: class_specific_nms takes one value per class "
                    f"({num_class}), the other NMS types a single value"
                )
        self.nms_type = nms_type
        self.nms_thresh = nms_thresh
        self.nms_pre_maxsize = nms_pre_maxsize
        self.nms_post_maxsize = nms_post_maxsize
        self.with_iou = bool(with_iou)
        self.iou_reg_loss = bool(iou_reg_loss)
        if iou_rectifier is not None and (not with_iou or len(iou_rectifier) != num_class):
            raise ValueError(
                f"CenterHead: iou_rectifier {iou_rectifier!r} needs the iou branch and one value "
                f"per class ({num_class})"
            )
        self.iou_rectifier = None if iou_rectifier is None else tuple(map(float, iou_rectifier))

        self.shared_conv = nn.Sequential(
            nn.Conv2d(input_channels, shared_conv_channel, 3, padding=1, bias=use_bias_before_norm),
            nn.BatchNorm2d(shared_conv_channel, eps=bn_eps, momentum=bn_momentum),
            nn.ReLU(),
        )
        names = ["center", "center_z", "dim", "rot"] + (["vel"] if with_velocity else [])
        names += ["iou"] if with_iou else []
        if isinstance(reg_num_conv, Mapping):
            unknown = set(reg_num_conv) - set(names)
            if unknown:
                raise ValueError(f"CenterHead: num_conv given for unknown heads {sorted(unknown)}")
        heads = {
            n: (
                REG_HEADS[n],
                reg_num_conv.get(n, 2) if isinstance(reg_num_conv, Mapping) else reg_num_conv,
            )
            for n in names
        }
        heads["hm"] = (num_class, num_hm_conv)
        self.head = SeparateHead(
            shared_conv_channel, heads, init_bias, use_bias_before_norm, bn_eps, bn_momentum
        )

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> CenterHead:
        settings = read_stage(cls, cfg, SECTION)
        class_names = list(model_info["class_names"])
        check_one_head(settings.class_names_each_head, class_names)
        order = list(settings.separate_head_cfg.head_order)
        head_dict = settings.separate_head_cfg.head_dict
        # OpenPCDet builds a branch per HEAD_DICT entry; HEAD_ORDER lists the box code only, so
        # DSVT's ``iou`` branch is in HEAD_DICT alone
        if set(head_dict) - set(order) - {"iou"}:
            raise ConfigError(
                f"{SECTION}.SEPARATE_HEAD_CFG.HEAD_DICT has heads not in HEAD_ORDER: "
                f"{sorted(set(head_dict) - set(order) - {'iou'})} (only 'iou' may be extra)"
            )
        reg_num_conv = branch_num_convs(
            settings.separate_head_cfg,
            order + (["iou"] if "iou" in head_dict else []),
            REG_HEADS,
            f"{SECTION}.SEPARATE_HEAD_CFG",
        )
        tac = settings.target_assigner_config
        stride = tac.feature_map_stride
        if (
            model_info.get("backbone_stride") is not None
            and stride != model_info["backbone_stride"]
        ):
            raise ConfigError(
                f"{SECTION}.TARGET_ASSIGNER_CONFIG.FEATURE_MAP_STRIDE ({stride}) differs "
                f"from the backbones' output stride ({model_info['backbone_stride']:g} voxels "
                f"per cell: the 3D backbone's stride times the BEV backbone's)"
            )
        weights = settings.loss_config.loss_weights
        post = settings.post_processing
        if post.use_iou_to_rectify_score and ("iou" not in head_dict or not post.iou_rectifier):
            raise ConfigError(
                f"{SECTION}.POST_PROCESSING.USE_IOU_TO_RECTIFY_SCORE needs an 'iou' "
                "branch in SEPARATE_HEAD_CFG.HEAD_DICT and IOU_RECTIFIER (one value per class)"
            )
        nms = post.nms_config
        return cls(
            input_channels=model_info["num_bev_features"],
            num_class=len(class_names),
            point_cloud_range=model_info["point_cloud_range"],
            voxel_size=model_info["voxel_size"],
            grid_size=model_info["grid_size"],
            feature_map_stride=stride,
            with_velocity="vel" in order,
            shared_conv_channel=settings.shared_conv_channel,
            use_bias_before_norm=settings.use_bias_before_norm,
            num_hm_conv=settings.num_hm_conv,
            reg_num_conv=reg_num_conv,
            num_max_objs=tac.num_max_objs,
            gaussian_overlap=tac.gaussian_overlap,
            min_radius=tac.min_radius,
            cls_weight=weights.cls_weight,
            loc_weight=weights.loc_weight,
            code_weights=as_lists(weights.code_weights),
            score_thresh=post.score_thresh,
            post_center_limit_range=as_lists(post.post_center_limit_range),
            max_obj_per_sample=post.max_obj_per_sample,
            nms_thresh=as_lists(nms.nms_thresh),
            nms_pre_maxsize=as_lists(nms.nms_pre_maxsize),
            nms_post_maxsize=as_lists(nms.nms_post_maxsize),
            nms_type=nms.nms_type,
            with_iou="iou" in head_dict,
            iou_reg_loss=settings.iou_reg_loss,
            iou_rectifier=as_lists(post.iou_rectifier) if post.use_iou_to_rectify_score else None,
            bn_eps=settings.bn_eps,
            bn_momentum=settings.bn_momentum,
        )

    def openpcdet_names(self) -> dict[str, str | None]:
        """This head's ``state_dict`` keys -> the names OpenPCDet's CenterHead gives the same
        tensors (``None``: a buffer OpenPCDet does not save; it comes from the config).

        OpenPCDet nests each branch: ``heads_list.0.<head>.<k>.0`` / ``.<k>.1`` are the conv and
        BatchNorm of the k-th conv-BN-ReLU block and ``heads_list.0.<head>.<num_conv - 1>`` the
        output conv; here a branch is one flat ``nn.Sequential`` (``head.branches.<head>.<i>``).
        """
        names: dict[str, str | None] = {}
        for key in self.state_dict():
            parts = key.split(".")
            if parts[0] == "head":  # head.branches.<name>.<i>.<tensor>
                name, i, tensor = parts[2], int(parts[3]), ".".join(parts[4:])
                if i == len(self.head.branches[name]) - 1:  # the output conv
                    names[key] = f"heads_list.0.{name}.{i // 3}.{tensor}"
                else:
                    names[key] = f"heads_list.0.{name}.{i // 3}.{i % 3}.{tensor}"
            elif key == "code_weights":
                names[key] = None
            else:  # shared_conv: the same names
                names[key] = key
        return names

    def forward(self, batch_dict: dict) -> dict:
        x = self.shared_conv(batch_dict["spatial_features_2d"])  # (B, C_shared, H, W)
        if tuple(x.shape[-2:]) != self.feature_map_size:
            raise ValueError(
                f"CenterHead: feature map is {tuple(x.shape[-2:])}, expected "
                f"{self.feature_map_size} (grid / FEATURE_MAP_STRIDE)"
            )
        batch_dict["head_outputs"] = self.head(x)
        return batch_dict

    def assign_targets(self, gt_boxes: torch.Tensor) -> cu.CenterTargets:
        """(B, M, 8|10) padded GT boxes -> heatmap and regression targets on this head's grid."""
        return cu.encode_center_targets(
            gt_boxes,
            num_class=self.num_class,
            feature_map_size=self.feature_map_size,
            point_cloud_range=self.point_cloud_range,
            voxel_size=self.voxel_size,
            feature_map_stride=self.feature_map_stride,
            with_velocity=self.with_velocity,
            num_max_objs=self.num_max_objs,
            gaussian_overlap=self.gaussian_overlap,
            min_radius=self.min_radius,
        )

    def loss(self, head_outputs: Mapping[str, torch.Tensor], gt_boxes: torch.Tensor) -> dict:
        """Focal heatmap loss + weighted L1 box loss.

        Returns:
            ``{'loss', 'hm_loss', 'loc_loss'}`` scalars (``loss`` is the weighted total).
        """
        if gt_boxes.shape[-1] == 10 and not self.with_velocity:
            gt_boxes = torch.cat([gt_boxes[..., :7], gt_boxes[..., -1:]], dim=-1)
        targets = self.assign_targets(gt_boxes)
        hm_loss = cu.focal_loss_centernet(head_outputs["hm"], targets.heatmap)
        reg_maps = [head_outputs[n] for n in ("center", "center_z", "dim", "rot")]
        if self.with_velocity:
            reg_maps.append(head_outputs["vel"])
        pred = cu.gather_feature_at(torch.cat(reg_maps, dim=1).float(), targets.inds)
        reg_loss = cu.reg_l1_loss_centernet(pred, targets.box_targets, targets.mask)  # (code,)
        loc_loss = (reg_loss * self.code_weights).sum() * self.loc_weight
        hm_loss = hm_loss * self.cls_weight
        losses = {"loss": hm_loss + loc_loss, "hm_loss": hm_loss, "loc_loss": loc_loss}
        if self.with_iou or self.iou_reg_loss:
            losses.update(self._iou_losses(head_outputs, targets))
            losses["loss"] = sum(v for k, v in losses.items() if k != "loss")
        return losses

    def _iou_losses(
        self, head_outputs: Mapping[str, torch.Tensor], targets: cu.CenterTargets
    ) -> dict[str, torch.Tensor]:
        """``iou_loss``: L1 of the ``iou`` map at the GT cells to ``2 * IoU3D - 1`` of the
        (detached) decoded box with its GT box; ``iou_reg_loss``: ``loc_weight`` x mean
        ``1 - DIoU`` of the decoded boxes. Both are means over the objects (0 without any)."""
        boxes = cu.boxes_at_cells(
            head_outputs["center"],
            head_outputs["center_z"],
            head_outputs["dim"],
            head_outputs["rot"],
            targets.inds,
            point_cloud_range=self.point_cloud_range,
            voxel_size=self.voxel_size,
            feature_map_stride=self.feature_map_stride,
        )[targets.mask]  # (n, 7)
        gt = targets.src_boxes[targets.mask]  # (n, 7)
        num = targets.mask.sum().clamp(min=1).float()
        out = {}
        if self.with_iou:
            pred_iou = cu.gather_feature_at(head_outputs["iou"].float(), targets.inds)
            iou_target = boxes_aligned_iou3d(boxes.detach(), gt) * 2 - 1
            diff = (pred_iou[targets.mask][:, 0] - iou_target).abs()
            out["iou_loss"] = diff.sum() / num
        if self.iou_reg_loss:
            diou = cu.diou3d_axis_aligned(boxes, gt)
            out["iou_reg_loss"] = (1.0 - diou).sum() / num * self.loc_weight
        return out

    @torch.no_grad()
    def predict(self, head_outputs: Mapping[str, torch.Tensor]) -> list[dict]:
        """Decode, filter and NMS the maps.

        Returns:
            per sample ``{'pred_boxes': (K, 7|9), 'pred_scores': (K,), 'pred_labels': (K,)
            int64 1-based}``, sorted by decreasing score.
        """
        decoded = cu.decode_center_maps(
            head_outputs["hm"],
            head_outputs["center"],
            head_outputs["center_z"],
            head_outputs["dim"],
            head_outputs["rot"],
            head_outputs.get("vel"),
            point_cloud_range=self.point_cloud_range,
            voxel_size=self.voxel_size,
            feature_map_stride=self.feature_map_stride,
            max_obj_per_sample=self.max_obj_per_sample,
            score_thresh=self.score_thresh,
            post_center_limit_range=self.post_center_limit_range,
            iou=head_outputs["iou"] if self.iou_rectifier is not None else None,
        )
        out = []
        for d in decoded:
            if self.iou_rectifier is not None:
                r = d["scores"].new_tensor(self.iou_rectifier)[d["labels"]]
                d["scores"] = d["scores"].pow(1 - r) * d["iou"].pow(r)
            keep = self._nms(d["boxes"][:, :7], d["scores"], d["labels"])
            out.append(
                {
                    "pred_boxes": d["boxes"][keep],
                    "pred_scores": d["scores"][keep],
                    "pred_labels": d["labels"][keep] + 1,
                }
            )
        return out

    def _nms(self, boxes: torch.Tensor, scores: torch.Tensor, labels: torch.Tensor):
        """Indices kept by NMS over all boxes, or class by class with that class's threshold
        and sizes (``class_specific_nms``), by decreasing score."""
        if self.nms_type == "class_specific_nms":
            return nms_bev_per_class(
                boxes, scores, labels, self.nms_thresh, self.nms_pre_maxsize,
                self.nms_post_maxsize,
            )  # fmt: skip
        return nms_bev(boxes, scores, self.nms_thresh, self.nms_pre_maxsize, self.nms_post_maxsize)
