"""The confidence analysis: the scores of a variant's targets by the confidence kind its family
names (:mod:`.confidence`), its ``confidence`` key of a ``results.json`` entry (a union tagged by
``kind`` over the registered kinds), the report's confident-phantom and centre-gap tables and
the score histograms (paper Figs. 5 and 9)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.evaluation.analyses.confidence import (
    COMMON_PROPERTIES,
    CONFIDENCE_KINDS,
    confidence_of,
)
from pcdet_atlas.evaluation.analyses.registry import (
    Analysis,
    ReportFigure,
    ReportSection,
    VariantData,
    register_analysis,
)
from pcdet_atlas.evaluation.analyses.schema_parts import (
    check_histogram,
    check_rate,
    closed,
    fail,
    nullable,
)
from pcdet_atlas.evaluation.results.figures import HIGH_SCORE
from pcdet_atlas.evaluation.results.queries import attack_variants, family_variants
from pcdet_atlas.evaluation.results.style import (
    figure_grid,
    label_panels,
    legend_below,
    render,
    variant_styles,
)
from pcdet_atlas.evaluation.results.tables import (
    MISSING,
    _render,
    latex_escape,
    ordered_variants,
    variant_label,
)

__all__ = [
    "ConfidenceAnalysis",
    "centre_gap_table",
    "confidence_histograms",
    "confidence_histograms_figure",
    "confidence_schema",
    "confident_phantom_table",
]


def confidence_schema() -> dict:
    """The ``confidence`` entry: the registered kind named by ``kind`` decides the other keys (a
    tagged union: errors come from the branch of the entry's own kind)."""
    kinds = {
        name: closed({"kind": {"const": name}, **COMMON_PROPERTIES, **kind.properties})
        for name, kind in CONFIDENCE_KINDS.items()
    }
    return {
        "type": "object",
        "required": ["kind"],
        "properties": {"kind": {"enum": list(kinds)}},
        "allOf": [
            {
                "if": {
                    "type": "object",
                    "required": ["kind"],
                    "properties": {"kind": {"const": kind}},
                },
                "then": schema,
            }  # fmt: skip
            for kind, schema in kinds.items()
        ],
    }


def confidence_histograms(
    results_list: Sequence[Mapping], family: str, path: Path, notes: list[str] | None = None
) -> Path | str:
    """:func:`confidence_histograms_figure` written to ``path`` (PNG, PDF beside)."""
    return render(lambda: confidence_histograms_figure(results_list, family, notes), path)


def confidence_histograms_figure(
    results_list: Sequence[Mapping], family: str, notes: list[str] | None = None
):
    """Per model (a panel each, one y-axis for all), the score distribution of the detected
    targets per variant (injection: the phantoms' scores, paper Fig. 5; removal: the surviving
    targets' scores with the clean run's scores of the same targets dashed, paper Fig. 9), as
    fractions of the detected targets; the dotted line is the 0.7 high-confidence threshold
    (the share above it: the report's confident-phantom table). One legend under the panels."""
    from matplotlib.lines import Line2D

    kind = {"injection": "injection", "removal": "removal"}.get(family)
    if kind is None:
        return f"no confidence figure for family {family!r}"
    panels = []
    for r in results_list:
        names = [n for n in family_variants(r, family)
                 if (r["variants"][n]["confidence"] or {}).get("kind") == kind]  # fmt: skip
        if names:
            panels.append((r, names))
    if not panels:
        return f"no {family} variant with confidence data"
    styles = variant_styles(attack_variants(results_list))
    drawn: set[str] = set()
    clean_drawn = False
    shown = [n for n in attack_variants(results_list, family) if any(n in ns for _, ns in panels)]
    fig, axes = figure_grid(len(panels), sharey=True,
                            legend_entries=len(shown) + 1 + (kind == "removal"))  # fmt: skip
    for ax, (r, names) in zip(axes, panels):
        clean_total = None
        for name in names:
            c = r["variants"][name]["confidence"]
            h = c["histogram"]
            counts = np.asarray(h["counts"], dtype=float)
            if counts.sum() > 0:
                ax.stairs(counts / counts.sum(), h["bin_edges"], **styles[name].line())
                drawn.add(name)
            if kind == "removal":
                pc = np.asarray(c["paired_clean_histogram"]["counts"], dtype=float)
                clean_total = pc if clean_total is None else clean_total + pc
                clean_edges = c["paired_clean_histogram"]["bin_edges"]
        if clean_total is not None and clean_total.sum() > 0:
            clean_drawn = True
            ax.stairs(clean_total / clean_total.sum(), clean_edges, color="black", ls=":",
                      lw=1.2)  # fmt: skip
        ax.axvline(HIGH_SCORE, color="0.5", ls=":", lw=0.8)
        ax.set_title(f"{r['model']}")
        if not any(n in drawn for n in names):
            ax.text(0.5, 0.5, "no target detected", ha="center", transform=ax.transAxes)
        ax.grid(lw=0.3)
    xlabel = "phantom score" if kind == "injection" else "surviving target score"
    label_panels(axes, xlabel, "fraction of detected")
    handles = [Line2D([], [], **styles[n].line(), label=variant_label(n))
               for n in shown if n in drawn]  # fmt: skip
    if clean_drawn:
        handles.append(Line2D([], [], color="black", ls=":", lw=1.2,
                              label="clean run (same targets)"))  # fmt: skip
    handles.append(Line2D([], [], color="0.5", ls=":", lw=0.8, label=f"score {HIGH_SCORE}"))
    legend_below(fig, handles)
    return fig


def _confidence_table(results_list, kind: str, cell, fmt: str) -> str | None:
    """A row per model, a column per variant with ``kind`` confidence data (``injection`` /
    ``removal``); ``cell(confidence)`` writes an entry's cell. None without such a variant."""
    names = ordered_variants(
        {
            n
            for r in results_list
            for n, v in r["variants"].items()
            if (v["confidence"] or {}).get("kind") == kind
        }  # fmt: skip
    )
    if not names:
        return None
    header = ["Model", *(variant_label(n) for n in names)]
    rows = []
    for r in results_list:
        row = [r["model"]]
        for n in names:
            entry = r["variants"].get(n)
            row.append(MISSING if entry is None else cell(entry["confidence"]))
        rows.append(row)
    if fmt == "latex":
        rows = [[latex_escape(c) for c in row] for row in rows]
    return _render(fmt, None, header, rows)


def centre_gap_table(results_list: Sequence[Mapping], fmt: str = "markdown") -> str | None:
    """Per model and removal variant, the centre gap: the peak of the clean run's scores of the
    surviving targets minus the peak of their attacked scores (docs/evaluation.md
    "Confidence"); None when no model has a removal variant with confidence data."""

    def cell(conf):
        if conf is None or conf["peak_gap"] is None:
            return "-"
        return f"{conf['peak_gap']:.3f}"

    return _confidence_table(results_list, "removal", cell, fmt)


def confident_phantom_table(results_list: Sequence[Mapping], fmt: str = "markdown") -> str | None:
    """Per model and injection variant, the share of detected phantoms scoring above the
    confidence threshold (0.7, the paper's Fig. 5 statement), with the counts, and the median
    phantom score; None when no model has an injection variant with confidence data."""

    def cell(conf):
        if conf is None or not conf["num_detected"]:
            return "-"
        share = f"{conf['fraction_above']:.2f} ({conf['num_above']}/{conf['num_detected']})"
        return f"{share}, median {conf['median_score']:.2f}"

    return _confidence_table(results_list, "injection", cell, fmt)


def _tables(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    sections = []
    confident = confident_phantom_table(results_list, fmt)
    if confident is not None:
        sections.append(("Phantoms detected with confidence above 0.7 (paper Fig. 5)", confident))
    gap = centre_gap_table(results_list, fmt)
    if gap is not None:
        sections.append(("Centre gap under removal (clean peak - attacked peak)", gap))
    return sections


@register_analysis
class ConfidenceAnalysis(Analysis):
    """The ``confidence`` entry of the kind a family names (:func:`~.confidence.confidence_of`)."""

    name = "confidence"
    required = True

    def schema(self) -> dict[str, dict]:
        return {"confidence": nullable(confidence_schema())}

    def compute(self, data: VariantData) -> dict:
        return {"confidence": confidence_of(data)}

    def check(self, entry: Mapping, path: str) -> None:
        c, num_targets = entry["confidence"], entry["num_targets"]
        if c is None:
            return
        path = f"{path}['confidence']"
        if c["num_targets"] != num_targets:
            fail(
                f"{path}['num_targets']", f"{c['num_targets']} != variant num_targets {num_targets}"
            )
        kind = CONFIDENCE_KINDS.get(c["kind"])
        n = c[kind.shown]
        if n > num_targets:
            fail(f"{path}['{kind.shown}']", f"{n} > num_targets {num_targets}")
        check_rate(
            c["fraction_above"], c["num_above"], n, f"{path}['fraction_above']",
            f"{path}['num_above']",
        )  # fmt: skip
        check_histogram(c["histogram"], f"{path}['histogram']", total=n)
        if kind.check is not None:
            kind.check(c, path)

    def sections(self) -> list[ReportSection]:
        return [ReportSection(_tables, order=50)]

    def figures(self) -> list[ReportFigure]:
        return [
            ReportFigure("confidence_injection.png",
                         "Phantom confidence under injection (paper Fig. 5)",
                         lambda r, p, n: confidence_histograms(r, "injection", p, n), order=40),
            ReportFigure("confidence_removal.png", "Target confidence under removal (paper Fig. 9)",
                         lambda r, p, n: confidence_histograms(r, "removal", p, n), order=50),
        ]  # fmt: skip
