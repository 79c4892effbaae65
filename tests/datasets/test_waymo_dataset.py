"""WaymoDataset: the processed-Waymo layout, single- and multi-frame loading, options, collate."""

from __future__ import annotations

import pickle
import re
import sys
import types

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader
from waymo_tiny_data import (
    CLASS_NAMES,
    DATASET_CFG,
    MULTIFRAME_CFG,
    dataset_cfg,
    ego_pose,
    world_points,
    write_tiny_waymo,
)

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file, resolve_repo_path
from pcdet_atlas.datasets import WaymoDataset, build_dataloader
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.datasets.loader import ResumableSampler
from pcdet_atlas.datasets.multiframe import (
    history_sample_indices,
    outside_ego_mask,
    transform_points_to_frame,
)
from pcdet_atlas.ops.boxes import points_in_boxes_mask, transform_points
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.utils.paths import UnsafePathError
from pcdet_atlas.utils.seeding import derive_seed

SEQ_A = "segment-111_with_camera_labels"
SEQ_B = "segment-222_with_camera_labels"
SEQ_V = "segment-333_with_camera_labels"


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    return write_tiny_waymo(tmp_path_factory.mktemp("tiny_waymo"), empty_frames={(SEQ_B, 2)})


# ---------------------------------------------------------------------------- format
def test_format_round_trip_keys_dtypes_shapes(tiny_root):
    """What the helpers write is OpenPCDet's layout; what the loader returns follows it."""
    assert (tiny_root / "ImageSets" / "train.txt").read_text().splitlines() == [
        f"{SEQ_A}.tfrecord",
        f"{SEQ_B}.tfrecord",
    ]
    with open(wf.sequence_pkl_path(tiny_root, SEQ_A), "rb") as f:
        infos = pickle.load(f)
    info = infos[3]
    assert set(info) == set(wf.INFO_KEYS) | {"annos"}
    assert info["point_cloud"] == {"num_features": 5, "lidar_sequence": SEQ_A, "sample_idx": 3}
    assert info["frame_id"] == f"{SEQ_A}_003"
    assert info["pose"].dtype == np.float32 and info["pose"].shape == (4, 4)
    assert isinstance(info["num_points_of_each_lidar"], list)
    annos = info["annos"]
    assert set(annos) == set(wf.ANNO_KEYS) and "score" not in annos
    assert annos["gt_boxes_lidar"].shape == (7, 9) and annos["gt_boxes_lidar"].dtype == np.float64
    assert annos["difficulty"].dtype == np.int64 and annos["num_points_in_gt"].dtype == np.int64
    raw = np.load(wf.frame_npy_path(tiny_root, SEQ_A, 3))
    assert raw.dtype == np.float32 and raw.shape[1] == 6
    assert (wf.data_dir(tiny_root) / SEQ_A / "0003.npy").is_file()

    ds = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=tiny_root)
    assert DATASETS.get("WaymoDataset") is WaymoDataset
    assert len(ds) == 6 and ds.split == "val"
    sample = ds[3]
    assert sample["frame_id"] == f"{SEQ_V}_003" and sample["sample_idx"] == 3
    assert sample["sequence_name"] == SEQ_V
    assert sample["points"].dtype == np.float32 and sample["points"].shape[1] == 5
    assert sample["gt_boxes"].dtype == np.float32 and sample["gt_boxes"].shape[1] == 8
    np.testing.assert_array_equal(sample["pose"], ds.infos[3]["pose"])
    # Sign is not a class: dropped; class index is 1-based in CLASS_NAMES order
    assert list(sample["gt_names"]) == ["Vehicle"] * 4 + ["Pedestrian", "Cyclist"]
    np.testing.assert_array_equal(sample["gt_boxes"][:, 7], [1, 1, 1, 1, 2, 3])
    assert sample["metadata"]["timestamp_micros"] == 1_500_000_000_300_000
    assert ds.get_frame_info(SEQ_V, 3) is ds.infos[3]


def test_data_path_resolves_against_the_repository_root(tiny_root, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # the working directory plays no part
    ds = WaymoDataset(dataset_cfg(DATA_PATH=str(tiny_root)), CLASS_NAMES, training=False)
    assert ds.root_path == tiny_root and len(ds) == 6
    assert resolve_repo_path("data/waymo") == REPO_ROOT / "data" / "waymo"
    # a plain dict works as well as an EasyDict
    plain = WaymoDataset(dict(dataset_cfg()), CLASS_NAMES, training=False, root_path=tiny_root)
    assert len(plain) == 6


@pytest.mark.parametrize("key", ["DATA_SPLIT", "PROCESSED_DATA_TAG"])
def test_a_split_or_data_tag_leaving_the_root_is_refused(tmp_path, key):
    """``DATA_SPLIT`` names ``ImageSets/<split>.txt`` and ``PROCESSED_DATA_TAG`` the frames'
    folder: each must be one file name (``../x`` would read beside the root), named with its
    file; ``set_split`` (``--split`` of the GT-database tool) is held to the same rule."""
    root = write_tiny_waymo(tmp_path / "root")
    (root / "val_copy.txt").write_text((root / "ImageSets" / "val.txt").read_text())
    if key == "DATA_SPLIT":  # ImageSets/../val_copy.txt
        value, shown, entry = "../val_copy", "DATA_SPLIT.test", "DATA_SPLIT: {test: '../val_copy'}"
    else:  # the root's own frames, reached from outside it
        value = f"../root/{wf.PROCESSED_DATA_TAG}"
        shown, entry = key, f"PROCESSED_DATA_TAG: '{value}'"
    yaml_path = tmp_path / "data.yaml"
    yaml_path.write_text(f"_BASE_CONFIG_: {DATASET_CFG}\n{entry}\n")
    expected = rf"DATA_CONFIG\.{shown} '{re.escape(value)}' \(from {re.escape(str(yaml_path))}\)"
    with pytest.raises(UnsafePathError, match=expected + " is not one file or folder name"):
        WaymoDataset(cfg_from_yaml_file(yaml_path), CLASS_NAMES, training=False, root_path=root)
    ds = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=root)
    with pytest.raises(UnsafePathError, match=r"split '\.\./val_copy' \(from WaymoDataset\.set_"):
        ds.set_split("../val_copy")
    assert ds.split == "val" and len(ds) == 6  # left as it was


def test_get_lidar_nlz_and_tanh(tiny_root):
    raw = np.load(wf.frame_npy_path(tiny_root, SEQ_A, 1))
    cfg = dataset_cfg(DISABLE_NLZ_FLAG_ON_POINTS=True)
    keep_all = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    pts = keep_all.get_lidar(SEQ_A, 1)
    assert pts.shape == (raw.shape[0], 5) and pts.dtype == np.float32
    np.testing.assert_allclose(pts[:, 3], np.tanh(raw[:, 3]), rtol=1e-6)
    np.testing.assert_array_equal(pts[:, 4], raw[:, 4])  # elongation untouched by default
    np.testing.assert_array_equal(pts[:, :3], raw[:, :3])

    nlz = WaymoDataset(
        dataset_cfg(DISABLE_NLZ_FLAG_ON_POINTS=False, POINTS_TANH_DIM=[3, 4]),
        CLASS_NAMES,
        training=False,
        root_path=tiny_root,
    )
    pts = nlz.get_lidar(SEQ_A, 1)
    kept = raw[raw[:, 5] == -1]
    assert 0 < len(pts) == len(kept) < len(raw)
    np.testing.assert_allclose(pts[:, 4], np.tanh(kept[:, 4]), rtol=1e-6)


@pytest.mark.parametrize("disable_nlz", [False, True])
@pytest.mark.parametrize("num_runs", [0, 1, 37, 400])
def test_loaded_points_drops_rows_like_a_mask(tiny_root, disable_nlz, num_runs):
    """``loaded_points(rows, drop)`` (the attacked frames' path: block copies between dropped
    runs, or one masked gather when NLZ rows are dropped too) equals the plain mask reference;
    a file read with spare rows gives the same points."""
    ds = WaymoDataset(
        dataset_cfg(DISABLE_NLZ_FLAG_ON_POINTS=disable_nlz), CLASS_NAMES, root_path=tiny_root
    )
    path = wf.frame_npy_path(tiny_root, SEQ_A, 1)
    raw = wf.load_frame_points(path)
    spare = wf.load_frame_points(path, spare_rows=64)
    assert spare.shape == (len(raw) + 64, 6) and np.array_equal(spare[: len(raw)], raw)
    for rows in (raw, np.where(raw[:, 5:] == 1, -1.0, raw).astype(np.float32)):  # +- NLZ rows
        rng = np.random.default_rng(num_runs)
        count = min(num_runs, (len(rows) - 4) // 4)  # the masked copy: test_removal.py
        starts = np.sort(rng.choice(len(rows) - 4, count, replace=False))
        drop = np.unique(
            np.concatenate([s + np.arange(rng.integers(1, 4)) for s in starts] or [[]])
        )
        keep = np.ones(len(rows), bool) if disable_nlz else rows[:, 5] == -1
        keep[drop.astype(np.int64)] = False
        want = rows[keep, :5].copy()
        want[:, 3] = np.tanh(want[:, 3])
        got = ds.loaded_points(rows, drop.astype(np.int64))
        assert got.flags.c_contiguous and np.array_equal(got, want)
    assert np.array_equal(ds.loaded_points(raw), ds.get_lidar(SEQ_A, 1))


@pytest.mark.parametrize("multiframe", [False, True])
def test_samples_do_not_alias_the_infos(tiny_root, multiframe):
    """As OpenPCDet (which deep-copies the info), editing a sample in place never changes the
    dataset's infos or a later sample."""
    ds = WaymoDataset(
        dataset_cfg(multiframe=multiframe), CLASS_NAMES, training=False, root_path=tiny_root
    )
    first = ds[3]
    pose_before = ds.infos[3]["pose"].copy()
    for value in first.values():
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            value[...] = -7.0
    np.testing.assert_array_equal(ds.infos[3]["pose"], pose_before)
    again = ds[3]
    np.testing.assert_array_equal(again["pose"], pose_before)
    assert not (again["points"] == -7.0).all() and not (again["gt_boxes"] == -7.0).all()


# ---------------------------------------------------------------------------- multi-frame
@pytest.mark.parametrize("sample_idx", [5, 3])
def test_multiframe_static_world_points_align_within_1cm(tiny_root, sample_idx):
    """A static world point seen in frames t-3..t lands at one place in frame t (<= 1 cm)."""
    ds = WaymoDataset(
        dataset_cfg(multiframe=True), CLASS_NAMES, training=False, root_path=tiny_root
    )
    info = ds.get_frame_info(SEQ_V, sample_idx)
    points = ds.get_lidar(SEQ_V, sample_idx)
    stacked, num_points, history, poses = ds.get_sequence_data(
        info, points, SEQ_V, sample_idx, ds.sequence_cfg
    )
    assert stacked.dtype == np.float32 and stacked.shape[1] == 6
    np.testing.assert_array_equal(history, [sample_idx - 1, sample_idx - 2, sample_idx - 3])
    assert poses.shape == (16, 4) and poses.dtype == np.float32
    for j, s in enumerate([sample_idx, *history]):
        np.testing.assert_allclose(poses[4 * j : 4 * j + 4], ego_pose(s).astype(np.float32))
    assert num_points.sum() == len(stacked)
    ids = stacked[:, 4].astype(np.int64)  # elongation column holds the world id
    expected = transform_points(world_points()[ids], np.linalg.inv(ego_pose(sample_idx)))
    err = np.linalg.norm(stacked[:, :3] - expected, axis=1)
    assert err.max() < 0.01
    # the same world point appears in several frames, all at one place
    lags = np.round(stacked[:, 5].astype(np.float64), 6)
    assert set(lags) == {0.0, 0.1, 0.2, 0.3}
    common = set(ids[lags == 0]) & set(ids[np.isclose(lags, 0.3)])
    assert len(common) > 100
    # raw coordinates of one world point differ a lot between frames t-3 and t (the ego moves
    # and turns), so the alignment above is not trivial
    old, cur = ds.get_lidar(SEQ_V, sample_idx - 3), ds.get_lidar(SEQ_V, sample_idx)
    shared, i_old, i_cur = np.intersect1d(old[:, 4], cur[:, 4], return_indices=True)
    assert len(shared) > 100
    assert np.median(np.linalg.norm(old[i_old, :3] - cur[i_cur, :3], axis=1)) > 3.0
    # history points within 1 m of the ego are removed, current ones kept
    hist = stacked[lags > 0]
    assert not ((np.abs(hist[:, 0]) < 1) & (np.abs(hist[:, 1]) < 1)).any()


def _stack_per_frame(ds, info, points, seq, sample_idx, k, onehot):
    """Reference stacking, one frame at a time as OpenPCDet's loop: float64 column-wise
    transform, ego mask, lag/one-hot, then one concatenation."""
    pose_cur = info["pose"].astype(np.float64)
    history = history_sample_indices(sample_idx, (-k, 0))
    extra = np.zeros((len(points), k + 1 if onehot else 1))
    if onehot:
        extra[:, 0] = 1
    parts = [np.hstack([points, extra])]
    for j, s_pre in enumerate(history):
        pre = ds.get_lidar(seq, int(s_pre))
        pose_pre = ds.get_frame_info(seq, int(s_pre))["pose"].astype(np.float64)
        xyz = transform_points_to_frame(pre[:, :3], pose_pre, pose_cur)
        extra = np.zeros((len(pre), k + 1 if onehot else 1))
        extra[:, j + 1 if onehot else 0] = 1 if onehot else 0.1 * (sample_idx - s_pre)
        part = np.hstack([xyz.astype(np.float32), pre[:, 3:], extra.astype(np.float32)])
        parts.append(part[outside_ego_mask(xyz, 1.0)])
    return np.concatenate(parts).astype(np.float32), [len(p) for p in parts]


@pytest.mark.parametrize("onehot", [False, True])
def test_multiframe_stacking_is_bitwise_the_per_frame_reference(tiny_root, onehot):
    """The single-buffer stacking gives the same bits as the frame-by-frame reference, and
    agrees with OpenPCDet's homogeneous float32-pose matmuls within float32 rounding."""
    cfg = dataset_cfg(multiframe=True)
    if onehot:
        cfg.SEQUENCE_CONFIG.ONEHOT_TIMESTAMP = True
        feats = ["x", "y", "z", "intensity", "elongation", "t0", "t1", "t2", "t3"]
        cfg.POINT_FEATURE_ENCODING.src_feature_list = feats
        cfg.POINT_FEATURE_ENCODING.used_feature_list = feats
    ds = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    dropped_ego = False
    for sample_idx in (0, 2, 4, 5):
        info = ds.get_frame_info(SEQ_V, sample_idx)
        points = ds.get_lidar(SEQ_V, sample_idx)
        got, counts, _, _ = ds.get_sequence_data(info, points, SEQ_V, sample_idx, ds.sequence_cfg)
        ref, ref_counts = _stack_per_frame(ds, info, points, SEQ_V, sample_idx, 3, onehot)
        assert got.dtype == np.float32 and got.flags.c_contiguous
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(counts, ref_counts)
        raw = [
            len(ds.get_lidar(SEQ_V, int(s))) for s in history_sample_indices(sample_idx, (-3, 0))
        ]
        dropped_ego |= sum(ref_counts[1:]) < sum(raw)
        # OpenPCDet: [xyz, 1] @ pose_pre.T -> global, [g, 1] @ inv(pose_cur.T) (float32 poses)
        start = counts[0]
        for s_pre in history_sample_indices(sample_idx, (-3, 0)):
            pre = ds.get_lidar(SEQ_V, int(s_pre))
            pose_pre = ds.get_frame_info(SEQ_V, int(s_pre))["pose"]
            ones = np.ones((len(pre), 1))
            g = np.dot(np.concatenate([pre[:, :3], ones], -1), pose_pre.T)[:, :3]
            cur = np.dot(np.concatenate([g, ones], -1), np.linalg.inv(info["pose"].T))[:, :3]
            cur = cur[outside_ego_mask(cur, 1.0)]
            np.testing.assert_allclose(got[start : start + len(cur), :3], cur, rtol=0, atol=2e-4)
            start += len(cur)
    assert dropped_ego  # the ego-removal path was exercised


def test_multiframe_time_column_and_clipping_at_sequence_start(tiny_root):
    ds = WaymoDataset(
        dataset_cfg(multiframe=True), CLASS_NAMES, training=False, root_path=tiny_root
    )
    np.testing.assert_array_equal(history_sample_indices(1, (-3, 0)), [0, 0, 0])
    np.testing.assert_array_equal(history_sample_indices(0, (-3, 0)), [0, 0, 0])
    np.testing.assert_array_equal(history_sample_indices(7, (-3, 0)), [6, 5, 4])
    info = ds.get_frame_info(SEQ_V, 1)
    stacked, num_points, history, poses = ds.get_sequence_data(
        info, ds.get_lidar(SEQ_V, 1), SEQ_V, 1, ds.sequence_cfg
    )
    np.testing.assert_array_equal(history, [0, 0, 0])
    # frame 0 is repeated three times, each with lag 0.1 * (1 - 0)
    assert num_points[1] == num_points[2] == num_points[3]
    lags = stacked[:, 5]
    np.testing.assert_allclose(lags[: num_points[0]], 0.0)
    np.testing.assert_allclose(lags[num_points[0] :], np.float32(0.1))
    for j in (1, 2, 3):
        np.testing.assert_array_equal(poses[4 * j : 4 * j + 4], poses[4:8])
    # through __getitem__: poses and a 6-column cloud
    sample = ds[1]
    assert sample["points"].shape[1] == 6 and sample["poses"].shape == (16, 4)
    assert set(np.round(sample["points"][:, 5].astype(np.float64), 6)) == {0.0, 0.1}


def test_onehot_timestamp(tiny_root):
    cfg = dataset_cfg(multiframe=True)
    cfg.SEQUENCE_CONFIG.ONEHOT_TIMESTAMP = True
    cfg.SEQUENCE_CONFIG.SAMPLE_OFFSET = [-1, 0]
    feats = ["x", "y", "z", "intensity", "elongation", "t0", "t1"]
    cfg.POINT_FEATURE_ENCODING.src_feature_list = feats
    cfg.POINT_FEATURE_ENCODING.used_feature_list = feats
    ds = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    pts = ds[4]["points"]
    assert pts.shape[1] == 7
    np.testing.assert_array_equal(pts[:, 5] + pts[:, 6], 1.0)
    assert pts[:, 6].sum() > 0 and pts[:, 5].sum() > 0


# ---------------------------------------------------------------------------- options
def test_sampled_interval_over_the_concatenated_split(tiny_root):
    cfg = dataset_cfg()
    cfg.SAMPLED_INTERVAL = {"train": 3, "test": 2}
    ds = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=tiny_root)
    assert len(ds.all_infos) == 11
    # OpenPCDet samples the concatenation of all sequences, not each sequence
    got = [(i["point_cloud"]["lidar_sequence"], i["point_cloud"]["sample_idx"]) for i in ds.infos]
    assert got == [(SEQ_A, 0), (SEQ_A, 3), (SEQ_B, 0), (SEQ_B, 3)]
    assert len(ds.seq_name_to_infos[SEQ_B]) == 5  # history lookups see every frame
    test_ds = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    assert [i["point_cloud"]["sample_idx"] for i in test_ds.infos] == [0, 2, 4]


def test_filter_empty_boxes_only_in_training(tiny_root):
    cfg = dataset_cfg()
    cfg.DATA_PROCESSOR = []  # keep out-of-range boxes so only the empty-box filter acts
    train = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=tiny_root)
    test = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    test.infos = train.infos  # same frames
    annos = train.infos[0]["annos"]
    class_mask = np.isin(annos["name"], CLASS_NAMES)
    n_empty = int(((annos["num_points_in_gt"] == 0) & class_mask).sum())
    assert n_empty >= 1
    assert len(test[0]["gt_boxes"]) == class_mask.sum()
    assert len(train[0]["gt_boxes"]) == class_mask.sum() - n_empty
    cfg.FILTER_EMPTY_BOXES_FOR_TRAIN = False
    unfiltered = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=tiny_root)
    assert len(unfiltered[0]["gt_boxes"]) == class_mask.sum()


def test_train_with_speed_box_width(tiny_root):
    ds7 = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=tiny_root)
    ds9 = WaymoDataset(
        dataset_cfg(TRAIN_WITH_SPEED=True), CLASS_NAMES, training=False, root_path=tiny_root
    )
    b7, b9 = ds7[2]["gt_boxes"], ds9[2]["gt_boxes"]
    assert b7.shape[1] == 8 and b9.shape[1] == 10
    np.testing.assert_array_equal(b7[:, :7], b9[:, :7])
    annos = ds9.infos[2]["annos"]
    keep = np.isin(annos["name"], CLASS_NAMES)
    np.testing.assert_allclose(b9[:, 7:9], annos["gt_boxes_lidar"][keep, 7:9], rtol=1e-6)
    assert np.abs(b9[:, 7:9]).max() > 0.5


def test_point_cloud_range_masks_points_and_training_boxes(tiny_root):
    cfg = dataset_cfg(POINT_CLOUD_RANGE=[-10, -10, -2, 10, 10, 0.5])
    train = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=tiny_root)
    test = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    test.infos = train.infos
    for sample, training in ((train[1], True), (test[1], False)):
        xy = sample["points"][:, :2]
        assert (np.abs(xy) <= 10).all() and len(xy) > 0
        inside = (np.abs(sample["gt_boxes"][:, :2]) <= 10).all(axis=1)
        assert inside.all() if training else not inside.all()
    # z is not masked unless FILTER_Z (OpenPCDet's mask_points_by_range is BEV only)
    assert (test[1]["points"][:, 2] > 0.5).any()
    cfg.DATA_PROCESSOR[0].FILTER_Z = True
    z_masked = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=tiny_root)
    z_masked.infos = train.infos
    z = z_masked[1]["points"][:, 2]
    assert len(z) > 0 and (z <= 0.5).all() and (z >= -2).all()


# ---------------------------------------------------------------------------- empty and batches
@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("multiframe", [False, True])
def test_empty_frame_flows_through_getitem_and_collate(tiny_root, training, multiframe):
    ds = WaymoDataset(
        dataset_cfg(multiframe=multiframe, augment=True, shuffle=True),
        CLASS_NAMES,
        training=training,
        root_path=tiny_root,
    )
    if not training:
        ds.set_split("train")
    index = next(i for i, info in enumerate(ds.infos) if info["frame_id"] == wf.frame_id(SEQ_B, 2))
    sample = ds[index]
    width = 10 if multiframe else 8
    assert sample["gt_boxes"].shape == (0, width) and len(sample["gt_names"]) == 0
    if not multiframe:
        assert sample["points"].shape == (0, 5)
    batch = ds.collate_batch([sample, ds[index - 1]])
    assert batch["batch_size"] == 2
    assert batch["gt_boxes"].shape[0] == 2 and batch["gt_boxes"].shape[2] == width
    assert (batch["gt_boxes"][0] == 0).all()
    only_empty = ds.collate_batch([sample])
    assert only_empty["gt_boxes"].shape == (1, 0, width)
    assert only_empty["points"].shape[1] == sample["points"].shape[1] + 1


def test_empty_frame_file_reads_with_spare_rows(tiny_root):
    """An empty frame read with room for an attack's rows: the room and nothing else."""
    path = wf.frame_npy_path(tiny_root, SEQ_B, 2)
    assert wf.load_frame_points(path).shape == (0, 6)
    spare = wf.load_frame_points(path, spare_rows=7)
    assert spare.shape == (7, 6) and spare.dtype == np.float32


def test_collate_pads_and_keeps_unknown_keys_as_lists(tiny_root):
    ds = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=tiny_root)
    samples = [ds[0], ds[1]]
    samples[0]["attack"] = {"variant": "clean", "target_box": None}
    samples[1]["attack"] = {"variant": "clean", "target_box": np.zeros(7, np.float32)}
    batch = WaymoDataset.collate_batch(samples)
    n0, n1 = len(samples[0]["points"]), len(samples[1]["points"])
    assert batch["points"].shape == (n0 + n1, 6) and batch["points"].dtype == np.float32
    np.testing.assert_array_equal(batch["points"][:n0, 0], 0)
    np.testing.assert_array_equal(batch["points"][n0:, 0], 1)
    np.testing.assert_array_equal(batch["points"][n0:, 1:], samples[1]["points"])
    assert batch["attack"] == [samples[0]["attack"], samples[1]["attack"]]
    assert isinstance(batch["metadata"], list) and isinstance(batch["gt_names"], list)
    assert batch["frame_id"].tolist() == [samples[0]["frame_id"], samples[1]["frame_id"]]
    assert batch["pose"].shape == (2, 4, 4)


def test_collate_refuses_a_key_missing_from_some_samples(tiny_root):
    """A key only some samples have would give a list shorter than the batch, misaligned with
    the batch index: an error naming the key and the samples that lack it."""
    ds = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=tiny_root)
    samples = [ds[0], ds[1], ds[2]]
    for i in (0, 2):
        del samples[i]["gt_boxes"]
    del samples[1]["metadata"]
    with pytest.raises(ValueError) as info:
        WaymoDataset.collate_batch(samples)
    message = str(info.value)
    assert "every sample of a batch must have the same keys; in this batch of 3" in message
    ids = [s["frame_id"] for s in samples]
    assert f"'gt_boxes' is missing from sample(s) 0 ({ids[0]}), 2 ({ids[2]})" in message
    assert f"'metadata' is missing from sample(s) 1 ({ids[1]})" in message


def test_build_dataloader_is_independent_of_workers(tiny_root):
    cfg = dataset_cfg(augment=True, shuffle=True)
    cfg.DATASET = "WaymoDataset"

    def first_batches(workers):
        ds, loader, sampler = build_dataloader(
            cfg,
            CLASS_NAMES,
            batch_size=3,
            dist=False,
            root_path=tiny_root,
            workers=workers,
            seed=7,
            training=True,
        )
        assert isinstance(sampler, ResumableSampler) and ds.seed == 7
        ds.set_epoch(2)
        return list(loader)

    a, b = first_batches(0), first_batches(2)
    assert len(a) == len(b) == 4
    for x, y in zip(a, b):
        assert x["frame_id"].tolist() == y["frame_id"].tolist()
        np.testing.assert_array_equal(x["points"], y["points"])
        np.testing.assert_array_equal(x["gt_boxes"], y["gt_boxes"])


def test_training_order_is_torch_shuffle_and_resumes_part_way(tiny_root):
    """The training sampler draws the order DataLoader(shuffle=True) draws from the seeded
    generator (checkpoints trained before it stay reproducible), and a pass started at a batch
    boundary yields exactly the rest of that epoch's batches."""
    cfg = dataset_cfg(augment=True, shuffle=True)
    cfg.DATASET = "WaymoDataset"
    ds, loader, sampler = build_dataloader(
        cfg, CLASS_NAMES, batch_size=3, dist=False, root_path=tiny_root, workers=0, seed=7,
        training=True,
    )  # fmt: skip

    def order(epoch, start=0):
        loader.generator.manual_seed(derive_seed(7, "dataloader_shuffle", epoch))
        sampler.start_at(start)
        return [int(i) for batch in loader.batch_sampler for i in batch]

    for epoch in (0, 1):
        torch_order = DataLoader(
            ds, batch_size=3, shuffle=True,
            generator=torch.Generator().manual_seed(derive_seed(7, "dataloader_shuffle", epoch)),
        ).batch_sampler  # fmt: skip
        whole = order(epoch)
        assert whole == [int(i) for batch in torch_order for i in batch]
        assert sorted(whole) == list(range(len(ds))) and len(loader) == 4
        assert order(epoch, start=6) == whole[6:] and len(loader) == 2  # batches 3 and 4
    assert len(ds) == 11
    with pytest.raises(ValueError, match=r"start_at\(12\): a pass has 11 indices"):
        sampler.start_at(12)


@pytest.mark.parametrize("training,seed", [(False, None), (True, 7)])
def test_a_pass_leaves_the_global_rng_alone(tiny_root, training, seed):
    """An evaluation or seeded loader draws its workers' base seed from its own generator: a
    pass over it (the RPN over the train split before a second stage trains, a resumed epoch)
    does not shift the global draws that dropout then makes."""
    cfg = dataset_cfg(augment=training, shuffle=training)
    cfg.DATASET = "WaymoDataset"
    _, loader, _ = build_dataloader(
        cfg, CLASS_NAMES, batch_size=4, dist=False, root_path=tiny_root, workers=0, seed=seed,
        training=training,
    )  # fmt: skip
    torch.manual_seed(3)
    before = torch.get_rng_state()
    assert len(list(loader)) == len(loader) > 0
    assert torch.equal(torch.get_rng_state(), before)


def test_merge_all_iters_to_one_epoch(tiny_root):
    cfg = dataset_cfg(augment=True)
    ds, loader, _ = build_dataloader(
        cfg,
        CLASS_NAMES,
        1,
        False,
        root_path=tiny_root,
        workers=0,
        training=True,
        merge_all_iters_to_one_epoch=True,
        total_epochs=3,
    )
    assert len(ds) == 3 * len(ds.infos)
    first, third = ds[0], ds[2 * len(ds.infos)]
    assert first["frame_id"] == third["frame_id"]
    assert first["noise_rot"] != third["noise_rot"]  # later passes count as later epochs


# ---------------------------------------------------------------------------- predictions
def test_generate_prediction_dicts_and_evaluation(tiny_root, monkeypatch):
    ds = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=tiny_root)
    batch = ds.collate_batch([ds[0], ds[1]])
    preds = [
        {
            "pred_boxes": torch.tensor([[1.0, 2, 0, 4, 2, 1.5, 0.1], [5, 5, 0, 1, 1, 1, 0]]),
            "pred_scores": torch.tensor([0.9, 0.3]),
            "pred_labels": torch.tensor([1, 3]),
        },
        {
            "pred_boxes": torch.zeros((0, 7)),
            "pred_scores": torch.zeros(0),
            "pred_labels": torch.zeros(0, dtype=torch.long),
        },
    ]
    annos = ds.generate_prediction_dicts(batch, preds, CLASS_NAMES)
    assert set(annos[0]) == {"name", "score", "boxes_lidar", "pred_labels", "frame_id", "metadata"}
    assert annos[0]["name"].tolist() == ["Vehicle", "Cyclist"]
    assert (
        annos[0]["boxes_lidar"].shape == (2, 7) and annos[0]["frame_id"] == ds.infos[0]["frame_id"]
    )
    assert annos[1]["boxes_lidar"].shape == (0, 7) and len(annos[1]["name"]) == 0
    assert annos[1]["metadata"] == ds.infos[1]["metadata"]

    seen = {}

    def fake_waymo_evaluate(gt_annos, det_annos, class_names):
        seen.update(gt=gt_annos, det=det_annos, classes=class_names)
        return {"Vehicle/L2/AP": 0.5, "L2/mAP": 0.25}

    fake = types.ModuleType("pcdet_atlas.evaluation.waymo_metric")
    fake.waymo_evaluate = fake_waymo_evaluate
    monkeypatch.setitem(sys.modules, "pcdet_atlas.evaluation.waymo_metric", fake)
    det_annos = [dict(annos[0], frame_id=info["frame_id"]) for info in ds.infos]
    text, result = ds.evaluation(det_annos, CLASS_NAMES, eval_metric="waymo")
    assert result == {"Vehicle/L2/AP": 0.5, "L2/mAP": 0.25} and "L2/mAP: 0.2500" in text
    assert len(seen["gt"]) == len(ds.infos) and seen["classes"] == CLASS_NAMES
    assert set(seen["gt"][0]) >= {"name", "gt_boxes_lidar", "num_points_in_gt", "difficulty"}
    with pytest.raises(ValueError, match="out of order"):
        ds.evaluation(det_annos[::-1], CLASS_NAMES)
    with pytest.raises(ValueError, match="detection dicts"):
        ds.evaluation(det_annos[:2], CLASS_NAMES)


def test_num_points_in_gt_of_tiny_data_matches_points(tiny_root):
    """Guard on the test data itself: the counts the builder writes are real."""
    raw = np.load(wf.frame_npy_path(tiny_root, SEQ_A, 2))
    with open(wf.sequence_pkl_path(tiny_root, SEQ_A), "rb") as f:
        annos = pickle.load(f)[2]["annos"]
    counts = points_in_boxes_mask(raw[:, :3].astype(np.float64), annos["gt_boxes_lidar"]).sum(1)
    np.testing.assert_array_equal(counts, annos["num_points_in_gt"])


# ---------------------------------------------------------------------------- synthetic data
@pytest.mark.parametrize("multiframe", [False, True], ids=["1frame", "4frame"])
def test_loads_the_synthetic_dataset(synthetic_root, tmp_path, multiframe):
    """The embedded synthetic dataset reads like real data, in test and in training mode
    (with a GT database built in a root that links to the fixture's data: the fixture root is
    shared and read-only, and database paths stay under their root)."""
    from pcdet_atlas.datasets.gt_database import create_groundtruth_database, gt_database_paths

    cfg = dataset_cfg(multiframe=multiframe, shuffle=True)
    test_ds = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=synthetic_root)
    assert len(test_ds) == 70 and test_ds.split == "val"
    sample = test_ds[40]
    width = 6 if multiframe else 5
    assert sample["points"].shape[1] == width and len(sample["points"]) > 1000
    assert np.isfinite(sample["points"]).all() and sample["points"].dtype == np.float32
    assert sample["gt_boxes"].shape[1] == (10 if multiframe else 8)
    if multiframe:
        assert sample["poses"].shape == (16, 4)
        assert set(np.round(sample["points"][:, 5].astype(np.float64), 6)) == {0, 0.1, 0.2, 0.3}

    root = tmp_path / "root"
    root.mkdir()
    for name in ("ImageSets", wf.PROCESSED_DATA_TAG):
        (root / name).symlink_to(synthetic_root / name)
    db_builder = WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)
    db_builder.set_split("train")
    db_builder.all_infos = db_builder.all_infos[::5]  # a small database is enough here
    offset = (-4, 0) if multiframe else None
    create_groundtruth_database(db_builder)
    paths = gt_database_paths(root, wf.PROCESSED_DATA_TAG, "train", 1, offset)
    train_cfg = dataset_cfg(multiframe=multiframe, augment=True, shuffle=True)
    shipped = cfg_from_yaml_file(MULTIFRAME_CFG if multiframe else DATASET_CFG)
    sampling = shipped.DATA_AUGMENTOR.AUG_CONFIG_LIST[0]
    assert sampling.NAME == "gt_sampling"
    sampling.DB_INFO_PATH = [paths["info"].name]
    sampling.DB_DATA_PATH = [paths["global"].name]
    train_cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = [sampling, *train_cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST]
    train_ds = WaymoDataset(train_cfg, CLASS_NAMES, training=True, root_path=root)
    assert len(train_ds) == 20
    batch = train_ds.collate_batch([train_ds[i] for i in (0, 9, 15)])
    assert batch["points"].shape[1] == width + 1 and batch["gt_boxes"].shape[0] == 3
    assert np.isfinite(batch["points"]).all()


def test_evaluation_end_to_end_with_the_waymo_metric(tiny_root):
    """Detections equal to the (non-empty) ground truth score AP 1 through the real metric."""
    ds = WaymoDataset(dataset_cfg(), CLASS_NAMES, training=False, root_path=tiny_root)
    det_annos = []
    for info in ds.infos:
        annos = info["annos"]
        keep = np.isin(annos["name"], CLASS_NAMES) & (annos["num_points_in_gt"] > 0)
        det_annos.append(
            {
                "name": annos["name"][keep],
                "score": np.ones(int(keep.sum()), np.float32),
                "boxes_lidar": annos["gt_boxes_lidar"][keep, :7].astype(np.float32),
                "frame_id": info["frame_id"],
            }
        )
    text, result = ds.evaluation(det_annos, CLASS_NAMES, eval_metric="waymo")
    assert result["L2/mAP"] == pytest.approx(1.0) and "Vehicle/L1/AP: 1.0000" in text
    for det in det_annos:  # relabel every Vehicle detection as Cyclist: Vehicle AP falls to 0
        det["name"] = np.where(det["name"] == "Vehicle", "Cyclist", det["name"])
    _, worse = ds.evaluation(det_annos, CLASS_NAMES)
    assert worse["Vehicle/L1/AP"] == 0.0 and worse["L1/mAP"] < 1.0
