"""PHiM's streaming polar backbone: intra-sector blocks of a dimensionally decomposed
convolution and a bidirectional Mamba over serialized voxels, then a global forward Mamba across
the sectors' range-band tokens (docs/model_zoo.md "PHiM").

Each frame is streamed sector by sector in increasing azimuth from the seam at ``-pi``; the
state of the inter-sector Mamba starts at zero for every frame (every sample of a batch is its
own sequence of sectors), so nothing carries over between frames or sequences.

Dimensionally decomposed operations replace the 3D convolution and the positional encoding: a
depthwise convolution split into three 1-D kernels, along range, azimuth and height, over the
sparse voxels of the sector (its azimuth step is dilated with decreasing range so that it spans
about one range cell in metres: distortion-aware), and the Mamba's causal 1-D convolution along
serializations that alternate between ray-major (along range, one azimuth bin after the other,
snake order) and ring-major (along azimuth, one range bin after the other). A voxel learns
where it is from its neighbours and the VFE's polar decorations, not from an added embedding.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import fields_of, setting
from pcdet_atlas.models.model_utils.mamba import Mamba, PackedSequences, RMSNorm, pack_sequences
from pcdet_atlas.models.model_utils.polar_grid import PolarGrid
from pcdet_atlas.models.model_utils.scatter import scatter_max, scatter_mean
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES

__all__ = [
    "BidirectionalMambaBlock",
    "DecomposedConvBlock",
    "PolarSectorMamba",
    "polar_neighbours",
    "serialization_keys",
]

#: how a sector reaches the global Mamba: the mean of its voxels, or ``mean_max`` (mean and
#: per-channel max) per range band
SECTOR_POOLS = ("mean", "mean_max")


def polar_neighbours(coords: torch.Tensor, grid: PolarGrid) -> torch.Tensor:
    """``(V, 6)`` row of each voxel's neighbour one step before and after it along range,
    azimuth and height, in that order, ``-1`` where that cell is empty or outside the sector.

    coords: ``(V, 4)`` ``[b, z, a, r]``, unique. The azimuth step of a voxel at range bin ``r``
    is ``max(1, round(dr / (r_c * da)))`` bins (``r_c`` the cell's centre range, ``dr`` and
    ``da`` the range and azimuth cell sizes), at most half a sector: the neighbour is about one
    range cell away in metres at every range.
    """
    V = coords.shape[0]
    out = coords.new_full((V, 6), -1)
    if V == 0:
        return out
    nr, _, nz = grid.grid_size
    sb = grid.sector_bins
    dr, da, _ = grid.cell_size
    b, z, a, r = coords.unbind(1)
    sector, a_in = a // sb, a % sb
    r_c = grid.range_m[0] + (r.to(torch.float64) + 0.5) * dr
    step_a = torch.round(dr / (r_c * da)).clamp(1, max(1, sb // 2)).long()  # (V,)

    def key(z_, a_, r_):
        return (((b * grid.num_sectors + sector) * nz + z_) * sb + a_) * nr + r_

    keys = key(z, a_in, r)
    sorted_keys, order = torch.sort(keys)
    for j, (axis, sign) in enumerate(
        [("r", -1), ("r", 1), ("a", -1), ("a", 1), ("z", -1), ("z", 1)]
    ):
        zq, aq, rq = z, a_in, r
        if axis == "r":
            rq = r + sign
            ok = (rq >= 0) & (rq < nr)
        elif axis == "a":
            aq = a_in + sign * step_a
            ok = (aq >= 0) & (aq < sb)
        else:
            zq = z + sign
            ok = (zq >= 0) & (zq < nz)
        q = key(zq, aq, rq)
        pos = torch.searchsorted(sorted_keys, q).clamp(max=V - 1)
        hit = ok & (sorted_keys[pos] == q)
        out[:, j] = torch.where(hit, order[pos], torch.full_like(pos, -1))
    return out


class DecomposedConvBlock(nn.Module):
    """``x + W_out silu(dwconv(norm x))``: a depthwise 3x3x3 convolution decomposed into its
    range, azimuth and height 1-D kernels (7 taps per channel: the centre and two per axis) on
    the sparse voxels, then a pointwise projection."""

    def __init__(self, d_model: int):
        super().__init__()
        self.norm = RMSNorm(d_model)
        bound = 7**-0.5  # a depthwise kernel's default bound: 1 / sqrt(fan_in)
        self.centre = nn.Parameter(torch.empty(d_model).uniform_(-bound, bound))
        self.taps = nn.Parameter(torch.empty(6, d_model).uniform_(-bound, bound))
        self.out_proj = nn.Linear(d_model, d_model)

    def forward(self, x: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        """x: (V, d) voxel rows, neighbours: (V, 6) from :func:`polar_neighbours` -> (V, d)."""
        h = self.norm(x)
        padded = torch.cat([h, h.new_zeros(1, h.shape[1])])  # row V: an empty neighbour
        idx = torch.where(neighbours < 0, h.shape[0], neighbours)  # (V, 6)
        y = h * self.centre
        for j in range(6):
            y = y + padded.index_select(0, idx[:, j]) * self.taps[j]
        return x + self.out_proj(F.silu(y))


class BidirectionalMambaBlock(nn.Module):
    """``x + Mamba_fwd(norm x) + reverse(Mamba_bwd(reverse(norm x)))`` within each sequence."""

    def __init__(self, d_model: int, *, d_state: int, d_conv: int, expand: int):
        super().__init__()
        self.norm = RMSNorm(d_model)
        self.forward_mamba = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand)
        self.backward_mamba = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand)

    def forward(self, x: torch.Tensor, packed: PackedSequences) -> torch.Tensor:
        """x: (V, d_model) voxel rows -> (V, d_model)."""
        h = self.norm(x)
        fwd = packed.from_padded(self.forward_mamba(packed.to_padded(h)))
        bwd = packed.from_padded(
            self.backward_mamba(packed.to_padded(h, reverse=True)), reverse=True
        )
        return x + fwd + bwd


def serialization_keys(coords: torch.Tensor, grid: PolarGrid) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray-major and ring-major snake keys ``(V,)`` of voxels ``[b, z, a, r]`` within their sector
    (unique per sector; height is the fastest axis in both)."""
    nr, _, nz = grid.grid_size
    ns = grid.sector_bins
    z, a, r = coords[:, 1], coords[:, 2] % ns, coords[:, 3]
    r_snake = torch.where(a % 2 == 1, nr - 1 - r, r)
    a_snake = torch.where(r % 2 == 1, ns - 1 - a, a)
    ray_major = (a * nr + r_snake) * nz + z
    ring_major = (r * ns + a_snake) * nz + z
    return ray_major, ring_major


@dataclass(frozen=True, kw_only=True)
class PolarSectorMambaConfig(StageConfig):
    """``MODEL.BACKBONE_3D`` of PolarSectorMamba."""

    d_model: int = setting(32, ge=1, doc="token width")
    num_blocks: int = setting(2, ge=1, doc="Mamba blocks per sector")
    d_state: int = setting(16, ge=1, doc="Mamba state size")
    d_conv: int = setting(4, ge=1, doc="Mamba conv width")
    expand: int = setting(2, ge=1, doc="Mamba expansion")
    decomposed_conv: bool = setting(True, doc="a polar conv before each block")
    position_embedding: bool = setting(False, doc="range, azimuth, height embeddings")
    range_tokens: int = setting(8, ge=1, doc="range-band tokens per sector")
    sector_pool: str = setting(
        "mean_max", choices=("mean", "mean_max"), doc="pooling of a band's voxels"
    )


@MODEL_STAGES.register()
class PolarSectorMamba(nn.Module):
    """Polar voxel features -> contextual voxel features, streamed sector by sector.

    Reads ``voxel_features`` (V, C_in), ``voxel_coords`` (V, 4) ``[b, z, a, r]`` and
    ``batch_size``; writes ``voxel_features`` (V, num_point_features).
    """

    CONFIG = PolarSectorMambaConfig

    def __init__(
        self,
        *,
        input_channels: int,
        grid: PolarGrid,
        d_model: int = PolarSectorMambaConfig.d_model,
        num_blocks: int = PolarSectorMambaConfig.num_blocks,
        d_state: int = PolarSectorMambaConfig.d_state,
        d_conv: int = PolarSectorMambaConfig.d_conv,
        expand: int = PolarSectorMambaConfig.expand,
        decomposed_conv: bool = PolarSectorMambaConfig.decomposed_conv,
        position_embedding: bool = PolarSectorMambaConfig.position_embedding,
        range_tokens: int = PolarSectorMambaConfig.range_tokens,
        sector_pool: str = PolarSectorMambaConfig.sector_pool,
    ):
        """
        Args:
            decomposed_conv: a :class:`DecomposedConvBlock` before every Mamba block.
            position_embedding: add per-axis (range, azimuth in sector, height) embeddings to
                the input instead (the checkpoints trained before the decomposed convolution).
            range_tokens: tokens per sector for the global Mamba, one per equal band of range
                bins, streamed sector by sector, near to far inside a sector.
            sector_pool: ``mean_max`` (a token is the projected mean and max of its band's
                voxels) or ``mean`` (the mean alone, with one token per sector).
        """
        super().__init__()
        nr, _, nz = grid.grid_size
        if sector_pool not in SECTOR_POOLS:
            raise ValueError(f"PolarSectorMamba: sector_pool must be one of {SECTOR_POOLS}")
        if not 1 <= range_tokens <= nr or (sector_pool == "mean" and range_tokens != 1):
            raise ValueError(
                f"PolarSectorMamba: range_tokens must lie in [1, {nr}] (1 with the mean pool), "
                f"got {range_tokens}"
            )
        self.grid = grid
        self.range_tokens = int(range_tokens)
        self.sector_pool = sector_pool
        self.input_proj = nn.Linear(input_channels, d_model)
        if position_embedding:
            self.pos_range = nn.Embedding(nr, d_model)
            self.pos_azimuth = nn.Embedding(grid.sector_bins, d_model)
            self.pos_height = nn.Embedding(nz, d_model)
            for emb in (self.pos_range, self.pos_azimuth, self.pos_height):
                nn.init.normal_(emb.weight, std=0.02)
        self.position_embedding = position_embedding
        self.conv_blocks = (
            nn.ModuleList(DecomposedConvBlock(d_model) for _ in range(num_blocks))
            if decomposed_conv
            else None
        )
        self.blocks = nn.ModuleList(
            BidirectionalMambaBlock(d_model, d_state=d_state, d_conv=d_conv, expand=expand)
            for _ in range(num_blocks)
        )
        if sector_pool == "mean_max":
            self.token_proj = nn.Linear(2 * d_model, d_model)
        self.sector_norm = RMSNorm(d_model)
        self.sector_mamba = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand)
        self.sector_proj = nn.Linear(d_model, d_model)
        self.out_norm = nn.LayerNorm(d_model)
        self.num_point_features = d_model

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> PolarSectorMamba:
        settings = read_stage(cls, cfg, "MODEL.BACKBONE_3D")
        grid = model_info.get("polar_grid")
        if grid is None:
            raise ValueError("PolarSectorMamba needs a polar VFE (MODEL.VFE.NAME: PolarVFE)")
        kwargs = fields_of(settings)
        del kwargs["name"]
        try:
            return cls(input_channels=model_info["num_point_features"], grid=grid, **kwargs)
        except ValueError as err:
            raise ConfigError(f"MODEL.BACKBONE_3D: {err}") from err

    def forward(self, batch_dict: dict) -> dict:
        feats = batch_dict["voxel_features"]  # (V, C_in)
        coords = batch_dict["voxel_coords"]  # (V, 4) b, z, a, r
        B, S, T = int(batch_dict["batch_size"]), self.grid.num_sectors, self.range_tokens
        sector = coords[:, 2] // self.grid.sector_bins
        seq = coords[:, 0] * S + sector  # (V,) one sequence per (sample, sector)
        x = self.input_proj(feats)  # (V, d)
        if self.position_embedding:
            x = (
                x
                + self.pos_range(coords[:, 3])
                + self.pos_azimuth(coords[:, 2] % self.grid.sector_bins)
                + self.pos_height(coords[:, 1])
            )
        if x.shape[0]:
            neighbours = polar_neighbours(coords, self.grid) if self.conv_blocks else None
            orders = [
                pack_sequences(seq, key, B * S) for key in serialization_keys(coords, self.grid)
            ]
            for i, block in enumerate(self.blocks):
                if self.conv_blocks is not None:
                    x = self.conv_blocks[i](x, neighbours)
                x = block(x, orders[i % 2])
        # the global forward Mamba streams the frame's sectors in azimuth order, each as T
        # range-band tokens near to far: a voxel receives the state of the sectors before its
        # own and of its sector's bands up to its own (an empty band is a zero token)
        band = coords[:, 3] * T // self.grid.grid_size[0]
        token = seq * T + band  # (V,)
        mean = scatter_mean(x, token, B * S * T)  # (B*S*T, d)
        if self.sector_pool == "mean_max":
            tokens = self.token_proj(torch.cat([mean, scatter_max(x, token, B * S * T)], 1))
        else:
            tokens = mean
        context = self.sector_mamba(self.sector_norm(tokens.view(B, S * T, -1)))
        x = x + self.sector_proj(context.reshape(B * S * T, -1)).index_select(0, token)
        batch_dict["voxel_features"] = self.out_norm(x)  # (V, d)
        return batch_dict
