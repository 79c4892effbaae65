"""State-space model blocks: Mamba's selective scan in plain torch, and a convolutional SSM.

``selective_scan`` computes what mamba_ssm's ``selective_scan_ref`` computes (real case), chunked
so it needs no Python loop over the whole sequence; ``selective_scan_reference`` is the plain
sequential loop, kept as the slow test reference. ``ConvSSM`` is the convolutional state-space
forecaster of ConvSSM (Smith et al., 2023): a diagonal, log-parameterised state recurrence over a
short history of feature maps.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["selective_scan", "selective_scan_reference", "ConvSSM"]


def _check_scan_args(u, delta, A, B, C, D, z, delta_bias) -> None:
    if u.dim() != 3:
        raise ValueError(f"selective_scan: u must be (b, d, l), got {tuple(u.shape)}")
    b, d, l = u.shape
    if A.dim() != 2 or A.shape[0] != d:
        raise ValueError(f"selective_scan: A must be (d, n) = ({d}, n), got {tuple(A.shape)}")
    n = A.shape[1]
    expected = {
        "delta": (delta, (b, d, l)),
        "B": (B, (b, n, l)),
        "C": (C, (b, n, l)),
        "D": (D, (d,)),
        "z": (z, (b, d, l)),
        "delta_bias": (delta_bias, (d,)),
    }
    for name, (t, shape) in expected.items():
        if t is not None and tuple(t.shape) != shape:
            raise ValueError(f"selective_scan: {name} must be {shape}, got {tuple(t.shape)}")
    if l == 0:
        raise ValueError("selective_scan: the sequence length l must be >= 1")


def _prepare(u, delta, A, B, C, delta_bias, delta_softplus):
    """Everything cast to the compute dtype, delta biased and softplus-ed."""
    dtype = torch.float64 if u.dtype == torch.float64 else torch.float32
    u, delta, A, B, C = (t.to(dtype) for t in (u, delta, A, B, C))
    if delta_bias is not None:
        delta = delta + delta_bias.to(dtype)[:, None]
    if delta_softplus:
        delta = F.softplus(delta)
    return u, delta, A, B, C


def _finish(y, u, D, z, dtype_in):
    """``(y + D u) * silu(z)`` in the compute dtype, returned in u's dtype."""
    if D is not None:
        y = y + D.to(y.dtype)[:, None] * u
    if z is not None:
        y = y * F.silu(z.to(y.dtype))
    return y.to(dtype_in)


def selective_scan(
    u: torch.Tensor,
    delta: torch.Tensor,
    A: torch.Tensor,
    B: torch.Tensor,
    C: torch.Tensor,
    D: torch.Tensor | None = None,
    z: torch.Tensor | None = None,
    delta_bias: torch.Tensor | None = None,
    delta_softplus: bool = False,
    chunk_size: int = 64,
) -> torch.Tensor:
    """Mamba's selective scan, ``selective_scan_ref`` of mamba_ssm (real case), chunked.

    u, delta, z (b, d, l); A (d, n); B, C (b, n, l); D, delta_bias (d,). Returns (b, d, l) in u's
    dtype::

        delta <- softplus(delta + delta_bias)          (each if given)
        h_t = exp(delta_t A) h_{t-1} + delta_t B_t u_t (per b, d, n; h_0 = 0)
        out_t = (sum_n C_t[n] h_t[n] + D u_t) * silu(z_t)

    Computes in float64 when u is float64, else in float32 (the reference's float32), so never
    less precise than the reference. The sequence is cut into chunks of ``chunk_size`` steps: a
    sequential scan runs inside all chunks at once from a zero state, then a loop over chunks
    carries the state across, decayed by ``exp(cumsum(delta A))``. With delta >= 0 and A < 0
    every exponent is <= 0, so nothing overflows for any delta or A (no ratios of exponentials).
    Memory is a few (b, d, n, l) tensors; Python loops are chunk_size + l / chunk_size long.
    """
    _check_scan_args(u, delta, A, B, C, D, z, delta_bias)
    if chunk_size < 1:
        raise ValueError(f"selective_scan: chunk_size must be >= 1, got {chunk_size}")
    dtype_in = u.dtype
    u, delta, A, B, C = _prepare(u, delta, A, B, C, delta_bias, delta_softplus)
    b, d, l = u.shape
    n = A.shape[1]
    T = min(chunk_size, l)
    nc = -(-l // T)
    L = nc * T
    du, dl, Bp, Cp = delta * u, delta, B, C
    if L > l:  # identity steps: delta = 0 decays by exp(0) = 1, B = C = 0 adds and reads nothing
        du, dl, Bp, Cp = (F.pad(t, (0, L - l)) for t in (du, dl, Bp, Cp))

    # time-major inside a chunk so that each step of the local loop reads a contiguous slice
    dl = dl.view(b, d, nc, T).permute(3, 0, 1, 2).contiguous()  # (T, b, d, nc)
    du = du.view(b, d, nc, T).permute(3, 0, 1, 2).contiguous()  # (T, b, d, nc)
    Bp = Bp.view(b, n, nc, T).permute(3, 0, 2, 1).contiguous()  # (T, b, nc, n)
    Cp = Cp.view(b, n, nc, T).permute(3, 0, 2, 1).contiguous()  # (T, b, nc, n)
    dA = dl[..., None] * A[:, None, :]  # (T, b, d, nc, n), <= 0
    dBu = du[..., None] * Bp[:, :, None]  # (T, b, d, nc, n)

    # unbind, not indexing: the backward of each index would write a zero-padded full tensor
    h = torch.zeros_like(dBu[0])  # (b, d, nc, n)
    states = []
    for decay_i, dBu_i in zip(dA.exp().unbind(0), dBu.unbind(0)):  # all chunks, zero state
        h = decay_i * h + dBu_i
        states.append(h)
    h_local = torch.stack(states)  # (T, b, d, nc, n)

    # decay exponent from the chunk start, <= 0: cumsum(delta A) = cumsum(delta) A, n times cheaper
    cum = dl.cumsum(0)[..., None] * A[:, None, :]  # (T, b, d, nc, n)
    chunk_decay = cum[-1].exp()  # (b, d, nc, n)
    carry = h.new_zeros(b, d, n)  # (b, d, n)
    carries = []
    for decay_c, last_c in zip(chunk_decay.unbind(2), h.unbind(2)):  # state entering chunk c
        carries.append(carry)
        carry = decay_c * carry + last_c
    carry_in = torch.stack(carries, 2)  # (b, d, nc, n)

    h = h_local + cum.exp() * carry_in  # (T, b, d, nc, n)
    y = (h * Cp[:, :, None]).sum(-1)  # (T, b, d, nc)
    y = y.permute(1, 2, 3, 0).reshape(b, d, L)[..., :l]  # (b, d, l)
    return _finish(y, u, D, z, dtype_in)


def selective_scan_reference(
    u: torch.Tensor,
    delta: torch.Tensor,
    A: torch.Tensor,
    B: torch.Tensor,
    C: torch.Tensor,
    D: torch.Tensor | None = None,
    z: torch.Tensor | None = None,
    delta_bias: torch.Tensor | None = None,
    delta_softplus: bool = False,
) -> torch.Tensor:
    """The definition of :func:`selective_scan` as a plain loop over l (mamba's
    ``selective_scan_ref``): the slow test reference and the benchmark's "plain loop"."""
    _check_scan_args(u, delta, A, B, C, D, z, delta_bias)
    dtype_in = u.dtype
    u, delta, A, B, C = _prepare(u, delta, A, B, C, delta_bias, delta_softplus)
    decay = torch.exp(delta[:, :, None, :] * A[None, :, :, None])  # (b, d, n, l)
    dBu = (delta * u)[:, :, None, :] * B[:, None]  # (b, d, n, l)
    h = u.new_zeros(u.shape[0], u.shape[1], A.shape[1])  # (b, d, n)
    ys = []
    for decay_t, dBu_t, C_t in zip(decay.unbind(3), dBu.unbind(3), C.unbind(2)):
        h = decay_t * h + dBu_t
        ys.append(torch.einsum("bdn,bn->bd", h, C_t))
    return _finish(torch.stack(ys, 2), u, D, z, dtype_in)


class ConvSSM(nn.Module):
    """One-step forecast of a feature map from its history with a convolutional SSM.

    The paper's ``h_k = A h_{k-1} + B(X_k)``, ``X_hat_{k+1} = C(h_k) + D X_k`` with A diagonal
    over the state channels and log-parameterised: ``A_bar = exp(-exp(A_log))`` in [0, 1] for
    every A_log. Discretised by zero-order hold, the input gain is ``1 - A_bar`` (its 1/|A|
    factor absorbed into the learned conv B)::

        h_j = A_bar * h_{j-1} + (1 - A_bar) * B(X_j)     (h_0 = 0)

    so each state is a convex combination of past B(X_j) (weights summing to 1 - A_bar^k) and the
    forecast stays bounded for any history length and any A_log. B and C are 'same' convs; D is
    a learnable per-channel skip.

    forward: x (b, k, in_channels, h, w), the k >= 1 history maps oldest first ->
    (b, in_channels, h, w).
    """

    # exp(-exp(20)) is exactly 0 even in float64; clamping keeps exp(A_log) finite so its
    # gradient is 0 there instead of 0 * inf = NaN
    _MAX_A_LOG = 20.0

    def __init__(self, in_channels: int, state_channels: int, kernel_size: int = 3):
        super().__init__()
        self.in_channels = in_channels
        self.state_channels = state_channels
        # log-uniform decay rates 0.05..2: memories 1 / (1 - A_bar) from ~20 steps down to ~1
        rates = torch.linspace(math.log(0.05), math.log(2.0), state_channels)
        self.A_log = nn.Parameter(rates)  # (S,)
        self.B = nn.Conv2d(in_channels, state_channels, kernel_size, padding="same")
        self.C = nn.Conv2d(state_channels, in_channels, kernel_size, padding="same")
        self.D = nn.Parameter(torch.ones(in_channels))  # (C,)

    def decay(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(A_bar, 1 - A_bar)``, each (state_channels,)."""
        rate = self.A_log.clamp(max=self._MAX_A_LOG).exp()
        return torch.exp(-rate), -torch.expm1(-rate)  # expm1: 1 - A_bar stays > 0 for tiny rates

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 5 or x.shape[1] < 1 or x.shape[2] != self.in_channels:
            raise ValueError(
                f"ConvSSM: x must be (b, k >= 1, {self.in_channels}, h, w), got {tuple(x.shape)}"
            )
        b, k = x.shape[:2]
        a_bar, gain = (t[:, None, None] for t in self.decay())  # (S, 1, 1)
        bx = self.B(x.flatten(0, 1)).unflatten(0, (b, k))  # (b, k, S, h, w), one conv for all
        h = gain * bx[:, 0]  # (b, S, h, w)
        for j in range(1, k):
            h = a_bar * h + gain * bx[:, j]
        return self.C(h) + self.D[:, None, None] * x[:, -1]  # (b, C, h, w)
