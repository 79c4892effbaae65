"""The paper's report from ``results.json`` files: ``report.md`` with its tables (and, on request,
``report.tex`` with the same tables), and its figures as PNGs (docs/evaluation.md "Report").

Tables: a model summary (clean L2 mAP/mAPH, input frames, clean rank, model time per frame,
mean ASR per family), the injection table (paper Table 3) and the removal table (Table 4) with
per-variant L2 mAP and ASR with its run-level interval (best and second best marked), the LOT
ablation (Tables 5 and 6) when both models of the pair are given, the lifecycle's onset and
decay (Finding 3: ASR at k = 0, 1, W, W + 1), the share of phantoms detected with confidence above
0.7 (Fig. 5), the centre-gap table, the robustness ranks, the paired model comparison, the
seed-to-seed spread (when two results are one model config trained with different seeds:
:mod:`~pcdet_atlas.evaluation.results.seeds`), and each model's full table with its runs and
targets. A model that was not evaluated on a variant shows ``missing`` there, never a
zero; a mean or pooled value over a family needs every variant of the family that any model has,
each with an ASR, and otherwise reads ``missing (n of m variants)``. The ranks name the variants
they are over and those left out; under each figure the report names what it leaves out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from pcdet_atlas.config import cfg_from_yaml_file, resolve_repo_path
from pcdet_atlas.evaluation.intervals import asr_interval
from pcdet_atlas.evaluation.results import figures
from pcdet_atlas.evaluation.results.build import paired_from_results, ranks_from_results
from pcdet_atlas.evaluation.results.io import find_results_files, load_results
from pcdet_atlas.evaluation.results.schema import ResultsError
from pcdet_atlas.evaluation.results.seeds import seed_spread_text
from pcdet_atlas.evaluation.results.tables import (
    MISSING,
    _render,
    format_comparison_table,
    format_ranks,
    format_table,
    latex_escape,
    missing_of,
    ordered_variants,
    variant_label,
)

__all__ = [
    "DEFAULT_LOT_PAIR",
    "FIGURES",
    "centre_gap_table",
    "collect_results",
    "confident_phantom_table",
    "lifecycle_table",
    "lot_ablation_table",
    "paired_table",
    "summary_table",
    "write_report",
]

#: The model names (``ATLAS.MODEL_NAME``) of the LOT ablation: the detector and its defence.
DEFAULT_LOT_PAIR = ("PHiM", "PHiM+LOT")
#: Figure file -> (caption, how it is drawn: ``draw(results_list, path, notes)``, appending to
#: ``notes`` what the figure leaves out).
FIGURES = {
    "rank_correlation.png": ("Robustness rank correlation (paper Fig. 3)",
                             figures.rank_correlation),
    "lifecycle_injection.png": ("Injection ASR over the attack lifecycle (paper Fig. 6)",
                                lambda r, p, n: figures.lifecycle_curves(r, "injection", p, n)),
    "lifecycle_removal.png": ("Removal ASR over the attack lifecycle (paper Fig. 4)",
                              lambda r, p, n: figures.lifecycle_curves(r, "removal", p, n)),
    "confidence_injection.png": ("Phantom confidence under injection (paper Fig. 5)",
                                 lambda r, p, n: figures.confidence_histograms(r, "injection", p)),
    "confidence_removal.png": ("Target confidence under removal (paper Fig. 9)",
                               lambda r, p, n: figures.confidence_histograms(r, "removal", p)),
    "heatmap_injection.png": ("Phantom confidence over the lifecycle (paper Fig. 7)",
                              lambda r, p, n: figures.lifecycle_heatmaps(r, "injection", p, n)),
    "heatmap_removal.png": ("Target confidence over the lifecycle (paper Fig. 8)",
                            lambda r, p, n: figures.lifecycle_heatmaps(r, "removal", p, n)),
    "accuracy_vs_time.png": ("Clean L2 mAP against model time per frame, coloured by mean ASR",
                             figures.accuracy_vs_time),
}  # fmt: skip


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
    text = f"{entry['asr']:.2f}"
    if entry["asr_ci"] is not None:
        text += f" [{entry['asr_ci'][0]:.2f}, {entry['asr_ci'][1]:.2f}]"
    return text


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
    mean = figures.mean_asr(results, variants)
    if mean is None:
        return missing_of(len(figures.covered_variants(results, variants)), len(variants))
    return _fmt(mean)


def summary_table(results_list: Sequence[Mapping], fmt: str = "markdown") -> str:
    """A row per model: clean L2 mAP / mAPH (x100), input frames, clean rank (1 = highest clean
    L2 mAP), model ms/frame on the clean run (:func:`figures.frame_cost`: with the RPN's time
    for proposals read from the prediction store, ``≥`` where it cannot be added; in Markdown
    each such model is explained under the table) and its device, mean ASR per family (over
    every variant of the family that any of the models has: ``missing (n of m variants)`` for a
    model without all of them)."""
    families = {f: figures.attack_variants(results_list, f) for f in ("injection", "removal")}
    maps = [(r["variants"].get("clean") or {}).get("L2/mAP") for r in results_list]
    order = sorted({m for m in maps if m is not None}, reverse=True)
    header = ["Model", "L2 mAP", "L2 mAPH", "Frames", "Clean rank", "ms/frame", "Device",
              "Mean inj. ASR", "Mean rem. ASR"]  # fmt: skip
    rows, notes = [], []
    for r, l2 in zip(results_list, maps):
        clean = r["variants"].get("clean")
        frames = input_frames(r)
        ms, lower_bound, note = figures.frame_cost(r, results_list)
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


def lot_ablation_table(base: Mapping, defended: Mapping, fmt: str = "markdown") -> str:
    """The LOT ablation (paper Tables 5 and 6): per variant both models' L2 mAP and ASR (with
    intervals) and the ASR change the defence makes (defended - base)."""
    names = ordered_variants(set(base["variants"]) | set(defended["variants"]))
    header = ["Variant", f"{base['model']} L2 mAP", f"{base['model']} ASR",
              f"{defended['model']} L2 mAP", f"{defended['model']} ASR", "ΔASR"]  # fmt: skip
    rows = []
    for name in names:
        a, b = base["variants"].get(name), defended["variants"].get(name)
        cells = [variant_label(name)]
        for entry in (a, b):
            cells += [MISSING, MISSING] if entry is None else [
                _fmt(entry["L2/mAP"], 100, 1), _fmt_ci(entry)]  # fmt: skip
        delta = None
        if a is not None and b is not None and a["asr"] is not None and b["asr"] is not None:
            delta = b["asr"] - a["asr"]
        cells.append("-" if delta is None else f"{delta:+.2f}")
        rows.append(cells)
    if fmt == "latex":
        rows = [[latex_escape(c) for c in row] for row in rows]
        header[-1] = "ASR change"
    return _render(fmt, None, header, rows)


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


def _pooled_lifecycle_interval(lcs: Sequence[Mapping], k: int) -> tuple[float, float] | None:
    """The run-level interval of position ``k`` pooled over lifecycles ``lcs``: each spoof run's
    counts summed over the variants (the variants of a family share their runs), None when a
    lifecycle lacks per-run counts (schema 5 and older) or there are fewer than two runs."""
    pooled: dict[tuple[str, int], dict] = {}
    for lc in lcs:
        if lc.get("runs") is None or k not in lc["k"]:
            return None
        for run in lc["runs"][lc["k"].index(k)]:
            key = (run["sequence"], run["run_id"])
            into = pooled.setdefault(key, {"sequence": run["sequence"], "run_id": run["run_id"],
                                           "num_targets": 0, "num_success": 0})  # fmt: skip
            into["num_targets"] += run["num_targets"]
            into["num_success"] += run["num_success"]
    return asr_interval(list(pooled.values())) if pooled else None


def lifecycle_table(results_list: Sequence[Mapping], fmt: str = "markdown") -> str | None:
    """The attack lifecycle at the positions the paper's Finding 3 compares, per model and family
    (the family's variants pooled): k = 0 (the last clean frame: the clean model's own rate, a
    missed removal target or a detection where the phantom will be), k = 1 (only the current
    frame spoofed), k = W (the whole W-frame input spoofed) and k = W + 1 (the current frame
    clean again, the rest of the input still spoofed), as ASR with the successes and targets
    behind it and its run-level 95% interval (each run's counts summed over the variants;
    pooling repeats the clean k = 0 frames, which every variant shares). A model is
    pooled over every variant of the family that any of the models has, each with an ASR and
    lifecycle data, or its cells read ``missing (n of m variants)``; None without lifecycle
    data."""
    families = [f for f in _families_present(results_list)
                if any(v["family"] == f and v["lifecycle"] is not None
                       for r in results_list for v in r["variants"].values())]  # fmt: skip
    if not families:
        return None
    names = {f: figures.attack_variants(results_list, f) for f in families}
    header, rows = ["Model", "W"], []
    positions = (("k=0", lambda w: 0), ("k=1", lambda w: 1), ("k=W", lambda w: w),
                 ("k=W+1", lambda w: w + 1))  # fmt: skip
    for family in families:
        header += [f"{family} {label}" for label, _ in positions]
    for r in results_list:
        window, row = None, [r["model"]]
        for family in families:
            pooled = figures.covered_variants(r, names[family], lifecycle=True)
            if len(pooled) < len(names[family]):
                row += [missing_of(len(pooled), len(names[family]))] * len(positions)
                continue
            lcs = [r["variants"][n]["lifecycle"] for n in pooled]
            window = int(lcs[0]["window"])
            for _, position in positions:
                k = position(window)
                hits = sum(lc["num_success"][lc["k"].index(k)] for lc in lcs if k in lc["k"])
                total = sum(lc["num_targets"][lc["k"].index(k)] for lc in lcs if k in lc["k"])
                ci = _pooled_lifecycle_interval(lcs, k)
                interval = "" if ci is None else f" [{ci[0]:.2f}, {ci[1]:.2f}]"
                row.append("-" if not total else f"{hits / total:.2f}{interval} ({hits}/{total})")
        rows.append(row[:1] + ["-" if window is None else str(window)] + row[1:])
    if fmt == "latex":
        rows = [[latex_escape(c) for c in row] for row in rows]
    return _render(fmt, None, header, rows)


def _families_present(results_list: Sequence[Mapping]) -> list[str]:
    fams = {v["family"] for r in results_list for v in r["variants"].values()}
    return [f for f in ("injection", "removal") if f in fams] + sorted(
        fams - {"clean", "injection", "removal"}
    )


def _table_sections(results_list, fmt, lot_pair) -> list[tuple[str, str]]:
    """(title, table) of every table of the report, in its order."""
    sections = [("Models", summary_table(results_list, fmt))]
    titles = {"injection": "Point injection (paper Table 3)",
              "removal": "Point removal (paper Table 4)"}  # fmt: skip
    for family in _families_present(results_list):
        sections.append((
            titles.get(family, f"Family {family}"),
            format_comparison_table(results_list, fmt, family=family, missing="show"),
        ))  # fmt: skip
    by_name = {r["model"]: r for r in results_list}
    if lot_pair[0] in by_name and lot_pair[1] in by_name:
        sections.append((
            f"LOT ablation: {lot_pair[0]} vs {lot_pair[1]} (paper Tables 5 and 6)",
            lot_ablation_table(by_name[lot_pair[0]], by_name[lot_pair[1]], fmt),
        ))  # fmt: skip
    lifecycle = lifecycle_table(results_list, fmt)
    if lifecycle is not None:
        sections.append(("Attack onset and decay (paper Finding 3)", lifecycle))
    confident = confident_phantom_table(results_list, fmt)
    if confident is not None:
        sections.append(("Phantoms detected with confidence above 0.7 (paper Fig. 5)", confident))
    gap = centre_gap_table(results_list, fmt)
    if gap is not None:
        sections.append(("Centre gap under removal (clean peak - attacked peak)", gap))
    return sections


def _ranks_text(results_list) -> str:
    """The ranks over the ranked variants every model has with an ASR, naming them and the
    variants left out."""
    variants, dropped = figures.ranked_variants(results_list)
    note = figures.ranked_variants_note(variants, dropped)
    if len(results_list) < 2 or not variants:
        return f"needs at least 2 models with a common ranked variant\n\n{note}"
    ranks = format_ranks(ranks_from_results(results_list, variants=variants), "markdown")
    return f"{ranks}\n\n{note}"


def paired_table(results_list: Sequence[Mapping], group: str, variants: Sequence[str]) -> str:
    """Markdown: each model's mean ASR over ``variants`` (a rank group's) and, per pair, the
    difference row - column with its paired 95% interval over the sequences
    (:func:`paired_from_results`), **bold** where the interval excludes 0; or why it cannot be
    computed."""
    if len(results_list) < 2 or not variants:
        return f"needs at least 2 models with a common {group} variant"
    try:
        out = paired_from_results(results_list, variants)
    except ResultsError as err:
        return f"not computed: {err}"
    models = out["models"]
    header = ["Model", "mean ASR", *models]
    rows = []
    for a in models:
        row = [a, f"{out['mean_asr'][a]:.2f}"]
        for b in models:
            if a == b:
                row.append("-")
                continue
            text = f"{out['difference'][a][b]:+.2f}"
            if out["ci"] is not None:
                lo, hi = out["ci"][a][b]
                text += f" [{lo:+.2f}, {hi:+.2f}]"
                if lo > 0 or hi < 0:
                    text = f"**{text}**"
            row.append(text)
        rows.append(row)
    runs = ", ".join(f"{variant_label(v)}: {n}" for v, n in out["num_runs"].items())
    table = _render("markdown", None, header, rows)
    unit = "sequences" if out["cluster"] == "sequence" else "runs of one sequence"
    return (f"{table}\n\nOver {len(variants)} variant(s), clustered by {out['num_clusters']} "
            f"{unit}; runs per variant: {runs}.")  # fmt: skip


def _paired_text(results_list) -> str:
    """The paired comparison per rank group, over the ranked variants every model has with an
    ASR."""
    variants, _ = figures.ranked_variants(results_list)
    groups: dict[str, list[str]] = {}
    for name in variants:
        groups.setdefault(results_list[0]["variants"][name]["rank_group"], []).append(name)
    if not groups:
        return "needs at least 2 models with a common ranked variant"
    parts = [
        "Row minus column: the difference of the two models' mean ASR over the group's "
        "variants, with its 95% paired interval over the sequences the spoof runs lie in "
        "(a cluster-robust t interval on the per-sequence differences, the same runs for every "
        "model and variant; docs/evaluation.md); **bold**: the interval excludes 0. Each pair "
        "is judged on its own (no correction for the number of pairs)."
    ]
    for group, names in groups.items():
        parts += [f"### {group}", paired_table(results_list, group, names)]
    return "\n\n".join(parts)


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


def write_report(
    results_list: Sequence[Mapping],
    out_dir: str | Path,
    *,
    sources: Sequence[str | Path] | None = None,
    latex: bool = False,
    lot_pair: tuple[str, str] = DEFAULT_LOT_PAIR,
    command: str | None = None,
    appendix: str | None = None,
) -> dict:
    """Write ``report.md`` and the figures (and ``report.tex`` with ``latex``) to ``out_dir``
    (``appendix``: Markdown added at the end, e.g. how the results were produced).

    Returns ``{'report': path, 'latex': path | None, 'figures': {file: path | reason}}``; a
    figure that cannot be drawn from these results is named in the report with the reason, and
    what a figure leaves out is written under it.
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
    for title, table in _table_sections(results_list, "markdown", lot_pair):
        lines += [f"## {title}", "", table, ""]
    lines += ["## Robustness ranks", "", _ranks_text(results_list), ""]
    lines += ["## Paired model comparison", "", _paired_text(results_list), ""]
    seeds = seed_spread_text(results_list)
    if seeds is not None:
        lines += ["## Seed-to-seed spread", "", seeds, ""]
    drawn: dict = {}
    lines += ["## Figures", ""]
    for name, (caption, draw) in FIGURES.items():
        notes: list[str] = []
        result = draw(results_list, out_dir / name, notes)
        drawn[name] = result
        shown = f"![{caption}]({name})" if isinstance(result, Path) else f"Not drawn: {result}."
        lines += [f"### {caption}", "", shown, ""]
        for note in notes:
            lines += [note, ""]
    lines += ["## Per-model results", ""]
    for r in results_list:
        lines += [format_table(r, "markdown"), ""]
    if appendix:
        lines += [appendix, ""]
    report = out_dir / "report.md"
    report.write_text("\n".join(lines))
    tex = None
    if latex:
        parts = ["% ATLAS report tables (booktabs)", ""]
        for title, table in _table_sections(results_list, "latex", lot_pair):
            parts += [f"% {title}", "\\begin{table}[t]", "\\centering", "\\small", table,
                      f"\\caption{{{latex_escape(title)}}}", "\\end{table}", ""]  # fmt: skip
        tex = out_dir / "report.tex"
        tex.write_text("\n".join(parts))
    return {"report": report, "latex": tex, "figures": drawn}
