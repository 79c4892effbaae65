"""The attack lifecycle: ASR and matched scores by lifecycle position k = 0..2W around each spoof
run, for a detector with a W-frame input (paper Findings 3 and 4)."""

from __future__ import annotations

import numpy as np

from pcdet_atlas.evaluation.analyses.asr import CI_LEVEL, counts_per_run
from pcdet_atlas.evaluation.analyses.matching import AttackMetricError, TargetMatches
from pcdet_atlas.evaluation.analyses.scores import NUM_SCORE_BINS, rate, score_histogram
from pcdet_atlas.evaluation.intervals import asr_interval

__all__ = ["SCHEDULE_WINDOW", "lifecycle_asr", "lifecycle_position"]

#: The schedule window the attack engine records ``lifecycle_k`` for by default (docs/attacks.md,
#: ``pcdet_atlas.attacks.schedule.DEFAULT_WINDOW``; a schedule config with another ``WINDOW``
#: must pass ``recorded_window=`` explicitly).
SCHEDULE_WINDOW = 32


def lifecycle_position(
    lifecycle_k: np.ndarray, is_shadow: np.ndarray, window: int, recorded_window: int
) -> np.ndarray:
    """Map recorded ``lifecycle_k`` to a detector's lifecycle position k in 0..2W, -1 = outside.

    The attack engine records k for its own window ``recorded_window`` (We): 0 = last clean
    frame before onset, 1..We = the first spoofed frames, We+1..2We = clean shadow frames after the
    run. For a detector with a window ``window`` (W <= We) the positions are 0, the first W
    spoofed frames (k = 1..W) and the first W frames after the run (k = W+1..2W).

    Raises AttackMetricError where the record contradicts itself (a shadow target at 1..We or a
    spoofed one outside it), which is what a wrong ``recorded_window`` produces, and for a
    ``window`` below 1 or above ``recorded_window``.
    """
    if window < 1 or recorded_window < window:
        raise AttackMetricError(
            f"lifecycle needs 1 <= window <= recorded_window, got {window}, {recorded_window}"
        )
    k = np.asarray(lifecycle_k, dtype=np.int64)
    shadow = np.asarray(is_shadow, dtype=bool)
    out = np.full(k.shape, -1, dtype=np.int64)
    bad_shadow = shadow & (k >= 1) & (k <= recorded_window)
    bad_spoofed = ~shadow & ((k <= 0) | (k > recorded_window))
    bad_range = (k > 2 * recorded_window) | (shadow & (k < 0))
    if np.any(bad_shadow | bad_spoofed | bad_range):
        bad = np.flatnonzero(bad_shadow | bad_spoofed | bad_range)[:5]
        raise AttackMetricError(
            f"lifecycle_k {k[bad].tolist()} (shadow {shadow[bad].tolist()}) is inconsistent "
            f"with recorded_window={recorded_window}: expected shadow at 0 and "
            f"{recorded_window + 1}..{2 * recorded_window}, spoofed at 1..{recorded_window}"
        )
    out[shadow & (k == 0)] = 0
    onset = ~shadow & (k >= 1) & (k <= window)
    out[onset] = k[onset]
    after = k - recorded_window
    decay = shadow & (after >= 1) & (after <= window)
    out[decay] = window + after[decay]
    return out


def lifecycle_asr(
    matches: TargetMatches,
    window: int,
    *,
    recorded_window: int | None = None,
    num_bins: int = NUM_SCORE_BINS,
    clean_scores: np.ndarray | None = None,
) -> dict:
    """ASR by lifecycle position k = 0..2W for a detector with a ``window``-frame input.

    Shadow targets (k = 0 and k = W+1..2W) are scored exactly like attacked ones (success = the
    phantom is detected / the target is missed) although the current frame is clean there.
    ``recorded_window`` is the schedule window the attack engine recorded ``lifecycle_k`` for
    (default :data:`SCHEDULE_WINDOW` = 32); see :func:`lifecycle_position` for the mapping. The
    engine records the frame between two runs as k = 0 of the next run, so with W equal to the
    schedule window position 2W only holds frames after a sequence's last run.

    Returns column lists over k: ``{'window', 'recorded_window', 'k', 'attacked' (bool: k in
    1..W), 'num_targets', 'num_success', 'asr', 'asr_ci' (per k the
    :func:`~pcdet_atlas.evaluation.intervals.asr_interval` of that position's targets grouped
    by their spoof run, None below two runs), 'runs' (per k those per-run counts, as
    :func:`~.asr.run_counts`, for intervals of pooled variants), 'num_success_lenient',
    'asr_lenient', 'score_bin_edges', 'score_counts' (per k: histogram of the matched scores),
    'clean_score_counts'}``: per k the histogram of ``clean_scores`` (T,), the clean run's
    matched score of the same targets (:func:`~.matching.clean_matched_scores`, NaN = not
    detected), the baseline of the lifecycle heatmaps; None without ``clean_scores``.
    """
    recorded_window = SCHEDULE_WINDOW if recorded_window is None else recorded_window
    pos = lifecycle_position(matches.lifecycle_k, matches.is_shadow, window, recorded_window)
    ks = list(range(2 * window + 1))
    success, lenient = matches.success, matches.success_lenient
    out: dict = {
        "window": int(window),
        "recorded_window": int(recorded_window),
        "k": ks,
        "attacked": [1 <= k <= window for k in ks],
        "num_targets": [],
        "num_success": [],
        "asr": [],
        "asr_ci": [],
        "runs": [],
        "num_success_lenient": [],
        "asr_lenient": [],
        "score_bin_edges": score_histogram(np.zeros(0), num_bins)["bin_edges"],
        "score_counts": [],
        "clean_score_counts": None if clean_scores is None else [],
    }
    if clean_scores is not None and len(clean_scores) != len(matches):
        raise AttackMetricError(
            f"clean_scores has {len(clean_scores)} entries for {len(matches)} targets"
        )
    for k in ks:
        at = pos == k
        n, n_ok, n_len = int(at.sum()), int(success[at].sum()), int(lenient[at].sum())
        out["num_targets"].append(n)
        out["num_success"].append(n_ok)
        out["asr"].append(rate(n_ok, n))
        runs = counts_per_run(matches.select(at)) if n else []
        ci = asr_interval(runs, level=CI_LEVEL) if n else None
        out["asr_ci"].append(None if ci is None else [float(ci[0]), float(ci[1])])
        out["runs"].append(runs)
        out["num_success_lenient"].append(n_len)
        out["asr_lenient"].append(rate(n_len, n))
        scores = matches.matched_score[at & matches.detected]
        out["score_counts"].append(score_histogram(scores, num_bins)["counts"])
        if clean_scores is not None:
            clean = clean_scores[at]
            clean = clean[np.isfinite(clean)]
            out["clean_score_counts"].append(score_histogram(clean, num_bins)["counts"])
    return out
