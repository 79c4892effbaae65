"""The dataset fingerprint follows what a run reads of a split: the split file, the sequences'
info pkls and every frame file's size and mtime; it stays put otherwise."""

import os
import re

import numpy as np
import pytest

from pcdet_atlas.config import cfg_from_yaml_file
from pcdet_atlas.datasets.fingerprint import data_config_fingerprint, dataset_fingerprint
from pcdet_atlas.datasets.waymo_format import PROCESSED_DATA_TAG, WaymoFormatError
from pcdet_atlas.utils.paths import UnsafePathError


def tiny_dataset(root):
    """Two sequences of two frames each (the fingerprint reads no pkl content)."""
    (root / "ImageSets").mkdir(parents=True)
    (root / "ImageSets" / "val.txt").write_text("seq_a.tfrecord\nseq_b.tfrecord\n")
    (root / "ImageSets" / "train.txt").write_text("seq_a.tfrecord\n")
    for seq in ("seq_a", "seq_b"):
        folder = root / PROCESSED_DATA_TAG / seq
        folder.mkdir(parents=True)
        (folder / f"{seq}.pkl").write_bytes(b"infos of " + seq.encode())
        for i in range(2):
            np.save(folder / f"{i:04d}.npy", np.zeros((3, 6), np.float32))
    return root


def test_the_fingerprint_follows_infos_and_frames(tmp_path):
    root = tiny_dataset(tmp_path / "data")
    seq_b = root / PROCESSED_DATA_TAG / "seq_b"
    first = dataset_fingerprint(root, "val")
    assert len(first) == 64 and dataset_fingerprint(root, "val") == first
    cfg = {"DATA_PATH": str(root), "DATA_SPLIT": {"train": "train", "test": "val"}}
    assert data_config_fingerprint(cfg, "test") == first
    train = dataset_fingerprint(root, "train")
    assert data_config_fingerprint(cfg, "train") == train != first

    frame = seq_b / "0001.npy"  # rewritten in place with other points of the same size
    stat = frame.stat()
    np.save(frame, np.ones((3, 6), np.float32))
    os.utime(frame, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1))
    assert frame.stat().st_size == stat.st_size
    rewritten = dataset_fingerprint(root, "val")
    assert rewritten != first
    assert dataset_fingerprint(root, "train") == train  # seq_a only: untouched

    pkl = seq_b / "seq_b.pkl"  # the same size and mtime, other bytes: the infos are hashed
    stat = pkl.stat()
    pkl.write_bytes(b"infos of seq_c")
    os.utime(pkl, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert dataset_fingerprint(root, "val") not in (first, rewritten)
    np.save(seq_b / "0002.npy", np.zeros((1, 6), np.float32))  # a frame added
    added = dataset_fingerprint(root, "val")
    (root / "ImageSets" / "val.txt").write_text("seq_a.tfrecord\n")
    assert len({added, rewritten, first, dataset_fingerprint(root, "val")}) == 4

    (root / "ImageSets" / "val.txt").write_text("seq_a.tfrecord\nseq_x.tfrecord\n")
    with pytest.raises(WaymoFormatError, match="'seq_x'.*no info pkl"):
        dataset_fingerprint(root, "val")


def test_a_split_or_tag_leaving_the_root_is_refused(tmp_path):
    """``ImageSets/../outside.txt`` or ``../data/<tag>`` would be read beside the root: the
    split and the tag must each be one file name, named with the config file they came from."""
    root = tiny_dataset(tmp_path / "data")
    (root / "outside.txt").write_text("seq_a.tfrecord\n")
    with pytest.raises(UnsafePathError, match=r"split '\.\./outside' \(from the split of "):
        dataset_fingerprint(root, "../outside")
    with pytest.raises(
        UnsafePathError, match=rf"PROCESSED_DATA_TAG '\.\./data/{PROCESSED_DATA_TAG}'"
    ):
        dataset_fingerprint(root, "train", f"../data/{PROCESSED_DATA_TAG}")
    yaml_path = tmp_path / "data.yaml"
    yaml_path.write_text(f"DATA_PATH: {root}\nDATA_SPLIT: {{train: ../outside}}\n")
    with pytest.raises(UnsafePathError, match=rf"DATA_SPLIT\.train '\.\./outside' \(from "
                       rf"{re.escape(str(yaml_path))}\)"):  # fmt: skip
        data_config_fingerprint(cfg_from_yaml_file(yaml_path), "train")
