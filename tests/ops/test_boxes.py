import math

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon

from pcdet_atlas.ops.boxes import (
    boxes_bev_overlap,
    boxes_to_corners_3d,
    boxes_to_corners_bev,
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


# ---------------------------------------------------------------------------- BEV overlap
def _polygon(box):
    return Polygon(boxes_to_corners_bev(np.asarray(box, dtype=np.float64)[None])[0])


_box = st.tuples(
    st.floats(-20, 20),
    st.floats(-20, 20),
    st.floats(0.1, 8),
    st.floats(0.1, 8),
    st.floats(-np.pi, np.pi),
).map(lambda t: [t[0], t[1], 0.0, t[2], t[3], 1.0, t[4]])


@settings(max_examples=200, deadline=None)
@given(a=st.lists(_box, min_size=1, max_size=4), b=st.lists(_box, min_size=1, max_size=4))
def test_bev_overlap_matches_polygon_clipping(a, b):
    got = boxes_bev_overlap(np.array(a), np.array(b))
    for i, ba in enumerate(a):
        for j, bb in enumerate(b):
            area = _polygon(ba).intersection(_polygon(bb)).area
            if area > 1e-6:
                assert got[i, j]
            elif area == 0:
                assert not got[i, j]


def test_bev_overlap_edge_cases():
    box = np.array([[0, 0, 0, 2, 2, 1, 0.0]])
    touching = np.array([[2, 0, 5, 2, 2, 1, 0.0]])  # shares an edge, z ignored
    rotated_inside = np.array([[0, 0, 0, 0.5, 0.5, 1, 0.7]])
    far = np.array([[100, 0, 0, 2, 2, 1, 0.0]])
    degenerate = np.array([[0, 0, 0, 0, 2, 1, 0.0]])
    assert not boxes_bev_overlap(box, touching)[0, 0]
    assert boxes_bev_overlap(box, rotated_inside)[0, 0]
    assert boxes_bev_overlap(box, box)[0, 0]
    assert not boxes_bev_overlap(box, far)[0, 0]
    assert not boxes_bev_overlap(box, degenerate)[0, 0]
    # negative length and width: no area, as in boxes_iou_bev (a product test would say > 0)
    negative = np.array([[0, 0, 0, -2, -2, 1, 0.0]])
    assert not boxes_bev_overlap(box, negative)[0, 0]
    assert not boxes_bev_overlap(negative, box)[0, 0]
    assert boxes_bev_overlap(np.zeros((0, 7)), box).shape == (0, 1)
