"""PHiM and PHiM+LOT: polar voxels, padded Mamba sequences, streaming causality and per-frame
state, LOT's hard cases, the occupancy target across the seam, and the staged training."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
from model_batches import make_batch

from pcdet_atlas.config import REPO_ROOT, ConfigError, cfg_from_yaml_file
from pcdet_atlas.models import build_network_from_config
from pcdet_atlas.models.backbones_3d.polar_sector_mamba import polar_neighbours
from pcdet_atlas.models.model_utils.mamba import Mamba, pack_sequences
from pcdet_atlas.models.model_utils.polar_grid import PolarGrid, polar_voxelize
from pcdet_atlas.models.occupancy.occupancy_targets import occupancy_target
from pcdet_atlas.train_utils.stages import (
    apply_stage_freezing,
    load_stage_init,
    stage_from_config,
    stage_init_checkpoint,
)

CFGS = REPO_ROOT / "cfgs" / "atlas"
PHIM_CONFIGS = sorted(p for p in CFGS.rglob("*.yaml") if cfg_from_yaml_file(p).MODEL.NAME == "PHiM")
SYN_PHIM = CFGS / "synthetic" / "phim.yaml"
SYN_PHIM_FINE = CFGS / "synthetic" / "phim_fine.yaml"
SYN_STAGES = [CFGS / "synthetic" / "phim_lot" / f for f in
              ("stage1_score.yaml", "stage2_ssm.yaml", "stage3_finetune.yaml")]  # fmt: skip


CROP_M = 25.6  # smoke runs crop the Cartesian BEV to +-25.6 m: the same parameters, less map


def build(path: Path, seed: int = 0, crop: bool = True, **model_overrides):
    cfg = cfg_from_yaml_file(path)
    if crop:
        pcr = cfg.DATA_CONFIG.POINT_CLOUD_RANGE
        cfg.DATA_CONFIG.POINT_CLOUD_RANGE = [-CROP_M, -CROP_M, pcr[2], CROP_M, CROP_M, pcr[5]]
    for key, value in model_overrides.items():
        section, name = key.split(".")
        cfg.MODEL[section][name] = value
    torch.manual_seed(seed)
    return build_network_from_config(cfg), cfg


def one_sample(batch: dict, b: int) -> dict:
    pts = batch["points"][batch["points"][:, 0] == b].clone()
    pts[:, 0] = 0
    return {"points": pts, "batch_size": 1, "gt_boxes": batch["gt_boxes"][b : b + 1]}


# ----------------------------------------------------------------------------- polar grid
def test_polar_voxelize_matches_a_per_point_reference():
    grid = PolarGrid((0.0, 40.0), (-2.0, 4.0), (20, 64, 3), 8)
    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(3000, 3, generator=g) - 0.5) * torch.tensor([90.0, 90.0, 7.0])
    # the seam: +pi (y = +0, x < 0) and -pi, a point on a range edge, one just below +pi
    extra = torch.tensor([[-5.0, 0.0, 0.0], [-5.0, -0.0, 0.0], [10.0, 0.0, 1.0],
                          [-7.0, 3.1e-15, 0.5]])  # fmt: skip
    xyz = torch.cat([xyz, extra])
    points = torch.cat([torch.zeros(len(xyz), 1), xyz, torch.zeros(len(xyz), 2)], 1).double()
    vox = polar_voxelize(points, grid)
    dr, da, dz = grid.cell_size
    expected = {}
    for i, (x, y, z) in enumerate(xyz.double().tolist()):
        r, t = math.hypot(x, y), math.atan2(y, x)
        t = t - 2 * math.pi if t >= math.pi else t
        # just below +pi, t + pi may round up to 2 pi: such points stay in the last bin
        a = min(math.floor((t + math.pi) / da), 63)
        cell = (math.floor((z + 2.0) / dz), a, math.floor(r / dr))
        if 0 <= cell[0] < 3 and 0 <= cell[2] < 20:
            expected[i] = (0, *cell)
    got_idx = torch.nonzero(vox.point_mask).squeeze(1).tolist()
    assert set(got_idx) == set(expected)
    coords = vox.voxel_coords[vox.point_voxel_idx].tolist()
    assert all(tuple(c) == expected[i] for i, c in zip(got_idx, coords))
    n = len(xyz)
    seam = {tuple(c) for i, c in zip(got_idx, coords) if i in (n - 4, n - 3)}
    assert seam == {(0, 1, 0, 2)}  # +pi and -pi share the first azimuth bin
    assert expected[n - 1][2] == 63  # just below +pi: the last bin, not outside


def test_polar_grid_measures_from_its_origin():
    """Range and azimuth are taken about ``origin_xy``: voxels of points about an origin are
    those of the shifted points about zero, and the occupancy target moves with the boxes."""
    kw = dict(range_m=(0.0, 40.0), z_range_m=(-2.0, 4.0), grid_size=(40, 128, 3), num_sectors=8)
    at_lidar = PolarGrid(**kw, origin_xy=(1.43, -0.5))
    g = torch.Generator().manual_seed(1)
    xyz = (torch.rand(2000, 3, generator=g) - 0.5) * torch.tensor([80.0, 80.0, 6.0])
    points = torch.cat([torch.zeros(len(xyz), 1), xyz, torch.zeros(len(xyz), 2)], 1).double()
    shifted = points.clone()
    shifted[:, 1] -= 1.43
    shifted[:, 2] += 0.5
    a, b = polar_voxelize(points, at_lidar), polar_voxelize(shifted, PolarGrid(**kw))
    assert torch.equal(a.voxel_coords, b.voxel_coords)
    assert torch.equal(a.point_voxel_idx, b.point_voxel_idx)
    # a point 1 m in front of the sensor lies in range bin 1 about it, bin 2 about the vehicle
    probe = torch.tensor([[0.0, 2.93, -0.5, 0.0, 0.0, 0.0]], dtype=torch.float64)
    assert polar_voxelize(probe, at_lidar).voxel_coords[0, 3] == 1
    boxes = torch.tensor([[[12.0, 5.0, 0.8, 4.6, 2.0, 1.6, 0.3, 1.0]]])
    moved = boxes.clone()
    moved[0, 0, :2] -= torch.tensor([1.43, -0.5])
    torch.testing.assert_close(
        occupancy_target(boxes, at_lidar, (2, 2)), occupancy_target(moved, PolarGrid(**kw), (2, 2))
    )
    with pytest.raises(ValueError, match="origin_xy"):
        PolarGrid(**kw, origin_xy=(float("nan"), 0.0))


def test_polar_neighbours_match_a_per_voxel_reference():
    """Each voxel's neighbours along range, azimuth (dilated by range) and height, inside its
    sector only, against a dictionary lookup."""
    grid = PolarGrid((0.0, 32.0), (-2.0, 4.0), (40, 256, 4), 4)
    g = torch.Generator().manual_seed(0)
    cells = torch.stack(
        [torch.randint(0, 2, (6000,), generator=g), torch.randint(0, 4, (6000,), generator=g),
         torch.randint(0, 256, (6000,), generator=g), torch.randint(0, 40, (6000,), generator=g)],
        dim=1,
    ).unique(dim=0)  # fmt: skip
    got = polar_neighbours(cells, grid)
    where = {tuple(c): i for i, c in enumerate(cells.tolist())}
    dr, da, _ = grid.cell_size
    sb = grid.sector_bins
    dilated = 0
    for i, (b, z, a, r) in enumerate(cells.tolist()):
        step = min(max(1, round(dr / ((r + 0.5) * dr * da))), sb // 2)
        dilated += step > 1
        want = []
        for dz, dad, drr in [(0, 0, -1), (0, 0, 1), (0, -step, 0), (0, step, 0), (-1, 0, 0),
                             (1, 0, 0)]:  # fmt: skip
            q = (b, z + dz, a + dad, r + drr)
            same_sector = (a + dad) // sb == a // sb and 0 <= a + dad < 256
            want.append(where.get(q, -1) if same_sector else -1)
        assert got[i].tolist() == want, (i, (b, z, a, r))
    assert dilated > 100 and (got >= 0).sum() > 1000  # both cases are exercised
    assert polar_neighbours(cells[:0], grid).shape == (0, 6)


def test_decomposed_conv_reads_its_neighbours_and_nothing_else():
    model, _ = build(SYN_PHIM_FINE)
    block = model.backbone_3d.conv_blocks[0]
    grid = model.backbone_3d.grid
    coords = torch.tensor([[0, 2, 100, 50], [0, 2, 100, 51], [0, 2, 100, 53], [0, 3, 100, 50]])
    nb = polar_neighbours(coords, grid)
    assert nb[0].tolist() == [-1, 1, -1, -1, -1, 3]
    x = torch.randn(4, block.norm.weight.shape[0])
    with torch.no_grad():
        y = block(x, nb)
        x2 = x.clone()
        x2[2] += 1.0  # two range bins away: not a neighbour of voxel 0
        assert torch.equal(block(x2, nb)[0], y[0])
        x3 = x.clone()
        x3[3] += 1.0  # one height bin above voxel 0
        assert not torch.allclose(block(x3, nb)[0], y[0])


def test_sector_buffer_point_offsets_tell_where_in_the_cell_the_points_lie():
    from pcdet_atlas.models.map_to_bev.sector_feature_buffer import SectorFeatureBuffer

    def bev(point_offsets: bool, xy: list[list[float]]) -> torch.Tensor:
        torch.manual_seed(0)
        stage = SectorFeatureBuffer(
            input_channels=4, num_bev_features=8, point_cloud_range=(0, 0, -2, 4, 4, 4),
            bev_cell_m=(1.0, 1.0), point_offsets=point_offsets,
        ).eval()  # fmt: skip
        batch = {
            "voxel_features": torch.arange(8.0).view(2, 4),
            "voxel_coords": torch.zeros(2, 4, dtype=torch.long),
            "voxel_point_idx": torch.tensor([0, 0, 1]),
            "voxel_point_xy": torch.tensor(xy),
            "batch_size": 1,
        }
        with torch.no_grad():
            return stage(batch)["spatial_features"][0]  # (C, ny, nx)

    # one voxel's two points at two places in cell (x 1, y 2); the other voxel's point far off
    near = [[1.1, 2.1], [1.2, 2.2], [3.5, 0.5]]
    far = [[1.9, 2.9], [1.8, 2.8], [3.5, 0.5]]
    off_near, off_far = bev(False, near), bev(False, far)
    assert torch.equal(off_near, off_far)  # without offsets a cell only knows which voxel
    on_near, on_far = bev(True, near), bev(True, far)
    assert not torch.allclose(on_near[:, 2, 1], on_far[:, 2, 1])  # with them, where in the cell
    assert torch.equal(on_near[:, 0, 3], on_far[:, 0, 3])  # the other cell is untouched
    empty = torch.ones(4, 4, dtype=torch.bool)
    empty[2, 1] = empty[0, 3] = False
    assert not on_near[:, empty].any() and not off_near[:, empty].any()


def test_pack_sequences_round_trip_and_reverse():
    seq = torch.tensor([1, 0, 1, 1, 2, 0])
    key = torch.tensor([5, 3, 1, 2, 0, 0])
    packed = pack_sequences(seq, key, 4)
    x = torch.arange(6, dtype=torch.float32)[:, None] + 1
    pad = packed.to_padded(x)  # (4, 3, 1)
    assert pad.shape == (4, 3, 1)
    assert pad[1, :, 0].tolist() == [3.0, 4.0, 1.0]  # sequence 1 ordered by key
    assert pad[0, :2, 0].tolist() == [6.0, 2.0] and pad[3].abs().sum() == 0
    rev = packed.to_padded(x, reverse=True)
    assert rev[1, :, 0].tolist() == [1.0, 4.0, 3.0] and rev[0, :2, 0].tolist() == [2.0, 6.0]
    assert torch.equal(packed.from_padded(pad), x)
    assert torch.equal(packed.from_padded(rev, reverse=True), x)


def test_mamba_valid_outputs_do_not_depend_on_padding():
    torch.manual_seed(0)
    layer = Mamba(8, d_state=4, expand=2).eval()
    x = torch.randn(10, 8)
    alone = pack_sequences(torch.zeros(10, dtype=torch.long), torch.arange(10), 1)
    y_alone = alone.from_padded(layer(alone.to_padded(x)))
    # the same sequence beside a longer one: padded to 30 rows
    seq = torch.cat([torch.zeros(10), torch.ones(30)]).long()
    both = pack_sequences(seq, torch.cat([torch.arange(10), torch.arange(30)]), 2)
    y_both = both.from_padded(layer(both.to_padded(torch.cat([x, torch.randn(30, 8)]))))[:10]
    torch.testing.assert_close(y_both, y_alone, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------- the PHiM detector
def with_lag(batch: dict, lag_s: float) -> torch.Tensor:
    """``batch['points']`` with a time-lag column."""
    points = batch["points"]
    return torch.cat([points, torch.full_like(points[:, :1], lag_s)], dim=1)


def with_history(batch: dict, frames: int) -> dict:
    """``batch`` with ``frames`` previous frames (other points, lags 0.1 s apart) and a
    time-lag column, for a LOT that forecasts from frames; ``batch`` as it is for 0."""
    if not frames:
        return batch
    history = [make_batch(num_point_features=5, points_per_box=50, background=300, seed=1 + j)
               for j in range(frames)]  # fmt: skip
    points = [with_lag(f, 0.1 * j) for j, f in enumerate([batch, *history])]
    return {**batch, "points": torch.cat(points)}


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(p, marks=[] if "synthetic" in p.parts else [pytest.mark.slow])
        for p in PHIM_CONFIGS
    ],
    ids=lambda p: str(p.relative_to(CFGS)),
)
def test_phim_configs_build_train_and_predict(path: Path):
    model, cfg = build(path)
    full, _ = build(path, crop=False)  # the config as shipped builds, with the same tensors
    assert {k: v.shape for k, v in model.state_dict().items()} == {
        k: v.shape for k, v in full.state_dict().items()
    }
    del full
    stage = stage_from_config(cfg)
    if stage is not None:
        apply_stage_freezing(model, stage)
    assert (model.lot is not None) == ("LOT" in cfg.MODEL)
    batch = make_batch(num_point_features=5, points_per_box=50, background=300)
    batch = with_history(batch, model.lot.history_frames if model.lot is not None else 0)
    model.train()
    losses = model.loss(batch)
    assert all(torch.isfinite(v) for v in losses.values())
    losses["loss"].backward()
    trainable = [n for n, p in model.named_parameters() if p.requires_grad]
    assert trainable
    no_grad = [n for n, p in model.named_parameters() if p.requires_grad and p.grad is None]
    assert not no_grad, no_grad
    model.eval()
    preds = model.predict(batch)
    assert len(preds) == 2 and preds[0]["pred_boxes"].shape[1] == 7


def test_phim_state_never_leaks_between_frames():
    model, _ = build(SYN_PHIM)
    model.eval()
    batch = make_batch(num_point_features=5)
    a, b = one_sample(batch, 0), one_sample(batch, 1)
    first = model.predict(a)[0]
    model.predict(b)
    again = model.predict(a)[0]
    for key in first:
        assert torch.equal(first[key], again[key])  # nothing carried over from frame b
    together = model.predict(batch)[0]  # a beside b in one batch: own sectors, own state
    torch.testing.assert_close(together["pred_scores"], first["pred_scores"], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(together["pred_boxes"], first["pred_boxes"], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("path", [SYN_PHIM, SYN_PHIM_FINE], ids=lambda p: p.stem)
def test_phim_streams_sectors_causally_in_azimuth_order(path: Path):
    """A sector's features depend on the sectors streamed before it, never on later ones."""
    model, _ = build(path)
    model.eval()
    grid = model.vfe.grid
    batch = one_sample(make_batch(num_point_features=5, background=4000), 0)
    extra = batch["points"][:50].clone()
    extra[:, 1:3] = torch.tensor([0.0, 20.0])  # azimuth +pi/2: a late sector
    changed = {**batch, "points": torch.cat([batch["points"], extra])}
    with torch.no_grad():
        outs = [model.backbone_3d(model.vfe(dict(x))) for x in (batch, changed)]
    late = int(math.floor((math.pi / 2 + math.pi) / grid.cell_size[1])) // grid.sector_bins
    for out in outs:
        out["sector"] = out["voxel_coords"][:, 2] // grid.sector_bins
    early = [o["voxel_features"][o["sector"] < late] for o in outs]
    assert early[0].shape[0] > 0
    torch.testing.assert_close(early[1], early[0], rtol=1e-5, atol=1e-6)
    after = [o["voxel_features"][o["sector"] == late] for o in outs]
    assert after[0].shape != after[1].shape or not torch.allclose(after[0], after[1])


# ----------------------------------------------------------------------------------- LOT
def lot_model(**overrides):
    model, cfg = build(SYN_STAGES[2], **{f"LOT.{k}": v for k, v in overrides.items()})
    return model.eval(), cfg


def test_lot_empty_frame_empty_sectors_and_everything_filtered():
    model, _ = lot_model()
    empty = {"points": torch.zeros(0, 6), "batch_size": 1, "gt_boxes": torch.zeros(1, 1, 8)}
    pred = model.predict(empty)[0]
    assert torch.isfinite(pred["pred_scores"]).all()
    out = model.lot(model.vfe(dict(empty)))
    assert out["lot_current"].abs().sum() == 0 and out["voxel_features"].shape[0] == 0
    # all points in one sector: the other sectors are empty maps, forecasts stay finite
    batch = one_sample(make_batch(num_point_features=5, background=0), 0)
    batch["points"] = batch["points"][:200]
    out = model.lot(model.vfe(dict(batch)))
    assert torch.isfinite(out["lot_final"]).all()
    sectors = out["voxel_coords"][:, 2] // model.vfe.grid.sector_bins
    assert sectors.unique().numel() <= 2
    # a threshold above every confidence: no voxel reaches the backbone, the head still runs
    model_all, _ = lot_model(FILTER_THRESH=1.01)
    batch = make_batch(num_point_features=5)
    out = model_all.lot(model_all.vfe(dict(batch)))
    assert out["voxel_features"].shape[0] == 0 and out["voxel_point_idx"].numel() == 0
    preds = model_all.predict(batch)
    assert all(torch.isfinite(p["pred_scores"]).all() for p in preds)
    model_all.train()
    losses = model_all.loss(batch)
    assert torch.isfinite(losses["loss"])


def test_lot_keeps_points_with_their_voxels():
    model, _ = lot_model(FILTER_THRESH=0.5)
    batch = make_batch(num_point_features=5)
    before = model.vfe(dict(batch))
    after = model.lot(dict(before))
    keep = after["lot_keep"]
    kept_rows = before["voxel_features"][keep]
    assert torch.equal(after["voxel_features"], kept_rows)
    # every remaining point points at the voxel it belonged to before the filter
    old = before["voxel_point_idx"][keep[before["voxel_point_idx"]]]
    assert torch.equal(before["voxel_coords"][old], after["voxel_coords"][after["voxel_point_idx"]])
    assert after["lot_voxel_confidence"].shape == keep.shape


def test_lot_masked_pooling_scores_a_sparse_cell_as_its_voxels():
    """An occupancy cell holding one voxel: the paper's average pooling divides its score by the
    cell's bins (empty bins count as zero occupancy), below a full cell of voxels with the same
    score; masked pooling gives each cell the mean score of its voxels."""
    maps = {}
    for pooling in ("masked", "average"):
        lot = lot_model(POOLING=pooling)[0].lot
        with torch.no_grad():  # every voxel scores sigmoid(0) = 0.5
            lot.score_mlp[-1].weight.zero_()
            lot.score_mlp[-1].bias.zero_()
        pa, pr = lot.pool_size
        # cell (0, 0): one voxel; cell (0, 1): every bin at two heights
        coords = [[0, 1, 0, 0]] + [
            [0, z, a, pr + r] for z in range(2) for a in range(pa) for r in range(pr)
        ]  # fmt: skip
        batch = {
            "voxel_features": torch.randn(len(coords), lot.score_mlp[0].in_features),
            "voxel_coords": torch.tensor(coords), "batch_size": 1,
        }  # fmt: skip
        maps[pooling] = lot.current_map(batch)[0]
    bins = pa * pr
    assert maps["masked"][0, 0] == 0.5 and maps["masked"][0, 1] == 0.5
    assert maps["average"][0, 0] == 0.5 / bins and maps["average"][0, 1] == 0.5
    for m in maps.values():  # every other cell is empty
        assert m.sum() == m[0, 0] + m[0, 1]
    with pytest.raises(ValueError, match="POOLING"):
        lot_model(POOLING="max")


def test_occupancy_target_across_the_azimuth_seam():
    grid = PolarGrid((0.0, 76.8), (-2.0, 4.0), (96, 384, 4), 8)
    box = torch.tensor([[[-20.0, 0.0, 0.8, 4.6, 2.0, 1.6, 0.0, 1.0]]])  # straddles +-pi
    target = occupancy_target(box, grid, (2, 2))[0]  # (192, 48)
    rows = torch.nonzero(target.eq(1).any(1)).squeeze(1).tolist()
    assert 0 in rows and 191 in rows and 96 not in rows  # both ends of the azimuth axis
    r_cells = torch.nonzero(target.eq(1).any(0)).squeeze(1)
    r_lo, r_hi = (r_cells.min().item() * 1.6, (r_cells.max().item() + 1) * 1.6)
    assert r_lo <= 17.7 and r_hi >= 22.3  # the footprint's radial extent 17.7 .. 22.3 m
    assert target.max() == 1 and target.min() >= 0
    assert 0.01 < target[0, 15] < 0.5  # the Gaussian's tail beyond the footprint
    # the same box away from the seam gives the same picture, shifted by half a turn
    turned = box.clone()
    turned[0, 0, 0] = 20.0
    shifted = occupancy_target(turned, grid, (2, 2))[0]
    torch.testing.assert_close(torch.roll(shifted, 96, 0), target, atol=1e-5, rtol=0)
    assert occupancy_target(torch.zeros(1, 2, 8), grid, (2, 2)).abs().sum() == 0


# -------------------------------------------------------------------------- staged training
def run_stage_step(stage_path: Path, init: dict):
    model, cfg = build(stage_path, seed=1)
    model.load_state_dict(init, strict=False)
    stage = stage_from_config(cfg)
    apply_stage_freezing(model, stage)
    model.train()
    before = copy.deepcopy(model.state_dict())
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-2,
                            weight_decay=0.01)  # fmt: skip
    losses = model.loss(make_batch(num_point_features=5))
    losses["loss"].backward()
    opt.step()
    after = model.state_dict()
    return stage, before, after


@pytest.mark.parametrize("index", [1, 2], ids=["stage2", "stage3"])
def test_staged_freezing_keeps_frozen_tensors_bitwise(index):
    init, _ = build(SYN_STAGES[0], seed=0)
    stage, before, after = run_stage_step(SYN_STAGES[index], init.state_dict())
    trained = [k for k in before if any(k.startswith(t + ".") for t in stage.train)]
    frozen = [k for k in before if k not in trained]
    assert trained and frozen
    changed_frozen = [k for k in frozen if not torch.equal(before[k], after[k])]
    assert not changed_frozen, changed_frozen  # weights and batch-norm statistics alike
    assert any(not torch.equal(before[k], after[k]) for k in trained)


def test_stage_without_predecessor_checkpoint_stops_naming_both(tmp_path):
    stage = stage_from_config(cfg_from_yaml_file(SYN_STAGES[1]))
    with pytest.raises(FileNotFoundError, match=r"stage2_ssm.*stage1_score"):
        stage_init_checkpoint(stage, output_root=tmp_path, extra_tag="x", pretrained_model=None)
    # a checkpoint without the score MLP stage 2 must freeze (PHiM's, not stage 1's)
    phim, _ = build(SYN_PHIM)
    ckpt = tmp_path / "phim.pth"
    torch.save({"model_state": phim.state_dict()}, ckpt)
    model, _ = build(SYN_STAGES[1])
    with pytest.raises(ValueError, match=r"stage2_ssm.*lot\.score_mlp.*phim\.pth"):
        load_stage_init(model, stage, ckpt)
    # stage 1 starts from PHiM's checkpoint: LOT is new, the frozen VFE comes from it
    stage1 = stage_from_config(cfg_from_yaml_file(SYN_STAGES[0]))
    new = load_stage_init(model, stage1, ckpt)
    assert new and all(k.startswith("lot.") for k in new)
    assert torch.equal(model.vfe.pfn_layers[0].linear.weight, phim.vfe.pfn_layers[0].linear.weight)


def test_stage_configs_say_what_trains():
    expect = {
        "stage1_score": ({"lot.score_mlp"}, {"vfe"}, ["occupancy"]),
        "stage2_ssm": ({"lot.convssm"}, {"vfe", "lot.score_mlp"}, ["forecast"]),
        "stage3_finetune": (
            {"backbone_3d", "map_to_bev_module", "backbone_2d", "dense_head"},
            {"vfe", "lot"},
            ["detection"],
        ),
    }
    for folder in (
        CFGS / "phim_lot",
        CFGS / "synthetic" / "phim_lot",
        CFGS / "synthetic" / "phim_lot_fine",
    ):
        for name, (train, freeze, terms) in expect.items():
            cfg = cfg_from_yaml_file(folder / f"{name}.yaml")
            stage = stage_from_config(cfg)
            assert (stage.name, set(stage.train), set(stage.freeze)) == (name, train, freeze)
            assert list(cfg.MODEL.LOSS_TERMS) == terms


# ------------------------------------------------------------ LOT forecasting from frames
SYN_FRAME_STAGES = [CFGS / "synthetic" / "phim_lot_fine" / f for f in
                    ("stage1_score.yaml", "stage2_ssm.yaml", "stage3_finetune.yaml")]  # fmt: skip


def frame_model(path: Path, **overrides):
    """A LOT-from-frames config on a small polar grid (0.8 m x 2pi/192 x 1.5 m to 38.4 m)."""
    small = {"VFE.RANGE_M": [0.0, 38.4], "VFE.GRID_SIZE": [48, 192, 4], **overrides}
    return build(path, **small)


def four_frames(history_seed: int = 1) -> tuple[dict, list[dict]]:
    """A 4-frame batch (current frame of ``make_batch``, 3 previous frames of other points,
    lags 0.1 / 0.2 / 0.3 s) and its frames as single-frame batches, current first."""
    frames = [make_batch(num_point_features=5)] + [
        make_batch(num_point_features=5, seed=history_seed + j, background=500) for j in range(3)
    ]
    points = torch.cat([with_lag(f, 0.1 * j) for j, f in enumerate(frames)])
    return {**frames[0], "points": points}, frames


def test_lot_forecasts_from_the_previous_frames_and_detects_on_the_current_one():
    model, _ = frame_model(SYN_FRAME_STAGES[2], **{"LOT.FILTER_THRESH": 0.0})
    model.eval()
    stages = super(type(model), model).run_stages  # the stages without splitting frames
    batch, frames = four_frames()
    split = model.split_frames(batch)
    assert torch.equal(split["points"], frames[0]["points"])  # the detector's points
    history = split["lot_history"]  # (B, 3, A', R'), oldest first
    for j in (1, 2, 3):
        want = model.lot.current_map(model.vfe(dict(frames[j])))
        torch.testing.assert_close(history[:, 3 - j], want, rtol=0, atol=0)
    # nothing filtered: the history changes only the forecast, never what the detector sees
    alone = stages({**frames[0], "lot_history": history})
    full = model.run_stages(batch)
    assert torch.equal(full["lot_current"], alone["lot_current"])
    assert bool(full["lot_keep"].all())
    for key in ("pred_boxes", "pred_scores"):
        want = model.dense_head.predict(alone["head_outputs"])[0][key]
        torch.testing.assert_close(model.predict(batch)[0][key], want)
    other, _ = four_frames(history_seed=7)
    moved = model.run_stages(other)
    assert torch.equal(moved["lot_current"], full["lot_current"])
    assert not torch.allclose(moved["lot_forecast_logits"], full["lot_forecast_logits"])
    # frames before the sequence start: empty maps, finite forecast
    first = model.run_stages({**frames[0], "points": with_lag(frames[0], 0.0)})
    assert torch.isfinite(first["lot_final"]).all()
    with pytest.raises(ValueError, match=r"t-3\.\.t.*time lag 0\.4"):
        model.split_frames({**frames[0], "points": with_lag(frames[0], 0.4)})


def test_lot_frames_need_the_matching_sequence_config():
    cfg = cfg_from_yaml_file(SYN_FRAME_STAGES[0])
    cfg.DATA_CONFIG.SEQUENCE_CONFIG.SAMPLE_OFFSET = [-2, 0]
    with pytest.raises(ConfigError, match=r"BUFFER_LENGTH 3 .*SAMPLE_OFFSET \[-3, 0\]"):
        build_network_from_config(cfg)
    phim = cfg_from_yaml_file(SYN_PHIM_FINE)
    phim.DATA_CONFIG.SEQUENCE_CONFIG = {"ENABLED": True, "SAMPLE_OFFSET": [-3, 0]}
    with pytest.raises(ConfigError, match="PHiM reads one frame"):
        build_network_from_config(phim)
