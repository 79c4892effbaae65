"""Sparse conv vs a dense ``torch.nn.functional.conv3d`` reference on small grids."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from pcdet_atlas.ops import spconv
from pcdet_atlas.ops.spconv import (
    SparseConv3d,
    SparseConvTensor,
    SparseModule,
    SparseSequential,
    SubMConv3d,
)
from pcdet_atlas.utils.common import deterministic_algorithms
from tests.device_params import DEVICES


def random_sparse(
    shape, batch_size, channels, n_per_batch, seed=0, dtype=torch.float64, device="cpu"
):
    """Distinct random sites per batch, rows shuffled (not sorted) so order matters."""
    g = torch.Generator().manual_seed(seed)
    d, h, w = shape
    rows = []
    for b in range(batch_size):
        cells = torch.randperm(d * h * w, generator=g)[:n_per_batch]
        rows.append(
            torch.stack([torch.full_like(cells, b), cells // (h * w), cells // w % h, cells % w], 1)
        )
    indices = torch.cat(rows)[torch.randperm(batch_size * n_per_batch, generator=g)]
    features = torch.randn(indices.shape[0], channels, generator=g, dtype=dtype)
    return SparseConvTensor(
        features.to(device), indices.to(torch.int32).to(device), shape, batch_size
    )


def dense_weight(conv):
    return conv.weight.permute(0, 4, 1, 2, 3)  # (out, in, kD, kH, kW)


def dense_conv(conv, x, padding):
    out = F.conv3d(x.dense(), dense_weight(conv), conv.bias, conv.stride, padding, conv.dilation)
    return out  # (B, C, D', H', W')


def at_sites(dense, indices):
    idx = indices.long()
    return dense[idx[:, 0], :, idx[:, 1], idx[:, 2], idx[:, 3]]  # (N, C)


def reached_sites(conv, x):
    """Output sites any active input reaches: dense conv of the occupancy with a ones kernel."""
    occ = torch.zeros((x.batch_size, 1, *x.spatial_shape), dtype=torch.float64)
    idx = x.indices.long().cpu()
    occ[idx[:, 0], 0, idx[:, 1], idx[:, 2], idx[:, 3]] = 1.0
    ones = torch.ones((1, 1, *conv.kernel_size), dtype=torch.float64)
    hit = F.conv3d(occ, ones, None, conv.stride, conv.padding, conv.dilation)[:, 0] > 0
    return torch.nonzero(hit).to(torch.int32)  # sorted by (b, z, y, x)


SUBM_CASES = [
    # shape, batch, kernel, padding, dilation
    ((5, 7, 6), 1, 3, 1, 1),
    ((5, 7, 6), 3, 3, 0, 1),  # padding is ignored by submanifold convs
    ((4, 9, 5), 2, (3, 1, 3), 0, 1),
    ((7, 7, 7), 2, 3, 1, 2),
    ((6, 5, 7), 2, 5, 2, 1),
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("shape,batch,kernel,padding,dilation", SUBM_CASES)
def test_subm_matches_dense_conv_masked_to_input_sites(
    device, shape, batch, kernel, padding, dilation
):
    x = random_sparse(shape, batch, 3, 25, device=device)
    conv = SubMConv3d(3, 4, kernel, padding=padding, dilation=dilation, bias=True)
    conv = conv.double().to(device)
    out = conv(x)
    centred = tuple(d * (k - 1) // 2 for k, d in zip(conv.kernel_size, conv.dilation))
    expected = at_sites(dense_conv(conv, x, centred), x.indices)
    assert torch.equal(out.indices, x.indices)  # input row order kept
    assert out.spatial_shape == list(shape)
    torch.testing.assert_close(out.features, expected)


@pytest.mark.parametrize(
    "kernel,dilation", [(3, 1), ((3, 1, 5), (1, 1, 2)), ((5, 3, 1), (1, 2, 1))]
)
def test_subm_rules_are_every_neighbour_pair(kernel, dilation):
    """The submanifold rules against a site dictionary: per kernel offset, exactly the pairs
    (input row, output row) whose sites differ by that offset (half the offsets are searched,
    the other half mirrored)."""
    x = random_sparse((6, 7, 8), 2, 1, 60, seed=11)
    conv = SubMConv3d(1, 1, kernel, dilation=dilation)
    rules = conv._rules(x)
    site_row = {tuple(site): row for row, site in enumerate(x.indices.tolist())}
    centre = [k // 2 for k in conv.kernel_size]
    kd, kh, kw = conv.kernel_size
    for k, (in_rows, out_rows) in enumerate(rules.pairs):
        offset = (k // (kh * kw), k // kw % kh, k % kw)
        delta = [(o - c) * d for o, c, d in zip(offset, centre, conv.dilation)]
        want = set()
        for out_row, (b, z, y, w) in enumerate(x.indices.tolist()):
            in_row = site_row.get((b, z + delta[0], y + delta[1], w + delta[2]))
            if in_row is not None:
                want.add((in_row, out_row))
        assert set(zip(in_rows.tolist(), out_rows.tolist())) == want, offset
        assert len(want) == in_rows.numel()  # no pair twice


REGULAR_CASES = [
    # shape, batch, kernel, stride, padding, dilation
    ((5, 7, 6), 1, 3, 1, 0, 1),
    ((5, 7, 6), 2, 3, 2, 1, 1),
    ((9, 8, 7), 2, 3, 2, 0, 1),
    ((7, 6, 5), 3, 3, 1, 2, 2),
    ((9, 6, 5), 2, (3, 1, 1), (2, 1, 1), 0, 1),  # OpenPCDet's conv_out
    ((6, 6, 6), 2, 2, 2, 0, 1),
    ((8, 7, 9), 1, (3, 2, 3), (1, 2, 3), (1, 0, 2), (2, 1, 1)),
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("shape,batch,kernel,stride,padding,dilation", REGULAR_CASES)
def test_regular_matches_dense_conv_at_reached_sites(
    device, shape, batch, kernel, stride, padding, dilation
):
    x = random_sparse(shape, batch, 3, 30, seed=1, device=device)
    conv = SparseConv3d(3, 4, kernel, stride, padding, dilation, bias=True).double().to(device)
    out = conv(x)
    dense = dense_conv(conv, x, conv.padding)
    assert out.spatial_shape == list(dense.shape[2:])
    # exactly the reached sites, in linear-index order
    assert torch.equal(out.indices.cpu(), reached_sites(conv, x))
    torch.testing.assert_close(out.features, at_sites(dense, out.indices))


def test_output_spatial_shape_formula():
    x = random_sparse((41, 16, 16), 1, 2, 10, dtype=torch.float32)
    conv = SparseConv3d(2, 2, (3, 1, 1), (2, 1, 1), padding=0)
    # floor((41 + 0 - 2 - 1) / 2) + 1 = 20
    assert conv(x).spatial_shape == [20, 16, 16]
    conv = SparseConv3d(2, 2, 3, 2, padding=1)
    assert conv(x).spatial_shape == [21, 8, 8]


def test_indice_key_reuses_the_same_rules_object():
    x = random_sparse((6, 7, 5), 2, 3, 20)
    first = SubMConv3d(3, 4, 3, indice_key="subm1").double()
    second = SubMConv3d(4, 4, 3, indice_key="subm1").double()
    y = first(x)
    rules = x.indice_dict["subm1"]
    z = second(y)
    assert y.indice_dict is x.indice_dict and z.indice_dict is x.indice_dict
    assert x.indice_dict["subm1"] is rules  # not rebuilt
    fresh = SubMConv3d(4, 4, 3).double()
    fresh.load_state_dict(second.state_dict())
    torch.testing.assert_close(
        z.features, fresh(SparseConvTensor(y.features, y.indices, y.spatial_shape, 2)).features
    )


@pytest.mark.parametrize("kernel,dilation", [(5, 1), (3, 2), ((3, 3, 1), 1)])
def test_indice_key_with_another_kernel_or_dilation_is_an_error(kernel, dilation):
    x = random_sparse((6, 7, 5), 1, 3, 20)
    y = SubMConv3d(3, 3, 3, indice_key="k").double()(x)
    with pytest.raises(ValueError, match="indice_key 'k' was built for kernel .3, 3, 3., "
                       "dilation .1, 1, 1.; this layer has"):  # fmt: skip
        SubMConv3d(3, 3, kernel, dilation=dilation, indice_key="k").double()(y)


@pytest.mark.parametrize("kernel", [2, (3, 4, 3), (1, 1, 2)])
def test_subm_even_kernel_is_an_error(kernel):
    """A submanifold kernel is centred on each site: an even size has no centre (spconv
    refuses it too)."""
    with pytest.raises(ValueError, match="SubMConv3d: kernel_size must be odd .* got"):
        SubMConv3d(1, 1, kernel)
    SparseConv3d(1, 1, kernel)  # a regular sparse conv takes any size


@pytest.mark.parametrize("subm", [True, False])
def test_gradients_match_dense_reference(subm):
    x = random_sparse((5, 6, 5), 2, 3, 20, seed=3)
    feats = x.features.clone().requires_grad_(True)
    x = x.replace_feature(feats)
    if subm:
        conv = SubMConv3d(3, 2, 3, bias=True).double()
        padding = (1, 1, 1)
    else:
        conv = SparseConv3d(3, 2, 3, stride=2, padding=1, bias=True).double()
        padding = conv.padding
    out = conv(x)
    g = torch.Generator().manual_seed(5)
    upstream = torch.randn(out.features.shape, generator=g, dtype=torch.float64)
    (out.features * upstream).sum().backward()
    sparse_grads = (feats.grad.clone(), conv.weight.grad.clone(), conv.bias.grad.clone())

    feats_ref = x.features.detach().clone().requires_grad_(True)
    weight_ref = conv.weight.detach().clone().requires_grad_(True)
    bias_ref = conv.bias.detach().clone().requires_grad_(True)
    dense_in = SparseConvTensor(feats_ref, x.indices, x.spatial_shape, 2).dense()
    dense_out = F.conv3d(
        dense_in, weight_ref.permute(0, 4, 1, 2, 3), bias_ref, conv.stride, padding
    )
    (at_sites(dense_out, out.indices) * upstream).sum().backward()
    for got, want in zip(sparse_grads, (feats_ref.grad, weight_ref.grad, bias_ref.grad)):
        torch.testing.assert_close(got, want)


@pytest.mark.parametrize("conv_cls", [SubMConv3d, SparseConv3d])
def test_many_slices_give_the_one_slice_result(conv_cls, monkeypatch):
    """Cut into many slices (the CPU's few-MB runs; a submanifold layer's second half mirroring
    its first, whose backward shares one gather between a slice and its mirror), a layer gives
    the forward and gradients of its one-slice form."""
    x = random_sparse((6, 7, 5), 2, 3, 80, seed=7)
    conv = conv_cls(3, 4, 3).double()
    g = torch.Generator().manual_seed(2)
    upstream = torch.randn(conv(x).features.shape, generator=g, dtype=torch.float64)

    def run():
        feats = x.features.clone().requires_grad_(True)
        conv.weight.grad = None
        out = conv(x.replace_feature(feats))
        (out.features * upstream).sum().backward()
        return len(conv._rules(x).slices), out.features, feats.grad, conv.weight.grad

    one = run()
    monkeypatch.setattr(spconv, "_CPU_SLICE_ELEMENTS", 64)
    many = run()
    assert one[0] == 1 and many[0] >= 4
    if conv_cls is SubMConv3d:  # the second half of the slices mirrors the first
        assert many[0] % 2 == 0
    for got, want in zip(many[1:], one[1:]):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("conv_cls", [SubMConv3d, SparseConv3d])
def test_gradcheck_features_and_weight(conv_cls):
    """The conv's own backward against finite differences, for the features and the weight."""
    x = random_sparse((4, 4, 4), 1, 2, 8, seed=7)
    conv = conv_cls(2, 2, 3, padding=1, bias=True).double()
    feats = x.features.clone().requires_grad_(True)
    weight = conv.weight.detach().clone().requires_grad_(True)

    def run(f, w):
        params = {"weight": w, "bias": conv.bias}
        return torch.func.functional_call(conv, params, (x.replace_feature(f),)).features

    assert torch.autograd.gradcheck(run, (feats, weight))


@pytest.mark.parametrize("conv_cls", [SubMConv3d, SparseConv3d])
def test_empty_input(conv_cls):
    x = SparseConvTensor(torch.zeros(0, 3), torch.zeros(0, 4, dtype=torch.int32), (5, 6, 7), 2)
    out = conv_cls(3, 4, 3)(x)
    assert out.features.shape == (0, 4)
    assert out.indices.shape == (0, 4)
    assert out.dense().shape[:2] == (2, 4)


RULE_CASES = [
    (SubMConv3d, {"kernel_size": 3}),
    (SubMConv3d, {"kernel_size": 3, "dilation": 2}),
    (SparseConv3d, {"kernel_size": 3, "stride": 2, "padding": 1}),
    (SparseConv3d, {"kernel_size": (3, 1, 1), "stride": (2, 1, 1)}),
]


@pytest.mark.parametrize("conv_cls,kwargs", RULE_CASES)
def test_rows_never_repeat_within_a_kernel_offset(conv_cls, kwargs):
    """What makes the scatter collision-free, hence deterministic without sorting (also in torch's
    deterministic mode): within one offset an input row feeds one output row and an output row
    reads one input row."""
    x = random_sparse((6, 7, 5), 2, 2, 60, seed=11)
    rules = conv_cls(2, 2, **kwargs)._rules(x)
    assert sum(in_rows.numel() for in_rows, _ in rules.pairs) > 60
    for in_rows, out_rows in rules.pairs:
        assert in_rows.unique().numel() == in_rows.numel()
        assert out_rows.unique().numel() == out_rows.numel()


@pytest.mark.parametrize("conv_cls,kwargs", RULE_CASES)
def test_reduction_tables_list_every_pair_once_and_pad_reads_zero(conv_cls, kwargs):
    """Each slice's fixed-width table names every pair's block row once, in its output row;
    the other entries name the slice's pad row, a padding row (it reads the zero row, so its
    product adds nothing)."""
    x = random_sparse((6, 7, 5), 2, 2, 60, seed=11)
    rules = conv_cls(2, 2, **kwargs)._rules(x)
    num_in, num_out = rules.in_indices.shape[0], rules.out_indices.shape[0]
    listed = 0
    for part in rules.slices:
        row0 = part.rows.start
        assert int(rules.gather_in[row0 + part.pad]) == num_in
        assert int(rules.gather_out[row0 + part.pad]) == num_out
        table = part.out_bags.long()
        real = table != part.pad
        assert real.sum() == (rules.gather_out[part.rows] < num_out).sum()
        out_of_entry = torch.arange(num_out)[:, None].expand_as(table)[real]
        assert torch.equal(rules.gather_out[row0 + table[real]], out_of_entry)
        listed += int(real.sum())
    assert listed == sum(rules.group_counts) > 60


def test_regular_rules_on_a_grid_past_int32_keys_match_a_small_grid():
    """A grid of more than 2**31 output cells takes int64 keys: the same sites near its far
    corner give the same features, shifted, as on a small grid (int32 keys)."""
    x = random_sparse((6, 7, 5), 2, 3, 40, seed=5)
    inner = x.indices + torch.tensor([0, 1, 1, 1], dtype=torch.int32)  # reach stays in the grid
    small = SparseConvTensor(x.features, inner, (8, 9, 7), 2)
    shift = torch.tensor([0, 1992, 1991, 1993], dtype=torch.int32)
    big = SparseConvTensor(x.features, inner + shift, (2000, 2000, 2000), 2)
    conv = SparseConv3d(3, 4, 3, padding=1).double()
    want, got = conv(small), conv(big)
    assert torch.equal(got.indices, want.indices + shift)
    torch.testing.assert_close(got.features, want.features, rtol=0, atol=0)


@pytest.fixture
def restore_deterministic_mode(monkeypatch):
    """Leaves torch's deterministic mode as it found it; cuBLAS needs a fixed workspace in it."""
    monkeypatch.setenv("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    with deterministic_algorithms(False):
        yield


def conv_step(conv, x):
    """Forward and backward of ``conv`` on ``x``: output, feature and weight gradients."""
    feats = x.features.clone().requires_grad_(True)
    conv.zero_grad()
    out = conv(x.replace_feature(feats)).features
    out.square().sum().backward()
    return out.detach(), feats.grad, conv.weight.grad.clone()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("warn_only", [False, True])
@pytest.mark.parametrize("conv_cls", [SubMConv3d, SparseConv3d])
def test_deterministic_mode_gives_the_same_bits_and_stays_on(
    device, warn_only, conv_cls, restore_deterministic_mode
):
    x = random_sparse((6, 7, 5), 2, 3, 40, seed=13, dtype=torch.float32, device=device)
    conv = conv_cls(3, 4, 3, padding=1, stride=1 if conv_cls is SubMConv3d else 2).to(device)
    torch.use_deterministic_algorithms(False)
    free = conv_step(conv, x)
    torch.use_deterministic_algorithms(True, warn_only=warn_only)
    strict = conv_step(conv, x)
    assert torch.are_deterministic_algorithms_enabled()
    assert torch.is_deterministic_algorithms_warn_only_enabled() == warn_only
    for got, want in zip(strict, free):
        assert torch.equal(got, want)


def aten_ops(fn) -> int:
    """aten ops ``fn`` runs, nested ones not counted (what a GPU would launch)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn()
    return sum(
        1
        for e in prof.events()
        if e.name.startswith("aten::")
        and (e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::"))
    )


@pytest.mark.parametrize("conv_cls", [SubMConv3d, SparseConv3d])
def test_ops_per_layer_do_not_grow_with_the_kernel_offsets(conv_cls):
    """One batched gather-GEMM-reduce over all offsets: a 5x5x5 kernel (125 offsets) runs the
    same number of ops as a 3x3x3 one (27) and a 3x1x1 one (3), rules, forward and backward."""
    x = random_sparse((9, 9, 9), 2, 3, 120, seed=5, dtype=torch.float32)
    counts = []
    for kernel in (3, 5, (3, 1, 1)):
        conv = conv_cls(3, 4, kernel, stride=1 if conv_cls is SubMConv3d else 2)
        assert len(conv._rules(x).slices) == 1
        counts.append(aten_ops(lambda conv=conv: conv_step(conv, x)))
    assert counts[0] == counts[1] == counts[2], counts


def test_state_dict_has_spconv_layout_and_loads_strict():
    block = SparseSequential(
        SubMConv3d(4, 16, 3, padding=1, bias=False, indice_key="subm1"),
        nn.BatchNorm1d(16),
        nn.ReLU(),
        SparseConv3d(16, 32, (3, 1, 1), (2, 1, 1), bias=True, indice_key="spconv_down2"),
    )
    shapes = {k: tuple(v.shape) for k, v in block.state_dict().items()}
    assert shapes["0.weight"] == (16, 3, 3, 3, 4)
    assert shapes["3.weight"] == (32, 3, 1, 1, 16)
    assert shapes["3.bias"] == (32,)
    assert [k for k in shapes if k.startswith(("0.", "3."))] == ["0.weight", "3.weight", "3.bias"]
    # a state_dict written by spconv 2.x is plain tensors of these shapes
    foreign = {k: torch.randn(v) if v else torch.tensor(3) for k, v in shapes.items()}
    twin = SparseSequential(
        SubMConv3d(4, 16, 3, padding=1, bias=False, indice_key="subm1"),
        nn.BatchNorm1d(16),
        nn.ReLU(),
        SparseConv3d(16, 32, (3, 1, 1), (2, 1, 1), bias=True, indice_key="spconv_down2"),
    )
    twin.load_state_dict(foreign, strict=True)
    assert torch.equal(twin[3].weight, foreign["3.weight"])
    with pytest.raises(RuntimeError, match="size mismatch"):
        bad = dict(foreign, **{"0.weight": foreign["0.weight"].permute(0, 4, 1, 2, 3)})
        twin.load_state_dict(bad, strict=True)


def test_bias_defaults_as_spconv():
    """spconv's convs carry a bias unless ``bias=False``: code ported from spconv that leaves
    it out must get the same parameters (and a strict load of its state_dict)."""
    for conv_cls in (SubMConv3d, SparseConv3d):
        assert conv_cls(4, 8, 3).bias.shape == (8,)
        assert conv_cls(4, 8, 3, bias=False).bias is None
        assert list(conv_cls(4, 8, 3, bias=False).state_dict()) == ["weight"]


def test_sparse_sequential_numbers_children_and_dispatches():
    class Double(SparseModule):
        def forward(self, x):
            assert isinstance(x, SparseConvTensor)
            return x.replace_feature(x.features * 2)

    seq = SparseSequential(Double(), nn.ReLU(), nn.Identity())
    assert [name for name, _ in seq.named_children()] == ["0", "1", "2"]
    assert isinstance(seq, SparseModule) and isinstance(seq[0], Double)
    x = random_sparse((4, 4, 4), 1, 2, 6)
    out = seq(x)
    assert isinstance(out, SparseConvTensor)
    assert torch.equal(out.indices, x.indices)
    torch.testing.assert_close(out.features, torch.relu(x.features * 2))


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="int32"):
        SparseConvTensor(torch.zeros(2, 3), torch.zeros(2, 4, dtype=torch.int64), (4, 4, 4), 1)
    with pytest.raises(ValueError, match="2 indices for 3 feature rows"):
        SparseConvTensor(torch.zeros(3, 3), torch.zeros(2, 4, dtype=torch.int32), (4, 4, 4), 1)
    x = random_sparse((4, 4, 4), 1, 2, 6)
    with pytest.raises(ValueError, match="expected 3 input channels, got 2"):
        SubMConv3d(3, 3, 3).double()(x)
    with pytest.raises(ValueError, match="too small"):
        SparseConv3d(2, 2, 5).double()(x)
    with pytest.raises(ValueError, match="padding must be >= 0"):
        SparseConv3d(2, 2, 3, padding=-1)


@pytest.mark.parametrize(
    "site", [[0, 4, 0, 0], [0, 0, 0, 5], [0, -1, 0, 0], [2, 0, 0, 0], [-1, 0, 0, 0]]
)
def test_out_of_range_indices_are_a_clear_error(site):
    # x = 5 on a W = 5 grid would alias (y + 1, x = 0) in the rules' linear keys
    indices = torch.tensor([[0, 1, 1, 1], site], dtype=torch.int32)
    with pytest.raises(ValueError, match="must lie in"):
        SparseConvTensor(torch.zeros(2, 3), indices, (4, 5, 5), 2)
    with pytest.raises(ValueError, match="spatial_shape"):
        SparseConvTensor(torch.zeros(0, 3), torch.zeros(0, 4, dtype=torch.int32), (4, 0, 5), 1)
