"""The lifecycle analysis: ASR and matched scores by lifecycle position k (:mod:`.lifecycle`), its
``lifecycle`` key of a ``results.json`` entry, the report's onset-and-decay table (paper Finding
3), the ASR curves over the lifecycle (Figs. 4 and 6) and the score heatmaps (Figs. 7 and 8)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.evaluation.analyses.lifecycle import lifecycle_asr
from pcdet_atlas.evaluation.analyses.matching import clean_matched_scores
from pcdet_atlas.evaluation.analyses.registry import (
    Analysis,
    ReportFigure,
    ReportSection,
    VariantData,
    register_analysis,
)
from pcdet_atlas.evaluation.analyses.schema_parts import (
    COUNT,
    FRAC,
    INTERVAL,
    RUN,
    check_histogram,
    check_rate,
    closed,
    fail,
    nullable,
)
from pcdet_atlas.evaluation.intervals import asr_interval
from pcdet_atlas.evaluation.results.figures import HIGH_SCORE
from pcdet_atlas.evaluation.results.queries import (
    attack_variants,
    covered_variants,
    families_present,
    family_variants,
)
from pcdet_atlas.evaluation.results.style import (
    MASKED_COLOUR,
    MASKED_HATCH,
    OKABE_ITO,
    data_norm,
    figure_grid,
    label_panels,
    legend_below,
    render,
    variant_styles,
)
from pcdet_atlas.evaluation.results.tables import (
    _render,
    format_interval,
    latex_escape,
    missing_of,
    variant_label,
)

__all__ = [
    "LifecycleAnalysis",
    "lifecycle_curves",
    "lifecycle_curves_figure",
    "lifecycle_heatmaps",
    "lifecycle_heatmaps_figure",
    "lifecycle_table",
]

#: The shading of the spoofed positions k = 1..W (Okabe and Ito's yellow, lightened).
SPOOFED_COLOUR = "#FAF4B7"

LIFECYCLE_SCHEMA = closed(
    {
        "window": {"type": "integer", "minimum": 1},
        "recorded_window": {"type": "integer", "minimum": 1},
        "k": {"type": "array", "items": COUNT},
        "score_bin_edges": {"type": "array", "items": {"type": "number"}, "minItems": 2},
        "attacked": {"type": "array", "items": {"type": "boolean"}},
        "num_targets": {"type": "array", "items": COUNT},
        "num_success": {"type": "array", "items": COUNT},
        "asr": {"type": "array", "items": nullable(FRAC)},
        # per k the run-level interval of the ASR; None before schema 6
        "asr_ci": nullable(
            {
                "type": "array",
                "items": nullable(INTERVAL),
            }
        ),  # fmt: skip
        # per k the per-run counts behind it (pooled intervals); None before schema 6
        "runs": nullable({"type": "array", "items": {"type": "array", "items": RUN}}),
        "num_success_lenient": {"type": "array", "items": COUNT},
        "asr_lenient": {"type": "array", "items": nullable(FRAC)},
        "score_counts": {"type": "array", "items": {"type": "array", "items": COUNT}},
        # the clean run's scores of the same targets per k; None without a clean run / before 4
        "clean_score_counts": nullable(
            {"type": "array", "items": {"type": "array", "items": COUNT}}
        ),
    }
)


def _lifecycle(lc: Mapping, path: str) -> None:
    w = lc["window"]
    if lc["recorded_window"] < w:
        fail(f"{path}['recorded_window']", f"must be >= window {w}")
    if lc["k"] != list(range(2 * w + 1)):
        fail(f"{path}['k']", f"expected [0, ..., {2 * w}], got {lc['k']!r}")
    for key in ("attacked", "num_targets", "num_success", "asr", "asr_ci", "runs",
                "num_success_lenient",
                "asr_lenient", "score_counts", "clean_score_counts"):  # fmt: skip
        if lc[key] is not None and len(lc[key]) != 2 * w + 1:
            fail(f"{path}['{key}']", f"expected a list of {2 * w + 1} entries")
    if lc["attacked"] != [1 <= k <= w for k in range(2 * w + 1)]:
        fail(f"{path}['attacked']", "must be True exactly at k = 1..window")
    for k in range(2 * w + 1):
        at, n = f"{path}[k={k}]", lc["num_targets"][k]
        for num_key, rate_key in (("num_success", "asr"), ("num_success_lenient", "asr_lenient")):
            check_rate(
                lc[rate_key][k], lc[num_key][k], n, f"{at}['{rate_key}']", f"{at}['{num_key}']"
            )
        if lc["runs"] is not None:
            counts = [(sum(r[c] for r in lc["runs"][k])) for c in ("num_targets", "num_success")]
            if counts != [n, lc["num_success"][k]]:
                fail(
                    f"{at}['runs']", f"add up to {counts}, not the {n} targets and their successes"
                )
        ci = None if lc["asr_ci"] is None else lc["asr_ci"][k]
        if ci is not None and not (n and ci[0] <= lc["asr"][k] <= ci[1]):
            fail(f"{at}['asr_ci']", f"{ci} must hold the ASR {lc['asr'][k]} (targets {n})")
        hist = {"bin_edges": lc["score_bin_edges"], "counts": lc["score_counts"][k]}
        check_histogram(hist, f"{at}['score_counts']")
        if sum(lc["score_counts"][k]) > n:
            fail(f"{at}['score_counts']", f"more scores than targets ({n})")
        if lc["clean_score_counts"] is not None:
            clean = {"bin_edges": lc["score_bin_edges"], "counts": lc["clean_score_counts"][k]}
            check_histogram(clean, f"{at}['clean_score_counts']")
            if sum(clean["counts"]) > n:
                fail(f"{at}['clean_score_counts']", f"more scores than targets ({n})")


def _lifecycle_models(results_list, family, notes):
    """(results, its ``family`` variants with lifecycle data) of each model with one; the others
    are named in ``notes``."""
    out, without = [], []
    for r in results_list:
        names = [n for n in family_variants(r, family) if r["variants"][n]["lifecycle"]]
        if names:
            out.append((r, names))
        else:
            without.append(r["model"])
    if out and without and notes is not None:
        notes.append(f"No panel (no {family} variant with lifecycle data): {', '.join(without)}.")
    return out


def _spoofed_patch():
    from matplotlib.patches import Patch

    return Patch(facecolor=SPOOFED_COLOUR, edgecolor="none", label="spoofed frames (k = 1..W)")


def _k_axis(ax) -> None:
    """Integer ticks on the lifecycle position axis."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True, nbins=5))


def lifecycle_curves(
    results_list: Sequence[Mapping], family: str, path: Path, notes: list[str] | None = None
) -> Path | str:
    """:func:`lifecycle_curves_figure` written to ``path`` (PNG, PDF beside)."""
    return render(lambda: lifecycle_curves_figure(results_list, family, notes), path)


def lifecycle_curves_figure(
    results_list: Sequence[Mapping], family: str, notes: list[str] | None = None
):
    """ASR by lifecycle position k per model (a panel each, one ASR axis for all) and variant (a
    line each, its band the run-level 95% interval ``asr_ci`` where the results have one): k =
    1..W spoofed (shaded), k > W the clean frames after the run (paper Figs. 4 and 6); one
    legend under the panels."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    models = _lifecycle_models(results_list, family, notes)
    if not models:
        return f"no {family} variant with lifecycle data"
    styles = variant_styles(attack_variants(results_list))
    shown = [n for n in attack_variants(results_list, family) if any(n in ns for _, ns in models)]
    banded = any(r["variants"][n]["lifecycle"].get("asr_ci") is not None
                 for r, names in models for n in names)  # fmt: skip
    fig, axes = figure_grid(len(models), sharey=True,
                            legend_entries=len(shown) + 1 + banded)  # fmt: skip
    for ax, (r, names) in zip(axes, models):
        window = r["variants"][names[0]]["lifecycle"]["window"]
        ax.axvspan(0.5, window + 0.5, color=SPOOFED_COLOUR, lw=0, zorder=0)
        for name in names:
            lc, style = r["variants"][name]["lifecycle"], styles[name]
            asr = np.array([np.nan if a is None else a for a in lc["asr"]], dtype=float)
            ax.plot(lc["k"], asr, marker=style.marker, ms=2, **style.line(), zorder=3)
            if lc.get("asr_ci") is not None:  # the run-level 95% interval as a band
                lo, hi = (
                    np.array([np.nan if c is None else c[i] for c in lc["asr_ci"]], dtype=float)
                    for i in (0, 1)
                )
                ax.fill_between(lc["k"], lo, hi, color=style.colour, alpha=0.15, lw=0, zorder=2)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlim(-0.5, 2 * window + 0.5)
        _k_axis(ax)
        ax.set_title(f"{r['model']} (W = {window})")
        ax.grid(lw=0.3)
    label_panels(axes, "lifecycle position k", "ASR")
    handles = [Line2D([], [], marker=styles[n].marker, ms=3, **styles[n].line(),
                      label=variant_label(n)) for n in shown]  # fmt: skip
    handles.append(_spoofed_patch())
    if banded:
        handles.append(Patch(facecolor="0.5", alpha=0.3, lw=0, label="95% interval (runs)"))
    legend_below(fig, handles)
    return fig


def _bin_centres(edges) -> np.ndarray:
    edges = np.asarray(edges, dtype=float)
    return 0.5 * (edges[1:] + edges[:-1])


def _mean_from_counts(edges, counts) -> float:
    counts = np.asarray(counts, dtype=float)
    return float(counts @ _bin_centres(edges) / counts.sum()) if counts.sum() > 0 else np.nan


def _pooled_lifecycles(r, names, family_names):
    """The lifecycles of ``names`` that pool with the first (same window and score bins), and
    why each other variant of ``family_names`` is not pooled."""
    lcs = [r["variants"][n]["lifecycle"] for n in names]
    window, edges = lcs[0]["window"], lcs[0]["score_bin_edges"]
    pooled = [lc for lc in lcs if lc["window"] == window and lc["score_bin_edges"] == edges]
    left = {}
    for name in family_names:
        entry = r["variants"].get(name)
        if entry is None:
            left[name] = "not evaluated"
        elif entry["lifecycle"] is None:
            left[name] = "no lifecycle data"
        elif entry["lifecycle"]["window"] != window:
            left[name] = f"window {entry['lifecycle']['window']}, not {window}"
        elif entry["lifecycle"]["score_bin_edges"] != edges:
            left[name] = f"score bins differ from {names[0]}'s"
    return pooled, left


def lifecycle_heatmaps(
    results_list: Sequence[Mapping], family: str, path: Path, notes: list[str] | None = None
) -> Path | str:
    """:func:`lifecycle_heatmaps_figure` written to ``path`` (PNG, PDF beside)."""
    return render(lambda: lifecycle_heatmaps_figure(results_list, family, notes), path)


def lifecycle_heatmaps_figure(
    results_list: Sequence[Mapping], family: str, notes: list[str] | None = None
):
    """Per model, the targets' matched scores by lifecycle position (the family's variants
    pooled): each column k is the fraction of that k's targets detected with a score in each
    bin (a column sums to the detected fraction); a column without targets has no value and is
    masked (grey, hatched), never drawn as a zero. One colour scale for all panels, spanning the
    drawn cells' values; one score axis. The white line is the mean attacked score of the
    detected targets; the dashed blue line the clean baseline, the mean clean-run score of the
    same targets at the same frames (paper Figs. 7 and 8). A panel pools what it can
    (``notes``: the variants of the family that a model's panel leaves out, and why)."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.patheffects import withStroke

    models = _lifecycle_models(results_list, family, notes)
    if not models:
        return f"no {family} variant with lifecycle data"
    family_names = attack_variants(results_list, family)
    panels = []
    for r, names in models:
        lcs, left = _pooled_lifecycles(r, names, family_names)
        window, edges = lcs[0]["window"], lcs[0]["score_bin_edges"]
        if left and notes is not None:
            notes.append(f"{r['model']}: pooled without "
                         + ", ".join(f"{n} ({why})" for n, why in left.items()) + ".")  # fmt: skip
        counts = np.sum([np.asarray(lc["score_counts"], dtype=float) for lc in lcs], axis=0)
        targets = np.sum([np.asarray(lc["num_targets"], dtype=float) for lc in lcs], axis=0)
        frac = np.divide(counts, targets[:, None], out=np.zeros_like(counts),
                         where=targets[:, None] > 0)  # fmt: skip
        frac = np.ma.masked_array(frac, mask=np.broadcast_to(targets[:, None] == 0, frac.shape))
        panels.append((r, lcs, window, edges, counts, frac))
    cells = np.ma.concatenate([frac.ravel() for *_, frac in panels])
    # no cell with targets: every cell masked, and no colour bar to span nothing
    norm = data_norm(cells) if cells.count() else Normalize(0.0, 1.0)
    cmap = colormaps["magma"].with_extremes(bad=(0.0, 0.0, 0.0, 0.0))  # masked: see-through
    clean_drawn = masked = False
    fig, axes = figure_grid(len(models), sharey=True, legend_entries=5)
    outline = [withStroke(linewidth=2.2, foreground="black")]
    for ax, (r, lcs, window, edges, counts, frac) in zip(axes, panels):
        ks = np.asarray(lcs[0]["k"])
        ax.patch.set_facecolor(MASKED_COLOUR)  # what a masked cell shows
        ax.patch.set_hatch(MASKED_HATCH)
        ax.patch.set_edgecolor("0.55")
        masked |= bool(frac.mask.any())
        ax.imshow(frac.T, origin="lower", aspect="auto", cmap=cmap, norm=norm,
                  interpolation="nearest",
                  extent=(ks[0] - 0.5, ks[-1] + 0.5, edges[0], edges[-1]))  # fmt: skip
        ax.plot(ks, [_mean_from_counts(edges, c) for c in counts], color="white", lw=1,
                marker="o", ms=2, path_effects=outline)  # fmt: skip
        clean = [lc["clean_score_counts"] for lc in lcs]
        if all(c is not None for c in clean):
            clean_drawn = True
            clean_counts = np.sum([np.asarray(c, dtype=float) for c in clean], axis=0)
            ax.plot(ks, [_mean_from_counts(edges, c) for c in clean_counts], color=OKABE_ITO[5],
                    ls="--", lw=1, marker="s", ms=2)  # fmt: skip
        ax.axvline(window + 0.5, color=OKABE_ITO[2], ls=":", lw=1)
        ax.axhline(HIGH_SCORE, color="0.6", ls=":", lw=0.8)
        _k_axis(ax)
        ax.set_title(f"{r['model']} (W = {window})")
    label_panels(axes, "lifecycle position k", "score")
    if cells.count():
        fig.colorbar(ScalarMappable(norm, cmap), ax=list(axes), label="fraction of targets")
    handles = [Line2D([], [], color="white", marker="o", ms=2, path_effects=outline,
                      label="attacked score (mean)")]  # fmt: skip
    if clean_drawn:
        handles.append(Line2D([], [], color=OKABE_ITO[5], ls="--", marker="s", ms=2,
                              label="clean baseline (mean)"))  # fmt: skip
    handles += [
        Line2D([], [], color=OKABE_ITO[2], ls=":", label="end of spoofing (k = W)"),
        Line2D([], [], color="0.6", ls=":", label=f"score {HIGH_SCORE}"),
    ]
    if masked:
        handles.append(Patch(facecolor=MASKED_COLOUR, edgecolor="0.55", hatch=MASKED_HATCH,
                             label="no targets at this k"))  # fmt: skip
    legend_below(fig, handles)
    return fig


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
    families = [f for f in families_present(results_list)
                if any(v["family"] == f and v["lifecycle"] is not None
                       for r in results_list for v in r["variants"].values())]  # fmt: skip
    if not families:
        return None
    names = {f: attack_variants(results_list, f) for f in families}
    header, rows = ["Model", "W"], []
    positions = (("k=0", lambda w: 0), ("k=1", lambda w: 1), ("k=W", lambda w: w),
                 ("k=W+1", lambda w: w + 1))  # fmt: skip
    for family in families:
        header += [f"{family} {label}" for label, _ in positions]
    for r in results_list:
        window, row = None, [r["model"]]
        for family in families:
            pooled = covered_variants(r, names[family], lifecycle=True)
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
                interval = format_interval(ci)
                row.append("-" if not total else f"{hits / total:.2f}{interval} ({hits}/{total})")
        rows.append(row[:1] + ["-" if window is None else str(window)] + row[1:])
    if fmt == "latex":
        rows = [[latex_escape(c) for c in row] for row in rows]
    return _render(fmt, None, header, rows)


def _table(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    table = lifecycle_table(results_list, fmt)
    return [] if table is None else [("Attack onset and decay (paper Finding 3)", table)]


def _curves(family: str):
    return lambda results_list, path, notes: lifecycle_curves(results_list, family, path, notes)


def _heatmap(family: str):
    return lambda results_list, path, notes: lifecycle_heatmaps(results_list, family, path, notes)


@register_analysis
class LifecycleAnalysis(Analysis):
    """The ``lifecycle`` entry (:func:`~.lifecycle.lifecycle_asr`) of a detector with a temporal
    window; None without one or without targets."""

    name = "lifecycle"
    required = True

    def schema(self) -> dict[str, dict]:
        return {"lifecycle": nullable(LIFECYCLE_SCHEMA)}

    def compute(self, data: VariantData) -> dict:
        matches = data.matches
        if data.window is None or len(matches) == 0:
            return {"lifecycle": None}
        clean_scores = (
            None
            if data.clean_det_annos is None
            else clean_matched_scores(matches, data.clean_det_annos, iou_fn=data.iou_fn)
        )
        lifecycle = lifecycle_asr(
            matches,
            data.window,
            recorded_window=data.recorded_window,
            num_bins=data.num_bins,
            clean_scores=clean_scores,
        )
        return {"lifecycle": lifecycle}

    def check(self, entry: Mapping, path: str) -> None:
        if entry["lifecycle"] is not None:
            _lifecycle(entry["lifecycle"], f"{path}['lifecycle']")

    def sections(self) -> list[ReportSection]:
        return [ReportSection(_table, order=40)]

    def figures(self) -> list[ReportFigure]:
        return [
            ReportFigure("lifecycle_injection.png",
                         "Injection ASR over the attack lifecycle (paper Fig. 6)",
                         _curves("injection"), order=20),
            ReportFigure("lifecycle_removal.png",
                         "Removal ASR over the attack lifecycle (paper Fig. 4)",
                         _curves("removal"), order=30),
            ReportFigure("heatmap_injection.png",
                         "Phantom confidence over the lifecycle (paper Fig. 7)",
                         _heatmap("injection"), order=60),
            ReportFigure("heatmap_removal.png",
                         "Target confidence over the lifecycle (paper Fig. 8)",
                         _heatmap("removal"), order=70),
        ]  # fmt: skip
