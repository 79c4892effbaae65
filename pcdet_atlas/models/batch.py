"""Moving a collated batch onto a device (OpenPCDet's ``load_data_to_gpu``, device-generic)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

__all__ = ["load_data_to_device"]

# keys that stay on the host as they are (identifiers, metadata, per-frame records)
HOST_KEYS = frozenset(
    {
        "frame_id",
        "sequence_name",
        "sample_idx",
        "metadata",
        "gt_names",
        "attack",
        "pose",
        "frame_seed",
    }
)


def load_data_to_device(batch_dict: Mapping, device: str | torch.device) -> dict:
    """A new dict with numeric numpy arrays / tensors moved to ``device``.

    Floating arrays become float32 tensors, integer arrays int64 tensors; strings, lists, dicts and
    the keys in :data:`HOST_KEYS` are left as they are.
    """
    out = {}
    for key, val in batch_dict.items():
        if key in HOST_KEYS:
            out[key] = val
        elif isinstance(val, np.ndarray) and val.dtype.kind in "fiub":
            t = torch.from_numpy(np.ascontiguousarray(val))
            if val.dtype.kind == "f":
                t = t.float()
            elif val.dtype.kind in "iu":
                t = t.long()
            out[key] = t.to(device)
        elif isinstance(val, torch.Tensor):
            out[key] = val.to(device)
        else:
            out[key] = val
    return out
