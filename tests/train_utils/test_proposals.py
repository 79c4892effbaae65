"""The training-proposal cache is keyed by everything its content depends on: a changed setting
in the RPN's config file or a dataset rewritten in place gets a new file, computed again, and the
old file is never served. The RPN and the loader are stand-ins: only the cache is under test."""

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from easydict import EasyDict

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.datasets.waymo_format import PROCESSED_DATA_TAG
from pcdet_atlas.train_utils import proposals
from pcdet_atlas.utils.paths import UnsafePathError

RPN_CFG = REPO_ROOT / "cfgs" / "atlas" / "synthetic" / "cp4f.yaml"


def tiny_dataset(root):
    (root / "ImageSets").mkdir(parents=True)
    (root / "ImageSets" / "train.txt").write_text("seq_a.tfrecord\n")
    folder = root / PROCESSED_DATA_TAG / "seq_a"
    folder.mkdir(parents=True)
    (folder / "seq_a.pkl").write_bytes(b"infos")
    for i in range(2):
        np.save(folder / f"{i:04d}.npy", np.zeros((3, 6), np.float32))
    return root


@pytest.fixture
def setup(tmp_path, monkeypatch):
    """A stand-in two-stage model whose RPN config is a file in tmp, and a counting RPN run."""
    rpn_cfg = tmp_path / "rpn.yaml"
    rpn_cfg.write_text(f"_BASE_CONFIG_: {RPN_CFG}\n")
    model = SimpleNamespace(
        rpn=None,
        rpn_info={"cfg": str(rpn_cfg), "sha256": "a" * 64, "cache_dir": str(tmp_path / "cache")},
    )
    data_cfg = EasyDict(
        DATA_PATH=str(tiny_dataset(tmp_path / "data")), DATA_SPLIT={"train": "train"}
    )
    runs = []

    def predict(rpn, loader, **kw):  # each run's proposals differ: a served stale one shows
        runs.append(len(runs))
        score = np.array([0.5 + len(runs) / 10])
        anno = {"frame_id": "seq_a_000", "boxes_lidar": np.zeros((1, 9)), "score": score,
                "pred_labels": np.array([1])}  # fmt: skip
        return [anno], None

    monkeypatch.setattr(proposals, "build_dataloader", lambda *a, **kw: (None, None, None))
    monkeypatch.setattr(proposals, "predict_dataset", predict)
    return model, data_cfg, rpn_cfg, runs


def proposals_of(model, data_cfg):
    table, path = proposals.training_proposals(
        model, data_cfg, ["Vehicle"], device=None, logger=None
    )
    return float(table["seq_a_000"][0, 9]), path


def test_a_changed_rpn_setting_or_dataset_is_computed_again(setup):
    model, data_cfg, rpn_cfg, runs = setup
    score, path = proposals_of(model, data_cfg)
    assert runs == [0] and path.is_file()
    assert proposals_of(model, data_cfg) == (score, path) and runs == [0]  # read from the cache

    # a setting changed in the RPN's config file (the same file name, the same checkpoint)
    rpn_cfg.write_text(
        rpn_cfg.read_text()
        + "MODEL:\n  DENSE_HEAD:\n    POST_PROCESSING:\n      SCORE_THRESH: 0.3\n"
    )
    changed, other = proposals_of(model, data_cfg)
    assert runs == [0, 1] and other != path and changed != score and path.is_file()

    # a frame of the train split rewritten in place
    frame = Path(data_cfg.DATA_PATH) / PROCESSED_DATA_TAG / "seq_a" / "0000.npy"
    stat = frame.stat()
    np.save(frame, np.ones((3, 6), np.float32))  # same size: only the mtime tells
    os.utime(frame, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1))
    rewritten, third = proposals_of(model, data_cfg)
    assert runs == [0, 1, 2] and third not in (path, other) and rewritten != changed
    assert proposals_of(model, data_cfg) == (rewritten, third) and runs == [0, 1, 2]

    # another RPN checkpoint: another file too
    model.rpn_info["sha256"] = "b" * 64
    assert proposals_of(model, data_cfg)[1] not in (path, other, third) and len(runs) == 4


def test_a_file_whose_record_disagrees_with_its_name_is_refused(setup):
    model, data_cfg, _, runs = setup
    _, path = proposals_of(model, data_cfg)
    data = torch.load(path, weights_only=True)
    data["rpn_model_config"]["MODEL"]["DENSE_HEAD"]["POST_PROCESSING"]["SCORE_THRESH"] = 0.9
    torch.save(data, path)
    with pytest.raises(ValueError) as err:
        proposals_of(model, data_cfg)
    assert str(path) in str(err.value)
    assert "rpn_model_config: differs at MODEL.DENSE_HEAD.POST_PROCESSING.SCORE_THRESH" in str(
        err.value
    )
    assert runs == [0]


def test_a_split_leaving_the_cache_folder_is_refused(setup):
    """``DATA_SPLIT.train`` names the cache file ``<split>.pt``: ``../x`` is refused before the
    RPN runs or anything is written."""
    model, data_cfg, _, runs = setup
    data = Path(data_cfg.DATA_PATH)
    (data / "x.txt").write_text("seq_a.tfrecord\n")  # ImageSets/../x.txt exists
    data_cfg.DATA_SPLIT = {"train": "../x"}
    with pytest.raises(UnsafePathError, match=r"DATA_SPLIT\.train '\.\./x' \(from "):
        proposals_of(model, data_cfg)
    assert runs == [] and not Path(model.rpn_info["cache_dir"]).exists()
