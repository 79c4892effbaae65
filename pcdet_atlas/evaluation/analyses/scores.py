"""Score distributions of matched targets: rounding, fixed-bin histograms and the peak (mode) at
the paper's resolution; shared by the confidence and lifecycle analyses."""

from __future__ import annotations

import numpy as np

from pcdet_atlas.evaluation.analyses.matching import AttackMetricError

__all__ = [
    "HIGH_SCORE_THRESHOLD",
    "NUM_SCORE_BINS",
    "PEAK_RESOLUTION",
    "rate",
    "score_histogram",
    "score_peak",
    "score_values",
]

HIGH_SCORE_THRESHOLD = 0.7
NUM_SCORE_BINS = 20  # fixed bins of width 0.05 over [0, 1]
PEAK_RESOLUTION = 1e-3  # the centre gap's resolution (the paper reports three decimals)


def rate(num: int, den: int) -> float | None:
    """``num / den``, None when ``den`` is 0 (a rate of no targets is undefined)."""
    return None if den == 0 else num / den


def score_values(scores: np.ndarray) -> np.ndarray:
    """(S,) scores as float64 rounded to 1e-6, so that a float32 score printed as 0.9 counts as 0.9
    (float32(0.9) = 0.89999998) in bins and thresholds."""
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(scores)) or np.any((scores < 0) | (scores > 1)):
        raise AttackMetricError(f"scores must be finite and in [0, 1]; got {scores}")
    return np.round(scores, 6)


def score_histogram(scores: np.ndarray, num_bins: int = NUM_SCORE_BINS) -> dict:
    """Counts of ``scores`` (S,) in ``num_bins`` equal bins ``[i / n, (i + 1) / n)`` over [0, 1]
    (the last bin also holds 1.0); scores are rounded to 1e-6 first (see ``score_values``).

    Returns ``{'bin_edges': [num_bins + 1 floats], 'counts': [num_bins ints]}``.
    """
    scores = score_values(scores)
    index = np.clip(np.floor(scores * num_bins + 1e-9).astype(np.int64), 0, num_bins - 1)
    counts = np.bincount(index, minlength=num_bins)
    edges = [round(i / num_bins, 12) for i in range(num_bins + 1)]
    return {"bin_edges": edges, "counts": counts.tolist()}


def score_peak(scores: np.ndarray, resolution: float = PEAK_RESOLUTION) -> float | None:
    """Peak (mode) of a score distribution at the paper's resolution (0.001 by default).

    The maximum of a Gaussian kernel density estimate (Silverman's rule-of-thumb bandwidth,
    ``0.9 min(std, IQR / 1.34) n^(-1/5)``, the std alone when the IQR is 0) on a grid of step
    ``resolution`` over [0, 1]; ties go to the lowest score. A sample with no spread (one score,
    or identical scores) has its value as peak (the limit of the estimate as the bandwidth
    shrinks), on the same grid. None for an empty sample.
    """
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if scores.size == 0:
        return None
    steps = int(round(1.0 / resolution))
    std = float(scores.std(ddof=1)) if scores.size > 1 else 0.0
    if std == 0.0:
        return round(float(np.round(scores[0] * steps)) / steps, 12)
    q75, q25 = np.percentile(scores, [75, 25])
    spread = min(std, (q75 - q25) / 1.34) or std
    bandwidth = 0.9 * spread * scores.size ** (-0.2)
    grid = np.arange(steps + 1) / steps  # (G,)
    density = np.exp(-0.5 * ((grid[:, None] - scores[None]) / bandwidth) ** 2).sum(1)
    return round(float(grid[int(np.argmax(density))]), 12)  # argmax: the lowest of ties
