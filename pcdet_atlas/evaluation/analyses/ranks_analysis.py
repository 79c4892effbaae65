"""The ranks analysis: robustness ranks of several models (:mod:`.ranks`; a variant's group is
its attack class's ``RANK_GROUP``, a core key of the entry), the report's ranks section and the
rank correlation figure (paper Fig. 3). It adds no key of its own to a variant entry."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.evaluation.analyses.registry import (
    Analysis,
    ReportFigure,
    ReportSection,
    VariantData,
    register_analysis,
)
from pcdet_atlas.evaluation.results.build import ranks_from_results
from pcdet_atlas.evaluation.results.queries import ranked_variants, ranked_variants_note
from pcdet_atlas.evaluation.results.seeds import one_per_model_config
from pcdet_atlas.evaluation.results.style import OKABE_ITO, figure_grid, legend_below, render
from pcdet_atlas.evaluation.results.tables import format_ranks

__all__ = ["RanksAnalysis", "rank_correlation", "rank_correlation_figure"]


def rank_correlation(
    results_list: Sequence[Mapping], path: Path, notes: list[str] | None = None
) -> Path | str:
    """:func:`rank_correlation_figure` written to ``path`` (PNG, PDF beside)."""
    return render(lambda: rank_correlation_figure(results_list, notes), path)


def rank_correlation_figure(results_list: Sequence[Mapping], notes: list[str] | None = None):
    """Removal rank against injection rank per model, with the least-squares line and R² in the
    legend under the panel (paper Fig. "Robustness Correlation"); over the ranked variants every
    model has with an ASR and one result per model config (``notes``: which variants, and the
    results left out). One column wide."""
    from matplotlib.ticker import MaxNLocator

    results_list, retrained = one_per_model_config(results_list)
    variants, dropped = ranked_variants(results_list)
    if notes is not None:
        notes.append(ranked_variants_note(variants, dropped))
        notes += [retrained] if retrained else []
    groups = {results_list[0]["variants"][n]["rank_group"] for n in variants} if variants else set()
    if len(results_list) < 3 or not {"injection", "removal"} <= groups:
        return (
            "needs at least 3 models sharing injection and removal variants "
            f"({len(results_list)} models, rank groups {sorted(groups)})"
        )
    ranks = ranks_from_results(results_list, variants=variants)
    x_group, y_group = ranks["fit_axes"]
    models = ranks["models"]
    x = np.array([ranks["group_ranks"][x_group][m] for m in models])
    y = np.array([ranks["group_ranks"][y_group][m] for m in models])
    fit = ranks["fit"]
    fig, (ax,) = figure_grid(1, panel_height_in=2.5, legend_entries=int(fit is not None))
    ax.scatter(x, y, s=16, color=OKABE_ITO[0], zorder=3)
    for m, xi, yi in zip(models, x, y):
        ax.annotate(m, (xi, yi), textcoords="offset points", xytext=(4, 3))
    if fit is not None:
        xs = np.linspace(x.min() - 0.3, x.max() + 0.3, 2)
        (line,) = ax.plot(xs, fit["slope"] * xs + fit["intercept"], "--", color=OKABE_ITO[1],
                          label=f"y = {fit['slope']:.3f}x + {fit['intercept']:.3f}, "
                                f"R² = {fit['r2']:.2f}")  # fmt: skip
        legend_below(fig, [line], ncols=1)
    for axis in (ax.xaxis, ax.yaxis):  # ranks are whole numbers (ties average to halves)
        axis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel(f"{x_group} rank (1 = most robust)")
    ax.set_ylabel(f"{y_group} rank (1 = most robust)")
    ax.set_title(f"Robustness ranks over {len(variants)} variants")
    ax.grid(lw=0.3)
    return fig


def _ranks_text(results_list) -> str:
    """The ranks over the ranked variants every model has with an ASR, one result per model
    config, naming the variants and the results left out."""
    results_list, retrained = one_per_model_config(results_list)
    variants, dropped = ranked_variants(results_list)
    note = ranked_variants_note(variants, dropped) + (f"\n\n{retrained}" if retrained else "")
    if len(results_list) < 2 or not variants:
        return f"needs at least 2 models with a common ranked variant\n\n{note}"
    ranks = format_ranks(ranks_from_results(results_list, variants=variants), "markdown")
    return f"{ranks}\n\n{note}"


def _section(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    return [("Robustness ranks", _ranks_text(results_list))]


@register_analysis
class RanksAnalysis(Analysis):
    """Ranks across models; nothing per variant."""

    name = "ranks"
    required = True

    def schema(self) -> dict[str, dict]:
        return {}

    def compute(self, data: VariantData) -> dict:
        return {}

    def sections(self) -> list[ReportSection]:
        return [ReportSection(_section, order=70, latex=False)]

    def figures(self) -> list[ReportFigure]:
        return [ReportFigure("rank_correlation.png", "Robustness rank correlation (paper Fig. 3)",
                             rank_correlation, order=10)]  # fmt: skip
