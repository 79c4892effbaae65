"""CenterFormer's centre queries and their transformer (ECCV'22), in plain batched torch.

The top-K cells of a centre heatmap become queries (in training the ground-truth centre cells are
put first, so that every object has a query); each query reads its own feature, attends to the
other queries, and cross-attends to a ``k x k`` window of cells around it on each level of a
multi-scale BEV feature pyramid (the non-deformable form of CenterFormer's released
``RPN_transformer``). Positions are cells of the query map (the finest level), embedded by one
shared linear layer for queries and keys.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

__all__ = [
    "select_center_queries",
    "neighbour_cells",
    "gather_neighbours",
    "CrossAttention",
    "CenterTransformer",
]


def select_center_queries(
    scores: torch.Tensor, num_queries: int, gt_inds: torch.Tensor | None = None,
    gt_mask: torch.Tensor | None = None,
) -> torch.Tensor:  # fmt: skip
    """The ``num_queries`` cells of highest score per sample (ties: lower cell first).

    Args:
        scores: (B, HW) heatmap scores in [0, 1] (the class maximum per cell).
        num_queries: K (at most HW).
        gt_inds, gt_mask: (B, M) flat ground-truth centre cells and which are real; their cells
            rank above every other cell (score + 1, CenterFormer's training rule), each once.
    Returns:
        (B, K) int64 flat cell indices, by decreasing (boosted) score.
    """
    if scores.dim() != 2:
        raise ValueError(f"scores must be (B, HW), got {tuple(scores.shape)}")
    if not 1 <= num_queries <= scores.shape[1]:
        raise ValueError(f"num_queries must be in 1..{scores.shape[1]} cells, got {num_queries}")
    ranked = scores.detach().float()
    if gt_inds is not None:
        boost = torch.zeros_like(ranked)
        # 1 at each real GT cell, once; amax: a padding slot naming the same cell cannot undo it
        boost.scatter_reduce_(1, gt_inds, gt_mask.to(ranked.dtype), reduce="amax")
        ranked = ranked + boost
    order = torch.sort(ranked, dim=1, descending=True, stable=True).indices
    return order[:, :num_queries]


def neighbour_cells(
    cells_xy: torch.Tensor, level_scale: int, kernel_size: int, level_hw: tuple[int, int]
) -> torch.Tensor:
    """The ``k x k`` window around each query on a level ``level_scale`` times coarser.

    Args:
        cells_xy: (B, K, 2) int64 ``(x, y)`` query cells on the query map.
        level_scale: query-map cells per level cell. kernel_size: k (odd).
        level_hw: (H_l, W_l) of the level; window cells beyond it are clamped onto its border
            (as CenterFormer does, so a border query reads some cells twice).
    Returns:
        (B, K, k * k, 2) int64 ``(x, y)`` level cells, the window row by row.
    """
    r = kernel_size // 2
    offs = torch.arange(-r, r + 1, device=cells_xy.device)
    oy, ox = torch.meshgrid(offs, offs, indexing="ij")
    window = torch.stack([ox.reshape(-1), oy.reshape(-1)], dim=1)  # (k*k, 2)
    centre = torch.div(cells_xy, level_scale, rounding_mode="floor")  # (B, K, 2)
    cells = centre[:, :, None, :] + window[None, None]  # (B, K, k*k, 2)
    h, w = level_hw
    return torch.stack([cells[..., 0].clamp(0, w - 1), cells[..., 1].clamp(0, h - 1)], dim=-1)


def gather_neighbours(
    cells_xy: torch.Tensor, levels: Sequence[torch.Tensor], kernel_sizes: Sequence[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Features and positions of each query's window on every level.

    Args:
        cells_xy: (B, K, 2) int64 query cells on ``levels[0]``.
        levels: maps (B, C, H_l, W_l), finest first; each level's size divides the first's.
        kernel_sizes: one odd window size per level.
    Returns:
        ``(features (B, K, N, C), positions (B, K, N, 2))`` with ``N = sum k_l^2``; a position is
        the window cell's corner in query-map cells (cell x level scale).
    """
    if len(kernel_sizes) != len(levels):
        raise ValueError(
            f"CenterFormer: {len(kernel_sizes)} cross-attention kernel sizes for "
            f"{len(levels)} feature levels; give one per level"
        )
    B, C, H0, W0 = levels[0].shape
    feats, pos = [], []
    for level, k in zip(levels, kernel_sizes):
        h, w = level.shape[-2:]
        if H0 % h or W0 % w or H0 // h != W0 // w or level.shape[1] != C:
            raise ValueError(
                f"CenterFormer: a feature level of {tuple(level.shape[1:])} does not tile the "
                f"query map {(C, H0, W0)} (same channels, sizes dividing it by one factor)"
            )
        scale = H0 // h
        cells = neighbour_cells(cells_xy, scale, int(k), (h, w))  # (B, K, k*k, 2)
        flat = (cells[..., 1] * w + cells[..., 0]).reshape(B, -1)  # (B, K*k*k)
        table = level.reshape(B, C, h * w).transpose(1, 2)  # (B, HW_l, C)
        picked = torch.gather(table, 1, flat[..., None].expand(-1, -1, C))
        feats.append(picked.reshape(B, cells_xy.shape[1], -1, C))
        pos.append(cells * scale)
    return torch.cat(feats, dim=2), torch.cat(pos, dim=2)


class _GELU(nn.Module):
    """GELU, tanh form (CenterFormer's)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.gelu(x, approximate="tanh")


class SelfAttention(nn.Module):
    """Multi-head attention among the queries of a sample (q, k, v without bias)."""

    def __init__(self, dim: int, heads: int, dim_head: int, dropout: float):
        super().__init__()
        self.heads, self.dim_head = heads, dim_head
        self.to_qkv = nn.Linear(dim, 3 * heads * dim_head, bias=False)
        self.to_out = nn.Sequential(nn.Linear(heads * dim_head, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, K, _ = x.shape
        q, k, v = self.to_qkv(x).reshape(B, K, 3, self.heads, self.dim_head).permute(2, 0, 3, 1, 4)
        att = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.dim_head), dim=-1)
        out = (att @ v).transpose(1, 2).reshape(B, K, -1)  # (B, K, heads * dim_head)
        return self.to_out(out)


class CrossAttention(nn.Module):
    """Each query attends to its own ``N`` keys (its windows), multi-head."""

    def __init__(self, dim: int, heads: int, dim_head: int, dropout: float):
        super().__init__()
        self.heads, self.dim_head = heads, dim_head
        self.to_q = nn.Linear(dim, heads * dim_head, bias=False)
        self.to_kv = nn.Linear(dim, 2 * heads * dim_head, bias=False)
        self.to_out = nn.Sequential(nn.Linear(heads * dim_head, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """x: (B, K, C) queries; y: (B, K, N, C) their keys -> (B, K, C)."""
        B, K, N, _ = y.shape
        q = self.to_q(x).reshape(B, K, self.heads, 1, self.dim_head)
        k, v = (
            self.to_kv(y).reshape(B, K, N, 2, self.heads, self.dim_head).permute(3, 0, 1, 4, 2, 5)
        )
        att = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.dim_head), dim=-1)
        return self.to_out((att @ v).reshape(B, K, -1))  # (B, K, heads * dim_head) -> (B, K, C)


class CenterTransformerLayer(nn.Module):
    """Pre-norm self-attention, cross-attention (one LayerNorm for queries and keys) and GELU
    feed-forward, each residual; positions are added before each attention."""

    def __init__(self, dim: int, heads: int, dim_head: int, mlp_dim: int, dropout: float):
        super().__init__()
        self.self_norm = nn.LayerNorm(dim)
        self.self_attn = SelfAttention(dim, heads, dim_head, dropout)
        self.cross_norm = nn.LayerNorm(dim)
        self.cross_attn = CrossAttention(dim, heads, dim_head, dropout)
        self.ffn_norm = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(
            nn.Linear(dim, mlp_dim), _GELU(), nn.Dropout(dropout), nn.Linear(mlp_dim, dim),
            nn.Dropout(dropout),
        )  # fmt: skip

    def forward(
        self, x: torch.Tensor, x_pos: torch.Tensor, y: torch.Tensor, y_pos: torch.Tensor
    ) -> torch.Tensor:
        x = x + self.self_attn(self.self_norm(x + x_pos))
        x = x + self.cross_attn(self.cross_norm(x + x_pos), self.cross_norm(y + y_pos))
        return x + self.ffn(self.ffn_norm(x))


class CenterTransformer(nn.Module):
    """``depth`` layers over the queries; queries and keys share one linear position embedding
    of their ``(x, y)`` query-map cells."""

    def __init__(
        self, dim: int, depth: int, heads: int, dim_head: int, mlp_dim: int, dropout: float
    ):
        super().__init__()
        for name, value in (("DEPTH", depth), ("HEADS", heads), ("DIM_HEAD", dim_head),
                            ("MLP_DIM", mlp_dim)):  # fmt: skip
            if int(value) < 1:
                raise ValueError(f"TRANSFORMER.{name} must be >= 1, got {value}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"TRANSFORMER.DROPOUT must be in [0, 1), got {dropout}")
        self.pos_embedding = nn.Linear(2, dim)
        self.layers = nn.ModuleList(
            CenterTransformerLayer(dim, heads, dim_head, mlp_dim, dropout) for _ in range(depth)
        )

    def forward(
        self, x: torch.Tensor, x_cells: torch.Tensor, y: torch.Tensor, y_cells: torch.Tensor
    ) -> torch.Tensor:
        """x: (B, K, C) query features at cells ``x_cells`` (B, K, 2); y: (B, K, N, C) keys at
        ``y_cells`` (B, K, N, 2) -> (B, K, C)."""
        x_pos = self.pos_embedding(x_cells.to(x.dtype))
        y_pos = self.pos_embedding(y_cells.to(y.dtype))
        for layer in self.layers:
            x = layer(x, x_pos, y, y_pos)
        return x
