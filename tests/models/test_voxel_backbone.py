"""MeanVFE -> VoxelBackBone8x / VoxelResBackBone8x -> HeightCompression with OpenPCDet's names."""

import pytest
import torch

from pcdet_atlas.models.backbones_3d import VoxelBackBone8x, VoxelResBackBone8x
from pcdet_atlas.models.map_to_bev import HeightCompression
from pcdet_atlas.models.vfe import MeanVFE
from pcdet_atlas.registry import MODEL_STAGES

PCR = (0.0, -1.6, -2.0, 3.2, 1.6, 2.0)
VOXEL = (0.2, 0.2, 0.1)  # grid 16 x 16 x 40: sparse shape [41, 16, 16] as OpenPCDet's Waymo z


def tiny_points(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(n, 3, generator=g) * torch.tensor([3.2, 3.2, 4.0]) + torch.tensor(PCR[:3])
    batch = torch.randint(0, 2, (n, 1), generator=g).float()
    return torch.cat([batch, xyz, torch.rand(n, 2, generator=g)], 1)  # (N, 1 + 5)


def bn_keys(prefix, c):
    return {
        f"{prefix}.weight": (c,), f"{prefix}.bias": (c,), f"{prefix}.running_mean": (c,),
        f"{prefix}.running_var": (c,), f"{prefix}.num_batches_tracked": (),
    }  # fmt: skip


def res_keys(prefix, c):
    keys = {}
    for i in (1, 2):
        keys[f"{prefix}.conv{i}.weight"] = (c, 3, 3, 3, c)
        keys[f"{prefix}.conv{i}.bias"] = (c,)
        keys.update(bn_keys(f"{prefix}.bn{i}", c))
    return keys


def openpcdet_res_keys(c_in):
    """VoxelResBackBone8x's state_dict in OpenPCDet (spconv 2.x layout), written out."""
    keys = {"conv_input.0.weight": (16, 3, 3, 3, c_in), **bn_keys("conv_input.1", 16)}
    keys.update(res_keys("conv1.0", 16) | res_keys("conv1.1", 16))
    for stage, (cin, cout) in zip((2, 3, 4), ((16, 32), (32, 64), (64, 128))):
        keys[f"conv{stage}.0.0.weight"] = (cout, 3, 3, 3, cin)
        keys.update(bn_keys(f"conv{stage}.0.1", cout))
        keys.update(res_keys(f"conv{stage}.1", cout) | res_keys(f"conv{stage}.2", cout))
    keys["conv_out.0.weight"] = (128, 3, 1, 1, 128)
    keys.update(bn_keys("conv_out.1", 128))
    return keys


def openpcdet_plain_keys(c_in):
    """VoxelBackBone8x's state_dict in OpenPCDet, written out."""
    keys = {"conv_input.0.weight": (16, 3, 3, 3, c_in), **bn_keys("conv_input.1", 16)}
    keys["conv1.0.0.weight"] = (16, 3, 3, 3, 16)
    keys.update(bn_keys("conv1.0.1", 16))
    for stage, (cin, cout) in zip((2, 3, 4), ((16, 32), (32, 64), (64, 64))):
        for j in range(3):
            keys[f"conv{stage}.{j}.0.weight"] = (cout, 3, 3, 3, cin if j == 0 else cout)
            keys.update(bn_keys(f"conv{stage}.{j}.1", cout))
    keys["conv_out.0.weight"] = (128, 3, 1, 1, 64)
    keys.update(bn_keys("conv_out.1", 128))
    return keys


@pytest.mark.parametrize(
    "cls,expected",
    [(VoxelResBackBone8x, openpcdet_res_keys), (VoxelBackBone8x, openpcdet_plain_keys)],
)
def test_state_dict_names_and_shapes_are_openpcdets(cls, expected):
    net = cls(input_channels=5, grid_size=(16, 16, 40))
    got = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    assert got == expected(5)
    # an OpenPCDet state_dict of these shapes loads strictly
    foreign = {k: torch.randn(s) if s else torch.tensor(7) for k, s in expected(5).items()}
    net.load_state_dict(foreign, strict=True)


@pytest.mark.parametrize("cls", [VoxelResBackBone8x, VoxelBackBone8x])
def test_stages_run_from_config_with_stride8_bev_and_gradients(cls):
    info = {"num_point_features": 5, "point_cloud_range": PCR}
    vfe = MODEL_STAGES.get("MeanVFE").from_config(
        {"NAME": "MeanVFE", "VOXEL_SIZE": VOXEL, "MAX_POINTS_PER_VOXEL": 5,
         "MAX_NUMBER_OF_VOXELS": {"train": 150, "test": 300}},
        info,
    )  # fmt: skip
    info.update(num_point_features=5, grid_size=vfe.grid.grid_size)
    backbone = MODEL_STAGES.get(cls.__name__).from_config({"NAME": cls.__name__}, info)
    bev = HeightCompression.from_config({"NAME": "HeightCompression", "NUM_BEV_FEATURES": 256}, {})
    batch = {"points": tiny_points(), "batch_size": 2}
    for stage in (vfe, backbone, bev):
        batch = stage(batch)
    assert backbone.sparse_shape == [41, 16, 16]
    enc = batch["encoded_spconv_tensor"]
    # z: 41 -> 21 -> 11 -> 5 (conv4 pads z by 0) -> 2 (conv_out (3,1,1) / (2,1,1)); x, y: / 8
    assert enc.spatial_shape == [2, 2, 2]
    assert batch["spatial_features"].shape == (2, 256, 2, 2)
    assert batch["spatial_features_stride"] == 8
    assert torch.isfinite(batch["spatial_features"]).all()
    assert batch["voxel_features"].shape[0] <= 2 * 150  # train cap per frame
    batch["spatial_features"].square().sum().backward()
    missing = [n for n, p in backbone.named_parameters() if p.grad is None or not p.grad.any()]
    assert missing == []


def test_mean_vfe_means_and_split_caps():
    vfe = MeanVFE(
        num_point_features=5, point_cloud_range=PCR, voxel_size=VOXEL, max_points_per_voxel=2,
        max_number_of_voxels={"train": 10, "test": 1000},
    )  # fmt: skip
    pts = tiny_points(600)
    vfe.train()
    train = vfe({"points": pts})
    assert torch.bincount(train["voxel_coords"][:, 0]).tolist() == [10, 10]
    vfe.eval()
    test = vfe({"points": pts})
    n = test["voxel_coords"].shape[0]
    assert n > 20
    # every voxel's mean is the mean of its first (at most 2) points in input order
    cells = ((pts[:, 1:4] - torch.tensor(PCR[:3])) / torch.tensor(VOXEL)).floor().long()
    for i in range(0, n, 7):
        b, z, y, x = test["voxel_coords"][i].tolist()
        rows = pts[(pts[:, 0] == b) & (cells == torch.tensor([x, y, z])).all(1), 1:][:2]
        torch.testing.assert_close(test["voxel_features"][i], rows.mean(0))
    with pytest.raises(ValueError, match="MAX_NUMBER_OF_VOXELS must map exactly"):
        MeanVFE(
            num_point_features=5, point_cloud_range=PCR, voxel_size=VOXEL,
            max_points_per_voxel=2, max_number_of_voxels={"train": 10},
        )  # fmt: skip


def test_height_compression_checks_bev_width():
    from pcdet_atlas.ops.spconv import SparseConvTensor

    enc = SparseConvTensor(torch.ones(1, 4), torch.zeros(1, 4, dtype=torch.int32), (2, 3, 3), 1)
    batch = {"encoded_spconv_tensor": enc, "encoded_spconv_tensor_stride": 8}
    out = HeightCompression(num_bev_features=8)(dict(batch))
    assert out["spatial_features"].shape == (1, 8, 3, 3)
    with pytest.raises(ValueError, match="NUM_BEV_FEATURES is 256"):
        HeightCompression(num_bev_features=256)(dict(batch))
