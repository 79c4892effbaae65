"""Reading and writing ``results.json`` (validated both ways; written atomically)."""

from __future__ import annotations

import gzip
import json
import zlib
from collections.abc import Mapping
from pathlib import Path

from pcdet_atlas.evaluation.results.build import plain
from pcdet_atlas.evaluation.results.schema import SCHEMA_VERSION, ResultsError, validate_results
from pcdet_atlas.utils.common import write_atomic

__all__ = [
    "RESULTS_FILE_PATTERNS",
    "check_version_content",
    "find_results_files",
    "load_results",
    "load_results_dir",
    "read_results_bytes",
    "save_results",
    "upgrade_v1",
    "upgrade_v2",
    "upgrade_v3",
    "upgrade_v4",
    "upgrade_v5",
    "upgrade_v6",
]


def save_results(results: Mapping, path: str | Path) -> Path:
    """Validate and write ``results`` as JSON (NaN is refused: undefined values are null)."""
    results = plain(results)
    validate_results(results, where=str(path))
    text = json.dumps(results, indent=2, allow_nan=False) + "\n"
    return write_atomic(path, lambda f: f.write(text.encode()))


#: The names of results files a folder is searched for (``**/`` below it): the ``results.json``
#: of ``tools/test.py`` and the archived ``<model>.results.json.gz`` of a report
#: (:mod:`~pcdet_atlas.evaluation.results.archive`), either plain or gzip-compressed.
RESULTS_FILE_PATTERNS = ("results.json", "results.json.gz", "*.results.json", "*.results.json.gz")


def find_results_files(folder: str | Path) -> list[Path]:
    """Every results file below ``folder`` (:data:`RESULTS_FILE_PATTERNS`), sorted by path."""
    folder = Path(folder)
    return sorted({p for pattern in RESULTS_FILE_PATTERNS for p in folder.glob(f"**/{pattern}")})


def read_results_bytes(path: str | Path) -> bytes:
    """The JSON bytes of a results file: a name ending in ``.gz`` is gunzipped (a file that is not
    a whole gzip stream is a :class:`ResultsError` naming it), any other is read as it is."""
    path = Path(path)
    data = path.read_bytes()
    if not path.name.endswith(".gz"):
        return data
    try:
        return gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as err:  # BadGzipFile is an OSError; EOF: truncated
        raise ResultsError(
            f"{path}: not a readable gzip file ({type(err).__name__}: {err}); a name ending in "
            ".gz must hold a whole gzip-compressed results.json (truncated or not compressed?)"
        ) from err


def load_results(path: str | Path) -> dict:
    """Read and validate one ``results.json`` (gzip-compressed when its name ends in ``.gz``),
    upgrading an older schema version; errors name the file and the key."""
    path = Path(path)
    try:
        results = json.loads(read_results_bytes(path).decode("utf-8"))
    except UnicodeDecodeError as err:
        raise ResultsError(f"{path}: not UTF-8 text ({err})") from err
    except json.JSONDecodeError as err:
        raise ResultsError(f"{path}: not valid JSON ({err})") from err
    for version, upgrade in enumerate(UPGRADES, start=1):  # each version to the next in turn
        if isinstance(results, dict) and results.get("schema_version") == version:
            results = upgrade(results, where=str(path))
    validate_results(results, where=str(path))
    return results


#: Schema 1 predates ``rank_group``; its only ranked families were these, each its own group.
_V1_RANK_GROUPS = {"injection": "injection", "removal": "removal"}
#: The keys of a ``variants`` entry (``lifecycle.``: of its lifecycle) that each schema version
#: added; a file of an older version holds none of them, and its upgrade adds them.
_ADDED_IN = {
    "rank_group": 2, "asr_ci": 3, "num_runs": 3, "num_spoofed_frames": 3, "num_untargeted": 3,
    "num_reused_frames": 4, "num_recomputed_frames": 4, "lifecycle.clean_score_counts": 4,
    "runs": 5, "lifecycle.asr_ci": 6, "lifecycle.runs": 6,
}  # fmt: skip
#: The top-level keys each schema version added (as :data:`_ADDED_IN` for a variant's).
_TOP_ADDED_IN = {
    "training_seed": 7,
    "model_sha256": 7,
    "source_commit": 8,
    "source_dirty": 8,
}


def check_version_content(results: dict, where: str = "results") -> None:
    """Refuse a file whose ``schema_version`` its content contradicts: a variant holding a value
    under a key that only a later version has (upgrading it would overwrite the value; a null
    there is what the upgrade sets anyway). Raises :class:`ResultsError` naming the file, the
    version and the key."""
    version, variants = results.get("schema_version"), results.get("variants")
    if type(version) is not int or version >= SCHEMA_VERSION or not isinstance(variants, dict):
        return  # validation names what is wrong
    for key, added in _TOP_ADDED_IN.items():
        if results.get(key) is not None and added > version:
            raise ResultsError(
                f"{where}: has {key!r}, a key of schema {added} and later, but the file says "
                f"schema_version {version}: the version contradicts the content (an upgrade "
                "would overwrite the key); set schema_version to the version the file was "
                "written with"
            )
    for name, entry in variants.items():
        if not isinstance(entry, dict):
            continue
        lifecycle = entry.get("lifecycle") if isinstance(entry.get("lifecycle"), dict) else {}
        for key, added in _ADDED_IN.items():
            held = lifecycle.get(key.split(".", 1)[1]) if "." in key else entry.get(key)
            if held is not None and added > version:
                raise ResultsError(
                    f"{where}['variants'][{name!r}]: has {key!r}, a key of schema {added} and "
                    f"later, but the file says schema_version {version}: the version contradicts "
                    "the content (an upgrade would overwrite the key); set schema_version to "
                    "the version the file was written with"
                )


def upgrade_v1(results: dict, *, where: str = "results") -> dict:
    """A schema-1 results dict as schema 2: each variant gains the ``rank_group`` its family had
    (the only change between the two). A file whose content contradicts its version is refused
    (:func:`check_version_content`), as by every upgrade."""
    check_version_content(results, where)
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


def _with_nulls(
    results: dict,
    version: int,
    where: str,
    keys: tuple[str, ...],
    lifecycle_keys: tuple[str, ...],
    top_keys: tuple[str, ...] = (),
) -> dict:
    """``results`` as schema ``version``: every variant gains ``keys`` and its lifecycle (when
    it has one) ``lifecycle_keys``, and the file ``top_keys``, all None (the older schema did not
    record them)."""
    check_version_content(results, where)
    variants = results.get("variants")
    if not isinstance(variants, dict):
        return results  # validation names what is wrong
    upgraded = {}
    for name, entry in variants.items():
        if isinstance(entry, dict):
            entry = {**entry, **dict.fromkeys(keys)}
            if lifecycle_keys and isinstance(entry.get("lifecycle"), dict):
                entry["lifecycle"] = {**entry["lifecycle"], **dict.fromkeys(lifecycle_keys)}
        upgraded[name] = entry
    top = dict.fromkeys(top_keys)
    return {**results, **top, "schema_version": version, "variants": upgraded}


def upgrade_v2(results: dict, *, where: str = "results") -> dict:
    """A schema-2 results dict as schema 3: each variant gains ``asr_ci``, ``num_runs``,
    ``num_spoofed_frames`` and ``num_untargeted`` as None (unknown: schema 2 did not have them)."""
    keys = ("asr_ci", "num_runs", "num_spoofed_frames", "num_untargeted")
    return _with_nulls(results, 3, where, keys, ())


def upgrade_v3(results: dict, *, where: str = "results") -> dict:
    """A schema-3 results dict as schema 4: each variant gains ``num_reused_frames`` and
    ``num_recomputed_frames`` as None, and its lifecycle ``clean_score_counts`` as None
    (schema 3 did not record them)."""
    keys = ("num_reused_frames", "num_recomputed_frames")
    return _with_nulls(results, 4, where, keys, ("clean_score_counts",))


def upgrade_v4(results: dict, *, where: str = "results") -> dict:
    """A schema-4 results dict as schema 5: each variant gains ``runs`` (the per-run counts) as
    None (schema 4 did not record them)."""
    return _with_nulls(results, 5, where, ("runs",), ())


def upgrade_v5(results: dict, *, where: str = "results") -> dict:
    """A schema-5 results dict as schema 6: each lifecycle gains ``asr_ci`` and ``runs`` as None
    (schema 5 did not record the lifecycle's intervals)."""
    return _with_nulls(results, 6, where, (), ("asr_ci", "runs"))


def upgrade_v6(results: dict, *, where: str = "results") -> dict:
    """A schema-6 results dict as schema 7: the file gains ``training_seed`` and
    ``model_sha256`` as None (schema 6 did not record what the weights were trained with)."""
    return _with_nulls(results, 7, where, (), (), ("training_seed", "model_sha256"))


def upgrade_v7(results: dict, *, where: str = "results") -> dict:
    """A schema-7 results dict as schema 8: the file gains ``source_commit`` and
    ``source_dirty`` as None (schema 7 did not record the code's revision)."""
    return _with_nulls(results, 8, where, (), (), ("source_commit", "source_dirty"))


#: ``UPGRADES[v - 1]`` turns a schema-``v`` dict into schema ``v + 1``
UPGRADES = (
    upgrade_v1,
    upgrade_v2,
    upgrade_v3,
    upgrade_v4,
    upgrade_v5,
    upgrade_v6,
    upgrade_v7,
)


def load_results_dir(root: str | Path, pattern: str = "**/results.json") -> list[dict]:
    """The results files under ``root`` matching ``pattern`` (by default every
    ``results.json``; the compressed and ``<model>.results.json`` forms need their own pattern, or
    :func:`~pcdet_atlas.evaluation.results.report.collect_results`), sorted by path.

    Raises:
        ResultsError: no file matches, or a file is invalid (naming it).
    """
    paths = sorted(Path(root).glob(pattern))
    if not paths:
        raise ResultsError(f"{root}: no file matches {pattern!r}")
    return [load_results(p) for p in paths]
