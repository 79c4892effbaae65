"""Every number docs/results.md quotes is a number of a committed artefact, within its rounding.

The convention (read it before editing docs/results.md):

1. A number in docs/results.md (prose, lists, tables and headings alike) is by default a claim
   about the committed report, ``docs/results/report.md``, and must be found in the report
   sections its own section reads: each part of the doc (the text before the first ``##``
   heading, and each ``##`` section) names them in a comment,
   ``<!-- report: Models; Point removal -->`` (report headings ``## ...``, each name a prefix of
   one; a ``##`` section's ``###`` subsections belong to it); a later such comment in the part
   scopes the text after it. Scoping matters: most two-decimal values occur somewhere in the
   report, few in the one table a claim is about. A row of a table in the doc whose first cell
   names a row of a report table in scope (a model) is checked against those rows only.
2. A value with its interval, ``x [lo, hi]`` (an ASR, a paired difference ``Δ x [lo, hi]``),
   must be found as such a triple in the report, each of the three within its rounding: a
   difference cannot be quoted with another pair's interval.
3. Within its rounding: a number written with d decimals matches a report number with e >= d
   decimals that rounds to it (``|v - r| <= 10^-d / 2``; with e = d: the same digits); a
   number may not be quoted with more decimals than its source has. ``38%`` is the fraction
   0.38 (and ``29-31%`` two of them); ``1,188`` is 1188; the sign counts (``-0.00`` equals
   ``+0.00``).
4. A number from another committed file sits in a source span,
   ``<!-- source: PATH -->...<!-- /source -->`` (PATH repository-relative, a glob allowed: the
   span's numbers must be found in one of the files; e.g. the LOT filter's keep rates in
   ``docs/model_zoo.md``, the removal rates in ``cfgs/attacks/rem_*.yaml``).
   ``<!-- source: paper -->...<!-- /source -->`` marks what the ATLAS paper states: the paper is
   not in the repository, so these numbers are the only ones exempt by markup (the span must
   hold at least one number, and the spans are few: see ``MAX_PAPER_SPANS``).
5. Not results, exempt by pattern (the whole list, ``EXEMPT``): inline and fenced code
   (commands, config keys, variant names such as ``rem_20``), link targets, figure / table /
   finding numbers (``Fig. 3``, ``Figs. 4 and 6``, ``Tables 5 and 6``, ``Finding 1``),
   lifecycle positions (``k=1``, ``k=W+1``, ``W-1``), and digits inside a name (``CP-4f``,
   ``L2``, ``rem_20``; the word rule of the number pattern).

Numbers written as words are not checked: write a number that is a result in digits.
"""

from __future__ import annotations

import glob
import re
from pathlib import Path

import pytest

from pcdet_atlas.config import REPO_ROOT

DOC = REPO_ROOT / "docs" / "results.md"
REPORT = REPO_ROOT / "docs" / "results" / "report.md"
#: the paper's numbers cannot be checked here; keep their spans few and reviewed
MAX_PAPER_SPANS = 12

_NUM = r"[-+−]?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?%?"
NUMBER = re.compile(rf"(?<![\w.]){_NUM}(?![\w])")
TRIPLE = re.compile(rf"(?<![\w.])({_NUM})[*_]*\s*\[\s*({_NUM})\s*,\s*({_NUM})\s*\]")
SOURCE = re.compile(r"<!--\s*source:\s*(\S+)\s*-->(.*?)<!--\s*/source\s*-->", re.S)
#: what is not a result (convention 5), removed before numbers are read
EXEMPT = [
    re.compile(r"```.*?```", re.S),  # fenced code
    re.compile(r"`[^`]*`"),  # inline code
    re.compile(r"\]\([^)]*\)"),  # link targets
    re.compile(r"\b(?:Figs?|Tables?|Findings?)\.?\s+\d+(?:\s*(?:,|and|-)\s*\d+)*"),
    re.compile(r"\bk\s*=\s*(?:W\s*[-+]\s*\d+|W|\d+)"),  # lifecycle positions
    re.compile(r"\bW\s*[-+]\s*\d+"),
]


def parse(token: str) -> tuple[float, int]:
    """A number token -> (value, decimals); percentages as fractions."""
    text = token.replace("−", "-").replace(",", "")
    percent = text.endswith("%")
    text = text.rstrip("%")
    decimals = len(text.split(".")[1]) if "." in text else 0
    value = float(text)
    return (value / 100, decimals + 2) if percent else (value, decimals)


def numbers_of(text: str, emphasis: str = "*") -> list[tuple[float, int]]:
    """Every number of a text, its ``emphasis`` characters taken for spaces (the doc's bold;
    a report's ``**0.31**`` and ``_0.18_`` too, ``emphasis="*_"``)."""
    text = re.sub(f"[{emphasis}]", " ", text)
    text = re.sub(r"(\d)[-–](\d+(?:\.\d+)?%)", r"\1% \2", text)  # 29-31%: both percent
    return [parse(m.group(0)) for m in NUMBER.finditer(text)]


def triples_of(text: str) -> list[tuple[tuple[float, int], ...]]:
    return [tuple(map(parse, m.groups())) for m in TRIPLE.finditer(text)]


def match(quoted: tuple[float, int], found: tuple[float, int]) -> bool:
    (v, d), (r, e) = quoted, found
    return e >= d and abs(v - r) <= 10.0**-d / 2 + 1e-9


def missing(quoted: list, found: list) -> list:
    return [q for q in quoted if not any(match(q, f) for f in found)]


def claims(doc: str) -> tuple[str, list[tuple[str, str]]]:
    """The doc's text outside source spans (exempt patterns removed), and each span as (source,
    text)."""
    spans = [(m.group(1), m.group(2)) for m in SOURCE.finditer(doc)]
    rest = SOURCE.sub(" ", doc)
    rest = re.sub(r"<!--.*?-->", " ", rest, flags=re.S)  # the scope comment among them
    for pattern in EXEMPT:
        rest = pattern.sub(" ", rest)
    spans = [(src, _exempted(text)) for src, text in spans]
    return rest, spans


def _exempted(text: str) -> str:
    for pattern in EXEMPT:
        text = pattern.sub(" ", text)
    return text


def _label(q: tuple[float, int]) -> str:
    return f"{q[0]:.{q[1]}f}"


SCOPE = re.compile(r"<!--\s*report:\s*(.*?)\s*-->", re.S)


def report_sections(report: str) -> dict[str, str]:
    """The report's ``##`` sections by heading (``###`` subsections inside their section)."""
    parts = re.split(r"^## ", report, flags=re.M)
    return {part.split("\n", 1)[0].strip(): part for part in parts[1:]}


def doc_parts(doc: str) -> list[tuple[str, str]]:
    """The doc split at its ``##`` headings: (first line, text) per part."""
    parts = re.split(r"^(?=## )", doc, flags=re.M)
    return [(part.split("\n", 1)[0], part) for part in parts if part.strip()]


def check(doc: str, report: str) -> None:
    """Raise an AssertionError naming every number of ``doc`` that the convention cannot
    find, part by part of the doc."""
    sections = report_sections(report)
    paper = 0
    for heading, part in doc_parts(doc):
        chunks = SCOPE.split(part)  # [before, scope, text, scope, text, ...]
        assert len(chunks) > 1, (
            f"{heading!r}: no <!-- report: ... --> comment naming its report sections"
        )
        assert not numbers_of(claims(chunks[0])[0]), f"{heading!r}: numbers before its scope"
        for scope, text in zip(chunks[1::2], chunks[2::2], strict=True):
            chosen = []
            for name in (n.strip() for n in scope.split(";")):
                hits = [title for title in sections if title.startswith(name)]
                assert hits, f"{heading!r}: no report section starts with {name!r}"
                chosen += [sections[title] for title in hits]
            paper += check_part(text, "\n".join(chosen), heading)
    assert paper <= MAX_PAPER_SPANS, f"{paper} paper spans: more than {MAX_PAPER_SPANS}"


def rows_by_label(report: str) -> dict[str, list[str]]:
    """The report's table rows by their first cell (emphasis removed)."""
    rows: dict[str, list[str]] = {}
    for line in report.splitlines():
        if line.startswith("| "):
            label = re.sub(r"[*_]", "", line.split("|")[1]).strip()
            rows.setdefault(label, []).append(line)
    return rows


def check_part(doc: str, report: str, heading: str = "") -> int:
    """:func:`check` of one part of the doc against the report sections it reads; returns the
    number of its paper spans."""
    rest, spans = claims(doc)
    rows = rows_by_label(report)
    kept = []
    for line in rest.splitlines():
        label = line.split("|")[1].strip() if line.startswith("| ") else None
        if label not in rows:
            kept.append(line)
            continue
        absent = missing(numbers_of(line), numbers_of("\n".join(rows[label]), "*_"))
        assert not absent, (
            f"{heading}: row {label!r}: numbers not in the report's {label!r} rows: "
            + ", ".join(map(_label, absent))
        )
    rest = "\n".join(kept)
    found = numbers_of(report, "*_")
    report_triples = triples_of(re.sub(r"[*_]", "", report))
    bad_triples = [
        t for t in triples_of(rest)
        if not any(all(match(q, f) for q, f in zip(t, r)) for r in report_triples)
    ]  # fmt: skip
    assert not bad_triples, f"{heading}: value [interval] not in the report: " + "; ".join(
        f"{_label(t[0])} [{_label(t[1])}, {_label(t[2])}]" for t in bad_triples
    )
    singles = numbers_of(TRIPLE.sub(" ", rest))
    absent = missing(singles, found)
    assert not absent, f"{heading}: numbers not in the report: {', '.join(map(_label, absent))}"
    paper = 0
    for source, text in spans:
        quoted = numbers_of(text)
        assert quoted, f"source span {source!r} holds no number: {text.strip()[:60]!r}"
        if source == "paper":
            paper += 1
            continue
        files = sorted(glob.glob(str(REPO_ROOT / source)))
        assert files, f"source span names {source!r}: no such committed file"
        found_there = [n for f in files for n in numbers_of(Path(f).read_text(), "*_")]
        absent = missing(quoted, found_there)
        assert not absent, f"numbers not in {source}: {', '.join(map(_label, absent))}"
    return paper


def test_every_number_of_results_md_is_in_the_report_or_its_named_source():
    check(DOC.read_text(), REPORT.read_text())


#: a report as the check sees one: an ASR with its interval, a paired difference, a rank
FAKE_REPORT = """# ATLAS report

## Point injection

| CP-4f | 0.35 [0.20, 0.52] | _0.18_ [0.06, 0.34] |

## Robustness ranks

| CP-4f | 2.167 | removal rank = -0.5815 * injection rank, 0.291 | 0.64 |

## Paired model comparison

### injection

| CP-4f | **-0.22 [-0.31, -0.13]** | **+0.03 [-0.01, +0.07]** |
"""
SCOPED = "<!-- report: Point injection; Robustness; Paired -->\n"


@pytest.mark.parametrize(
    "doc, problem",
    [
        ("CP-4f's mean injection ASR is 0.36.", "not in the report: 0.36"),
        ("Δ -0.22 [-0.31, -0.12]", "-0.22 [-0.31, -0.12]"),  # the wrong interval end
        ("Δ -0.22 [-0.01, +0.07]", "-0.22 [-0.01, 0.07]"),  # another pair's interval
        ("R² = 0.2913", "not in the report: 0.2913"),  # more decimals than the report's
        ("in 39% of cases", "not in the report: 0.39"),
        ("<!-- source: docs/model_zoo.md -->kept 97.77%<!-- /source -->", "0.9777"),
        ("<!-- source: docs/nothing.md -->0.5<!-- /source -->", "no such committed file"),
        ("<!-- source: paper --> the paper says so<!-- /source -->", "holds no number"),
    ],
)
def test_the_check_fails_on_what_the_report_does_not_say(doc, problem):
    """The check itself, on a small report: wrong values, the interval of another pair, false
    precision, a source span whose file lacks the number, an empty paper span: each named; and
    what the report says passes, within its rounding."""
    good = ("CP-4f 0.35 [0.20, 0.52], 35%, Δ -0.22 [-0.31, -0.13], rank 2.2, R² = 0.29, "
            "+0.03 [-0.01, +0.07], 0.18 [0.06, 0.34], Fig. 3, k=W+1")  # fmt: skip
    check(SCOPED + good, FAKE_REPORT)
    with pytest.raises(AssertionError, match=re.escape(problem)):
        check(SCOPED + doc, FAKE_REPORT)


def test_numbers_are_looked_up_in_the_sections_a_part_names():
    check("<!-- report: Robustness -->\n0.64", FAKE_REPORT)
    with pytest.raises(AssertionError, match="not in the report: 0.64"):
        check("<!-- report: Point injection -->\n0.64", FAKE_REPORT)  # elsewhere in the report
    with pytest.raises(AssertionError, match="'## Ranks': no <!-- report"):
        check("<!-- report: Robustness -->\n0.64\n## Ranks\n2.2", FAKE_REPORT)
    with pytest.raises(AssertionError, match="no report section starts with 'Lifecycle'"):
        check("<!-- report: Lifecycle -->\n0.64", FAKE_REPORT)


def test_a_table_row_of_a_model_is_checked_against_that_models_rows():
    report = FAKE_REPORT.replace("## Robustness", "| PHiM | 0.52 [0.40, 0.60] |\n\n## Robustness")
    check("<!-- report: Point injection -->\nPHiM 0.35, CP-4f 0.52", report)  # prose: anywhere
    check("<!-- report: Point injection -->\n| PHiM | 0.52 |\n| CP-4f | 0.35 |", report)
    with pytest.raises(AssertionError, match="row 'PHiM': numbers not in .* rows: 0.35"):
        check("<!-- report: Point injection -->\n| PHiM | 0.35 |", report)


def test_exempt_patterns_cover_only_what_they_say():
    text = "Fig. 3, Figs. 4 and 6, Tables 5 and 6, Finding 1, k=W+1, k=1, W-1, `rem_20 0.77`"
    assert numbers_of(_exempted(text)) == []
    assert numbers_of("CP-4f, MSF-8f, L2 mAP, R², rem_20") == []
    assert numbers_of("1,188 frames, -0.09, +0.03, 38%, 0.13-0.77, 29-31%") == [
        (1188.0, 0), (-0.09, 2), (0.03, 2), (0.38, 2), (0.13, 2), (0.77, 2), (0.29, 2), (0.31, 2)
    ]  # fmt: skip
