"""The synthetic Waymo-format generator: format, determinism, idempotency, sensor physics."""

from __future__ import annotations

import pickle

import numpy as np

from pcdet_atlas.datasets import waymo_format as wf


def _sequences(root, split):
    lines = (root / "ImageSets" / f"{split}.txt").read_text().splitlines()
    return [wf.sequence_name_from_line(line) for line in lines]


def _infos(root, seq):
    with open(wf.sequence_pkl_path(root, seq), "rb") as fh:
        return pickle.load(fh)


def test_fixture_layout_and_format(synthetic_root):
    root = synthetic_root
    assert len(_sequences(root, "train")) == 2 and len(_sequences(root, "val")) == 1
    for split, frames in (("train", 10), ("val", 70)):
        all_infos = []
        for seq in _sequences(root, split):
            assert seq.startswith("segment-") and seq.endswith("_with_camera_labels")
            infos = _infos(root, seq)
            wf.validate_sequence_infos(infos, wf.sequence_pkl_path(root, seq))
            assert len(infos) == frames
            for info in infos[:: max(1, frames // 5)]:
                points = np.load(wf.frame_npy_path(root, seq, info["point_cloud"]["sample_idx"]))
                wf.validate_points(points, seq)
                assert info["num_points_of_each_lidar"] == [len(points), 0, 0, 0, 0]
                assert set(np.unique(points[:, 5])) <= {-1.0, 1.0}
            all_infos += infos
        with open(root / f"{wf.PROCESSED_DATA_TAG}_infos_{split}.pkl", "rb") as fh:
            concat = pickle.load(fh)
        assert [i["frame_id"] for i in concat] == [i["frame_id"] for i in all_infos]
