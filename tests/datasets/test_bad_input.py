"""Every bad input of issue 2 raises an error naming the file, the frame or key, and what was
expected; empty frames are valid (tested in test_waymo_dataset.py)."""

from __future__ import annotations

import pickle
import re
import shutil

import numpy as np
import pytest
from malicious_files import malicious_pickle
from waymo_tiny_data import CLASS_NAMES, DATASET_CFG, dataset_cfg, write_tiny_waymo

from pcdet_atlas.config import ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets import WaymoDataset
from pcdet_atlas.datasets import waymo_format as wf

SEQ = "segment-777_with_camera_labels"


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return write_tiny_waymo(
        tmp_path_factory.mktemp("pristine"), {"train": [(SEQ, 4)], "val": [(SEQ, 4)]}
    )


@pytest.fixture
def root(pristine, tmp_path):
    dst = tmp_path / "root"
    shutil.copytree(pristine, dst)
    return dst


def _dataset(root, **overrides):
    return WaymoDataset(dataset_cfg(**overrides), CLASS_NAMES, training=False, root_path=root)


def _edit_infos(root, edit):
    path = wf.sequence_pkl_path(root, SEQ)
    with open(path, "rb") as f:
        infos = pickle.load(f)
    edit(infos)
    with open(path, "wb") as f:
        pickle.dump(infos, f)
    return path


# ---------------------------------------------------------------------------- point files
def test_missing_npy_names_the_file(root):
    npy = wf.frame_npy_path(root, SEQ, 2)
    npy.unlink()
    ds = _dataset(root)
    with pytest.raises(wf.WaymoFormatError, match="0002.npy: frame file not found") as info:
        ds[2]
    assert isinstance(info.value.__cause__, FileNotFoundError)
    ds[1]  # the others still load


def test_missing_history_npy_names_the_file(root):
    wf.frame_npy_path(root, SEQ, 0).unlink()
    ds = WaymoDataset(dataset_cfg(multiframe=True), CLASS_NAMES, training=False, root_path=root)
    with pytest.raises(wf.WaymoFormatError, match=r"0000\.npy"):
        ds[2]  # frame 2 needs frame 0 as history


def test_truncated_npy_names_the_file(root):
    npy = wf.frame_npy_path(root, SEQ, 1)
    data = npy.read_bytes()
    npy.write_bytes(data[: len(data) // 2])
    with pytest.raises(wf.WaymoFormatError, match=r"0001\.npy: cannot read frame points") as info:
        _dataset(root)[1]
    assert info.value.__cause__ is not None


def test_not_an_npy_file(root):
    wf.frame_npy_path(root, SEQ, 1).write_text("hello")
    with pytest.raises(wf.WaymoFormatError, match=r"0001\.npy"):
        _dataset(root).get_lidar(SEQ, 1)


@pytest.mark.parametrize("spare_rows", [0, 1000])  # a plain load and the injection's
@pytest.mark.parametrize("rows", [10**13, 3])  # 218 TiB, or fewer rows than the file holds
def test_npy_header_shape_not_matching_the_file_size(root, spare_rows, rows):
    """The header's shape is checked against the file's size before anything is allocated: a
    declared (10**13, 6) was a bare MemoryError."""
    npy = wf.frame_npy_path(root, SEQ, 1)
    with open(npy, "wb") as f:
        header = {"descr": "<f4", "fortran_order": False, "shape": (rows, 6)}
        np.lib.format.write_array_header_1_0(f, header)
        f.write(np.zeros((10, 6), np.float32).tobytes())
    size = npy.stat().st_size
    with pytest.raises(
        wf.WaymoFormatError,
        match=rf"0001\.npy: cannot read frame points .*declares shape \({rows}, 6\) of float32 "
        rf"\({rows * 24} data bytes\) but the file holds {size} bytes",
    ):
        wf.load_frame_points(npy, spare_rows)


@pytest.mark.parametrize("columns", [5, 7])
def test_wrong_column_count(root, columns):
    np.save(wf.frame_npy_path(root, SEQ, 1), np.zeros((10, columns), np.float32))
    with pytest.raises(
        wf.WaymoFormatError, match=rf"0001\.npy: expected a \(N, 6\).*\(10, {columns}\)"
    ):
        _dataset(root)[1]


def test_wrong_dtype(root):
    np.save(wf.frame_npy_path(root, SEQ, 1), np.zeros((10, 6), np.float64))
    with pytest.raises(wf.WaymoFormatError, match=r"0001\.npy: expected float32"):
        _dataset(root)[1]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("column", [1, 3, 4])  # y, intensity, elongation
def test_nan_inf_points(root, bad, column):
    npy = wf.frame_npy_path(root, SEQ, 3)
    pts = np.load(npy)
    pts[5, column] = bad
    np.save(npy, pts)
    with pytest.raises(wf.WaymoFormatError, match=r"0003\.npy: 1 point\(s\) with NaN/inf .*row 5"):
        _dataset(root)[3]


@pytest.mark.parametrize("flag", [0.0, 2.0, 0.5, -0.0])
def test_nlz_flag_other_than_plus_minus_one(root, flag):
    """A converter writing NLZ flags {0, 1} would lose every point to the NLZ filter silently."""
    npy = wf.frame_npy_path(root, SEQ, 3)
    pts = np.load(npy)
    pts[7:, 5] = flag
    np.save(npy, pts)
    expected = rf"0003\.npy: the NLZ flag \(column 5\) must be -1 .* or 1 .*; {len(pts) - 7} "
    expected += rf"point\(s\) have another value \(first at row 7: {re.escape(repr(flag))}\)"
    for disable in (False, True):
        with pytest.raises(wf.WaymoFormatError, match=expected):
            _dataset(root, DISABLE_NLZ_FLAG_ON_POINTS=disable)[3]


def test_nlz_flags_of_project_written_frames_pass(root):
    """Both flag values load; the filter keeps exactly the -1 rows."""
    rows = wf.load_frame_points(wf.frame_npy_path(root, SEQ, 3))
    assert set(np.unique(rows[:, 5]).tolist()) == {-1.0, 1.0}
    kept = _dataset(root, DISABLE_NLZ_FLAG_ON_POINTS=False).get_lidar(SEQ, 3)
    assert len(kept) == int((rows[:, 5] == -1).sum())


# ---------------------------------------------------------------------------- info pkls
def test_pkl_entry_missing_key(root):
    path = _edit_infos(root, lambda infos: infos[2].pop("pose"))
    with pytest.raises(wf.WaymoFormatError, match=r"\[frame 2\]: missing key 'pose'") as info:
        _dataset(root)
    assert str(path) in str(info.value)


def test_pkl_annos_missing_key(root):
    _edit_infos(root, lambda infos: infos[1]["annos"].pop("num_points_in_gt"))
    with pytest.raises(
        wf.WaymoFormatError, match=r"\[frame 1\]: missing key 'annos.num_points_in_gt'"
    ):
        _dataset(root)


def test_pkl_point_cloud_missing_key(root):
    _edit_infos(root, lambda infos: infos[0]["point_cloud"].pop("sample_idx"))
    with pytest.raises(
        wf.WaymoFormatError, match=r"\[frame 0\]: missing key 'point_cloud.sample_idx'"
    ):
        _dataset(root)


@pytest.mark.parametrize(
    "column,value,message",
    [(0, np.nan, "has NaN/inf values"), (6, np.inf, "has NaN/inf values"),
     (3, 0.0, "size .* every size must be > 0"), (5, -1.5, "size .* every size must be > 0")],
)  # fmt: skip
def test_pkl_gt_boxes_non_finite_or_not_positive(root, column, value, message):
    def edit(infos):
        infos[2]["annos"]["gt_boxes_lidar"][0, column] = value

    path = _edit_infos(root, edit)
    with pytest.raises(wf.WaymoFormatError, match=rf"\[frame 2\]: 'annos.gt_boxes_lidar'.*{message}"
                       ) as info:  # fmt: skip
        _dataset(root)
    assert str(path) in str(info.value)


def test_frame_index_gap(root):
    path = _edit_infos(root, lambda infos: infos.pop(1))
    with pytest.raises(
        wf.WaymoFormatError, match="frame index gap: entry 1 has sample_idx 2"
    ) as info:
        _dataset(root)
    assert str(path) in str(info.value)


def test_unknown_class_name(root):
    def edit(infos):
        infos[3]["annos"]["name"] = np.array(["Car"] + list(infos[3]["annos"]["name"][1:]))

    _edit_infos(root, edit)
    with pytest.raises(
        wf.WaymoFormatError, match=r"\[frame 3\]: unknown class name\(s\) \['Car'\]"
    ):
        _dataset(root)


def test_wrong_sequence_name_inside_pkl(root):
    def edit(infos):
        infos[0]["point_cloud"]["lidar_sequence"] = "segment-other"

    _edit_infos(root, edit)
    with pytest.raises(wf.WaymoFormatError, match=r"\[frame 0\]: 'point_cloud.lidar_sequence'"):
        _dataset(root)


def test_corrupt_pkl(root):
    wf.sequence_pkl_path(root, SEQ).write_bytes(b"\x80\x04garbage")
    with pytest.raises(wf.WaymoFormatError, match=rf"{SEQ}\.pkl: cannot unpickle"):
        _dataset(root)


def test_a_pkl_that_would_run_code_is_refused(root, tmp_path):
    marker = tmp_path / "marker"
    path = malicious_pickle(wf.sequence_pkl_path(root, SEQ), marker)
    with pytest.raises(wf.WaymoFormatError, match=rf"{SEQ}\.pkl: refused to unpickle the global "):
        _dataset(root)
    assert not marker.exists()
    with pytest.raises(wf.WaymoFormatError, match=re.escape(str(path))):
        wf.load_sequence_infos(path)
    assert not marker.exists()


@pytest.mark.parametrize("dtype", ["<U10", object])
def test_openpcdet_infos_with_numpy_values_load(root, dtype):
    """OpenPCDet's infos hold numpy arrays (names as ``<U10`` or object arrays of str) and
    numpy scalars: what the restricted unpickler reads."""

    def numpy_values(infos):
        for info in infos:
            info["annos"]["name"] = np.asarray(info["annos"]["name"], dtype=dtype)
            info["metadata"]["timestamp_micros"] = np.int64(info["metadata"]["timestamp_micros"])

    path = _edit_infos(root, numpy_values)
    infos = wf.load_sequence_infos(path)
    assert infos[0]["annos"]["name"].dtype == np.dtype(dtype)
    assert isinstance(infos[0]["metadata"]["timestamp_micros"], np.int64)
    assert len(_dataset(root)) == 4


def test_missing_sequence_pkl_is_not_skipped(root):
    (root / "ImageSets" / "val.txt").write_text(f"{SEQ}.tfrecord\nsegment-404.tfrecord\n")
    with pytest.raises(
        wf.WaymoFormatError, match="'segment-404' listed in ImageSets has no info pkl"
    ):
        _dataset(root)


def test_missing_image_set(root):
    (root / "ImageSets" / "val.txt").unlink()
    with pytest.raises(wf.WaymoFormatError, match=r"ImageSets/val\.txt: split file not found"):
        _dataset(root)


def test_evaluation_names_the_first_unlabelled_frame(root):
    """Every frame is checked for 'annos', not only the first."""
    pkl = _edit_infos(root, lambda infos: infos[2].pop("annos"))
    ds = _dataset(root)
    det_annos = [
        {"name": np.array([]), "score": np.zeros(0), "boxes_lidar": np.zeros((0, 7)),
         "frame_id": info["frame_id"]}
        for info in ds.infos
    ]  # fmt: skip
    expected = (
        rf"{re.escape(str(pkl))} \[frame 2\]: frame {SEQ}_002 of sequence '{SEQ}' has no ground "
        rf"truth \('annos'\), so split 'val' cannot be evaluated \(1 of its 4 frames"
    )
    with pytest.raises(wf.WaymoFormatError, match=expected):
        ds.evaluation(det_annos, CLASS_NAMES)
    _edit_infos(root, lambda infos: [info.pop("annos", None) for info in infos])
    with pytest.raises(wf.WaymoFormatError, match=r"split 'val' has no ground truth \('annos'\)"):
        _dataset(root).evaluation(det_annos, CLASS_NAMES)


def test_train_with_speed_needs_9_values(root):
    def edit(infos):
        infos[0]["annos"]["gt_boxes_lidar"] = infos[0]["annos"]["gt_boxes_lidar"][:, :7]

    _edit_infos(root, edit)
    ds = _dataset(root, TRAIN_WITH_SPEED=True)
    with pytest.raises(wf.WaymoFormatError, match=r"_000: TRAIN_WITH_SPEED needs \(M, 9\)"):
        ds[0]


# ---------------------------------------------------------------------------- configs
def test_unknown_data_config_key(root):
    cfg = dataset_cfg()
    cfg.SAMPLED_INTERVALS = {"train": 1, "test": 1}
    with pytest.raises(ConfigError, match="unknown key 'SAMPLED_INTERVALS' in DATA_CONFIG"):
        WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)


def test_unknown_key_in_yaml_names_the_file(root, tmp_path):
    yaml_path = tmp_path / "bad.yaml"
    yaml_path.write_text(
        "_BASE_CONFIG_: cfgs/dataset_configs/waymo_dataset.yaml\nFILTER_EMPTY_BOX: True\n"
    )
    cfg = cfg_from_yaml_file(yaml_path)
    with pytest.raises(ConfigError, match=r"unknown key 'FILTER_EMPTY_BOX'.*bad\.yaml"):
        WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)


def test_missing_base_file(tmp_path):
    yaml_path = tmp_path / "child.yaml"
    yaml_path.write_text("_BASE_CONFIG_: no_such_base.yaml\nDATA_PATH: x\n")
    with pytest.raises(
        ConfigError, match=r"child\.yaml: _BASE_CONFIG_ 'no_such_base\.yaml' not found"
    ):
        cfg_from_yaml_file(yaml_path)


@pytest.mark.parametrize("training", [True, False])
def test_unknown_key_in_augmentor_item(root, training):
    cfg = dataset_cfg(augment=True)
    cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST[0].WORLD_ROT_ANGEL = [0, 1]
    with pytest.raises(ConfigError, match=r"unknown key 'WORLD_ROT_ANGEL'.*random_world_flip"):
        WaymoDataset(cfg, CLASS_NAMES, training=training, root_path=root)


def test_unknown_augmentation_name(root):
    cfg = dataset_cfg(augment=True)
    cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST[0].NAME = "random_world_flop"
    with pytest.raises(ConfigError, match=r"random_world_flop.*Did you mean 'random_world_flip'"):
        WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=root)


def test_unknown_key_in_processor_item(root):
    cfg = dataset_cfg()
    cfg.DATA_PROCESSOR[0].REMOVE_OUTSIDE_BOX = True
    with pytest.raises(ConfigError, match=r"unknown key 'REMOVE_OUTSIDE_BOX'.*DATA_PROCESSOR\[0\]"):
        WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)


def test_voxelization_in_data_processor_is_refused(root):
    cfg = dataset_cfg()
    cfg.DATA_PROCESSOR.append(
        {"NAME": "transform_points_to_voxels", "VOXEL_SIZE": [0.1, 0.1, 0.15]}
    )
    with pytest.raises(ConfigError, match="voxelization is part of the model"):
        WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)


def test_unknown_key_in_sequence_config(root):
    cfg = dataset_cfg(multiframe=True)
    cfg.SEQUENCE_CONFIG.SAMPLE_OFFSETS = [-3, 0]
    with pytest.raises(
        ConfigError, match="unknown key 'SAMPLE_OFFSETS' in DATA_CONFIG.SEQUENCE_CONFIG"
    ):
        WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)


def test_feature_list_must_fit_the_columns(root):
    cfg = dataset_cfg(multiframe=True)
    cfg.POINT_FEATURE_ENCODING.src_feature_list = ["x", "y", "z", "intensity", "elongation"]
    cfg.POINT_FEATURE_ENCODING.used_feature_list = ["x", "y", "z", "intensity"]
    with pytest.raises(ConfigError, match="produces 6 point columns"):
        WaymoDataset(cfg, CLASS_NAMES, training=False, root_path=root)


def test_missing_gt_database_names_the_file(root):
    cfg = dataset_cfg()  # keeps gt_sampling out; put it back
    shipped = cfg_from_yaml_file(DATASET_CFG).DATA_AUGMENTOR.AUG_CONFIG_LIST
    cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = shipped[:1]
    with pytest.raises(
        wf.WaymoFormatError, match=r"dbinfos_train_sampled_1\.pkl: GT database info file not found"
    ):
        WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=root)


def test_a_gt_database_pkl_that_would_run_code_is_refused(root, tmp_path):
    cfg = dataset_cfg()
    cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = cfg_from_yaml_file(
        DATASET_CFG
    ).DATA_AUGMENTOR.AUG_CONFIG_LIST[:1]  # gt_sampling
    marker = tmp_path / "marker"
    malicious_pickle(root / "waymo_processed_data_v0_5_0_waymo_dbinfos_train_sampled_1.pkl", marker)
    with pytest.raises(
        wf.WaymoFormatError, match=r"dbinfos_train_sampled_1\.pkl: refused to unpickle the global"
    ):
        WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=root)
    assert not marker.exists()


def test_missing_required_augmentation_key(root):
    cfg = dataset_cfg(augment=True)
    augs = cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST
    rotation = next(a for a in augs if a.NAME == "random_world_rotation")
    del rotation["WORLD_ROT_ANGLE"]
    with pytest.raises(
        ConfigError,
        match=r"missing required key random_world_rotation\.WORLD_ROT_ANGLE in .*AUG_CONFIG_LIST",
    ):
        WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=root)
    rotation["WORLD_ROT_ANGLE"] = 0.78  # a scalar angle is symmetric: fine
    scaling = next(a for a in augs if a.NAME == "random_world_scaling")
    scaling["WORLD_SCALE_RANGE"] = 1.05  # a scalar scale is not
    with pytest.raises(
        ConfigError, match=r"WORLD_SCALE_RANGE = 1\.05 .*expected a \[low, high\] pair"
    ):
        WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=root)


@pytest.mark.parametrize("key", ["SAMPLE_GROUPS", "PREPARE.filter_by_min_points"])
def test_gt_sampling_class_typo_names_key_and_file(root, key):
    """'Pedestrain:10' is no class: an error before anything is loaded, not a silent no-op."""
    cfg = dataset_cfg()
    shipped = cfg_from_yaml_file(DATASET_CFG).DATA_AUGMENTOR.AUG_CONFIG_LIST
    cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST = shipped[:1]
    item = cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST[0]
    if key == "SAMPLE_GROUPS":
        item.SAMPLE_GROUPS = ["Vehicle:15", "Pedestrain:10"]
    else:
        item.PREPARE.filter_by_min_points = ["Vehicle:5", "Pedestrain:5"]
    expected = (
        rf"gt_sampling\.{re.escape(key)} \(DATA_AUGMENTOR\.AUG_CONFIG_LIST\[0\] of "
        rf"{re.escape(str(DATASET_CFG))}\): \['Pedestrain'\] is not a class name"
    )
    with pytest.raises(ConfigError, match=expected):
        WaymoDataset(cfg, CLASS_NAMES, training=True, root_path=root)


def test_empty_split_names_split_and_path(root):
    (root / "ImageSets" / "val.txt").write_text("")
    with pytest.raises(wf.WaymoFormatError, match=r"ImageSets/val\.txt: split 'val' lists no seq"):
        _dataset(root)
