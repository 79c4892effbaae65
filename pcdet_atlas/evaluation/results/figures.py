"""The report's figures that belong to no single analysis: drawing only. The data a figure shows
comes from :mod:`~pcdet_atlas.evaluation.results.queries`; its style, size and files (PNG and
PDF) from :mod:`~pcdet_atlas.evaluation.results.style`; the analyses' own figures live with them
(:mod:`pcdet_atlas.evaluation.analyses`).

A figure is a builder, ``*_figure(results_list, ..., notes)``, that returns a ``Figure`` or a
string saying why the figure cannot be drawn from the results it was given (too few models, no
timing), and a function of the report's ``ReportFigure`` form that builds it in the paper style
and writes it (:func:`~pcdet_atlas.evaluation.results.style.render`). What a figure leaves out
of the given results (a model, a variant, a colour) its builder appends, with the reason, to
``notes`` when given a list, for the report to print under the figure."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from pcdet_atlas.evaluation.results.queries import (
    attack_variants,
    covered_variants,
    frame_cost,
    mean_asr,
)
from pcdet_atlas.evaluation.results.style import data_norm, figure_grid, legend_below, render
from pcdet_atlas.evaluation.results.tables import missing_of

__all__ = ["HIGH_SCORE", "accuracy_vs_time", "accuracy_vs_time_figure"]

#: The high-confidence score the confidence and heatmap figures mark (the paper's 0.7).
HIGH_SCORE = 0.7


# ----------------------------------------------------------------------------- accuracy/time
def accuracy_vs_time(
    results_list: Sequence[Mapping], path: Path, notes: list[str] | None = None
) -> Path | str:
    """:func:`accuracy_vs_time_figure` written to ``path`` (PNG, PDF beside)."""
    return render(lambda: accuracy_vs_time_figure(results_list, notes), path)


def accuracy_vs_time_figure(results_list: Sequence[Mapping], notes: list[str] | None = None):
    """Clean L2 mAP against measured model ms/frame per model (:func:`frame_cost`: a two-stage
    model's proposals read from the prediction store at its RPN's time; a right-pointing marker
    where that time cannot be added and the value is a lower bound), the marker coloured by the
    mean ASR over the attack variants of all the models (:func:`mean_asr`; the colour bar spans
    the models' values); a model without every one of them has a hollow grey marker. ``notes``:
    the models left out (no clean timing or mAP), those drawn hollow, and how each store-served
    model's time was counted. One column wide."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FormatStrFormatter, FuncFormatter

    variants = attack_variants(results_list)
    points, untimed, time_notes = [], [], []
    for r in results_list:
        (ms, lower_bound, note), clean = frame_cost(r, results_list), r["variants"].get("clean")
        if ms is None or clean is None or clean["L2/mAP"] is None:
            untimed.append(r["model"])
            continue
        time_notes += [] if note is None else [note]
        points.append((r, ms, 100.0 * clean["L2/mAP"], mean_asr(r, variants), lower_bound))
    if not points:
        return "no model has a clean variant with timing and L2 mAP"
    devices = sorted({str(r.get("extra", {}).get("device", "?")) for r, *_ in points})
    hollow = [p for p in points if p[3] is None]
    lower = any(p[4] for p in points)
    handles = []
    if hollow:
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec="grey",
                              label="no mean ASR (not every attack variant)"))  # fmt: skip
    if lower:
        handles.append(Line2D([], [], ls="", marker=">", mfc="none", mec="black",
                              label="time is a lower bound (store reads untimed)"))  # fmt: skip
    fig, (ax,) = figure_grid(1, panel_height_in=2.5, extra_height_in=0.18 * len(handles))
    asrs = [p[3] for p in points if p[3] is not None]
    colours = ScalarMappable(data_norm(asrs), "viridis_r") if asrs else None
    for r, x, y, asr, lower_bound in points:
        face = "none" if asr is None else colours.to_rgba(asr)
        ax.scatter([x], [y], s=24, facecolors=[face], edgecolors="grey" if asr is None else "black",
                   linewidths=0.6, marker=">" if lower_bound else "o", zorder=3)  # fmt: skip
        ax.annotate(r["model"], (x, y), textcoords="offset points", xytext=(4, 3))
    if handles:
        legend_below(fig, handles, ncols=1)
    if colours is not None:
        fig.colorbar(colours, ax=ax, label="mean ASR over attack variants")
    if notes is not None and untimed:
        notes.append(f"Left out (no clean timing or clean L2 mAP): {', '.join(untimed)}.")
    if notes is not None and hollow:
        cells = [f"{r['model']} ({missing_of(len(covered_variants(r, variants)), len(variants))})"
                 for r, *_ in hollow]  # fmt: skip
        notes.append(f"Hollow grey marker, no mean ASR colour: {', '.join(cells)}.")
    if notes is not None:
        notes += [f"Model time per frame of {note}." for note in time_notes]
    ax.set_xscale("log")
    ax.margins(0.15)  # room for the model names inside the axes
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    # minor ticks labelled at 2, 3 and 5 x 10^n only: all eight collide within a decade
    minor = FuncFormatter(lambda x, _: f"{x:g}" if f"{x:g}"[0] in "235" else "")
    ax.xaxis.set_minor_formatter(minor)
    ax.set_xlabel(f"model time per frame (ms, {', '.join(devices)})")
    ax.set_ylabel("clean L2 mAP (x100)")
    ax.grid(which="both")
    return fig
