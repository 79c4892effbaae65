import math
from collections import defaultdict

import numpy as np
import pytest
import torch
from device_params import DEVICES
from hypothesis import given, settings
from hypothesis import strategies as st
from raycast_reference import reference_raycast_merge, reference_wedge_rows

from pcdet_atlas.attacks.counters import AttackCounters
from pcdet_atlas.attacks.raycast import (
    _elevation_band_rows,
    _sector_wedges,
    azimuth_sector_candidates,
    disc_wedges,
    raycast_merge,
    wedge_rows,
)
from pcdet_atlas.ops.lidar_model import LidarModel


def candidates_among_all_rows(scene, columns, lidar):
    rows = torch.arange(scene.shape[0])
    return azimuth_sector_candidates(scene, columns, lidar, rows)


#: The sector pre-filter must be a superset, over the whole scene or among given rows.
CANDIDATE_FNS = [azimuth_sector_candidates, candidates_among_all_rows]


def reference_merge(scene, spoof, lidar, p_dual=0.0, generator=None):
    """docs/attacks.md's raycast rules, plainly: a dict of rays -> lists of (range, index)."""
    s_bin, s_fov, s_rng = (t.tolist() for t in lidar.bin_index(scene.cpu().double()))
    p_bin, p_fov, p_rng = (t.tolist() for t in lidar.bin_index(spoof.cpu().double()))
    scene_rays, spoof_rays = defaultdict(list), defaultdict(list)
    for i, (b, fov, r) in enumerate(zip(s_bin, s_fov, s_rng)):
        if fov and r > 0 and math.isfinite(r):
            scene_rays[b].append((r, i))
    for j, (b, fov, r) in enumerate(zip(p_bin, p_fov, p_rng)):
        if fov and 0 < r <= lidar.max_range:
            spoof_rays[b].append((r, j))
    keep_scene = [True] * len(s_bin)
    keep_spoof = [False] * len(p_bin)
    primary = []
    for b in sorted(spoof_rays):
        echo_r, j = min(spoof_rays[b])  # nearest, then lowest index
        returns = scene_rays.get(b, [])
        if returns and echo_r >= max(r for r, _ in returns):
            continue
        keep_spoof[j] = True
        for r, i in returns:
            if r > echo_r:
                keep_scene[i] = False
        if returns and echo_r < min(r for r, _ in returns):
            primary.append(b)
    if p_dual > 0 and primary:
        u = torch.rand(len(primary), generator=generator, dtype=torch.float64).tolist()
        for b, draw in zip(primary, u):
            if draw < p_dual:
                keep_scene[min(scene_rays[b])[1]] = True
    return torch.tensor(keep_scene, dtype=torch.bool), torch.tensor(keep_spoof, dtype=torch.bool)


def small_lidar(azimuth_bins=90):
    return LidarModel(np.deg2rad([-15.0, -10.0, -6.0, -3.0, -1.0, 0.5, 2.0]), azimuth_bins)


def ray_points(lidar, beams, cols, ranges, frac_az=None, frac_el=None):
    """Points on given rays: beam centre elevation, azimuth inside the column, range in metres."""
    beams = np.asarray(beams)
    cols = np.asarray(cols)
    ranges = np.asarray(ranges, dtype=np.float64)
    width = 2 * np.pi / lidar.azimuth_bins
    frac_az = 0.5 if frac_az is None else frac_az
    az = -np.pi + (cols + frac_az) * width
    el = lidar.inclinations.numpy()[beams] + (0.0 if frac_el is None else frac_el)
    o = lidar.origin.numpy()
    xyz = np.stack(
        [
            o[0] + ranges * np.cos(el) * np.cos(az),
            o[1] + ranges * np.cos(el) * np.sin(az),
            o[2] + ranges * np.sin(el),
        ],
        1,
    )
    return torch.as_tensor(xyz, dtype=torch.float32)


def random_case(seed, lidar, num_scene=3000, num_spoof=300, center_deg=None, spread_deg=20.0):
    """A scene with several returns per ray in places, and a spoof cluster sharing its rays."""
    g = np.random.default_rng(seed)
    M, B = lidar.azimuth_bins, lidar.num_beams
    center = g.uniform(-180, 180) if center_deg is None else center_deg
    col_c = int((np.deg2rad(center) + np.pi) / (2 * np.pi / M))
    span = max(1, int(spread_deg / 360 * M))
    s_cols = g.integers(0, M, num_scene)
    near = g.random(num_scene) < 0.5  # half the scene inside the spoof's sector
    s_cols[near] = (col_c + g.integers(-span, span + 1, near.sum())) % M
    scene = ray_points(
        lidar,
        g.integers(0, B, num_scene),
        s_cols,
        g.uniform(2, 90, num_scene),  # some beyond max_range
        frac_az=g.uniform(0, 1, num_scene),
        frac_el=g.uniform(-0.004, 0.004, num_scene),
    )
    p_cols = (col_c + g.integers(-span, span + 1, num_spoof)) % M
    spoof = ray_points(
        lidar,
        g.integers(0, B, num_spoof),
        p_cols,
        g.uniform(3, 85, num_spoof),
        frac_az=g.uniform(0, 1, num_spoof),
        frac_el=g.uniform(-0.004, 0.004, num_spoof),
    )
    # exact duplicates: equal ranges must tie-break to the lower index
    spoof[num_spoof // 2 :: 7] = spoof[num_spoof // 2 - 1]
    scene[::11] = scene[1::11][: scene[::11].shape[0]]
    return scene, spoof


def check_against_reference(scene, spoof, lidar, p_dual=0.0, seed=0, device="cpu"):
    gen = torch.Generator().manual_seed(seed) if p_dual > 0 else None
    ref_gen = torch.Generator().manual_seed(seed) if p_dual > 0 else None
    keep_scene, keep_spoof = raycast_merge(
        scene.to(device), spoof.to(device), lidar, p_dual=p_dual, generator=gen
    )
    assert keep_scene.device.type == device and keep_scene.dtype == torch.bool
    assert keep_scene.shape == (scene.shape[0],) and keep_spoof.shape == (spoof.shape[0],)
    exp_scene, exp_spoof = reference_merge(scene, spoof, lidar, p_dual, ref_gen)
    assert torch.equal(keep_scene.cpu(), exp_scene)
    assert torch.equal(keep_spoof.cpu(), exp_spoof)
    return keep_scene.cpu(), keep_spoof.cpu()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(6))
def test_matches_reference_random_scenes(seed, device):
    lidar = small_lidar() if seed % 2 else LidarModel.waymo_top()
    scene, spoof = random_case(seed, lidar)
    keep_scene, keep_spoof = check_against_reference(scene, spoof, lidar, 0.0, device=device)
    assert 0 < keep_spoof.sum() < spoof.shape[0] and (~keep_scene).sum() > 0  # non-trivial case
    check_against_reference(scene, spoof, lidar, 0.4, seed=seed, device=device)


@pytest.mark.parametrize("device", DEVICES)
def test_spoof_straddling_pi(device):
    lidar = LidarModel.waymo_top()
    for seed in range(3):
        scene, spoof = random_case(100 + seed, lidar, center_deg=180.0, spread_deg=6.0)
        _, keep_spoof = check_against_reference(scene, spoof, lidar, device=device)
        cols = lidar.bin_index(spoof.double())[0] % lidar.azimuth_bins
        assert (cols[keep_spoof] < 10).any() and (cols[keep_spoof] > 2640).any()
    # points exactly on the seam (y = 0 behind the sensor, azimuth +-pi) both sides
    o = lidar.origin
    seam = torch.tensor(
        [[o[0] - 20.0, 0.0, o[2]], [o[0] - 30.0, -0.0, o[2]], [o[0] - 10.0, 0.0, o[2]]]
    )
    check_against_reference(seam[:2], seam[2:], lidar, device=device)
    keep_scene, _ = raycast_merge(seam[:2].to(device), seam[2:].to(device), lidar, p_dual=0)
    assert not keep_scene.any()


def test_bin_edges_and_beam_midpoints():
    lidar = small_lidar(azimuth_bins=48)
    g = np.random.default_rng(7)
    n = 800
    mids = ((lidar.inclinations[1:] + lidar.inclinations[:-1]) / 2).numpy()
    cols = g.integers(0, 48, n)
    beams = g.integers(0, lidar.num_beams - 1, n)
    ranges = g.uniform(2, 60, n)
    width = 2 * np.pi / 48
    az = -np.pi + cols * width  # exactly on a column edge (in float64)
    el = mids[beams]  # exactly on a beam midpoint
    o = lidar.origin.numpy()
    xyz = np.stack(
        [
            o[0] + ranges * np.cos(el) * np.cos(az),
            o[1] + ranges * np.cos(el) * np.sin(az),
            o[2] + ranges * np.sin(el),
        ],
        1,
    )
    for dtype in (torch.float32, torch.float64):
        pts = torch.as_tensor(xyz, dtype=dtype)
        scene, spoof = pts[:600], pts[600:]
        check_against_reference(scene, spoof, lidar)
        # the sector prefilter never misses a point of an occupied column
        s_bin = lidar.bin_index(scene.double())[0] % 48
        p_cols = torch.unique(lidar.bin_index(spoof.double())[0] % 48)
        needed = torch.nonzero(torch.isin(s_bin, p_cols)).squeeze(1)
        for candidates in CANDIDATE_FNS:
            assert torch.isin(needed, candidates(scene, p_cols, lidar)).all()


@settings(max_examples=40, deadline=None)
@given(
    data=st.lists(
        st.tuples(
            st.integers(0, 1),  # beam
            st.sampled_from([0, 1, 5, 11]),  # column (0 and 11 meet at the +-pi seam)
            st.sampled_from([0.0, 5.0, 5.0, 10.0, 20.0, 74.0, 75.0, 80.0]),  # range (dups)
            st.booleans(),  # spoof?
        ),
        max_size=40,
    )
)
def test_property_small_rays(data):
    lidar = LidarModel(np.deg2rad([-15.0, -10.0, -6.0, -3.0, -1.0, 0.5, 2.0]), 12)
    if data:
        beams, cols, ranges, is_spoof = map(np.array, zip(*data))
        pts = ray_points(lidar, beams, cols, ranges, frac_az=0.5)
        scene, spoof = pts[~is_spoof], pts[is_spoof]
    else:
        scene = spoof = torch.zeros(0, 3)
    check_against_reference(scene, spoof, lidar)
    check_against_reference(scene, spoof, lidar, p_dual=0.5, seed=3)


def test_range_zero_out_of_fov_and_beyond_max_range():
    lidar = LidarModel.waymo_top()
    o = lidar.origin.tolist()
    beam0 = int(torch.argmin(lidar.inclinations.abs()))
    spoof = ray_points(lidar, [beam0, beam0, beam0], [1325, 1325, 1325], [10.0, 76.0, 0.0])
    spoof[2] = torch.tensor(o)  # a spoof point at the sensor: no direction, dropped
    scene = torch.cat(
        [
            torch.tensor([o]),  # range 0: never touched, not a return
            torch.tensor([[o[0] + 20.0, 0.0, o[2] + 40.0]]),  # above the fan: never touched
            ray_points(lidar, [beam0], [1325], [80.0]),  # beyond max_range: still a return
        ]
    )
    counters = AttackCounters()
    keep_scene, keep_spoof = raycast_merge(scene, spoof, lidar, p_dual=0.0, counters=counters)
    assert keep_spoof.tolist() == [True, False, False]  # 76 m > max_range is dropped
    assert keep_scene.tolist() == [True, True, False]  # the 80 m return is occluded
    assert counters.bins_touched == 1
    check_against_reference(scene, spoof, lidar)
    # an out-of-FOV spoof point is dropped, a spoof behind every return too
    spoof2 = torch.cat([spoof[:1] + torch.tensor([0.0, 0.0, 30.0]), spoof[1:2]])
    keep_scene, keep_spoof = raycast_merge(scene[2:], spoof2[1:], lidar, p_dual=0.0)
    assert keep_spoof.tolist() == [False] and keep_scene.all()  # 76 m: beyond max_range
    far_scene = ray_points(lidar, [beam0], [1325], [8.0])
    keep_scene, keep_spoof = raycast_merge(far_scene, spoof[:1], lidar, p_dual=0.0)
    assert keep_spoof.tolist() == [False] and keep_scene.tolist() == [True]
    assert not raycast_merge(scene, spoof2[:1], lidar, p_dual=0.0)[1].any()


def test_equal_ranges():
    lidar = LidarModel.waymo_top()
    counters = AttackCounters()
    gen = torch.Generator().manual_seed(0)
    one = ray_points(lidar, [20], [700], [15.0])
    # a spoof exactly at the only return is not in front of it: dropped
    keep_scene, keep_spoof = raycast_merge(one, one.clone(), lidar, 1.0, gen, counters)
    assert keep_spoof.tolist() == [False] and keep_scene.tolist() == [True]
    # at the nearest of two returns: kept, occludes the farther one, not primary (no draw)
    two = torch.cat([one, ray_points(lidar, [20], [700], [25.0])])
    keep_scene, keep_spoof = raycast_merge(two, one.clone(), lidar, 1.0, gen, counters)
    assert keep_spoof.tolist() == [True] and keep_scene.tolist() == [True, False]
    assert counters.dual_draws == 0 and counters.bins_touched == 2
    check_against_reference(two, one.clone(), lidar)


def test_points_near_the_sensor_axis():
    """Float32 azimuths of points a few ulps from the sensor axis are far off; the sector
    prefilter must still find every point of an occupied column."""
    lidar = LidarModel.waymo_top()
    o = torch.tensor(lidar.origin.tolist(), dtype=torch.float32)
    ulp = float(torch.finfo(torch.float32).eps) * 1.43
    k = torch.arange(-12, 13, dtype=torch.float32)
    gx, gy = torch.meshgrid(o[0] + k * ulp, k * 1e-7, indexing="ij")
    scene = torch.stack([gx.flatten(), gy.flatten(), torch.full_like(gx.flatten(), o[2])], 1)
    cols = lidar.bin_index(scene.double())[0] % lidar.azimuth_bins
    present = torch.unique(cols)
    assert present.numel() > 100
    for c in present[:: max(1, present.numel() // 60)]:
        needed = torch.nonzero(cols == c).squeeze(1)
        for candidates in CANDIDATE_FNS:
            assert torch.isin(needed, candidates(scene, c.view(1), lidar)).all(), int(c)
    # and the merge agrees with the reference on such a scene
    spoof = ray_points(lidar, [40, 50, 60], [300, 1325, 2000], [10.0, 12.0, 14.0])
    check_against_reference(scene, spoof, lidar)


def test_empty_inputs():
    lidar = LidarModel.waymo_top()
    spoof = ray_points(lidar, [10, 10, 20], [5, 5, 7], [10.0, 9.0, 4.0])
    keep_scene, keep_spoof = raycast_merge(torch.zeros(0, 3), spoof, lidar, p_dual=0.0)
    assert keep_scene.shape == (0,) and keep_spoof.tolist() == [False, True, True]
    counters = AttackCounters()
    scene = spoof.clone()
    keep_scene, keep_spoof = raycast_merge(
        scene, torch.zeros(0, 3), lidar, p_dual=0.0, counters=counters
    )
    assert keep_scene.all() and keep_spoof.shape == (0,)
    assert counters.snapshot() == AttackCounters().snapshot()  # no spoof: no work, no draw
    keep_scene, keep_spoof = raycast_merge(
        torch.zeros(0, 5), torch.zeros(0, 5), lidar, 0.01, torch.Generator()
    )
    assert keep_scene.shape == (0,) and keep_spoof.shape == (0,)


def test_ties_break_to_lower_index_and_determinism():
    lidar = LidarModel.waymo_top()
    spoof = ray_points(lidar, [30] * 4, [100] * 4, [12.0, 9.0, 9.0, 9.0])
    spoof[3] = spoof[1]
    scene = ray_points(lidar, [30] * 4, [100] * 4, [20.0, 15.0, 15.0, 30.0])
    scene[2] = scene[1]
    gen = torch.Generator().manual_seed(0)
    keep_scene, keep_spoof = raycast_merge(scene, spoof, lidar, p_dual=1.0, generator=gen)
    assert keep_spoof.tolist() == [False, True, False, False]
    assert keep_scene.tolist() == [False, True, False, False]  # second echo: lower index
    # same seed -> same result; different seeds differ somewhere over many primary rays
    scene, spoof = random_case(5, LidarModel.waymo_top(), num_scene=4000, num_spoof=600)
    a = raycast_merge(scene, spoof, lidar, 0.5, torch.Generator().manual_seed(1))
    b = raycast_merge(scene, spoof, lidar, 0.5, torch.Generator().manual_seed(1))
    c = raycast_merge(scene, spoof, lidar, 0.5, torch.Generator().manual_seed(2))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert not torch.equal(a[0], c[0]) and torch.equal(a[1], c[1])


def test_dual_return_frequency():
    lidar = LidarModel.waymo_top()
    g = np.random.default_rng(0)
    n = 4000  # distinct rays, each with a spoof in front of two scene returns
    flat = g.choice(lidar.num_bins, n, replace=False)
    beams, cols = flat // lidar.azimuth_bins, flat % lidar.azimuth_bins
    spoof = ray_points(lidar, beams, cols, g.uniform(5, 10, n))
    near = ray_points(lidar, beams, cols, g.uniform(20, 40, n))
    far = ray_points(lidar, beams, cols, g.uniform(50, 70, n))
    scene = torch.cat([near, far])
    p = 0.1
    counters = AttackCounters()
    gen = torch.Generator().manual_seed(11)
    keep_scene, keep_spoof = raycast_merge(scene, spoof, lidar, p, gen, counters=counters)
    assert keep_spoof.all() and not keep_scene[n:].any()  # far returns always occluded
    kept = int(keep_scene[:n].sum())
    assert counters.dual_draws == n and counters.bins_touched == n
    assert abs(kept - n * p) <= 5 * math.sqrt(n * p * (1 - p))
    # p_dual = 0: deterministic, no draw, no generator needed
    counters.reset()
    keep_scene, _ = raycast_merge(scene, spoof, lidar, 0.0, counters=counters)
    assert not keep_scene.any() and counters.dual_draws == 0


def test_work_restricted_to_sector():
    lidar = LidarModel.waymo_top()
    scene, spoof = random_case(3, lidar, num_scene=5000, num_spoof=200, center_deg=30.0)
    spread = scene.shape[0]
    # spoof sector around +30 deg; add 50k points in the opposite half of the scan
    g = np.random.default_rng(1)
    m = 50000
    far_cols = g.integers(0, lidar.azimuth_bins // 2 - 200, m)  # azimuth in [-180, -30) deg
    extra = ray_points(
        lidar, g.integers(0, 64, m), far_cols, g.uniform(2, 70, m), frac_az=g.uniform(0, 1, m)
    )
    c1, c2 = AttackCounters(), AttackCounters()
    k1 = raycast_merge(scene, spoof, lidar, p_dual=0.0, counters=c1)
    k2 = raycast_merge(torch.cat([scene, extra]), spoof, lidar, p_dual=0.0, counters=c2)
    assert c1.snapshot() == c2.snapshot()
    assert torch.equal(k2[0][:spread], k1[0]) and k2[0][spread:].all()
    assert torch.equal(k1[1], k2[1])
    assert c1.points_examined < 0.6 * spread + spoof.shape[0]  # far-sector scene points skipped
    # the examined points grow with the points inside the sector
    c3 = AttackCounters()
    raycast_merge(torch.cat([scene, scene]), spoof, lidar, p_dual=0.0, counters=c3)
    assert c3.points_examined - spoof.shape[0] == 2 * (c1.points_examined - spoof.shape[0])


def test_extra_columns_and_float64():
    lidar = small_lidar()
    scene, spoof = random_case(9, lidar, num_scene=1000, num_spoof=100)
    extra = torch.randn(scene.shape[0], 2)
    a = raycast_merge(torch.cat([scene, extra], 1), spoof, lidar, p_dual=0.0)
    b = raycast_merge(scene.double(), spoof.double(), lidar, p_dual=0.0)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_non_finite_scene_points_untouched():
    lidar = LidarModel.waymo_top()
    spoof = ray_points(lidar, [40], [1300], [10.0])
    scene = torch.cat(
        [
            ray_points(lidar, [40], [1300], [30.0]),
            torch.tensor([[math.nan, 0.0, 0.0], [math.inf, 0.0, 2.0], [5.0, math.inf, 2.0]]),
        ]
    )
    keep_scene, keep_spoof = raycast_merge(scene, spoof, lidar, p_dual=0.0)
    assert keep_scene.tolist() == [False, True, True, True] and keep_spoof.all()


def test_bad_arguments():
    lidar = LidarModel.waymo_top()
    pts = torch.zeros(3, 3)
    with pytest.raises(ValueError, match="explicit torch.Generator"):
        raycast_merge(pts, pts, lidar, p_dual=0.01)
    with pytest.raises(ValueError, match="p_dual"):
        raycast_merge(pts, pts, lidar, p_dual=1.5, generator=torch.Generator())
    with pytest.raises(ValueError, match="shape"):
        raycast_merge(torch.zeros(3, 2), pts, lidar, p_dual=0.0)
    with pytest.raises(TypeError, match="floating"):
        raycast_merge(torch.zeros(3, 3, dtype=torch.long), pts, lidar, p_dual=0.0)
    with pytest.raises(ValueError, match="non-finite"):
        raycast_merge(pts, torch.full((1, 3), math.nan), lidar, p_dual=0.0)


# ---------------------------------------------------------------- hard sectors vs the reference
@pytest.mark.parametrize("seed", range(8))
def test_matches_reference_narrow_wide_split_and_seam_sectors(seed):
    lidar = small_lidar() if seed % 2 else LidarModel.waymo_top()
    spread = [3.0, 20.0, 120.0, 200.0][seed % 4]  # narrow, wide, split wedges, full scan
    center = [None, 179.0, -179.5, None][seed // 2 % 4]  # incl. sectors across the seam
    scene, spoof = random_case(seed, lidar, 3000, 300, center_deg=center, spread_deg=spread)
    extra = torch.randn(scene.shape[0], 2)
    for p_dual in (0.0, 0.5):
        exp_scene, exp_spoof = reference_merge(
            scene, spoof, lidar, p_dual, torch.Generator().manual_seed(seed)
        )
        for sc, sp in ((scene, spoof), (scene.double(), spoof.double()),
                       (torch.cat([scene, extra], 1), spoof)):  # fmt: skip
            gen = torch.Generator().manual_seed(seed)
            keep_scene, keep_spoof = raycast_merge(sc, sp, lidar, p_dual, gen)
            assert torch.equal(keep_scene, exp_scene) and torch.equal(keep_spoof, exp_spoof)


def test_spoof_in_few_beams_on_beam_midpoints():
    """Scene points exactly on beam midpoints and column edges around the spoof's beams."""
    lidar = LidarModel.waymo_top()
    g = np.random.default_rng(3)
    n = 6000
    mids = ((lidar.inclinations[1:] + lidar.inclinations[:-1]) / 2).numpy()
    beams = g.integers(18, 34, n)
    on_mid = g.random(n) < 0.5
    el = np.where(on_mid, mids[beams], lidar.inclinations.numpy()[beams])
    cols = 1300 + g.integers(-40, 40, n)
    az = -np.pi + (cols + np.where(g.random(n) < 0.3, 0.0, g.random(n))) * 2 * np.pi / 2651
    r = g.uniform(3, 70, n)
    o = lidar.origin.numpy()
    xyz = np.stack(
        [
            o[0] + r * np.cos(el) * np.cos(az),
            o[1] + r * np.cos(el) * np.sin(az),
            o[2] + r * np.sin(el),
        ],
        1,
    )
    scene = torch.as_tensor(xyz[:5000], dtype=torch.float32)
    spoof = ray_points(
        lidar, g.integers(22, 29, 400), 1300 + g.integers(-30, 30, 400), g.uniform(4, 60, 400)
    )
    for p_dual in (0.0, 1.0):
        keep_scene, keep_spoof = raycast_merge(
            scene, spoof, lidar, p_dual, torch.Generator().manual_seed(0)
        )
        exp = reference_merge(scene, spoof, lidar, p_dual, torch.Generator().manual_seed(0))
        assert torch.equal(keep_scene, exp[0]) and torch.equal(keep_spoof, exp[1])
    assert (~keep_scene).sum() > 50 and keep_spoof.sum() > 50


def test_low_precision_and_grad_inputs():
    lidar = LidarModel.waymo_top()
    scene, spoof = random_case(2, lidar, num_scene=2000, num_spoof=200)
    ks, kp = raycast_merge(scene, spoof, lidar, 0.0)
    ks_bf, kp_bf = raycast_merge(scene.bfloat16(), spoof.bfloat16(), lidar, 0.0)
    assert ks_bf.shape == (scene.shape[0],)
    # bfloat16 points are cast exactly as the same values in float32 would be
    ks_up, kp_up = raycast_merge(scene.bfloat16().float(), spoof.bfloat16().float(), lidar, 0.0)
    assert torch.equal(ks_bf, ks_up) and torch.equal(kp_bf, kp_up)
    assert (ks_bf != ks).sum() <= 5 and kp_bf.sum() > 0.5 * kp.sum()  # close to full precision
    ks_grad, kp_grad = raycast_merge(scene.clone().requires_grad_(), spoof, lidar, 0.0)
    assert torch.equal(ks_grad, ks) and torch.equal(kp_grad, kp)


@pytest.mark.parametrize("device", DEVICES)
def test_dual_draws_from_numpy_generator_or_predrawn_uniforms(device):
    """A numpy Generator draws on the host, so CPU and CUDA inputs consume the same uniforms;
    an array of uniforms drawn beforehand gives the result of the generator it came from, and
    a too short one is an error."""
    lidar = LidarModel.waymo_top()
    scene, spoof = random_case(5, lidar, 3000, 300)
    ref = raycast_merge(scene, spoof, lidar, 0.5, np.random.default_rng(7))
    table = np.random.default_rng(7).random(spoof.shape[0])
    for source in (lambda: np.random.default_rng(7), lambda: table):
        ks, kp = raycast_merge(scene.to(device), spoof.to(device), lidar, 0.5, source())
        assert torch.equal(ks.cpu(), ref[0]) and torch.equal(kp.cpu(), ref[1])
    # the draws decide: other uniforms keep other second echoes
    other = raycast_merge(scene, spoof, lidar, 0.5, np.random.default_rng(8))
    assert not torch.equal(other[0], ref[0])
    with pytest.raises(ValueError, match="at least"):
        raycast_merge(scene, spoof, lidar, 0.5, table[:3])
    with pytest.raises(ValueError, match="explicit torch.Generator"):
        raycast_merge(scene, spoof, lidar, 0.5, generator=0.3)


def test_sector_wedges_merge_small_gaps_only():
    width = 2 * math.pi / 2651
    one = _sector_wedges([100, 101, 105, 120, 130], 2651)  # gaps of a few columns: one wedge
    assert len(one) == 1
    assert one[0][0] < -math.pi + 100 * width and one[0][1] > -math.pi + 131 * width
    two = _sector_wedges([100, 101, 1000, 1001], 2651)  # ~120 deg apart: two wedges
    assert len(two) == 2
    seam = _sector_wedges([0, 3, 2645, 2650], 2651)  # small gaps across the +-pi seam
    assert len(seam) == 1 and seam[0][0] < math.pi < seam[0][1]
    assert _sector_wedges(list(range(0, 2651, 10)), 2651) is None  # most of the circle


@pytest.mark.parametrize("seed", range(6))
def test_disc_wedge_rows_hold_the_sector_of_any_points_in_the_disc(seed):
    """The wedge pre-filter an injection shares between its ground estimate and its raycast:
    its rows hold every point of the disc and every sector candidate of points inside the
    disc (at any height), so the raycast given them as candidates is unchanged; none when the
    disc reaches the sensor's axis."""
    lidar = LidarModel.waymo_top()
    rng = np.random.default_rng(seed)
    ox, oy = lidar.origin_xyz[:2]
    angle = [math.pi - 0.01, -math.pi + 0.02, 0.3, 2.0, -1.2, math.pi][seed]  # seam too
    dist, radius = [4.5, 8.0, 17.0, 30.0, 60.0, 12.0][seed], [3.0, 3.0, 3.0, 4.5, 6.0, 3.0][seed]
    center = np.array([ox + dist * math.cos(angle), oy + dist * math.sin(angle)])
    scene = np.c_[rng.uniform(-75, 75, (40000, 2)), rng.uniform(-3, 4, 40000)]
    near = center + rng.uniform(-radius - 1, radius + 1, (8000, 2))
    scene = np.concatenate([scene, np.c_[near, rng.uniform(-2.5, 3, 8000)]]).astype(np.float32)
    u = rng.uniform(0, 2 * math.pi, 600)
    rad = radius * np.sqrt(rng.uniform(0, 0.999, 600))
    spoof = np.c_[center[0] + rad * np.cos(u), center[1] + rad * np.sin(u)]
    spoof = np.c_[spoof, rng.uniform(-2, 2.5, 600)].astype(np.float32)
    wedges = disc_wedges(lidar, center, radius)
    scene, spoof = torch.from_numpy(scene), torch.from_numpy(spoof)
    rows = wedge_rows(scene, wedges, lidar)
    assert rows.numel() < len(scene) / 2 and bool((rows.diff() > 0).all())
    d2 = ((scene[:, :2].double() - torch.from_numpy(center)) ** 2).sum(1)
    assert torch.isin(torch.nonzero(d2 <= radius * radius).squeeze(1), rows).all()
    columns = torch.unique(lidar.bin_index(spoof)[0] % lidar.azimuth_bins)
    assert torch.isin(azimuth_sector_candidates(scene, columns, lidar), rows).all()
    for p_dual in (0.0, 0.5):
        uniforms = rng.random(len(spoof))
        plain = raycast_merge(scene, spoof, lidar, p_dual, uniforms)
        given = raycast_merge(scene, spoof, lidar, p_dual, uniforms, candidates=rows)
        assert all(torch.equal(a, b) for a, b in zip(plain, given))
        assert (~plain[0]).any()
    assert disc_wedges(lidar, (ox + 2.0, oy), 3.0) is None  # the disc holds the sensor
    assert disc_wedges(lidar, (ox + 3.0, oy), 2.99) is not None


# ------------------------------------------- bitwise against the previous implementation
def reference_cases():
    """Scenes and spoofs that reach every branch of the pre-filters: sectors narrow, wide,
    split and across the seam; spoofs partly out of the FOV or beyond max_range; NaN scene
    points; sensors with laser offsets (no band filter) and with steep beams (band edges not
    tested); float64, bfloat16 and extra columns."""
    steep = LidarModel(np.deg2rad([-80.0, -60.0, -30.0, -5.0, 10.0, 45.0, 75.0]), 180)
    lidars = [LidarModel.waymo_top(), small_lidar(), LidarModel.preset("hdl64e"), steep]
    for seed in range(8):
        lidar = lidars[seed % 4]
        spread = [3.0, 20.0, 120.0, 200.0][seed // 2 % 4]
        center = [None, 179.0, -179.5, None][seed % 4]
        scene, spoof = random_case(seed, lidar, 3000, 600, center_deg=center, spread_deg=spread)
        if seed % 3:  # a spoof in a few beams: the elevation band filter drops scene points
            beam = lidar.bin_index(spoof)[0] // lidar.azimuth_bins
            spoof = spoof[(beam >= 2) & (beam <= 4)]
        scene[::13] = math.nan
        spoof[::17, 2] = 100.0  # far above the FOV
        spoof[1::19] *= 3.0  # some beyond max_range
        yield lidar, scene, spoof
        yield lidar, scene.double(), spoof.double()
        yield lidar, scene.bfloat16(), spoof.bfloat16()
        yield lidar, torch.cat([scene, torch.randn(scene.shape[0], 2)], 1), spoof


@pytest.mark.parametrize("p_dual", [0.0, 0.5])
def test_matches_previous_implementation_bitwise(p_dual):
    for lidar, scene, spoof in reference_cases():
        rows = torch.arange(0, scene.shape[0])  # the candidates path, every row
        for cand in (None, rows):
            got_c, exp_c = AttackCounters(), AttackCounters()
            got = raycast_merge(
                scene, spoof, lidar, p_dual, torch.Generator().manual_seed(3), got_c, cand
            )
            exp = reference_raycast_merge(
                scene, spoof, lidar, p_dual, torch.Generator().manual_seed(3), exp_c, cand
            )
            assert torch.equal(got[0], exp[0]) and torch.equal(got[1], exp[1])
            assert got_c.snapshot() == exp_c.snapshot()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_wedge_rows_match_previous_implementation(dtype):
    """Same rows as bool half-plane tests (the library compares in place into floats), for
    narrow and wide wedges, points exactly on wedge edges, NaN and infinite coordinates, and
    among given rows."""
    lidar = LidarModel.waymo_top()
    g = torch.Generator().manual_seed(0)
    for trial in range(40):
        pts = (torch.rand(4001, 3, generator=g, dtype=torch.float64) * 2 - 1) * 10.0 ** (
            trial % 5 - 1
        )
        a0 = float(torch.rand(1, generator=g)) * 2 * math.pi - math.pi
        widths = [1e-3, 0.05, 0.5, 1.5]
        wedges = [
            (a0 + 0.7 * k, a0 + 0.7 * k + widths[(trial + k) % 4]) for k in range(trial % 3 + 1)
        ]
        r = torch.linspace(0, 40, 300, dtype=torch.float64)
        edge = torch.stack(
            [lidar.origin_xyz[0] + r * math.cos(a0), lidar.origin_xyz[1] + r * math.sin(a0), r], 1
        )
        pts = torch.cat([pts, edge])
        pts[::97] = math.nan
        pts[5::97, 0] = math.inf
        pts[7::97, 1] = -math.inf
        pts = pts.to(dtype)
        rows = torch.arange(0, pts.shape[0], 3)
        assert torch.equal(wedge_rows(pts, wedges, lidar), reference_wedge_rows(pts, wedges, lidar))
        assert torch.equal(
            wedge_rows(pts, wedges, lidar, rows), reference_wedge_rows(pts, wedges, lidar, rows)
        )


def test_elevation_band_keeps_every_return_of_the_spoof_beams_and_drops_the_rest():
    """The band pre-filter (exact superset) on a Waymo-like sector: every candidate binned into
    the spoof's beams survives it, including points on the beam midpoints bounding the band,
    and most of the others are dropped before the exact binning."""
    lidar = LidarModel.waymo_top()
    g = np.random.default_rng(5)
    n = 20000
    incl = lidar.inclinations.numpy()
    beams = g.integers(0, lidar.num_beams - 1, n)
    on_mid = g.random(n) < 0.3  # exactly between two beams (a tie goes to the lower one)
    frac_el = np.where(on_mid, (incl[beams + 1] - incl[beams]) / 2, g.uniform(-2e-3, 2e-3, n))
    cols = g.integers(1200, 1300, n)
    scene = ray_points(lidar, beams, cols, g.uniform(0.5, 80, n), frac_el=frac_el)
    rows = torch.arange(n)
    for lo, hi in ((20, 30), (0, 5), (50, 63), (31, 31)):
        band = _elevation_band_rows(scene, rows, lidar, lo, hi)
        exact = lidar.bin_index(scene)[0] // lidar.azimuth_bins
        inside = torch.nonzero((exact >= lo) & (exact <= hi)).squeeze(1)
        assert torch.isin(inside, band).all()
        assert band.numel() < inside.numel() + 0.05 * n  # the rest dropped (but a margin)
