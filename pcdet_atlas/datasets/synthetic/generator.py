"""Write a synthetic dataset in OpenPCDet's processed Waymo layout (docs/synthetic.md).

:func:`create_synthetic_waymo` builds each sequence's :class:`~.scene.SyntheticScene`, scans
every frame with the Waymo TOP model (:meth:`LidarModel.waymo_top`) through the torch ray caster,
and writes ``%04d.npy`` frames, the sequence pkl (last, atomically), ``ImageSets/<split>.txt``,
the ``*_infos_<split>.pkl`` concatenation and ``synthetic_meta.json``. Re-running with the same
arguments rewrites nothing that is finished; other arguments into the same root are an error.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import pickle
import time
from collections.abc import Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.datasets.synthetic.actors import SURFACE_SOLID
from pcdet_atlas.datasets.synthetic.raycast import (
    GROUND_ID,
    column_azimuths,
    ray_directions,
    raycast_scan,
)
from pcdet_atlas.datasets.synthetic.scene import FRAME_DT, SyntheticScene
from pcdet_atlas.datasets.synthetic.sensor import SensorModel
from pcdet_atlas.ops.boxes import points_in_boxes_mask
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.utils.common import write_atomic
from pcdet_atlas.utils.safe_pickle import load_pickle
from pcdet_atlas.utils.seeding import derive_seed

__all__ = [
    "GENERATOR_VERSION",
    "META_FILE",
    "SyntheticDatasetError",
    "create_synthetic_waymo",
    "sequence_name",
    "generate_frame",
    "difficulty_from_points",
    "count_points_in_boxes",
    "format_summary",
    "DEFAULT_NUM_SEQUENCES",
    "DEFAULT_FRAMES_PER_SEQUENCE",
]

GENERATOR_VERSION = "1.4"
META_FILE = "synthetic_meta.json"
SPLITS = ("train", "val")


class SyntheticDatasetError(RuntimeError):
    """An output root that cannot take this generation (other arguments, foreign data)."""


def sequence_name(seed: int, split: str, index: int) -> str:
    """A Waymo-like segment name, e.g. ``segment-1234..._4580_000_4600_000_with_camera_labels``."""
    digits = derive_seed(seed, "synthetic_waymo", split, index, "name")
    start = derive_seed(seed, "synthetic_waymo", split, index, "start") % 9000 + 100
    return f"segment-{digits}_{start}_000_{start + 20}_000_with_camera_labels"


def _context_name(sequence: str) -> str:
    return sequence[len("segment-") : -len("_with_camera_labels")]


def difficulty_from_points(num_points: np.ndarray) -> np.ndarray:
    """Waymo's detection difficulty as OpenPCDet stores it: LEVEL_2 (2) for <= 5 points, else 1."""
    return np.where(np.asarray(num_points) <= 5, 2, 1).astype(np.int64)


def count_points_in_boxes(
    points_xyz: np.ndarray, boxes: np.ndarray, lidar: LidarModel | None = None
) -> np.ndarray:
    """``(M,)`` int64 number of ``(N, 3)`` points inside each ``(M, 7)`` box (closed faces).

    Uses :func:`points_in_boxes_mask` on each box's candidate points only: those whose azimuth
    from the sensor lies in the box's azimuth interval (points bucketed by azimuth bin). Boxes
    containing the sensor are tested against all points.
    """
    counts = np.zeros(len(boxes), dtype=np.int64)
    if len(boxes) == 0 or len(points_xyz) == 0:
        return counts
    lidar = lidar or LidarModel.waymo_top()
    m = lidar.azimuth_bins
    ox, oy = float(lidar.origin[0]), float(lidar.origin[1])
    col = np.floor(
        (np.arctan2(points_xyz[:, 1] - oy, points_xyz[:, 0] - ox) + math.pi) / (2 * math.pi / m)
    ).astype(np.int64)
    col = np.clip(col, 0, m - 1)
    order = np.argsort(col, kind="stable")
    start = np.searchsorted(col[order], np.arange(m + 1))
    for i, box in enumerate(boxes):
        cx, cy, hx, hy, yaw = box[0] - ox, box[1] - oy, box[3] / 2, box[4] / 2, box[6]
        c, s = math.cos(yaw), math.sin(yaw)
        corners = [(cx + c * a - s * b, cy + s * a + c * b) for a in (hx, -hx) for b in (hy, -hy)]
        local_x = -(cx * c + cy * s)
        local_y = -(-cx * s + cy * c)
        if abs(local_x) <= hx + 1e-6 and abs(local_y) <= hy + 1e-6:
            idx = np.arange(len(points_xyz))
        else:
            centre = math.atan2(cy, cx)
            rel = [
                (math.atan2(y, x) - centre + math.pi) % (2 * math.pi) - math.pi for x, y in corners
            ]
            lo = math.floor((centre + min(rel) + math.pi) / (2 * math.pi / m)) - 1
            hi = math.floor((centre + max(rel) + math.pi) / (2 * math.pi / m)) + 1
            if hi - lo + 1 >= m:
                idx = np.arange(len(points_xyz))
            else:
                cols = np.arange(lo, hi + 1) % m
                breaks = np.nonzero(np.diff(cols) != 1)[0]
                runs = np.split(cols, breaks + 1)
                idx = np.concatenate([order[start[r[0]] : start[r[-1] + 1]] for r in runs])
        if len(idx):
            counts[i] = int(points_in_boxes_mask(points_xyz[idx, :3], box[None, :7]).sum())
    return counts


def lidar_directions(lidar: LidarModel, device, dtype=torch.float32) -> torch.Tensor:
    """``(B * M, 3)`` unit ray directions of ``lidar`` (ray id ``beam * M + column``)."""
    incl = lidar.inclinations.to(device, dtype)
    return ray_directions(incl, column_azimuths(lidar.azimuth_bins, device, dtype))


def generate_frame(
    scene: SyntheticScene,
    f: int,
    lidar: LidarModel,
    sensor: SensorModel,
    device: str | torch.device = "cpu",
    dirs: torch.Tensor | None = None,
) -> tuple[np.ndarray, dict]:
    """Scan frame ``f`` of ``scene`` (``dirs``: the ray grid's ``(B * M, 3)`` unit directions,
    recomputed when not given).

    Returns:
        ``points`` float32 ``(N, 6)`` ``[x, y, z, intensity, elongation, NLZ]`` in the vehicle
        frame (NLZ 1 inside a no-label zone, else -1), ordered like a Waymo range image
        (highest beam first, azimuth decreasing from +pi), and the frame's labels (see
        :meth:`SyntheticScene.labels`) with ``num_points_in_gt`` added.
    """
    dtype = torch.float32
    origin = lidar.origin.to(device, dtype)
    prims = scene.primitives(
        f, sensor_xy=tuple(lidar.origin[:2].tolist()), max_range=lidar.max_range, device=device
    )
    if dirs is None:
        dirs = lidar_directions(lidar, device, dtype)
    hits = raycast_scan(
        origin, lidar.inclinations, lidar.azimuth_bins, prims, 0.0, lidar.max_range, dirs=dirs
    )
    num_rays = dirs.shape[0]
    # albedo / surface of what each ray hit
    albedo = torch.zeros(num_rays, device=device, dtype=dtype)
    surface = torch.full((num_rays,), SURFACE_SOLID, device=device, dtype=torch.long)
    nb = prims.num_boxes
    is_box = (hits.prim_id >= 0) & (hits.prim_id < nb)
    is_cyl = hits.prim_id >= nb
    albedo[is_box] = prims.box_albedo[hits.prim_id[is_box]]
    surface[is_box] = prims.box_surface[hits.prim_id[is_box]]
    albedo[is_cyl] = prims.cyl_albedo[hits.prim_id[is_cyl] - nb]
    surface[is_cyl] = prims.cyl_surface[hits.prim_id[is_cyl] - nb]
    rng = scene.random_generator("frame", f, "sensor")
    ground = torch.nonzero(hits.prim_id == GROUND_ID).flatten()
    if ground.numel():
        local = origin[None] + hits.range_m[ground, None] * dirs[ground]
        pose = scene.pose(f)
        xy = local[:, :2].double().cpu().numpy() @ pose[:2, :2].T + pose[:2, 3]
        g_alb, _ = scene.road_map.ground_albedo(xy, rng.standard_normal(len(xy)))
        albedo[ground] = torch.as_tensor(g_alb, dtype=dtype).to(device)
    cos = (hits.normal * dirs).sum(dim=1).abs()
    valid, rng_m, intensity, elongation = sensor.returns(
        hits.range_m, cos, albedo, surface, lidar.max_range, rng
    )
    # Waymo range-image order: row 0 = highest beam, columns from +pi downwards = reversed ids
    keep = torch.flip(torch.nonzero(valid).flatten(), dims=[0])
    xyz = origin[None] + rng_m[keep, None] * dirs[keep]
    points = torch.cat(
        [
            xyz,
            intensity[keep, None],
            elongation[keep, None],
            torch.full((keep.numel(), 1), -1.0, device=device, dtype=dtype),
        ],
        dim=1,
    )
    points = points.cpu().numpy().astype(np.float32)
    if len(scene.no_label_zones):
        pose = scene.pose(f)
        xy = points[:, :2].astype(np.float64) @ pose[:2, :2].T + pose[:2, 3]
        points[scene.in_no_label_zone(xy), 5] = 1.0
    labels = scene.labels(f, sensor_xy=tuple(lidar.origin[:2].tolist()), max_range=lidar.max_range)
    labels["num_points_in_gt"] = count_points_in_boxes(points[:, :3], labels["boxes"], lidar)
    return points, labels


def _frame_info(scene: SyntheticScene, sequence: str, f: int, points, labels, t0: int) -> dict:
    pose = scene.pose(f)
    difficulty = difficulty_from_points(labels["num_points_in_gt"])
    boxes = labels["boxes"]
    annos = wf.make_annos(
        name=labels["name"],
        difficulty=difficulty,
        location=boxes[:, 0:3],
        dimensions=boxes[:, 3:6],
        heading_angles=boxes[:, 6],
        obj_ids=labels["obj_ids"],
        num_points_in_gt=labels["num_points_in_gt"],
        speed_global=labels["speed_global"],
        pose=pose.astype(np.float32),
        tracking_difficulty=difficulty,
        accel_global=labels["accel_global"],
    )
    return wf.make_frame_info(
        sequence,
        f,
        pose=pose,
        num_points_of_each_lidar=[len(points), 0, 0, 0, 0],
        timestamp_micros=t0 + int(round(f * FRAME_DT * 1e6)),
        annos=annos,
        context_name=_context_name(sequence),
    )


# ---------------------------------------------------------------------------------- dataset
#: The default dataset of ``make demo`` (see docs/synthetic.md for the time budget).
DEFAULT_NUM_SEQUENCES = {"train": 12, "val": 1}
DEFAULT_FRAMES_PER_SEQUENCE = {"train": 60, "val": 198}


def _split_ints(value, name: str, minimum: int) -> dict[str, int]:
    if not isinstance(value, Mapping):
        raise SyntheticDatasetError(
            f"{name} must be a dict like {{'train': N, 'val': M}}, got {value!r}"
        )
    unknown = sorted(set(value) - set(SPLITS))
    if unknown:
        raise SyntheticDatasetError(f"{name}: unknown split(s) {unknown}; expected {SPLITS}")
    out = {}
    for split in SPLITS:
        v = value.get(split, 0 if name == "num_sequences" else minimum)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
            raise SyntheticDatasetError(f"{name}[{split!r}] must be an int >= {minimum}, got {v!r}")
        out[split] = int(v)
    return out


def _write_if_changed(path: Path, data: bytes) -> bool:
    """Atomically write ``data`` unless the file already holds exactly it; True if written."""
    if path.exists() and path.read_bytes() == data:
        return False
    write_atomic(path, lambda f: f.write(data))
    return True


def _check_meta(meta_path: Path, meta: dict) -> None:
    old = json.loads(meta_path.read_text())
    conflicts = []
    for key in ("generator_version", "args", "lidar", "sensor"):
        if old.get(key) != meta[key]:
            conflicts.append(f"{key}: existing {old.get(key)!r} vs requested {meta[key]!r}")
    if conflicts:
        raise SyntheticDatasetError(
            f"{meta_path}: this root holds a synthetic dataset generated with other arguments; "
            "use another root or delete it. Conflicts: " + "; ".join(conflicts)
        )


def _drop_never_seen(infos: list[dict]) -> None:
    """Remove, in place, the labels of objects that have no point in any frame of the
    sequence (as on Waymo, where annotators label what the LiDAR saw at some time; objects
    occluded in some frames keep their labels there, with ``num_points_in_gt`` 0)."""
    seen: set[str] = set()
    for info in infos:
        annos = info["annos"]
        seen.update(annos["obj_ids"][annos["num_points_in_gt"] > 0].tolist())
    for info in infos:
        annos = info["annos"]
        keep = np.array([oid in seen for oid in annos["obj_ids"].tolist()], dtype=bool)
        if keep.all():
            continue
        if not keep.any():
            info["annos"] = wf.make_annos([], [], [], [], [], [], [], [], info["pose"])
            continue
        info["annos"] = {
            k: v[keep] if k != "name" and k != "obj_ids" else np.array(v[keep].tolist())
            for k, v in annos.items()
        }


@contextmanager
def _torch_threads(num: int | None):
    """Temporarily set torch's intra-op threads (restored on exit); ``None`` leaves them."""
    if num is None:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(num)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _t0(seed: int, split: str, index: int) -> int:
    """First timestamp (micros) of a sequence, in Waymo's 2017-2019 range."""
    return 1_510_000_000_000_000 + derive_seed(seed, "synthetic_waymo", split, index, "t0") % (
        60_000_000_000_000
    )


def _generate_chunk(task: dict) -> list[dict]:
    """Write frames ``task['start']:task['stop']`` of one sequence; return their infos.

    Runs in the main process or a worker; results do not depend on how frames are chunked.
    """
    seed, split, index = task["seed"], task["split"], task["index"]
    name = sequence_name(seed, split, index)
    root, device = Path(task["root"]), task["device"]
    lidar, sensor = LidarModel.waymo_top(), SensorModel()
    with _torch_threads(task["threads"]):
        scene = SyntheticScene(seed, split, index, task["num_frames"])
        dirs = lidar_directions(lidar, device)
        infos = []
        for f in range(task["start"], task["stop"]):
            points, labels = generate_frame(scene, f, lidar, sensor, device, dirs=dirs)
            wf.save_frame_points(wf.frame_npy_path(root, name, f), points)
            infos.append(_frame_info(scene, name, f, points, labels, _t0(seed, split, index)))
    return infos


def _generate_sequences(root, seed, todo, frames, device, workers, threads, logger):
    """Generate the ``(split, index)`` sequences of ``todo``; return ``{(split, index): infos}``.

    With several workers, long sequences are cut into contiguous frame chunks (each rebuilds
    the scene, which is deterministic) for load balance; a sequence's pkl is written,
    atomically and last, once all its frames exist.
    """
    tasks = []
    total = sum(frames[split] for split, _ in todo)
    target = max(16, math.ceil(total / (4 * workers)))  # frames per chunk, for load balance
    for split, index in todo:
        n = frames[split]
        name = sequence_name(seed, split, index)
        wf.sequence_pkl_path(root, name).parent.mkdir(parents=True, exist_ok=True)
        chunks = 1 if workers <= 1 else max(1, round(n / target))
        bounds = np.linspace(0, n, chunks + 1).round().astype(int)
        for a, b in zip(bounds[:-1], bounds[1:]):
            tasks.append(
                {
                    "seed": seed, "split": split, "index": index, "num_frames": n,
                    "start": int(a), "stop": int(b), "root": str(root), "device": str(device),
                    "threads": threads,
                }
            )  # fmt: skip
    tasks.sort(key=lambda t: t["start"] - t["stop"])  # longest first
    remaining = {key: sum(1 for t in tasks if (t["split"], t["index"]) == key) for key in todo}
    parts: dict = {key: [] for key in todo}
    results = {}

    def finish(task, infos):
        key = (task["split"], task["index"])
        parts[key].append((task["start"], infos))
        remaining[key] -= 1
        if remaining[key] == 0:
            seq_infos = [i for _, chunk in sorted(parts[key], key=lambda p: p[0]) for i in chunk]
            _drop_never_seen(seq_infos)
            name = sequence_name(seed, *key)
            pkl_path = wf.sequence_pkl_path(root, name)
            wf.validate_sequence_infos(seq_infos, pkl_path)
            wf.save_sequence_infos(pkl_path, seq_infos)  # last: finished once the pkl exists
            results[key] = seq_infos
            if logger is not None:
                logger.info(
                    "synthetic %s #%d %s: %d frames, %.0f points/frame, %.1f objects/frame",
                    key[0], key[1], name, len(seq_infos),
                    np.mean([i["num_points_of_each_lidar"][0] for i in seq_infos]),
                    np.mean([len(i["annos"]["name"]) for i in seq_infos]),
                )  # fmt: skip

    if workers <= 1 or len(tasks) <= 1:
        for task in tasks:
            finish(task, _generate_chunk(task))
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            futures = {pool.submit(_generate_chunk, task): task for task in tasks}
            for fut in as_completed(futures):
                finish(futures[fut], fut.result())
    return results


def create_synthetic_waymo(
    root_path: str | Path,
    num_sequences: Mapping[str, int] | None = None,
    frames_per_sequence: Mapping[str, int] | None = None,
    seed: int = 0,
    device: str | torch.device = "cpu",
    logger: logging.Logger | None = None,
    workers: int = 1,
    threads: int | None = 1,
) -> dict:
    """Generate (or complete) a synthetic dataset in OpenPCDet's processed Waymo layout.

    Args:
        root_path: dataset root (``DATA_PATH``); gets ``ImageSets/``,
            ``waymo_processed_data_v0_5_0/`` and the ``*_infos_<split>.pkl`` files.
        num_sequences: ``{'train': N, 'val': M}`` (default :data:`DEFAULT_NUM_SEQUENCES`).
        frames_per_sequence: ``{'train': F, 'val': G}`` at 10 Hz (default
            :data:`DEFAULT_FRAMES_PER_SEQUENCE`).
        seed: dataset seed; the same seed and sizes give byte-identical files (on one device).
        device: torch device for ray casting.
        logger: optional logger for progress.
        workers: processes generating frame chunks in parallel (results do not depend on it).
        threads: torch intra-op threads per process while generating (``None``: unchanged);
            1 is fastest here, the ray caster's tensors are too small to split well.
    Returns:
        A summary dict: ``root``, ``sequences`` (names per split), ``frames`` per split,
        ``generated``/``reused`` sequence counts, ``points_per_frame`` (mean, min, max),
        ``objects_per_class``, ``elapsed_s``, ``disk_bytes``.
    Raises:
        SyntheticDatasetError: the root holds data from other arguments or foreign data.
    """
    tic = time.perf_counter()
    num_sequences = _split_ints(
        DEFAULT_NUM_SEQUENCES if num_sequences is None else num_sequences, "num_sequences", 0
    )
    frames = _split_ints(
        DEFAULT_FRAMES_PER_SEQUENCE if frames_per_sequence is None else frames_per_sequence,
        "frames_per_sequence",
        1,
    )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SyntheticDatasetError(f"seed must be a non-negative int, got {seed!r}")
    seed = int(seed)
    # checked before anything is written: a bad argument leaves the root untouched
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SyntheticDatasetError(f"workers must be an int >= 1, got {workers!r}")
    if threads is not None and (
        isinstance(threads, bool) or not isinstance(threads, int) or threads < 1
    ):
        raise SyntheticDatasetError(f"threads must be None or an int >= 1, got {threads!r}")
    root = Path(root_path)
    lidar = LidarModel.waymo_top()
    sensor = SensorModel()
    sequences = {s: [sequence_name(seed, s, i) for i in range(num_sequences[s])] for s in SPLITS}
    meta = {
        "generator": "pcdet_atlas.datasets.synthetic",
        "generator_version": GENERATOR_VERSION,
        "args": {"num_sequences": num_sequences, "frames_per_sequence": frames, "seed": seed},
        "lidar": lidar.to_config(),
        "sensor": sensor.to_dict(),
        "sequences": sequences,
    }
    meta_path = root / META_FILE
    if meta_path.exists():
        _check_meta(meta_path, meta)
    elif (root / "ImageSets").exists() or wf.data_dir(root).exists():
        raise SyntheticDatasetError(
            f"{root}: holds Waymo-format data without {META_FILE}; refusing to write a synthetic "
            "dataset into it (choose an empty root)"
        )
    root.mkdir(parents=True, exist_ok=True)
    _write_if_changed(meta_path, (json.dumps(meta, indent=2, sort_keys=True) + "\n").encode())
    (root / "ImageSets").mkdir(exist_ok=True)
    wf.data_dir(root).mkdir(exist_ok=True)

    existing, todo = {}, []
    for split in SPLITS:
        lines = "".join(f"{name}.tfrecord\n" for name in sequences[split])
        _write_if_changed(root / "ImageSets" / f"{split}.txt", lines.encode())
        for index, name in enumerate(sequences[split]):
            pkl_path = wf.sequence_pkl_path(root, name)
            if not pkl_path.exists():
                todo.append((split, index))
                continue
            infos = load_pickle(pkl_path)
            wf.validate_sequence_infos(infos, pkl_path)
            if len(infos) != frames[split]:
                raise SyntheticDatasetError(
                    f"{pkl_path}: has {len(infos)} frames, expected {frames[split]}"
                )
            existing[(split, index)] = infos
    new = _generate_sequences(root, seed, todo, frames, device, workers, threads, logger)
    existing.update(new)
    split_infos = {}
    for split in SPLITS:
        infos_all = [i for index in range(num_sequences[split]) for i in existing[(split, index)]]
        info_path = root / f"{wf.PROCESSED_DATA_TAG}_infos_{split}.pkl"
        _write_if_changed(info_path, pickle.dumps(infos_all))
        split_infos[split] = infos_all
    generated, reused = len(new), len(existing) - len(new)

    all_infos = [i for s in SPLITS for i in split_infos[s]]
    npts = np.array([i["num_points_of_each_lidar"][0] for i in all_infos], dtype=np.int64)
    classes: dict[str, int] = {}
    for info in all_infos:
        for n in info["annos"]["name"]:
            classes[str(n)] = classes.get(str(n), 0) + 1
    disk = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    return {
        "root": str(root),
        "sequences": sequences,
        "frames": {s: len(split_infos[s]) for s in SPLITS},
        "generated": generated,
        "reused": reused,
        "points_per_frame": {
            "mean": float(npts.mean()) if len(npts) else 0.0,
            "min": int(npts.min()) if len(npts) else 0,
            "max": int(npts.max()) if len(npts) else 0,
        },
        "objects_per_class": dict(sorted(classes.items())),
        "elapsed_s": time.perf_counter() - tic,
        "disk_bytes": int(disk),
    }


def format_summary(summary: dict) -> str:
    """Human-readable lines of a :func:`create_synthetic_waymo` summary."""
    ppf = summary["points_per_frame"]
    lines = [
        f"synthetic Waymo-format dataset at {summary['root']}",
        "  sequences: "
        + ", ".join(f"{s} {len(v)}" for s, v in summary["sequences"].items())
        + f" (generated {summary['generated']}, reused {summary['reused']})",
        "  frames:    " + ", ".join(f"{s} {n}" for s, n in summary["frames"].items()),
        f"  points/frame (TOP): mean {ppf['mean']:.0f}, min {ppf['min']}, max {ppf['max']}",
        "  objects (frame labels): "
        + ", ".join(f"{k} {v}" for k, v in summary["objects_per_class"].items()),
        f"  disk: {summary['disk_bytes'] / 2**30:.2f} GiB",
        f"  time: {summary['elapsed_s']:.1f} s",
    ]
    return "\n".join(lines)
