"""Evaluation: the Waymo L1/L2 AP/APH metric, attack success rate and the other analyses
(:mod:`~pcdet_atlas.evaluation.analyses`, a registry), and ``results.json`` with its report (the
box IoU and NMS they use are in :mod:`pcdet_atlas.ops`)."""

# the analyses first: their built-ins register before results reads the registry
from pcdet_atlas.evaluation.analyses import (
    AttackMetricError,
    TargetMatches,
    asr_from_matches,
    attack_success_rate,
    evaluate_attack,
    injection_confidence,
    lifecycle_asr,
    linear_fit,
    match_targets,
    paired_asr_differences,
    register_analysis,
    removal_confidence,
    robustness_ranks,
    run_counts,
)
from pcdet_atlas.evaluation.intervals import asr_interval, coverage_simulation
from pcdet_atlas.evaluation.localization import ap_by_iou, localization_errors
from pcdet_atlas.evaluation.results import (
    ResultsError,
    build_results,
    build_variant_result,
    format_comparison_table,
    format_ranks,
    format_table,
    load_results,
    load_results_dir,
    ranks_from_results,
    save_results,
    validate_results,
)
from pcdet_atlas.evaluation.waymo_metric import (
    WAYMO_IOU_THRESHOLDS,
    WAYMO_SCORE_CUTOFFS,
    compute_waymo_curves,
    summarize_waymo_curves,
    waymo_average_precision,
    waymo_evaluate,
    waymo_heading_accuracy,
)

__all__ = [
    "AttackMetricError",
    "ResultsError",
    "TargetMatches",
    "WAYMO_IOU_THRESHOLDS",
    "WAYMO_SCORE_CUTOFFS",
    "ap_by_iou",
    "asr_from_matches",
    "asr_interval",
    "attack_success_rate",
    "build_results",
    "build_variant_result",
    "compute_waymo_curves",
    "coverage_simulation",
    "evaluate_attack",
    "format_comparison_table",
    "format_ranks",
    "format_table",
    "injection_confidence",
    "lifecycle_asr",
    "linear_fit",
    "localization_errors",
    "load_results",
    "load_results_dir",
    "match_targets",
    "paired_asr_differences",
    "ranks_from_results",
    "register_analysis",
    "removal_confidence",
    "robustness_ranks",
    "run_counts",
    "save_results",
    "summarize_waymo_curves",
    "validate_results",
    "waymo_average_precision",
    "waymo_evaluate",
    "waymo_heading_accuracy",
]
