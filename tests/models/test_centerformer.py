"""CenterFormer: the windowed multi-scale cross-attention against dense masked attention, the
top-K query selection against a sorting loop (ground-truth centres among the queries in training
only), the box code round trip behind the IoU target, the corner target, IoU rectification and
class-specific NMS, gradients to every parameter, and the configs building, training and
predicting."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from model_batches import make_batch

from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.models import build_network, build_network_from_config
from pcdet_atlas.models.detectors import CenterFormer
from pcdet_atlas.models.model_utils import centernet_utils as cu
from pcdet_atlas.models.model_utils.center_transformer import (
    CenterTransformerLayer,
    gather_neighbours,
    select_center_queries,
)

CFGS = REPO_ROOT / "cfgs" / "atlas"
SYN = CFGS / "synthetic" / "centerformer.yaml"
CELLS = 64  # smoke runs crop the voxel grid to CELLS x CELLS: the same parameters, less map


def cropped(path: Path = SYN, seed: int = 0) -> CenterFormer:
    cfg = cfg_from_yaml_file(path)
    half = CELLS * cfg.MODEL.VFE.VOXEL_SIZE[0] / 2
    torch.manual_seed(seed)
    return build_network(
        cfg.MODEL,
        class_names=cfg.CLASS_NAMES,
        point_cloud_range=[-half, -half, -2.0, half, half, 4.0],
        num_point_features=5,
    )


def batch_for(model: CenterFormer) -> dict:
    half = model.vfe.grid.point_cloud_range[3]
    return make_batch(num_point_features=5, extent=half, scale=half / 20)


# ------------------------------------------------------------------- cross-attention
def dense_cross_attention(layer, x, x_cells, levels, kernel_sizes, pos_embedding):
    """The cross-attention sub-layer as dense attention of each query over every cell of every
    level, masked to its windows: a cell's weight is multiplied by the number of window offsets
    that land on it after clamping to the level (log-count added to the logits)."""
    B, K, C = x.shape
    heads, dh = layer.cross_attn.heads, layer.cross_attn.dim_head
    norm = layer.cross_norm
    H0 = levels[0].shape[-2]
    q = layer.cross_attn.to_q(norm(x + pos_embedding(x_cells.to(x.dtype))))  # (B, K, h*d)
    keys, pos, counts = [], [], []
    for level, k in zip(levels, kernel_sizes):
        h, w = level.shape[-2:]
        scale = H0 // h
        ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        cell = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1)  # (HW, 2)
        keys.append(level.reshape(B, C, h * w).transpose(1, 2))  # (B, HW, C)
        pos.append(cell * scale)
        count = torch.zeros(B, K, h * w, dtype=x.dtype)
        for b in range(B):
            for i in range(K):
                qx, qy = (int(v) // scale for v in x_cells[b, i])
                for dy in range(-(k // 2), k // 2 + 1):
                    for dx in range(-(k // 2), k // 2 + 1):
                        cx, cy = min(max(qx + dx, 0), w - 1), min(max(qy + dy, 0), h - 1)
                        count[b, i, cy * w + cx] += 1
        counts.append(count)
    y = torch.cat(keys, dim=1)  # (B, P, C), every cell of every level
    y_pos = pos_embedding(torch.cat(pos, dim=0).to(x.dtype))  # (P, C)
    count = torch.cat(counts, dim=2)  # (B, K, P)
    kv = layer.cross_attn.to_kv(norm(y + y_pos[None]))  # (B, P, 2 h d)
    k_, v_ = kv.reshape(B, -1, 2, heads, dh).permute(2, 0, 3, 1, 4)  # (B, h, P, d) each
    q = q.reshape(B, K, heads, dh).transpose(1, 2)  # (B, h, K, d)
    logits = q @ k_.transpose(-1, -2) / math.sqrt(dh) + torch.log(count)[:, None]
    out = torch.softmax(logits, dim=-1) @ v_  # (B, h, K, d)
    return layer.cross_attn.to_out(out.transpose(1, 2).reshape(B, K, heads * dh))


def test_windowed_cross_attention_matches_dense_masked_attention():
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    B, K, C = 2, 9, 16
    layer = CenterTransformerLayer(C, heads=2, dim_head=8, mlp_dim=32, dropout=0.0).double()
    pos_embedding = torch.nn.Linear(2, C).double()
    levels = [
        torch.randn(B, C, 12 // s, 12 // s, generator=g, dtype=torch.float64) for s in (1, 2, 4)
    ]
    cells = torch.randint(0, 12, (B, K, 2), generator=g)
    cells[0, :4] = torch.tensor([[0, 0], [11, 11], [0, 11], [5, 0]])  # borders: clamped windows
    kernel_sizes = (3, 5, 3)  # a window wider than the coarsest level (3 x 3) repeats cells
    x = torch.randn(B, K, C, generator=g, dtype=torch.float64)
    keys, key_cells = gather_neighbours(cells, levels, kernel_sizes)
    assert keys.shape == (B, K, 9 + 25 + 9, C) and key_cells.shape == (B, K, 43, 2)
    x_pos = pos_embedding(cells.double())
    got = layer.cross_attn(
        layer.cross_norm(x + x_pos), layer.cross_norm(keys + pos_embedding(key_cells.double()))
    )
    expected = dense_cross_attention(layer, x, cells, levels, kernel_sizes, pos_embedding)
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10)


def test_neighbour_windows_read_the_cells_they_name():
    """Each gathered key is the level's feature at the window cell its position names."""
    g = torch.Generator().manual_seed(1)
    levels = [torch.randn(1, 4, 16 // s, 16 // s, generator=g) for s in (1, 2, 4)]
    cells = torch.tensor([[[15, 0], [7, 9], [0, 15]]])
    keys, key_cells = gather_neighbours(cells, levels, (3, 3, 3))
    for i in range(3):
        for n in range(27):
            level = levels[n // 9]
            scale = 16 // level.shape[-1]
            x, y = (key_cells[0, i, n] // scale).tolist()
            assert torch.equal(keys[0, i, n], level[0, :, y, x])
            qx, qy = (cells[0, i] // scale).tolist()
            assert abs(x - qx) <= 1 and abs(y - qy) <= 1  # inside the query's window
    with pytest.raises(ValueError, match="3 feature levels; give one per level"):
        gather_neighbours(cells, levels, (3, 3))


# ------------------------------------------------------------------- query selection
def brute_force_queries(scores, k, gt_inds=None, gt_mask=None):
    out = []
    for b in range(scores.shape[0]):
        gt = set()
        if gt_inds is not None:
            gt = {int(i) for i, m in zip(gt_inds[b], gt_mask[b]) if m}
        ranked = sorted(
            range(scores.shape[1]),
            key=lambda c: (-(float(scores[b, c].detach()) + (1.0 if c in gt else 0.0)), c),
        )
        out.append(ranked[:k])
    return torch.tensor(out)


def test_top_k_queries_match_a_sorting_loop():
    g = torch.Generator().manual_seed(0)
    scores = (torch.rand(3, 60, generator=g) * 10).floor() / 10  # many ties
    assert torch.equal(select_center_queries(scores, 12), brute_force_queries(scores, 12))
    gt_inds = torch.randint(0, 60, (3, 5), generator=g)
    gt_inds[1, 3] = gt_inds[1, 2]  # two objects in one cell: one query
    gt_mask = torch.rand(3, 5, generator=g) > 0.3
    gt_mask[2, 0] = True
    gt_inds[2, 3:], gt_mask[2, 3:] = gt_inds[2, 0], False  # padding slots at a real object's cell
    got = select_center_queries(scores, 12, gt_inds, gt_mask)
    assert torch.equal(got, brute_force_queries(scores, 12, gt_inds, gt_mask))
    for b in range(3):  # every real ground-truth cell is a query, each once
        assert set(gt_inds[b][gt_mask[b]].tolist()) <= set(got[b].tolist())
        assert len(set(got[b].tolist())) == 12
    with pytest.raises(ValueError, match="num_queries must be in 1..60"):
        select_center_queries(scores, 61)


def test_ground_truth_centres_are_queries_in_training_only(monkeypatch):
    model = cropped()
    head = model.dense_head
    head.num_queries = 8  # of 32 x 32 cells: a random heatmap ranks the objects' cells anywhere
    batch = batch_for(model)
    seen = []
    run = head.run_queries

    def recording(batch_dict, gt_inds=None, gt_mask=None):
        out = run(batch_dict, gt_inds, gt_mask)
        seen.append((out, gt_inds))
        return out

    monkeypatch.setattr(head, "run_queries", recording)
    targets = cu.encode_center_targets(
        batch["gt_boxes"], num_class=3, feature_map_size=head.feature_map_size,
        point_cloud_range=head.point_cloud_range, voxel_size=head.voxel_size,
        feature_map_stride=head.feature_map_stride, with_velocity=False,
    )  # fmt: skip
    model.train()
    model.loss(batch)
    model.eval()  # batch norms frozen: the heatmap is the same in both passes below
    model.loss(batch)
    model.predict(batch)
    (train_out, train_gt), (eval_out, eval_gt), (pred_out, _) = seen
    assert train_gt is not None and eval_gt is None
    for b in range(2):
        gt_cells = set(targets.inds[b][targets.mask[b]].tolist())
        assert gt_cells <= set(train_out["order"][b].tolist())
        assert not gt_cells <= set(eval_out["order"][b].tolist())  # not by chance
    # outside training the queries are the heatmap's top-K alone, in loss and in predict
    scores = torch.sigmoid(eval_out["hm"].float()).flatten(2).max(dim=1).values
    assert torch.equal(eval_out["order"], brute_force_queries(scores, 8))
    assert torch.equal(pred_out["order"], eval_out["order"])


# ------------------------------------------------------------------- targets and decoding
def test_box_codes_decode_to_the_ground_truth_boxes():
    """The regression target at an object's centre cell decodes back to its box: the IoU
    head's target (IoU of the decoded prediction with the decoded target) is the IoU with the
    ground truth."""
    head = cropped().dense_head
    gt = make_batch(num_point_features=5, scale=0.5)["gt_boxes"]
    t = cu.encode_center_targets(
        gt, num_class=3, feature_map_size=head.feature_map_size,
        point_cloud_range=head.point_cloud_range, voxel_size=head.voxel_size,
        feature_map_stride=head.feature_map_stride, with_velocity=False,
    )  # fmt: skip
    boxes = head.decode_boxes(t.box_targets, t.inds, head.feature_map_size[1])
    for b in range(2):
        n = int(t.mask[b].sum())
        assert n == int((gt[b, :, 3] > 0).sum())
        torch.testing.assert_close(boxes[b, :n], gt[b, :n, :7], rtol=0, atol=1e-5)


def test_corner_heatmap_peaks_at_the_centre_and_edge_midpoints():
    head = cropped().dense_head  # 32 x 32 cells of 0.64 m from -10.24 m
    box = torch.tensor([[[0.32, 0.32, 1.0, 4.48, 1.92, 1.6, 0.0, 1.0]]])  # centre of cell (16, 16)
    hm = head.corner_targets(box)[0, 0]
    peaks = {tuple(p) for p in torch.nonzero(hm == 1).tolist()}  # (y, x)
    # the centre is at 16.5 cells; half length 2.24 m = 3.5 cells along x (16.5 +- 3.5 -> cells
    # 20 and 13), half width 0.96 m = 1.5 cells along y (cells 18 and 15)
    assert peaks == {(16, 16), (16, 20), (16, 13), (18, 16), (15, 16)}
    assert float(hm.sum()) > 5  # Gaussians, not points
    assert head.corner_targets(torch.zeros(1, 2, 8)).sum() == 0  # padding rows draw nothing


def test_iou_rectification_and_class_specific_nms():
    """Two overlapping boxes of different classes both survive (per-class NMS); of the same
    class the lower-scored one is suppressed. Scores are the heatmap's times the predicted IoU
    to the power of the class's IOU_RECTIFIER (1 for vehicles, 4 for cyclists)."""
    head = cropped().dense_head  # 32 x 32 cells of 0.64 m from -10.24 m
    H, W = head.feature_map_size
    order = torch.tensor([[16 * W + 16, 16 * W + 17, 20 * W + 16, 5 * W + 5]])
    codes = torch.zeros(1, 8, 4)
    codes[:, 3:6] = math.log(2.0)  # 2 m cubes
    codes[:, 6] = 1.0  # heading 0
    codes[0, 0, 1] = -0.9  # query 1 at x 0.064 m overlaps query 0 at 0 (BEV IoU 0.94)
    out = {
        "hm": torch.zeros(1, 3, H, W), "order": order,
        "center": codes[:, 0:2], "center_z": codes[:, 2:3], "dim": codes[:, 3:6],
        "rot": codes[:, 6:8], "iou": torch.tensor([[[0.0, 0.0, 0.6, 1.0]]]),
        "scores": torch.tensor([[0.9, 0.8, 0.7, 0.05]]), "labels": torch.tensor([[0, 2, 0, 1]]),
    }  # fmt: skip
    pred = head.predict(out)[0]
    # query 3 is under the score threshold; IoU 0 -> 0.5, 0.6 -> 0.8; the cyclist's 0.5 ** 4
    assert pred["pred_labels"].tolist() == [1, 1, 3]
    torch.testing.assert_close(pred["pred_scores"], torch.tensor([0.7 * 0.8, 0.9 * 0.5, 0.05]))
    out["labels"] = torch.tensor([[0, 0, 0, 1]])  # one class: query 1 (0.4) is suppressed
    pred = head.predict(out)[0]
    assert pred["pred_scores"].tolist() == pytest.approx([0.56, 0.45])
    torch.testing.assert_close(pred["pred_boxes"][:, :2], torch.tensor([[0.0, 2.56], [0.0, 0.0]]))


# ------------------------------------------------------------------- the whole model
def test_gradients_reach_every_parameter():
    model = cropped().train()
    batch = batch_for(model)
    losses = model.loss(batch)
    assert set(losses) == {"loss", "hm_loss", "loc_loss", "iou_loss", "corner_loss"}
    assert all(torch.isfinite(v) for v in losses.values())
    losses["loss"].backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, f"{name} received no gradient"
        assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


@pytest.mark.parametrize(
    "path", [SYN, pytest.param(CFGS / "centerformer.yaml", marks=pytest.mark.slow)],
    ids=lambda p: str(p.relative_to(CFGS)),
)  # fmt: skip
def test_config_builds_trains_two_steps_and_predicts(path: Path):
    cfg = cfg_from_yaml_file(path)
    full = build_network_from_config(cfg)  # the config as shipped builds
    assert type(full) is CenterFormer
    fms = cfg.MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG.FEATURE_MAP_STRIDE
    grid = full.vfe.grid.grid_size
    assert full.dense_head.feature_map_size == (grid[1] // fms, grid[0] // fms)
    assert cfg.ATLAS.TEMPORAL_WINDOW == 1 and cfg.ATLAS.MODEL_NAME == "CenterFormer"
    model = cropped(path)
    assert {k: v.shape for k, v in model.state_dict().items()} == {
        k: v.shape for k, v in full.state_dict().items()
    }
    del full
    batch = batch_for(model)
    optim = torch.optim.AdamW(model.parameters(), lr=1e-3)
    model.train()
    for _ in range(2):
        optim.zero_grad()
        ret, tb, _ = model(batch)  # OpenPCDet's training contract, through loss()
        assert math.isfinite(tb["loss"]) and {"hm_loss", "iou_loss"} <= set(tb)
        ret["loss"].backward()
        optim.step()
    assert "head_outputs" not in batch and "voxel_features" not in batch  # input untouched
    model.eval()
    keep = batch["points"][:, 0] == 0  # sample 1 has no points: empty frames are legal
    preds, recall = model({"points": batch["points"][keep], "batch_size": 2})
    assert len(preds) == 2 and recall == {}
    for p in preds:
        k = p["pred_boxes"].shape[0]
        assert p["pred_boxes"].shape == (k, 7) and torch.isfinite(p["pred_boxes"]).all()
        assert p["pred_scores"].shape == (k,) and p["pred_labels"].shape == (k,)
        assert ((p["pred_labels"] >= 1) & (p["pred_labels"] <= 3)).all()
        assert (p["pred_scores"][:-1] >= p["pred_scores"][1:]).all()


@pytest.mark.parametrize(
    "body,match",
    [
        ("  DENSE_HEAD:\n    TARGET_ASSIGNER_CONFIG:\n      FEATURE_MAP_STRIDE: 4\n",
         r"FEATURE_MAP_STRIDE \(4\) differs from the query map's stride \(2 voxels"),
        ("  BACKBONE_2D:\n    NUM_FILTERS: [64, 128, 32]\n",
         r"NUM_FILTERS \[64, 128, 32\] must be"),
        ("  DENSE_HEAD:\n    TRANSFORMER:\n      KERNEL_SIZE: [3, 3, 3]\n",
         r"unknown key 'KERNEL_SIZE' in MODEL\.DENSE_HEAD\.TRANSFORMER \(from .*bad\.yaml"),
        ("  DENSE_HEAD:\n    POST_PROCESSING:\n      IOU_RECTIFIER: [1, 4]\n",
         r"IOU_RECTIFIER needs one value per class \(3\), got \[1\.0, 4\.0\]"),
    ],
)  # fmt: skip
def test_config_mistakes_name_the_key(tmp_path, body, match):
    path = tmp_path / "bad.yaml"
    path.write_text(f"_BASE_CONFIG_: {SYN}\nMODEL:\n{body}")
    with pytest.raises(ConfigError, match=match):
        build_network_from_config(cfg_from_yaml_file(path))
