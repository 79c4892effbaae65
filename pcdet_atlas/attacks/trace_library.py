"""The trace library of recorded vehicles replayed by point injection (docs/attacks.md).

For every annotated vehicle track of a split, the points inside its box are gathered over the
whole sequence in the **canonical box frame** (box centre at the origin, heading along +x, z up),
with each point's raw intensity and elongation and its *source range* (distance from the TOP
sensor origin when it was recorded), plus the track's box size. Aggregating over frames keeps
the real range-dependent sparsity, self-occlusion and intensity statistics of a LiDAR vehicle.

One file (``.npz``, no pickle) holds the whole library::

    points      (P, 3) float32   canonical xyz of all traces, concatenated
    intensity   (P,)   float32   raw intensity (as in the .npy frames, before tanh)
    elongation  (P,)   float32   raw elongation
    src_range   (P,)   float32   range from the sensor origin at recording time, m
    offsets     (K+1,) int64     trace k owns rows offsets[k]:offsets[k+1]
    box_size    (K, 3) float32   [l, w, h] (median over the frames used), m
    sequence    (K,)   str       source sequence name
    obj_id      (K,)   str       source object id
    num_frames  (K,)   int64     frames that contributed points
    build_info  ()     str       JSON: split, filters, data root, sensor origin, seed

Built by ``tools/data/build_trace_library.py`` from the *train* split with filters taken from the
``TRACE_LIBRARY`` section of an injection attack YAML.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pcdet_atlas.config import ConfigError, cfg_from_list, cfg_from_yaml_file, key_source
from pcdet_atlas.config_values import config_files, read_section, setting
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.ops.boxes import points_in_boxes_mask
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.utils.common import write_atomic
from pcdet_atlas.utils.paths import UnsafePathError, regular_file, resolve_under, safe_component
from pcdet_atlas.utils.safe_pickle import load_pickle
from pcdet_atlas.utils.seeding import numpy_generator

__all__ = [
    "Trace",
    "TraceLibrary",
    "TraceFilter",
    "build_trace_library",
    "library_file",
    "write_trace_library",
]


@dataclass(frozen=True)
class Trace:
    """One recorded vehicle in its canonical box frame.

    Attributes:
        xyz: ``(P, 3)`` float32 canonical points, m.
        intensity, elongation, src_range: ``(P,)`` float32 (raw, raw, m).
        box_size: ``(3,)`` float32 ``[l, w, h]``, m.
    """

    xyz: np.ndarray
    intensity: np.ndarray
    elongation: np.ndarray
    src_range: np.ndarray
    box_size: np.ndarray
    sequence: str
    obj_id: str

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class TraceFilter:
    """Which tracks and frames enter the library.

    Args:
        classes: object classes kept (default Vehicle).
        min_points: fewest aggregated points for a track to be kept.
        min_points_per_frame: a frame's box contributes only if it holds at least this many.
        min_frames: fewest contributing frames for a track to be kept.
        range_m: ``(lo, hi)`` band of the box centre's range from the sensor origin (m) for a
            frame to contribute.
        max_points_per_trace: cap; larger traces are subsampled without replacement.
        seed: seed of that subsampling.
    """

    classes: tuple[str, ...] = setting(
        ("Vehicle",),
        choices=wf.WAYMO_CLASSES,
        check=len,
        expected=f"a non-empty list of classes of {wf.WAYMO_CLASSES}, e.g. [Vehicle]",
        doc="classes gathered",
    )
    min_points: int = setting(
        200, ge=1, expected="a positive integer", doc="fewest aggregated points per track"
    )
    min_points_per_frame: int = setting(
        10, ge=1, expected="a positive integer", doc="fewest points for a frame to contribute"
    )
    min_frames: int = setting(
        1, ge=1, expected="a positive integer", doc="fewest contributing frames"
    )
    range_m: tuple[float, float] = setting(
        (5.0, 50.0),
        check=lambda b: 0 <= b[0] < b[1],
        expected="[lo, hi], two finite numbers with 0 <= lo < hi (m)",
        doc="box-centre range band of contributing frames, m",
    )
    max_points_per_trace: int = setting(
        4000, ge=1, expected="a positive integer", doc="cap (deterministic subsample)"
    )
    seed: int = setting(0, doc="seed of that subsample")
    path: str = setting(
        "atlas_trace_library.npz",
        compare=False,
        doc="library file; relative = under the dataset root",
    )
    split: str = setting("train", compare=False, doc="split the library is built from")

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> TraceFilter:
        """Read a ``TRACE_LIBRARY`` section (every key optional); ``SPLIT`` names
        ``ImageSets/<SPLIT>.txt``, so it must be one safe file name (``UnsafePathError``)."""
        out = read_section(cls, cfg, "TRACE_LIBRARY")
        safe_component(out.split, "TRACE_LIBRARY.SPLIT", key_source(cfg or {}, "SPLIT"))
        if out.max_points_per_trace < out.min_points:
            raise ConfigError(
                f"TRACE_LIBRARY (from {config_files(cfg)}): need MIN_POINTS <= "
                f"MAX_POINTS_PER_TRACE, got {out.min_points}, {out.max_points_per_trace}"
            )
        return out

    def to_dict(self) -> dict:
        return {
            "classes": list(self.classes),
            "min_points": int(self.min_points),
            "min_points_per_frame": int(self.min_points_per_frame),
            "min_frames": int(self.min_frames),
            "range_m": [float(v) for v in self.range_m],
            "max_points_per_trace": int(self.max_points_per_trace),
            "seed": int(self.seed),
        }


class TraceLibrary:
    """The concatenated traces with their offsets (see the module docstring for the arrays)."""

    ARRAYS = ("points", "intensity", "elongation", "src_range", "offsets", "box_size")

    def __init__(
        self,
        points: np.ndarray,
        intensity: np.ndarray,
        elongation: np.ndarray,
        src_range: np.ndarray,
        offsets: np.ndarray,
        box_size: np.ndarray,
        sequence: Iterable[str],
        obj_id: Iterable[str],
        num_frames: np.ndarray,
        build_info: Mapping | None = None,
        path: str | Path | None = None,
    ):
        self.points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        self.intensity = np.asarray(intensity, dtype=np.float32).reshape(-1)
        self.elongation = np.asarray(elongation, dtype=np.float32).reshape(-1)
        self.src_range = np.asarray(src_range, dtype=np.float32).reshape(-1)
        self.offsets = np.asarray(offsets, dtype=np.int64).reshape(-1)
        self.box_size = np.asarray(box_size, dtype=np.float32).reshape(-1, 3)
        self.sequence = np.asarray(list(sequence), dtype=str)
        self.obj_id = np.asarray(list(obj_id), dtype=str)
        self.num_frames = np.asarray(num_frames, dtype=np.int64).reshape(-1)
        self.build_info = dict(build_info or {})
        self.path = None if path is None else str(path)
        self._check()

    def _check(self) -> None:
        where = self.path or "trace library"
        p, k = self.points.shape[0], self.box_size.shape[0]
        if self.offsets.shape != (k + 1,) or self.offsets[0] != 0 or self.offsets[-1] != p:
            raise ValueError(f"{where}: offsets must be (K+1,) from 0 to {p}, got {self.offsets}")
        if (np.diff(self.offsets) <= 0).any():
            raise ValueError(f"{where}: every trace must hold at least one point")
        for name in ("intensity", "elongation", "src_range"):
            if getattr(self, name).shape != (p,):
                raise ValueError(f"{where}: {name} must have {p} entries")
        for name in ("sequence", "obj_id", "num_frames"):
            if getattr(self, name).shape != (k,):
                raise ValueError(f"{where}: {name} must have {k} entries")
        if not np.isfinite(self.points).all() or not (self.box_size > 0).all():
            raise ValueError(f"{where}: non-finite points or non-positive box sizes")

    def __len__(self) -> int:
        return int(self.box_size.shape[0])

    def trace(self, index: int) -> Trace:
        if not 0 <= index < len(self):
            raise IndexError(f"trace {index} outside a library of {len(self)} traces")
        lo, hi = int(self.offsets[index]), int(self.offsets[index + 1])
        return Trace(
            xyz=self.points[lo:hi],
            intensity=self.intensity[lo:hi],
            elongation=self.elongation[lo:hi],
            src_range=self.src_range[lo:hi],
            box_size=self.box_size[index],
            sequence=str(self.sequence[index]),
            obj_id=str(self.obj_id[index]),
        )

    def build_mismatch(
        self, filters: TraceFilter, sensor_origin: Sequence[float]
    ) -> dict[str, tuple[Any, Any]]:
        """``{setting: (stored, wanted)}`` of the build settings (``filters``, ``split``,
        ``sensor_origin``) in which this library differs from the one a variant with ``filters``
        and a LiDAR at ``sensor_origin`` reads (the recorded source ranges of the intensity
        correction are from that origin); empty when it was built for it."""
        want = {"filters": filters.to_dict(), "split": filters.split,
                "sensor_origin": [float(v) for v in sensor_origin]}  # fmt: skip
        stored = {key: self.build_info.get(key) for key in want}
        return {key: (stored[key], want[key]) for key in want if stored[key] != want[key]}

    def trace_sizes(self) -> np.ndarray:
        return np.diff(self.offsets)

    # ------------------------------------------------------------------ io
    def save(self, path: str | Path) -> Path:
        """Write the library atomically as one ``.npz``."""
        path = Path(path)
        arrays = dict(
            points=self.points,
            intensity=self.intensity,
            elongation=self.elongation,
            src_range=self.src_range,
            offsets=self.offsets,
            box_size=self.box_size,
            sequence=self.sequence,
            obj_id=self.obj_id,
            num_frames=self.num_frames,
            build_info=np.array(json.dumps(self.build_info, sort_keys=True)),
        )
        write_atomic(path, lambda f: np.savez(f, **arrays))
        self.path = str(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> TraceLibrary:
        """Read a library written by :meth:`save`; ``path`` must be a regular file (a FIFO or a
        device is an ``UnsafePathError``)."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(
                f"trace library not found: {path}. Build it with "
                "`python tools/data/build_trace_library.py --cfg <injection yaml> "
                "--data_path <root>`"
            )
        regular_file(path, "trace library")
        try:
            with np.load(path, allow_pickle=False) as data:
                expected = (*cls.ARRAYS, "sequence", "obj_id", "num_frames", "build_info")
                missing = [k for k in expected if k not in data]
                unexpected = sorted(set(data.files) - set(expected))
                if missing or unexpected:
                    raise ValueError(
                        f"{path}: not a trace library (missing arrays {missing}, unexpected "
                        f"arrays {unexpected}; expected exactly {list(expected)})"
                    )
                arrays = {k: data[k] for k in data.files}
        except (OSError, EOFError, zipfile.BadZipFile, ValueError) as err:
            if str(path) in str(err):
                raise
            raise ValueError(
                f"{path}: cannot read the trace library (truncated or not a .npz written by "
                f"tools/data/build_trace_library.py; rebuild it): {type(err).__name__}: {err}"
            ) from err
        try:
            info = json.loads(str(arrays.pop("build_info")))
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: build_info is not valid JSON ({err}); rebuild it") from err
        if not isinstance(info, dict):
            raise ValueError(
                f"{path}: build_info must be a JSON object, got {type(info).__name__}; rebuild it"
            )
        try:
            return cls(**arrays, build_info=info, path=path)
        except (TypeError, ValueError) as err:
            if str(path) in str(err):
                raise
            raise ValueError(
                f"{path}: malformed trace library arrays: {type(err).__name__}: {err}"
            ) from err


# ---------------------------------------------------------------------------- building
def _canonical(points_xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    """``(P, 3)`` vehicle-frame points -> the canonical frame of ``box`` (7,)."""
    rel = points_xyz - box[None, :3]
    c, s = np.cos(box[6]), np.sin(box[6])
    x = rel[:, 0] * c + rel[:, 1] * s
    y = -rel[:, 0] * s + rel[:, 1] * c
    return np.stack([x, y, rel[:, 2]], axis=1)


def build_trace_library(
    root_path: str | Path,
    filters: TraceFilter,
    split: str = "train",
    sensor_origin: Iterable[float] = (1.43, 0.0, 2.184),
    tag: str = wf.PROCESSED_DATA_TAG,
    progress: Callable[[Iterable], Iterable] | None = None,
    logger=None,
) -> TraceLibrary:
    """Gather every track of ``filters.classes`` of a split into a :class:`TraceLibrary`.

    Reads the processed Waymo layout directly (per-sequence pkls and raw ``.npy`` frames), so
    intensity and elongation stay raw. A sequence without labels contributes nothing.
    Raises ``ValueError`` if no track passes the filters (an empty library is never written).
    """
    root = Path(root_path)
    origin = np.asarray(list(sensor_origin), dtype=np.float64)
    split_file = wf.image_set_path(root, split, "the split of build_trace_library")
    sequences = wf.read_image_set(split_file)
    if not sequences:
        raise ValueError(f"{split_file}: split {split!r} lists no sequence")
    iterator = progress(sequences) if progress is not None else sequences
    lo_r, hi_r = filters.range_m
    tracks: dict[tuple[str, str], dict] = {}
    for seq in iterator:
        pkl = wf.sequence_pkl_path(root, seq, tag)
        if not pkl.is_file():
            raise FileNotFoundError(f"{pkl}: sequence pkl of {seq} (listed in {split}.txt) missing")
        infos = load_pickle(pkl)
        wf.validate_sequence_infos(infos, pkl)
        for info in infos:
            annos = info.get("annos")
            if annos is None or len(annos["name"]) == 0:
                continue
            names = np.asarray(annos["name"]).astype(str)
            boxes = np.asarray(annos["gt_boxes_lidar"], dtype=np.float64)[:, :7]
            rng = np.linalg.norm(boxes[:, :3] - origin[None], axis=1)
            sel = np.flatnonzero(np.isin(names, filters.classes) & (rng >= lo_r) & (rng <= hi_r))
            if sel.size == 0:
                continue
            idx = info["point_cloud"]["sample_idx"]
            npy = wf.frame_npy_path(root, seq, idx, tag)
            if not npy.is_file():
                raise FileNotFoundError(f"{npy}: frame {idx} of {seq} missing")
            pts = np.load(npy, allow_pickle=False)
            wf.validate_points(pts, npy)
            inside = points_in_boxes_mask(pts[:, :3].astype(np.float64), boxes[sel])  # (S, N)
            for row, b in enumerate(sel):
                mask = inside[row]
                count = int(mask.sum())
                if count < filters.min_points_per_frame:
                    continue
                obj = str(np.asarray(annos["obj_ids"])[b])
                entry = tracks.setdefault(
                    (seq, obj), {"xyz": [], "feat": [], "size": [], "frames": 0}
                )
                p = pts[mask].astype(np.float64)
                entry["xyz"].append(_canonical(p[:, :3], boxes[b]))
                src = np.linalg.norm(p[:, :3] - origin[None], axis=1)
                entry["feat"].append(np.stack([p[:, 3], p[:, 4], src], axis=1))
                entry["size"].append(boxes[b, 3:6])
                entry["frames"] += 1
    xyz_all, feat_all, sizes, seqs, objs, nframes, offsets = [], [], [], [], [], [], [0]
    for (seq, obj), entry in sorted(tracks.items()):
        xyz = np.concatenate(entry["xyz"])
        feat = np.concatenate(entry["feat"])
        if xyz.shape[0] < filters.min_points or entry["frames"] < filters.min_frames:
            continue
        if xyz.shape[0] > filters.max_points_per_trace:
            gen = numpy_generator(filters.seed, "trace_library", seq, obj, "subsample")
            keep = np.sort(gen.permutation(xyz.shape[0])[: filters.max_points_per_trace])
            xyz, feat = xyz[keep], feat[keep]
        xyz_all.append(xyz)
        feat_all.append(feat)
        sizes.append(np.median(np.stack(entry["size"]), axis=0))
        seqs.append(seq)
        objs.append(obj)
        nframes.append(entry["frames"])
        offsets.append(offsets[-1] + xyz.shape[0])
    if not sizes:
        raise ValueError(
            f"no {list(filters.classes)} track of split {split!r} under {root} passes the trace "
            f"filters {filters.to_dict()}"
        )
    feat = np.concatenate(feat_all)
    library = TraceLibrary(
        points=np.concatenate(xyz_all),
        intensity=feat[:, 0],
        elongation=feat[:, 1],
        src_range=feat[:, 2],
        offsets=np.asarray(offsets),
        box_size=np.stack(sizes),
        sequence=seqs,
        obj_id=objs,
        num_frames=np.asarray(nframes),
        build_info={
            "split": split,
            "data_root": str(root),
            "filters": filters.to_dict(),
            "sensor_origin": origin.tolist(),
        },
    )
    if logger is not None:
        logger.info(
            f"trace library: {len(library)} traces, {library.points.shape[0]} points from "
            f"{len(sequences)} sequences of {split}"
        )
    return library


def write_trace_library(
    cfg_path: str | Path,
    data_root: str | Path,
    *,
    set_cfgs: Sequence[str] | None = None,
    out: str | Path | None = None,
    overwrite: bool = False,
    progress: Callable[[Iterable], Iterable] | None = None,
    logger=None,
) -> Path:
    """Build the trace library of the injection YAML at ``cfg_path`` (with the ``KEY VALUE``
    pairs ``set_cfgs``) from the dataset at ``data_root`` and write it; returns the file.

    Filters and split (``SPLIT``, train by default) come from its ``TRACE_LIBRARY`` section, the
    sensor origin from its ``LIDAR`` section; the file is ``out`` if given, else
    ``TRACE_LIBRARY.PATH`` (relative: under ``data_root``). Every injection variant naming that
    file shares it, so an existing library built with other filters (or another split, or
    another ``LIDAR.ORIGIN``) is not replaced unless ``overwrite``: a ``FileExistsError`` names
    both builds.
    """
    cfg = cfg_from_yaml_file(cfg_path)
    if set_cfgs:
        cfg_from_list(list(set_cfgs), cfg)
    if "TRACE_LIBRARY" not in cfg:
        raise ConfigError(f"{cfg_path}: no TRACE_LIBRARY section (not an injection attack?)")
    filters = TraceFilter.from_config(cfg.TRACE_LIBRARY)
    root = Path(data_root)
    if out is not None:  # the caller's (--out) choice: anywhere
        out = Path(out) if Path(out).is_absolute() else root / out
    else:
        out = library_file(filters.path, root, key_source(cfg.TRACE_LIBRARY, "PATH"), write=True)
    lidar = LidarModel.from_config(cfg.get("LIDAR"))
    if out.is_file() and not overwrite:
        check_same_build(out, filters, list(lidar.origin_xyz))
    library = build_trace_library(
        root, filters, split=filters.split, sensor_origin=lidar.origin.tolist(),
        progress=progress, logger=logger,
    )  # fmt: skip
    library.save(out)
    if logger is not None:
        sizes = library.trace_sizes()
        logger.info(
            f"wrote {out}: {len(library)} traces, points per trace min/median/max "
            f"{sizes.min()}/{int(np.median(sizes))}/{sizes.max()}"
        )
    return out


def library_file(value: str, root: str | Path, source: str, *, write: bool = False) -> Path:
    """The file ``TRACE_LIBRARY.PATH`` = ``value`` (from ``source``) names. A relative ``value``
    lies under ``root`` (:func:`~pcdet_atlas.utils.paths.resolve_under`: no ``..``, symlinks
    resolved). An absolute one is read as it is but never written (``write``): a YAML does not
    make a tool create a file outside the dataset root; ``--out`` does. An existing file must be
    a regular one (it is hashed and loaded: a FIFO or a device would never end)."""
    if Path(value).is_absolute():
        if write:
            raise UnsafePathError(
                f"TRACE_LIBRARY.PATH {value!r} (from {source}) is absolute: a library is written "
                f"under the dataset root {root} (a relative PATH), or where --out says"
            )
        path = Path(value)
    else:
        path = resolve_under(root, value, "TRACE_LIBRARY.PATH", source)
    if path.exists():
        regular_file(path, f"TRACE_LIBRARY.PATH (from {source})")
    return path


def check_same_build(path: Path, filters: TraceFilter, sensor_origin: list[float]) -> None:
    """Refuse to replace the library at ``path`` when it was built with other filters, split or
    sensor origin: the injection variants that share it would stop loading (or, read by an older
    copy of their YAML, run on other traces)."""
    differs = TraceLibrary.load(path).build_mismatch(filters, sensor_origin)
    if differs:
        have = {key: pair[0] for key, pair in differs.items()}
        want = {key: pair[1] for key, pair in differs.items()}
        raise FileExistsError(
            f"{path} holds a trace library built with {have}, not {want}; every injection variant "
            "whose TRACE_LIBRARY.PATH names this file shares it. Write this one elsewhere (--out, "
            "or another TRACE_LIBRARY.PATH in its YAML) or pass --overwrite to replace it"
        )
