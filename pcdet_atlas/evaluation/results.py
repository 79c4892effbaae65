"""``results.json``: one file per evaluated model, its validation, and the paper's tables.

Schema (version 2; every key required unless marked optional; unknown keys are errors)::

    {
      "schema_version": 2,
      "model": str,                      # display name, e.g. "CenterPoint-4f"
      "checkpoint": str | null,          # path of the evaluated weights
      "config": str,                     # path of the model config
      "pcdet_atlas_version": str,
      "created": str,                    # ISO 8601 time, e.g. "2026-11-21T08:00:00+00:00"
      "class_names": [str, ...],         # e.g. ["Vehicle", "Pedestrian", "Cyclist"]
      "variants": {                      # variant name -> entry, e.g. "clean", "rem_40"
        <variant>: {
          "family": str,                 # "clean" | "injection" | "removal" | <new family>
          "rank_group": str | null,      # the attack class's RANK_GROUP (robustness ranks)
          "num_frames": int,
          "L1/mAP", "L1/mAPH", "L2/mAP", "L2/mAPH": float in [0, 1] | null,
          "per_class": {<class>: {"L1/AP", "L1/APH", "L2/AP", "L2/APH": float | null}},
          "asr", "asr_lenient": float in [0, 1] | null,    # null when num_targets == 0
          "num_targets", "num_success", "num_success_lenient": int,
          "iou_threshold": float, "score_threshold": float | null, "target_class": str | null,
          "confidence": {...} | null,    # attack_metrics.injection_confidence / removal_confidence
          "lifecycle": {...} | null,     # attack_metrics.lifecycle_asr
          "extra": {...}                 # optional, free-form
        }
      },
      "extra": {...}                     # optional, free-form
    }

mAP values are fractions as :func:`waymo_evaluate` returns them; the printers show them x100 with
one decimal and ASR with two decimals, as the paper's tables do.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Iterable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pcdet_atlas.evaluation.attack_metrics import robustness_ranks
from pcdet_atlas.version import __version__

SCHEMA_VERSION = 2
METRIC_KEYS = ("L1/mAP", "L1/mAPH", "L2/mAP", "L2/mAPH")
CLASS_METRIC_KEYS = ("L1/AP", "L1/APH", "L2/AP", "L2/APH")
ATTACK_KEYS = (
    "asr",
    "asr_lenient",
    "num_targets",
    "num_success",
    "num_success_lenient",
    "iou_threshold",
    "score_threshold",
    "target_class",
    "confidence",
    "lifecycle",
)
TOP_KEYS = (
    "schema_version",
    "model",
    "checkpoint",
    "config",
    "pcdet_atlas_version",
    "created",
    "class_names",
    "variants",
)
VARIANT_KEYS = ("family", "rank_group", "num_frames", *METRIC_KEYS, "per_class", *ATTACK_KEYS)

#: The paper's variants in the order its tables print them, with their column labels.
PAPER_VARIANT_LABELS = {
    "clean": "Clean",
    "inj_rel_easy": "Rel-Fixed Easy",
    "inj_rel_medium": "Rel-Fixed Medium",
    "inj_rel_hard": "Rel-Fixed Hard",
    "inj_global_easy": "Global Easy",
    "inj_global_medium": "Global Medium",
    "inj_global_hard": "Global Hard",
    "rem_10": "Removal 10",
    "rem_20": "Removal 20",
    "rem_30": "Removal 30",
    "rem_40": "Removal 40",
    "rem_50": "Removal 50",
    "rem_60": "Removal 60",
}
PAPER_VARIANTS = tuple(PAPER_VARIANT_LABELS)


class ResultsError(ValueError):
    """A results dict or file that does not follow the schema; the message names the key."""


# ---------------------------------------------------------------------------- building
def _plain(value):
    """numpy scalars / arrays -> Python types, recursively (JSON-ready)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
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
        attack: :func:`attack_metrics.evaluate_attack` output; None for a variant without targets
            (clean), which stores ASR None and zero counts.
    """
    entry: dict = {"family": family, "rank_group": rank_group, "num_frames": int(num_frames)}
    for key in METRIC_KEYS:
        entry[key] = None if metrics is None else metrics[key]
    entry["per_class"] = {
        cls: {k: None if metrics is None else metrics[f"{cls}/{k}"] for k in CLASS_METRIC_KEYS}
        for cls in class_names
    }
    if attack is None:
        entry.update(
            asr=None,
            asr_lenient=None,
            num_targets=0,
            num_success=0,
            num_success_lenient=0,
            iou_threshold=0.7,
            score_threshold=None,
            target_class=None,
            confidence=None,
            lifecycle=None,
        )
    else:
        for key, want in (("variant", variant), ("family", family), ("num_frames", num_frames)):
            if key in attack and attack[key] != want:
                raise ResultsError(
                    f"variant {variant!r}: attack metrics have {key}={attack[key]!r}, expected "
                    f"{want!r}"
                )
        for key in ATTACK_KEYS:
            if key not in attack:
                raise ResultsError(f"variant {variant!r}: attack metrics lack key '{key}'")
            entry[key] = attack[key]
    if extra is not None:
        entry["extra"] = dict(extra)
    entry = _plain(entry)
    _validate_variant(entry, f"variants[{variant!r}]", list(class_names))
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
) -> dict:
    """A complete, validated results dict (``created`` defaults to now, UTC)."""
    results = {
        "schema_version": SCHEMA_VERSION,
        "model": model,
        "checkpoint": None if checkpoint is None else str(checkpoint),
        "config": str(config),
        "pcdet_atlas_version": __version__,
        "created": created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "class_names": list(class_names),
        "variants": {name: dict(entry) for name, entry in variants.items()},
    }
    if extra is not None:
        results["extra"] = dict(extra)
    results = _plain(results)
    validate_results(results)
    return results


# ---------------------------------------------------------------------------- validation
def _fail(path: str, msg: str) -> None:
    raise ResultsError(f"{path}: {msg}")


def _check_keys(d, path: str, required: Iterable[str], optional: Iterable[str] = ()) -> None:
    if not isinstance(d, Mapping):
        _fail(path, f"expected a dict, got {type(d).__name__}")
    required = tuple(required)
    for key in required:
        if key not in d:
            _fail(path, f"missing key '{key}'")
    allowed = set(required) | set(optional)
    for key in d:
        if key not in allowed:
            _fail(path, f"unknown key '{key}' (allowed: {sorted(allowed)})")


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)


def _check_int(v, path: str, lo: int = 0) -> int:
    if not _is_int(v) or v < lo:
        _fail(path, f"expected an int >= {lo}, got {v!r}")
    return int(v)


def _check_frac(v, path: str, nullable: bool = True) -> None:
    if v is None and nullable:
        return
    if not _is_real(v) or not 0.0 <= v <= 1.0:
        _fail(path, f"expected a number in [0, 1]{' or null' if nullable else ''}, got {v!r}")


def _check_str(v, path: str, nullable: bool = False) -> None:
    if v is None and nullable:
        return
    if not isinstance(v, str) or not v:
        _fail(path, f"expected a non-empty string{' or null' if nullable else ''}, got {v!r}")


def _check_rate(rate, num, den, path: str) -> None:
    if den == 0:
        if rate is not None:
            _fail(path, f"must be null when there are no targets, got {rate!r}")
        return
    _check_frac(rate, path, nullable=False)
    if abs(rate - num / den) > 1e-9:
        _fail(path, f"{rate!r} != {num}/{den}")


def _check_histogram(h, path: str, total: int | None = None) -> int:
    _check_keys(h, path, ("bin_edges", "counts"))
    edges, counts = h["bin_edges"], h["counts"]
    if not isinstance(edges, list) or len(edges) < 2 or not all(_is_real(e) for e in edges):
        _fail(f"{path}['bin_edges']", f"expected a list of >= 2 numbers, got {edges!r}")
    if any(b <= a for a, b in zip(edges, edges[1:])):
        _fail(f"{path}['bin_edges']", "must be strictly increasing")
    if not isinstance(counts, list) or len(counts) != len(edges) - 1:
        _fail(f"{path}['counts']", f"expected {len(edges) - 1} counts, got {counts!r}")
    for i, c in enumerate(counts):
        _check_int(c, f"{path}['counts'][{i}]")
    if total is not None and sum(counts) != total:
        _fail(f"{path}['counts']", f"sum {sum(counts)} != {total}")
    return len(counts)


_CONFIDENCE_KEYS = {
    "injection": (
        "kind",
        "high_score_threshold",
        "num_targets",
        "num_detected",
        "num_above",
        "fraction_above",
        "mean_score",
        "median_score",
        "histogram",
    ),
    "removal": (
        "kind",
        "high_score_threshold",
        "num_targets",
        "num_surviving",
        "num_above",
        "fraction_above",
        "num_paired",
        "num_clean_missed",
        "mean_score_drop",
        "median_score_drop",
        "clean_peak",
        "attacked_peak",
        "peak_gap",
        "histogram",
        "paired_attacked_histogram",
        "paired_clean_histogram",
    ),
}


def _check_confidence(c, path: str, num_targets: int) -> None:
    if not isinstance(c, Mapping) or c.get("kind") not in _CONFIDENCE_KEYS:
        _fail(path, f"expected a dict with 'kind' in {sorted(_CONFIDENCE_KEYS)}, got {c!r}")
    kind = c["kind"]
    _check_keys(c, path, _CONFIDENCE_KEYS[kind])
    _check_frac(c["high_score_threshold"], f"{path}['high_score_threshold']", nullable=False)
    if _check_int(c["num_targets"], f"{path}['num_targets']") != num_targets:
        _fail(f"{path}['num_targets']", f"{c['num_targets']} != variant num_targets {num_targets}")
    shown = "num_detected" if kind == "injection" else "num_surviving"
    n = _check_int(c[shown], f"{path}['{shown}']")
    if n > num_targets:
        _fail(f"{path}['{shown}']", f"{n} > num_targets {num_targets}")
    above = _check_int(c["num_above"], f"{path}['num_above']")
    _check_rate(c["fraction_above"], above, n, f"{path}['fraction_above']")
    _check_histogram(c["histogram"], f"{path}['histogram']", total=n)
    if kind == "injection":
        for key in ("mean_score", "median_score"):
            _check_frac(c[key], f"{path}['{key}']")
        return
    paired = _check_int(c["num_paired"], f"{path}['num_paired']")
    missed = _check_int(c["num_clean_missed"], f"{path}['num_clean_missed']")
    if paired + missed != n:
        _fail(path, f"num_paired {paired} + num_clean_missed {missed} != num_surviving {n}")
    for key in ("clean_peak", "attacked_peak"):
        _check_frac(c[key], f"{path}['{key}']")
    for key in ("mean_score_drop", "median_score_drop", "peak_gap"):
        v = c[key]
        if v is not None and (not _is_real(v) or not -1.0 <= v <= 1.0):
            _fail(f"{path}['{key}']", f"expected a number in [-1, 1] or null, got {v!r}")
    for key in ("paired_attacked_histogram", "paired_clean_histogram"):
        _check_histogram(c[key], f"{path}['{key}']", total=paired)


_LIFECYCLE_LISTS = (
    "attacked",
    "num_targets",
    "num_success",
    "asr",
    "num_success_lenient",
    "asr_lenient",
    "score_counts",
)


def _check_lifecycle(lc, path: str) -> None:
    _check_keys(lc, path, ("window", "recorded_window", "k", "score_bin_edges", *_LIFECYCLE_LISTS))
    w = _check_int(lc["window"], f"{path}['window']", lo=1)
    if _check_int(lc["recorded_window"], f"{path}['recorded_window']", lo=1) < w:
        _fail(f"{path}['recorded_window']", f"must be >= window {w}")
    if lc["k"] != list(range(2 * w + 1)):
        _fail(f"{path}['k']", f"expected [0, ..., {2 * w}], got {lc['k']!r}")
    for key in _LIFECYCLE_LISTS:
        if not isinstance(lc[key], list) or len(lc[key]) != 2 * w + 1:
            _fail(f"{path}['{key}']", f"expected a list of {2 * w + 1} entries")
    if lc["attacked"] != [1 <= k <= w for k in range(2 * w + 1)]:
        _fail(f"{path}['attacked']", "must be True exactly at k = 1..window")
    for k in range(2 * w + 1):
        at = f"{path}[k={k}]"
        n = _check_int(lc["num_targets"][k], f"{at}['num_targets']")
        for num_key, rate_key in (("num_success", "asr"), ("num_success_lenient", "asr_lenient")):
            s = _check_int(lc[num_key][k], f"{at}['{num_key}']")
            if s > n:
                _fail(f"{at}['{num_key}']", f"{s} > num_targets {n}")
            _check_rate(lc[rate_key][k], s, n, f"{at}['{rate_key}']")
        hist = {"bin_edges": lc["score_bin_edges"], "counts": lc["score_counts"][k]}
        _check_histogram(hist, f"{at}['score_counts']")
        if sum(lc["score_counts"][k]) > n:
            _fail(f"{at}['score_counts']", f"more scores than targets ({n})")


def _validate_variant(v, path: str, class_names: list[str]) -> None:
    _check_keys(v, path, VARIANT_KEYS, optional=("extra",))
    _check_str(v["family"], f"{path}['family']")
    if v["rank_group"] is not None:
        _check_str(v["rank_group"], f"{path}['rank_group']")
    _check_int(v["num_frames"], f"{path}['num_frames']")
    for key in METRIC_KEYS:
        _check_frac(v[key], f"{path}['{key}']")
    _check_keys(v["per_class"], f"{path}['per_class']", class_names)
    for cls in class_names:
        cpath = f"{path}['per_class'][{cls!r}]"
        _check_keys(v["per_class"][cls], cpath, CLASS_METRIC_KEYS)
        for key in CLASS_METRIC_KEYS:
            _check_frac(v["per_class"][cls][key], f"{cpath}['{key}']")
    n = _check_int(v["num_targets"], f"{path}['num_targets']")
    for num_key, rate_key in (("num_success", "asr"), ("num_success_lenient", "asr_lenient")):
        s = _check_int(v[num_key], f"{path}['{num_key}']")
        if s > n:
            _fail(f"{path}['{num_key}']", f"{s} > num_targets {n}")
        _check_rate(v[rate_key], s, n, f"{path}['{rate_key}']")
    thr = v["iou_threshold"]
    if not _is_real(thr) or not 0.0 <= thr <= 1.0:
        _fail(f"{path}['iou_threshold']", f"expected a number in [0, 1], got {thr!r}")
    _check_frac(v["score_threshold"], f"{path}['score_threshold']")
    _check_str(v["target_class"], f"{path}['target_class']", nullable=True)
    if v["confidence"] is not None:
        _check_confidence(v["confidence"], f"{path}['confidence']", n)
    if v["lifecycle"] is not None:
        _check_lifecycle(v["lifecycle"], f"{path}['lifecycle']")
    if "extra" in v and not isinstance(v["extra"], Mapping):
        _fail(f"{path}['extra']", "expected a dict")


def validate_results(results: Mapping, where: str = "results") -> None:
    """Check a results dict against the schema; raise :class:`ResultsError` naming the bad key."""
    _check_keys(results, where, TOP_KEYS, optional=("extra",))
    if results["schema_version"] != SCHEMA_VERSION:
        _fail(
            f"{where}['schema_version']",
            f"expected {SCHEMA_VERSION}, got {results['schema_version']!r}",
        )
    for key in ("model", "config", "pcdet_atlas_version", "created"):
        _check_str(results[key], f"{where}['{key}']")
    _check_str(results["checkpoint"], f"{where}['checkpoint']", nullable=True)
    try:
        datetime.fromisoformat(results["created"])
    except ValueError:
        _fail(f"{where}['created']", f"not an ISO 8601 time: {results['created']!r}")
    names = results["class_names"]
    if not isinstance(names, list) or not names or not all(isinstance(c, str) for c in names):
        _fail(f"{where}['class_names']", f"expected a non-empty list of str, got {names!r}")
    if len(set(names)) != len(names):
        _fail(f"{where}['class_names']", f"duplicate class in {names!r}")
    variants = results["variants"]
    if not isinstance(variants, Mapping) or not variants:
        _fail(f"{where}['variants']", "expected a non-empty dict of variant entries")
    for name, entry in variants.items():
        _check_str(name, f"{where}['variants'] key")
        _validate_variant(entry, f"{where}['variants'][{name!r}]", names)
    if "extra" in results and not isinstance(results["extra"], Mapping):
        _fail(f"{where}['extra']", "expected a dict")


# ---------------------------------------------------------------------------- files
def save_results(results: Mapping, path: str | Path) -> Path:
    """Validate and write ``results`` as JSON (NaN is refused: undefined values are null)."""
    results = _plain(results)
    validate_results(results, where=str(path))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(results, f, indent=2, allow_nan=False)
        f.write("\n")
    tmp.replace(path)
    return path


def load_results(path: str | Path) -> dict:
    """Read and validate one ``results.json``; errors name the file and the key."""
    path = Path(path)
    try:
        with open(path) as f:
            results = json.load(f)
    except json.JSONDecodeError as err:
        raise ResultsError(f"{path}: not valid JSON ({err})") from err
    validate_results(results, where=str(path))
    return results


def load_results_dir(root: str | Path, pattern: str = "**/results.json") -> list[dict]:
    """All results files under ``root`` matching ``pattern``, sorted by path."""
    paths = sorted(Path(root).glob(pattern))
    if not paths:
        raise ResultsError(f"{root}: no file matches {pattern!r}")
    return [load_results(p) for p in paths]


# ---------------------------------------------------------------------------- ranks
def ranks_from_results(
    results_list: Sequence[Mapping],
    *,
    variants: Sequence[str] | None = None,
    tie_method: str = "average",
) -> dict:
    """:func:`attack_metrics.robustness_ranks` over several models' results (one per model).

    ``variants`` restricts the settings ranked (default: every variant of the first model with a
    ``rank_group``; every model must have them all, in the same group).
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


# ---------------------------------------------------------------------------- printing
def ordered_variants(names: Iterable[str]) -> list[str]:
    """The paper's variant order first, then any other variant by name."""
    names = set(names)
    return [v for v in PAPER_VARIANTS if v in names] + sorted(names - set(PAPER_VARIANTS))


def variant_label(name: str) -> str:
    return PAPER_VARIANT_LABELS.get(name, name)


def _fmt_map(v) -> str:
    return "-" if v is None else f"{100.0 * v:.1f}"


def _fmt_asr(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def _render(
    fmt: str, groups: list[tuple[str, int]] | None, header: list[str], rows: list[list[str]]
) -> str:
    """Plain-text or Markdown table. ``groups``: (label, span) over ``header`` (text: a header
    line above, Markdown: prefixed to the column names)."""
    if fmt == "markdown":
        head = list(header)
        if groups is not None:
            col = 0
            for label, span in groups:
                for j in range(col, col + span):
                    if label:
                        head[j] = f"{label} {head[j]}"
                col += span
        lines = ["| " + " | ".join(head) + " |"]
        lines.append("|" + "|".join([":---"] + ["---:"] * (len(head) - 1)) + "|")
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    if fmt != "text":
        raise ValueError(f"fmt must be 'text' or 'markdown', got {fmt!r}")
    widths = [max(len(r[j]) for r in [header, *rows]) for j in range(len(header))]
    sep = "  "
    lines = []
    if groups is not None:
        col, cells = 0, []
        for label, span in groups:
            width = sum(widths[col : col + span]) + len(sep) * (span - 1)
            if len(label) > width:  # widen the group's last column
                widths[col + span - 1] += len(label) - width
                width = len(label)
            cells.append(label.center(width) if span > 1 else label.ljust(width))
            col += span
        lines.append(sep.join(cells).rstrip())

    def line(cells):
        out = [cells[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(cells[1:], widths[1:])]
        return sep.join(out).rstrip()

    lines.append(line(header))
    lines.append(sep.join("-" * w for w in widths))
    lines += [line(r) for r in rows]
    return "\n".join(lines)


def format_table(
    results: Mapping,
    fmt: str = "text",
    *,
    variants: Sequence[str] | None = None,
    lenient: bool = True,
) -> str:
    """One model's table: a row per variant (paper order), columns L2 mAP, L2 mAPH, ASR
    (and the lenient IoU > 0 ASR beside it), targets. mAP x100, one decimal; ASR two decimals.
    ``fmt``: 'text' or 'markdown'."""
    names = ordered_variants(results["variants"]) if variants is None else list(variants)
    header = ["Variant", "L2 mAP", "L2 mAPH", "ASR"] + (["ASR (IoU>0)"] if lenient else [])
    header.append("Targets")
    rows = []
    for name in names:
        if name not in results["variants"]:
            raise ResultsError(f"{results['model']}: no variant {name!r}")
        v = results["variants"][name]
        row = [name, _fmt_map(v["L2/mAP"]), _fmt_map(v["L2/mAPH"]), _fmt_asr(v["asr"])]
        if lenient:
            row.append(_fmt_asr(v["asr_lenient"]))
        row.append(str(v["num_targets"]))
        rows.append(row)
    title = f"{results['model']} ({results['config']})"
    table = _render(fmt, None, header, rows)
    return (f"**{title}**\n\n" if fmt == "markdown" else f"{title}\n") + table


def _best_marks(values: list[float | None], higher_is_better: bool) -> list[str]:
    """'best' / 'second' / '' per value, compared as displayed (ties share the mark)."""
    shown = sorted({v for v in values if v is not None}, reverse=higher_is_better)
    marks = []
    for v in values:
        if v is None or not shown:
            marks.append("")
        elif v == shown[0]:
            marks.append("best")
        elif len(shown) > 1 and v == shown[1]:
            marks.append("second")
        else:
            marks.append("")
    return marks


def format_comparison_table(
    results_list: Sequence[Mapping],
    fmt: str = "text",
    *,
    family: str | None = None,
    variants: Sequence[str] | None = None,
    models_as: str = "rows",
    mark_best: bool = True,
) -> str:
    """Several models side by side: L2 mAP and ASR per variant, as the paper's Tables 2 and 3.

    Args:
        family: only the variants of this family (e.g. 'injection' for the paper's Table 2).
        variants: explicit variant list (default: all present, paper order).
        models_as: 'rows' (the paper's layout: a row per detector, a column pair per variant) or
            'columns' (a row per variant, a column pair per model; narrower for many variants).
        mark_best: Markdown only: best **bold**, second-best _italic_ per variant (mAP higher,
            ASR lower is better), compared at the printed precision.
    """
    if models_as not in ("rows", "columns"):
        raise ValueError(f"models_as must be 'rows' or 'columns', got {models_as!r}")
    models = [r["model"] for r in results_list]
    if variants is None:
        present = {n: v["family"] for r in results_list for n, v in r["variants"].items()}
        variants = [n for n in ordered_variants(present) if family is None or present[n] == family]
    if not variants:
        raise ResultsError(f"no variant to print (family={family!r})")
    cells: dict[tuple[str, str], tuple[str, str]] = {}
    for name in variants:
        maps, asrs = [], []
        for r in results_list:
            if name not in r["variants"]:
                raise ResultsError(f"{r['model']}: no variant {name!r}")
            v = r["variants"][name]
            maps.append(None if v["L2/mAP"] is None else _fmt_map(v["L2/mAP"]))
            asrs.append(None if v["asr"] is None else _fmt_asr(v["asr"]))
        map_marks = _best_marks([None if m is None else float(m) for m in maps], True)
        asr_marks = _best_marks([None if a is None else float(a) for a in asrs], False)
        for i, model in enumerate(models):
            m, a = maps[i] or "-", asrs[i] or "-"
            if fmt == "markdown" and mark_best and len(models) > 1:
                m, a = _mark(m, map_marks[i]), _mark(a, asr_marks[i])
            cells[(model, name)] = (m, a)
    if models_as == "rows":
        groups = [("", 1)] + [(variant_label(n), 2) for n in variants]
        header = ["Detector"] + ["L2 mAP", "ASR"] * len(variants)
        rows = [[m] + [c for n in variants for c in cells[(m, n)]] for m in models]
    else:
        groups = [("", 1)] + [(m, 2) for m in models]
        header = ["Variant"] + ["L2 mAP", "ASR"] * len(models)
        rows = [[variant_label(n)] + [c for m in models for c in cells[(m, n)]] for n in variants]
    return _render(fmt, groups, header, rows)


def _mark(text: str, mark: str) -> str:
    return f"**{text}**" if mark == "best" else f"_{text}_" if mark == "second" else text


def format_ranks(ranks: Mapping, fmt: str = "text") -> str:
    """The robustness ranks of :func:`ranks_from_results` as a table, with the fit below it."""
    groups = list(ranks["group_ranks"])
    header = ["Model", *(f"{g.capitalize()} rank" for g in groups)]
    rows = [[m, *(f"{ranks['group_ranks'][g][m]:.3f}" for g in groups)] for m in ranks["models"]]
    table = _render(fmt, None, header, rows)
    fit, (x, y) = ranks["fit"], ranks["fit_axes"]
    if fit is None:
        return table + f"\n\nlinear fit of the {y} rank on the {x} rank: not enough models"
    return table + (
        f"\n\n{y} rank = {fit['slope']:.4f} * {x} rank + {fit['intercept']:.4f}"
        f"  (R^2 = {fit['r2']:.3f}, {fit['num_models']} models)"
    )
