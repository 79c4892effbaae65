"""OpenPCDet's ``WaymoDataset``: the per-sequence infos of a split, sampled; frames read by
``get_lidar``; a sequence input stacked by ``get_sequence_data``. Its pickles are read as
OpenPCDet reads them, with ``pickle.load`` (which runs code a file names): the integration
must not let these readers see a dataset's files."""

import copy
import os
import pickle

import numpy as np

from pcdet.datasets.dataset import DatasetTemplate


class WaymoDataset(DatasetTemplate):
    def __init__(self, dataset_cfg, class_names, training=True, root_path=None, logger=None):
        super().__init__(dataset_cfg=dataset_cfg, class_names=class_names, training=training,
                         root_path=root_path, logger=logger)  # fmt: skip
        self.data_path = self.root_path / self.dataset_cfg.PROCESSED_DATA_TAG
        self.split = self.dataset_cfg.DATA_SPLIT[self.mode]
        split_dir = self.root_path / "ImageSets" / (self.split + ".txt")
        self.sample_sequence_list = [x.strip() for x in open(split_dir).readlines()]
        self.infos = []
        self.seq_name_to_infos = self.include_waymo_data(self.mode)
        if self.dataset_cfg.get("USE_PREDBOX", False):
            self.pred_boxes_dict = self.load_pred_boxes_to_dict(
                pred_boxes_path=self.dataset_cfg.ROI_BOXES_PATH[self.mode]
            )
        else:
            self.pred_boxes_dict = {}

    def set_split(self, split):
        super().__init__(
            dataset_cfg=self.dataset_cfg, class_names=self.class_names, training=self.training,
            root_path=self.root_path, logger=self.logger,
        )  # fmt: skip
        self.split = split
        split_dir = self.root_path / "ImageSets" / (self.split + ".txt")
        self.sample_sequence_list = [x.strip() for x in open(split_dir).readlines()]
        self.infos = []
        self.seq_name_to_infos = self.include_waymo_data(self.mode)

    def include_waymo_data(self, mode):
        """Every sequence's infos into ``self.infos``, then every SAMPLED_INTERVAL-th; returns
        ``{sequence: infos}`` for a sequence input, else None."""
        seq_name_to_infos = {}
        for line in self.sample_sequence_list:
            sequence_name = os.path.splitext(line)[0]
            info_path = self.data_path / sequence_name / f"{sequence_name}.pkl"
            if not info_path.exists():
                continue
            with open(info_path, "rb") as f:
                infos = pickle.load(f)
            self.infos.extend(infos)
            seq_name_to_infos[infos[0]["point_cloud"]["lidar_sequence"]] = infos
        interval = self.dataset_cfg.SAMPLED_INTERVAL[mode]
        if interval > 1:
            self.infos = self.infos[::interval]
        sequence_cfg = self.dataset_cfg.get("SEQUENCE_CONFIG", None)
        return seq_name_to_infos if sequence_cfg is not None and sequence_cfg.ENABLED else None

    def load_pred_boxes_to_dict(self, pred_boxes_path):
        with open(pred_boxes_path, "rb") as f:
            pred_dicts = pickle.load(f)
        pred_boxes_dict = {}
        for box_dict in pred_dicts:
            seq_name = box_dict["frame_id"][:-4].replace("training_", "").replace("validation_", "")
            sample_idx = int(box_dict["frame_id"][-3:])
            labels = np.array([self.class_names.index(n) + 1 for n in box_dict["name"]])
            pred_boxes_dict.setdefault(seq_name, {})[sample_idx] = np.concatenate(
                (box_dict["boxes_lidar"], box_dict["score"][:, np.newaxis], labels[:, np.newaxis]),
                axis=-1,
            )
        return pred_boxes_dict

    def get_lidar(self, sequence_name, sample_idx):
        point_features = np.load(self.data_path / sequence_name / f"{sample_idx:04d}.npy")
        points_all, nlz_flag = point_features[:, 0:5], point_features[:, 5]
        if not self.dataset_cfg.get("DISABLE_NLZ_FLAG_ON_POINTS", False):
            points_all = points_all[nlz_flag == -1]
        for dim in self.dataset_cfg.get("POINTS_TANH_DIM", None) or [3]:
            points_all[:, dim] = np.tanh(points_all[:, dim])
        return points_all

    def get_sequence_data(self, info, points, sequence_name, sample_idx, sequence_cfg,
                          load_pred_boxes=False):  # fmt: skip
        """The frame and its SAMPLE_OFFSET history (newest first) in the current vehicle frame,
        a time-lag column appended (0.1 s a frame), the ego's own returns (|x|, |y| < 1 m) of
        the history dropped."""
        if load_pred_boxes:
            raise NotImplementedError("the stand-in has no predicted-box history")
        pose_cur = info["pose"].reshape((4, 4))
        num_pts_cur = points.shape[0]
        first, last = sequence_cfg.SAMPLE_OFFSET
        sample_idx_pre_list = np.clip(sample_idx + np.arange(first, last), 0, 0x7FFFFFFF)[::-1]
        points = np.hstack([points, np.zeros((points.shape[0], 1), points.dtype)])
        points_pre_all, num_points_pre, pose_all = [], [], [pose_cur]
        sequence_info = self.seq_name_to_infos[sequence_name]
        for sample_idx_pre in sample_idx_pre_list:
            points_pre = self.get_lidar(sequence_name, sample_idx_pre)
            pose_pre = sequence_info[sample_idx_pre]["pose"].reshape((4, 4))
            xyz1 = np.concatenate([points_pre[:, :3], np.ones((len(points_pre), 1))], axis=-1)
            world = xyz1 @ pose_pre.T
            current = (world @ np.linalg.inv(pose_cur.T))[:, :3]
            lag = 0.1 * (sample_idx - sample_idx_pre) * np.ones((len(points_pre), 1))
            points_pre = np.hstack([current, points_pre[:, 3:], lag.astype(points_pre.dtype)])
            ego = (np.abs(points_pre[:, 0]) < 1.0) & (np.abs(points_pre[:, 1]) < 1.0)
            points_pre = points_pre[~ego]
            points_pre_all.append(points_pre)
            num_points_pre.append(points_pre.shape[0])
            pose_all.append(pose_pre)
        points = np.concatenate([points] + points_pre_all, axis=0).astype(np.float32)
        num_points_all = np.array([num_pts_cur] + num_points_pre).astype(np.int32)
        poses = np.concatenate(pose_all, axis=0).astype(np.float32)
        return points, num_points_all, sample_idx_pre_list, poses, None, None, None

    def __len__(self):
        if self._merge_all_iters_to_one_epoch:
            return len(self.infos) * self.total_epochs
        return len(self.infos)

    def __getitem__(self, index):
        if self._merge_all_iters_to_one_epoch:
            index = index % len(self.infos)
        info = copy.deepcopy(self.infos[index])
        sequence_name = info["point_cloud"]["lidar_sequence"]
        sample_idx = info["point_cloud"]["sample_idx"]
        input_dict = {"sample_idx": sample_idx}
        points = self.get_lidar(sequence_name, sample_idx)
        sequence_cfg = self.dataset_cfg.get("SEQUENCE_CONFIG", None)
        if sequence_cfg is not None and sequence_cfg.ENABLED:
            points, _, _, poses, _, _, _ = self.get_sequence_data(
                info, points, sequence_name, sample_idx, sequence_cfg
            )
            input_dict["poses"] = poses
        input_dict.update({"points": points, "frame_id": info["frame_id"]})
        if "annos" in info:
            annos = info["annos"]
            keep = annos["name"] != "unknown"
            boxes = annos["gt_boxes_lidar"][keep]
            if not self.dataset_cfg.get("TRAIN_WITH_SPEED", False):
                boxes = boxes[:, 0:7]
            input_dict.update({"gt_names": annos["name"][keep], "gt_boxes": boxes})
        data_dict = self.prepare_data(data_dict=input_dict)
        data_dict["metadata"] = info.get("metadata", info["frame_id"])
        return data_dict
