"""Attack success rate of one variant from its :class:`~.matching.TargetMatches`, counted per
spoof run (the unit of its interval), and paired differences of several models' mean ASR.

``ASR = num_success / num_targets`` over the attacked (non-shadow) targets; None when there is no
target (e.g. the clean variant). Success and the lenient IoU > 0 success: :mod:`.matching`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from pcdet_atlas.evaluation.analyses.matching import AttackMetricError, TargetMatches, match_targets
from pcdet_atlas.evaluation.analyses.scores import rate
from pcdet_atlas.evaluation.intervals import asr_interval, paired_interval

__all__ = [
    "CI_LEVEL",
    "asr_from_matches",
    "attack_success_rate",
    "counts_per_run",
    "paired_asr_differences",
    "run_counts",
]

CI_LEVEL = 0.95  # the ASR's interval (intervals.asr_interval: sequences as clusters)


def run_counts(matches: TargetMatches) -> list[dict]:
    """Targets and successes per spoof run of the attacked (non-shadow) targets of ``matches``:
    ``[{'sequence', 'run_id', 'num_targets', 'num_success', 'num_success_lenient'}, ...]``
    sorted by ``(sequence, run_id)``, one entry per run with at least one target. The unit of
    the ASR's interval, and what a paired comparison of two models needs
    (:func:`paired_asr_differences`). ``run_counts(matches.select(mask))`` counts the attacked
    targets of a subset; :func:`counts_per_run` counts every target given, shadows included
    (the lifecycle's count at one position k)."""
    attacked = matches.attacked()
    return counts_per_run(attacked)


def counts_per_run(attacked: TargetMatches) -> list[dict]:
    """:func:`run_counts` of every target of ``attacked``."""
    run = attacked.run  # (T,) index of (sequence, run_id) in sorted order
    first = np.unique(run, return_index=True)[1]  # (R,) a target of each run
    num = first.size
    targets = np.bincount(run, minlength=num)
    success = np.bincount(run[attacked.success], minlength=num)
    lenient = np.bincount(run[attacked.success_lenient], minlength=num)
    return [
        {
            "sequence": str(attacked.sequence[i]),
            "run_id": int(attacked.run_id[i]),
            "num_targets": int(targets[r]),
            "num_success": int(success[r]),
            "num_success_lenient": int(lenient[r]),
        }
        for r, i in enumerate(first)
    ]


def asr_from_matches(matches: TargetMatches) -> dict:
    """ASR of the attacked (non-shadow) targets.

    Returns ``{'asr', 'asr_ci', 'num_runs', 'runs', 'num_targets', 'num_success',
    'asr_lenient', 'num_success_lenient', 'num_spoofed_frames', 'num_untargeted',
    'iou_threshold', 'score_threshold', 'target_class'}``; the rates are None without targets.
    ``asr_ci`` is the 95% interval of :func:`pcdet_atlas.evaluation.intervals.asr_interval`
    over the per-run counts ``runs`` (:func:`run_counts`; sequences as clusters, the runs of a
    single sequence; ``[lo, hi]``, None with fewer than two runs). ``num_untargeted`` spoofed
    frames recorded no target and are not in the ASR (see :class:`TargetMatches`).
    """
    attacked = matches.attacked()
    n = len(attacked)
    n_ok, n_len = int(attacked.success.sum()), int(attacked.success_lenient.sum())
    runs = run_counts(matches)  # a run is (sequence, run_id): run ids repeat across sequences
    ci = asr_interval(runs, level=CI_LEVEL)
    return {
        "asr": rate(n_ok, n),
        "asr_ci": None if ci is None else list(ci),
        "num_runs": len(runs),
        "runs": runs,
        "num_targets": n,
        "num_success": n_ok,
        "asr_lenient": rate(n_len, n),
        "num_success_lenient": n_len,
        "num_spoofed_frames": matches.num_spoofed,
        "num_untargeted": matches.num_untargeted,
        "iou_threshold": matches.iou_threshold,
        "score_threshold": matches.score_threshold,
        "target_class": matches.target_class,
    }


def paired_asr_differences(
    runs: Mapping[str, Mapping[str, Sequence[Mapping]]],
    *,
    level: float = CI_LEVEL,
) -> dict:
    """Differences of the mean ASR between models scored on the same spoof runs, with paired
    intervals over the sequences.

    A model's mean ASR is the mean of its per-variant ASRs (the variants of one rank group, say).
    Models attacked on the same runs share the runs' difficulty (the phantom trace and
    placement, the removal target), and the variants of a family share their runs too: the
    attacks key their draws by sequence and run start, not by budget, so run r of ``rem_10``
    removes around the same target as run r of ``rem_40``. The runs of a sequence share its
    scene. The cluster is therefore the sequence, across all the given variants (the run when
    every run comes from one sequence): each cluster's contribution to the difference of two
    mean ASRs is ``sum_v (d_hits_c,v - d_v * targets_c,v) / targets_v / V`` (``d_hits``: the
    two models' successes minus each other in the cluster, ``d_v``: their ASR difference on
    variant v), and the interval is the cluster-robust t interval of
    :func:`pcdet_atlas.evaluation.intervals.paired_interval` (``C - 1`` degrees of freedom).
    Closed-form: no draw, the same interval every call.

    Args:
        runs: model -> variant -> the variant's per-run counts (:func:`run_counts`, the
            ``runs`` of a ``results.json`` entry). Every model needs the same variants, each with
            the same runs and the same number of targets per run.

    Returns:
        ``{'models', 'variants', 'num_runs' (per variant), 'num_clusters' (sequences over all
        the variants; runs with one sequence), 'cluster' ('sequence' | 'run'), 'mean_asr'
        {model: float}, 'difference' {a: {b: mean_asr[a] - mean_asr[b]}}, 'ci' {a: {b: [lo,
        hi]}}}`` (within [-1, 1]); ``ci`` is None with fewer than two runs.

    Raises:
        AttackMetricError: fewer than two models, no variant, a variant without targets or with
            a run listed twice, or models whose variants, runs or targets per run differ (they
            were not scored on the same targets), naming them.
    """
    models = list(runs)
    if len(models) < 2:
        raise AttackMetricError(f"a paired comparison needs at least 2 models, got {models}")
    variants = list(runs[models[0]])
    if not variants:
        raise AttackMetricError(f"model {models[0]!r}: no variant to compare")
    for m in models[1:]:
        if set(runs[m]) != set(variants):
            raise AttackMetricError(
                f"models {models[0]!r} and {m!r} have different variants: {sorted(variants)} "
                f"and {sorted(runs[m])}"
            )

    def by_run(model: str, variant: str) -> dict:
        out = {}
        for r in runs[model][variant]:
            key = (str(r["sequence"]), int(r["run_id"]))
            if key in out:
                raise AttackMetricError(f"model {model!r}, variant {variant!r}: run {key} twice")
            out[key] = r
        return out

    first = {v: by_run(models[0], v) for v in variants}
    keys = sorted({key for v in variants for key in first[v]})
    column = {key: j for j, key in enumerate(keys)}
    hits, targets = [], []  # per variant: (M, R) successes, (R,) targets (0: not a run of it)
    for v in variants:
        ref = {key: int(r["num_targets"]) for key, r in first[v].items()}
        if sum(ref.values()) < 1:
            raise AttackMetricError(f"model {models[0]!r}, variant {v!r}: no targets")
        table = np.zeros((len(models), len(keys)))
        for i, m in enumerate(models):
            own = by_run(m, v)
            counts = {key: int(r["num_targets"]) for key, r in own.items()}
            if counts != ref:
                diff = sorted(set(counts.items()) ^ set(ref.items()))[:3]
                raise AttackMetricError(
                    f"variant {v!r}: models {models[0]!r} and {m!r} were not scored on the same "
                    f"targets (runs and targets per run differ, e.g. {diff})"
                )
            for key, r in own.items():
                table[i, column[key]] = r["num_success"]
        count = np.zeros(len(keys))
        for key, n in ref.items():
            count[column[key]] = n
        hits.append(table)
        targets.append(count)
    rates = [h.sum(1) / t.sum() for h, t in zip(hits, targets)]  # per variant (M,)
    mean = np.mean(rates, axis=0)  # (M,)
    sequences = sorted({seq for seq, _ in keys})
    unit = "sequence" if len(sequences) >= 2 else "run"
    cluster_of = np.array([sequences.index(seq) if unit == "sequence" else j
                           for j, (seq, _) in enumerate(keys)])  # (R,)  # fmt: skip
    num_clusters = int(cluster_of.max()) + 1
    # (M, C) each model's linearised contribution per cluster to its mean ASR
    contrib = np.zeros((len(models), num_clusters))
    for h, t, p in zip(hits, targets, rates):
        resid = (h - p[:, None] * t[None, :]) / t.sum() / len(variants)  # (M, R)
        np.add.at(contrib.T, cluster_of, resid.T)
    ci = None
    if len(keys) >= 2:
        delta = mean[:, None] - mean[None, :]  # (M, M)
        lo, hi = paired_interval(contrib[:, None, :] - contrib[None, :, :], delta, level)
        lo, hi = np.clip(lo, -1.0, 1.0), np.clip(hi, -1.0, 1.0)  # a difference of two rates
        ci = {a: {b: [float(lo[i, j]), float(hi[i, j])] for j, b in enumerate(models)}
              for i, a in enumerate(models)}  # fmt: skip
    return {
        "models": models,
        "variants": variants,
        "num_runs": {v: int(np.count_nonzero(t)) for v, t in zip(variants, targets)},
        "num_clusters": num_clusters,
        "cluster": unit,
        "mean_asr": {m: float(mean[i]) for i, m in enumerate(models)},
        "difference": {
            a: {b: float(mean[i] - mean[j]) for j, b in enumerate(models)}
            for i, a in enumerate(models)
        },  # fmt: skip
        "ci": ci,
    }


def attack_success_rate(
    det_annos: Sequence[Mapping], attack_infos: Sequence[Mapping] | None = None, **kwargs
) -> dict:
    """ASR and lenient ASR of one variant; ``kwargs`` as :func:`match_targets`."""
    return asr_from_matches(match_targets(det_annos, attack_infos, **kwargs))
