"""Exact rotated IoU and BEV NMS against slow, obvious references (shapely, a Python NMS); the
grouped sparse IoU against the dense one group by group."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from device_params import DEVICES
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon

from pcdet_atlas.ops.iou3d_nms import (
    boxes_aligned_iou3d,
    boxes_aligned_iou_bev,
    boxes_iou3d,
    boxes_iou3d_grouped,
    boxes_iou_bev,
    boxes_overlap_bev,
    nms_bev,
    nms_bev_per_class,
)


def _random_boxes(n: int, seed: int, spread: float = 4.0, offset: float = 0.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    b = torch.rand(n, 7, generator=g, dtype=torch.float64)
    b[:, :2] = (b[:, :2] * 2 - 1) * spread + offset
    b[:, 2] = b[:, 2] * 2 - 1
    b[:, 3:6] = b[:, 3:6] * 4 + 0.2
    b[:, 6] = (b[:, 6] * 2 - 1) * 2 * math.pi
    return b


def _polygon(box) -> Polygon:
    x, y, _, dx, dy, _, h = (float(v) for v in box[:7])
    c, s = math.cos(h), math.sin(h)
    pts = [(sx * dx / 2, sy * dy / 2) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    return Polygon([(x + c * px - s * py, y + s * px + c * py) for px, py in pts])


def _reference(a: torch.Tensor, b: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(BEV IoU, 3D IoU) from shapely polygons and the closed z-overlap, pair by pair."""
    bev = np.zeros((len(a), len(b)))
    iou3d = np.zeros((len(a), len(b)))
    for i, p in enumerate(a.tolist()):
        pa = _polygon(p)
        for j, q in enumerate(b.tolist()):
            pb = _polygon(q)
            inter = pa.intersection(pb).area
            bev[i, j] = inter / (pa.area + pb.area - inter)
            zo = max(
                0.0, min(p[2] + p[5] / 2, q[2] + q[5] / 2) - max(p[2] - p[5] / 2, q[2] - q[5] / 2)
            )
            vol = inter * zo
            iou3d[i, j] = vol / (p[3] * p[4] * p[5] + q[3] * q[4] * q[5] - vol)
    return bev, iou3d


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("offset", [0.0, 1e5])
def test_matches_shapely_on_random_boxes(device, offset):
    a = _random_boxes(40, seed=1, offset=offset).to(device)
    b = _random_boxes(50, seed=2, offset=offset).to(device)
    ref_bev, ref_3d = _reference(a.cpu(), b.cpu())
    assert (ref_bev > 0).mean() > 0.2  # the test exercises real overlaps
    np.testing.assert_allclose(boxes_iou_bev(a, b).cpu().numpy(), ref_bev, atol=1e-6, rtol=0)
    np.testing.assert_allclose(boxes_iou3d(a, b).cpu().numpy(), ref_3d, atol=1e-6, rtol=0)
    # aligned variants agree with the diagonal of the pairwise result
    n = 40
    diag_bev = boxes_aligned_iou_bev(a[:n], b[:n]).cpu().numpy()
    np.testing.assert_allclose(diag_bev, np.diag(ref_bev[:n, :n]), atol=1e-6, rtol=0)
    diag_3d = boxes_aligned_iou3d(a[:n], b[:n]).cpu().numpy()
    np.testing.assert_allclose(diag_3d, np.diag(ref_3d[:n, :n]), atol=1e-6, rtol=0)


def test_overlap_area_matches_shapely():
    a, b = _random_boxes(20, seed=3), _random_boxes(20, seed=4)
    ref = np.array(
        [[_polygon(p).intersection(_polygon(q)).area for q in b.tolist()] for p in a.tolist()]
    )
    np.testing.assert_allclose(boxes_overlap_bev(a, b).numpy(), ref, atol=1e-9, rtol=0)


def test_symmetry_identity_dtype_and_shapes():
    a, b = _random_boxes(30, seed=5), _random_boxes(25, seed=6)
    iou_ab, iou_ba = boxes_iou3d(a, b), boxes_iou3d(b, a)
    torch.testing.assert_close(iou_ab, iou_ba.T, atol=1e-12, rtol=0)
    torch.testing.assert_close(boxes_iou_bev(a, b), boxes_iou_bev(b, a).T, atol=1e-12, rtol=0)
    torch.testing.assert_close(boxes_iou3d(a, a).diagonal(), torch.ones(30, dtype=torch.float64))
    assert boxes_iou3d(a.float(), b.float()).dtype == torch.float32
    assert boxes_iou3d(a, b).dtype == torch.float64
    assert boxes_iou3d(a[:0], b).shape == (0, 25)
    assert boxes_iou_bev(a, b[:0]).shape == (30, 0)
    with pytest.raises(ValueError, match="expected shape"):
        boxes_iou3d(a[:, :6], b)
    # extra columns (velocities) are ignored
    torch.testing.assert_close(boxes_iou3d(torch.cat([a, a[:, :2]], 1), b), iou_ab)


def test_disjoint_is_zero_and_known_values():
    a = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0]])
    far = torch.tensor([[10.0, 0, 0, 2, 2, 2, 0], [0, 0, 5, 2, 2, 2, 0]])
    assert boxes_iou3d(a, far).abs().max() == 0
    # half shifted along x: inter 1*2*2 = 4, union 12
    half = torch.tensor([[1.0, 0, 0, 2, 2, 2, 0]])
    assert boxes_iou3d(a, half).item() == pytest.approx(1 / 3, abs=1e-7)
    # square rotated 45 deg inside itself: octagon area = 8 (sqrt(2) - 1) * 1, union 8 - inter
    rot = torch.tensor([[0.0, 0, 0, 2, 2, 2, math.pi / 4]])
    inter = 8 * (math.sqrt(2) - 1)
    assert boxes_iou_bev(a, rot).item() == pytest.approx(inter / (8 - inter), abs=1e-7)
    # z: half overlap in height
    up = torch.tensor([[0.0, 0, 1, 2, 2, 2, 0]])
    assert boxes_iou3d(a, up).item() == pytest.approx(1 / 3, abs=1e-7)
    assert boxes_iou_bev(a, up).item() == pytest.approx(1.0, abs=1e-7)


@pytest.mark.parametrize("device", DEVICES)
def test_degenerate_cases_are_finite_and_exact(device):
    base = torch.tensor([3.0, -2.0, 0.5, 4.0, 2.0, 1.5, 0.3], dtype=torch.float64)

    def t(*values):
        return torch.tensor(values, dtype=torch.float64)

    cases = {
        "identical": (base, base, 1.0),
        "rotated_pi": (base, base + t(*[0, 0, 0, 0, 0, 0, math.pi]), 1.0),
        "rotated_2pi": (base, base + t(*[0, 0, 0, 0, 0, 0, -2 * math.pi]), 1.0),
        "touching_edge": (base, _shift_local(base, 4.0, 0.0), 0.0),
        "collinear_half": (base, _shift_local(base, 2.0, 0.0), 1 / 3),
        "collinear_side": (base, _shift_local(base, 0.0, 1.0), 1 / 3),
        "touching_corner": (base, _shift_local(base, 4.0, 2.0), 0.0),
        "contained": (base, base * t(*[1, 1, 1, 0.5, 0.5, 0.5, 1.0]), 0.125),
        "zero_size": (base, base * t(*[1, 1, 1, 0, 1, 1, 1.0]), 0.0),
        "negative_size": (base, base * t(*[1, 1, 1, -1, 1, 1, 1.0]), 0.0),
        "tiny": (base * t(*[1, 1, 1, 1e-6, 1e-6, 1e-6, 1]),) * 2 + (1.0,),
        "huge": (base * t(*[1, 1, 1, 1e6, 1e6, 1e6, 1]),) * 2 + (1.0,),
        "far_away": (base + t(*[1e5, -1e5, 0, 0, 0, 0, 0]),) * 2 + (1.0,),
    }
    for name, (p, q, expected) in cases.items():
        p, q = p[None].to(device), q[None].to(device)
        for fn in (boxes_iou3d, boxes_aligned_iou3d):
            value = fn(p, q).reshape(-1)
            assert torch.isfinite(value).all(), name
            assert value.item() == pytest.approx(expected, abs=1e-9), (name, fn.__name__)


def _shift_local(box: torch.Tensor, fx: float, fy: float) -> torch.Tensor:
    c, s = math.cos(box[6].item()), math.sin(box[6].item())
    out = box.clone()
    out[0] += c * fx - s * fy
    out[1] += s * fx + c * fy
    return out


_finite = st.floats(-50, 50, allow_nan=False, allow_infinity=False)
_size = st.one_of(st.floats(0.0, 10.0), st.sampled_from([0.0, 1e-7, 1e-3, 1e4]))
_angle = st.one_of(
    st.floats(-10, 10, allow_nan=False), st.sampled_from([0.0, math.pi, -math.pi, math.pi / 2])
)
_box = st.tuples(_finite, _finite, _finite, _size, _size, _size, _angle)


@settings(max_examples=100, deadline=None)
@given(st.lists(_box, min_size=1, max_size=4), st.lists(_box, min_size=1, max_size=4))
def test_hypothesis_bounds_symmetry_no_nan(boxes_a, boxes_b):
    a = torch.tensor(boxes_a, dtype=torch.float64)
    b = torch.tensor(boxes_b, dtype=torch.float64)
    # snap some b boxes onto a boxes to hit identical / collinear / touching cases
    nb = b.shape[0]
    flip = torch.tensor([0, 0, 0, 0, 0, 0, math.pi], dtype=torch.float64)
    b = torch.cat([b, a, a + flip])
    iou = boxes_iou3d(a, b)
    assert torch.isfinite(iou).all()
    assert (iou >= 0).all() and (iou <= 1).all()
    torch.testing.assert_close(iou, boxes_iou3d(b, a).T, atol=1e-9, rtol=0)
    bev = boxes_iou_bev(a, b)
    assert torch.isfinite(bev).all() and (bev <= 1).all()
    positive = (a[:, 3:6] > 1e-2).all(dim=1)
    na = a.shape[0]
    self_iou = iou[torch.arange(na), nb + torch.arange(na)]
    flipped = iou[torch.arange(na), nb + na + torch.arange(na)]
    assert torch.allclose(self_iou[positive], torch.ones_like(self_iou[positive]), atol=1e-9)
    assert torch.allclose(flipped[positive], torch.ones_like(flipped[positive]), atol=1e-9)


def test_gradcheck_generic_configurations():
    a = torch.tensor(
        [[0.1, 0.2, 0.05, 4.0, 2.0, 1.5, 0.3], [5.0, 1.0, 0.0, 1.0, 0.8, 1.7, -1.1]],
        dtype=torch.float64,
        requires_grad=True,
    )
    b = torch.tensor(
        [[0.8, -0.3, 0.2, 3.5, 1.8, 1.6, 0.9], [5.3, 1.2, 0.3, 0.9, 0.7, 1.8, 0.4]],
        dtype=torch.float64,
        requires_grad=True,
    )
    assert torch.autograd.gradcheck(boxes_iou3d, (a, b))
    assert torch.autograd.gradcheck(boxes_aligned_iou3d, (a, b))
    assert torch.autograd.gradcheck(boxes_iou_bev, (a, b))
    loss = (1 - boxes_aligned_iou3d(a, b)).sum()
    loss.backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


def test_identical_boxes_gradient_is_finite():
    a = torch.tensor([[1.0, 2.0, 0.0, 4.0, 2.0, 1.5, 0.3]], dtype=torch.float64, requires_grad=True)
    iou = boxes_aligned_iou3d(a, a.detach().clone())
    iou.sum().backward()
    assert torch.isfinite(a.grad).all()


def test_large_inputs_are_chunked(monkeypatch):
    import pcdet_atlas.ops.iou3d_nms as mod

    a, b = _random_boxes(60, seed=7), _random_boxes(80, seed=8)
    full = boxes_iou3d(a, b)
    monkeypatch.setattr(mod, "PAIR_CHUNK", 7)
    torch.testing.assert_close(boxes_iou3d(a, b), full, atol=0, rtol=0)


def _nms_reference(
    boxes: torch.Tensor, scores: torch.Tensor, thresh: float, pre, post
) -> list[int]:
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    if pre is not None:
        order = order[:pre]
    polys = [_polygon(b) for b in boxes.tolist()]
    kept: list[int] = []
    for i in order:
        ok = True
        for j in kept:
            inter = polys[i].intersection(polys[j]).area
            if inter / (polys[i].area + polys[j].area - inter) > thresh:
                ok = False
                break
        if ok:
            kept.append(i)
    return kept if post is None else kept[:post]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("pre,post", [(None, None), (40, None), (None, 5), (30, 10)])
def test_nms_bev_matches_python_reference(device, pre, post):
    boxes = _random_boxes(80, seed=9, spread=6.0)
    g = torch.Generator().manual_seed(10)
    scores = torch.rand(80, generator=g)
    scores[10:20] = 0.5  # ties are broken by index
    keep = nms_bev(boxes.to(device), scores.to(device), 0.1, pre, post)
    assert keep.device.type == torch.device(device).type and keep.dtype == torch.long
    assert keep.cpu().tolist() == _nms_reference(boxes, scores, 0.1, pre, post)


def test_nms_bev_edge_cases():
    box = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0]])
    boxes = box.repeat(3, 1)
    assert nms_bev(boxes, torch.tensor([0.2, 0.9, 0.9]), 0.5).tolist() == [1]
    assert nms_bev(boxes[:0], torch.zeros(0), 0.5).numel() == 0
    # threshold is strict: IoU exactly 1/3 with thresh 1/3 keeps both
    two = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0], [1.0, 0, 0, 2, 2, 2, 0]], dtype=torch.float64)
    assert nms_bev(two, torch.tensor([0.9, 0.8]), 0.34).tolist() == [0, 1]
    assert nms_bev(two, torch.tensor([0.9, 0.8]), 0.3).tolist() == [0]
    with pytest.raises(ValueError, match="scores"):
        nms_bev(two, torch.tensor([0.9]), 0.5)


def test_nms_bev_bad_arguments_are_named_errors():
    two = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0], [1.0, 0, 0, 2, 2, 2, 0]])
    scores = torch.tensor([0.9, 0.8])
    with pytest.raises(TypeError, match="scores"):
        nms_bev(two, [0.9, 0.8], 0.5)
    with pytest.raises(ValueError, match="iou_thresh"):
        nms_bev(two, scores, float("nan"))  # would suppress nothing
    with pytest.raises(ValueError, match="pre_max_size"):
        nms_bev(two, scores, 0.5, pre_max_size=-1)  # would drop the last box
    with pytest.raises(ValueError, match="post_max_size"):
        nms_bev(two, scores, 0.5, post_max_size=2.5)
    assert nms_bev(two, scores, 0.5, pre_max_size=np.int64(1)).tolist() == [0]
    assert nms_bev(two, scores, 0.5, pre_max_size=0).numel() == 0


def test_nms_bev_per_class_against_a_reference():
    # the Python NMS per label with that label's settings, pooled, by score (ties: class order)
    boxes = _random_boxes(90, seed=11, spread=6.0)
    g = torch.Generator().manual_seed(12)
    scores = torch.rand(90, generator=g)
    scores[5:25] = 0.5  # ties across and within classes
    labels = torch.randint(0, 3, (90,), generator=g)
    thresh, pre, post = (0.1, 0.3, 0.05), (30, 25, 40), (8, 30, 5)
    expected = []
    for k in range(3):
        idx = torch.nonzero(labels == k).squeeze(1)
        kept = _nms_reference(boxes[idx], scores[idx], thresh[k], pre[k], post[k])
        expected += [int(idx[i]) for i in kept]
    expected.sort(key=lambda i: -float(scores[i]))  # stable: class order, then NMS order
    keep = nms_bev_per_class(boxes, scores, labels, thresh, pre, post)
    assert keep.tolist() == expected
    assert len(set(labels[keep].tolist())) == 3  # every class kept something
    with pytest.raises(ValueError, match=r"labels must lie in \[0, 1\]"):
        nms_bev_per_class(boxes, scores, labels, thresh[:2], pre[:2], post[:2])
    with pytest.raises(ValueError, match="one iou_thresh, pre_max_size and post_max_size"):
        nms_bev_per_class(boxes, scores, labels, thresh, pre[:2], post)
    assert nms_bev_per_class(boxes[:0], scores[:0], labels[:0], thresh, pre, post).numel() == 0


@settings(max_examples=60, deadline=None)
@given(
    st.tuples(st.floats(0.05, 8.0), st.floats(0.05, 8.0), st.floats(0.05, 3.0)),
    st.one_of(st.floats(-1.5, 1.5), st.sampled_from([0.0, 0.5, 1.0, -1.0])),
    st.one_of(st.floats(-1.5, 1.5), st.sampled_from([0.0, 0.25, 1.0])),
    _angle,
    st.sampled_from([0.0, 1e3, 1e5, -1e5]),
    st.booleans(),
)
def test_hypothesis_shifted_copies_have_exact_iou(dims, fx, fy, heading, offset, flip):
    """A copy shifted along its own axes (touching at |f| = 1, collinear edges at f = 0) has BEV
    IoU ``s / (2 - s)`` with ``s = (1 - |fx|)+ (1 - |fy|)+``, wherever the pair sits."""
    dx, dy, dz = dims
    a = torch.tensor([[offset, -offset, 0.5, dx, dy, dz, heading]], dtype=torch.float64)
    c, s = math.cos(heading), math.sin(heading)
    b = a.clone()
    b[0, 0] += c * fx * dx - s * fy * dy
    b[0, 1] += s * fx * dx + c * fy * dy
    if flip:
        b[0, 6] += math.pi
    share = max(0.0, 1 - abs(fx)) * max(0.0, 1 - abs(fy))
    expected = share / (2 - share)
    tol = 1e-9 * (1 + abs(offset) / min(dx, dy))
    assert boxes_iou_bev(a, b).item() == pytest.approx(expected, abs=tol)
    assert boxes_iou3d(a, b).item() == pytest.approx(expected, abs=tol)
    assert boxes_aligned_iou3d(b, a).item() == pytest.approx(expected, abs=tol)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("min_iou", [0.0, 0.3, 0.5])
def test_grouped_iou_is_the_dense_iou_of_each_group_bit_for_bit(device, min_iou):
    """Groups of various sizes (one without A boxes, one without B boxes, B ids not starting at
    0), shuffled: every pair the dense op gives a nonzero IoU comes back with exactly its value
    (with ``min_iou``: every pair at or above it), no pair crosses groups, none is returned twice,
    and the pairs left out are the dense op's zeros (or below ``min_iou``)."""
    gen = torch.Generator().manual_seed(3)
    a = _random_boxes(300, 1, spread=6.0).float()
    b = _random_boxes(260, 2, spread=6.0).float()
    b[:80] = a[:80] + 0.2 * torch.rand(80, 7, generator=gen)  # heavy overlaps, near-ties
    b[80:90] = b[70:80]  # exact duplicates within a group: equal IoUs
    group_a = torch.randint(0, 5, (300,), generator=gen) * 2  # groups 0, 2, ..., 8
    group_b = torch.randint(1, 6, (260,), generator=gen) * 2  # groups 2, ..., 10
    group_b[:80] = group_a[:80].clamp(min=2)  # the overlapping copies in their box's group
    group_b[80:90] = group_b[70:80]
    ia, ib, iou = boxes_iou3d_grouped(
        a.to(device), group_a.to(device), b.to(device), group_b.to(device), min_iou=min_iou
    )
    ia, ib, iou = ia.cpu(), ib.cpu(), iou.cpu()
    assert iou.dtype == torch.float32 and torch.all(ia[1:] >= ia[:-1])
    assert torch.equal(group_a[ia], group_b[ib])
    assert len(set(zip(ia.tolist(), ib.tolist()))) == len(ia)
    got = torch.full((300, 260), -1.0)
    got[ia, ib] = iou
    for g in range(12):
        rows, cols = (group_a == g).nonzero()[:, 0], (group_b == g).nonzero()[:, 0]
        dense = boxes_iou3d(a[rows], b[cols])  # (|rows|, |cols|)
        mine = got[rows][:, cols]
        back = mine >= 0
        assert torch.equal(mine[back], dense[back])  # bit for bit where returned
        assert bool((dense[~back] < max(min_iou, 1e-30)).all())  # left out: 0 or below min_iou
        if min_iou == 0:
            assert bool((dense[~back] == 0).all())
    assert bool((iou >= 0.5).sum() > 20)  # the heavy overlaps are in
    empty = torch.zeros(0, dtype=torch.long)
    ia, ib, iou = boxes_iou3d_grouped(a[:0], empty, b, group_b)
    assert ia.shape == ib.shape == iou.shape == (0,)
    with pytest.raises(ValueError, match="group_a: expected an int64 tensor of shape"):
        boxes_iou3d_grouped(a, group_a.int(), b, group_b)
    with pytest.raises(ValueError, match="group ids must be >= 0"):
        boxes_iou3d_grouped(a, group_a - 1, b, group_b)
