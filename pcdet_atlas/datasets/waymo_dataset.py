"""``WaymoDataset``: OpenPCDet's processed Waymo layout, single- and multi-frame.

Reads ``ImageSets/<split>.txt`` and, per listed sequence,
``<DATA_PATH>/<PROCESSED_DATA_TAG>/<seq>/<seq>.pkl`` (frame infos) and ``%04d.npy`` (points);
format details in :mod:`pcdet_atlas.datasets.waymo_format` and ``docs/data.md``. Every frame's
points, current or history, are read through :meth:`WaymoDataset.get_lidar`, the one hook a
subclass (the attack dataset) overrides.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from easydict import EasyDict

from pcdet_atlas.config import ConfigError, key_source
from pcdet_atlas.config_values import setting, unsupported
from pcdet_atlas.datasets.dataset import DatasetConfig, DatasetTemplate
from pcdet_atlas.datasets.multiframe import (
    SECONDS_PER_FRAME,
    SequenceConfig,
    SequenceSettings,
    compress_rows,
    copy_rows,
    history_sample_indices,
    relative_pose,
    rows_except,
    transform_points_into,
)
from pcdet_atlas.datasets.proposal_history import PROPOSAL_COLUMNS, gather_history
from pcdet_atlas.datasets.waymo_format import (
    PROCESSED_DATA_TAG,
    WaymoFormatError,
    find_sequence_pkl,
    frame_npy_path,
    image_set_path,
    load_frame_points,
    load_sequence_infos,
    read_image_set,
)
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.utils.paths import safe_component

__all__ = ["WaymoDataset", "WaymoDatasetConfig"]

NUM_LOADED_FEATURES = 5  # x, y, z, intensity, elongation (the NLZ column is consumed)
EGO_RADIUS_M = 1.0  # history points with |x| < r and |y| < r are the ego's own (OpenPCDet)


@dataclass(frozen=True, kw_only=True)
class WaymoDatasetConfig(DatasetConfig):
    """The ``DATA_CONFIG`` keys of a Waymo-format dataset (beyond :class:`DatasetConfig`'s)."""

    processed_data_tag: str = setting(PROCESSED_DATA_TAG, doc="folder of the frame files")
    data_split: dict[str, str] = setting(
        default_factory=dict,
        check=lambda d: all(isinstance(v, str) for v in d.values()),
        expected="{train: <split>, test: <split>}",
        doc="the ImageSets split per mode",
    )
    sampled_interval: dict[str, int] = setting(
        default_factory=dict,
        check=lambda d: all(type(v) is int and v >= 1 for v in d.values()),
        expected="{train: n, test: n} with integers n >= 1",
        doc="every n-th frame per mode",
    )
    filter_empty_boxes_for_train: bool = setting(False, doc="drop boxes without points (train)")
    disable_nlz_flag_on_points: bool = setting(False, doc="keep no-label-zone points")
    points_tanh_dim: tuple[int, ...] | None = setting(
        None,
        ge=0,
        lt=NUM_LOADED_FEATURES,
        expected=f"column indices 0-{NUM_LOADED_FEATURES - 1}",
        doc="columns squashed by tanh (None: intensity)",
    )
    train_with_speed: bool = setting(False, doc="boxes carry vx, vy")
    sequence_config: SequenceSettings | None = setting(None, doc="multi-frame samples")
    use_shared_memory: bool = unsupported(
        "frames are read from disk; the OS page cache serves repeated reads"
    )
    shared_memory_file_limit: int | None = setting(None, doc="accepted for OpenPCDet configs")


@DATASETS.register()
class WaymoDataset(DatasetTemplate):
    """Waymo frames as OpenPCDet's ``WaymoDataset`` serves them.

    Attributes:
        infos: frame infos of the split after ``SAMPLED_INTERVAL`` (what ``__getitem__`` walks).
        all_infos: every frame info of the split (interval 1), in ImageSets order.
        seq_name_to_infos: sequence name -> its full info list (indexed by ``sample_idx``).
        sequence_cfg: :class:`SequenceConfig` or ``None`` (single frame).
    """

    CONFIG = WaymoDatasetConfig

    def __init__(
        self,
        dataset_cfg: Mapping,
        class_names: Sequence[str],
        training: bool = True,
        root_path: str | Path | None = None,
        logger: logging.Logger | None = None,
    ):
        if not isinstance(dataset_cfg, EasyDict):  # plain dicts work too (notebooks, tests)
            dataset_cfg = EasyDict(dataset_cfg)
        super().__init__(dataset_cfg, class_names, training, root_path, logger)
        settings = self.settings
        self.sequence_cfg = SequenceConfig.from_settings(settings.sequence_config)
        self.processed_data_tag = safe_component(
            settings.processed_data_tag,
            "DATA_CONFIG.PROCESSED_DATA_TAG",
            key_source(dataset_cfg, "PROCESSED_DATA_TAG"),
        )
        self.data_path = self.root_path / self.processed_data_tag
        self.disable_nlz_flag = settings.disable_nlz_flag_on_points
        tanh_dims = settings.points_tanh_dim
        self.tanh_dims = [3] if tanh_dims is None else list(tanh_dims)
        self.train_with_speed = settings.train_with_speed
        self.filter_empty_boxes_for_train = settings.filter_empty_boxes_for_train
        for key in ("DATA_SPLIT", "SAMPLED_INTERVAL"):
            if self.mode not in getattr(settings, key.lower()):
                raise ConfigError(f"DATA_CONFIG.{key} needs a {self.mode!r} entry")
        self.sampled_interval = settings.sampled_interval[self.mode]
        produced = NUM_LOADED_FEATURES + (
            self.sequence_cfg.num_extra_columns if self.sequence_cfg is not None else 0
        )
        src = self.point_feature_encoder.src_feature_list
        if len(src) != produced:
            raise ConfigError(
                f"DATA_CONFIG.POINT_FEATURE_ENCODING.src_feature_list {src} has {len(src)} "
                f"entries, but this dataset produces {produced} point columns "
                f"({'multi' if self.sequence_cfg else 'single'}-frame)"
            )
        self.proposals: Mapping[str, np.ndarray] | None = None
        self.proposals_source = ""
        self.proposal_history = 0
        split = settings.data_split[self.mode]
        safe_component(
            split, f"DATA_CONFIG.DATA_SPLIT.{self.mode}", key_source(dataset_cfg, "DATA_SPLIT")
        )
        self.set_split(split)

    # ------------------------------------------------------------------ infos
    def set_split(self, split: str) -> None:
        """Load the sequences of ``ImageSets/<split>.txt`` (OpenPCDet's ``set_split``); a split
        that is not one safe file name (``../x``) is an ``UnsafePathError``."""
        split_file = image_set_path(self.root_path, split, f"{type(self).__name__}.set_split")
        self.split = split
        self.sample_sequence_list = read_image_set(split_file)
        if not self.sample_sequence_list:
            raise WaymoFormatError(f"{split_file}: split {split!r} lists no sequence")
        self.all_infos, self.seq_name_to_infos = self.include_waymo_data()
        self.infos = self.all_infos[:: self.sampled_interval]
        self.logger.info(
            f"Waymo {split}: {len(self.seq_name_to_infos)} sequences, {len(self.all_infos)} "
            f"frames, {len(self.infos)} after SAMPLED_INTERVAL={self.sampled_interval}"
        )

    def include_waymo_data(self) -> tuple[list[dict], dict[str, list[dict]]]:
        """Read and check every listed sequence pkl; a missing one is an error."""
        all_infos: list[dict] = []
        seq_name_to_infos: dict[str, list[dict]] = {}
        for sequence in self.sample_sequence_list:
            pkl = find_sequence_pkl(self.root_path, sequence, self.processed_data_tag)
            if pkl.stem in seq_name_to_infos:
                raise WaymoFormatError(f"{pkl}: sequence listed twice in ImageSets/{self.split}")
            infos = load_sequence_infos(pkl)
            seq_name_to_infos[pkl.stem] = infos
            all_infos.extend(infos)
        return all_infos, seq_name_to_infos

    def get_frame_info(self, sequence_name: str, sample_idx: int) -> dict:
        """The info dict of frame ``sample_idx`` of ``sequence_name`` (any frame of the split)."""
        infos = self.seq_name_to_infos.get(sequence_name)
        if infos is None:
            raise KeyError(f"sequence {sequence_name!r} is not in split {self.split!r}")
        if not 0 <= sample_idx < len(infos):
            raise IndexError(
                f"sequence {sequence_name!r} has frames 0..{len(infos) - 1}, not {sample_idx}"
            )
        return infos[sample_idx]

    def set_proposals(self, table: Mapping[str, np.ndarray], source: str, history: int = 0) -> None:
        """Serve ``roi_boxes`` with every sample: ``table[frame_id]`` ``(R, 11)`` ``[x, y, z, dx,
        dy, dz, heading, vx, vy, score, label]`` (the training proposals of a two-stage model,
        read from ``source``). Every frame of ``self.infos`` must have an entry.

        With ``history`` ``H > 0`` also ``roi_history`` ``(N, 12)`` (the proposals of the ``H``
        previous frames in the sample's vehicle frame, frames back in the last column) and
        ``roi_history_frames`` (how many previous frames exist): every frame of the split's
        sequences must then have an entry (:mod:`pcdet_atlas.datasets.proposal_history`).
        """
        if self.data_augmentor is not None and "gt_sampling" in self.data_augmentor.names:
            raise ConfigError(
                "DATA_CONFIG.DATA_AUGMENTOR: gt_sampling pastes objects that have no proposals; "
                "leave it out of a two-stage model's augmentation"
            )
        if isinstance(history, bool) or not isinstance(history, int) or history < 0:
            raise ValueError(f"set_proposals: history must be an int >= 0, got {history!r}")
        needed = self.all_infos if history else self.infos
        missing = [info["frame_id"] for info in needed if info["frame_id"] not in table]
        if missing:
            raise KeyError(
                f"{source}: no proposals for {len(missing)} of the {len(needed)} frames of "
                f"split {self.split!r} (first: {missing[0]})"
            )
        for frame_id, boxes in table.items():
            if np.ndim(boxes) != 2 or np.shape(boxes)[1] != PROPOSAL_COLUMNS:
                raise ValueError(f"{source}: proposals of {frame_id} must be (R, "
                                 f"{PROPOSAL_COLUMNS}), got {np.shape(boxes)}")  # fmt: skip
        self.proposals, self.proposals_source = table, source
        self.proposal_history = history

    def sample_proposals(self, sequence_name: str, sample_idx: int) -> dict:
        """``roi_boxes`` (and with a history ``roi_history``, ``roi_history_frames``) of a frame
        from the table of :meth:`set_proposals`."""
        infos = self.seq_name_to_infos[sequence_name]
        out = {
            "roi_boxes": np.array(self.proposals[infos[sample_idx]["frame_id"]], dtype=np.float64)
        }
        if self.proposal_history:
            rows, count = gather_history(
                lambda k: self.proposals[infos[k]["frame_id"]],
                lambda k: np.asarray(infos[k]["pose"], dtype=np.float64),
                sample_idx, self.proposal_history,
            )  # fmt: skip
            out["roi_history"], out["roi_history_frames"] = rows, np.int64(count)
        return out

    # ------------------------------------------------------------------ points
    def get_lidar(self, sequence_name: str, sample_idx: int) -> np.ndarray:
        """Points of one frame, float32 ``(N, 5)`` ``[x, y, z, tanh(intensity), elongation]``
        in its own vehicle frame (NLZ points dropped unless ``DISABLE_NLZ_FLAG_ON_POINTS``;
        tanh on the ``POINTS_TANH_DIM`` columns, default intensity only)."""
        return self.loaded_points(load_frame_points(self.frame_path(sequence_name, sample_idx)))

    def frame_path(self, sequence_name: str, sample_idx: int) -> Path:
        """The ``%04d.npy`` file of a frame."""
        return frame_npy_path(self.root_path, sequence_name, sample_idx, self.processed_data_tag)

    def loaded_points(self, rows: np.ndarray, drop: np.ndarray | None = None) -> np.ndarray:
        """Raw ``(N, 6)`` rows of a frame file -> the loader's ``(N', 5)`` points: the rows
        kept in their order (NLZ rows dropped unless ``DISABLE_NLZ_FLAG_ON_POINTS``, and the
        ascending row indices ``drop``), tanh on the ``POINTS_TANH_DIM`` columns."""
        features = rows[:, :NUM_LOADED_FEATURES]
        keep = None if self.disable_nlz_flag else rows[:, 5] == -1
        if drop is not None and drop.size and (keep is None or keep.all()):
            points = rows_except(features, drop)  # block copies, or a masked copy
        elif keep is None:
            points = copy_rows(features)
        else:  # the row selection makes a new array: no second copy
            if drop is not None:
                keep[drop] = False
            points = compress_rows(keep, features)
        for dim in self.tanh_dims:
            points[:, dim] = np.tanh(points[:, dim])
        return points

    def get_sequence_data(
        self,
        info: Mapping,
        points: np.ndarray,
        sequence_name: str,
        sample_idx: int,
        sequence_cfg: SequenceConfig,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Stack frame ``sample_idx`` with its history in the current vehicle frame.

        Args:
            info: the current frame's info (its ``pose`` is the target frame).
            points: ``(N, 5)`` current points from :meth:`get_lidar`.
            sequence_cfg: offsets; history frame ``t-j`` comes from ``get_lidar`` and its
                ``pose`` from :meth:`get_frame_info`.
        Returns:
            points: float32 ``(N', 6)`` ``[x, y, z, intensity, elongation, lag_s]`` (current
                first, then t-1, t-2, ...; lag ``0.1 * (t - s)``; one-hot columns instead with
                ``ONEHOT_TIMESTAMP``), history points within 1 m of the ego (|x|, |y| < 1) dropped;
            num_points_all: int32 ``(k+1,)`` points per frame;
            sample_idx_pre_list: int64 ``(k,)`` history indices (clipped at 0);
            poses: float32 ``(4 (k+1), 4)`` current pose then the history poses.
        """
        pose_cur = np.asarray(info["pose"], dtype=np.float64).reshape(4, 4)
        history = history_sample_indices(sample_idx, sequence_cfg.sample_offset)
        frames = [points]
        poses = [pose_cur]
        for s_pre in history:
            frames.append(self.get_lidar(sequence_name, int(s_pre)))
            poses.append(
                np.asarray(
                    self.get_frame_info(sequence_name, int(s_pre))["pose"], dtype=np.float64
                ).reshape(4, 4)
            )
        num_feat = points.shape[1]
        num_cols = num_feat + sequence_cfg.num_extra_columns
        # One output array, every frame written once in place (history xyz straight from the
        # float64 transform); ego points of the history are then dropped in one row gather.
        stacked = np.empty((sum(len(f) for f in frames), num_cols), dtype=np.float32)
        keep = np.ones(len(stacked), dtype=bool)
        num_points_all = np.empty(len(frames), dtype=np.int32)
        start = 0
        frame_indices = [sample_idx, *(int(s) for s in history)]
        for position, (pts, pose) in enumerate(zip(frames, poses)):
            block = stacked[start : start + len(pts)]
            if position == 0:
                block[:, :num_feat] = pts
                num_points_all[0] = len(pts)
            else:
                if pts.shape[1] != num_feat:
                    raise WaymoFormatError(
                        f"{sequence_name} frame {frame_indices[position]}: get_lidar gave "
                        f"{pts.shape[1]} columns, the current frame {num_feat}"
                    )
                block[:, 3:num_feat] = pts[:, 3:]
                outside = transform_points_into(
                    pts[:, :3], relative_pose(pose, pose_cur), block[:, :3], EGO_RADIUS_M
                )
                keep[start : start + len(pts)] = outside
                num_points_all[position] = np.count_nonzero(outside)
            if sequence_cfg.onehot_timestamp:
                block[:, num_feat:] = 0.0
                block[:, num_feat + position] = 1.0
            else:  # time lag 0.1 s per frame, from the (clipped) history index
                block[:, num_feat] = SECONDS_PER_FRAME * (sample_idx - frame_indices[position])
            start += len(pts)
        if num_points_all.sum() != len(stacked):
            stacked = compress_rows(keep, stacked)
        return stacked, num_points_all, history, np.concatenate(poses).astype(np.float32)

    # ------------------------------------------------------------------ samples
    def __len__(self) -> int:
        if self._merge_all_iters_to_one_epoch:
            return len(self.infos) * self.total_epochs
        return len(self.infos)

    def get_annotations(self, info: Mapping) -> dict:
        """``gt_names`` ``(M,)`` and ``gt_boxes`` float64 ``(M, 7|9)`` of one labelled frame."""
        annos = info["annos"]
        names = np.asarray(annos["name"])
        keep = names != "unknown"
        boxes = np.asarray(annos["gt_boxes_lidar"], dtype=np.float64)[keep]
        names = names[keep]
        if self.train_with_speed:
            if boxes.shape[1] != 9:
                raise WaymoFormatError(
                    f"{info['frame_id']}: TRAIN_WITH_SPEED needs (M, 9) 'annos.gt_boxes_lidar', "
                    f"got {boxes.shape}"
                )
        else:
            boxes = boxes[:, :7]
        if self.training and self.filter_empty_boxes_for_train:
            nonempty = np.asarray(annos["num_points_in_gt"])[keep] > 0
            boxes, names = boxes[nonempty], names[nonempty]
        return {"gt_names": names, "gt_boxes": boxes}

    def __getitem__(self, index: int) -> dict:
        """One sample: ``points`` float32 ``(N, C)``, ``frame_id``, ``sequence_name``,
        ``sample_idx``, ``pose`` (4, 4), ``poses`` (multi-frame), ``gt_boxes`` float32
        ``(M, 8|10)`` (class index last), ``gt_names``, ``metadata`` and the pipeline's keys."""
        epoch = None
        if self._merge_all_iters_to_one_epoch:
            epoch = self.epoch + index // len(self.infos)
            index = index % len(self.infos)
        return self.get_sample(self.infos[index], epoch)

    def frame_sample(self, sequence_name: str, sample_idx: int) -> dict:
        """The sample of any frame of the split, also one that ``SAMPLED_INTERVAL`` leaves out
        (as ``__getitem__`` builds it; the proposal bank reads history frames this way)."""
        return self.get_sample(self.get_frame_info(sequence_name, int(sample_idx)), None)

    def get_sample(self, info: Mapping, epoch: int | None = None) -> dict:
        """The sample of the frame of ``info`` (``__getitem__``'s dict) at ``epoch``."""
        sequence_name = info["point_cloud"]["lidar_sequence"]
        sample_idx = int(info["point_cloud"]["sample_idx"])
        points = self.get_lidar(sequence_name, sample_idx)
        input_dict = {
            "frame_id": info["frame_id"],
            "sequence_name": sequence_name,
            "sample_idx": sample_idx,
            "pose": np.array(info["pose"], dtype=np.float32).reshape(4, 4),  # a copy
            "metadata": copy.deepcopy(info.get("metadata", info["frame_id"])),
        }
        if self.sequence_cfg is not None:
            points, _, _, poses = self.get_sequence_data(
                info, points, sequence_name, sample_idx, self.sequence_cfg
            )
            input_dict["poses"] = poses
        input_dict["points"] = points
        if "annos" in info:
            input_dict.update(self.get_annotations(info))
        if self.proposals is not None:
            input_dict.update(self.sample_proposals(sequence_name, sample_idx))
        return self.prepare_data(input_dict, epoch=epoch)

    # ------------------------------------------------------------------ predictions
    @staticmethod
    def generate_prediction_dicts(
        batch_dict: Mapping, pred_dicts: Sequence[Mapping], class_names, output_path=None
    ) -> list[dict]:
        """Model outputs -> OpenPCDet anno dicts, one per sample.

        Args:
            batch_dict: the collated batch (``frame_id``, ``metadata``).
            pred_dicts: per sample ``pred_boxes`` ``(K, 7|9)``, ``pred_scores`` ``(K,)``,
                ``pred_labels`` ``(K,)`` (1-based class index); torch or numpy.
        Returns:
            dicts with ``name`` ``(K,)`` str, ``score`` ``(K,)``, ``boxes_lidar`` ``(K, 7|9)``,
            ``pred_labels`` ``(K,)``, ``frame_id``, ``metadata``.
        """

        def to_numpy(x) -> np.ndarray:
            return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)

        names_table = np.array(class_names)
        annos = []
        for index, box_dict in enumerate(pred_dicts):
            scores = to_numpy(box_dict["pred_scores"]).astype(np.float32).reshape(-1)
            boxes = to_numpy(box_dict["pred_boxes"]).astype(np.float32)
            boxes = boxes.reshape(len(scores), -1) if boxes.size else np.zeros((0, 7), np.float32)
            labels = to_numpy(box_dict["pred_labels"]).astype(np.int64).reshape(-1)
            if len(labels) and (labels.min() < 1 or labels.max() > len(class_names)):
                raise ValueError(
                    f"pred_labels must be 1..{len(class_names)}, got {labels.min()}..{labels.max()}"
                )
            annos.append(
                {
                    "name": names_table[labels - 1] if len(labels) else np.array([], dtype="<U10"),
                    "score": scores,
                    "boxes_lidar": boxes,
                    "pred_labels": labels,
                    "frame_id": batch_dict["frame_id"][index],
                    "metadata": batch_dict["metadata"][index],
                }
            )
        return annos

    def evaluation(self, det_annos: Sequence[Mapping], class_names, **kwargs):
        """Waymo L1/L2 AP/APH of ``det_annos`` (one per ``self.infos`` entry, same order).

        Returns ``(result_str, ap_dict)`` as OpenPCDet. Keyword ``eval_metric`` must be
        ``'waymo'`` if given.
        """
        metric = kwargs.get("eval_metric", "waymo")
        if metric != "waymo":
            raise ValueError(f"eval_metric {metric!r} is not supported (only 'waymo')")
        unlabelled = [info for info in self.infos if "annos" not in info]
        if len(unlabelled) == len(self.infos):
            raise WaymoFormatError(f"split {self.split!r} has no ground truth ('annos')")
        if unlabelled:
            first = unlabelled[0]["point_cloud"]
            sequence, sample_idx = first["lidar_sequence"], first["sample_idx"]
            pkl = find_sequence_pkl(self.root_path, sequence, self.processed_data_tag)
            raise WaymoFormatError(
                f"{pkl} [frame {sample_idx}]: frame {unlabelled[0]['frame_id']} of sequence "
                f"{sequence!r} has no ground truth ('annos'), so split {self.split!r} cannot be "
                f"evaluated ({len(unlabelled)} of its {len(self.infos)} frames are unlabelled)"
            )
        if len(det_annos) != len(self.infos):
            raise ValueError(
                f"{len(det_annos)} detection dicts for {len(self.infos)} frames of {self.split!r}"
            )
        for det, info in zip(det_annos, self.infos):
            if det.get("frame_id", info["frame_id"]) != info["frame_id"]:
                raise ValueError(
                    f"detections out of order: {det['frame_id']} where {info['frame_id']} expected"
                )
        from pcdet_atlas.evaluation.waymo_metric import waymo_evaluate

        gt_annos = [copy.deepcopy(info["annos"]) for info in self.infos]
        ap_dict = waymo_evaluate(gt_annos, list(det_annos), class_names)
        result_str = "\n" + "".join(f"{key}: {float(val):.4f}\n" for key, val in ap_dict.items())
        return result_str, ap_dict
