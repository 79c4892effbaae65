"""The training seed's share of a difference: the report's "Seed-to-seed spread" section.

Two results with the same ``model_sha256`` (the same model config, data and schedule) and
different ``training_seed`` are one model trained twice. How far its ASRs move between the two
is a difference no model comparison can be trusted to exceed by chance alone: per variant the
section gives each seed's ASR with its run-level interval and their paired difference, per rank
group (attack family) the difference of the mean ASRs with its paired interval, and then which
model-vs-model differences of the report's paired comparison exceed that spread.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from pcdet_atlas.evaluation.results import queries
from pcdet_atlas.evaluation.results.build import paired_from_results
from pcdet_atlas.evaluation.results.schema import ResultsError
from pcdet_atlas.evaluation.results.tables import (
    _render,
    format_interval,
    ordered_variants,
    variant_label,
)

__all__ = ["one_per_model_config", "seed_groups", "seed_spread", "seed_spread_text"]


def _label(results: Mapping) -> str:
    return f"{results['model']} (seed {results['training_seed']})"


def seed_groups(results_list: Sequence[Mapping]) -> tuple[list[list[Mapping]], list[str]]:
    """The results that are one model trained with different seeds: groups of at least two with
    the same ``model_sha256`` and different known ``training_seed`` (in the report's order), and
    a note for each set of results that share a model config but cannot be told apart by seed
    (a seed unknown, or the same seed twice)."""
    by_config: dict[str, list[Mapping]] = {}
    for r in results_list:
        if r.get("model_sha256") is not None:
            by_config.setdefault(r["model_sha256"], []).append(r)
    groups, notes = [], []
    for members in by_config.values():
        if len(members) < 2:
            continue
        unknown = [r["model"] for r in members if r.get("training_seed") is None]
        seeds = [r["training_seed"] for r in members if r.get("training_seed") is not None]
        names = ", ".join(r["model"] for r in members)
        if unknown:
            notes.append(f"{names} share a model config, but the training seed of "
                         f"{', '.join(unknown)} is not recorded: left out here.")  # fmt: skip
        if len(set(seeds)) < len(seeds):
            notes.append(f"{names} share a model config and a training seed: evaluations of "
                         "the same training, left out here.")  # fmt: skip
        if not unknown and len(set(seeds)) == len(seeds):
            groups.append(members)
    return groups, notes


def one_per_model_config(results_list: Sequence[Mapping]) -> tuple[list[Mapping], str | None]:
    """The results with one per model config: of a model trained with several seeds
    (:func:`seed_groups`) only the first in the report's order stays, so that a retraining does
    not count as another detector (in the robustness ranks and their fit). Returns the results
    kept and a note naming those left out (None when none is)."""
    groups, _ = seed_groups(results_list)
    left_out = {id(r): group[0] for group in groups for r in group[1:]}
    if not left_out:
        return list(results_list), None
    kept = [r for r in results_list if id(r) not in left_out]
    names = "; ".join(
        f"{r['model']} (a retraining of {first['model']} with seed {r['training_seed']})"
        for r in results_list
        if (first := left_out.get(id(r))) is not None
    )
    return kept, f"One result per model config: left out {names} (see the seed-to-seed spread)."


def _paired(results_list: Sequence[Mapping], variants: Sequence[str]) -> dict | None:
    try:
        return paired_from_results(results_list, variants)
    except ResultsError:
        return None  # no per-run counts (before schema 5) or other runs: no interval to give


def _diff_cell(out: dict | None, a: str, b: str, digits: int = 2) -> str:
    """``b - a`` with its paired interval from a :func:`paired_from_results` output."""
    if out is None:
        return "-"
    text = f"{out['difference'][b][a]:+.{digits}f}"
    if out["ci"] is not None:
        lo, hi = out["ci"][b][a]
        text += f" [{lo:+.{digits}f}, {hi:+.{digits}f}]"
    return text


def _asr_cell(entry: Mapping) -> str:
    return f"{entry['asr']:.2f}" + format_interval(entry["asr_ci"])


def seed_spread(group: Sequence[Mapping]) -> dict:
    """Per rank group, the largest absolute difference of mean ASR between the first result of
    ``group`` and each other (the seed-to-seed spread), over the ranked variants all of them
    have with an ASR: ``{rank_group: {'spread': float, 'variants': [...], 'pairs': [(a, b,
    paired output | None, mean difference b - a)]}}``."""
    variants, _ = queries.ranked_variants(group)
    out: dict = {}
    for name in variants:
        rank_group = group[0]["variants"][name]["rank_group"]
        out.setdefault(rank_group, {"variants": [], "pairs": [], "spread": 0.0})
        out[rank_group]["variants"].append(name)
    for item in out.values():
        names = item["variants"]
        for other in group[1:]:
            pair = [group[0], other]
            paired = _paired(pair, names)
            diff = queries.mean_asr(other, names) - queries.mean_asr(group[0], names)
            item["pairs"].append((group[0]["model"], other["model"], paired, diff))
            item["spread"] = max(item["spread"], abs(diff))
    return out


def _group_text(group: Sequence[Mapping]) -> list[str]:
    first = group[0]
    variants = ordered_variants(
        {n for n, v in first["variants"].items() if v["rank_group"] is not None}
    )
    variants = [n for n in variants
                if all(n in r["variants"] and r["variants"][n]["asr"] is not None
                       for r in group)]  # fmt: skip
    header = ["Variant", *(f"{_label(r)} ASR" for r in group)]
    header += [f"{_label(r)} - seed {first['training_seed']}" for r in group[1:]]
    rows = []
    for name in variants:
        row = [variant_label(name), *(_asr_cell(r["variants"][name]) for r in group)]
        for other in group[1:]:
            paired = _paired([first, other], [name])
            row.append(_diff_cell(paired, first["model"], other["model"]))
        rows.append(row)
    parts = [
        f"**{', '.join(_label(r) for r in group)}**: one model config "
        f"(`{first['config']}`; model digest `{first['model_sha256'][:12]}`) trained with "
        f"{len(group)} seeds.",
        _render("markdown", None, header, rows),
    ]
    spread = seed_spread(group)
    header = ["Rank group", "Variants", *(f"{_label(r)} mean ASR" for r in group)]
    header += [f"{_label(r)} - seed {first['training_seed']}" for r in group[1:]]
    rows = []
    for rank_group, item in spread.items():
        row = [rank_group, str(len(item["variants"]))]
        row += [f"{queries.mean_asr(r, item['variants']):.2f}" for r in group]
        for a, b, paired, diff in item["pairs"]:
            row.append(f"{diff:+.2f}" if paired is None else _diff_cell(paired, a, b))
        rows.append(row)
    parts.append(_render("markdown", None, header, rows))
    return parts


def _exceeding_text(results_list: Sequence[Mapping], groups: Sequence[Sequence[Mapping]]) -> str:
    """Which of the report's paired model differences exceed the seed spread, per rank group."""
    variants, _ = queries.ranked_variants(results_list)
    by_group: dict[str, list[str]] = {}
    for name in variants:
        by_group.setdefault(results_list[0]["variants"][name]["rank_group"], []).append(name)
    same_training = [{r["model"] for r in group} for group in groups]
    lines = []
    for rank_group, names in by_group.items():
        spread = max(
            abs(queries.mean_asr(other, names) - queries.mean_asr(group[0], names))
            for group in groups
            for other in group[1:]
        )
        out = _paired(results_list, names)
        if out is None:
            lines.append(f"- {rank_group}: seed spread {spread:.2f}; the paired comparison "
                         "cannot be computed (see above).")  # fmt: skip
            continue
        models = out["models"]
        beyond, above, within = [], [], []
        for i, first in enumerate(models):
            for second in models[i + 1 :]:
                if any({first, second} <= members for members in same_training):
                    continue  # the seed pair itself: the spread, not a model difference
                # named so that the difference is positive: a - b > 0
                a, b = (first, second) if out["difference"][first][second] >= 0 else (second, first)
                text = f"{a} - {b} {_diff_cell(out, b, a)}"
                if out["difference"][a][b] <= spread:
                    within.append(text)
                elif out["ci"] is not None and out["ci"][a][b][0] > spread:
                    beyond.append(text)
                else:
                    above.append(text)
        lines.append(
            f"- **{rank_group}** (seed spread {spread:.2f}: the largest |difference of mean ASR| "
            "between seeds over these variants). Interval beyond the spread: "
            f"{'; '.join(beyond) or 'none'}. Above the spread, its interval not: "
            f"{'; '.join(above) or 'none'}. Within the spread: {'; '.join(within) or 'none'}."
        )
    return "\n".join(lines)


def seed_spread_text(results_list: Sequence[Mapping]) -> str | None:
    """The report's "Seed-to-seed spread" section (Markdown), or None when no two results are
    one model config trained with different seeds."""
    groups, notes = seed_groups(results_list)
    if not groups:
        return None if not notes else "\n\n".join(["No seed pair to measure.", *notes])
    parts = [
        "Results of one model config (the same `model_sha256`: model, data and schedule) trained "
        "with different seeds. Per variant each seed's ASR with its run-level 95% interval and "
        "their difference with its paired 95% interval over the sequences; per rank group the "
        "difference of the mean ASRs. With two seeds the difference is one draw of the "
        "seed-to-seed variation, not its distribution."
    ]
    for group in groups:
        parts += _group_text(group)
    parts += [
        "Model differences of the paired comparison (over the ranked variants every model has) "
        "against the seed spread of their rank group; pairs of one model's seeds are left out:",
        _exceeding_text(results_list, groups),
        *notes,
    ]
    return "\n\n".join(parts)
