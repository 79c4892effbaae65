"""DynamicPillarVFE: the eval-mode PFN form (BatchNorm folded, no per-point concat, ReLU after
the max) computes the same function as running the layers one by one."""

from __future__ import annotations

import pytest
import torch

from pcdet_atlas.models.vfe.dynamic_pillar_vfe import DynamicPillarVFE

RANGE = (-8.0, -8.0, -2.0, 8.0, 8.0, 4.0)


def _points(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=gen) * 2 - 1) * torch.tensor([9.0, 9.0, 3.0])  # some out
    feats = torch.rand(n, 2, generator=gen)
    batch = torch.randint(0, 2, (n, 1), generator=gen).float()
    return torch.cat([batch, xyz, feats], dim=1)


def _layerwise(vfe: DynamicPillarVFE, batch: dict) -> torch.Tensor:
    """The reference: the eval form switched off, every layer run as in training."""
    vfe.fold_eval = False
    try:
        return vfe(dict(batch))["pillar_features"]
    finally:
        vfe.fold_eval = True


@pytest.mark.parametrize(
    "filters,use_norm,with_distance",
    [
        ((32,), True, False),
        ((16, 32), True, False),
        ((8, 16, 32), True, True),
        ((16, 32), False, False),
    ],
)
def test_eval_form_equals_layerwise(filters, use_norm, with_distance, monkeypatch):
    torch.manual_seed(0)
    vfe = DynamicPillarVFE(
        num_point_features=5, point_cloud_range=RANGE, voxel_size=(0.5, 0.5, 6.0),
        num_filters=filters, use_norm=use_norm, with_distance=with_distance,
    )  # fmt: skip
    for layer in vfe.pfn_layers:  # non-trivial statistics, a negative scale among them
        if use_norm:
            layer.norm.running_mean.uniform_(-0.5, 0.5)
            layer.norm.running_var.uniform_(0.2, 2.0)
            with torch.no_grad():
                layer.norm.weight.uniform_(-1.5, 1.5)
                layer.norm.bias.uniform_(-0.3, 0.3)
            assert (layer.norm.weight < 0).any()
    vfe.eval()
    calls = []  # which form ran: the comparison must be of the two different code paths
    pfn_eval = DynamicPillarVFE._pfn_eval
    monkeypatch.setattr(
        DynamicPillarVFE, "_pfn_eval", lambda self, *a: calls.append(1) or pfn_eval(self, *a)
    )
    batch = {"points": _points(3000, 1), "batch_size": 2}
    with torch.no_grad():
        fast = vfe(dict(batch))["pillar_features"]
        assert len(calls) == 1  # eval mode took the folded form
        ref = _layerwise(vfe, batch)
        assert len(calls) == 1  # fold_eval = False did not
    assert fast.shape == ref.shape and ref.shape[1] == filters[-1]
    assert ref.abs().max() > 0.1  # the comparison is not of zeros
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)


def test_training_mode_runs_layerwise():
    """Training uses batch statistics: the eval form must not be taken (its BN fold would use
    the running ones), and the output differs from eval mode's."""
    torch.manual_seed(0)
    vfe = DynamicPillarVFE(
        num_point_features=5, point_cloud_range=RANGE, voxel_size=(0.5, 0.5, 6.0),
        num_filters=(16, 32),
    )  # fmt: skip
    batch = {"points": _points(2000, 2), "batch_size": 2}
    vfe.train()
    train_out = vfe(dict(batch))["pillar_features"]
    assert train_out.requires_grad
    train_out.sum().backward()
    assert all(p.grad is not None for p in vfe.parameters())
    vfe.eval()
    with torch.no_grad():
        assert not torch.allclose(vfe(dict(batch))["pillar_features"], train_out.detach())


def test_points_outside_the_z_range_enter_their_pillar_unless_dropped():
    """As OpenPCDet's dynamic VFE (x and y bounds only), a point below or above the z range
    falls in the pillar under it; DROP_OUTSIDE_Z drops it. Its f_center z is taken from the
    pillar's fixed centre height either way."""
    torch.manual_seed(0)
    pts = torch.tensor(
        [
            [0.0, 0.1, 0.1, 1.0, 0.5, 0.5],  # inside
            [0.0, 0.2, 0.2, 5.0, 0.5, 0.5],  # above z (4.0), same pillar
            [0.0, 3.1, 3.1, -3.0, 0.5, 0.5],  # below z (-2.0), a pillar of its own
            [0.0, 9.5, 0.1, 1.0, 0.5, 0.5],  # outside x: never
        ]
    )
    kept = DynamicPillarVFE(
        num_point_features=5, point_cloud_range=RANGE, voxel_size=(0.5, 0.5, 6.0),
        num_filters=(8,),
    ).eval()  # fmt: skip
    dropped = DynamicPillarVFE.from_config(
        {"NAME": "DynamicPillarVFE", "VOXEL_SIZE": [0.5, 0.5, 6.0], "NUM_FILTERS": [8],
         "DROP_OUTSIDE_Z": True},
        {"num_point_features": 5, "point_cloud_range": RANGE, "voxel_size": None},
    ).eval()  # fmt: skip
    dropped.load_state_dict(kept.state_dict())
    with torch.no_grad():
        out_kept = kept({"points": pts, "batch_size": 1})
        out_dropped = dropped({"points": pts, "batch_size": 1})
        solo = kept({"points": pts[:1], "batch_size": 1})  # the inside point's pillar alone
    assert out_kept["voxel_coords"].tolist() == [[0, 0, 16, 16], [0, 0, 22, 22]]
    assert out_dropped["voxel_coords"].tolist() == [[0, 0, 16, 16]]
    torch.testing.assert_close(out_dropped["pillar_features"], solo["pillar_features"])
    assert not torch.allclose(out_kept["pillar_features"][:1], solo["pillar_features"])
