import math

import numpy as np
import torch

from pcdet_atlas.utils.box_utils import (
    boxes_to_corners_3d,
    points_in_boxes_mask,
    transform_boxes,
    transform_points,
)


def pose(yaw, t):
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = t
    return m


def test_points_in_boxes_rotated():
    box = np.array([[10.0, 5.0, 1.0, 4.0, 2.0, 2.0, math.pi / 2]])
    pts = np.array(
        [[10.0, 6.9, 1.0], [10.0, 7.1, 1.0], [10.9, 5.0, 1.0], [11.1, 5.0, 1.0], [10, 5, 2.5]]
    )
    mask = points_in_boxes_mask(pts, box)
    assert mask.tolist() == [[True, False, True, False, False]]
    assert points_in_boxes_mask(np.zeros((0, 3)), box).shape == (1, 0)


def test_corners_inside_their_box():
    rng = np.random.default_rng(0)
    boxes = np.concatenate(
        [rng.normal(size=(5, 3)) * 10, rng.uniform(1, 4, (5, 3)), rng.uniform(-3, 3, (5, 1))], 1
    )
    corners = boxes_to_corners_3d(boxes)
    assert corners.shape == (5, 8, 3)
    centres = corners.mean(axis=1)
    np.testing.assert_allclose(centres, boxes[:, :3], atol=1e-9)


def test_transform_boxes_consistent_with_points():
    T = pose(0.7, [3.0, -2.0, 0.5])
    box = np.array([[4.0, 1.0, 0.5, 4.5, 2.0, 1.6, 0.3, 2.0, -1.0]])
    corners = boxes_to_corners_3d(box)[0]
    moved = transform_boxes(box, T)
    np.testing.assert_allclose(
        boxes_to_corners_3d(moved)[0], transform_points(corners, T), atol=1e-9
    )
    # velocity rotates with the pose
    np.testing.assert_allclose(moved[0, 7:9], T[:2, :2] @ box[0, 7:9], atol=1e-12)
    back = transform_boxes(moved, np.linalg.inv(T))
    np.testing.assert_allclose(back, box, atol=1e-9)
    tb = transform_boxes(torch.as_tensor(box), torch.as_tensor(T))
    assert isinstance(tb, torch.Tensor)
