"""Intervals of attack success rates whose targets are clustered: 32-frame spoof runs (one
phantom or removal target each) nested in sequences (docs/evaluation.md, "ASR interval").

The targets of a run share its phantom trace and placement, the runs of a sequence share its
scene, so neither targets nor runs are independent draws: the sequences are. Both intervals here
treat the **sequence** as the cluster (the runs of a sequence when there is only one):

* :func:`asr_interval`: a continuity-corrected Wilson score interval at an effective sample
  size ``n / deff``, the design effect ``deff >= 1`` estimated from the spread between clusters
  (a cluster-robust variance of the pooled rate over its binomial variance), with a t quantile
  of ``clusters - 1`` degrees of freedom in place of the normal one. Wilson keeps the interval
  inside [0, 1] and skewed near 0 and 1 (informative at 0 or all successes); the t quantile
  pays for estimating ``deff`` from few clusters.
* :func:`paired_interval`: the difference of two models' mean ASRs on the same runs, a
  cluster-robust (linearised) t interval over the same clusters.

:func:`coverage_simulation` draws ATLAS-shaped data (nested Beta rates, binomial targets) and
reports the empirical coverage and width of these intervals; the docs' tables are
:func:`format_coverage_table` of it (``python tools/dev/interval_coverage.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.special import expit, logit
from scipy.stats import t as student_t

from pcdet_atlas.utils.seeding import numpy_generator

__all__ = [
    "asr_interval",
    "cluster_counts",
    "coverage_simulation",
    "format_coverage_table",
    "paired_interval",
    "paired_simulation",
    "wilson_cluster_interval",
]


def _check_level(level: float) -> None:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")


def _t_quantile(level: float, df: np.ndarray | int) -> np.ndarray:
    """The two-sided ``level`` quantile of Student's t with ``df`` >= 1 degrees of freedom."""
    return np.asarray(student_t.ppf(0.5 + level / 2, df), dtype=np.float64)


def cluster_counts(runs: Sequence[Mapping]) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Targets and successes per cluster of per-run counts (a ``results.json`` ``runs`` list).

    The clusters are the sequences when the runs come from at least two, else the runs of the
    one sequence (the interval then speaks for that sequence only); None with fewer than two
    runs or no target (no spread between clusters can be seen).

    Returns:
        ``(targets (C,) float64, successes (C,) float64, 'sequence' | 'run')``, clusters
        sorted by name; runs without targets are dropped.

    Raises:
        ValueError: a run lacking a key, with negative counts or more successes than targets,
            naming the run and the key.
    """
    per_seq: dict[str, list[tuple[int, int]]] = {}
    for i, r in enumerate(runs):
        for key in ("sequence", "num_targets", "num_success"):
            if key not in r:
                raise ValueError(f"run {i}: lacks key '{key}'")
        n, k = int(r["num_targets"]), int(r["num_success"])
        if n < 0 or not 0 <= k <= n:
            raise ValueError(
                f"run {i} ({r['sequence']!r}, {r.get('run_id')!r}): 'num_success' {k} must be "
                f"in [0, 'num_targets' {n}]"
            )
        if n > 0:
            per_seq.setdefault(str(r["sequence"]), []).append((n, k))
    if len(per_seq) >= 2:
        names = sorted(per_seq)
        targets = [sum(n for n, _ in per_seq[s]) for s in names]
        hits = [sum(k for _, k in per_seq[s]) for s in names]
        return np.asarray(targets, float), np.asarray(hits, float), "sequence"
    flat = [nk for s in per_seq.values() for nk in s]
    if len(flat) < 2:
        return None
    return np.asarray([n for n, _ in flat], float), np.asarray([k for _, k in flat], float), "run"


def wilson_cluster_interval(
    hits: np.ndarray, targets: np.ndarray, level: float = 0.95
) -> tuple[np.ndarray, np.ndarray]:
    """Continuity-corrected Wilson interval (Newcombe 1998, method 4) of the pooled rate
    ``p = sum(hits) / sum(targets)`` over clusters, at the effective size ``n / deff`` with a t
    quantile of ``C - 1`` degrees of freedom in place of the normal one.

    ``deff = max(1, V_cluster / V_binomial)``: ``V_cluster = C / (C - 1) * sum((hits_c - p *
    targets_c)^2) / n^2`` (the cluster-robust variance of the ratio ``p``), ``V_binomial =
    p (1 - p) / n``; ``deff = 1`` at ``p`` 0 or 1. The effective size is also capped at
    ``C + (k + 3/2) * n / C``, ``k`` the fewer of successes and failures: fewer successes than
    clusters cannot show their spread (all of them may come from one cluster), so each counts
    for at most a cluster's worth of targets (``n / C``). With no success (or no failure) the
    interval stays informative: ``C + 3 n / (2 C)`` targets' worth, ``[0, 0.048]`` for 6
    sequences of 96 targets. As that leaves the clustering open, its upper limit can exceed
    the one of 1-2 successes (0.033 and 0.032 there). The cap matters below about ``C``
    successes; it was chosen with :func:`coverage_simulation`.

    Args:
        hits, targets: (..., C) successes and targets per cluster (C >= 2, targets > 0), any
            leading batch shape (replicates of a simulation).

    Returns:
        ``(lo, hi)``, each (...,) float64 in [0, 1].
    """
    _check_level(level)
    hits, targets = np.asarray(hits, np.float64), np.asarray(targets, np.float64)
    c = hits.shape[-1]
    if c < 2:
        raise ValueError(f"a cluster interval needs >= 2 clusters, got {c}")
    n = targets.sum(-1)  # (...,)
    p = hits.sum(-1) / n
    resid = hits - p[..., None] * targets  # (..., C)
    v_cluster = c / (c - 1) * (resid**2).sum(-1) / n**2
    v_binom = p * (1 - p) / n
    with np.errstate(divide="ignore", invalid="ignore"):
        deff = np.where(v_binom > 0, v_cluster / v_binom, 1.0)
    k_min = np.minimum(hits.sum(-1), n - hits.sum(-1))  # (...,) successes or failures
    # fewer successes (or failures) than clusters cannot show their spread: cap what they claim
    n_eff = np.minimum(n / np.maximum(deff, 1.0), c + (k_min + 1.5) * n / c)
    z = _t_quantile(level, c - 1)
    z2, m = z * z, n_eff
    # continuity-corrected Wilson (Newcombe 1998, method 4) at the effective size
    root_lo = np.sqrt(np.maximum(z2 - 2 - 1 / m + 4 * p * (m * (1 - p) + 1), 0.0))
    root_hi = np.sqrt(np.maximum(z2 + 2 - 1 / m + 4 * p * (m * (1 - p) - 1), 0.0))
    lo = (2 * m * p + z2 - 1 - z * root_lo) / (2 * (m + z2))
    hi = (2 * m * p + z2 + 1 + z * root_hi) / (2 * (m + z2))
    lo, hi = np.where(p <= 0, 0.0, lo), np.where(p >= 1, 1.0, hi)
    return np.clip(lo, 0.0, 1.0), np.clip(hi, 0.0, 1.0)


def asr_interval(
    runs: Sequence[Mapping], level: float = 0.95, seed: int = 0
) -> tuple[float, float] | None:
    """Interval of the ASR ``sum(num_success) / sum(num_targets)`` of per-run counts.

    ``runs``: ``[{'sequence', 'run_id', 'num_targets', 'num_success', ...}, ...]`` (a
    ``results.json`` variant's ``runs``). The clusters are the sequences; with one sequence its
    runs (an interval for that sequence, not for others); None without targets or with a single
    run. The interval is :func:`wilson_cluster_interval`: closed-form, so ``seed`` (kept for a
    resampling method's signature) changes nothing.

    Returns:
        ``(lo, hi)`` in [0, 1], containing the ASR; None as above.
    """
    del seed  # closed-form: nothing is drawn
    _check_level(level)
    counts = cluster_counts(runs)
    if counts is None:
        return None
    targets, hits, _ = counts
    lo, hi = wilson_cluster_interval(hits, targets, level)
    return float(lo), float(hi)


def paired_interval(
    contributions: np.ndarray, difference: np.ndarray | float, level: float = 0.95
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster-robust t interval of a difference of pooled rates, from each cluster's
    linearised contribution (influence) to it.

    Args:
        contributions: (..., C) per cluster, summing to 0 over C (C >= 2): for a difference of
            mean ASRs, ``sum_v (d_hits_c,v - d_p_v * targets_c,v) / targets_v / V`` over the
            V variants (:func:`pcdet_atlas.evaluation.paired_asr_differences`).
        difference: (...,) the estimate.

    Returns:
        ``difference -/+ t_{C-1} * sqrt(C / (C - 1) * sum(contributions^2))``, each (...,).
    """
    _check_level(level)
    u = np.asarray(contributions, np.float64)
    c = u.shape[-1]
    if c < 2:
        raise ValueError(f"a cluster interval needs >= 2 clusters, got {c}")
    se = np.sqrt(c / (c - 1) * (u**2).sum(-1))
    half = _t_quantile(level, c - 1) * se
    return difference - half, difference + half


# ---------------------------------------------------------------------------- simulation
def _beta_around(mean: np.ndarray, icc: float, rng: np.random.Generator) -> np.ndarray:
    """Rates with the given ``mean`` (any shape) and intra-class correlation ``icc`` (Beta with
    ``a + b = 1 / icc - 1``); ``icc`` 0: the mean itself."""
    if icc <= 0:
        return np.array(mean, np.float64, copy=True)
    s = 1.0 / icc - 1.0
    mean = np.clip(mean, 1e-9, 1 - 1e-9)
    return rng.beta(mean * s, (1 - mean) * s)


def _run_rates(
    rate: float, shape: tuple[int, int, int], icc_run: float, icc_sequence: float,
    rng: np.random.Generator,
) -> np.ndarray:  # fmt: skip
    """(B, S, R) run rates: sequence rates ~ Beta(mean ``rate``, ICC ``icc_sequence``), run rates
    ~ Beta(mean the sequence's, ICC ``icc_run``); their mean is ``rate``."""
    b, s, r = shape
    seq = _beta_around(np.full((b, s, 1), rate), icc_sequence, rng)  # (B, S, 1)
    return _beta_around(np.broadcast_to(seq, (b, s, r)), icc_run, rng)


def coverage_simulation(
    rates: Sequence[float] = (0.02, 0.1, 0.5, 0.9, 0.98),
    num_sequences: Sequence[int] = (6, 20),
    correlations: Mapping[str, tuple[float, float]] | None = None,
    *,
    runs_per_sequence: int = 3,
    targets_per_run: int = 32,
    num_replicates: int = 400,
    level: float = 0.95,
    seed: int = 0,
) -> list[dict]:
    """Empirical coverage and width of :func:`asr_interval` on simulated ATLAS-shaped data.

    Per scenario (rate x sequences x correlation), ``num_replicates`` data sets of
    ``num_sequences`` sequences of ``runs_per_sequence`` runs of ``targets_per_run`` targets
    (run rates from nested Betas, targets ~ Binomial(``targets_per_run``, run rate)), each
    scored by the interval over its sequences.

    Args:
        correlations: name -> ``(icc_run, icc_sequence)``; default none (0, 0), moderate
            (0.1, 0.05) and strong (0.25, 0.1).
        seed: with the scenario, the key of its generator
            (:func:`pcdet_atlas.utils.seeding.numpy_generator`): a scenario draws the same data
            whatever else the grid holds.

    Returns:
        One dict per scenario: ``{'rate', 'num_sequences', 'correlation', 'icc_run',
        'icc_sequence', 'coverage' (fraction of intervals holding the rate), 'mean_width',
        'true_sd' (standard deviation of the pooled ASR over the replicates), 'width_ratio'
        (mean width / (2 * 1.96 * true_sd))}``.
    """
    correlations = _default_correlations() if correlations is None else correlations
    out = []
    for name, (icc_run, icc_seq) in correlations.items():
        for s in num_sequences:
            for rate in rates:
                rng = numpy_generator("asr_coverage", seed, name, s, rate, runs_per_sequence)
                shape = (num_replicates, s, runs_per_sequence)
                run = _run_rates(rate, shape, icc_run, icc_seq, rng)
                hits = rng.binomial(targets_per_run, run).sum(-1).astype(np.float64)  # (B, S)
                targets = np.full(hits.shape, float(runs_per_sequence * targets_per_run))
                lo, hi = wilson_cluster_interval(hits, targets, level)
                est = hits.sum(-1) / targets.sum(-1)
                out.append(_scenario_row(rate, s, name, icc_run, icc_seq, lo, hi, est, rate))
    return out


def paired_simulation(
    rates: Sequence[tuple[float, float]] = ((0.1, 0.15), (0.5, 0.55), (0.85, 0.9)),
    num_sequences: Sequence[int] = (6, 20),
    correlations: Mapping[str, tuple[float, float]] | None = None,
    *,
    model_sd: float = 0.3,
    runs_per_sequence: int = 3,
    targets_per_run: int = 32,
    num_replicates: int = 400,
    level: float = 0.95,
    seed: int = 0,
) -> list[dict]:
    """Coverage and width of :func:`paired_interval` for the difference of two models attacked
    on the same runs.

    Model A's run rates are drawn as in :func:`coverage_simulation` (rate ``a``); model B's
    share them on the logit scale: ``logit(rate_B) = logit(rate_A) + logit(b) - logit(a) +
    N(0, model_sd^2)`` per run (a run hard for A is hard for B, with model-specific noise). The
    true difference is the mean of ``rate_A - rate_B`` over 200,000 run draws.

    Returns:
        As :func:`coverage_simulation`, ``rate`` being ``'a-b'`` and ``true_difference`` added.
    """
    correlations = _default_correlations() if correlations is None else correlations
    out = []
    for name, (icc_run, icc_seq) in correlations.items():
        for s in num_sequences:
            for a, b in rates:
                rng = numpy_generator("paired_coverage", seed, name, s, a, b, runs_per_sequence)
                shift = logit(b) - logit(a)
                big = np.clip(_run_rates(a, (200_000, 1, 1), icc_run, icc_seq, rng), 1e-6, 1 - 1e-6)
                big_b = expit(logit(big) + shift + model_sd * rng.standard_normal(big.shape))
                truth = float(np.mean(big - big_b))
                shape = (num_replicates, s, runs_per_sequence)
                ra = np.clip(_run_rates(a, shape, icc_run, icc_seq, rng), 1e-6, 1 - 1e-6)
                rb = expit(logit(ra) + shift + model_sd * rng.standard_normal(shape))
                ha = rng.binomial(targets_per_run, ra).sum(-1).astype(np.float64)  # (B, S)
                hb = rng.binomial(targets_per_run, rb).sum(-1).astype(np.float64)
                n_c = float(runs_per_sequence * targets_per_run)
                n = n_c * s
                diff = (ha.sum(-1) - hb.sum(-1)) / n  # (B,)
                u = ((ha - hb) - diff[:, None] * n_c) / n  # (B, S) linearised contributions
                lo, hi = paired_interval(u, diff, level)
                out.append(_scenario_row(f"{a}-{b}", s, name, icc_run, icc_seq, lo, hi, diff,
                                         truth) | {"true_difference": truth})  # fmt: skip
    return out


def _default_correlations() -> dict[str, tuple[float, float]]:
    return {"none": (0.0, 0.0), "moderate": (0.1, 0.05), "strong": (0.25, 0.1)}


def _scenario_row(rate, s, name, icc_run, icc_seq, lo, hi, est, truth) -> dict:
    sd = float(np.std(est, ddof=1))
    width = float(np.mean(hi - lo))
    return {
        "rate": rate,
        "num_sequences": int(s),
        "correlation": name,
        "icc_run": icc_run,
        "icc_sequence": icc_seq,
        "coverage": float(np.mean((lo <= truth) & (truth <= hi))),
        "mean_width": width,
        "true_sd": sd,
        "width_ratio": width / (2 * 1.96 * sd) if sd > 0 else math.inf,
    }


def format_coverage_table(rows: Sequence[Mapping]) -> str:
    """Markdown table of :func:`coverage_simulation` / :func:`paired_simulation` rows:
    coverage / width ratio per rate (columns) and correlation x sequences (rows)."""
    rates = list(dict.fromkeys(r["rate"] for r in rows))
    keys = list(dict.fromkeys((r["correlation"], r["num_sequences"]) for r in rows))
    cell = {(r["correlation"], r["num_sequences"], r["rate"]): r for r in rows}
    lines = [
        "| correlation (ICC run, seq) | sequences | " + " | ".join(str(r) for r in rates) + " |",
        "|---|---|" + "---|" * len(rates),
    ]
    for name, s in keys:
        first = next(r for r in rows if r["correlation"] == name)
        row = [f"{name} ({first['icc_run']}, {first['icc_sequence']})", str(s)]
        for rate in rates:
            r = cell.get((name, s, rate))
            row.append("-" if r is None else f"{r['coverage']:.2f} / {r['width_ratio']:.2f}")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)
