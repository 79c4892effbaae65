"""The official Waymo Open Dataset 3D detection metric (L1/L2 AP and APH), in numpy and torch.

Semantics are those of ``waymo-open-dataset`` 1.6.7 (C++ ``detection_metrics``, ``matcher``,
``metrics_utils``, ``iou``) as driven by OpenPCDet's ``waymo_eval.py``; see
``docs/evaluation.md``. In short:

- GT boxes of the evaluated classes with ``num_points_in_gt > 0`` are kept; an unknown difficulty
  (0) becomes LEVEL_2 if the box has <= 5 points, else LEVEL_1. Boxes farther than 1000.5 m are
  dropped (OpenPCDet's distance mask). Headings go through ``limit_period`` in float32;
  predictions get a sigmoid if the largest score of all predictions within the distance limit,
  of any class (evaluated or not), is > 1.
- 101 float32 score cutoffs ``0.00, 0.01, ..., 0.99, 1.0``. For every frame, class and cutoff the
  predictions with ``score >= cutoff`` are matched to all GTs of that class by maximum-weight
  (Hungarian) matching with weights ``round(iou * 1e6)``; a pair can match iff
  ``float32(iou) >= threshold`` (Vehicle 0.7, Pedestrian / Sign / Cyclist 0.5). 3D IoU is exact,
  computed in float64 and cast to float32; it is 0 when any dimension is ``<= 0.01`` or ``>= 1e6``.
- A matched prediction is a TP whatever the GT's level; an unmatched prediction is an FP; an
  unmatched GT is an FN at level k only if its level is <= k. So L1 and L2 differ only in FN.
- Per cutoff: ``P = TP / (TP + FP)`` (0 if empty), ``R = TP / (TP + FN)``, ``P = 1`` where
  ``R = 0``; APH uses ``sum(heading accuracy) / (TP + FP)``. AP is the official float32
  integration: recall -> best precision map seeded with ``{0: 1}``, walked from high to low
  recall with a running max, gaps wider than 0.05 filled in steps of 0.05, the ``R = 0`` entry's
  precision replaced by its neighbour's, then the trapezoid rule. (Float32 rounding can put an AP
  1 ulp above 1; :func:`waymo_evaluate` clips its outputs to [0, 1], the curves keep the raw value.)

Exact and fast: the matching is solved with ``scipy.optimize.linear_sum_assignment`` on the integer
weights, once per *distinct* prediction subset (cutoffs that keep the same predictions share one
result) and per connected component of the frame's "can match" graph (components are independent
problems); a component with one prediction and one GT needs no solver at all. The inputs are
checked and flattened by :mod:`~pcdet_atlas.evaluation.waymo_inputs`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pcdet_atlas.evaluation.waymo_inputs import (
    WAYMO_IOU_THRESHOLDS,
    Objects,
    cat,
    check_frames,
    collect_det,
    collect_gt,
    evaluated_gt_mask,
)
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d

__all__ = [
    "WAYMO_IOU_THRESHOLDS",
    "WAYMO_SCORE_CUTOFFS",
    "compute_waymo_curves",
    "evaluated_gt_mask",
    "summarize_waymo_curves",
    "waymo_average_precision",
    "waymo_evaluate",
    "waymo_heading_accuracy",
]

#: The 101 official score cutoffs, float32.
WAYMO_SCORE_CUTOFFS = np.array([i * 0.01 for i in range(100)] + [1.0], dtype=np.float32)
LEVELS = (1, 2)
DESIRED_RECALL_DELTA = np.float32(0.05)
KMAX_IOU = np.float32(1e6)
MIN_BOX_DIM, MAX_BOX_DIM = 0.01, 1e6
MATCHERS = ("hungarian", "score_first")
#: candidate (prediction, GT) pairs bounded at once (~100 MB of float64 temporaries)
EDGE_CHUNK = 1 << 20


# --------------------------------------------------------------------------------------------
# Geometry of candidate pairs
# --------------------------------------------------------------------------------------------
def _candidate_edges(gt: Objects, det: Objects, thr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (pred, gt) index pairs of the same frame and class that may reach the IoU threshold.

    A pair is dropped only if a cheap upper bound of its 3D IoU (BEV overlap bounded by the
    overlap of the axis-aligned hulls and by the smaller footprint, times the z-overlap) is below
    the class threshold (with a 1e-6 relative margin), so no pair that can match is ever lost.
    Pairs come ordered by (frame, class), then prediction, then GT (each in input order), in
    blocks of at most :data:`EDGE_CHUNK` pairs.

    Only pairs whose hull centres lie within reach along x are formed: the GTs of each (frame,
    class) are sorted by hull centre x, and a prediction reaches those whose centre is within its
    own half-extent plus the largest GT half-extent of the group (and a margin far above the
    float64 rounding of the sort key), a range found by binary search: the hulls of any other
    pair do not overlap along x, so their bound is 0.
    """
    if len(gt.cls) == 0 or len(det.cls) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    gt_key = gt.frame * 64 + gt.cls
    det_key = det.frame * 64 + det.cls
    gb, db = _hull(gt.boxes), _hull(det.boxes)  # (K, 9): x, y, z, dx, dy, dz, ex, ey, footprint
    d_order = np.argsort(det_key, kind="stable")
    groups, g_group = np.unique(gt_key, return_inverse=True)  # (F,), (G,) group of each GT
    d_group = np.minimum(np.searchsorted(groups, det_key), len(groups) - 1)  # (P,)
    d_in = groups[d_group] == det_key  # the prediction's (frame, class) has GTs
    reach = np.zeros(len(groups))  # (F,) largest GT hull half-extent along x per group
    np.maximum.at(reach, g_group, gb[:, 6])
    # sort key: group rank, then hull centre x, groups spaced wider than any window; pairs
    # across groups that rounding might still let through are dropped below by group
    x0 = min(float(gb[:, 0].min()), float(db[:, 0].min()))
    x1 = max(float(gb[:, 0].max()), float(db[:, 0].max()))
    window = db[:, 6] + reach[d_group] + 1e-3  # (P,) metres
    span = (x1 - x0) + 2 * float(window.max()) + 1.0
    g_sort = g_group * span + (gb[:, 0] - x0)
    g_order = np.argsort(g_sort, kind="stable")
    g_sorted = g_sort[g_order]
    d_centre = d_group * span + (db[:, 0] - x0)
    margin = 1e-12 * np.abs(d_centre) + 1e-6  # ~1e4 times the keys' float64 rounding
    g_lo = np.searchsorted(g_sorted, d_centre - window - margin)  # (P,) first GT in reach
    g_hi = np.searchsorted(g_sorted, d_centre + window + margin, side="right")
    counts = np.where(d_in, g_hi - g_lo, 0)[d_order]  # per prediction in d_order
    g_lo = g_lo[d_order]
    d_hi, d_lo = (
        [db[:, j] + db[:, h] for j, h in ((0, 6), (1, 7))],
        [db[:, j] - db[:, h] for j, h in ((0, 6), (1, 7))],
    )  # per axis (K,): the hull's upper and lower bound
    g_hi_xy, g_lo_xy = (
        [gb[:, j] + gb[:, h] for j, h in ((0, 6), (1, 7))],
        [gb[:, j] - gb[:, h] for j, h in ((0, 6), (1, 7))],
    )
    ends = np.cumsum(counts)
    pred_idx, gt_idx = [], []
    start = 0
    while start < len(d_order):
        # predictions [start, stop) whose pairs fill about one block
        stop = int(np.searchsorted(ends, ends[start] - counts[start] + EDGE_CHUNK, side="right"))
        stop = max(start + 1, stop)
        rows = np.arange(start, stop)
        row = np.repeat(rows, counts[rows])  # (E,) position in d_order of each pair
        first = ends[rows] - counts[rows]  # (R,) each row's first pair, counted over all rows
        offset = np.arange(len(row)) - np.repeat(first - first[0], counts[rows])  # within row
        di, gi = d_order[row], g_order[g_lo[row] + offset]
        # the hulls' overlap along x and y first, from per-box bounds (the same floats as
        # per pair): a pair without both has bound 0 and is dropped below anyway
        over_x = np.minimum(d_hi[0][di], g_hi_xy[0][gi]) - np.maximum(d_lo[0][di], g_lo_xy[0][gi])
        near = (over_x > 0) & (g_group[gi] == d_group[di])
        row, di, gi, over_x = row[near], di[near], gi[near], over_x[near]
        over_y = np.minimum(d_hi[1][di], g_hi_xy[1][gi]) - np.maximum(d_lo[1][di], g_lo_xy[1][gi])
        near = over_y > 0
        row, di, gi, over = row[near], di[near], gi[near], (over_x[near], over_y[near])
        a, b = db[di], gb[gi]  # (E, 9)
        zo = np.minimum(a[:, 2] + a[:, 5] / 2, b[:, 2] + b[:, 5] / 2) - np.maximum(
            a[:, 2] - a[:, 5] / 2, b[:, 2] - b[:, 5] / 2
        )
        area = np.minimum(np.clip(over[0], 0, None) * np.clip(over[1], 0, None), a[:, 8])
        inter = np.minimum(area, b[:, 8]) * np.clip(zo, 0, None)  # (E,) upper bound
        union = a[:, 8] * a[:, 5] + b[:, 8] * b[:, 5] - inter
        bound = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
        keep = (bound >= thr[det.cls[di]] * (1 - 1e-6)) & (zo >= 0)
        row, di, gi = row[keep], di[keep], gi[keep]
        by_input = np.lexsort((gi, row))  # each prediction's GTs in input order
        pred_idx.append(di[by_input])
        gt_idx.append(gi[by_input])
        start = stop
    return cat(pred_idx, np.int64), cat(gt_idx, np.int64)


def _hull(boxes: np.ndarray) -> np.ndarray:
    """``(K, 7)`` boxes -> ``(K, 9)`` float64: the box, half-extents of its axis-aligned hull
    (slightly inflated) and its footprint area."""
    b = boxes.astype(np.float64)
    c, s = np.abs(np.cos(b[:, 6])), np.abs(np.sin(b[:, 6]))
    ex = (c * b[:, 3] + s * b[:, 4]) / 2 * (1 + 1e-9) + 1e-9
    ey = (s * b[:, 3] + c * b[:, 4]) / 2 * (1 + 1e-9) + 1e-9
    return np.concatenate([b[:, :6], ex[:, None], ey[:, None], (b[:, 3] * b[:, 4])[:, None]], 1)


def _waymo_iou(det_boxes: np.ndarray, gt_boxes: np.ndarray) -> np.ndarray:
    """Official 3D IoU of aligned pairs: float64 geometry, 0 for degenerate dims, as float32."""
    if len(det_boxes) == 0:
        return np.zeros(0, dtype=np.float32)
    iou = boxes_aligned_iou3d(
        torch.from_numpy(det_boxes.astype(np.float64)),
        torch.from_numpy(gt_boxes.astype(np.float64)),
    ).numpy()
    dims = np.concatenate([det_boxes[:, 3:6], gt_boxes[:, 3:6]], axis=1).astype(np.float64)
    valid = ((dims > MIN_BOX_DIM) & (dims < MAX_BOX_DIM)).all(axis=1)
    return np.where(valid, iou, 0.0).astype(np.float32)


def _normalize_angle(rad: np.ndarray) -> np.ndarray:
    """Official ``NormalizeAngle`` (wrap to [-pi, pi) via ``PositiveModulo``), float64."""
    x = np.asarray(rad, dtype=np.float64) + np.pi
    y = 2 * np.pi
    modulo = x - np.trunc(x * (1 / y)) * y
    shifted = y + modulo
    wrapped = np.where(modulo >= 0, modulo, np.where(shifted >= y, 0.0, shifted))
    return wrapped - np.pi


def waymo_heading_accuracy(pred_heading, gt_heading) -> np.ndarray:
    """Official heading accuracy ``clamp(1 - |dtheta| / pi, 0, 1)`` with dtheta folded to [0, pi].

    Args:
        pred_heading: ``(K,)`` radians.
        gt_heading: ``(K,)`` radians.

    Returns:
        ``(K,)`` float32 in [0, 1].
    """
    pd = _normalize_angle(pred_heading).astype(np.float32)
    gt = _normalize_angle(gt_heading).astype(np.float32)
    diff = np.abs(pd - gt)  # float32
    diff = np.where(diff > np.pi, (2.0 * np.pi - diff.astype(np.float64)).astype(np.float32), diff)
    return np.clip(1.0 - diff.astype(np.float64) / np.pi, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Matching and accumulation
# --------------------------------------------------------------------------------------------
class _Accumulator:
    """Per-class, per-cutoff sums: TP, matched level-1 GTs and heading accuracy (range adds)."""

    def __init__(self, num_classes: int, num_cutoffs: int):
        self.shape = (num_classes, num_cutoffs + 1)
        self.tp = np.zeros(self.shape, np.int64)
        self.tp_l1 = np.zeros(self.shape, np.int64)  # matched GTs of level 1
        self.ha = np.zeros(self.shape, np.float64)

    def add(self, cls, hi, tp, tp_l1, ha, lo=0):
        """Add to cutoffs ``lo <= k < hi`` (all arguments broadcast arrays or scalars)."""
        cls, hi, lo, tp, tp_l1, ha = np.broadcast_arrays(cls, hi, lo, tp, tp_l1, ha)
        for arr, val in ((self.tp, tp), (self.tp_l1, tp_l1), (self.ha, ha)):
            np.add.at(arr, (cls, lo), val)
            np.add.at(arr, (cls, hi), np.negative(val))

    def totals(self):
        cut = self.shape[1] - 1
        return (
            np.cumsum(self.tp, axis=1)[:, :cut],
            np.cumsum(self.tp_l1, axis=1)[:, :cut],
            np.cumsum(self.ha, axis=1)[:, :cut],
        )


def _match_hungarian(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximum-weight matching; returns (rows, cols) of the pairs with positive weight."""
    rows, cols = linear_sum_assignment(weights, maximize=True)
    ok = weights[rows, cols] > 0
    return rows[ok], cols[ok]


def _match_score_first(weights: np.ndarray, order: np.ndarray, ious: np.ndarray):
    """Greedy COCO-style matching: predictions by descending score take the unmatched GT with the
    highest IoU (first index on ties) among those they can match. (The official
    ``ScoreFirstMatcher`` of 1.6.7 compares IoUs at the wrong indices; see docs/evaluation.md.)"""
    taken = np.zeros(weights.shape[1], dtype=bool)
    rows, cols = [], []
    for r in order:
        cand = np.where((weights[r] > 0) & ~taken, ious[r], -1.0)
        c = int(np.argmax(cand))
        if cand[c] >= 0:
            taken[c] = True
            rows.append(r)
            cols.append(c)
    return np.array(rows, dtype=np.int64), np.array(cols, dtype=np.int64)


def _accumulate(gt: Objects, det: Objects, thr: np.ndarray, cutoffs: np.ndarray, matcher: str):
    """Per class and cutoff: TP, TP matched to level-1 GT, sum of heading accuracy.

    ``thr``: ``(C,)`` float32 IoU threshold per class index; ``cutoffs``: ``(K,)`` float32.
    """
    acc = _Accumulator(len(thr), len(cutoffs))
    n_pred = np.searchsorted(cutoffs, det.score, side="right")  # pred present for cutoff k < n
    pi, gi = _candidate_edges(gt, det, thr)
    iou = _waymo_iou(det.boxes[pi], gt.boxes[gi])
    ok = iou >= thr[det.cls[pi]]
    pi, gi, iou = pi[ok], gi[ok], iou[ok]
    # std::round(float iou * kMaxIoU): float32 product, halves rounded away from zero
    weight = np.floor(iou * KMAX_IOU + np.float32(0.5)).astype(np.int64)
    ha = waymo_heading_accuracy(det.boxes[pi, 6], gt.boxes[gi, 6])
    if len(pi) == 0:
        return acc
    # connected components of the bipartite "can match" graph (nodes: preds, then GTs)
    n_det = len(det.score)
    n_nodes = n_det + len(gt.cls)
    graph = coo_matrix((np.ones(len(pi)), (pi, n_det + gi)), shape=(n_nodes, n_nodes))
    _, label = connected_components(graph, directed=False)
    comp = label[pi]  # component of each edge
    is_l1 = (gt.level[gi] == 1).astype(np.int64)
    # trivial components: exactly one edge, one prediction, one GT
    edges_per_comp = np.bincount(comp, minlength=label.max() + 1)
    single = edges_per_comp[comp] == 1
    s = np.nonzero(single)[0]
    acc.add(det.cls[pi[s]], n_pred[pi[s]], 1, is_l1[s], ha[s].astype(np.float64))
    multi = np.nonzero(~single)[0]
    if len(multi) == 0:
        return acc
    order = multi[np.argsort(comp[multi], kind="stable")]
    starts = np.flatnonzero(np.r_[True, np.diff(comp[order]) != 0])
    g_sorted = gi[order]
    one_gt = np.minimum.reduceat(g_sorted, starts) == np.maximum.reduceat(g_sorted, starts)
    sizes = np.diff(np.r_[starts, len(order)])
    rows = []  # per subset matching: (cls, hi, tp, tp_l1, ha, lo)
    if one_gt.any():
        edges = order[np.repeat(one_gt, sizes)]
        if matcher == "hungarian":
            rows.append(_one_gt_components(edges, comp, pi, weight, ha, is_l1, det.cls, n_pred))
        else:
            rows.append(_one_gt_greedy(edges, comp, pi, weight, ha, is_l1, det, n_pred))
    for first, size in zip(starts[~one_gt], sizes[~one_gt]):
        edges = order[first : first + size]
        edge_data = (pi[edges], gi[edges], weight[edges], iou[edges], ha[edges], is_l1[edges])
        rows.append(_solve_component(det, edge_data, n_pred, matcher))
    cls, hi, tp, tp_l1, hsum, lo = (np.concatenate(col) for col in zip(*rows))
    acc.add(cls, hi, tp, tp_l1, hsum, lo)
    return acc


def _one_gt_components(edges, comp, pi, weight, ha, is_l1, det_cls, n_pred):
    """The matchings of every component whose edges share one GT, at all their subsets at once.

    A subset keeps the predictions of ``n_pred >= hi``; a maximum-weight matching to a single GT
    takes the present prediction of the highest weight, the lowest prediction index among equal
    weights (as ``linear_sum_assignment`` breaks the tie, which :func:`_solve_component` uses).
    The edges are ordered by component, ``n_pred`` descending and prediction index; a running
    best over each component's edges, taken at the last edge of each ``n_pred`` value, is the
    matching of that subset. Returns the rows :func:`_solve_component` would give.
    """
    p = pi[edges]
    n = n_pred[p]
    c = comp[edges]
    order = np.lexsort((p, -n, c))
    edges, p, n, c = edges[order], p[order], n[order], c[order]
    w = weight[edges]
    first = np.r_[True, c[1:] != c[:-1]]
    starts = np.flatnonzero(first)
    pos = np.arange(len(c)) - np.repeat(starts, np.diff(np.r_[starts, len(c)]))
    best = np.arange(len(c))  # per edge: the best edge among its component's edges so far
    by_pos = np.argsort(pos, kind="stable")
    bounds = np.searchsorted(pos[by_pos], np.arange(int(pos.max()) + 2))  # edges at each pos
    for j in range(1, int(pos.max()) + 1):
        at = by_pos[bounds[j] : bounds[j + 1]]  # the j-th edge of every component that has one
        prev = best[at - 1]
        take = (w[at] > w[prev]) | ((w[at] == w[prev]) & (p[at] < p[prev]))
        best[at] = np.where(take, at, prev)
    last = np.r_[(c[1:] != c[:-1]) | (n[1:] != n[:-1]), True]  # last edge of each subset
    ends = np.flatnonzero(last)
    hi = n[ends]
    next_in_comp = np.r_[c[ends[1:]] == c[ends[:-1]], False]
    lo = np.where(next_in_comp, np.r_[hi[1:], 0], 0)
    keep = hi > 0
    chosen = edges[best[ends[keep]]]
    matched = (weight[chosen] > 0).astype(np.int64)
    return (det_cls[p[ends[keep]]], hi[keep], matched, is_l1[chosen] * matched,
            ha[chosen].astype(np.float64) * matched, lo[keep])  # fmt: skip


def _one_gt_greedy(edges, comp, pi, weight, ha, is_l1, det: Objects, n_pred):
    """The greedy (score-first) matchings of every component whose edges share one GT: the
    prediction of the highest score (lowest index on ties) among those of positive weight takes
    the GT at every cutoff that keeps it, as :func:`_match_score_first` in
    :func:`_solve_component`. Returns the same rows."""
    edges = edges[weight[edges] > 0]
    p, c = pi[edges], comp[edges]
    order = np.lexsort((p, -det.score[p], c))
    edges, p, c = edges[order], p[order], c[order]
    first = np.r_[True, c[1:] != c[:-1]]
    chosen, p = edges[first], p[first]
    k = len(chosen)
    return (det.cls[p], n_pred[p], np.ones(k, np.int64), is_l1[chosen],
            ha[chosen].astype(np.float64), np.zeros(k, np.int64))  # fmt: skip


def _solve_component(det: Objects, edge_data, n_pred, matcher: str):
    """Match one connected component at every distinct prediction subset.

    ``edge_data``: per edge (prediction index, GT index, integer weight, float32 IoU, heading
    accuracy, GT-is-level-1); ``n_pred``: per prediction, the number of cutoffs keeping it.
    Returns per subset matching ``(cls, hi, tp, tp_l1, ha, lo)`` arrays: ``tp`` matches, of them
    ``tp_l1`` to level-1 GTs, with heading accuracy summing to ``ha``, at cutoffs ``lo <= k <
    hi``.
    """
    pe, ge, we, ioue, hae, l1e = edge_data
    preds, p_local = np.unique(pe, return_inverse=True)
    gts, g_local = np.unique(ge, return_inverse=True)
    cls = det.cls[preds[0]]
    w = np.zeros((len(preds), len(gts)), np.int64)
    w[p_local, g_local] = we
    iou = np.zeros(w.shape, np.float32)
    iou[p_local, g_local] = ioue
    ha = np.zeros(w.shape, np.float64)
    ha[p_local, g_local] = hae
    l1 = np.zeros(w.shape, np.int64)
    l1[p_local, g_local] = l1e
    n = n_pred[preds]
    if matcher == "score_first":
        # greedy matching of a score-sorted prefix is the prefix of the full greedy matching
        by_score = np.lexsort((preds, -det.score[preds]))
        rows, cols = _match_score_first(w, by_score, iou)
        k = len(rows)
        return (np.full(k, cls), n[rows], np.ones(k, np.int64), l1[rows, cols],
                ha[rows, cols], np.zeros(k, np.int64))  # fmt: skip
    out = []
    levels = np.unique(n)[::-1]  # distinct subsets, largest cutoff bound first
    for j, hi in enumerate(levels):
        lo = levels[j + 1] if j + 1 < len(levels) else 0
        if hi == 0:
            break
        present = np.nonzero(n >= hi)[0]
        rows, cols = _match_hungarian(w[present])
        out.append((cls, hi, len(rows), l1[present[rows], cols].sum(),
                    ha[present[rows], cols].sum(), lo))  # fmt: skip
    if not out:
        return tuple(np.zeros(0, np.int64) for _ in range(4)) + (
            np.zeros(0, np.float64),
            np.zeros(0, np.int64),
        )
    return tuple(np.array(col) for col in zip(*out))


# --------------------------------------------------------------------------------------------
# Precision / recall / AP
# --------------------------------------------------------------------------------------------
def waymo_average_precision(precisions, recalls, max_recall_delta: float = 0.05) -> float:
    """Official ``ComputeMeanAveragePrecision`` (float32 arithmetic, same order of operations).

    Args:
        precisions: ``(K,)`` precision per score cutoff (with the ``P = 1 at R = 0`` rule applied).
        recalls: ``(K,)`` recall per score cutoff.
        max_recall_delta: recall step of the interpolation (official 0.05).

    Returns:
        AP in [0, 1] as a Python float (holding a float32 value).
    """
    p = np.asarray(precisions, dtype=np.float32).reshape(-1)
    r = np.asarray(recalls, dtype=np.float32).reshape(-1)
    if p.shape != r.shape:
        raise ValueError(f"precisions {p.shape} and recalls {r.shape} must have the same shape")
    if p.size == 0:
        return 0.0
    best: dict[float, np.float32] = {0.0: np.float32(1.0)}
    for pi, ri in zip(p.tolist(), r.tolist()):
        best[ri] = max(best.get(ri, np.float32(0.0)), np.float32(pi))
    delta = np.float32(max_recall_delta)
    step_limit = np.float32(delta + np.float32(1e-6))
    last = np.float32(min(best))
    max_p = np.float32(0.0)
    curve: list[tuple[np.float32, np.float32]] = []  # (precision, recall), recall descending
    for rk in sorted(best, reverse=True):
        rk32 = np.float32(rk)
        while np.float32(last - rk32) > step_limit:
            last = np.float32(last - delta)
            curve.append((max_p, last))
        max_p = max(best[rk], max_p)
        curve.append((max_p, rk32))
        last = rk32
    if len(curve) < 2:  # only R = 0: the official integral is empty
        return 0.0
    curve[-1] = (curve[-2][0], curve[-1][1])  # neutralise the artificial (P = 1, R = 0) point
    ap = np.float32(0.0)
    for (p0, r0), (p1, r1) in zip(curve[:-1], curve[1:]):
        ap = np.float32(float(ap) + 0.5 * float(np.float32(r0 - r1)) * float(np.float32(p0 + p1)))
    return float(ap)


def _precision_recall(tp, fp, fn, sum_ha):
    """Official ``ToDetectionMetrics``: float32 P, R, P_heading per cutoff."""
    tp32 = tp.astype(np.float32)
    tp_fp = tp + fp
    tp_fn = tp + fn
    with np.errstate(divide="ignore", invalid="ignore"):
        precision = np.where(tp_fp > 0, tp32 / tp_fp.astype(np.float32), np.float32(0))
        precision_ha = np.where(
            tp_fp > 0, sum_ha.astype(np.float32) / tp_fp.astype(np.float32), np.float32(0)
        )
        recall = np.where(tp_fn > 0, tp32 / tp_fn.astype(np.float32), np.float32(0))
    precision = np.where(recall == 0, np.float32(1), precision).astype(np.float32)
    precision_ha = np.where(recall == 0, np.float32(1), precision_ha).astype(np.float32)
    return precision, recall.astype(np.float32), precision_ha


def compute_waymo_curves(
    gt_annos: Sequence[dict],
    det_annos: Sequence[dict],
    class_names: Sequence[str],
    matcher: str = "hungarian",
    iou_thresholds: Mapping[str, float] | None = None,
) -> dict[str, dict[str, np.ndarray | float]]:
    """Per-cutoff counts, PR curves and AP/APH of every class and difficulty level.

    Args:
        gt_annos: per frame, OpenPCDet GT annos: ``name`` (M,), ``gt_boxes_lidar`` (M, 7+),
            ``num_points_in_gt`` (M,), ``difficulty`` (M,) in {0, 1, 2}; optional ``frame_id``.
        det_annos: per frame (aligned with ``gt_annos``): ``name`` (K,), ``boxes_lidar`` (K, 7+),
            ``score`` (K,); optional ``frame_id`` (checked against the GT's when both exist).
        class_names: evaluated classes, a subset of Vehicle, Pedestrian, Sign, Cyclist.
        matcher: ``'hungarian'`` (official) or ``'score_first'`` (greedy, COCO-style; for
            comparison only).
        iou_thresholds: per-class IoU thresholds replacing the official ones
            (:data:`WAYMO_IOU_THRESHOLDS`) for the classes it names, each in ``(0, 1]``: for
            diagnosis (e.g. Vehicle AP at 0.5 / 0.6 / 0.7), not for reporting.

    Returns:
        ``{'<Class>/L1': curve, '<Class>/L2': curve, ...}`` where each curve holds
        ``score_cutoffs`` (101,) float32, ``tp``, ``fp``, ``fn`` (101,) int64, ``sum_ha`` (101,)
        float64, ``precision``, ``recall``, ``precision_ha`` (101,) float32, and ``ap``, ``aph``
        (floats). ``precision`` already has the official ``P = 1 where R = 0`` rule applied.
    """
    if isinstance(class_names, str):
        raise TypeError(
            f"class_names must be a list of class names, got the string {class_names!r} "
            f"(write [{class_names!r}])"
        )
    class_names = list(class_names)
    unknown = [c for c in class_names if c not in WAYMO_IOU_THRESHOLDS]
    if unknown or not class_names:
        raise ValueError(
            f"class_names: {unknown or class_names} not evaluable; "
            f"expected a non-empty subset of {list(WAYMO_IOU_THRESHOLDS)}"
        )
    if len(set(class_names)) != len(class_names):
        raise ValueError(f"class_names: duplicates in {class_names}")
    if matcher not in MATCHERS:
        raise ValueError(f"matcher: expected one of {MATCHERS}, got {matcher!r}")
    check_frames(gt_annos, det_annos)
    gt = collect_gt(gt_annos, class_names)
    det = collect_det(det_annos, class_names)
    cutoffs = WAYMO_SCORE_CUTOFFS
    thresholds = dict(WAYMO_IOU_THRESHOLDS)
    for name, value in (iou_thresholds or {}).items():
        if name not in class_names or not 0.0 < float(value) <= 1.0:
            raise ValueError(
                f"iou_thresholds: {name!r}: {value!r}; expected a class of {class_names} and a "
                "threshold in (0, 1]"
            )
        thresholds[name] = float(value)
    thr = np.array([thresholds[c] for c in class_names], dtype=np.float32)
    acc = _accumulate(gt, det, thr, cutoffs, matcher)
    tp, tp_l1, sum_ha = acc.totals()  # (C, K)
    n_pred = np.searchsorted(cutoffs, det.score, side="right")
    curves = {}
    for c, name in enumerate(class_names):
        # predictions of class c present at cutoff k: n_pred > k
        hist = np.bincount(n_pred[det.cls == c], minlength=len(cutoffs) + 1)
        present = hist[::-1].cumsum()[::-1][1:]  # (K,)
        levels_c = gt.level[gt.cls == c]
        for level in LEVELS:
            num_gt = int((levels_c <= level).sum())
            matched = tp_l1[c] if level == 1 else tp[c]
            tp_c, fp_c, fn_c = tp[c].copy(), present - tp[c], num_gt - matched
            precision, recall, precision_ha = _precision_recall(tp_c, fp_c, fn_c, sum_ha[c])
            curves[f"{name}/L{level}"] = {
                "score_cutoffs": cutoffs.copy(),
                "tp": tp_c,
                "fp": fp_c,
                "fn": fn_c,
                "sum_ha": sum_ha[c].copy(),
                "precision": precision,
                "recall": recall,
                "precision_ha": precision_ha,
                "ap": waymo_average_precision(precision, recall),
                "aph": waymo_average_precision(precision_ha, recall),
            }
    return curves


def summarize_waymo_curves(curves: dict, class_names: Sequence[str]) -> dict[str, float]:
    """Flat metric dict from :func:`compute_waymo_curves`: per class AP/APH and the class means."""
    out: dict[str, float] = {}
    for level in LEVELS:
        for name in class_names:
            curve = curves[f"{name}/L{level}"]
            out[f"{name}/L{level}/AP"] = min(1.0, max(0.0, float(curve["ap"])))
            out[f"{name}/L{level}/APH"] = min(1.0, max(0.0, float(curve["aph"])))
    for level in LEVELS:
        out[f"L{level}/mAP"] = float(np.mean([out[f"{n}/L{level}/AP"] for n in class_names]))
        out[f"L{level}/mAPH"] = float(np.mean([out[f"{n}/L{level}/APH"] for n in class_names]))
    return out


def waymo_evaluate(
    gt_annos: Sequence[dict],
    det_annos: Sequence[dict],
    class_names: Sequence[str],
    matcher: str = "hungarian",
) -> dict[str, float]:
    """Waymo L1/L2 AP and APH, identical to the official ``waymo-open-dataset`` 1.6.7 metric.

    Args:
        gt_annos, det_annos, class_names, matcher: as :func:`compute_waymo_curves` (whose
            ``iou_thresholds`` this takes as Waymo's: Vehicle 0.7, Pedestrian and Cyclist 0.5;
            other thresholds: :func:`compute_waymo_curves` and :func:`summarize_waymo_curves`).

    Returns:
        ``{'<Class>/L1/AP', '<Class>/L1/APH', '<Class>/L2/AP', '<Class>/L2/APH', ...,
        'L1/mAP', 'L1/mAPH', 'L2/mAP', 'L2/mAPH'}``, values in [0, 1]; the means are over
        ``class_names``. Use :func:`compute_waymo_curves` for per-cutoff PR curves and counts.
    """
    curves = compute_waymo_curves(gt_annos, det_annos, class_names, matcher=matcher)
    return summarize_waymo_curves(curves, class_names)
