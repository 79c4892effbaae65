"""Pure-torch sparse 3D convolution with the interface of spconv 2.x's ``spconv.pytorch``.

OpenPCDet's voxel backbones (``VoxelBackBone8x``, ``VoxelResBackBone8x``) are written against
``spconv.pytorch``; this module offers the same names and the same parameter layout so that their
code shape carries over and a spconv 2.x ``state_dict`` loads with ``strict=True`` (see
docs/model_zoo.md):

- ``SparseConvTensor(features, indices, spatial_shape, batch_size)``: ``features`` ``(N, C)``,
  ``indices`` ``(N, 4)`` int32 ``[batch, z, y, x]``, ``spatial_shape`` ``[D, H, W]``.
- ``SubMConv3d`` / ``SparseConv3d``: ``weight`` ``(out, kD, kH, kW, in)`` and optional ``bias``
  ``(out,)`` are their only state.
- ``SparseModule`` and ``SparseSequential``.

Rules (which input site feeds which output site through which kernel offset) are built by sorting
linear site keys and ``torch.searchsorted`` / ``torch.unique``; the convolution is a
gather-GEMM-scatter per kernel offset. Within one offset every output site receives at most one
input site, so the scatter has no collisions and the result is deterministic on CPU and GPU, in
torch's deterministic mode or not; in that mode the scatter keeps its atomic CUDA kernel
(:func:`_collision_free_index_add`).

Output order: a submanifold conv keeps the input's rows. A regular sparse conv lists its output
sites sorted by their linear index ``((b * D + z) * H + y) * W + x``. spconv 2.x's maintainer
states its regular-conv output order is sorted when its ``direct_table`` option is off and
unspecified when it is on (traveller59/spconv#592); the sites and their features are the same.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.utils.common import deterministic_algorithms

__all__ = [
    "IndicePairs",
    "SparseConv3d",
    "SparseConvTensor",
    "SparseModule",
    "SparseSequential",
    "SubMConv3d",
]


def _triple(value: int | Sequence[int], name: str) -> tuple[int, int, int]:
    if isinstance(value, int):
        return (value, value, value)
    out = tuple(int(v) for v in value)
    if len(out) != 3:
        raise ValueError(f"{name} must be an int or 3 ints (z, y, x), got {value!r}")
    return out  # type: ignore[return-value]


def _linear_keys(indices: torch.Tensor, spatial_shape: Sequence[int]) -> torch.Tensor:
    """``(N, 4)`` ``[b, z, y, x]`` -> ``(N,)`` int64 ``((b * D + z) * H + y) * W + x``."""
    d, h, w = spatial_shape
    idx = indices.long()
    return ((idx[:, 0] * d + idx[:, 1]) * h + idx[:, 2]) * w + idx[:, 3]


#: marks indices already checked (a conv's output sites, ``replace_feature``), so the range
#: check (a device sync) runs once per input tensor, not once per layer
_TRUSTED = object()


class SparseConvTensor:
    """Active sites of a ``(B, C, D, H, W)`` grid: ``features`` ``(N, C)`` at ``indices``
    ``(N, 4)``.

    ``indice_dict`` carries rules between layers by ``indice_key``; tensors derived from this one
    (``replace_feature``, a conv's output) share it.
    """

    def __init__(
        self,
        features: torch.Tensor,
        indices: torch.Tensor,
        spatial_shape: Sequence[int],
        batch_size: int,
        indice_dict: dict[str, IndicePairs] | None = None,
        _trusted_indices: object = None,
    ) -> None:
        if features.dim() != 2:
            raise ValueError(
                f"SparseConvTensor: features must be (N, C), got {tuple(features.shape)}"
            )
        if indices.dim() != 2 or indices.shape[1] != 4:
            raise ValueError(
                f"SparseConvTensor: indices must be (N, 4) [batch, z, y, x], got "
                f"{tuple(indices.shape)}"
            )
        if indices.shape[0] != features.shape[0]:
            raise ValueError(
                f"SparseConvTensor: {indices.shape[0]} indices for {features.shape[0]} feature rows"
            )
        if indices.dtype != torch.int32:
            raise ValueError(f"SparseConvTensor: indices must be int32, got {indices.dtype}")
        if len(spatial_shape) != 3:
            raise ValueError(
                f"SparseConvTensor: spatial_shape must be [D, H, W], got {spatial_shape}"
            )
        shape = [int(s) for s in spatial_shape]
        if min(shape) < 1 or int(batch_size) < 0:
            raise ValueError(
                f"SparseConvTensor: spatial_shape must be >= 1 and batch_size >= 0, got "
                f"{spatial_shape}, {batch_size}"
            )
        if indices.shape[0] and _trusted_indices is not _TRUSTED:
            # an out-of-range site would alias another one in the linear keys of the rules
            low = indices.amin(dim=0).tolist()
            high = indices.amax(dim=0).tolist()
            limits = [int(batch_size), *shape]
            if min(low) < 0 or any(h >= n for h, n in zip(high, limits)):
                raise ValueError(
                    f"SparseConvTensor: indices [batch, z, y, x] must lie in [0, {limits}), got "
                    f"min {low}, max {high}"
                )
        self.features = features
        self.indices = indices
        self.spatial_shape = shape
        self.batch_size = int(batch_size)
        self.indice_dict: dict[str, IndicePairs] = {} if indice_dict is None else indice_dict

    def replace_feature(self, features: torch.Tensor) -> SparseConvTensor:
        """The same sites (and shared rules) with new ``(N, C')`` features."""
        return SparseConvTensor(
            features, self.indices, self.spatial_shape, self.batch_size, self.indice_dict, _TRUSTED
        )

    def dense(self, channels_first: bool = True) -> torch.Tensor:
        """``(B, C, D, H, W)`` (or ``(B, D, H, W, C)``), zeros at inactive sites."""
        d, h, w = self.spatial_shape
        out = self.features.new_zeros((self.batch_size, d, h, w, self.features.shape[1]))
        idx = self.indices.long()
        out = out.index_put((idx[:, 0], idx[:, 1], idx[:, 2], idx[:, 3]), self.features)
        return out.permute(0, 4, 1, 2, 3).contiguous() if channels_first else out


@dataclass(frozen=True)
class IndicePairs:
    """Rules of one conv layer: ``pairs[k] = (in_rows, out_rows)`` for kernel offset ``k``.

    ``out_indices`` / ``out_spatial_shape`` describe the output sites; a submanifold layer with the
    same ``indice_key`` reuses the whole object.
    """

    in_indices: torch.Tensor  # (N_in, 4) int32
    out_indices: torch.Tensor  # (N_out, 4) int32
    in_spatial_shape: tuple[int, int, int]
    out_spatial_shape: tuple[int, int, int]
    kernel_size: tuple[int, int, int]
    dilation: tuple[int, int, int]
    subm: bool
    pairs: tuple[tuple[torch.Tensor, torch.Tensor], ...]  # per offset: (n_k,), (n_k,) int64


def _kernel_offsets(kernel_size: tuple[int, int, int], device: torch.device) -> torch.Tensor:
    """``(K, 3)`` kernel positions ``(kz, ky, kx)`` in the weight's ``(kD, kH, kW)`` order."""
    grids = torch.meshgrid(*(torch.arange(k, device=device) for k in kernel_size), indexing="ij")
    return torch.stack([g.reshape(-1) for g in grids], dim=1)


def _subm_pairs(
    indices: torch.Tensor,
    spatial_shape: tuple[int, int, int],
    kernel_size: tuple[int, int, int],
    dilation: tuple[int, int, int],
) -> IndicePairs:
    """Submanifold rules: output sites are the input sites; kernel centred on each site.

    The kernel sizes are odd (``SubMConv3d`` checks), so the offsets pair up around the centre:
    when site ``i`` feeds site ``o`` through offset ``d``, ``o`` feeds ``i`` through ``-d``; only
    half the offsets are searched (the mirror of flat offset ``k`` is ``K - 1 - k``) and the centre
    maps every site to itself.
    """
    device = indices.device
    shape = torch.tensor(spatial_shape, device=device)
    sorted_keys, order = torch.sort(_linear_keys(indices, spatial_shape))
    sorted_zyx = indices.long()[order, 1:]
    centre = torch.tensor([k // 2 for k in kernel_size], device=device)
    deltas = (_kernel_offsets(kernel_size, device) - centre) * torch.tensor(dilation, device=device)
    _, h, w = spatial_shape
    shifts = ((deltas[:, 0] * h + deltas[:, 1]) * w + deltas[:, 2]).tolist()  # linear key shifts
    pairs: list = [None] * deltas.shape[0]
    for k, delta in enumerate(deltas):
        if pairs[k] is not None:
            continue
        if k == len(pairs) // 2:  # the centre
            rows = torch.arange(len(order), device=device)
            pairs[k] = (rows, rows)
            continue
        # the key each site reads through this offset, in key order (a sorted query is a
        # cache-friendly search); a shift that leaves the grid is masked, not wrapped
        nb_zyx = sorted_zyx + delta
        inside = ((nb_zyx >= 0) & (nb_zyx < shape)).all(dim=1)
        nb_keys = sorted_keys + shifts[k]
        pos = torch.searchsorted(sorted_keys, nb_keys).clamp_max(max(len(order) - 1, 0))
        found = inside & (sorted_keys[pos] == nb_keys) if len(order) else inside
        at = torch.nonzero(found, as_tuple=True)[0]
        in_rows, out_rows = order[pos[at]], order[at]
        pairs[k] = (in_rows, out_rows)
        pairs[len(pairs) - 1 - k] = (out_rows, in_rows)
    return IndicePairs(
        indices, indices, spatial_shape, spatial_shape, kernel_size, dilation, True, tuple(pairs)
    )


def conv_output_shape(
    spatial_shape: Sequence[int],
    kernel_size: tuple[int, int, int],
    stride: tuple[int, int, int],
    padding: tuple[int, int, int],
    dilation: tuple[int, int, int],
) -> tuple[int, int, int]:
    """spconv's (and ``nn.Conv3d``'s) output size: ``floor((in + 2p - d(k-1) - 1) / s) + 1``."""
    out = tuple(
        (n + 2 * p - d * (k - 1) - 1) // s + 1
        for n, k, s, p, d in zip(spatial_shape, kernel_size, stride, padding, dilation)
    )
    if min(out) < 1:
        raise ValueError(
            f"sparse conv: input spatial shape {list(spatial_shape)} is too small for kernel "
            f"{kernel_size}, stride {stride}, padding {padding}, dilation {dilation} "
            f"(output shape {list(out)})"
        )
    return out  # type: ignore[return-value]


def _regular_pairs(
    indices: torch.Tensor,
    spatial_shape: tuple[int, int, int],
    kernel_size: tuple[int, int, int],
    stride: tuple[int, int, int],
    padding: tuple[int, int, int],
    dilation: tuple[int, int, int],
) -> IndicePairs:
    """Regular sparse conv rules: every output site some input reaches, sorted by linear index."""
    device = indices.device
    out_shape = conv_output_shape(spatial_shape, kernel_size, stride, padding, dilation)
    idx = indices.long()
    # per axis (each on its own): input coordinate i reaches output o through kernel position
    # k when o * s - p + k * d == i
    out_axis, valid_axis = [], []
    for axis, (k, s, p, d, n_out) in enumerate(
        zip(kernel_size, stride, padding, dilation, out_shape)
    ):
        num = idx[None, :, 1 + axis] + p - torch.arange(k, device=device)[:, None] * d  # (k, N)
        o = torch.div(num, s, rounding_mode="floor")
        out_axis.append(o)
        valid_axis.append((num % s == 0) & (o >= 0) & (o < n_out))
    kd, kh, kw = kernel_size
    valid = (
        valid_axis[0][:, None, None] & valid_axis[1][None, :, None] & valid_axis[2][None, None, :]
    ).reshape(kd * kh * kw, -1)  # (K, N), K in the weight's (kD, kH, kW) order
    k_ids, in_rows = torch.nonzero(valid, as_tuple=True)
    kz, ky, kx = k_ids // (kh * kw), k_ids // kw % kh, k_ids % kw
    out_sites = torch.stack(  # (P, 4)
        [idx[in_rows, 0], out_axis[0][kz, in_rows], out_axis[1][ky, in_rows],
         out_axis[2][kx, in_rows]], dim=1,
    )  # fmt: skip
    out_keys, out_rows = torch.unique(
        _linear_keys(out_sites, out_shape), sorted=True, return_inverse=True
    )
    # decode the sorted keys back into [b, z, y, x]
    od, oh, ow = out_shape
    out_indices = torch.stack(
        [
            out_keys // (od * oh * ow),
            out_keys // (oh * ow) % od,
            out_keys // ow % oh,
            out_keys % ow,
        ],
        dim=1,
    ).to(torch.int32)
    # nonzero lists (k, n) row-major: each offset's pairs are one slice
    counts = torch.bincount(k_ids, minlength=kd * kh * kw).tolist()
    pairs = tuple(zip(in_rows.split(counts), out_rows.split(counts)))
    return IndicePairs(
        indices, out_indices, spatial_shape, out_shape, kernel_size, dilation, False, pairs
    )


class SparseModule(nn.Module):
    """Base of modules that take and return a ``SparseConvTensor`` (``SparseSequential`` passes
    the whole tensor to them, not its features)."""


class _SparseConvNd(SparseModule):
    #: submanifold (outputs at the input sites) or regular sparse conv
    SUBM: bool = False

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int | Sequence[int],
        stride: int | Sequence[int] = 1,
        padding: int | Sequence[int] = 0,
        dilation: int | Sequence[int] = 1,
        bias: bool = True,
        indice_key: str | None = None,
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = _triple(kernel_size, "kernel_size")
        self.stride = _triple(stride, "stride")
        self.padding = _triple(padding, "padding")
        self.dilation = _triple(dilation, "dilation")
        self.indice_key = indice_key
        self.subm = subm = self.SUBM
        if min(self.kernel_size) < 1 or min(self.stride) < 1 or min(self.dilation) < 1:
            raise ValueError(
                f"{type(self).__name__}: kernel_size, stride and dilation must be >= 1, got "
                f"{self.kernel_size}, {self.stride}, {self.dilation}"
            )
        if min(self.padding) < 0:
            raise ValueError(f"{type(self).__name__}: padding must be >= 0, got {self.padding}")
        if subm and self.stride != (1, 1, 1):
            raise ValueError(f"SubMConv3d: stride must be 1, got {self.stride}")
        if subm and any(k % 2 == 0 for k in self.kernel_size):
            raise ValueError(
                f"SubMConv3d: kernel_size must be odd (a kernel centred on each site, as "
                f"spconv), got {self.kernel_size}"
            )
        # spconv 2.x layout (KRSC): (out, kD, kH, kW, in)
        self.weight = nn.Parameter(torch.empty(out_channels, *self.kernel_size, in_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # nn.Conv3d's init; fan_in = in_channels * kD * kH * kW whichever axis order
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        if self.bias is not None:
            bound = 1.0 / math.sqrt(self.in_channels * math.prod(self.kernel_size))
            nn.init.uniform_(self.bias, -bound, bound)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, "
            f"stride={self.stride}, padding={self.padding}, dilation={self.dilation}, "
            f"bias={self.bias is not None}, indice_key={self.indice_key!r}"
        )

    def _rules(self, x: SparseConvTensor) -> IndicePairs:
        shape = tuple(x.spatial_shape)
        cached = x.indice_dict.get(self.indice_key) if self.indice_key is not None else None
        if cached is not None and self.subm:
            if (
                not cached.subm
                or cached.in_spatial_shape != shape
                or cached.in_indices.shape != (x.indices.shape)
            ):
                raise ValueError(
                    f"{type(self).__name__}: indice_key {self.indice_key!r} holds rules of another "
                    f"layout (subm={cached.subm}, shape {list(cached.in_spatial_shape)}, "
                    f"{cached.in_indices.shape[0]} sites); this input has shape {list(shape)}, "
                    f"{x.indices.shape[0]} sites"
                )
            if (cached.kernel_size, cached.dilation) != (self.kernel_size, self.dilation):
                raise ValueError(
                    f"SubMConv3d: indice_key {self.indice_key!r} was built for kernel "
                    f"{cached.kernel_size}, dilation {cached.dilation}; this layer has kernel "
                    f"{self.kernel_size}, dilation {self.dilation}"
                )
            return cached
        if self.subm:
            rules = _subm_pairs(x.indices, shape, self.kernel_size, self.dilation)
        else:
            rules = _regular_pairs(
                x.indices, shape, self.kernel_size, self.stride, self.padding, self.dilation
            )
        if self.indice_key is not None and cached is None:
            x.indice_dict[self.indice_key] = rules
        return rules

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        if not isinstance(x, SparseConvTensor):
            raise TypeError(
                f"{type(self).__name__} takes a SparseConvTensor, got {type(x).__name__}"
            )
        if x.features.shape[1] != self.in_channels:
            raise ValueError(
                f"{type(self).__name__}: expected {self.in_channels} input channels, got "
                f"{x.features.shape[1]}"
            )
        rules = self._rules(x)
        return SparseConvTensor(
            self.apply_rules(x.features, rules), rules.out_indices, rules.out_spatial_shape,
            x.batch_size, x.indice_dict, _TRUSTED,
        )  # fmt: skip

    def apply_rules(self, features: torch.Tensor, rules: IndicePairs) -> torch.Tensor:
        """The output features ``(N_out, out)`` of ``features`` ``(N_in, in)`` under ``rules``:
        per kernel offset, gather its input rows, one GEMM, scatter-add into its output rows."""
        weight = self.weight.reshape(self.out_channels, -1, self.in_channels)  # (out, K, in)
        out = _GatherGemmScatter.apply(features, weight, rules.pairs, rules.out_indices.shape[0])
        if self.bias is not None:
            out = out + self.bias
        return out


def _collision_free_index_add(tensor: torch.Tensor) -> contextlib.AbstractContextManager:
    """A context in which ``index_add_`` on ``tensor`` runs torch's own CUDA kernel also when
    ``torch.use_deterministic_algorithms(True)`` is in effect.

    That mode sends every CUDA ``index_add_`` through a sort-based ``index_put_`` (a sort, host
    synchronisations, ~2x the time of a voxel CP-4f training step on a GPU,
    docs/benchmarks.md). The sparse conv's index rows never repeat within one call, so each
    output element gets exactly one atomic add: the result is the same bits either way. The mode
    and its ``warn_only`` setting are restored on exit, also on an error."""
    if tensor.is_cuda and torch.are_deterministic_algorithms_enabled():
        return deterministic_algorithms(False)
    return contextlib.nullcontext()


class _GatherGemmScatter(torch.autograd.Function):
    """``out[o] = sum_k W_k x[i]`` over the pairs ``(i, o)`` of each kernel offset ``k``, with
    its own backward: the gradients go to one ``(N_in, in)`` buffer and one weight buffer, offset
    by offset (autograd through the gathers would allocate a full-size gradient per offset and
    sum them, plus an accumulating ``index_put_`` each).

    Within one offset an output row receives at most one input row and an input row feeds at
    most one output row, so every ``index_add_`` is collision-free and deterministic."""

    @staticmethod
    def forward(ctx, features, weight, pairs, num_out):  # weight (out, K, in)
        out = features.new_zeros((num_out, weight.shape[0]))
        for k, (in_rows, out_rows) in enumerate(pairs):
            if in_rows.numel():
                rows = features.index_select(0, in_rows) @ weight[:, k].t()
                with _collision_free_index_add(out):
                    out.index_add_(0, out_rows, rows)
        ctx.save_for_backward(features, weight)
        ctx.pairs = pairs
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        features, weight = ctx.saved_tensors
        need_features, need_weight = ctx.needs_input_grad[:2]
        grad_features = torch.zeros_like(features) if need_features else None
        grad_weight = torch.zeros_like(weight) if need_weight else None
        for k, (in_rows, out_rows) in enumerate(ctx.pairs):
            if not in_rows.numel():
                continue
            grad = grad_out.index_select(0, out_rows)  # (n, out)
            if need_features:
                rows = grad @ weight[:, k]
                with _collision_free_index_add(grad_features):
                    grad_features.index_add_(0, in_rows, rows)
            if need_weight:
                grad_weight[:, k] = grad.t() @ features.index_select(0, in_rows)
        return grad_features, grad_weight, None, None


class SubMConv3d(_SparseConvNd):
    """Submanifold conv: outputs at the input sites, in the input's row order, with a kernel
    centred on each site whatever ``padding`` says (as spconv). Arguments as spconv's:
    ``(in_channels, out_channels, kernel_size, stride=1, padding=0, dilation=1, bias=True,
    indice_key=None)``."""

    SUBM = True


class SparseConv3d(_SparseConvNd):
    """Regular sparse conv: outputs at every site some input reaches under stride / padding /
    dilation, sorted by linear index; output shape ``floor((in + 2p - d(k-1) - 1) / s) + 1``.
    Arguments as :class:`SubMConv3d`'s."""


class SparseSequential(nn.Sequential, SparseModule):
    """``nn.Sequential`` over a ``SparseConvTensor``: sparse modules get the tensor, plain torch
    modules (``BatchNorm1d``, ``ReLU``, ...) get its ``(N, C)`` features."""

    def forward(self, x):  # type: ignore[override]
        for module in self:
            if isinstance(module, SparseModule) or not isinstance(x, SparseConvTensor):
                x = module(x)
            else:
                x = x.replace_feature(module(x.features))
        return x
