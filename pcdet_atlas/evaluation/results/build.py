"""Building ``results.json`` entries from the metrics of an evaluation run, and the robustness
ranks of several runs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime, timezone

import numpy as np

from pcdet_atlas.evaluation.analyses.asr import paired_asr_differences
from pcdet_atlas.evaluation.analyses.matching import AttackMetricError
from pcdet_atlas.evaluation.analyses.ranks import robustness_ranks
from pcdet_atlas.evaluation.analyses.registry import registered_analyses
from pcdet_atlas.evaluation.results.schema import (
    CLASS_METRIC_KEYS,
    METRIC_KEYS,
    SCHEMA_VERSION,
    ResultsError,
    validate_results,
    validate_variant,
)
from pcdet_atlas.utils.provenance import SourceRevision
from pcdet_atlas.version import __version__

__all__ = [
    "build_results",
    "build_variant_result",
    "paired_from_results",
    "plain",
    "ranks_from_results",
]


def plain(value):
    """numpy scalars / arrays -> Python types, recursively (JSON-ready)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    return value


def build_variant_result(
    variant: str,
    *,
    family: str,
    num_frames: int,
    metrics: Mapping[str, float] | None,
    class_names: Sequence[str],
    attack: Mapping | None = None,
    extra: Mapping | None = None,
    rank_group: str | None = None,
    num_reused_frames: int | None = None,
) -> dict:
    """One ``variants`` entry from the Waymo metric and the attack metrics of that variant.

    Args:
        variant: the variant name (checked against ``attack['variant']``).
        family: the attack family of the variant.
        rank_group: the family's robustness-rank group (its ``RANK_GROUP``), None if unranked.
        num_frames: number of evaluated frames.
        metrics: :func:`waymo_evaluate` output (``'L2/mAP'`` ..., ``'<Class>/L2/AP'`` ...; other
            keys such as PR curves are not stored); None when the split has no ground truth.
        class_names: the evaluated classes (keys of ``per_class``).
        attack: :func:`~pcdet_atlas.evaluation.analyses.evaluate_attack` output; None for a
            variant without targets (clean), which stores each analysis's empty values (ASR
            None and zero counts).
        num_reused_frames: frames that took the clean run's prediction instead of running the
            model (the rest count as recomputed); None: not recorded.
    """
    entry: dict = {"family": family, "rank_group": rank_group, "num_frames": int(num_frames)}
    entry["num_reused_frames"] = None if num_reused_frames is None else int(num_reused_frames)
    entry["num_recomputed_frames"] = (
        None if num_reused_frames is None else int(num_frames) - int(num_reused_frames)
    )
    for key in METRIC_KEYS:
        entry[key] = None if metrics is None else metrics[key]
    entry["per_class"] = {
        cls: {k: None if metrics is None else metrics[f"{cls}/{k}"] for k in CLASS_METRIC_KEYS}
        for cls in class_names
    }
    if attack is None:
        for analysis in registered_analyses():
            entry.update(analysis.empty())
    else:
        for key, want in (("variant", variant), ("family", family), ("num_frames", num_frames)):
            if key in attack and attack[key] != want:
                raise ResultsError(
                    f"variant {variant!r}: attack metrics have {key}={attack[key]!r}, expected "
                    f"{want!r}"
                )
        for analysis in registered_analyses():
            for key in analysis.schema():
                if key not in attack:
                    raise ResultsError(
                        f"variant {variant!r}: attack metrics lack key '{key}' (analysis "
                        f"{analysis.name!r})"
                    )
                entry[key] = attack[key]
    if extra is not None:
        entry["extra"] = dict(extra)
    entry = plain(entry)
    validate_variant(entry, f"variants[{variant!r}]", list(class_names))
    return entry


def build_results(
    *,
    model: str,
    config: str,
    checkpoint: str | None,
    class_names: Sequence[str],
    variants: Mapping[str, Mapping],
    created: str | None = None,
    extra: Mapping | None = None,
    training_seed: int | None = None,
    model_sha256: str | None = None,
    source: SourceRevision | None = None,
) -> dict:
    """A complete, validated results dict (``created`` defaults to now, UTC). ``training_seed``:
    the seed the checkpoint was trained with; ``model_sha256``: the digest of the model's config
    without the seed (``pcdet_atlas.train_utils.checkpoint.model_config_sha256``): two results
    with the same digest and different seeds measure the seed's share of a difference (the
    report's "Seed-to-seed spread"); ``source``: the git revision of the code that computed the
    results (:func:`pcdet_atlas.utils.provenance.source_revision`); None: not recorded."""
    results = {
        "schema_version": SCHEMA_VERSION,
        "model": model,
        "checkpoint": None if checkpoint is None else str(checkpoint),
        "config": str(config),
        "pcdet_atlas_version": __version__,
        "created": created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "training_seed": None if training_seed is None else int(training_seed),
        "model_sha256": model_sha256,
        "source_commit": None if source is None else source.commit,
        "source_dirty": None if source is None else source.dirty,
        "class_names": list(class_names),
        "variants": {name: dict(entry) for name, entry in variants.items()},
    }
    if extra is not None:
        results["extra"] = dict(extra)
    results = plain(results)
    validate_results(results)
    return results


def ranks_from_results(
    results_list: Sequence[Mapping],
    *,
    variants: Sequence[str] | None = None,
    tie_method: str = "average",
) -> dict:
    """:func:`~pcdet_atlas.evaluation.analyses.ranks.robustness_ranks` over several models'
    results (one per model).

    ``variants`` restricts the settings ranked (default: every variant of the first model with a
    ``rank_group``; every model must have them all, in the same group).

    Raises:
        ResultsError: two models of one name, or a variant missing or in another rank group.
        AttackMetricError: a ranked variant without an ASR (no targets), naming model and variant.
    """
    models = [r["model"] for r in results_list]
    if len(set(models)) != len(models):
        raise ResultsError(f"model names must be unique to rank them, got {models}")
    first = results_list[0]["variants"]
    names = list(first) if variants is None else list(variants)
    groups = {}
    for name in names:
        if name not in first:
            raise ResultsError(f"{results_list[0]['model']}: no variant {name!r}")
        if first[name]["rank_group"] is not None:
            groups[name] = first[name]["rank_group"]
    asr = {}
    for r in results_list:
        asr[r["model"]] = {}
        for name in groups:
            if name not in r["variants"]:
                raise ResultsError(f"{r['model']}: no variant {name!r} to rank")
            if r["variants"][name]["rank_group"] != groups[name]:
                raise ResultsError(f"{r['model']}: variant {name!r} has another rank group")
            asr[r["model"]][name] = r["variants"][name]["asr"]
    return robustness_ranks(asr, groups, tie_method=tie_method)


def paired_from_results(results_list: Sequence[Mapping], variants: Sequence[str]) -> dict:
    """:func:`~pcdet_atlas.evaluation.analyses.asr.paired_asr_differences` of several
    models' results over ``variants`` (one rank group's, say), from their per-run counts.

    Raises:
        ResultsError: a model without one of the variants, or whose file has no per-run counts
            (written before schema 5), or models not scored on the same runs, naming them.
    """
    runs = {}
    for r in results_list:
        runs[r["model"]] = {}
        for name in variants:
            entry = r["variants"].get(name)
            if entry is None:
                raise ResultsError(f"{r['model']}: no variant {name!r} to compare")
            if entry["runs"] is None:
                raise ResultsError(
                    f"{r['model']}, variant {name!r}: no per-run counts (a results.json from "
                    "before schema 5; evaluate it again)"
                )
            runs[r["model"]][name] = entry["runs"]
    try:
        return paired_asr_differences(runs)
    except AttackMetricError as err:
        raise ResultsError(str(err)) from err
