"""Where a detector's AP is lost: missed objects or loose boxes.

The Waymo metric counts a Vehicle prediction only at 3D IoU >= 0.7, so a detector that finds every
vehicle with boxes a few degrees or decimetres off scores like one that misses most of them.
:func:`ap_by_iou` recomputes the L2 AP/APH of one class at several IoU thresholds (a steep fall
between 0.5 and 0.7 means loose boxes), and :func:`localization_errors` matches predictions to
ground-truth boxes one to one by 3D IoU and measures each box parameter's error in the frame of
the ground-truth box: centre along / across its heading, height of the centre, length, width,
height, and heading (with front/back flips counted apart, since IoU ignores them but APH does not).
:func:`projected_ap` answers "what would the AP be with half the centre error": it scales the
errors of the matched predictions and evaluates again.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from pcdet_atlas.evaluation.waymo_metric import compute_waymo_curves, evaluated_gt_mask
from pcdet_atlas.ops.iou3d_nms import boxes_iou3d

__all__ = [
    "ERROR_COMPONENTS",
    "ap_by_iou",
    "box_errors",
    "localization_errors",
    "match_by_iou",
    "projected_ap",
]

#: Names of the per-pair errors of :func:`box_errors` (m, m, m, m, m, m, rad).
ERROR_COMPONENTS = ("along", "across", "z", "length", "width", "height", "heading")


def ap_by_iou(
    gt_annos: Sequence[dict],
    det_annos: Sequence[dict],
    class_name: str,
    thresholds: Sequence[float] = (0.3, 0.5, 0.6, 0.7, 0.8),
) -> dict[float, tuple[float, float]]:
    """``{threshold: (L2 AP, L2 APH)}`` of ``class_name`` (annos as for the Waymo metric)."""
    out = {}
    for thr in thresholds:
        curve = compute_waymo_curves(
            gt_annos, det_annos, [class_name], iou_thresholds={class_name: thr}
        )[f"{class_name}/L2"]
        out[float(thr)] = (float(curve["ap"]), float(curve["aph"]))
    return out


def match_by_iou(
    gt_boxes: np.ndarray, pred_boxes: np.ndarray, min_iou: float = 0.1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one matching of ``(M, 7+)`` ground truth and ``(K, 7+)`` predictions, greedily
    by descending 3D IoU (ties: lower GT index, then lower prediction index), pairs below
    ``min_iou`` left out. Returns GT indices, prediction indices and IoUs of the pairs."""
    empty = np.zeros(0, dtype=np.int64)
    if len(gt_boxes) == 0 or len(pred_boxes) == 0:
        return empty, empty, np.zeros(0)
    iou = _iou3d_matrix(gt_boxes, pred_boxes)
    gi, pi = np.nonzero(iou >= min_iou)
    order = np.lexsort((pi, gi, -iou[gi, pi]))
    used_g, used_p, pairs = set(), set(), []
    for g, p in zip(gi[order].tolist(), pi[order].tolist()):
        if g not in used_g and p not in used_p:
            used_g.add(g)
            used_p.add(p)
            pairs.append((g, p))
    g, p = (np.array(v, dtype=np.int64) for v in zip(*pairs)) if pairs else (empty, empty)
    return g, p, iou[g, p]


def match_score_first(
    gt_boxes: np.ndarray, pred_boxes: np.ndarray, scores: np.ndarray, min_iou: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching in descending score order (ties: lower index), each prediction taking
    the unmatched ground-truth box of highest 3D IoU >= ``min_iou``: the pairs a detector's
    ranking makes (a low-scoring duplicate with a tighter box does not displace the
    high-scoring prediction). Returns GT and prediction indices."""
    empty = np.zeros(0, dtype=np.int64)
    if len(gt_boxes) == 0 or len(pred_boxes) == 0:
        return empty, empty
    iou = _iou3d_matrix(gt_boxes, pred_boxes)
    free = np.ones(len(gt_boxes), dtype=bool)
    gi, pi = [], []
    for p in np.argsort(-np.asarray(scores), kind="stable").tolist():
        col = np.where(free, iou[:, p], -1.0)
        g = int(col.argmax())
        if col[g] >= min_iou:
            free[g] = False
            gi.append(g)
            pi.append(p)
    return np.array(gi, dtype=np.int64), np.array(pi, dtype=np.int64)


def box_errors(gt: np.ndarray, pred: np.ndarray) -> dict[str, np.ndarray]:
    """Errors of row-aligned ``(N, 7+)`` boxes ``[x, y, z, l, w, h, heading]``, prediction minus
    ground truth: the centre offset rotated into the ground-truth box frame (``along`` its
    heading, ``across`` it), ``z``, ``length``, ``width``, ``height``, ``heading`` wrapped to
    ``[-pi, pi)``; plus ``flipped`` (``|heading| > pi / 2``) and ``heading_mod_pi`` (the heading
    error folded to ``[-pi / 2, pi / 2)``, what IoU sees)."""
    gt = np.asarray(gt, dtype=np.float64)
    pred = np.asarray(pred, dtype=np.float64)
    cos, sin = np.cos(gt[:, 6]), np.sin(gt[:, 6])
    dx, dy = pred[:, 0] - gt[:, 0], pred[:, 1] - gt[:, 1]
    heading = np.mod(pred[:, 6] - gt[:, 6] + math.pi, 2 * math.pi) - math.pi
    return {
        "along": cos * dx + sin * dy,
        "across": -sin * dx + cos * dy,
        "z": pred[:, 2] - gt[:, 2],
        "length": pred[:, 3] - gt[:, 3],
        "width": pred[:, 4] - gt[:, 4],
        "height": pred[:, 5] - gt[:, 5],
        "heading": heading,
        "flipped": np.abs(heading) > math.pi / 2,
        "heading_mod_pi": np.mod(heading + math.pi / 2, math.pi) - math.pi / 2,
    }


def localization_errors(
    gt_annos: Sequence[dict],
    det_annos: Sequence[dict],
    class_name: str,
    min_points: int = 1,
    score_threshold: float = 0.0,
    min_iou: float = 0.1,
) -> dict:
    """Per-component error statistics of the predictions matched to ground-truth boxes.

    Args:
        gt_annos, det_annos: per frame, aligned (``name``, ``gt_boxes_lidar``,
            ``num_points_in_gt`` / ``name``, ``boxes_lidar``, ``score``).
        class_name: the class compared (predictions and ground truth of that name only).
        min_points: ground-truth boxes with fewer LiDAR points are left out.
        score_threshold: predictions scoring below it are left out.
        min_iou: pairs below this 3D IoU are not matched (missed / spurious).
    Returns:
        ``num_gt``, ``num_matched``, ``iou_median``; per component of
        :data:`ERROR_COMPONENTS` ``{'bias', 'median_abs', 'p90_abs'}`` (heading: of the error
        folded to ``[-pi/2, pi/2)``), ``flipped_fraction``; and ``errors``, the per-pair arrays.
    """
    if len(gt_annos) != len(det_annos):
        raise ValueError(f"{len(gt_annos)} ground-truth frames but {len(det_annos)} predictions")
    parts, ious, num_gt = [], [], 0
    for gt, det in zip(gt_annos, det_annos):
        g_names, p_names = np.asarray(gt["name"]), np.asarray(det["name"])
        g_sel = (g_names == class_name) & (np.asarray(gt["num_points_in_gt"]) >= min_points)
        p_sel = (p_names == class_name) & (np.asarray(det["score"]) >= score_threshold)
        g_boxes = _rows(gt["gt_boxes_lidar"], len(g_names))[g_sel]
        p_boxes = _rows(det["boxes_lidar"], len(p_names))[p_sel]
        num_gt += len(g_boxes)
        gi, pi, iou = match_by_iou(g_boxes, p_boxes, min_iou)
        parts.append((g_boxes[gi, :7], p_boxes[pi, :7]))
        ious.append(iou)
    gt_m = np.concatenate([g for g, _ in parts]) if parts else np.zeros((0, 7))
    pred_m = np.concatenate([p for _, p in parts]) if parts else np.zeros((0, 7))
    errors = box_errors(gt_m, pred_m)
    iou = np.concatenate(ious) if ious else np.zeros(0)
    out: dict = {
        "num_gt": num_gt,
        "num_matched": len(gt_m),
        "iou_median": float(np.median(iou)) if iou.size else math.nan,
        "flipped_fraction": float(errors["flipped"].mean()) if iou.size else math.nan,
        "errors": errors,
    }
    for name in ERROR_COMPONENTS:
        values = errors["heading_mod_pi" if name == "heading" else name]
        if values.size == 0:
            out[name] = {"bias": math.nan, "median_abs": math.nan, "p90_abs": math.nan}
            continue
        out[name] = {
            "bias": float(values.mean()),
            "median_abs": float(np.median(np.abs(values))),
            "p90_abs": float(np.percentile(np.abs(values), 90)),
        }
    return out


#: Box columns of each error component (the centre's along / across pair moves x and y together).
_COMPONENT_COLUMNS = {"center": (0, 1), "z": (2,), "length": (3,), "width": (4,), "height": (5,)}


def projected_ap(
    gt_annos: Sequence[dict],
    det_annos: Sequence[dict],
    class_name: str,
    factors: dict[str, float],
    iou_threshold: float | None = None,
    min_iou: float = 0.3,
) -> float:
    """L2 AP of ``class_name`` after scaling the errors of the matched predictions.

    Predictions are matched by :func:`match_score_first` (3D IoU >= ``min_iou``) to the
    ground-truth boxes the metric scores (those with LiDAR points, see
    :func:`~pcdet_atlas.evaluation.waymo_metric.evaluated_gt_mask`); each matched box is moved
    to ``gt + factor * (pred - gt)`` for the components named in ``factors`` (``center``,
    ``z``, ``length``, ``width``, ``height``, ``heading``; the heading error is folded to
    ``[-pi/2, pi/2)`` first, so a flipped box stays flipped). ``factors={'center': 0.5}``
    answers "what if the centre error halved"; all factors 0 give the AP at ``min_iou``.
    ``iou_threshold``: the class's official one unless given.
    """
    unknown = set(factors) - set(_COMPONENT_COLUMNS) - {"heading"}
    if unknown:
        raise ValueError(
            f"factors: unknown component(s) {sorted(unknown)}; expected "
            f"{[*_COMPONENT_COLUMNS, 'heading']}"
        )
    moved = []
    for i, (gt, det) in enumerate(zip(gt_annos, det_annos)):
        g_sel = evaluated_gt_mask(gt, [class_name], f"gt_annos[{i}]")
        p_idx = np.flatnonzero(np.asarray(det["name"]) == class_name)
        g_boxes = _rows(gt["gt_boxes_lidar"], len(g_sel))[g_sel]
        boxes = _rows(det["boxes_lidar"], len(det["name"])).copy()
        gi, pi = match_score_first(g_boxes, boxes[p_idx], np.asarray(det["score"])[p_idx], min_iou)
        g, rows = g_boxes[gi], p_idx[pi]
        for name, factor in factors.items():
            if name == "heading":
                err = np.mod(boxes[rows, 6] - g[:, 6] + math.pi / 2, math.pi) - math.pi / 2
                boxes[rows, 6] -= (1.0 - factor) * err
            else:
                for col in _COMPONENT_COLUMNS[name]:
                    boxes[rows, col] = g[:, col] + factor * (boxes[rows, col] - g[:, col])
        moved.append(dict(det, boxes_lidar=boxes))
    thresholds = None if iou_threshold is None else {class_name: iou_threshold}
    curve = compute_waymo_curves(gt_annos, moved, [class_name], iou_thresholds=thresholds)
    return float(curve[f"{class_name}/L2"]["ap"])


def _iou3d_matrix(gt_boxes: np.ndarray, pred_boxes: np.ndarray) -> np.ndarray:
    """``(M, K)`` float64 3D IoU of ``(M, 7+)`` and ``(K, 7+)`` boxes."""
    return boxes_iou3d(
        torch.as_tensor(np.asarray(gt_boxes)[:, :7], dtype=torch.float64),
        torch.as_tensor(np.asarray(pred_boxes)[:, :7], dtype=torch.float64),
    ).numpy()


def _rows(boxes, count: int) -> np.ndarray:
    """``(count, 7+)`` float64 boxes (an empty list or ``(0,)`` array gives ``(0, 7)``)."""
    boxes = np.asarray(boxes, dtype=np.float64)
    return boxes.reshape(count, -1) if count else np.zeros((0, 7))
