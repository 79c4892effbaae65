"""Robustness ranks: per-setting ASR ranks of several models, averaged per rank group (the attack
class's ``RANK_GROUP``), and the linear fit between two groups (paper Fig. 3)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from pcdet_atlas.evaluation.analyses.matching import AttackMetricError

__all__ = ["linear_fit", "robustness_ranks"]


def linear_fit(x: np.ndarray, y: np.ndarray) -> dict:
    """Ordinary least squares ``y = slope * x + intercept`` of (P,) points.

    Returns ``{'slope', 'intercept', 'r2', 'pearson_r', 'p_value', 'num_models'}`` (``p_value``:
    two-sided test of zero slope, ``scipy.stats.linregress``).
    """
    from scipy.stats import linregress

    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1 or x.size < 2 or np.ptp(x) == 0:
        raise AttackMetricError(f"linear fit needs >= 2 points with varying x, got {x} and {y}")
    reg = linregress(x, y)
    return {
        "slope": float(reg.slope),
        "intercept": float(reg.intercept),
        "r2": float(reg.rvalue**2),
        "pearson_r": float(reg.rvalue),
        "p_value": float(reg.pvalue),
        "num_models": int(x.size),
    }


def robustness_ranks(
    asr_by_model: Mapping[str, Mapping[str, float]],
    variant_groups: Mapping[str, str | None],
    *,
    tie_method: str = "average",
    min_models_for_fit: int = 3,
    fit_axes: tuple[str, str] = ("injection", "removal"),
) -> dict:
    """Per-setting ASR ranks of several models, averaged per rank group, and their linear fit.

    In each setting (variant) the models are ranked by ASR, rank 1 = lowest ASR = most robust;
    ties get the mean of the ranks they span (``tie_method`` as ``scipy.stats.rankdata``:
    'average', 'min', 'max', 'dense', 'ordinal'). A model's rank in a group is the mean of its
    ranks over the group's variants. The fit is ordinary least squares of the ``fit_axes[1]``
    group's rank on the ``fit_axes[0]`` group's (the paper's Fig. "Robustness Correlation":
    removal on injection).

    Args:
        asr_by_model: model -> variant -> ASR in [0, 1]. Every model needs every ranked variant.
        variant_groups: variant -> rank group (the attack class's ``RANK_GROUP``); variants whose
            group is None (e.g. clean) are not ranked.
        min_models_for_fit: below this many models the fit is None (two points fit exactly).

    Returns:
        ``{'models': [...], 'tie_method', 'per_setting': {variant: {model: rank}},
        'group_ranks': {group: {model: r}}, 'fit_axes': [x group, y group], 'fit': {'slope',
        'intercept', 'r2', 'pearson_r', 'p_value', 'num_models'} or None}`` (None also when a
        fit axis has no variant, or when every model has the same rank on the x axis).
    """
    from scipy.stats import rankdata

    models = sorted(asr_by_model)
    if len(models) < 2:
        raise AttackMetricError(f"ranking needs at least 2 models, got {models}")
    ranked: dict[str, list[str]] = {}
    for variant, group in sorted(variant_groups.items()):
        if group is not None:
            ranked.setdefault(str(group), []).append(variant)
    per_setting: dict[str, dict[str, float]] = {}
    for variant in (v for variants in ranked.values() for v in variants):
        values = []
        for m in models:
            asr = asr_by_model[m].get(variant)
            if asr is None or not math.isfinite(asr):
                raise AttackMetricError(f"model {m!r} has no ASR for variant {variant!r}")
            values.append(float(asr))
        ranks = rankdata(values, method=tie_method)
        per_setting[variant] = {m: float(r) for m, r in zip(models, ranks)}
    group_ranks = {
        group: {m: float(np.mean([per_setting[v][m] for v in variants])) for m in models}
        for group, variants in ranked.items()
    }
    fit = None
    x_group, y_group = fit_axes
    if x_group in group_ranks and y_group in group_ranks and len(models) >= min_models_for_fit:
        x = np.array([group_ranks[x_group][m] for m in models])
        if np.ptp(x) > 0:
            fit = linear_fit(x, np.array([group_ranks[y_group][m] for m in models]))
    return {
        "models": models,
        "tie_method": tie_method,
        "per_setting": per_setting,
        "group_ranks": group_ranks,
        "fit_axes": [x_group, y_group],
        "fit": fit,
    }
