"""A cheap fingerprint of one split of a processed Waymo dataset: what the caches of its
predictions (training proposals, ``tools/test.py --resume``, ``tools/reproduce.py``) are keyed by,
so that a dataset rewritten in place is evaluated again instead of served from the old run.

It covers everything a run reads of the split (docs/data.md): the bytes of
``ImageSets/<split>.txt`` and of every listed sequence's info pkl (SHA-256), and the name, size
and modification time (ns) of every ``.npy`` frame file in those sequences' folders. Frames are
not hashed (tens of thousands of files): rewriting one changes its mtime. Copying a dataset
without keeping mtimes (``cp -r`` rather than ``cp -a`` / ``rsync -a``) therefore changes the
fingerprint too, and what was evaluated on it is evaluated again.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path

from pcdet_atlas.config import key_source, resolve_repo_path
from pcdet_atlas.datasets.waymo_format import (
    PROCESSED_DATA_TAG,
    data_dir,
    find_sequence_pkl,
    image_set_path,
    read_image_set,
)
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.paths import safe_component

__all__ = ["data_config_fingerprint", "dataset_fingerprint", "sequence_label_sha256"]


def sequence_label_sha256(root: str | Path, sequences, tag: str = PROCESSED_DATA_TAG) -> dict:
    """``{sequence: SHA-256 of its info pkl}`` for ``sequences`` of the dataset at ``root``: the
    labels an attack was generated against, by content (a copied dataset keeps them, whatever
    its files' times).

    Raises:
        WaymoFormatError: a sequence's pkl is missing (naming the paths tried).
    """
    return {str(name): file_sha256(find_sequence_pkl(root, name, tag)) for name in sequences}


def dataset_fingerprint(root: str | Path, split: str, tag: str = PROCESSED_DATA_TAG) -> str:
    """Hex SHA-256 of split ``split`` of the dataset at ``root`` (module docstring).

    Raises:
        WaymoFormatError: the split file or a listed sequence's pkl is missing (naming it).
        UnsafePathError: ``split`` or ``tag`` is not one safe path component (``../x``).
    """
    root = Path(root)
    data_dir(root, tag)  # the tag checked before anything is read
    split_file = image_set_path(root, split, "the split of dataset_fingerprint")
    sequences = read_image_set(split_file)
    digest = hashlib.sha256(f"split={split}|tag={tag}|".encode())
    digest.update(file_sha256(split_file).encode())
    for sequence in sequences:
        pkl = find_sequence_pkl(root, sequence, tag)
        digest.update(f"|{pkl.parent.name}/{pkl.name}:{file_sha256(pkl)}".encode())
        with os.scandir(pkl.parent) as entries:
            frames = [e for e in entries if e.name.endswith(".npy") and e.is_file()]
        for entry in sorted(frames, key=lambda e: e.name):
            stat = entry.stat()
            digest.update(f"|{entry.name}:{stat.st_size}:{stat.st_mtime_ns}".encode())
    return digest.hexdigest()


def data_config_fingerprint(data_cfg: Mapping, mode: str) -> str:
    """:func:`dataset_fingerprint` of the split a ``DATA_CONFIG`` reads in ``mode`` (``'train'``
    or ``'test'``: its ``DATA_SPLIT[mode]`` under ``DATA_PATH`` and ``PROCESSED_DATA_TAG``)."""
    split = str(data_cfg["DATA_SPLIT"][mode])
    tag = data_cfg.get("PROCESSED_DATA_TAG", PROCESSED_DATA_TAG)
    safe_component(split, f"DATA_SPLIT.{mode}", key_source(data_cfg, "DATA_SPLIT"))
    safe_component(tag, "PROCESSED_DATA_TAG", key_source(data_cfg, "PROCESSED_DATA_TAG"))
    return dataset_fingerprint(resolve_repo_path(data_cfg["DATA_PATH"]), split, tag)
