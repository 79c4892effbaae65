"""Building blocks of the ``results.json`` schema that each analysis states its part with (JSON
Schema fragments, checked with ``jsonschema``), and the error of a results file that breaks it."""

from __future__ import annotations

from typing import NoReturn

__all__ = [
    "COUNT",
    "FRAC",
    "HISTOGRAM",
    "INTERVAL",
    "NAME",
    "RUN",
    "SIGNED_FRAC",
    "ResultsError",
    "check_histogram",
    "check_rate",
    "closed",
    "fail",
    "nullable",
]


class ResultsError(ValueError):
    """A results dict or file that does not follow the schema; the message names the key."""


def nullable(schema: dict) -> dict:
    """``schema`` or null (its other keywords apply to its own type only, so errors stay
    specific, where an ``anyOf`` would only say that no branch matched)."""
    return {**schema, "type": [schema["type"], "null"]}


def closed(properties: dict, optional: tuple[str, ...] = ()) -> dict:
    """An object with exactly ``properties`` (all required except ``optional``)."""
    return {
        "type": "object",
        "properties": properties,
        "required": [k for k in properties if k not in optional],
        "additionalProperties": False,
    }


FRAC = {"type": "number", "minimum": 0.0, "maximum": 1.0}
COUNT = {"type": "integer", "minimum": 0}
#: A name (model, config, checkpoint, class, sequence ...): one line of printable text, as it
#: becomes a line of report.md and a cell of its tables; a newline or another control character
#: (C0, DEL, C1) is refused. ``(?!\n)``: Python's ``$`` also matches before a final newline.
NAME = {"type": "string", "minLength": 1, "pattern": "^[^\x00-\x1f\x7f-\x9f]+$(?!\n)"}
SIGNED_FRAC = {"type": "number", "minimum": -1.0, "maximum": 1.0}
#: A rate's interval ``[lo, hi]`` (e.g. :func:`pcdet_atlas.evaluation.intervals.asr_interval`).
INTERVAL = {"type": "array", "items": FRAC, "minItems": 2, "maxItems": 2}
HISTOGRAM = closed(
    {
        "bin_edges": {"type": "array", "items": {"type": "number"}, "minItems": 2},
        "counts": {"type": "array", "items": COUNT},
    }
)
#: One spoof run's counts (:func:`pcdet_atlas.evaluation.analyses.asr.run_counts`).
RUN = closed(
    {
        "sequence": NAME,
        "run_id": COUNT,
        "num_targets": {"type": "integer", "minimum": 1},
        "num_success": COUNT,
        "num_success_lenient": COUNT,
    }
)


def fail(path: str, msg: str) -> NoReturn:
    raise ResultsError(f"{path}: {msg}")


def check_rate(rate, num: int, den: int, path: str, num_path: str) -> None:
    """``rate`` is ``num / den`` (null when ``den`` is 0) and ``num <= den``."""
    if num > den:
        fail(num_path, f"{num} > num_targets {den}")
    if den == 0 and rate is not None:
        fail(path, f"must be null when there are no targets, got {rate!r}")
    if den > 0 and (rate is None or abs(rate - num / den) > 1e-9):
        fail(path, f"{rate!r} != {num}/{den}")


def check_histogram(h, path: str, total: int | None = None) -> None:
    """Strictly increasing edges, one count per bin, and (given) ``total`` counts in all."""
    edges, counts = h["bin_edges"], h["counts"]
    if any(b <= a for a, b in zip(edges, edges[1:])):
        fail(f"{path}['bin_edges']", "must be strictly increasing")
    if len(counts) != len(edges) - 1:
        fail(f"{path}['counts']", f"expected {len(edges) - 1} counts, got {len(counts)}")
    if total is not None and sum(counts) != total:
        fail(f"{path}['counts']", f"sum {sum(counts)} != {total}")
