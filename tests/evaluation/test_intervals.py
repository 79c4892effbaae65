"""The ASR interval and the paired interval over sequences (docs/evaluation.md, "ASR interval"):
coverage on simulated ATLAS-shaped data, edge cases, a textbook reference, and that
``results.json`` reports them."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import scipy.stats

from pcdet_atlas.evaluation import (
    asr_interval,
    build_variant_result,
    coverage_simulation,
    evaluate_attack,
    paired_asr_differences,
)
from pcdet_atlas.evaluation.intervals import (
    cluster_counts,
    format_coverage_table,
    paired_interval,
    paired_simulation,
    wilson_cluster_interval,
)
from pcdet_atlas.evaluation.results.build import paired_from_results


def runs_of(hits, targets=32, runs_per_sequence=3, prefix="seq"):
    """Per-run counts, ``runs_per_sequence`` consecutive runs to a sequence."""
    return [
        {"sequence": f"{prefix}_{i // runs_per_sequence}", "run_id": i % runs_per_sequence,
         "num_targets": targets, "num_success": int(h), "num_success_lenient": int(h)}
        for i, h in enumerate(hits)
    ]  # fmt: skip


def cc_wilson(k: float, n: float, z: float) -> tuple[float, float]:
    """Newcombe's (1998) continuity-corrected Wilson interval, written out for one proportion."""
    p = k / n
    lo = 2 * n * p + z * z - 1 - z * math.sqrt(z * z - 2 - 1 / n + 4 * p * (n * (1 - p) + 1))
    hi = 2 * n * p + z * z + 1 + z * math.sqrt(z * z + 2 - 1 / n + 4 * p * (n * (1 - p) - 1))
    lo, hi = lo / (2 * (n + z * z)), hi / (2 * (n + z * z))
    return (0.0 if k == 0 else max(lo, 0.0)), (1.0 if k == n else min(hi, 1.0))


# ---------------------------------------------------------------------------- coverage
def test_coverage_on_simulated_atlas_data():
    """The documented target (docs/evaluation.md): >= 90% coverage of the nominal 95% for rates
    0.02-0.98 with 6-20 sequences of 3-5 runs, from no to moderate correlation, and for rates
    0.1-0.9 under strong correlation, with a mean width under 2x the true spread (2 x 1.96 x the
    pooled ASR's standard deviation). With 1,000 data sets per scenario the standard error is
    about 0.01; these cells simulate to >= 0.93, so the 0.90 floor holds with room. The paired
    difference (two models on the same runs, up to strong correlation) simulates to >= 0.90."""
    start = time.perf_counter()
    moderate = {"none": (0.0, 0.0), "moderate": (0.1, 0.05)}
    rows = coverage_simulation((0.02, 0.1, 0.5, 0.98), (6, 20), moderate, num_replicates=1000)
    rows += coverage_simulation((0.05, 0.95), (12,), moderate, runs_per_sequence=5,
                                num_replicates=1000)  # fmt: skip
    rows += coverage_simulation((0.1, 0.5, 0.9), (6, 20), {"strong": (0.25, 0.1)},
                                num_replicates=1000)  # fmt: skip
    for r in rows:
        assert r["coverage"] >= 0.90 and r["width_ratio"] <= 2.0, r
    assert np.mean([r["coverage"] for r in rows]) >= 0.95
    paired = paired_simulation(((0.1, 0.15), (0.5, 0.55)), (6, 20), num_replicates=1000)
    for r in paired:
        assert r["coverage"] >= 0.88 and r["width_ratio"] <= 2.0, r
    assert time.perf_counter() - start < 30


def test_simulation_is_seeded_per_scenario():
    """A scenario draws the same data whatever else the grid holds, and another seed others."""
    one = coverage_simulation((0.3,), (6,), {"m": (0.1, 0.05)}, num_replicates=50)
    grid = coverage_simulation((0.1, 0.3), (6, 12), {"m": (0.1, 0.05)}, num_replicates=50)
    assert one[0] == next(r for r in grid if r["rate"] == 0.3 and r["num_sequences"] == 6)
    other = coverage_simulation((0.3,), (6,), {"m": (0.1, 0.05)}, num_replicates=50, seed=1)
    assert other[0]["mean_width"] != one[0]["mean_width"]
    table = format_coverage_table(grid).splitlines()
    assert table[0] == "| correlation (ICC run, seq) | sequences | 0.1 | 0.3 |"
    assert len(table) == 4 and table[2].startswith("| m (0.1, 0.05) | 6 | ")


# ---------------------------------------------------------------------------- the interval
def test_against_the_textbook_interval():
    """Clusters that agree exactly (deff <= 1, so 1) give Newcombe's continuity-corrected
    Wilson interval of all the targets with the t quantile of C - 1 degrees of freedom."""
    runs = runs_of([8, 8, 8, 8, 8, 8], runs_per_sequence=1)  # 6 sequences, 48 of 192
    z = scipy.stats.t.ppf(0.975, 5)
    assert asr_interval(runs) == pytest.approx(cc_wilson(48, 192, z), abs=1e-12)
    lo, hi = asr_interval(runs, level=0.9)
    assert cc_wilson(48, 192, scipy.stats.t.ppf(0.95, 5)) == pytest.approx((lo, hi), abs=1e-12)


def test_spread_between_sequences_widens_the_interval():
    """The same 96 of 192 targets: spread evenly over six sequences, or all in three of them."""
    even = asr_interval(runs_of([16] * 6, runs_per_sequence=1))
    lumped = asr_interval(runs_of([32, 32, 32, 0, 0, 0], runs_per_sequence=1))
    assert even[0] <= 0.5 <= even[1] and lumped[0] <= 0.5 <= lumped[1]
    assert lumped[1] - lumped[0] > 3 * (even[1] - even[0])


def test_runs_of_a_sequence_are_one_cluster():
    """Runs count through their sequence: the interval of per-run counts is the cluster interval
    of the per-sequence sums, whatever the run order or run ids."""
    rng = np.random.default_rng(0)
    hits = rng.integers(0, 33, 18)
    runs = runs_of(hits)
    per_seq = hits.reshape(6, 3).sum(1)
    want = wilson_cluster_interval(per_seq, np.full(6, 96.0))
    assert asr_interval(runs) == pytest.approx((float(want[0]), float(want[1])), abs=1e-15)
    assert asr_interval(runs[::-1]) == asr_interval(runs)
    assert cluster_counts(runs)[2] == "sequence"


@pytest.mark.parametrize(
    "num_sequences, upper", [(1, 0.28), (2, 0.53), (6, 0.048), (20, 0.032)]
)  # fmt: skip
def test_all_or_no_successes_stay_informative(num_sequences, upper):
    """No success in 3 runs of 32 per sequence: ``[0, hi]``, hi inside (0, 1) (the effective
    size ``C + 3 n / (2 C)`` allows for clustering the data cannot show; few clusters pay
    their t quantile: 3 runs of one sequence 2 degrees of freedom, 2 sequences 1); all
    successes: the mirror image."""
    none = asr_interval(runs_of([0] * (3 * num_sequences)))
    every = asr_interval(runs_of([32] * (3 * num_sequences)))
    assert none[0] == 0.0 and none[1] == pytest.approx(upper, abs=0.005)
    assert every == pytest.approx((1 - none[1], 1.0), abs=1e-12)


def test_one_sequence_one_run_and_no_targets():
    """One sequence: its runs are the clusters (an interval for that sequence); one run, or no
    target: None (no spread between clusters can be seen)."""
    one_seq = runs_of([10, 20, 5], runs_per_sequence=3)
    assert cluster_counts(one_seq)[2] == "run"
    want = wilson_cluster_interval(np.array([10, 20, 5]), np.full(3, 32.0))
    assert asr_interval(one_seq) == pytest.approx((float(want[0]), float(want[1])), abs=1e-15)
    assert asr_interval(runs_of([10])) is None
    assert asr_interval([]) is None
    assert asr_interval(runs_of([0, 0], targets=0)) is None
    # runs without targets are left out rather than counted as clusters
    assert asr_interval(one_seq + runs_of([0], targets=0, prefix="empty")) == asr_interval(one_seq)


def test_deterministic_and_holds_the_asr():
    """Closed-form: the same interval every call and for every ``seed``; it holds the ASR."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        hits = rng.binomial(32, rng.uniform(0, 1, 12))
        runs = runs_of(hits)
        ci = asr_interval(runs)
        assert ci == asr_interval(runs, seed=0) == asr_interval(runs, seed=7)
        asr = hits.sum() / (32 * 12)
        assert 0.0 <= ci[0] <= asr <= ci[1] <= 1.0 and ci[0] < ci[1]
        assert asr_interval(runs, level=0.8)[1] - asr_interval(runs, level=0.8)[0] < ci[1] - ci[0]


def test_bad_counts_are_named():
    with pytest.raises(ValueError, match=r"run 1 \('seq_0', 1\): 'num_success' 40"):
        asr_interval(runs_of([3, 40]))
    with pytest.raises(ValueError, match="run 0: lacks key 'sequence'"):
        asr_interval([{"num_targets": 3, "num_success": 1}])
    with pytest.raises(ValueError, match=r"level must be in \(0, 1\), got 95"):
        asr_interval(runs_of([3, 4]), level=95)


def test_paired_interval_is_the_paired_t_interval():
    """Equal clusters: the linearised interval is the paired t interval of per-cluster
    differences."""
    rng = np.random.default_rng(4)
    d = rng.normal(0.05, 0.1, 8)  # per-sequence ASR differences
    lo, hi = paired_interval((d - d.mean()) / 8, d.mean())
    half = scipy.stats.t.ppf(0.975, 7) * d.std(ddof=1) / math.sqrt(8)
    assert (lo, hi) == pytest.approx((d.mean() - half, d.mean() + half), abs=1e-14)
    with pytest.raises(ValueError, match="needs >= 2 clusters, got 1"):
        paired_interval(np.zeros(1), 0.0)


# ---------------------------------------------------------------------------- results.json
def test_results_json_reports_these_intervals():
    """``asr_ci`` of an evaluated variant (through ``build_variant_result``) is
    :func:`asr_interval` of its own per-run counts, clustered by sequence; the report's paired
    comparison is :func:`paired_asr_differences` of the per-run counts."""
    from tests.evaluation.test_attack_metrics import spoof_runs

    d_a, i_a, _ = spoof_runs("seq_a", runs=range(6))
    d_b, i_b, _ = spoof_runs("seq_b", runs=range(6, 12))
    i_b = [{**i, "run_id": i["run_id"] - 6} for i in i_b]
    attack = evaluate_attack(d_a + d_b, i_a + i_b)
    entry = build_variant_result("inj_rel_easy", family="injection", num_frames=attack[
        "num_frames"], metrics=None, class_names=["Vehicle"], attack=attack)  # fmt: skip
    assert entry["asr_ci"] == list(asr_interval(entry["runs"])) == attack["asr_ci"]
    assert cluster_counts(entry["runs"])[2] == "sequence"
    results = [{"model": m, "variants": {"inj_rel_easy": entry}} for m in ("A", "B")]
    want = paired_asr_differences({m: {"inj_rel_easy": entry["runs"]} for m in ("A", "B")})
    assert paired_from_results(results, ["inj_rel_easy"]) == want
    assert want["cluster"] == "sequence" and want["num_clusters"] == 2
