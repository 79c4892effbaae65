"""Mamba layers in pure torch over padded batches of variable-length voxel sequences.

:class:`Mamba` is mamba_ssm's ``Mamba`` mixer (``mamba_simple.py``: in-projection to ``x, z``,
causal depthwise conv1d, SiLU, input-dependent ``delta, B, C``, selective scan with ``D`` skip
and ``silu(z)`` gate, out-projection; its initialisation of ``dt_proj``, ``A_log`` and ``D``) on
:func:`~pcdet_atlas.models.ssm.selective_scan`. :class:`PackedSequences` lays ``V`` voxel rows out
as ``(num_seq, max_len)`` sequences, forward or with every sequence reversed, padding at the end;
a causal layer never reads a sequence's padding for its valid positions, so a voxel's output does
not depend on how long the other sequences of the batch are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.models.ssm import selective_scan

__all__ = ["RMSNorm", "Mamba", "PackedSequences", "pack_sequences"]


class RMSNorm(nn.Module):
    """``x / rms(x) * weight`` over the last dimension (Mamba's norm)."""

    def __init__(self, dim: int, eps: float = 1e-5):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + self.eps) * self.weight


class Mamba(nn.Module):
    """Selective state-space mixer ``(S, L, d_model) -> (S, L, d_model)``, causal along L."""

    def __init__(
        self,
        d_model: int,
        *,
        d_state: int = 16,
        d_conv: int = 4,
        expand: int = 2,
        dt_min: float = 1e-3,
        dt_max: float = 0.1,
    ):
        super().__init__()
        self.d_inner = expand * d_model
        self.d_state = d_state
        self.dt_rank = math.ceil(d_model / 16)
        self.in_proj = nn.Linear(d_model, 2 * self.d_inner, bias=False)
        self.conv1d = nn.Conv1d(
            self.d_inner, self.d_inner, d_conv, groups=self.d_inner, padding=d_conv - 1
        )
        self.x_proj = nn.Linear(self.d_inner, self.dt_rank + 2 * d_state, bias=False)
        self.dt_proj = nn.Linear(self.dt_rank, self.d_inner, bias=True)
        self.out_proj = nn.Linear(self.d_inner, d_model, bias=False)
        # mamba_simple's init: dt_proj weight U(+-dt_rank^-0.5), bias softplus^-1 of a
        # log-uniform dt in [dt_min, dt_max]; A = -(1..N) per channel through A_log; D = 1
        bound = self.dt_rank**-0.5
        nn.init.uniform_(self.dt_proj.weight, -bound, bound)
        dt = torch.exp(
            torch.rand(self.d_inner) * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min)
        ).clamp(min=1e-4)
        with torch.no_grad():
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))
        a = torch.arange(1, d_state + 1, dtype=torch.float32).repeat(self.d_inner, 1)
        self.A_log = nn.Parameter(torch.log(a))  # (d_inner, N)
        self.D = nn.Parameter(torch.ones(self.d_inner))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        S, L, _ = x.shape
        xz = self.in_proj(x).transpose(1, 2)  # (S, 2 * d_inner, L)
        u, z = xz.chunk(2, dim=1)  # (S, d_inner, L) each
        u = F.silu(self.conv1d(u)[..., :L])  # causal: keep the first L outputs
        dbc = self.x_proj(u.transpose(1, 2))  # (S, L, dt_rank + 2N)
        dt, B, C = dbc.split([self.dt_rank, self.d_state, self.d_state], dim=-1)
        delta = (dt @ self.dt_proj.weight.T).transpose(1, 2)  # (S, d_inner, L), bias in the scan
        y = selective_scan(
            u, delta, -torch.exp(self.A_log.float()), B.transpose(1, 2), C.transpose(1, 2),
            D=self.D.float(), z=z, delta_bias=self.dt_proj.bias.float(), delta_softplus=True,
        )  # fmt: skip
        return self.out_proj(y.transpose(1, 2))  # (S, L, d_model)


@dataclass(frozen=True)
class PackedSequences:
    """Where each of ``V`` rows sits in a ``(num_seq, max_len)`` padded layout.

    Attributes:
        slot: (V,) int64 flat position ``seq * max_len + pos`` of every row.
        slot_reversed: (V,) the same with every sequence reversed (``pos -> len - 1 - pos``).
        num_seq, max_len: the layout.
    """

    slot: torch.Tensor
    slot_reversed: torch.Tensor
    num_seq: int
    max_len: int

    def to_padded(self, x: torch.Tensor, reverse: bool = False) -> torch.Tensor:
        """``(V, C)`` rows -> ``(num_seq, max_len, C)``, zeros in the padding."""
        slot = self.slot_reversed if reverse else self.slot
        out = x.new_zeros(self.num_seq * self.max_len, x.shape[1]).index_copy(0, slot, x)
        return out.view(self.num_seq, self.max_len, x.shape[1])

    def from_padded(self, y: torch.Tensor, reverse: bool = False) -> torch.Tensor:
        """``(num_seq, max_len, C)`` -> ``(V, C)`` rows in the original order."""
        slot = self.slot_reversed if reverse else self.slot
        return y.reshape(self.num_seq * self.max_len, y.shape[-1]).index_select(0, slot)


def pack_sequences(seq_id: torch.Tensor, key: torch.Tensor, num_seq: int) -> PackedSequences:
    """Order rows by ``key`` within their sequence ``seq_id`` (both ``(V,)`` int64, keys
    non-negative and unique within a sequence) and lay them out as padded sequences."""
    V = seq_id.shape[0]
    if V == 0:
        empty = seq_id.new_zeros(0)
        return PackedSequences(empty, empty, num_seq, 0)
    span = int(key.max()) + 1
    order = torch.argsort(seq_id * span + key)  # (V,) rows in sequence order
    counts = torch.bincount(seq_id, minlength=num_seq)  # (num_seq,)
    starts = torch.cumsum(counts, 0) - counts
    seq_sorted = seq_id[order]
    pos = torch.arange(V, device=seq_id.device) - starts[seq_sorted]
    max_len = int(counts.max())
    slot = torch.empty_like(order)
    slot[order] = seq_sorted * max_len + pos
    slot_rev = torch.empty_like(order)
    slot_rev[order] = seq_sorted * max_len + counts[seq_sorted] - 1 - pos
    return PackedSequences(slot, slot_rev, num_seq, max_len)
