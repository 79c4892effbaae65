import math
import os
import re

import numpy as np
import pytest
import torch
from atlas_helpers import GROUND_Z, synthetic_library, write_tiny_waymo
from device_params import DEVICES

from pcdet_atlas.attacks import injection as injection_module
from pcdet_atlas.attacks.base import SequenceData
from pcdet_atlas.attacks.counters import COUNTERS
from pcdet_atlas.attacks.ground import GroundEstimator
from pcdet_atlas.attacks.injection import InjectionAttack, sample_phantom
from pcdet_atlas.attacks.intensity import RangeIntensityModel
from pcdet_atlas.attacks.trace_library import TraceFilter, TraceLibrary, build_trace_library
from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.multiframe import relative_pose
from pcdet_atlas.datasets.waymo_format import (
    load_frame_points,
    load_sequence_infos,
    sequence_pkl_path,
)
from pcdet_atlas.ops.boxes import transform_boxes
from pcdet_atlas.utils.paths import UnsafePathError

SEQ = "segment-tinyval_with_camera_labels"
BUDGETS = {"easy": (100, 200), "medium": (300, 500), "hard": (500, 1000)}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = write_tiny_waymo(tmp_path_factory.mktemp("tiny_inj"), frames={"train": 6, "val": 70})
    lib = build_trace_library(root, TraceFilter(min_points=100), split="train")
    seq = SequenceData(SEQ, load_sequence_infos(sequence_pkl_path(root, SEQ)))
    return root, lib, seq


def toy_library(sizes=(50, 3000)):
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-1, 1, (n, 3)) for n in sizes]).astype(np.float32)
    total = pts.shape[0]
    return TraceLibrary(
        points=pts,
        intensity=np.full(total, 0.2),
        elongation=np.full(total, 0.1),
        src_range=np.full(total, 20.0),
        offsets=np.concatenate([[0], np.cumsum(sizes)]),
        box_size=np.tile([4.5, 2.0, 1.6], (len(sizes), 1)),
        sequence=["s"] * len(sizes),
        obj_id=[f"o{i}" for i in range(len(sizes))],
        num_frames=np.ones(len(sizes)),
    )


def test_sampling_ranges_budgets_and_common_random_numbers():
    lib = toy_library()
    sizes = lib.trace_sizes()
    for start in range(0, 40 * 64, 64):
        keys = (0, "injection", "relative", "seq", start)
        draws = {b: sample_phantom(lib, keys, rng_) for b, rng_ in BUDGETS.items()}
        trace, _, _, place = draws["easy"]
        assert 15 <= place[0] <= 20 and -3 <= place[1] <= 3 and -0.2 <= place[2] <= 0.2
        for name, (t, requested, sel, p) in draws.items():
            lo, hi = BUDGETS[name]
            assert t == trace and np.array_equal(p, place)  # budget-independent placement
            assert lo <= requested <= hi
            assert len(sel) == min(requested, sizes[t]) and len(set(sel.tolist())) == len(sel)
        easy, hard = draws["easy"][2], draws["hard"][2]
        assert np.array_equal(easy, hard[: len(easy)])  # easy is a prefix of hard
    # the small trace (50 points) caps every budget, and the cap is recorded as requested > n
    small = [
        sample_phantom(lib, (0, "injection", "global", "s", k), BUDGETS["easy"]) for k in range(40)
    ]
    capped = [(req, len(sel)) for t, req, sel, _ in small if t == 0]
    assert capped and all(n == 50 < req for req, n in capped)


def test_ground_estimator_percentile_and_fallbacks():
    rng = np.random.default_rng(1)
    ground = np.c_[rng.uniform(10, 20, (500, 2)), rng.normal(0.3, 0.02, 500)]
    car = np.c_[rng.uniform(14, 16, (300, 2)), rng.uniform(0.5, 1.8, 300)]
    est = GroundEstimator(radius=3.0)(np.concatenate([ground, car]), (15.0, 15.0))
    assert est.source == "disc" and abs(est.z - 0.3) < 0.05
    est = GroundEstimator(radius=1.0, min_points=10)(ground[::40], (15.0, 15.0))
    assert est.source == "wide_disc" and abs(est.z - 0.3) < 0.05
    est = GroundEstimator(fallback_z=-0.1)(ground, (60.0, 0.0))
    assert est.source == "fallback" and est.z == -0.1


def test_intensity_model_follows_range():
    model = RangeIntensityModel(intensity_exponent=2.0, elongation_exponent=1.0)
    inten, elong = model(np.array([0.4, 0.4]), np.array([0.1, 0.1]), np.array([10.0, 10.0]),
                         np.array([20.0, 5.0]))  # fmt: skip
    np.testing.assert_allclose(inten, [0.1, 1.6], rtol=1e-6)
    np.testing.assert_allclose(elong, [0.2, 0.05], rtol=1e-6)
    same = RangeIntensityModel(intensity_exponent=0.0, elongation_exponent=0.0)
    np.testing.assert_allclose(same(np.array([0.4]), np.array([0.1]), [10.0], [30.0])[0], [0.4])


def make_attack(lib, mode, budget="hard", p_dual=0.0):
    return InjectionAttack("inj_test", lib, mode, BUDGETS[budget], p_dual=p_dual)


def run_frames(attack, seq, root, frames):
    out = {}
    for k in frames:
        pts = load_frame_points(root / "waymo_processed_data_v0_5_0" / SEQ / f"{k:04d}.npy")
        out[k] = (pts, attack.simulate(pts[:, :3], seq, k))
    return out


def test_global_phantom_fixed_in_world_and_on_the_ground(tiny):
    root, lib, seq = tiny
    attack = make_attack(lib, "global")
    res = run_frames(attack, seq, root, range(32, 64, 3))
    world = []
    for k, (_, r) in res.items():
        box = r.meta["target_box"].astype(np.float64)
        assert abs(box[2] - box[5] / 2 - GROUND_Z) <= 0.15  # bottom on the ground
        world.append(transform_boxes(box[None], seq.pose(k))[0])
        added = r.added
        assert added.shape[0] == r.meta["num_visible"] > 0
        assert added[:, 2].min() >= GROUND_Z - 0.15 - 1.6  # phantom points near/above ground
    world = np.array(world)
    assert np.abs(world[:, :2] - world[0, :2]).max() <= 0.01  # fixed in the world (x, y)
    assert np.abs(world[:, 6] - world[0, 6]).max() <= 1e-4
    # the anchor is the run's last frame: there it sits at the sampled ego offset
    last = run_frames(attack, seq, root, [63])[63][1].meta["target_box"]
    assert 15 <= last[0] <= 20 and -3 <= last[1] <= 3


def test_relative_phantom_fixed_in_ego(tiny):
    root, lib, seq = tiny
    attack = make_attack(lib, "relative", "medium")
    res = run_frames(attack, seq, root, [32, 45, 63])
    boxes = np.array([r.meta["target_box"] for _, r in res.values()])
    assert np.abs(boxes[:, [0, 1, 3, 4, 5, 6]] - boxes[0, [0, 1, 3, 4, 5, 6]]).max() <= 1e-5
    assert 15 <= boxes[0, 0] <= 20 and -3 <= boxes[0, 1] <= 3 and abs(boxes[0, 6]) <= 0.2
    assert np.all(np.abs(boxes[:, 2] - boxes[:, 5] / 2 - GROUND_Z) <= 0.15)
    for _, r in res.values():
        assert r.meta["num_spoof_points"] <= 500
        assert 0 < r.meta["num_visible"] <= r.meta["num_spoof_points"]


def test_budgets_share_placement_and_differ_only_in_points(tiny):
    root, lib, seq = tiny
    metas = {}
    for b in BUDGETS:
        attack = make_attack(lib, "global", b)
        metas[b] = run_frames(attack, seq, root, [40])[40][1].meta
        lo, hi = BUDGETS[b]
        assert metas[b]["num_spoof_points"] <= hi
        assert metas[b]["num_spoof_points"] >= min(lo, int(lib.trace_sizes().min()))
    for b in ("medium", "hard"):
        np.testing.assert_array_equal(metas[b]["target_box"], metas["easy"]["target_box"])
    assert metas["easy"]["num_visible"] <= metas["hard"]["num_visible"]


def test_phantom_occludes_and_merges(tiny):
    root, lib, seq = tiny
    attack = make_attack(lib, "relative", "hard")
    pts, r = run_frames(attack, seq, root, [50])[50]
    out = r.apply(pts[:, :5])
    n_removed = int((~r.keep).sum())
    assert n_removed == r.meta["num_removed"] > 0  # ground behind the phantom is occluded
    assert out.shape == (pts.shape[0] - n_removed + r.meta["num_visible"], 5)
    # occluded scene points lie behind the phantom, in its azimuth sector
    gone = pts[~r.keep, :3]
    assert np.all(np.hypot(gone[:, 0], gone[:, 1]) > r.meta["target_box"][0] - 4)


def test_config_errors_and_library_checks(tiny, tmp_path):
    root, lib, _ = tiny
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml")
    cfg.POSITION_MODE = "sideways"
    with pytest.raises(ConfigError, match="POSITION_MODE = 'sideways'"):
        InjectionAttack.from_config(cfg, data_root=root)
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml")
    cfg.BUDGET = [300, 100]
    with pytest.raises(ConfigError, match="BUDGET"):
        InjectionAttack.from_config(cfg, data_root=root)
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml")
    missing = InjectionAttack.from_config(cfg, data_root=tmp_path)
    with pytest.raises(FileNotFoundError, match="build_trace_library"):
        _ = missing.library
    lib.save(tmp_path / "atlas_trace_library.npz")  # built with MIN_POINTS 100, YAML says 200
    mismatch = InjectionAttack.from_config(cfg, data_root=tmp_path)
    with pytest.raises(ConfigError, match="rebuild"):
        _ = mismatch.library


@pytest.mark.parametrize("kind", ["dotdot", "inner_dotdot", "symlink_out", "fifo"])
def test_a_trace_library_path_leaving_the_data_root_is_refused(tiny, tmp_path, kind):
    """A relative ``TRACE_LIBRARY.PATH`` stays under the dataset root (no ``..``, no symlink out
    of it), and the file it names must be a regular one: it is hashed and loaded, and a FIFO or
    a device would never end. An absolute PATH is read as it is (written only with --out)."""
    root, lib, _ = tiny
    data_root = tmp_path / "root"
    data_root.mkdir()
    outside = lib.save(tmp_path / "outside.npz")
    value = {"dotdot": "../outside.npz", "inner_dotdot": "sub/../../outside.npz"}.get(
        kind, "atlas_trace_library.npz"
    )
    if kind == "symlink_out":
        (data_root / value).symlink_to(outside)
    elif kind == "fifo":
        os.mkfifo(data_root / value)
    yaml = tmp_path / "inj.yaml"
    yaml.write_text(f"_BASE_CONFIG_: {REPO_ROOT / 'cfgs/attacks/inj_rel_easy.yaml'}\n"
                    f"TRACE_LIBRARY:\n  PATH: {value}\n  MIN_POINTS: 100\n")  # fmt: skip
    cfg = cfg_from_yaml_file(yaml)
    expected = {
        "dotdot": rf"TRACE_LIBRARY\.PATH '\.\./outside\.npz' \(from {re.escape(str(yaml))}\) is "
        "not a relative path",
        "inner_dotdot": r"TRACE_LIBRARY\.PATH 'sub/\.\./\.\./outside\.npz' \(from .*inj\.yaml\)",
        "symlink_out": rf"resolves to {re.escape(str(outside.resolve()))}, outside its root",
        "fifo": r"TRACE_LIBRARY\.PATH \(from .*inj\.yaml\) .*atlas_trace_library\.npz is a FIFO",
    }[kind]
    with pytest.raises(UnsafePathError, match=expected):
        InjectionAttack.from_config(cfg, data_root=data_root)
    cfg.TRACE_LIBRARY.PATH = str(outside)  # absolute: read where it says
    assert InjectionAttack.from_config(cfg, data_root=data_root).library_path == outside


@pytest.mark.parametrize(
    "build,stored,expected",
    [
        ({"split": "val"}, "'split': 'val'", "'split': 'train'"),
        ({"sensor_origin": (1.0, 0.0, 2.0)}, "[1.0, 0.0, 2.0]", "[1.43, 0.0, 2.184]"),
    ],
    ids=["split", "sensor_origin"],
)
def test_library_of_another_split_or_sensor_origin_is_refused(
    tiny, tmp_path, build, stored, expected
):
    """The library at the shared default path is checked at load against the config's split
    and LIDAR origin (the recorded ranges behind the intensity correction depend on it), not
    only its filters; a library built as the config says loads."""
    root = tiny[0]
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/inj_rel_easy.yaml")
    filters = TraceFilter.from_config(cfg.TRACE_LIBRARY)
    path = build_trace_library(root, filters, **build).save(tmp_path / "atlas_trace_library.npz")
    with pytest.raises(ConfigError) as info:
        _ = InjectionAttack.from_config(cfg, data_root=tmp_path).library
    message = str(info.value)
    assert str(path) in message and stored in message and expected in message, message
    build_trace_library(root, filters).save(path)
    assert len(InjectionAttack.from_config(cfg, data_root=tmp_path).library) > 0


def test_phantoms_on_the_fallback_ground_are_counted(tiny):
    """A phantom with no scene point near it stands on GROUND.FALLBACK_Z, and the attack
    counters record it; a phantom on the scene's ground is not counted."""
    root, lib, seq = tiny
    attack = make_attack(lib, "relative")
    with COUNTERS.measure() as work:
        run_frames(attack, seq, root, [40])
    assert work["frames_simulated"] == 1 and work["ground_fallbacks"] == 0
    with COUNTERS.measure() as work:
        meta = attack.simulate(np.zeros((0, 3), np.float32), seq, 40).meta
    assert work["ground_fallbacks"] == 1
    box = meta["target_box"]
    assert box[2] - box[5] / 2 == pytest.approx(attack.ground.fallback_z, abs=1e-5)


def test_run_cache_keys_the_root_and_frame_count(tiny):
    """A run's cached state belongs to one sequence of one root: the same name with another
    frame count (other run bounds) or another root gets its own run."""
    root, lib, seq = tiny
    attack = make_attack(lib, "global")
    assert attack.run_state(seq, 0).end == 63
    short = SequenceData(seq.name, seq.infos[:50], root=seq.root)
    assert attack.run_state(short, 0).end == 49
    turned = [
        {**info, "pose": info["pose"] @ np.diag([-1.0, -1.0, 1.0, 1.0])} for info in seq.infos
    ]
    other = attack.run_state(SequenceData(seq.name, turned, root="/another/root"), 0)
    assert not np.array_equal(other.anchor_pose, attack.run_state(seq, 0).anchor_pose)


def test_dual_returns_deterministic_per_frame(tiny):
    root, lib, seq = tiny
    a = run_frames(make_attack(lib, "global", p_dual=0.5), seq, root, [41])[41][1]
    b = run_frames(make_attack(lib, "global", p_dual=0.5), seq, root, [41])[41][1]
    np.testing.assert_array_equal(a.keep, b.keep)
    np.testing.assert_array_equal(a.added, b.added)
    c = run_frames(make_attack(lib, "global", p_dual=0.0), seq, root, [41])[41][1]
    assert a.meta["num_removed"] < c.meta["num_removed"]  # second echoes survive
    assert math.isfinite(float(a.added[:, 3].sum()))


def test_dual_uniforms_one_row_per_frame_of_the_run(tiny):
    """The dual-return uniforms are drawn once per run, one row per frame: a frame's draws do
    not depend on which frames were simulated before it; the phantom pose uses the cached
    inverse pose, bit for bit ``relative_pose``."""
    root, lib, seq = tiny
    attack = make_attack(lib, "global", p_dual=0.5)
    run = attack.run_state(seq, 0)
    start, end = attack.run_bounds(seq, 0)
    assert run.dual_uniforms.shape == (end - start + 1, run.budget)
    assert make_attack(lib, "global").run_state(seq, 0).dual_uniforms is None
    alone = run_frames(make_attack(lib, "global", p_dual=0.5), seq, root, [44])[44][1]
    after = run_frames(make_attack(lib, "global", p_dual=0.5), seq, root, [50, 38, 44])[44][1]
    np.testing.assert_array_equal(alone.keep, after.keep)
    np.testing.assert_array_equal(alone.added, after.added)
    for k in (start, 44, end):
        want = relative_pose(seq.pose(end), seq.pose(k))
        assert np.array_equal(seq.world_to_vehicle(k) @ run.anchor_pose, want)


def test_on_synthetic_data_phantom_sits_on_ground_and_stays_in_world(synthetic_root, tmp_path):
    from pcdet_atlas.datasets.waymo_format import frame_npy_path, read_image_set

    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/inj_global_medium.yaml")
    cfg.TRACE_LIBRARY.PATH = str(synthetic_library(synthetic_root, tmp_path))
    attack = InjectionAttack.from_config(cfg)
    name = read_image_set(synthetic_root / "ImageSets" / "val.txt")[0]
    seq = SequenceData(name, load_sequence_infos(sequence_pkl_path(synthetic_root, name)))
    world = []
    for k in (40, 52, 63):  # the synthetic ground is the plane z = 0 of the vehicle frame
        pts = load_frame_points(frame_npy_path(synthetic_root, name, k))
        meta = attack.simulate(pts[:, :3], seq, k).meta
        box = meta["target_box"].astype(np.float64)
        assert abs(box[2] - box[5] / 2) <= 0.15
        assert 300 <= meta["num_spoof_points"] <= 500 and meta["num_visible"] > 0
        world.append(transform_boxes(box[None], seq.pose(k))[0])
    world = np.array(world)
    assert np.abs(world[:, :2] - world[0, :2]).max() <= 0.01


@pytest.mark.parametrize("mode", ["relative", "global"])
def test_phantom_sector_prefilter_changes_nothing(tiny, mode, monkeypatch):
    """On CPU one wedge around the phantom (its points and the ground disc) feeds both the
    ground estimate and the raycaster; the frames equal those attacked with full-scene scans,
    and the pre-filter holds a small part of the scene."""
    root, lib, seq = tiny
    frames = [32, 40, 47, 55, 63]
    got = make_attack(lib, mode, p_dual=0.3)
    sizes = []
    sector = got._phantom_sector

    def recording(scene_xyz, *args):
        rows = sector(scene_xyz, *args)
        sizes.append((len(rows), len(scene_xyz)))
        return rows

    monkeypatch.setattr(got, "_phantom_sector", recording)
    ref = make_attack(lib, mode, p_dual=0.3)
    monkeypatch.setattr(ref, "_phantom_sector", lambda *args: None)
    out, want = run_frames(got, seq, root, frames), run_frames(ref, seq, root, frames)
    for k in frames:
        np.testing.assert_array_equal(out[k][1].removed_rows(), want[k][1].removed_rows())
        np.testing.assert_array_equal(out[k][1].added, want[k][1].added)
        assert str(out[k][1].meta) == str(want[k][1].meta)
    assert len(sizes) == len(frames) and all(0 < n < total / 4 for n, total in sizes)


@pytest.mark.parametrize("device", DEVICES)
def test_raycast_device_gives_identical_frames(tiny, device):
    root, lib, seq = tiny
    ref = run_frames(make_attack(lib, "global", p_dual=0.3), seq, root, [47])[47][1]
    attack = InjectionAttack("inj_test", lib, "global", BUDGETS["hard"], p_dual=0.3, device=device)
    out = run_frames(attack, seq, root, [47])[47][1]
    np.testing.assert_array_equal(out.keep, ref.keep)
    np.testing.assert_array_equal(out.added, ref.added)


def test_ground_estimator_matches_brute_force_disc_percentile():
    """The small disc's square is scanned first and the wide disc's only when needed; the
    estimate is the brute-force lower percentile of the points within each radius (float64
    distances), including points exactly on the disc boundaries, and from given rows that hold
    the small disc."""
    rng = np.random.default_rng(0)
    est = GroundEstimator(radius=3.0, percentile=10.0, min_points=10, fallback_radius=8.0)
    for trial in range(30):
        n = [5, 40, 400, 4000][trial % 4]
        center = rng.uniform(-20, 20, 2)
        xyz = np.concatenate(
            [
                np.c_[center + rng.uniform(-9, 9, (n, 2)), rng.normal(0, 2.0, n)],
                # exactly on both boundaries (in float32)
                np.c_[center + [[3.0, 0.0], [0.0, -8.0]], [[0.1], [0.2]]],
            ]
        ).astype(np.float32)
        d2 = ((xyz[:, :2].astype(np.float64) - center) ** 2).sum(1)
        z = xyz[:, 2].astype(np.float64)
        ok = np.abs(z) <= est.max_abs_z
        expected = None
        for radius, source in ((3.0, "disc"), (8.0, "wide_disc")):
            sel = z[ok & (d2 <= radius * radius)]
            if sel.size >= 10:
                k = int(np.floor(0.10 * (sel.size - 1)))
                expected = (np.sort(sel)[k], source, sel.size)
                break
        # rows holding the small disc (a wedge's, say): some points beyond it, in order
        near = np.flatnonzero((d2 <= 3.2**2) | (rng.random(len(xyz)) < 0.1))
        for rows in (None, near):
            got = est(xyz, center, rows=rows)
            if expected is None:
                assert got.source == "fallback" and got.z == est.fallback_z
            else:
                assert (got.z, got.source, got.num_points) == expected


def test_fully_occluded_phantom_records_no_target(tiny, monkeypatch):
    """A phantom none of whose points survives the raycast is not in the scan: the frame is
    spoofed but records no target (the evaluation counts it as untargeted, not as a failure)."""
    root, lib, seq = tiny
    attack = make_attack(lib, "relative", "hard")
    pts = load_frame_points(root / "waymo_processed_data_v0_5_0" / SEQ / "0050.npy")
    visible = attack.simulate(pts[:, :3], seq, 50)
    assert visible.meta["num_visible"] > 0 and visible.meta["target_box"] is not None
    real = injection_module.raycast_merge

    def everything_occluded(*args, **kwargs):  # as if an occluder stood before every ray
        keep_scene, keep_spoof = real(*args, **kwargs)
        return keep_scene, torch.zeros_like(keep_spoof)

    monkeypatch.setattr(injection_module, "raycast_merge", everything_occluded)
    r = attack.simulate(pts[:, :3], seq, 50)
    assert r.meta["spoofed"] and r.meta["num_visible"] == 0 and r.added.shape[0] == 0
    assert r.meta["target_box"] is None
    assert r.meta["num_spoof_points"] == visible.meta["num_spoof_points"]
