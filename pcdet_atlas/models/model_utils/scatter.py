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


class _ScatterMax(torch.autograd.Function):
    """Per-group max with a row-wise backward (``index_select`` / ``index_add_``).

    Forward is ``scatter_reduce_('amax', include_self=False)``. The backward splits each group's
    gradient evenly among the elements equal to the group's max, like torch's own
    ``ScatterReduceBackward0``, but gathers and scatters whole rows with a 1-D index instead of an
    expanded ``(N, C)`` one and does not clone the output buffer, which makes it cheaper on CPU
    for the VFE's millions of points (docs/benchmarks.md, "Training step"). One difference, on
    purpose: torch also counts the excluded initial value (0) as a tie when a group's max is
    exactly 0, halving the gradient of the true maximisers there (pytorch issue "scatter_reduce
    amax include_self=False gradient"); here only the reduced elements count. Behind a ReLU (the
    VFE) such elements get no gradient
    either way, so the model's gradients are the same.
    """

    @staticmethod
    def forward(ctx, src: torch.Tensor, index: torch.Tensor, dim_size: int) -> torch.Tensor:
        out = src.new_zeros(dim_size, src.shape[1])
        out.scatter_reduce_(
            0, index[:, None].expand_as(src), src, reduce="amax", include_self=False
        )
        ctx.save_for_backward(src, index, out)
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        src, index, out = ctx.saved_tensors
        is_max = (src == out.index_select(0, index)).to(out.dtype)  # (N, C) 1 / 0
        ties = torch.zeros_like(out).index_add_(0, index, is_max)  # (P, C), >= 1 where used
        grad_src = (grad_out / ties).index_select(0, index).mul_(is_max)
        return grad_src, None, None


def scatter_max(src: torch.Tensor, index: torch.Tensor, dim_size: int) -> torch.Tensor:
    """Per-group element-wise max ``(dim_size, C)`` via ``scatter_reduce_('amax')``.

    Differentiable w.r.t. ``src``: the gradient of a group goes to its maximal elements, split
    evenly among ties (see :class:`_ScatterMax`).
    """
    _check(src, index)
    if src.requires_grad and torch.is_grad_enabled():
        return _ScatterMax.apply(src, index, dim_size)
    out = src.new_zeros(dim_size, src.shape[1])
    return out.scatter_reduce_(
        0, index[:, None].expand_as(src), src, reduce="amax", include_self=False
    )
