"""The training step's row-wise scatter and gathers compute what the straightforward code does.

References: torch's own autograd of ``scatter_reduce_('amax')`` for the per-pillar max, plain
``x[idx]`` indexing, and the voxelization by per-point loops in ``test_voxelize``.
"""

import pytest
import torch
from device_params import DEVICES
from model_batches import make_batch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.models import build_network
from pcdet_atlas.models.model_utils.scatter import scatter_max
from pcdet_atlas.models.vfe import dynamic_pillar_vfe


def torch_autograd_scatter_max(src, index, dim_size):
    """The reference: torch's own ``scatter_reduce_`` autograd (``ScatterReduceBackward0``)."""
    out = src.new_zeros(dim_size, src.shape[1])
    return out.scatter_reduce_(
        0, index[:, None].expand_as(src), src, reduce="amax", include_self=False
    )


@pytest.mark.parametrize("device", DEVICES)
def test_scatter_max_backward_equals_torch_where_the_max_is_not_zero(device):
    g = torch.Generator().manual_seed(3)
    src = torch.randn(400, 5, generator=g).to(device)
    idx = torch.randint(1, 30, (400,), generator=g).to(device)
    src[100:150], idx[100:150] = src[150:200], idx[150:200]  # duplicated points: ties
    src[5, 2] = src[9, 2] = 10.0  # a tie at a group max (rows 5 and 9 alone in group 0)
    idx[5] = idx[9] = 0
    grad_out = torch.randn(31, 5, generator=g).to(device)

    a = src.clone().requires_grad_(True)
    out_a = scatter_max(a, idx, 31)
    out_a.backward(grad_out)
    b = src.clone().requires_grad_(True)
    out_b = torch_autograd_scatter_max(b, idx, 31)
    out_b.backward(grad_out)
    assert torch.equal(out_a, out_b)
    assert (out_b != 0).sum() > 100 and (out_b[1:30] != 0).all()  # the case compared
    torch.testing.assert_close(a.grad, b.grad, rtol=0, atol=0)
    # the tie at 10.0 splits the group's gradient in two
    assert a.grad[5, 2] == a.grad[9, 2] == grad_out[0, 2] / 2


def test_scatter_max_backward_where_torch_counts_the_excluded_zero():
    """torch divides by one tie too many when the group max is exactly 0 (the excluded initial
    value counts as a tie); the reduction's true derivative is 1 for a unique maximiser."""
    src = torch.tensor([[0.0], [-1.0], [3.0]], requires_grad=True)
    idx = torch.tensor([0, 0, 1])
    scatter_max(src, idx, 2).sum().backward()
    assert src.grad.tolist() == [[1.0], [0.0], [1.0]]
    ref = src.detach().clone().requires_grad_(True)
    torch_autograd_scatter_max(ref, idx, 2).sum().backward()
    assert ref.grad.tolist() == [[0.5], [0.0], [1.0]]  # the documented difference


def test_scatter_max_without_grad_and_gradcheck():
    src = torch.randn(30, 3, dtype=torch.float64)
    idx = torch.randint(0, 6, (30,))
    with torch.no_grad():
        assert torch.equal(scatter_max(src, idx, 6), torch_autograd_scatter_max(src, idx, 6))
    x = src.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: scatter_max(t, idx, 6), (x,))


@pytest.mark.parametrize("cfg_name", ["centerpoint", "cp4f"])
def test_model_loss_and_gradients_equal_the_reference_computation(cfg_name, monkeypatch):
    """One training step (loss, backward) of the synthetic model on a fixed batch: the loss and
    every parameter gradient equal those of the reference VFE (torch autograd for the per-pillar
    max, ``x[idx]`` gathers)."""
    cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "atlas" / "synthetic" / f"{cfg_name}.yaml")
    multi = cfg_name == "cp4f"

    def run():
        torch.manual_seed(0)
        model = build_network(
            cfg.MODEL,
            class_names=cfg.CLASS_NAMES,
            point_cloud_range=[-20.48, -20.48, -2.0, 20.48, 20.48, 4.0],
            num_point_features=6 if multi else 5,
        ).train()
        batch = make_batch(num_point_features=6 if multi else 5, with_velocity=multi)
        # duplicated points: ties at positive per-pillar maxima
        batch["points"] = torch.cat([batch["points"], batch["points"][:300]])
        losses = model.loss(batch)
        losses["loss"].backward()
        return (
            {k: float(v.detach()) for k, v in losses.items()},
            {n: p.grad.clone() for n, p in model.named_parameters()},
        )

    new_losses, new_grads = run()
    with monkeypatch.context() as m:
        m.setattr(dynamic_pillar_vfe, "scatter_max", torch_autograd_scatter_max)
        old_losses, old_grads = run()
    for k in old_losses:
        assert new_losses[k] == pytest.approx(old_losses[k], rel=1e-6), k
    assert new_grads.keys() == old_grads.keys()
    for name in old_grads:
        scale = old_grads[name].abs().max().clamp(min=1e-6)
        err = (new_grads[name] - old_grads[name]).abs().max() / scale
        assert err < 1e-5, f"{name}: relative gradient difference {err:.2e}"
