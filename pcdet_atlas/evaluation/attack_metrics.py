"""Attack metrics (docs/evaluation.md): success rate, confidence, lifecycle, robustness ranks.

Inputs are the two per-frame lists every evaluation run produces, aligned by index:

* ``det_annos``: OpenPCDet detection annos, one dict per frame with ``name`` (K,) str,
  ``boxes_lidar`` (K, 7|9) ``[x, y, z, dx, dy, dz, heading(, vx, vy)]`` in metres / radians (vehicle
  frame, z = box centre) and ``score`` (K,) in [0, 1]; ``frame_id`` is used when present.
* ``attack_infos``: the attack metadata dict of each frame (key ``attack`` of an
  ``AtlasWaymoDataset`` sample; schema in ``docs/evaluation.md``): ``variant``, ``family``,
  ``spoofed``, ``target_box`` (7,) or None, ``target_is_shadow``, ``lifecycle_k``, and on a
  frame with a target its run, ``sequence_name`` and ``run_id`` ...
  When ``attack_infos`` is None, each det anno must carry its metadata under ``anno['attack']``.

Everything is computed from one pass, :func:`match_targets`, that finds for every recorded target
box the best 3D IoU of the predictions (of the target's class, above an optional score threshold)
and the best score among the matching ones; ASR, the lenient ASR, the confidence statistics and
the lifecycle curve are all read off that record, so they always agree with each other.

Definitions (paper §"Evaluation Metric"; docs/evaluation.md, "Attack metrics"):

* **Target**: a frame whose ``target_box`` is not None. Attacked targets have ``spoofed`` True;
  *shadow* targets (``target_is_shadow`` True: the frame before a run and the frames after it) are
  only used by the lifecycle analysis and never enter the ASR.
* **Detected**: some prediction of the target's class (default ``'Vehicle'``; the paper's box
  ``g = [x, y, z, l, w, h, θ, c]`` includes the class) has 3D IoU >= 0.7 with the target box.
* **Injection** succeeds when the phantom is detected; **removal** succeeds when the target is not.
* **Lenient** (MVP, Zhang et al. USENIX Sec'24): "detected" means IoU > 0 instead, so a lenient
  injection success is any overlapping prediction and a lenient removal success needs *no*
  overlapping prediction at all. (Lenient injection ASR >= ASR; lenient removal ASR <= ASR.)
* ``ASR = num_success / num_targets``; None when there is no target (e.g. the clean variant).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from pcdet_atlas.evaluation.intervals import asr_interval, paired_interval
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d

ASR_IOU_THRESHOLD = 0.7
HIGH_SCORE_THRESHOLD = 0.7
NUM_SCORE_BINS = 20  # fixed bins of width 0.05 over [0, 1]
PEAK_RESOLUTION = 1e-3  # the centre gap's resolution (the paper reports three decimals)
CI_LEVEL = 0.95  # the ASR's interval (intervals.asr_interval: sequences as clusters)
DEFAULT_TARGET_CLASS = "Vehicle"
#: The schedule window the attack engine records ``lifecycle_k`` for by default (docs/attacks.md,
#: ``pcdet_atlas.attacks.schedule.DEFAULT_WINDOW``; a schedule config with another ``WINDOW``
#: must pass ``recorded_window=`` explicitly).
SCHEDULE_WINDOW = 32

IouFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
#: Metadata keys by which the attack class tells the evaluation how to score it.
SCORING_KEYS = ("success_if_detected", "confidence", "rank_group")


class AttackMetricError(ValueError):
    """Predictions or attack metadata that cannot be evaluated; the message names frame and key."""


# ---------------------------------------------------------------------------- matching
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


# ---------------------------------------------------------------------------- ASR
def _rate(num: int, den: int) -> float | None:
    return None if den == 0 else num / den


def run_counts(matches: TargetMatches) -> list[dict]:
    """Targets and successes per spoof run of the attacked (non-shadow) targets of ``matches``:
    ``[{'sequence', 'run_id', 'num_targets', 'num_success', 'num_success_lenient'}, ...]``
    sorted by ``(sequence, run_id)``, one entry per run with at least one target. The unit of
    the ASR's interval, and what a paired comparison of two models needs
    (:func:`paired_asr_differences`). ``run_counts(matches.select(mask))`` counts any subset
    (the lifecycle counts the targets at one position k, shadows included)."""
    attacked = matches.attacked()
    return _counts_per_run(attacked)


def _counts_per_run(attacked: TargetMatches) -> list[dict]:
    """:func:`run_counts` of every target of ``attacked``."""
    run = attacked.run  # (T,) index of (sequence, run_id) in sorted order
    first = np.unique(run, return_index=True)[1]  # (R,) a target of each run
    num = first.size
    targets = np.bincount(run, minlength=num)
    success = np.bincount(run[attacked.success], minlength=num)
    lenient = np.bincount(run[attacked.success_lenient], minlength=num)
    return [
        {
            "sequence": str(attacked.sequence[i]),
            "run_id": int(attacked.run_id[i]),
            "num_targets": int(targets[r]),
            "num_success": int(success[r]),
            "num_success_lenient": int(lenient[r]),
        }
        for r, i in enumerate(first)
    ]


def asr_from_matches(matches: TargetMatches) -> dict:
    """ASR of the attacked (non-shadow) targets.

    Returns ``{'asr', 'asr_ci', 'num_runs', 'runs', 'num_targets', 'num_success',
    'asr_lenient', 'num_success_lenient', 'num_spoofed_frames', 'num_untargeted',
    'iou_threshold', 'score_threshold', 'target_class'}``; the rates are None without targets.
    ``asr_ci`` is the 95% interval of :func:`pcdet_atlas.evaluation.intervals.asr_interval`
    over the per-run counts ``runs`` (:func:`run_counts`; sequences as clusters, the runs of a
    single sequence; ``[lo, hi]``, None with fewer than two runs). ``num_untargeted`` spoofed
    frames recorded no target and are not in the ASR (see :class:`TargetMatches`).
    """
    attacked = matches.attacked()
    n = len(attacked)
    n_ok, n_len = int(attacked.success.sum()), int(attacked.success_lenient.sum())
    runs = run_counts(matches)  # a run is (sequence, run_id): run ids repeat across sequences
    ci = asr_interval(runs, level=CI_LEVEL)
    return {
        "asr": _rate(n_ok, n),
        "asr_ci": None if ci is None else list(ci),
        "num_runs": len(runs),
        "runs": runs,
        "num_targets": n,
        "num_success": n_ok,
        "asr_lenient": _rate(n_len, n),
        "num_success_lenient": n_len,
        "num_spoofed_frames": matches.num_spoofed,
        "num_untargeted": matches.num_untargeted,
        "iou_threshold": matches.iou_threshold,
        "score_threshold": matches.score_threshold,
        "target_class": matches.target_class,
    }


def paired_asr_differences(
    runs: Mapping[str, Mapping[str, Sequence[Mapping]]],
    *,
    level: float = CI_LEVEL,
) -> dict:
    """Differences of the mean ASR between models scored on the same spoof runs, with paired
    intervals over the sequences.

    A model's mean ASR is the mean of its per-variant ASRs (the variants of one rank group, say).
    Models attacked on the same runs share the runs' difficulty (the phantom trace and
    placement, the removal target), and the variants of a family share their runs too: the
    attacks key their draws by sequence and run start, not by budget, so run r of ``rem_10``
    removes around the same target as run r of ``rem_40``. The runs of a sequence share its
    scene. The cluster is therefore the sequence, across all the given variants (the run when
    every run comes from one sequence): each cluster's contribution to the difference of two
    mean ASRs is ``sum_v (d_hits_c,v - d_v * targets_c,v) / targets_v / V`` (``d_hits``: the
    two models' successes minus each other in the cluster, ``d_v``: their ASR difference on
    variant v), and the interval is the cluster-robust t interval of
    :func:`pcdet_atlas.evaluation.intervals.paired_interval` (``C - 1`` degrees of freedom).
    Closed-form: no draw, the same interval every call.

    Args:
        runs: model -> variant -> the variant's per-run counts (:func:`run_counts`, the
            ``runs`` of a ``results.json`` entry). Every model needs the same variants, each with
            the same runs and the same number of targets per run.

    Returns:
        ``{'models', 'variants', 'num_runs' (per variant), 'num_clusters' (sequences over all
        the variants; runs with one sequence), 'cluster' ('sequence' | 'run'), 'mean_asr'
        {model: float}, 'difference' {a: {b: mean_asr[a] - mean_asr[b]}}, 'ci' {a: {b: [lo,
        hi]}}}`` (within [-1, 1]); ``ci`` is None with fewer than two runs.

    Raises:
        AttackMetricError: fewer than two models, no variant, a variant without targets or with
            a run listed twice, or models whose variants, runs or targets per run differ (they
            were not scored on the same targets), naming them.
    """
    models = list(runs)
    if len(models) < 2:
        raise AttackMetricError(f"a paired comparison needs at least 2 models, got {models}")
    variants = list(runs[models[0]])
    if not variants:
        raise AttackMetricError(f"model {models[0]!r}: no variant to compare")
    for m in models[1:]:
        if set(runs[m]) != set(variants):
            raise AttackMetricError(
                f"models {models[0]!r} and {m!r} have different variants: {sorted(variants)} "
                f"and {sorted(runs[m])}"
            )

    def by_run(model: str, variant: str) -> dict:
        out = {}
        for r in runs[model][variant]:
            key = (str(r["sequence"]), int(r["run_id"]))
            if key in out:
                raise AttackMetricError(f"model {model!r}, variant {variant!r}: run {key} twice")
            out[key] = r
        return out

    first = {v: by_run(models[0], v) for v in variants}
    keys = sorted({key for v in variants for key in first[v]})
    column = {key: j for j, key in enumerate(keys)}
    hits, targets = [], []  # per variant: (M, R) successes, (R,) targets (0: not a run of it)
    for v in variants:
        ref = {key: int(r["num_targets"]) for key, r in first[v].items()}
        if sum(ref.values()) < 1:
            raise AttackMetricError(f"model {models[0]!r}, variant {v!r}: no targets")
        table = np.zeros((len(models), len(keys)))
        for i, m in enumerate(models):
            own = by_run(m, v)
            counts = {key: int(r["num_targets"]) for key, r in own.items()}
            if counts != ref:
                diff = sorted(set(counts.items()) ^ set(ref.items()))[:3]
                raise AttackMetricError(
                    f"variant {v!r}: models {models[0]!r} and {m!r} were not scored on the same "
                    f"targets (runs and targets per run differ, e.g. {diff})"
                )
            for key, r in own.items():
                table[i, column[key]] = r["num_success"]
        count = np.zeros(len(keys))
        for key, n in ref.items():
            count[column[key]] = n
        hits.append(table)
        targets.append(count)
    rates = [h.sum(1) / t.sum() for h, t in zip(hits, targets)]  # per variant (M,)
    mean = np.mean(rates, axis=0)  # (M,)
    sequences = sorted({seq for seq, _ in keys})
    unit = "sequence" if len(sequences) >= 2 else "run"
    cluster_of = np.array([sequences.index(seq) if unit == "sequence" else j
                           for j, (seq, _) in enumerate(keys)])  # (R,)  # fmt: skip
    num_clusters = int(cluster_of.max()) + 1
    # (M, C) each model's linearised contribution per cluster to its mean ASR
    contrib = np.zeros((len(models), num_clusters))
    for h, t, p in zip(hits, targets, rates):
        resid = (h - p[:, None] * t[None, :]) / t.sum() / len(variants)  # (M, R)
        np.add.at(contrib.T, cluster_of, resid.T)
    ci = None
    if len(keys) >= 2:
        delta = mean[:, None] - mean[None, :]  # (M, M)
        lo, hi = paired_interval(contrib[:, None, :] - contrib[None, :, :], delta, level)
        lo, hi = np.clip(lo, -1.0, 1.0), np.clip(hi, -1.0, 1.0)  # a difference of two rates
        ci = {a: {b: [float(lo[i, j]), float(hi[i, j])] for j, b in enumerate(models)}
              for i, a in enumerate(models)}  # fmt: skip
    return {
        "models": models,
        "variants": variants,
        "num_runs": {v: int(np.count_nonzero(t)) for v, t in zip(variants, targets)},
        "num_clusters": num_clusters,
        "cluster": unit,
        "mean_asr": {m: float(mean[i]) for i, m in enumerate(models)},
        "difference": {
            a: {b: float(mean[i] - mean[j]) for j, b in enumerate(models)}
            for i, a in enumerate(models)
        },  # fmt: skip
        "ci": ci,
    }


def attack_success_rate(
    det_annos: Sequence[Mapping], attack_infos: Sequence[Mapping] | None = None, **kwargs
) -> dict:
    """ASR and lenient ASR of one variant; ``kwargs`` as :func:`match_targets`."""
    return asr_from_matches(match_targets(det_annos, attack_infos, **kwargs))


# ---------------------------------------------------------------------------- confidence
def _score_values(scores: np.ndarray) -> np.ndarray:
    """(S,) scores as float64 rounded to 1e-6, so that a float32 score printed as 0.9 counts as 0.9
    (float32(0.9) = 0.89999998) in bins and thresholds."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(scores)) or np.any((scores < 0) | (scores > 1)):
        raise AttackMetricError(f"scores must be finite and in [0, 1]; got {scores}")
    return np.round(scores, 6)


def score_histogram(scores: np.ndarray, num_bins: int = NUM_SCORE_BINS) -> dict:
    """Counts of ``scores`` (S,) in ``num_bins`` equal bins ``[i / n, (i + 1) / n)`` over [0, 1]
    (the last bin also holds 1.0); scores are rounded to 1e-6 first (see ``_score_values``).

    Returns ``{'bin_edges': [num_bins + 1 floats], 'counts': [num_bins ints]}``.
    """
    scores = _score_values(scores)
    index = np.clip(np.floor(scores * num_bins + 1e-9).astype(np.int64), 0, num_bins - 1)
    counts = np.bincount(index, minlength=num_bins)
    edges = [round(i / num_bins, 12) for i in range(num_bins + 1)]
    return {"bin_edges": edges, "counts": counts.tolist()}


def score_peak(scores: np.ndarray, resolution: float = PEAK_RESOLUTION) -> float | None:
    """Peak (mode) of a score distribution at the paper's resolution (0.001 by default).

    The maximum of a Gaussian kernel density estimate (Silverman's rule-of-thumb bandwidth,
    ``0.9 min(std, IQR / 1.34) n^(-1/5)``, the std alone when the IQR is 0) on a grid of step
    ``resolution`` over [0, 1]; ties go to the lowest score. A sample with no spread (one score,
    or identical scores) has its value as peak (the limit of the estimate as the bandwidth
    shrinks), on the same grid. None for an empty sample.
    """
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if scores.size == 0:
        return None
    steps = int(round(1.0 / resolution))
    std = float(scores.std(ddof=1)) if scores.size > 1 else 0.0
    if std == 0.0:
        return round(float(np.round(scores[0] * steps)) / steps, 12)
    q75, q25 = np.percentile(scores, [75, 25])
    spread = min(std, (q75 - q25) / 1.34) or std
    bandwidth = 0.9 * spread * scores.size ** (-0.2)
    grid = np.arange(steps + 1) / steps  # (G,)
    density = np.exp(-0.5 * ((grid[:, None] - scores[None]) / bandwidth) ** 2).sum(1)
    return round(float(grid[int(np.argmax(density))]), 12)  # argmax: the lowest of ties


def injection_confidence(
    matches: TargetMatches,
    *,
    high_score: float = HIGH_SCORE_THRESHOLD,
    num_bins: int = NUM_SCORE_BINS,
) -> dict:
    """Confidence of the detected phantoms (attacked injection targets with IoU >= threshold).

    The score of a phantom is the highest score among its matching predictions. Returns
    ``{'kind': 'injection', 'high_score_threshold', 'num_targets', 'num_detected', 'num_above',
    'fraction_above' (of detected phantoms, score > high_score; None if none detected),
    'mean_score', 'median_score', 'histogram'}``.
    """
    attacked = matches.attacked()
    scores = _score_values(attacked.matched_score[attacked.detected])
    n_above = int(np.sum(scores > high_score))
    return {
        "kind": "injection",
        "high_score_threshold": float(high_score),
        "num_targets": len(attacked),
        "num_detected": int(scores.size),
        "num_above": n_above,
        "fraction_above": _rate(n_above, int(scores.size)),
        "mean_score": float(scores.mean()) if scores.size else None,
        "median_score": float(np.median(scores)) if scores.size else None,
        "histogram": score_histogram(scores, num_bins),
    }


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


def removal_confidence(
    matches: TargetMatches,
    clean_det_annos: Sequence[Mapping],
    *,
    high_score: float = HIGH_SCORE_THRESHOLD,
    num_bins: int = NUM_SCORE_BINS,
    iou_fn: IouFn | None = None,
) -> dict:
    """Scores of the removal targets that survived (were still detected), against the clean run.

    For each surviving attacked target, the attacked score is the best score among the
    predictions matching its box (IoU >= threshold), and its clean score is the same quantity
    in the clean run's predictions for the same ``frame_id`` and the same target box (same class
    and score rules as ``matches``). Targets the clean model misses too are counted in
    ``num_clean_missed`` and left out of the paired statistics.

    Returns ``{'kind': 'removal', 'high_score_threshold', 'num_targets', 'num_surviving',
    'num_above', 'fraction_above' (surviving scores > high_score), 'num_paired',
    'num_clean_missed', 'mean_score_drop' (clean - attacked, paired), 'median_score_drop',
    'clean_peak', 'attacked_peak', 'peak_gap' (clean_peak - attacked_peak, see
    :func:`score_peak`; over the paired targets), 'histogram' (all surviving scores),
    'paired_attacked_histogram', 'paired_clean_histogram'}``.
    """
    attacked = matches.attacked()
    surviving = attacked.select(attacked.detected)
    clean_scores = clean_matched_scores(surviving, clean_det_annos, iou_fn=iou_fn)
    attacked_scores = _score_values(surviving.matched_score)
    paired = np.isfinite(clean_scores)
    att_p, clean_p = attacked_scores[paired], _score_values(clean_scores[paired])
    drop = clean_p - att_p
    n_above = int(np.sum(attacked_scores > high_score))
    clean_peak, att_peak = score_peak(clean_p), score_peak(att_p)
    return {
        "kind": "removal",
        "high_score_threshold": float(high_score),
        "num_targets": len(attacked),
        "num_surviving": len(surviving),
        "num_above": n_above,
        "fraction_above": _rate(n_above, len(surviving)),
        "num_paired": int(paired.sum()),
        "num_clean_missed": int((~paired).sum()),
        "mean_score_drop": float(drop.mean()) if drop.size else None,
        "median_score_drop": float(np.median(drop)) if drop.size else None,
        "clean_peak": clean_peak,
        "attacked_peak": att_peak,
        "peak_gap": None if clean_peak is None else clean_peak - att_peak,
        "histogram": score_histogram(attacked_scores, num_bins),
        "paired_attacked_histogram": score_histogram(att_p, num_bins),
        "paired_clean_histogram": score_histogram(clean_p, num_bins),
    }


# ---------------------------------------------------------------------------- lifecycle
def lifecycle_position(
    lifecycle_k: np.ndarray, is_shadow: np.ndarray, window: int, recorded_window: int
) -> np.ndarray:
    """Map recorded ``lifecycle_k`` to a detector's lifecycle position k in 0..2W, -1 = outside.

    The attack engine records k for its own window ``recorded_window`` (We): 0 = last clean
    frame before onset, 1..We = the first spoofed frames, We+1..2We = clean shadow frames after the
    run. For a detector with a window ``window`` (W <= We) the positions are 0, the first W
    spoofed frames (k = 1..W) and the first W frames after the run (k = W+1..2W).

    Raises AttackMetricError where the record contradicts itself (a shadow target at 1..We or a
    spoofed one outside it), which is what a wrong ``recorded_window`` produces.
    """
    if window < 1 or recorded_window < window:
        raise AttackMetricError(
            f"lifecycle needs 1 <= window <= recorded_window, got {window}, {recorded_window}"
        )
    k = np.asarray(lifecycle_k, dtype=np.int64)
    shadow = np.asarray(is_shadow, dtype=bool)
    out = np.full(k.shape, -1, dtype=np.int64)
    bad_shadow = shadow & (k >= 1) & (k <= recorded_window)
    bad_spoofed = ~shadow & ((k <= 0) | (k > recorded_window))
    bad_range = (k > 2 * recorded_window) | (shadow & (k < 0))
    if np.any(bad_shadow | bad_spoofed | bad_range):
        bad = np.flatnonzero(bad_shadow | bad_spoofed | bad_range)[:5]
        raise AttackMetricError(
            f"lifecycle_k {k[bad].tolist()} (shadow {shadow[bad].tolist()}) is inconsistent "
            f"with recorded_window={recorded_window}: expected shadow at 0 and "
            f"{recorded_window + 1}..{2 * recorded_window}, spoofed at 1..{recorded_window}"
        )
    out[shadow & (k == 0)] = 0
    onset = ~shadow & (k >= 1) & (k <= window)
    out[onset] = k[onset]
    after = k - recorded_window
    decay = shadow & (after >= 1) & (after <= window)
    out[decay] = window + after[decay]
    return out


def lifecycle_asr(
    matches: TargetMatches,
    window: int,
    *,
    recorded_window: int | None = None,
    num_bins: int = NUM_SCORE_BINS,
    clean_scores: np.ndarray | None = None,
) -> dict:
    """ASR by lifecycle position k = 0..2W for a detector with a ``window``-frame input.

    Shadow targets (k = 0 and k = W+1..2W) are scored exactly like attacked ones (success = the
    phantom is detected / the target is missed) although the current frame is clean there.
    ``recorded_window`` is the schedule window the attack engine recorded ``lifecycle_k`` for
    (default :data:`SCHEDULE_WINDOW` = 32); see :func:`lifecycle_position` for the mapping. The
    engine records the frame between two runs as k = 0 of the next run, so with W equal to the
    schedule window position 2W only holds frames after a sequence's last run.

    Returns column lists over k: ``{'window', 'recorded_window', 'k', 'attacked' (bool: k in
    1..W), 'num_targets', 'num_success', 'asr', 'asr_ci' (per k the
    :func:`~pcdet_atlas.evaluation.intervals.asr_interval` of that position's targets grouped
    by their spoof run, None below two runs), 'runs' (per k those per-run counts, as
    :func:`run_counts`, for intervals of pooled variants), 'num_success_lenient', 'asr_lenient',
    'score_bin_edges', 'score_counts' (per k: histogram of the matched scores),
    'clean_score_counts'}``: per k the histogram of ``clean_scores`` (T,), the clean run's
    matched score of the same targets (:func:`clean_matched_scores`, NaN = not detected), the
    baseline of the lifecycle heatmaps; None without ``clean_scores``.
    """
    recorded_window = SCHEDULE_WINDOW if recorded_window is None else recorded_window
    pos = lifecycle_position(matches.lifecycle_k, matches.is_shadow, window, recorded_window)
    ks = list(range(2 * window + 1))
    success, lenient = matches.success, matches.success_lenient
    out: dict = {
        "window": int(window),
        "recorded_window": int(recorded_window),
        "k": ks,
        "attacked": [1 <= k <= window for k in ks],
        "num_targets": [],
        "num_success": [],
        "asr": [],
        "asr_ci": [],
        "runs": [],
        "num_success_lenient": [],
        "asr_lenient": [],
        "score_bin_edges": score_histogram(np.zeros(0), num_bins)["bin_edges"],
        "score_counts": [],
        "clean_score_counts": None if clean_scores is None else [],
    }
    if clean_scores is not None and len(clean_scores) != len(matches):
        raise AttackMetricError(
            f"clean_scores has {len(clean_scores)} entries for {len(matches)} targets"
        )
    for k in ks:
        at = pos == k
        n, n_ok, n_len = int(at.sum()), int(success[at].sum()), int(lenient[at].sum())
        out["num_targets"].append(n)
        out["num_success"].append(n_ok)
        out["asr"].append(_rate(n_ok, n))
        runs = _counts_per_run(matches.select(at)) if n else []
        ci = asr_interval(runs, level=CI_LEVEL) if n else None
        out["asr_ci"].append(None if ci is None else [float(ci[0]), float(ci[1])])
        out["runs"].append(runs)
        out["num_success_lenient"].append(n_len)
        out["asr_lenient"].append(_rate(n_len, n))
        scores = matches.matched_score[at & matches.detected]
        out["score_counts"].append(score_histogram(scores, num_bins)["counts"])
        if clean_scores is not None:
            clean = clean_scores[at]
            clean = clean[np.isfinite(clean)]
            out["clean_score_counts"].append(score_histogram(clean, num_bins)["counts"])
    return out


# ---------------------------------------------------------------------------- one variant
def evaluate_attack(
    det_annos: Sequence[Mapping],
    attack_infos: Sequence[Mapping] | None = None,
    *,
    clean_det_annos: Sequence[Mapping] | None = None,
    window: int | None = None,
    recorded_window: int | None = None,
    iou_threshold: float = ASR_IOU_THRESHOLD,
    score_threshold: float | None = None,
    target_class: str | None = DEFAULT_TARGET_CLASS,
    high_score: float = HIGH_SCORE_THRESHOLD,
    num_bins: int = NUM_SCORE_BINS,
    success_if_detected: bool | None = None,
    iou_fn: IouFn | None = None,
) -> dict:
    """All attack metrics of one variant, in the layout of a ``results.json`` variant entry.

    Returns ``{'variant', 'family', 'num_frames', **asr_from_matches(...), 'confidence',
    'lifecycle'}``. ``confidence`` is the analysis the family's metadata names:
    :func:`injection_confidence` ('injection') or :func:`removal_confidence` ('removal', None if
    ``clean_det_annos`` is not given); None without targets or analysis. ``lifecycle`` is
    :func:`lifecycle_asr` when ``window`` is given, else None.
    """
    iou_fn = boxes_aligned_iou3d if iou_fn is None else iou_fn
    matches = match_targets(
        det_annos,
        attack_infos,
        iou_threshold=iou_threshold,
        score_threshold=score_threshold,
        target_class=target_class,
        success_if_detected=success_if_detected,
        iou_fn=iou_fn,
    )
    out = {"variant": matches.variant, "family": matches.family, "num_frames": matches.num_frames}
    out.update(asr_from_matches(matches))
    confidence = None
    if len(matches.attacked()) > 0:
        if matches.confidence == "injection":
            confidence = injection_confidence(matches, high_score=high_score, num_bins=num_bins)
        elif matches.confidence == "removal" and clean_det_annos is not None:
            confidence = removal_confidence(
                matches, clean_det_annos, high_score=high_score, num_bins=num_bins, iou_fn=iou_fn
            )
    out["confidence"] = confidence
    out["lifecycle"] = None
    if window is not None and len(matches) > 0:
        clean_scores = (
            None
            if clean_det_annos is None
            else clean_matched_scores(matches, clean_det_annos, iou_fn=iou_fn)
        )
        out["lifecycle"] = lifecycle_asr(
            matches, window, recorded_window=recorded_window, num_bins=num_bins,
            clean_scores=clean_scores,
        )  # fmt: skip
    return out


# ---------------------------------------------------------------------------- ranks
def linear_fit(x: np.ndarray, y: np.ndarray) -> dict:
    """Ordinary least squares ``y = slope * x + intercept`` of (P,) points.

    Returns ``{'slope', 'intercept', 'r2', 'pearson_r', 'p_value', 'num_models'}`` (``p_value``:
    two-sided test of zero slope, ``scipy.stats.linregress``).
    """
    from scipy.stats import linregress

    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1 or x.size < 2 or np.ptp(x) == 0:
        raise AttackMetricError(f"linear fit needs >= 2 points with varying x, got {x} and {y}")
    reg = linregress(x, y)
    return {
        "slope": float(reg.slope),
        "intercept": float(reg.intercept),
        "r2": float(reg.rvalue**2),
        "pearson_r": float(reg.rvalue),
        "p_value": float(reg.pvalue),
        "num_models": int(x.size),
    }


def robustness_ranks(
    asr_by_model: Mapping[str, Mapping[str, float]],
    variant_groups: Mapping[str, str | None],
    *,
    tie_method: str = "average",
    min_models_for_fit: int = 3,
    fit_axes: tuple[str, str] = ("injection", "removal"),
) -> dict:
    """Per-setting ASR ranks of several models, averaged per rank group, and their linear fit.

    In each setting (variant) the models are ranked by ASR, rank 1 = lowest ASR = most robust;
    ties get the mean of the ranks they span (``tie_method`` as ``scipy.stats.rankdata``:
    'average', 'min', 'max', 'dense', 'ordinal'). A model's rank in a group is the mean of its
    ranks over the group's variants. The fit is ordinary least squares of the ``fit_axes[1]``
    group's rank on the ``fit_axes[0]`` group's (the paper's Fig. "Robustness Correlation":
    removal on injection).

    Args:
        asr_by_model: model -> variant -> ASR in [0, 1]. Every model needs every ranked variant.
        variant_groups: variant -> rank group (the attack class's ``RANK_GROUP``); variants whose
            group is None (e.g. clean) are not ranked.
        min_models_for_fit: below this many models the fit is None (two points fit exactly).

    Returns:
        ``{'models': [...], 'tie_method', 'per_setting': {variant: {model: rank}},
        'group_ranks': {group: {model: r}}, 'fit_axes': [x group, y group], 'fit': {'slope',
        'intercept', 'r2', 'pearson_r', 'p_value', 'num_models'} or None}`` (None also when a
        fit axis has no variant).
    """
    from scipy.stats import rankdata

    models = sorted(asr_by_model)
    if len(models) < 2:
        raise AttackMetricError(f"ranking needs at least 2 models, got {models}")
    ranked: dict[str, list[str]] = {}
    for variant, group in sorted(variant_groups.items()):
        if group is not None:
            ranked.setdefault(str(group), []).append(variant)
    per_setting: dict[str, dict[str, float]] = {}
    for variant in (v for variants in ranked.values() for v in variants):
        values = []
        for m in models:
            asr = asr_by_model[m].get(variant)
            if asr is None or not math.isfinite(asr):
                raise AttackMetricError(f"model {m!r} has no ASR for variant {variant!r}")
            values.append(float(asr))
        ranks = rankdata(values, method=tie_method)
        per_setting[variant] = {m: float(r) for m, r in zip(models, ranks)}
    group_ranks = {
        group: {m: float(np.mean([per_setting[v][m] for v in variants])) for m in models}
        for group, variants in ranked.items()
    }
    fit = None
    x_group, y_group = fit_axes
    if x_group in group_ranks and y_group in group_ranks and len(models) >= min_models_for_fit:
        x = np.array([group_ranks[x_group][m] for m in models])
        if np.ptp(x) > 0:
            fit = linear_fit(x, np.array([group_ranks[y_group][m] for m in models]))
    return {
        "models": models,
        "tie_method": tie_method,
        "per_setting": per_setting,
        "group_ranks": group_ranks,
        "fit_axes": [x_group, y_group],
        "fit": fit,
    }
