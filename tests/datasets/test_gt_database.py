"""The GT database (tools/data/create_gt_database.py) and every shipped dataset YAML building on
it."""

from __future__ import annotations

import logging
import runpy
from pathlib import Path

import numpy as np
import pytest
from malicious_files import malicious_pickle
from waymo_tiny_data import CLASS_NAMES, write_tiny_waymo

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import WaymoDataset, gt_database
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.datasets.gt_database import create_groundtruth_database, gt_database_paths
from pcdet_atlas.datasets.multiframe import SequenceConfig
from pcdet_atlas.ops.boxes import points_in_boxes_mask
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.utils.common import save_pickle
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError, load_pickle

CFG_DIR = REPO_ROOT / "cfgs" / "dataset_configs"
TAG = wf.PROCESSED_DATA_TAG


@pytest.fixture(scope="module")
def db_root(tmp_path_factory):
    root = write_tiny_waymo(tmp_path_factory.mktemp("tiny_db"))
    tool = runpy.run_path(
        str(REPO_ROOT / "tools" / "data" / "create_gt_database.py"), run_name="tool"
    )
    tool["main"](
        [
            "--cfg_file",
            str(CFG_DIR / "waymo_dataset.yaml"),
            str(CFG_DIR / "waymo_dataset_multiframe.yaml"),
            "--data_path",
            str(root),
        ]
    )
    return root


def _load(path):
    return load_pickle(path)  # what the project's readers use: its own files load


def test_single_frame_database(db_root):
    paths = gt_database_paths(db_root, TAG, "train", 1)
    assert paths["info"].name == f"{TAG}_waymo_dbinfos_train_sampled_1.pkl"
    assert paths["global"].name == f"{TAG}_gt_database_train_sampled_1_global.npy"
    db = _load(paths["info"])
    assert set(db) == {"Vehicle", "Pedestrian", "Cyclist"}  # Sign is not a used class
    infos = _load(db_root / f"{TAG}_infos_train.pkl")
    assert len(infos) == 11  # the concatenated split infos are written too
    # Vehicles from every 4th frame of the concatenated infos, Pedestrians every 2nd
    frames = lambda name: sorted({infos.index(_info(infos, d)) for d in db[name]})  # noqa: E731
    assert frames("Vehicle") == [0, 4, 8]
    assert frames("Pedestrian") == [0, 2, 4, 6, 8, 10]
    assert frames("Cyclist") == list(range(11))
    global_points = np.load(paths["global"])
    assert global_points.dtype == np.float32 and global_points.shape[1] == 5
    for entry in db["Vehicle"] + db["Pedestrian"]:
        assert set(entry) == {
            "name",
            "path",
            "sequence_name",
            "sample_idx",
            "gt_idx",
            "box3d_lidar",
            "num_points_in_gt",
            "difficulty",
            "global_data_offset",
        }
        assert entry["path"] == (
            f"{TAG}_gt_database_train_sampled_1/{entry['sequence_name']}_"
            f"{entry['sample_idx']:04d}_{entry['name']}_{entry['gt_idx']}.bin"
        )
        pts = np.fromfile(db_root / entry["path"], dtype=np.float32).reshape(-1, 5)
        start, end = entry["global_data_offset"]
        np.testing.assert_array_equal(pts, global_points[start:end])
        assert len(pts) == entry["num_points_in_gt"]
        assert entry["box3d_lidar"].shape == (9,)
        # points are box-centred and lie in the box
        centred_box = np.concatenate([[0, 0, 0], entry["box3d_lidar"][3:7]])[None]
        centred_box[:, 3:6] += 1e-4  # points on a face, up to float32 rounding of the shift
        assert points_in_boxes_mask(pts[:, :3].astype(np.float64), centred_box).all()
        # and they are the frame's points in that box (tanh'd intensity, NLZ kept per config)
        info = _info(infos, entry)
        raw = np.load(wf.frame_npy_path(db_root, entry["sequence_name"], entry["sample_idx"]))
        # gt_idx counts the frame's boxes after the Vehicle/Pedestrian subsampling (OpenPCDet)
        k = int(np.nonzero((info["annos"]["gt_boxes_lidar"] == entry["box3d_lidar"]).all(1))[0][0])
        inside = points_in_boxes_mask(
            raw[:, :3].astype(np.float64), info["annos"]["gt_boxes_lidar"][k][None]
        )[0]
        assert inside.sum() == len(pts) == info["annos"]["num_points_in_gt"][k]
        np.testing.assert_allclose(np.sort(pts[:, 3]), np.sort(np.tanh(raw[inside, 3])), rtol=1e-6)


def _info(infos, entry):
    return next(
        i
        for i in infos
        if i["point_cloud"]["lidar_sequence"] == entry["sequence_name"]
        and i["point_cloud"]["sample_idx"] == entry["sample_idx"]
    )


def test_multi_frame_database(db_root):
    paths = gt_database_paths(db_root, TAG, "train", 1, (-4, 0))
    assert paths["info"].name == f"{TAG}_waymo_dbinfos_train_sampled_1_multiframe_-4_to_0.pkl"
    db = _load(paths["info"])
    global_points = np.load(paths["global"])
    assert global_points.shape[1] == 6
    lags = set(np.round(global_points[:, 5].astype(np.float64), 6))
    assert lags == {0.0, 0.1, 0.2, 0.3, 0.4}  # 5 frames, whatever SAMPLE_OFFSET says
    single = _load(gt_database_paths(db_root, TAG, "train", 1)["info"])
    assert len(db["Vehicle"]) == len(single["Vehicle"]) > 0
    for a, b in zip(db["Vehicle"], single["Vehicle"]):
        assert a["path"].startswith(f"{TAG}_gt_database_train_sampled_1_multiframe_-4_to_0/")
        assert a["num_points_in_gt"] >= b["num_points_in_gt"]
        assert (a["sequence_name"], a["sample_idx"]) == (b["sequence_name"], b["sample_idx"])
        start, end = a["global_data_offset"]
        current = (global_points[start:end, 5] == 0).sum()
        # frame 0's history is frame 0 again (clipped), with lag 0 as well
        copies = 5 if a["sample_idx"] == 0 else 1
        assert current == copies * b["num_points_in_gt"]


@pytest.mark.parametrize("name", sorted(p.name for p in CFG_DIR.glob("*.yaml")))
@pytest.mark.parametrize("training", [True, False])
def test_every_dataset_yaml_builds_and_loads(db_root, name, training):
    cfg = cfg_from_yaml_file(CFG_DIR / name)
    expected_root = "data/synthetic_waymo" if name.startswith("synthetic") else "data/waymo"
    assert cfg.DATA_PATH == expected_root  # relative: resolved against the repository root
    ds = DATASETS.get(cfg.DATASET)(cfg, CLASS_NAMES, training=training, root_path=db_root)
    sample = ds[len(ds) - 1]
    multiframe = ds.sequence_cfg is not None
    assert sample["points"].shape[1] == ds.num_point_features == (6 if multiframe else 5)
    assert sample["points"].dtype == np.float32 and np.isfinite(sample["points"]).all()
    assert sample["gt_boxes"].shape[1] == (10 if multiframe else 8)
    if training:
        names = [a.NAME for a in cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST]
        assert ds.data_augmentor.names == names
    batch = ds.collate_batch([sample, ds[0]])
    assert batch["batch_size"] == 2


@pytest.mark.parametrize("multiframe", [False, True])
def test_training_with_gt_sampling_adds_objects(db_root, multiframe):
    cfg = cfg_from_yaml_file(
        CFG_DIR / ("waymo_dataset_multiframe.yaml" if multiframe else "waymo_dataset.yaml")
    )
    cfg.SAMPLED_INTERVAL = {"train": 1, "test": 1}
    cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST[:1]  # gt_sampling
    cfg.DATA_PROCESSOR = []
    ds = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=db_root)
    plain = WaymoDataset(
        cfg_from_yaml_file(CFG_DIR / "waymo_dataset.yaml"), CLASS_NAMES, False, db_root
    )
    added = 0
    for i in range(len(ds)):
        sample = ds[i]
        n_plain = len(ds.get_annotations(ds.infos[i])["gt_names"])
        added += len(sample["gt_boxes"]) - n_plain
        assert len(plain.infos) > 0
    assert added > 0


def test_backup_db_info_and_disable_aug_list(db_root, caplog):
    """A missing single-frame database falls back (with a warning) to BACKUP_DB_INFO, as
    OpenPCDet; DISABLE_AUG_LIST removes augmentations by name."""
    cfg = cfg_from_yaml_file(CFG_DIR / "waymo_dataset.yaml")
    sampling = cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST[0]
    sampling.DB_INFO_PATH = ["no_such_dbinfos.pkl"]
    sampling.BACKUP_DB_INFO = {
        "DB_INFO_PATH": f"{TAG}_waymo_dbinfos_train_sampled_1_multiframe_-4_to_0.pkl",
        "DB_DATA_PATH": f"{TAG}_gt_database_train_sampled_1_multiframe_-4_to_0_global.npy",
        "NUM_POINT_FEATURES": 6,
    }
    cfg.DATA_AUGMENTOR.DISABLE_AUG_LIST = ["random_world_flip", "random_world_scaling"]
    logger = logging.getLogger("test_backup_db_info")
    with caplog.at_level("WARNING", logger=logger.name):
        ds = WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=db_root, logger=logger)
    assert "using BACKUP_DB_INFO" in caplog.text
    assert ds.data_augmentor.names == ["gt_sampling", "random_world_rotation"]
    sampler = ds.data_augmentor.transforms[0][1]
    assert sampler.num_point_features == 6
    sample = ds[0]
    assert sample["points"].shape[1] == 5  # multi-frame objects reduced to their lag-0 points
    assert "flip_x" not in sample and "noise_scale" not in sample and "noise_rot" in sample


@pytest.mark.parametrize("config", ["waymo_dataset.yaml", "waymo_dataset_multiframe.yaml"])
def test_workers_build_the_same_database(db_root, tmp_path, config):
    dataset = WaymoDataset(
        cfg_from_yaml_file(CFG_DIR / config), ["Vehicle", "Pedestrian", "Cyclist"],
        training=False, root_path=db_root,
    )  # fmt: skip
    dataset.set_split("train")
    built = {}
    for workers in (0, 2):
        paths = create_groundtruth_database(
            dataset, save_path=tmp_path / str(workers), workers=workers
        )
        # the three outputs and nothing else (the workers' job file is gone)
        assert sorted((tmp_path / str(workers)).iterdir()) == sorted(paths.values())
        db = _load(paths["info"])
        bins = {f.name: f.read_bytes() for f in paths["dir"].iterdir()}
        built[workers] = (db, bins, paths["global"].read_bytes())
    (db0, bins0, global0), (db2, bins2, global2) = built[0], built[2]
    assert bins0 == bins2 and len(bins0) > 10
    assert global0 == global2
    assert list(db0) == list(db2)
    for name in db0:
        assert len(db0[name]) == len(db2[name]) > 0
        for a, b in zip(db0[name], db2[name]):
            assert list(a) == list(b)
            assert Path(a.pop("path")).name == Path(b.pop("path")).name
            box_a, box_b = a.pop("box3d_lidar"), b.pop("box3d_lidar")
            np.testing.assert_array_equal(box_a, box_b)
            assert a == b


def test_the_workers_job_is_plain_values_and_one_that_would_run_code_is_refused(
    db_root, tmp_path, monkeypatch
):
    """The job file holds the dataset's registered class name, plain config, root, split and
    infos (read with the restricted unpickler): each worker rebuilds the dataset from it."""
    dataset = WaymoDataset(
        cfg_from_yaml_file(CFG_DIR / "waymo_dataset_multiframe.yaml"), ["Vehicle"],
        training=False, root_path=db_root,
    )  # fmt: skip
    dataset.set_split("train")
    dataset.all_infos = dataset.all_infos[::2]  # a caller's subset travels with the job
    job = gt_database._worker_job(dataset, SequenceConfig((-4, 0)), ["Vehicle"], tmp_path / "db")
    monkeypatch.setattr(gt_database, "_WORKER_JOB", None)
    gt_database._load_worker_job(save_pickle(job, tmp_path / "job.pkl"))
    rebuilt, sequence_cfg, used_classes, db_dir = gt_database._WORKER_JOB
    assert type(rebuilt) is WaymoDataset and rebuilt.split == "train"
    assert rebuilt.root_path == dataset.root_path and rebuilt.sequence_cfg is not None
    assert [i["frame_id"] for i in rebuilt.all_infos] == [i["frame_id"] for i in dataset.all_infos]
    assert sequence_cfg.sample_offset == (-4, 0) and not sequence_cfg.onehot_timestamp
    assert used_classes == ["Vehicle"] and db_dir == tmp_path / "db"

    marker = tmp_path / "marker"
    evil = malicious_pickle(tmp_path / "evil_job.pkl", marker, job)
    with pytest.raises(RefusedGlobalError, match=rf"{evil}: refused to unpickle the global "):
        gt_database._load_worker_job(evil)
    assert not marker.exists()

    class Unregistered(WaymoDataset):
        pass

    other = Unregistered(dataset.dataset_cfg, ["Vehicle"], training=False, root_path=db_root)
    with pytest.raises(ValueError, match=r"Unregistered is not in the DATASETS registry"):
        create_groundtruth_database(other, save_path=tmp_path / "out", workers=2)
    assert not (tmp_path / "out").exists()


def test_negative_workers_is_an_error(db_root):
    dataset = WaymoDataset(
        cfg_from_yaml_file(CFG_DIR / "waymo_dataset.yaml"), ["Vehicle"], training=False,
        root_path=db_root,
    )  # fmt: skip
    with pytest.raises(ValueError, match="workers must be >= 0, got -1"):
        create_groundtruth_database(dataset, workers=-1)


def test_a_rebuild_killed_before_the_info_file_leaves_none(db_root, tmp_path, monkeypatch):
    """The info file's offsets index the stacked points: a rebuild killed while it writes them
    leaves no info file (an error naming it) instead of the old one beside new points."""
    from pcdet_atlas.datasets import gt_database

    dataset = WaymoDataset(
        cfg_from_yaml_file(CFG_DIR / "waymo_dataset_multiframe.yaml"), ["Vehicle"],
        training=False, root_path=db_root,
    )  # fmt: skip
    dataset.set_split("train")
    paths = create_groundtruth_database(dataset, save_path=tmp_path)
    assert paths["info"].is_file() and paths["global"].is_file()

    def killed(path, write, **kw):  # the objects' .bin files are written, then the points
        if not str(path).endswith("_global.npy"):
            return real_write_atomic(path, write, **kw)
        raise KeyboardInterrupt(f"killed while writing {path}")

    real_write_atomic = gt_database.write_atomic

    monkeypatch.setattr(gt_database, "write_atomic", killed)
    with pytest.raises(KeyboardInterrupt, match="_global.npy"):
        create_groundtruth_database(dataset, save_path=tmp_path)
    assert not paths["info"].exists()


def test_a_rebuild_replaces_symlinks_planted_in_the_database_folder(db_root, tmp_path):
    """A dataset received with a ``*_gt_database_*`` folder holding ``<object>.bin -> ~/.bashrc``:
    rebuilding the database replaces the link by the object's points, the target is untouched."""
    dataset = WaymoDataset(
        cfg_from_yaml_file(CFG_DIR / "waymo_dataset.yaml"), CLASS_NAMES, training=False,
        root_path=db_root,
    )  # fmt: skip
    dataset.set_split("train")
    paths = create_groundtruth_database(dataset, save_path=tmp_path)
    entry = _load(paths["info"])["Cyclist"][0]
    planted = paths["dir"] / Path(entry["path"]).name
    points = planted.read_bytes()
    victim = tmp_path / "victim"
    victim.write_text("IMPORTANT USER DATA\n")
    planted.unlink()
    planted.symlink_to(victim)
    create_groundtruth_database(dataset, save_path=tmp_path)
    assert victim.read_text() == "IMPORTANT USER DATA\n"
    assert not planted.is_symlink() and planted.read_bytes() == points
