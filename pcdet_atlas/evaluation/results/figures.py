"""The paper's figures from ``results.json`` dicts, drawn headless (matplotlib's ``Figure``, no
display and no pyplot state). Each function writes one PNG and returns its path, or returns a
string saying why the figure cannot be drawn from the results it was given (too few models, no
lifecycle or confidence data, no timing). What a figure leaves out of the given results (a model,
a variant, a colour) it appends, with the reason, to ``notes`` when given a list, for the report
to print under the figure."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.config import cfg_from_yaml_file, repo_relative, resolve_repo_path
from pcdet_atlas.evaluation.results.build import ranks_from_results
from pcdet_atlas.evaluation.results.tables import missing_of, ordered_variants, variant_label

__all__ = [
    "accuracy_vs_time",
    "attack_variants",
    "confidence_histograms",
    "covered_variants",
    "frame_cost",
    "lifecycle_curves",
    "lifecycle_heatmaps",
    "mean_asr",
    "ms_per_frame",
    "rank_correlation",
    "ranked_variants",
    "ranked_variants_note",
    "rpn_results",
]

DPI = 120
HIGH_SCORE = 0.7


def _figure(num_panels: int, panel_size=(4.0, 3.0), max_cols: int = 4):
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


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def family_variants(results: Mapping, family: str) -> list[str]:
    return [n for n in ordered_variants(results["variants"])
            if results["variants"][n]["family"] == family]  # fmt: skip


def ms_per_frame(results: Mapping) -> float | None:
    """Model time per frame of the clean variant (``extra.timing_s.model`` of ``tools/test.py``
    over its frames), in ms; None when the file has no clean timing."""
    clean = results["variants"].get("clean")
    if clean is None:
        return None
    model_s = clean.get("extra", {}).get("timing_s", {}).get("model")
    if model_s is None or clean["num_frames"] == 0:
        return None
    return 1000.0 * float(model_s) / clean["num_frames"]


def _store_counts(results: Mapping) -> tuple[int, int]:
    """(batches read from the prediction store, batches in all) of the clean run; (0, 0)
    without store counts."""
    store = (results["variants"].get("clean") or {}).get("extra", {}).get("prediction_store")
    if not store:
        return 0, 0
    return int(store.get("hits", 0)), int(store.get("hits", 0)) + int(store.get("misses", 0))


def rpn_results(results: Mapping, results_list: Sequence[Mapping]) -> tuple[Mapping | None, str]:
    """The entry of ``results_list`` that is the RPN of ``results``' model (the model whose
    config and checkpoint are the ``MODEL.RPN.CFG`` and ``MODEL.RPN.CHECKPOINT`` of the config
    ``results`` names), and ``''``; or None and why there is none."""
    try:
        rpn = cfg_from_yaml_file(resolve_repo_path(results["config"])).get("MODEL", {}).get("RPN")
    except (OSError, ValueError) as err:  # ConfigError is a ValueError
        return None, f"its config cannot be read ({err})"
    if not rpn or "CFG" not in rpn or "CHECKPOINT" not in rpn:
        return None, f"its config {results['config']} names no RPN (MODEL.RPN.CFG, CHECKPOINT)"

    def same(path: str | Path) -> Path:  # one name for a file, however a config wrote it
        return repo_relative(resolve_repo_path(path))

    want = (same(rpn["CFG"]), same(rpn["CHECKPOINT"]))
    for r in results_list:
        if r.get("checkpoint") and (same(r["config"]), same(r["checkpoint"])) == want:
            return r, ""
    return None, f"its RPN ({want[0]} with {want[1]}) is not in the report"


def frame_cost(
    results: Mapping, results_list: Sequence[Mapping] = ()
) -> tuple[float | None, bool, str | None]:
    """A model's time per frame on the clean run in ms, whether it is only a lower bound, and a
    note (None when there is nothing to say). A two-stage model that read its RPN's proposals
    from the prediction store did not spend the RPN's time: that share of the clean batches is
    added back at the RPN's own clean ms/frame when the RPN is in ``results_list``
    (:func:`rpn_results`) and computed every batch of its own clean run; otherwise the time is
    a lower bound and the note says why."""
    own = ms_per_frame(results)
    hits, batches = _store_counts(results)
    if own is None or hits == 0:
        return own, False, None
    rpn, why = rpn_results(results, results_list)
    if rpn is not None and _store_counts(rpn)[0]:
        rpn, why = None, f"its RPN {rpn['model']} read clean batches from the store as well"
    rpn_ms = None if rpn is None else ms_per_frame(rpn)
    if rpn is not None and rpn_ms is None:
        why = f"its RPN {rpn['model']} has no clean timing"
    served = f"{hits} of {batches} clean batches"
    if rpn_ms is None:
        note = (f"{results['model']}: at least {own:.0f} ms; {served} were read from the "
                f"prediction store, untimed: {why}")  # fmt: skip
        return own, True, note
    added = rpn_ms * hits / batches
    note = (f"{results['model']}: {own:.0f} ms of its own + {added:.0f} ms for the proposals of "
            f"{served} read from the prediction store, at {rpn['model']}'s clean "
            f"{rpn_ms:.0f} ms/frame")  # fmt: skip
    return own + added, False, note


def attack_variants(results_list: Sequence[Mapping], family: str | None = None) -> list[str]:
    """The variants of ``family`` (None: of every family but clean) that any of the models has,
    in the paper's order: what a model's mean or pooled value must cover to compare with the
    other models'."""
    names = {n for r in results_list for n, v in r["variants"].items()
             if (v["family"] != "clean" if family is None else v["family"] == family)}  # fmt: skip
    return ordered_variants(names)


def covered_variants(
    results: Mapping, variants: Sequence[str], *, lifecycle: bool = False
) -> list[str]:
    """Those of ``variants`` the model has with an ASR (and, with ``lifecycle``, its data)."""
    entries = [(n, results["variants"].get(n)) for n in variants]
    return [n for n, v in entries if v is not None and v["asr"] is not None
            and (not lifecycle or v["lifecycle"] is not None)]  # fmt: skip


def mean_asr(results: Mapping, variants: Sequence[str]) -> float | None:
    """Mean ASR of a model over ``variants`` (:func:`attack_variants` of the models compared);
    None unless it has every one of them with an ASR: a mean over fewer variants does not
    compare with the other models' and is shown as missing, never in their place."""
    if not variants or len(covered_variants(results, variants)) < len(variants):
        return None
    return float(np.mean([results["variants"][n]["asr"] for n in variants]))


def ranked_variants(results_list: Sequence[Mapping]) -> tuple[list[str], dict[str, str]]:
    """The ranked variants (with a rank group) that every model has with an ASR, and each other
    ranked variant of any model with why it is left out (who lacks it, who has no ASR for it)."""
    names = ordered_variants({n for r in results_list for n, v in r["variants"].items()
                              if v["rank_group"] is not None})  # fmt: skip
    used, dropped = [], {}
    for name in names:
        entries = [(r["model"], r["variants"].get(name)) for r in results_list]
        lacking = [m for m, v in entries if v is None]
        no_asr = [m for m, v in entries if v is not None and v["asr"] is None]
        why = ([f"not evaluated by {', '.join(lacking)}"] if lacking else []) + (
            [f"no ASR from {', '.join(no_asr)}"] if no_asr else [])  # fmt: skip
        if why:
            dropped[name] = "; ".join(why)
        else:
            used.append(name)
    return used, dropped


def ranked_variants_note(variants: Sequence[str], dropped: Mapping[str, str]) -> str:
    """Markdown: the variants the ranks are over and those left out, with the reason."""
    lines = [f"Ranked over {len(variants)} variant(s): {', '.join(variants) or 'none'}."]
    if dropped:
        lines += ["Left out of the ranks:"] + [f"- {n}: {why}" for n, why in dropped.items()]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- Fig. 3
def rank_correlation(
    results_list: Sequence[Mapping], path: Path, notes: list[str] | None = None
) -> Path | str:
    """Removal rank against injection rank per model, with the least-squares line and R²
    (paper Fig. "Robustness Correlation"); over the ranked variants every model has with an
    ASR (``notes``: which variants, and those left out)."""
    variants, dropped = ranked_variants(results_list)
    if notes is not None:
        notes.append(ranked_variants_note(variants, dropped))
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
    fig, (ax,) = _figure(1, (5.0, 4.2))
    ax.scatter(x, y, color="tab:blue", zorder=3)
    for m, xi, yi in zip(models, x, y):
        ax.annotate(m, (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=8)
    fit = ranks["fit"]
    if fit is not None:
        xs = np.linspace(x.min() - 0.3, x.max() + 0.3, 2)
        ax.plot(xs, fit["slope"] * xs + fit["intercept"], "--", color="tab:red",
                label=f"y = {fit['slope']:.3f}x + {fit['intercept']:.3f}, "
                      f"R² = {fit['r2']:.2f}")  # fmt: skip
        ax.legend(fontsize=8)
    ax.set_xlabel(f"{x_group} rank (1 = most robust)")
    ax.set_ylabel(f"{y_group} rank (1 = most robust)")
    ax.set_title(f"Robustness rank correlation ({len(variants)} variants)", fontsize=10)
    ax.grid(alpha=0.3)
    return _save(fig, path)


# ----------------------------------------------------------------------------- Figs. 4, 6
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


def _shade_attack(ax, window: int) -> None:
    ax.axvspan(0.5, window + 0.5, color="tab:red", alpha=0.08, lw=0)
    ax.axvline(window + 0.5, color="tab:red", ls="--", lw=1)


def lifecycle_curves(
    results_list: Sequence[Mapping], family: str, path: Path, notes: list[str] | None = None
) -> Path | str:
    """ASR by lifecycle position k per model (a panel each) and variant (a line each, its band
    the run-level 95% interval where the results have one): k = 1..W spoofed (shaded), the
    dashed line the onset/decay boundary, k > W the clean frames after the run (paper Figs. 4
    and 6)."""
    models = _lifecycle_models(results_list, family, notes)
    if not models:
        return f"no {family} variant with lifecycle data"
    fig, axes = _figure(len(models))
    for ax, (r, names) in zip(axes, models):
        window = r["variants"][names[0]]["lifecycle"]["window"]
        _shade_attack(ax, window)
        for name in names:
            lc = r["variants"][name]["lifecycle"]
            asr = np.array([np.nan if a is None else a for a in lc["asr"]], dtype=float)
            (line,) = ax.plot(lc["k"], asr, marker=".", ms=3, lw=1, label=variant_label(name))
            if lc.get("asr_ci") is not None:  # the run-level 95% interval as a band
                lo, hi = (
                    np.array([np.nan if c is None else c[i] for c in lc["asr_ci"]], dtype=float)
                    for i in (0, 1)
                )
                ax.fill_between(lc["k"], lo, hi, color=line.get_color(), alpha=0.12, lw=0)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("lifecycle position k")
        ax.set_ylabel("ASR")
        ax.set_title(f"{r['model']} (W = {window})", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    return _save(fig, path)


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
    """Per model, the targets' matched scores by lifecycle position (the family's variants
    pooled): each column k is the fraction of that k's targets detected with a score in each
    bin (a column sums to the detected fraction); one colour scale for all panels, up to the
    largest cell. The white line is the mean attacked score of the detected targets; the dashed
    blue line the clean baseline, the mean clean-run score of the same targets at the same
    frames (paper Figs. 7 and 8). A panel pools what it can (``notes``: the variants of the
    family that a model's panel leaves out, and why)."""
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
        panels.append((r, lcs, window, edges, counts, frac))
    vmax = max(float(frac.max()) for *_, frac in panels) or 1.0
    fig, axes = _figure(len(models), (4.2, 3.2))
    image = None
    for ax, (r, lcs, window, edges, counts, frac) in zip(axes, panels):
        ks = np.asarray(lcs[0]["k"])
        image = ax.imshow(frac.T, origin="lower", aspect="auto", cmap="magma", vmin=0, vmax=vmax,
                          extent=(ks[0] - 0.5, ks[-1] + 0.5, edges[0], edges[-1]))  # fmt: skip
        ax.plot(ks, [_mean_from_counts(edges, c) for c in counts], color="white", lw=1.2,
                marker="o", ms=3, label="attacked (mean)")  # fmt: skip
        clean = [lc["clean_score_counts"] for lc in lcs]
        if all(c is not None for c in clean):
            clean_counts = np.sum([np.asarray(c, dtype=float) for c in clean], axis=0)
            ax.plot(ks, [_mean_from_counts(edges, c) for c in clean_counts], color="deepskyblue",
                    ls="--", lw=1.5, marker="s", ms=3, label="clean baseline (mean)")  # fmt: skip
        ax.axvline(window + 0.5, color="cyan", ls=":", lw=1)
        ax.axhline(HIGH_SCORE, color="grey", ls=":", lw=0.8)
        ax.set_xlabel("lifecycle position k")
        ax.set_ylabel("score")
        ax.set_title(f"{r['model']} ({family}, W = {window})", fontsize=10)
        ax.legend(fontsize=6, loc="lower right")
    fig.colorbar(image, ax=list(axes), shrink=0.8, label="fraction of targets")
    return _save(fig, path)


# ----------------------------------------------------------------------------- Figs. 5, 9
def confidence_histograms(results_list: Sequence[Mapping], family: str, path: Path) -> Path | str:
    """Per model, the score distribution of the detected targets per variant (injection: the
    phantoms' scores, paper Fig. 5; removal: the surviving targets' scores with the clean run's
    scores of the same targets dashed, paper Fig. 9), as fractions of the detected targets;
    the dotted line is the 0.7 high-confidence threshold."""
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
    fig, axes = _figure(len(panels))
    for ax, (r, names) in zip(axes, panels):
        clean_total = None
        for name in names:
            c = r["variants"][name]["confidence"]
            h = c["histogram"]
            counts = np.asarray(h["counts"], dtype=float)
            if counts.sum() > 0:
                above = c["fraction_above"]
                label = f"{variant_label(name)} ({100 * above:.0f}% > {c['high_score_threshold']})"
                ax.stairs(counts / counts.sum(), h["bin_edges"], label=label)
            if kind == "removal":
                pc = np.asarray(c["paired_clean_histogram"]["counts"], dtype=float)
                clean_total = pc if clean_total is None else clean_total + pc
                clean_edges = c["paired_clean_histogram"]["bin_edges"]
        if clean_total is not None and clean_total.sum() > 0:
            ax.stairs(clean_total / clean_total.sum(), clean_edges, color="black", ls="--",
                      label="clean run (same targets)")  # fmt: skip
        ax.axvline(HIGH_SCORE, color="grey", ls=":", lw=1)
        ax.set_xlabel("score" if kind == "injection" else "surviving target score")
        ax.set_ylabel("fraction of detected")
        ax.set_title(f"{r['model']} ({family})", fontsize=10)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
        else:
            ax.text(0.5, 0.5, "no target detected", ha="center", transform=ax.transAxes)
        ax.grid(alpha=0.3)
    return _save(fig, path)


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
    fig, (ax,) = _figure(1, (5.5, 4.2))
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
    return _save(fig, path)
