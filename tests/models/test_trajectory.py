"""PTT's proposal trajectories: association by hand, the sequence start, future boxes, and
history proposals moved into the current frame against a computation in the world frame."""

from __future__ import annotations

import math

import numpy as np
import torch

from pcdet_atlas.datasets.proposal_history import gather_history, history_to_current
from pcdet_atlas.models.model_utils.trajectory import associate_trajectories, future_boxes


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
