"""What a model's evaluation suite costs on a device: frames the model computes times its
measured per-frame cost (``tools/bench/cost_model.py``).

Frames computed come either from the variants' spoof schedules (:func:`scheduled_frames`: the
same rule ``tools/test.py`` applies when it reuses clean predictions, over sequences of a given
length, in the loader's batches) or from ``results.json`` files, whose variants record
``num_recomputed_frames`` (:func:`recorded_frames`). Per-frame costs come from
``tools/bench/bench_models.py --json`` or from the user (:func:`parse_cost`): a latency in
seconds, for a two-stage model optionally split into its RPN and its second stage, because PTT's
RPN runs on fewer frames than its second stage (its proposal bank takes the untouched frames'
proposals from the clean run).

A device-hour is one device busy for an hour: a GPU, or on a CPU the latency's wall time times
the torch threads it ran with (core-hours).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.train_utils.atlas_eval import loader_batches

__all__ = [
    "FrameCost",
    "SuiteFrames",
    "config_key",
    "device_hours",
    "parse_cost",
    "read_bench_json",
    "recorded_frames",
    "scheduled_frames",
    "sequence_lengths",
]

BENCH_JSON_VERSION = 1


@dataclass(frozen=True)
class FrameCost:
    """One model's measured cost per frame. ``seconds``: the whole ``predict``; ``rpn_seconds``:
    its RPN's part (two-stage models; None: not split). ``threads``: torch CPU threads of a CPU
    measurement (None on a GPU). ``source``: where the figure comes from."""

    seconds: float
    rpn_seconds: float | None = None
    device: str = "cuda"
    threads: int | None = None
    source: str = ""

    def __post_init__(self):
        for name in ("seconds", "rpn_seconds"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{self.source or 'cost'}: {name} {value!r}, expected >= 0 s")
        if self.rpn_seconds is not None and self.rpn_seconds > self.seconds:
            raise ValueError(
                f"{self.source or 'cost'}: RPN {self.rpn_seconds} s > whole frame {self.seconds} s"
            )

    @property
    def core_factor(self) -> int:
        """Devices one second of latency occupies: 1 on a GPU, the threads on a CPU."""
        return 1 if self.device.startswith("cuda") else int(self.threads or 1)


@dataclass(frozen=True)
class SuiteFrames:
    """Frames one model computes over a suite. ``frames``: frames through the whole model (its
    second stage); ``rpn_frames``: frames through its RPN when they differ (PTT), else None;
    ``total``: frames of all ``variants``; ``source``: where the counts come from."""

    frames: int
    total: int
    variants: int
    rpn_frames: int | None = None
    source: str = ""


def config_key(path: str | Path) -> str:
    """A config named as ``bench_models.py`` prints it: relative to ``cfgs/`` when it is there
    (``atlas/synthetic/cp4f.yaml``), else the path as given."""
    p = Path(path)
    resolved = (p if p.is_absolute() else REPO_ROOT / p).resolve()
    try:
        return str(resolved.relative_to(REPO_ROOT / "cfgs"))
    except ValueError:
        pass
    parts = p.parts
    return str(Path(*parts[1:])) if parts and parts[0] == "cfgs" and len(parts) > 1 else str(p)


def parse_cost(
    text: str, device: str = "cuda", threads: int | None = None
) -> tuple[str, FrameCost]:
    """``CFG=SECONDS`` or ``CFG=RPN_SECONDS+SECOND_STAGE_SECONDS`` -> ``(config key, cost)``."""
    cfg, sep, value = text.partition("=")
    if not sep or not cfg or not value:
        raise ValueError(f"--cost {text!r}: expected CFG=SECONDS or CFG=RPN_SECONDS+SECOND_SECONDS")
    try:
        parts = [float(v) for v in value.split("+")]
    except ValueError:
        raise ValueError(
            f"--cost {text!r}: {value!r} is not seconds (e.g. 0.011 or 0.016+0.174)"
        ) from None
    if len(parts) > 2:
        raise ValueError(f"--cost {text!r}: at most two terms (RPN + second stage)")
    rpn = parts[0] if len(parts) == 2 else None
    cost = FrameCost(sum(parts), rpn, device, threads, source=f"--cost {text}")
    return config_key(cfg), cost


def read_bench_json(path: str | Path) -> dict[str, FrameCost]:
    """The per-frame costs ``tools/bench/bench_models.py --json`` wrote: config key -> cost."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable JSON file ({err})") from None
    if not isinstance(data, dict) or data.get("version") != BENCH_JSON_VERSION:
        raise ValueError(
            f"{path}: 'version' {data.get('version') if isinstance(data, dict) else None!r}, "
            f"expected {BENCH_JSON_VERSION} (the output of tools/bench/bench_models.py --json)"
        )
    for key in ("device", "threads", "models"):
        if key not in data:
            raise ValueError(f"{path}: missing key {key!r}")
    out = {}
    for cfg, entry in data["models"].items():
        for key in ("latency_s", "rpn_s"):
            if key not in entry:
                raise ValueError(f"{path}: models[{cfg!r}] has no {key!r}")
        threads = None if str(data["device"]).startswith("cuda") else int(data["threads"])
        out[cfg] = FrameCost(
            float(entry["latency_s"]), None if entry["rpn_s"] is None else float(entry["rpn_s"]),
            str(data["device"]), threads, source=str(path),
        )  # fmt: skip
    return out


def sequence_lengths(num_frames: int, sequence_frames: int) -> list[int]:
    """``num_frames`` cut into sequences of ``sequence_frames`` (the last one shorter)."""
    if num_frames < 1 or sequence_frames < 1:
        raise ValueError(f"frames {num_frames} and sequence frames {sequence_frames} must be >= 1")
    full, rest = divmod(num_frames, sequence_frames)
    return [sequence_frames] * full + ([rest] if rest else [])


def _attacked(attack, lengths: Sequence[int], reach: int) -> np.ndarray:
    """``(sum(lengths),)`` booleans: frames whose input (the frame and ``reach`` before it,
    within its sequence) the attack's schedule spoofs; ``frames_to_compute``'s rule."""
    per_length: dict[int, np.ndarray] = {}
    for n in set(lengths):
        spoofed = np.array([attack.needs_simulation(j, n) for j in range(n)], dtype=np.int64)
        csum = np.concatenate([[0], np.cumsum(spoofed)])
        j = np.arange(n)
        per_length[n] = csum[j + 1] - csum[np.maximum(0, j - reach)] > 0
    return np.concatenate([per_length[n] for n in lengths])


def _batched(mask: np.ndarray, batch_size: int, world: int) -> int:
    """Frames of the loader batches (all ``world`` processes) holding a True frame: a reusing
    run computes those batches whole."""
    return sum(len(b) for b in loader_batches(len(mask), batch_size, world) if mask[b].any())


def scheduled_frames(
    attacks: Mapping[str, object],
    lengths: Sequence[int],
    reach: int,
    *,
    rpn_reach: int | None = None,
    proposal_history: int = 0,
    batch_size: int = 1,
    world: int = 1,
) -> SuiteFrames:
    """Frames a model computes over the variants ``attacks`` (name -> built attack; ``clean``
    computes every frame) on sequences of ``lengths``, reusing clean predictions.

    Args:
        reach: the model's input reach (``input_reach``: point history + proposal history).
        rpn_reach: a model with a proposal history: its RPN's reach (the point history); its
            RPN frames are counted apart, plus ``proposal_history`` frames per variant at each
            of the ``world - 1`` process boundaries (a process proposes the history before its
            first frame itself; an upper bound, since a reusing variant takes the untouched ones
            from the clean run).
        batch_size, world: the batch of one process and the processes (the loader's batches,
            as ``loader_batches`` deals them).
    """
    total = frames = rpn_frames = 0
    for name, attack in attacks.items():
        n = sum(lengths)
        total += n
        if name == "clean":
            frames += n
            rpn_frames += n
        else:
            frames += _batched(_attacked(attack, lengths, reach), batch_size, world)
            if rpn_reach is not None:
                rpn_frames += _batched(_attacked(attack, lengths, rpn_reach), batch_size, world)
        rpn_frames += (world - 1) * proposal_history
    source = f"schedule, batch {batch_size} x {world} processes"
    return SuiteFrames(
        frames, total, len(attacks), rpn_frames if rpn_reach is not None else None, source
    )


def recorded_frames(results: Mapping, where: str) -> SuiteFrames:
    """Frames a ``results.json`` (loaded) recorded as computed: ``num_recomputed_frames`` per
    variant, and a proposal bank's ``extra.proposal_bank.rpn_frames`` where every variant has
    one. A variant without the counts is an error naming it."""
    frames = total = 0
    rpn: list[int | None] = []
    for name, v in results["variants"].items():
        if v.get("num_recomputed_frames") is None:
            raise ValueError(
                f"{where}: variant {name!r} has num_recomputed_frames null (written before "
                "schema 4); expected a count"
            )
        frames += int(v["num_recomputed_frames"])
        total += int(v["num_frames"])
        bank = (v.get("extra") or {}).get("proposal_bank")
        rpn.append(None if not isinstance(bank, Mapping) else bank.get("rpn_frames"))
    rpn_frames = sum(rpn) if rpn and all(r is not None for r in rpn) else None
    n = len(results["variants"])
    return SuiteFrames(frames, total, n, rpn_frames, f"{where} ({n} variants)")


def device_hours(cost: FrameCost, suite: SuiteFrames, scale: float = 1.0) -> float:
    """Device-hours of a suite: frames x per-frame cost (PTT: RPN frames x the RPN's part plus
    frames x the second stage's), times ``scale`` (e.g. target frames / recorded frames), on
    ``cost.core_factor`` devices per second of latency."""
    if suite.rpn_frames is not None and cost.rpn_seconds is not None:
        seconds = suite.rpn_frames * cost.rpn_seconds + suite.frames * (
            cost.seconds - cost.rpn_seconds
        )
    else:
        seconds = suite.frames * cost.seconds
    return seconds * scale * cost.core_factor / 3600.0
