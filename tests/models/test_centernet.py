import math

import pytest
import torch
from device_params import DEVICES
from model_batches import BOXES

from pcdet_atlas.models.dense_heads.center_head import CenterHead
from pcdet_atlas.models.model_utils import centernet_utils as cu

PCR = (-25.6, -25.6, -2.0, 25.6, 25.6, 4.0)
VS = (0.4, 0.4, 6.0)
GRID = (128, 128, 1)


def make_head(with_velocity, stride=2, **kw):
    return CenterHead(
        input_channels=8,
        num_class=3,
        point_cloud_range=PCR,
        voxel_size=VS,
        grid_size=GRID,
        feature_map_stride=stride,
        with_velocity=with_velocity,
        shared_conv_channel=8,
        **kw,
    )


def gt_tensor(with_velocity):
    rows = [torch.tensor(b) for b in BOXES]
    gt = torch.zeros(2, 3, 10)
    for i, r in enumerate(rows):
        gt[i, : r.shape[0]] = r
    return gt if with_velocity else torch.cat([gt[..., :7], gt[..., 9:]], -1)


def maps_from_targets(head, targets):
    """Ideal head outputs: +12 logits at the centre cells, -12 elsewhere, exact regressions."""
    B = targets.heatmap.shape[0]
    H, W = head.feature_map_size
    hm = torch.where(targets.heatmap == 1, 12.0, -12.0)
    reg = torch.zeros(B, head.code_size, H * W, device=targets.heatmap.device)
    for b in range(B):
        m = targets.mask[b]
        reg[b][:, targets.inds[b][m]] = targets.box_targets[b][m].T
    reg = reg.view(B, head.code_size, H, W)
    out = {"hm": hm, "center": reg[:, 0:2], "center_z": reg[:, 2:3], "dim": reg[:, 3:6]}
    out["rot"] = reg[:, 6:8]
    if head.with_velocity:
        out["vel"] = reg[:, 8:10]
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("with_velocity", [False, True])
@pytest.mark.parametrize("stride", [1, 2])
def test_encode_decode_round_trip(device, with_velocity, stride):
    head = make_head(with_velocity, stride).to(device)
    gt = gt_tensor(with_velocity).to(device)
    targets = head.assign_targets(gt)
    assert targets.mask.sum().item() == 4
    assert targets.heatmap.eq(1).sum().item() == 4  # exactly one peak per object
    preds = head.predict(maps_from_targets(head, targets))
    for b, boxes in enumerate(BOXES):
        want = torch.tensor(boxes)
        order = torch.argsort(preds[b]["pred_boxes"][:, 0].cpu())
        got = preds[b]["pred_boxes"].cpu()[order]
        want = want[torch.argsort(want[:, 0])]
        assert got.shape == (len(boxes), 9 if with_velocity else 7)
        torch.testing.assert_close(got[:, :6], want[:, :6], atol=1e-4, rtol=1e-5)
        dyaw = torch.remainder(got[:, 6] - want[:, 6] + math.pi, 2 * math.pi) - math.pi
        assert dyaw.abs().max() < 1e-4
        if with_velocity:
            torch.testing.assert_close(got[:, 7:9], want[:, 7:9], atol=1e-5, rtol=0)
        assert preds[b]["pred_labels"].cpu()[order].tolist() == want[:, 9].long().tolist()
        assert (preds[b]["pred_scores"] > 0.99).all()


def test_gaussian_shape_and_radius():
    head = make_head(False, stride=1)
    gt = torch.zeros(1, 1, 8)
    gt[0, 0] = torch.tensor([0.2, 0.2, 0.0, 4.0, 2.0, 1.5, 0.0, 1])
    t = head.assign_targets(gt)
    hm = t.heatmap[0, 0]
    iy, ix = divmod(int(t.inds[0, 0]), head.feature_map_size[1])
    assert hm[iy, ix] == 1 and hm.max() == 1 and t.heatmap[0, 1:].sum() == 0
    r = max(int(cu.gaussian_radius(torch.tensor(5.0), torch.tensor(10.0), 0.1)), 2)
    sigma = (2 * r + 1) / 6
    assert hm[iy, ix + 1].item() == pytest.approx(math.exp(-1 / (2 * sigma**2)), rel=1e-5)
    assert hm[iy + r, ix + r].item() > 0 and hm[iy, ix + r + 1].item() == 0
    # sub-cell offset target and log-size targets
    torch.testing.assert_close(
        t.box_targets[0, 0, :2], torch.tensor([(0.2 + 25.6) / 0.4 - ix, (0.2 + 25.6) / 0.4 - iy])
    )
    torch.testing.assert_close(t.box_targets[0, 0, 3:6], torch.log(torch.tensor([4.0, 2.0, 1.5])))


def test_targets_skip_padding_out_of_range_and_cap():
    head = make_head(False, stride=2, num_max_objs=2)
    gt = torch.zeros(1, 5, 8)
    gt[0, 0] = torch.tensor([1.0, 1.0, 0, 4, 2, 1.5, 0, 1])
    gt[0, 1] = torch.tensor([30.0, 1.0, 0, 4, 2, 1.5, 0, 1])  # outside the map
    gt[0, 2] = torch.tensor([5.0, 5.0, 0, 0.0, 2, 1.5, 0, 1])  # zero length
    gt[0, 3] = torch.tensor([-5.0, 5.0, 0, 1, 1, 1.5, 0, 2])
    gt[0, 4] = torch.tensor([-9.0, 5.0, 0, 1, 1, 1.5, 0, 3])  # beyond num_max_objs
    t = head.assign_targets(gt)
    assert t.mask.tolist() == [[True, True]]
    assert t.heatmap.eq(1).sum() == 3  # the heatmap keeps every valid object
    with pytest.raises(ValueError, match="class index out of range"):
        head.assign_targets(torch.tensor([[[0, 0, 0, 1, 1, 1, 0, 7.0]]]))


def test_velocity_head_needs_speed_columns():
    head = make_head(True)
    with pytest.raises(ValueError, match="TRAIN_WITH_SPEED"):
        head.assign_targets(gt_tensor(False))


def test_focal_loss_hand_computed():
    logits = torch.tensor([0.0, 2.0, -1.0]).view(1, 1, 1, 3)
    target = torch.tensor([1.0, 0.5, 0.0]).view(1, 1, 1, 3)
    p = torch.sigmoid(logits.flatten())
    want = -(
        math.log(p[0]) * (1 - p[0]) ** 2
        + math.log(1 - p[1]) * p[1] ** 2 * 0.5**4
        + math.log(1 - p[2]) * p[2] ** 2
    )
    assert cu.focal_loss_centernet(logits, target).item() == pytest.approx(want, rel=1e-5)


def test_reg_loss_is_masked_mean_per_channel():
    pred = torch.tensor([[[1.0, 2.0], [5.0, 5.0], [9.0, 9.0]]])
    target = torch.tensor([[[0.0, 0.0], [5.0, 3.0], [0.0, 0.0]]])
    mask = torch.tensor([[True, True, False]])
    torch.testing.assert_close(
        cu.reg_l1_loss_centernet(pred, target, mask), torch.tensor([0.5, 2.0]), atol=1e-3, rtol=0
    )


def test_decode_score_threshold_and_limit_range():
    hm = torch.full((1, 1, 4, 4), -10.0)
    hm[0, 0, 1, 1] = 5.0
    hm[0, 0, 2, 3] = -1.0  # score 0.27
    zeros = torch.zeros(1, 2, 4, 4)
    args = (hm, zeros, zeros[:, :1], zeros.repeat(1, 2, 1, 1)[:, :3], zeros, None)
    kw = dict(point_cloud_range=(0, 0, -1, 4, 4, 1), voxel_size=(1, 1, 2), feature_map_stride=1)
    out = cu.decode_center_maps(*args, score_thresh=0.1, **kw)[0]
    assert out["boxes"].shape == (2, 7) and out["scores"][0] > out["scores"][1]
    out = cu.decode_center_maps(*args, score_thresh=0.5, **kw)[0]
    assert out["boxes"].shape[0] == 1
    torch.testing.assert_close(out["boxes"][0, :2], torch.tensor([1.0, 1.0]))
    out = cu.decode_center_maps(
        *args, score_thresh=0.1, post_center_limit_range=(2, 0, -1, 4, 4, 1), **kw
    )[0]
    assert out["boxes"].shape[0] == 1 and out["boxes"][0, 0] == 3.0
