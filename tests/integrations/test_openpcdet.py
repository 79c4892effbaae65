"""pcdet_atlas.integrations.openpcdet against a stand-in OpenPCDet (openpcdet_standin/pcdet):
the stand-in has the signatures of OpenPCDet at the commit the integration names; the ATLAS
dataset registers in OpenPCDet's registry and serves every frame, current and history, attacked
exactly as this package's AtlasWaymoDataset does; tools/openpcdet_test.py runs an OpenPCDet
model on the variants and scores it as tools/evaluate_predictions.py scores its predictions."""

from __future__ import annotations

import copy
import importlib
import inspect
import logging
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from easydict import EasyDict
from malicious_files import malicious_checkpoint, malicious_pickle

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset as ProjectAtlasDataset
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.evaluation import load_results
from pcdet_atlas.evaluation.results.schema import METRIC_KEYS
from pcdet_atlas.utils.common import load_tool
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

STANDIN = Path(__file__).resolve().parent / "openpcdet_standin"
ATTACKS = REPO_ROOT / "cfgs" / "attacks"
CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]

#: OpenPCDet at commit 8cacccec11db6f59bf6934600c9a175dae254806 (v0.6.0): every interface the
#: integration touches, as its source declares it
OPENPCDET_SIGNATURES = {
    "pcdet.config:cfg_from_yaml_file": "(cfg_file, config)",
    "pcdet.config:cfg_from_list": "(cfg_list, config)",
    "pcdet.datasets:build_dataloader": "(dataset_cfg, class_names, batch_size, dist, "
    "root_path=None, workers=4, seed=None, logger=None, training=True, "
    "merge_all_iters_to_one_epoch=False, total_epochs=0)",
    "pcdet.datasets.dataset:DatasetTemplate.__init__": "(self, dataset_cfg=None, "
    "class_names=None, training=True, root_path=None, logger=None)",
    "pcdet.datasets.dataset:DatasetTemplate.generate_prediction_dicts": "(self, batch_dict, "
    "pred_dicts, class_names, output_path=None)",
    "pcdet.datasets.dataset:DatasetTemplate.prepare_data": "(self, data_dict)",
    "pcdet.datasets.dataset:DatasetTemplate.collate_batch": "(batch_list, _unused=False)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.__init__": "(self, dataset_cfg, "
    "class_names, training=True, root_path=None, logger=None)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.set_split": "(self, split)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.include_waymo_data": "(self, mode)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.load_pred_boxes_to_dict": "(self, "
    "pred_boxes_path)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.get_lidar": "(self, sequence_name, "
    "sample_idx)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.get_sequence_data": "(self, info, points, "
    "sequence_name, sample_idx, sequence_cfg, load_pred_boxes=False)",
    "pcdet.datasets.waymo.waymo_dataset:WaymoDataset.__getitem__": "(self, index)",
    "pcdet.models:build_network": "(model_cfg, num_class, dataset)",
    "pcdet.models:load_data_to_gpu": "(batch_dict)",
    # Detector3DTemplate's, which every OpenPCDet detector inherits
    "pcdet.models.detectors.point_count_oracle:PointCountOracle.load_params_from_file": "(self, "
    "filename, logger, to_cpu=False, pre_trained_path=None)",
    "pcdet.models.detectors.point_count_oracle:PointCountOracle._load_state_dict": "(self, "
    "model_state_disk, *, strict=True)",
}


def resolve(name: str):
    module, _, attr = name.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@pytest.fixture
def openpcdet(monkeypatch):
    """The integration imported with the stand-in on the path (and forgotten afterwards)."""

    def forget():
        for name in list(sys.modules):
            if name == "pcdet" or name.startswith(("pcdet.", "pcdet_atlas.integrations")):
                del sys.modules[name]

    forget()
    monkeypatch.syspath_prepend(str(STANDIN))
    integration = importlib.import_module("pcdet_atlas.integrations.openpcdet")
    yield integration
    forget()


def test_the_stand_in_has_openpcdets_signatures(openpcdet):
    assert "8cacccec11db6f59bf6934600c9a175dae254806" == openpcdet.OPENPCDET_COMMIT
    for name, signature in OPENPCDET_SIGNATURES.items():
        assert str(inspect.signature(resolve(name))) == signature, name
    assert isinstance(inspect.getattr_static(resolve("pcdet.datasets:DatasetTemplate"),
                      "collate_batch"), staticmethod)  # fmt: skip
    # the integration's overrides keep OpenPCDet's signatures (its constructor adds `attack`)
    ours, theirs = openpcdet.AtlasWaymoDataset, resolve("pcdet.datasets:WaymoDataset")
    for method in ("get_lidar", "__getitem__", "set_split", "collate_batch", "include_waymo_data",
                   "load_pred_boxes_to_dict"):  # fmt: skip
        assert inspect.signature(getattr(ours, method)) == inspect.signature(
            getattr(theirs, method)
        ), method
    assert str(inspect.signature(ours.__init__)) == (
        "(self, dataset_cfg, class_names, training=True, root_path=None, logger=None, attack=None)"
    )


def openpcdet_data_cfg(root, *, disable_nlz=True, interval=1, offset=(-3, 0)) -> EasyDict:
    """An OpenPCDet Waymo DATA_CONFIG of the fixture data (the keys OpenPCDet's reads)."""
    cfg = {
        "DATASET": "WaymoDataset", "DATA_PATH": str(root),
        "PROCESSED_DATA_TAG": "waymo_processed_data_v0_5_0",
        "POINT_CLOUD_RANGE": [-75.2, -75.2, -2, 75.2, 75.2, 4],
        "DATA_SPLIT": {"train": "train", "test": "val"},
        "SAMPLED_INTERVAL": {"train": 5, "test": interval},
        "DISABLE_NLZ_FLAG_ON_POINTS": disable_nlz,
    }  # fmt: skip
    cfg["SEQUENCE_CONFIG"] = {"ENABLED": True, "SAMPLE_OFFSET": list(offset)}
    return EasyDict(cfg)


def project_dataset(root, attack, *, disable_nlz=True):
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "dataset_configs" / "synthetic_waymo.yaml")
    cfg.DATA_PATH = str(root)
    cfg.DISABLE_NLZ_FLAG_ON_POINTS = disable_nlz
    return ProjectAtlasDataset(cfg, CLASSES, attack, training=False)


@pytest.mark.parametrize("disable_nlz", [True, False])
def test_every_frame_current_or_history_is_attacked_as_atlas_serves_it(
    openpcdet, synthetic_root, disable_nlz
):
    """rem_40 spoofs frames 32..63 of the 70-frame sequence; the input of the frame after the
    first one it removes points from reads that frame as history: each frame read, current or
    history, comes back as this package's AtlasWaymoDataset serves it, and the sample carries
    the same attack record."""
    from pcdet.datasets import __all__ as registry
    from pcdet.datasets import build_dataloader

    assert registry["AtlasWaymoDataset"] is openpcdet.AtlasWaymoDataset
    attack = ATTACKS / "rem_40.yaml"
    data_cfg = openpcdet.dataset.attack_data_cfg(
        openpcdet_data_cfg(synthetic_root, disable_nlz=disable_nlz), attack
    )
    dataset, loader, _ = build_dataloader(data_cfg, CLASSES, batch_size=2, dist=False,
                                          workers=0, logger=logging.getLogger("t"),
                                          training=False)  # fmt: skip
    assert type(dataset) is openpcdet.AtlasWaymoDataset
    reference = project_dataset(synthetic_root, attack, disable_nlz=disable_nlz)
    clean = project_dataset(synthetic_root, ATTACKS / "clean.yaml", disable_nlz=disable_nlz)
    seq = dataset.infos[0]["point_cloud"]["lidar_sequence"]  # the one val sequence, 70 frames
    removed = next(k for k in range(32, 63)
                   if len(reference.get_lidar(seq, k)) < len(clean.get_lidar(seq, k)))  # fmt: skip
    current = removed + 1
    read = []
    get_lidar = dataset.get_lidar

    def recording(sequence_name, sample_idx):
        points = get_lidar(sequence_name, sample_idx)
        read.append((int(sample_idx), points))
        return points

    dataset.get_lidar = recording
    index = next(i for i, info in enumerate(dataset.infos)
                 if info["point_cloud"]["sample_idx"] == current)  # fmt: skip
    sample = dataset[index]
    assert [k for k, _ in read] == [current, removed, removed - 1, removed - 2]
    for k, points in read:
        np.testing.assert_array_equal(points, reference.get_lidar(seq, k))
    assert len(read[1][1]) < len(clean.get_lidar(seq, removed))  # the history frame attacked
    np.testing.assert_equal(sample["atlas_attack"], reference.frame_attack_meta(seq, current))
    assert sample["atlas_attack"]["spoofed"] and sample["points"].shape[1] == 6  # + time lag
    batch = next(iter(loader))
    assert batch["atlas_attack"] == [dataset.frame_attack_meta(seq, 0),
                                     dataset.frame_attack_meta(seq, 1)]  # fmt: skip
    assert isinstance(batch["points"], np.ndarray) and batch["batch_size"] == 2


def test_a_config_without_attack_or_of_another_dataset_is_an_error(openpcdet, synthetic_root):
    from pcdet_atlas.config import ConfigError

    cfg = openpcdet_data_cfg(synthetic_root)
    cfg.DATASET = "AtlasWaymoDataset"
    with pytest.raises(ConfigError, match=r"needs DATA_CONFIG\.ATLAS_ATTACK"):
        openpcdet.AtlasWaymoDataset(cfg, CLASSES, training=False, logger=logging.getLogger("t"))
    cfg.DATASET = "KittiDataset"
    with pytest.raises(ConfigError, match=r"DATASET is 'KittiDataset'"):
        openpcdet.dataset.attack_data_cfg(cfg, ATTACKS / "rem_40.yaml")


def same_scores(got: dict, want: dict):
    for key in ("asr", "num_targets", "num_success", "confidence", "family", "num_frames"):
        assert got[key] == want[key], key
    for key in METRIC_KEYS:
        assert got[key] == pytest.approx(want[key], abs=1e-9), key


@pytest.mark.slow
def test_openpcdet_test_tool_runs_and_scores_an_openpcdet_model(
    openpcdet, synthetic_root, injection, tmp_path
):
    inj = tmp_path / "inj_global_hard.yaml"
    inj.write_text(
        f"_BASE_CONFIG_: {ATTACKS / 'inj_global_hard.yaml'}\n"
        f"TRACE_LIBRARY:\n  PATH: {injection.TRACE_LIBRARY.PATH}\n  MIN_POINTS: 100\n"
    )
    model_cfg = {
        "CLASS_NAMES": CLASSES,
        "DATA_CONFIG": {k: (dict(v) if isinstance(v, dict) else v) for k, v in
                        openpcdet_data_cfg(synthetic_root, interval=7, offset=(-1, 0)).items()},
        # rem_40's targets keep 200-3,100 of their 4,200-6,400 points on the spoofed frames
        "MODEL": {"NAME": "PointCountOracle", "MIN_POINTS": 4000, "SCORE_POINTS": 8000},
    }  # fmt: skip
    cfg_file = tmp_path / "oracle.yaml"
    cfg_file.write_text(yaml.safe_dump(copy.deepcopy(model_cfg)))
    ckpt = tmp_path / "oracle.pth"
    torch.save({"model_state": {"scale": torch.tensor(0.9)}}, ckpt)
    out = tmp_path / "out"
    results = load_tool("openpcdet_test").main([
        "--cfg_file", str(cfg_file), "--ckpt", str(ckpt), "--attacks",
        f"clean,rem_40,{inj}", "--out_dir", str(out), "--device", "cpu", "--workers", "0",
        "--batch_size", "2",
    ])  # fmt: skip
    written = load_results(out / "results.json")
    assert list(written["variants"]) == ["clean", "rem_40", "inj_global_hard"]
    rem = written["variants"]["rem_40"]
    assert rem["num_targets"] > 0 and rem["num_success"] == rem["num_targets"]  # hidden
    assert written["variants"]["clean"]["L2/mAP"] > 0  # the oracle finds the dense boxes
    assert written["variants"]["clean"]["extra"]["clean_predictions"] is False
    assert written == results | {"created": written["created"]}
    # the same predictions scored by tools/evaluate_predictions.py, the attack drawn on the fly
    data_cfg = REPO_ROOT / "cfgs" / "dataset_configs" / "synthetic_waymo.yaml"
    scored = load_tool("evaluate_predictions").main([
        "--data_cfg", str(data_cfg), "--data_path", str(synthetic_root), "--temporal_window",
        "2", "--predictions", *(f"{v}={out / n / 'result.pkl'}" for v, n in
                                [("clean", "clean"), (str(inj), "inj_global_hard"),
                                 ("rem_40", "rem_40")]),
        "--out_dir", str(tmp_path / "scored"), "--set", "SAMPLED_INTERVAL", "train:5,test:7",
    ])  # fmt: skip
    for variant, entry in written["variants"].items():
        same_scores(scored["variants"][variant], entry)
    load_tool("report").main(["--results", str(out), "--out_dir", str(tmp_path / "report")])
    assert "oracle" in (tmp_path / "report" / "report.md").read_text()


def test_a_checkpoint_that_could_run_code_is_refused_before_openpcdet_reads_it(openpcdet, tmp_path):
    marker = tmp_path / "ran"
    ckpt = malicious_checkpoint(tmp_path / "evil.pth", marker, model_state={})
    with pytest.raises(RefusedGlobalError, match="evil.pth"):
        openpcdet.evaluate_openpcdet(
            {"CLASS_NAMES": CLASSES, "DATA_CONFIG": {}, "MODEL": {}}, ckpt, "clean",
            tmp_path / "out", config="x.yaml", model_name="x", device="cpu",
        )  # fmt: skip
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_the_datasets_pickles_are_read_by_the_restricted_unpickler(
    openpcdet, synthetic_root, tmp_path
):
    """OpenPCDet reads a sequence's info pkl and a USE_PREDBOX file with pickle.load (the
    stand-in does too); the integration's dataset reads both without running what they name."""
    marker = tmp_path / "ran"
    root = tmp_path / "data"
    (root / "ImageSets").mkdir(parents=True)
    (root / "ImageSets" / "val.txt").write_text("segment-evil_with_camera_labels.tfrecord\n")
    tag = "waymo_processed_data_v0_5_0"
    pkl = root / tag / "segment-evil_with_camera_labels" / "segment-evil_with_camera_labels.pkl"
    malicious_pickle(pkl, marker, value=[])
    log = logging.getLogger("t")
    with pytest.raises(ValueError, match=r"camera_labels\.pkl: .*refused to unpickle"):
        openpcdet.AtlasWaymoDataset(openpcdet_data_cfg(root), CLASSES, training=False, logger=log)
    assert not marker.exists()
    # the split file and the processed-data folder are named by one path component each
    for key, value in (("DATA_SPLIT", {"train": "train", "test": "../val"}),
                       ("PROCESSED_DATA_TAG", "../data")):  # fmt: skip
        cfg = openpcdet_data_cfg(root)
        cfg[key] = value
        with pytest.raises(ValueError, match=r"\.\./"):
            openpcdet.AtlasWaymoDataset(cfg, CLASSES, training=False, logger=log)
    # a listed sequence without its info file is an error (OpenPCDet skips it)
    pkl.unlink()
    with pytest.raises(ValueError, match="segment-evil_with_camera_labels.*no info pkl"):
        openpcdet.AtlasWaymoDataset(openpcdet_data_cfg(root), CLASSES, training=False, logger=log)
    # the predicted boxes of a USE_PREDBOX config
    boxes = malicious_pickle(tmp_path / "roi_boxes.pkl", marker, value=[])
    cfg = openpcdet_data_cfg(synthetic_root)
    cfg.USE_PREDBOX, cfg.ROI_BOXES_PATH = True, {"train": str(boxes), "test": str(boxes)}
    attack = ATTACKS / "rem_40.yaml"
    with pytest.raises(RefusedGlobalError, match="roi_boxes.pkl"):
        openpcdet.AtlasWaymoDataset(cfg, CLASSES, training=False, logger=log, attack=attack)
    assert not marker.exists()


def test_the_weights_loaded_are_the_ones_read_with_weights_only(openpcdet, synthetic_root,
                                                                tmp_path, monkeypatch):  # fmt: skip
    """The checkpoint is read once: a file swapped for one that runs code after the check is
    never unpickled (OpenPCDet's load_params_from_file would read it again)."""
    marker = tmp_path / "ran"
    ckpt = tmp_path / "oracle.pth"
    torch.save({"model_state": {"scale": torch.tensor(0.25)}, "version": "x"}, ckpt)
    checked = openpcdet.evaluate.read_checkpoint

    def read_then_swap(path, **kwargs):
        got = checked(path, **kwargs)
        malicious_checkpoint(Path(path), marker, model_state={"scale": torch.tensor(0.5)})
        return got

    class Stop(Exception):
        pass

    def capture(model, loader, class_names):
        raise Stop(model)

    monkeypatch.setattr(openpcdet.evaluate, "read_checkpoint", read_then_swap)
    monkeypatch.setattr(openpcdet.evaluate, "predict_variant", capture)
    cfg = {"CLASS_NAMES": CLASSES, "DATA_CONFIG": openpcdet_data_cfg(synthetic_root, interval=50),
           "MODEL": EasyDict(NAME="PointCountOracle", MIN_POINTS=1, SCORE_POINTS=1)}  # fmt: skip
    with pytest.raises(Stop) as stopped:
        openpcdet.evaluate_openpcdet(
            cfg, ckpt, "clean", tmp_path / "out", config="x.yaml", model_name="x", device="cpu"
        )
    assert float(stopped.value.args[0].scale.detach()) == 0.25
    assert not marker.exists()
    with pytest.raises(ValueError, match="no 'model_state'"):
        openpcdet.evaluate.load_checkpoint_weights(
            stopped.value.args[0], {"state": {}}, "x.pth", logging.getLogger("t")
        )


def test_without_openpcdet_the_tool_names_the_import_error(monkeypatch, tmp_path, capsys):
    for name in list(sys.modules):
        if name == "pcdet" or name.startswith(("pcdet.", "pcdet_atlas.integrations")):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "pcdet", None)  # import pcdet -> ImportError
    tool = load_tool("openpcdet_test")
    with pytest.raises(tool.openpcdet.OpenPCDetMissingError, match=r"OpenPCDet is not "
                       r"importable \(ModuleNotFoundError: .*pcdet"):  # fmt: skip
        tool.main(["--cfg", "x.yaml", "--ckpt", "x.pth", "--out_dir", str(tmp_path)])
    for name in list(sys.modules):
        if name.startswith("pcdet_atlas.integrations"):
            del sys.modules[name]
