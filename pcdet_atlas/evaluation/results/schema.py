"""The ``results.json`` schema (a JSON Schema, checked with ``jsonschema``) and the invariants a
JSON Schema cannot state (counts that must add up); :func:`validate_results` runs both. A variant
entry holds the core keys stated here and the keys of every registered analysis
(:mod:`pcdet_atlas.evaluation.analyses`), each stating and checking its own part."""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import datetime

import jsonschema

from pcdet_atlas.evaluation.analyses.registry import registered_analyses
from pcdet_atlas.evaluation.analyses.schema_parts import (
    COUNT,
    FRAC,
    NAME,
    ResultsError,
    closed,
    fail,
    nullable,
)

__all__ = [
    "CLASS_METRIC_KEYS",
    "METRIC_KEYS",
    "ResultsError",
    "SCHEMA_VERSION",
    "results_schema",
    "validate_results",
    "validate_variant",
    "variant_schema",
]

SCHEMA_VERSION = 8
METRIC_KEYS = ("L1/mAP", "L1/mAPH", "L2/mAP", "L2/mAPH")
CLASS_METRIC_KEYS = ("L1/AP", "L1/APH", "L2/AP", "L2/APH")
SHA256 = {"type": "string", "pattern": "^[0-9a-f]{64}$"}


# ---------------------------------------------------------------------------- JSON Schema
def _core_properties() -> dict:
    """The keys of a variant entry that no analysis owns: family, frames, the Waymo metric."""
    return {
        "family": NAME,
        "rank_group": nullable(NAME),
        "num_frames": COUNT,
        **{key: nullable(FRAC) for key in METRIC_KEYS},
        "per_class": {
            "type": "object",
            "additionalProperties": closed({k: nullable(FRAC) for k in CLASS_METRIC_KEYS}),
        },
        # frames that took the clean run's prediction / ran the model; None before schema 4
        "num_reused_frames": nullable(COUNT),
        "num_recomputed_frames": nullable(COUNT),
        # free-form, but for the keys stated; an older entry without them stays valid
        "extra": {
            "type": "object",
            "properties": {
                # the SHA-256 of the variant's result.pkl, and of the clean variant's proposal
                # parts (pcdet_atlas.train_utils.eval_folder: a resumed call checks them)
                "result_sha256": SHA256,
                "proposals_sha256": {
                    "type": "object",
                    "propertyNames": {"pattern": "^proposals_rank[0-9]+[.]pkl$"},
                    "additionalProperties": SHA256,
                },
            },
        },
    }


def variant_schema() -> dict:
    """A ``variants`` entry: the core keys and those of every registered analysis (required for
    the built-ins, optional for the others, so that older files stay valid)."""
    properties, optional = _core_properties(), ["extra"]
    for analysis in registered_analyses():
        for key, schema in analysis.schema().items():
            if key in properties:
                raise ResultsError(f"analysis {analysis.name!r} states key {key!r}, a core key")
            properties[key] = schema
            if not analysis.required:
                optional.append(key)
    return closed(properties, optional=tuple(optional))


def results_schema() -> dict:
    """``results.json`` as a JSON Schema (draft 2020-12), with the registered analyses' keys;
    invariants: :func:`validate_results`."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        **closed(
            {
                "schema_version": {"const": SCHEMA_VERSION},
                "model": NAME,
                "checkpoint": nullable(NAME),
                "config": NAME,
                "pcdet_atlas_version": NAME,
                "created": NAME,
                # the seed the weights were trained with (null: not recorded)
                "training_seed": {"type": ["integer", "null"]},
                # the model config's digest, seed aside (null: not recorded)
                "model_sha256": {"type": ["string", "null"], "pattern": "^[0-9a-f]{64}$"},
                # the git commit of the code that computed the file, and whether tracked files
                # differed from it (null: not a git checkout, or not recorded)
                "source_commit": {"type": ["string", "null"], "pattern": "^[0-9a-f]{40}$"},
                "source_dirty": {"type": ["boolean", "null"]},
                "class_names": {"type": "array", "items": NAME, "minItems": 1},
                "variants": {
                    "type": "object",
                    "minProperties": 1,
                    "propertyNames": {"minLength": 1},
                    "additionalProperties": variant_schema(),
                },
                # free-form, but for the keys stated; a file without them (older) stays valid
                "extra": {
                    "type": "object",
                    "properties": {
                        # the test split's pcdet_atlas.datasets.fingerprint.dataset_fingerprint
                        "dataset_fingerprint": SHA256,
                    },
                },
            },
            optional=("extra",),
        ),
    }


_VALIDATORS: dict[str, jsonschema.Draft202012Validator] = {}


def _validator(schema: dict) -> jsonschema.Draft202012Validator:
    """A validator of ``schema``, built once per distinct schema (analyses may register later)."""
    key = repr(schema)
    if key not in _VALIDATORS:
        _VALIDATORS[key] = jsonschema.Draft202012Validator(schema)
    return _VALIDATORS[key]


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


def _finite_numbers(value, path: str) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        fail(path, f"{value!r} is not a finite number (undefined values are null)")
    if isinstance(value, Mapping):
        for key, item in value.items():
            _finite_numbers(item, f"{path}[{key!r}]")
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _finite_numbers(item, f"{path}[{i}]")


def _check_schema(validator: jsonschema.Draft202012Validator, value, where: str) -> None:
    _finite_numbers(value, where)
    error = jsonschema.exceptions.best_match(validator.iter_errors(value))
    if error is not None:
        fail(_at(where, error.absolute_path), _schema_message(error))


def _variant_invariants(v: Mapping, path: str, class_names: list[str]) -> None:
    """The core keys' invariants, then each analysis's (:meth:`Analysis.check`) where the entry
    holds its keys."""
    if set(v["per_class"]) != set(class_names):
        fail(f"{path}['per_class']", f"classes {sorted(v['per_class'])} != {class_names}")
    reused, recomputed = v["num_reused_frames"], v["num_recomputed_frames"]
    if (reused is None) != (recomputed is None) or (
        reused is not None and reused + recomputed != v["num_frames"]
    ):
        fail(
            f"{path}['num_reused_frames']",
            f"{reused} reused + {recomputed} recomputed frames != num_frames {v['num_frames']}",
        )
    for analysis in registered_analyses():
        if all(key in v for key in analysis.schema()):
            analysis.check(v, path)


def validate_variant(entry: Mapping, where: str, class_names: list[str]) -> None:
    """Check one ``variants`` entry (schema and invariants); errors name ``where`` and the key."""
    _check_schema(_validator(variant_schema()), entry, where)
    _variant_invariants(entry, where, class_names)


def validate_results(results: Mapping, where: str = "results") -> None:
    """Check a results dict against :func:`results_schema` and the invariants between its
    fields; raise :class:`ResultsError` naming the path of the bad key."""
    _check_schema(_validator(results_schema()), results, where)
    try:
        datetime.fromisoformat(results["created"])
    except ValueError:
        fail(f"{where}['created']", f"not an ISO 8601 time: {results['created']!r}")
    names = results["class_names"]
    if len(set(names)) != len(names):
        fail(f"{where}['class_names']", f"duplicate class in {names!r}")
    for name, v in results["variants"].items():
        _variant_invariants(v, f"{where}['variants'][{name!r}]", names)
