"""Tiny synthetic batches and device params for the model tests (imported as `model_batches`)."""

from __future__ import annotations

import numpy as np
import torch

from pcdet_atlas.utils.common import load_tool  # noqa: F401  (the tests' import)

# (x, y, z, dx, dy, dz, heading, vx, vy, cls) per sample: cars, a pedestrian, a cyclist
BOXES = [
    [
        [10.0, 4.0, 0.8, 4.6, 2.0, 1.6, 0.3, 3.0, 0.5, 1],
        [-12.0, -6.0, 0.9, 0.8, 0.8, 1.8, 0.0, 0.0, 1.0, 2],
        [5.0, -15.0, 0.8, 1.8, 0.7, 1.7, 1.2, -2.0, 0.0, 3],
    ],
    [[-8.0, 12.0, 1.0, 5.0, 2.2, 2.0, -2.0, 0.0, 0.0, 1]],
]


def make_batch(
    num_point_features: int = 5,
    with_velocity: bool = False,
    points_per_box: int = 200,
    background: int = 2000,
    extent: float = 20.0,
    scale: float = 1.0,
    seed: int = 0,
    device: str = "cpu",
) -> dict:
    """A collated batch of 2 samples: points inside each box plus uniform background.

    Box centres are multiplied by ``scale`` (to fit a small grid). ``points`` (N, 1 + C)
    ``[b, x, y, z, intensity, elongation, (time)]``; ``gt_boxes`` (2, 3, 8|10) padded with zero
    rows; ``batch_size`` 2.
    """
    g = torch.Generator().manual_seed(seed)
    pts, gts = [], []
    for b, boxes in enumerate(BOXES):
        rows = []
        boxes = [[box[0] * scale, box[1] * scale, *box[2:]] for box in boxes]
        for box in boxes:
            box_t = torch.tensor(box[:7])
            local = (torch.rand(points_per_box, 3, generator=g) - 0.5) * box_t[3:6]
            c, s = torch.cos(box_t[6]), torch.sin(box_t[6])
            xy = torch.stack(
                [local[:, 0] * c - local[:, 1] * s, local[:, 0] * s + local[:, 1] * c], 1
            )
            rows.append(torch.cat([xy + box_t[:2], local[:, 2:3] + box_t[2]], 1))
        bg = (torch.rand(background, 3, generator=g) - 0.5) * torch.tensor([2 * extent] * 2 + [4])
        xyz = torch.cat(rows + [bg])
        feats = torch.rand(xyz.shape[0], num_point_features - 3, generator=g)
        if num_point_features >= 6:  # time lag column in {0, .1, .2, .3}
            feats[:, 2] = torch.randint(0, 4, (xyz.shape[0],), generator=g).float() * 0.1
        pts.append(torch.cat([torch.full((xyz.shape[0], 1), float(b)), xyz, feats], 1))
        g_rows = torch.tensor(boxes)
        if not with_velocity:
            g_rows = torch.cat([g_rows[:, :7], g_rows[:, 9:]], 1)
        gts.append(g_rows)
    gt = torch.zeros(2, 3, gts[0].shape[1])
    for b, rows in enumerate(gts):
        gt[b, : rows.shape[0]] = rows
    return {
        "points": torch.cat(pts).to(device),
        "gt_boxes": gt.to(device),
        "batch_size": 2,
    }


def two_stage_batch(num_frames: int) -> dict:
    """The model tests' two-sample batch with 6 point columns, its boxes as jittered proposals
    (plus one far false positive) and a frame seed per sample."""
    batch = make_batch(num_point_features=6, with_velocity=True)
    rois = []
    for b in range(2):
        gt = batch["gt_boxes"][b]
        gt = gt[gt[:, 3] > 0]
        jitter = gt[:, :9].clone()
        jitter[:, 0] += 0.3
        far = torch.tensor([[30.0, 30.0, 1.0, 4.0, 2.0, 1.5, 0.0, 0.0, 0.0]])
        boxes = torch.cat([jitter, far])
        rows = torch.cat(
            [boxes, torch.full((len(boxes), 1), 0.8), torch.cat([gt[:, -1:], torch.ones(1, 1)])], 1
        )
        rois.append(rows)
    padded = torch.zeros(2, max(len(r) for r in rois), 11)
    for b, r in enumerate(rois):
        padded[b, : len(r)] = r
    batch["roi_boxes"] = padded
    batch["frame_seed"] = np.array([11, 12])
    if num_frames > 4:  # older frames: copies of the first points with larger lags
        extra = batch["points"][::3].clone()
        extra[:, -1] = 0.6
        batch["points"] = torch.cat([batch["points"], extra])
    return batch


def assert_same(a, b, where: str) -> None:
    """Bitwise equality of nested dicts / lists / arrays / scalars (dtypes included)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        assert type(a) is type(b) and (a == b or (a != a and b != b)), where


def assert_annos_equal(got: list[dict], want: list[dict]) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert_same(a, b, str(a["frame_id"]))
