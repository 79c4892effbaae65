"""Reading and writing ``results.json`` (validated both ways; written atomically)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from pcdet_atlas.evaluation.results.build import plain
from pcdet_atlas.evaluation.results.schema import ResultsError, validate_results
from pcdet_atlas.utils.common import write_atomic

__all__ = [
    "load_results",
    "load_results_dir",
    "save_results",
    "upgrade_v1",
    "upgrade_v2",
    "upgrade_v3",
    "upgrade_v4",
]


def save_results(results: Mapping, path: str | Path) -> Path:
    """Validate and write ``results`` as JSON (NaN is refused: undefined values are null)."""
    results = plain(results)
    validate_results(results, where=str(path))
    text = json.dumps(results, indent=2, allow_nan=False) + "\n"
    return write_atomic(path, lambda f: f.write(text.encode()))


def load_results(path: str | Path) -> dict:
    """Read and validate one ``results.json``; errors name the file and the key."""
    path = Path(path)
    try:
        with open(path) as f:
            results = json.load(f)
    except json.JSONDecodeError as err:
        raise ResultsError(f"{path}: not valid JSON ({err})") from err
    if isinstance(results, dict) and results.get("schema_version") == 1:
        results = upgrade_v1(results)
    if isinstance(results, dict) and results.get("schema_version") == 2:
        results = upgrade_v2(results)
    if isinstance(results, dict) and results.get("schema_version") == 3:
        results = upgrade_v3(results)
    if isinstance(results, dict) and results.get("schema_version") == 4:
        results = upgrade_v4(results)
    validate_results(results, where=str(path))
    return results


#: Schema 1 predates ``rank_group``; its only ranked families were these, each its own group.
_V1_RANK_GROUPS = {"injection": "injection", "removal": "removal"}


def upgrade_v1(results: dict) -> dict:
    """A schema-1 results dict as schema 2: each variant gains the ``rank_group`` its family had
    (the only change between the two)."""
    variants = results.get("variants")
    if not isinstance(variants, dict):
        return results  # validation names what is wrong
    upgraded = {
        name: {**entry, "rank_group": _V1_RANK_GROUPS.get(entry.get("family"))}
        if isinstance(entry, dict)
        else entry
        for name, entry in variants.items()
    }
    return {**results, "schema_version": 2, "variants": upgraded}


def upgrade_v2(results: dict) -> dict:
    """A schema-2 results dict as schema 3: each variant gains ``asr_ci``, ``num_runs``,
    ``num_spoofed_frames`` and ``num_untargeted`` as None (unknown: schema 2 did not have them)."""
    variants = results.get("variants")
    if not isinstance(variants, dict):
        return results  # validation names what is wrong
    upgraded = {
        name: {
            **entry,
            "asr_ci": None,
            "num_runs": None,
            "num_spoofed_frames": None,
            "num_untargeted": None,
        }  # fmt: skip
        if isinstance(entry, dict)
        else entry
        for name, entry in variants.items()
    }
    return {**results, "schema_version": 3, "variants": upgraded}


def upgrade_v3(results: dict) -> dict:
    """A schema-3 results dict as schema 4: each variant gains ``num_reused_frames`` and
    ``num_recomputed_frames`` as None, and its lifecycle ``clean_score_counts`` as None
    (schema 3 did not record them)."""
    variants = results.get("variants")
    if not isinstance(variants, dict):
        return results  # validation names what is wrong
    upgraded = {}
    for name, entry in variants.items():
        if isinstance(entry, dict):
            entry = {**entry, "num_reused_frames": None, "num_recomputed_frames": None}
            if isinstance(entry.get("lifecycle"), dict):
                entry["lifecycle"] = {**entry["lifecycle"], "clean_score_counts": None}
        upgraded[name] = entry
    return {**results, "schema_version": 4, "variants": upgraded}


def upgrade_v4(results: dict) -> dict:
    """A schema-4 results dict as schema 5: each variant gains ``runs`` (the per-run counts) as
    None (schema 4 did not record them)."""
    variants = results.get("variants")
    if not isinstance(variants, dict):
        return results  # validation names what is wrong
    upgraded = {
        name: {**entry, "runs": None} if isinstance(entry, dict) else entry
        for name, entry in variants.items()
    }
    return {**results, "schema_version": 5, "variants": upgraded}


def load_results_dir(root: str | Path, pattern: str = "**/results.json") -> list[dict]:
    """All results files under ``root`` matching ``pattern``, sorted by path."""
    paths = sorted(Path(root).glob(pattern))
    if not paths:
        raise ResultsError(f"{root}: no file matches {pattern!r}")
    return [load_results(p) for p in paths]
