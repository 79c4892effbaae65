"""The clean "attack": no frame is spoofed, nothing is simulated (the reference variant)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pcdet_atlas.attacks.base import BaseAttack, FrameAttack, ScheduleState, SequenceData
from pcdet_atlas.registry import ATTACKS

__all__ = ["CleanAttack"]


@ATTACKS.register()
class CleanAttack(BaseAttack):
    """Every frame clean; metadata says so (``family='clean'``, no run, no target)."""

    family = "clean"

    @classmethod
    def from_config(cls, cfg: Mapping, data_root: str | Path | None = None) -> CleanAttack:
        return cls(**cls._common_kwargs(cfg))

    def schedule_state(self, frame_idx: int, num_frames: int) -> ScheduleState:
        if not 0 <= int(frame_idx) < int(num_frames):
            raise ValueError(f"frame index {frame_idx} outside a sequence of {num_frames} frames")
        return ScheduleState(False, -1, -1, -1)

    def prepare_run(self, seq: SequenceData, run_id: int):
        raise RuntimeError("CleanAttack has no runs")

    def attack_frame(self, scene_xyz: np.ndarray, seq, frame_idx, run, state) -> FrameAttack:
        raise RuntimeError("CleanAttack never attacks a frame")

    def shadow_meta(self, seq, frame_idx, run, state) -> dict:
        raise RuntimeError("CleanAttack has no lifecycle frames")
