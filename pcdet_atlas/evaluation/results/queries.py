"""What the report's tables and figures read off several ``results.json`` dicts: a family's
variants, the variants a model covers, mean ASRs, the ranked variants, a model's time per frame
(with its RPN's share); no drawing and no formatting here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.config import cfg_from_yaml_file, repo_relative, resolve_repo_path
from pcdet_atlas.evaluation.results.tables import ordered_variants
from pcdet_atlas.utils.hashing import file_sha256

__all__ = [
    "attack_variants",
    "covered_variants",
    "families_present",
    "family_variants",
    "frame_cost",
    "mean_asr",
    "ms_per_frame",
    "ranked_variants",
    "ranked_variants_note",
    "rpn_results",
]


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
    candidates = [r for r in results_list if r.get("checkpoint") and same(r["config"]) == want[0]]
    for r in candidates:
        if same(r["checkpoint"]) == want[1]:
            return r, ""
    # written in another clone, the same checkpoint has another path: its recorded bytes match
    path = resolve_repo_path(want[1])
    if candidates and path.is_file():
        sha = file_sha256(path)
        for r in candidates:
            if r.get("extra", {}).get("checkpoint_sha256") == sha:
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


def families_present(results_list: Sequence[Mapping]) -> list[str]:
    """The attack families of the models' variants: injection and removal first, then the
    others by name (clean left out)."""
    fams = {v["family"] for r in results_list for v in r["variants"].values()}
    return [f for f in ("injection", "removal") if f in fams] + sorted(
        fams - {"clean", "injection", "removal"}
    )
