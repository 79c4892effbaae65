"""Confidence of an attack's targets, by the kind its family names (the attack class's
``CONFIDENCE``, recorded in every frame's metadata): ``injection`` (the scores of the detected
phantoms) and ``removal`` (the surviving targets' scores against the clean run's), or a kind
registered with :func:`register_confidence_kind`, which brings its computation and its keys of
the ``confidence`` entry as the attack families bring their scoring."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from pcdet_atlas.evaluation.analyses.matching import (
    AttackMetricError,
    IouFn,
    TargetMatches,
    clean_matched_scores,
)
from pcdet_atlas.evaluation.analyses.registry import VariantData
from pcdet_atlas.evaluation.analyses.schema_parts import (
    COUNT,
    FRAC,
    HISTOGRAM,
    SIGNED_FRAC,
    check_histogram,
    fail,
    nullable,
)
from pcdet_atlas.evaluation.analyses.scores import (
    HIGH_SCORE_THRESHOLD,
    NUM_SCORE_BINS,
    rate,
    score_histogram,
    score_peak,
    score_values,
)
from pcdet_atlas.registry import CONFIDENCE_KINDS

__all__ = [
    "CONFIDENCE_KINDS",
    "ConfidenceKind",
    "confidence_of",
    "injection_confidence",
    "register_confidence_kind",
    "removal_confidence",
]


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
    scores = score_values(attacked.matched_score[attacked.detected])
    n_above = int(np.sum(scores > high_score))
    return {
        "kind": "injection",
        "high_score_threshold": float(high_score),
        "num_targets": len(attacked),
        "num_detected": int(scores.size),
        "num_above": n_above,
        "fraction_above": rate(n_above, int(scores.size)),
        "mean_score": float(scores.mean()) if scores.size else None,
        "median_score": float(np.median(scores)) if scores.size else None,
        "histogram": score_histogram(scores, num_bins),
    }


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
    attacked_scores = score_values(surviving.matched_score)
    paired = np.isfinite(clean_scores)
    att_p, clean_p = attacked_scores[paired], score_values(clean_scores[paired])
    drop = clean_p - att_p
    n_above = int(np.sum(attacked_scores > high_score))
    clean_peak, att_peak = score_peak(clean_p), score_peak(att_p)
    return {
        "kind": "removal",
        "high_score_threshold": float(high_score),
        "num_targets": len(attacked),
        "num_surviving": len(surviving),
        "num_above": n_above,
        "fraction_above": rate(n_above, len(surviving)),
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


# ---------------------------------------------------------------------------- kinds
@dataclass(frozen=True)
class ConfidenceKind:
    """A confidence analysis a family can name in its ``CONFIDENCE``.

    ``compute(data)`` returns the variant's ``confidence`` entry (with ``kind`` = ``name``, the
    keys common to every kind and ``properties``), or None where it cannot be computed (e.g. no
    clean run); it runs only on a variant with attacked targets. ``shown``: the key that counts
    the targets whose scores ``histogram`` holds; ``check(entry, path)``: the invariants of its
    own keys.
    """

    name: str
    compute: Callable[[VariantData], dict | None]
    shown: str
    properties: Mapping[str, dict] = field(default_factory=dict)
    check: Callable[[Mapping, str], None] | None = None


#: The keys every kind's entry has besides ``kind``, its ``shown`` count and ``properties``.
COMMON_PROPERTIES = {
    "high_score_threshold": FRAC,
    "num_targets": COUNT,
    "num_above": COUNT,
    "fraction_above": nullable(FRAC),
    "histogram": HISTOGRAM,
}


def register_confidence_kind(kind: ConfidenceKind) -> ConfidenceKind:
    """Register ``kind`` under its name (a family's ``CONFIDENCE`` may then name it); a name
    taken already raises."""
    CONFIDENCE_KINDS.register(kind.name)(kind)
    return kind


def confidence_of(data: VariantData) -> dict | None:
    """The confidence entry of a variant: the kind its metadata names, None without one or
    without attacked targets. An unregistered kind is an error naming the known ones."""
    matches = data.matches
    if matches.confidence is None or len(matches.attacked()) == 0:
        return None
    if matches.confidence not in CONFIDENCE_KINDS:
        raise AttackMetricError(
            f"variant {matches.variant!r}: confidence kind {matches.confidence!r} (the family's "
            f"CONFIDENCE) is not registered; known: {CONFIDENCE_KINDS.list()}"
        )
    return CONFIDENCE_KINDS.get(matches.confidence).compute(data)


def _check_removal(c: Mapping, path: str) -> None:
    n = c["num_surviving"]
    if c["num_paired"] + c["num_clean_missed"] != n:
        fail(path, f"num_paired + num_clean_missed != num_surviving {n}")
    for key in ("paired_attacked_histogram", "paired_clean_histogram"):
        check_histogram(c[key], f"{path}['{key}']", total=c["num_paired"])


register_confidence_kind(
    ConfidenceKind(
        name="injection",
        compute=lambda d: injection_confidence(
            d.matches, high_score=d.high_score, num_bins=d.num_bins
        ),  # fmt: skip
        shown="num_detected",
        properties={
            "num_detected": COUNT,
            "mean_score": nullable(FRAC),
            "median_score": nullable(FRAC),
        },
    )
)
register_confidence_kind(
    ConfidenceKind(
        name="removal",
        compute=lambda d: (
            None
            if d.clean_det_annos is None
            else removal_confidence(
                d.matches,
                d.clean_det_annos,
                high_score=d.high_score,
                num_bins=d.num_bins,
                iou_fn=d.iou_fn,
            )
        ),  # fmt: skip
        shown="num_surviving",
        properties={
            "num_surviving": COUNT,
            "num_paired": COUNT,
            "num_clean_missed": COUNT,
            "mean_score_drop": nullable(SIGNED_FRAC),
            "median_score_drop": nullable(SIGNED_FRAC),
            "clean_peak": nullable(FRAC),
            "attacked_peak": nullable(FRAC),
            "peak_gap": nullable(SIGNED_FRAC),
            "paired_attacked_histogram": HISTOGRAM,
            "paired_clean_histogram": HISTOGRAM,
        },
        check=_check_removal,
    )
)
