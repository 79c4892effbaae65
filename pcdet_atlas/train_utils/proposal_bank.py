"""The proposal bank: every frame's RPN proposals computed once per variant and reused by every
window that reads them (PTT reads the proposals of the current and the 31 previous frames).

A frame's proposals are the frozen RPN's detections on **that frame's own** model input from the
dataset being evaluated: under an attack variant, its attacked 4-frame input (never the clean
run's). The bank keys them by ``(variant, sequence, frame, RPN checkpoint SHA-256)`` and keeps
them in memory in the evaluating process, in the vehicle frame they were predicted in; a
window's history is moved into its current vehicle frame when it is read
(:func:`~pcdet_atlas.datasets.proposal_history.gather_history`). Frames are computed when first
needed: the batch's current frames from the batch itself, any other frame from
``dataset.frame_sample`` (frames ``SAMPLED_INTERVAL`` skips, or the history before a worker's
first frame). ``rpn_frames`` counts the frames passed through the RPN. The bank drops the
oldest-inserted frame first and a window inserts its history newest first, so each frame is
computed exactly once when the capacity holds twice the frames a batch's windows span (its
current frames, those between them and the history before the first): at least
``2 * (num_history + 1)`` frames, which a batch of one needs; a smaller bank would drop the
frames the next window reads and compute them again and again.

Which frames the RPN sees together: the CPU RPN's output can depend on its batch at float32
rounding, so with ``batches`` (the loader's batches over all processes, as dataset indices) a
frame is always proposed with the frames of its loader batch, and a frame no batch holds alone,
wherever and whenever it is first read: a frame's proposals then depend on the batch size and
the process count (as its prediction does) but not on the loader workers, the order batches
arrive in or the batches a reusing run skips. Without ``batches`` (training-time evaluation), a
loader batch none of whose frames is banked is proposed together and any other frame alone,
so a frame's proposals may depend on the order batches arrive in. At batch size 1 both are every
frame alone.

Seeding (:meth:`ProposalBank.seed`): an attack variant's bank may start with the clean run's
proposals (:meth:`ProposalBank.seedable`) of the frames whose RPN batch (:func:`frame_batches`)
holds only frames whose RPN input the attack leaves untouched, so that only the other frames go
through the RPN again; a seeded frame then has bitwise the proposals a full run of the variant
computes for it.

Memory: one float32 row of 11 values per proposal (44 bytes); a frame of ~250 proposals is
~11 KB, a 198-frame sequence ~2.2 MB. The bank holds at most ``capacity`` frames (default 4096,
under 100 MB at 500 proposals a frame) and drops the oldest-inserted frame beyond that, so a
whole Waymo validation split (~40k frames) never accumulates.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from pcdet_atlas.datasets.proposal_history import PROPOSAL_COLUMNS, gather_history
from pcdet_atlas.models.batch import load_data_to_device
from pcdet_atlas.models.detectors.two_stage import TwoStageDetector

__all__ = ["ProposalBank", "frame_batches"]

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


def frame_batches(dataset, batches: Sequence[Sequence[int]]) -> dict[tuple, tuple]:
    """``{(sequence_name, sample_idx): frames of its batch}`` for every frame of ``batches``
    (lists of indices into ``dataset.infos``); a frame no batch holds is proposed alone.

    Raises:
        ValueError: an index out of range or held by two batches.
    """
    out: dict[tuple, tuple] = {}
    num_infos = len(dataset.infos)
    for batch in batches:
        frames = []
        for index in batch:
            if not 0 <= int(index) < num_infos:
                raise ValueError(
                    f"proposal batches: index {index} outside the dataset's {num_infos} frames"
                )
            point_cloud = dataset.infos[int(index)]["point_cloud"]
            frames.append((str(point_cloud["lidar_sequence"]), int(point_cloud["sample_idx"])))
        frames = tuple(frames)
        for frame in frames:
            if frame in out:
                raise ValueError(f"proposal batches: frame {frame} is in two batches")
            out[frame] = frames
    return out


class ProposalBank:
    """Proposals per ``(variant, sequence, frame, RPN)`` for one dataset (module docstring).

    Args:
        model: the two-stage model whose frozen RPN proposes (``model.propose``).
        dataset: the evaluated dataset (an ``AtlasWaymoDataset`` for a variant, or a clean
            ``WaymoDataset``); history frames are read through its ``frame_sample``.
        device: where the RPN runs. num_history: previous frames attached per sample
            (default: ``model.proposal_history``). capacity: frames kept (at least
            ``2 * (num_history + 1)``).
        batches: the loader's batches over all processes, as lists of indices into
            ``dataset.infos``: each frame is then proposed with the frames of its batch
            (module docstring); needed by :meth:`seedable`.
    """

    def __init__(
        self,
        model: TwoStageDetector,
        dataset,
        *,
        device: torch.device,
        num_history: int | None = None,
        capacity: int = DEFAULT_CAPACITY,
        batches: Sequence[Sequence[int]] | None = None,
    ):
        self.model, self.dataset, self.device = model, dataset, device
        self.num_history = int(model.proposal_history if num_history is None else num_history)
        if capacity < 2 * (self.num_history + 1):
            raise ValueError(
                f"ProposalBank capacity {capacity} is below 2 * (num_history + 1) = "
                f"{2 * (self.num_history + 1)} frames, twice a window (module docstring)"
            )
        self.capacity = int(capacity)
        attack = getattr(dataset, "attack", None)
        self.variant = str(attack.variant) if attack is not None else "clean"
        self.rpn_sha256 = model.rpn_info["sha256"]
        self._batch_of = None if batches is None else frame_batches(dataset, batches)
        self._frames: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.rpn_frames = 0  # frames passed through the RPN
        self.seeded = 0  # frames seeded (seed())
        self.rpn_calls = 0  # RPN forward passes (the frames of a batch share one)
        self.hits = 0

    def key(self, sequence_name: str, sample_idx: int) -> tuple:
        return (self.variant, str(sequence_name), int(sample_idx), self.rpn_sha256)

    def _store(self, key: tuple, rows: np.ndarray) -> None:
        rows.flags.writeable = False
        self._frames[key] = rows
        while len(self._frames) > self.capacity:
            self._frames.popitem(last=False)

    def _propose(self, frames: Sequence[tuple[str, int]], batch_dev: Mapping) -> list[np.ndarray]:
        """One RPN pass over ``frames`` (``batch_dev`` holds their samples, in that order): their
        proposals; banks those not banked yet."""
        self.rpn_calls += 1
        self.rpn_frames += len(frames)
        rows = [proposal_rows(p) for p in self.model.propose(batch_dev)]
        if len(rows) != len(frames):
            raise RuntimeError(
                f"the RPN returned {len(rows)} proposal sets for {len(frames)} frames {frames}"
            )
        for frame, frame_rows in zip(frames, rows):
            if self.key(*frame) not in self._frames:
                self._store(self.key(*frame), frame_rows)
        return rows

    def rpn_batch(self, sequence_name: str, sample_idx: int) -> tuple[tuple[str, int], ...]:
        """The frames a frame is proposed with, itself included (module docstring)."""
        frame = (str(sequence_name), int(sample_idx))
        if self._batch_of is None:
            return (frame,)
        return self._batch_of.get(frame, (frame,))

    def seed(self, rows_by_frame: Mapping[tuple[str, int], np.ndarray]) -> None:
        """Start from given proposals ``{(sequence_name, sample_idx): (R, 11) rows}``, each
        bitwise what this bank would compute for its frame (the caller's check: the clean run's
        :meth:`seedable` for the frames whose whole RPN batch the attack leaves untouched)."""
        for (sequence_name, sample_idx), rows in rows_by_frame.items():
            self._store(self.key(sequence_name, sample_idx), rows)
            self.seeded += 1

    def seedable(self) -> dict[tuple[str, int], np.ndarray]:
        """The proposals held, ``{(sequence_name, sample_idx): (R, 11) rows}`` (read-only), each
        proposed with the frames of its :meth:`rpn_batch`.

        Raises:
            ValueError: the bank was built without ``batches``: its frames' proposals depend on
                the order batches arrived in, so another run cannot start from them.
        """
        if self._batch_of is None:
            raise ValueError(
                "ProposalBank.seedable needs the loader's batches (ProposalBank(batches=...)): "
                "without them a frame's proposals depend on the order batches arrive in"
            )
        return {(key[1], key[2]): rows for key, rows in self._frames.items()}

    def frame(self, sequence_name: str, sample_idx: int) -> np.ndarray:
        """The proposals ``(R, 11)`` of a frame, in its own vehicle frame (computed with the
        frames of its :meth:`rpn_batch` if not banked)."""
        key = self.key(sequence_name, sample_idx)
        rows = self._frames.get(key)
        if rows is not None:
            self.hits += 1
            return rows
        frames = self.rpn_batch(sequence_name, sample_idx)
        samples = [self.dataset.frame_sample(seq, idx) for seq, idx in frames]
        batch = load_data_to_device(self.dataset.collate_batch(samples), self.device)
        return self._propose(frames, batch)[frames.index((str(sequence_name), int(sample_idx)))]

    def attach(self, batch: Mapping, batch_dev: Mapping) -> dict:
        """``batch_dev`` plus ``roi_boxes`` ``(B, R, 11)``, ``roi_history`` ``(B, N, 12)`` and
        ``roi_history_frames`` ``(B,)`` (on the device) for its samples; ``batch`` is the same
        batch on the host (its ``sequence_name``, ``sample_idx``)."""
        frames = [(str(seq), int(idx)) for seq, idx in zip(batch["sequence_name"],
                                                            batch["sample_idx"])]  # fmt: skip
        keys = [self.key(seq, idx) for seq, idx in frames]
        if self._batch_of is not None and tuple(frames) != self.rpn_batch(*frames[0]):
            raise ValueError(
                f"ProposalBank: the loader's batch {frames} is not one of the batches the bank "
                f"was given (frame {frames[0]} is in {self.rpn_batch(*frames[0])})"
            )
        if all(k not in self._frames for k in keys) and len(set(keys)) == len(keys):
            self._propose(frames, batch_dev)
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
