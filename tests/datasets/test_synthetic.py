"""The synthetic Waymo-format generator: format, determinism, idempotency, sensor physics."""

from __future__ import annotations

import json
import math
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from malicious_files import malicious_pickle

from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.datasets.synthetic import (
    META_FILE,
    SyntheticDatasetError,
    SyntheticScene,
    create_synthetic_waymo,
    sequence_name,
)
from pcdet_atlas.datasets.synthetic.generator import _generate_chunk
from pcdet_atlas.datasets.synthetic.raycast import (
    GROUND_ID,
    NO_HIT_ID,
    Primitives,
    column_azimuths,
    ray_box_distance,
    ray_cylinder_distance,
    ray_directions,
    raycast_scan,
)
from pcdet_atlas.datasets.synthetic.sensor import SensorModel
from pcdet_atlas.ops.boxes import points_in_boxes_mask, transform_boxes
from pcdet_atlas.ops.lidar_model import LidarModel
from pcdet_atlas.utils.safe_pickle import RefusedGlobalError

DEVICES = [
    "cpu",
    pytest.param(
        "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    ),
]


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Small tensors: one intra-op thread is fastest (and does not fight parallel jobs)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _sequences(root, split):
    lines = (root / "ImageSets" / f"{split}.txt").read_text().splitlines()
    return [wf.sequence_name_from_line(line) for line in lines]


def _infos(root, seq):
    with open(wf.sequence_pkl_path(root, seq), "rb") as fh:
        return pickle.load(fh)


def _points(root, seq, idx):
    return np.load(wf.frame_npy_path(root, seq, idx))


def _files(root):
    return {p.relative_to(root): p for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def val_seq(synthetic_root):
    return _sequences(synthetic_root, "val")[0]


@pytest.fixture(scope="module")
def fixture_args(synthetic_root):
    """``(seed, frames_per_sequence)`` the session fixture was generated with."""
    args = json.loads((synthetic_root / META_FILE).read_text())["args"]
    return args["seed"], args["frames_per_sequence"]


# ------------------------------------------------------------------------------- format
def test_fixture_layout_and_format(synthetic_root, fixture_args):
    root = synthetic_root
    seed, frames_per_sequence = fixture_args
    assert frames_per_sequence == {"train": 10, "val": 70}
    assert len(_sequences(root, "train")) == 2 and len(_sequences(root, "val")) == 1
    pattern = re.compile(r"^segment-\d+_\d+_000_\d+_000_with_camera_labels$")
    for split, frames in frames_per_sequence.items():
        all_infos = []
        for seq in _sequences(root, split):
            assert pattern.match(seq), seq
            infos = _infos(root, seq)
            wf.validate_sequence_infos(infos, wf.sequence_pkl_path(root, seq))
            assert len(infos) == frames
            stamps = [i["metadata"]["timestamp_micros"] for i in infos]
            assert np.all(np.diff(stamps) == 100_000)
            for info in infos[:: max(1, frames // 5)]:
                idx = info["point_cloud"]["sample_idx"]
                points = _points(root, seq, idx)
                wf.validate_points(points, seq)
                assert info["num_points_of_each_lidar"] == [len(points), 0, 0, 0, 0]
                assert set(np.unique(points[:, 5]).tolist()) <= {-1.0, 1.0}
                assert info["frame_id"] == f"{seq}_{idx:03d}"
                assert info["point_cloud"] == {
                    "num_features": 5,
                    "lidar_sequence": seq,
                    "sample_idx": idx,
                }
                assert info["metadata"]["context_name"] in seq
                assert info["image"] == wf.DEFAULT_IMAGE_SHAPES
                assert info["pose"].dtype == np.float32 and info["pose"].shape == (4, 4)
                _check_annos(info["annos"], info["pose"])
            all_infos += infos
        with open(root / f"{wf.PROCESSED_DATA_TAG}_infos_{split}.pkl", "rb") as fh:
            concat = pickle.load(fh)
        assert [i["frame_id"] for i in concat] == [i["frame_id"] for i in all_infos]
    meta = json.loads((root / META_FILE).read_text())
    assert len(meta["lidar"]["INCLINATIONS"]) == 64 and meta["lidar"]["MAX_RANGE"] == 75.0


def _check_annos(annos, pose):
    assert set(annos) == set(wf.ANNO_KEYS)
    n = len(annos["name"])
    assert n > 0
    assert annos["name"].dtype.kind == "U" and set(annos["name"]) <= set(wf.WAYMO_CLASSES[1:])
    assert annos["obj_ids"].dtype.kind == "U"
    for key, shape in (
        ("dimensions", (n, 3)),
        ("location", (n, 3)),
        ("heading_angles", (n,)),
        ("speed_global", (n, 2)),
        ("accel_global", (n, 2)),
        ("gt_boxes_lidar", (n, 9)),
    ):
        assert annos[key].dtype == np.float64 and annos[key].shape == shape, key
    for key in ("difficulty", "tracking_difficulty", "num_points_in_gt"):
        assert annos[key].dtype == np.int64 and annos[key].shape == (n,), key
    assert np.all((annos["heading_angles"] >= -math.pi) & (annos["heading_angles"] < math.pi))
    assert np.all(annos["dimensions"] > 0)
    # Waymo/OpenPCDet difficulty rule
    assert np.array_equal(annos["difficulty"], np.where(annos["num_points_in_gt"] <= 5, 2, 1))
    # gt_boxes_lidar = [location, dimensions, heading, global speed rotated into the vehicle frame]
    box = annos["gt_boxes_lidar"]
    assert np.allclose(box[:, 0:3], annos["location"]) and np.allclose(
        box[:, 3:6], annos["dimensions"]
    )
    rot = pose[:2, :2].astype(np.float64)
    assert np.allclose(box[:, 7:9], annos["speed_global"] @ rot, atol=1e-4)


# ------------------------------------------------------------------------------- determinism
def _small(root, seed=0, frames=2, **kw):
    return create_synthetic_waymo(
        root, {"train": 1, "val": 0}, {"train": frames, "val": 1}, seed=seed, **kw
    )


def test_determinism_idempotency_and_conflicts(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    summary = _small(a)
    assert summary["generated"] == 1 and summary["frames"] == {"train": 2, "val": 0}
    _small(b)
    _small(c, seed=1)
    files_a, files_b = _files(a), _files(b)
    assert files_a.keys() == files_b.keys()
    for rel, path in files_a.items():
        assert path.read_bytes() == files_b[rel].read_bytes(), rel
    seq_a = _sequences(a, "train")[0]
    seq_c = _sequences(c, "train")[0]
    assert seq_a != seq_c
    assert not np.array_equal(_points(a, seq_a, 0), _points(c, seq_c, 0))

    # idempotent: a second run rewrites nothing
    mtimes = {rel: p.stat().st_mtime_ns for rel, p in files_a.items()}
    again = _small(a)
    assert again["generated"] == 0 and again["reused"] == 1
    assert {rel: p.stat().st_mtime_ns for rel, p in _files(a).items()} == mtimes

    # an unfinished sequence (no pkl) is completed with the same bytes, the rest untouched
    pkl = wf.sequence_pkl_path(a, seq_a)
    pkl_bytes = pkl.read_bytes()
    pkl.unlink()
    assert _small(a)["generated"] == 1
    assert pkl.read_bytes() == pkl_bytes
    assert (a / META_FILE).stat().st_mtime_ns == mtimes[Path(META_FILE)]

    # other arguments into the same root: an error naming the conflict
    with pytest.raises(SyntheticDatasetError, match="args"):
        _small(a, frames=3)
    with pytest.raises(SyntheticDatasetError, match="seed"):
        _small(a, seed=5)


def test_an_existing_sequence_pkl_that_would_run_code_is_refused(tmp_path):
    """A rerun reads the sequences already written with the restricted unpickler."""
    _small(tmp_path, frames=1)
    marker = tmp_path / "marker"
    pkl = malicious_pickle(wf.sequence_pkl_path(tmp_path, _sequences(tmp_path, "train")[0]), marker)
    with pytest.raises(RefusedGlobalError, match=rf"{pkl}: refused to unpickle the global "):
        _small(tmp_path, frames=1)
    assert not marker.exists()


def test_refuses_foreign_root_and_bad_args(tmp_path):
    (tmp_path / "ImageSets").mkdir()
    with pytest.raises(SyntheticDatasetError, match=META_FILE):
        _small(tmp_path)
    with pytest.raises(SyntheticDatasetError, match="unknown split"):
        create_synthetic_waymo(tmp_path / "x", {"test": 1}, {"train": 1})
    with pytest.raises(SyntheticDatasetError, match="frames_per_sequence"):
        create_synthetic_waymo(tmp_path / "x", {"train": 1}, {"train": 0})
    with pytest.raises(SyntheticDatasetError, match="seed"):
        create_synthetic_waymo(tmp_path / "x", {"train": 1}, {"train": 1}, seed=-1)
    # bad workers / threads: an error before anything is written
    for kwargs, name in (({"workers": 0}, "workers"), ({"threads": 0}, "threads")):
        with pytest.raises(SyntheticDatasetError, match=name):
            create_synthetic_waymo(tmp_path / "y", {"train": 1}, {"train": 1}, **kwargs)
        assert not (tmp_path / "y").exists()


def test_chunking_does_not_change_frames(synthetic_root, val_seq, fixture_args, tmp_path):
    """Frames generated in another chunk split (as with other worker counts) are identical."""
    seed, frames = fixture_args
    task = {
        "seed": seed,
        "split": "val",
        "index": 0,
        "num_frames": frames["val"],
        "start": 33,
        "stop": 35,
        "root": str(tmp_path),
        "device": "cpu",
        "threads": 1,
    }
    assert sequence_name(seed, "val", 0) == val_seq
    wf.frame_npy_path(tmp_path, val_seq, 0).parent.mkdir(parents=True)
    infos = _generate_chunk(task)
    ref = _infos(synthetic_root, val_seq)
    assert len(infos) == 2
    for f, info in zip((33, 34), infos):
        assert (
            wf.frame_npy_path(tmp_path, val_seq, f).read_bytes()
            == wf.frame_npy_path(synthetic_root, val_seq, f).read_bytes()
        )
        # the chunk's labels, less the objects the whole sequence never saw, are the pkl's
        keep = np.isin(info["annos"]["obj_ids"], ref[f]["annos"]["obj_ids"])
        assert keep.sum() == len(ref[f]["annos"]["obj_ids"])
        for key, value in ref[f]["annos"].items():
            assert np.array_equal(info["annos"][key][keep], value), key
        rest = {k: v for k, v in ref[f].items() if k != "annos"}
        assert pickle.dumps({k: v for k, v in info.items() if k != "annos"}) == pickle.dumps(rest)


# ------------------------------------------------------------------------------- physics
PHYSICS_FRAMES = (0, 33, 69)


def test_points_lie_on_the_sensor_grid(synthetic_root, val_seq):
    lidar = LidarModel.waymo_top()
    centres = column_azimuths(lidar.azimuth_bins)
    for f in PHYSICS_FRAMES:
        xyz = torch.from_numpy(_points(synthetic_root, val_seq, f)[:, :3])
        az, el, rng = lidar.spherical(xyz)
        assert float(rng.max()) <= 75.0 + 1e-3 and float(rng.min()) > 0.4
        beam = lidar.beam_index(el)
        assert float((el - lidar.inclinations[beam]).abs().max()) < 2e-5  # rad, noise is radial
        col = lidar.azimuth_index(az)
        assert float((az - centres[col]).abs().max()) < 2e-5
        bins, in_fov, _ = lidar.bin_index(xyz)
        assert bool(in_fov.all())
        assert torch.unique(bins).numel() == bins.numel()  # one return per (beam, column)
        # Waymo range-image order: highest beam first, azimuth decreasing within a beam
        assert bool((bins[1:] < bins[:-1]).all())
        assert 60_000 < len(xyz) < 169_664


def _brute_force_first_hit(origin, dirs, prims):
    """Nearest hit of each ray over ALL primitives and the ground (no culling): ``(R,)``."""
    best = torch.full((dirs.shape[0],), math.inf, dtype=dirs.dtype)
    for k in range(prims.num_boxes):
        t = ray_box_distance(origin, dirs, prims.boxes[k].expand(dirs.shape[0], 7))
        best = torch.minimum(best, t)
    for k in range(prims.num_cylinders):
        t = ray_cylinder_distance(origin, dirs, prims.cylinders[k].expand(dirs.shape[0], 5))
        best = torch.minimum(best, t)
    down = dirs[:, 2] < 0
    t_ground = torch.where(down, -origin[2] / torch.where(down, dirs[:, 2], -1.0), math.inf)
    return torch.minimum(best, t_ground)


def test_no_return_from_behind_an_occluder(synthetic_root, val_seq, fixture_args):
    """Re-cast the rays of a subset of points against every primitive of the scene: each point
    is the first surface on its ray, up to range noise."""
    lidar = LidarModel.waymo_top()
    sensor = SensorModel()
    seed, frames = fixture_args
    scene = SyntheticScene(seed, "val", 0, frames["val"])
    origin = lidar.origin.clone()
    for f in PHYSICS_FRAMES[:2]:
        points = torch.from_numpy(_points(synthetic_root, val_seq, f)[:, :3]).double()
        gen = torch.Generator().manual_seed(f)
        pick = torch.randperm(len(points), generator=gen)[:400]
        rel = points[pick] - origin
        rng = rel.norm(dim=1)
        dirs = rel / rng[:, None]
        prims = scene.primitives(f, dtype=torch.float64)
        first = _brute_force_first_hit(origin, dirs, prims)
        tol = 6 * (sensor.range_std_m + sensor.range_std_per_m * first + sensor.foliage_range_std_m)
        assert bool(torch.isfinite(first).all())
        assert bool((rng <= first + tol).all()), float((rng - first - tol).max())
        assert bool((rng >= first - tol).all())
        assert float((rng - first).abs().median()) < 0.05


def test_num_points_in_gt_counts_points_in_boxes(synthetic_root, val_seq):
    infos = _infos(synthetic_root, val_seq)
    for f in PHYSICS_FRAMES:
        points = _points(synthetic_root, val_seq, f)
        annos = infos[f]["annos"]
        mask = points_in_boxes_mask(points[:, :3], annos["gt_boxes_lidar"][:, :7])
        assert np.array_equal(mask.sum(axis=1), annos["num_points_in_gt"])
        assert (annos["num_points_in_gt"] > 100).sum() >= 5


def test_no_label_zone_flags(synthetic_root, fixture_args):
    seed, frames = fixture_args
    flagged = 0
    for split in ("train", "val"):
        for index, seq in enumerate(_sequences(synthetic_root, split)):
            scene = SyntheticScene(seed, split, index, frames[split])
            infos = _infos(synthetic_root, seq)
            for f in (0, frames[split] - 1):
                points = _points(synthetic_root, seq, f)
                pose = infos[f]["pose"].astype(np.float64)
                xy = points[:, :2].astype(np.float64) @ pose[:2, :2].T + pose[:2, 3]
                expected = np.where(scene.in_no_label_zone(xy), 1.0, -1.0)
                assert np.array_equal(points[:, 5], expected)
                flagged += int((expected == 1).sum())
                # nothing is labelled inside a no-label zone
                boxes = infos[f]["annos"]["gt_boxes_lidar"]
                centres = boxes[:, :2] @ pose[:2, :2].T + pose[:2, 3]
                assert not scene.in_no_label_zone(centres).any()
    assert flagged > 0


def test_every_label_was_seen_at_some_frame(synthetic_root, fixture_args):
    seed, frames = fixture_args
    for split in ("train", "val"):
        for seq in _sequences(synthetic_root, split):
            best: dict[str, int] = {}
            zero = 0
            for info in _infos(synthetic_root, seq):
                annos = info["annos"]
                for oid, n in zip(annos["obj_ids"].tolist(), annos["num_points_in_gt"].tolist()):
                    best[oid] = max(best.get(oid, 0), n)
                    zero += n == 0
            assert best and min(best.values()) > 0, seq
    assert zero > 0  # occluded frames of a seen object keep their label with 0 points


def test_ego_drives_turns_and_stops():
    """Over a few 198-frame scenes the ego stops at a junction and turns, and always drives."""
    stops = turns = 0
    for seed in range(3):
        scene = SyntheticScene(seed, "val", 0, 198)
        speed = np.linalg.norm(np.diff(scene.ego_xy, axis=0), axis=1) / 0.1
        assert speed.sum() * 0.1 > 30.0 and speed.max() < 14.0
        stops += (speed < 0.05).sum() >= 10
        turns += abs(np.unwrap(scene.ego_yaw)[-1] - scene.ego_yaw[0]) > math.radians(60)
    assert stops >= 1 and turns >= 1


def test_ego_motion_and_rigid_poses(synthetic_root, val_seq):
    infos = _infos(synthetic_root, val_seq)
    poses = np.stack([i["pose"] for i in infos]).astype(np.float64)
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-5)
    assert np.allclose(np.linalg.det(rot), 1.0, atol=1e-5)
    assert np.allclose(poses[:, 3], [0, 0, 0, 1]) and np.allclose(rot[:, 2, 2], 1.0)
    step = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1)
    assert step.sum() > 10.0  # the ego drives
    assert step.max() < 2.0  # < 20 m/s, and no teleport


def test_tracks_are_stable_and_move_with_their_speed(synthetic_root, val_seq):
    infos = _infos(synthetic_root, val_seq)
    checked_moving = checked_static = 0
    for f in range(0, len(infos) - 1, 7):
        a, b = infos[f]["annos"], infos[f + 1]["annos"]
        assert len(set(a["obj_ids"])) == len(a["obj_ids"])  # unique ids within a frame
        ga = transform_boxes(a["gt_boxes_lidar"][:, :7], infos[f]["pose"].astype(np.float64))
        gb = transform_boxes(b["gt_boxes_lidar"][:, :7], infos[f + 1]["pose"].astype(np.float64))
        index_b = {oid: j for j, oid in enumerate(b["obj_ids"])}
        for i, oid in enumerate(a["obj_ids"]):
            if oid not in index_b:
                continue
            j = index_b[oid]
            assert a["name"][i] == b["name"][j]
            assert np.allclose(a["dimensions"][i], b["dimensions"][j])  # rigid label box
            moved = (gb[j, :2] - ga[i, :2]) / 0.1
            mean_speed = (a["speed_global"][i] + b["speed_global"][j]) / 2
            assert np.allclose(moved, mean_speed, atol=0.3), (oid, moved, mean_speed)
            if np.linalg.norm(mean_speed) > 1.0:
                checked_moving += 1
            elif np.linalg.norm(mean_speed) == 0.0:
                assert np.allclose(ga[i, :3], gb[j, :3], atol=2e-3)
                checked_static += 1
    assert checked_moving >= 10 and checked_static >= 10


def test_vehicles_have_body_and_cabin(synthetic_root, val_seq):
    """The front 10% of a well-observed vehicle (hood / cab) is clearly lower than its top."""
    infos = _infos(synthetic_root, val_seq)
    lower = total = 0
    for f in PHYSICS_FRAMES:
        points = _points(synthetic_root, val_seq, f)
        annos = infos[f]["annos"]
        boxes = annos["gt_boxes_lidar"][:, :7]
        mask = points_in_boxes_mask(points[:, :3], boxes)
        for k in np.nonzero((annos["name"] == "Vehicle") & (annos["num_points_in_gt"] > 300))[0]:
            p = points[mask[k]]
            c, s = math.cos(boxes[k, 6]), math.sin(boxes[k, 6])
            along = (p[:, 0] - boxes[k, 0]) * c + (p[:, 1] - boxes[k, 1]) * s
            front = along > 0.4 * boxes[k, 3]
            if front.sum() < 10:
                continue
            total += 1
            lower += p[front, 2].max() < p[:, 2].max() - 0.15
    assert total >= 5 and lower >= 0.9 * total, (lower, total)


# ------------------------------------------------------------------------------- ray caster
def _reference_hit(origin, d, boxes, cylinders, max_range):
    """Plain per-ray reference: nearest of ground (z = 0), boxes and cylinders."""
    best, best_id = math.inf, NO_HIT_ID
    if d[2] < 0:
        best, best_id = -origin[2] / d[2], GROUND_ID
    for k, (x, y, z, dx, dy, dz, yaw) in enumerate(boxes):
        c, s = math.cos(yaw), math.sin(yaw)
        o = (origin[0] - x, origin[1] - y, origin[2] - z)
        ol = (o[0] * c + o[1] * s, -o[0] * s + o[1] * c, o[2])
        dl = (d[0] * c + d[1] * s, -d[0] * s + d[1] * c, d[2])
        t_near, t_far = -math.inf, math.inf
        for axis, half in enumerate((dx / 2, dy / 2, dz / 2)):
            if abs(dl[axis]) < 1e-12:
                if abs(ol[axis]) > half:
                    t_near = math.inf
                continue
            t1, t2 = (-half - ol[axis]) / dl[axis], (half - ol[axis]) / dl[axis]
            t_near, t_far = max(t_near, min(t1, t2)), min(t_far, max(t1, t2))
        if t_near <= t_far and 1e-3 < t_near < best:
            best, best_id = t_near, k
    for k, (x, y, z0, z1, r) in enumerate(cylinders):
        ox, oy = origin[0] - x, origin[1] - y
        a = d[0] ** 2 + d[1] ** 2
        b = 2 * (ox * d[0] + oy * d[1])
        cc = ox**2 + oy**2 - r**2
        cands = []
        if a > 1e-12 and b * b - 4 * a * cc >= 0:
            t = (-b - math.sqrt(b * b - 4 * a * cc)) / (2 * a)
            if z0 <= origin[2] + t * d[2] <= z1:
                cands.append(t)
        if abs(d[2]) > 1e-12:
            for zc in (z0, z1):
                t = (zc - origin[2]) / d[2]
                if (ox + t * d[0]) ** 2 + (oy + t * d[1]) ** 2 <= r * r:
                    cands.append(t)
        for t in cands:
            if 1e-3 < t < best:
                best, best_id = t, len(boxes) + k
    if best > max_range:
        return math.inf, NO_HIT_ID
    return best, best_id


@pytest.mark.parametrize("device", DEVICES)
def test_raycast_matches_per_ray_reference(device):
    gen = np.random.default_rng(0)
    n_box, n_cyl = 25, 12
    xy = gen.uniform(-25, 25, (n_box, 2))
    dims = gen.uniform(0.3, 6.0, (n_box, 3))
    boxes = np.concatenate(
        [
            xy,
            dims[:, 2:3] / 2 + gen.uniform(0, 1.5, (n_box, 1)),
            dims,
            gen.uniform(-3, 3, (n_box, 1)),
        ],
        axis=1,
    )
    cxy = gen.uniform(-20, 20, (n_cyl, 2))
    z0 = gen.uniform(0, 2.5, (n_cyl, 1))
    cylinders = np.concatenate(
        [cxy, z0, z0 + gen.uniform(0.3, 5, (n_cyl, 1)), gen.uniform(0.1, 2.0, (n_cyl, 1))], axis=1
    )
    boxes[0] = [0.5, 0.0, 1.0, 3.0, 2.0, 4.0, 0.3]  # the sensor is inside: never hit
    incl = torch.linspace(-0.35, 0.3, 12, dtype=torch.float64)
    num_cols = 180
    origin = torch.tensor([1.43, 0.0, 2.184], dtype=torch.float64)
    prims = Primitives(
        torch.from_numpy(boxes),
        torch.full((n_box,), 0.3),
        torch.zeros(n_box, dtype=torch.long),
        torch.from_numpy(cylinders),
        torch.full((n_cyl,), 0.3),
        torch.zeros(n_cyl, dtype=torch.long),
    ).to(device, torch.float64)
    hits = raycast_scan(origin.to(device), incl.to(device), num_cols, prims, 0.0, 40.0)
    dirs = ray_directions(incl, column_azimuths(num_cols))
    ref = [_reference_hit(origin.tolist(), d.tolist(), boxes, cylinders, 40.0) for d in dirs]
    ref_t = torch.tensor([t for t, _ in ref], dtype=torch.float64)
    ref_id = torch.tensor([i for _, i in ref])
    got_t, got_id = hits.range_m.cpu(), hits.prim_id.cpu()
    assert torch.equal(torch.isfinite(got_t), torch.isfinite(ref_t))
    fin = torch.isfinite(ref_t)
    assert torch.allclose(got_t[fin], ref_t[fin], atol=1e-9, rtol=0)
    assert (got_id == ref_id).float().mean() > 0.999
    kinds = set(ref_id.tolist())
    assert GROUND_ID in kinds and NO_HIT_ID in kinds and any(0 <= k < n_box for k in kinds)
    assert any(k >= n_box for k in kinds) and 0 not in kinds
    # normals are unit and face the sensor
    normal = hits.normal.cpu()[fin]
    assert torch.allclose(normal.norm(dim=1), torch.ones(int(fin.sum()), dtype=torch.float64))
    assert bool(((normal * dirs[fin]).sum(dim=1) <= 1e-9).all())


def test_cli_writes_the_requested_sizes(tmp_path, capsys):
    import importlib.util

    from pcdet_atlas.config import REPO_ROOT

    spec = importlib.util.spec_from_file_location(
        "create_synthetic_waymo_cli", REPO_ROOT / "tools" / "data" / "create_synthetic_waymo.py"
    )
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    argv = ["--out_dir", str(tmp_path), "--train_sequences", "0", "--val_sequences", "1"]
    summary = cli.main(argv + ["--val_frames", "1", "--seed", "3", "--workers", "1"])
    assert summary["frames"] == {"train": 0, "val": 1}
    assert _sequences(tmp_path, "val") == [sequence_name(3, "val", 0)]
    assert (tmp_path / "ImageSets" / "train.txt").read_text() == ""
    out = capsys.readouterr().out
    assert "points/frame" in out and "time:" in out


def test_windowed_raycast_equals_brute_force_on_a_scene(fixture_args):
    """The culled caster finds exactly the first hits of an unculled cast on a real scene."""
    seed, frames = fixture_args
    scene = SyntheticScene(seed, "val", 0, frames["val"])
    lidar = LidarModel.waymo_top()
    incl = lidar.inclinations[::4].to(torch.float32)  # 16 beams x 1327 columns
    origin = lidar.origin.to(torch.float32)
    prims = scene.primitives(40)
    hits = raycast_scan(origin, incl, 1327, prims, 0.0, 75.0)
    dirs = ray_directions(incl, column_azimuths(1327, dtype=torch.float32))
    ref = _brute_force_first_hit(origin, dirs, prims)
    ref = torch.where(ref > 75.0, torch.full_like(ref, math.inf), ref)
    assert torch.equal(torch.isfinite(ref), torch.isfinite(hits.range_m))
    fin = torch.isfinite(ref)
    assert torch.allclose(hits.range_m[fin], ref[fin], atol=1e-4, rtol=0)
    assert int((hits.prim_id >= 0).sum()) > 1000


def test_windowed_raycast_keeps_grazing_hits_of_thin_far_objects():
    """Thin, far primitives (poles, legs at 40-75 m) span a few columns: float32 window bounds
    must never cull a ray that grazes them (full-resolution grid vs an unculled cast)."""
    gen = np.random.default_rng(1)
    n = 24
    rng_m = gen.uniform(40.0, 74.0, n)
    az = gen.uniform(-math.pi, math.pi, n)
    xy = np.stack([1.43 + rng_m * np.cos(az), rng_m * np.sin(az)], axis=1)
    z0 = gen.uniform(0.0, 1.0, (n, 1))
    cylinders = np.concatenate(
        [xy, z0, z0 + gen.uniform(0.5, 3.0, (n, 1)), gen.uniform(0.04, 0.3, (n, 1))], 1
    )
    boxes = np.concatenate(
        [xy[::-1] * 0.97, gen.uniform(0.5, 2.0, (n, 1)), gen.uniform(0.05, 0.4, (n, 2)),
         gen.uniform(0.5, 2.0, (n, 1)), gen.uniform(-3, 3, (n, 1))], 1
    )  # fmt: skip
    prims = Primitives(
        torch.from_numpy(boxes),
        torch.full((n,), 0.3),
        torch.zeros(n, dtype=torch.long),
        torch.from_numpy(cylinders),
        torch.full((n,), 0.3),
        torch.zeros(n, dtype=torch.long),
    ).to("cpu", torch.float32)
    lidar = LidarModel.waymo_top()
    origin = lidar.origin.to(torch.float32)
    hits = raycast_scan(origin, lidar.inclinations, lidar.azimuth_bins, prims, None, 75.0)
    dirs = ray_directions(
        lidar.inclinations.to(torch.float32),
        column_azimuths(lidar.azimuth_bins, dtype=torch.float32),
    )
    ref = torch.full((dirs.shape[0],), math.inf)
    for k in range(n):
        ref = torch.minimum(
            ref, ray_box_distance(origin, dirs, prims.boxes[k].expand(len(dirs), 7))
        )
        ref = torch.minimum(
            ref, ray_cylinder_distance(origin, dirs, prims.cylinders[k].expand(len(dirs), 5))
        )
    ref = torch.where(ref > 75.0, torch.full_like(ref, math.inf), ref)
    assert int(torch.isfinite(ref).sum()) > 500
    assert torch.equal(torch.isfinite(ref), torch.isfinite(hits.range_m))
    fin = torch.isfinite(ref)
    assert torch.equal(hits.range_m[fin], ref[fin])
