"""``results.json``: one file per evaluated model. ``schema`` states and checks it (a JSON Schema
plus the invariants between fields; each registered analysis of
:mod:`pcdet_atlas.evaluation.analyses` states and checks its own keys), ``build`` makes its
entries, ``io`` reads and writes it and ``tables`` prints the paper's tables from it; ``report``
writes the paper's report (tables, and figures as PNG and PDF) from several of them
(``tools/report.py``): its own sections and figures (``queries`` reads the data, ``figures``
draws, ``style`` is the figures' one look) and those of every registered analysis; ``archive``
keeps the files a report was made from beside it, gzip-compressed.

Schema (version 8; every key required unless marked optional; unknown keys are errors)::

    {
      "schema_version": 8,
      "model": str,                      # display name, e.g. "CenterPoint-4f"
      "checkpoint": str | null,          # path of the evaluated weights
      "config": str,                     # path of the model config
      "pcdet_atlas_version": str,
      "created": str,                    # ISO 8601 time, e.g. "2026-11-21T08:00:00+00:00"
      "training_seed": int | null,       # the seed the weights were trained with (the
                                         # checkpoint's train_settings, else ATLAS.TRAINING_SEED)
      "model_sha256": str | null,        # digest of the config's CLASS_NAMES, MODEL, OPTIMIZATION
                                         # and DATA_CONFIG (no DATA_PATH): same model, seed aside
      "source_commit": str | null,       # git commit of the code that wrote the file (null: not
      "source_dirty": bool | null,       # a git checkout); whether tracked files differed from it
      "class_names": [str, ...],         # e.g. ["Vehicle", "Pedestrian", "Cyclist"]
      "variants": {                      # variant name -> entry, e.g. "clean", "rem_40"
        <variant>: {
          "family": str,                 # "clean" | "injection" | "removal" | <new family>
          "rank_group": str | null,      # the attack class's RANK_GROUP (robustness ranks)
          "num_frames": int,
          "L1/mAP", "L1/mAPH", "L2/mAP", "L2/mAPH": float in [0, 1] | null,
          "per_class": {<class>: {"L1/AP", "L1/APH", "L2/AP", "L2/APH": float | null}},
          "num_reused_frames", "num_recomputed_frames": int | null,  # clean predictions reused
          "asr", "asr_lenient": float in [0, 1] | null,    # null when num_targets == 0
          "asr_ci": [lo, hi] | null,     # 95% interval, asr_interval (null below 2 runs)
          "num_runs": int | null,        # spoof runs the targets come from
          "runs": [{"sequence": str, "run_id": int, "num_targets": int, "num_success": int,
                    "num_success_lenient": int}, ...] | null,  # per run, sorted (null: before
                                                               # schema 5)
          "num_targets", "num_success", "num_success_lenient": int,
          "num_spoofed_frames", "num_untargeted": int | null,  # spoofed frames; those without
                                                               # a target (phantom not in scan)
          "iou_threshold": float, "score_threshold": float | null, "target_class": str | null,
          "confidence": {...} | null,    # analyses.confidence: injection / removal / <new kind>
          "lifecycle": {...} | null,     # analyses.lifecycle.lifecycle_asr (clean_score_counts:
                                         # the clean run's scores of the same targets per k;
                                         # asr_ci and runs per k, null before schema 6)
          <key of a registered analysis>: ...  # optional unless built in
          "extra": {...}                 # optional, free-form
        }
      },
      "extra": {...}                     # optional, free-form
    }

mAP values are fractions as :func:`waymo_evaluate` returns them; the printers show them x100 with
one decimal and ASR with two decimals, as the paper's tables do.
"""

from pcdet_atlas.evaluation.results.archive import archive_results, archive_run_results
from pcdet_atlas.evaluation.results.build import (
    build_results,
    build_variant_result,
    plain,
    ranks_from_results,
)
from pcdet_atlas.evaluation.results.io import load_results, load_results_dir, save_results
from pcdet_atlas.evaluation.results.report import collect_results, write_report
from pcdet_atlas.evaluation.results.schema import (
    SCHEMA_VERSION,
    ResultsError,
    results_schema,
    validate_results,
)
from pcdet_atlas.evaluation.results.tables import (
    PAPER_VARIANT_LABELS,
    PAPER_VARIANTS,
    format_comparison_table,
    format_ranks,
    format_table,
    ordered_variants,
    variant_label,
)

__all__ = [
    "PAPER_VARIANTS",
    "PAPER_VARIANT_LABELS",
    "ResultsError",
    "SCHEMA_VERSION",
    "archive_results",
    "archive_run_results",
    "build_results",
    "build_variant_result",
    "collect_results",
    "format_comparison_table",
    "format_ranks",
    "format_table",
    "load_results",
    "load_results_dir",
    "ordered_variants",
    "plain",
    "ranks_from_results",
    "results_schema",
    "save_results",
    "validate_results",
    "variant_label",
    "write_report",
]
