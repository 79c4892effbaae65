"""The attributable ASR: the success rate over the targets whose outcome the clean run would not
have produced anyway.

The paper's ASR judges each attacked frame alone, so two outcomes count as successes that the
attack did not cause: a **removal** target the clean model misses as well (nothing was left to
remove), and a **phantom** placed where the clean model already detects a box of the target's
class at IoU >= the threshold (a phantom in the ego lane may overlap a real vehicle, whose
detection then matches it). A target is *confounded* when the clean run's predictions of the
same frame already satisfy the success rule (:func:`~.matching.clean_matched_scores`: the same
class, score and IoU rules). The attributable ASR leaves the confounded targets out, with its
interval over their runs (:func:`~pcdet_atlas.evaluation.intervals.asr_interval`), and
``num_confounded`` / ``num_confounded_success`` say how many there were and how many of them
the ASR counted as successes (docs/evaluation.md "Attributable ASR").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from pcdet_atlas.evaluation.analyses.asr import CI_LEVEL, run_counts
from pcdet_atlas.evaluation.analyses.matching import TargetMatches, clean_matched_scores
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
    check_rate,
    closed,
    fail,
    nullable,
)
from pcdet_atlas.evaluation.analyses.scores import rate
from pcdet_atlas.evaluation.intervals import asr_interval
from pcdet_atlas.evaluation.results.queries import families_present, family_variants
from pcdet_atlas.evaluation.results.tables import (
    MISSING,
    _render,
    format_interval,
    ordered_variants,
    variant_label,
)

__all__ = ["AttributableAnalysis", "attributable_asr", "confounded_targets"]

ATTRIBUTABLE = closed(
    {
        "asr": nullable(FRAC),
        "asr_ci": nullable(INTERVAL),
        "num_runs": COUNT,
        "num_targets": COUNT,
        "num_success": COUNT,
        "num_confounded": COUNT,
        "num_confounded_success": COUNT,
    }
)


def confounded_targets(
    matches: TargetMatches, clean_det_annos: Sequence[Mapping], *, iou_fn=None
) -> np.ndarray:
    """(T,) bool over the attacked targets of ``matches``: the clean run's predictions of the
    same frame already give the attack's success (injection: the phantom box is detected;
    removal: the target is missed)."""
    attacked = matches.attacked()
    detected_clean = np.isfinite(clean_matched_scores(attacked, clean_det_annos, iou_fn=iou_fn))
    return detected_clean if matches.success_if_detected else ~detected_clean


def attributable_asr(
    matches: TargetMatches, clean_det_annos: Sequence[Mapping], *, iou_fn=None
) -> dict:
    """The ASR over the attacked targets that are not confounded (:func:`confounded_targets`).

    Returns ``{'asr', 'asr_ci', 'num_runs', 'num_targets', 'num_success', 'num_confounded',
    'num_confounded_success'}``: ``asr`` None and ``asr_ci`` None without such targets,
    ``asr_ci`` also None with fewer than two runs.
    """
    attacked = matches.attacked()
    confounded = confounded_targets(matches, clean_det_annos, iou_fn=iou_fn)
    kept = attacked.select(~confounded)
    runs = run_counts(kept)
    ci = asr_interval(runs, level=CI_LEVEL)
    n_ok = int(kept.success.sum())
    return {
        "asr": rate(n_ok, len(kept)),
        "asr_ci": None if ci is None else list(ci),
        "num_runs": len(runs),
        "num_targets": len(kept),
        "num_success": n_ok,
        "num_confounded": int(confounded.sum()),
        "num_confounded_success": int(attacked.success[confounded].sum()),
    }


def _cell(v: Mapping | None) -> str:
    if v is None:
        return MISSING
    a = v.get("attributable")
    if a is None:
        return "-"
    if a["asr"] is None:
        return f"- ({a['num_confounded']} confounded)"
    return f"{a['asr']:.2f}{format_interval(a['asr_ci'])}; {a['num_confounded']}"


def attributable_tables(results_list: Sequence[Mapping], fmt: str) -> list[tuple[str, str]]:
    """Per attack family, each model's attributable ASR per variant with its interval and the
    number of confounded targets left out; none when no result has the analysis."""
    if not any(v.get("attributable") for r in results_list for v in r["variants"].values()):
        return []
    out = []
    for family in families_present(results_list):
        names = ordered_variants({n for r in results_list for n in family_variants(r, family)})
        header = ["Model", *(variant_label(n) for n in names)]
        rows = [[r["model"], *(_cell(r["variants"].get(n)) for n in names)] for r in results_list]
        table = _render(fmt, None, header, rows)
        if fmt == "markdown":
            table += (
                "\n\nCell: the ASR over the targets whose outcome the clean run of the same frame "
                "would not already give, its 95% interval; the number of such confounded "
                "targets left out (injection: the clean model detects a box on the phantom's "
                "place; removal: it misses the target too). `-`: no clean run known; "
                f"{MISSING}: the variant was not evaluated."
            )
        out.append((f"Attributable ASR, {family}", table))
    return out


@register_analysis
class AttributableAnalysis(Analysis):
    """The attributable ASR (:func:`attributable_asr`); None without the clean predictions."""

    name = "attributable"

    def schema(self) -> dict[str, dict]:
        return {"attributable": nullable(ATTRIBUTABLE)}

    def compute(self, data: VariantData) -> dict:
        if data.clean_det_annos is None or not len(data.matches.attacked()):
            return {"attributable": None}
        return {
            "attributable": attributable_asr(data.matches, data.clean_det_annos, iou_fn=data.iou_fn)
        }

    def check(self, entry: Mapping, path: str) -> None:
        a = entry.get("attributable")
        if a is None:
            return
        p = f"{path}['attributable']"
        n_ok, n = a["num_success"], a["num_targets"]
        check_rate(a["asr"], n_ok, n, f"{p}['asr']", f"{p}['num_success']")
        if a["num_targets"] + a["num_confounded"] != entry["num_targets"]:
            fail(p, f"{a['num_targets']} targets + {a['num_confounded']} confounded != "
                    f"num_targets {entry['num_targets']}")  # fmt: skip
        if a["num_confounded_success"] > a["num_confounded"]:
            fail(f"{p}['num_confounded_success']", f"> num_confounded {a['num_confounded']}")
        if a["num_success"] + a["num_confounded_success"] != entry["num_success"]:
            fail(p, f"{a['num_success']} + {a['num_confounded_success']} successes != "
                    f"num_success {entry['num_success']}")  # fmt: skip
        if a["asr_ci"] is not None and (a["num_runs"] < 2 or a["asr_ci"][0] > a["asr_ci"][1]):
            fail(f"{p}['asr_ci']", f"{a['asr_ci']} with {a['num_runs']} runs")

    def sections(self) -> list[ReportSection]:
        return [ReportSection(attributable_tables, order=25)]
