"""Fit a :class:`LidarModel` from a sequence's TOP-LiDAR points (docs/attacks.md): the reading
of the frames; the fit itself is :mod:`pcdet_atlas.ops.beam_fit`.

OpenPCDet's ``.npy`` frames do not keep the per-frame calibration, so the real 64 TOP inclinations
are estimated from the points themselves: the first ``num_points_of_each_lidar[0]`` rows of each
frame are the TOP returns (both returns, vehicle frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcdet_atlas.datasets.waymo_format import (
    PROCESSED_DATA_TAG,
    frame_npy_path,
    load_frame_points,
    load_sequence_infos,
    sequence_pkl_path,
)
from pcdet_atlas.ops.beam_fit import FitReport, estimate_azimuth_bins, fit_report
from pcdet_atlas.ops.lidar_model import WAYMO_AZIMUTH_BINS, WAYMO_TOP_ORIGIN, LidarModel

__all__ = ["top_lidar_points", "sequence_top_points", "fit_lidar_from_sequence", "SequenceFit"]


def top_lidar_points(points: np.ndarray, info: dict, where: str) -> np.ndarray:
    """The TOP rows ``(n_TOP, C)`` of a frame's ``(N, C)`` points, checked against the info.

    In a frame written by ``tools/data/generate_atlas.py`` the TOP count includes the
    ``info['atlas']['num_injected_rows']`` phantom rows, which are the last rows of the file.
    """
    counts = info.get("num_points_of_each_lidar")
    if counts is None or len(counts) == 0:
        raise ValueError(f"{where}: frame info has no 'num_points_of_each_lidar'")
    if sum(int(c) for c in counts) != points.shape[0]:
        raise ValueError(
            f"{where}: num_points_of_each_lidar sums to {sum(map(int, counts))} but the frame "
            f"has {points.shape[0]} points"
        )
    injected = int(info.get("atlas", {}).get("num_injected_rows", 0))
    if not 0 <= injected <= int(counts[0]):
        raise ValueError(
            f"{where}: atlas.num_injected_rows = {injected}: expected 0 to the TOP count "
            f"{int(counts[0])}"
        )
    top = points[: int(counts[0]) - injected]
    return np.concatenate([top, points[points.shape[0] - injected :]]) if injected else top


@dataclass
class SequenceFit:
    """A fitted :class:`LidarModel`, its :class:`FitReport` on the points it was fitted to, and
    the share of azimuth gaps that are whole firing steps (``None`` unless estimated)."""

    lidar: LidarModel
    report: FitReport
    azimuth_share: float | None = None


def sequence_top_points(
    root: str | Path,
    sequence: str,
    frames: Sequence[int] | None = None,
    tag: str = PROCESSED_DATA_TAG,
) -> list[np.ndarray]:
    """The ``(n_f, 3)`` TOP points of some frames of one sequence (default: 10 spread over it)."""
    infos = load_sequence_infos(sequence_pkl_path(root, sequence, tag))
    if not infos:
        raise ValueError(f"{sequence_pkl_path(root, sequence, tag)}: sequence has no frames")
    if frames is None:
        frames = sorted(set(np.linspace(0, len(infos) - 1, num=min(10, len(infos))).astype(int)))
    chunks = []
    for idx in frames:
        if not 0 <= int(idx) < len(infos):
            raise ValueError(f"{sequence}: frame {idx} out of range [0, {len(infos)})")
        path = frame_npy_path(root, sequence, int(idx), tag)
        chunks.append(top_lidar_points(load_frame_points(path), infos[int(idx)], str(path))[:, :3])
    return chunks


def fit_lidar_from_sequence(
    root: str | Path,
    sequence: str,
    frames: Sequence[int] | None = None,
    max_points: int = 400_000,
    origin: Sequence[float] = WAYMO_TOP_ORIGIN,
    tag: str = PROCESSED_DATA_TAG,
    num_beams: int = 64,
    offsets: str = "auto",
    azimuth_bins: int | str | None = None,
    **kwargs,
) -> SequenceFit:
    """Fit the sensor model from the TOP points of some frames of one sequence.

    Args:
        root: dataset root (the folder holding ``ImageSets`` and ``tag``).
        sequence: sequence name (folder under ``tag``).
        frames: sample indices to use; default: 10 frames spread over the sequence.
        max_points: at most this many points are used (evenly strided, deterministic).
        origin: sensor position in the vehicle frame, metres.
        num_beams, offsets: see :meth:`LidarModel.fit`.
        azimuth_bins: firings per turn, ``"estimate"`` (from the beams' azimuth gaps, frame by
            frame) or ``None`` (the paper's 2651).
        **kwargs: passed to :class:`LidarModel` (``max_range``).
    """
    chunks = sequence_top_points(root, sequence, frames, tag)
    pts = np.concatenate(chunks)
    if pts.shape[0] > max_points:
        pts = pts[:: int(np.ceil(pts.shape[0] / max_points))]
    estimate = azimuth_bins == "estimate"
    if estimate or azimuth_bins is None:
        azimuth_bins = WAYMO_AZIMUTH_BINS
    lidar = LidarModel.fit(
        pts, num_beams, origin, offsets=offsets, azimuth_bins=int(azimuth_bins), **kwargs
    )
    share = None
    if estimate:
        bins, share = estimate_azimuth_bins(chunks, lidar)
        lidar = LidarModel(lidar.inclinations, bins, origin, lidar.max_range, offsets=lidar.offsets)
    return SequenceFit(lidar, fit_report(lidar, pts), share)
