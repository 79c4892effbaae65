"""Work counters of the attack engine, so that laziness is provable (docs/attacks.md).

One :class:`AttackCounters` object per process, :data:`COUNTERS`, is the only module-level
mutable state of the engine. It is deliberately global: the raycaster and the dataset increment
it without threading a handle through every call, and tests read it around a block of work::

    from pcdet_atlas.attacks.counters import COUNTERS

    with COUNTERS.measure() as work:
        dataset[i]
    assert work["frames_simulated"] == 0  # a clean frame does no attack work

Each DataLoader worker is a separate process with its own copy, so measure in the main process
(``num_workers=0``) when a test needs exact figures. Counters only count; they never influence
results, so determinism (docs/attacks.md) does not depend on them.

Fields (all non-negative ints):
    raycast_calls: calls of :func:`~pcdet_atlas.attacks.raycast.raycast_merge` that had at
        least one spoof point.
    bins_touched: distinct (azimuth, beam) rays holding a valid spoof point, summed over calls.
    points_examined: scene points examined (the candidates of the spoof's azimuth sector, of
        which those in the elevation band of its beams are binned exactly) plus spoof points,
        summed over calls.
    dual_draws: uniforms drawn for dual returns (one per bin where the spoof is the primary echo).
    frames_simulated: frames (current or history) that went through an attack simulation.
    history_frames_resimulated: history frames of a multi-frame input that were simulated
        (a subset of ``frames_simulated``).
    removal_points_examined: scene points a removal attack looked at (near its sector).
    frame_cache_hits: spoofed frames served from ``AtlasWaymoDataset``'s attacked-frame cache.
    frame_cache_misses: spoofed frames simulated and stored in that cache (with the cache off,
        neither counts).
    ground_fallbacks: injected phantoms set on ``GROUND.FALLBACK_Z`` because neither ground disc
        held ``GROUND.MIN_POINTS`` scene points (:mod:`pcdet_atlas.attacks.ground`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, fields

__all__ = ["AttackCounters", "COUNTERS"]


@dataclass
class AttackCounters:
    """Per-process work counters of the attack engine (see the module docstring)."""

    raycast_calls: int = 0
    bins_touched: int = 0
    points_examined: int = 0
    dual_draws: int = 0
    frames_simulated: int = 0
    history_frames_resimulated: int = 0
    removal_points_examined: int = 0
    frame_cache_hits: int = 0
    frame_cache_misses: int = 0
    ground_fallbacks: int = 0

    def reset(self) -> None:
        """Set every counter to zero."""
        for f in fields(self):
            setattr(self, f.name, 0)

    def snapshot(self) -> dict[str, int]:
        """The current values, as a new ``{name: int}`` dict."""
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}

    def add(self, **increments: int) -> None:
        """Increment named counters, e.g. ``COUNTERS.add(frames_simulated=1)``.

        Raises:
            KeyError: for an unknown counter name (a typo would otherwise count nothing).
            ValueError: for a negative increment.
        """
        for name, value in increments.items():
            if name not in _COUNTER_NAMES:
                raise KeyError(f"unknown attack counter {name!r}; known: {sorted(_COUNTER_NAMES)}")
            value = int(value)
            if value < 0:
                raise ValueError(f"counter {name!r} increment must be >= 0, got {value}")
            setattr(self, name, getattr(self, name) + value)

    @contextlib.contextmanager
    def measure(self) -> Iterator[dict[str, int]]:
        """Context manager yielding a dict that holds, on exit, the work done inside the block.

        The dict has every counter name, with value 0 inside the block, filled with
        ``after - before`` when the block ends (also when it raises). Nesting is fine.
        """
        before = self.snapshot()
        delta = dict.fromkeys(before, 0)
        try:
            yield delta
        finally:
            after = self.snapshot()
            delta.update({k: after[k] - before[k] for k in before})


#: The counter names, computed once (``dataclasses.fields`` is slow, and
#: :meth:`AttackCounters.add` runs a few times per simulated frame).
_COUNTER_NAMES = frozenset(f.name for f in fields(AttackCounters))

#: The per-process counters object of the attack engine.
COUNTERS = AttackCounters()
