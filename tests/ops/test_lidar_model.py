import math

import numpy as np
import pytest
import torch
from device_params import DEVICES

from pcdet_atlas.config import ConfigError
from pcdet_atlas.ops.lidar_model import (
    LidarModel,
    spherical_offsets,
    waymo_top_inclinations_deg,
)


def test_default_table():
    deg = waymo_top_inclinations_deg()
    assert deg.shape == (64,)
    assert deg[0] == pytest.approx(-17.6) and deg[-1] == pytest.approx(2.4)
    spacing = np.diff(deg)
    assert (spacing > 0).all() and spacing[0] > 2 * spacing[-1]  # denser near the horizon
    lidar = LidarModel.waymo_top()
    assert lidar.azimuth_bins == 2651 and lidar.num_bins == 64 * 2651


def test_bin_index_relative_to_origin_and_edges():
    lidar = LidarModel.waymo_top()
    o = lidar.origin
    # a point at the sensor height straight ahead is on elevation 0 -> nearest beam to 0 deg
    beam0 = int(np.argmin(np.abs(waymo_top_inclinations_deg())))
    xyz = torch.tensor([[o[0] + 10.0, 0.0, o[2]]], dtype=torch.float64)
    bins, fov, rng = lidar.bin_index(xyz)
    assert int(bins[0]) // lidar.azimuth_bins == beam0
    assert bool(fov[0]) and float(rng[0]) == pytest.approx(10.0)
    # azimuth exactly -pi is mapped to +pi (last bin); +pi also last bin; just above -pi bin 0
    az = torch.tensor([-math.pi, math.pi, -math.pi + 1e-9, 0.0], dtype=torch.float64)
    idx = lidar.azimuth_index(torch.where(az == -math.pi, torch.full_like(az, math.pi), az))
    assert idx.tolist()[:3] == [2650, 2650, 0]
    # a point straight up is outside the field of view
    up = torch.tensor([[o[0], 0.0, o[2] + 5.0]], dtype=torch.float64)
    assert not bool(lidar.bin_index(up)[1][0])


def test_fit_recovers_table():
    truth = LidarModel.waymo_top()
    rng = np.random.default_rng(0)
    incl = truth.inclinations.numpy() + rng.normal(0, 0.0006, 64)  # a different unit of the sensor
    incl.sort()
    beams = rng.integers(0, 64, 50000)
    az = rng.uniform(-np.pi, np.pi, 50000)
    r = rng.uniform(5, 70, 50000)
    el = incl[beams] + rng.normal(0, 2e-4, 50000)
    o = truth.origin.numpy()
    pts = np.stack(
        [
            o[0] + r * np.cos(el) * np.cos(az),
            o[1] + r * np.cos(el) * np.sin(az),
            o[2] + r * np.sin(el),
        ],
        1,
    )
    fitted = LidarModel.fit(pts)
    np.testing.assert_allclose(fitted.inclinations.numpy(), incl, atol=2e-4)


def test_from_config_and_errors():
    lidar = LidarModel.from_config({"INCLINATIONS_DEG": [-10.0, -5.0, 0.0], "AZIMUTH_BINS": 100})
    assert lidar.num_beams == 3 and lidar.azimuth_bins == 100
    again = LidarModel.from_config(lidar.to_config())
    assert torch.equal(again.inclinations, lidar.inclinations)
    with pytest.raises(ConfigError, match="unknown key 'BEAMS'"):
        LidarModel.from_config({"BEAMS": 64})
    with pytest.raises(ValueError, match="ascending"):
        LidarModel([0.1, 0.0])
    with pytest.raises(ValueError, match="origin"):
        LidarModel([0.0, 0.1], origin=(1.43, float("nan"), 2.184))  # every bin would be NaN


@pytest.mark.parametrize("device", DEVICES)
def test_bin_index_device_and_dtype_agree(device):
    lidar = LidarModel.waymo_top()
    gen = torch.Generator().manual_seed(0)
    xyz = (torch.rand(20000, 3, generator=gen) - 0.5) * torch.tensor([150.0, 150.0, 20.0])
    ref = lidar.bin_index(xyz.double())
    for pts in (xyz, xyz.double()):
        bins, fov, rng = lidar.bin_index(pts.to(device))
        assert bins.dtype == torch.long and fov.dtype == torch.bool and rng.dtype == torch.float64
        assert torch.equal(bins.cpu(), ref[0]) and torch.equal(fov.cpu(), ref[1])
        assert torch.equal(rng.cpu(), ref[2])
    assert (ref[0] >= 0).all() and (ref[0] < lidar.num_bins).all()


def test_pickle_roundtrip_drops_device_cache():
    import pickle

    lidar = LidarModel.waymo_top(max_range=80.0)
    lidar.bin_index(torch.zeros(1, 3))  # fills the per-device cache
    again = pickle.loads(pickle.dumps(lidar))
    assert again._device_cache == {} and again.to_config() == lidar.to_config()
    xyz = torch.tensor([[10.0, 5.0, 1.0], [-20.0, -0.0, 2.0]])
    for a, b in zip(again.bin_index(xyz), lidar.bin_index(xyz)):
        assert torch.equal(a, b)


def test_spherical_on_cpu_is_the_shared_numpy_arithmetic():
    """CPU binning goes through ``spherical_offsets`` (numpy), the arithmetic the raycaster and
    the removal sector use: same values for float32 and float64 input, azimuth in
    (-pi, pi] (a point straight behind the sensor with y = -0.0 folds to +pi)."""
    lidar = LidarModel.waymo_top()
    g = np.random.default_rng(1)
    xyz = (g.normal(size=(4000, 3)) * 30).astype(np.float32)
    xyz[0] = [lidar.origin_np[0] - 10.0, -0.0, 1.0]
    for pts in (xyz, xyz.astype(np.float64)):
        got = lidar.spherical(torch.from_numpy(pts))
        rel = pts.astype(np.float64) - lidar.origin_np
        want = spherical_offsets(rel[:, 0], rel[:, 1], rel[:, 2])
        for a, b in zip(got, want):
            assert a.dtype == torch.float64 and np.array_equal(a.numpy(), b)
    # the raycaster bins spoof points from strided columns and scene candidates from contiguous
    # gathers: numpy must give the same values for both layouts
    strided = spherical_offsets(rel[:, 0], rel[:, 1], rel[:, 2])
    contiguous = spherical_offsets(*(np.ascontiguousarray(rel[:, d]) for d in range(3)))
    assert all(np.array_equal(a, b) for a, b in zip(strided, contiguous))
    azimuth = got[0].numpy()
    assert azimuth[0] == math.pi and (azimuth > -math.pi).all() and (azimuth <= math.pi).all()
    np.testing.assert_allclose(
        got[2].numpy(), np.linalg.norm(xyz - lidar.origin_np, axis=1), rtol=1e-6
    )
    with pytest.raises(ValueError, match="read-only"):
        lidar.origin_np[0] = 0.0


# ------------------------------------------------------------------ laser offsets and presets
def _offset_beam_reference(lidar, xyz):
    """Per point, the beam whose elevation at the point's horizontal distance is nearest (a
    plain loop) and whether it lies within half the outermost spacings of the fan there."""
    incl = lidar.inclinations.tolist()
    beams, fov = [], []
    for x, y, z in (np.asarray(xyz) - lidar.origin_np).tolist():
        d = math.hypot(x, y)
        phi = math.atan2(z, d)
        pred = [math.atan(math.tan(t) + c / d) for t, c in zip(incl, lidar.offsets.tolist())]
        err = [abs(phi - p) for p in pred]
        beams.append(err.index(min(err)))
        fov.append(pred[0] - (incl[1] - incl[0]) / 2 <= phi <= pred[-1] + (incl[-1] - incl[-2]) / 2)
    return np.array(beams), np.array(fov)


def test_offset_binning_matches_a_per_point_loop():
    gen = torch.Generator().manual_seed(0)
    incl = np.deg2rad([-20.0, -12.0, -6.0, -3.0, -1.0, 0.0, 1.5])
    lidar = LidarModel(incl, azimuth_bins=360, origin=(1.0, 0.5, 2.0),
                       offsets=[0.1, 0.12, 0.15, 0.2, 0.2, 0.25, 0.3])  # fmt: skip
    xyz = torch.rand((3000, 3), generator=gen, dtype=torch.float64) * torch.tensor(
        [60.0, 60.0, 6.0], dtype=torch.float64
    ) - torch.tensor([30.0, 30.0, 1.0], dtype=torch.float64)
    bins, fov, _ = lidar.bin_index(xyz)
    beams, ref_fov = _offset_beam_reference(lidar, xyz.numpy())
    np.testing.assert_array_equal((bins // lidar.azimuth_bins).numpy(), beams)
    np.testing.assert_array_equal(fov.numpy(), ref_fov)
    az, el, rng = lidar.spherical(xyz)
    np.testing.assert_array_equal(lidar.beam_index(el, rng * torch.cos(el)).numpy(), beams)
    with pytest.raises(ValueError, match="horizontal distance"):
        lidar.beam_index(el)
    # near points see the offset lasers far above their angle: the single-origin table differs
    single = LidarModel(incl, azimuth_bins=360, origin=(1.0, 0.5, 2.0))
    assert (single.bin_index(xyz)[0] != bins).float().mean() > 0.1


def test_zero_offsets_are_the_single_origin_model():
    incl = np.deg2rad(waymo_top_inclinations_deg())
    zero = LidarModel(incl, offsets=np.zeros(64))
    assert zero.offsets is None and "OFFSETS" not in zero.to_config()
    with pytest.raises(ValueError, match="one per beam"):
        LidarModel(incl, offsets=np.zeros(3))


def test_presets_and_offsets_from_config():
    lidar = LidarModel.from_config({"PRESET": "hdl64e", "ORIGIN": [0.0, 0.0, 1.9]})
    assert lidar.num_beams == 64 and lidar.azimuth_bins == 2005 and lidar.offsets is not None
    assert LidarModel.from_config({"PRESET": "hdl32e", "AZIMUTH_BINS": 1085}).azimuth_bins == 1085
    with pytest.raises(ConfigError, match="hdl32e, hdl64e, waymo_top"):
        LidarModel.from_config({"PRESET": "vlp16"})
    with pytest.raises(ConfigError, match="preset carries its own offsets"):
        LidarModel.from_config({"PRESET": "hdl32e", "OFFSETS": [0.0] * 32})
    with pytest.raises(ConfigError, match="not"):
        LidarModel.from_config({"PRESET": "hdl32e", "INCLINATIONS_DEG": [0.0, 1.0]})
    with pytest.raises(ConfigError, match="2 laser heights"):
        LidarModel.from_config({"INCLINATIONS_DEG": [0.0, 1.0], "OFFSETS": [0.1]})
    rebuilt = LidarModel.from_config(lidar.to_config())
    assert torch.equal(rebuilt.offsets, lidar.offsets)
    assert torch.equal(rebuilt.inclinations, lidar.inclinations)
