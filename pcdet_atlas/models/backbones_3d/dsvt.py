"""DSVT: Dynamic Sparse Voxel Transformer with rotated sets (Wang et al., CVPR 2023), pure torch.

Voxels attend to each other inside equal-size sets cut from their window
(:func:`~pcdet_atlas.models.model_utils.dsvt_utils.set_partition`); the two encoder layers of a
block use the y-major and then the x-major partition (rotated sets), and consecutive blocks
alternate between the plain windows and larger windows shifted by half a window (shift 0:
``window_shape``, shift 1: ``window_shape * hybrid_factor`` offset by ``shifts_list``). Between
stages, DSVT-V pools voxels along z with attention (:class:`Stage_ReductionAtt_Block`): the
max over a pooling cell is the query of an attention over the cell's positions. DSVT-P is the
one-stage form (pillars, no pooling).

Module and parameter names are those of OpenPCDet's ``backbones_3d/dsvt.py``, so that an
OpenPCDet DSVT checkpoint loads as it is (docs/model_zoo.md says how closely the computation
matches).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint

from pcdet_atlas.config_values import as_lists, setting
from pcdet_atlas.models.model_utils.dsvt_utils import (
    PositionEmbeddingLearned,
    pooling_index,
    set_key_mask,
    set_partition,
    window_coords,
)
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES

ACTIVATIONS = {"relu": F.relu, "gelu": F.gelu}
NUM_SHIFTS = 2


class SetAttention(nn.Module):
    """Multi-head self-attention inside each set, then a feed-forward layer (post-norm)."""

    def __init__(
        self, d_model: int, nhead: int, dropout: float, dim_feedforward: int, activation: str
    ):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d_model, nhead, dropout=dropout, batch_first=True)
        self.linear1 = nn.Linear(d_model, dim_feedforward)
        self.linear2 = nn.Linear(dim_feedforward, d_model)
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)
        self.d_model = d_model
        self.activation = ACTIVATIONS[activation]

    def forward(
        self,
        src: torch.Tensor,
        pos: torch.Tensor,
        key_padding_mask: torch.Tensor,
        voxel_inds: torch.Tensor,
    ) -> torch.Tensor:
        """src, pos: (N, C); key_padding_mask, voxel_inds: (S, T) sets of T voxels -> (N, C)."""
        set_feats = src[voxel_inds]  # (S, T, C)
        qk = set_feats + pos[voxel_inds]
        out = self.self_attn(qk, qk, set_feats, key_padding_mask=key_padding_mask)[0]
        # back to voxels: a voxel repeated to fill a window's sets (its copies sit in one set,
        # next to each other) takes the output of its first occurrence, as the released code does
        flat = voxel_inds.reshape(-1)
        first = torch.full((src.shape[0],), flat.numel(), dtype=torch.long, device=src.device)
        first = first.scatter_reduce(
            0, flat, torch.arange(flat.numel(), device=src.device), reduce="amin"
        )
        src = self.norm1(src + out.reshape(-1, self.d_model)[first])
        return self.norm2(src + self.linear2(self.activation(self.linear1(src))))


class DSVT_EncoderLayer(nn.Module):  # noqa: N801  (OpenPCDet's name)
    """Set attention with a residual connection and a LayerNorm around it."""

    def __init__(
        self, d_model: int, nhead: int, dim_feedforward: int, dropout: float, activation: str
    ):
        super().__init__()
        self.win_attn = SetAttention(d_model, nhead, dropout, dim_feedforward, activation)
        self.norm = nn.LayerNorm(d_model)

    def forward(self, src, set_voxel_inds, set_voxel_masks, pos):
        return self.norm(src + self.win_attn(src, pos, set_voxel_masks, set_voxel_inds))


class DSVTBlock(nn.Module):
    """Two encoder layers: the y-major sets, then the x-major sets of one shift."""

    def __init__(
        self, d_model: int, nhead: int, dim_feedforward: int, dropout: float, activation: str
    ):
        super().__init__()
        self.encoder_list = nn.ModuleList(
            DSVT_EncoderLayer(d_model, nhead, dim_feedforward, dropout, activation)
            for _ in range(2)
        )

    def forward(
        self,
        src: torch.Tensor,
        set_voxel_inds_list: Sequence[torch.Tensor],
        set_voxel_masks_list: Sequence[torch.Tensor],
        pos_embed_list: Sequence[torch.Tensor],
        block_id: int,
    ) -> torch.Tensor:
        """``set_voxel_*_list[shift]``: (2, S, T) per shift; ``pos_embed_list[i]``: (N, C).

        Block ``block_id`` uses shift ``block_id % 2``. Encoder ``i`` takes position embedding
        ``i`` (computed in shift ``i``'s windows) whatever the shift: the released code's
        pairing, kept so that its checkpoints compute what they were trained to.
        """
        shift = block_id % NUM_SHIFTS
        for i, layer in enumerate(self.encoder_list):
            src = layer(
                src, set_voxel_inds_list[shift][i], set_voxel_masks_list[shift][i],
                pos_embed_list[i],
            )  # fmt: skip
        return src


class Stage_ReductionAtt_Block(nn.Module):  # noqa: N801  (OpenPCDet's name)
    """DSVT-V's attention-style 3D pooling: the max over a pooling cell queries the cell's
    ``pool_volume`` positions (empty ones hold zeros), with a learned embedding per position."""

    def __init__(self, input_channel: int, pool_volume: int):
        super().__init__()
        self.pool_volume = pool_volume
        self.norm = nn.LayerNorm(input_channel)
        self.self_attn = nn.MultiheadAttention(input_channel, 8, batch_first=True)
        self.pos_embedding = nn.Parameter(torch.randn(pool_volume, input_channel))
        nn.init.normal_(self.pos_embedding, std=0.01)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (M, V, C) features at the V positions of M cells -> (M, C)."""
        query = x.amax(dim=1, keepdim=True)  # (M, 1, C)
        key = x + self.pos_embedding[None]
        out = self.self_attn(query, key, x)[0]
        return self.norm(out + query).squeeze(1)


class DSVTInputLayer(nn.Module):
    """Windows, sets, pooling cells and position embeddings of every stage and shift.

    Everything but the position embeddings is index bookkeeping without gradients.
    """

    def __init__(
        self,
        *,
        sparse_shape: Sequence[int],
        window_shape: Sequence[Sequence[int]],
        downsample_stride: Sequence[Sequence[int]],
        d_model: Sequence[int],
        set_info: Sequence[Sequence[int]],
        hybrid_factor: Sequence[int],
        shifts_list: Sequence[Sequence[Sequence[int]]],
        normalize_pos: bool = False,
    ):
        super().__init__()
        self.stage_num = len(d_model)
        for name, value in (("window_shape", window_shape), ("set_info", set_info),
                            ("shifts_list", shifts_list)):  # fmt: skip
            if len(value) != self.stage_num:
                raise ValueError(
                    f"DSVT INPUT_LAYER.{name} needs one entry per stage ({self.stage_num}, "
                    f"the length of d_model), got {len(value)}"
                )
        if len(downsample_stride) != self.stage_num - 1:
            raise ValueError(
                f"DSVT INPUT_LAYER.downsample_stride needs {self.stage_num - 1} entries (one "
                f"between consecutive stages), got {len(downsample_stride)}"
            )
        self.set_info = [tuple(int(v) for v in s) for s in set_info]
        self.d_model = [int(v) for v in d_model]
        self.downsample_stride = [tuple(int(v) for v in s) for s in downsample_stride]
        #: per stage, the window of shift 0 and the larger one of shift 1
        self.window_shape = [
            [tuple(int(v) for v in w), tuple(int(v) * int(h) for v, h in zip(w, hybrid_factor))]
            for w in window_shape
        ]
        self.shift_list = [[tuple(int(v) for v in s) for s in shifts] for shifts in shifts_list]
        self.normalize_pos = bool(normalize_pos)
        self.sparse_shape_list = [tuple(int(v) for v in sparse_shape)]
        for stride in self.downsample_stride:
            last = self.sparse_shape_list[-1]
            self.sparse_shape_list.append(tuple(math.ceil(n / s) for n, s in zip(last, stride)))
        self.posembed_layers = nn.ModuleList()
        for s in range(self.stage_num):
            dim = 3 if self.sparse_shape_list[s][2] > 1 else 2
            for win in self.window_shape[s]:
                if (win[2] > 1) != (dim == 3):
                    raise ValueError(
                        f"DSVT stage {s}: window {win} and a grid of {self.sparse_shape_list[s][2]}"
                        " z layers disagree (a 3D window needs z layers, a 2D one a single one)"
                    )
            self.posembed_layers.append(
                nn.ModuleList(
                    nn.ModuleList(
                        PositionEmbeddingLearned(dim, self.d_model[s]) for _ in range(NUM_SHIFTS)
                    )
                    for _ in range(self.set_info[s][1])
                )
            )

    def forward(self, voxel_coords: torch.Tensor) -> dict:
        """voxel_coords: (N, 4) ``[b, z, y, x]`` of stage 0 -> per stage ``coords`` (N_s, 4),
        ``set_voxel_inds`` / ``set_voxel_masks`` (one (2, S, T) per shift), ``pos_embed``
        ([block][shift] (N_s, C)), and between stages ``pool_cell`` / ``pool_index``."""
        coords = voxel_coords.long()
        stages = []
        for s in range(self.stage_num):
            info: dict = {"coords": coords, "set_voxel_inds": [], "set_voxel_masks": []}
            in_win = []
            for shift in range(NUM_SHIFTS):
                win = self.window_shape[s][shift]
                batch_win, coors_in_win = window_coords(
                    coords, self.sparse_shape_list[s], win, self.shift_list[s][shift]
                )
                inds = set_partition(batch_win, coors_in_win, win, self.set_info[s][0])
                info["set_voxel_inds"].append(inds)
                info["set_voxel_masks"].append(set_key_mask(inds))
                in_win.append(coors_in_win)
            info["pos_embed"] = [
                [self.get_pos_embed(in_win[shift], s, b, shift) for shift in range(NUM_SHIFTS)]
                for b in range(self.set_info[s][1])
            ]
            if s < self.stage_num - 1:
                cell, index, coords = pooling_index(
                    coords, self.sparse_shape_list[s], self.downsample_stride[s]
                )
                info["pool_cell"], info["pool_index"] = cell, index
            stages.append(info)
        return {"stages": stages, "voxel_coords": coords}

    def get_pos_embed(
        self, coors_in_win: torch.Tensor, stage_id: int, block_id: int, shift_id: int
    ) -> torch.Tensor:
        """(N, 3) ``[z, y, x]`` in the window -> (N, C): the position relative to the window's
        centre, ``(x, y)`` or ``(x, y, z)``."""
        wx, wy, wz = self.window_shape[stage_id][shift_id]
        ndim = 2 if wz == 1 else 3
        wz = 0 if wz == 1 else wz
        c = coors_in_win.float()
        z, y, x = c[:, 0] - wz / 2, c[:, 1] - wy / 2, c[:, 2] - wx / 2
        if self.normalize_pos:  # the released constant
            x, y = x / wx * 2 * 3.1415, y / wy * 2 * 3.1415
            z = z / wz * 2 * 3.1415 if ndim == 3 else z
        location = torch.stack((x, y) if ndim == 2 else (x, y, z), dim=-1)
        return self.posembed_layers[stage_id][block_id][shift_id](location)


_Ints = tuple[int, ...]


@dataclass(frozen=True, kw_only=True)
class DSVTInputLayerConfig:
    """``MODEL.BACKBONE_3D.INPUT_LAYER`` (OpenPCDet's lower-case keys)."""

    sparse_shape: tuple[int, int, int] = setting(
        key="sparse_shape", ge=1, doc="the VFE's grid [nx, ny, nz]"
    )
    downsample_stride: tuple[_Ints, ...] = setting(
        key="downsample_stride", ge=1, doc="per stage transition, [sx, sy, sz]"
    )
    d_model: _Ints = setting(key="d_model", ge=1, doc="width per stage")
    set_info: tuple[_Ints, ...] = setting(key="set_info", ge=1, doc="[set size, blocks] per stage")
    window_shape: tuple[_Ints, ...] = setting(
        key="window_shape", ge=1, doc="window [x, y, z] per stage"
    )
    hybrid_factor: _Ints = setting(key="hybrid_factor", ge=1, doc="shifted windows' scale x, y, z")
    shifts_list: tuple[tuple[_Ints, ...], ...] = setting(
        key="shifts_list", doc="window shifts per stage"
    )
    normalize_pos: bool = setting(False, key="normalize_pos", doc="normalise the positions")


@dataclass(frozen=True, kw_only=True)
class DSVTConfig(StageConfig):
    """``MODEL.BACKBONE_3D`` of DSVT (OpenPCDet's keys)."""

    input_layer: DSVTInputLayerConfig = setting(doc="voxel sets and windows per stage")
    block_name: tuple[str, ...] = setting(
        key="block_name", choices=("DSVTBlock",), doc="one DSVTBlock per stage"
    )
    set_info: tuple[_Ints, ...] = setting(key="set_info", ge=1, doc="[set size, blocks] per stage")
    d_model: _Ints = setting(key="d_model", ge=1, doc="width per stage")
    nhead: _Ints = setting(key="nhead", ge=1, doc="attention heads per stage")
    dim_feedforward: _Ints = setting(key="dim_feedforward", ge=1, doc="feed-forward width")
    dropout: float = setting(0.0, key="dropout", ge=0, lt=1, doc="dropout")
    activation: str = setting("gelu", key="activation", doc="feed-forward activation")
    reduction_type: str = setting("attention", key="reduction_type", doc="pooling between stages")
    output_shape: tuple[int, int] = setting(key="output_shape", ge=1, doc="BEV grid [nx, ny]")
    conv_out_channel: int = setting(key="conv_out_channel", ge=1, doc="output width")
    use_checkpoint: bool = setting(False, doc="activation checkpointing in training")


@MODEL_STAGES.register()
class DSVT(nn.Module):
    """Reads ``voxel_features`` (N, d_model[0]) and ``voxel_coords`` (N, 4) ``[b, z, y, x]`` on
    the VFE's grid; writes ``pillar_features`` = ``voxel_features`` (M, d_model[-1]) and
    ``voxel_coords`` (M, 4) of the last stage (z = 0 where the stages pooled z to one layer)."""

    CONFIG = DSVTConfig

    def __init__(
        self,
        *,
        input_layer: DSVTInputLayer,
        set_info: Sequence[Sequence[int]],
        d_model: Sequence[int],
        nhead: Sequence[int],
        dim_feedforward: Sequence[int],
        dropout: float = DSVTConfig.dropout,
        activation: str = DSVTConfig.activation,
        reduction_type: str = DSVTConfig.reduction_type,
        output_shape: Sequence[int],
        conv_out_channel: int,
        use_checkpoint: bool = DSVTConfig.use_checkpoint,
    ):
        """
        Args:
            input_layer: the index bookkeeping (its sizes must agree with these).
            set_info: per stage ``[set_size, num_blocks]``.
            d_model / nhead / dim_feedforward: per stage widths and heads.
            reduction_type: pooling between stages; only DSVT-V's ``'attention'``.
            output_shape: ``(nx, ny)`` of the last stage's grid (checked).
            conv_out_channel: the output width (must be ``d_model[-1]``).
            use_checkpoint: recompute the blocks in backward (less memory, more time).
        """
        super().__init__()
        self.input_layer = input_layer
        stage_num = len(d_model)
        for name, value in (("set_info", set_info), ("nhead", nhead),
                            ("dim_feedforward", dim_feedforward)):  # fmt: skip
            if len(value) != stage_num:
                raise ValueError(
                    f"DSVT {name} needs one entry per stage ({stage_num}), got {len(value)}"
                )
        if [tuple(int(v) for v in s) for s in set_info] != input_layer.set_info:
            raise ValueError(
                f"DSVT set_info {list(set_info)} differs from INPUT_LAYER.set_info "
                f"{input_layer.set_info}"
            )
        if [int(v) for v in d_model] != input_layer.d_model:
            raise ValueError(f"DSVT d_model {list(d_model)} differs from INPUT_LAYER.d_model")
        if activation not in ACTIVATIONS:
            raise ValueError(f"DSVT activation must be one of {sorted(ACTIVATIONS)}")
        if reduction_type != "attention":
            raise ValueError(
                f"DSVT reduction_type {reduction_type!r}: only 'attention' (DSVT-V's pooling) "
                "is implemented"
            )
        last = input_layer.sparse_shape_list[-1]
        if tuple(int(v) for v in output_shape) != last[:2] or last[2] != 1:
            raise ValueError(
                f"DSVT output_shape {list(output_shape)}: the last stage's grid is {list(last)}; "
                "expected output_shape [nx, ny] of it and a single z layer"
            )
        if int(conv_out_channel) != int(d_model[-1]):
            raise ValueError(
                f"DSVT conv_out_channel ({conv_out_channel}) must equal d_model[-1] "
                f"({d_model[-1]}): the blocks' output is the backbone's output"
            )
        for s in range(stage_num):
            self.add_module(
                f"stage_{s}",
                nn.ModuleList(
                    DSVTBlock(d_model[s], nhead[s], dim_feedforward[s], dropout, activation)
                    for _ in range(set_info[s][1])
                ),
            )
            self.add_module(
                f"residual_norm_stage_{s}",
                nn.ModuleList(nn.LayerNorm(d_model[s]) for _ in range(set_info[s][1])),
            )
            if s < stage_num - 1:
                if d_model[s + 1] != d_model[s]:
                    raise ValueError("DSVT attention pooling keeps the width: d_model must agree")
                volume = math.prod(input_layer.downsample_stride[s])
                self.add_module(
                    f"stage_{s}_reduction", Stage_ReductionAtt_Block(d_model[s], volume)
                )
        self.stage_num = stage_num
        self.use_torch_ckpt = bool(use_checkpoint)
        self.num_point_features = int(conv_out_channel)
        strides = {(sx, sy) for sx, sy, _ in input_layer.downsample_stride}
        xy = [math.prod(s[i] for s in input_layer.downsample_stride) for i in (0, 1)]
        if xy[0] != xy[1]:
            raise ValueError(f"DSVT downsample_stride must pool x and y alike, got {strides}")
        #: voxels per output cell along x and y
        self.output_stride = xy[0]
        for p in self.parameters():  # the released initialisation
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> DSVT:
        settings = read_stage(cls, cfg, "MODEL.BACKBONE_3D")
        il = settings.input_layer
        grid = tuple(int(v) for v in model_info["grid_size"])
        if il.sparse_shape != grid:
            raise ValueError(
                f"DSVT INPUT_LAYER.sparse_shape {list(il.sparse_shape)} differs from the "
                f"VFE's grid {list(grid)} (POINT_CLOUD_RANGE / VOXEL_SIZE)"
            )
        if model_info["num_point_features"] != settings.d_model[0]:
            raise ValueError(
                f"DSVT d_model[0] ({settings.d_model[0]}) must equal the VFE output width "
                f"({model_info['num_point_features']})"
            )
        input_layer = DSVTInputLayer(
            sparse_shape=as_lists(il.sparse_shape),
            window_shape=as_lists(il.window_shape),
            downsample_stride=as_lists(il.downsample_stride),
            d_model=as_lists(il.d_model),
            set_info=as_lists(il.set_info),
            hybrid_factor=as_lists(il.hybrid_factor),
            shifts_list=as_lists(il.shifts_list),
            normalize_pos=il.normalize_pos,
        )
        return cls(
            input_layer=input_layer,
            set_info=as_lists(settings.set_info),
            d_model=as_lists(settings.d_model),
            nhead=as_lists(settings.nhead),
            dim_feedforward=as_lists(settings.dim_feedforward),
            dropout=settings.dropout,
            activation=settings.activation,
            reduction_type=settings.reduction_type,
            output_shape=as_lists(settings.output_shape),
            conv_out_channel=settings.conv_out_channel,
            use_checkpoint=settings.use_checkpoint,
        )

    def forward(self, batch_dict: dict) -> dict:
        feats = batch_dict["voxel_features"]  # (N, C)
        info = self.input_layer(batch_dict["voxel_coords"])
        output = feats
        block_id = 0
        for s, stage in enumerate(info["stages"]):
            blocks = getattr(self, f"stage_{s}")
            norms = getattr(self, f"residual_norm_stage_{s}")
            for b, (block, norm) in enumerate(zip(blocks, norms)):
                args = (stage["set_voxel_inds"], stage["set_voxel_masks"], stage["pos_embed"][b])
                if self.use_torch_ckpt and self.training:
                    out = checkpoint(block, output, *args, block_id, use_reentrant=False)
                else:
                    out = block(output, *args, block_id)
                output = norm(out + output)
                block_id += 1
            if s < self.stage_num - 1:
                reduction = getattr(self, f"stage_{s}_reduction")
                cells = int(stage["pool_cell"].max()) + 1 if output.shape[0] else 0
                prepool = output.new_zeros(cells, reduction.pool_volume, output.shape[1])
                prepool = prepool.index_put((stage["pool_cell"], stage["pool_index"]), output)
                output = reduction(prepool)  # (M, C)
        batch_dict["pillar_features"] = batch_dict["voxel_features"] = output
        batch_dict["voxel_coords"] = info["voxel_coords"]
        return batch_dict
