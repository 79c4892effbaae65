"""The paper's tables from ``results.json`` dicts: one model, a comparison of models, the ranks."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

from pcdet_atlas.evaluation.results.schema import ResultsError

__all__ = [
    "FORMATS",
    "MISSING",
    "PAPER_VARIANTS",
    "PAPER_VARIANT_LABELS",
    "format_comparison_table",
    "format_ranks",
    "format_table",
    "latex_escape",
    "missing_of",
    "ordered_variants",
    "variant_label",
]

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


def format_interval(ci) -> str:
    """A rate's interval as the tables print it after the rate, `` [lo, hi]`` (two decimals);
    ``''`` without one."""
    return "" if ci is None else f" [{ci[0]:.2f}, {ci[1]:.2f}]"


#: Cell of a variant a model was not evaluated on (not a zero: the value is unknown).
MISSING = "missing"
FORMATS = ("text", "markdown", "latex")
_LATEX_ESCAPES = {"&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{",
                  "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "<": "$<$",
                  ">": "$>$", "≥": "$\\geq$"}  # fmt: skip


def missing_of(num: int, total: int) -> str:
    """The cell of a value over ``total`` variants of which the model has only ``num``."""
    return f"{MISSING} ({num} of {total} variants)"


def latex_escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped (backslash excluded: cells never hold one
    except the marks this module adds)."""
    return "".join(_LATEX_ESCAPES.get(c, c) for c in text)


def _render_latex(groups: list[tuple[str, int]] | None, header: list[str], rows) -> str:
    r"""A booktabs ``tabular``: grouped header with ``\cmidrule`` under each group."""
    spec = "l" + "r" * (len(header) - 1)
    lines = [f"\\begin{{tabular}}{{{spec}}}", "\\toprule"]
    if groups is not None:
        cells, rules, col = [], [], 1
        for label, span in groups:
            text = latex_escape(label)
            cells.append(f"\\multicolumn{{{span}}}{{c}}{{{text}}}" if span > 1 else text)
            if label and span > 1:
                rules.append(f"\\cmidrule(lr){{{col}-{col + span - 1}}}")
            col += span
        lines.append(" & ".join(cells) + " \\\\")
        lines += rules
    lines.append(" & ".join(latex_escape(h) for h in header) + " \\\\")
    lines.append("\\midrule")
    lines += [" & ".join(r) + " \\\\" for r in rows]
    lines += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(lines)


def _render(
    fmt: str, groups: list[tuple[str, int]] | None, header: list[str], rows: list[list[str]]
) -> str:
    """Plain-text, Markdown or LaTeX table. ``groups``: (label, span) over ``header`` (text: a
    header line above, Markdown: prefixed to the column names, LaTeX: a multicolumn row).
    LaTeX cells must come escaped (:func:`latex_escape`); the header is escaped here."""
    if fmt == "latex":
        return _render_latex(groups, header, rows)
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
        raise ValueError(f"fmt must be one of {FORMATS}, got {fmt!r}")
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
    """One model's table: a row per variant (paper order), columns L2 mAP, L2 mAPH, ASR with its
    95% run-level interval, the lenient IoU > 0 ASR beside it, spoof runs and targets. mAP x100,
    one decimal; ASR two decimals. ``fmt``: 'text', 'markdown' or 'latex'."""
    names = ordered_variants(results["variants"]) if variants is None else list(variants)
    header = ["Variant", "L2 mAP", "L2 mAPH", "ASR [95% CI]"]
    header += (["ASR (IoU>0)"] if lenient else []) + ["Runs", "Targets"]
    rows = []
    for name in names:
        if name not in results["variants"]:
            raise ResultsError(f"{results['model']}: no variant {name!r}")
        v = results["variants"][name]
        asr = _fmt_asr(v["asr"]) + format_interval(v["asr_ci"])
        row = [name, _fmt_map(v["L2/mAP"]), _fmt_map(v["L2/mAPH"]), asr]
        if lenient:
            row.append(_fmt_asr(v["asr_lenient"]))
        row += ["-" if v["num_runs"] is None else str(v["num_runs"]), str(v["num_targets"])]
        rows.append(row)
    title = f"{results['model']} ({results['config']})"
    if fmt == "latex":
        rows = [[latex_escape(c) for c in r] for r in rows]
        return f"% {title}\n" + _render(fmt, None, header, rows)
    table = _render(fmt, None, header, rows)
    return (f"**{title}**\n\n" if fmt == "markdown" else f"{title}\n") + table


def _best_marks(values: list[float | None], higher_is_better: bool) -> list[str]:
    """'best' / 'second' / '' per value, compared as displayed, by competition ranking: 'best'
    where no value is better, 'second' where exactly one is (a tie for best leaves no second);
    nothing where fewer than two values are known."""
    known = [v for v in values if v is not None]
    if len(known) < 2:
        return [""] * len(values)
    marks = []
    for v in values:
        better = None if v is None else sum(u > v if higher_is_better else u < v for u in known)
        marks.append({0: "best", 1: "second"}.get(better, ""))
    return marks


def format_comparison_table(
    results_list: Sequence[Mapping],
    fmt: str = "text",
    *,
    family: str | None = None,
    variants: Sequence[str] | None = None,
    models_as: str = "rows",
    mark_best: bool = True,
    missing: str = "error",
) -> str:
    """Several models side by side: L2 mAP and ASR per variant, as the paper's Tables 3 and 4.

    Args:
        family: only the variants of this family (e.g. 'injection' for the paper's Table 3,
            'removal' for Table 4).
        variants: explicit variant list (default: all present, paper order).
        models_as: 'rows' (the paper's layout: a row per detector, a column pair per variant) or
            'columns' (a row per variant, a column pair per model; narrower for many variants).
        mark_best: Markdown: best **bold**, second-best _italic_; LaTeX: best ``\\textbf``,
            second ``\\underline``; per variant (mAP higher, ASR lower is better), compared at
            the printed precision: best where no model is better, second where exactly one is
            (models tied for best leave no second); nothing where fewer than two models have a
            value.
        missing: 'error' (a model without one of the variants raises :class:`ResultsError`) or
            'show' (its cells read ``missing``: the value is unknown, not zero).

    An ASR with a run-level interval is printed ``0.49 [0.31, 0.66]``; the marks compare the
    point estimates (overlapping intervals mean the order is not settled).
    """
    if models_as not in ("rows", "columns"):
        raise ValueError(f"models_as must be 'rows' or 'columns', got {models_as!r}")
    if missing not in ("error", "show"):
        raise ValueError(f"missing must be 'error' or 'show', got {missing!r}")
    esc = latex_escape if fmt == "latex" else str
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
                if missing == "error":
                    raise ResultsError(f"{r['model']}: no variant {name!r}")
                maps.append(None), asrs.append(None)
                continue
            v = r["variants"][name]
            maps.append(None if v["L2/mAP"] is None else _fmt_map(v["L2/mAP"]))
            asrs.append(None if v["asr"] is None else _fmt_asr(v["asr"]))
        map_marks = _best_marks([None if m is None else float(m) for m in maps], True)
        asr_marks = _best_marks([None if a is None else float(a) for a in asrs], False)
        for i, model in enumerate(models):
            entry = results_list[i]["variants"].get(name)
            if entry is None:
                cells[(model, name)] = (MISSING, MISSING)
                continue
            m, a = maps[i] or "-", asrs[i] or "-"
            if fmt in ("markdown", "latex") and mark_best and len(models) > 1:
                m, a = _mark(m, map_marks[i], fmt), _mark(a, asr_marks[i], fmt)
            cells[(model, name)] = (m, a + format_interval(entry["asr_ci"]))
    if models_as == "rows":
        groups = [("", 1)] + [(variant_label(n), 2) for n in variants]
        header = ["Detector"] + ["L2 mAP", "ASR"] * len(variants)
        rows = [[esc(m)] + [c for n in variants for c in cells[(m, n)]] for m in models]
    else:
        groups = [("", 1)] + [(m, 2) for m in models]
        header = ["Variant"] + ["L2 mAP", "ASR"] * len(models)
        rows = [
            [esc(variant_label(n))] + [c for m in models for c in cells[(m, n)]] for n in variants
        ]
    return _render(fmt, groups, header, rows)


def _mark(text: str, mark: str, fmt: str = "markdown") -> str:
    if fmt == "latex":
        wrap = {"best": "\\textbf{%s}", "second": "\\underline{%s}"}.get(mark, "%s")
        return wrap % text
    return f"**{text}**" if mark == "best" else f"_{text}_" if mark == "second" else text


def format_ranks(ranks: Mapping, fmt: str = "text") -> str:
    """The robustness ranks of :func:`ranks_from_results` as a table, with the fit below it."""
    groups = list(ranks["group_ranks"])
    header = ["Model", *(f"{g.capitalize()} rank" for g in groups)]
    rows = [[m, *(f"{ranks['group_ranks'][g][m]:.3f}" for g in groups)] for m in ranks["models"]]
    table = _render(fmt, None, header, rows)
    fit, (x, y) = ranks["fit"], ranks["fit_axes"]
    if fit is None:
        why = "not enough models"
        if x in ranks["group_ranks"] and len(set(ranks["group_ranks"][x].values())) == 1:
            why = f"every model has the same {x} rank"
        return table + f"\n\nlinear fit of the {y} rank on the {x} rank: {why}"
    return table + (
        f"\n\n{y} rank = {fit['slope']:.4f} * {x} rank + {fit['intercept']:.4f}"
        f"  (R^2 = {fit['r2']:.3f}, {fit['num_models']} models)"
    )
