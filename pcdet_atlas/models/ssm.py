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
    # time-major inside a chunk so that each step of the local loop reads a contiguous slice;
    # the state dimension n outside (b, d, nc): every broadcast and sum over n is then over
    # whole contiguous blocks, not over an innermost dimension of 4-16 elements
    dl = dl.view(b, d, nc, T).permute(3, 0, 1, 2).contiguous()  # (T, b, d, nc)
    du = du.view(b, d, nc, T).permute(3, 0, 1, 2).contiguous()  # (T, b, d, nc)
    Bp = Bp.view(b, n, nc, T).permute(3, 1, 0, 2).contiguous()  # (T, n, b, nc)
    Cp = Cp.view(b, n, nc, T).permute(3, 1, 0, 2).contiguous()  # (T, n, b, nc)
    y = _ChunkedScan.apply(dl, du, A, Bp, Cp)  # (T, b, d, nc)
    y = y.permute(1, 2, 3, 0).reshape(b, d, L)[..., :l]  # (b, d, l)
    return _finish(y, u, D, z, dtype_in)


def _times_A(x: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """``x[t, b, d, c] * A[d, n]`` as (T, n, b, d, nc)."""
    return x[:, None] * A.t()[None, :, None, :, None]


def _prefix_sum(x: torch.Tensor) -> torch.Tensor:
    """Inclusive sum over dim 0 by a loop over its (few) slices: torch's CPU cumsum over a
    leading dimension is many times slower than these contiguous adds."""
    out = x.clone()
    for t in range(1, x.shape[0]):
        out[t] += out[t - 1]
    return out


def _suffix_sum_exclusive(x: torch.Tensor) -> torch.Tensor:
    """``out[t] = sum_{s > t} x[s]`` over dim 0, summed from the end (no difference of two
    prefix sums, which would cancel)."""
    out = torch.zeros_like(x)
    for t in range(x.shape[0] - 2, -1, -1):
        torch.add(out[t + 1], x[t + 1], out=out[t])
    return out


class _ChunkedScan(torch.autograd.Function):
    """``h_t = exp(delta_t A) h_{t-1} + du_t B_t``, ``y_t = sum_n C_t[n] h_t[n]`` over chunks.

    Inputs in the chunked, time-major layout of :func:`selective_scan`: dl, du (T, b, d, nc);
    A (d, n); B, C (T, n, b, nc); output y (T, b, d, nc); states (T, n, b, d, nc). The forward
    scans all chunks at once from a zero state (in place, one buffer), then carries the state
    across chunks, decayed by ``exp(cumsum(delta) A)`` from the chunk start. The backward is the
    recurrence's own adjoint, a scan run backwards the same way::

        g_t = C_t dy_t + exp(delta_{t+1} A) g_{t+1}     (gradient reaching h_t)
        dL/d(delta_t A) = g_t exp(delta_t A) h_{t-1},   dL/d(du_t B_t) = g_t

    instead of autograd's graph of every step (a saved tensor and three kernels per step). With
    delta >= 0 and A < 0 every exponent is <= 0: nothing overflows, forward or backward.
    """

    @staticmethod
    def forward(ctx, dl, du, A, Bp, Cp):
        decay = _times_A(dl, A).exp_()  # (T, n, b, d, nc), exponent <= 0
        h = du[:, None] * Bp[:, :, :, None]  # (T, n, b, d, nc): du B, scanned in place below
        for t in range(1, h.shape[0]):  # all chunks at once, from a zero state
            h[t].addcmul_(decay[t], h[t - 1])
        nc = h.shape[-1]
        carry_in = torch.zeros_like(h[0])  # (n, b, d, nc): the state entering each chunk
        if nc > 1:
            from_start = _times_A(_prefix_sum(dl), A).exp_()  # (T, n, b, d, nc)
            for c in range(1, nc):
                torch.addcmul(h[-1, ..., c - 1], from_start[-1, ..., c - 1], carry_in[..., c - 1],
                              out=carry_in[..., c])  # fmt: skip
            h.addcmul_(from_start, carry_in)
        ctx.save_for_backward(dl, du, A, Bp, Cp, decay, h, carry_in)
        return (h * Cp[:, :, :, None]).sum(1)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, dy):
        dl, du, A, Bp, Cp, decay, h, carry_in = ctx.saved_tensors
        T, nc = h.shape[0], h.shape[-1]
        g = dy[:, None] * Cp[:, :, :, None]  # (T, n, b, d, nc), scanned backwards in place
        for t in range(T - 2, -1, -1):  # all chunks at once, from a zero gradient
            g[t].addcmul_(decay[t + 1], g[t + 1])
        if nc > 1:  # the gradient entering each chunk's last step from the next chunk
            to_end = _times_A(_suffix_sum_exclusive(dl), A).exp_()  # (T, n, b, d, nc)
            entering = torch.zeros_like(g[0])  # (n, b, d, nc)
            for c in range(nc - 2, -1, -1):
                step = torch.addcmul(g[0, ..., c + 1], to_end[0, ..., c + 1], entering[..., c + 1])
                torch.mul(decay[0, ..., c + 1], step, out=entering[..., c])
            g.addcmul_(to_end, entering)
        grad_dA = g * decay  # (T, n, b, d, nc): times h_{t-1}
        grad_dA[1:] *= h[:-1]
        grad_dA[0] *= carry_in
        At = A.t()[:, None, :, None]  # (n, 1, d, 1)
        grad_dl = (grad_dA * At).sum(1)
        grad_A = (grad_dA * dl[:, None]).sum((0, 2, 4)).t()
        grad_du = (g * Bp[:, :, :, None]).sum(1)
        grad_B = (g * du[:, None]).sum(3)
        grad_C = (h * dy[:, None]).sum(3)
        return grad_dl, grad_du, grad_A, grad_B, grad_C


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
