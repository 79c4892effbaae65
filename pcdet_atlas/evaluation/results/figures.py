"""The report's figures that belong to no single analysis, and the drawing helpers every figure
uses: drawn headless (matplotlib's ``Figure``, no display and no pyplot state). A figure function
writes one PNG and returns its path, or returns a string saying why the figure cannot be drawn
from the results it was given (too few models, no timing). What a figure leaves out of the given
results (a model, a variant, a colour) it appends, with the reason, to ``notes`` when given a
list, for the report to print under the figure. The data a figure shows comes from
:mod:`~pcdet_atlas.evaluation.results.queries`; the analyses' own figures live with them
(:mod:`pcdet_atlas.evaluation.analyses`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from pcdet_atlas.evaluation.results.queries import (
    attack_variants,
    covered_variants,
    frame_cost,
    mean_asr,
)
from pcdet_atlas.evaluation.results.tables import missing_of

__all__ = ["DPI", "HIGH_SCORE", "accuracy_vs_time", "figure_grid", "save_png"]

DPI = 120
HIGH_SCORE = 0.7


def figure_grid(num_panels: int, panel_size=(4.0, 3.0), max_cols: int = 4):
    """A ``Figure`` with ``num_panels`` axes in rows of at most ``max_cols``, and those axes."""
    from matplotlib.figure import Figure

    cols = max(1, min(max_cols, num_panels))
    rows = -(-num_panels // cols)
    fig = Figure(
        figsize=(panel_size[0] * cols, panel_size[1] * rows), dpi=DPI, layout="constrained"
    )
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[num_panels:]:
        ax.set_visible(False)
    return fig, axes[:num_panels]


def save_png(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG at ``path`` (its folder made); -> ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


# ----------------------------------------------------------------------------- accuracy/time
def accuracy_vs_time(
    results_list: Sequence[Mapping], path: Path, notes: list[str] | None = None
) -> Path | str:
    """Clean L2 mAP against measured model ms/frame per model (:func:`frame_cost`: a two-stage
    model's proposals read from the prediction store at its RPN's time; a right-pointing marker
    where that time cannot be added and the value is a lower bound), the marker coloured by the
    mean ASR over the attack variants of all the models (:func:`mean_asr`); a model without
    every one of them has a hollow grey marker. ``notes``: the models left out (no clean timing
    or mAP), those drawn hollow, and how each store-served model's time was counted."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
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
    fig, (ax,) = figure_grid(1, (5.5, 4.2))
    colours = ScalarMappable(Normalize(0.0, 1.0), "viridis_r")
    hollow = [p for p in points if p[3] is None]
    for r, x, y, asr, lower_bound in points:
        face = "none" if asr is None else colours.to_rgba(asr)
        ax.scatter([x], [y], s=60, facecolors=[face], edgecolors="grey" if asr is None else "black",
                   marker=">" if lower_bound else "o", zorder=3)  # fmt: skip
        ax.annotate(r["model"], (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
    if hollow:
        ax.scatter([], [], s=60, facecolors="none", edgecolors="grey",
                   label="no mean ASR (not every attack variant)")  # fmt: skip
    if any(p[4] for p in points):
        ax.scatter([], [], s=60, marker=">", facecolors="none", edgecolors="black",
                   label="time is a lower bound (store reads untimed)")  # fmt: skip
    if hollow or any(p[4] for p in points):
        ax.legend(fontsize=7, loc="lower right")
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
    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    # minor ticks labelled at 2, 3 and 5 x 10^n only: all eight collide within a decade
    minor = FuncFormatter(lambda x, _: f"{x:g}" if f"{x:g}"[0] in "235" else "")
    ax.xaxis.set_minor_formatter(minor)
    ax.set_xlabel(f"model time per frame (ms, {', '.join(devices)})")
    ax.set_ylabel("clean L2 mAP (x100)")
    ax.set_title("Accuracy vs time", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    return save_png(fig, path)
