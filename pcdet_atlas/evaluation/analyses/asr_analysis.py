"""The ASR analysis: the attack success rate of a variant with its run-level interval and
per-run counts (:mod:`.asr`), its keys of a ``results.json`` entry, the paper's per-family
tables (Tables 3 and 4) and the paired comparison of the models' mean ASR."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from pcdet_atlas.evaluation.analyses.asr import asr_from_matches
from pcdet_atlas.evaluation.analyses.matching import ASR_IOU_THRESHOLD
from pcdet_atlas.evaluation.analyses.registry import (
    Analysis,
    ReportSection,
    VariantData,
    register_analysis,
)
from pcdet_atlas.evaluation.analyses.schema_parts import (
    COUNT,
    FRAC,
    INTERVAL,
    NAME,
    RUN,
    ResultsError,
    check_rate,
    fail,
    nullable,
)
from pcdet_atlas.evaluation.results.build import paired_from_results
from pcdet_atlas.evaluation.results.queries import families_present, ranked_variants
from pcdet_atlas.evaluation.results.tables import _render, format_comparison_table, variant_label

__all__ = ["AsrAnalysis", "paired_table"]

#: The report's title of a family's table (any other family: "Family <name>").
FAMILY_TITLES = {
    "injection": "Point injection (paper Table 3)",
    "removal": "Point removal (paper Table 4)",
}


def _runs(v: Mapping, path: str) -> None:
    """The per-run counts add up to the variant's, one entry per run, sorted."""
    runs = v["runs"]
    keys = [(r["sequence"], r["run_id"]) for r in runs]
    if keys != sorted(set(keys)):
        fail(path, "runs must be unique and sorted by (sequence, run_id)")
    if len(runs) != v["num_runs"]:
        fail(path, f"{len(runs)} runs != num_runs {v['num_runs']}")
    for i, r in enumerate(runs):
        for key in ("num_success", "num_success_lenient"):
            if r[key] > r["num_targets"]:
                fail(f"{path}[{i}]['{key}']", f"{r[key]} > num_targets {r['num_targets']}")
    for key in ("num_targets", "num_success", "num_success_lenient"):
        total = sum(r[key] for r in runs)
        if total != v[key]:
            fail(path, f"the runs' {key} add up to {total}, not {v[key]}")


def family_tables(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    """Per attack family, L2 mAP and ASR of every model per variant (paper Tables 3 and 4)."""
    return [
        (
            FAMILY_TITLES.get(family, f"Family {family}"),
            format_comparison_table(results_list, fmt, family=family, missing="show"),
        )
        for family in families_present(results_list)
    ]


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
    variants, _ = ranked_variants(results_list)
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


def paired_section(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    """The paired comparison (Markdown only)."""
    return [("Paired model comparison", _paired_text(results_list))]


@register_analysis
class AsrAnalysis(Analysis):
    """ASR, lenient ASR, their targets and runs (:func:`~.asr.asr_from_matches`)."""

    name = "asr"
    required = True

    def schema(self) -> dict[str, dict]:
        return {
            "asr": nullable(FRAC),
            # [lo, hi] intervals.asr_interval; None with < 2 runs or from before schema 3
            "asr_ci": nullable(INTERVAL),
            "num_runs": nullable(COUNT),
            # per-run counts, sorted by (sequence, run_id); None before schema 5
            "runs": nullable({"type": "array", "items": RUN}),
            "asr_lenient": nullable(FRAC),
            "num_targets": COUNT,
            "num_success": COUNT,
            "num_success_lenient": COUNT,
            "num_spoofed_frames": nullable(COUNT),  # None: a file from before schema 3
            "num_untargeted": nullable(COUNT),
            "iou_threshold": FRAC,
            "score_threshold": nullable(FRAC),
            "target_class": nullable(NAME),
        }

    def compute(self, data: VariantData) -> dict:
        return asr_from_matches(data.matches)

    def empty(self) -> dict:
        return {
            "asr": None, "asr_ci": None, "num_runs": 0, "runs": [], "asr_lenient": None,
            "num_targets": 0, "num_success": 0, "num_success_lenient": 0,
            "num_spoofed_frames": 0, "num_untargeted": 0, "iou_threshold": ASR_IOU_THRESHOLD,
            "score_threshold": None, "target_class": None,
        }  # fmt: skip

    def check(self, v: Mapping, path: str) -> None:
        n = v["num_targets"]
        ci = v["asr_ci"]
        if ci is not None and (v["asr"] is None or ci[0] > ci[1]):
            fail(f"{path}['asr_ci']", f"{ci} is not an interval [lo <= hi] of an ASR {v['asr']}")
        if ci is not None and (v["num_runs"] is None or v["num_runs"] < 2):
            fail(f"{path}['asr_ci']", f"must be null with num_runs {v['num_runs']} (< 2 runs)")
        if v["num_runs"] is not None and v["num_runs"] > n:
            fail(f"{path}['num_runs']", f"{v['num_runs']} runs > num_targets {n}")
        if v["runs"] is not None:
            _runs(v, f"{path}['runs']")
        spoofed, untargeted = v["num_spoofed_frames"], v["num_untargeted"]
        if (spoofed is None) != (untargeted is None) or (
            spoofed is not None and (untargeted > spoofed or n > spoofed)
        ):
            fail(
                f"{path}['num_untargeted']",
                f"{v['num_untargeted']} untargeted and {n} targets of {v['num_spoofed_frames']} "
                "spoofed frames",
            )
        for num_key, rate_key in (("num_success", "asr"), ("num_success_lenient", "asr_lenient")):
            check_rate(v[rate_key], v[num_key], n, f"{path}['{rate_key}']", f"{path}['{num_key}']")

    def sections(self) -> list[ReportSection]:
        return [ReportSection(family_tables, order=20),
                ReportSection(paired_section, order=80, latex=False)]  # fmt: skip
