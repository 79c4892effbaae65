"""PTT: every PTT config builds and trains (smoke), the head masks the frames before the sequence
start and reads the others, the dataset serves the proposal history moved with the boxes, the
proposal bank computes each frame once and bitwise as recomputing it, and a spoofed history
frame's phantom reaches PTT's input while the current frame is clean (the paper's Finding 3)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from device_params import DEVICES
from model_batches import two_stage_batch

from pcdet_atlas.attacks import AtlasWaymoDataset
from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.datasets.dataset import collate_batch
from pcdet_atlas.datasets.proposal_history import gather_history, history_to_current
from pcdet_atlas.models import build_network_from_config, load_data_to_device
from pcdet_atlas.models.detectors import PTT
from pcdet_atlas.ops.iou3d_nms import boxes_iou_bev
from pcdet_atlas.train_utils.proposal_bank import ProposalBank, proposal_rows

CFGS = REPO_ROOT / "cfgs" / "atlas"
PTT_CONFIGS = sorted(p for p in CFGS.rglob("*.yaml") if cfg_from_yaml_file(p).MODEL.NAME == "PTT")
CPU = torch.device("cpu")


def test_ptt_configs_exist():
    assert {str(p.relative_to(CFGS)) for p in PTT_CONFIGS} == {
        "ptt_32f.yaml",
        "synthetic/ptt_32f.yaml",
    }


def with_history(batch: dict, counts=(3, 0)) -> dict:
    """``two_stage_batch`` plus a proposal history: each sample's proposals moved back by their
    velocity, ``counts[b]`` frames of it (0: the first frame of its sequence)."""
    rows = []
    for b, count in enumerate(counts):
        cur = batch["roi_boxes"][b]
        cur = cur[cur[:, 10] > 0]
        parts = []
        for back in range(1, count + 1):
            moved = cur.clone()
            moved[:, 0:2] -= 0.1 * back * moved[:, 7:9]
            parts.append(torch.cat([moved, torch.full((len(moved), 1), float(back))], 1))
        rows.append(torch.cat(parts) if parts else torch.zeros(0, 12))
    padded = torch.zeros(len(counts), max(1, max(len(r) for r in rows)), 12)
    for b, r in enumerate(rows):
        padded[b, : len(r)] = r
    return {**batch, "roi_history": padded, "roi_history_frames": torch.tensor(counts)}


def synthetic_ptt() -> PTT:
    torch.manual_seed(0)
    return build_network_from_config(cfg_from_yaml_file(CFGS / "synthetic" / "ptt_32f.yaml"))


@pytest.mark.parametrize("path", PTT_CONFIGS, ids=lambda p: str(p.relative_to(CFGS)))
def test_build_train_predict(path, real_rpn_checkpoint):
    cfg = cfg_from_yaml_file(path)
    if "synthetic" not in path.parts:  # a random RPN, fewer ROIs and points (no GPU here)
        cfg.MODEL.RPN.CHECKPOINT = str(real_rpn_checkpoint)
        cfg.MODEL.ROI_HEAD.TARGET_CONFIG.ROI_PER_IMAGE = 8
        cfg.MODEL.ROI_HEAD.SAMPLER.NUM_POINTS = 16
    model = build_network_from_config(cfg)
    assert isinstance(model, PTT)
    assert model.proposal_history + 1 == cfg.ATLAS.TEMPORAL_WINDOW == 32  # lifecycle k 0..64
    assert model.rpn_info["window"] == 4
    batch = with_history(two_stage_batch(4))
    model.train()
    ret, tb, _ = model(batch)
    assert {"loss", "rcnn_loss_cls", "rcnn_loss_reg", "rcnn_loss_traj", "rcnn_loss_corner"} <= set(
        tb
    )
    ret["loss"].backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    model.eval()
    preds, _ = model(batch)
    assert len(preds) == 2
    for b, p in enumerate(preds):
        assert p["pred_boxes"].shape[1] == 7 and torch.isfinite(p["pred_boxes"]).all()
        assert len(p["rois"]) == int((batch["roi_boxes"][b, :, 10] > 0).sum())


def test_predict_without_a_proposal_history_says_where_it_comes_from():
    model = synthetic_ptt().eval()
    with pytest.raises(KeyError, match="roi_history.*ProposalBank"):
        model.predict(two_stage_batch(4))


def head_outputs(model: PTT, batch: dict) -> torch.Tensor:
    model.eval()
    with torch.no_grad():
        rois, valid = batch["roi_boxes"][..., :9], batch["roi_boxes"][..., 10] > 0
        histories = model.histories(batch)
        traj, ok = zip(*(model.roi_head.trajectories(rois[b], histories[b]) for b in range(2)))
        out = model.roi_head({
            **batch, "roi_valid": valid, "trajectories": torch.stack(traj),
            "trajectory_valid": torch.stack(ok) & valid[:, None],
            "generators": model.sample_generators(batch, "ptt_points"),
        })  # fmt: skip
    return torch.cat([out["rcnn_reg"], out["rcnn_cls"][0][..., None]], -1)


def test_the_head_masks_frames_before_the_sequence_start_and_reads_the_others():
    model = synthetic_ptt()
    base = with_history(two_stage_batch(4), counts=(3, 3))
    ref = head_outputs(model, base)
    # frames 4..31 of both samples are padding: their boxes continue the prediction; moving
    # the history's existing frames changes the output, the padding frames cannot be moved
    moved = copy.deepcopy(base)
    moved["roi_history"][0, :, 1] += (moved["roi_history"][0, :, 11] == 3) * 0.4
    out = head_outputs(model, moved)
    assert not torch.allclose(out[0], ref[0])  # frame t-3 is read
    assert torch.equal(out[1], ref[1])  # the other sample is independent of it
    # one frame fewer (t-3 now before the sequence start): its boxes stop counting
    shorter = copy.deepcopy(base)
    shorter["roi_history_frames"] = torch.tensor([2, 3])
    masked = head_outputs(model, shorter)
    shorter["roi_history"][0, :, 1] += (shorter["roi_history"][0, :, 11] == 3) * 0.4
    assert torch.equal(head_outputs(model, shorter), masked)
    assert not torch.allclose(masked[0], ref[0])


@pytest.mark.parametrize("device", DEVICES[1:])
def test_the_head_computes_on_cuda_what_it_computes_on_the_cpu(device):
    """The same batch and proposal history on both devices (the sampler's keys and the
    association run on each; the keys are drawn on the CPU): outputs agree to float32
    rounding."""
    model = synthetic_ptt()
    batch = with_history(two_stage_batch(4), counts=(3, 3))
    ref = head_outputs(model, batch)
    out = head_outputs(model.to(device), load_data_to_device(batch, device)).cpu()
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=1e-4)


def test_the_dataset_serves_the_history_moved_with_the_boxes(synthetic_root):
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "ptt_32f.yaml")
    cfg.DATA_CONFIG.DATA_PATH = str(synthetic_root)
    dataset, _, _ = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, 1, False, workers=0, training=True
    )
    index = 7
    info = dataset.infos[index]
    seq = dataset.seq_name_to_infos[info["point_cloud"]["lidar_sequence"]]
    t = int(info["point_cloud"]["sample_idx"])
    anno = dataset.get_annotations(info)
    names = list(cfg.CLASS_NAMES)
    labels = np.array([names.index(n) + 1 if n in names else 0 for n in anno["gt_names"]], float)
    gt_t = anno["gt_boxes"][:, :9]

    def rows(boxes):
        return np.concatenate([boxes, np.full((len(boxes), 1), 0.9), labels[:, None]], 1).astype(
            np.float32
        )

    # every frame's proposals: frame t's ground truth as seen from that frame, so frame t's
    # whole history, moved back into frame t, lands on its ground truth
    table = {s["frame_id"]: np.zeros((0, 11), np.float32) for s in dataset.all_infos}
    table.update(
        {s["frame_id"]: rows(history_to_current(gt_t, info["pose"], s["pose"])) for s in seq}
    )
    dataset.set_proposals(table, "table.pkl", history=31)
    sample = dataset[index]
    assert int(sample["roi_history_frames"]) == t  # frames t-1 .. 0; older ones do not exist
    hist = sample["roi_history"]
    assert sorted(set(hist[:, 11].astype(int))) == list(range(1, t + 1))
    assert sample["flip_x"] or sample["flip_y"] or abs(sample["noise_rot"]) > 0
    for back in range(1, t + 1):  # moved by the augmentation exactly as the boxes
        frame = hist[hist[:, 11] == back]
        for box in sample["gt_boxes"]:
            assert np.abs(frame[:, :9] - box[:9]).max(1).min() < 1e-3
    batch = collate_batch([sample, dataset[0]])
    assert batch["roi_history"].shape[2] == 12 and batch["roi_history_frames"].tolist() == [t, 0]
    with pytest.raises(KeyError, match="no proposals for"):
        dataset.set_proposals({info["frame_id"]: table[info["frame_id"]]}, "t.pkl", history=31)


@pytest.fixture(scope="module")
def val_cfg(synthetic_root):
    cfg = cfg_from_yaml_file(CFGS / "synthetic" / "ptt_32f.yaml")
    data_cfg = copy.deepcopy(cfg.DATA_CONFIG)
    data_cfg.DATA_PATH = str(synthetic_root)
    return cfg, data_cfg


def test_the_bank_computes_each_frame_once_and_as_recomputing_it(val_cfg):
    cfg, data_cfg = val_cfg
    clean = AtlasWaymoDataset(
        data_cfg, cfg.CLASS_NAMES, REPO_ROOT / "cfgs" / "attacks" / "clean.yaml", training=False
    )
    model = synthetic_ptt().eval()
    bank = ProposalBank(model, clean, device=CPU, num_history=4)
    for index in (5, 6, 7, 9):  # in order, one skipped frame (8)
        sample = clean[index]
        batch = collate_batch([sample])
        out = bank.attach(batch, load_data_to_device(batch, CPU))
        assert int(out["roi_history_frames"][0]) == 4
    # frames 1..9 were needed, each computed once: the current ones from the batch itself,
    # the history before the first and the skipped frame 8 from the dataset
    assert bank.stats()["rpn_frames"] == 9
    seq = sample["sequence_name"]
    for k in (1, 7, 8):
        again = clean.frame_sample(seq, k)
        fresh = proposal_rows(model.propose(load_data_to_device(collate_batch([again]), CPU))[0])
        np.testing.assert_array_equal(bank.frame(seq, k), fresh)
    assert bank.stats()["rpn_frames"] == 9  # those were hits
    infos = clean.seq_name_to_infos[seq]
    rows, count = gather_history(
        lambda k: bank.frame(seq, k), lambda k: np.asarray(infos[k]["pose"]), 9, 4
    )
    got = out["roi_history"][0]
    got = got[got[:, 10] > 0].numpy()
    np.testing.assert_array_equal(got, rows.astype(np.float32))
    np.testing.assert_array_equal(
        out["roi_boxes"][0][: len(bank.frame(seq, 9))].numpy(), bank.frame(seq, 9)
    )
    with pytest.raises(ValueError, match=r"capacity 63 is below 2 \* \(num_history \+ 1\) = 64"):
        ProposalBank(model, clean, device=CPU, num_history=31, capacity=63)


def test_the_smallest_bank_still_computes_each_frame_once(val_cfg):
    """At its smallest capacity (twice a window) the bank drops only frames no later window
    reads: a pass over frames 5..16 with 4 frames of history computes frames 1..16 once each
    (a bank of one window, 5 frames, drops frame t as window t + 1 inserts itself)."""
    cfg, data_cfg = val_cfg
    clean = AtlasWaymoDataset(
        data_cfg, cfg.CLASS_NAMES, REPO_ROOT / "cfgs" / "attacks" / "clean.yaml", training=False
    )
    bank = ProposalBank(synthetic_ptt().eval(), clean, device=CPU, num_history=4, capacity=10)
    for index in range(5, 17):
        batch = collate_batch([clean[index]])
        bank.attach(batch, load_data_to_device(batch, CPU))
    assert bank.stats()["rpn_frames"] == 16 and bank.stats()["frames_held"] == 10


def test_a_spoofed_history_reaches_ptt_while_the_current_frame_is_clean(val_cfg, injection):
    """Frame 68 and its 4-frame RPN input (65..68) are clean, 27 of its 31 previous frames belong
    to the spoof run 32..63: the phantom the RPN proposed on those frames is in frame 68's
    proposal history (moved into frame 68), not in its current proposals, and not in the clean
    variant's history."""
    cfg, data_cfg = val_cfg
    attacked = AtlasWaymoDataset(data_cfg, cfg.CLASS_NAMES, injection, training=False)
    clean = AtlasWaymoDataset(
        data_cfg, cfg.CLASS_NAMES, REPO_ROOT / "cfgs" / "attacks" / "clean.yaml", training=False
    )
    model = synthetic_ptt().eval()
    bank, clean_bank = (ProposalBank(model, d, device=CPU) for d in (attacked, clean))
    index = 68
    sample = attacked[index]
    assert not sample["attack"]["spoofed"]
    batch = collate_batch([sample])
    out = bank.attach(batch, load_data_to_device(batch, CPU))
    assert bank.stats()["rpn_frames"] == 32  # frames 37..68, each once
    seq, infos = sample["sequence_name"], attacked.seq_name_to_infos[sample["sequence_name"]]
    hist = out["roi_history"][0]
    found = []
    for back in (8, 16, 24):
        meta = attacked.frame_attack_meta(seq, index - back)
        assert meta["spoofed"]
        phantom = history_to_current(
            meta["target_box"][None, :9].astype(np.float64), infos[index - back]["pose"],
            infos[index]["pose"],
        )  # fmt: skip
        phantom = torch.from_numpy(phantom).float()
        rows = hist[(hist[:, 11] == back) & (hist[:, 10] > 0)]
        iou = boxes_iou_bev(rows[:, :7], phantom[:, :7]).amax() if len(rows) else 0.0
        clean_rows = clean_bank.frame(seq, index - back)
        clean_iou = boxes_iou_bev(
            torch.from_numpy(history_to_current(clean_rows[:, :9], infos[index - back]["pose"],
                                                infos[index]["pose"]))[:, :7],
            phantom[:, :7],
        ).amax() if len(clean_rows) else 0.0  # fmt: skip
        assert float(clean_iou) < 0.1  # the clean run never saw it
        found.append(float(iou) > 0.3)
        current = out["roi_boxes"][0]
        current = current[current[:, 10] > 0]
        assert float(boxes_iou_bev(current[:, :7], phantom[:, :7]).amax()) < 0.3
    assert sum(found) >= 2
    preds = model.predict(out)  # PTT reads this input: the contaminated history
    assert torch.isfinite(preds[0]["pred_boxes"]).all()
