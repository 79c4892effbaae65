"""The inputs of the Waymo metric (:mod:`~pcdet_atlas.evaluation.waymo_metric`): ground truth
and predictions checked frame by frame (keys, shapes, class names, frame ids) and flattened into
one array per field over all frames, with each GT box's difficulty level and the official
distance mask and heading normalisation; the first bad frame is named in the error."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from pcdet_atlas.utils.common import limit_period

__all__ = [
    "DISTANCE_LIMIT_M",
    "WAYMO_IOU_THRESHOLDS",
    "WAYMO_OBJECT_NAMES",
    "Objects",
    "cat",
    "check_frames",
    "collect_det",
    "collect_gt",
    "evaluated_gt_mask",
]

#: IoU threshold per Waymo class (official config ``iou_thresholds: 0.0 0.7 0.5 0.5 0.5``).
WAYMO_IOU_THRESHOLDS = {"Vehicle": 0.7, "Pedestrian": 0.5, "Sign": 0.5, "Cyclist": 0.5}
#: Names an anno may hold: the evaluable classes and Waymo's type 0. A box of one of these that
#: is not in ``class_names`` is left out; any other name is an error (a typo such as 'Car' would
#: otherwise drop every box of the class silently).
WAYMO_OBJECT_NAMES = frozenset(WAYMO_IOU_THRESHOLDS) | {"unknown"}
DISTANCE_LIMIT_M = 1000.5


class Objects:
    """Flattened objects of one side (GT or predictions): arrays over all frames, ``(K, ...)``."""

    def __init__(self, frame, cls, boxes, score, level):
        self.frame = frame  # (K,) int64 frame index
        self.cls = cls  # (K,) int64 index into class_names
        self.boxes = boxes  # (K, 7) float32, heading limit_period'ed
        self.score = score  # (K,) float32 (predictions) or None
        self.level = level  # (K,) int64 1 | 2 (GT) or None


def _field(anno: dict, key: str, where: str) -> np.ndarray:
    if key not in anno:
        raise KeyError(f"{where}: missing key '{key}' (have {sorted(anno)})")
    return np.asarray(anno[key])


def _boxes(anno: dict, key: str, where: str, n: int) -> np.ndarray:
    boxes = _field(anno, key, where)
    if boxes.size == 0:
        boxes = boxes.reshape(0, 7)
    if boxes.ndim != 2 or boxes.shape[1] < 7 or boxes.shape[0] != n:
        raise ValueError(
            f"{where}: '{key}' must be ({n}, 7+) [x,y,z,dx,dy,dz,heading], got {boxes.shape}"
        )
    boxes = boxes[:, :7].astype(np.float32)
    if not np.isfinite(boxes).all():
        raise ValueError(f"{where}: '{key}' contains non-finite values")
    boxes[:, 6] = limit_period(boxes[:, 6], offset=0.5, period=np.float32(2 * np.pi))
    return boxes


def _class_index(names: np.ndarray, class_names: Sequence[str], where: str) -> np.ndarray:
    """``(M,)`` int64 index into ``class_names``, -1 for a Waymo class not evaluated."""
    lookup = {name: i for i, name in enumerate(class_names)}
    out = np.empty(len(names), dtype=np.int64)
    for i, name in enumerate(names):
        name = str(name)
        if name not in lookup and name not in WAYMO_OBJECT_NAMES:
            raise ValueError(
                f"{where}: 'name' {name!r} (box {i}) is not a Waymo class; expected one of "
                f"{sorted(WAYMO_OBJECT_NAMES)} (evaluated: {list(class_names)})"
            )
        out[i] = lookup.get(name, -1)
    return out


def _in_range(boxes: np.ndarray) -> np.ndarray:
    return np.linalg.norm(boxes[:, 0:2].astype(np.float64), axis=1) < DISTANCE_LIMIT_M


def evaluated_gt_mask(anno: Mapping, class_names: Sequence[str], where: str = "gt") -> np.ndarray:
    """``(M,)`` bool: the GT boxes of one frame's ``anno`` the metric scores (a class of
    ``class_names``, ``num_points_in_gt > 0``, within the distance limit); the others are
    dropped before matching. Bad annos raise errors naming ``where``."""
    return _gt_fields(anno, class_names, where)[3]


def _gt_fields(anno: Mapping, class_names: Sequence[str], where: str):
    """``(cls, boxes, level, keep)`` of one GT anno, all ``(M, ...)``."""
    names = _field(anno, "name", where).reshape(-1)
    n = len(names)
    box = _boxes(anno, "gt_boxes_lidar", where, n)
    num_points = _field(anno, "num_points_in_gt", where).reshape(-1)
    difficulty = _field(anno, "difficulty", where).reshape(-1).astype(np.int64)
    if len(num_points) != n or len(difficulty) != n:
        raise ValueError(
            f"{where}: 'num_points_in_gt' ({len(num_points)}) and 'difficulty' "
            f"({len(difficulty)}) must have one entry per box ({n})"
        )
    bad = ~np.isin(difficulty, (0, 1, 2))
    if bad.any():
        raise ValueError(
            f"{where}: 'difficulty' must be 0 (unknown), 1 or 2, got {difficulty[bad][:5]}"
        )
    level = difficulty.copy()
    level[(difficulty == 0) & (num_points > 5)] = 1
    level[(difficulty == 0) & (num_points <= 5)] = 2
    cls = _class_index(names, class_names, where)
    keep = (cls >= 0) & (num_points > 0) & _in_range(box)
    return cls, box, level, keep


def collect_gt(gt_annos: Sequence[dict], class_names: Sequence[str]) -> Objects:
    """The evaluated GT of all frames, checked and converted in one pass over the concatenated
    fields; a frame that fails a check is handed to :func:`_gt_fields` for its error."""
    fields = []
    for i, anno in enumerate(gt_annos):
        try:
            names = np.asarray(anno["name"]).reshape(-1)
            boxes = np.asarray(anno["gt_boxes_lidar"])
            boxes = boxes.reshape(0, 7) if boxes.size == 0 else boxes
            num_points = np.asarray(anno["num_points_in_gt"]).reshape(-1)
            difficulty = np.asarray(anno["difficulty"]).reshape(-1)
            n = len(names)
            if boxes.ndim != 2 or boxes.shape[1] < 7 or boxes.shape[0] != n:
                raise ValueError
            if len(num_points) != n or len(difficulty) != n:
                raise ValueError
        except (KeyError, ValueError):
            _first_error(gt_annos, i, _gt_fields, class_names, "gt_annos")
            raise
        fields.append((names, boxes[:, :7].astype(np.float32), num_points, difficulty))
    if not fields:
        return Objects(*(np.zeros(0, np.int64),) * 2, _cat_boxes([]), None, np.zeros(0, np.int64))
    frame = np.repeat(np.arange(len(fields)), [len(f[0]) for f in fields])
    boxes, num_points, difficulty = (np.concatenate(f) for f in list(zip(*fields))[1:])
    difficulty = difficulty.astype(np.int64)
    bad = ~np.isfinite(boxes).all(axis=1) | ~np.isin(difficulty, (0, 1, 2))
    cls = _checked_classes(gt_annos, fields, frame, bad, _gt_fields, class_names, "gt_annos")
    boxes[:, 6] = limit_period(boxes[:, 6], offset=0.5, period=np.float32(2 * np.pi))
    level = difficulty.copy()
    level[(difficulty == 0) & (num_points > 5)] = 1
    level[(difficulty == 0) & (num_points <= 5)] = 2
    keep = (cls >= 0) & (num_points > 0) & _in_range(boxes)
    return Objects(frame[keep], cls[keep], boxes[keep], None, level[keep])


def _first_error(annos, last: int, fields_fn, class_names, name: str) -> None:
    """Run the one-frame checks ``fields_fn`` on frames ``0 .. last``: the first bad frame
    raises its error (as checking frame by frame would)."""
    for i in range(last + 1):
        fields_fn(annos[i], class_names, f"{name}[{i}]")


def _checked_classes(
    annos, fields: list, frame: np.ndarray, bad: np.ndarray, fields_fn, class_names, name: str
) -> np.ndarray:
    """``(M,)`` class indices of the frames' objects (:func:`_class_indices`); a row that is
    ``bad`` or has a name that is no Waymo class raises the error of the first such frame, as
    checking frame by frame would (:func:`_first_error`)."""
    cls = _class_indices([f[0] for f in fields], class_names)
    if cls is None:  # names numpy cannot compare: the frames' own lookups
        _first_error(annos, len(annos) - 1, fields_fn, class_names, name)
        cls = np.concatenate([fields_fn(a, class_names, "")[0] for a in annos])
    if bad.any() or (cls < -1).any():
        _first_error(annos, int(frame[bad | (cls < -1)].min()), fields_fn, class_names, name)
    return cls


def _class_indices(names: list[np.ndarray], class_names: Sequence[str]) -> np.ndarray | None:
    """``(M,)`` int64 index into ``class_names`` of the frames' names, concatenated (as
    :func:`_class_index`), -1 for a Waymo class not evaluated, -2 for a name that is not a Waymo
    class; ``None`` for names numpy cannot concatenate or sort (mixed types)."""
    try:
        unique, inverse = np.unique(np.concatenate(names), return_inverse=True)
    except TypeError:
        return None
    lookup = {name: i for i, name in enumerate(class_names)}
    index = np.array(
        [lookup.get(str(u), -1 if str(u) in WAYMO_OBJECT_NAMES else -2) for u in unique],
        dtype=np.int64,
    )
    return index[inverse.reshape(-1)]


def collect_det(det_annos: Sequence[dict], class_names: Sequence[str]) -> Objects:
    """The evaluated predictions of all frames, in one pass as :func:`collect_gt` (checks by
    :func:`_det_fields`)."""
    fields = []
    for i, anno in enumerate(det_annos):
        try:
            names = np.asarray(anno["name"]).reshape(-1)
            boxes = np.asarray(anno["boxes_lidar"])
            boxes = boxes.reshape(0, 7) if boxes.size == 0 else boxes
            score = np.asarray(anno["score"]).reshape(-1)
            n = len(names)
            if boxes.ndim != 2 or boxes.shape[1] < 7 or boxes.shape[0] != n or len(score) != n:
                raise ValueError
        except (KeyError, ValueError):
            _first_error(det_annos, i, _det_fields, class_names, "det_annos")
            raise
        fields.append((names, boxes[:, :7].astype(np.float32), score.astype(np.float32)))
    if not fields:
        return Objects(*(np.zeros(0, np.int64),) * 2, _cat_boxes([]), np.zeros(0, np.float32), None)
    frame = np.repeat(np.arange(len(fields)), [len(f[0]) for f in fields])
    boxes, score = (np.concatenate(f) for f in list(zip(*fields))[1:])
    bad = ~np.isfinite(boxes).all(axis=1) | ~np.isfinite(score)
    cls = _checked_classes(det_annos, fields, frame, bad, _det_fields, class_names, "det_annos")
    boxes[:, 6] = limit_period(boxes[:, 6], offset=0.5, period=np.float32(2 * np.pi))
    in_range = _in_range(boxes)
    keep = (cls >= 0) & in_range
    score_kept = score[keep]
    if in_range.any() and float(score[in_range].max()) > 1:  # OpenPCDet: logits are squashed
        score_kept = (1.0 / (1.0 + np.exp(-score_kept.astype(np.float64)))).astype(np.float32)
    return Objects(frame[keep], cls[keep], boxes[keep], score_kept, None)


def _det_fields(anno: Mapping, class_names: Sequence[str], where: str):
    """``(cls, boxes, score)`` of one prediction anno (its checks, raising naming ``where``)."""
    names = _field(anno, "name", where).reshape(-1)
    n = len(names)
    box = _boxes(anno, "boxes_lidar", where, n)
    score = _field(anno, "score", where).reshape(-1).astype(np.float32)
    if len(score) != n:
        raise ValueError(f"{where}: 'score' has {len(score)} entries for {n} boxes")
    if not np.isfinite(score).all():
        raise ValueError(f"{where}: 'score' contains non-finite values")
    return _class_index(names, class_names, where), box, score


def cat(parts, dtype) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype=dtype)


def _cat_boxes(parts) -> np.ndarray:
    return np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 7), np.float32)


def check_frames(gt_annos: Sequence[dict], det_annos: Sequence[dict]) -> None:
    if len(gt_annos) != len(det_annos):
        raise ValueError(
            f"gt_annos ({len(gt_annos)} frames) and det_annos ({len(det_annos)} frames) must be "
            "aligned per frame"
        )
    for i, (gt, det) in enumerate(zip(gt_annos, det_annos)):
        if "frame_id" in gt and "frame_id" in det and str(gt["frame_id"]) != str(det["frame_id"]):
            raise ValueError(
                f"frame {i}: gt frame_id {gt['frame_id']!r} != det frame_id {det['frame_id']!r}"
            )
