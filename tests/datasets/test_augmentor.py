"""Augmentations and processors: geometry kept, GT sampling semantics, keyed determinism."""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import re
import threading

import numpy as np
import pytest
from shapely.geometry import Polygon
from waymo_tiny_data import CLASS_NAMES, dataset_cfg, write_tiny_waymo

from pcdet_atlas.config import ConfigError
from pcdet_atlas.datasets import WaymoDataset
from pcdet_atlas.datasets.augmentor import DataAugmentor
from pcdet_atlas.datasets.augmentor.box_ops import box_index_of_points
from pcdet_atlas.datasets.augmentor.gt_sampling import GTSampling
from pcdet_atlas.datasets.augmentor.processors import (
    ShufflePoints,
    mask_boxes_outside_range,
    mask_points_by_range,
    row_hash_order,
)
from pcdet_atlas.datasets.augmentor.world_transforms import (
    RandomWorldFlip,
    RandomWorldRotation,
    RandomWorldScaling,
)
from pcdet_atlas.datasets.multiframe import (
    compress_rows,
    copy_rows,
    row_records,
    rows_except,
)
from pcdet_atlas.datasets.waymo_format import WaymoFormatError
from pcdet_atlas.ops.boxes import boxes_to_corners_bev, points_in_boxes_mask
from pcdet_atlas.registry import TRANSFORMS
from pcdet_atlas.utils.paths import UnsafePathError


def _scene(seed=0, n_boxes=6, n_points=3000):
    rng = np.random.default_rng(seed)
    boxes = np.column_stack(
        [
            rng.uniform(-30, 30, (n_boxes, 2)),
            rng.uniform(-1, 1, n_boxes),
            rng.uniform(1, 5, (n_boxes, 3)),
            rng.uniform(-np.pi, np.pi, n_boxes),
            rng.uniform(-5, 5, (n_boxes, 2)),
        ]
    )
    pts = np.column_stack(
        [
            rng.uniform(-35, 35, (n_points, 2)),
            rng.uniform(-3, 3, n_points),
            rng.random((n_points, 2)),
        ]
    ).astype(np.float32)
    # make sure every box holds points
    inner = [b[:3] + (rng.random((30, 3)) - 0.5) * b[3:6] * 0.8 for b in boxes]  # rotated below
    for b, p in zip(boxes, inner):
        d = p[:, :2] - b[:2]
        c, s = np.cos(b[6]), np.sin(b[6])
        p[:, :2] = b[:2] + d @ np.array([[c, s], [-s, c]])
    extra = np.column_stack([np.concatenate(inner), rng.random((30 * n_boxes, 2))])
    pts = np.concatenate([pts, extra.astype(np.float32)])
    return {
        "points": pts,
        "gt_boxes": boxes,
        "gt_names": np.array(["Vehicle"] * n_boxes),
        "gt_boxes_mask": np.ones(n_boxes, bool),
    }


# ---------------------------------------------------------------------------- world transforms
@pytest.mark.parametrize(
    "transform",
    [
        RandomWorldFlip(["x", "y"]),
        RandomWorldRotation((-np.pi, np.pi)),
        RandomWorldScaling((0.8, 1.2)),
    ],
    ids=["flip", "rotation", "scaling"],
)
@pytest.mark.parametrize("draw", range(6))
def test_world_transforms_keep_points_in_boxes(transform, draw):
    data = _scene(seed=draw)
    before = points_in_boxes_mask(data["points"][:, :3].astype(np.float64), data["gt_boxes"])
    orig_pts, orig_boxes = data["points"].copy(), data["gt_boxes"].copy()
    out = transform(data, np.random.default_rng(draw))
    after = points_in_boxes_mask(out["points"][:, :3].astype(np.float64), out["gt_boxes"])
    # membership is kept except for points within float32 rounding of a face
    assert before.sum() > 100
    assert (before != after).sum() <= 2
    mat = _expected_linear(out)  # from the recorded draw, not from the transform's matrix
    np.testing.assert_allclose(out.get("lidar_aug_matrix", np.eye(4))[:3, :3], mat, atol=1e-12)
    if not isinstance(transform, RandomWorldFlip):  # a continuous draw: never the identity here
        assert not np.allclose(mat, np.eye(3), atol=1e-3)
    np.testing.assert_allclose(orig_pts[:, :3] @ mat.T, out["points"][:, :3], atol=1e-4)
    size_factor = out.get("noise_scale", 1.0)
    np.testing.assert_allclose(out["gt_boxes"][:, 3:6], orig_boxes[:, 3:6] * size_factor)
    np.testing.assert_allclose(orig_boxes[:, :3] @ mat.T, out["gt_boxes"][:, :3], atol=1e-9)
    vel = np.column_stack([orig_boxes[:, 7:9], np.zeros(len(orig_boxes))]) @ mat.T
    np.testing.assert_allclose(vel[:, :2], out["gt_boxes"][:, 7:9], atol=1e-9)
    np.testing.assert_array_equal(out["points"][:, 3:], orig_pts[:, 3:])
    # headings: the box's forward direction maps like a vector
    fwd = np.column_stack([np.cos(orig_boxes[:, 6]), np.sin(orig_boxes[:, 6])]) @ mat[:2, :2].T
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    got = np.column_stack([np.cos(out["gt_boxes"][:, 6]), np.sin(out["gt_boxes"][:, 6])])
    np.testing.assert_allclose(got, fwd, atol=1e-9)


def _expected_linear(out: dict) -> np.ndarray:
    """The 3x3 map a world transform should have applied, from what it recorded."""
    if "noise_rot" in out:
        c, s = np.cos(out["noise_rot"]), np.sin(out["noise_rot"])
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # CCW about z
    if "noise_scale" in out:
        return np.eye(3) * out["noise_scale"]
    # flip_x mirrors across the x axis (y -> -y), flip_y across the y axis (x -> -x)
    return np.diag([-1.0 if out["flip_y"] else 1.0, -1.0 if out["flip_x"] else 1.0, 1.0])


def test_flip_draws_both_outcomes_and_records_them():
    seen = set()
    for i in range(40):
        data = _scene(n_boxes=1)
        orig = data["points"][:, :3].copy()
        out = RandomWorldFlip(["x", "y"])(data, np.random.default_rng(i))
        seen.add((out["flip_x"], out["flip_y"]))
        np.testing.assert_array_equal(out["points"][:, :3], orig * np.diag(_expected_linear(out)))
    assert seen == {(False, False), (False, True), (True, False), (True, True)}


def test_rotation_and_scaling_ranges():
    rots = [
        RandomWorldRotation((-0.5, 0.25))(_scene(n_boxes=1), np.random.default_rng(i))["noise_rot"]
        for i in range(50)
    ]
    assert min(rots) >= -0.5 and max(rots) <= 0.25 and np.ptp(rots) > 0.5
    scales = [
        RandomWorldScaling((0.95, 1.05))(_scene(n_boxes=1), np.random.default_rng(i))["noise_scale"]
        for i in range(50)
    ]
    assert min(scales) >= 0.95 and max(scales) <= 1.05 and np.ptp(scales) > 0.05


def test_augmentor_wraps_heading_and_applies_mask():
    aug = DataAugmentor([("random_world_rotation", RandomWorldRotation((3.0, 3.1)))])
    data = _scene(n_boxes=4)
    data["gt_boxes"][:, 6] = 3.0
    data["gt_boxes_mask"] = np.array([True, False, True, True])
    out = aug.forward(data, (0, 0, "seq", 0))
    assert len(out["gt_boxes"]) == 3 and "gt_boxes_mask" not in out
    assert (out["gt_boxes"][:, 6] >= -np.pi).all() and (out["gt_boxes"][:, 6] < np.pi).all()


# ---------------------------------------------------------------------------- processors
def test_mask_points_by_range_is_bev_unless_filter_z():
    pts = np.array([[0, 0, 10, 0, 0], [5, 0, 0, 0, 0], [0, 11, 0, 0, 0]], np.float32)
    rng = [-10, -10, -2, 10, 10, 4]
    np.testing.assert_array_equal(mask_points_by_range(pts, rng), [True, True, False])
    np.testing.assert_array_equal(mask_points_by_range(pts, rng, True), [False, True, False])


def test_mask_boxes_by_corners_counts_all_8_corners_as_openpcdet():
    # OpenPCDet counts the xy of all 8 box corners (each BEV corner twice): a box with one
    # BEV corner in range has 2 corners in range, so min_num_corners=2 keeps it.
    rng = [-10, -10, -2, 10, 10, 4]
    box = np.array([[10.5, 10.5, 0, 2, 2, 2, 0]])  # only its corner (9.5, 9.5) is inside
    keep = mask_boxes_outside_range(box, rng, min_num_corners=2, use_center_to_filter=False)
    np.testing.assert_array_equal(keep, [True])
    keep = mask_boxes_outside_range(box, rng, min_num_corners=3, use_center_to_filter=False)
    np.testing.assert_array_equal(keep, [False])
    keep = mask_boxes_outside_range(box, rng, min_num_corners=1, use_center_to_filter=True)
    np.testing.assert_array_equal(keep, [False])  # centre outside


def test_compress_rows_equals_boolean_indexing():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((1000, 6)).astype(np.float32)
    for mask in (rng.random(1000) < 0.7, np.zeros(1000, bool), np.ones(1000, bool)):
        for arr in (a, a[:, :5], np.asfortranarray(a)):
            got = compress_rows(mask, arr)
            assert got.shape == arr[mask].shape and got.dtype == arr.dtype
            np.testing.assert_array_equal(got, arr[mask])


@pytest.mark.parametrize("num_runs", [0, 1, 30, 64, 65, 500])
def test_rows_except_and_copy_rows_equal_plain_indexing(num_runs):
    """Rows moved as opaque records (strided rows of a frame file's first columns, contiguous
    and Fortran-ordered arrays) equal numpy's element-wise results (selection, copy),
    on both sides of the block-copy / masked-copy switch (64 runs of dropped rows)."""
    rng = np.random.default_rng(num_runs)
    raw = rng.standard_normal((3000, 6)).astype(np.float32)
    keep = np.ones(len(raw), bool)
    for start in np.sort(rng.choice(len(raw) - 4, num_runs, replace=False))[::2]:
        keep[start : start + rng.integers(1, 4)] = False  # runs, some merging
    drop = np.flatnonzero(~keep)
    for arr in (raw[:, :5], raw, np.asfortranarray(raw[:, :5])):
        assert (row_records(arr) is None) == (not arr.flags.c_contiguous and arr.strides[1] != 4)
        got = rows_except(arr, drop)
        assert got.flags.c_contiguous and got.dtype == arr.dtype
        np.testing.assert_array_equal(got, arr[keep])
        copied = copy_rows(arr)
        assert copied.flags.c_contiguous and not np.shares_memory(copied, arr)
        np.testing.assert_array_equal(copied, arr)


def test_shuffle_is_a_permutation():
    data = {"points": np.arange(50, dtype=np.float32).reshape(10, 5)}
    out = ShufflePoints(True)(dict(data), np.random.default_rng(0))
    assert not np.array_equal(out["points"], data["points"])
    np.testing.assert_array_equal(np.sort(out["points"][:, 0]), data["points"][:, 0])
    same = ShufflePoints(False)(dict(data), np.random.default_rng(0))
    np.testing.assert_array_equal(same["points"], data["points"])


def _row_bytes(rows: np.ndarray) -> np.ndarray:
    return (
        np.ascontiguousarray(rows)
        .view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1])))
        .ravel()
    )


def test_shuffle_order_depends_on_the_rows_not_their_order():
    """A subset of the rows comes out in its order within the whole set, whatever order the
    rows came in: the newest frames of a longer sample keep a shorter sample's order."""
    rng = np.random.default_rng(3)
    points = rng.standard_normal((400, 6)).astype(np.float32)
    points[10] = points[20]  # equal rows are interchangeable
    full = points[row_hash_order(points, 11)]
    subset = rng.random(400) < 0.4
    part = points[subset]
    shuffled = part[rng.permutation(len(part))]
    for rows in (part, shuffled):
        got = rows[row_hash_order(rows, 11)]
        in_full = np.isin(_row_bytes(full), _row_bytes(part))
        np.testing.assert_array_equal(got, full[in_full])
    other_seed = points[row_hash_order(points, 12)]
    assert not np.array_equal(other_seed, full)
    np.testing.assert_array_equal(np.sort(full, axis=0), np.sort(points, axis=0))
    assert row_hash_order(points[:0], 11).shape == (0,)  # an empty frame
    for odd in (points[:, :5], points.astype(np.float64)):  # rows not a multiple of 8 bytes
        order = row_hash_order(odd, 11)
        np.testing.assert_array_equal(np.sort(order), np.arange(400))


def test_registered_transforms():
    assert {
        "gt_sampling",
        "random_world_flip",
        "random_world_rotation",
        "random_world_scaling",
        "mask_points_and_boxes_outside_range",
        "shuffle_points",
    } <= set(TRANSFORMS.list())
    assert "transform_points_to_voxels" not in TRANSFORMS


# ---------------------------------------------------------------------------- box ops
def _polygon(box):
    return Polygon(boxes_to_corners_bev(np.asarray(box, dtype=np.float64)[None, :7])[0])


def test_box_index_of_points_matches_mask():
    data = _scene(seed=3, n_boxes=8)
    boxes = data["gt_boxes"].copy()
    boxes[1] = boxes[0]  # overlapping boxes: the lower index wins
    idx = box_index_of_points(data["points"], boxes)
    mask = points_in_boxes_mask(data["points"][:, :3].astype(np.float64), boxes)
    expected = np.where(mask.any(0), mask.argmax(0), -1)
    np.testing.assert_array_equal(idx, expected)
    assert (idx == 0).sum() > 0 and (idx == 1).sum() == 0


@pytest.mark.parametrize("span", [40.0, 150.0, 5000.0])
def test_box_index_of_points_over_wide_scenes_and_cell_edges(span):
    """The BEV grid that picks candidate points changes nothing: against the brute-force mask
    for scenes narrower and far wider than its cells, boxes on cell edges and off the points."""
    rng = np.random.default_rng(int(span))
    background = rng.uniform(-span / 2, span / 2, (20000, 2))
    centres = np.column_stack([background[:30], rng.uniform(-1, 3, 30)])
    centres[:5, 0] = np.floor(centres[:5, 0])  # on the edges of 1 m cells
    boxes = np.column_stack(
        [centres, rng.uniform(0.5, 6.0, (30, 3)), rng.uniform(-np.pi, np.pi, 30)]
    )
    boxes[-1, :2] = span  # off the points
    near = np.repeat(centres, 40, axis=0) + rng.uniform(-3, 3, (1200, 3))
    corners = boxes_to_corners_bev(boxes[:10])[:, 0]  # on a corner of a box
    xyz = np.concatenate(
        [np.column_stack([background, rng.uniform(-1, 3, 20000)]), near,
         np.column_stack([corners, centres[:10, 2]])]
    )  # fmt: skip
    points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz))])
    idx = box_index_of_points(points, boxes)
    mask = points_in_boxes_mask(points[:, :3].astype(np.float64), boxes)
    np.testing.assert_array_equal(idx, np.where(mask.any(0), mask.argmax(0), -1))
    assert (idx >= 0).sum() > 100


# ---------------------------------------------------------------------------- GT sampling
def _write_db(root, entries, num_features=5):
    """entries: (name, box(9,), points (n, F) box-centred). Writes .bin files, pkl, global."""
    db_dir = root / "db"
    db_dir.mkdir(parents=True, exist_ok=True)
    infos, stacked, offset = {}, [], 0
    for i, (name, box, pts) in enumerate(entries):
        path = db_dir / f"obj_{i}.bin"
        pts.astype(np.float32).tofile(path)
        infos.setdefault(name, []).append(
            {
                "name": name,
                "path": str(path.relative_to(root)),
                "sequence_name": "s",
                "sample_idx": i,
                "gt_idx": 0,
                "box3d_lidar": np.asarray(box, np.float64),
                "num_points_in_gt": len(pts),
                "difficulty": 1,
                "global_data_offset": [offset, offset + len(pts)],
            }
        )
        stacked.append(pts.astype(np.float32))
        offset += len(pts)
    with open(root / "dbinfos.pkl", "wb") as f:
        pickle.dump(infos, f)
    np.save(root / "global.npy", np.concatenate(stacked))


def _obj_points(box, n, rng, num_features=5, lags=(0.0,)):
    local = (rng.random((n, 3)) - 0.5) * np.asarray(box[3:6]) * 0.8
    c, s = np.cos(box[6]), np.sin(box[6])
    local[:, :2] = local[:, :2] @ np.array([[c, s], [-s, c]])
    cols = [local, rng.random((n, 2))]
    if num_features == 6:
        cols.append(np.asarray(lags)[np.arange(n) % len(lags)][:, None])
    return np.concatenate(cols, axis=1)


@pytest.mark.parametrize("use_shared_memory", [False, True])
def test_gt_sampling_pastes_only_non_colliding_and_clears_points(tmp_path, use_shared_memory):
    rng = np.random.default_rng(0)
    existing = np.array([[0.0, 0, 0, 4, 2, 1.6, 0.0], [10, 10, 0, 4, 2, 1.6, 0.0]])
    db_boxes = {
        "free_a": [20, 0, 0, 4, 2, 1.6, 0.2, 1, 0],
        "free_b": [-15, -15, 0, 4, 2, 1.6, 1.0, 0, 0],
        "hits_existing": [1.5, 0.5, 0, 4, 2, 1.6, 0.3, 0, 0],  # overlaps existing[0]
        "pair_1": [-20, 10, 0, 4, 2, 1.6, 0.0, 0, 0],
        "pair_2": [-18, 10.5, 0, 4, 2, 1.6, 0.4, 0, 0],  # overlaps pair_1: both rejected
        "touching": [10, 12, 0, 4, 2, 1.6, 0.0, 0, 0],  # shares an edge with existing[1]: allowed
    }
    entries = [("Vehicle", box, _obj_points(box, 20, rng)) for box in db_boxes.values()]
    entries.append(
        ("Vehicle", [30, 30, 0, 4, 2, 1.6, 0, 0, 0], _obj_points(db_boxes["free_a"], 3, rng))
    )
    _write_db(tmp_path, entries)
    sampler = GTSampling(
        root_path=tmp_path,
        class_names=CLASS_NAMES,
        db_info_paths=["dbinfos.pkl"],
        db_data_paths=["global.npy"],
        use_shared_memory=use_shared_memory,
        sample_groups={"Vehicle": 100},
        num_point_features=5,
        min_points={"Vehicle": 5},  # drops the 3-point entry
        limit_whole_scene=True,
    )
    assert len(sampler.db_infos["Vehicle"]) == 6
    # scene points: a grid, some of them inside where the free boxes will go
    gx, gy = np.meshgrid(np.arange(-30, 30, 0.5), np.arange(-30, 30, 0.5))
    scene = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size), np.ones((gx.size, 2))])
    data = {
        "points": scene.astype(np.float32),
        "gt_boxes": existing,
        "gt_names": np.array(["Vehicle", "Vehicle"]),
        "gt_boxes_mask": np.array([True, True]),
    }
    out = sampler(data, np.random.default_rng(1))
    pasted = out["gt_boxes"][2:]
    got = {
        name
        for name, box in db_boxes.items()
        if any(np.allclose(box[:7], p[:7], atol=1e-5) for p in pasted)
    }
    assert got == {"free_a", "free_b", "touching"}
    assert out["gt_boxes"].shape == (5, 7)  # scene boxes have 7 values: speeds dropped
    assert list(out["gt_names"]) == ["Vehicle"] * 5
    # no pasted box overlaps anything else
    for i in range(len(out["gt_boxes"])):
        for j in range(i):
            area = _polygon(out["gt_boxes"][i]).intersection(_polygon(out["gt_boxes"][j])).area
            assert area < 1e-9
    # scene points inside pasted boxes are gone; object points are prepended
    n_obj = 60
    obj, rest = out["points"][:n_obj], out["points"][n_obj:]
    assert (points_in_boxes_mask(rest[:, :3].astype(np.float64), pasted).sum(0) == 0).all()
    assert points_in_boxes_mask(obj[:, :3].astype(np.float64), pasted).any(0).all()
    inside_before = points_in_boxes_mask(scene[:, :3], pasted).any(0).sum()
    assert inside_before > 0 and len(rest) == len(scene) - inside_before


def test_gt_sampling_limit_whole_scene_and_time_filter(tmp_path):
    rng = np.random.default_rng(0)
    boxes = [[x, 0, 0, 4, 2, 1.6, 0, 0, 0] for x in (-30, -20, -10, 10, 20, 30)]
    lags = (0.0, 0.1, 0.2, 0.3, 0.4)
    _write_db(tmp_path, [("Vehicle", b, _obj_points(b, 10, rng, 6, lags)) for b in boxes], 6)

    def make(**kw):
        return GTSampling(
            root_path=tmp_path,
            class_names=CLASS_NAMES,
            db_info_paths=["dbinfos.pkl"],
            sample_groups={"Vehicle": 4},
            num_point_features=6,
            **kw,
        )

    existing = np.array([[0.0, 20, 0, 4, 2, 1.6, 0], [0.0, -20, 0, 4, 2, 1.6, 0]])

    def scene(columns):
        return {
            "points": np.zeros((0, columns), np.float32),
            "gt_boxes": existing.copy(),
            "gt_names": np.array(["Vehicle", "Vehicle"]),
            "gt_boxes_mask": np.array([True, True]),
        }

    limited = make(limit_whole_scene=True)(scene(6), np.random.default_rng(0))
    assert len(limited["gt_boxes"]) == 4  # 2 existing + (4 - 2) sampled
    full = make(limit_whole_scene=False, filter_obj_points_by_timestamp=True, time_range=[0.3, 0.0])
    out = full(scene(6), np.random.default_rng(0))
    assert len(out["gt_boxes"]) == 6
    assert set(np.round(out["points"][:, 5].astype(np.float64), 6)) == {0.0, 0.1, 0.2, 0.3}
    assert len(out["points"]) == 4 * 8  # lag 0.4 points dropped (2 of 10 per object)
    # a 5-column (single-frame) scene keeps only lag-0 points and drops the column
    single = make(limit_whole_scene=False)(scene(5), np.random.default_rng(0))
    assert single["points"].shape == (4 * 2, 5)


def test_gt_sampling_rejects_mismatched_point_file(tmp_path):
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    _write_db(tmp_path, [("Vehicle", box, _obj_points(box, 10, np.random.default_rng(0)))])
    with open(tmp_path / "dbinfos.pkl", "rb") as f:
        infos = pickle.load(f)
    infos["Vehicle"][0]["num_points_in_gt"] = 11
    with open(tmp_path / "dbinfos.pkl", "wb") as f:
        pickle.dump(infos, f)
    sampler = GTSampling(tmp_path, CLASS_NAMES, ["dbinfos.pkl"], {"Vehicle": 1}, 5)
    data = {
        "points": np.zeros((0, 5), np.float32),
        "gt_boxes": np.zeros((0, 7)),
        "gt_names": np.array([], dtype=str),
        "gt_boxes_mask": np.zeros(0, bool),
    }
    with pytest.raises(
        WaymoFormatError, match=r"obj_0\.bin: 10 points, but its db_info says num_points_in_gt=11"
    ):
        sampler(data, np.random.default_rng(0))


@pytest.mark.parametrize("use_shared_memory", [False, True])
@pytest.mark.parametrize("column", [0, 3, 4])  # x, intensity, elongation
def test_gt_sampling_rejects_non_finite_object_points(tmp_path, use_shared_memory, column):
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    pts = _obj_points(box, 10, np.random.default_rng(0))
    pts[7, column] = np.nan
    _write_db(tmp_path, [("Vehicle", box, pts)])
    sampler = GTSampling(
        tmp_path, CLASS_NAMES, ["dbinfos.pkl"], {"Vehicle": 1}, 5,
        use_shared_memory=use_shared_memory, db_data_paths=["global.npy"],
    )  # fmt: skip
    data = {
        "points": np.zeros((0, 5), np.float32),
        "gt_boxes": np.zeros((0, 7)),
        "gt_boxes_mask": np.zeros(0, bool),
        "gt_names": np.array([], dtype=str),
    }
    where = r"global\.npy\[0:10\]" if use_shared_memory else r"obj_0\.bin"
    with pytest.raises(WaymoFormatError, match=rf"{where}: 1 point\(s\) with NaN/inf .*row 7, "
                       rf"column {column}"):  # fmt: skip
        sampler(data, np.random.default_rng(0))


@pytest.mark.parametrize("key", ["sample_groups", "min_points"])
def test_gt_sampling_class_names_typo_is_an_error(tmp_path, key):
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    _write_db(tmp_path, [("Vehicle", box, _obj_points(box, 10, np.random.default_rng(0)))])
    groups = {"sample_groups": {"Vehicle": 1}, "min_points": {"Vehicle": 5}}
    groups[key] = {**groups[key], "Pedestrain": 10}
    name = "SAMPLE_GROUPS" if key == "sample_groups" else "PREPARE.filter_by_min_points"
    with pytest.raises(
        ConfigError, match=rf"gt_sampling\.{name} \(my\.yaml\): \['Pedestrain'\] is not a class"
    ):
        GTSampling(
            tmp_path, CLASS_NAMES, ["dbinfos.pkl"], groups["sample_groups"], 5,
            min_points=groups["min_points"], section="my.yaml",
        )  # fmt: skip


def test_gt_sampling_waymo_class_not_trained_is_left_out_and_logged(tmp_path, caplog):
    rng = np.random.default_rng(0)
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    _write_db(tmp_path, [("Vehicle", box, _obj_points(box, 10, rng)),
                         ("Cyclist", box, _obj_points(box, 10, rng))])  # fmt: skip
    logger = logging.getLogger("test_gt_sampling_not_trained")
    with caplog.at_level("INFO", logger=logger.name):
        sampler = GTSampling(
            tmp_path, ["Vehicle"], ["dbinfos.pkl"], {"Vehicle": 1, "Cyclist": 2, "Sign": 1}, 5,
            min_points={"Cyclist": 5}, logger=logger, section="my.yaml",
        )  # fmt: skip
    assert sampler.sample_groups == {"Vehicle": 1} and set(sampler.db_infos) == {"Vehicle"}
    lines = [r.getMessage() for r in caplog.records if "not in CLASS_NAMES" in r.getMessage()]
    assert lines == [
        "gt_sampling.PREPARE.filter_by_min_points (my.yaml): ['Cyclist'] not in CLASS_NAMES "
        "['Vehicle']; left out",
        "gt_sampling.SAMPLE_GROUPS (my.yaml): ['Cyclist', 'Sign'] not in CLASS_NAMES "
        "['Vehicle']; left out",
    ]


def _empty_scene():
    return {
        "points": np.zeros((0, 5), np.float32),
        "gt_boxes": np.zeros((0, 7)),
        "gt_boxes_mask": np.zeros(0, bool),
        "gt_names": np.array([], dtype=str),
    }


@pytest.mark.parametrize("where", ["absolute", "dotdot", "inner_dotdot", "empty"])
def test_gt_sampling_refuses_a_db_info_path_outside_the_data_root(tmp_path, where):
    """A db_info ``path`` is data: an absolute one or one with ``..`` is refused when the
    database is loaded, naming the info file and the entry, before anything is read."""
    root = tmp_path / "root"
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    rng = np.random.default_rng(0)
    _write_db(root, [("Vehicle", box, _obj_points(box, 10, rng)) for _ in range(2)])
    secret = tmp_path / "secret.bin"
    _obj_points(box, 10, rng).astype(np.float32).tofile(secret)
    bad = {"absolute": str(secret), "dotdot": "../secret.bin",
           "inner_dotdot": "db/../../secret.bin", "empty": ""}[where]  # fmt: skip
    with open(root / "dbinfos.pkl", "rb") as f:
        infos = pickle.load(f)
    infos["Vehicle"][1]["path"] = bad
    with open(root / "dbinfos.pkl", "wb") as f:
        pickle.dump(infos, f)
    info_file = re.escape(str(root / "dbinfos.pkl"))
    with pytest.raises(UnsafePathError, match=rf"path '{re.escape(bad)}' \(from {info_file} "
                       r"Vehicle\[1\]\) is not a relative path"):  # fmt: skip
        GTSampling(root, CLASS_NAMES, ["dbinfos.pkl"], {"Vehicle": 2}, 5)


@pytest.mark.parametrize(
    "bad, message",
    [
        ("name path box3d_lidar num_points_in_gt difficulty", r"Vehicle\[1\] is a str, expected "
                                                              r"a db_info dict with keys \['name'"),
        (["name", "path"], r"Vehicle\[1\] is a list, expected a db_info dict"),
    ],
)  # fmt: skip
def test_gt_sampling_refuses_a_db_info_that_is_not_a_dict(tmp_path, bad, message):
    """``key not in info`` holds for a string naming every key: an entry that is no dict is
    refused when the database loads, naming the info file, the class and the index."""
    root = tmp_path / "root"
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    rng = np.random.default_rng(0)
    _write_db(root, [("Vehicle", box, _obj_points(box, 10, rng)) for _ in range(2)])
    with open(root / "dbinfos.pkl", "rb") as f:
        infos = pickle.load(f)
    infos["Vehicle"][1] = bad
    with open(root / "dbinfos.pkl", "wb") as f:
        pickle.dump(infos, f)
    info_file = re.escape(str(root / "dbinfos.pkl"))
    with pytest.raises(WaymoFormatError, match=rf"{info_file}: {message}"):
        GTSampling(root, CLASS_NAMES, ["dbinfos.pkl"], {"Vehicle": 2}, 5)
    infos["Vehicle"] = {"name": "Vehicle"}  # a class's entries that are no list
    with open(root / "dbinfos.pkl", "wb") as f:
        pickle.dump(infos, f)
    with pytest.raises(WaymoFormatError, match=rf"{info_file}: Vehicle is a dict, expected a list"):
        GTSampling(root, CLASS_NAMES, ["dbinfos.pkl"], {"Vehicle": 2}, 5)


@pytest.mark.parametrize("key", ["DB_INFO_PATH", "DB_DATA_PATH"])
def test_gt_sampling_refuses_db_paths_outside_the_data_root(tmp_path, key):
    """``DB_INFO_PATH`` / ``DB_DATA_PATH`` are relative to the data root and stay under it."""
    root = tmp_path / "root"
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    for folder in (root, tmp_path):  # a database under the root, and one beside it
        _write_db(folder, [("Vehicle", box, _obj_points(box, 10, np.random.default_rng(0)))])
    value = "../dbinfos.pkl" if key == "DB_INFO_PATH" else str(tmp_path / "global.npy")
    paths = {"DB_INFO_PATH": ["dbinfos.pkl"], "DB_DATA_PATH": ["global.npy"], key: [value]}
    with pytest.raises(UnsafePathError, match=rf"gt_sampling\.{key} '{re.escape(value)}' "
                       r"\(from my\.yaml\) is not a relative path"):  # fmt: skip
        GTSampling(
            root, CLASS_NAMES, paths["DB_INFO_PATH"], {"Vehicle": 1}, 5,
            db_data_paths=paths["DB_DATA_PATH"], use_shared_memory=True, section="my.yaml",
        )  # fmt: skip


@pytest.mark.parametrize("kind", ["symlink_out", "fifo"])
def test_gt_sampling_reads_only_regular_files_under_the_data_root(tmp_path, kind):
    """A lexically fine ``path`` that is a symlink leading out of the root, or a FIFO (a read
    that never ends, as ``/dev/zero``), is refused when the object is read."""
    root = tmp_path / "root"
    box = [0, 0, 0, 4, 2, 1.6, 0, 0, 0]
    rng = np.random.default_rng(0)
    _write_db(root, [("Vehicle", box, _obj_points(box, 10, rng))])
    obj = root / "db" / "obj_0.bin"
    obj.unlink()
    if kind == "symlink_out":
        secret = tmp_path / "secret.bin"
        _obj_points(box, 10, rng).astype(np.float32).tofile(secret)
        obj.symlink_to(secret)
        expected = (
            rf"obj_0\.bin \(from a db_info of .*dbinfos\.pkl\) resolves to "
            rf"{re.escape(str(secret.resolve()))}, outside its root"
        )
    else:
        os.mkfifo(obj)
        expected = r"GT database object .*obj_0\.bin is a FIFO, not a regular file"
    sampler = GTSampling(root, CLASS_NAMES, ["dbinfos.pkl"], {"Vehicle": 1}, 5)
    with _fifo_read_ends(obj), pytest.raises(UnsafePathError, match=expected):
        sampler(_empty_scene(), np.random.default_rng(0))


@contextlib.contextmanager
def _fifo_read_ends(path):
    """Were the FIFO at ``path`` opened for reading (the read would never end), a writer opens
    and closes it, which ends the read: the test then fails instead of hanging."""
    done = threading.Event()

    def writer():
        while path.is_fifo() and not done.wait(0.2):
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
                return
            except OSError:  # no reader yet
                pass

    thread = threading.Thread(target=writer, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


# ---------------------------------------------------------------------------- determinism
@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    return write_tiny_waymo(tmp_path_factory.mktemp("tiny_aug"))


def test_augmentation_is_keyed_by_seed_epoch_and_frame(tiny_root):
    cfg = dataset_cfg(augment=True, shuffle=True)
    ds = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=tiny_root)
    other = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=tiny_root)
    a, b = ds[3], other[3]
    np.testing.assert_array_equal(a["points"], b["points"])
    np.testing.assert_array_equal(a["gt_boxes"], b["gt_boxes"])
    _ = other[5]  # loading other frames first changes nothing
    np.testing.assert_array_equal(other[3]["points"], a["points"])
    assert ds[4]["noise_rot"] != a["noise_rot"]  # frames differ
    ds.set_epoch(1)
    assert ds[3]["noise_rot"] != a["noise_rot"]  # epochs differ
    ds.set_epoch(0)
    assert ds[3]["noise_rot"] == a["noise_rot"]
    ds.seed = 123
    assert ds[3]["noise_rot"] != a["noise_rot"]  # seeds differ
