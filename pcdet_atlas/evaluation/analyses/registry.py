"""The analyses registry: an analysis is one class that owns its computation on one variant,
its keys of a ``results.json`` variant entry (their JSON Schema and the invariants between
them), and its report sections and figures (docs/evaluation.md "Adding an analysis").

:func:`~pcdet_atlas.evaluation.analyses.evaluate.evaluate_attack` runs every registered analysis
on a variant, :mod:`pcdet_atlas.evaluation.results` builds and checks its keys, and the report
draws its sections and figures; nothing else names it. A plugin module registers one with::

    from pcdet_atlas.evaluation.analyses import Analysis, register_analysis

    @register_analysis
    class MeanIou(Analysis):
        name = "mean_iou"
        ...
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from pcdet_atlas.evaluation.analyses.matching import IouFn, TargetMatches
from pcdet_atlas.registry import ANALYSES

__all__ = [
    "ANALYSES",
    "Analysis",
    "ReportFigure",
    "ReportSection",
    "VariantData",
    "register_analysis",
    "registered_analyses",
]

#: Where the sections and figures of an analysis that sets no ``order`` go: after the built-ins.
LAST = 1000


@dataclass(frozen=True)
class VariantData:
    """What an analysis of one variant reads: the matched targets (:class:`TargetMatches`), the
    per-frame predictions and attack metadata they came from, the clean run's predictions (None
    when unknown), the detector's temporal ``window`` (None: no lifecycle), the schedule window
    the metadata was recorded for, the confidence threshold and score bins, and the IoU."""

    matches: TargetMatches
    det_annos: Sequence[Mapping]
    attack_infos: Sequence[Mapping]
    clean_det_annos: Sequence[Mapping] | None
    window: int | None
    recorded_window: int | None
    high_score: float
    num_bins: int
    iou_fn: IouFn


@dataclass(frozen=True)
class ReportSection:
    """A part of ``report.md`` (and of ``report.tex`` with ``latex``): ``make(results_list, fmt)``
    returns its ``(title, text)`` pairs, none to leave it out; ``order`` places it among the
    others (built-ins: 10-90)."""

    make: Callable[[Sequence[Mapping], str], list[tuple[str, str]]]
    order: int = LAST
    latex: bool = True


@dataclass(frozen=True)
class ReportFigure:
    """A figure of the report: ``draw(results_list, path, notes)`` writes ``path`` (``file``, a
    ``.png``, with the PDF beside it: :func:`~pcdet_atlas.evaluation.results.style.render`)
    and returns it, or returns why it cannot be drawn, appending to ``notes`` what it leaves
    out."""

    file: str
    caption: str
    draw: Callable[[Sequence[Mapping], Path, list[str]], Path | str]
    order: int = LAST


class Analysis:
    """One analysis of a variant's attack metrics.

    Subclasses set ``name`` and implement :meth:`schema` and :meth:`compute`; the rest is
    optional. ``required``: a results file must hold the analysis's keys (the built-ins);
    False (default) keeps files written before the analysis existed valid.
    """

    name: ClassVar[str] = ""
    required: ClassVar[bool] = False

    def schema(self) -> dict[str, dict]:
        """Its keys of a variant entry, in order, each with the JSON Schema of its value."""
        raise NotImplementedError

    def compute(self, data: VariantData) -> dict:
        """Its keys' values for one variant (plain Python or numpy values)."""
        raise NotImplementedError

    def empty(self) -> dict:
        """Its keys' values for a variant without attack metrics (the clean variant)."""
        return dict.fromkeys(self.schema())

    def check(self, entry: Mapping, path: str) -> None:
        """The invariants between its keys (and the entry's) that a JSON Schema cannot state;
        raise :class:`~.schema_parts.ResultsError` naming ``path`` and the key."""

    def sections(self) -> Sequence[ReportSection]:
        """Its tables and text in the report."""
        return ()

    def figures(self) -> Sequence[ReportFigure]:
        """Its figures in the report."""
        return ()


def register_analysis(analysis):
    """Register an :class:`Analysis` subclass (or instance) under its ``name``; usable as a class
    decorator. Raises naming both when its name or one of its keys is taken already."""
    instance = analysis() if isinstance(analysis, type) else analysis
    if not isinstance(instance, Analysis) or not instance.name:
        raise TypeError(f"{analysis!r} is not an Analysis with a name")
    keys = set(instance.schema())
    for name, other in ANALYSES.items():
        shared = keys & set(other.schema())
        if shared and name != instance.name:
            raise ValueError(
                f"analysis {instance.name!r} writes {sorted(shared)}, keys of analysis {name!r}"
            )
    ANALYSES.register(instance.name)(instance)
    return analysis


def registered_analyses() -> list[Analysis]:
    """The registered analyses in the order they registered (the built-ins first)."""
    return [analysis for _, analysis in ANALYSES.items()]
