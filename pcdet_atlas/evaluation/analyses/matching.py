"""Matching each recorded target box of one variant against that frame's predictions: the one
pass every attack analysis reads (docs/evaluation.md, "Attack metrics").

Inputs are the two per-frame lists every evaluation run produces, aligned by index:

* ``det_annos``: OpenPCDet detection annos, one dict per frame with ``name`` (K,) str,
  ``boxes_lidar`` (K, 7|9) ``[x, y, z, dx, dy, dz, heading(, vx, vy)]`` in metres / radians (vehicle
  frame, z = box centre) and ``score`` (K,) in [0, 1]; ``frame_id`` is used when present.
* ``attack_infos``: the attack metadata dict of each frame (key ``attack`` of an
  ``AtlasWaymoDataset`` sample; schema in ``docs/evaluation.md``): ``variant``, ``family``,
  ``spoofed``, ``target_box`` (7,) or None, ``target_is_shadow``, ``lifecycle_k``, and on a
  frame with a target its run, ``sequence_name`` and ``run_id`` ...
  When ``attack_infos`` is None, each det anno must carry its metadata under ``anno['attack']``.

:func:`match_targets` finds for every recorded target box the best 3D IoU of the predictions (of
the target's class, above an optional score threshold) and the best score among the matching
ones; the ASR, the confidence statistics and the lifecycle curve are all read off that record
(:class:`TargetMatches`), so they always agree with each other.

Definitions (paper §"Evaluation Metric"):

* **Target**: a frame whose ``target_box`` is not None. Attacked targets have ``spoofed`` True;
  *shadow* targets (``target_is_shadow`` True: the frame before a run and the frames after it) are
  only used by the lifecycle analysis and never enter the ASR.
* **Detected**: some prediction of the target's class (default ``'Vehicle'``; the paper's box
  ``g = [x, y, z, l, w, h, θ, c]`` includes the class) has 3D IoU >= 0.7 with the target box.
* **Injection** succeeds when the phantom is detected; **removal** succeeds when the target is not.
* **Lenient** (MVP, Zhang et al. USENIX Sec'24): "detected" means IoU > 0 instead, so a lenient
  injection success is any overlapping prediction and a lenient removal success needs *no*
  overlapping prediction at all. (Lenient injection ASR >= ASR; lenient removal ASR <= ASR.)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d

__all__ = [
    "ASR_IOU_THRESHOLD",
    "DEFAULT_TARGET_CLASS",
    "SCORING_KEYS",
    "AttackMetricError",
    "IouFn",
    "TargetMatches",
    "clean_matched_scores",
    "match_targets",
]

ASR_IOU_THRESHOLD = 0.7
DEFAULT_TARGET_CLASS = "Vehicle"
IouFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
#: Metadata keys by which the attack class tells the evaluation how to score it.
SCORING_KEYS = ("success_if_detected", "confidence", "rank_group")


class AttackMetricError(ValueError):
    """Predictions or attack metadata that cannot be evaluated; the message names frame and key."""


@dataclass
class TargetMatches:
    """One row per recorded target box (attacked and shadow), in frame order.

    Arrays of length T: ``frame_index`` (int, index into the input lists), ``frame_id`` (str, ''
    if unknown), ``sequence`` (str, the metadata's ``sequence_name``), ``run_id`` (int, numbered
    per sequence), ``lifecycle_k`` (int), ``is_shadow`` (bool), ``target_box`` (T, 7)
    float64, ``max_iou`` (float64, best 3D IoU of an eligible prediction, 0 if none),
    ``matched_score`` (float64, best score among eligible predictions with IoU >= ``iou_threshold``,
    NaN if none) and ``overlap_score`` (same for IoU > 0). ``num_spoofed``: the spoofed frames of
    the input, ``num_untargeted``: those that recorded no target (a phantom of which no point
    survived the raycast, a removal target lost or not fired); neither counts in the ASR.
    """

    variant: str
    family: str
    success_if_detected: bool
    confidence: str | None
    iou_threshold: float
    score_threshold: float | None
    target_class: str | None
    num_frames: int
    num_spoofed: int
    num_untargeted: int
    frame_index: np.ndarray
    frame_id: np.ndarray
    sequence: np.ndarray
    run_id: np.ndarray
    lifecycle_k: np.ndarray
    is_shadow: np.ndarray
    target_box: np.ndarray
    max_iou: np.ndarray
    matched_score: np.ndarray
    overlap_score: np.ndarray
    _ROW_FIELDS: ClassVar[tuple[str, ...]] = (
        "frame_index",
        "frame_id",
        "sequence",
        "run_id",
        "lifecycle_k",
        "is_shadow",
        "target_box",
        "max_iou",
        "matched_score",
        "overlap_score",
    )

    def __len__(self) -> int:
        return int(self.frame_index.shape[0])

    @property
    def detected(self) -> np.ndarray:
        """(T,) bool: some prediction has IoU >= ``iou_threshold``."""
        return self.max_iou >= self.iou_threshold

    @property
    def detected_lenient(self) -> np.ndarray:
        """(T,) bool: some prediction overlaps the target at all (IoU > 0)."""
        return self.max_iou > 0.0

    @property
    def run(self) -> np.ndarray:
        """(T,) int64: one id per spoof run, a run being ``(sequence, run_id)`` (``run_id`` is
        numbered per sequence)."""
        seq = np.unique(self.sequence, return_inverse=True)[1].reshape(-1)
        pairs = np.stack([seq, self.run_id], axis=1)  # (T, 2)
        return np.unique(pairs, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)

    @property
    def success(self) -> np.ndarray:
        """(T,) bool attack success per target (injection: detected; removal: not detected)."""
        return self.detected if self.success_if_detected else ~self.detected

    @property
    def success_lenient(self) -> np.ndarray:
        return self.detected_lenient if self.success_if_detected else ~self.detected_lenient

    def select(self, mask: np.ndarray) -> TargetMatches:
        """The rows where ``mask`` (T,) bool is True."""
        rows = {name: getattr(self, name)[mask] for name in self._ROW_FIELDS}
        return TargetMatches(
            variant=self.variant,
            family=self.family,
            success_if_detected=self.success_if_detected,
            confidence=self.confidence,
            iou_threshold=self.iou_threshold,
            score_threshold=self.score_threshold,
            target_class=self.target_class,
            num_frames=self.num_frames,
            num_spoofed=self.num_spoofed,
            num_untargeted=self.num_untargeted,
            **rows,
        )

    def attacked(self) -> TargetMatches:
        """Only the attacked (non-shadow) targets: the ones the ASR counts."""
        return self.select(~self.is_shadow)


def _frame_where(index: int, anno: Mapping, info: Mapping) -> str:
    fid = anno.get("frame_id", info.get("frame_id"))
    return f"frame {index}" + (f" ({fid})" if fid is not None else "")


def _check_predictions(anno: Mapping, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> names (K,) str, boxes (K, 7) float64, scores (K,) float64, checked."""
    for key in ("name", "boxes_lidar", "score"):
        if key not in anno:
            raise AttackMetricError(f"{where}: det anno lacks key '{key}'")
    names = np.asarray(anno["name"]).reshape(-1).astype(str)
    boxes = np.asarray(anno["boxes_lidar"], dtype=np.float64)
    scores = np.asarray(anno["score"], dtype=np.float64).reshape(-1)
    if boxes.size == 0:
        boxes = boxes.reshape(0, 7)
    if boxes.ndim != 2 or boxes.shape[1] not in (7, 9):
        raise AttackMetricError(
            f"{where}: det anno 'boxes_lidar' must be (K, 7) or (K, 9), got {boxes.shape}"
        )
    if not (len(names) == len(boxes) == len(scores)):
        raise AttackMetricError(
            f"{where}: det anno lengths differ: name {len(names)}, boxes_lidar {len(boxes)}, "
            f"score {len(scores)}"
        )
    if not np.all(np.isfinite(boxes[:, :7])) or not np.all(np.isfinite(scores)):
        raise AttackMetricError(f"{where}: det anno has non-finite 'boxes_lidar' or 'score'")
    if np.any((scores < 0) | (scores > 1)):  # thresholds and bins are on probabilities
        raise AttackMetricError(
            f"{where}: det anno 'score' must be in [0, 1] (probabilities, not logits), got "
            f"{scores[(scores < 0) | (scores > 1)][:5].tolist()}"
        )
    return names, boxes[:, :7], scores


def _check_attack_info(info: Mapping, where: str) -> np.ndarray | None:
    """Validate one frame's attack metadata; -> its target box (7,) float64 or None."""
    for key in ("variant", "family", "spoofed", "target_box", "target_is_shadow", "lifecycle_k"):
        if key not in info:
            raise AttackMetricError(f"{where}: attack metadata lacks key '{key}'")
    box = info["target_box"]
    spoofed, shadow = bool(info["spoofed"]), bool(info["target_is_shadow"])
    if spoofed and shadow:
        raise AttackMetricError(f"{where}: 'spoofed' and 'target_is_shadow' are both True")
    if box is None:
        if shadow:
            raise AttackMetricError(f"{where}: 'target_is_shadow' is True but 'target_box' is None")
        return None
    box = np.asarray(box, dtype=np.float64).reshape(-1)
    if box.shape[0] not in (7, 9) or not np.all(np.isfinite(box)):
        raise AttackMetricError(
            f"{where}: 'target_box' must be 7 (or 9) finite values, got {info['target_box']!r}"
        )
    if not spoofed and not shadow:
        raise AttackMetricError(
            f"{where}: 'target_box' is set on a frame that is neither spoofed nor a shadow frame"
        )
    if np.any(box[3:6] <= 0):
        raise AttackMetricError(f"{where}: 'target_box' has non-positive size {box[3:6]}")
    return box[:7]


def _check_run(info: Mapping, where: str) -> tuple[str, int]:
    """-> the ``(sequence_name, run_id)`` of a frame that records a target: its spoof run, the
    cluster of the ASR's interval, which a frame without it would silently merge with others."""
    sequence, run_id = info.get("sequence_name"), info.get("run_id")
    if not sequence:
        raise AttackMetricError(
            f"{where}: a target frame needs its 'sequence_name' (a run is (sequence_name, "
            f"run_id)), got {sequence!r}"
        )
    if run_id is None or int(run_id) < 0:
        raise AttackMetricError(f"{where}: a target frame needs a 'run_id' >= 0, got {run_id!r}")
    return str(sequence), int(run_id)


class _PairBatch:
    """Candidate (target, prediction) pairs gathered over many frames, scored in one IoU call."""

    def __init__(self) -> None:
        self.targets: list[np.ndarray] = []  # (7,) each
        self.pair_target: list[np.ndarray] = []  # (P_i,) target index per pair
        self.pair_boxes: list[np.ndarray] = []  # (P_i, 7)
        self.pair_scores: list[np.ndarray] = []  # (P_i,)

    def add(self, target: np.ndarray, boxes: np.ndarray, scores: np.ndarray) -> None:
        """Register ``target`` (7,) against the eligible predictions ``boxes`` (K, 7) / ``scores``.

        Keeps only the pairs that can overlap: boxes whose BEV circumcircles are apart have
        (BEV and 3D) IoU exactly 0, so dropping them changes no result.
        """
        idx = len(self.targets)
        self.targets.append(target)
        if len(boxes) == 0:
            return
        radius_t = 0.5 * math.hypot(target[3], target[4])
        radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
        dist = np.hypot(boxes[:, 0] - target[0], boxes[:, 1] - target[1])
        near = dist <= radius + radius_t + 1e-6
        if np.any(near):
            self.pair_target.append(np.full(int(near.sum()), idx, dtype=np.int64))
            self.pair_boxes.append(boxes[near])
            self.pair_scores.append(scores[near])

    def evaluate(
        self, iou_threshold: float, iou_fn: IouFn
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """-> per target (T,): best IoU (0 if no overlap), best score at IoU >= ``iou_threshold``
        and best score at IoU > 0 (NaN where there is none)."""
        num = len(self.targets)
        max_iou = np.zeros(num)
        matched = np.full(num, -np.inf)
        overlap = np.full(num, -np.inf)
        if self.pair_target:
            seg = np.concatenate(self.pair_target)
            boxes_b = np.concatenate(self.pair_boxes)
            scores = np.concatenate(self.pair_scores)
            boxes_a = np.stack(self.targets)[seg]
            iou = iou_fn(
                torch.as_tensor(boxes_a, dtype=torch.float64),
                torch.as_tensor(boxes_b, dtype=torch.float64),
            )
            iou = np.asarray(torch.as_tensor(iou).detach().cpu(), dtype=np.float64).reshape(-1)
            np.maximum.at(max_iou, seg, iou)
            hit, over = iou >= iou_threshold, iou > 0.0
            np.maximum.at(matched, seg[hit], scores[hit])
            np.maximum.at(overlap, seg[over], scores[over])
        matched[np.isneginf(matched)] = np.nan
        overlap[np.isneginf(overlap)] = np.nan
        return max_iou, matched, overlap


def _eligible(
    names: np.ndarray,
    scores: np.ndarray,
    target_class: str | None,
    score_threshold: float | None,
) -> np.ndarray:
    """(K,) bool: the predictions that may match a target (class and score rules)."""
    keep = np.ones(len(names), dtype=bool)
    if target_class is not None:
        keep &= names == target_class
    if score_threshold is not None:
        keep &= scores >= score_threshold
    return keep


def match_targets(
    det_annos: Sequence[Mapping],
    attack_infos: Sequence[Mapping] | None = None,
    *,
    iou_threshold: float = ASR_IOU_THRESHOLD,
    score_threshold: float | None = None,
    target_class: str | None = DEFAULT_TARGET_CLASS,
    success_if_detected: bool | None = None,
    iou_fn: IouFn | None = None,
) -> TargetMatches:
    """Match every recorded target box of one variant against that frame's predictions.

    Args:
        det_annos: per-frame OpenPCDet detection annos (see module doc).
        attack_infos: per-frame attack metadata aligned with ``det_annos``; None: use
            ``anno['attack']``.
        iou_threshold: 3D IoU at which a prediction counts as a detection of the target (0.7).
        score_threshold: if set, only predictions with ``score >= score_threshold`` count (models
            deployed with a score cut-off); None (default) = every prediction, as in the paper.
        target_class: only predictions with this ``name`` count (the targets are Vehicles and the
            paper's target box carries the class); None = class-agnostic.
        success_if_detected: whether a detected target is a success; default the metadata's
            ``success_if_detected`` (the attack class's ``SUCCESS_IF_DETECTED``).
        iou_fn: row-aligned torch IoU ``(P, 7), (P, 7) -> (P,)``; default the exact
            :func:`pcdet_atlas.ops.iou3d_nms.boxes_aligned_iou3d`, called once for all the
            (target, prediction) pairs that can overlap.

    Raises:
        AttackMetricError: misaligned inputs, missing keys, bad boxes, several variants,
            families or scoring rules mixed in one call, a target without a success rule, or a
            target frame without its run (``sequence_name`` and a ``run_id`` >= 0).
    """
    if attack_infos is None:
        attack_infos = []
        for i, anno in enumerate(det_annos):
            if "attack" not in anno:
                raise AttackMetricError(
                    f"frame {i}: attack_infos not given and det anno has no 'attack' key"
                )
            attack_infos.append(anno["attack"])
    if len(det_annos) != len(attack_infos):
        raise AttackMetricError(
            f"det_annos ({len(det_annos)} frames) and attack_infos ({len(attack_infos)}) differ"
        )
    if not det_annos:
        raise AttackMetricError("no frames to evaluate (det_annos is empty)")
    iou_fn = boxes_aligned_iou3d if iou_fn is None else iou_fn

    for i, info in enumerate(attack_infos):
        for key in ("variant", "family", *SCORING_KEYS):
            if key not in info:
                raise AttackMetricError(f"frame {i}: attack metadata lacks key '{key}'")
    found = {
        key: {info[key] for info in attack_infos} for key in ("variant", "family", *SCORING_KEYS)
    }
    if any(len(values) != 1 for values in found.values()):
        raise AttackMetricError(
            "one call evaluates one variant; got "
            + ", ".join(f"{key} {sorted(map(str, v))}" for key, v in found.items() if len(v) != 1)
        )
    variant, family = str(found["variant"].pop()), str(found["family"].pop())
    if success_if_detected is None:
        success_if_detected = found["success_if_detected"].pop()
    confidence = found["confidence"].pop()

    fields = ("frame_index", "frame_id", "sequence", "run_id", "lifecycle_k", "is_shadow", "box")
    rows: dict[str, list] = {k: [] for k in fields}
    batch = _PairBatch()
    num_spoofed = num_untargeted = 0
    for i, (anno, info) in enumerate(zip(det_annos, attack_infos)):
        where = _frame_where(i, anno, info)
        if "frame_id" in anno and "frame_id" in info and anno["frame_id"] != info["frame_id"]:
            raise AttackMetricError(
                f"{where}: det anno frame_id {anno['frame_id']!r} != attack metadata "
                f"frame_id {info['frame_id']!r} (inputs not aligned)"
            )
        names, boxes, scores = _check_predictions(anno, where)
        target = _check_attack_info(info, where)
        num_spoofed += bool(info["spoofed"])
        if target is None:
            num_untargeted += bool(info["spoofed"])
            continue
        if success_if_detected is None:
            raise AttackMetricError(
                f"{where}: family {family!r} records a target but its metadata has no "
                "success_if_detected (set the attack class's SUCCESS_IF_DETECTED)"
            )
        keep = _eligible(names, scores, target_class, score_threshold)
        batch.add(target, boxes[keep], scores[keep])
        sequence, run_id = _check_run(info, where)
        fid = anno.get("frame_id", info.get("frame_id"))
        rows["frame_index"].append(i)
        rows["frame_id"].append("" if fid is None else str(fid))
        rows["sequence"].append(sequence)
        rows["run_id"].append(run_id)
        rows["lifecycle_k"].append(int(info["lifecycle_k"]))
        rows["is_shadow"].append(bool(info["target_is_shadow"]))
        rows["box"].append(target)

    max_iou, matched_score, overlap_score = batch.evaluate(iou_threshold, iou_fn)
    return TargetMatches(
        variant=variant,
        family=family,
        success_if_detected=bool(success_if_detected),
        confidence=None if confidence is None else str(confidence),
        iou_threshold=float(iou_threshold),
        score_threshold=None if score_threshold is None else float(score_threshold),
        target_class=target_class,
        num_frames=len(det_annos),
        num_spoofed=num_spoofed,
        num_untargeted=num_untargeted,
        frame_index=np.asarray(rows["frame_index"], dtype=np.int64),
        frame_id=np.asarray(rows["frame_id"], dtype=str),
        sequence=np.asarray(rows["sequence"], dtype=str),
        run_id=np.asarray(rows["run_id"], dtype=np.int64),
        lifecycle_k=np.asarray(rows["lifecycle_k"], dtype=np.int64),
        is_shadow=np.asarray(rows["is_shadow"], dtype=bool),
        target_box=np.asarray(rows["box"], dtype=np.float64).reshape(-1, 7),
        max_iou=max_iou,
        matched_score=matched_score,
        overlap_score=overlap_score,
    )


def _align_by_frame_id(clean_det_annos: Sequence[Mapping], frame_ids: np.ndarray) -> list[Mapping]:
    by_id: dict[str, Mapping] = {}
    for i, anno in enumerate(clean_det_annos):
        if "frame_id" not in anno:
            raise AttackMetricError(f"clean det anno {i} has no 'frame_id' to align by")
        fid = str(anno["frame_id"])
        if fid in by_id:
            raise AttackMetricError(f"clean det annos contain frame_id {fid!r} twice")
        by_id[fid] = anno
    aligned = []
    for fid in frame_ids:
        if fid == "":
            raise AttackMetricError(
                "attacked det annos need 'frame_id' to align with the clean run"
            )
        if fid not in by_id:
            raise AttackMetricError(f"frame_id {fid!r} of the attacked run is not in the clean run")
        aligned.append(by_id[fid])
    return aligned


def clean_matched_scores(
    matches: TargetMatches, clean_det_annos: Sequence[Mapping], *, iou_fn: IouFn | None = None
) -> np.ndarray:
    """(T,) the clean run's matched score of each target: the best score among the clean
    predictions of the same ``frame_id`` that match the target box (the class, score and IoU
    rules of ``matches``); NaN where the clean run has no such prediction."""
    iou_fn = boxes_aligned_iou3d if iou_fn is None else iou_fn
    clean_annos = _align_by_frame_id(clean_det_annos, matches.frame_id)
    batch = _PairBatch()
    for j, anno in enumerate(clean_annos):
        names, boxes, scores = _check_predictions(anno, f"clean frame {matches.frame_id[j]}")
        keep = _eligible(names, scores, matches.target_class, matches.score_threshold)
        batch.add(matches.target_box[j], boxes[keep], scores[keep])
    _, clean_scores, _ = batch.evaluate(matches.iou_threshold, iou_fn)
    return clean_scores
