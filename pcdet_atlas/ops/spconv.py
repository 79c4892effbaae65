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

Rules (which input site feeds which output site through which kernel offset) come from an
occupancy bitmap of the grid (submanifold) or from ``torch.unique`` over the reached output keys
(regular); the convolution is one batched gather-GEMM-reduce over all kernel offsets
(:class:`_GatherGemmReduce`): no op writes two values into one place, so the result is
deterministic on CPU and GPU, in torch's deterministic mode or not.

Output order: a submanifold conv keeps the input's rows. A regular sparse conv lists its output
sites sorted by their linear index ``((b * D + z) * H + y) * W + x``. spconv 2.x's maintainer
states its regular-conv output order is sorted when its ``direct_table`` option is off and
unspecified when it is on (traveller59/spconv#592); the sites and their features are the same.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

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
class RuleSlice:
    """The pairs of consecutive groups ``groups`` (see :class:`IndicePairs`): their block rows
    ``rows`` and blocks ``blocks`` (slices of the layer's), and the table that sums each output
    row's products.

    ``out_bags`` ``(N_out, width)``, one column per group of the slice: output row ``o``'s block
    row (relative to ``rows.start``) in each group, or ``pad`` where ``o`` has no pair in it;
    ``pad`` is a padding row of the slice (every non-empty group ends in one): it reads the zero
    row, so its product is zero and adding it changes no sum."""

    groups: slice
    rows: slice
    blocks: slice
    pad: int
    out_bags: torch.Tensor  # (N_out, width) int32


@dataclass(frozen=True)
class IndicePairs:
    """Rules of one conv layer, laid out for a batched gather-GEMM-reduce over all kernel offsets
    (:class:`_GatherGemmReduce`).

    A pair ``(i, o, k)`` says input row ``i`` feeds output row ``o`` through kernel offset ``k``
    (the weight's flat ``(kD, kH, kW)`` index). The pairs are listed in groups of one offset each
    (``group_offsets``, ``group_counts``; a submanifold layer's centre, which
    maps every site to itself, is not listed: it is one plain GEMM). Each group is padded to a
    whole number of ``block``-row blocks with at least one padding row, so that one ``bmm``
    multiplies every block by its offset's weight:

    - ``gather_in`` / ``gather_out`` ``(n_blocks * block,)``: the input / output row of each
      block row; padding rows read row ``N_in`` / ``N_out``, a zero row appended for them.
    - ``block_offsets`` ``(n_blocks,)``: each block's kernel offset; ``group_blocks`` ``(G,)``:
      the number of (consecutive) blocks of each group.
    - ``slices``: the offsets cut into consecutive runs (one on a GPU; on the CPU runs of a few MB
      of gathered rows, which stay in cache and which the allocator reuses instead of mapping
      fresh pages), each with the fixed-width ``embedding_bag`` table that sums every output
      row's products in kernel-offset order: a reduction with no scatter, so no write collisions
      on any device. The feature gradient's tables (:attr:`in_bags`) are built on first use; a
      submanifold layer needs none (its feature gradient is the same rules with the mirrored,
      transposed weights).

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
    group_offsets: tuple[int, ...]
    group_counts: tuple[int, ...]
    block: int
    gather_in: torch.Tensor  # (n_blocks * block,) int64
    gather_out: torch.Tensor  # (n_blocks * block,) int64
    block_offsets: torch.Tensor  # (n_blocks,) int64
    group_blocks: torch.Tensor  # (G,) int64
    slices: tuple[RuleSlice, ...]

    @property
    def num_pairs(self) -> int:
        """All ``(i, o, k)`` pairs, a submanifold layer's centre included."""
        return sum(self.group_counts) + (int(self.in_indices.shape[0]) if self.subm else 0)

    @functools.cached_property
    def in_bags(self) -> tuple[torch.Tensor, ...]:
        """Per slice, ``(N_in, width)``: each input row's block rows, as ``out_bags`` is each
        output row's (the feature gradient's reduction of a regular conv)."""
        num_in = int(self.in_indices.shape[0])
        return tuple(
            _bag_table(self.gather_in, self.group_blocks, self.block, part, num_in)
            for part in self.slices
        )

    @property
    def pairs(self) -> tuple[tuple[torch.Tensor, torch.Tensor], ...]:
        """``pairs[k] = (in_rows, out_rows)`` for each kernel offset ``k`` in the weight's order
        (a view for tests and tools; the convolution reads the batched layout)."""
        num_offsets = math.prod(self.kernel_size)
        empty = self.gather_in.new_zeros(0)
        pairs = [(empty, empty)] * num_offsets
        start = 0
        for k, count, blocks in zip(
            self.group_offsets, self.group_counts, self.group_blocks.tolist()
        ):  # each group's pairs, then its padding rows
            rows = slice(start, start + count)
            pairs[k] = (self.gather_in[rows], self.gather_out[rows])
            start += blocks * self.block
        if self.subm:
            rows = torch.arange(self.in_indices.shape[0], device=self.gather_in.device)
            pairs[num_offsets // 2] = (rows, rows)
        return tuple(pairs)


def _kernel_offsets(kernel_size: tuple[int, int, int], device: torch.device) -> torch.Tensor:
    """``(K, 3)`` kernel positions ``(kz, ky, kx)`` in the weight's ``(kD, kH, kW)`` order."""
    grids = torch.meshgrid(*(torch.arange(k, device=device) for k in kernel_size), indexing="ij")
    return torch.stack([g.reshape(-1) for g in grids], dim=1)


#: gathered rows (elements) per slice of kernel offsets on the CPU: a few MB, see IndicePairs
_CPU_SLICE_ELEMENTS = 1 << 21


def _block_size(num_pairs: int, num_groups: int, channels: int) -> int:
    """Rows per GEMM block: large enough that the per-block weight copies stay small beside the
    gathered rows (``block >= 2 * channels``), small enough that the padding of each group to a
    whole block (half a block per group on average) stays a small share of the pairs."""
    want = max(num_pairs // (8 * max(num_groups, 1)), 2 * channels, 16)
    return min(1 << (want.bit_length() - 1), 1024)


def _bag_table(
    gather: torch.Tensor, group_blocks: torch.Tensor, block: int, part: RuleSlice, num: int
) -> torch.Tensor:
    """``(num, width)``: for each of ``num`` rows and each group of slice ``part``, the block
    row (relative to the slice) that ``gather`` sends to it, else ``part.pad``. Padding block rows
    (``gather == num``) land in a dropped extra row."""
    device = gather.device
    width = part.groups.stop - part.groups.start
    column = torch.arange(width, device=device).repeat_interleave(
        group_blocks[part.groups], output_size=part.blocks.stop - part.blocks.start
    )  # (blocks,) each block's group within the slice
    rows = gather[part.rows].view(-1, block)  # (blocks, block)
    at = (rows * width + column[:, None]).view(-1)
    table = torch.full(((num + 1) * width,), part.pad, dtype=torch.int32, device=device)
    table.index_copy_(0, at, torch.arange(at.numel(), dtype=torch.int32, device=device))
    return table[: num * width].view(num, width)


def _batched_rules(
    in_rows: Sequence[torch.Tensor],
    out_rows: Sequence[torch.Tensor],
    group_offsets: list[int],
    group_counts: list[int],
    num_in: int,
    num_out: int,
    channels: int,
    mirrored: bool = False,
) -> dict:
    """The batched layout of :class:`IndicePairs` from the pairs ``in_rows`` / ``out_rows``
    (each a list of consecutive parts, ``(P,)`` in all), listed in groups of one kernel offset
    each (``group_offsets[g]``, distinct, ``group_counts[g]`` pairs each,
    ``P = sum(group_counts)``); each output row sums its products in the groups' order.
    ``mirrored``: the second half of the groups lists the first half's pairs reversed, group by
    group (a submanifold layer); when the layer takes more than one slice, the second half's
    slices then mirror the first half's."""
    device = in_rows[0].device
    num_pairs = sum(int(rows.numel()) for rows in in_rows)
    num_groups = len(group_offsets)
    block = _block_size(num_pairs, num_groups, channels)
    # every non-empty group ends in a padding row: the slices' pad (see RuleSlice)
    blocks = [(c + block) // block if c else 0 for c in group_counts]
    counts = torch.tensor(group_counts, dtype=torch.long, device=device)
    group_blocks = torch.tensor(blocks, dtype=torch.long, device=device)
    starts = torch.cumsum(counts, 0) - counts
    padded_starts = (torch.cumsum(group_blocks, 0) - group_blocks) * block
    slot = torch.arange(num_pairs, device=device)
    slot += (padded_starts - starts).repeat_interleave(counts, output_size=num_pairs)
    num_rows = sum(blocks) * block
    gather_in = torch.full((num_rows,), num_in, dtype=torch.long, device=device)
    for rows, at in zip(in_rows, slot.split([int(r.numel()) for r in in_rows])):
        gather_in.index_copy_(0, at, rows)
    gather_out = torch.full((num_rows,), num_out, dtype=torch.long, device=device)
    for rows, at in zip(out_rows, slot.split([int(r.numel()) for r in out_rows])):
        gather_out.index_copy_(0, at, rows)
    offsets = torch.tensor(group_offsets, dtype=torch.long, device=device)
    block_offsets = offsets.repeat_interleave(group_blocks, output_size=sum(blocks))

    # cut the groups into runs of about _CPU_SLICE_ELEMENTS gathered elements (one on a GPU);
    # mirrored: the second half's groups mirror the first's, and are cut alike
    budget = _CPU_SLICE_ELEMENTS // max(channels, 1) if device.type == "cpu" else num_rows
    mirrored = mirrored and num_rows > budget
    cut_groups = num_groups // 2 if mirrored else num_groups
    cuts, rows = [0], 0
    for g, n in enumerate(blocks[:cut_groups]):
        if rows and rows + n * block > budget:
            cuts.append(g)
            rows = 0
        rows += n * block
    cuts.append(cut_groups)
    if mirrored:
        cuts += [cut_groups + g for g in cuts[1:]]
    slices, block_start = [], 0
    for g0, g1 in zip(cuts[:-1], cuts[1:]):
        n = sum(blocks[g0:g1])
        if n == 0:  # only empty groups
            continue
        row0 = block_start * block
        part = RuleSlice(
            slice(g0, g1), slice(row0, row0 + n * block),
            slice(block_start, block_start + n), n * block - 1, gather_out.new_zeros(0),
        )  # fmt: skip
        table = _bag_table(gather_out, group_blocks, block, part, num_out)
        slices.append(dataclasses.replace(part, out_bags=table))
        block_start += n
    return {
        "group_offsets": tuple(group_offsets),
        "group_counts": tuple(group_counts),
        "block": block,
        "gather_in": gather_in,
        "gather_out": gather_out,
        "block_offsets": block_offsets,
        "group_blocks": group_blocks,
        "slices": tuple(slices),
    }


@functools.lru_cache(maxsize=8)
def _occupancy_code(device: torch.device) -> torch.Tensor:
    """``code[byte * 8 + bit]``: whether bit ``bit`` of ``byte`` is set (bit 0 of the code) and
    how many lower bits are (the rest): a cell's presence and rank within its 8-cell word."""
    byte = torch.arange(256, device=device)[:, None]
    bit = torch.arange(8, device=device)[None, :]
    below = torch.zeros_like(byte * bit)
    for b in range(8):
        below += ((byte >> b) & 1) * (b < bit)
    return ((below << 1) | ((byte >> bit) & 1)).reshape(-1).to(torch.uint8)


def _subm_pairs(
    indices: torch.Tensor,
    spatial_shape: tuple[int, int, int],
    kernel_size: tuple[int, int, int],
    dilation: tuple[int, int, int],
    channels: int,
) -> IndicePairs:
    """Submanifold rules: output sites are the input sites; kernel centred on each site.

    Sites are looked up in an occupancy bitmap of the grid padded by the kernel's reach (so a
    neighbour key never wraps into another row and needs no bounds test): one bit per cell in
    8-cell words, and the sorted position of each word's first site; a neighbour is present when
    its bit is set, at that position plus the set bits below it in its word. The kernel sizes are
    odd (``SubMConv3d`` checks), so the offsets pair up around the centre: when site ``i`` feeds
    ``o`` through offset ``d``, ``o`` feeds ``i`` through ``-d``; only half the offsets are looked
    up (the mirror of flat offset ``k`` is ``K - 1 - k``) and the centre is not listed.
    """
    device = indices.device
    num_offsets = math.prod(kernel_size)
    centre = num_offsets // 2
    reach = [(k // 2) * d for k, d in zip(kernel_size, dilation)]
    padded = [n + 2 * r for n, r in zip(spatial_shape, reach)]
    shifted = indices.long() + torch.tensor([0, *reach], device=device)
    sorted_keys, order = torch.sort(_linear_keys(shifted, padded))
    num = int(sorted_keys.numel())
    deltas = _kernel_offsets(kernel_size, device) - torch.tensor(kernel_size, device=device) // 2
    deltas = deltas * torch.tensor(dilation, device=device)
    shifts = (deltas[:centre, 0] * padded[1] + deltas[:centre, 1]) * padded[2] + deltas[:centre, 2]
    if num:
        last = int(sorted_keys[-1])
        num_words = last // 8 + 1
        if last < 2**31:  # the neighbours' keys lie in [0, last]: half the memory traffic
            sorted_keys, shifts = sorted_keys.int(), shifts.int()
        word = sorted_keys >> 3
        bits = torch.zeros(num_words, dtype=torch.uint8, device=device)
        # distinct bits: the sum is their OR
        bits.index_add_(0, word, (1 << (sorted_keys & 7)).to(torch.uint8))
        starts = torch.ones(num, dtype=torch.bool, device=device)
        starts[1:] = word[1:] != word[:-1]
        at = torch.nonzero(starts, as_tuple=True)[0]
        first = torch.empty(num_words, dtype=torch.int32, device=device)  # read at set bits only
        first.index_copy_(0, word.index_select(0, at).long(), at.int())
        # the first half's shifts are negative and the padding keeps every neighbour in the grid
        neighbour = (sorted_keys[None, :] + shifts[:, None]).view(-1)  # (K // 2 * N,)
        neighbour_word = neighbour >> 3
        code = bits.index_select(0, neighbour_word).to(neighbour.dtype).mul_(8)
        code = _occupancy_code(device).index_select(0, code.add_(neighbour & 7))
        hit = torch.nonzero(code & 1, as_tuple=True)[0]  # offset-major, site order within
        half = torch.div(hit, num, rounding_mode="floor")
        site = hit - half * num
        found = first.index_select(0, neighbour_word.index_select(0, hit))
        found = found.long().add_(code.index_select(0, hit) >> 1)
        counts = torch.bincount(half, minlength=centre).tolist()
        near, here = order.index_select(0, found), order.index_select(0, site)
    else:
        counts = [0] * centre
        near = here = order
    # offset k < centre reads the neighbour into the site; its mirror K - 1 - k the site into
    # the neighbour
    rules = _batched_rules(
        [near, here], [here, near],
        list(range(centre)) + list(range(num_offsets - 1, centre, -1)), counts + counts,
        num, num, channels, mirrored=True,
    )  # fmt: skip
    return IndicePairs(
        indices, indices, spatial_shape, spatial_shape, kernel_size, dilation, True, **rules
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
    channels: int,
) -> IndicePairs:
    """Regular sparse conv rules: every output site some input reaches, sorted by linear index."""
    device = indices.device
    out_shape = conv_output_shape(spatial_shape, kernel_size, stride, padding, dilation)
    idx = indices.long()
    # per axis (each on its own): input coordinate i reaches output o through kernel position
    # k when o * s - p + k * d == i
    od, oh, ow = out_shape
    num_cells = (int(idx[:, 0].max()) + 1 if idx.shape[0] else 1) * od * oh * ow
    # the output keys lie in [0, num_cells): int32 where they fit, half the traffic
    key_dtype = torch.int32 if num_cells <= 2**31 else torch.long
    scale = (oh * ow, ow, 1)  # each axis' share of the output's linear key
    key_axis, valid_axis = [], []
    for axis, (k, s, p, d, n_out) in enumerate(
        zip(kernel_size, stride, padding, dilation, out_shape)
    ):
        num = idx[None, :, 1 + axis] + p - torch.arange(k, device=device)[:, None] * d  # (k, N)
        o = torch.div(num, s, rounding_mode="floor")
        key_axis.append((o * scale[axis]).to(key_dtype))
        valid_axis.append((o * s == num) & (o >= 0) & (o < n_out))
    kd, kh, kw = kernel_size
    num_offsets = kd * kh * kw
    valid = (
        valid_axis[0][:, None, None] & valid_axis[1][None, :, None] & valid_axis[2][None, None, :]
    ).view(-1)  # (K * N,), K in the weight's (kD, kH, kW) order
    key_z = key_axis[0] + (idx[None, :, 0] * (od * oh * ow)).to(key_dtype)
    keys = ((key_z[:, None] + key_axis[1][None, :])[:, :, None] + key_axis[2][None, None, :]).view(
        -1
    )  # (K * N,) output keys
    hit = torch.nonzero(valid, as_tuple=True)[0]  # offset-major, input order within
    k_ids = torch.div(hit, idx.shape[0], rounding_mode="floor")
    in_rows = hit - k_ids * idx.shape[0]
    hit_keys = keys.index_select(0, hit)
    # a sort of the pairs' int32 keys beats flagging the reached cells in a grid-sized bitmap
    # and ranking them (and does not grow with the grid)
    out_keys, out_rows = torch.unique(hit_keys, sorted=True, return_inverse=True)
    out_keys = out_keys.long()
    # decode the sorted keys back into [b, z, y, x]
    out_indices = torch.stack(
        [
            out_keys // (od * oh * ow),
            out_keys // (oh * ow) % od,
            out_keys // ow % oh,
            out_keys % ow,
        ],
        dim=1,
    ).to(torch.int32)
    # nonzero lists (k, n) row-major: each offset's pairs are one group
    counts = torch.bincount(k_ids, minlength=num_offsets).tolist()
    rules = _batched_rules(
        [in_rows], [out_rows], list(range(num_offsets)), counts, idx.shape[0], out_keys.shape[0],
        channels,
    )  # fmt: skip
    return IndicePairs(
        indices, out_indices, spatial_shape, out_shape, kernel_size, dilation, False, **rules
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
        channels = max(self.in_channels, self.out_channels)
        if self.subm:
            rules = _subm_pairs(x.indices, shape, self.kernel_size, self.dilation, channels)
        else:
            rules = _regular_pairs(
                x.indices,
                shape,
                self.kernel_size,
                self.stride,
                self.padding,
                self.dilation,
                channels,
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
        """The output features ``(N_out, out)`` of ``features`` ``(N_in, in)`` under ``rules``
        (:class:`_GatherGemmReduce`)."""
        weight = self.weight.reshape(self.out_channels, -1, self.in_channels)  # (out, K, in)
        out = _GatherGemmReduce.apply(features, weight, rules)
        if self.bias is not None:
            out = out + self.bias
        return out


class _GatherGemmReduce(torch.autograd.Function):
    """``out[o] = sum_k W_k x[i]`` over the pairs ``(i, o, k)`` of ``rules`` in a number of ops
    that does not grow with the number of kernel offsets: per slice of offsets
    (:class:`IndicePairs`; one on a GPU) one gather of the pairs' input rows into blocks of one
    offset each, one ``bmm`` of every block with its offset's weight, one ``embedding_bag``
    summing each output row's products in its groups' order; plus one GEMM for a submanifold
    layer's centre. The backward has the same form: the feature gradient gathers the output
    gradient's rows and sums them per input row (a submanifold layer: its forward with the
    mirrored, transposed weights); the weight gradient is one ``bmm`` of the
    gathered blocks and a sum over each offset's blocks (``segment_reduce``).

    No op writes two values into one place, so the result is deterministic on CPU and GPU, in
    torch's deterministic mode or not."""

    @staticmethod
    def forward(ctx, features, weight, rules):  # features (N_in, in), weight (out, K, in)
        rows = _with_zero_row(features)
        weight_t = weight.permute(1, 2, 0)  # (K, in, out)
        out = features.new_zeros((rules.out_indices.shape[0], weight.shape[0]))
        for part in rules.slices:
            out += _sum_blocks(
                rows, weight_t, rules.gather_in[part.rows], rules.block,
                rules.block_offsets[part.blocks], part.out_bags,
            )  # fmt: skip
        if rules.subm:
            out.addmm_(features, weight[:, weight.shape[1] // 2].t())
        ctx.save_for_backward(features, weight)
        ctx.rules = rules
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        features, weight = ctx.saved_tensors
        rules = ctx.rules
        need_features, need_weight = ctx.needs_input_grad[:2]
        grad_out = grad_out.contiguous()
        grad_rows, rows = _with_zero_row(grad_out), _with_zero_row(features)
        weight_oi = weight.permute(1, 0, 2)  # (K, out, in)
        centre = weight.shape[1] // 2
        grad_features = torch.zeros_like(features) if need_features else None
        grad_weight = torch.zeros_like(weight) if need_weight else None
        if rules.subm:
            _subm_backward(grad_rows, rows, weight, rules, grad_features, grad_weight)
        else:
            in_bags = rules.in_bags if need_features else None
            for s, part in enumerate(rules.slices):
                gather_out = rules.gather_out[part.rows]
                if need_features:
                    grad_features += _sum_blocks(
                        grad_rows, weight_oi, gather_out, rules.block,
                        rules.block_offsets[part.blocks], in_bags[s],
                    )  # fmt: skip
                if need_weight:
                    blocks_in = rows.index_select(0, rules.gather_in[part.rows])
                    blocks_out = grad_rows.index_select(0, gather_out)
                    _weight_grad(blocks_out, blocks_in, rules, part.groups, grad_weight)
        if rules.subm and need_features:
            grad_features.addmm_(grad_out, weight[:, centre])
        if rules.subm and need_weight:
            grad_weight[:, centre] = grad_out.t() @ features
        return grad_features, grad_weight, None


def _subm_backward(grad_rows, rows, weight, rules, grad_features, grad_weight) -> None:
    """A submanifold layer's backward into ``grad_features`` / ``grad_weight`` (either None).

    Its pairs are symmetric: ``(i, o, k)`` and ``(o, i, K - 1 - k)``, the second half of its
    slices holding the first half's pairs reversed, row for row. So the feature gradient is the
    forward with the mirrored, transposed weights on the same tables, and the output gradient
    gathered at one slice's input rows is what the weight gradient of its mirror slice reads at
    that slice's output rows: one gather of the output gradient serves both. In one slice (a
    GPU) the two halves of its rows mirror each other."""
    weight_mirror = weight.permute(1, 0, 2).flip(0)  # (K, out, in), offset k holds K - 1 - k's
    if len(rules.slices) == 1:
        (part,) = rules.slices
        grad = grad_rows.index_select(0, rules.gather_in[part.rows])
        if grad_features is not None:
            grad_features += _reduce_blocks(
                grad, weight_mirror, rules.block, rules.block_offsets[part.blocks], part.out_bags
            )
        if grad_weight is not None:
            blocks_in = rows.index_select(0, rules.gather_in[part.rows])
            half_rows, half_groups = grad.shape[0] // 2, len(rules.group_counts) // 2
            groups = (slice(0, half_groups), slice(half_groups, 2 * half_groups))
            _weight_grad(grad[half_rows:], blocks_in[:half_rows], rules, groups[0], grad_weight)
            _weight_grad(grad[:half_rows], blocks_in[half_rows:], rules, groups[1], grad_weight)
        return
    half = len(rules.slices) // 2
    for pair in zip(rules.slices[:half], rules.slices[half:]):
        grads = [grad_rows.index_select(0, rules.gather_in[part.rows]) for part in pair]
        if grad_features is not None:
            for part, grad in zip(pair, grads):
                grad_features += _reduce_blocks(
                    grad, weight_mirror, rules.block, rules.block_offsets[part.blocks],
                    part.out_bags,
                )  # fmt: skip
        if grad_weight is not None:
            for part, grad in zip(pair, reversed(grads)):
                blocks_in = rows.index_select(0, rules.gather_in[part.rows])
                _weight_grad(grad, blocks_in, rules, part.groups, grad_weight)


def _weight_grad(blocks_out, blocks_in, rules, groups: slice, grad_weight) -> None:
    """Writes the weight gradient of the offsets of ``groups`` into ``grad_weight`` ``(out, K,
    in)`` from its gathered output-gradient and input rows ``(rows, out)`` / ``(rows, in)``: one
    ``bmm`` of the blocks, summed over each group's blocks."""
    shape = (-1, rules.block)
    blocks_out = blocks_out.view(*shape, blocks_out.shape[1])
    blocks_in = blocks_in.view(*shape, blocks_in.shape[1])
    partial = torch.bmm(blocks_out.transpose(1, 2), blocks_in)  # (blocks, out, in)
    per_group = torch.segment_reduce(
        partial.flatten(1), "sum", lengths=rules.group_blocks[groups], unsafe=True
    )  # (groups, out * in)
    offsets = torch.tensor(rules.group_offsets[groups], device=grad_weight.device)
    grad_weight[:, offsets] = per_group.view(-1, *partial.shape[1:]).transpose(0, 1)


def _with_zero_row(rows: torch.Tensor) -> torch.Tensor:
    """``(N, C)`` -> ``(N + 1, C)``: row ``N``, zeros, is what the blocks' padding rows read."""
    return torch.cat([rows, rows.new_zeros((1, rows.shape[1]))])


def _sum_blocks(rows, weight, gather, block, block_offsets, bags):
    """``rows`` ``(N + 1, C)`` gathered by ``gather`` into blocks, each block times its offset's
    ``weight`` ``(K, C, C')``, the products summed into one row per row of ``bags`` (a
    ``(num_bags, width)`` table of block rows): ``(num_bags, C')``."""
    return _reduce_blocks(rows.index_select(0, gather), weight, block, block_offsets, bags)


def _reduce_blocks(gathered, weight, block, block_offsets, bags):
    """:func:`_sum_blocks` on rows already gathered, ``(n_blocks * block, C)``."""
    blocks = gathered.view(-1, block, gathered.shape[1])  # (blocks, block, C)
    products = torch.bmm(blocks, weight.index_select(0, block_offsets))
    return torch.nn.functional.embedding_bag(bags, products.view(-1, weight.shape[2]), mode="sum")


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
