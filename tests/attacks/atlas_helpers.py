"""A tiny hand-built Waymo-format dataset for the attack tests (flat ground at z = 0, box-shaped
vehicles moving at constant velocity, an ego driving and turning slowly).

Independent of the synthetic generator so the attack engine's tests run on a scene whose
ground truth is known exactly: ground height 0 in the vehicle frame, vehicle tracks with fixed
obj_ids and speeds.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from easydict import EasyDict

from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.utils.common import load_tool  # noqa: F401  (the tests' import)

GROUND_Z = 0.0
SENSOR_Z = 2.184
# (obj_id, world x0, world y0, heading, speed, l, w, h)
VEHICLES = [
    ("veh_a", 22.0, 4.0, 0.0, 4.0, 4.6, 1.9, 1.6),
    ("veh_b", 35.0, -4.0, 0.0, 6.0, 5.0, 2.1, 1.8),
    ("veh_c", 10.0, 12.0, math.pi / 2, 0.0, 4.2, 1.8, 1.5),
    ("veh_d", -18.0, -3.5, 0.0, 7.0, 4.8, 2.0, 1.7),
]


def ego_pose(t: float) -> np.ndarray:
    """Ego pose at time t (s): forward at 5 m/s with a slow left turn."""
    yaw = 0.02 * t
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    pose[:3, 3] = [5.0 * t, 0.5 * t * t * 0.2, 0.0]
    return pose


def _ground_points(rng: np.random.Generator) -> np.ndarray:
    elev = np.deg2rad(np.linspace(-17.0, -2.5, 24))
    az = np.linspace(-math.pi, math.pi, 900, endpoint=False)
    e, a = np.meshgrid(elev, az, indexing="ij")
    r_h = (SENSOR_Z - GROUND_Z) / np.tan(-e)
    x = 1.43 + r_h * np.cos(a)
    y = r_h * np.sin(a)
    keep = r_h < 70
    xyz = np.stack([x[keep], y[keep], np.full(keep.sum(), GROUND_Z)], axis=1)
    xyz[:, 2] += rng.normal(0, 0.02, xyz.shape[0])
    return xyz


def _box_surface_points(box: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    l, w, h = box[3:6]
    u = rng.uniform(-0.5, 0.5, (n, 3)) * np.array([l, w, h])
    face = rng.integers(0, 5, n)  # four sides and the roof
    u[face == 0, 0] = l / 2
    u[face == 1, 0] = -l / 2
    u[face == 2, 1] = w / 2
    u[face == 3, 1] = -w / 2
    u[face == 4, 2] = h / 2
    c, s = math.cos(box[6]), math.sin(box[6])
    x = c * u[:, 0] - s * u[:, 1] + box[0]
    y = s * u[:, 0] + c * u[:, 1] + box[1]
    return np.stack([x, y, u[:, 2] + box[2]], axis=1)


def write_tiny_waymo(
    root: Path, frames: dict[str, int] | None = None, seed: int = 0, nlz_every: int = 0
) -> Path:
    """Write train/val sequences (``{'train': F, 'val': G}`` frames) under ``root``; with
    ``nlz_every = n`` every n-th point is flagged as inside a no-label zone (NLZ = 1)."""
    frames = frames or {"train": 12, "val": 70}
    root = Path(root)
    (root / "ImageSets").mkdir(parents=True, exist_ok=True)
    for split, num in frames.items():
        seq = f"segment-tiny{split}_with_camera_labels"
        (root / "ImageSets" / f"{split}.txt").write_text(f"{seq}.tfrecord\n")
        wf.data_dir(root).joinpath(seq).mkdir(parents=True, exist_ok=True)
        infos = []
        for k in range(num):
            rng = np.random.default_rng([seed, k, len(split)])
            t = 0.1 * k
            pose = ego_pose(t)
            inv = np.linalg.inv(pose)
            pts = [_ground_points(rng)]
            names, locs, dims, heads, ids, npts, speeds = [], [], [], [], [], [], []
            for obj, x0, y0, hd, v, l, w, h in VEHICLES:
                vel = v * np.array([math.cos(hd), math.sin(hd)])
                cw = np.array([x0 + vel[0] * t, y0 + vel[1] * t, h / 2, 1.0])
                c = inv @ cw
                heading = hd - math.atan2(pose[1, 0], pose[0, 0])
                box = np.array([c[0], c[1], c[2], l, w, h, heading])
                p = _box_surface_points(box, 400, rng)
                pts.append(p)
                names.append("Vehicle")
                locs.append(box[:3])
                dims.append(box[3:6])
                heads.append((heading + math.pi) % (2 * math.pi) - math.pi)
                ids.append(obj)
                npts.append(len(p))
                speeds.append(vel)
            xyz = np.concatenate(pts)
            feats = np.zeros((xyz.shape[0], 6), dtype=np.float32)
            feats[:, :3] = xyz
            feats[:, 3] = rng.uniform(0.05, 0.6, xyz.shape[0])
            feats[:, 4] = rng.uniform(0.0, 0.2, xyz.shape[0])
            feats[:, 5] = -1
            if nlz_every:
                feats[::nlz_every, 5] = 1
            wf.save_frame_points(wf.frame_npy_path(root, seq, k), feats)
            annos = wf.make_annos(
                names, [1] * len(names), np.array(locs), np.array(dims), heads, ids, npts,
                np.array(speeds), pose,
            )  # fmt: skip
            infos.append(
                wf.make_frame_info(
                    seq, k, pose, [xyz.shape[0], 0, 0, 0, 0], 1000 + 100000 * k, annos
                )
            )
        wf.save_sequence_infos(wf.sequence_pkl_path(root, seq), infos)
    return root


def dataset_cfg(root: Path, multiframe: bool = False) -> EasyDict:
    """A DATA_CONFIG for the tiny dataset (test split = val)."""
    from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file

    name = "synthetic_waymo_multiframe.yaml" if multiframe else "synthetic_waymo.yaml"
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "dataset_configs" / name)
    cfg.DATA_PATH = str(root)
    return cfg


_LIBRARIES: dict[str, Path] = {}


def synthetic_library(root: Path, out_dir: Path) -> Path:
    """The trace library of ``root`` built with the shipped injection filters, saved once per
    session under ``out_dir`` (never inside the read-only fixture dataset)."""
    from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
    from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file

    key = str(root)
    if key not in _LIBRARIES or not _LIBRARIES[key].is_file():
        cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / "inj_rel_easy.yaml")
        library = build_trace_library(root, TraceFilter.from_config(cfg.TRACE_LIBRARY))
        _LIBRARIES[key] = library.save(Path(out_dir) / "synthetic_trace_library.npz")
    return _LIBRARIES[key]
