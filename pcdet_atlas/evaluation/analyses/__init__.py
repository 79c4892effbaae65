"""Attack analyses (docs/evaluation.md "Attack metrics"): one pass matches a variant's targets
(:mod:`.matching`), then each registered analysis reads the match (:mod:`.registry`) and owns
its keys of ``results.json``, its report tables and its figures.

The computation of each concern lives in its own module: :mod:`.asr` (success rate, per-run
counts, paired differences), :mod:`.confidence` (score statistics by confidence kind),
:mod:`.lifecycle` (ASR by lifecycle position), :mod:`.ranks` (robustness ranks) and
:mod:`.scores` (histograms, peaks); the registered analyses that bring them into results and
the report are :mod:`.asr_analysis`, :mod:`.attributable_analysis` (computation and analysis in
one module: the ASR over the targets whose outcome the clean run would not already give),
:mod:`.confidence_analysis`, :mod:`.lifecycle_analysis` and :mod:`.ranks_analysis`, imported
last here so that they register in that order.
"""

# the built-in analyses register on import, in this order (their keys' order in an entry)
from pcdet_atlas.evaluation.analyses import (
    asr_analysis,  # noqa: E402, I001
    attributable_analysis,  # noqa: E402
    confidence_analysis,  # noqa: E402
    lifecycle_analysis,  # noqa: E402
    ranks_analysis,  # noqa: E402
)
from pcdet_atlas.evaluation.analyses.asr import (
    CI_LEVEL,
    asr_from_matches,
    attack_success_rate,
    paired_asr_differences,
    run_counts,
)
from pcdet_atlas.evaluation.analyses.confidence import (
    CONFIDENCE_KINDS,
    ConfidenceKind,
    injection_confidence,
    register_confidence_kind,
    removal_confidence,
)
from pcdet_atlas.evaluation.analyses.evaluate import evaluate_attack
from pcdet_atlas.evaluation.analyses.lifecycle import (
    SCHEDULE_WINDOW,
    lifecycle_asr,
    lifecycle_position,
)
from pcdet_atlas.evaluation.analyses.matching import (
    ASR_IOU_THRESHOLD,
    DEFAULT_TARGET_CLASS,
    SCORING_KEYS,
    AttackMetricError,
    TargetMatches,
    clean_matched_scores,
    match_targets,
)
from pcdet_atlas.evaluation.analyses.ranks import linear_fit, robustness_ranks
from pcdet_atlas.evaluation.analyses.registry import (
    ANALYSES,
    Analysis,
    ReportFigure,
    ReportSection,
    VariantData,
    register_analysis,
    registered_analyses,
)
from pcdet_atlas.evaluation.analyses.schema_parts import ResultsError
from pcdet_atlas.evaluation.analyses.scores import (
    HIGH_SCORE_THRESHOLD,
    NUM_SCORE_BINS,
    score_histogram,
    score_peak,
)

__all__ = [
    "ANALYSES",
    "ASR_IOU_THRESHOLD",
    "Analysis",
    "AttackMetricError",
    "CI_LEVEL",
    "CONFIDENCE_KINDS",
    "ConfidenceKind",
    "DEFAULT_TARGET_CLASS",
    "HIGH_SCORE_THRESHOLD",
    "NUM_SCORE_BINS",
    "ReportFigure",
    "ReportSection",
    "ResultsError",
    "SCHEDULE_WINDOW",
    "SCORING_KEYS",
    "TargetMatches",
    "VariantData",
    "asr_analysis",
    "asr_from_matches",
    "attack_success_rate",
    "attributable_analysis",
    "clean_matched_scores",
    "confidence_analysis",
    "evaluate_attack",
    "injection_confidence",
    "lifecycle_analysis",
    "lifecycle_asr",
    "lifecycle_position",
    "linear_fit",
    "match_targets",
    "paired_asr_differences",
    "ranks_analysis",
    "register_analysis",
    "register_confidence_kind",
    "registered_analyses",
    "removal_confidence",
    "robustness_ranks",
    "run_counts",
    "score_histogram",
    "score_peak",
]
