"""MSF's second stage: motion-guided sampling against a brute-force reference, BiFA's two
directions, ROI jitter, target assignment and the loss."""

from __future__ import annotations

import math

import pytest
import torch

from pcdet_atlas.models.model_utils.motion_sampler import (
    _sort_within_slots,
    cylinder_pairs,
    frame_of_points,
    propagate_boxes,
    sample_cylinder_points,
    sampling_radius,
)
from pcdet_atlas.models.model_utils.roi_sampler import RoiSamplerConfig
from pcdet_atlas.models.roi_heads.msf_head import (
    BiFATransformer,
    MSFHead,
    spherical_offsets,
)
from pcdet_atlas.models.roi_heads.roi_head_template import augment_boxes
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d
from tests.device_params import DEVICES


def scene(seed: int = 0, num_frames: int = 4, per_frame: int = 3000):
    """Points of ``num_frames`` frames (lag column 0.1 i) around three moving boxes."""
    g = torch.Generator().manual_seed(seed)
    boxes = torch.tensor(
        [
            [5.0, 2.0, 0.8, 4.5, 2.0, 1.6, 0.4, 8.0, 1.0],
            [-6.0, 3.0, 0.9, 0.8, 0.8, 1.8, 0.0, 0.0, 1.2],
            [5.5, 2.5, 0.8, 4.2, 1.9, 1.5, 0.5, 7.0, 0.0],  # overlaps the first: shared points
        ]
    )
    rows = []
    for i in range(num_frames):
        xy = (torch.rand(per_frame, 2, generator=g) - 0.5) * 30.0
        z = torch.rand(per_frame, 1, generator=g) * 2
        feat = torch.rand(per_frame, 2, generator=g)
        lag = torch.full((per_frame, 1), 0.1 * i)
        rows.append(torch.cat([xy, z, feat, lag], 1))
    return torch.cat(rows), boxes


def brute_force(points, frames, traj, num_sample, gamma, growth, keys):
    """Per box and frame: the cylinder's points by a plain loop, then the smallest keys."""
    num_frames, num_boxes = traj.shape[:2]
    out = torch.zeros(num_boxes, num_frames, num_sample, points.shape[1])
    valid = torch.zeros(num_boxes, num_frames, num_sample, dtype=torch.bool)
    for r in range(num_boxes):
        for i in range(num_frames):
            box = traj[i, r]
            radius = (gamma ** (i + 1) if growth else gamma) * math.hypot(box[3] / 2, box[4] / 2)
            cand = [
                n
                for n in range(points.shape[0])
                if frames[n] == i
                and (points[n, 0] - box[0]) ** 2 + (points[n, 1] - box[1]) ** 2 <= radius**2
            ]
            cand.sort(key=lambda n: float(keys[n]))
            for slot, n in enumerate(cand[:num_sample]):
                out[r, i, slot] = points[n]
                valid[r, i, slot] = True
    return out, valid


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("growth", [True, False])
def test_sampler_matches_brute_force(growth, device):
    points, boxes = scene()
    traj = propagate_boxes(boxes, 4)
    frames = frame_of_points(points[:, -1], 4)
    out, valid = sample_cylinder_points(
        points[:, :-1].to(device), frames.to(device), traj.to(device), num_sample=64, gamma=1.1,
        radius_growth=growth, generator=torch.Generator().manual_seed(7),
    )  # fmt: skip
    assert out.device.type == valid.device.type == device
    out, valid = out.cpu(), valid.cpu()
    keys = torch.rand(
        points.shape[0], generator=torch.Generator().manual_seed(7), dtype=torch.float64
    )
    ref_out, ref_valid = brute_force(points[:, :-1], frames, traj, 64, 1.1, growth, keys)
    assert torch.equal(valid, ref_valid)
    assert torch.equal(out, ref_out)
    full = valid.all(-1)  # some cylinders hold more than 64 points, some fewer
    assert full.any() and not full.all()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("spread", ["equal", "one_large", "tiny_median", "far_box"])
def test_cylinder_pairs_match_brute_force(spread, device):
    """Every (box, point) pair within the radius, once, sorted by box, whatever the radii (the
    grid's cell follows the median radius; a large or far box must still find all its points)."""
    g = torch.Generator().manual_seed(3)
    xy = (torch.rand(4000, 2, generator=g) - 0.5) * 80.0
    xy[:500] = xy[:500] * 0.05  # a dense cluster, as the ground near the sensor
    centers = (torch.rand(40, 2, generator=g) - 0.5) * 70.0
    centers[0] = 0.0
    radius = torch.full((40,), 2.5)
    if spread == "one_large":
        radius[0] = 30.0
    elif spread == "tiny_median":
        radius = torch.full((40,), 1e-4)
        radius[:3] = torch.tensor([4.0, 8.0, 0.0])
    elif spread == "far_box":
        centers[1] = torch.tensor([500.0, -300.0])
        radius[1] = 600.0
    box_id, point_id = cylinder_pairs(xy.to(device), centers.to(device), radius.to(device))
    box_id, point_id = box_id.cpu(), point_id.cpu()
    d2 = ((xy[None] - centers[:, None]) ** 2).sum(-1)
    want = torch.nonzero(d2 <= radius[:, None] ** 2)
    got = torch.stack([box_id, point_id], 1)
    assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, want.tolist()))
    assert len(set(map(tuple, got.tolist()))) == got.shape[0] > 0
    assert bool((box_id[1:] >= box_id[:-1]).all())


@pytest.mark.parametrize("device", DEVICES)
def test_cylinder_pairs_keep_to_their_group(device):
    """With groups (MSF: frames), a box pairs only with its own group's points; a point of
    group -1, or of a group no box has, pairs with none."""
    g = torch.Generator().manual_seed(4)
    xy = (torch.rand(3000, 2, generator=g) - 0.5) * 40.0
    point_group = torch.randint(-1, 4, (3000,), generator=g)  # group 3: no box
    centers = (torch.rand(30, 2, generator=g) - 0.5) * 36.0
    box_group = torch.arange(3).repeat_interleave(10)
    radius = 2.0 + 4.0 * torch.rand(30, generator=g)
    box_id, point_id = cylinder_pairs(
        xy.to(device), centers.to(device), radius.to(device),
        point_group=point_group.to(device), box_group=box_group.to(device),
    )  # fmt: skip
    box_id, point_id = box_id.cpu(), point_id.cpu()
    d2 = ((xy[None] - centers[:, None]) ** 2).sum(-1)
    same = box_group[:, None] == point_group[None]
    want = torch.nonzero((d2 <= radius[:, None] ** 2) & same)
    got = torch.stack([box_id, point_id], 1)
    assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, want.tolist()))
    assert got.shape[0] == want.shape[0] > 0
    assert bool((box_id[1:] >= box_id[:-1]).all())
    with pytest.raises(ValueError, match="both point_group and box_group"):
        cylinder_pairs(xy, centers, radius, point_group=point_group)
    with pytest.raises(ValueError, match="box_group must be >= 0"):
        cylinder_pairs(xy, centers, radius, point_group=point_group, box_group=box_group - 1)


@pytest.mark.parametrize("device", DEVICES)
def test_cylinder_pairs_find_a_point_on_the_edge(device):
    """A point at exactly the radius is found when the radius is a whole number of grid cells
    (here the only box's radius is the median: 2 cells) and the point's cell index rounds up
    across a cell edge."""
    xy = torch.tensor([[0.2, 0.2], [43.68477249145508, 40.0]])
    centers = torch.tensor([[39.10742950439453, 40.0]])
    radius = torch.tensor([4.57734489440918])
    assert bool(((xy[1] - centers[0]) ** 2).sum() <= radius[0] ** 2)
    box_id, point_id = cylinder_pairs(xy.to(device), centers.to(device), radius.to(device))
    assert box_id.tolist() == [0] and point_id.tolist() == [1]


@pytest.mark.parametrize("device", DEVICES)
def test_sampler_does_not_read_points_of_other_frames(device):
    """Points of no sampled frame (a NaN one among them) are never read."""
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]])
    traj = torch.tensor([[[0.0, 0.0, 0.0, 4.0, 2.0, 1.0, 0.0]]])
    out, valid = sample_cylinder_points(
        pts.to(device), torch.tensor([0, 0, -1], device=device), traj.to(device), num_sample=4,
        gamma=1.0, radius_growth=False,
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert int(valid.sum()) == 2 and torch.isfinite(out).all()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("num_slots", [7, 1024, 3000])
def test_sort_within_slots_is_a_lexicographic_sort(num_slots, device):
    """Sorted by (slot, key), equal keys in their given order, across the 2^10-slot runs."""
    g = torch.Generator().manual_seed(num_slots)
    slot = torch.sort(torch.randint(0, num_slots, (5000,), generator=g)).values
    key = torch.rand(5000, generator=g, dtype=torch.float64)
    key[100:110] = key[100]  # ties, kept in their order
    key[-5:] = key[-1]
    order = _sort_within_slots(slot.to(device), key.to(device), num_slots)
    want = sorted(range(5000), key=lambda i: (int(slot[i]), float(key[i]), i))
    assert order.tolist() == want


def test_radius_grows_with_the_frame_age():
    box = torch.tensor([[0.0, 0.0, 0.0, 4.0, 3.0, 1.5, 0.0]])
    base = math.hypot(2.0, 1.5)
    for i in range(4):
        assert float(sampling_radius(box, i, 1.1, True)) == pytest.approx(base * 1.1 ** (i + 1))
        assert float(sampling_radius(box, i, 1.1, False)) == pytest.approx(base * 1.1)
    # a point just outside frame 0's radius but inside frame 3's is drawn in frame 3 only
    r0, r3 = base * 1.1, base * 1.1**4
    pts = torch.tensor([[0.5 * (r0 + r3), 0.0, 0.0, 0.1, 0.2]] * 2)
    frames = torch.tensor([0, 3])
    traj = box[None].repeat(4, 1, 1)
    _, valid = sample_cylinder_points(
        pts, frames, traj, num_sample=4, gamma=1.1, radius_growth=True,
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert not valid[0, 0].any() and valid[0, 3, 0] and int(valid.sum()) == 1


def test_propagation_moves_boxes_back_along_their_velocity():
    boxes = torch.tensor([[1.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.3, 10.0, -5.0]])
    traj = propagate_boxes(boxes, 3)
    assert torch.allclose(traj[:, 0, 0], torch.tensor([1.0, 0.0, -1.0]))
    assert torch.allclose(traj[:, 0, 1], torch.tensor([2.0, 2.5, 3.0]))
    assert torch.equal(traj[:, 0, 2:7], boxes[:, 2:7].expand(3, -1))


def test_frame_of_points_uses_the_time_lag():
    lag = torch.tensor([0.0, 0.1, 0.2000001, 0.3, 0.35, 0.7, -0.1])
    assert frame_of_points(lag, 4).tolist() == [0, 1, 2, 3, -1, -1, -1]
    assert frame_of_points(lag, 8)[5] == 7


def test_spherical_offsets_by_hand():
    box = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]])
    point = torch.tensor([[[0.0, 0.0, 1.0]]])  # above the centre
    feat = spherical_offsets(point, box)
    assert feat.shape == (1, 1, 27)
    diag = math.sqrt(12.0)
    assert float(feat[0, 0, 8]) == pytest.approx(1.0 / diag, rel=1e-4)  # distance to the centre
    assert float(feat[0, 0, 26]) == pytest.approx(0.0, abs=1e-2)  # straight up: polar angle ~0


def small_transformer(bifa_layers: int) -> BiFATransformer:
    torch.manual_seed(0)
    return BiFATransformer(4, 16, 2, 2, 32, layers=2, bifa_layers=bifa_layers, dropout=0.0).eval()


def test_bifa_carries_information_both_ways_and_keeps_frames_apart():
    points = torch.randn(4, 3, 8, 16)  # (T, N, K, C)
    changed = points.clone()
    changed[2] += torch.randn(3, 8, 16)  # perturb frame 2 only
    with torch.no_grad():
        base, moved = small_transformer(1)(points)[0], small_transformer(1)(changed)[0]
        delta = (base - moved).abs().amax(dim=(1, 2))  # per frame, first layer's tokens
        assert delta[1] > 1e-4 and delta[3] > 1e-4  # newer and older neighbours both see it
        assert delta[0] == 0  # one hop per direction per layer: frame 0 is two away
        # without BiFA each frame's token sees its own frame only (no mixing of frames)
        base, moved = small_transformer(0)(points), small_transformer(0)(changed)
        for layer_base, layer_moved in zip(base, moved):
            delta = (layer_base - layer_moved).abs().amax(dim=(1, 2))
            assert delta[2] > 1e-4 and torch.all(delta[[0, 1, 3]] == 0)


def test_augment_boxes_reaches_the_threshold_or_keeps_the_last_try():
    g = torch.Generator().manual_seed(3)
    gt = torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]]).repeat(50, 1)
    rois = gt.clone()
    rois[:, 0] += torch.linspace(0.0, 0.8, 50)
    base = boxes_aligned_iou3d(rois, gt)
    out, iou = augment_boxes(rois, gt, base, tries=10, keep_ratio=0.2, iou_thresh=0.55, generator=g)
    kept = (out == rois).all(1)
    assert torch.allclose(iou[kept], base[kept].to(iou.dtype))
    moved = ~kept
    assert moved.any() and kept.any()
    assert torch.allclose(
        iou[moved], boxes_aligned_iou3d(out[moved], gt[moved]).to(iou.dtype), atol=1e-6
    )
    assert (iou >= 0.55).float().mean() > 0.9  # nearly all reach the foreground threshold
    assert (out[:, :2] - rois[:, :2]).abs().max() <= 0.5 + 1e-6
    assert ((out[:, 3:6] / rois[:, 3:6]) - 1).abs().max() <= 0.15 + 1e-6


def tiny_head(num_frames: int = 4) -> MSFHead:
    torch.manual_seed(0)
    return MSFHead(
        num_class=3, num_point_features=6, num_frames=num_frames, num_points=16, hidden_dim=32,
        nheads=2, point_nheads=2, enc_layers=2, bifa_layers=1, dim_feedforward=64,
        dropout=0.0, embed_dim=16, sampler_cfg=RoiSamplerConfig(roi_per_image=16),
    )  # fmt: skip


def head_batch():
    points, boxes = scene(per_frame=1500)
    batch_points = torch.cat([torch.zeros(points.shape[0], 1), points], 1)
    gt = torch.cat([boxes[:2], torch.tensor([[1.0], [2.0]])], 1)[None]  # 10 columns
    near = boxes[:2] + torch.tensor([0.2, -0.1, 0, 0, 0, 0, 0.05, 0, 0])
    far = torch.tensor([[9.0, -9.0, 0.5, 4.0, 2.0, 1.5, 0.0, 0.0, 0.0]])
    rois = torch.cat([near, far])[None]
    labels = torch.tensor([[1, 2, 1]])
    return batch_points, gt, rois, labels


def test_targets_and_loss_train_the_head():
    head = tiny_head()
    points, gt, rois, labels = head_batch()
    gens = [torch.Generator().manual_seed(1)]
    targets = head.assign_targets(rois, labels, torch.ones_like(labels, dtype=torch.bool), gt, gens)
    assert targets["rois"].shape == (1, 16, 9) and targets["roi_valid"].all()
    assert targets["reg_valid"].any() and (~targets["reg_valid"]).any()
    # frame 0 of the trajectory is the (jittered) ROI; older frames follow the velocity
    assert torch.equal(targets["trajectories"][:, 0], targets["rois"][..., :7])
    # the regression target decodes back to the matched ground truth
    from pcdet_atlas.models.model_utils.box_coder import decode_roi_boxes, encode_roi_targets

    fg = targets["reg_valid"][0]
    codes = encode_roi_targets(
        targets["gt_of_rois"][0, fg], targets["rois"][0, fg, :7], head.box_coder
    )
    back = decode_roi_boxes(codes, targets["rois"][0, fg, :7], head.box_coder)
    assert torch.allclose(back[:, :6], targets["gt_of_rois"][0, fg, :6], atol=1e-4)
    head.train()
    opt = torch.optim.Adam(head.parameters(), lr=3e-3)
    losses = []
    for _ in range(15):
        gens = [torch.Generator().manual_seed(2)]
        out = head(
            {"points": points, "trajectories": targets["trajectories"],
             "roi_valid": targets["roi_valid"], "generators": gens}
        )  # fmt: skip
        loss = head.loss(out, targets)
        assert all(torch.isfinite(v) for v in loss.values())
        opt.zero_grad()
        loss["loss"].backward()
        opt.step()
        losses.append(float(loss["loss"].detach()))
    assert losses[-1] < 0.6 * losses[0]


def test_a_frame_without_proposals_trains_nothing():
    head = tiny_head()
    points, gt, rois, labels = head_batch()
    rois2 = torch.cat([rois, torch.zeros_like(rois)])
    labels2 = torch.cat([labels, torch.zeros_like(labels)])
    valid = labels2 > 0
    targets = head.assign_targets(rois2, labels2, valid, gt.repeat(2, 1, 1),
                                  [torch.Generator().manual_seed(1)] * 2)  # fmt: skip
    assert targets["roi_valid"][0].all() and not targets["roi_valid"][1].any()
    pts2 = torch.cat([points, torch.cat([torch.ones(5, 1), points[:5, 1:]], 1)])
    gens = [torch.Generator()] * 2
    out = head(
        {"points": pts2, "trajectories": targets["trajectories"],
         "roi_valid": targets["roi_valid"], "generators": gens}
    )  # fmt: skip
    assert torch.isfinite(head.loss(out, targets)["loss"])
