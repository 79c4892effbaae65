import math

import numpy as np
import pytest
from atlas_helpers import write_tiny_waymo

from pcdet_atlas.attacks.base import ScheduleState, SequenceData, attack_from_file
from pcdet_atlas.attacks.removal import PDistTable, RemovalAttack, RemovalRun, sector_mask
from pcdet_atlas.attacks.tracking import FrameLabels, TargetPolicy, TrackedFrame, Tracker
from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.ops.lidar_model import LidarModel

LIDAR = LidarModel.waymo_top()
ORIGIN = LIDAR.origin.numpy()


def binomial_ok(k: int, n: int, p: float, z: float = 5.0) -> bool:
    return abs(k - n * p) <= z * math.sqrt(n * p * (1 - p)) + 1


def reference_sector(xyz, center, alpha, beta):
    """Plain per-point reference of the A-HFR sector (degrees, math module)."""
    out = []
    tc = math.atan2(center[1] - ORIGIN[1], center[0] - ORIGIN[0])
    pc = math.atan2(center[2] - ORIGIN[2], math.hypot(center[0] - ORIGIN[0], center[1] - ORIGIN[1]))
    for i, (x, y, z) in enumerate(xyz.astype(np.float64)):
        t = math.atan2(y - ORIGIN[1], x - ORIGIN[0])
        p = math.atan2(z - ORIGIN[2], math.hypot(x - ORIGIN[0], y - ORIGIN[1]))
        d = (t - tc + math.pi) % (2 * math.pi) - math.pi
        if abs(d) <= alpha / 2 and abs(p - pc) <= beta / 2:
            out.append(i)
    return np.array(out, dtype=np.int64)


def random_scene(n=30000, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-60, 60, (n, 3)).astype(np.float32)
    xyz[:, 2] = rng.uniform(-2, 5, n)
    return xyz


@pytest.mark.parametrize(
    "center,alpha_deg",
    [
        ((20.0, 5.0, 0.8), 10.0),
        ((-25.0, 0.3, 1.0), 30.0),  # behind the ego: the sector straddles +-pi
        ((-25.0, -0.2, 1.0), 60.0),
        ((3.0, -30.0, 0.0), 20.0),
    ],
)
def test_sector_matches_reference_including_wraparound(center, alpha_deg):
    xyz = random_scene(8000, seed=int(alpha_deg))
    alpha, beta = math.radians(alpha_deg), math.radians(16.0)
    idx, examined = sector_mask(xyz, np.array(center), LIDAR, alpha, beta)
    ref = reference_sector(xyz, center, alpha, beta)
    assert ref.size > 20
    np.testing.assert_array_equal(idx, ref)
    assert examined < xyz.shape[0] / 2  # only the wedge's points get exact angles
    if center[0] < 0:  # points on both sides of the seam are in it
        az = np.arctan2(xyz[idx, 1] - ORIGIN[1], xyz[idx, 0] - ORIGIN[0])
        assert (az > 3.0).any() and (az < -3.0).any()


def make_attack(p_remove=0.9, alpha_deg=30.0, prob=1.0):
    return RemovalAttack(
        variant="rem_test",
        azimuth_width=math.radians(alpha_deg),
        p_remove=p_remove,
        p_dist=PDistTable([0.0], [prob]),
        lidar=LIDAR,
    )


def one_frame_run(box):
    return RemovalRun(0, 32, 63, "t", {40: TrackedFrame(40, np.asarray(box, float), "t")})


def test_removal_only_inside_sector_and_fraction_matches_p_remove():
    attack = make_attack(p_remove=0.9, alpha_deg=40.0)
    xyz = random_scene(60000, seed=3)
    box = np.array([-20.0, 1.0, 0.8, 4.5, 2.0, 1.6, 0.0])
    seq = SequenceData("seq", [{"pose": np.eye(4)}] * 70)
    state = ScheduleState(True, 0, 8, 9)
    res = attack.attack_frame(xyz, seq, 40, one_frame_run(box), state)
    sector = reference_sector(xyz, box[:3], math.radians(40.0), math.radians(16.0))
    removed = np.flatnonzero(~res.keep)
    assert set(removed.tolist()) <= set(sector.tolist())  # nothing outside the sector
    assert binomial_ok(removed.size, sector.size, 0.9)
    assert res.meta["fired"] and res.meta["tracked"] and res.meta["num_removed"] == removed.size
    np.testing.assert_allclose(res.meta["target_box"], box, atol=1e-6)
    out = res.apply(np.concatenate([xyz, np.zeros((len(xyz), 2), np.float32)], 1))
    assert out.shape[0] == xyz.shape[0] - removed.size


def test_lost_or_not_fired_frames_remove_nothing_and_record_no_box():
    seq = SequenceData("seq", [{"pose": np.eye(4)}] * 70)
    state = ScheduleState(True, 0, 8, 9)
    xyz = random_scene(5000)
    never = make_attack(prob=0.0)
    res = never.attack_frame(xyz, seq, 40, one_frame_run([20, 0, 0.8, 4, 2, 1.5, 0]), state)
    assert res.keep is None and res.meta["target_box"] is None
    assert res.meta["tracked"] and not res.meta["fired"]
    lost = RemovalRun(0, 32, 63, "t", {40: TrackedFrame(40, None, None)})
    res = make_attack().attack_frame(xyz, seq, 40, lost, state)
    assert res.keep is None and not res.meta["tracked"] and res.meta["target_box"] is None


def test_gate_frequency_follows_p_dist_and_is_common_across_widths():
    table = PDistTable([0.0, 10.0, 30.0], [0.9, 0.5, 0.2])
    a10 = make_attack(alpha_deg=10.0)
    a60 = make_attack(alpha_deg=60.0)
    n = 4000
    for r, p in ((5.0, 0.9), (20.0, 0.5), (45.0, 0.2)):
        fired = [a10.gate_uniform(f"s{r}", k) < table(r) for k in range(n)]
        assert binomial_ok(sum(fired), n, p)
    u10 = [a10.gate_uniform("seq", k) for k in range(200)]
    u60 = [a60.gate_uniform("seq", k) for k in range(200)]
    assert u10 == u60


def test_p_dist_table_lookup_and_validation():
    table = PDistTable([0.0, 10.0, 20.0], [0.9, 0.6, 0.3])
    assert table(0.0) == 0.9 and table(9.99) == 0.9 and table(10.0) == 0.6 and table(500.0) == 0.3
    with pytest.raises(ValueError, match="EDGES_M"):
        PDistTable([5.0, 10.0], [0.5, 0.5])
    with pytest.raises(ValueError, match="one value per bin"):
        PDistTable([0.0, 10.0], [0.5])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        PDistTable([0.0], [1.5])


def labels_with(boxes, names=None, ids=None, npts=None, speed=None, pose=None):
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    m = len(boxes)
    return FrameLabels(
        boxes,
        np.array(names or ["Vehicle"] * m),
        np.array(ids or [f"o{i}" for i in range(m)]),
        np.array(npts or [100] * m),
        np.asarray(speed if speed is not None else np.zeros((m, 2)), float),
        np.eye(4) if pose is None else pose,
    )


def test_target_choice_policy():
    from pcdet_atlas.attacks.tracking import choose_target

    lab = labels_with(
        [[3, 0, 1, 4, 2, 1.5, 0], [12, 0, 1, 4, 2, 1.5, 0], [9, 1, 1, 4, 2, 1.5, 0],
         [8, -1, 1, 0.8, 0.8, 1.8, 0]],
        names=["Vehicle", "Vehicle", "Vehicle", "Pedestrian"],
        npts=[500, 100, 10, 300],
    )  # fmt: skip
    # 0 is too close (< 5 m from the sensor), 2 has too few points, 3 is a pedestrian
    assert choose_target(lab, TargetPolicy(), ORIGIN) == 1
    assert choose_target(lab, TargetPolicy(min_points=5), ORIGIN) == 2
    assert choose_target(lab, TargetPolicy(range_m=(30.0, 50.0)), ORIGIN) is None
    picks = {choose_target(lab, TargetPolicy(policy="random", min_points=5), ORIGIN, (0, s))
             for s in range(30)}  # fmt: skip
    assert picks == {1, 2}


def test_tracker_velocity_distance_and_volume_checks():
    tracker = Tracker(dt=0.1, d_max=2.0, volume_ratio=0.7)
    frames = {}
    for k in range(5):
        x = 10.0 + 1.5 * k  # 15 m/s
        boxes = [[x, 0, 1, 4, 2, 1.5, 0], [x + 1.2, 3.0, 1, 4, 2, 1.5, 0]]
        if k == 3:
            boxes[0][3] = 8.0  # volume doubles: rejected -> lost this frame
        frames[k] = labels_with(boxes, ids=["a", "b"], speed=[[15.0, 0.0], [15.0, 0.0]])
    track = tracker.track(frames, 0, 0, "Vehicle", stop=4)
    assert [track[k].obj_id for k in range(5)] == ["a", "a", "a", None, "a"]
    # without the velocity prediction the 1.5 m steps are still within d_max, but the nearer
    # box "b" would win if the prediction were ignored and "a" moved 3 m
    far = {k: labels_with([[10.0 + 3.0 * k, 0, 1, 4, 2, 1.5, 0]], ids=["a"], speed=[[30.0, 0]])
           for k in range(3)}  # fmt: skip
    assert all(t.tracked for t in tracker.track(far, 0, 0, "Vehicle", stop=2).values())
    still = {k: labels_with([[10.0 + 3.0 * k, 0, 1, 4, 2, 1.5, 0]], ids=["a"]) for k in range(3)}
    assert not tracker.track(still, 0, 0, "Vehicle", stop=2)[1].tracked  # 3 m > d_max, no speed


def test_tracking_follows_same_object_on_scene(tmp_path):
    root = write_tiny_waymo(tmp_path / "tiny", frames={"val": 70})
    from pcdet_atlas.datasets.waymo_format import load_sequence_infos, sequence_pkl_path

    name = "segment-tinyval_with_camera_labels"
    seq = SequenceData(name, load_sequence_infos(sequence_pkl_path(root, name)))
    attack = attack_from_file(REPO_ROOT / "cfgs/attacks/rem_20.yaml")
    run = attack.prepare_run(seq, 0)
    tracked = [t for t in run.track.values() if t.tracked]
    assert sorted(run.track) == list(range(31, 70))  # the lifecycle: frames 31..69
    assert len(tracked) >= 0.9 * len(run.track)
    same = sum(t.obj_id == run.target_obj_id for t in tracked)
    assert same >= 0.95 * len(tracked)
    # frames fired only where tracked; the box is recorded only on tracked + fired frames
    boxes = 0
    for k in range(32, 64):
        state = attack.schedule_state(k, seq.num_frames)
        res = attack.attack_frame(np.zeros((0, 3), np.float32), seq, k, run, state)
        assert (res.meta["target_box"] is not None) == (res.meta["tracked"] and res.meta["fired"])
        boxes += res.meta["target_box"] is not None
    assert boxes >= 16  # most frames of the window fire at a tracked target


def test_removal_config_errors(tmp_path):
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/rem_40.yaml")
    RemovalAttack.from_config(cfg)
    cfg.TARGET.POLICY = "farthest"
    with pytest.raises(ConfigError, match="POLICY"):
        RemovalAttack.from_config(cfg)
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs/attacks/rem_40.yaml")
    cfg.P_DIST.PROB = [0.5]
    with pytest.raises(ConfigError, match="one value per bin"):
        RemovalAttack.from_config(cfg)


@pytest.mark.parametrize("num_removed", [0, 1, 300, 5000])
def test_frame_attack_apply_matches_masked_reference(num_removed):
    from pcdet_atlas.attacks.base import FrameAttack

    rng = np.random.default_rng(num_removed)
    points = rng.random((20000, 6)).astype(np.float32)
    keep = np.ones(len(points), bool)
    keep[rng.choice(len(points), num_removed, replace=False)] = False
    if num_removed:
        keep[[0, -1]] = False  # removed rows at both ends
    for mask in (keep, None):
        for added in (np.zeros((0, 5), np.float32), rng.random((7, 5)).astype(np.float32)):
            out = FrameAttack(mask, added, {}).apply(points, lambda a: 2 * a, fill_value=-1.0)
            expected = points if mask is None else points[mask]
            rows = np.full((len(added), 6), -1.0, np.float32)
            rows[:, :5] = 2 * added
            np.testing.assert_array_equal(out, np.concatenate([expected, rows]))


@pytest.mark.parametrize("num_runs", [1, 40, 2000])
def test_frame_attack_apply_runs_of_removed_rows(num_runs):
    """Removal sectors delete runs of consecutive rows: block copies between runs (or one
    masked copy beyond ``_MAX_RUN_COPIES`` runs) give ``points[keep]``; a ``removed`` index
    array passed along gives the same rows as the mask alone."""
    from pcdet_atlas.attacks.base import FrameAttack

    rng = np.random.default_rng(num_runs)
    points = rng.random((30000, 5)).astype(np.float32)
    keep = np.ones(len(points), bool)
    starts = np.sort(rng.choice(len(points) - 8, num_runs, replace=False))
    for s, n in zip(starts, rng.integers(1, 8, num_runs)):
        keep[s : s + n] = False
    keep[-3:] = False  # a run at the end
    removed = np.flatnonzero(~keep)
    added = rng.random((5, 5)).astype(np.float32)
    expected = np.concatenate([points[keep], added])
    for attack in (FrameAttack(keep, added, {}), FrameAttack(keep, added, {}, removed=removed)):
        np.testing.assert_array_equal(attack.apply(points), expected)
