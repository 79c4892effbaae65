"""OpenPCDet's processed Waymo format (``waymo_processed_data_v0_5_0``), written and checked.

One place states the layout, keys, dtypes and shapes that OpenPCDet's converter writes (see
``docs/data.md``), so the reader, the synthetic generator, the attack writer and the tests agree.
Layout under ``root``::

    ImageSets/{train,val}.txt                       # one "<sequence>.tfrecord" per line
    waymo_processed_data_v0_5_0/<seq>/<seq>.pkl     # list of frame info dicts, by sample_idx
    waymo_processed_data_v0_5_0/<seq>/%04d.npy      # float32 (N, 6): x y z intensity elongation NLZ
"""

from __future__ import annotations

import math
import os
import pickle
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.utils.common import save_pickle, write_atomic
from pcdet_atlas.utils.paths import safe_component
from pcdet_atlas.utils.safe_pickle import load_pickle

PROCESSED_DATA_TAG = "waymo_processed_data_v0_5_0"
WAYMO_CLASSES = ["unknown", "Vehicle", "Pedestrian", "Sign", "Cyclist"]
NUM_POINT_COLUMNS = 6  # x, y, z, intensity (raw), elongation (raw), NLZ flag (1 in NLZ, -1 not)
LIDAR_NAMES = ["TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR"]
#: (height, width) of the five Waymo cameras, as the converter stores them per frame.
DEFAULT_IMAGE_SHAPES = {
    "image_shape_0": (1280, 1920),
    "image_shape_1": (1280, 1920),
    "image_shape_2": (1280, 1920),
    "image_shape_3": (886, 1920),
    "image_shape_4": (886, 1920),
}
INFO_KEYS = ("point_cloud", "frame_id", "metadata", "image", "pose", "num_points_of_each_lidar")
POINT_CLOUD_KEYS = ("num_features", "lidar_sequence", "sample_idx")
ANNO_KEYS = (
    "name",
    "difficulty",
    "dimensions",
    "location",
    "heading_angles",
    "obj_ids",
    "tracking_difficulty",
    "num_points_in_gt",
    "speed_global",
    "accel_global",
    "gt_boxes_lidar",
)


class WaymoFormatError(ValueError):
    """Data that does not match OpenPCDet's processed Waymo format."""


# ---------------------------------------------------------------------------- paths
def data_dir(root: str | Path, tag: str = PROCESSED_DATA_TAG) -> Path:
    """``root/<tag>``; a ``PROCESSED_DATA_TAG`` that is not one safe path component is an
    :class:`~pcdet_atlas.utils.paths.UnsafePathError`."""
    return Path(root) / safe_component(tag, "PROCESSED_DATA_TAG", f"data under {root}")


def image_set_path(root: str | Path, split: str, source: str) -> Path:
    """``root/ImageSets/<split>.txt``; a ``split`` (from ``source``: a flag, a config key) that is
    not one safe path component (``../x``) is an :class:`~pcdet_atlas.utils.paths.UnsafePathError`.
    """
    return Path(root) / "ImageSets" / f"{safe_component(split, 'split', source)}.txt"


def sequence_name_from_line(line: str) -> str:
    """``segment-..._with_camera_labels.tfrecord`` -> ``segment-..._with_camera_labels``."""
    return os.path.splitext(line.strip())[0]


def sequence_dir(root: str | Path, sequence: str, tag: str = PROCESSED_DATA_TAG) -> Path:
    """A sequence's folder; a name that is not one safe path component (``../x``) is an
    :class:`~pcdet_atlas.utils.paths.UnsafePathError`: nothing outside ``root`` is read or
    written."""
    return data_dir(root, tag) / safe_component(sequence, "sequence name", f"data under {root}")


def sequence_pkl_path(root: str | Path, sequence: str, tag: str = PROCESSED_DATA_TAG) -> Path:
    return sequence_dir(root, sequence, tag) / f"{sequence}.pkl"


def frame_npy_path(
    root: str | Path, sequence: str, sample_idx: int, tag: str = PROCESSED_DATA_TAG
) -> Path:
    return sequence_dir(root, sequence, tag) / f"{sample_idx:04d}.npy"


def frame_id(sequence: str, sample_idx: int) -> str:
    """OpenPCDet's ``frame_id``: note ``%03d`` here while the ``.npy`` name uses ``%04d``."""
    return f"{sequence}_{sample_idx:03d}"


# ---------------------------------------------------------------------------- building
def make_annos(
    name: Sequence[str],
    difficulty: Sequence[int],
    location: np.ndarray,
    dimensions: np.ndarray,
    heading_angles: Sequence[float],
    obj_ids: Sequence[str],
    num_points_in_gt: Sequence[int],
    speed_global: np.ndarray,
    pose: np.ndarray,
    tracking_difficulty: Sequence[int] | None = None,
    accel_global: np.ndarray | None = None,
) -> dict:
    """An ``annos`` dict exactly as OpenPCDet's ``generate_labels`` writes it.

    ``location`` is the box centre in the vehicle frame, ``dimensions`` is ``[l, w, h]``,
    ``speed_global`` is the global-frame ``[vx, vy]``; ``gt_boxes_lidar`` gets the speed rotated
    into the vehicle frame. With zero objects the per-object arrays have shape ``(0,)`` as the
    converter's ``np.array([])`` gives, and ``gt_boxes_lidar`` is ``(0, 9)``.
    """
    n = len(name)
    if n == 0:
        empty = np.array([])
        return {
            "name": np.array([], dtype="<U10"),
            "difficulty": np.array([], dtype=np.int64),
            "dimensions": empty.copy(),
            "location": empty.copy(),
            "heading_angles": empty.copy(),
            "obj_ids": np.array([], dtype="<U1"),
            "tracking_difficulty": np.array([], dtype=np.int64),
            "num_points_in_gt": np.array([], dtype=np.int64),
            "speed_global": empty.copy(),
            "accel_global": empty.copy(),
            "gt_boxes_lidar": np.zeros((0, 9)),
        }
    location = np.asarray(location, dtype=np.float64).reshape(n, 3)
    dimensions = np.asarray(dimensions, dtype=np.float64).reshape(n, 3)
    heading = np.asarray(heading_angles, dtype=np.float64).reshape(n)
    speed_global = np.asarray(speed_global, dtype=np.float64).reshape(n, 2)
    accel = np.zeros((n, 2)) if accel_global is None else np.asarray(accel_global, np.float64)
    global_speed = np.pad(speed_global, ((0, 0), (0, 1)), mode="constant", constant_values=0)
    pose = np.asarray(pose, dtype=np.float64).reshape(4, 4)
    speed = np.dot(global_speed, np.linalg.inv(pose[:3, :3].T))[:, :2]
    gt_boxes_lidar = np.concatenate([location, dimensions, heading[:, None], speed], axis=1)
    tracking = difficulty if tracking_difficulty is None else tracking_difficulty
    return {
        "name": np.array(list(name)),
        "difficulty": np.array(difficulty, dtype=np.int64).reshape(n),
        "dimensions": dimensions,
        "location": location,
        "heading_angles": heading,
        "obj_ids": np.array(list(obj_ids)),
        "tracking_difficulty": np.array(tracking, dtype=np.int64).reshape(n),
        "num_points_in_gt": np.array(num_points_in_gt, dtype=np.int64).reshape(n),
        "speed_global": speed_global,
        "accel_global": accel.reshape(n, 2),
        "gt_boxes_lidar": gt_boxes_lidar,
    }


def make_frame_info(
    sequence: str,
    sample_idx: int,
    pose: np.ndarray,
    num_points_of_each_lidar: Sequence[int],
    timestamp_micros: int,
    annos: dict | None = None,
    context_name: str | None = None,
) -> dict:
    """One frame info dict with every key of OpenPCDet's converter (``annos`` if labelled)."""
    info = {
        "point_cloud": {
            "num_features": 5,
            "lidar_sequence": sequence,
            "sample_idx": int(sample_idx),
        },
        "frame_id": frame_id(sequence, sample_idx),
        "metadata": {
            "context_name": context_name if context_name is not None else sequence,
            "timestamp_micros": int(timestamp_micros),
        },
        "image": dict(DEFAULT_IMAGE_SHAPES),
        "pose": np.asarray(pose, dtype=np.float32).reshape(4, 4),
        "num_points_of_each_lidar": [int(v) for v in num_points_of_each_lidar],
    }
    if annos is not None:
        info["annos"] = annos
    return info


def save_frame_points(path: str | Path, points: np.ndarray) -> None:
    """Write a ``(N, 6)`` float32 frame (raw intensity/elongation, NLZ flag +-1) atomically."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != NUM_POINT_COLUMNS or points.dtype != np.float32:
        raise WaymoFormatError(
            f"{path}: frame points must be float32 (N, {NUM_POINT_COLUMNS}), got "
            f"{points.dtype} {points.shape}"
        )
    write_atomic(path, lambda f: np.save(f, points), sync=False)  # regenerable bulk data


def save_sequence_infos(path: str | Path, infos: list[dict]) -> None:
    """Write a per-sequence info pkl atomically (a list of frame infos ordered by sample_idx)."""
    save_pickle(infos, path)


# ---------------------------------------------------------------------------- checking
def validate_points(points: np.ndarray, where: str | Path) -> None:
    """Raise :class:`WaymoFormatError` unless ``points`` is a finite float32 ``(N, 6)`` array
    whose NLZ flag (column 5) is -1 or 1 (any other value would make the loader's NLZ filter
    keep or drop rows by accident)."""
    if points.ndim != 2 or points.shape[1] != NUM_POINT_COLUMNS:
        raise WaymoFormatError(
            f"{where}: expected a (N, {NUM_POINT_COLUMNS}) array [x, y, z, intensity, elongation, "
            f"NLZ_flag], got shape {points.shape}"
        )
    if points.dtype != np.float32:
        raise WaymoFormatError(f"{where}: expected float32 points, got {points.dtype}")
    bad = ~np.isfinite(points)
    if bad.any():
        rows = np.nonzero(bad.any(axis=1))[0]
        raise WaymoFormatError(
            f"{where}: {rows.size} point(s) with NaN/inf values (first at row {int(rows[0])}: "
            f"{points[rows[0]].tolist()})"
        )
    bad = np.abs(points[:, 5]) != 1
    if bad.any():
        rows = np.nonzero(bad)[0]
        raise WaymoFormatError(
            f"{where}: the NLZ flag (column 5) must be -1 (outside a no-label zone) or 1 "
            f"(inside); {rows.size} point(s) have another value (first at row {int(rows[0])}: "
            f"{points[rows[0], 5].item()!r})"
        )


def validate_frame_info(info: dict, where: str, index: int | None = None) -> None:
    """Raise :class:`WaymoFormatError` if a frame info dict lacks a key or has a bad shape."""
    at = f"{where}" + (f" [frame {index}]" if index is not None else "")
    if not isinstance(info, dict):
        raise WaymoFormatError(f"{at}: frame info must be a dict, got {type(info).__name__}")
    for key in INFO_KEYS:
        if key not in info:
            raise WaymoFormatError(f"{at}: missing key {key!r} (expected keys: {INFO_KEYS})")
    for key in POINT_CLOUD_KEYS:
        if key not in info["point_cloud"]:
            raise WaymoFormatError(f"{at}: missing key 'point_cloud.{key}'")
    safe_component(info["frame_id"], "frame_id", at)  # names --save_to_file's <frame_id>.txt
    safe_component(info["point_cloud"]["lidar_sequence"], "point_cloud.lidar_sequence", at)
    pose = np.asarray(info["pose"])
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise WaymoFormatError(f"{at}: 'pose' must be a finite 4x4 matrix, got shape {pose.shape}")
    if "annos" in info:
        annos = info["annos"]
        for key in ANNO_KEYS:
            if key not in annos:
                raise WaymoFormatError(f"{at}: missing key 'annos.{key}' (expected: {ANNO_KEYS})")
        n = len(annos["name"])
        boxes = np.asarray(annos["gt_boxes_lidar"])
        if boxes.ndim != 2 or boxes.shape[0] != n or boxes.shape[1] not in (7, 9):
            raise WaymoFormatError(
                f"{at}: 'annos.gt_boxes_lidar' must be ({n}, 9) or ({n}, 7) for {n} objects, got "
                f"{boxes.shape}"
            )
        if not np.isfinite(boxes).all():
            row = int(np.nonzero(~np.isfinite(boxes).all(axis=1))[0][0])
            raise WaymoFormatError(
                f"{at}: 'annos.gt_boxes_lidar' has NaN/inf values (first at object {row}: "
                f"{boxes[row].tolist()})"
            )
        if n and not (boxes[:, 3:6] > 0).all():
            row = int(np.nonzero(~(boxes[:, 3:6] > 0).all(axis=1))[0][0])
            raise WaymoFormatError(
                f"{at}: 'annos.gt_boxes_lidar' object {row} has size (dx, dy, dz) "
                f"{boxes[row, 3:6].tolist()}; every size must be > 0"
            )
        for key in ("difficulty", "num_points_in_gt", "obj_ids"):
            if len(annos[key]) != n:
                raise WaymoFormatError(
                    f"{at}: 'annos.{key}' has {len(annos[key])} entries for {n} objects"
                )
        unknown = sorted(set(map(str, annos["name"])) - set(WAYMO_CLASSES))
        if unknown:
            raise WaymoFormatError(
                f"{at}: unknown class name(s) {unknown} in 'annos.name' (known: {WAYMO_CLASSES})"
            )


def validate_sequence_infos(infos: list, pkl_path: str | Path) -> None:
    """Check every frame info of a sequence pkl and that ``sample_idx`` runs 0, 1, 2, ... gap-free
    (multi-frame loading indexes the list by ``sample_idx``)."""
    if not isinstance(infos, list):
        raise WaymoFormatError(f"{pkl_path}: expected a list of frame infos, got {type(infos)}")
    for i, info in enumerate(infos):
        validate_frame_info(info, str(pkl_path), i)
        got = info["point_cloud"]["sample_idx"]
        if got != i:
            raise WaymoFormatError(
                f"{pkl_path}: frame index gap: entry {i} has sample_idx {got}, expected {i} "
                f"(per-sequence pkls must list every frame in order)"
            )


# ---------------------------------------------------------------------------- reading
def load_frame_points(path: str | Path, spare_rows: int = 0) -> np.ndarray:
    """Read and check one ``%04d.npy`` frame: float32 ``(N, 6)`` ``[x, y, z, intensity,
    elongation, NLZ_flag]``, raw intensity/elongation, finite.

    Args:
        spare_rows: extra rows allocated after the ``N`` read ones and left **uninitialised**
            (the returned array is ``(N + spare_rows, 6)``): room for rows a caller appends
            without copying the frame (an injection attack's phantom).

    Any read failure (missing, truncated, not an ``.npy``, a header shape the file's size does
    not hold, object array) is re-raised as :class:`WaymoFormatError` naming the file, chained to
    numpy's error.
    """
    path = Path(path)
    try:
        points = _read_npy_with_spare_rows(path, int(spare_rows))
    except FileNotFoundError as err:
        raise WaymoFormatError(f"{path}: frame file not found") from err
    except (OSError, ValueError, EOFError) as err:
        raise WaymoFormatError(
            f"{path}: cannot read frame points (truncated or not a float32 (N, "
            f"{NUM_POINT_COLUMNS}) .npy file): {err}"
        ) from err
    validate_points(points[: len(points) - spare_rows], path)
    return points


def _read_npy_header(f) -> tuple[tuple[int, ...], bool, np.dtype]:
    """``(shape, fortran_order, dtype)`` from the header of the ``.npy`` file open as ``f``,
    checked against the file's size: the data after the header must be exactly ``shape`` times
    the item size (else a header declaring a huge shape is allocated before the read fails).
    Object arrays are left to ``np.load``, which refuses them."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(f)
    else:
        shape, fortran_order, dtype = np.lib.format.read_array_header_2_0(f)
    if not dtype.hasobject:
        declared = math.prod(shape) * dtype.itemsize
        file_size, header_size = os.fstat(f.fileno()).st_size, f.tell()
        if file_size - header_size != declared:
            raise ValueError(
                f"the header declares shape {shape} of {dtype} ({declared} data bytes) but the "
                f"file holds {file_size} bytes ({file_size - header_size} after the "
                f"{header_size}-byte header)"
            )
    return shape, fortran_order, dtype


def _read_npy_with_spare_rows(path: Path, spare_rows: int) -> np.ndarray:
    """``np.load`` of a 2-D C-ordered ``.npy`` file into a fresh array with ``spare_rows``
    (possibly 0) uninitialised rows after the data: one header parse (checked against the file's
    size, :func:`_read_npy_header`), one read, no copy; any other layout or dtype is loaded by
    ``np.load`` and copied (so the checks and errors are those of a plain load)."""
    with open(path, "rb") as f:
        shape, fortran_order, dtype = _read_npy_header(f)
        if len(shape) != 2 or fortran_order or dtype != np.float32:
            loaded = np.load(path, allow_pickle=False)
            if loaded.ndim != 2:
                return loaded  # rejected by validate_points
            out = np.empty((loaded.shape[0] + spare_rows, loaded.shape[1]), loaded.dtype)
            out[: loaded.shape[0]] = loaded
            return out
        out = np.empty((shape[0] + spare_rows, shape[1]), dtype=np.float32)
        if out[: shape[0]].size == 0:  # an empty frame: nothing to read (and no byte view of it)
            return out
        data = memoryview(out[: shape[0]]).cast("B")
        if f.readinto(data) != data.nbytes:
            raise EOFError(f"file holds fewer than the {shape[0]} rows its header declares")
    return out


def load_sequence_infos(path: str | Path) -> list[dict]:
    """Read and check one per-sequence info pkl (see :func:`validate_sequence_infos`)."""
    path = Path(path)
    try:
        infos = load_pickle(path)
    except FileNotFoundError as err:
        raise WaymoFormatError(f"{path}: sequence info file not found") from err
    except (OSError, EOFError, ValueError, pickle.UnpicklingError, AttributeError) as err:
        raise WaymoFormatError(f"{path}: cannot unpickle sequence infos: {err}") from err
    validate_sequence_infos(infos, path)
    if len(infos) == 0:
        raise WaymoFormatError(f"{path}: sequence info list is empty (expected >= 1 frame)")
    sequence = path.stem
    for i, info in enumerate(infos):
        got = info["point_cloud"]["lidar_sequence"]
        if got != sequence:
            raise WaymoFormatError(
                f"{path} [frame {i}]: 'point_cloud.lidar_sequence' is {got!r}, expected the "
                f"folder name {sequence!r}"
            )
    return infos


def read_image_set(path: str | Path) -> list[str]:
    """Sequence names listed in ``ImageSets/<split>.txt`` (one ``*.tfrecord`` per line)."""
    path = Path(path)
    if not path.is_file():
        raise WaymoFormatError(
            f"{path}: split file not found (expected ImageSets/<split>.txt listing one "
            f"'<sequence>.tfrecord' per line)"
        )
    lines = [line.strip() for line in path.read_text().splitlines()]
    return [
        safe_component(sequence_name_from_line(line), "sequence name", f"{path} line {i}")
        for i, line in enumerate(lines, 1)
        if line
    ]


def find_sequence_pkl(root: str | Path, sequence: str, tag: str = PROCESSED_DATA_TAG) -> Path:
    """The per-sequence pkl of ``sequence``, accepting the name variants OpenPCDet accepts
    (``training_``/``validation_``/``testing_`` prefixes, no ``_with_camera_labels``).

    Raises :class:`WaymoFormatError` listing every path tried when none exists.
    """
    candidates = [sequence]
    for prefix in ("training", "validation", "testing"):
        candidates.append(sequence.replace("segment", f"{prefix}_segment", 1))
    candidates.append(sequence.replace("_with_camera_labels", ""))
    tried = []
    for name in dict.fromkeys(candidates):
        path = sequence_pkl_path(root, name, tag)
        if path.is_file():
            return path
        tried.append(str(path))
    raise WaymoFormatError(
        f"sequence {sequence!r} listed in ImageSets has no info pkl; tried: {', '.join(tried)}"
    )
