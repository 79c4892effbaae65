"""The report's figures follow the paper style (pcdet_atlas/evaluation/results/style.py), checked
on the drawn ``Figure`` objects: 8-pt text, one- or two-column width, one legend outside every
axes, integer ticks on the lifecycle's k, one y-axis where panels are compared, masked heatmap
cells apart from zeros, colour bars spanning the data, the lifecycle intervals as bands; PNG and
PDF with bytes that depend on the figure alone; the caller's matplotlib state left alone."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from matplotlib.collections import PolyCollection
from matplotlib.colors import rgb_to_hsv, to_rgba
from matplotlib.image import AxesImage
from matplotlib.text import Text

from pcdet_atlas.evaluation.analyses.confidence_analysis import confidence_histograms_figure
from pcdet_atlas.evaluation.analyses.lifecycle_analysis import (
    lifecycle_curves_figure,
    lifecycle_heatmaps_figure,
)
from pcdet_atlas.evaluation.analyses.ranks_analysis import rank_correlation_figure
from pcdet_atlas.evaluation.results import queries
from pcdet_atlas.evaluation.results.figures import accuracy_vs_time, accuracy_vs_time_figure
from pcdet_atlas.evaluation.results.report import report_figures, write_report
from pcdet_atlas.evaluation.results.style import (
    DOUBLE_COLUMN_IN,
    FONT_PT,
    MASKED_HATCH,
    SINGLE_COLUMN_IN,
    paper_style,
    save_figure,
    variant_series,
    variant_styles,
)
from pcdet_atlas.evaluation.results.tables import PAPER_VARIANTS

sys.path.insert(0, str(Path(__file__).parent))
import test_report  # noqa: E402  (the report tests' hand-made results)
from test_report import model  # noqa: E402

BUILDERS = {
    "accuracy_vs_time": lambda rs: accuracy_vs_time_figure(rs, []),
    "rank_correlation": lambda rs: rank_correlation_figure(rs, []),
    **{f"lifecycle_{f}": (lambda rs, f=f: lifecycle_curves_figure(rs, f, []))
       for f in ("injection", "removal")},
    **{f"heatmap_{f}": (lambda rs, f=f: lifecycle_heatmaps_figure(rs, f, []))
       for f in ("injection", "removal")},
    **{f"confidence_{f}": (lambda rs, f=f: confidence_histograms_figure(rs, f, []))
       for f in ("injection", "removal")},
}  # fmt: skip
MULTI_PANEL = [name for name in BUILDERS if name.split("_")[0] in ("lifecycle", "heatmap",
                                                                   "confidence")]  # fmt: skip


@pytest.fixture(scope="module")
def models():
    return [
        model("CenterPoint", 0.60, 0.3, 0.8, 40.0),
        model("CP-4f", 0.70, 0.5, 0.6, 60.0, skip=("rem_40",)),  # not evaluated on rem_40
        model("PHiM", 0.65, 0.4, 0.7, 120.0),
        model("PHiM+LOT", 0.64, 0.45, 0.5, 150.0),
    ]


def drawn(name: str, results_list):
    """The figure ``name`` built and drawn (layout done, ticks made) in the paper style."""
    with paper_style():
        fig = BUILDERS[name](results_list)
        assert not isinstance(fig, str), fig
        fig.canvas.draw()
    return fig


def test_the_builders_are_the_report_figures():
    assert {f"{name}.png" for name in BUILDERS} == {f.file for f in report_figures()}


@pytest.mark.parametrize("name", list(BUILDERS))
def test_size_text_and_one_legend_outside_the_data(models, name):
    fig = drawn(name, models)
    assert fig.get_figwidth() in (SINGLE_COLUMN_IN, DOUBLE_COLUMN_IN)
    texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]
    assert len(texts) > 5 and {t.get_fontsize() for t in texts} == {FONT_PT}, name
    assert all(ax.get_legend() is None for ax in fig.axes)  # no legend inside a panel
    (legend,) = fig.legends
    box = legend.get_window_extent()
    assert fig.bbox.contains(box.x0, box.y0) and fig.bbox.contains(box.x1, box.y1)
    for ax in fig.axes:  # the panels and any colour bar, with their ticks and labels
        if ax.get_visible():
            assert not box.overlaps(ax.get_tightbbox()), (name, ax.get_title())


@pytest.mark.parametrize("name", MULTI_PANEL)
def test_compared_panels_share_one_y_axis(models, name):
    fig = drawn(name, models)
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert len(panels) == 4
    assert len({ax.get_ylim() for ax in panels}) == 1
    shared = panels[0].get_shared_y_axes()
    assert all(shared.joined(panels[0], ax) for ax in panels[1:])
    labelled = [ax for ax in panels if ax.get_ylabel()]
    assert labelled == [ax for ax in panels if ax.get_subplotspec().is_first_col()]


@pytest.mark.parametrize("name", ["lifecycle_injection", "heatmap_removal"])
def test_k_ticks_are_integers(name, monkeypatch):
    monkeypatch.setattr(test_report, "WINDOW", 1)  # k = 0..2: autoscale would tick at halves
    fig = drawn(name, [model("CenterPoint", 0.60, 0.3, 0.8, 40.0)])
    (ax,) = [ax for ax in fig.axes if ax.get_title()]
    lo, hi = ax.get_xlim()
    ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
    assert len(ticks) >= 3 and all(float(t).is_integer() for t in ticks), ticks


def test_lifecycle_bands_are_the_run_intervals(models):
    fig = drawn("lifecycle_injection", models)
    ax = next(ax for ax in fig.axes if ax.get_title().startswith("PHiM (W"))
    bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
    names = queries.family_variants(models[2], "injection")
    assert len(bands) == len(names) == 2
    for band, name in zip(bands, names):
        lc = models[2]["variants"][name]["lifecycle"]
        vertices = {tuple(np.round(v, 9)) for v in band.get_paths()[0].vertices}
        for k, ci in zip(lc["k"], lc["asr_ci"]):
            assert (k, round(ci[0], 9)) in vertices and (k, round(ci[1], 9)) in vertices
        assert to_rgba(band.get_facecolor()[0], 1.0) == to_rgba(
            variant_styles(queries.attack_variants(models))[name].colour
        )


def test_heatmap_masks_positions_without_targets_and_its_colour_bar_spans_the_data(models):
    gap = copy.deepcopy(models[:2])
    for name in ("rem_10", "rem_40"):
        lc = gap[0]["variants"][name]["lifecycle"]
        lc["num_targets"][3] = 0
        lc["score_counts"][3] = [0] * len(lc["score_counts"][3])
    fig = drawn("heatmap_removal", gap)
    images = [im for ax in fig.axes for im in ax.get_images()]
    assert len(images) == 2 and all(isinstance(im, AxesImage) for im in images)
    data = images[0].get_array()  # (score bins, k)
    assert data.mask[:, 3].all() and not data.mask[:, [0, 1, 2, 4]].any()
    assert images[1].get_array().mask.sum() == 0  # CP-4f has targets at every k
    assert images[0].cmap.get_bad()[3] == 0.0  # a masked cell shows the panel behind it ...
    ax = images[0].axes
    assert ax.patch.get_hatch() == MASKED_HATCH  # ... grey and hatched, unlike a zero
    assert "no targets at this k" in [t.get_text() for t in fig.legends[0].get_texts()]
    # one colour scale from the smallest to the largest drawn cell of any panel
    cells = np.ma.concatenate([im.get_array().ravel() for im in images]).compressed()
    (bar,) = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert bar.get_ylim() == pytest.approx((cells.min(), cells.max()))
    assert cells.max() < 0.5  # the data do not reach 1: neither does the bar
    assert all(im.norm.vmax == pytest.approx(cells.max()) for im in images)
    unmasked = drawn("heatmap_removal", models[:2])
    assert "no targets at this k" not in [t.get_text() for t in unmasked.legends[0].get_texts()]
    for lc in (gap[0]["variants"][n]["lifecycle"] for n in ("rem_10", "rem_40")):
        lc["num_targets"] = [0] * len(lc["k"])
        lc["score_counts"] = [[0] * len(c) for c in lc["score_counts"]]
    empty = drawn("heatmap_removal", gap[:1])  # no cell with targets: all masked, no colour bar
    assert empty.axes[0].get_images()[0].get_array().mask.all()
    assert [ax for ax in empty.axes if ax.get_label() == "<colorbar>"] == []


def test_accuracy_colour_bar_spans_the_mean_asrs(models):
    fig = drawn("accuracy_vs_time", models)
    variants = queries.attack_variants(models)
    means = [m for r in models if (m := queries.mean_asr(r, variants)) is not None]
    assert len(means) == 3 and max(means) - min(means) < 0.5
    (bar,) = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert bar.get_ylim() == pytest.approx((min(means), max(means)))


def test_variant_styles_hue_per_series_shade_per_level():
    styles = variant_styles(PAPER_VARIANTS[1:])
    assert len({s.colour for s in styles.values()}) == 12
    series = {}
    for name in PAPER_VARIANTS[1:]:
        series.setdefault(variant_series(name)[0], []).append(styles[name])
    assert list(series) == ["Rel-Fixed", "Global", "Removal"]
    assert variant_series("rem_30") == ("Removal", "30") and variant_series("x_y_z") == ("x_y", "z")
    hues = []
    for members in series.values():
        assert len({(s.linestyle, s.marker) for s in members}) == 1
        hsv = rgb_to_hsv(np.array([s.colour for s in members]))
        assert np.allclose(hsv[:, 0], hsv[0, 0], atol=1e-6)  # one hue ...
        assert list(hsv[:, 2] + (1 - hsv[:, 1])) == sorted(
            hsv[:, 2] + (1 - hsv[:, 1]), reverse=True
        )  # ... darker when harder
        hues.append(hsv[0, 0])
    assert len(set(np.round(hues, 3))) == 3
    assert len({m[0].linestyle for m in series.values()}) == 3


def test_files_are_png_and_pdf_with_stable_bytes_and_no_leak(models, tmp_path):
    """The report writes a PDF beside every PNG; the bytes carry no date or version and do not
    depend on the caller's rcParams, which come back as they were."""
    out = write_report(models, tmp_path / "a")
    for name, png in out["figures"].items():
        pdf = png.with_suffix(".pdf")
        assert pdf.read_bytes()[:5] == b"%PDF-" and pdf.stat().st_size > 5000, name
        assert b"CreationDate" not in pdf.read_bytes() and b"Matplotlib" not in pdf.read_bytes()
        assert b"/FontFile2" in pdf.read_bytes()  # TrueType embedded, not Type 3
        assert b"Software" not in png.read_bytes()[:200]
    before = dict(matplotlib.rcParams)
    with matplotlib.rc_context({"lines.linewidth": 5.0, "font.size": 20.0}):
        changed = dict(matplotlib.rcParams)
        again = accuracy_vs_time(models, tmp_path / "b" / "accuracy_vs_time.png")
        assert dict(matplotlib.rcParams) == changed
    assert dict(matplotlib.rcParams) == before
    for suffix in (".png", ".pdf"):
        first = (tmp_path / "a" / "accuracy_vs_time").with_suffix(suffix)
        assert again.with_suffix(suffix).read_bytes() == first.read_bytes(), suffix


def test_a_figure_replaces_planted_symlinks_instead_of_writing_through_them(tmp_path):
    """A received report folder with ``<figure>.png`` / ``.pdf`` linking elsewhere: the figure
    files replace the links, their targets keep their content."""
    from matplotlib.figure import Figure

    out = tmp_path / "report"
    out.mkdir()
    for suffix in (".png", ".pdf"):
        (tmp_path / f"victim{suffix}").write_text("IMPORTANT USER DATA\n")
        (out / f"fig{suffix}").symlink_to(tmp_path / f"victim{suffix}")
    with paper_style():
        fig = Figure()
        fig.add_subplot().plot([0, 1], [1, 0])
        save_figure(fig, out / "fig.png")
    for suffix, magic in ((".png", b"\x89PNG"), (".pdf", b"%PDF-")):
        assert (tmp_path / f"victim{suffix}").read_text() == "IMPORTANT USER DATA\n"
        assert not (out / f"fig{suffix}").is_symlink()
        assert (out / f"fig{suffix}").read_bytes().startswith(magic)
    assert sorted(p.name for p in out.iterdir()) == ["fig.pdf", "fig.png"]


def test_without_matplotlib_the_report_is_written_and_names_the_extra(
    models, tmp_path, monkeypatch
):
    """matplotlib is the ``plots`` extra: without it the report's tables are written and each
    figure says it was not drawn and how to install what draws it."""
    for name in ("matplotlib", "matplotlib.style", "cycler"):
        monkeypatch.setitem(sys.modules, name, None)  # an import of it now fails
    out = write_report(models, tmp_path / "report")
    text = out["report"].read_text()
    assert "## Point injection (paper Table 3)" in text
    assert out["figures"] and all(isinstance(r, str) for r in out["figures"].values())
    assert text.count("Not drawn: matplotlib is not installed") == len(out["figures"])
    assert "pip install -e .[plots]" in text and not list((tmp_path / "report").glob("*.png"))
