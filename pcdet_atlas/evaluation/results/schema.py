"""The ``results.json`` schema (a JSON Schema, checked with ``jsonschema``) and the invariants a
JSON Schema cannot state (counts that must add up); :func:`validate_results` runs both."""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import datetime

import jsonschema

__all__ = [
    "ATTACK_KEYS",
    "CLASS_METRIC_KEYS",
    "METRIC_KEYS",
    "RESULTS_SCHEMA",
    "ResultsError",
    "SCHEMA_VERSION",
    "validate_results",
    "validate_variant",
]

SCHEMA_VERSION = 8
METRIC_KEYS = ("L1/mAP", "L1/mAPH", "L2/mAP", "L2/mAPH")
CLASS_METRIC_KEYS = ("L1/AP", "L1/APH", "L2/AP", "L2/APH")
ATTACK_KEYS = (
    "asr",
    "asr_ci",
    "num_runs",
    "runs",
    "asr_lenient",
    "num_targets",
    "num_success",
    "num_success_lenient",
    "num_spoofed_frames",
    "num_untargeted",
    "iou_threshold",
    "score_threshold",
    "target_class",
    "confidence",
    "lifecycle",
)


class ResultsError(ValueError):
    """A results dict or file that does not follow the schema; the message names the key."""


# ---------------------------------------------------------------------------- JSON Schema
def _nullable(schema: dict) -> dict:
    """``schema`` or null (its other keywords apply to its own type only, so errors stay
    specific, where an ``anyOf`` would only say that no branch matched)."""
    return {**schema, "type": [schema["type"], "null"]}


def _closed(properties: dict, optional: tuple[str, ...] = ()) -> dict:
    """An object with exactly ``properties`` (all required except ``optional``)."""
    return {
        "type": "object",
        "properties": properties,
        "required": [k for k in properties if k not in optional],
        "additionalProperties": False,
    }


_FRAC = {"type": "number", "minimum": 0.0, "maximum": 1.0}
_COUNT = {"type": "integer", "minimum": 0}
_NAME = {"type": "string", "minLength": 1}
_SIGNED_FRAC = {"type": "number", "minimum": -1.0, "maximum": 1.0}
_HISTOGRAM = _closed(
    {
        "bin_edges": {"type": "array", "items": {"type": "number"}, "minItems": 2},
        "counts": {"type": "array", "items": _COUNT},
    }
)
_CONFIDENCE_COMMON = {
    "high_score_threshold": _FRAC,
    "num_targets": _COUNT,
    "num_above": _COUNT,
    "fraction_above": _nullable(_FRAC),
    "histogram": _HISTOGRAM,
}
_CONFIDENCE_KINDS = {
    "injection": _closed(
        {
            "kind": {"const": "injection"},
            **_CONFIDENCE_COMMON,
            "num_detected": _COUNT,
            "mean_score": _nullable(_FRAC),
            "median_score": _nullable(_FRAC),
        }
    ),
    "removal": _closed(
        {
            "kind": {"const": "removal"},
            **_CONFIDENCE_COMMON,
            "num_surviving": _COUNT,
            "num_paired": _COUNT,
            "num_clean_missed": _COUNT,
            "mean_score_drop": _nullable(_SIGNED_FRAC),
            "median_score_drop": _nullable(_SIGNED_FRAC),
            "clean_peak": _nullable(_FRAC),
            "attacked_peak": _nullable(_FRAC),
            "peak_gap": _nullable(_SIGNED_FRAC),
            "paired_attacked_histogram": _HISTOGRAM,
            "paired_clean_histogram": _HISTOGRAM,
        }
    ),
}
#: The analysis named by ``kind`` decides the other keys (a tagged union: errors come from the
#: branch of the entry's own kind).
_CONFIDENCE = {
    "type": "object",
    "required": ["kind"],
    "properties": {"kind": {"enum": list(_CONFIDENCE_KINDS)}},
    "allOf": [
        {
            "if": {"type": "object", "required": ["kind"], "properties": {"kind": {"const": kind}}},
            "then": schema,
        }
        for kind, schema in _CONFIDENCE_KINDS.items()
    ],
}
#: One spoof run's counts (``attack_metrics.run_counts``).
_RUN = _closed(
    {
        "sequence": _NAME,
        "run_id": _COUNT,
        "num_targets": {"type": "integer", "minimum": 1},
        "num_success": _COUNT,
        "num_success_lenient": _COUNT,
    }
)
_LIFECYCLE = _closed(
    {
        "window": {"type": "integer", "minimum": 1},
        "recorded_window": {"type": "integer", "minimum": 1},
        "k": {"type": "array", "items": _COUNT},
        "score_bin_edges": {"type": "array", "items": {"type": "number"}, "minItems": 2},
        "attacked": {"type": "array", "items": {"type": "boolean"}},
        "num_targets": {"type": "array", "items": _COUNT},
        "num_success": {"type": "array", "items": _COUNT},
        "asr": {"type": "array", "items": _nullable(_FRAC)},
        # per k the run-level interval of the ASR; None before schema 6
        "asr_ci": _nullable(
            {
                "type": "array",
                "items": _nullable({"type": "array", "items": _FRAC, "minItems": 2, "maxItems": 2}),
            }
        ),  # fmt: skip
        # per k the per-run counts behind it (pooled intervals); None before schema 6
        "runs": _nullable({"type": "array", "items": {"type": "array", "items": _RUN}}),
        "num_success_lenient": {"type": "array", "items": _COUNT},
        "asr_lenient": {"type": "array", "items": _nullable(_FRAC)},
        "score_counts": {"type": "array", "items": {"type": "array", "items": _COUNT}},
        # the clean run's scores of the same targets per k; None without a clean run / before 4
        "clean_score_counts": _nullable(
            {"type": "array", "items": {"type": "array", "items": _COUNT}}
        ),
    }
)
_VARIANT = _closed(
    {
        "family": _NAME,
        "rank_group": _nullable(_NAME),
        "num_frames": _COUNT,
        **{key: _nullable(_FRAC) for key in METRIC_KEYS},
        "per_class": {
            "type": "object",
            "additionalProperties": _closed({k: _nullable(_FRAC) for k in CLASS_METRIC_KEYS}),
        },
        "asr": _nullable(_FRAC),
        # [lo, hi] intervals.asr_interval; None with < 2 runs or from before schema 3
        "asr_ci": _nullable({"type": "array", "items": _FRAC, "minItems": 2, "maxItems": 2}),
        "num_runs": _nullable(_COUNT),
        # per-run counts, sorted by (sequence, run_id); None before schema 5
        "runs": _nullable({"type": "array", "items": _RUN}),
        "asr_lenient": _nullable(_FRAC),
        "num_targets": _COUNT,
        "num_success": _COUNT,
        "num_success_lenient": _COUNT,
        "num_spoofed_frames": _nullable(_COUNT),  # None: a file from before schema 3
        "num_untargeted": _nullable(_COUNT),
        # frames that took the clean run's prediction / ran the model; None before schema 4
        "num_reused_frames": _nullable(_COUNT),
        "num_recomputed_frames": _nullable(_COUNT),
        "iou_threshold": _FRAC,
        "score_threshold": _nullable(_FRAC),
        "target_class": _nullable(_NAME),
        "confidence": _nullable(_CONFIDENCE),
        "lifecycle": _nullable(_LIFECYCLE),
        "extra": {"type": "object"},
    },
    optional=("extra",),
)
#: ``results.json`` as a JSON Schema (draft 2020-12); invariants: :func:`validate_results`.
RESULTS_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    **_closed(
        {
            "schema_version": {"const": SCHEMA_VERSION},
            "model": _NAME,
            "checkpoint": _nullable(_NAME),
            "config": _NAME,
            "pcdet_atlas_version": _NAME,
            "created": _NAME,
            # the seed the weights were trained with (null: not recorded)
            "training_seed": {"type": ["integer", "null"]},
            # the model config's digest, seed aside (null: not recorded)
            "model_sha256": {"type": ["string", "null"], "pattern": "^[0-9a-f]{64}$"},
            # the git commit of the code that computed the file, and whether tracked files
            # differed from it (null: not a git checkout, or not recorded)
            "source_commit": {"type": ["string", "null"], "pattern": "^[0-9a-f]{40}$"},
            "source_dirty": {"type": ["boolean", "null"]},
            "class_names": {"type": "array", "items": _NAME, "minItems": 1},
            "variants": {
                "type": "object",
                "minProperties": 1,
                "propertyNames": {"minLength": 1},
                "additionalProperties": _VARIANT,
            },
            # free-form, but for the keys stated; a file without them (older) stays valid
            "extra": {
                "type": "object",
                "properties": {
                    # the test split's pcdet_atlas.datasets.fingerprint.dataset_fingerprint
                    "dataset_fingerprint": {"type": "string", "pattern": "^[0-9a-f]{64}$"},
                },
            },
        },
        optional=("extra",),
    ),
}
_VALIDATOR = jsonschema.Draft202012Validator(RESULTS_SCHEMA)
_VARIANT_VALIDATOR = jsonschema.Draft202012Validator(_VARIANT)


# ---------------------------------------------------------------------------- validation
def _at(where: str, path) -> str:
    return where + "".join(f"[{p!r}]" if isinstance(p, str) else f"[{p}]" for p in path)


def _schema_message(error: jsonschema.ValidationError) -> str:
    """The deepest, most specific message of a schema error (a ``oneOf`` names its branch)."""
    if error.validator == "required":
        missing = error.message.split("'")[1]
        return f"missing key '{missing}'"
    if error.validator == "additionalProperties" and isinstance(error.instance, Mapping):
        allowed = set(error.schema.get("properties", {}))
        extra = sorted(set(error.instance) - allowed)
        return f"unknown key {', '.join(map(repr, extra))} (allowed: {sorted(allowed)})"
    return error.message


def _fail(path: str, msg: str) -> None:
    raise ResultsError(f"{path}: {msg}")


def _finite_numbers(value, path: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        _fail(path, f"{value!r} is not a finite number (undefined values are null)")
    if isinstance(value, Mapping):
        for key, item in value.items():
            _finite_numbers(item, f"{path}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _finite_numbers(item, f"{path}[{i}]")


def _rate(rate, num: int, den: int, path: str, num_path: str) -> None:
    if num > den:
        _fail(num_path, f"{num} > num_targets {den}")
    if den == 0 and rate is not None:
        _fail(path, f"must be null when there are no targets, got {rate!r}")
    if den > 0 and (rate is None or abs(rate - num / den) > 1e-9):
        _fail(path, f"{rate!r} != {num}/{den}")


def _histogram(h: Mapping, path: str, total: int | None = None) -> None:
    edges, counts = h["bin_edges"], h["counts"]
    if any(b <= a for a, b in zip(edges, edges[1:])):
        _fail(f"{path}['bin_edges']", "must be strictly increasing")
    if len(counts) != len(edges) - 1:
        _fail(f"{path}['counts']", f"expected {len(edges) - 1} counts, got {len(counts)}")
    if total is not None and sum(counts) != total:
        _fail(f"{path}['counts']", f"sum {sum(counts)} != {total}")


def _confidence(c: Mapping, path: str, num_targets: int) -> None:
    if c["num_targets"] != num_targets:
        _fail(f"{path}['num_targets']", f"{c['num_targets']} != variant num_targets {num_targets}")
    shown = "num_detected" if c["kind"] == "injection" else "num_surviving"
    n = c[shown]
    if n > num_targets:
        _fail(f"{path}['{shown}']", f"{n} > num_targets {num_targets}")
    _rate(
        c["fraction_above"], c["num_above"], n, f"{path}['fraction_above']", f"{path}['num_above']"
    )
    _histogram(c["histogram"], f"{path}['histogram']", total=n)
    if c["kind"] == "removal":
        if c["num_paired"] + c["num_clean_missed"] != n:
            _fail(path, f"num_paired + num_clean_missed != num_surviving {n}")
        for key in ("paired_attacked_histogram", "paired_clean_histogram"):
            _histogram(c[key], f"{path}['{key}']", total=c["num_paired"])


def _lifecycle(lc: Mapping, path: str) -> None:
    w = lc["window"]
    if lc["recorded_window"] < w:
        _fail(f"{path}['recorded_window']", f"must be >= window {w}")
    if lc["k"] != list(range(2 * w + 1)):
        _fail(f"{path}['k']", f"expected [0, ..., {2 * w}], got {lc['k']!r}")
    for key in ("attacked", "num_targets", "num_success", "asr", "asr_ci", "runs",
                "num_success_lenient",
                "asr_lenient", "score_counts", "clean_score_counts"):  # fmt: skip
        if lc[key] is not None and len(lc[key]) != 2 * w + 1:
            _fail(f"{path}['{key}']", f"expected a list of {2 * w + 1} entries")
    if lc["attacked"] != [1 <= k <= w for k in range(2 * w + 1)]:
        _fail(f"{path}['attacked']", "must be True exactly at k = 1..window")
    for k in range(2 * w + 1):
        at, n = f"{path}[k={k}]", lc["num_targets"][k]
        for num_key, rate_key in (("num_success", "asr"), ("num_success_lenient", "asr_lenient")):
            _rate(lc[rate_key][k], lc[num_key][k], n, f"{at}['{rate_key}']", f"{at}['{num_key}']")
        if lc["runs"] is not None:
            counts = [(sum(r[c] for r in lc["runs"][k])) for c in ("num_targets", "num_success")]
            if counts != [n, lc["num_success"][k]]:
                _fail(
                    f"{at}['runs']", f"add up to {counts}, not the {n} targets and their successes"
                )
        ci = None if lc["asr_ci"] is None else lc["asr_ci"][k]
        if ci is not None and not (n and ci[0] <= lc["asr"][k] <= ci[1]):
            _fail(f"{at}['asr_ci']", f"{ci} must hold the ASR {lc['asr'][k]} (targets {n})")
        hist = {"bin_edges": lc["score_bin_edges"], "counts": lc["score_counts"][k]}
        _histogram(hist, f"{at}['score_counts']")
        if sum(lc["score_counts"][k]) > n:
            _fail(f"{at}['score_counts']", f"more scores than targets ({n})")
        if lc["clean_score_counts"] is not None:
            clean = {"bin_edges": lc["score_bin_edges"], "counts": lc["clean_score_counts"][k]}
            _histogram(clean, f"{at}['clean_score_counts']")
            if sum(clean["counts"]) > n:
                _fail(f"{at}['clean_score_counts']", f"more scores than targets ({n})")


def _check_schema(validator: jsonschema.Draft202012Validator, value, where: str) -> None:
    _finite_numbers(value, where)
    error = jsonschema.exceptions.best_match(validator.iter_errors(value))
    if error is not None:
        _fail(_at(where, error.absolute_path), _schema_message(error))


def _runs(v: Mapping, path: str) -> None:
    """The per-run counts add up to the variant's, one entry per run, sorted."""
    runs = v["runs"]
    keys = [(r["sequence"], r["run_id"]) for r in runs]
    if keys != sorted(set(keys)):
        _fail(path, "runs must be unique and sorted by (sequence, run_id)")
    if len(runs) != v["num_runs"]:
        _fail(path, f"{len(runs)} runs != num_runs {v['num_runs']}")
    for i, r in enumerate(runs):
        for key in ("num_success", "num_success_lenient"):
            if r[key] > r["num_targets"]:
                _fail(f"{path}[{i}]['{key}']", f"{r[key]} > num_targets {r['num_targets']}")
    for key in ("num_targets", "num_success", "num_success_lenient"):
        total = sum(r[key] for r in runs)
        if total != v[key]:
            _fail(path, f"the runs' {key} add up to {total}, not {v[key]}")


def _variant_invariants(v: Mapping, path: str, class_names: list[str]) -> None:
    if set(v["per_class"]) != set(class_names):
        _fail(f"{path}['per_class']", f"classes {sorted(v['per_class'])} != {class_names}")
    n = v["num_targets"]
    ci = v["asr_ci"]
    if ci is not None and (v["asr"] is None or ci[0] > ci[1]):
        _fail(f"{path}['asr_ci']", f"{ci} is not an interval [lo <= hi] of an ASR {v['asr']}")
    if ci is not None and (v["num_runs"] is None or v["num_runs"] < 2):
        _fail(f"{path}['asr_ci']", f"must be null with num_runs {v['num_runs']} (< 2 runs)")
    if v["num_runs"] is not None and v["num_runs"] > n:
        _fail(f"{path}['num_runs']", f"{v['num_runs']} runs > num_targets {n}")
    if v["runs"] is not None:
        _runs(v, f"{path}['runs']")
    spoofed, untargeted = v["num_spoofed_frames"], v["num_untargeted"]
    if (spoofed is None) != (untargeted is None) or (
        spoofed is not None and (untargeted > spoofed or n > spoofed)
    ):
        _fail(
            f"{path}['num_untargeted']",
            f"{v['num_untargeted']} untargeted and {n} targets of {v['num_spoofed_frames']} "
            "spoofed frames",
        )
    for num_key, rate_key in (("num_success", "asr"), ("num_success_lenient", "asr_lenient")):
        _rate(v[rate_key], v[num_key], n, f"{path}['{rate_key}']", f"{path}['{num_key}']")
    reused, recomputed = v["num_reused_frames"], v["num_recomputed_frames"]
    if (reused is None) != (recomputed is None) or (
        reused is not None and reused + recomputed != v["num_frames"]
    ):
        _fail(
            f"{path}['num_reused_frames']",
            f"{reused} reused + {recomputed} recomputed frames != num_frames {v['num_frames']}",
        )
    if v["confidence"] is not None:
        _confidence(v["confidence"], f"{path}['confidence']", n)
    if v["lifecycle"] is not None:
        _lifecycle(v["lifecycle"], f"{path}['lifecycle']")


def validate_variant(entry: Mapping, where: str, class_names: list[str]) -> None:
    """Check one ``variants`` entry (schema and invariants); errors name ``where`` and the key."""
    _check_schema(_VARIANT_VALIDATOR, entry, where)
    _variant_invariants(entry, where, class_names)


def validate_results(results: Mapping, where: str = "results") -> None:
    """Check a results dict against :data:`RESULTS_SCHEMA` and the invariants between its
    fields; raise :class:`ResultsError` naming the path of the bad key."""
    _check_schema(_VALIDATOR, results, where)
    try:
        datetime.fromisoformat(results["created"])
    except ValueError:
        _fail(f"{where}['created']", f"not an ISO 8601 time: {results['created']!r}")
    names = results["class_names"]
    if len(set(names)) != len(names):
        _fail(f"{where}['class_names']", f"duplicate class in {names!r}")
    for name, v in results["variants"].items():
        _variant_invariants(v, f"{where}['variants'][{name!r}]", names)
