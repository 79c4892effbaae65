"""GT sampling ("copy-paste") from a GT database, with OpenPCDet's semantics.

The database (``tools/data/create_gt_database.py``, :mod:`pcdet_atlas.datasets.gt_database`) is a
pickle ``{class_name: [db_info, ...]}`` plus the object points, either one ``.bin`` per object
(``db_info['path']``, relative to the data root) or one stacked ``*_global.npy`` indexed by
``db_info['global_data_offset']`` (``USE_SHARED_MEMORY: True``; read through a memory map, so
the OS page cache shares it between workers). Per frame:

1. for each class of ``SAMPLE_GROUPS`` draw ``n`` database objects without replacement, with
   ``n = target - (GT boxes of that class in the frame)`` under ``LIMIT_WHOLE_SCENE``;
2. keep a sampled box only if its BEV overlap is zero with every existing box and with every
   other sampled box (a colliding pair loses both, as OpenPCDet);
3. remove the scene points inside the kept boxes (enlarged by ``REMOVE_EXTRA_WIDTH``) and
   prepend the objects' points (moved to their box centre).

Multi-frame databases carry a time-lag column; ``FILTER_OBJ_POINTS_BY_TIMESTAMP`` keeps the
object points whose lag is inside ``TIME_RANGE``, and a single-frame scene given a multi-frame
database keeps only lag-0 points and drops the column.

Deliberate difference: OpenPCDet walks a shuffled pointer through the database (state shared by
the calls of one worker); here each frame draws from a generator keyed by (seed, epoch, frame),
so the samples do not depend on worker count or loading order.
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import setting, unsupported
from pcdet_atlas.datasets.augmentor.base import read_transform_config
from pcdet_atlas.datasets.augmentor.box_ops import box_index_of_points, enlarge_boxes
from pcdet_atlas.datasets.multiframe import compress_rows
from pcdet_atlas.datasets.waymo_format import WAYMO_CLASSES, WaymoFormatError
from pcdet_atlas.ops.boxes import boxes_bev_overlap
from pcdet_atlas.registry import TRANSFORMS
from pcdet_atlas.utils.paths import regular_file, relative_parts, resolve_under
from pcdet_atlas.utils.safe_pickle import load_pickle

__all__ = ["GTSampling", "parse_class_counts"]

DB_INFO_KEYS = ("name", "path", "box3d_lidar", "num_points_in_gt", "difficulty")
#: Class names a per-class entry may hold besides ``class_names``: Waymo's object classes.
OBJECT_CLASSES = tuple(name for name in WAYMO_CLASSES if name != "unknown")


def parse_class_counts(items: Sequence[str], key: str) -> dict[str, int]:
    """``['Vehicle:15', 'Pedestrian:10']`` -> ``{'Vehicle': 15, 'Pedestrian': 10}``."""
    out = {}
    for item in items:
        name, sep, count = str(item).partition(":")
        if not sep or not count.strip().lstrip("-").isdigit():
            raise ConfigError(f"gt_sampling.{key}: expected 'ClassName:count', got {item!r}")
        out[name.strip()] = int(count)
    return out


def _trained_classes(
    counts: Mapping[str, int], key: str, class_names: Sequence[str], section: str, logger
) -> dict[str, int]:
    """The entries of ``counts`` whose class is trained; other Waymo classes are logged and left
    out, any other name is an error."""
    unknown = [name for name in counts if name not in class_names and name not in OBJECT_CLASSES]
    if unknown:
        raise ConfigError(
            f"gt_sampling.{key} ({section}): {unknown} is not a class name; expected one of "
            f"the Waymo classes {list(OBJECT_CLASSES)}"
        )
    ignored = [name for name in counts if name not in class_names]
    if ignored:
        logger.info(
            f"gt_sampling.{key} ({section}): {ignored} not in CLASS_NAMES {list(class_names)}; "
            f"left out"
        )
    return {name: count for name, count in counts.items() if name in class_names}


@dataclass(frozen=True, kw_only=True)
class PrepareConfig:
    filter_by_min_points: tuple[str, ...] = setting(
        (), key="filter_by_min_points", doc="'Class:n': fewest points of a database object"
    )
    filter_by_difficulty: tuple[int, ...] = setting(
        (), key="filter_by_difficulty", doc="database difficulties dropped"
    )


@dataclass(frozen=True, kw_only=True)
class BackupDbInfoConfig:
    db_info_path: str = setting(doc="dbinfos pickle used when DB_INFO_PATH is missing")
    db_data_path: str = setting(doc="its stacked _global.npy")
    num_point_features: int = setting(ge=1, doc="its point columns")


@dataclass(frozen=True, kw_only=True)
class GTSamplingConfig:
    db_info_path: tuple[str, ...] = setting(doc="dbinfos pickles, relative to DATA_PATH")
    db_data_path: tuple[str, ...] | None = setting((), doc="one stacked _global.npy per pickle")
    backup_db_info: BackupDbInfoConfig | None = setting(None, doc="used when the first is missing")
    use_shared_memory: bool = setting(False, doc="read the _global.npy through a memory map")
    prepare: PrepareConfig | None = setting(None, doc="database filters")
    sample_groups: tuple[str, ...] = setting(doc="'Class:n': objects wanted per frame")
    num_point_features: int = setting(ge=1, doc="columns of the stored object points")
    remove_extra_width: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0), doc="m added to pasted boxes when clearing scene points"
    )
    limit_whole_scene: bool = setting(False, doc="count the frame's own objects")
    filter_obj_points_by_timestamp: bool = setting(False, doc="keep object points in TIME_RANGE")
    time_range: tuple[float, float] | None = setting(None, doc="[t0, t1] lag range, s")
    use_road_plane: bool = unsupported("Waymo has no road planes")
    database_with_fakelidar: bool = unsupported("a fake-LiDAR database is not supported")


@TRANSFORMS.register("gt_sampling")
class GTSampling:
    """Paste objects from a GT database into the scene (see the module docstring)."""

    CONFIG = GTSamplingConfig

    def __init__(
        self,
        root_path: str | Path,
        class_names: Sequence[str],
        db_info_paths: Sequence[str | Path],
        sample_groups: Mapping[str, int],
        num_point_features: int,
        db_data_paths: Sequence[str | Path] = (),
        use_shared_memory: bool = GTSamplingConfig.use_shared_memory,
        min_points: Mapping[str, int] | None = None,
        removed_difficulty: Sequence[int] = (),
        remove_extra_width: Sequence[float] = GTSamplingConfig.remove_extra_width,
        limit_whole_scene: bool = GTSamplingConfig.limit_whole_scene,
        filter_obj_points_by_timestamp: bool = GTSamplingConfig.filter_obj_points_by_timestamp,
        time_range: Sequence[float] | None = GTSamplingConfig.time_range,
        logger=None,
        section: str = "<unknown>",
    ):
        """
        Args:
            root_path: data root; database paths are relative to it and stay under it (an
                absolute path or a ``..`` part is an ``UnsafePathError``, in the info files too).
            class_names: classes the detector trains on (database classes outside are ignored).
            db_info_paths: dbinfos pickles (``{class: [db_info]}``), merged.
            sample_groups: class -> number of objects wanted per frame.
            num_point_features: columns of the stored object points (5, or 6 with time lag).
            db_data_paths: the stacked ``_global.npy`` per info file (``use_shared_memory``).
            min_points: class -> minimum ``num_points_in_gt`` of a database object.
            removed_difficulty: database objects with these difficulties are dropped.
            remove_extra_width: (3,) m added to the pasted boxes when clearing scene points.
            limit_whole_scene: subtract the frame's own GT count from each class target.
            filter_obj_points_by_timestamp / time_range: keep object points with lag in range (s).
            section: where the config item sits (for error messages).

        A class of ``sample_groups`` / ``min_points`` that is neither in ``class_names`` nor a
        Waymo object class (a typo) is a :class:`ConfigError`; a Waymo class not trained is
        ignored, and logged.
        """
        logger = logger if logger is not None else logging.getLogger(__name__)
        self.root_path = Path(root_path)
        self.class_names = list(class_names)
        self.num_point_features = int(num_point_features)
        self.use_shared_memory = bool(use_shared_memory)
        self.remove_extra_width = np.asarray(remove_extra_width, dtype=np.float64).reshape(3)
        self.limit_whole_scene = bool(limit_whole_scene)
        self.filter_by_time = bool(filter_obj_points_by_timestamp)
        if self.filter_by_time and (time_range is None or len(time_range) != 2):
            raise ConfigError(
                f"gt_sampling: FILTER_OBJ_POINTS_BY_TIMESTAMP needs TIME_RANGE [t0, t1], got "
                f"{time_range!r}"
            )
        self.time_range = tuple(float(t) for t in time_range) if time_range is not None else None
        self.db_info_paths = [
            resolve_under(self.root_path, p, "gt_sampling.DB_INFO_PATH", section)
            for p in db_info_paths
        ]
        self.db_data_paths = [
            resolve_under(self.root_path, p, "gt_sampling.DB_DATA_PATH", section)
            for p in db_data_paths
        ]
        if self.use_shared_memory and len(self.db_data_paths) != len(self.db_info_paths):
            raise ConfigError(
                "gt_sampling: USE_SHARED_MEMORY needs one DB_DATA_PATH per DB_INFO_PATH, got "
                f"{len(self.db_data_paths)} for {len(self.db_info_paths)}"
            )
        trained = (self.class_names, section, logger)
        min_points = _trained_classes(min_points or {}, "PREPARE.filter_by_min_points", *trained)
        sample_groups = _trained_classes(sample_groups, "SAMPLE_GROUPS", *trained)
        self.db_infos = self._load_db_infos()
        for class_name, count in min_points.items():
            self.db_infos[class_name] = [
                x for x in self.db_infos[class_name] if x["num_points_in_gt"] >= count
            ]
        removed = set(int(d) for d in removed_difficulty)
        for class_name in self.db_infos:
            self.db_infos[class_name] = [
                x for x in self.db_infos[class_name] if int(x["difficulty"]) not in removed
            ]
        self.sample_groups = {k: int(v) for k, v in sample_groups.items()}
        sizes = {k: len(v) for k, v in self.db_infos.items()}
        logger.info(f"gt_sampling: database objects per class after PREPARE: {sizes}")
        for class_name in self.sample_groups:
            if not self.db_infos.get(class_name):
                logger.warning(
                    f"gt_sampling: no database objects of class {class_name!r} in "
                    f"{[str(p) for p in self.db_info_paths]}; nothing of it will be pasted"
                )
        self._global_data: list[np.ndarray | None] = [None] * len(self.db_data_paths)

    # ------------------------------------------------------------------ config
    @classmethod
    def from_config(
        cls, cfg: Mapping, *, root_path, class_names, logger=None, section="<unknown>", **context
    ) -> GTSampling:
        settings = read_transform_config(cls, cfg, section)
        prepare = settings.prepare or PrepareConfig()
        info_paths = list(settings.db_info_path)
        data_paths = list(settings.db_data_path or ())
        num_features = settings.num_point_features
        backup = settings.backup_db_info
        root = Path(root_path)
        first = resolve_under(root, info_paths[0], "gt_sampling.DB_INFO_PATH", section)
        if backup is not None and not first.exists():
            if len(info_paths) != 1:
                raise ConfigError("gt_sampling: BACKUP_DB_INFO needs exactly one DB_INFO_PATH")
            what = "gt_sampling.BACKUP_DB_INFO.DB_INFO_PATH"
            (logger or logging.getLogger(__name__)).warning(
                f"gt_sampling: {first} not found; using BACKUP_DB_INFO "
                f"{resolve_under(root, backup.db_info_path, what, section)}"
            )
            info_paths = [backup.db_info_path]
            data_paths = [backup.db_data_path]
            num_features = backup.num_point_features
        return cls(
            root_path=root,
            class_names=class_names,
            db_info_paths=info_paths,
            db_data_paths=data_paths,
            sample_groups=parse_class_counts(list(settings.sample_groups), "SAMPLE_GROUPS"),
            num_point_features=num_features,
            use_shared_memory=settings.use_shared_memory,
            min_points=parse_class_counts(
                list(prepare.filter_by_min_points), "PREPARE.filter_by_min_points"
            ),
            removed_difficulty=list(prepare.filter_by_difficulty),
            remove_extra_width=settings.remove_extra_width,
            limit_whole_scene=settings.limit_whole_scene,
            filter_obj_points_by_timestamp=settings.filter_obj_points_by_timestamp,
            time_range=settings.time_range,
            logger=logger,
            section=section,
        )

    # ------------------------------------------------------------------ database
    def _load_db_infos(self) -> dict[str, list[dict]]:
        db_infos: dict[str, list[dict]] = {name: [] for name in self.class_names}
        for data_index, path in enumerate(self.db_info_paths):
            try:
                infos = load_pickle(regular_file(path, "GT database info file"))
            except FileNotFoundError as err:
                raise WaymoFormatError(
                    f"{path}: GT database info file not found (build it with "
                    f"tools/data/create_gt_database.py, or drop gt_sampling from AUG_CONFIG_LIST)"
                ) from err
            except (OSError, EOFError, ValueError, pickle.UnpicklingError) as err:
                raise WaymoFormatError(f"{path}: cannot unpickle GT database infos: {err}") from err
            if not isinstance(infos, dict):
                raise WaymoFormatError(f"{path}: expected {{class: [db_info]}}, got {type(infos)}")
            for class_name in self.class_names:
                entries = infos.get(class_name, [])
                if not isinstance(entries, list):
                    raise WaymoFormatError(
                        f"{path}: {class_name} is a {type(entries).__name__}, expected a list of "
                        "db_info dicts"
                    )
                for j, info in enumerate(entries):
                    if not isinstance(info, dict):
                        raise WaymoFormatError(
                            f"{path}: {class_name}[{j}] is a {type(info).__name__}, expected a "
                            f"db_info dict with keys {list(DB_INFO_KEYS)}"
                        )
                    for key in DB_INFO_KEYS:
                        if key not in info:
                            raise WaymoFormatError(f"{path}: {class_name}[{j}] lacks key {key!r}")
                    # the text only (a database holds millions); the read resolves symlinks
                    relative_parts(info["path"], "path", f"{path} {class_name}[{j}]")
                    if self.use_shared_memory and "global_data_offset" not in info:
                        raise WaymoFormatError(
                            f"{path}: {class_name}[{j}] lacks 'global_data_offset' "
                            f"(needed by USE_SHARED_MEMORY)"
                        )
                    db_infos[class_name].append({**info, "_data_index": data_index})
        return db_infos

    def _global_array(self, data_index: int) -> np.ndarray:
        arr = self._global_data[data_index]
        if arr is None:
            path = self.db_data_paths[data_index]
            try:
                arr = np.load(
                    regular_file(path, "GT database points"), mmap_mode="r", allow_pickle=False
                )
            except (OSError, ValueError) as err:
                raise WaymoFormatError(f"{path}: cannot read GT database points: {err}") from err
            if arr.ndim != 2 or arr.shape[1] != self.num_point_features:
                raise WaymoFormatError(
                    f"{path}: expected (N, {self.num_point_features}) points "
                    f"(NUM_POINT_FEATURES), got {arr.shape}"
                )
            self._global_data[data_index] = arr
        return arr

    def load_object_points(self, info: Mapping) -> np.ndarray:
        """Points of one database object, float32 ``(n, NUM_POINT_FEATURES)``, box-centred."""
        if self.use_shared_memory:
            start, end = info["global_data_offset"]
            points = np.array(self._global_array(info["_data_index"])[start:end], np.float32)
            where = f"{self.db_data_paths[info['_data_index']]}[{start}:{end}]"
        else:
            index = info.get("_data_index")  # set by _load_db_infos
            source = "a db_info" if index is None else f"a db_info of {self.db_info_paths[index]}"
            path = resolve_under(self.root_path, info["path"], "path", source)
            where = str(path)
            try:
                flat = np.fromfile(regular_file(path, "GT database object"), dtype=np.float32)
            except OSError as err:
                raise WaymoFormatError(f"{path}: cannot read GT database object: {err}") from err
            if flat.size % self.num_point_features:
                raise WaymoFormatError(
                    f"{path}: {flat.size} floats is not a multiple of NUM_POINT_FEATURES="
                    f"{self.num_point_features}"
                )
            points = flat.reshape(-1, self.num_point_features)
        if points.shape[0] != info["num_points_in_gt"]:
            raise WaymoFormatError(
                f"{where}: {points.shape[0]} points, but its db_info says num_points_in_gt="
                f"{info['num_points_in_gt']}"
            )
        bad = ~np.isfinite(points)
        if bad.any():
            row, col = (int(v[0]) for v in np.nonzero(bad))
            raise WaymoFormatError(
                f"{where}: {int(bad.any(axis=1).sum())} point(s) with NaN/inf values (first at "
                f"row {row}, column {col}: {points[row].tolist()})"
            )
        return points

    # ------------------------------------------------------------------ sampling
    def sample(self, gt_boxes: np.ndarray, gt_names: np.ndarray, rng: np.random.Generator):
        """Draw and collision-check database objects for one frame.

        Returns ``(sampled_boxes (K, B) float, infos list[K])`` with ``B = gt_boxes.shape[1]``.
        """
        existed = np.asarray(gt_boxes, dtype=np.float64)
        width = existed.shape[1]
        kept_infos: list[dict] = []
        for class_name, target in self.sample_groups.items():
            num = target - int(np.sum(gt_names == class_name)) if self.limit_whole_scene else target
            pool = self.db_infos.get(class_name, [])
            if num <= 0 or not pool:
                continue
            idx = rng.choice(len(pool), size=min(num, len(pool)), replace=False)
            sampled = [pool[i] for i in idx]
            boxes = np.stack([np.asarray(x["box3d_lidar"], np.float64) for x in sampled])
            boxes = boxes.astype(np.float32).astype(np.float64)  # OpenPCDet compares float32
            if boxes.shape[1] < width:
                raise WaymoFormatError(
                    f"gt_sampling: {class_name} boxes of {[str(p) for p in self.db_info_paths]} "
                    f"have {boxes.shape[1]} values, the scene's {width} (TRAIN_WITH_SPEED needs "
                    "a database with speeds)"
                )
            hit_existing = boxes_bev_overlap(boxes, existed).any(axis=1)
            hit_sampled = boxes_bev_overlap(boxes, boxes)
            np.fill_diagonal(hit_sampled, False)
            valid = ~(hit_existing | hit_sampled.any(axis=1))
            existed = np.concatenate([existed, boxes[valid][:, :width]], axis=0)
            kept_infos.extend(info for info, ok in zip(sampled, valid) if ok)
        return existed[gt_boxes.shape[0] :], kept_infos

    def __call__(self, data_dict: dict, rng: np.random.Generator) -> dict:
        gt_boxes = data_dict["gt_boxes"]
        gt_names = np.asarray(data_dict["gt_names"]).astype(str)
        sampled_boxes, infos = self.sample(gt_boxes, gt_names, rng)
        mask = data_dict.pop("gt_boxes_mask", np.ones(len(gt_names), dtype=bool))
        if not infos:
            data_dict["gt_boxes"], data_dict["gt_names"] = gt_boxes[mask], gt_names[mask]
            return data_dict
        points = data_dict["points"]
        obj_points = []
        for info in infos:
            pts = self.load_object_points(info).copy()
            pts[:, :3] += np.asarray(info["box3d_lidar"][:3], dtype=np.float32)
            obj_points.append(pts)
        obj = np.concatenate(obj_points, axis=0)
        if self.filter_by_time or obj.shape[1] != points.shape[1]:
            if self.filter_by_time:
                t_min, t_max = min(self.time_range), max(self.time_range)
            elif obj.shape[1] == points.shape[1] + 1:  # multi-frame DB into a 1-frame scene
                t_min = t_max = 0.0
            else:
                raise WaymoFormatError(
                    f"gt_sampling: the points of {[str(p) for p in self.db_info_paths]} have "
                    f"{obj.shape[1]} columns, the scene {points.shape[1]} (frame "
                    f"{data_dict.get('frame_id')}); NUM_POINT_FEATURES does not fit this dataset"
                )
            lag = obj[:, -1]
            obj = obj[(lag < t_max + 1e-6) & (lag > t_min - 1e-6)]
        clear = enlarge_boxes(sampled_boxes[:, :7], self.remove_extra_width)
        points = compress_rows(box_index_of_points(points, clear) < 0, points)
        data_dict["points"] = np.concatenate(
            [obj[:, : points.shape[1]].astype(points.dtype), points], axis=0
        )
        names = np.array([info["name"] for info in infos])
        data_dict["gt_names"] = np.concatenate([gt_names[mask], names], axis=0)
        data_dict["gt_boxes"] = np.concatenate([gt_boxes[mask], sampled_boxes], axis=0)
        return data_dict
