"""The one style of the report's figures: 8-pt text, a figure one column (3.5 in) or two columns
(7.16 in) wide, a colour-blind-safe palette (Okabe and Ito's hues: a hue per attack series, a
shade per difficulty level), and the files a figure is written as: a PNG and a PDF beside it,
their bytes a function of the figure alone (no creation date, no software version).

A figure is built and saved inside :func:`paper_style` (:func:`render` does both): matplotlib's
defaults with this module's rcParams on top, whatever the caller's rcParams hold, which are
restored on exit. Figures are drawn headless (``Figure`` on an Agg canvas, no pyplot state).

A variant's series and level come from its label (:func:`variant_series`): ``Rel-Fixed Easy`` is
level ``Easy`` of series ``Rel-Fixed``, ``Removal 30`` level ``30`` of ``Removal``; a variant
named outside the paper's set splits at its last underscore. The series of a figure take the
palette's hues in the paper's variant order (Rel-Fixed, Global, Removal, then others by name),
their levels light to dark in the same order (harder = darker), and a line style and marker each
so that print in grey still tells them apart.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcdet_atlas.evaluation.results.tables import ordered_variants, variant_label
from pcdet_atlas.utils.files import write_atomic

__all__ = [
    "DOUBLE_COLUMN_IN",
    "DPI",
    "FONT_PT",
    "MASKED_COLOUR",
    "MASKED_HATCH",
    "OKABE_ITO",
    "PDF_METADATA",
    "PNG_METADATA",
    "PlottingUnavailable",
    "RC_PARAMS",
    "SINGLE_COLUMN_IN",
    "VariantStyle",
    "data_norm",
    "figure_grid",
    "label_panels",
    "legend_below",
    "legend_columns",
    "paper_style",
    "render",
    "save_figure",
    "variant_series",
    "variant_styles",
]

#: Text size of every label, title, tick and legend, in points.
FONT_PT = 8
#: Widths of a one-column and a two-column figure (IEEE / ACM two-column layouts), in inches.
SINGLE_COLUMN_IN = 3.5
DOUBLE_COLUMN_IN = 7.16
#: Resolution of the PNG (the PDF is vector).
DPI = 200
#: Okabe and Ito's colour-blind-safe hues (yellow left out: too light on white), in the order
#: series take them.
OKABE_ITO = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000")
#: A heatmap cell without data (not a zero): light grey under a hatch.
MASKED_COLOUR = "0.82"
MASKED_HATCH = "////"
#: Line styles and markers of the series, in order.
SERIES_LINES = ("-", "--", "-.", ":")
SERIES_MARKERS = ("o", "s", "^", "D")

RC_PARAMS = {
    "font.size": FONT_PT,
    "axes.titlesize": FONT_PT,
    "axes.labelsize": FONT_PT,
    "xtick.labelsize": FONT_PT,
    "ytick.labelsize": FONT_PT,
    "legend.fontsize": FONT_PT,
    "legend.title_fontsize": FONT_PT,
    "figure.titlesize": FONT_PT,
    "figure.labelsize": FONT_PT,
    "axes.linewidth": 0.6,
    "lines.linewidth": 1.0,
    "lines.markersize": 3.0,
    "xtick.major.width": 0.6,
    "ytick.major.width": 0.6,
    "xtick.minor.width": 0.4,
    "ytick.minor.width": 0.4,
    "grid.linewidth": 0.4,
    "grid.alpha": 0.4,
    "hatch.linewidth": 0.5,
    "legend.frameon": False,
    "figure.dpi": DPI,
    "savefig.dpi": DPI,
    "pdf.fonttype": 42,  # TrueType in the PDF: venues refuse Type 3 fonts
    "ps.fonttype": 42,
    "svg.hashsalt": "pcdet_atlas",
}
#: Metadata written into the files: none that changes between runs or matplotlib versions.
PNG_METADATA = {"Software": None}
PDF_METADATA = {"Creator": None, "Producer": None, "CreationDate": None}


class PlottingUnavailable(RuntimeError):
    """The figures need matplotlib, an optional dependency (the ``plots`` extra)."""


@contextmanager
def paper_style() -> Iterator[None]:
    """matplotlib's defaults with :data:`RC_PARAMS` (and the Okabe-Ito colour cycle) on top while
    inside; the caller's rcParams come back on exit.

    Raises:
        PlottingUnavailable: matplotlib is not installed (it is the ``plots`` extra).
    """
    try:
        import matplotlib.style
        from cycler import cycler
    except ModuleNotFoundError as err:
        raise PlottingUnavailable(
            f"matplotlib is not installed ({err}); install the plots extra: pip install -e .[plots]"
        ) from err
    rc = {**RC_PARAMS, "axes.prop_cycle": cycler(color=list(OKABE_ITO))}
    with matplotlib.style.context(["default", rc]):
        yield


def figure_grid(
    num_panels: int,
    *,
    panel_height_in: float = 1.6,
    max_cols: int = 4,
    width_in: float | None = None,
    extra_height_in: float = 0.0,
    legend_entries: int = 0,
    sharey: bool = False,
):
    """A ``Figure`` (constrained layout, on an Agg canvas) with ``num_panels`` axes in rows of at
    most ``max_cols``, and those axes. One or two columns of panels make a one-column figure,
    more a two-column one (``width_in`` overrides); ``legend_entries``: room under the panels
    for a :func:`legend_below` of that many entries, ``extra_height_in`` for anything else;
    ``sharey``: one y-axis for every panel, its tick labels on the first column only."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = max(1, min(max_cols, num_panels))
    rows = -(-num_panels // cols)
    if width_in is None:
        width_in = SINGLE_COLUMN_IN if cols <= 2 else DOUBLE_COLUMN_IN
    if legend_entries:
        rows_of_legend = -(-legend_entries // legend_columns(width_in, legend_entries))
        extra_height_in += 0.12 + 0.16 * rows_of_legend
    fig = Figure(figsize=(width_in, panel_height_in * rows + extra_height_in),
                 layout="constrained")  # fmt: skip
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False, sharey=sharey).ravel()
    for ax in axes[num_panels:]:
        ax.set_visible(False)
    return fig, axes[:num_panels]


def label_panels(axes, xlabel: str, ylabel: str) -> None:
    """Panels of a :func:`figure_grid` labelled once: ``ylabel`` on the first column, ``xlabel``
    under each panel with no panel below it."""
    for ax in axes:
        spec = ax.get_subplotspec()
        below = spec.rowspan.stop * spec.get_gridspec().ncols + spec.colspan.start
        if spec.is_first_col():
            ax.set_ylabel(ylabel)
        if below >= len(axes):
            ax.set_xlabel(xlabel)


def legend_columns(width_in: float, num_entries: int) -> int:
    """Columns of a legend of ``num_entries`` under a figure ``width_in`` wide: about 1.75 in
    each."""
    return max(1, min(num_entries, int(width_in // 1.75)))


def legend_below(fig, handles: list, ncols: int | None = None):
    """The figure's one legend, under its panels (outside every axes: constrained layout makes
    room), of ``handles`` (artists with labels) in ``ncols`` columns (default:
    :func:`legend_columns`)."""
    if ncols is None:
        ncols = legend_columns(fig.get_figwidth(), len(handles))
    return fig.legend(handles=handles, loc="outside lower center", ncols=ncols,
                      handlelength=2.2, columnspacing=1.2)  # fmt: skip


def data_norm(values, pad: float = 0.05):
    """A colour ``Normalize`` from the smallest to the largest of the finite ``values`` (masked
    ones left out), so a colour bar spans the data; ``pad`` either side when they are all one
    value. Raises when there is no finite value."""
    from matplotlib.colors import Normalize

    values = np.ma.asarray(values, dtype=float).compressed()
    values = values[np.isfinite(values)]
    if values.size == 0:
        raise ValueError("data_norm: no finite value for a colour bar to span")
    lo, hi = float(values.min()), float(values.max())
    return Normalize(lo - pad, hi + pad) if hi - lo < 1e-12 else Normalize(lo, hi)


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG at ``path`` and as a PDF beside it (``path`` with ``.pdf``), folder
    made, with :data:`PNG_METADATA` / :data:`PDF_METADATA`, each file whole
    (:func:`~pcdet_atlas.utils.files.write_atomic`: a symlink at its name is replaced, not
    written through); -> ``path`` (the PNG)."""
    path = Path(path)
    if path.suffix != ".png":
        raise ValueError(f"{path}: a figure is written as <name>.png (and <name>.pdf beside it)")
    write_atomic(path, lambda f: fig.savefig(f, format="png", metadata=PNG_METADATA))
    write_atomic(
        path.with_suffix(".pdf"), lambda f: fig.savefig(f, format="pdf", metadata=PDF_METADATA)
    )
    return path


def render(build: Callable[[], object], path: Path) -> Path | str:
    """``build()`` (a ``Figure``, or a string saying why there is none) in :func:`paper_style`,
    saved by :func:`save_figure`; -> the PNG's path, or that string (also when matplotlib is not
    installed: the report then names every figure as not drawn, with the install command)."""
    try:
        with paper_style():
            fig = build()
            if isinstance(fig, str):
                return fig
            return save_figure(fig, path)
    except PlottingUnavailable as err:
        return str(err)


def variant_series(name: str) -> tuple[str, str]:
    """``(series, level)`` of a variant: its label's leading words and last word (``Rel-Fixed
    Easy`` -> ``('Rel-Fixed', 'Easy')``); a name without a paper label splits at its last
    underscore; a name with neither is a series of one level, ``''``."""
    label = variant_label(name)
    for sep in (" ", "_"):
        if sep in label:
            series, level = label.rsplit(sep, 1)
            return series, level
    return label, ""


@dataclass(frozen=True)
class VariantStyle:
    """How one variant is drawn: its colour (its series' hue at its level's shade), line style
    and marker (its series')."""

    colour: tuple[float, float, float]
    linestyle: str
    marker: str

    def line(self) -> dict:
        """Keyword arguments of ``Axes.plot`` / ``Axes.stairs``."""
        return {"color": self.colour, "linestyle": self.linestyle}


def _shade(hue: str, t: float) -> tuple[float, float, float]:
    """``hue`` mixed with white (``t`` < 0) or black (``t`` > 0) by ``|t|``."""
    from matplotlib.colors import to_rgb

    rgb = np.asarray(to_rgb(hue))
    mixed = rgb + (-t) * (1.0 - rgb) if t < 0 else rgb * (1.0 - t)
    return tuple(float(c) for c in mixed)


def variant_styles(names: Iterable[str]) -> dict[str, VariantStyle]:
    """A :class:`VariantStyle` for each variant of ``names``: a hue per series (in the paper's
    order), a shade per level within its series (lightest first), a line style and marker per
    series. Give every variant the report holds, so a variant looks the same in every figure."""
    ordered = ordered_variants(names)
    series: dict[str, list[str]] = {}
    for name in ordered:
        series.setdefault(variant_series(name)[0], []).append(name)
    out = {}
    for i, members in enumerate(series.values()):
        hue = OKABE_ITO[i % len(OKABE_ITO)]
        shades = np.linspace(-0.5, 0.35, len(members)) if len(members) > 1 else [0.0]
        for name, t in zip(members, shades):
            out[name] = VariantStyle(_shade(hue, float(t)), SERIES_LINES[i % len(SERIES_LINES)],
                                     SERIES_MARKERS[i % len(SERIES_MARKERS)])  # fmt: skip
    return out
