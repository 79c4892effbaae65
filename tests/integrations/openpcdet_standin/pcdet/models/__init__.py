"""OpenPCDet's ``build_network`` and ``load_data_to_gpu`` (here: arrays to CPU tensors, the same
keys left alone)."""

import numpy as np
import torch

from pcdet.models.detectors import build_detector

SKIPPED = ("frame_id", "metadata", "calib", "image_paths", "ori_shape", "img_process_infos")


def build_network(model_cfg, num_class, dataset):
    return build_detector(model_cfg=model_cfg, num_class=num_class, dataset=dataset)


def load_data_to_gpu(batch_dict):
    for key, value in batch_dict.items():
        if not isinstance(value, np.ndarray) or key in SKIPPED:
            continue
        if key == "image_shape":
            batch_dict[key] = torch.from_numpy(value).int()
        else:
            batch_dict[key] = torch.from_numpy(value).float()
