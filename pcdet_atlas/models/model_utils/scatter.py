"""Scatter reductions over a group index, in plain torch (replacing ``torch_scatter``).

All functions take ``src`` of shape ``(N, C)`` and an int64 ``index`` of shape ``(N,)`` with values
in ``[0, dim_size)`` and return ``(dim_size, C)``. Groups that receive no element get 0.
"""

from __future__ import annotations

import torch

__all__ = ["scatter_sum", "scatter_mean", "scatter_max"]


def _check(src: torch.Tensor, index: torch.Tensor) -> None:
    if src.dim() != 2 or index.dim() != 1 or index.shape[0] != src.shape[0]:
        raise ValueError(
            f"scatter: expected src (N, C) and index (N,), got {tuple(src.shape)} and "
            f"{tuple(index.shape)}"
        )


def scatter_sum(src: torch.Tensor, index: torch.Tensor, dim_size: int) -> torch.Tensor:
    """Per-group sum ``(dim_size, C)`` via ``index_add_``."""
    _check(src, index)
    out = src.new_zeros(dim_size, src.shape[1])
    return out.index_add_(0, index, src)


def scatter_mean(
    src: torch.Tensor, index: torch.Tensor, dim_size: int, counts: torch.Tensor | None = None
) -> torch.Tensor:
    """Per-group mean ``(dim_size, C)``; ``counts`` (dim_size,) may be passed if already known."""
    total = scatter_sum(src, index, dim_size)
    if counts is None:
        counts = torch.bincount(index, minlength=dim_size)
    return total / counts.clamp(min=1).to(total.dtype)[:, None]


def scatter_max(src: torch.Tensor, index: torch.Tensor, dim_size: int) -> torch.Tensor:
    """Per-group element-wise max ``(dim_size, C)`` via ``scatter_reduce_('amax')``.

    Differentiable w.r.t. ``src``: the gradient goes to the maximal element (split among ties).
    """
    _check(src, index)
    out = src.new_zeros(dim_size, src.shape[1])
    return out.scatter_reduce_(
        0, index[:, None].expand_as(src), src, reduce="amax", include_self=False
    )
