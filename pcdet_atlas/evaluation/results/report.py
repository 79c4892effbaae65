"""The paper's report from ``results.json`` files: ``report.md`` with its tables (and, on request,
``report.tex`` with the same tables), and its figures, each a PNG with a PDF beside it
(docs/evaluation.md "Report").

The report's own sections: a model summary (clean L2 mAP/mAPH, input frames, clean rank, model
time per frame, mean ASR per family), the LOT ablation (Tables 5 and 6) when both models of the
pair are given, the seed-to-seed spread (when two results are one model config trained with
different seeds: :mod:`~pcdet_atlas.evaluation.results.seeds`), the accuracy-against-time figure
and each model's full table with its runs and targets. Between them, in their ``order``, the
sections and figures of every registered analysis (:mod:`pcdet_atlas.evaluation.analyses`): the
injection and removal tables (paper Tables 3 and 4) and the paired model comparison (ASR), the
lifecycle's onset and decay (Finding 3), the share of confident phantoms (Fig. 5) and the centre
gap (confidence), the robustness ranks, and their figures. A model that was not evaluated on a
variant shows ``missing`` there, never a zero; a mean or pooled value over a family needs every
variant of the family that any model has, each with an ASR, and otherwise reads ``missing (n of
m variants)``. The ranks name the variants they are over and those left out; under each figure
the report names what it leaves out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from pcdet_atlas.config import cfg_from_yaml_file, resolve_repo_path
from pcdet_atlas.evaluation.analyses.registry import (
    ReportFigure,
    ReportSection,
    registered_analyses,
)
from pcdet_atlas.evaluation.results import figures, queries
from pcdet_atlas.evaluation.results.build import paired_from_results
from pcdet_atlas.evaluation.results.io import find_results_files, load_results
from pcdet_atlas.evaluation.results.schema import ResultsError
from pcdet_atlas.evaluation.results.seeds import seed_spread_text
from pcdet_atlas.evaluation.results.tables import (
    MISSING,
    _render,
    format_interval,
    format_table,
    latex_escape,
    missing_of,
    ordered_variants,
    variant_label,
)
from pcdet_atlas.utils.files import write_atomic

__all__ = [
    "DEFAULT_LOT_CONTROL",
    "DEFAULT_LOT_PAIR",
    "collect_results",
    "lot_ablation_table",
    "report_figures",
    "report_sections",
    "summary_table",
    "write_report",
]

#: The model names (``ATLAS.MODEL_NAME``) of the LOT ablation: the detector and its defence.
DEFAULT_LOT_PAIR = ("PHiM", "PHiM+LOT")
#: The model name of the ablation's control: the detector fine-tuned on the defence's last-stage
#: schedule with the defence off (cfgs/atlas/synthetic/phim_lot_fine/control.yaml).
DEFAULT_LOT_CONTROL = "PHiM (no-LOT control)"


def collect_results(paths: Sequence[str | Path]) -> list[tuple[Path, dict]]:
    """``(file, results)`` for every given results file and every one under a given folder
    (:data:`~pcdet_atlas.evaluation.results.io.RESULTS_FILE_PATTERNS`: ``results.json`` and
    ``<model>.results.json``, either also gzip-compressed as ``.gz``; sorted), each validated.
    Two files of the same model name are an error naming both."""
    found: list[Path] = []
    for arg in paths:
        path = Path(arg)
        if path.is_dir():
            inside = find_results_files(path)
            if not inside:
                raise ResultsError(
                    f"{path}: no results.json under this folder (nor results.json.gz, "
                    "<model>.results.json or <model>.results.json.gz)"
                )
            found += inside
        elif path.is_file():
            found.append(path)
        else:
            raise ResultsError(f"{path}: no such file or folder")
    out, seen = [], {}
    for path in found:
        results = load_results(path)
        model = results["model"]
        if model in seen:
            raise ResultsError(
                f"model {model!r} appears twice: {seen[model]} and {path} (give one results.json "
                "per model, or set ATLAS.MODEL_NAME apart)"
            )
        seen[model] = path
        out.append((path, results))
    if not out:
        raise ResultsError("no results.json given")
    return out


def _fmt(value: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "-" if value is None else f"{scale * value:.{digits}f}"


def _fmt_ci(entry: Mapping) -> str:
    if entry["asr"] is None:
        return "-"
    return f"{entry['asr']:.2f}" + format_interval(entry["asr_ci"])


def input_frames(results: Mapping) -> int | None:
    """The model's temporal window as its lifecycle records it (None without lifecycle data)."""
    for entry in results["variants"].values():
        if entry["lifecycle"] is not None:
            return int(entry["lifecycle"]["window"])
    return None


def _mean_asr_cell(results: Mapping, variants: Sequence[str]) -> str:
    """A model's mean ASR over ``variants`` (a family's, across the report), or ``missing (n of
    m variants)`` where it lacks one of them or its ASR."""
    if not variants:
        return "-"
    mean = queries.mean_asr(results, variants)
    if mean is None:
        return missing_of(len(queries.covered_variants(results, variants)), len(variants))
    return _fmt(mean)


def summary_table(results_list: Sequence[Mapping], fmt: str = "markdown") -> str:
    """A row per model: clean L2 mAP / mAPH (x100), input frames, clean rank (1 = highest clean
    L2 mAP), model ms/frame on the clean run (:func:`queries.frame_cost`: with the RPN's time
    for proposals read from the prediction store, ``≥`` where it cannot be added; in Markdown
    each such model is explained under the table) and its device, mean ASR per family (over
    every variant of the family that any of the models has: ``missing (n of m variants)`` for a
    model without all of them)."""
    families = {f: queries.attack_variants(results_list, f) for f in ("injection", "removal")}
    maps = [(r["variants"].get("clean") or {}).get("L2/mAP") for r in results_list]
    order = sorted({m for m in maps if m is not None}, reverse=True)
    header = ["Model", "L2 mAP", "L2 mAPH", "Frames", "Clean rank", "ms/frame", "Device",
              "Mean inj. ASR", "Mean rem. ASR"]  # fmt: skip
    rows, notes = [], []
    for r, l2 in zip(results_list, maps):
        clean = r["variants"].get("clean")
        frames = input_frames(r)
        ms, lower_bound, note = queries.frame_cost(r, results_list)
        notes += [] if note is None else [note]
        rows.append([
            r["model"],
            MISSING if clean is None else _fmt(clean["L2/mAP"], 100, 1),
            MISSING if clean is None else _fmt(clean["L2/mAPH"], 100, 1),
            "-" if frames is None else str(frames),
            "-" if l2 is None else str(order.index(l2) + 1),
            "-" if ms is None else f"{'≥' if lower_bound else ''}{ms:.0f}",
            str(r.get("extra", {}).get("device", "-")),
            _mean_asr_cell(r, families["injection"]),
            _mean_asr_cell(r, families["removal"]),
        ])  # fmt: skip
    if fmt == "latex":
        rows = [[latex_escape(c) for c in row] for row in rows]
        return _render(fmt, None, header, rows)
    text = _render(fmt, None, header, rows)
    return "\n\n".join([text, *(f"ms/frame of {note}." for note in notes)])


def _paired_cell(
    defended: Mapping, control: Mapping, variants: Sequence[str], notes: list[str]
) -> str:
    """``defended - control`` of the mean ASR over ``variants`` with its paired 95% interval
    (:func:`~pcdet_atlas.evaluation.results.build.paired_from_results`); ``-`` where a variant
    lacks an ASR, and where the two cannot be paired (not scored on the same runs, no per-run
    counts), with the reason added to ``notes``."""
    pair = (defended, control)
    if not variants or any((r["variants"].get(v) or {}).get("asr") is None
                           for r in pair for v in variants):  # fmt: skip
        return "-"
    try:
        paired = paired_from_results([defended, control], variants)
    except ResultsError as err:
        notes.append(f"Not paired over {', '.join(variants)}: {err}.")
        return "-"
    a, b = defended["model"], control["model"]
    text = f"{paired['difference'][a][b]:+.2f}"
    if paired["ci"] is not None:
        lo, hi = paired["ci"][a][b]
        text += f" [{lo:+.2f}, {hi:+.2f}]"
    return text


def lot_ablation_table(
    base: Mapping, defended: Mapping, fmt: str = "markdown", control: Mapping | None = None
) -> str:
    """The LOT ablation (paper Tables 5 and 6): per variant each model's L2 mAP and ASR (with
    intervals) and the ASR change the defence makes.

    With ``control`` (the same detector fine-tuned on the defence's last-stage schedule without
    the defence) the change is ``defended - control`` with its paired interval over the
    sequences, per variant and per family mean (the rows "Injection, mean" and "Removal, mean"),
    beside ``defended - base``, which also counts the extra epochs. Without it, only
    ``defended - base``."""
    models = [base] + ([control] if control is not None else []) + [defended]
    names = ordered_variants(set().union(*(m["variants"] for m in models)))
    header = ["Variant"]
    for m in models:
        header += [f"{m['model']} L2 mAP", f"{m['model']} ASR"]
    if control is not None:
        header.append(f"ΔASR vs {control['model']} [95% CI]")
    header.append(f"ΔASR vs {base['model']}")
    rows, notes = [], []
    for name in names:
        entries = [m["variants"].get(name) for m in models]
        cells = [variant_label(name)]
        for entry in entries:
            cells += [MISSING, MISSING] if entry is None else [
                _fmt(entry["L2/mAP"], 100, 1), _fmt_ci(entry)]  # fmt: skip
        if control is not None:
            cells.append("-" if name == "clean" else _paired_cell(defended, control, [name], notes))
        a, b = entries[0], entries[-1]
        delta = None
        if a is not None and b is not None and a["asr"] is not None and b["asr"] is not None:
            delta = b["asr"] - a["asr"]
        cells.append("-" if delta is None else f"{delta:+.2f}")
        rows.append(cells)
    if control is not None:
        for family in ("injection", "removal"):
            variants = queries.attack_variants(models, family)
            if variants:
                row = [f"{family.capitalize()}, mean"]
                for m in models:
                    row += ["", _mean_asr_cell(m, variants)]
                base_mean = queries.mean_asr(base, variants)
                lot_mean = queries.mean_asr(defended, variants)
                rows.append(row + [_paired_cell(defended, control, variants, notes),
                                   "-" if base_mean is None or lot_mean is None
                                   else f"{lot_mean - base_mean:+.2f}"])  # fmt: skip
    if fmt == "latex":
        rows = [[latex_escape(c) for c in row] for row in rows]
        header = [h.replace("ΔASR", "ASR change") for h in header]
        return _render(fmt, None, header, rows)
    return "\n\n".join([_render(fmt, None, header, rows), *notes])


def rpn_cell(results: Mapping) -> str:
    """The proposal network a model's config names (``MODEL.RPN.CFG`` with its checkpoint), ``-``
    for a model without one, or why it cannot be told."""
    try:
        rpn = cfg_from_yaml_file(resolve_repo_path(results["config"])).get("MODEL", {}).get("RPN")
    except (OSError, ValueError) as err:  # ConfigError is a ValueError
        return f"? (config unreadable: {type(err).__name__})"
    if not rpn:
        return "-"
    return f"`{rpn.get('CFG')}` (`{rpn.get('CHECKPOINT')}`)"


def code_cell(results: Mapping) -> str:
    """The package version and the git commit that wrote a results file (12 digits; "modified"
    when tracked files differed from it), or the version alone where no commit was recorded."""
    commit = results.get("source_commit")
    if commit is None:
        return str(results["pcdet_atlas_version"])
    dirty = " (modified)" if results.get("source_dirty") else ""
    return f"{results['pcdet_atlas_version']} `{commit[:12]}`{dirty}"


def _summary_section(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    return [("Models", summary_table(results_list, fmt))]


def _lot_section(lot_pair: tuple[str, str], lot_control: str | None):
    def make(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
        by_name = {r["model"]: r for r in results_list}
        if lot_pair[0] not in by_name or lot_pair[1] not in by_name:
            return []
        control = by_name.get(lot_control) if lot_control else None
        table = lot_ablation_table(by_name[lot_pair[0]], by_name[lot_pair[1]], fmt, control)
        if control is None:
            title = f"LOT ablation: {lot_pair[0]} vs {lot_pair[1]} (paper Tables 5 and 6)"
            if fmt == "markdown":
                table += (f"\n\nNo no-LOT control ({lot_control or 'none named'}) in these "
                          f"results: the change from {lot_pair[0]} also counts {lot_pair[1]}'s "
                          "extra fine-tuning epochs, not LOT alone.")  # fmt: skip
        else:
            title = (f"LOT ablation: {lot_pair[0]}, {lot_control} and {lot_pair[1]} "
                     "(paper Tables 5 and 6)")  # fmt: skip
            if fmt == "markdown":
                table += (f"\n\nΔASR vs {lot_control}: {lot_pair[1]} minus the same detector "
                          "fine-tuned on the same last-stage schedule without LOT (what LOT "
                          "does), with its paired 95% interval over the sequences; the rows "
                          "\"mean\" compare each family's mean ASR. ΔASR vs "
                          f"{lot_pair[0]} also counts the extra epochs.")  # fmt: skip
        return [(title, table)]

    return make


def _seeds_section(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    seeds = seed_spread_text(results_list)
    return [] if seeds is None else [("Seed-to-seed spread", seeds)]


def report_sections(
    lot_pair: tuple[str, str] = DEFAULT_LOT_PAIR, lot_control: str | None = DEFAULT_LOT_CONTROL
) -> list[ReportSection]:
    """The report's sections in their order: its own (the model summary, the LOT ablation of
    ``lot_pair`` with its no-LOT control ``lot_control`` where the results have it, the
    seed-to-seed spread) and those of every registered analysis."""
    own = [
        ReportSection(_summary_section, order=10),
        ReportSection(_lot_section(lot_pair, lot_control), order=30),
        ReportSection(_seeds_section, order=90, latex=False),
    ]
    found = own + [s for analysis in registered_analyses() for s in analysis.sections()]
    return sorted(found, key=lambda section: section.order)  # stable: ties keep their order


def report_figures() -> list[ReportFigure]:
    """The report's figures in their order: those of every registered analysis and its own
    accuracy-against-time figure. Two figures of one file name are an error naming both."""
    found = [f for analysis in registered_analyses() for f in analysis.figures()]
    found.append(ReportFigure("accuracy_vs_time.png",
                              "Clean L2 mAP against model time per frame, coloured by mean ASR",
                              figures.accuracy_vs_time, order=80))  # fmt: skip
    files = [f.file for f in found]
    if len(set(files)) != len(files):
        twice = sorted({name for name in files if files.count(name) > 1})
        raise ResultsError(f"report figures {twice} are drawn by two analyses")
    return sorted(found, key=lambda figure: figure.order)


def write_report(
    results_list: Sequence[Mapping],
    out_dir: str | Path,
    *,
    sources: Sequence[str | Path] | None = None,
    latex: bool = False,
    lot_pair: tuple[str, str] = DEFAULT_LOT_PAIR,
    lot_control: str | None = DEFAULT_LOT_CONTROL,
    command: str | None = None,
    appendix: str | None = None,
) -> dict:
    """Write ``report.md`` and the figures (and ``report.tex`` with ``latex``) to ``out_dir``
    (``appendix``: Markdown added at the end, e.g. how the results were produced).

    Returns ``{'report': path, 'latex': path | None, 'figures': {file: path | reason}}``; a
    figure that cannot be drawn from these results is named in the report with the reason, and
    what a figure leaves out is written under it. Each file is written whole
    (:func:`~pcdet_atlas.utils.files.write_atomic`): a symlink at its name in a received report
    folder is replaced, not written through.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = ["# ATLAS report", ""]
    if command:
        lines += [f"Generated by `{command}`.", ""]
    lines += ["| Model | Config | Checkpoint | RPN | Code | Results file |", "|" + ":---|" * 6]
    for i, r in enumerate(results_list):
        src = "-" if sources is None else f"`{sources[i]}`"
        lines.append(f"| {r['model']} | `{r['config']}` | `{r['checkpoint']}` "
                     f"| {rpn_cell(r)} | {code_cell(r)} | {src} |")  # fmt: skip
    lines += [
        "",
        "L2 mAP and mAPH x100; ASR with its 95% interval over the sequences "
        "(docs/evaluation.md); best **bold**, second _italic_ per variant (point estimates); "
        f"`{MISSING}`: the model was not evaluated on that variant; `{MISSING} (n of m variants)`: "
        "a mean or pooled value over a family of m variants, of which the model has n with an "
        "ASR.",
        "",
    ]
    sections = report_sections(lot_pair, lot_control)
    for section in sections:
        for title, text in section.make(results_list, "markdown"):
            lines += [f"## {title}", "", text, ""]
    drawn: dict = {}
    lines += ["## Figures", ""]
    for figure in report_figures():
        notes: list[str] = []
        result = figure.draw(results_list, out_dir / figure.file, notes)
        drawn[figure.file] = result
        shown = (f"![{figure.caption}]({figure.file})" if isinstance(result, Path)
                 else f"Not drawn: {result}.")  # fmt: skip
        lines += [f"### {figure.caption}", "", shown, ""]
        for note in notes:
            lines += [note, ""]
    lines += ["## Per-model results", ""]
    for r in results_list:
        lines += [format_table(r, "markdown"), ""]
    if appendix:
        lines += [appendix, ""]
    report = write_atomic(out_dir / "report.md", lambda f: f.write("\n".join(lines).encode()))
    tex = None
    if latex:
        parts = ["% ATLAS report tables (booktabs)", ""]
        tables = [t for section in sections if section.latex
                  for t in section.make(results_list, "latex")]  # fmt: skip
        for title, table in tables:
            parts += [f"% {title}", "\\begin{table}[t]", "\\centering", "\\small", table,
                      f"\\caption{{{latex_escape(title)}}}", "\\end{table}", ""]  # fmt: skip
        tex = write_atomic(out_dir / "report.tex", lambda f: f.write("\n".join(parts).encode()))
    return {"report": report, "latex": tex, "figures": drawn}
