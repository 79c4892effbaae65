"""Hand-built tiny datasets in OpenPCDet's processed Waymo layout, for the dataset tests.

A static world (a ground grid and a few labelled objects) is observed from an ego vehicle that
moves and turns far from the global origin. Column 4 (elongation, which the loader leaves as is)
holds each point's world id, so tests can check where every point lands.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.ops.boxes import points_in_boxes_mask, transform_boxes, transform_points

DATASET_CFG = REPO_ROOT / "cfgs" / "dataset_configs" / "waymo_dataset.yaml"
MULTIFRAME_CFG = REPO_ROOT / "cfgs" / "dataset_configs" / "waymo_dataset_multiframe.yaml"
CLASS_NAMES = ["Vehicle", "Pedestrian", "Cyclist"]

# world boxes [x, y, z, l, w, h, heading] relative to the world anchor, with class and speed
_OBJECTS = [
    ("Vehicle", [12.0, 3.0, 0.9, 4.5, 2.0, 1.8, 0.3], [2.0, 0.5]),
    ("Vehicle", [-8.0, -6.0, 0.9, 4.8, 2.1, 1.7, -1.0], [0.0, 0.0]),
    ("Vehicle", [20.0, -12.0, 1.2, 8.0, 2.6, 2.6, 1.2], [-1.0, 3.0]),
    ("Vehicle", [60.0, 60.0, 0.9, 4.5, 2.0, 1.8, 0.0], [0.0, 0.0]),  # never has points
    ("Pedestrian", [5.0, -4.0, 0.9, 0.8, 0.8, 1.8, 0.0], [0.5, 0.0]),
    ("Cyclist", [-3.0, 9.0, 0.9, 1.8, 0.7, 1.7, 2.0], [0.0, 4.0]),
    ("Sign", [15.0, 10.0, 2.5, 0.2, 0.8, 0.8, 0.0], [0.0, 0.0]),
]
WORLD_ANCHOR = np.array([1000.0, -500.0, 10.0])


def world_points(seed: int = 0) -> np.ndarray:
    """``(P, 3)`` float64 static world points: a ground grid plus points inside the objects."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(-40, 40.1, 2.5), np.arange(-40, 40.1, 2.5))
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    parts = [ground]
    for _, box, _ in _OBJECTS[:3] + _OBJECTS[4:]:
        box = np.asarray(box)
        local = (rng.random((40, 3)) - 0.5) * box[3:6] * 0.9
        c, s = np.cos(box[6]), np.sin(box[6])
        xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + box[:2]
        parts.append(np.column_stack([xy, local[:, 2] + box[2]]))
    return np.concatenate(parts) + WORLD_ANCHOR


def ego_pose(k: int) -> np.ndarray:
    """4x4 vehicle -> global pose of frame ``k``: driving a curve, turning ~6 deg per frame."""
    yaw = 0.1 * k - 0.4
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = WORLD_ANCHOR + [1.5 * k, 0.2 * k * k - 3.0, 0.02 * k]
    return pose


def frame_points_and_annos(sequence: str, k: int, pose: np.ndarray, empty: bool = False):
    """Raw ``(N, 6)`` float32 frame points and the annos dict of frame ``k``."""
    if empty:
        pts = np.zeros((0, 6), np.float32)
        return pts, wf.make_annos([], [], [], [], [], [], [], [], pose)
    world = world_points()
    inv = np.linalg.inv(pose)
    local = transform_points(world, inv)
    visible = np.linalg.norm(local[:, :2], axis=1) < 45.0
    ids = np.nonzero(visible)[0]
    local = local[visible]
    intensity = 0.5 + (ids % 7) * 0.4  # raw; tanh applied by the loader
    nlz = np.where(ids % 10 == 0, 1.0, -1.0)
    pts = np.column_stack([local, intensity, ids.astype(np.float64), nlz]).astype(np.float32)
    names, boxes, speeds = [], [], []
    for name, box, speed in _OBJECTS:
        wbox = np.asarray(box, dtype=np.float64)[None].copy()
        wbox[0, :3] += WORLD_ANCHOR
        boxes.append(transform_boxes(wbox, inv)[0])
        names.append(name)
        speeds.append(speed)
    boxes = np.array(boxes)
    npts = points_in_boxes_mask(pts[:, :3].astype(np.float64), boxes).sum(axis=1)
    annos = wf.make_annos(
        name=names,
        difficulty=[1 if n > 5 else 2 for n in npts],
        location=boxes[:, :3],
        dimensions=boxes[:, 3:6],
        heading_angles=boxes[:, 6],
        obj_ids=[f"{sequence[-6:]}_obj{i}" for i in range(len(names))],
        num_points_in_gt=npts,
        speed_global=np.array(speeds),
        pose=pose,
    )
    return pts, annos


def write_tiny_waymo(
    root: str | Path,
    splits: dict[str, list[tuple[str, int]]] | None = None,
    empty_frames: set[tuple[str, int]] = frozenset(),
) -> Path:
    """Write sequences ``{split: [(name, num_frames)]}``; returns ``root``."""
    root = Path(root)
    if splits is None:
        splits = {
            "train": [("segment-111_with_camera_labels", 6), ("segment-222_with_camera_labels", 5)],
            "val": [("segment-333_with_camera_labels", 6)],
        }
    (root / "ImageSets").mkdir(parents=True, exist_ok=True)
    for split, sequences in splits.items():
        lines = []
        for sequence, num_frames in sequences:
            lines.append(f"{sequence}.tfrecord")
            folder = wf.data_dir(root) / sequence
            folder.mkdir(parents=True, exist_ok=True)
            infos = []
            for k in range(num_frames):
                pose = ego_pose(k)
                pts, annos = frame_points_and_annos(
                    sequence, k, pose, (sequence, k) in empty_frames
                )
                wf.save_frame_points(wf.frame_npy_path(root, sequence, k), pts)
                infos.append(
                    wf.make_frame_info(
                        sequence,
                        k,
                        pose,
                        [len(pts), 0, 0, 0, 0],
                        timestamp_micros=1_500_000_000_000_000 + 100_000 * k,
                        annos=annos,
                    )
                )
            wf.save_sequence_infos(wf.sequence_pkl_path(root, sequence), infos)
        (root / "ImageSets" / f"{split}.txt").write_text("\n".join(lines) + "\n")
    return root


def dataset_cfg(
    multiframe: bool = False, augment: bool = False, shuffle: bool = False, **overrides
):
    """The shipped Waymo dataset config with test-friendly changes (no GT sampling unless the
    database exists; no shuffling so rows can be compared)."""
    cfg = cfg_from_yaml_file(MULTIFRAME_CFG if multiframe else DATASET_CFG)
    cfg.SAMPLED_INTERVAL = {"train": 1, "test": 1}
    if not augment:
        cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = []
    else:
        cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = [
            a for a in cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST if a.NAME != "gt_sampling"
        ]
    if not shuffle:
        cfg.DATA_PROCESSOR = [p for p in cfg.DATA_PROCESSOR if p.NAME != "shuffle_points"]
    for key, val in overrides.items():
        cfg[key] = val
    return cfg
