"""PHiM's streaming polar backbone: intra-sector bidirectional Mamba blocks over serialized
voxels, then a global forward Mamba across the sectors of the frame (docs/model_zoo.md "PHiM").

Each frame is streamed sector by sector in increasing azimuth from the seam at ``-pi``; the
state of the inter-sector Mamba starts at zero for every frame (every sample of a batch is its
own sequence of sectors), so nothing carries over between frames or sequences.

Dimensionally decomposed operations: the voxel position enters as a sum of three per-axis
embeddings (range bin, azimuth bin within the sector, height bin) instead of a 3D positional
encoding, and the local mixing that a 3D convolution would do is the Mamba's causal 1-D
convolution along serializations that alternate between ray-major (along range, one azimuth bin
after the other, snake order) and ring-major (along azimuth, one range bin after the other).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from pcdet_atlas.config import check_known_keys
from pcdet_atlas.models.model_utils.mamba import Mamba, PackedSequences, RMSNorm, pack_sequences
from pcdet_atlas.models.model_utils.polar_grid import PolarGrid
from pcdet_atlas.models.model_utils.scatter import scatter_mean
from pcdet_atlas.registry import MODEL_STAGES

__all__ = ["BidirectionalMambaBlock", "PolarSectorMamba", "serialization_keys"]


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


@MODEL_STAGES.register()
class PolarSectorMamba(nn.Module):
    """Polar voxel features -> contextual voxel features, streamed sector by sector.

    Reads ``voxel_features`` (V, C_in), ``voxel_coords`` (V, 4) ``[b, z, a, r]`` and
    ``batch_size``; writes ``voxel_features`` (V, num_point_features).
    """

    def __init__(
        self,
        *,
        input_channels: int,
        grid: PolarGrid,
        d_model: int = 32,
        num_blocks: int = 2,
        d_state: int = 16,
        d_conv: int = 4,
        expand: int = 2,
    ):
        super().__init__()
        self.grid = grid
        nr, _, nz = grid.grid_size
        self.input_proj = nn.Linear(input_channels, d_model)
        self.pos_range = nn.Embedding(nr, d_model)
        self.pos_azimuth = nn.Embedding(grid.sector_bins, d_model)
        self.pos_height = nn.Embedding(nz, d_model)
        for emb in (self.pos_range, self.pos_azimuth, self.pos_height):
            nn.init.normal_(emb.weight, std=0.02)
        self.blocks = nn.ModuleList(
            BidirectionalMambaBlock(d_model, d_state=d_state, d_conv=d_conv, expand=expand)
            for _ in range(num_blocks)
        )
        self.sector_norm = RMSNorm(d_model)
        self.sector_mamba = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand)
        self.sector_proj = nn.Linear(d_model, d_model)
        self.out_norm = nn.LayerNorm(d_model)
        self.num_point_features = d_model

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> PolarSectorMamba:
        check_known_keys(
            cfg, ["NAME", "D_MODEL", "NUM_BLOCKS", "D_STATE", "D_CONV", "EXPAND"],
            "MODEL.BACKBONE_3D",
        )  # fmt: skip
        grid = model_info.get("polar_grid")
        if grid is None:
            raise ValueError("PolarSectorMamba needs a polar VFE (MODEL.VFE.NAME: PolarVFE)")
        return cls(
            input_channels=model_info["num_point_features"],
            grid=grid,
            d_model=int(cfg.get("D_MODEL", 32)),
            num_blocks=int(cfg.get("NUM_BLOCKS", 2)),
            d_state=int(cfg.get("D_STATE", 16)),
            d_conv=int(cfg.get("D_CONV", 4)),
            expand=int(cfg.get("EXPAND", 2)),
        )

    def forward(self, batch_dict: dict) -> dict:
        feats = batch_dict["voxel_features"]  # (V, C_in)
        coords = batch_dict["voxel_coords"]  # (V, 4) b, z, a, r
        B, S = int(batch_dict["batch_size"]), self.grid.num_sectors
        sector = coords[:, 2] // self.grid.sector_bins
        seq = coords[:, 0] * S + sector  # (V,) one sequence per (sample, sector)
        x = (
            self.input_proj(feats)
            + self.pos_range(coords[:, 3])
            + self.pos_azimuth(coords[:, 2] % self.grid.sector_bins)
            + self.pos_height(coords[:, 1])
        )  # (V, d)
        if x.shape[0]:
            orders = [
                pack_sequences(seq, key, B * S) for key in serialization_keys(coords, self.grid)
            ]
            for i, block in enumerate(self.blocks):
                x = block(x, orders[i % 2])
        # the global forward Mamba streams the frame's sectors in azimuth order: sector s
        # receives the state of sectors 0..s (an empty sector is a zero token)
        tokens = scatter_mean(x, seq, B * S).view(B, S, -1)  # (B, S, d)
        context = self.sector_mamba(self.sector_norm(tokens)).reshape(B * S, -1)  # (B*S, d)
        x = x + self.sector_proj(context).index_select(0, seq)
        batch_dict["voxel_features"] = self.out_norm(x)  # (V, d)
        return batch_dict
