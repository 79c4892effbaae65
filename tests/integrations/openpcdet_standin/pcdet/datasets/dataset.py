"""OpenPCDet's ``DatasetTemplate``: prediction dicts, ``prepare_data`` (ground-truth classes
only, here) and ``collate_batch``."""

from collections import defaultdict
from pathlib import Path

import numpy as np
import torch.utils.data as torch_data


class DatasetTemplate(torch_data.Dataset):
    def __init__(self, dataset_cfg=None, class_names=None, training=True, root_path=None,
                 logger=None):  # fmt: skip
        super().__init__()
        self.dataset_cfg = dataset_cfg
        self.training = training
        self.class_names = class_names
        self.logger = logger
        self.root_path = root_path if root_path is not None else Path(self.dataset_cfg.DATA_PATH)
        if self.dataset_cfg is None or class_names is None:
            return
        self.point_cloud_range = np.array(self.dataset_cfg.POINT_CLOUD_RANGE, dtype=np.float32)
        self.total_epochs = 0
        self._merge_all_iters_to_one_epoch = False

    @property
    def mode(self):
        return "train" if self.training else "test"

    def __getstate__(self):
        state = dict(self.__dict__)
        del state["logger"]
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)

    def generate_prediction_dicts(self, batch_dict, pred_dicts, class_names, output_path=None):
        """Per sample ``name``, ``score``, ``boxes_lidar``, ``pred_labels`` (numpy), its
        ``frame_id`` and, where the batch has it, ``metadata``."""
        box_dim = 9 if self.dataset_cfg.get("TRAIN_WITH_SPEED", False) else 7
        annos = []
        for index, box_dict in enumerate(pred_dicts):
            scores = box_dict["pred_scores"].cpu().numpy()
            boxes = box_dict["pred_boxes"].cpu().numpy()
            labels = box_dict["pred_labels"].cpu().numpy()
            num = scores.shape[0]
            anno = {"name": np.zeros(num), "score": np.zeros(num),
                    "boxes_lidar": np.zeros([num, box_dim]),
                    "pred_labels": np.zeros(num)}  # fmt: skip
            if num:
                anno = {"name": np.array(class_names)[labels - 1], "score": scores,
                        "boxes_lidar": boxes, "pred_labels": labels}  # fmt: skip
            anno["frame_id"] = batch_dict["frame_id"][index]
            if "metadata" in batch_dict:
                anno["metadata"] = batch_dict["metadata"][index]
            annos.append(anno)
        return annos

    def merge_all_iters_to_one_epoch(self, merge=True, epochs=None):
        self._merge_all_iters_to_one_epoch = bool(merge)
        self.total_epochs = epochs if merge else self.total_epochs

    def __len__(self):
        raise NotImplementedError

    def __getitem__(self, index):
        raise NotImplementedError

    def prepare_data(self, data_dict):
        """Ground truth of ``class_names`` only, the 1-based class appended to ``gt_boxes``."""
        if data_dict.get("gt_boxes") is not None:
            keep = np.array([n in self.class_names for n in data_dict["gt_names"]], dtype=bool)
            names = data_dict["gt_names"][keep]
            classes = np.array([self.class_names.index(n) + 1 for n in names], dtype=np.float32)
            data_dict["gt_boxes"] = np.concatenate(
                [data_dict["gt_boxes"][keep], classes.reshape(-1, 1)], axis=1
            )
        data_dict.pop("gt_names", None)
        return data_dict

    @staticmethod
    def collate_batch(batch_list, _unused=False):
        data_dict = defaultdict(list)
        for sample in batch_list:
            for key, value in sample.items():
                data_dict[key].append(value)
        batch_size = len(batch_list)
        ret = {}
        for key, values in data_dict.items():
            if key in ("points", "voxel_coords"):
                ret[key] = np.concatenate(
                    [np.pad(v, ((0, 0), (1, 0)), constant_values=i) for i, v in enumerate(values)]
                )
            elif key == "gt_boxes":
                width = values[0].shape[-1]
                boxes = np.zeros((batch_size, max(len(v) for v in values), width), np.float32)
                for k, v in enumerate(values):
                    boxes[k, : len(v)] = v
                ret[key] = boxes
            else:
                ret[key] = np.stack(values, axis=0)
        ret["batch_size"] = batch_size
        return ret
