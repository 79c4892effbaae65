"""PTT's second stage (Huang et al., CVPR'24): refine the current frame's proposals with the
current frame's points and a 32-frame history of proposals (docs/model_zoo.md, "PTT").

Per proposal (ROI) the head reads a box sequence of ``L = F + 1 + H`` frames in the order
``[F future boxes (farthest first), the ROI, H past boxes (newest first)]``: the past boxes are
the ROI's trajectory through the proposal history
(:func:`~pcdet_atlas.models.model_utils.trajectory.associate_trajectories`), the future boxes the
ROI extrapolated by its velocity (:func:`~pcdet_atlas.models.model_utils.trajectory.future_boxes`).
Past frames before the start of the sequence are masked everywhere (attention keys and pooling).

1. Point-to-proposal (P-T) features: ``NUM_POINTS`` current-frame points sampled in a cylinder
   around the ROI, each encoded against every box of the sequence (offsets to its 8 corners and
   centre in spherical form, with intensity and elongation) by an MLP.
2. Proposal-to-proposal features: the box sequence relative to the ROI (centre rotated into the
   ROI's heading, size, heading difference, time) by a linear layer; concatenated per frame with
   the frame's P-T features max-pooled over the points.
3. Memories: the sequence split into future ``[:F]``, short-term ``[F : F + S]`` (the ROI and
   ``S - 1`` past frames) and long-term (the older past frames). The long memory attends to
   itself, the short memory queries the long one, the future memory (with a learnt token) queries
   both; the three concatenated pass a self-attention over all frames.
4. Current-point branch: self-attention over the ROI's P-T features of the current frame,
   max-pooled to the current feature, which queries each memory; the three answers are fused
   back into it (residual).
5. Point-trajectory aggregator: the memories max-pooled over the valid frames and the current
   feature give the trajectory feature (and an auxiliary box); the refined box is regressed from
   ``[current, trajectory]`` features, the confidence from the current feature.

Attention blocks are PTT's (no layer norm): ``O = Q + softmax(Q K^T / sqrt(d_head)) V`` then
``O + ReLU(W O)``, with the scale of the head dimension where the released code uses the full
width (docs/model_zoo.md lists this and the other deliberate differences).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.config_values import check_finite, section, setting
from pcdet_atlas.models.model_utils.motion_sampler import sample_batch_points
from pcdet_atlas.models.model_utils.released_names import (
    FoldedBias,
    NoCounterpart,
    PermutedInputs,
    Reshaped,
    renamed,
)
from pcdet_atlas.models.model_utils.trajectory import associate_trajectories, future_boxes
from pcdet_atlas.models.roi_heads.msf_head import mlp, spherical_offsets
from pcdet_atlas.models.roi_heads.roi_head_template import RoiHeadConfig, TemporalRoIHead
from pcdet_atlas.models.stage_config import read_stage
from pcdet_atlas.registry import MODEL_STAGES

__all__ = ["PTTHead", "MemoryAttention", "box_sequence_features", "history_frames"]


class LinearBN(nn.Module):
    """A per-token linear layer with batch norm over all tokens (OpenPCDet's ``Conv1d(k=1)`` +
    ``BatchNorm1d``) and an optional ReLU, on channel-last tensors ``(..., C)``."""

    def __init__(self, dim_in: int, dim_out: int, relu: bool = True):
        super().__init__()
        self.linear = nn.Linear(dim_in, dim_out, bias=False)
        self.norm = nn.BatchNorm1d(dim_out)
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.norm(self.linear(x).reshape(-1, self.linear.out_features))
        out = out.reshape(*x.shape[:-1], -1)
        return F.relu(out) if self.relu else out


class MemoryAttention(nn.Module):
    """PTT's attention block: ``O = Q' + softmax(Q' K'^T / sqrt(d_head)) V'`` over the unmasked
    keys, then ``O + ReLU(W_o O)``; heads split the ``dim`` channels. A query whose keys are all
    masked gets ``Q'`` alone."""

    def __init__(self, dim_q: int, dim_k: int, dim: int, heads: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"attention width {dim} is not divisible by {heads} heads")
        self.heads = heads
        self.q, self.k, self.v = nn.Linear(dim_q, dim), nn.Linear(dim_k, dim), nn.Linear(dim_k, dim)
        self.out = nn.Linear(dim, dim)

    def forward(
        self, query: torch.Tensor, key: torch.Tensor, key_valid: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``query`` ``(N, Lq, dim_q)``, ``key`` ``(N, Lk, dim_k)``, ``key_valid`` ``(N, Lk)``
        bool -> ``(N, Lq, dim)``."""
        num, len_q, _ = query.shape
        q = self.q(query)
        split = lambda x: x.reshape(num, x.shape[1], self.heads, -1).transpose(1, 2)  # noqa: E731
        qh, kh, vh = split(q), split(self.k(key)), split(self.v(key))
        logits = qh @ kh.transpose(-1, -2) / math.sqrt(qh.shape[-1])  # (N, h, Lq, Lk)
        if key_valid is not None:
            mask = key_valid[:, None, None, :]
            logits = logits.masked_fill(~mask, torch.finfo(logits.dtype).min)
            weights = torch.softmax(logits, dim=-1) * mask  # all keys masked: zero weights
        else:
            weights = torch.softmax(logits, dim=-1)
        out = q + (weights @ vh).transpose(1, 2).reshape(num, len_q, -1)
        return out + F.relu(self.out(out))


def box_sequence_features(boxes: torch.Tensor, current: int) -> torch.Tensor:
    """``(N, L, 8)`` proposal-to-proposal inputs of a box sequence ``(N, L, 7+)``: centre minus
    the current box's centre rotated into its heading, size, heading minus the current heading
    (wrapped to [-pi, pi)), and the frame's time lag ``0.1 (l - current)`` s (future frames
    negative)."""
    ref = boxes[:, current]
    delta = boxes[..., 0:3] - ref[:, None, 0:3]
    cos, sin = torch.cos(-ref[:, 6])[:, None], torch.sin(-ref[:, 6])[:, None]
    x = delta[..., 0] * cos - delta[..., 1] * sin
    y = delta[..., 0] * sin + delta[..., 1] * cos
    heading = boxes[..., 6] - ref[:, None, 6]
    heading = heading - 2 * math.pi * torch.floor(heading / (2 * math.pi) + 0.5)
    lag = 0.1 * (torch.arange(boxes.shape[1], device=boxes.device, dtype=boxes.dtype) - current)
    return torch.stack(
        [x, y, delta[..., 2], boxes[..., 3], boxes[..., 4], boxes[..., 5], heading,
         lag[None].expand_as(x)], dim=-1,
    )  # fmt: skip


def history_frames(
    roi_history: torch.Tensor, history_count: int, num_history: int
) -> list[torch.Tensor | None]:
    """One sample's collated ``roi_history`` ``(N, 12)`` (label 0 rows: padding) -> for frames
    ``t-1 .. t-num_history`` its proposals ``(R_k, 11)``, ``None`` from the sequence start on."""
    real = roi_history[roi_history[:, 10] > 0]
    back = real[:, 11].round().long()
    return [real[back == k, :11] if k <= history_count else None for k in range(1, num_history + 1)]


@dataclass(frozen=True, kw_only=True)
class PTTSamplerConfig:
    """``MODEL.ROI_HEAD.SAMPLER``."""

    num_points: int = setting(256, ge=1, doc="points per proposal")
    gamma: float = setting(1.1, gt=0, doc="ball radius factor")


@dataclass(frozen=True, kw_only=True)
class PTTHeadConfig(RoiHeadConfig):
    """``MODEL.ROI_HEAD`` of PTTHead."""

    num_history: int = setting(31, ge=0, doc="past frames of a track")
    num_future: int = setting(16, ge=0, doc="future boxes predicted")
    short_frames: int = setting(8, ge=1, doc="frames with point features")
    association_iou: float = setting(0.5, ge=0, le=1, doc="IoU that associates proposals")
    sampler: PTTSamplerConfig = section(PTTSamplerConfig)
    embed_dim: int = setting(64, ge=1, doc="point embedding width")
    point_dim: int = setting(128, ge=1, doc="point feature width")
    box_dim: int = setting(64, ge=1, doc="box feature width")
    pool_dim: int = setting(32, ge=1, doc="pooled width")
    token_dim: int = setting(32, ge=1, doc="token width")
    hidden_dim: int = setting(256, ge=1, doc="transformer width")
    nheads: int = setting(4, ge=1, doc="attention heads")


@MODEL_STAGES.register()
class PTTHead(TemporalRoIHead):
    """The PTT ROI head (module docstring); config keys in :meth:`from_config` and
    docs/model_zoo.md.

    :meth:`forward` reads ``points`` ``(N, 1 + C)`` (time lag last; only lag-0 points are
    used), ``trajectories`` ``(B, 1 + H, R, 9)`` (each ROI's box per frame, frame 0 the ROI,
    then frames ``t-1 .. t-H``), ``trajectory_valid`` ``(B, 1 + H, R)``, ``roi_valid``
    ``(B, R)`` and ``generators``, and writes ``rcnn_cls`` (a one-element list of ``(B, R)``
    logits), ``rcnn_reg`` and ``traj_reg`` ``(B, R, 7)`` codes, and ``aux_reg`` (empty).
    """

    CONFIG = PTTHeadConfig

    def __init__(
        self,
        *,
        num_class: int,
        num_point_features: int,
        num_history: int = PTTHeadConfig.num_history,
        num_future: int = PTTHeadConfig.num_future,
        short_frames: int = PTTHeadConfig.short_frames,
        association_iou: float = PTTHeadConfig.association_iou,
        iou_weight: Sequence[float] = (0.5, 0.4, 0.4),
        num_points: int = PTTSamplerConfig.num_points,
        gamma: float = PTTSamplerConfig.gamma,
        embed_dim: int = PTTHeadConfig.embed_dim,
        point_dim: int = PTTHeadConfig.point_dim,
        box_dim: int = PTTHeadConfig.box_dim,
        pool_dim: int = PTTHeadConfig.pool_dim,
        token_dim: int = PTTHeadConfig.token_dim,
        hidden_dim: int = PTTHeadConfig.hidden_dim,
        nheads: int = PTTHeadConfig.nheads,
        sampler_cfg=None,
        roi_aug: Mapping | None = None,
        loss_weights: Mapping | None = None,
    ):
        super().__init__(
            num_class=num_class, num_point_features=num_point_features, iou_weight=iou_weight,
            sampler_cfg=sampler_cfg, roi_aug=roi_aug, loss_weights=loss_weights,
        )  # fmt: skip
        if not 1 <= short_frames <= num_history:
            raise ValueError(
                f"SHORT_FRAMES must be in [1, NUM_HISTORY={num_history}], got {short_frames}"
            )
        if num_future < 1:
            raise ValueError(f"NUM_FUTURE must be >= 1, got {num_future}")
        if token_dim >= box_dim + pool_dim:
            raise ValueError(
                f"TOKEN_DIM ({token_dim}) must be below BOX_DIM + POOL_DIM ({box_dim + pool_dim})"
            )
        self.num_history, self.num_future = int(num_history), int(num_future)
        self.short_frames = int(short_frames)
        self.association_iou = float(association_iou)
        self.num_points, self.gamma = int(num_points), float(gamma)
        frame_dim = box_dim + pool_dim
        extra = self.point_feature_dim - 3
        self.point_embed = mlp([27 + extra, embed_dim, embed_dim, point_dim])
        self.box_embed = nn.Sequential(nn.BatchNorm1d(8), nn.Linear(8, box_dim, bias=False))
        self.box_norm = nn.BatchNorm1d(box_dim)
        self.point_pool = LinearBN(point_dim, pool_dim)
        self.future_proj = LinearBN(frame_dim, frame_dim - token_dim)
        self.future_token = nn.Parameter(torch.zeros(token_dim))
        nn.init.normal_(self.future_token, std=0.02)
        self.long_attn = MemoryAttention(frame_dim, frame_dim, frame_dim, nheads)
        self.short_attn = MemoryAttention(frame_dim, frame_dim, frame_dim, nheads)
        self.future_attn = MemoryAttention(frame_dim, frame_dim, frame_dim, nheads)
        self.memory_proj = LinearBN(frame_dim, point_dim)
        self.memory_attn = MemoryAttention(point_dim, point_dim, point_dim, nheads)
        self.point_attn = MemoryAttention(point_dim, point_dim, point_dim, nheads)
        self.current_proj = nn.Linear(point_dim, hidden_dim)
        self.segment_proj = nn.ModuleList(LinearBN(point_dim, hidden_dim) for _ in range(3))
        self.segment_attn = nn.ModuleList(
            MemoryAttention(hidden_dim, hidden_dim, hidden_dim, nheads) for _ in range(3)
        )
        self.segment_fuse = LinearBN(3 * hidden_dim, hidden_dim)
        self.aggregate = nn.Sequential(
            LinearBN(point_dim, hidden_dim), LinearBN(hidden_dim, 2 * hidden_dim, relu=False)
        )
        self.trajectory_fc = nn.Sequential(
            LinearBN(3 * hidden_dim, 2 * hidden_dim), LinearBN(2 * hidden_dim, hidden_dim),
            LinearBN(hidden_dim, hidden_dim),
        )  # fmt: skip
        self.traj_center = mlp([hidden_dim, hidden_dim, 3], bias_last=False)
        self.traj_size = mlp([hidden_dim, hidden_dim, 3], bias_last=False)
        self.traj_heading = mlp([hidden_dim, hidden_dim, 1], bias_last=False)
        self.class_embed = nn.Linear(hidden_dim, 1)
        self.joint_reg = mlp([2 * hidden_dim, hidden_dim, hidden_dim, hidden_dim, 7])
        nn.init.normal_(self.joint_reg[-1].weight, std=0.001)
        nn.init.zeros_(self.joint_reg[-1].bias)

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> PTTHead:
        settings = read_stage(cls, cfg, "MODEL.ROI_HEAD")
        common = cls.common_config(settings, model_info["class_names"])
        check_finite(cfg, "MODEL.ROI_HEAD")
        return cls(
            num_point_features=model_info["num_rawpoint_features"],
            num_history=settings.num_history,
            num_future=settings.num_future,
            short_frames=settings.short_frames,
            association_iou=settings.association_iou,
            num_points=settings.sampler.num_points,
            gamma=settings.sampler.gamma,
            embed_dim=settings.embed_dim,
            point_dim=settings.point_dim,
            box_dim=settings.box_dim,
            pool_dim=settings.pool_dim,
            token_dim=settings.token_dim,
            hidden_dim=settings.hidden_dim,
            nheads=settings.nheads,
            **common,
        )

    # ------------------------------------------------------------------ released checkpoints
    def openpcdet_names(self) -> dict:
        """This head's ``state_dict`` keys -> the names the PTT repository's ``PTTHead`` gives
        the same tensors (KuanchihHuang/PTT, ``pcdet/models/roi_heads/ptt_head.py``; its
        detector saves the head as ``roi_head``, the transformer as ``roi_head.ptt``).

        Kernel-size-1 ``Conv1d`` weights there are ``Linear`` weights here; their biases, before
        a BatchNorm, fold into its running mean; the future token comes first in the future
        memory's query there, last here. The current frame's point features have no
        counterpart: the released code reads them as 128 pairs of points (two points' channels
        side by side) at twice the width, here they stay 256 points.
        """
        linear_bn = {  # ours -> the released (conv or linear, BatchNorm) pair
            "future_proj": ("ptt.conv_future", "ptt.bn_future"),
            "memory_proj": ("ptt.conv2", "ptt.bn2"),
            "segment_proj.0": ("ptt.conv2_future", "ptt.bn2_future"),
            "segment_proj.1": ("ptt.conv2_short", "ptt.bn2_short"),
            "segment_proj.2": ("ptt.conv2_long", "ptt.bn2_long"),
            "segment_fuse": ("ptt.conv_point", "ptt.bn_point"),
            "aggregate.0": ("ptt.conv3", "ptt.bn3"),
            "aggregate.1": ("ptt.conv4", "ptt.bn4"),
            "trajectory_fc.0": ("ptt.conv_final", "ptt.bn_final"),
            "trajectory_fc.1": ("ptt.fc1", "ptt.x_bn1"),
            "trajectory_fc.2": ("ptt.fc2", "ptt.x_bn2"),
        }
        attention = {
            "long_attn": "ptt.attn1_long", "short_attn": "ptt.attn1_short",
            "future_attn": "ptt.attn1_future", "memory_attn": "ptt.attn2",
            "segment_attn.0": "ptt.cross_future", "segment_attn.1": "ptt.cross_short",
            "segment_attn.2": "ptt.cross_long",
        }  # fmt: skip
        modules = {
            "box_embed.0": "ptt.pre_bn",
            "box_norm": "ptt.bn1",
            "class_embed": "class_embed.0",
            **{f"{ours}.norm": bn for ours, (_, bn) in linear_bn.items()},
            **{
                f"{ours}.{part}": f"{theirs}.fc_{part[0]}"
                for ours, theirs in attention.items()
                for part in ("q", "k", "v", "out")
            },
        }
        for ours, theirs, layers in (
            ("point_embed", "up_dimension_geometry", self.point_embed),
            ("joint_reg", "jointembed", self.joint_reg),
        ):
            linear = [i for i, m in enumerate(layers) if isinstance(m, nn.Linear)]
            modules.update({f"{ours}.{i}": f"{theirs}.layers.{k}" for k, i in enumerate(linear)})
        for ours, theirs in (
            ("traj_center", "fc_ce"), ("traj_size", "fc_s"), ("traj_heading", "fc_hr")
        ):  # fmt: skip
            modules[f"{ours}.0"], modules[f"{ours}.2"] = f"ptt.{theirs}1", f"ptt.{theirs}2"
        pooled = NoCounterpart(
            "the released code views each frame's P-T features (K points x C) as K/2 pairs of "
            "points x 2C (ptt_head.py, src.view) and projects their max over the pairs (the even "
            "points' max beside the odd points'), where this head projects the max over the K "
            "points (C channels)",
            ("ptt.conv2_p", "ptt.bn2_p"),
        )
        current = NoCounterpart(
            "the released current-point attention runs over those K/2 pairs at width 2C and is "
            "max-pooled, where this head attends over the K points at width C and projects them "
            "(current_proj) before the max",
            ("ptt.attn3_point",),
        )
        token = self.future_token.numel()
        frame_dim = self.future_attn.q.in_features
        names: dict = {}
        for key, value in self.state_dict().items():
            module, owner = key.rsplit(".", 1)[0], key.rsplit(".", 2)[0]
            if owner in linear_bn and key.endswith(".linear.weight"):
                conv = linear_bn[owner][0]
                is_conv = not conv.startswith("ptt.fc")  # a Conv1d(kernel 1) there
                names[key] = (
                    Reshaped(f"{conv}.weight", (*value.shape, 1)) if is_conv else f"{conv}.weight"
                )
            elif owner in linear_bn and key.endswith(".norm.running_mean"):
                bn, conv = linear_bn[owner][1], linear_bn[owner][0]
                names[key] = FoldedBias(f"{bn}.running_mean", f"{conv}.bias")
            elif key == "box_embed.1.weight":  # Conv1d(8, 64, 1) there, its bias folded
                names[key] = Reshaped("ptt.conv1.weight", (*value.shape, 1))
            elif key == "box_norm.running_mean":
                names[key] = FoldedBias("ptt.bn1.running_mean", "ptt.conv1.bias")
            elif key == "future_token":
                names[key] = Reshaped("ptt.future_token", (1, 1, token))
            elif key == "future_attn.q.weight":  # query [projection, token] here, [token, ...]
                order = (*range(token, frame_dim), *range(token))
                names[key] = PermutedInputs("ptt.attn1_future.fc_q.weight", order)
            elif module.startswith("point_pool."):
                names[key] = pooled
            elif module.startswith("point_attn.") or module == "current_proj":
                names[key] = current
            else:
                theirs = renamed(key, modules)
                if theirs is None:
                    raise ValueError(f"PTTHead: no released name for {key}")
                names[key] = theirs
        return names

    @staticmethod
    def openpcdet_unused() -> dict[str, str]:
        """Modules of the released ``PTTHead`` that its forward never reads (built, never
        called), with no counterpart here."""
        never = "built by the released PTTHead, never called by its forward"
        return {
            "fc": never,
            "bn": never,
            "up_dimension_motion": never,
            "roi_grid_pool_layer": never + " (roi_grid_pool() is never called)",
            "grid_pos_embeded": never,
            "pos": never,
            "ptt.attn1": never,
            "ptt.attn3": never,
            "bbox_embed": (
                "training-only auxiliary boxes of the released PTTHead (bbox_embed.0 on the "
                "current feature, the others never called), and this head has no auxiliary box"
            ),
        }

    # ------------------------------------------------------------------ trajectories
    def trajectories(
        self, rois: torch.Tensor, history: list[torch.Tensor | None]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(1 + H, R, 9)`` boxes and validity of proposals ``rois`` ``(R, 9)`` followed back
        through one sample's ``history`` (:func:`history_frames`)."""
        boxes, _, valid = associate_trajectories(
            rois[:, :9], [h if h is None else h[:, :9] for h in history], self.association_iou
        )
        return boxes, valid

    # ------------------------------------------------------------------ features
    def forward(self, batch: dict) -> dict:
        traj, traj_valid = batch["trajectories"], batch["trajectory_valid"]
        batch_size, frames, num_rois = traj.shape[:3]
        if frames != 1 + self.num_history:
            raise ValueError(
                f"PTTHead: {frames} trajectory frames for NUM_HISTORY={self.num_history} (+1)"
            )
        num, fut = batch_size * num_rois, self.num_future
        pts, pts_valid = sample_batch_points(  # (B, R, 1, K, C): the current frame's points
            batch["points"], traj[:, :1, :, :7], batch["generators"], num_sample=self.num_points,
            gamma=self.gamma, radius_growth=True,
        )  # fmt: skip
        pts = pts.reshape(num, self.num_points, -1)
        roi_valid = batch["roi_valid"].reshape(num)
        pts_valid = pts_valid.reshape(num, self.num_points) & roi_valid[:, None]
        past = traj.permute(0, 2, 1, 3).reshape(num, frames, -1)  # (N, 1 + H, 9)
        seq = torch.cat([future_boxes(past[:, 0], fut).transpose(0, 1), past], dim=1)
        length = seq.shape[1]
        frame_valid = torch.cat([
            past.new_ones(num, fut, dtype=torch.bool),
            traj_valid.permute(0, 2, 1).reshape(num, frames),
        ], dim=1) & roi_valid[:, None]  # fmt: skip
        frame_valid[:, fut] = True  # the ROI itself (keys stay defined for padding ROIs)

        # 1. P-T features (N, L, K, P): every point against every box of the sequence
        geometry = spherical_offsets(pts[:, None, :, 0:3], seq[..., :7], pts[:, None, :, 3:])
        pt_feat = self.point_embed(geometry).mul_(pts_valid[:, None, :, None])  # in place
        # 2. per-frame features (N, L, D): box sequence + pooled points
        box = self.box_embed(box_sequence_features(seq, fut).reshape(-1, 8))
        box = F.relu(self.box_norm(box)).reshape(num, length, -1)
        frame_feat = torch.cat([box, self.point_pool(pt_feat.amax(dim=2))], dim=-1)
        # 3. memories
        short_end = fut + self.short_frames
        future, short, long = frame_feat[:, :fut], frame_feat[:, fut:short_end], frame_feat[
            :, short_end:]  # fmt: skip
        v_short, v_long = frame_valid[:, fut:short_end], frame_valid[:, short_end:]
        future = torch.cat(
            [self.future_proj(future), self.future_token.expand(num, fut, -1)], dim=-1
        )
        if long.shape[1]:
            long = self.long_attn(long, long, v_long)
            short = self.short_attn(short, long, v_long)
        memory_keys = torch.cat([short, long], dim=1)
        future = self.future_attn(future, memory_keys, torch.cat([v_short, v_long], dim=1))
        memory = self.memory_proj(torch.cat([future, short, long], dim=1))
        memory = self.memory_attn(memory, memory, frame_valid)  # (N, L, P)
        # 4. current-point branch
        cur = self.point_attn(pt_feat[:, fut], pt_feat[:, fut], pts_valid)
        cur = self.current_proj(cur).masked_fill(~pts_valid[..., None], float("-inf"))
        cur = cur.max(dim=1).values
        cur = torch.where(torch.isfinite(cur), cur, torch.zeros_like(cur))  # no valid point
        segments = [(0, fut), (fut, short_end), (short_end, length)]
        answers = []
        for (lo, hi), proj, attn in zip(segments, self.segment_proj, self.segment_attn):
            if hi == lo:
                answers.append(torch.zeros_like(cur))
                continue
            answers.append(attn(cur[:, None], proj(memory[:, lo:hi]), frame_valid[:, lo:hi])[:, 0])
        cur = cur + self.segment_fuse(torch.cat(answers, dim=-1))
        # 5. point-trajectory aggregator
        agg = self.aggregate(memory).masked_fill(~frame_valid[..., None], float("-inf"))
        agg = agg.max(dim=1).values  # the ROI's own frame is always valid
        feat = self.trajectory_fc(torch.cat([agg, cur], dim=-1))
        traj_code = torch.cat(
            [self.traj_center(feat), self.traj_size(feat), self.traj_heading(feat)], dim=-1
        )
        joint = self.joint_reg(torch.cat([cur, feat], dim=-1))
        batch = dict(batch)
        batch["rcnn_cls"] = [self.class_embed(cur).reshape(batch_size, num_rois)]
        batch["rcnn_reg"] = joint.reshape(batch_size, num_rois, 7)
        batch["traj_reg"] = traj_code.reshape(batch_size, num_rois, 7)
        batch["aux_reg"] = []
        return batch
