"""CenterFormerHead: CenterFormer's centre heatmap, centre queries, transformer and per-query
box heads with an IoU branch (``RPN_transformer`` + ``CenterHeadIoU_1d`` of the released code).

On the query map (``spatial_features_2d``) a conv heatmap head scores every cell; the top-K cells
(class maximum) become queries (with the ground-truth centre cells put first in training), whose
features pass :class:`~pcdet_atlas.models.model_utils.center_transformer.CenterTransformer`
(self-attention, then cross-attention to a window around the query on each pyramid level); a
shared 1x1 conv and one small 1x1 conv branch per output then regress ``center`` 2, ``center_z``
1, ``dim`` 3, ``rot`` 2 (cos, sin) and ``iou`` 1 per query. Training adds a corner heatmap (the
centre and the four edge midpoints of each box) as an auxiliary target. Decoding keeps queries
above the score threshold, rectifies scores by the predicted IoU (``score * iou ** f[class]``)
and runs class-specific rotated BEV NMS.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import as_lists, section, setting
from pcdet_atlas.models.dense_heads.center_config import (
    CenterTargetConfig,
    LossWeightsConfig,
    SeparateHeadConfig,
    branch_num_convs,
    check_one_head,
)
from pcdet_atlas.models.model_utils import centernet_utils as cu
from pcdet_atlas.models.model_utils.center_transformer import (
    CenterTransformer,
    gather_neighbours,
    select_center_queries,
)
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d, nms_bev_per_class
from pcdet_atlas.registry import MODEL_STAGES

#: per-query outputs and their widths (the box code is the first four, CenterPoint's order)
QUERY_HEADS = {"center": 2, "center_z": 1, "dim": 3, "rot": 2, "iou": 1}
BOX_CODE = ("center", "center_z", "dim", "rot")


def _conv_bn_relu(cin: int, cout: int) -> list[nn.Module]:
    bn = nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01)
    return [nn.Conv2d(cin, cout, 3, padding=1, bias=True), bn, nn.ReLU()]


class QueryHeads(nn.Module):
    """One 1x1 conv branch per output over the queries: ``num_conv - 1`` x (conv-BN-ReLU),
    then a conv (CenterFormer's ``SepHead`` with ``final_kernel`` 1)."""

    def __init__(self, in_channels: int, head_conv: int, num_conv: Mapping[str, int]):
        super().__init__()
        self.branches = nn.ModuleDict()
        for name, out_ch in QUERY_HEADS.items():
            layers: list[nn.Module] = []
            cin = in_channels
            for _ in range(int(num_conv.get(name, 2)) - 1):
                layers += [nn.Conv1d(cin, head_conv, 1), nn.BatchNorm1d(head_conv), nn.ReLU()]
                cin = head_conv
            layers.append(nn.Conv1d(cin, out_ch, 1))
            branch = nn.Sequential(*layers)
            for m in branch.modules():
                if isinstance(m, nn.Conv1d):
                    nn.init.kaiming_normal_(m.weight)
                    nn.init.zeros_(m.bias)
            self.branches[name] = branch

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """x: (B, C, K) -> ``name -> (B, out, K)``."""
        return {name: branch(x) for name, branch in self.branches.items()}


SECTION = "MODEL.DENSE_HEAD"
#: per-class NMS threshold, pre- and post-NMS sizes of Vehicle, Pedestrian, Cyclist
_NMS_DEFAULTS = ((0.8, 0.55, 0.55), (1600, 1600, 800), (200, 200, 100))


@dataclass(frozen=True, kw_only=True)
class TransformerConfig:
    """``MODEL.DENSE_HEAD.TRANSFORMER``: the queries' cross-attention."""

    depth: int = setting(3, ge=1, doc="attention blocks")
    heads: int = setting(4, ge=1, doc="attention heads")
    dim_head: int = setting(64, ge=1, doc="width per head")
    mlp_dim: int = setting(256, ge=1, doc="feed-forward width")
    dropout: float = setting(0.3, ge=0, lt=1, doc="dropout")
    kernel_sizes: tuple[int, ...] = setting((3, 3, 3), ge=1, doc="window per pyramid level")


@dataclass(frozen=True, kw_only=True)
class QuerySeparateHeadConfig(SeparateHeadConfig):
    head_order: tuple[str, ...] = setting(
        tuple(QUERY_HEADS),
        check=lambda order: order == tuple(QUERY_HEADS),
        expected=f"[{', '.join(QUERY_HEADS)}]",
        doc="the query branches, in order",
    )


@dataclass(frozen=True, kw_only=True)
class QueryTargetConfig(CenterTargetConfig):
    feature_map_stride: int = setting(4, ge=1, doc="voxels per query-map cell")


@dataclass(frozen=True, kw_only=True)
class QueryLossWeightsConfig(LossWeightsConfig):
    iou_weight: float = setting(1.0, key="iou_weight", ge=0, doc="IoU branch loss weight")
    corner_weight: float = setting(1.0, key="corner_weight", ge=0, doc="corner heatmap weight")


@dataclass(frozen=True, kw_only=True)
class QueryLossConfig:
    loss_weights: QueryLossWeightsConfig = section(QueryLossWeightsConfig)


@dataclass(frozen=True, kw_only=True)
class QueryNmsConfig:
    """``POST_PROCESSING.NMS_CONFIG``: per-class rotated BEV NMS."""

    nms_type: str = setting(
        "nms_gpu",
        choices=("nms_gpu", "nms_bev"),
        expected="'nms_gpu' or 'nms_bev' (rotated BEV NMS)",
        doc="rotated BEV NMS",
    )
    multi_classes_nms: bool = setting(
        True, check=bool, expected="True (CenterFormer's NMS is per class)", doc="per class"
    )
    nms_thresh: float | tuple[float, ...] | None = setting(
        None, doc="IoU threshold, one or per class (default 0.8, 0.55, 0.55)"
    )
    nms_pre_maxsize: int | tuple[int, ...] | None = setting(
        None, doc="boxes before NMS, one or per class (default 1600, 1600, 800)"
    )
    nms_post_maxsize: int | tuple[int, ...] | None = setting(
        None, doc="boxes after NMS, one or per class (default 200, 200, 100)"
    )


@dataclass(frozen=True, kw_only=True)
class QueryPostConfig:
    score_thresh: float = setting(0.1, doc="boxes scoring below are dropped")
    post_center_limit_range: tuple[float, float, float, float, float, float] | None = setting(
        None, doc="box centres outside are dropped, m"
    )
    iou_rectifier: tuple[float, ...] | None = setting(None, doc="r per class")
    nms_config: QueryNmsConfig = section(QueryNmsConfig)


@dataclass(frozen=True, kw_only=True)
class CenterFormerHeadConfig(StageConfig):
    """``MODEL.DENSE_HEAD`` of CenterFormerHead."""

    class_names_each_head: tuple[tuple[str, ...], ...] | None = setting(
        None, doc="one head over all CLASS_NAMES"
    )
    hm_head_channel: int = setting(64, ge=1, doc="width of the heatmap head")
    corner_head: bool = setting(True, doc="corner heatmap auxiliary head")
    num_queries: int = setting(500, ge=1, doc="top-K heatmap cells taken as queries")
    use_gt_queries: bool = setting(True, doc="training queries include the GT centres")
    transformer: TransformerConfig = section(TransformerConfig)
    shared_conv_channel: int = setting(64, ge=1, doc="width of the shared conv")
    head_conv: int = setting(64, ge=1, doc="width of the query branches")
    separate_head_cfg: QuerySeparateHeadConfig = section(QuerySeparateHeadConfig)
    target_assigner_config: QueryTargetConfig = section(QueryTargetConfig)
    loss_config: QueryLossConfig = section(QueryLossConfig)
    post_processing: QueryPostConfig = section(QueryPostConfig)


@MODEL_STAGES.register()
class CenterFormerHead(nn.Module):
    """Reads ``spatial_features_2d`` (B, C, H, W), the query map, and ``multi_scale_features_2d``
    (finest first, each C wide); writes ``head_outputs``: ``hm`` (B, num_class, H, W) logits,
    ``order`` (B, K) the queries' flat cells, ``scores`` / ``labels`` (B, K) their heatmap score
    and 0-based class, and per query ``center`` (B, 2, K), ``center_z`` (B, 1, K), ``dim``
    (B, 3, K) log-sizes, ``rot`` (B, 2, K) ``[cos, sin]``, ``iou`` (B, 1, K) in [-1, 1]."""

    CONFIG = CenterFormerHeadConfig

    def __init__(
        self,
        *,
        input_channels: int,
        num_class: int,
        point_cloud_range: Sequence[float],
        voxel_size: Sequence[float],
        grid_size: Sequence[int],
        feature_map_stride: int = QueryTargetConfig.feature_map_stride,
        hm_head_channel: int = CenterFormerHeadConfig.hm_head_channel,
        corner_head: bool = CenterFormerHeadConfig.corner_head,
        num_queries: int = CenterFormerHeadConfig.num_queries,
        use_gt_queries: bool = CenterFormerHeadConfig.use_gt_queries,
        kernel_sizes: Sequence[int] = TransformerConfig.kernel_sizes,
        depth: int = TransformerConfig.depth,
        heads: int = TransformerConfig.heads,
        dim_head: int = TransformerConfig.dim_head,
        mlp_dim: int = TransformerConfig.mlp_dim,
        dropout: float = TransformerConfig.dropout,
        shared_conv_channel: int = CenterFormerHeadConfig.shared_conv_channel,
        head_conv: int = CenterFormerHeadConfig.head_conv,
        reg_num_conv: Mapping[str, int] | None = None,
        init_bias: float = -2.19,
        num_max_objs: int = 500,
        gaussian_overlap: float = 0.1,
        min_radius: int = 2,
        cls_weight: float = 1.0,
        loc_weight: float = 2.0,
        iou_weight: float = QueryLossWeightsConfig.iou_weight,
        corner_weight: float = QueryLossWeightsConfig.corner_weight,
        code_weights: Sequence[float] | None = None,
        score_thresh: float = 0.1,
        post_center_limit_range: Sequence[float] | None = None,
        iou_rectifier: Sequence[float] | None = None,
        nms_thresh: Sequence[float] = _NMS_DEFAULTS[0],
        nms_pre_maxsize: Sequence[int] = _NMS_DEFAULTS[1],
        nms_post_maxsize: Sequence[int] = _NMS_DEFAULTS[2],
    ):
        """
        Args:
            input_channels: C, width of the query map and of every pyramid level.
            num_class: heatmap channels (classes are 1-based in ``gt_boxes`` and predictions).
            point_cloud_range, voxel_size, grid_size: the VFE's grid (metres / cells).
            feature_map_stride: voxels per query-map cell along x and y.
            hm_head_channel: hidden width of the heatmap and corner heads.
            corner_head: train the auxiliary corner heatmap.
            num_queries: K (capped at the query map's cells).
            use_gt_queries: put the ground-truth centre cells first among the queries in training.
            kernel_sizes: cross-attention window per pyramid level (odd).
            depth, heads, dim_head, mlp_dim, dropout: the transformer.
            reg_num_conv: convs per query branch (default 2 each).
            code_weights: L1 weight per box code channel (8).
            iou_rectifier: per class exponent of the predicted IoU in the score (default 1s).
            nms_thresh / nms_pre_maxsize / nms_post_maxsize: per class rotated BEV NMS.
        """
        super().__init__()
        self.num_class = int(num_class)
        self.point_cloud_range = tuple(float(v) for v in point_cloud_range)
        self.voxel_size = tuple(float(v) for v in voxel_size)
        self.feature_map_stride = int(feature_map_stride)
        self.feature_map_size = cu.head_map_size(grid_size, feature_map_stride, "CenterFormerHead")
        self.num_queries = int(num_queries)
        if self.num_queries < 1:
            raise ValueError(f"CenterFormerHead: NUM_QUERIES must be >= 1, got {num_queries}")
        self.use_gt_queries = bool(use_gt_queries)
        self.kernel_sizes = tuple(int(k) for k in kernel_sizes)
        if any(k < 1 or k % 2 == 0 for k in self.kernel_sizes):
            raise ValueError(
                f"CenterFormerHead: KERNEL_SIZES must be odd, got {list(kernel_sizes)}"
            )
        if code_weights is None:
            code_weights = [1.0] * 8
        if len(code_weights) != 8:
            raise ValueError(
                f"CenterFormerHead: code_weights needs 8 values (center 2, center_z 1, dim 3, "
                f"rot 2), got {len(code_weights)}"
            )
        self.register_buffer("code_weights", torch.tensor(code_weights, dtype=torch.float32))
        rectifier = [1.0] * self.num_class if iou_rectifier is None else list(iou_rectifier)
        self.iou_rectifier = tuple(float(v) for v in rectifier)
        self.nms_thresh = tuple(float(v) for v in nms_thresh)
        self.nms_pre_maxsize = tuple(int(v) for v in nms_pre_maxsize)
        self.nms_post_maxsize = tuple(int(v) for v in nms_post_maxsize)
        for name, values in (("IOU_RECTIFIER", self.iou_rectifier), ("NMS_THRESH", self.nms_thresh),
                             ("NMS_PRE_MAXSIZE", self.nms_pre_maxsize),
                             ("NMS_POST_MAXSIZE", self.nms_post_maxsize)):  # fmt: skip
            if len(values) != self.num_class:
                raise ValueError(
                    f"CenterFormerHead: {name} needs one value per class ({self.num_class}), "
                    f"got {list(values)}"
                )
        self.num_max_objs = int(num_max_objs)
        self.gaussian_overlap = float(gaussian_overlap)
        self.min_radius = int(min_radius)
        self.cls_weight, self.loc_weight = float(cls_weight), float(loc_weight)
        self.iou_weight, self.corner_weight = float(iou_weight), float(corner_weight)
        self.score_thresh = float(score_thresh)
        self.post_center_limit_range = (
            None if post_center_limit_range is None else tuple(map(float, post_center_limit_range))
        )

        self.hm_head = nn.Sequential(
            *_conv_bn_relu(input_channels, hm_head_channel),
            nn.Conv2d(hm_head_channel, self.num_class, 3, padding=1, bias=True),
        )
        nn.init.constant_(self.hm_head[-1].bias, init_bias)
        self.corner_head = None
        if corner_head:
            self.corner_head = nn.Sequential(
                *_conv_bn_relu(input_channels, hm_head_channel),
                nn.Conv2d(hm_head_channel, 1, 3, padding=1, bias=True),
            )
            nn.init.constant_(self.corner_head[-1].bias, init_bias)
        self.transformer = CenterTransformer(
            input_channels, depth, heads, dim_head, mlp_dim, float(dropout)
        )
        self.shared_conv = nn.Sequential(
            nn.Conv1d(input_channels, shared_conv_channel, 1, bias=True),
            nn.BatchNorm1d(shared_conv_channel),
            nn.ReLU(),
        )
        num_conv = dict(reg_num_conv or {})
        unknown = set(num_conv) - set(QUERY_HEADS)
        if unknown:
            raise ValueError(
                f"CenterFormerHead: num_conv given for unknown heads {sorted(unknown)}"
            )
        self.heads = QueryHeads(shared_conv_channel, head_conv, num_conv)

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> CenterFormerHead:
        settings = read_stage(cls, cfg, SECTION)
        class_names = list(model_info["class_names"])
        check_one_head(settings.class_names_each_head, class_names)
        separate = settings.separate_head_cfg
        order = list(separate.head_order)
        if set(separate.head_dict) - set(order):
            raise ConfigError(
                f"{SECTION}.SEPARATE_HEAD_CFG.HEAD_DICT has heads not in HEAD_ORDER: "
                f"{sorted(set(separate.head_dict) - set(order))}"
            )
        reg_num_conv = branch_num_convs(
            separate, order, QUERY_HEADS, f"{SECTION}.SEPARATE_HEAD_CFG"
        )
        tac = settings.target_assigner_config
        stride = tac.feature_map_stride
        before = model_info.get("backbone_stride")
        if before is not None and stride != before:
            raise ConfigError(
                f"{SECTION}.TARGET_ASSIGNER_CONFIG.FEATURE_MAP_STRIDE ({stride}) differs "
                f"from the query map's stride ({before:g} voxels per cell: the 3D backbone's "
                f"stride over the BEV backbone's UPSAMPLE_STRIDE)"
            )
        weights = settings.loss_config.loss_weights
        post = settings.post_processing
        nms = post.nms_config
        n = len(class_names)

        def per_class(value, default: Sequence) -> list:
            value = default[:n] if value is None else value
            return list(value) if isinstance(value, Sequence) else [value] * n

        tr = settings.transformer
        return cls(
            input_channels=model_info["num_bev_features"],
            num_class=n,
            point_cloud_range=model_info["point_cloud_range"],
            voxel_size=model_info["voxel_size"],
            grid_size=model_info["grid_size"],
            feature_map_stride=stride,
            hm_head_channel=settings.hm_head_channel,
            corner_head=settings.corner_head,
            num_queries=settings.num_queries,
            use_gt_queries=settings.use_gt_queries,
            kernel_sizes=list(tr.kernel_sizes),
            depth=tr.depth,
            heads=tr.heads,
            dim_head=tr.dim_head,
            mlp_dim=tr.mlp_dim,
            dropout=tr.dropout,
            shared_conv_channel=settings.shared_conv_channel,
            head_conv=settings.head_conv,
            reg_num_conv=reg_num_conv,
            num_max_objs=tac.num_max_objs,
            gaussian_overlap=tac.gaussian_overlap,
            min_radius=tac.min_radius,
            cls_weight=weights.cls_weight,
            loc_weight=weights.loc_weight,
            iou_weight=weights.iou_weight,
            corner_weight=weights.corner_weight,
            code_weights=as_lists(weights.code_weights),
            score_thresh=post.score_thresh,
            post_center_limit_range=as_lists(post.post_center_limit_range),
            iou_rectifier=as_lists(post.iou_rectifier),
            nms_thresh=per_class(nms.nms_thresh, _NMS_DEFAULTS[0]),
            nms_pre_maxsize=per_class(nms.nms_pre_maxsize, _NMS_DEFAULTS[1]),
            nms_post_maxsize=per_class(nms.nms_post_maxsize, _NMS_DEFAULTS[2]),
        )

    # ------------------------------------------------------------------------ running
    def forward(self, batch_dict: dict) -> dict:
        """Inference: the top-K heatmap cells are the queries."""
        batch_dict["head_outputs"] = self.run_queries(batch_dict)
        return batch_dict

    def run_queries(
        self,
        batch_dict: Mapping,
        gt_inds: torch.Tensor | None = None,
        gt_mask: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """The heatmap, the queries (``gt_inds`` / ``gt_mask`` (B, M): cells put first) and their
        outputs (see the class docstring)."""
        x_up = batch_dict["spatial_features_2d"]  # (B, C, H, W)
        if tuple(x_up.shape[-2:]) != self.feature_map_size:
            raise ValueError(
                f"CenterFormerHead: query map is {tuple(x_up.shape[-2:])}, expected "
                f"{self.feature_map_size} (grid / FEATURE_MAP_STRIDE)"
            )
        B, C, H, W = x_up.shape
        hm = self.hm_head(x_up)  # (B, num_class, H, W) logits
        probs = torch.sigmoid(hm.detach().float()).reshape(B, self.num_class, H * W)
        cell_scores, cell_labels = probs.max(dim=1)  # (B, HW)
        order = select_center_queries(cell_scores, min(self.num_queries, H * W), gt_inds, gt_mask)
        cells_xy = torch.stack([order % W, torch.div(order, W, rounding_mode="floor")], dim=-1)
        query = torch.gather(x_up.reshape(B, C, H * W), 2, order[:, None].expand(B, C, -1))
        keys, key_cells = gather_neighbours(
            cells_xy, batch_dict["multi_scale_features_2d"], self.kernel_sizes
        )  # (B, K, N, C), (B, K, N, 2)
        feat = self.transformer(query.transpose(1, 2), cells_xy, keys, key_cells)  # (B, K, C)
        out = self.heads(self.shared_conv(feat.transpose(1, 2)))  # name -> (B, out, K)
        out.update(
            hm=hm,
            order=order,
            scores=torch.gather(cell_scores, 1, order),
            labels=torch.gather(cell_labels, 1, order),
        )
        return out

    def decode_boxes(self, codes: torch.Tensor, order: torch.Tensor, width: int) -> torch.Tensor:
        """(B, K, 8) box codes ``[dx_off, dy_off, z, log dx, log dy, log dz, cos, sin]`` at the
        flat query-map cells ``order`` (B, K) -> (B, K, 7) boxes in metres."""
        xs = (order % width).to(codes.dtype)
        ys = torch.div(order, width, rounding_mode="floor").to(codes.dtype)
        cell_x = self.feature_map_stride * self.voxel_size[0]
        cell_y = self.feature_map_stride * self.voxel_size[1]
        x = (xs + codes[..., 0]) * cell_x + self.point_cloud_range[0]
        y = (ys + codes[..., 1]) * cell_y + self.point_cloud_range[1]
        # log-size clamped so an untrained head cannot produce inf boxes (e^6 = 403 m)
        size = torch.exp(codes[..., 3:6].clamp(max=6.0))
        heading = torch.atan2(codes[..., 7], codes[..., 6])
        return torch.cat(
            [x[..., None], y[..., None], codes[..., 2:3], size, heading[..., None]], -1
        )

    # --------------------------------------------------------------------------- loss
    def loss(self, batch_dict: Mapping, gt_boxes: torch.Tensor) -> dict[str, torch.Tensor]:
        """Heatmap focal loss, L1 box loss on the queries at a ground-truth centre cell, IoU
        loss (smooth L1 to ``2 IoU - 1`` of the decoded box) and the corner heatmap's MSE.

        Returns:
            ``{'loss', 'hm_loss', 'loc_loss', 'iou_loss'(, 'corner_loss')}`` scalars.
        """
        if gt_boxes.dim() != 3 or gt_boxes.shape[-1] not in (8, 10):
            raise ValueError(f"gt_boxes must be (B, M, 8|10), got {tuple(gt_boxes.shape)}")
        if gt_boxes.shape[-1] == 10:  # no velocity head: drop [vx, vy]
            gt_boxes = torch.cat([gt_boxes[..., :7], gt_boxes[..., -1:]], dim=-1)
        H, W = self.feature_map_size
        targets = cu.encode_center_targets(
            gt_boxes,
            num_class=self.num_class,
            feature_map_size=self.feature_map_size,
            point_cloud_range=self.point_cloud_range,
            voxel_size=self.voxel_size,
            feature_map_stride=self.feature_map_stride,
            with_velocity=False,
            num_max_objs=self.num_max_objs,
            gaussian_overlap=self.gaussian_overlap,
            min_radius=self.min_radius,
        )
        with_gt = self.training and self.use_gt_queries
        out = self.run_queries(
            batch_dict, targets.inds if with_gt else None, targets.mask if with_gt else None
        )
        hm_loss = cu.focal_loss_centernet(out["hm"], targets.heatmap) * self.cls_weight

        # the queries at a ground-truth centre cell regress that object (the first one there)
        hit = (out["order"][:, :, None] == targets.inds[:, None, :]) & targets.mask[:, None, :]
        matched = hit.any(dim=2)  # (B, K)
        slot = hit.float().argmax(dim=2)  # (B, K) first matching object
        box_target = torch.gather(
            targets.box_targets, 1, slot[..., None].expand(-1, -1, 8)
        )  # (B, K, 8)
        codes = torch.cat([out[n] for n in BOX_CODE], dim=1).transpose(1, 2).float()  # (B, K, 8)
        reg = cu.reg_l1_loss_centernet(codes, box_target, matched)  # (8,)
        loc_loss = (reg * self.code_weights).sum() * self.loc_weight

        iou_pred = out["iou"][:, 0].float()[matched]  # (P,)
        with torch.no_grad():
            pred_boxes = self.decode_boxes(codes.detach(), out["order"], W)[matched]
            gt = self.decode_boxes(box_target, out["order"], W)[matched]
            iou_target = 2 * boxes_aligned_iou3d(pred_boxes, gt).to(iou_pred.dtype) - 1
        num = matched.sum()
        iou_loss = F.smooth_l1_loss(iou_pred, iou_target, reduction="sum") / (num + 1e-4)
        losses = {"hm_loss": hm_loss, "loc_loss": loc_loss, "iou_loss": iou_loss * self.iou_weight}
        if self.corner_head is not None:
            corner = torch.sigmoid(self.corner_head(batch_dict["spatial_features_2d"]).float())
            target = self.corner_targets(gt_boxes)  # (B, 1, H, W)
            on = (target > 0).float()
            mse = ((corner - target) ** 2 * on).sum() / (on.sum() + 1e-4)
            losses["corner_loss"] = mse * self.corner_weight
        losses["loss"] = sum(losses.values())
        return losses

    def corner_targets(self, gt_boxes: torch.Tensor) -> torch.Tensor:
        """(B, M, 8) boxes -> (B, 1, H, W) corner heatmap: a Gaussian of half the centre's
        radius at each box's centre and at the midpoints of its four edges (max-merged)."""
        B = gt_boxes.shape[0]
        H, W = self.feature_map_size
        heatmap = gt_boxes.new_zeros(B, 1, H, W, dtype=torch.float32)
        boxes = gt_boxes.float()
        cell_x = self.voxel_size[0] * self.feature_map_stride
        cell_y = self.voxel_size[1] * self.feature_map_stride
        cls = boxes[..., -1].long()
        cx = (boxes[..., 0] - self.point_cloud_range[0]) / cell_x  # (B, M) cells
        cy = (boxes[..., 1] - self.point_cloud_range[1]) / cell_y
        valid = (cls > 0) & (boxes[..., 3] > 0) & (boxes[..., 4] > 0)
        valid &= (cx >= 0) & (cx < W) & (cy >= 0) & (cy < H)
        b_idx, m_idx = torch.nonzero(valid, as_tuple=True)
        if b_idx.numel() == 0:
            return heatmap
        box = boxes[b_idx, m_idx]  # (P, 8)
        radius = cu.gaussian_radius(box[:, 4] / cell_y, box[:, 3] / cell_x, self.gaussian_overlap)
        radius = torch.div(
            radius.floor().clamp(min=self.min_radius).long(), 2, rounding_mode="floor"
        )
        c, s = torch.cos(box[:, 6]), torch.sin(box[:, 6])
        hx, hy = box[:, 3] / 2, box[:, 4] / 2  # half length (heading axis) and width, metres
        # centre, then the midpoints of the front, back, left and right edges, in cells
        dx = torch.stack([0 * hx, hx * c, -hx * c, -hy * s, hy * s], dim=1) / cell_x  # (P, 5)
        dy = torch.stack([0 * hx, hx * s, -hx * s, hy * c, -hy * c], dim=1) / cell_y
        px = (cx[b_idx, m_idx][:, None] + dx).floor().long()  # (P, 5)
        py = (cy[b_idx, m_idx][:, None] + dy).floor().long()
        _splat_gaussians(
            heatmap, b_idx[:, None].expand_as(px).reshape(-1), px.reshape(-1), py.reshape(-1),
            radius[:, None].expand_as(px).reshape(-1),
        )  # fmt: skip
        return heatmap

    # ------------------------------------------------------------------------- decode
    @torch.no_grad()
    def predict(self, head_outputs: Mapping[str, torch.Tensor]) -> list[dict]:
        """Decode the queries, keep those above the score threshold and inside
        ``POST_CENTER_LIMIT_RANGE``, rectify scores by the predicted IoU, NMS per class.

        Returns:
            per sample ``{'pred_boxes': (K, 7), 'pred_scores': (K,), 'pred_labels': (K,) int64
            1-based}``, sorted by decreasing score.
        """
        order = head_outputs["order"]
        W = head_outputs["hm"].shape[-1]
        codes = torch.cat([head_outputs[n] for n in BOX_CODE], dim=1).transpose(1, 2).float()
        boxes = self.decode_boxes(codes, order, W)  # (B, K, 7)
        scores, labels = head_outputs["scores"].float(), head_outputs["labels"]
        keep = scores > self.score_thresh
        if self.post_center_limit_range is not None:
            lim = boxes.new_tensor(self.post_center_limit_range)
            keep &= (boxes[..., :3] >= lim[:3]).all(-1) & (boxes[..., :3] <= lim[3:]).all(-1)
        iou = ((head_outputs["iou"][:, 0].float() + 1) / 2).clamp(0.0, 1.0)  # (B, K)
        power = boxes.new_tensor(self.iou_rectifier)[labels]
        rectified = scores * iou.pow(power)
        out = []
        for b in range(boxes.shape[0]):
            idx = torch.nonzero(keep[b]).squeeze(1)
            idx = idx[
                nms_bev_per_class(
                    boxes[b, idx], rectified[b, idx], labels[b, idx], self.nms_thresh,
                    self.nms_pre_maxsize, self.nms_post_maxsize,
                )
            ]  # fmt: skip
            out.append({
                "pred_boxes": boxes[b, idx],
                "pred_scores": rectified[b, idx],
                "pred_labels": labels[b, idx] + 1,
            })  # fmt: skip
        return out


def _splat_gaussians(
    heatmap: torch.Tensor, b: torch.Tensor, x: torch.Tensor, y: torch.Tensor, radius: torch.Tensor
) -> None:
    """Max-merge a Gaussian (sigma ``(2r + 1) / 6``, cut at ``r`` cells) at each cell ``(x, y)``
    of sample ``b`` into ``heatmap`` (B, 1, H, W), in place (CenterNet's ``draw_gaussian``)."""
    if b.numel() == 0:
        return
    _, _, H, W = heatmap.shape
    r_max = int(radius.max())
    offs = torch.arange(-r_max, r_max + 1, device=heatmap.device)
    oy, ox = torch.meshgrid(offs, offs, indexing="ij")
    oy, ox = oy.reshape(-1), ox.reshape(-1)  # (S,)
    sigma = (2 * radius.float() + 1) / 6
    val = torch.exp(-(ox[None] ** 2 + oy[None] ** 2).float() / (2 * sigma[:, None] ** 2))
    val = torch.where(val < torch.finfo(val.dtype).eps, torch.zeros_like(val), val)
    px, py = x[:, None] + ox[None], y[:, None] + oy[None]  # (P, S)
    inside = (ox.abs()[None] <= radius[:, None]) & (oy.abs()[None] <= radius[:, None])
    inside &= (px >= 0) & (px < W) & (py >= 0) & (py < H)
    flat = (b[:, None].expand_as(px) * H + py) * W + px
    heatmap.view(-1).scatter_reduce_(0, flat[inside], val[inside], reduce="amax")
