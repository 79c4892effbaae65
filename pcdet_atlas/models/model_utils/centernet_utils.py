"""CenterNet/CenterPoint target encoding, losses and decoding, in plain batched torch.

The conventions are OpenPCDet's CenterHead for Waymo: a BEV heatmap per class with a Gaussian of
CornerNet radius at each object's (integer) centre cell, regression targets
``[dx_off, dy_off, z, log(dx), log(dy), log(dz), cos, sin, (vx, vy)]`` at the centre cell, the
CornerNet focal loss and a masked L1 loss, and top-K decoding without peak max-pooling.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = [
    "head_map_size",
    "gaussian_radius",
    "CenterTargets",
    "encode_center_targets",
    "focal_loss_centernet",
    "reg_l1_loss_centernet",
    "gather_feature_at",
    "decode_center_maps",
    "boxes_at_cells",
    "diou3d_axis_aligned",
]


def head_map_size(grid_size, feature_map_stride: int, owner: str) -> tuple[int, int]:
    """``(H, W)`` cells of a head's map over the VFE grid ``grid_size`` (x, y, ...) at
    ``feature_map_stride`` voxels per cell; a ValueError naming ``owner`` when the stride does
    not divide the grid."""
    stride = int(feature_map_stride)
    if grid_size[0] % stride or grid_size[1] % stride:
        raise ValueError(
            f"{owner}: grid {tuple(grid_size[:2])} not divisible by FEATURE_MAP_STRIDE "
            f"{feature_map_stride}"
        )
    return int(grid_size[1]) // stride, int(grid_size[0]) // stride


def gaussian_radius(height: torch.Tensor, width: torch.Tensor, min_overlap: float) -> torch.Tensor:
    """CornerNet's Gaussian radius (in cells) for boxes of ``height x width`` cells.

    The smallest of the three radii for which a corner-shifted box keeps IoU >= ``min_overlap``
    with the original (the formula OpenPCDet and CenterPoint use). Shapes broadcast.
    """
    b1 = height + width
    c1 = width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + torch.sqrt((b1**2 - 4 * c1).clamp(min=0))) / 2
    b2 = 2 * (height + width)
    c2 = (1 - min_overlap) * width * height
    r2 = (b2 + torch.sqrt((b2**2 - 16 * c2).clamp(min=0))) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (height + width)
    c3 = (min_overlap - 1) * width * height
    r3 = (b3 + torch.sqrt((b3**2 - 4 * a3 * c3).clamp(min=0))) / 2
    return torch.minimum(torch.minimum(r1, r2), r3)


@dataclass
class CenterTargets:
    """Training targets for a batch.

    Attributes:
        heatmap: (B, num_class, H, W) float in [0, 1]; exactly 1 at every object's centre cell.
        box_targets: (B, K, code_size) regression targets at the centre cells.
        inds: (B, K) int64 flat cell index ``y * W + x`` of each object.
        mask: (B, K) bool, which of the K slots hold an object.
        src_boxes: (B, K, 7) the GT box ``[x, y, z, dx, dy, dz, heading]`` of each slot (the
            IoU branch's target; zeros in empty slots).
    """

    heatmap: torch.Tensor
    box_targets: torch.Tensor
    inds: torch.Tensor
    mask: torch.Tensor
    src_boxes: torch.Tensor


def encode_center_targets(
    gt_boxes: torch.Tensor,
    *,
    num_class: int,
    feature_map_size: tuple[int, int],
    point_cloud_range: tuple[float, ...],
    voxel_size: tuple[float, ...],
    feature_map_stride: int,
    with_velocity: bool,
    num_max_objs: int = 500,
    gaussian_overlap: float = 0.1,
    min_radius: int = 2,
) -> CenterTargets:
    """Encode padded GT boxes as CenterPoint targets.

    Args:
        gt_boxes: (B, M, 8) ``[x, y, z, dx, dy, dz, heading, cls]`` or (B, M, 10) with
            ``[vx, vy]`` before ``cls``; ``cls`` is 1-based, rows with ``cls == 0`` are padding.
        feature_map_size: ``(H, W)`` of the head's output (y cells, x cells).
        point_cloud_range, voxel_size: the model's voxel grid (metres).
        feature_map_stride: head cells per voxel along x and y.
        with_velocity: append ``[vx, vy]`` to the regression target (needs 10-column boxes).
        num_max_objs: K; objects beyond it (in GT order) are dropped from the targets.

    Boxes whose centre falls outside the feature map, or with non-positive length or width, get no
    target (OpenPCDet's rule).
    """
    if gt_boxes.dim() != 3 or gt_boxes.shape[-1] not in (8, 10):
        raise ValueError(f"gt_boxes must be (B, M, 8|10), got {tuple(gt_boxes.shape)}")
    if with_velocity and gt_boxes.shape[-1] != 10:
        raise ValueError(
            "the head regresses velocity but gt_boxes have no [vx, vy] columns "
            f"(got {gt_boxes.shape[-1]} columns, expected 10: enable TRAIN_WITH_SPEED)"
        )
    device = gt_boxes.device
    B, M, _ = gt_boxes.shape
    H, W = feature_map_size
    code_size = 10 if with_velocity else 8
    heatmap = torch.zeros(B, num_class, H, W, device=device)
    box_targets = torch.zeros(B, num_max_objs, code_size, device=device)
    inds = torch.zeros(B, num_max_objs, dtype=torch.long, device=device)
    mask = torch.zeros(B, num_max_objs, dtype=torch.bool, device=device)
    src_boxes = torch.zeros(B, num_max_objs, 7, device=device)
    if M == 0:
        return CenterTargets(heatmap, box_targets, inds, mask, src_boxes)

    boxes = gt_boxes.float()
    cls = boxes[..., -1].long()  # (B, M) 1-based
    cell_x = voxel_size[0] * feature_map_stride
    cell_y = voxel_size[1] * feature_map_stride
    cx = (boxes[..., 0] - point_cloud_range[0]) / cell_x  # (B, M) continuous cells
    cy = (boxes[..., 1] - point_cloud_range[1]) / cell_y
    cx = cx.clamp(min=0, max=W - 0.5)
    cy = cy.clamp(min=0, max=H - 0.5)
    ix, iy = cx.long(), cy.long()
    in_map = (
        (boxes[..., 0] >= point_cloud_range[0])
        & (boxes[..., 0] < point_cloud_range[0] + W * cell_x)
        & (boxes[..., 1] >= point_cloud_range[1])
        & (boxes[..., 1] < point_cloud_range[1] + H * cell_y)
    )
    valid = (cls > 0) & (cls <= num_class) & (boxes[..., 3] > 0) & (boxes[..., 4] > 0) & in_map
    bad_cls = (cls < 0) | (cls > num_class)
    if bad_cls.any():
        raise ValueError(
            f"gt_boxes class index out of range 0..{num_class}: {cls[bad_cls].unique().tolist()}"
        )

    # heatmap: one Gaussian patch per valid box, merged by element-wise max
    radius = gaussian_radius(boxes[..., 4] / cell_y, boxes[..., 3] / cell_x, gaussian_overlap)
    radius = radius.floor().clamp(min=min_radius).long()  # (B, M)
    b_idx, m_idx = torch.nonzero(valid, as_tuple=True)
    if b_idx.numel() > 0:
        r = radius[b_idx, m_idx]  # (P,)
        r_max = int(r.max())
        offs = torch.arange(-r_max, r_max + 1, device=device)
        oy, ox = torch.meshgrid(offs, offs, indexing="ij")
        oy, ox = oy.reshape(-1), ox.reshape(-1)  # (S,)
        sigma = (2 * r.float() + 1) / 6
        val = torch.exp(-(ox[None] ** 2 + oy[None] ** 2).float() / (2 * sigma[:, None] ** 2))
        val = torch.where(val < torch.finfo(val.dtype).eps, torch.zeros_like(val), val)
        px = ix[b_idx, m_idx][:, None] + ox[None]  # (P, S)
        py = iy[b_idx, m_idx][:, None] + oy[None]
        keep = (ox.abs()[None] <= r[:, None]) & (oy.abs()[None] <= r[:, None])
        keep &= (px >= 0) & (px < W) & (py >= 0) & (py < H)
        c = (cls[b_idx, m_idx] - 1)[:, None].expand_as(px)
        bb = b_idx[:, None].expand_as(px)
        flat = ((bb * num_class + c) * H + py) * W + px
        heatmap.view(-1).scatter_reduce_(0, flat[keep], val[keep], reduce="amax")

    # regression targets in the first K slots of each sample, in GT order
    slot = torch.cumsum(valid.long(), dim=1) - 1  # (B, M)
    use = valid & (slot < num_max_objs)
    b_u, m_u = torch.nonzero(use, as_tuple=True)
    s_u = slot[b_u, m_u]
    sel = boxes[b_u, m_u]
    target = [
        (cx - ix)[b_u, m_u, None],
        (cy - iy)[b_u, m_u, None],
        sel[:, 2:3],
        torch.log(sel[:, 3:6]),
        torch.cos(sel[:, 6:7]),
        torch.sin(sel[:, 6:7]),
    ]
    if with_velocity:
        target.append(sel[:, 7:9])
    box_targets[b_u, s_u] = torch.cat(target, dim=1)
    inds[b_u, s_u] = iy[b_u, m_u] * W + ix[b_u, m_u]
    mask[b_u, s_u] = True
    src_boxes[b_u, s_u] = sel[:, :7]
    return CenterTargets(heatmap, box_targets, inds, mask, src_boxes)


def boxes_at_cells(
    center: torch.Tensor,
    center_z: torch.Tensor,
    dim: torch.Tensor,
    rot: torch.Tensor,
    inds: torch.Tensor,
    *,
    point_cloud_range: tuple[float, ...],
    voxel_size: tuple[float, ...],
    feature_map_stride: int,
) -> torch.Tensor:
    """The boxes the regression maps predict at cells ``inds`` (B, K): (B, K, 7)
    ``[x, y, z, dx, dy, dz, heading]``, differentiable in the maps (OpenPCDet's
    ``decode_bbox_from_pred_dicts`` read at those cells)."""
    W = center.shape[-1]
    xs = (inds % W).float()
    ys = torch.div(inds, W, rounding_mode="floor").float()
    off = gather_feature_at(center.float(), inds)  # (B, K, 2)
    x = (xs + off[..., 0]) * feature_map_stride * voxel_size[0] + point_cloud_range[0]
    y = (ys + off[..., 1]) * feature_map_stride * voxel_size[1] + point_cloud_range[1]
    z = gather_feature_at(center_z.float(), inds)[..., 0]
    # log-size clamped as in decoding, so an untrained head cannot make inf volumes
    size = torch.exp(gather_feature_at(dim.float(), inds).clamp(max=6.0))  # (B, K, 3)
    cs = gather_feature_at(rot.float(), inds)
    heading = torch.atan2(cs[..., 1], cs[..., 0])
    return torch.cat([torch.stack([x, y, z], -1), size, heading[..., None]], dim=-1)


def diou3d_axis_aligned(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Distance-IoU of row-aligned boxes (N, 7+) x (N, 7+) -> (N,) in [-1, 1], with the boxes
    taken axis-aligned (heading ignored), as OpenPCDet's ``bbox3d_overlaps_diou`` that DSVT's
    IoU regression loss uses: 3D IoU minus the squared centre distance over the squared
    diagonal of the enclosing box. Differentiable."""
    p_lo, p_hi = pred[:, :3] - pred[:, 3:6] / 2, pred[:, :3] + pred[:, 3:6] / 2
    g_lo, g_hi = gt[:, :3] - gt[:, 3:6] / 2, gt[:, :3] + gt[:, 3:6] / 2
    inter = (torch.minimum(p_hi, g_hi) - torch.maximum(p_lo, g_lo)).clamp(min=0).prod(-1)
    union = pred[:, 3:6].prod(-1) + gt[:, 3:6].prod(-1) - inter
    centre = (gt[:, :3] - pred[:, :3]).pow(2).sum(-1)
    diag = (torch.maximum(p_hi, g_hi) - torch.minimum(p_lo, g_lo)).clamp(min=0).pow(2).sum(-1)
    return (inter / union - centre / diag).clamp(min=-1.0, max=1.0)


def focal_loss_centernet(pred_logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CornerNet's penalty-reduced focal loss (alpha 2, beta 4), normalised by the positives.

    Args:
        pred_logits: (B, C, H, W) heatmap logits.
        target: (B, C, H, W) Gaussian heatmap; cells equal to 1 are the positives.
    Returns:
        scalar loss.
    """
    return focal_loss_centernet_prob(torch.sigmoid(pred_logits.float()), target)


def focal_loss_centernet_prob(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """:func:`focal_loss_centernet` on probabilities ``pred`` (any shape, values in [0, 1],
    clamped to [1e-4, 1 - 1e-4] as OpenPCDet's ``_sigmoid``) instead of logits."""
    pred = pred.float().clamp(min=1e-4, max=1 - 1e-4)
    pos = target.eq(1).float()
    neg_weight = torch.pow(1 - target, 4)
    pos_loss = (torch.log(pred) * torch.pow(1 - pred, 2) * pos).sum()
    neg_loss = (torch.log(1 - pred) * torch.pow(pred, 2) * neg_weight * (1 - pos)).sum()
    num_pos = pos.sum().clamp(min=1)
    return -(pos_loss + neg_loss) / num_pos


def gather_feature_at(feature_map: torch.Tensor, inds: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) map, (B, K) flat cell indices -> (B, K, C) features at those cells."""
    B, C = feature_map.shape[:2]
    flat = feature_map.reshape(B, C, -1)
    return torch.gather(flat, 2, inds[:, None, :].expand(B, C, inds.shape[1])).transpose(1, 2)


def reg_l1_loss_centernet(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """Masked L1 per code channel, summed over objects and divided by their number.

    Args:
        pred, target: (B, K, code_size). mask: (B, K) bool.
    Returns:
        (code_size,) loss per regression channel.
    """
    m = mask.float()[..., None]
    num = m.sum()
    target = torch.where(torch.isnan(target), pred.detach(), target)
    loss = F.l1_loss(pred * m, target * m, reduction="none")
    return loss.sum(dim=(0, 1)) / (num + 1e-4)


def decode_center_maps(
    heatmap_logits: torch.Tensor,
    center: torch.Tensor,
    center_z: torch.Tensor,
    dim: torch.Tensor,
    rot: torch.Tensor,
    vel: torch.Tensor | None,
    *,
    point_cloud_range: tuple[float, ...],
    voxel_size: tuple[float, ...],
    feature_map_stride: int,
    max_obj_per_sample: int = 500,
    score_thresh: float = 0.1,
    post_center_limit_range: tuple[float, ...] | None = None,
    iou: torch.Tensor | None = None,
) -> list[dict[str, torch.Tensor]]:
    """Top-K decoding of the head maps into boxes (before NMS).

    Args:
        heatmap_logits: (B, C, H, W). center: (B, 2, H, W) sub-cell offsets. center_z: (B, 1, H, W)
            metres. dim: (B, 3, H, W) log-sizes. rot: (B, 2, H, W) ``[cos, sin]``. vel: (B, 2, H, W)
            m/s or None.
        max_obj_per_sample: K of the top-K over all classes and cells.
        post_center_limit_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` box centres must
            lie in (inclusive), or None.
        iou: (B, 1, H, W) the IoU branch's map in [-1, 1], or None.
    Returns:
        per sample ``{'boxes': (k, 7|9), 'scores': (k,), 'labels': (k,) 0-based}`` (and
        ``'iou'`` (k,) in [0, 1] with ``iou``) with score > ``score_thresh``, sorted by
        decreasing score.
    """
    B, C, H, W = heatmap_logits.shape
    scores_map = torch.sigmoid(heatmap_logits.float()).reshape(B, -1)
    k = min(max_obj_per_sample, scores_map.shape[1])
    scores, flat = torch.topk(scores_map, k, dim=1)  # (B, k)
    labels = torch.div(flat, H * W, rounding_mode="floor")
    cell = flat % (H * W)
    ys = torch.div(cell, W, rounding_mode="floor").float()
    xs = (cell % W).float()

    off = gather_feature_at(center.float(), cell)  # (B, k, 2)
    z = gather_feature_at(center_z.float(), cell)  # (B, k, 1)
    # log-size clamped so an untrained head cannot produce inf boxes (e^6 = 403 m)
    size = torch.exp(gather_feature_at(dim.float(), cell).clamp(max=6.0))  # (B, k, 3)
    cs = gather_feature_at(rot.float(), cell)
    heading = torch.atan2(cs[..., 1:2], cs[..., 0:1])
    x = (xs[..., None] + off[..., 0:1]) * feature_map_stride * voxel_size[0] + point_cloud_range[0]
    y = (ys[..., None] + off[..., 1:2]) * feature_map_stride * voxel_size[1] + point_cloud_range[1]
    parts = [x, y, z, size, heading]
    if vel is not None:
        parts.append(gather_feature_at(vel.float(), cell))
    boxes = torch.cat(parts, dim=-1)  # (B, k, 7|9)

    keep = scores > score_thresh
    if post_center_limit_range is not None:
        lim = boxes.new_tensor(post_center_limit_range)
        keep &= (boxes[..., :3] >= lim[:3]).all(-1) & (boxes[..., :3] <= lim[3:]).all(-1)
    out = [
        {"boxes": boxes[i][keep[i]], "scores": scores[i][keep[i]], "labels": labels[i][keep[i]]}
        for i in range(B)
    ]
    if iou is not None:  # [-1, 1] -> [0, 1]
        cell_iou = ((gather_feature_at(iou.float(), cell)[..., 0] + 1) * 0.5).clamp(0.0, 1.0)
        for i, d in enumerate(out):
            d["iou"] = cell_iou[i][keep[i]]
    return out
