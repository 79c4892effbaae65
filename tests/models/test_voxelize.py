from collections import defaultdict

import numpy as np
import pytest
import torch
from device_params import DEVICES

from pcdet_atlas.models.model_utils import voxelize as voxelize_module
from pcdet_atlas.models.model_utils.hard_voxelize import hard_voxelize
from pcdet_atlas.models.model_utils.scatter import scatter_max, scatter_mean, scatter_sum
from pcdet_atlas.models.model_utils.voxelize import VoxelGrid, voxelize

GRID = VoxelGrid((-4.0, -2.0, -1.0, 4.0, 2.0, 1.0), (0.5, 0.25, 2.0))


def reference_voxelize(points, grid):
    """Dict of lists: (b, z, y, x) -> list of point indices, by a per-point Python loop."""
    pcr, vs = grid.point_cloud_range, grid.voxel_size
    nx, ny, nz = grid.grid_size
    groups = defaultdict(list)
    for i, p in enumerate(points.tolist()):
        cell = [int((p[1 + k] - pcr[k]) // vs[k]) for k in range(3)]
        if all(0 <= cell[k] < (nx, ny, nz)[k] for k in range(3)):
            groups[(int(p[0]), cell[2], cell[1], cell[0])].append(i)
    return groups


def random_points(n, seed):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 5, generator=g, dtype=torch.float64)
    pts[:, 0] = torch.randint(0, 3, (n,), generator=g).double()
    pts[:, 1:4] = pts[:, 1:4] * torch.tensor([10.0, 6.0, 3.0], dtype=torch.float64) - torch.tensor(
        [5.0, 3.0, 1.5], dtype=torch.float64
    )
    # points exactly on cell edges and on both range boundaries
    pts[:4, 1:4] = torch.tensor(
        [[-4.0, -2.0, -1.0], [4.0, 0.0, 0.0], [0.5, 0.25, 0.0], [3.999, 1.999, 0.999]],
        dtype=torch.float64,
    )
    return pts


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dense", [True, False], ids=["dense_table", "unique"])
def test_voxelize_matches_dict_of_lists(device, dense, monkeypatch):
    if not dense:
        monkeypatch.setattr(voxelize_module, "DENSE_KEY_LIMIT", 0)
    pts = random_points(600, 0)
    ref = reference_voxelize(pts, GRID)
    vox = voxelize(pts.to(device), GRID)
    coords = [tuple(c) for c in vox.voxel_coords.cpu().tolist()]
    assert coords == sorted(ref)  # sorted by (b, z, y, x)
    assert vox.voxel_num_points.cpu().tolist() == [len(ref[c]) for c in coords]
    kept = torch.nonzero(vox.point_mask.cpu()).squeeze(1).tolist()
    assert sorted(kept) == sorted(i for idx in ref.values() for i in idx)
    for i, v in zip(kept, vox.point_voxel_idx.cpu().tolist()):
        assert i in ref[coords[v]]
    # half-open cells: the upper range boundary point is outside, the lower inside
    assert vox.point_mask[0] and not vox.point_mask[1]


def test_voxelize_empty_and_float32():
    empty = voxelize(torch.zeros(0, 5), GRID)
    assert empty.voxel_coords.shape == (0, 4) and empty.point_voxel_idx.shape == (0,)
    pts = random_points(300, 1)
    a = voxelize(pts.float(), GRID)
    ref = reference_voxelize(pts.float().double(), GRID)
    assert [tuple(c) for c in a.voxel_coords.tolist()] == sorted(ref)


def test_bad_grid_and_points_raise():
    with pytest.raises(ValueError, match="whole number of voxels"):
        VoxelGrid((0.0, 0.0, 0.0, 1.0, 1.0, 1.0), (0.3, 0.5, 1.0))
    with pytest.raises(ValueError, match="positive"):
        VoxelGrid((0.0, 0.0, 0.0, 1.0, 1.0, 1.0), (0.5, 0.0, 1.0))
    with pytest.raises(ValueError, match=r"\(N, 1 \+ C>=3\)"):
        voxelize(torch.zeros(4, 3), GRID)


@pytest.mark.parametrize("device", DEVICES)
def test_scatter_reductions_against_loops(device):
    g = torch.Generator().manual_seed(0)
    src = torch.randn(50, 4, generator=g, dtype=torch.float64)
    idx = torch.randint(0, 7, (50,), generator=g)
    idx[idx == 3] = 4  # group 3 stays empty
    s = scatter_sum(src.to(device), idx.to(device), 7).cpu()
    m = scatter_mean(src.to(device), idx.to(device), 7).cpu()
    mx = scatter_max(src.to(device), idx.to(device), 7).cpu()
    for k in range(7):
        rows = src[idx == k]
        if rows.shape[0] == 0:
            assert (s[k] == 0).all() and (m[k] == 0).all() and (mx[k] == 0).all()
            continue
        torch.testing.assert_close(s[k], rows.sum(0))
        torch.testing.assert_close(m[k], rows.mean(0))
        torch.testing.assert_close(mx[k], rows.max(0).values)


def test_scatter_max_gradcheck():
    g = torch.Generator().manual_seed(1)
    src = torch.randn(12, 3, generator=g, dtype=torch.float64, requires_grad=True)
    idx = torch.tensor([0, 0, 1, 2, 2, 2, 4, 4, 1, 0, 2, 4])
    assert torch.autograd.gradcheck(lambda x: scatter_max(x, idx, 5), (src,))
    assert torch.autograd.gradcheck(lambda x: scatter_mean(x, idx, 5), (src,))


def test_unbounded_z_needs_a_pillar_grid():
    points = torch.tensor([[0.0, 0.5, 0.5, 9.0]])
    pillars = VoxelGrid((0.0, 0.0, -1.0, 2.0, 2.0, 1.0), (1.0, 1.0, 2.0))
    assert voxelize(points, pillars).voxel_coords.shape[0] == 0
    assert voxelize(points, pillars, bound_z=False).voxel_coords.tolist() == [[0, 0, 0, 0]]
    voxels = VoxelGrid((0.0, 0.0, -1.0, 2.0, 2.0, 1.0), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="pillar grid"):
        voxelize(points, voxels, bound_z=False)


@pytest.mark.parametrize(
    "pcr,vs",
    [
        ((-75.2, -75.2, -2.0, 75.2, 75.2, 4.0), (0.1, 0.1, 0.15)),  # OpenPCDet's voxel CenterPoint
        ((-74.88, -74.88, -2.0, 74.88, 74.88, 4.0), (0.32, 0.32, 6.0)),  # its dynamic pillars
    ],
    ids=["voxel", "pillar"],
)
def test_cells_at_edges_follow_spconvs_float32_arithmetic(pcr, vs):
    """Points exactly on cell edges and 1-2 float32 ulps around them land where spconv's voxel
    generator puts them: ``floor((p - range_min) / voxel_size)``, every operand and result
    rounded to float32 (numpy float32 arithmetic as the reference)."""
    grid = VoxelGrid(pcr, vs)
    nx, ny, nz = grid.grid_size
    edges = [
        pcr[k] + np.arange(n + 1, dtype=np.float64) * vs[k] for k, n in enumerate((nx, ny, nz))
    ]
    g = np.random.default_rng(0)
    cols = []
    for k in range(3):
        on_edge = edges[k][g.integers(0, len(edges[k]), 400)].astype(np.float32)
        ulps = g.integers(-2, 3, 400)
        cols.append(np.array([np.float32(v) for v in _step_ulps(on_edge, ulps)], np.float32))
    xyz = np.stack(cols, 1)  # (400, 3) float32
    lo, size = np.asarray(pcr[:3], np.float32), np.asarray(vs, np.float32)
    expected = np.floor((xyz - lo) / size).astype(np.int64)  # float32 all the way
    inside = ((expected >= 0) & (expected < np.array([nx, ny, nz]))).all(1)
    points = torch.cat([torch.zeros(400, 1), torch.from_numpy(xyz), torch.zeros(400, 2)], 1)
    vox = voxelize(points, grid)
    assert vox.point_mask.numpy().tolist() == inside.tolist()
    got = vox.voxel_coords[vox.point_voxel_idx][:, [3, 2, 1]].numpy()
    assert (got == expected[inside]).all()
    hard = hard_voxelize(points, grid, 400, 400)
    rows = {tuple(c) for c in hard.voxel_coords[:, [3, 2, 1]].tolist()}
    assert rows == {tuple(c) for c in expected[inside].tolist()}
    # the test can fail: float64 arithmetic puts some of these points in other cells
    wide = np.floor((xyz.astype(np.float64) - np.asarray(pcr[:3])) / np.asarray(vs)).astype(int)
    assert (wide != expected).any(1).sum() > 0


def _step_ulps(values: np.ndarray, steps: np.ndarray) -> list:
    """Each float32 value moved ``steps`` ulps (towards +inf for a positive step)."""
    out = []
    for v, s in zip(values, steps):
        for _ in range(abs(int(s))):
            v = np.nextafter(v, np.float32(np.inf if s > 0 else -np.inf), dtype=np.float32)
        out.append(v)
    return out
