"""Building the GT-sampling database from the train split (OpenPCDet's
``create_groundtruth_database`` for Waymo).

For every frame ``k`` of the split's info list (every ``sampled_interval``-th), the points
inside each labelled box are cut out, moved to the box centre and written as float32
``<seq>_<sample_idx:04d>_<name>_<i>.bin``; Vehicles are taken only when ``k % 4 == 0`` and
Pedestrians only when ``k % 2 == 0`` (OpenPCDet's subsampling). Points come from the dataset's
own loading (``get_lidar``: tanh applied, NLZ per config). With ``SEQUENCE_CONFIG`` enabled the
database is built from at least 5 frames (``SAMPLE_OFFSET[0] = min(-4, offset)``) and carries the
time-lag column. Outputs under ``save_path`` (the data root by default)::

    <tag>_gt_database_<split>_sampled_<n>[_multiframe_<st>_to_<ed>]/   one .bin per object
    <tag>_waymo_dbinfos_<split>_sampled_<n>[...].pkl                    {class: [db_info]}
    <tag>_gt_database_<split>_sampled_<n>[...]_global.npy               all objects stacked

``db_info`` keys: ``name, path (relative to the data root), sequence_name, sample_idx, gt_idx,
box3d_lidar (9,), num_points_in_gt, difficulty, global_data_offset [start, end]``.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import tempfile
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from pcdet_atlas.config import to_plain
from pcdet_atlas.datasets.augmentor.box_ops import box_index_of_points
from pcdet_atlas.datasets.multiframe import SequenceConfig
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.utils.common import save_pickle, write_atomic
from pcdet_atlas.utils.safe_pickle import load_pickle

__all__ = ["create_groundtruth_database", "gt_database_paths", "write_split_infos"]


def gt_database_paths(
    save_path: str | Path,
    processed_data_tag: str,
    split: str,
    sampled_interval: int,
    sample_offset: Sequence[int] | None = None,
) -> dict[str, Path]:
    """The three output paths (``dir``, ``info``, ``global``), OpenPCDet's names."""
    save_path = Path(save_path)
    stem = f"{split}_sampled_{sampled_interval}"
    if sample_offset is not None:
        stem += f"_multiframe_{sample_offset[0]}_to_{sample_offset[1]}"
    return {
        "dir": save_path / f"{processed_data_tag}_gt_database_{stem}",
        "info": save_path / f"{processed_data_tag}_waymo_dbinfos_{stem}.pkl",
        "global": save_path / f"{processed_data_tag}_gt_database_{stem}_global.npy",
    }


def write_split_infos(dataset, save_path: str | Path | None = None) -> Path:
    """Write ``<tag>_infos_<split>.pkl`` (the concatenation of the split's sequence infos, as
    OpenPCDet's info creation does) unless it exists; returns its path."""
    save_path = Path(save_path) if save_path is not None else dataset.root_path
    path = save_path / f"{dataset.processed_data_tag}_infos_{dataset.split}.pkl"
    if path.exists():
        return path
    return save_pickle(dataset.all_infos, path)


def create_groundtruth_database(
    dataset,
    save_path: str | Path | None = None,
    sampled_interval: int = 1,
    used_classes: Sequence[str] | None = ("Vehicle", "Pedestrian", "Cyclist"),
    logger: logging.Logger | None = None,
    workers: int = 0,
) -> dict[str, Path]:
    """Build the database of ``dataset``'s current split (a ``WaymoDataset``, ideally built
    with ``training=False`` and ``set_split('train')``). Returns :func:`gt_database_paths`.

    ``workers`` > 0 cuts the frames' objects out in that many processes (spawned, each
    rebuilding ``dataset`` from its registered class, config, root and split, with its
    ``all_infos``: :func:`_worker_job`); the database does not depend on it (the ``.bin`` and
    ``_global.npy`` files byte for byte, the info pickle's content)."""
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    logger = logger if logger is not None else logging.getLogger(__name__)
    save_path = Path(save_path) if save_path is not None else dataset.root_path
    sequence_cfg = None
    offset = None
    if dataset.sequence_cfg is not None:
        offset = (min(-4, dataset.sequence_cfg.sample_offset[0]), 0)
        sequence_cfg = SequenceConfig(sample_offset=offset, onehot_timestamp=False)
    paths = gt_database_paths(
        save_path, dataset.processed_data_tag, dataset.split, sampled_interval, offset
    )
    plain_job = _worker_job(dataset, sequence_cfg, used_classes, paths["dir"]) if workers else None
    paths["dir"].mkdir(parents=True, exist_ok=True)

    frames = range(0, len(dataset.all_infos), sampled_interval)
    job = (dataset, sequence_cfg, used_classes, paths["dir"])
    all_db_infos: dict[str, list[dict]] = {}
    stacked: list[np.ndarray] = []
    offset_cnt = 0
    with contextlib.ExitStack() as stack:
        if workers:
            # The job goes to the workers through a file: a spawned worker imports this package
            # before it reads its start-up pipe, and a dataset-sized payload in that pipe would
            # make the pool start its workers one import after another.
            job_dir = stack.enter_context(tempfile.TemporaryDirectory(dir=save_path))
            job_path = save_pickle(plain_job, Path(job_dir) / "job.pkl")
            pool = stack.enter_context(
                ProcessPoolExecutor(
                    workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_load_worker_job, initargs=(job_path,),
                )
            )  # fmt: skip
            objects = pool.map(_worker_frame_objects, frames, chunksize=4)
        else:
            objects = (_frame_objects(job, k) for k in frames)
        for frame in objects:
            for db_info, gt_points in frame:
                db_info["global_data_offset"] = [offset_cnt, offset_cnt + gt_points.shape[0]]
                offset_cnt += gt_points.shape[0]
                stacked.append(gt_points)
                all_db_infos.setdefault(db_info["name"], []).append(db_info)
    for name, entries in all_db_infos.items():
        logger.info(f"GT database {name}: {len(entries)} objects")
    num_columns = 5 + (1 if sequence_cfg is not None else 0)
    global_points = (
        np.concatenate(stacked, axis=0) if stacked else np.zeros((0, num_columns), np.float32)
    )
    # the info file's offsets index the stacked points: the old info goes first and the new
    # one is published last, each file whole, so a kill in between leaves no info file (an
    # error naming it) rather than offsets into another database's points
    Path(paths["info"]).unlink(missing_ok=True)
    write_atomic(paths["global"], lambda f: np.save(f, global_points))
    save_pickle(all_db_infos, paths["info"])
    return paths


def _frame_objects(job: tuple, k: int) -> list[tuple[dict, np.ndarray]]:
    """The objects of info ``k`` as ``(db_info without global_data_offset, points)``, their
    ``.bin`` files written; ``job`` is ``(dataset, sequence_cfg, used_classes, db_dir)``."""
    dataset, sequence_cfg, used_classes, db_dir = job
    info = dataset.all_infos[k]
    if "annos" not in info:
        return []
    sequence_name = info["point_cloud"]["lidar_sequence"]
    sample_idx = int(info["point_cloud"]["sample_idx"])
    points = dataset.get_lidar(sequence_name, sample_idx)
    if sequence_cfg is not None:
        points, _, _, _ = dataset.get_sequence_data(
            info, points, sequence_name, sample_idx, sequence_cfg
        )
    annos = info["annos"]
    names = np.asarray(annos["name"])
    difficulty = np.asarray(annos["difficulty"])
    gt_boxes = np.asarray(annos["gt_boxes_lidar"], dtype=np.float64)
    keep = np.ones(len(names), dtype=bool)
    if k % 4 != 0:
        keep &= names != "Vehicle"
    if k % 2 != 0:
        keep &= names != "Pedestrian"
    names, difficulty, gt_boxes = names[keep], difficulty[keep], gt_boxes[keep]
    if len(names) == 0:
        return []
    owner = box_index_of_points(points, gt_boxes[:, :7])  # (N,) first containing box
    # each box's points in their original order: one stable sort instead of a mask per box
    inside = np.flatnonzero(owner >= 0)
    inside = inside[np.argsort(owner[inside], kind="stable")]
    bounds = np.searchsorted(owner[inside], np.arange(len(names) + 1))
    out = []
    for i in range(len(names)):
        if used_classes is not None and names[i] not in used_classes:
            continue
        gt_points = points[inside[bounds[i] : bounds[i + 1]]].astype(np.float32)
        gt_points[:, :3] -= gt_boxes[i, :3].astype(np.float32)
        file_path = db_dir / f"{sequence_name}_{sample_idx:04d}_{names[i]}_{i}.bin"
        # whole, and a symlink planted at the name in an existing database is replaced
        write_atomic(file_path, lambda f, pts=gt_points: pts.tofile(f), sync=False)
        db_info = {
            "name": str(names[i]),
            "path": str(file_path.relative_to(dataset.root_path))
            if file_path.is_relative_to(dataset.root_path)
            else str(file_path),
            "sequence_name": sequence_name,
            "sample_idx": sample_idx,
            "gt_idx": i,
            "box3d_lidar": gt_boxes[i],
            "num_points_in_gt": int(gt_points.shape[0]),
            "difficulty": difficulty[i],
        }
        out.append((db_info, gt_points))
    return out


_WORKER_JOB: tuple | None = None


def _worker_job(dataset, sequence_cfg, used_classes, db_dir) -> dict:
    """The workers' job in plain values, read back with the restricted unpickler (no object of
    the project's classes is pickled): the dataset's registered class name, plain config (its
    ``DATA_SPLIT`` set to the current split), class names, mode, root and ``all_infos``."""
    cls = type(dataset)
    if cls.__name__ not in DATASETS or DATASETS.get(cls.__name__) is not cls:
        raise ValueError(
            f"workers > 0 rebuild the dataset in each worker from its registered class; "
            f"{cls.__module__}.{cls.__qualname__} is not in the DATASETS registry: register it, "
            "or pass workers=0"
        )
    cfg = to_plain(dataset.dataset_cfg)
    cfg["DATA_SPLIT"] = {**cfg.get("DATA_SPLIT", {}), dataset.mode: dataset.split}
    return {
        "dataset": cls.__name__,
        "dataset_cfg": cfg,
        "class_names": list(dataset.class_names),
        "training": bool(dataset.training),
        "root_path": str(dataset.root_path),
        "all_infos": dataset.all_infos,
        "sequence_cfg": None
        if sequence_cfg is None
        else [list(sequence_cfg.sample_offset), sequence_cfg.onehot_timestamp],
        "used_classes": None if used_classes is None else list(used_classes),
        "db_dir": str(db_dir),
    }


def _load_worker_job(path: Path) -> None:
    global _WORKER_JOB
    job = load_pickle(path)
    dataset = DATASETS.get(job["dataset"])(
        job["dataset_cfg"], job["class_names"], training=job["training"],
        root_path=job["root_path"],
    )  # fmt: skip
    dataset.all_infos = job["all_infos"]  # the caller's (it may hold a subset)
    seq = job["sequence_cfg"]
    sequence_cfg = None if seq is None else SequenceConfig(seq[0], onehot_timestamp=seq[1])
    _WORKER_JOB = (dataset, sequence_cfg, job["used_classes"], Path(job["db_dir"]))


def _worker_frame_objects(k: int) -> list[tuple[dict, np.ndarray]]:
    return _frame_objects(_WORKER_JOB, k)
