"""MSF's second stage (He et al., CVPR'23): refine the current frame's proposals with points
sampled along each proposal's motion over the last ``T`` frames (docs/model_zoo.md, "MSF").

Per proposal (ROI) and frame ``i``: up to ``NUM_POINTS`` points from a cylinder around the
proposal propagated ``i`` frames back (:mod:`~pcdet_atlas.models.model_utils.motion_sampler`);
each point is embedded by its geometry (offsets to frame ``i``'s box corners and centre, in
spherical form, with intensity and elongation) plus its motion (the same offsets to the current
box, with the frame's time); a trajectory branch encodes the box sequence; ``ENC_LAYERS``
blocks of point self-attention, a per-frame query token attending to its frame's points and,
in the first ``BIFA_LAYERS`` blocks, bidirectional feature aggregation (BiFA) between adjacent
frames; the frames' final tokens and the trajectory feature give the refined box, the current
frame's token the confidence.

Deliberate difference from the released code: BiFA runs per frame (each group holds one frame's
points). The released code's reshape builds groups of 32-point slices of all frames.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.config_values import check_finite, section, setting
from pcdet_atlas.models.model_utils.motion_sampler import propagate_boxes, sample_batch_points
from pcdet_atlas.models.model_utils.released_names import Reshaped, renamed
from pcdet_atlas.models.model_utils.roi_sampler import RoiSamplerConfig
from pcdet_atlas.models.roi_heads.roi_head_template import RoiHeadConfig, TemporalRoIHead
from pcdet_atlas.models.stage_config import read_stage
from pcdet_atlas.ops.boxes import boxes_to_corners_3d
from pcdet_atlas.registry import MODEL_STAGES

__all__ = ["MSFHead", "BiFATransformer", "attention", "mlp", "spherical_offsets"]


def mlp(dims: Sequence[int], *, bias_last: bool = True) -> nn.Sequential:
    """Linear layers ``dims[0] -> ... -> dims[-1]`` with ReLU between (none after the last)."""
    layers: list[nn.Module] = []
    for k, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        last = k == len(dims) - 2
        layers.append(nn.Linear(a, b, bias=bias_last or not last))
        if not last:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def spherical_offsets(
    points_xyz: torch.Tensor, boxes: torch.Tensor, extra: torch.Tensor | None = None
) -> torch.Tensor:
    """``(..., K, 27 + E)`` offsets of points ``(..., K, 3)`` to the 8 corners and the centre of
    their box ``(..., 7)`` (leading dimensions broadcast), each as (distance / box diagonal,
    atan(dy / dx), acos(dz / distance)), grouped as 9 distances, 9 azimuths, 9 polar angles (the
    released code's encoding), followed by the points' ``extra`` ``(..., K, E)`` channels (none
    by default; broadcast too), in one concatenation."""
    lead = boxes.shape[:-1]
    corners = boxes_to_corners_3d(boxes.reshape(-1, boxes.shape[-1])[:, :7]).reshape(*lead, 8, 3)
    anchors = torch.cat([corners, boxes[..., None, 0:3]], dim=-2)  # (..., 9, 3)
    # (..., K, 9, 3); subtracted as (..., K, 27) rows (xyz 9 times - the 9 anchors), a
    # broadcast over whole rows rather than over 3-element ones (the same numbers, faster)
    delta = (points_xyz.tile(9) - anchors.flatten(-2)[..., None, :]).unflatten(-1, (9, 3))
    dist = torch.linalg.vector_norm(delta, dim=-1)
    diagonal = torch.linalg.vector_norm(boxes[..., 3:6], dim=-1)[..., None, None]
    azimuth = torch.atan(delta[..., 1] / (delta[..., 0] + 1e-5))
    polar = torch.acos((delta[..., 2] / (dist + 1e-5)).clamp(-1.0, 1.0))
    parts = [dist / (diagonal + 1e-5), azimuth, polar]
    if extra is not None:
        parts.append(extra.expand(*dist.shape[:-1], extra.shape[-1]))
    return torch.cat(parts, dim=-1)


class TrajectoryPointNet(nn.Module):
    """The trajectory branch: a PointNet over the box sequence ``(N, 8, T)`` (centre relative
    to the current box and rotated into its heading, size, heading 0, time) -> an auxiliary box
    code ``(N, 7)`` and a feature ``(N, hidden)``."""

    def __init__(self, hidden: int, code_size: int = 7):
        super().__init__()
        widths = [8, 64, 128, 256, 512]
        self.input_norm = nn.BatchNorm1d(8)
        convs, norms = [], []
        for a, b in zip(widths[:-1], widths[1:]):
            convs.append(nn.Conv1d(a, b, 1))
            norms.append(nn.BatchNorm1d(b))
        self.convs, self.norms = nn.ModuleList(convs), nn.ModuleList(norms)
        self.fc = nn.Sequential(
            nn.Linear(512, hidden), nn.BatchNorm1d(hidden), nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden), nn.BatchNorm1d(hidden), nn.ReLU(inplace=True),
        )  # fmt: skip
        self.center = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 3, bias=False)
        )
        self.size = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 3, bias=False)
        )
        self.heading = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, code_size - 6, bias=False)
        )

    def forward(self, seq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.input_norm(seq)
        for k, (conv, norm) in enumerate(zip(self.convs, self.norms)):
            x = norm(conv(x))
            if k < len(self.convs) - 1:
                x = F.relu(x)
        feat = self.fc(x.max(dim=2).values)
        return torch.cat([self.center(feat), self.size(feat), self.heading(feat)], 1), feat


def trajectory_sequence(trajectories: torch.Tensor) -> torch.Tensor:
    """``(N, 8, T)`` inputs of :class:`TrajectoryPointNet` from boxes ``(N, T, 7)``."""
    num_frames = trajectories.shape[1]
    seq = trajectories[..., :7].clone()
    seq[..., 0:3] = seq[..., 0:3] - seq[:, :1, 0:3]
    yaw0 = seq[:, 0, 6]
    cos, sin = torch.cos(-yaw0)[:, None], torch.sin(-yaw0)[:, None]
    x, y = seq[..., 0].clone(), seq[..., 1].clone()
    seq[..., 0], seq[..., 1] = x * cos - y * sin, x * sin + y * cos
    seq[..., 6] = 0.0
    time = 0.1 * torch.arange(num_frames, dtype=seq.dtype, device=seq.device)
    seq = torch.cat([seq, time[None, :, None].expand(seq.shape[0], -1, 1)], dim=2)
    return seq.transpose(1, 2).contiguous()


def attention(
    attn: nn.MultiheadAttention, query: torch.Tensor, memory: torch.Tensor | None = None
) -> torch.Tensor:
    """``attn``'s attention (its projections, heads and dropout; no masks) of ``query``
    ``(B, Lq, C)`` over ``memory`` ``(B, L, C)`` (``None``: over itself) -> ``(B, Lq, C)``.

    Batch first throughout: the heads are views ``(B, h, L, C / h)`` of the projections, and
    the attention's output, laid out ``(B, Lq, h, C / h)`` by the fused kernels, feeds the
    output projection as it is, where ``nn.MultiheadAttention``'s forward (sequence first)
    copies its inputs, projections and output between layouts."""
    batch, len_q, dim = query.shape
    heads = attn.num_heads
    weight, bias = attn.in_proj_weight, attn.in_proj_bias
    if memory is None:  # one packed projection for q, k and v
        qkv = F.linear(query, weight, bias).view(batch, len_q, 3, heads, dim // heads)
        q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)
    else:
        q = F.linear(query, weight[:dim], bias[:dim]).view(batch, len_q, heads, -1).transpose(1, 2)
        kv = F.linear(memory, weight[dim:], bias[dim:]).view(batch, -1, 2, heads, dim // heads)
        k, v = kv.permute(2, 0, 3, 1, 4).unbind(0)
    out = F.scaled_dot_product_attention(q, k, v, dropout_p=attn.dropout if attn.training else 0.0)
    return attn.out_proj(out.transpose(1, 2).reshape(batch, len_q, dim))


def group_max(token: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``(F, N, C)`` max over each group: its token ``(F, N, C)`` and points ``(F, N, K, C)``."""
    return torch.maximum(token, points.amax(dim=2))


def fuse_pooled(
    fuse: nn.Linear,
    norm: nn.LayerNorm,
    token: torch.Tensor,
    points: torch.Tensor,
    pooled: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One BiFA step on ``F`` frames: ``norm(fuse([x, pooled]) + x)`` for each token ``x``
    ``(F, N, C)`` and point ``(F, N, K, C)``, ``pooled`` ``(F, N, C)`` the features each frame
    takes. ``fuse`` runs as its two halves, the pooled one once per frame and ROI (not per
    point, and no concatenated input)."""
    dim = token.shape[-1]
    own = fuse.weight[:, :dim]
    pool = F.linear(pooled, fuse.weight[:, dim:], fuse.bias)
    return (
        norm(F.linear(token, own) + pool + token),
        norm(F.linear(points, own) + pool[:, :, None] + points),
    )


class EncoderLayer(nn.Module):
    """One MSF block over ``T`` groups (each a frame's query token and points): point
    self-attention, the query token attending to its frame's points, and (``bifa``)
    bidirectional aggregation between adjacent frames."""

    def __init__(
        self, dim: int, heads: int, point_heads: int, ffn: int, dropout: float, bifa: bool
    ):
        super().__init__()
        self.point_attn = nn.MultiheadAttention(dim, point_heads, dropout=dropout)
        self.point_norm1, self.point_norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.point_ffn = nn.Sequential(
            nn.Linear(dim, ffn), nn.ReLU(inplace=True), nn.Dropout(dropout), nn.Linear(ffn, dim)
        )
        self.token_attn = nn.MultiheadAttention(dim, heads, dropout=dropout)
        self.token_norm1, self.token_norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.token_ffn = nn.Sequential(
            nn.Linear(dim, ffn), nn.ReLU(inplace=True), nn.Dropout(dropout), nn.Linear(ffn, dim)
        )
        self.dropout = nn.Dropout(dropout)
        self.bifa = bifa
        if bifa:
            self.forward_fuse, self.backward_fuse = nn.Linear(2 * dim, dim), nn.Linear(2 * dim, dim)
            self.forward_norm, self.backward_norm = nn.LayerNorm(dim), nn.LayerNorm(dim)

    def forward(
        self, token: torch.Tensor, points: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``token`` ``(T, N, C)`` and ``points`` ``(T, N, K, C)`` (frame, ROI, point, channel)
        -> both updated. The attention runs with frames and ROIs on the batch axis
        (``(T * N, K, C)``, a view)."""
        num_frames, num, length, dim = points.shape
        pts = points.reshape(num_frames * num, length, dim)
        tok = token.reshape(num_frames * num, 1, dim)
        pts = self.point_norm1(pts + self.dropout(attention(self.point_attn, pts)))
        pts = self.point_norm2(pts + self.dropout(self.point_ffn(pts)))
        tok = self.token_norm1(tok + self.dropout(attention(self.token_attn, tok, pts)))
        tok = self.token_norm2(tok + self.dropout(self.token_ffn(tok)))
        token, points = tok.reshape(num_frames, num, dim), pts.reshape(num_frames, num, length, dim)
        if self.bifa and num_frames > 1:
            token, points = self._bifa(token, points)
        return token, points

    def _bifa(self, token: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frame ``k`` takes the max-pooled features of frame ``k - 1`` (forward, newer ->
        older), then of frame ``k + 1`` (backward), each by a linear layer on the concatenation,
        a residual and a layer norm (:func:`fuse_pooled`)."""
        pooled = group_max(token, points)  # (T, N, C)
        # forward: frames 1 .. T-1 (frame 0 keeps its own)
        fwd_token, fwd_points = fuse_pooled(
            self.forward_fuse, self.forward_norm, token[1:], points[1:], pooled[:-1]
        )
        pooled = group_max(fwd_token, fwd_points)  # of frames 1 .. T-1
        # backward: frame 0, and apart (not concatenated with it) frames 1 .. T-2; the last
        # frame keeps its forward result
        first = fuse_pooled(
            self.backward_fuse, self.backward_norm, token[:1], points[:1], pooled[:1]
        )
        middle = fuse_pooled(
            self.backward_fuse, self.backward_norm, fwd_token[:-1], fwd_points[:-1], pooled[1:]
        )
        return (
            torch.cat([first[0], middle[0], fwd_token[-1:]]),
            torch.cat([first[1], middle[1], fwd_points[-1:]]),
        )


class BiFATransformer(nn.Module):
    """``layers`` :class:`EncoderLayer` blocks (the first ``bifa_layers`` with BiFA) over one
    group per frame, each led by a learnt query token of its frame."""

    def __init__(self, num_frames: int, dim: int, heads: int, point_heads: int, ffn: int,
                 layers: int, bifa_layers: int, dropout: float):  # fmt: skip
        super().__init__()
        self.token = nn.Parameter(torch.zeros(num_frames, 1, 1, dim))
        nn.init.normal_(self.token, std=0.02)
        self.layers = nn.ModuleList(
            EncoderLayer(dim, heads, point_heads, ffn, dropout, bifa=k < bifa_layers)
            for k in range(layers)
        )

    def forward(self, points: torch.Tensor) -> list[torch.Tensor]:
        """``points``: ``(T, N, K, C)`` embedded points (frame, ROI, point, channel); returns
        each layer's tokens ``(T, N, C)``."""
        num_frames, num, _, dim = points.shape
        token = self.token.reshape(num_frames, 1, dim).expand(num_frames, num, dim)
        tokens = []
        for layer in self.layers:
            token, points = layer(token, points)
            tokens.append(token)
        return tokens


@dataclass(frozen=True, kw_only=True)
class MSFSamplerConfig:
    """``MODEL.ROI_HEAD.SAMPLER``: points around each proposal's trajectory."""

    num_points: int = setting(128, ge=1, doc="points per proposal and frame")
    gamma: float = setting(1.1, gt=0, doc="ball radius factor")
    radius_growth: bool = setting(True, doc="radius grows with the frame's age")


@dataclass(frozen=True, kw_only=True)
class MSFTransformerConfig:
    """``MODEL.ROI_HEAD.TRANSFORMER``."""

    hidden_dim: int = setting(256, ge=1, doc="token width")
    nheads: int = setting(4, ge=1, doc="attention heads")
    point_nheads: int = setting(8, ge=1, doc="point attention heads")
    enc_layers: int = setting(3, ge=1, doc="encoder layers")
    bifa_layers: int = setting(2, ge=0, doc="bidirectional feature aggregation layers (0: none)")
    dim_feedforward: int = setting(512, ge=1, doc="feed-forward width")
    dropout: float = setting(0.1, ge=0, lt=1, doc="dropout")


@dataclass(frozen=True, kw_only=True)
class MSFHeadConfig(RoiHeadConfig):
    """``MODEL.ROI_HEAD`` of MSFHead."""

    num_frames: int = setting(4, ge=1, doc="frames of each trajectory")
    sampler: MSFSamplerConfig = section(MSFSamplerConfig)
    transformer: MSFTransformerConfig = section(MSFTransformerConfig)
    embed_dim: int = setting(64, ge=1, doc="point embedding width")


@MODEL_STAGES.register()
class MSFHead(TemporalRoIHead):
    """The MSF ROI head (module docstring); config keys in :meth:`from_config` and
    docs/model_zoo.md.

    :meth:`forward` reads ``points`` ``(N, 1 + C)`` with the time lag last, ``trajectories``
    ``(B, T, R, 7)`` (each proposal's box per frame, frame 0 the proposal itself),
    ``roi_valid`` ``(B, R)`` bool and ``generators`` (one CPU ``torch.Generator`` per sample),
    and writes ``rcnn_cls`` (list over blocks of ``(B, R)`` logits), ``rcnn_reg`` ``(B, R, 7)``
    codes of the refined box, ``aux_reg`` (list over blocks and frame tokens of ``(B, R, 7)``
    codes) and ``traj_reg`` ``(B, R, 7)`` (the trajectory branch's codes).
    """

    CONFIG = MSFHeadConfig

    def __init__(
        self,
        *,
        num_class: int,
        num_point_features: int,
        num_frames: int = MSFHeadConfig.num_frames,
        iou_weight: Sequence[float] = (0.5, 0.4, 0.4),
        num_points: int = MSFSamplerConfig.num_points,
        gamma: float = MSFSamplerConfig.gamma,
        radius_growth: bool = MSFSamplerConfig.radius_growth,
        hidden_dim: int = MSFTransformerConfig.hidden_dim,
        nheads: int = MSFTransformerConfig.nheads,
        point_nheads: int = MSFTransformerConfig.point_nheads,
        enc_layers: int = MSFTransformerConfig.enc_layers,
        bifa_layers: int = MSFTransformerConfig.bifa_layers,
        dim_feedforward: int = MSFTransformerConfig.dim_feedforward,
        dropout: float = MSFTransformerConfig.dropout,
        embed_dim: int = MSFHeadConfig.embed_dim,
        sampler_cfg: RoiSamplerConfig | None = None,
        roi_aug: Mapping | None = None,
        loss_weights: Mapping | None = None,
    ):
        super().__init__(
            num_class=num_class, num_point_features=num_point_features, iou_weight=iou_weight,
            sampler_cfg=sampler_cfg, roi_aug=roi_aug, loss_weights=loss_weights,
        )  # fmt: skip
        if not 0 <= bifa_layers <= enc_layers:
            raise ValueError(
                f"BIFA_LAYERS must be in [0, ENC_LAYERS={enc_layers}], got {bifa_layers}"
            )
        self.num_frames = int(num_frames)
        self.num_points, self.gamma, self.radius_growth = (
            int(num_points),
            float(gamma),
            bool(radius_growth),
        )
        extra = self.point_feature_dim - 3
        self.geometry_embed = mlp([27 + extra, embed_dim, embed_dim, hidden_dim])
        self.motion_embed = mlp([30, embed_dim, embed_dim, hidden_dim])
        self.trajectory = TrajectoryPointNet(hidden_dim)
        self.transformer = BiFATransformer(
            self.num_frames, hidden_dim, nheads, point_nheads, dim_feedforward, enc_layers,
            bifa_layers, dropout,
        )  # fmt: skip
        self.class_embed = nn.Linear(hidden_dim, 1)
        self.frame_reg = nn.ModuleList(
            mlp([hidden_dim, hidden_dim, hidden_dim, hidden_dim, 7]) for _ in range(self.num_frames)
        )
        self.joint_reg = mlp(
            [hidden_dim * (self.num_frames + 1), hidden_dim, hidden_dim, hidden_dim, 7]
        )
        for head in [self.joint_reg, *self.frame_reg]:
            nn.init.normal_(head[-1].weight, std=0.001)
            nn.init.zeros_(head[-1].bias)

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> MSFHead:
        settings = read_stage(cls, cfg, "MODEL.ROI_HEAD")
        common = cls.common_config(settings, model_info["class_names"])
        check_finite(cfg, "MODEL.ROI_HEAD")
        sampler, trans = settings.sampler, settings.transformer
        return cls(
            num_point_features=model_info["num_rawpoint_features"],
            num_frames=settings.num_frames,
            num_points=sampler.num_points,
            gamma=sampler.gamma,
            radius_growth=sampler.radius_growth,
            hidden_dim=trans.hidden_dim,
            nheads=trans.nheads,
            point_nheads=trans.point_nheads,
            enc_layers=trans.enc_layers,
            bifa_layers=trans.bifa_layers,
            dim_feedforward=trans.dim_feedforward,
            dropout=trans.dropout,
            embed_dim=settings.embed_dim,
            **common,
        )

    # ------------------------------------------------------------------ released checkpoints
    def openpcdet_names(self) -> dict:
        """This head's ``state_dict`` keys -> the names the MSF repository's ``MSFHead`` gives
        the same tensors (skyhehe123/MSF, ``pcdet/models/roi_heads/msf_head.py`` and
        ``pcdet/models/model_utils/msf_utils.py``; its detector saves the head as ``roi_head``).

        Every tensor has one counterpart; the query tokens are ``(T, 1, C)`` there. The names say
        nothing of the forward: the released BiFA groups points otherwise (module docstring).
        """

        def mlp_layers(ours: str, theirs: str, mlp: nn.Sequential) -> dict[str, str]:
            linear = [i for i, m in enumerate(mlp) if isinstance(m, nn.Linear)]
            return {f"{ours}.{i}": f"{theirs}.layers.{k}" for k, i in enumerate(linear)}

        modules = {
            **mlp_layers("geometry_embed", "up_dimension_geometry", self.geometry_embed),
            **mlp_layers("motion_embed", "up_dimension_motion", self.motion_embed),
            **mlp_layers("joint_reg", "jointembed", self.joint_reg),
            **{
                k: v
                for f, reg in enumerate(self.frame_reg)
                for k, v in mlp_layers(f"frame_reg.{f}", f"bbox_embed.{f}", reg).items()
            },
            "class_embed": "class_embed.0",
            "trajectory.input_norm": "seqboxembed.pre_bn",
            "trajectory.fc.0": "seqboxembed.fc1",
            "trajectory.fc.1": "seqboxembed.bn1",
            "trajectory.fc.3": "seqboxembed.fc2",
            "trajectory.fc.4": "seqboxembed.bn2",
            **{f"trajectory.convs.{k}": f"seqboxembed.feat.conv{k + 1}" for k in range(4)},
            **{f"trajectory.norms.{k}": f"seqboxembed.feat.bn{k + 1}" for k in range(4)},
        }
        for ours, theirs in (("center", "fc_ce"), ("size", "fc_s"), ("heading", "fc_hr")):
            modules[f"trajectory.{ours}.0"] = f"seqboxembed.{theirs}1"
            modules[f"trajectory.{ours}.2"] = f"seqboxembed.{theirs}2"
        block = {  # one encoder layer: the point mixer, the token's attention, BiFA
            "point_attn": "mlp_mixer_3d.mixer", "point_norm1": "mlp_mixer_3d.norm",
            "point_norm2": "mlp_mixer_3d.norm_channel", "point_ffn.0": "mlp_mixer_3d.ffn.0",
            "point_ffn.3": "mlp_mixer_3d.ffn.3", "token_attn": "self_attn",
            "token_norm1": "norm1", "token_norm2": "norm2", "token_ffn.0": "linear1",
            "token_ffn.3": "linear2", "forward_fuse": "cross_conv_1",
            "forward_norm": "cross_norm_1", "backward_fuse": "cross_conv_2",
            "backward_norm": "cross_norm_2",
        }  # fmt: skip
        for layer in range(len(self.transformer.layers)):
            for ours, theirs in block.items():
                modules[f"transformer.layers.{layer}.{ours}"] = (
                    f"transformer.encoder.layers.{layer}.{theirs}"
                )
        names: dict = {}
        for key in self.state_dict():
            if key == "transformer.token":  # (T, 1, 1, C) here
                frames, dim = self.transformer.token.shape[0], self.transformer.token.shape[-1]
                names[key] = Reshaped(key, (frames, 1, dim))
                continue
            theirs = renamed(key, modules)
            if theirs is None:
                raise ValueError(f"MSFHead: no released name for {key}")
            names[key] = theirs
        return names

    def openpcdet_hint(self, missing: Sequence[str], unexpected: Sequence[str]) -> str | None:
        """Why a released checkpoint does not fit, where the released code explains it."""
        if any(".cross_conv_" in k or ".cross_norm_" in k for k in missing):
            return (
                "the released code builds BiFA's cross_conv_* / cross_norm_* only in encoder "
                "layers whose class-wide counter is at most enc_layers - 1, i.e. in the first "
                "model built in a process, and a checkpoint without them ran no BiFA: set "
                "MODEL.ROI_HEAD.TRANSFORMER.BIFA_LAYERS 0"
            )
        if self.num_frames != 4 and any(".bbox_embed." in k for k in [*missing, *unexpected]):
            return (
                "the released MSF is written for 4 frames (num_groups 4, its BiFA reshape and "
                "token split hard-code 4): there is no released counterpart of "
                f"NUM_FRAMES={self.num_frames}"
            )
        return None

    # ------------------------------------------------------------------ features
    def forward(self, batch: dict) -> dict:
        valid = batch["roi_valid"]
        trajectories = batch["trajectories"]  # (B, T, R, 7); frame 0 holds the ROIs
        batch_size, num_frames, num_rois = trajectories.shape[:3]
        if num_frames != self.num_frames:
            raise ValueError(
                f"MSFHead: {num_frames} trajectory frames for NUM_FRAMES={self.num_frames}"
            )
        pts, pts_valid = sample_batch_points(  # (B, R, T, K, C), (B, R, T, K)
            batch["points"],
            trajectories,
            batch["generators"],
            num_sample=self.num_points,
            gamma=self.gamma,
            radius_growth=self.radius_growth,
        )
        num = batch_size * num_rois
        # frame-major from here on, as the transformer reads them: (T, N, K, C), (T, N, 7)
        pts = pts.reshape(num, num_frames, self.num_points, -1).transpose(0, 1).contiguous()
        keep = pts_valid.reshape(num, num_frames, self.num_points).transpose(0, 1)
        keep = keep & valid.reshape(1, num, 1)  # empty slots and ROIs: 0
        boxes = trajectories.transpose(0, 1).reshape(num_frames, num, -1)
        lag = 0.1 * torch.arange(num_frames, dtype=pts.dtype, device=pts.device)
        time = torch.stack([torch.zeros_like(lag), torch.zeros_like(lag), lag], -1)  # (T, 3)
        # geometry: offsets to frame i's box, intensity, elongation; motion: offsets to the
        # current box, two zero channels and the frame's time (the released code's inputs)
        geometry = spherical_offsets(pts[..., 0:3], boxes, pts[..., 3:])
        motion = spherical_offsets(pts[..., 0:3], boxes[:1], time[:, None, None])
        src = self.geometry_embed(geometry) + self.motion_embed(motion)
        src.mul_(keep[..., None])  # in place: no second (T, N, K, C) tensor
        box_code, box_feat = self.trajectory(trajectory_sequence(boxes.transpose(0, 1)))
        tokens = self.transformer(src)  # per layer (T, N, C)
        last = tokens[-1]
        joint = self.joint_reg(torch.cat([last.transpose(0, 1).reshape(num, -1), box_feat], 1))
        batch = dict(batch)
        batch["rcnn_cls"] = [self.class_embed(t[0]).reshape(batch_size, num_rois) for t in tokens]
        batch["rcnn_reg"] = joint.reshape(batch_size, num_rois, 7)
        aux = [
            self.frame_reg[f](t[f]).reshape(batch_size, num_rois, 7)
            for t in tokens
            for f in range(num_frames)
        ]
        batch["aux_reg"] = aux
        batch["traj_reg"] = box_code.reshape(batch_size, num_rois, 7)
        return batch

    def default_trajectories(self, sample: int, chosen: torch.Tensor):
        """MSF's trajectories (:data:`TrajectoryFn`): each proposal moved back by its velocity,
        frame by frame."""
        del sample
        return propagate_boxes(chosen, self.num_frames), None
