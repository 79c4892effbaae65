"""Empty frames (0 points, 0 boxes; docs/conventions.md) through ``AtlasWaymoDataset``: as the
current frame and at every history position of 1-, 4-, 8- and 32-frame inputs, for each attack
family. An empty spoofed frame still carries its attack (an injection run's phantom, alone on
the fallback ground; a removal target recorded as lost), never a silent clean frame."""

import numpy as np
import pytest
from atlas_helpers import dataset_cfg, synthetic_library, write_tiny_waymo

from pcdet_atlas.attacks import COUNTERS
from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.attacks.metadata import validate_meta
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.datasets.multiframe import (
    SECONDS_PER_FRAME,
    outside_ego_mask,
    transform_points_to_frame,
)
from pcdet_atlas.datasets.waymo_dataset import EGO_RADIUS_M

CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
SEQ = "segment-tinyval_with_camera_labels"  # 72 frames: the run 32..63, then 8 clean frames
SEQ_B = "segment-tinyvalb_with_camera_labels"  # 34 frames: the run 32..33
EMPTY = 40  # the empty frame of SEQ, mid-run; a 32-frame window ending at 71 still holds it
FAMILIES = ["inj_rel_easy", "inj_global_easy", "rem_30"]
# history positions of the empty frame: every one up to 8 frames; first, middle, last of 32
POSITIONS = {1: [0], 4: [0, 1, 2, 3], 8: list(range(8)), 32: [0, 1, 16, 31]}


def blank_frames(root, sequence, frames):
    """Make ``frames`` of ``sequence`` empty: a ``(0, 6)`` float32 file, no labels and a point
    count of 0 in the info pkl."""
    path = wf.sequence_pkl_path(root, sequence)
    infos = wf.load_sequence_infos(path)
    for k in frames:
        wf.save_frame_points(wf.frame_npy_path(root, sequence, k), np.zeros((0, 6), np.float32))
        infos[k]["num_points_of_each_lidar"] = [0] * len(infos[k]["num_points_of_each_lidar"])
        infos[k]["annos"] = wf.make_annos([], [], [], [], [], [], [], [], infos[k]["pose"])
    wf.save_sequence_infos(path, infos)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = write_tiny_waymo(
        tmp_path_factory.mktemp("empty_frames"), frames={"train": 4, "val": 72, "valb": 34}
    )
    blank_frames(root, SEQ, [EMPTY])
    blank_frames(root, SEQ_B, [32])  # the first frame of SEQ_B's run
    return root, synthetic_library(root, tmp_path_factory.mktemp("empty_frames_lib"))


def make(data, name, num_frames, split="val"):
    root, library = data
    cfg = dataset_cfg(root, multiframe=num_frames > 1)
    if num_frames > 1:
        cfg.SEQUENCE_CONFIG.SAMPLE_OFFSET = [1 - num_frames, 0]
    cfg.DATA_PROCESSOR = [p for p in cfg.DATA_PROCESSOR if p.NAME != "shuffle_points"]
    cfg.DATA_SPLIT = {"train": "train", "test": split}
    attack = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / f"{name}.yaml")
    if "TRACE_LIBRARY" in attack:
        attack.TRACE_LIBRARY.PATH = str(library)
    ds = AtlasWaymoDataset(cfg, CLASSES, attack, root_path=root)
    assert [info["point_cloud"]["sample_idx"] for info in ds.infos] == list(range(len(ds)))
    return ds


def frame_block(sample, position):
    """The rows of the frame at history ``position`` of a stacked multi-frame sample (its
    lag column; rows of a frame are contiguous, in the frame's order)."""
    return sample["points"][sample["points"][:, -1] == np.float32(SECONDS_PER_FRAME * position)]


def assert_same_meta(a, b):
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray) or isinstance(b[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        else:
            assert a[key] == b[key], key


def check_empty_frame_meta(meta, injection):
    """An empty spoofed frame keeps its attack, and its record says what happened."""
    validate_meta(meta)
    assert meta["spoofed"] and meta["run_id"] == 0 and meta["run_position"] == EMPTY - 32
    assert meta["num_removed"] == 0  # no scene point to occlude or remove
    if injection:  # the phantom is in the scan, alone in its rays
        assert meta["target_obj_id"] == "phantom_run0" and meta["target_box"] is not None
        assert 0 < meta["num_visible"] <= meta["num_spoof_points"]
        assert meta["tracked"] and meta["fired"]
    else:  # no label: the target is lost on this frame (still named), nothing removed
        assert meta["target_obj_id"] is not None and meta["target_box"] is None
        assert not meta["tracked"] and not meta["fired"]


@pytest.mark.parametrize("num_frames", sorted(POSITIONS))
@pytest.mark.parametrize("name", FAMILIES)
def test_empty_frame_as_current_and_at_every_history_position(data, name, num_frames):
    injection = name.startswith("inj")
    single = make(data, name, 1)
    with COUNTERS.measure() as work:
        current = single[EMPTY]  # the empty frame as the current frame of a 1-frame input
    meta = current["attack"]
    check_empty_frame_meta(meta, injection)
    points = current["points"]  # (K, 5): the phantom's points only, or no row
    assert points.shape == (meta["num_visible"], 5) and points.dtype == np.float32
    if injection:  # the documented ground fallback: no scene point near the phantom
        assert work["ground_fallbacks"] == 1
        box = meta["target_box"]
        assert box[2] - box[5] / 2 == pytest.approx(single.attack.ground.fallback_z, abs=1e-5)
    if num_frames == 1:
        return

    ds = make(data, name, num_frames)
    infos = {k: ds.get_frame_info(SEQ, k) for k in range(len(ds))}
    # newest window first: the empty frame is first simulated as history
    for position in sorted(POSITIONS[num_frames], reverse=True):
        sample = ds[EMPTY + position]
        validate_meta(sample["attack"])
        assert sample["attack"]["spoofed"] == (32 <= EMPTY + position <= 63)
        counts = [len(frame_block(sample, q)) for q in range(num_frames)]
        assert sum(counts) == len(sample["points"]) and sample["points"].shape[1] == 6
        assert all(n > 0 for q, n in enumerate(counts) if q != position)
        # the empty frame's block: its phantom points (moved into the current frame, those
        # the ego has driven over dropped as the ego's own) or nothing
        block = frame_block(sample, position)
        if position == 0:
            np.testing.assert_array_equal(block[:, :5], points)
            assert_same_meta(sample["attack"], {**meta, "sequence_name": SEQ})
        else:
            pose, pose_cur = infos[EMPTY]["pose"], infos[EMPTY + position]["pose"]
            moved = transform_points_to_frame(points[:, :3], pose, pose_cur)
            outside = outside_ego_mask(moved, EGO_RADIUS_M)
            assert len(block) == np.count_nonzero(outside) > (0 if injection else -1)
            np.testing.assert_allclose(block[:, :3], moved[outside], atol=1e-4)
            np.testing.assert_array_equal(block[:, 3:5], points[outside, 3:5])
        if not injection and position == 1:  # the lost target coasts and is re-acquired
            assert sample["attack"]["tracked"]
            assert sample["attack"]["target_obj_id"] == meta["target_obj_id"]
        # bitwise the same frame and record, read as history or as the current frame
        np.testing.assert_array_equal(ds.get_lidar(SEQ, EMPTY), points)
        assert_same_meta(ds.frame_attack_meta(SEQ, EMPTY), {**meta, "sequence_name": SEQ})


@pytest.mark.parametrize("num_frames", [1, 4])
def test_an_empty_first_frame_leaves_the_removal_run_without_a_target(data, num_frames):
    """No box at the run's first frame: the run has no target, every spoofed frame records
    it (untargeted, nothing removed) and its points are the clean ones."""
    removal = make(data, "rem_30", num_frames, split="valb")
    clean = make(data, "clean", num_frames, split="valb")
    for k in (32, 33):
        sample, reference = removal[k], clean[k]
        meta = sample["attack"]
        validate_meta(meta)
        assert meta["spoofed"] and meta["family"] == "removal" and meta["run_id"] == 0
        assert meta["target_obj_id"] is None and meta["target_box"] is None
        assert not meta["tracked"] and not meta["fired"] and meta["num_removed"] == 0
        np.testing.assert_array_equal(sample["points"], reference["points"])
    current = removal[32]["points"]
    assert len(current if num_frames == 1 else frame_block(removal[32], 0)) == 0
