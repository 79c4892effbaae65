"""All attack analyses of one variant: :func:`evaluate_attack` matches its targets once and runs
every registered analysis (:mod:`~pcdet_atlas.evaluation.analyses.registry`) on the match."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from pcdet_atlas.evaluation.analyses.matching import (
    ASR_IOU_THRESHOLD,
    DEFAULT_TARGET_CLASS,
    AttackMetricError,
    IouFn,
    match_targets,
)
from pcdet_atlas.evaluation.analyses.registry import VariantData, registered_analyses
from pcdet_atlas.evaluation.analyses.scores import HIGH_SCORE_THRESHOLD, NUM_SCORE_BINS
from pcdet_atlas.ops.iou3d_nms import boxes_aligned_iou3d

__all__ = ["evaluate_attack"]


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

    Returns ``{'variant', 'family', 'num_frames'}`` and the keys of every registered analysis,
    in the order they registered: the built-ins' :func:`~.asr.asr_from_matches`, ``confidence``
    (the kind the family's metadata names, :func:`~.confidence.confidence_of`: 'injection' or
    'removal', None for removal without ``clean_det_annos``; None without targets or kind) and
    ``lifecycle`` (:func:`~.lifecycle.lifecycle_asr` when ``window`` is given and there are
    targets, else None). Arguments as :func:`~.matching.match_targets`; ``clean_det_annos``: the
    clean run's predictions (removal confidence, the lifecycle's clean baseline);
    ``recorded_window``: the attack schedule's window that the metadata's ``lifecycle_k`` counts
    in (None: the default schedule's 32; an attack with another ``SCHEDULE.WINDOW`` must pass
    it); ``high_score`` and ``num_bins``: the confidence analysis's score threshold and
    histogram bins.
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
    data = VariantData(
        matches=matches,
        det_annos=det_annos,
        attack_infos=[a["attack"] for a in det_annos] if attack_infos is None else attack_infos,
        clean_det_annos=clean_det_annos,
        window=window,
        recorded_window=recorded_window,
        high_score=high_score,
        num_bins=num_bins,
        iou_fn=iou_fn,
    )
    out = {"variant": matches.variant, "family": matches.family, "num_frames": matches.num_frames}
    for analysis in registered_analyses():
        part = analysis.compute(data)
        if set(part) != set(analysis.schema()):
            raise AttackMetricError(
                f"analysis {analysis.name!r} computed keys {sorted(part)}, but its schema "
                f"states {sorted(analysis.schema())}"
            )
        out.update(part)
    return out
