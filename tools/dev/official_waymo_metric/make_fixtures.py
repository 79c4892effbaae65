"""Generate seeded test scenes and store the OFFICIAL Waymo metric's outputs on them as fixtures.

Run inside the official venv (see ``setup_venv.sh``), from the repository root:

    .cache/waymo_official_venv/bin/python tools/dev/official_waymo_metric/make_fixtures.py \
        --out tests/evaluation/fixtures/official_waymo_metric.npz

For each scene the fixture holds the raw OpenPCDet-style inputs (``<scene>/gt_*``,
``<scene>/det_*``, ``<scene>/num_frames``) and the official op's outputs for the Hungarian matcher
(``<scene>/hungarian/{ap,aph,pr,pr_h}``) and for the greedy score-first matcher
(``<scene>/score_first/...``), for ``random_mixed`` also with Sign evaluated
(``random_mixed/with_sign/...``); ``breakdown_names`` gives the row order (shard-major, then level).
The tests in ``tests/evaluation/test_waymo_metric.py`` compare pcdet_atlas against these numbers,
so CI needs no TensorFlow. Scenes cover: many frames, all three classes (+ Sign GT that is not
evaluated), L2-only objects (<= 5 points or annotated level 2), zero-point GT, empty frames,
prediction-only and GT-only frames, crowded clusters where Hungarian and greedy differ, IoU ties,
near-threshold IoUs, heading flips and wrap-around, scores exactly on cutoffs, degenerate dims.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from official_eval import WAYMO_CLASSES, run_official  # noqa: E402

VEH, PED, SIGN, CYC = 1, 2, 3, 4
SIZE = {VEH: (4.5, 2.0, 1.7), PED: (0.8, 0.8, 1.8), SIGN: (0.3, 0.6, 0.8), CYC: (1.8, 0.7, 1.7)}


class SceneBuilder:
    """Accumulates GT and predictions frame by frame into flat arrays."""

    def __init__(self):
        self.gt = {k: [] for k in ("frame", "name", "boxes", "num_points", "difficulty")}
        self.det = {k: [] for k in ("frame", "name", "boxes", "score")}
        self.num_frames = 0

    def add_gt(self, frame, name, box, num_points, difficulty=0):
        for key, val in zip(self.gt, (frame, name, box, num_points, difficulty)):
            self.gt[key].append(val)
        self.num_frames = max(self.num_frames, frame + 1)

    def add_det(self, frame, name, box, score):
        for key, val in zip(self.det, (frame, name, box, score)):
            self.det[key].append(val)
        self.num_frames = max(self.num_frames, frame + 1)

    def arrays(self) -> dict:
        out = {"num_frames": np.int64(self.num_frames)}
        for side, store in (("gt", self.gt), ("det", self.det)):
            for key, vals in store.items():
                if key == "boxes":
                    arr = np.array(vals, dtype=np.float32).reshape(-1, 7)
                elif key == "score":
                    arr = np.array(vals, dtype=np.float32)
                else:
                    arr = np.array(vals, dtype=np.int64)
                out[f"{side}_{key}"] = arr
        return out


def _box(rng, cls, x, y, heading=None):
    l, w, h = SIZE[cls]
    scale = rng.uniform(0.85, 1.15, size=3)
    head = rng.uniform(-np.pi, np.pi) if heading is None else heading
    return [
        x,
        y,
        h * scale[2] / 2 + rng.normal(0, 0.1),
        l * scale[0],
        w * scale[1],
        h * scale[2],
        head,
    ]


def _perturb(rng, box, pos=0.15, size=0.06, head=0.1):
    b = np.array(box, dtype=np.float64)
    b[:3] += rng.normal(0, pos, 3) * np.array([1, 1, 0.5])
    b[3:6] *= np.exp(rng.normal(0, size, 3))
    b[6] += rng.normal(0, head)
    return b.tolist()


def _num_points(rng):
    u = rng.uniform()
    if u < 0.1:
        return 0
    if u < 0.3:
        return int(rng.integers(1, 6))  # L2 by the point rule
    return int(rng.integers(6, 2000))


def scene_random_mixed(rng, num_frames=60) -> dict:
    """Many frames, all classes, realistic-ish detector noise, empty and one-sided frames."""
    s = SceneBuilder()
    for f in range(num_frames):
        kind = f % 10
        if kind == 3:  # empty frame
            continue
        n_obj = {VEH: rng.integers(3, 12), PED: rng.integers(0, 8), CYC: rng.integers(0, 3)}
        for cls, n in n_obj.items():
            for _ in range(int(n)):
                x, y = rng.uniform(-70, 70), rng.uniform(-70, 70)
                gt_box = _box(rng, cls, x, y)
                if kind != 5:
                    diff = int(rng.choice([0, 0, 0, 1, 2]))
                    s.add_gt(f, cls, gt_box, _num_points(rng), diff)
                if kind == 7:  # GT only
                    continue
                if rng.uniform() < 0.8:
                    det = _perturb(rng, gt_box)
                    if rng.uniform() < 0.15:
                        det[6] += np.pi  # heading flip
                    label = cls if rng.uniform() < 0.93 else int(rng.choice([VEH, PED, CYC]))
                    s.add_det(f, label, det, float(rng.beta(5, 2)))
                    if rng.uniform() < 0.25:  # duplicate
                        s.add_det(f, cls, _perturb(rng, gt_box, 0.3), float(rng.beta(2, 4)))
        if rng.uniform() < 0.5:  # a sign GT: not an evaluated class
            s.add_gt(f, SIGN, _box(rng, SIGN, rng.uniform(-30, 30), rng.uniform(-30, 30)), 50)
        for _ in range(int(rng.integers(0, 6))):  # false positives
            cls = int(rng.choice([VEH, PED, CYC]))
            s.add_det(f, cls, _box(rng, cls, rng.uniform(-70, 70), rng.uniform(-70, 70)),
                      float(rng.beta(2, 5)))  # fmt: skip
    return s.arrays()


def scene_crowded(rng, num_frames=25) -> dict:
    """Tight clusters with several overlapping predictions: non-trivial matching components."""
    s = SceneBuilder()
    for f in range(num_frames):
        for cls, spacing, n in ((PED, 0.4, 8), (VEH, 2.5, 5), (CYC, 0.8, 4)):
            cx, cy = rng.uniform(-40, 40), rng.uniform(-40, 40)
            heading = rng.uniform(-np.pi, np.pi)
            for i in range(n):
                gt_box = _box(rng, cls, cx + i * spacing * np.cos(heading),
                              cy + i * spacing * np.sin(heading), heading)  # fmt: skip
                s.add_gt(f, cls, gt_box, _num_points(rng) or 40, int(rng.choice([0, 0, 2])))
                for _ in range(int(rng.integers(1, 4))):
                    det = _perturb(rng, gt_box, pos=0.25 if cls == VEH else 0.12)
                    s.add_det(f, cls, det, float(np.round(rng.uniform(0, 1), 2 if i % 2 else 6)))
    return s.arrays()


def scene_near_threshold(rng, num_frames=12) -> dict:
    """Predictions shifted so that IoU is just above / at / below 0.7 (Vehicle) and 0.5."""
    s = SceneBuilder()
    for f in range(num_frames):
        for k, (cls, thr) in enumerate(((VEH, 0.7), (PED, 0.5), (CYC, 0.5))):
            for j, rel in enumerate((-1e-4, -1e-6, 0.0, 1e-6, 1e-4, 2e-3)):
                x, y = -60 + 20 * k + 3 * j, -60 + 9 * f
                l, w, h = SIZE[cls]
                heading = float(rng.uniform(-np.pi, np.pi))
                gt_box = [x, y, h / 2, l, w, h, heading]
                t = thr + rel
                d = l * (1 - t) / (1 + t)  # shift along the box's length: IoU = (l-d)/(l+d)
                det = [x + d * np.cos(heading), y + d * np.sin(heading), h / 2, l, w, h, heading]
                s.add_gt(f, cls, gt_box, 100, 0)
                s.add_det(f, cls, det, float(rng.uniform(0.05, 1.0)))
    return s.arrays()


def scene_ties_and_headings(rng, num_frames=10) -> dict:
    """IoU ties (one prediction between two GTs, identical duplicate predictions), heading flips
    and wrap-around at +-pi, scores exactly on cutoffs and equal scores, degenerate boxes."""
    s = SceneBuilder()
    on_cutoffs = [0.0, 0.01, 0.5, 0.7, 0.99, 1.0]
    for f in range(num_frames):
        base_y = -40 + 8 * f
        # one prediction exactly between two identical-heading GTs: equal IoU with both
        g1 = [0.0, base_y, 0.85, 4.0, 2.0, 1.7, 0.0]
        g2 = [1.0, base_y, 0.85, 4.0, 2.0, 1.7, 0.0]
        s.add_gt(f, VEH, g1, 100, 0)
        s.add_gt(f, VEH, g2, 100, 0)
        s.add_det(f, VEH, [0.5, base_y, 0.85, 4.0, 2.0, 1.7, 0.0], on_cutoffs[f % 6])
        # one GT, two identical predictions with equal or different scores
        g3 = [20.0, base_y, 0.9, 0.8, 0.8, 1.8, 1.0]
        s.add_gt(f, PED, g3, 3 + f, 0)  # L2 by points for small f
        s.add_det(f, PED, list(g3), 0.6)
        s.add_det(f, PED, list(g3), 0.6 if f % 2 else 0.3)
        # heading flips / wrap-around on cyclists: HA differs, IoU identical
        g4 = [40.0, base_y, 0.85, 1.8, 0.7, 1.7, np.pi - 1e-3]
        s.add_gt(f, CYC, g4, 30, 0)
        flip = [0.0, np.pi, -2 * np.pi + 1e-3, np.pi / 2, 2 * np.pi, -np.pi][f % 6]
        s.add_det(f, CYC, g4[:6] + [g4[6] + flip], 0.8)
        # annotated level 2 with many points; level 1 with few points (annotator wins)
        s.add_gt(f, VEH, [60.0, base_y, 0.85, 4.5, 2.0, 1.7, 0.2], 500, 2)
        s.add_gt(f, VEH, [70.0, base_y, 0.85, 4.5, 2.0, 1.7, 0.2], 2, 1)
        s.add_det(f, VEH, [70.2, base_y, 0.85, 4.5, 2.0, 1.7, 0.2], 0.42)
        # degenerate predictions / GT: IoU forced to 0 by the official dims rule
        s.add_gt(f, PED, [-20.0, base_y, 0.9, 0.005, 0.8, 1.8, 0.0], 50, 0)
        s.add_det(f, PED, [-20.0, base_y, 0.9, 0.005, 0.8, 1.8, 0.0], 0.9)
        # zero-point GT with a perfect prediction: GT dropped, prediction is FP
        s.add_gt(f, VEH, [-40.0, base_y, 0.85, 4.5, 2.0, 1.7, 0.0], 0, 0)
        s.add_det(f, VEH, [-40.0, base_y, 0.85, 4.5, 2.0, 1.7, 0.0], 0.95)
    return s.arrays()


def scene_logits(rng, num_frames=8) -> dict:
    """Scores above 1 (logits): OpenPCDet applies a sigmoid before the official op."""
    s = SceneBuilder()
    for f in range(num_frames):
        for _ in range(6):
            cls = int(rng.choice([VEH, PED, CYC]))
            gt_box = _box(rng, cls, rng.uniform(-50, 50), rng.uniform(-50, 50))
            s.add_gt(f, cls, gt_box, _num_points(rng) or 20, 0)
            s.add_det(f, cls, _perturb(rng, gt_box), float(rng.normal(0, 3)))
    s.add_det(0, VEH, [0, 0, 1, 4, 2, 1.5, 0], 5.0)
    return s.arrays()


def scene_hungarian_vs_greedy(rng, num_frames=10) -> dict:
    """Chains where greedy score-first matching loses a TP that the Hungarian matching keeps: a
    high-score prediction between two GTs and a low-score one overlapping only the first GT."""
    s = SceneBuilder()
    for f in range(num_frames):
        for k in range(6):
            cls = (PED, CYC, VEH)[k % 3]
            thr = 0.7 if cls == VEH else 0.5
            l, w, h = SIZE[cls]
            x0, y0 = -50 + 15 * k, -45 + 9 * f
            d_max = l * (1 - thr) / (1 + thr)  # largest shift along x keeping IoU >= thr
            gap = d_max * rng.uniform(1.2, 1.9)  # GT A at 0, GT B at gap
            p1 = gap / 2 + rng.uniform(-0.1, 0.1) * (d_max - gap / 2)  # matches both
            s.add_gt(f, cls, [x0, y0, h / 2, l, w, h, 0.0], 100, 0)
            s.add_gt(f, cls, [x0 + gap, y0, h / 2, l, w, h, 0.0], 100, int(rng.choice([0, 2])))
            s.add_det(f, cls, [x0 + p1, y0, h / 2, l, w, h, 0.05], float(rng.uniform(0.5, 1.0)))
            p2 = -rng.uniform(0.0, 0.5) * d_max  # overlaps only A
            s.add_det(f, cls, [x0 + p2, y0, h / 2, l, w, h, -0.1], float(rng.uniform(0.0, 0.7)))
    return s.arrays()


def scene_only_predictions(rng) -> dict:
    s = SceneBuilder()
    for f in range(4):
        for _ in range(5):
            cls = int(rng.choice([VEH, PED, CYC]))
            s.add_det(f, cls, _box(rng, cls, rng.uniform(-50, 50), rng.uniform(-50, 50)),
                      float(rng.uniform()))  # fmt: skip
    return s.arrays()


def scene_only_gt(rng) -> dict:
    s = SceneBuilder()
    for f in range(4):
        for _ in range(5):
            cls = int(rng.choice([VEH, PED, CYC]))
            s.add_gt(f, cls, _box(rng, cls, rng.uniform(-50, 50), rng.uniform(-50, 50)),
                     _num_points(rng), 0)  # fmt: skip
    return s.arrays()


def scene_single_class(rng) -> dict:
    """Only vehicles: pedestrian and cyclist shards are empty (AP 0 for them)."""
    s = SceneBuilder()
    for f in range(6):
        for _ in range(8):
            gt_box = _box(rng, VEH, rng.uniform(-50, 50), rng.uniform(-50, 50))
            s.add_gt(f, VEH, gt_box, _num_points(rng) or 9, 0)
            s.add_det(f, VEH, _perturb(rng, gt_box, 0.12), float(rng.uniform()))
    return s.arrays()


SCENES = {
    "random_mixed": scene_random_mixed,
    "crowded": scene_crowded,
    "near_threshold": scene_near_threshold,
    "ties_and_headings": scene_ties_and_headings,
    "logits": scene_logits,
    "hungarian_vs_greedy": scene_hungarian_vs_greedy,
    "only_predictions": scene_only_predictions,
    "only_gt": scene_only_gt,
    "single_class": scene_single_class,
}


def main() -> None:
    parser = argparse.ArgumentParser(description="official Waymo metric fixtures")
    parser.add_argument("--out", default="tests/evaluation/fixtures/official_waymo_metric.npz")
    parser.add_argument("--seed", type=int, default=20241121)
    args = parser.parse_args()
    store: dict[str, np.ndarray] = {}
    summary = {}
    for i, (name, make) in enumerate(SCENES.items()):
        rng = np.random.default_rng([args.seed, i])
        scene = make(rng)
        for key, val in scene.items():
            store[f"{name}/{key}"] = val
        summary[name] = {
            "num_gt": int(len(scene["gt_frame"])),
            "num_det": int(len(scene["det_frame"])),
        }
        for matcher in ("hungarian", "score_first"):
            res = run_official(scene, matcher)
            store["breakdown_names"] = res["names"].astype(str)
            for key in ("ap", "aph", "pr", "pr_h"):
                store[f"{name}/{matcher}/{key}"] = res[key]
            summary[name][matcher] = {
                str(n): [round(float(a), 6), round(float(h), 6)]
                for n, a, h in zip(res["names"], res["ap"], res["aph"])
            }
        if name == "random_mixed":  # Sign GT evaluated too (OpenPCDet class_names incl. Sign)
            res = run_official(
                scene, "hungarian", class_names=["Vehicle", "Pedestrian", "Sign", "Cyclist"]
            )
            for key in ("ap", "aph", "pr", "pr_h"):
                store[f"{name}/with_sign/{key}"] = res[key]
    store["waymo_classes"] = np.array(WAYMO_CLASSES)
    np.savez_compressed(args.out, **store)
    with open(os.path.splitext(args.out)[0] + ".json", "w") as fh:
        json.dump({"seed": args.seed, "package": "waymo-open-dataset-tf-2-12-0==1.6.7",
                   "scenes": summary}, fh, indent=1, sort_keys=True)  # fmt: skip
    print(json.dumps({k: {m: v[m] for m in ("hungarian",)} for k, v in summary.items()}, indent=1))


if __name__ == "__main__":
    main()
