"""PTT's proposal trajectories: association by hand, the sequence start, future boxes, and
history proposals moved into the current frame against a computation in the world frame; the
batched association against the walk one frame at a time (``associate_reference``, the slow
reference) bit for bit on random scenes, edge cases and ties (real proposals: test_ptt.py)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from pcdet_atlas.attacks import AtlasWaymoDataset
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets.dataset import collate_batch
from pcdet_atlas.datasets.multiframe import SECONDS_PER_FRAME
from pcdet_atlas.datasets.proposal_history import gather_history, history_to_current
from pcdet_atlas.models import build_network_from_config, load_data_to_device
from pcdet_atlas.models.detectors.two_stage import roi_boxes_to_padded
from pcdet_atlas.models.model_utils.trajectory import associate_trajectories, future_boxes
from pcdet_atlas.models.roi_heads import ptt_head
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d
from pcdet_atlas.train_utils.proposal_bank import ProposalBank


def box(x, y, vx=10.0, vy=0.0, heading=0.0):
    return [x, y, 1.0, 4.0, 2.0, 1.5, heading, vx, vy]


def test_association_by_hand():
    # one car driving +x at 10 m/s: 1 m per frame; frame t-1 has it (slightly off), frame t-2
    # misses it, frame t-3 has it again, plus a far distractor in every frame
    current = torch.tensor([box(10.0, 0.0)])
    far = box(-30.0, 20.0, 0.0)
    history = [
        torch.tensor([box(9.1, 0.05, 9.0), far]),  # IoU with the prediction (9, 0) >= 0.5
        torch.tensor([far]),  # missed: the prediction is kept
        torch.tensor([box(7.2, 0.0, 9.0), far]),
    ]
    boxes, matched, valid = associate_trajectories(current, history)
    assert matched[:, 0].tolist() == [True, True, False, True]
    assert valid.all()
    assert torch.allclose(boxes[1, 0], history[0][0])  # the matched proposal itself
    # frame t-2: the t-1 proposal moved back by its own velocity (9 m/s -> 0.9 m)
    assert torch.allclose(boxes[2, 0, :2], torch.tensor([8.2, 0.05]))
    assert torch.allclose(boxes[2, 0, 2:], history[0][0, 2:])
    assert torch.allclose(boxes[3, 0], history[2][0])  # (7.3 predicted, 7.2 found)


def test_sequence_start_is_padding():
    current = torch.tensor([box(0.0, 0.0), box(5.0, 5.0, 0.0)])
    history = [torch.tensor([box(-1.0, 0.0)]), None, None]
    boxes, matched, valid = associate_trajectories(current, history)
    assert valid[:2].all() and not valid[2:].any()
    assert not matched[2:].any()
    # padding continues the prediction (finite features; the model masks these frames)
    assert torch.allclose(boxes[3, :, :2], boxes[1, :, :2] - 0.2 * boxes[1, :, 7:9])
    assert matched[1].tolist() == [True, False]  # the parked car has nothing to match


def test_future_boxes_farthest_first():
    current = torch.tensor([box(0.0, 0.0, 10.0, -5.0)])
    fut = future_boxes(current, 3)
    assert torch.allclose(fut[:, 0, 0], torch.tensor([3.0, 2.0, 1.0]))
    assert torch.allclose(fut[:, 0, 1], torch.tensor([-1.5, -1.0, -0.5]))


def pose(x, y, yaw):
    p = torch.eye(4, dtype=torch.float64)
    p[:2, :2] = torch.tensor([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    p[0, 3], p[1, 3] = x, y
    return p


def test_history_to_current_against_the_world_frame():
    then, now = pose(3.0, -2.0, 0.3), pose(10.0, 1.0, -0.4)
    local = torch.tensor([box(5.0, 2.0, 4.0, 1.0, heading=0.2)], dtype=torch.float64)
    # in the world: centre by the pose, heading + pose yaw, velocity rotated by the pose
    c = then @ torch.tensor([5.0, 2.0, 1.0, 1.0], dtype=torch.float64)
    world_heading = 0.2 + 0.3
    world_vel = then[:2, :2] @ torch.tensor([4.0, 1.0], dtype=torch.float64)
    moved = torch.from_numpy(history_to_current(local.numpy(), then.numpy(), now.numpy())[0])
    back_c = now @ torch.cat([moved[:3], torch.ones(1, dtype=torch.float64)])
    assert torch.allclose(back_c, c)
    assert math.isclose(float(moved[6]) + (-0.4), world_heading, abs_tol=1e-9)
    assert torch.allclose(now[:2, :2] @ moved[7:9], world_vel)
    assert torch.equal(moved[3:6], local[0, 3:6])


def test_gather_history_moves_each_frame_by_its_own_pose():
    poses = [pose(float(k), 0.5 * k, 0.05 * k).numpy() for k in range(6)]
    table = {
        k: np.array(
            [[*box(k, 1.0, 2.0, 0.5, heading=0.1), 0.9, 1.0]] * (k % 3), np.float32
        ).reshape(-1, 11)
        for k in range(6)
    }
    rows, count = gather_history(table.__getitem__, poses.__getitem__, 4, 31)
    assert count == 4  # frames 3, 2, 1, 0 exist; older ones are before the sequence start
    # frame k holds k % 3 proposals: frames 3 and 0 none, frame 2 two, frame 1 one
    assert rows[:, 11].tolist() == [2.0, 2.0, 3.0]
    for back in range(1, 5):
        frame = rows[rows[:, 11] == back]
        want = history_to_current(table[4 - back][:, :9].astype(np.float64), poses[4 - back],
                                  poses[4])  # fmt: skip
        np.testing.assert_array_equal(frame[:, :9], want)
        np.testing.assert_array_equal(frame[:, 9:11], table[4 - back][:, 9:11])
    rows, count = gather_history(table.__getitem__, poses.__getitem__, 5, 2)
    assert count == 2 and set(rows[:, 11].tolist()) <= {1.0, 2.0}
    assert gather_history(table.__getitem__, poses.__getitem__, 0, 31)[1] == 0


def associate_reference(current, history, iou_thresh=0.5):
    """The walk one frame at a time (the slow, obvious reference of the module docstring)."""
    num = current.shape[0]
    frames = 1 + len(history)
    boxes = current.new_zeros(frames, num, current.shape[1])
    matched = torch.zeros(frames, num, dtype=torch.bool)
    valid = torch.zeros(frames, num, dtype=torch.bool)
    boxes[0], matched[0], valid[0] = current, True, True
    started = True
    for i, props in enumerate(history, start=1):
        pred = boxes[i - 1].clone()
        pred[:, 0:2] = pred[:, 0:2] - SECONDS_PER_FRAME * pred[:, 7:9]
        boxes[i] = pred
        started = started and props is not None  # padding from the sequence start on
        valid[i] = started
        if not started or props.shape[0] == 0 or num == 0:
            continue
        iou, index = boxes_iou3d(pred[:, :7], props[:, :7]).max(dim=1)
        hit = iou >= iou_thresh
        boxes[i, hit] = props[index[hit]].to(boxes.dtype)
        matched[i] = hit
    return boxes, matched, valid


def assert_same_as_reference(current, history, iou_thresh=0.5):
    got = associate_trajectories(current, history, iou_thresh)
    want = associate_reference(current, history, iou_thresh)
    for name, g, w in zip(("boxes", "matched", "valid"), got, want):
        assert g.dtype == w.dtype and torch.equal(g, w), name
    return got


def scene(gen: torch.Generator, frames: int, objects: int = 12, per_object: int = 6, clutter=8):
    """Proposals of ``frames`` frames (current first) around moving objects, as a detector
    makes them: several jittered proposals per object (velocity jittered too), some objects
    missed in some frames, scattered false positives."""
    pos = (torch.rand(objects, 2, generator=gen) * 2 - 1) * 30
    vel = torch.randn(objects, 2, generator=gen) * 5
    size = torch.rand(objects, 3, generator=gen) * torch.tensor([3.0, 1.0, 1.0]) + 1
    heading = torch.atan2(vel[:, 1], vel[:, 0])
    out = []
    for f in range(frames):
        rows = []
        for o in range(objects):
            if torch.rand((), generator=gen) < 0.2:
                continue  # missed in this frame
            k = int(torch.randint(1, per_object + 1, (), generator=gen))
            centre = pos[o] - SECONDS_PER_FRAME * f * vel[o]
            box = torch.cat([centre, torch.zeros(1), size[o], heading[o : o + 1], vel[o]])
            jitter = torch.randn(k, 9, generator=gen) * torch.tensor(
                [0.3, 0.3, 0.1, 0.2, 0.1, 0.1, 0.05, 1.0, 1.0]
            )
            rows.append(box + jitter)
        fp = torch.rand(clutter, 9, generator=gen) * 2 - 1
        fp[:, :2] *= 40
        fp[:, 3:6] = fp[:, 3:6].abs() * 3 + 0.5
        fp[:, 7:9] *= 10
        rows.append(fp)
        props = torch.cat(rows)
        out.append(props[torch.randperm(len(props), generator=gen)])
    return out[0], out[1:]


@pytest.mark.parametrize("seed", range(6))
def test_association_is_the_walk_on_random_scenes(seed):
    gen = torch.Generator().manual_seed(seed)
    current, history = scene(gen, 32)
    boxes, matched, _ = assert_same_as_reference(current, history)
    assert matched[1:].float().mean() > 0.1  # the scenes exercise matches and misses
    assert not matched[1:].all()


@pytest.mark.parametrize("thresh", [0.0, 0.3, 0.7, 1.0, 1.5])
def test_association_is_the_walk_at_any_threshold(thresh):
    current, history = scene(torch.Generator().manual_seed(7), 10)
    assert_same_as_reference(current, history, thresh)


def test_association_is_the_walk_at_the_edges():
    gen = torch.Generator().manual_seed(11)
    current, history = scene(gen, 12)
    empty = current[:0]
    cases = {
        "no history": (current, []),
        "sequence start": (current, [None] * 5),
        "history then the start": (current, [*history[:3], None, None]),
        "a real frame after padding stays padding": (current, [history[0], None, history[1]]),
        "frames without proposals": (current, [empty, history[1], empty, empty, history[4]]),
        "every frame empty": (current, [empty] * 4),
        "no current proposals": (empty, history[:4]),
        "no current proposals, no history": (empty, []),
        "one proposal": (current[:1], history[:6]),
        "float64": (current.double(), [h.double() for h in history]),
    }
    for name, (cur, hist) in cases.items():
        try:
            assert_same_as_reference(cur, hist)
        except AssertionError as err:
            raise AssertionError(f"{name}: {err}") from None


def test_ties_take_the_first_of_equal_proposals():
    """Copies of a box that differ only in velocity (which the IoU does not read) have equal
    IoUs with the prediction: the first in the frame's order is taken, as the walk's max does,
    in a frame where it is not the frame's first proposal and in one where it is."""
    current = torch.tensor([box(10.0, 0.0), box(0.0, 10.0, 0.0, 5.0, heading=math.pi / 2)])
    frame1 = torch.tensor(
        [box(-20.0, 0.0), box(9.2, 0.0, 9.0), box(9.2, 0.0, 8.0), box(9.2, 0.0, 7.0)]
    )
    frame2 = torch.tensor(
        [box(0.0, 9.1, 0.0, v, heading=math.pi / 2) for v in (6.0, 5.0, 4.0)] + [box(8.3, 0.0)]
    )
    boxes, matched, _ = assert_same_as_reference(current, [frame1, frame2])
    assert matched.T.tolist() == [[True, True, True], [True, False, True]]
    assert boxes[1, 0, 7] == 9.0 and boxes[2, 1, 8] == 6.0  # the first copies


def test_bad_history_is_refused():
    current = torch.tensor([box(0.0, 0.0)])
    with pytest.raises(ValueError, match=r"history frame t-2 has torch.float64 proposals"):
        associate_trajectories(current, [current, current.double()])
    with pytest.raises(ValueError, match=r"history frame t-1 .* shape \(1, 7\)"):
        associate_trajectories(current, [current[:, :7]])
    nan = current.clone()
    nan[0, 7] = float("nan")
    with pytest.raises(ValueError, match="not finite"):
        associate_trajectories(current, [nan])


@pytest.mark.slow
def test_association_and_ptt_predictions_are_the_walks_on_real_proposals(
    synthetic_root, monkeypatch
):
    """The shipped synthetic PTT (its CP-4f RPN through the proposal bank) on val frames of the
    fixture sequence, from its start (history partly padding) to full 31-frame histories: the
    association of every frame's proposals is the walk's bit for bit, and so are the model's
    predictions with either association."""
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "ptt_32f.yaml")
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    data_cfg.DATA_PATH = str(synthetic_root)
    clean = AtlasWaymoDataset(
        data_cfg, cfg.CLASS_NAMES, REPO_ROOT / "cfgs" / "attacks" / "clean.yaml", training=False
    )
    torch.manual_seed(0)
    model = build_network_from_config(cfg).eval()
    model.load_params_from_file(REPO_ROOT / cfg.ATLAS.CHECKPOINT)
    bank = ProposalBank(model, clean, device=torch.device("cpu"))
    hits = []
    for index in (0, 2, 33, 34):
        batch = collate_batch([clean[index]])
        batch = bank.attach(batch, load_data_to_device(batch, torch.device("cpu")))
        rois = roi_boxes_to_padded(batch["roi_boxes"])[0]
        (history,) = model.histories(batch)
        assert sum(h is not None for h in history) == min(index, 31)
        _, matched, real = assert_same_as_reference(
            rois[0, :, :9], [h if h is None else h[:, :9] for h in history]
        )
        hits.append(float(matched[1:][real[1:]].float().mean()) if index else 0.0)
        got = model.predict(batch)
        with monkeypatch.context() as patch:
            patch.setattr(ptt_head, "associate_trajectories", associate_reference)
            want = model.predict(batch)
        for g, w in zip(got, want):
            assert g.keys() == w.keys()
            for key in g:
                assert torch.equal(g[key], w[key]), key
    assert min(hits[1:]) > 0.2  # proposals of the existing previous frames are taken
