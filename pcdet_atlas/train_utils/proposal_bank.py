"""The proposal bank: every frame's RPN proposals computed once per variant and reused by every
window that reads them (PTT reads the proposals of the current and the 31 previous frames).

A frame's proposals are the frozen RPN's detections on **that frame's own** model input from the
dataset being evaluated: under an attack variant, its attacked 4-frame input (never the clean
run's). The bank keys them by ``(variant, sequence, frame, RPN checkpoint SHA-256)`` and keeps
them in memory in the evaluating process, in the vehicle frame they were predicted in; a
window's history is moved into its current vehicle frame when it is read
(:func:`~pcdet_atlas.datasets.proposal_history.gather_history`). Frames are computed when first
needed: the batch's current frames from the batch itself (one RPN call when none of them is
banked yet), any other frame from ``dataset.frame_sample`` (frames ``SAMPLED_INTERVAL`` skips,
or the history before a worker's first frame). ``rpn_frames`` counts the frames computed; with
a capacity that holds a window's frames, each frame is computed exactly once.

Seeding (:meth:`ProposalBank.seed`): an attack variant's bank may start with the clean run's
proposals of the frames whose RPN input the attack leaves untouched, so that only the frames
it changes go through the RPN again. Only frames the clean run proposed alone (a batch of one,
or a history frame) are offered (:meth:`ProposalBank.seedable`): the CPU RPN's output can
depend on its batch at float32 rounding, and a full run of the variant proposes such a frame
alone too (it makes the same requests in the same order), so a seeded run stays bitwise a
full run. At batch size 1 that is every frame.

Memory: one float32 row of 11 values per proposal (44 bytes); a frame of ~250 proposals is
~11 KB, a 198-frame sequence ~2.2 MB. The bank holds at most ``capacity`` frames (default 4096,
under 100 MB at 500 proposals a frame) and drops the oldest-inserted frame beyond that, so a
whole Waymo validation split (~40k frames) never accumulates.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping

import numpy as np
import torch

from pcdet_atlas.datasets.proposal_history import PROPOSAL_COLUMNS, gather_history
from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.models.detectors.two_stage import TwoStageDetector

__all__ = ["ProposalBank"]

DEFAULT_CAPACITY = 4096


def proposal_rows(proposal: Mapping) -> np.ndarray:
    """An RPN output dict (``pred_boxes (R, 9)``, ``pred_scores``, ``pred_labels``) -> float32
    ``(R, 11)`` rows, the layout of the training proposal cache."""
    boxes = proposal["pred_boxes"].detach().cpu().float()
    scores = proposal["pred_scores"].detach().cpu().float().reshape(-1, 1)
    labels = proposal["pred_labels"].detach().cpu().float().reshape(-1, 1)
    if len(scores) == 0:
        return np.zeros((0, PROPOSAL_COLUMNS), dtype=np.float32)
    if boxes.shape[1] < 9:
        raise ValueError(f"RPN boxes need velocity columns (9), got {tuple(boxes.shape)}")
    return torch.cat([boxes[:, :9], scores, labels], dim=1).numpy()


class ProposalBank:
    """Proposals per ``(variant, sequence, frame, RPN)`` for one dataset (module docstring).

    Args:
        model: the two-stage model whose frozen RPN proposes (``model.propose``).
        dataset: the evaluated dataset (an ``AtlasWaymoDataset`` for a variant, or a clean
            ``WaymoDataset``); history frames are read through its ``frame_sample``.
        device: where the RPN runs. num_history: previous frames attached per sample
            (default: ``model.proposal_history``). capacity: frames kept.
    """

    def __init__(
        self,
        model: TwoStageDetector,
        dataset,
        *,
        device: torch.device,
        num_history: int | None = None,
        capacity: int = DEFAULT_CAPACITY,
    ):
        self.model, self.dataset, self.device = model, dataset, device
        self.num_history = int(model.proposal_history if num_history is None else num_history)
        if capacity < self.num_history + 1:
            raise ValueError(
                f"ProposalBank capacity {capacity} cannot hold one window ({self.num_history + 1}"
                " frames)"
            )
        self.capacity = int(capacity)
        attack = getattr(dataset, "attack", None)
        self.variant = str(attack.variant) if attack is not None else "clean"
        self.rpn_sha256 = model.rpn_info["sha256"]
        self._frames: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._alone: set[tuple] = set()  # keys whose proposals came from a batch of one
        self.rpn_frames = 0  # frames whose proposals were computed
        self.seeded = 0  # frames seeded (seed())
        self.rpn_calls = 0  # RPN forward passes (a batch's current frames share one)
        self.hits = 0

    def key(self, sequence_name: str, sample_idx: int) -> tuple:
        return (self.variant, str(sequence_name), int(sample_idx), self.rpn_sha256)

    def _store(self, key: tuple, rows: np.ndarray, *, alone: bool) -> None:
        rows.flags.writeable = False
        self._frames[key] = rows
        if alone:
            self._alone.add(key)
        while len(self._frames) > self.capacity:
            self._alone.discard(self._frames.popitem(last=False)[0])

    def seed(self, rows_by_frame: Mapping[tuple[str, int], np.ndarray]) -> None:
        """Start from given proposals ``{(sequence_name, sample_idx): (R, 11) rows}`` of frames
        proposed alone whose RPN input is the same in this bank's dataset (the caller's check:
        the clean run's :meth:`seedable` for the frames an attack leaves untouched)."""
        for (sequence_name, sample_idx), rows in rows_by_frame.items():
            self._store(self.key(sequence_name, sample_idx), rows, alone=True)
            self.seeded += 1

    def seedable(self) -> dict[tuple[str, int], np.ndarray]:
        """The proposals held that were proposed for their frame alone,
        ``{(sequence_name, sample_idx): (R, 11) rows}`` (read-only; module docstring)."""
        return {(key[1], key[2]): rows for key, rows in self._frames.items()
                if key in self._alone}  # fmt: skip

    def frame(self, sequence_name: str, sample_idx: int) -> np.ndarray:
        """The proposals ``(R, 11)`` of a frame, in its own vehicle frame (computed if not
        banked)."""
        key = self.key(sequence_name, sample_idx)
        rows = self._frames.get(key)
        if rows is not None:
            self.hits += 1
            return rows
        sample = self.dataset.frame_sample(sequence_name, sample_idx)
        batch = load_data_to_device(self.dataset.collate_batch([sample]), self.device)
        self.rpn_calls += 1
        rows = proposal_rows(self.model.propose(batch)[0])
        self._store(key, rows, alone=True)
        self.rpn_frames += 1
        return rows

    def attach(self, batch: Mapping, batch_dev: Mapping) -> dict:
        """``batch_dev`` plus ``roi_boxes`` ``(B, R, 11)``, ``roi_history`` ``(B, N, 12)`` and
        ``roi_history_frames`` ``(B,)`` (on the device) for its samples; ``batch`` is the same
        batch on the host (its ``sequence_name``, ``sample_idx``)."""
        frames = list(zip(batch["sequence_name"], (int(i) for i in batch["sample_idx"])))
        keys = [self.key(seq, idx) for seq, idx in frames]
        if all(k not in self._frames for k in keys) and len(set(keys)) == len(keys):
            self.rpn_calls += 1
            for key, proposal in zip(keys, self.model.propose(batch_dev)):
                self._store(key, proposal_rows(proposal), alone=len(keys) == 1)
                self.rpn_frames += 1
        samples = []
        for seq, idx in frames:
            current = self.frame(seq, idx)
            infos = self.dataset.seq_name_to_infos[seq]
            rows, count = gather_history(
                lambda k, seq=seq: self.frame(seq, k),
                lambda k, infos=infos: np.asarray(infos[k]["pose"], dtype=np.float64),
                idx, self.num_history,
            )  # fmt: skip
            samples.append({
                "roi_boxes": current.astype(np.float64), "roi_history": rows,
                "roi_history_frames": np.int64(count),
            })  # fmt: skip
        extra = load_data_to_device(self.dataset.collate_batch(samples), self.device)
        extra.pop("batch_size")
        return {**batch_dev, **extra}

    def stats(self) -> dict:
        """``{'rpn_frames', 'seeded', 'rpn_calls', 'hits', 'frames_held', 'bytes_held'}``."""
        return {
            "rpn_frames": self.rpn_frames,
            "seeded": self.seeded,
            "rpn_calls": self.rpn_calls,
            "hits": self.hits,
            "frames_held": len(self._frames),
            "bytes_held": int(sum(r.nbytes for r in self._frames.values())),
        }
