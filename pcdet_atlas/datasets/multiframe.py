"""Multi-frame input (OpenPCDet's ``SEQUENCE_CONFIG``): which history frames, and how their
points are moved into the current vehicle frame.

For frame ``t`` with ``SAMPLE_OFFSET = [-k, 0]`` the history is ``t-1, ..., t-k``, clipped at 0
(so early frames repeat frame 0, and the lag is still ``0.1 * (t - clipped index)`` s). A
history point goes vehicle(t-j) -> global -> vehicle(t) through the frames' poses.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import read_section, setting

__all__ = [
    "SequenceSettings",
    "SequenceConfig",
    "history_sample_indices",
    "relative_pose",
    "outside_ego_mask",
    "transform_points_to_frame",
    "transform_points_into",
    "row_records",
    "copy_rows",
    "compress_rows",
    "rows_except",
    "copy_rows_except",
]

SECONDS_PER_FRAME = 0.1


@dataclass(frozen=True, kw_only=True)
class SequenceSettings:
    """The ``DATA_CONFIG.SEQUENCE_CONFIG`` section."""

    enabled: bool = setting(False, doc="multi-frame samples")
    sample_offset: tuple[int, int] = setting(
        (-3, 0),
        check=lambda o: o[0] <= 0 and o[1] == 0,
        expected="[-k, 0] with k >= 0",
        doc="frames [-k, 0] of a sample",
    )
    onehot_timestamp: bool = setting(False, doc="one column per frame instead of the lag")


class SequenceConfig:
    """``SEQUENCE_CONFIG``: ``ENABLED``, ``SAMPLE_OFFSET [-k, 0]``, ``ONEHOT_TIMESTAMP``."""

    CONFIG = SequenceSettings

    def __init__(
        self,
        sample_offset: Sequence[int] = SequenceSettings.sample_offset,
        onehot_timestamp: bool = SequenceSettings.onehot_timestamp,
    ):
        if len(sample_offset) != 2 or int(sample_offset[0]) > 0 or int(sample_offset[1]) != 0:
            raise ConfigError(
                f"SEQUENCE_CONFIG.SAMPLE_OFFSET must be [-k, 0] with k >= 0, got {sample_offset!r}"
            )
        self.sample_offset = (int(sample_offset[0]), 0)
        self.onehot_timestamp = bool(onehot_timestamp)

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> SequenceConfig | None:
        """``None`` when the section is absent or ``ENABLED`` is false."""
        if cfg is None:
            return None
        return cls.from_settings(read_section(cls.CONFIG, cfg, "DATA_CONFIG.SEQUENCE_CONFIG"))

    @classmethod
    def from_settings(cls, settings: SequenceSettings | None) -> SequenceConfig | None:
        """``None`` when the section is absent or not enabled."""
        if settings is None or not settings.enabled:
            return None
        return cls(settings.sample_offset, settings.onehot_timestamp)

    @property
    def num_frames(self) -> int:
        return 1 - self.sample_offset[0]

    @property
    def num_extra_columns(self) -> int:
        """Columns added to the 5 point features: the lag, or one one-hot column per frame."""
        return self.num_frames if self.onehot_timestamp else 1


def history_sample_indices(sample_idx: int, sample_offset: Sequence[int]) -> np.ndarray:
    """``(k,)`` int64 history indices, nearest first, clipped at 0 (OpenPCDet's order)."""
    offsets = np.arange(int(sample_offset[0]), int(sample_offset[1]))
    return np.clip(sample_idx + offsets, 0, 0x7FFFFFFF)[::-1].astype(np.int64)


def relative_pose(pose_src: np.ndarray, pose_dst: np.ndarray) -> np.ndarray:
    """4x4 float64 transform vehicle(src) -> vehicle(dst) from vehicle->global poses."""
    src = np.asarray(pose_src, dtype=np.float64).reshape(4, 4)
    dst = np.asarray(pose_dst, dtype=np.float64).reshape(4, 4)
    return np.linalg.inv(dst) @ src


def transform_points_to_frame(
    xyz: np.ndarray, pose_src: np.ndarray, pose_dst: np.ndarray
) -> np.ndarray:
    """``(N, 3)`` points in vehicle(src) -> ``(N, 3)`` float64 in vehicle(dst)."""
    t = relative_pose(pose_src, pose_dst)
    x, y, z = (np.asarray(xyz[:, i], dtype=np.float64) for i in range(3))
    # column-wise: several times faster than an (N, 3) @ (3, 3) matmul, same float64 result
    return np.stack([t[r, 0] * x + t[r, 1] * y + t[r, 2] * z + t[r, 3] for r in range(3)], axis=1)


def outside_ego_mask(xyz: np.ndarray, center_radius: float = 1.0) -> np.ndarray:
    """``(N,)`` bool, False for points with ``|x| < r`` and ``|y| < r`` (m): the ego's own
    returns, which OpenPCDet's ``remove_ego_points`` drops from history frames."""
    return ~((np.abs(xyz[:, 0]) < center_radius) & (np.abs(xyz[:, 1]) < center_radius))


def transform_points_into(
    xyz: np.ndarray, transform: np.ndarray, out: np.ndarray, ego_radius: float | None = None
) -> np.ndarray | None:
    """Apply a 4x4 transform to ``(N, 3)`` points, writing the result into ``out`` ``(N, 3)``
    (any float dtype, e.g. three columns of a float32 stacked array) without temporaries.

    The arithmetic is that of :func:`transform_points_to_frame` (float64, ``t[r, 0] * x +
    t[r, 1] * y + t[r, 2] * z + t[r, 3]`` left to right), so the stored values are the same
    bits as casting its result to ``out.dtype``.

    Returns:
        with ``ego_radius``, the ``(N,)`` bool of :func:`outside_ego_mask` evaluated on the
        float64 result (before any cast); else ``None``.
    """
    t = np.asarray(transform, dtype=np.float64).reshape(4, 4)
    n = xyz.shape[0]
    x, y, z = (np.asarray(xyz[:, i], dtype=np.float64) for i in range(3))
    acc, tmp = np.empty(n), np.empty(n)
    near = None
    for r in range(3):
        np.multiply(x, t[r, 0], out=acc)
        np.multiply(y, t[r, 1], out=tmp)
        acc += tmp
        np.multiply(z, t[r, 2], out=tmp)
        acc += tmp
        acc += t[r, 3]
        if ego_radius is not None and r < 2:
            inside = np.less(np.abs(acc, out=tmp), ego_radius)
            near = inside if near is None else np.logical_and(near, inside, out=near)
        out[:, r] = acc
    return None if near is None else ~near


def row_records(array: np.ndarray) -> np.ndarray | None:
    """The rows of a 2-D array as a 1-D array of opaque records (a view, no copy), or ``None``
    when its last axis is not contiguous. Its rows may be strided, e.g. the first columns of a
    frame file's rows: numpy then moves each row as one block instead of element by element
    (docs/benchmarks.md, "Data loading")."""
    if array.ndim != 2 or array.shape[1] == 0 or array.strides[1] != array.itemsize:
        return None
    return array.view(np.dtype((np.void, array.shape[1] * array.itemsize)))[:, 0]


def _from_records(records: np.ndarray, like: np.ndarray) -> np.ndarray:
    return records.view(like.dtype).reshape(-1, like.shape[1])


def copy_rows(array: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of a 2-D array, row by row as records when its last axis is
    contiguous."""
    records = row_records(array)
    if records is None:
        return np.array(array, order="C")
    return _from_records(np.array(records), array)


def compress_rows(mask: np.ndarray, array: np.ndarray) -> np.ndarray:
    """``array[mask]`` for a 2-D ``array``, gathering whole rows as opaque records when its
    last axis is contiguous (several times faster than numpy's element-wise 2-D boolean
    indexing); a C-contiguous result."""
    records = row_records(array)
    return array[mask] if records is None else _from_records(records[mask], array)


#: Above this many runs of dropped rows, one masked copy beats copying the blocks between them
#: (each block copy has a fixed call cost; the mask's cost follows the frame's rows).
_MAX_RUN_COPIES = 64


def rows_except(points: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """``points`` without the ascending row indices ``drop``, a new C-contiguous array: block
    copies of the rows between runs of consecutive dropped rows (a removal sector is a few
    dozen runs, one or two per beam), or one masked copy when there are many runs (a phantom
    occludes a few hundred scattered points). ``points`` may be a strided view (e.g. the first
    columns of a frame file's rows); rows move as opaque records (:func:`row_records`)."""
    blocks = _kept_blocks(points.shape[0], drop)
    if blocks is None:
        return _masked_except(points, drop)
    out = np.empty((points.shape[0] - drop.size, points.shape[1]), dtype=points.dtype)
    _copy_blocks(points, blocks, out)
    return out


def copy_rows_except(points: np.ndarray, drop: np.ndarray, out: np.ndarray) -> None:
    """``out[:] = points`` without the ascending row indices ``drop`` (:func:`rows_except`
    into a given array)."""
    blocks = _kept_blocks(points.shape[0], drop)
    if blocks is None:
        out[:] = _masked_except(points, drop)
    else:
        _copy_blocks(points, blocks, out)


def _masked_except(points: np.ndarray, drop: np.ndarray) -> np.ndarray:
    keep = np.ones(points.shape[0], dtype=bool)
    keep[drop] = False
    return compress_rows(keep, points)


def _kept_blocks(num_rows: int, drop: np.ndarray) -> list[tuple[int, int]] | None:
    """``(start, stop)`` of the blocks of rows between the runs of ascending ``drop``, or
    ``None`` beyond ``_MAX_RUN_COPIES`` runs."""
    if drop.size == 0:
        return [(0, num_rows)]
    breaks = (np.diff(drop) != 1).nonzero()[0]  # last dropped row of each run but the last
    if breaks.size + 1 > _MAX_RUN_COPIES:
        return None
    starts = drop[np.concatenate([[0], breaks + 1])].tolist()  # first row of each run
    stops = (drop[np.concatenate([breaks, [drop.size - 1]])] + 1).tolist()
    return [*zip([0, *stops[:-1]], starts), (stops[-1], num_rows)]


def _copy_blocks(points: np.ndarray, blocks: list[tuple[int, int]], out: np.ndarray) -> None:
    src, dst = row_records(points), row_records(out)
    if src is None or dst is None:
        src, dst = points, out
    np.concatenate([src[a:b] for a, b in blocks], axis=0, out=dst)
