"""Hard voxelization's caps against a brute-force per-point reference (spconv's rule)."""

import math

import pytest
import torch

from pcdet_atlas.models.model_utils.hard_voxelize import hard_voxelize
from pcdet_atlas.models.model_utils.voxelize import VoxelGrid
from tests.device_params import DEVICES

GRID = VoxelGrid((0.0, -2.0, -1.0, 4.0, 2.0, 1.0), (0.5, 0.5, 0.5))


def reference(points, grid, max_points, max_voxels):
    """Per frame, points in input order: a dict of lists, as spconv's Point2VoxelCPU."""
    pcr, vs = grid.point_cloud_range, grid.voxel_size
    nx, ny, nz = grid.grid_size
    out = []  # (batch, (z, y, x), [rows])
    for b in sorted({int(v) for v in points[:, 0]}):
        voxels: dict = {}
        for row in points[points[:, 0] == b].tolist():
            cell = [math.floor((row[1 + i] - pcr[i]) / vs[i]) for i in range(3)]
            if not all(0 <= c < n for c, n in zip(cell, (nx, ny, nz))):
                continue
            key = (cell[2], cell[1], cell[0])
            if key not in voxels:
                if len(voxels) >= max_voxels:
                    continue
                voxels[key] = []
            if len(voxels[key]) < max_points:
                voxels[key].append(row[1:])
        out += [(b, key, rows) for key, rows in voxels.items()]
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("max_points,max_voxels", [(3, 1000), (2, 7), (1, 3), (100, 1)])
def test_caps_match_reference(device, max_points, max_voxels):
    g = torch.Generator().manual_seed(0)
    n = 300
    xyz = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([5.0, 5.0, 2.6])
    xyz -= torch.tensor([0.5, 2.5, 1.3])  # some points fall outside the range
    # few cells so voxels fill up; frames interleaved in the input
    xyz = (xyz / 0.5).floor() * 0.5 + 0.25 * (
        torch.rand(n, 1, generator=g, dtype=torch.float64) > 0.5
    )
    batch = torch.randint(0, 3, (n, 1), generator=g).double()
    points = torch.cat([batch, xyz, torch.arange(n, dtype=torch.float64)[:, None]], 1)
    result = hard_voxelize(points.to(device), GRID, max_points, max_voxels)
    expected = reference(points, GRID, max_points, max_voxels)
    assert len(expected) > 0
    assert result.voxel_coords.tolist() == [[b, *key] for b, key, _ in expected]
    assert result.voxel_num_points.tolist() == [len(rows) for _, _, rows in expected]
    for i, (_, _, rows) in enumerate(expected):
        assert result.voxels[i, : len(rows)].tolist() == rows
        assert (result.voxels[i, len(rows) :] == 0).all()


def test_empty_and_bad_caps():
    empty = hard_voxelize(torch.zeros(0, 5), GRID, 5, 10)
    assert empty.voxels.shape == (0, 5, 4) and empty.voxel_coords.shape == (0, 4)
    with pytest.raises(ValueError, match="MAX_NUMBER_OF_VOXELS"):
        hard_voxelize(torch.zeros(1, 5), GRID, 5, 0)
