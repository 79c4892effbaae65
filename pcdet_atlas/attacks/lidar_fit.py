"""Fit a :class:`LidarModel` beam table from a sequence's TOP-LiDAR points (docs/attacks.md).

OpenPCDet's ``.npy`` frames do not keep the per-frame calibration, so the real 64 TOP inclinations
are estimated from the points themselves: the first ``num_points_of_each_lidar[0]`` rows of each
frame are the TOP returns (both returns, vehicle frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pcdet_atlas.datasets.waymo_format import (
    PROCESSED_DATA_TAG,
    frame_npy_path,
    load_frame_points,
    load_sequence_infos,
    sequence_pkl_path,
)
from pcdet_atlas.ops.lidar_model import WAYMO_TOP_ORIGIN, LidarModel

__all__ = ["top_lidar_points", "fit_lidar_from_sequence"]


def top_lidar_points(points: np.ndarray, info: dict, where: str) -> np.ndarray:
    """The TOP rows ``(n_TOP, C)`` of a frame's ``(N, C)`` points, checked against the info.

    In a frame written by ``tools/generate_atlas.py`` the TOP count includes the
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


def fit_lidar_from_sequence(
    root: str | Path,
    sequence: str,
    frames: Sequence[int] | None = None,
    max_points: int = 400_000,
    origin: Sequence[float] = WAYMO_TOP_ORIGIN,
    tag: str = PROCESSED_DATA_TAG,
    **kwargs,
) -> LidarModel:
    """Fit the beam table from the TOP points of some frames of one sequence.

    Args:
        root: dataset root (the folder holding ``ImageSets`` and ``tag``).
        sequence: sequence name (folder under ``tag``).
        frames: sample indices to use; default: 10 frames spread over the sequence.
        max_points: at most this many points are used (evenly strided, deterministic).
        origin: sensor position in the vehicle frame, metres.
        **kwargs: passed to :class:`LidarModel` (``azimuth_bins``, ``max_range``).
    """
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
    pts = np.concatenate(chunks)
    if pts.shape[0] > max_points:
        pts = pts[:: int(np.ceil(pts.shape[0] / max_points))]
    return LidarModel.fit(pts, origin=origin, **kwargs)
