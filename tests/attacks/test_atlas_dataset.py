import shutil

import numpy as np
import pytest
import torch
from atlas_helpers import load_tool, synthetic_library, write_tiny_waymo

from pcdet_atlas.attacks import COUNTERS
from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.attacks.base import FrameAttack, build_attack
from pcdet_atlas.attacks.metadata import validate_meta
from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import WaymoDataset, collate_batch
from pcdet_atlas.datasets.waymo_format import (
    load_sequence_infos,
    save_sequence_infos,
    sequence_pkl_path,
)
from pcdet_atlas.registry import DATASETS

CLASSES = ["Vehicle", "Pedestrian", "Cyclist"]
ATTACKS = REPO_ROOT / "cfgs" / "attacks"


def data_cfg(root, multiframe=False):
    name = "synthetic_waymo_multiframe.yaml" if multiframe else "synthetic_waymo.yaml"
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "dataset_configs" / name)
    cfg.DATA_PATH = str(root)
    return cfg


@pytest.fixture(scope="module")
def library_path(synthetic_root, tmp_path_factory):
    return synthetic_library(synthetic_root, tmp_path_factory.mktemp("atlas_lib"))


def attack_cfg(name, library_path=None):
    cfg = cfg_from_yaml_file(ATTACKS / f"{name}.yaml")
    if library_path is not None and "TRACE_LIBRARY" in cfg:
        cfg.TRACE_LIBRARY.PATH = str(library_path)
    return cfg


def make(root, name, library_path=None, multiframe=False):
    return AtlasWaymoDataset(
        data_cfg(root, multiframe), CLASSES, attack_cfg(name, library_path), root_path=root
    )


def test_registered_and_clean_frames_do_no_work(synthetic_root, library_path):
    assert DATASETS.get("AtlasWaymoDataset") is AtlasWaymoDataset
    clean = WaymoDataset(data_cfg(synthetic_root), CLASSES, training=False)
    ds = make(synthetic_root, "inj_global_hard", library_path)
    for index in (5, 31, 64):  # clean frames, 31 and 64 carry shadow targets
        with COUNTERS.measure() as work:
            sample = ds[index]
        assert all(v == 0 for v in work.values()), work
        np.testing.assert_array_equal(sample["points"], clean[index]["points"])
        validate_meta(sample["attack"])
        assert not sample["attack"]["spoofed"]
        assert sample["attack"]["target_is_shadow"] == (index != 5)
    with COUNTERS.measure() as work:
        sample = ds[40]
    assert work["frames_simulated"] == 1 and work["raycast_calls"] == 1
    assert work["history_frames_resimulated"] == 0
    assert sample["attack"]["spoofed"] and sample["attack"]["num_visible"] > 0
    assert len(sample["points"]) != len(clean[40]["points"])
    # a run is (sequence, run_id): run ids are numbered per sequence
    assert sample["attack"]["sequence_name"] == ds.infos[40]["point_cloud"]["lidar_sequence"]


@pytest.mark.parametrize("index,simulated,history", [(31, 0, 0), (33, 2, 1), (34, 3, 2), (40, 4, 3),
                                                     (65, 2, 2), (67, 0, 0)])  # fmt: skip
def test_multiframe_resimulates_only_spoofed_history(synthetic_root, index, simulated, history):
    ds = make(synthetic_root, "rem_30", multiframe=True)
    with COUNTERS.measure() as work:
        sample = ds[index]
    assert work["frames_simulated"] == simulated
    assert work["history_frames_resimulated"] == history
    assert sample["points"].shape[1] == 6 and sample["attack"]["spoofed"] == (32 <= index <= 63)


def test_frame_identical_as_current_or_history_and_in_any_order(synthetic_root, library_path):
    seq = make(synthetic_root, "inj_rel_medium", library_path).infos[0]["point_cloud"][
        "lidar_sequence"
    ]
    direct = make(synthetic_root, "inj_rel_medium", library_path)
    first = {k: direct.get_lidar(seq, k) for k in (40, 41, 63)}
    hist = make(synthetic_root, "inj_rel_medium", library_path, multiframe=True)
    hist[44]  # frames 41..43 are first simulated as history (run state built from there)
    hist[64]  # 63 as history, from a clean current frame
    for k in (63, 41, 40):  # reverse order
        np.testing.assert_array_equal(hist.get_lidar(seq, k), first[k])
    # the stacked history block of frame 41 is frame 40's attacked points, moved by the poses
    pose = {k: hist.get_frame_info(seq, k)["pose"] for k in (40, 41)}
    stacked, counts, _, _ = hist.get_sequence_data(
        hist.infos[41], hist.get_lidar(seq, 41), seq, 41, hist.sequence_cfg
    )
    block = stacked[counts[0] : counts[0] + counts[1]]
    rel = np.linalg.inv(np.asarray(pose[41], np.float64)) @ np.asarray(pose[40], np.float64)
    xyz = first[40][:, :3].astype(np.float64) @ rel[:3, :3].T + rel[:3, 3]
    outside_ego = ~((np.abs(xyz[:, 0]) < 1.0) & (np.abs(xyz[:, 1]) < 1.0))
    np.testing.assert_allclose(block[:, :3], xyz[outside_ego], atol=1e-4)
    np.testing.assert_array_equal(block[:, 3:5], first[40][outside_ego, 3:5])


def _batches(dataset, workers):
    subset = torch.utils.data.Subset(dataset, [30, 31, 32, 45, 63, 64])
    loader = torch.utils.data.DataLoader(
        subset, batch_size=2, num_workers=workers, collate_fn=collate_batch, shuffle=False
    )
    return list(loader)


@pytest.mark.slow
def test_attacked_points_are_the_file_rows_minus_removed_plus_added(synthetic_root, library_path):
    """The one-selection path (phantom rows written into the room read with the frame) equals
    applying the attack to the frame file's rows and loading the result; an attack family
    whose ``max_added_points`` is too low takes the copying path with the same result."""
    from pcdet_atlas.datasets.waymo_format import load_frame_points

    ds = make(synthetic_root, "inj_rel_hard", library_path)
    seq = ds.infos[0]["point_cloud"]["lidar_sequence"]
    frame = 45
    rows = load_frame_points(ds.frame_path(seq, frame))
    result = ds.attack.simulate(rows, ds.sequence_data(seq), frame)
    assert result.removed_rows().size > 0 and len(result.added) > 0
    want = ds.loaded_points(result.apply(rows))  # added rows: flag -1, outside any NLZ
    assert 0 < len(result.added) <= ds.attack.max_added_points(ds.sequence_data(seq), frame)
    np.testing.assert_array_equal(ds.get_lidar(seq, frame), want)
    ds.attack.max_added_points = lambda seq, frame_idx: 0  # a bound that is too low
    np.testing.assert_array_equal(ds.get_lidar(seq, frame), want)


def test_added_rows_of_apply_are_kept_by_the_nlz_filter(synthetic_root):
    """``FrameAttack.apply`` on frame-file rows flags the added rows as outside any no-label
    zone by default, so a loader that drops NLZ rows keeps every phantom row."""
    cfg = data_cfg(synthetic_root)
    cfg.DISABLE_NLZ_FLAG_ON_POINTS = False
    ds = WaymoDataset(cfg, CLASSES, training=False)
    rows = np.zeros((4, 6), np.float32)
    rows[:, 5] = [-1, 1, -1, -1]  # one scene row in a no-label zone
    added = np.full((3, 5), 0.5, np.float32)
    out = FrameAttack.from_removed(4, np.array([2]), added, {}).apply(rows)
    np.testing.assert_array_equal(out[3:, 5], [-1, -1, -1])
    loaded = ds.loaded_points(out)
    assert len(loaded) == 2 + 3
    np.testing.assert_array_equal(loaded[2:, :3], added[:, :3])


def test_one_attack_shared_by_two_dataset_roots(tmp_path):
    """A built attack handed to datasets of two roots with the same sequence names gives each
    root its own runs (the run cache is keyed by the root), as an attack of its own would."""
    roots = [write_tiny_waymo(tmp_path / name, frames={"train": 6, "val": 66}) for name in "ab"]
    seq_name = "segment-tinyval_with_camera_labels"
    pkl = sequence_pkl_path(roots[1], seq_name)
    infos = load_sequence_infos(pkl)
    for k, info in enumerate(infos):  # root b: the ego turns faster
        turn = np.eye(4, dtype=np.float32)
        turn[:2, :2] = [[np.cos(0.01 * k), -np.sin(0.01 * k)], [np.sin(0.01 * k), np.cos(0.01 * k)]]
        info["pose"] = info["pose"] @ turn
    save_sequence_infos(pkl, infos)
    build_trace_library(roots[0], TraceFilter(min_points=100)).save(tmp_path / "lib.npz")
    cfg = attack_cfg("inj_global_easy", tmp_path / "lib.npz")
    cfg.TRACE_LIBRARY.MIN_POINTS = 100
    shared = build_attack(cfg)
    got, want = [], []
    for root in roots:
        ds = AtlasWaymoDataset(data_cfg(root), CLASSES, shared, root_path=root)
        own = AtlasWaymoDataset(data_cfg(root), CLASSES, cfg, root_path=root)
        got.append(ds.frame_attack_meta(seq_name, 40)["target_box"])
        want.append(own.frame_attack_meta(seq_name, 40)["target_box"])
        np.testing.assert_array_equal(ds.get_lidar(seq_name, 40), own.get_lidar(seq_name, 40))
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(want[0], want[1])  # the roots' runs do differ


def test_set_split_forgets_the_sequences_and_frames_of_the_last_split(synthetic_root):
    ds = make(synthetic_root, "rem_30", multiframe=True)
    seq = ds.infos[0]["point_cloud"]["lidar_sequence"]
    ds[40]
    assert ds._frame_cache and ds.sequence_data(seq).name == seq
    ds.set_split("train")
    assert ds.split == "train" and not ds._frame_cache
    with pytest.raises(KeyError, match="not in split 'train'"):
        ds.sequence_data(seq)
    ds.set_split("val")
    _assert_same_sample(ds[40], make(synthetic_root, "rem_30", multiframe=True)[40])


def test_same_output_with_zero_or_two_workers(synthetic_root, library_path):
    out = {}
    for workers in (0, 2):
        out[workers] = _batches(make(synthetic_root, "inj_global_easy", library_path), workers)
    assert len(out[0]) == len(out[2]) > 0
    for a, b in zip(out[0], out[2]):
        np.testing.assert_array_equal(a["points"], b["points"])
        assert len(a["attack"]) == len(b["attack"]) > 0
        for ma, mb in zip(a["attack"], b["attack"]):
            assert ma.keys() == mb.keys()
            for key in ma:
                if isinstance(ma[key], np.ndarray):
                    np.testing.assert_array_equal(ma[key], mb[key])
                else:
                    assert ma[key] == mb[key]


def test_lifecycle_metadata_over_a_run(synthetic_root):
    ds = make(synthetic_root, "rem_50")
    metas = [ds.frame_attack_meta(ds.infos[0]["point_cloud"]["lidar_sequence"], k)
             for k in range(len(ds.infos))]  # fmt: skip
    for k, m in enumerate(metas):
        validate_meta(m)
        assert m["sequence_name"] == ds.infos[0]["point_cloud"]["lidar_sequence"]
        assert m["spoofed"] == (32 <= k <= 63)
        assert m["lifecycle_k"] == (k - 31 if 31 <= k <= 69 else -1)
        assert m["target_is_shadow"] == ((k == 31 or k >= 64) and m["tracked"])
        if m["spoofed"]:
            assert (m["target_box"] is not None) == (m["tracked"] and m["fired"])
            assert m["run_position"] == k - 32 and m["run_id"] == 0
    fired = [m for m in metas if m["fired"]]
    assert fired and all(m["num_removed"] > 0 for m in fired)
    ids = [m["target_obj_id"] for m in metas if m["tracked"]]
    assert sum(i == ids[0] for i in ids) >= 0.95 * len(ids)  # one object tracked throughout


@pytest.mark.parametrize("keep_nlz", [True, False])
def test_generate_atlas_roundtrip_and_resume(tmp_path, keep_nlz):
    root = write_tiny_waymo(tmp_path / "tiny", frames={"train": 6, "val": 66}, nlz_every=7)
    load_tool("data/build_trace_library").main(
        ["--cfg", str(ATTACKS / "inj_rel_hard.yaml"), "--data_path", str(root),
         "--set", "TRACE_LIBRARY.MIN_POINTS", "100"]
    )  # fmt: skip
    cfg_path = tmp_path / "data.yaml"
    cfg_path.write_text(
        f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/dataset_configs/synthetic_waymo.yaml'}\n"
        f"DATA_PATH: {root}\nDISABLE_NLZ_FLAG_ON_POINTS: {keep_nlz}\n"
    )
    out = tmp_path / "out"
    args = ["--data_cfg", str(cfg_path), "--attack", str(ATTACKS / "inj_rel_hard.yaml"),
            "--out_dir", str(out), "--set", "TRACE_LIBRARY.MIN_POINTS", "100"]  # fmt: skip
    gen = load_tool("data/generate_atlas")
    gen.main(args)
    cfg = cfg_from_yaml_file(ATTACKS / "inj_rel_hard.yaml")
    cfg.TRACE_LIBRARY.MIN_POINTS = 100
    live_cfg, out_cfg = cfg_from_yaml_file(cfg_path), cfg_from_yaml_file(cfg_path)
    out_cfg.DATA_PATH = str(out)
    live = AtlasWaymoDataset(live_cfg, CLASSES, cfg, root_path=root)
    written = WaymoDataset(out_cfg, CLASSES, training=False, root_path=out)
    seq = live.infos[0]["point_cloud"]["lidar_sequence"]
    for k in (10, 31, 32, 50, 63, 65):
        np.testing.assert_array_equal(written.get_lidar(seq, k), live.get_lidar(seq, k))
    # the attack acts on every row of the file, NLZ rows included: the written frame and the
    # metadata do not depend on the loader's NLZ setting
    src_rows = np.load(root / "waymo_processed_data_v0_5_0" / seq / "0050.npy")
    out_rows = np.load(out / "waymo_processed_data_v0_5_0" / seq / "0050.npy")
    meta_50 = live.frame_attack_meta(seq, 50)
    visible, removed = meta_50["num_visible"], meta_50["num_removed"]
    assert visible > 0 and removed > 0
    assert len(out_rows) == len(src_rows) - removed + visible
    assert (out_rows[-visible:, 5] == -1).all()
    other_cfg = cfg_from_yaml_file(cfg_path)
    other_cfg.DISABLE_NLZ_FLAG_ON_POINTS = not keep_nlz
    other = AtlasWaymoDataset(other_cfg, CLASSES, cfg, root_path=root)
    assert str(other.frame_attack_meta(seq, 50)) == str(meta_50)
    # NLZ rows are returns like any other: the phantom occludes some (1 in 7 rows is NLZ)
    src_nlz = {r.tobytes() for r in src_rows[src_rows[:, 5] == 1]}
    assert 0 < sum(r.tobytes() in src_nlz for r in out_rows) < len(src_nlz)
    meta = __import__("pickle").load(open(out / "atlas_attack_metadata.pkl", "rb"))
    assert meta["variant"] == "inj_rel_hard" and len(meta["frames"]) == 66
    frame_40 = written.infos[40]["frame_id"]
    assert meta["frames"][frame_40]["spoofed"] and meta["frames"][frame_40]["num_visible"] > 0
    # resumable: a finished sequence is not rewritten
    npy = next((out / "waymo_processed_data_v0_5_0" / seq).glob("0040.npy"))
    stamp = npy.stat().st_mtime_ns
    gen.main(args)
    assert npy.stat().st_mtime_ns == stamp
    # resuming with another config of the same variant must not keep the old frames silently
    with pytest.raises(ValueError, match="SEED"):
        gen.main([*args, "SEED", "1"])
    assert npy.stat().st_mtime_ns == stamp
    # nor frames attacked from another dataset (synthetic sequence names repeat across them)
    copy = shutil.copytree(root, tmp_path / "tiny_copy")
    copy_cfg = tmp_path / "copy.yaml"
    copy_cfg.write_text(cfg_path.read_text().replace(f"DATA_PATH: {root}", f"DATA_PATH: {copy}"))
    with pytest.raises(ValueError, match=r"attacked from \{'root': .*tiny'"):
        gen.main([*args[:1], str(copy_cfg), *args[2:]])
    assert npy.stat().st_mtime_ns == stamp


def test_visualize_attack_writes_png(synthetic_root, tmp_path):
    viz = load_tool("dev/visualize_attack")
    ds = make(synthetic_root, "rem_30")
    out = viz.render(ds, 40, tmp_path / "rem.png", [-25.0, 55.0, -30.0, 30.0])
    assert out.stat().st_size > 50_000
    import matplotlib.image

    img = matplotlib.image.imread(out)
    assert img.shape[0] > 800 and img.shape[1] > 1200


@pytest.mark.parametrize("variant", ["inj_rel_easy", "rem_40"])
def test_metadata_feeds_the_attack_metrics(synthetic_root, library_path, variant):
    """The evaluation consumes the metadata as produced: an oracle detector that outputs every
    recorded target box gets ASR 1 for injection and 0 for removal."""
    from pcdet_atlas.evaluation.analyses import evaluate_attack

    ds = make(synthetic_root, variant, library_path)
    seq = ds.infos[0]["point_cloud"]["lidar_sequence"]
    frames = [30, 31, 32, 33, 45, 62, 63, 64, 65, 69]  # clean, k = 0, spoofed, shadows
    metas = [ds.frame_attack_meta(seq, k) for k in frames]
    dets = []
    for info, meta in zip([ds.infos[k] for k in frames], metas):
        box = meta["target_box"]
        boxes = np.zeros((0, 7), np.float32) if box is None else box[None]
        names = np.array(["Vehicle"] * len(boxes))
        scores = np.full(len(boxes), 0.9, np.float32)
        dets.append(
            {"frame_id": info["frame_id"], "name": names, "boxes_lidar": boxes, "score": scores}
        )
    out = evaluate_attack(dets, metas, window=32)
    expected = 1.0 if variant.startswith("inj") else 0.0
    assert out["family"] == metas[2]["family"] and out["asr"] == expected


def _assert_same_sample(a, b):
    np.testing.assert_array_equal(a["points"], b["points"])
    assert a["attack"].keys() == b["attack"].keys()
    for key, value in a["attack"].items():
        np.testing.assert_array_equal(value, b["attack"][key], err_msg=key)


@pytest.mark.parametrize("variant", ["inj_global_hard", "rem_30"])
def test_frame_cache_changes_no_bit_in_any_order(synthetic_root, library_path, variant):
    """Attacked 4-frame samples are bitwise the same with the attacked-frame cache and without
    it, read in order, in reverse and in a shuffled order."""
    cached = make(synthetic_root, variant, library_path, multiframe=True)
    plain = AtlasWaymoDataset(
        data_cfg(synthetic_root, True), CLASSES, attack_cfg(variant, library_path),
        root_path=synthetic_root, frame_cache_size=0,
    )  # fmt: skip
    assert cached.frame_cache_size == 4 and plain.frame_cache_size == 0
    indices = list(range(30, 40)) + [66, 64, 62, 35, 34, 33] + [50, 31, 60, 44, 52]
    for index in indices:
        _assert_same_sample(cached[index], plain[index])


def test_frame_cache_simulates_each_spoofed_frame_once_in_order(synthetic_root):
    """Read in order, a 4-frame input simulates one new frame per sample; without the cache
    every spoofed frame of the window is simulated again."""
    indices = range(30, 46)  # spoofed frames 32..45 are read 1 to 4 times each
    reads = sum(sum(32 <= f <= 63 for f in range(max(i - 3, 0), i + 1)) for i in indices)
    for size, simulated, hits in [(None, 14, reads - 14), (0, reads, 0)]:
        ds = AtlasWaymoDataset(
            data_cfg(synthetic_root, True), CLASSES, attack_cfg("rem_30"),
            root_path=synthetic_root, frame_cache_size=size,
        )  # fmt: skip
        with COUNTERS.measure() as work:
            for index in indices:
                ds[index]
        assert work["frames_simulated"] == simulated, (size, work)
        assert work["frame_cache_hits"] == hits
        assert work["frame_cache_misses"] == (14 if size is None else 0)


def test_frame_cache_gives_history_read_only_and_the_current_frame_a_copy(synthetic_root):
    ds = make(synthetic_root, "rem_30", multiframe=True)
    seq = ds.infos[0]["point_cloud"]["lidar_sequence"]
    first = ds[40]["points"].copy()
    ds._current = (seq, 40)  # as __getitem__ reads the current frame
    current = ds.get_lidar(seq, 40)
    ds._current = None
    current[:] = 0.0  # the sample's own array: writing it leaves the cache untouched
    history = ds.get_lidar(seq, 40)
    assert not history.flags.writeable
    with pytest.raises(ValueError):
        history[0, 0] = 1.0
    np.testing.assert_array_equal(ds[40]["points"], first)
    assert len(ds._frame_cache) <= ds.frame_cache_size


@pytest.mark.parametrize("size,error", [(-1, ValueError), (1.5, TypeError), (True, TypeError)])
def test_frame_cache_size_is_checked(synthetic_root, size, error):
    with pytest.raises(error, match="frame_cache_size"):
        AtlasWaymoDataset(
            data_cfg(synthetic_root), CLASSES, attack_cfg("rem_30"), root_path=synthetic_root,
            frame_cache_size=size,
        )  # fmt: skip
