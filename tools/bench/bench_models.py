"""Per-frame latency and peak memory of each detector, beside its synthetic L2 mAP.

    python tools/bench/bench_models.py                      # every config in cfgs/atlas/, CPU
    python tools/bench/bench_models.py --cfgs cfgs/atlas/synthetic/cp4f.yaml --frames 10 \
        --device cuda

Frames come from the synthetic dataset (``--data_path``, default ``data/synthetic_waymo``; a tiny
one is generated in a temporary folder if it is missing) through each config's own
``WaymoDataset`` pipeline (test mode, 1 to 8 frames), so the models see realistic clouds. Every
model runs ``predict`` on the same frames, batch size 1, after one warm-up frame; the models take
turns frame by frame so that machine load hits them alike. The frames start where no model's
input is padded at the sequence start (frame 3 with a 4-frame input, 7 with MSF-8f's, 31 with
PTT's proposal history), so that a multi-frame model reads as many points as it will mid-run.
Latency covers voxelization to NMS (not data loading); for a two-stage model (MSF, PTT) it is
split into the RPN's proposals and the second stage, and its parameter count is the second
stage's (the RPN's is its CP-4f row); a two-stage config whose RPN checkpoint is missing (the
real-Waymo ones) is listed as not built. PTT is timed with the proposal bank holding the
previous frames: its RPN column is the bank's one RPN pass for the new frame (plus reading the
history), and the bank's memory is printed below the table.
Peak memory of one ``predict`` (PTT's including its RPN pass into the bank) is measured in a
fresh process per model (so no model reuses memory another freed): CUDA
``max_memory_allocated``, or on CPU the rise of the process's peak resident set (``VmHWM``,
reset through ``/proc/self/clear_refs``).
With ``--eval``, a model whose ``ATLAS.CHECKPOINT`` exists is evaluated (Waymo L2 mAP) on the
val split of ``--data_path``; without a checkpoint the model runs with random weights and the
column says so ("checkpoint missing", or "no checkpoint" for configs without
``ATLAS.CHECKPOINT``, the real-Waymo ones).

``--bank_cfg`` (a PTT config) also times the evaluation of the first ``--bank_frames`` frames of
a val sequence under ``--bank_variant`` with the proposal bank (one RPN pass per frame) against
recomputing every window's 32 frames:

    python tools/bench/bench_models.py --cfgs --bank_cfg cfgs/atlas/synthetic/ptt_32f.yaml

``--vfe_forms`` times the VFE of each ``--cfgs`` config (random weights with BatchNorm
statistics from a few training-mode passes, or its checkpoint) in its two eval forms on the same
frames, alternating: the folded form ``DynamicPillarVFE`` uses in eval mode and the layer-by-layer
one (``fold_eval = False``), with the largest difference of their outputs:

    python tools/bench/bench_models.py --vfe_forms --cfgs cfgs/atlas/synthetic/cp4f.yaml --frames 8

For a model with a LOT stage (PHiM+LOT), the time LOT takes inside its frames is printed below
the table. ``--ssm`` times :func:`~pcdet_atlas.models.ssm.selective_scan` (chunked) against the
plain sequential loop (``selective_scan_reference``) on the same inputs, forward and forward +
backward, at ``--ssm_lengths`` steps (b 2, d 64, n 16, Mamba's sizes), alternating:

    python tools/bench/bench_models.py --cfgs --ssm --threads 1

``--spconv CFG`` times each sparse conv layer of a voxel config's 3D backbone (random weights) on
val frame ``--spconv_frame``: building its index pairs, its gather-GEMM-reduce forward and
forward + backward, beside ``conv3d`` with the same weights on the dense grid and, when spconv
2.x is importable (``pip install -e .[bench]``), beside spconv's layer with the same weights
(forward with its rules, forward + backward; both sides alternating), then the whole backbone.
``--spconv_layers`` keeps the named layers only; the aten ops of one forward and of one forward +
backward (counted by ``torch.profiler``) are printed per layer:

    python tools/bench/bench_models.py --cfgs --spconv cfgs/atlas/synthetic/cp4f_voxel.yaml \
        --frames 3

``--train_step`` instead times training steps (batch ``--batch_size``, the configs' own train
pipeline with GT sampling and augmentation, AdamW + one-cycle, gradient clipping: what
``tools/train.py`` does per iteration) of each ``--train_cfgs`` config, in a fresh process per
config and round: seconds per step of the model (forward, loss, backward, clip, optimizer) and of
the whole step with data loading (``--workers``). ``--baseline_src DIR`` runs the same on an older
source tree (``git archive <commit> pcdet_atlas cfgs | tar -x -C DIR``) in alternating
processes and prints both side by side, with the losses of both trees on the same batches;
``--default_malloc`` adds a row of this tree without ``retain_freed_cpu_memory`` (which
``tools/train.py`` applies on CPU). Needs a dataset with its GT databases (``--data_path``):

    python tools/bench/bench_models.py --train_step --baseline_src /tmp/old --rounds 2 --steps 4

``--baseline_src DIR`` without ``--train_step`` times the latency and peak memory of each
``--cfgs`` config in the older tree and in this one, ``--rounds`` alternating processes each,
and says whether both trees' predictions on the timed frames are bitwise equal; the older tree
needs the same checkpoints (``git archive <commit> pcdet_atlas cfgs checkpoints | tar -x -C DIR``):

    python tools/bench/bench_models.py --cfgs cfgs/atlas/synthetic/msf_8f.yaml \
        --baseline_src /tmp/old

For a two-stage model that table also counts the aten operators its second stage calls per frame
(``torch.profiler`` on the CPU, in an untimed pass over the same frames; each is one dispatch: a
kernel launch on a GPU, or a view), and for PTT the time and operators of its association
(``roi_head.trajectories``) inside that stage.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from pcdet_atlas.config import REPO_ROOT, cfg_from_yaml_file, resolve_cli_path
from pcdet_atlas.datasets import build_dataloader
from pcdet_atlas.models import build_network_from_config, load_data_to_device
from pcdet_atlas.models.detectors import PTT, TwoStageDetector
from pcdet_atlas.registry import DETECTORS
from pcdet_atlas.train_utils import eval_one_epoch
from pcdet_atlas.train_utils.atlas_eval import atlas_section, point_history, trained_checkpoint
from pcdet_atlas.train_utils.proposal_bank import ProposalBank
from pcdet_atlas.train_utils.setup import device_arg
from pcdet_atlas.utils.cli import add_debug_flag, baseline_tree_env, run_tool


def _read_hwm_kib() -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _reset_hwm() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _peak_memory_mib(
    cfg_file: str, data_path: str, device: str, trained: bool, start: int
) -> float:
    """Peak memory of one ``predict`` on val frame ``start`` in a fresh process (MiB). PTT: the
    bank holds the previous frames' proposals, and the frame's RPN pass into the bank counts, as
    a two-stage ``predict`` counts its RPN (and as the latency column does).

    CUDA: ``max_memory_allocated`` above what model and batch hold. CPU: rise of the process's
    peak resident set (``VmHWM``, reset just before) above its resident set before the call.
    """
    cfg = cfg_from_yaml_file(cfg_file)
    dev = torch.device(device)
    cfg, batches, dataset = _config_frames(cfg_file, Path(data_path), 1, dev, start)
    batch = batches[0]
    torch.manual_seed(0)
    model = build_network_from_config(cfg).to(dev).eval()
    if trained:
        model.load_params_from_file(REPO_ROOT / cfg.ATLAS.CHECKPOINT)
    bank = _warm_bank(model, dataset, batch, dev) if _reads_proposal_history(cfg) else None

    def run():
        model.predict(batch if bank is None else bank.attach(batch, batch))

    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
        torch.cuda.reset_peak_memory_stats(dev)
        base = torch.cuda.memory_allocated(dev)
        run()
        return (torch.cuda.max_memory_allocated(dev) - base) / 2**20
    base, ok = _rss_kib(), _reset_hwm()
    run()
    hwm = _read_hwm_kib()
    return (hwm - base) / 1024 if ok and hwm is not None else float("nan")


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(p)
    p.add_argument(
        "--cfgs", nargs="*", default=None, help="model configs (default: all; none: skip)"
    )
    p.add_argument(
        "--data_path",
        default=str(REPO_ROOT / "data" / "synthetic_waymo"),
        help="dataset root (default: the demo dataset)",
    )
    p.add_argument("--frames", type=int, default=5, help="timed frames per model")
    p.add_argument(
        "--device", type=device_arg, default="cpu", help="cpu / cuda / cuda:N (default: cpu)"
    )
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument(
        "--json", default=None, metavar="FILE",
        help="also write the latency table's per-frame costs here (tools/bench/cost_model.py)",
    )  # fmt: skip
    p.add_argument("--eval", action="store_true", help="L2 mAP of trained models on the val split")
    p.add_argument(
        "--share_cfg", default=None,
        help="also time a tools/test.py step of this model config on clean / injection / removal",
    )  # fmt: skip
    p.add_argument("--share_frames", type=int, default=8, help="frames from 32 on (a spoofed run)")
    p.add_argument(
        "--bank_cfg", default=None,
        help="also time a PTT evaluation with and without the proposal bank",
    )  # fmt: skip
    p.add_argument("--bank_frames", type=int, default=40, help="frames of --bank_cfg's run")
    p.add_argument("--bank_variant", default="inj_global_hard", help="the variant of --bank_cfg")
    p.add_argument(
        "--vfe_forms", action="store_true",
        help="time the VFE's folded eval form against the layer-by-layer one instead",
    )  # fmt: skip
    p.add_argument(
        "--reuse_cfgs", nargs="+", default=None,
        help="time a tools/test.py suite of these shipped models with and without reusing "
        "clean predictions, on the same frames",
    )  # fmt: skip
    p.add_argument("--reuse_attacks", default="all", help="variants of --reuse_cfgs' suite")
    p.add_argument("--ssm", action="store_true", help="time selective_scan against the loop")
    p.add_argument(
        "--spconv", default=None, metavar="CFG",
        help="time each sparse conv layer of this voxel config's 3D backbone against dense conv3d",
    )  # fmt: skip
    p.add_argument("--spconv_frame", type=int, default=40, help="the val frame of --spconv")
    p.add_argument(
        "--spconv_layers", nargs="+", default=None, metavar="NAME",
        help="--spconv on these layers only (module names, e.g. conv1.0.conv1)",
    )  # fmt: skip
    p.add_argument(
        "--spconv_crop", type=float, default=0.0,
        help="--spconv on the voxels within this many metres of the sensor (0: the whole frame)",
    )  # fmt: skip
    p.add_argument(
        "--ssm_lengths",
        type=int,
        nargs="+",
        default=[1024, 16384],
        help="sequence lengths of --ssm",
    )
    t = p.add_argument_group("training step (--train_step)")
    t.add_argument("--train_step", action="store_true", help="time training steps instead")
    t.add_argument(
        "--train_cfgs", nargs="+", default=list(TRAIN_STEP_CFGS), help="configs of --train_step"
    )
    t.add_argument("--steps", type=int, default=4, help="timed steps per process (after 1)")
    t.add_argument("--rounds", type=int, default=2, help="processes per tree and config")
    t.add_argument("--batch_size", type=int, default=4, help="batch of --train_step (default: 4)")
    t.add_argument("--workers", type=int, default=0, help="loader workers")
    t.add_argument(
        "--baseline_src", default=None,
        help="older source tree to compare against (training steps, or the latency table)",
    )  # fmt: skip
    t.add_argument(
        "--default_malloc", action="store_true",
        help="also time this tree with glibc malloc left as it is (no retain_freed_cpu_memory)",
    )  # fmt: skip
    t.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--latency_child", action="store_true", help=argparse.SUPPRESS)
    return p.parse_args()


TRAIN_STEP_CFGS = ("cfgs/atlas/synthetic/centerpoint.yaml", "cfgs/atlas/synthetic/cp4f.yaml")


def _train_step_child(cfg_file: str, data_path: str, args) -> dict:
    """Time ``1 + args.steps`` training steps of ``cfg_file`` in this process (the first one is
    a warm-up and is not counted). Returns per-step seconds and losses."""
    import pcdet_atlas
    from pcdet_atlas.models.optimization import build_optimizer, build_scheduler

    malloc = "default"
    if not args.default_malloc:
        try:  # what tools/train.py does on CPU (absent from older trees)
            from pcdet_atlas.train_utils.cpu_memory import retain_freed_cpu_memory
        except ImportError:
            retain_freed_cpu_memory = None
        if retain_freed_cpu_memory is not None and retain_freed_cpu_memory():
            malloc = "retained"

    cfg = cfg_from_yaml_file(cfg_file)
    cfg.DATA_CONFIG.DATA_PATH = data_path
    _, loader, _ = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, args.batch_size, False, workers=args.workers, seed=0,
        training=True, total_epochs=cfg.OPTIMIZATION.NUM_EPOCHS,
    )  # fmt: skip
    if hasattr(loader.dataset, "set_epoch"):
        loader.dataset.set_epoch(0)
    torch.manual_seed(0)
    model = build_network_from_config(cfg).train()
    optimizer = build_optimizer(model, cfg.OPTIMIZATION)
    scheduler = build_scheduler(
        optimizer, cfg.OPTIMIZATION, iters_per_epoch=len(loader),
        total_epochs=cfg.OPTIMIZATION.NUM_EPOCHS,
    )  # fmt: skip
    clip = float(cfg.OPTIMIZATION.get("GRAD_NORM_CLIP", 10.0))
    res: dict = {"package": str(Path(pcdet_atlas.__file__).parent), "threads": 0, "malloc": malloc}
    res.update(data=[], model=[], step=[], loss=[], points=[])
    it = iter(loader)
    t_prev = time.perf_counter()
    for _ in range(args.steps + 1):
        batch = next(it)
        t_data = time.perf_counter()
        batch = load_data_to_device(batch, "cpu")
        optimizer.zero_grad(set_to_none=True)
        ret, _, _ = model(batch)
        ret["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
        optimizer.step()
        scheduler.step()
        t_end = time.perf_counter()
        res["data"].append(t_data - t_prev)
        res["model"].append(t_end - t_data)
        res["step"].append(t_end - t_prev)
        res["loss"].append(float(ret["loss"].detach()))
        res["points"].append(int(batch["points"].shape[0]))
        t_prev = t_end
    res["threads"] = torch.get_num_threads()
    return res


def _tree_child(tree: str, src: Path, argv: list[str]) -> dict:
    """Run this script with ``argv`` in a fresh process that imports ``pcdet_atlas`` from the
    source tree ``src``; returns the JSON of its last output line, whose ``package`` must lie in
    ``src``."""
    env = baseline_tree_env(src)
    out = subprocess.run([sys.executable, __file__, *argv], env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"{tree}: {' '.join(argv)} failed:\n{out.stderr[-4000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if not Path(res["package"]).resolve().is_relative_to(src):
        raise SystemExit(f"{tree}: imported {res['package']}, not {src}")
    return res


def train_step_table(args, data_path: Path) -> None:
    """Seconds per training step of each config (and of the baseline tree, if given)."""
    trees = {"this tree": (REPO_ROOT, False)}  # label -> (source tree, default malloc)
    if args.default_malloc:
        trees = {"this tree, default malloc": (REPO_ROOT, True), **trees}
    if args.baseline_src:
        trees = {"baseline": (Path(args.baseline_src).resolve(), False), **trees}
    for tree, _ in trees.values():
        if not (tree / "pcdet_atlas" / "__init__.py").is_file():
            raise SystemExit(f"--baseline_src: no pcdet_atlas package under {tree}")
    results: dict = {(t, c): [] for t in trees for c in args.train_cfgs}
    loads = [os.getloadavg()[0]]
    for _ in range(args.rounds):
        for cfg_file in args.train_cfgs:
            for tree, (src, default_malloc) in trees.items():
                cmd = [
                    "--train_step", "--child", "--train_cfgs",
                    str((src / cfg_file) if (src / cfg_file).is_file() else Path(cfg_file)),
                    "--data_path", str(data_path), "--steps", str(args.steps),
                    "--batch_size", str(args.batch_size), "--workers", str(args.workers),
                ] + (["--threads", str(args.threads)] if args.threads else [])  # fmt: skip
                cmd += ["--default_malloc"] if default_malloc else []
                results[(tree, cfg_file)].append(_tree_child(tree, src, cmd))
                loads.append(os.getloadavg()[0])
    first = next(iter(results.values()))[0]
    print(
        f"\ntraining steps: batch {args.batch_size}, {args.workers} loader workers, "
        f"{first['threads']} torch threads, {args.steps} timed steps x {args.rounds} processes "
        f"per row (after 1 warm-up step each), medians; load average "
        f"{min(loads):.1f}-{max(loads):.1f}; data {data_path}\n"
    )
    print(
        "| config | tree | points/step | model s/step (fwd+loss+bwd+opt) | data s/step "
        "| total s/step | speed-up | loss step 1 .. last |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for cfg_file in args.train_cfgs:
        base_total = None
        for tree in trees:
            runs = results[(tree, cfg_file)]
            med = {
                k: statistics.median(v for r in runs for v in r[k][1:])
                for k in ("model", "data", "step", "points")
            }
            base_total = base_total or med["step"]
            losses = runs[0]["loss"]
            name = str(Path(cfg_file)).replace("cfgs/atlas/", "")
            print(
                f"| {name} | {tree.split(',')[0]} ({runs[0]['malloc']} malloc) | "
                f"{med['points']:,.0f} | {med['model']:.2f} | "
                f"{med['data']:.2f} | {med['step']:.2f} | {base_total / med['step']:.2f}x | "
                f"{losses[0]:.5f} .. {losses[-1]:.5f} |"
            )
        if len(trees) > 1:
            losses = [results[(t, cfg_file)][0]["loss"] for t in trees]
            rel = max(
                abs(x - y) / max(abs(y), 1e-12)
                for other in losses[:-1]
                for x, y in zip(other, losses[-1])
            )
            print(f"|  | max rel. loss difference to this tree | {rel:.1e} | | | | | |")


def test_step_shares(cfg_file: str, data_path: Path, frames: int, device: torch.device) -> None:
    """Share of a test step spent in data loading, attack simulation, model and metric.

    Frames ``32 .. 32 + frames`` of the val split (inside the first spoofed run) are served by
    ``AtlasWaymoDataset`` for ``clean``, ``inj_global_hard`` and ``rem_40``; data loading of the
    clean variant is plain loading, the rest of an attacked variant's data time is the attack.
    An untimed clean pass over the same frames runs first: the first pass pays for reading the
    files and growing the allocator, which would otherwise land on ``clean`` alone.
    """
    from pcdet_atlas.attacks.trace_library import TraceFilter, build_trace_library
    from pcdet_atlas.evaluation import evaluate_attack
    from pcdet_atlas.train_utils.atlas_eval import build_attack_loader
    from pcdet_atlas.train_utils.eval_utils import predict_dataset

    cfg = cfg_from_yaml_file(cfg_file)
    cfg.DATA_CONFIG.DATA_PATH = str(data_path)
    cfg.DATA_CONFIG.SAMPLED_INTERVAL = {"train": 1, "test": 1}
    torch.manual_seed(0)
    model = build_network_from_config(cfg).to(device).eval()
    attacks = REPO_ROOT / "cfgs" / "attacks"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        inj = cfg_from_yaml_file(attacks / "inj_global_hard.yaml")
        inj.TRACE_LIBRARY.MIN_POINTS = 100
        lib = build_trace_library(data_path, TraceFilter.from_config(inj.TRACE_LIBRARY))
        inj.TRACE_LIBRARY.PATH = str(lib.save(Path(tmp) / "lib.npz"))
        variants = [("warm-up", attacks / "clean.yaml"), ("clean", attacks / "clean.yaml")]
        variants += [("inj_global_hard", inj), ("rem_40", attacks / "rem_40.yaml")]
        for name, attack_cfg in variants:
            dataset, _ = build_attack_loader(  # its loader covers the whole split
                cfg.DATA_CONFIG, cfg.CLASS_NAMES, attack_cfg, batch_size=1, dist=False,
                workers=0, seed=0,
            )  # fmt: skip
            if len(dataset.infos) < 32 + frames:
                raise SystemExit(f"--share_cfg needs >= {32 + frames} val frames in {data_path}")
            dataset.infos = dataset.infos[32 : 32 + frames]
            loader = torch.utils.data.DataLoader(  # over the kept frames only
                dataset, batch_size=1, shuffle=False, collate_fn=dataset.collate_batch
            )
            timings: dict = {}
            annos, extras = predict_dataset(
                model, loader, device=device, show_progress=False, timings=timings
            )
            t0 = time.perf_counter()
            dataset.evaluation(annos, cfg.CLASS_NAMES, eval_metric="waymo")
            if name != "clean":
                evaluate_attack(annos, [e["attack"] for e in extras], window=1)
            timings["metric"] = time.perf_counter() - t0
            if name != "warm-up":
                rows.append((name, timings))
    clean_data = rows[0][1]["data"]
    print(f"\ntest step of {cfg_file}, {frames} frames (32..{31 + frames}), batch 1, {device}")
    print("| variant | data loading | attack simulation | model | metric | s / frame |")
    print("|---|---|---|---|---|---|")
    for name, t in rows:
        attack = max(0.0, t["data"] - clean_data) if name != "clean" else 0.0
        load = t["data"] - attack
        total = t["data"] + t["model"] + t["metric"]
        shares = [100 * x / total for x in (load, attack, t["model"], t["metric"])]
        print(
            f"| {name} | " + " | ".join(f"{s:.0f}%" for s in shares) + f" | {total / frames:.2f} |"
        )


def reuse_table(cfg_files: list[str], data_path: Path, args, device: torch.device) -> None:
    """Each model's evaluation suite (clean, then ``--reuse_attacks``; shipped checkpoint, batch 1)
    with and without reusing clean predictions, in one process on the same frames: per attack
    variant the full and the reusing run alternate (each first on every other variant, each
    suite with its own attack objects), so both see the same machine load and caches. Their
    results must agree (schema fields other than the reuse counts and timings)."""
    from pcdet_atlas.train_utils.atlas_eval import (
        EvalContext,
        build_variant_attacks,
        evaluate_variant,
        resolve_variants,
    )
    from pcdet_atlas.train_utils.eval_caches import EvalCaches

    print(f"\nevaluation suite with and without reuse, {data_path.name}, batch 1, {device}")
    print("| config | variants | frames | recomputed (reuse) | RPN frames without / with reuse | "
          "s without reuse | s with reuse | ratio |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for cfg_file in cfg_files:
        cfg = cfg_from_yaml_file(cfg_file)
        cfg.DATA_CONFIG.DATA_PATH = str(data_path)
        model = build_network_from_config(cfg)
        model.load_params_from_file(REPO_ROOT / cfg.ATLAS.CHECKPOINT)
        model.to(device).eval()
        variants = resolve_variants(args.reuse_attacks, cfg.get("ATLAS", {}))
        # each suite its own attacks: no run prepared for one suite is reused by the other
        suites = {reuse: build_variant_attacks(variants, data_path) for reuse in (False, True)}
        attacks = suites[False]
        seconds = {False: 0.0, True: 0.0}
        rpn = {False: 0, True: 0}  # frames through a proposal bank's RPN (PTT)
        frames = recomputed = 0
        context = EvalContext(
            data_cfg=cfg.DATA_CONFIG, class_names=cfg.CLASS_NAMES, device=device,
            workers=args.workers, temporal_window=atlas_section(cfg.get("ATLAS")).temporal_window,
            show_progress=False,
        )  # fmt: skip
        clean = None
        proposals: dict = {}  # the clean run's proposal bank, seeding the reusing runs
        for i, name in enumerate(attacks):
            entries = {}
            # the full and the reusing run alternate, each first on every other variant
            order = (False, True) if i % 2 else (True, False)
            for reuse in order if clean is not None else (False,):
                t0 = time.perf_counter()
                caches = EvalCaches(reuse=reuse)
                caches.clean_proposals = proposals  # the clean run fills it, the others read it
                if clean is not None:
                    caches.keep_clean(clean)
                entry, annos = evaluate_variant(
                    model, name, suites[reuse][name], context, caches=caches
                )
                elapsed = time.perf_counter() - t0
                entries[reuse] = entry
                bank = entry["extra"].get("proposal_bank", {}).get("rpn_frames", 0)
                if clean is None:  # the clean run is the same in both suites
                    seconds[False] += elapsed
                    seconds[True] += elapsed
                    rpn[False] += bank
                    rpn[True] += bank
                    frames += entry["num_frames"]
                    recomputed += entry["num_frames"]
                    clean = annos
                else:
                    seconds[reuse] += elapsed
                    rpn[reuse] += bank
            if True in entries:
                frames += entries[False]["num_frames"]
                recomputed += entries[True]["num_recomputed_frames"]
                a, b = ({k: v for k, v in e.items()
                         if k not in ("extra", "num_reused_frames", "num_recomputed_frames")}
                        for e in (entries[False], entries[True]))  # fmt: skip
                if a != b:
                    raise SystemExit(f"{cfg_file} {name}: reuse changed the results")
        passes = f"{rpn[False]:,} / {rpn[True]:,}" if rpn[False] else "-"
        print(f"| {Path(cfg_file).relative_to(REPO_ROOT / 'cfgs')} | {len(attacks)} | {frames:,} | "
              f"{recomputed:,} | {passes} | {seconds[False]:.0f} | {seconds[True]:.0f} | "
              f"{seconds[False] / seconds[True]:.2f}x |")  # fmt: skip


def _config_frames(
    cfg_file: str, data_path: Path, count: int, device: torch.device, start: int = 0
):
    """A model config (its data path set to ``data_path``), the val batches ``start`` to
    ``start + count - 1`` of its own test pipeline (batch 1) on ``device``, and the dataset."""
    cfg = cfg_from_yaml_file(cfg_file)
    cfg.DATA_CONFIG.DATA_PATH = str(data_path)
    dataset, loader, _ = build_dataloader(
        cfg.DATA_CONFIG, cfg.CLASS_NAMES, 1, False, workers=0, training=False
    )
    batches = []
    for index, batch in enumerate(loader):
        if index >= start:
            batches.append(load_data_to_device(batch, device))
        if len(batches) == count:
            break
    return cfg, batches, dataset


def _reads_proposal_history(cfg) -> bool:
    return DETECTORS.get(cfg.MODEL.NAME) is PTT


def _first_full_frame(cfg) -> int:
    """The first val frame whose model input is all real frames, none padded at the sequence
    start: the point history of a multi-frame input, PTT's ``NUM_HISTORY`` previous frames."""
    points = point_history(cfg.DATA_CONFIG)
    if not _reads_proposal_history(cfg):
        return points
    return max(points, int(cfg.MODEL.ROI_HEAD.get("NUM_HISTORY", 31)))


def _warm_bank(model, dataset, batch, device: torch.device) -> ProposalBank:
    """A proposal bank for ``model`` on ``dataset`` holding the history of ``batch``'s frame."""
    bank = ProposalBank(model, dataset, device=device)
    seq, idx = batch["sequence_name"][0], int(batch["sample_idx"][0])
    for back in range(min(bank.num_history, idx), 0, -1):
        bank.frame(seq, idx - back)
    return bank


def vfe_forms_table(cfg_files: list[str], data_path: Path, args, device: torch.device) -> None:
    """Print the VFE's eval-mode latency in its folded and its layer-by-layer form."""
    print(
        f"\nVFE eval forms, device {device}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, {args.frames} frames (after 1 warm-up), alternating"
    )
    print(
        "| config | points/frame | pillars/frame | folded ms | layer-by-layer ms | ratio "
        "| max abs diff |"
    )
    print("|---|---|---|---|---|---|---|")
    for cfg_file in cfg_files:
        if cfg_from_yaml_file(cfg_file).MODEL.VFE.NAME not in ("DynamicPillarVFE", "DynPillarVFE"):
            continue  # the two forms are the pillar VFE's; a voxel model's MeanVFE has one
        cfg, batches, _ = _config_frames(cfg_file, data_path, args.frames + 1, device)
        torch.manual_seed(0)
        model = build_network_from_config(cfg).to(device)
        ckpt = trained_checkpoint(cfg.get("ATLAS"))
        if ckpt is not None:
            model.load_params_from_file(ckpt)
        else:  # running statistics of real features (their plain average), not BN's 0 / 1
            for module in model.vfe.modules():
                if isinstance(module, torch.nn.BatchNorm1d):
                    module.reset_running_stats()
                    module.momentum = None
            with torch.no_grad():
                for batch in batches[:3]:
                    model.vfe(dict(batch))
        vfe = model.vfe.eval()
        times = {True: [], False: []}
        diff, points, pillars = 0.0, [], []
        with torch.no_grad():
            for i, batch in enumerate(batches):
                outs = {}
                for fold in (True, False):
                    vfe.fold_eval = fold
                    if device.type == "cuda":
                        torch.cuda.synchronize(device)
                    t0 = time.perf_counter()
                    outs[fold] = vfe(dict(batch))["pillar_features"]
                    if device.type == "cuda":
                        torch.cuda.synchronize(device)
                    if i:
                        times[fold].append(time.perf_counter() - t0)
                diff = max(diff, float((outs[True] - outs[False]).abs().max()))
                points.append(int(batch["points"].shape[0]))
                pillars.append(int(outs[True].shape[0]))
        vfe.fold_eval = True
        fast, slow = statistics.median(times[True]), statistics.median(times[False])
        name = str(Path(cfg_file).resolve().relative_to(REPO_ROOT / "cfgs"))
        print(
            f"| {name} | {statistics.mean(points):,.0f} | {statistics.mean(pillars):,.0f} "
            f"| {fast * 1e3:,.1f} | {slow * 1e3:,.1f} | {slow / fast:.2f}x | {diff:.1e} |"
        )


def _timed_runs(
    cfg_files: list[str], data_path: Path, args, device: torch.device
) -> tuple[list[dict], list[tuple[str, str]]]:
    """Build each config's model, measure its peak memory and time ``args.frames`` frames of
    each (models taking turns frame by frame, after one warm-up frame).
    Returns the runs (``times``, ``rpn_times``, ``digest`` of the timed frames' predictions, ...)
    and the configs whose model could not be built, with the reason."""
    runs, unbuilt = [], []
    # every model on the same frames, from the first one whose input no model pads
    start = max(_first_full_frame(cfg_from_yaml_file(c)) for c in cfg_files)
    for cfg_file in cfg_files:
        cfg, batches, dataset = _config_frames(cfg_file, data_path, args.frames + 1, device, start)
        torch.manual_seed(0)
        try:
            model = build_network_from_config(cfg).to(device).eval()
        except FileNotFoundError as err:  # a two-stage config whose RPN is not trained here
            unbuilt.append((cfg_file, str(err).split(" (")[0]))
            continue
        ckpt = trained_checkpoint(cfg.get("ATLAS"))
        trained = ckpt is not None
        if trained:
            model.load_params_from_file(ckpt)
        n_points = statistics.mean(int(b["points"].shape[0]) for b in batches)
        runs.append(
            {"cfg": cfg_file, "cfg_obj": cfg, "model": model, "batches": batches,
             "trained": trained, "ships_ckpt": bool(atlas_section(cfg.get("ATLAS")).checkpoint),
             "times": [], "points": n_points,
             "params": sum(p.numel() for p in model.parameters()), "rpn_times": []}
        )  # fmt: skip
        if getattr(model, "lot", None) is not None:  # time LOT inside the frames
            runs[-1]["lot_times"] = _time_module(model.lot)
        runs[-1]["assoc_calls"] = _time_association(model, device)
        runs[-1]["assoc_times"] = [] if runs[-1]["assoc_calls"] is not None else None
        if _reads_proposal_history(cfg):  # PTT: the bank already holding the frames' history
            runs[-1]["bank"] = _warm_bank(model, dataset, batches[0], device)

    ctx = multiprocessing.get_context("spawn")
    for run in runs:  # peak memory in a fresh process per model (no allocator reuse), warm-up
        with ctx.Pool(1) as pool:
            run["peak_mib"] = pool.apply(
                _peak_memory_mib, (run["cfg"], str(data_path), str(device), run["trained"], start)
            )
        run["digest"] = hashlib.sha256()
        warm = run["batches"][0]
        run["model"].predict(run["bank"].attach(warm, warm) if "bank" in run else warm)
    for i in range(1, args.frames + 1):  # models take turns frame by frame
        for run in runs:
            batch = run["batches"][min(i, len(run["batches"]) - 1)]
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            calls = len(run["assoc_calls"]) if run["assoc_calls"] is not None else 0
            t0 = time.perf_counter()
            if "bank" in run:  # PTT: the frame's RPN pass into the bank, then the head
                batch = run["bank"].attach(batch, batch)
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                run["rpn_times"].append(time.perf_counter() - t0)
                preds = run["model"].predict(batch)
            elif isinstance(run["model"], TwoStageDetector):  # RPN and second stage apart
                proposals = run["model"].propose(batch)
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                run["rpn_times"].append(time.perf_counter() - t0)
                preds = run["model"].refine(batch, proposals)
            else:
                preds = run["model"].predict(batch)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            run["times"].append(time.perf_counter() - t0)
            if run["assoc_calls"] is not None:
                run["assoc_times"].append(sum(run["assoc_calls"][calls:]))
            for pred in preds:  # outside the timing
                for key in sorted(pred):
                    if isinstance(pred[key], torch.Tensor):
                        run["digest"].update(pred[key].detach().cpu().contiguous().numpy())
    for run in runs:
        run["digest"] = run["digest"].hexdigest()
        run["ops"] = []  # per timed frame: (second-stage operators, of them association's)
        if not run["rpn_times"]:
            continue
        for batch in run["batches"][1 : args.frames + 1]:  # untimed, the RPN outside
            if "bank" in run:  # the bank holds the frame now: attach runs no RPN
                batch = run["bank"].attach(batch, batch)
                run["ops"].append(_operator_calls(run["model"].predict, batch))
            else:
                proposals = run["model"].propose(batch)
                run["ops"].append(_operator_calls(run["model"].refine, batch, proposals))
    return runs, unbuilt


def _latency_child(cfg_files: list[str], data_path: Path, args, device: torch.device) -> dict:
    """One ``--baseline_src`` latency process: the timed frames and peak memory of every
    config."""
    import pcdet_atlas

    runs, unbuilt = _timed_runs(cfg_files, data_path, args, device)
    keys = ("cfg", "times", "rpn_times", "digest", "trained", "peak_mib", "assoc_times", "ops")
    return {
        "package": str(Path(pcdet_atlas.__file__).parent), "threads": torch.get_num_threads(),
        "runs": [{k: run[k] for k in keys} for run in runs], "unbuilt": unbuilt,
    }  # fmt: skip


def latency_compare_table(
    cfg_files: list[str], data_path: Path, args, device: torch.device
) -> None:
    """The latency and peak memory of each config in the ``--baseline_src`` tree and in this
    one, timed in ``args.rounds`` alternating processes per tree, with whether both trees
    predicted the same (bitwise) on the timed frames. Each tree reads its own copy of a config
    (the config's path relative to the repository)."""
    trees = {"baseline": Path(args.baseline_src).resolve(), "this tree": REPO_ROOT}
    if not (trees["baseline"] / "pcdet_atlas" / "__init__.py").is_file():
        raise SystemExit(f"--baseline_src: no pcdet_atlas package under {trees['baseline']}")
    rel = [Path(c).resolve().relative_to(REPO_ROOT) for c in cfg_files]
    missing = [str(r) for r in rel if not (trees["baseline"] / r).is_file()]
    if missing:
        raise SystemExit(f"--baseline_src: {trees['baseline']} has no {', '.join(missing)}")
    results: dict = {(t, r): [] for t in trees for r in rel}
    unbuilt: dict = {}
    loads, threads = [os.getloadavg()[0]], None
    for _ in range(args.rounds):
        for tree, src in trees.items():
            cmd = [
                "--latency_child", "--cfgs", *(str(src / r) for r in rel),
                "--data_path", str(data_path), "--frames", str(args.frames),
                "--device", str(device),
            ] + (["--threads", str(args.threads)] if args.threads else [])  # fmt: skip
            res = _tree_child(tree, src, cmd)
            for cfg_file, reason in res["unbuilt"]:
                unbuilt[Path(cfg_file).resolve().relative_to(src)] = f"{tree}: {reason}"
            for run in res["runs"]:
                results[(tree, Path(run["cfg"]).resolve().relative_to(src))].append(run)
            threads = res["threads"]
            loads.append(os.getloadavg()[0])
    print(
        f"\ndevice {device}, torch {torch.__version__}, {threads} threads, {args.frames} frames "
        f"per model and process (batch 1, after 1 warm-up), {args.rounds} processes per tree "
        f"alternating, medians; load average {min(loads):.1f}-{max(loads):.1f}\n"
    )
    print(
        "| config | tree | latency ms | speed-up | RPN + 2nd stage ms | 2nd stage speed-up "
        "| 2nd stage ops | association ms | association ops | peak MiB | predictions |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for cfg in rel:
        name = str(cfg).replace("cfgs/atlas/", "")
        if cfg in unbuilt:
            print(f"| {name} | not built ({unbuilt[cfg]}) | | | | | | | | | |")
            continue
        if len({r["trained"] for t in trees for r in results[(t, cfg)]}) > 1:
            raise SystemExit(
                f"{cfg}: its checkpoint exists in one tree only (archive the baseline with its "
                f"checkpoints/)"
            )
        digests = {t: {r["digest"] for r in results[(t, cfg)]} for t in trees}
        base = base_second = None
        for tree in trees:
            runs = results[(tree, cfg)]
            med = statistics.median(t for r in runs for t in r["times"])
            base = base or med
            split = second_ratio = ops = assoc_ms = assoc_ops = "-"
            if runs[0]["ops"]:
                ops = f"{statistics.median(o for r in runs for o, _ in r['ops']):,.0f}"
            if runs[0]["assoc_times"] is not None:
                assoc = statistics.median(t for r in runs for t in r["assoc_times"])
                assoc_ms = f"{assoc * 1e3:,.1f}"
                assoc_ops = f"{statistics.median(a for r in runs for _, a in r['ops']):,.0f}"
            if runs[0]["rpn_times"]:
                pairs = [(t, p) for r in runs for t, p in zip(r["times"], r["rpn_times"])]
                rpn = statistics.median(p for _, p in pairs)
                second = statistics.median(t - p for t, p in pairs)
                base_second = base_second or second
                split = f"{rpn * 1e3:,.0f} + {second * 1e3:,.0f}"
                second_ratio = f"{base_second / second:.2f}x"
            peak = max(r["peak_mib"] for r in runs)
            if len(digests[tree]) > 1:  # its own processes disagree: non-deterministic kernels
                same = "not reproducible"
            elif tree == "baseline":
                same = "-"
            else:
                same = "bitwise equal" if digests["baseline"] == digests[tree] else "differ"
            print(
                f"| {name} | {tree} | {med * 1e3:,.0f} | {base / med:.2f}x | {split} | "
                f"{second_ratio} | {ops} | {assoc_ms} | {assoc_ops} | {peak:,.0f} | {same} |"
            )


def latency_table(cfg_files: list[str], data_path: Path, args, device: torch.device) -> None:
    """Print latency / peak memory / L2 mAP of each config, models taking turns per frame."""
    runs, unbuilt = _timed_runs(cfg_files, data_path, args, device)
    if args.eval:
        for run in runs:
            if run["trained"]:
                cfg = run["cfg_obj"]
                _, loader, _ = build_dataloader(
                    cfg.DATA_CONFIG, cfg.CLASS_NAMES, 1, False, workers=2, training=False
                )
                ap, annos = eval_one_epoch(run["model"], loader, device=device)
                run["l2_map"], run["eval_frames"] = float(ap["L2/mAP"]), len(annos)
    print(
        f"\ndevice {device}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{args.frames} frames per model (batch 1, after 1 warm-up)\n"
    )
    print(
        "| config | params (M) | points/frame | latency ms (median) | min-max ms | RPN + 2nd "
        "stage ms | peak MiB | L2 mAP |"
    )
    print("|---|---|---|---|---|---|---|---|")
    fastest = min(statistics.median(r["times"]) for r in runs)
    for run in runs:
        med = statistics.median(run["times"])
        name = str(Path(run["cfg"]).resolve().relative_to(REPO_ROOT / "cfgs"))
        if not run["ships_ckpt"]:
            mAP = "no checkpoint (train on real data)"
        elif not run["trained"]:
            mAP = "checkpoint missing (random weights)"
        elif "l2_map" in run:
            mAP = f"{run['l2_map']:.4f} ({run['eval_frames']} val frames)"
        else:
            mAP = "trained (pass --eval)"
        lo, hi = min(run["times"]) * 1e3, max(run["times"]) * 1e3
        split = "-"
        if run["rpn_times"]:
            rpn = statistics.median(run["rpn_times"])
            second = statistics.median(t - r for t, r in zip(run["times"], run["rpn_times"]))
            split = f"{rpn * 1e3:,.0f} + {second * 1e3:,.0f}"
        print(
            f"| {name} | {run['params'] / 1e6:.2f} | {run['points']:,.0f} | {med * 1e3:,.0f} "
            f"({med / fastest:.1f}x) | {lo:,.0f}-{hi:,.0f} | {split} | {run['peak_mib']:,.0f} "
            f"| {mAP} |"
        )
    for cfg_file, reason in unbuilt:
        name = str(Path(cfg_file).resolve().relative_to(REPO_ROOT / "cfgs"))
        print(f"| {name} | not built: {reason} | | | | | | |")
    if args.json:
        write_costs_json(runs, args, device)
    for run in runs:
        if "lot_times" in run:
            lot = statistics.median(run["lot_times"][-args.frames :])
            med = statistics.median(run["times"])
            name = str(Path(run["cfg"]).resolve().relative_to(REPO_ROOT / "cfgs"))
            print(
                f"\n{name}: LOT (score MLP, occupancy maps, ConvSSM forecast, filtering) takes "
                f"{lot * 1e3:,.1f} ms of the {med * 1e3:,.0f} ms frame ({lot / med:.1%})"
            )
    for run in runs:
        if "bank" in run:
            st = run["bank"].stats()
            name = str(Path(run["cfg"]).resolve().relative_to(REPO_ROOT / "cfgs"))
            print(
                f"\n{name}: frames {run['bank'].num_history}+ (a full history); the RPN column is "
                f"the bank's one RPN pass per new frame plus reading the previous frames; the "
                f"bank then held {st['frames_held']} frames, {st['bytes_held'] / 2**20:.2f} MiB "
                f"({st['bytes_held'] / max(1, st['frames_held']) / 1024:.1f} KiB per frame)"
            )


def write_costs_json(runs: list[dict], args, device: torch.device) -> None:
    """The median per-frame latency (and a two-stage model's RPN part) of each timed config, as
    ``tools/bench/cost_model.py --costs`` reads it."""
    models = {}
    for run in runs:
        name = str(Path(run["cfg"]).resolve().relative_to(REPO_ROOT / "cfgs"))
        rpn = statistics.median(run["rpn_times"]) if run["rpn_times"] else None
        models[name] = {"latency_s": statistics.median(run["times"]), "rpn_s": rpn,
                        "frames": len(run["times"]), "points_per_frame": run["points"]}  # fmt: skip
    out = {"version": 1, "device": str(device), "threads": torch.get_num_threads(),
           "torch": torch.__version__, "batch_size": 1, "models": models}  # fmt: skip
    Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    print(f"\nper-frame costs written to {args.json}")


def bank_table(cfg_file: str, data_path: Path, args, device: torch.device) -> None:
    """Print the cost of evaluating frames 0 .. N-1 of a val sequence under one variant with the
    proposal bank (one RPN pass per frame) and without it (each frame's own 32 RPN passes)."""
    from pcdet_atlas.train_utils.atlas_eval import build_attack_loader

    cfg = cfg_from_yaml_file(cfg_file)
    cfg.DATA_CONFIG.DATA_PATH = str(data_path)
    attack = REPO_ROOT / "cfgs" / "attacks" / f"{args.bank_variant}.yaml"
    torch.manual_seed(0)
    model = build_network_from_config(cfg).to(device).eval()
    ckpt = trained_checkpoint(cfg.get("ATLAS"))
    if ckpt is not None:
        model.load_params_from_file(ckpt)
    results = {}
    for mode in ("warm-up", "bank", "no bank"):  # warm-up: frame 0, untimed (first reads, allocs)
        dataset, loader = build_attack_loader(
            cfg.DATA_CONFIG, cfg.CLASS_NAMES, attack, batch_size=1, dist=False, workers=0,
            seed=0,
        )  # fmt: skip
        bank = ProposalBank(model, dataset, device=device)
        if mode == "warm-up":
            batch = next(iter(loader))
            model.predict(bank.attach(batch, load_data_to_device(batch, device)))
            continue
        passes, t0 = 0, time.perf_counter()
        for index, batch in enumerate(loader):
            if index == args.bank_frames:
                break
            if mode == "no bank":  # every window recomputes its 32 frames
                passes += bank.rpn_frames
                bank = ProposalBank(model, dataset, device=device)
            batch_dev = load_data_to_device(batch, device)
            model.predict(bank.attach(batch, batch_dev))
        passes += bank.rpn_frames
        results[mode] = (time.perf_counter() - t0, passes)
    name = str(Path(cfg_file).resolve().relative_to(REPO_ROOT / "cfgs"))
    print(
        f"\n{name}, variant {args.bank_variant}, frames 0-{args.bank_frames - 1} of the first val "
        f"sequence, device {device}, {torch.get_num_threads()} threads\n"
    )
    print("| proposals | RPN passes | RPN passes/frame | seconds | s/frame | ratio |")
    print("|---|---|---|---|---|---|")
    base = results["bank"][0]
    for mode, (secs, passes) in results.items():
        print(
            f"| {mode} | {passes} | {passes / args.bank_frames:.1f} | {secs:.1f} "
            f"| {secs / args.bank_frames:.2f} | {secs / base:.2f}x |"
        )


def _time_module(module: torch.nn.Module) -> list[float]:
    """Seconds of every forward of ``module`` from now on, appended to the returned list."""
    times: list[float] = []
    start: list[float] = []
    module.register_forward_pre_hook(lambda m, i: start.append(time.perf_counter()))
    module.register_forward_hook(lambda m, i, o: times.append(time.perf_counter() - start.pop()))
    return times


#: the profiler annotation around a second stage's association (``roi_head.trajectories``)
ASSOCIATION = "bench::association"


def _time_association(model, device: torch.device) -> list[float] | None:
    """Seconds of every call of the model's ``roi_head.trajectories`` (PTT's association) from
    now on, each call also annotated for the profiler; ``None`` for a model without one."""
    head = getattr(model, "roi_head", None)
    if not callable(getattr(head, "trajectories", None)):
        return None
    times: list[float] = []
    inner = head.trajectories

    def timed(*args, **kwargs):
        with torch.profiler.record_function(ASSOCIATION):
            t0 = time.perf_counter()
            out = inner(*args, **kwargs)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            times.append(time.perf_counter() - t0)
        return out

    head.trajectories = timed
    return times


def _operator_calls(fn, *args) -> tuple[int, int]:
    """Run ``fn(*args)`` under the CPU profiler: the aten operators it calls directly (not from
    within another operator: one dispatch each, a kernel launch or a view), all and those inside
    the association's annotation."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn(*args)
    total = inside = 0
    for event in prof.events():
        if not event.name.startswith("aten::"):
            continue
        parent, annotated = event.cpu_parent, False
        while parent is not None and not parent.name.startswith("aten::"):
            annotated |= parent.name == ASSOCIATION
            parent = parent.cpu_parent
        if parent is None:  # called from Python
            total += 1
            inside += annotated
    return total, inside


def ssm_table(lengths: list[int], frames: int, device: torch.device) -> None:
    """selective_scan (chunked) against the sequential loop, same inputs, alternating."""
    from pcdet_atlas.models.ssm import selective_scan, selective_scan_reference

    g = torch.Generator().manual_seed(0)
    b, d, n = 2, 64, 16
    print(f"\nselective_scan vs the plain loop: b {b}, d {d}, n {n}, {device}, "
          f"{torch.get_num_threads()} threads, median of {frames}")  # fmt: skip
    print("| l | pass | chunked ms | loop ms | speed-up | max abs diff |")
    print("|---|---|---|---|---|---|")
    for l in lengths:
        args = [
            torch.randn(b, d, l, generator=g), torch.rand(b, d, l, generator=g) - 2,
            -torch.rand(d, n, generator=g) * 4, torch.randn(b, n, l, generator=g),
            torch.randn(b, n, l, generator=g),
        ]  # fmt: skip
        args = [a.to(device) for a in args]
        kw = {"D": torch.ones(d, device=device), "delta_softplus": True}
        for backward in (False, True):
            times: dict = {selective_scan: [], selective_scan_reference: []}
            outs = {}
            for _ in range(frames):
                for fn in times:
                    inp = [a.clone().requires_grad_(backward) for a in args]
                    if device.type == "cuda":
                        torch.cuda.synchronize(device)
                    t0 = time.perf_counter()
                    with torch.set_grad_enabled(backward):
                        y = fn(*inp, **kw)
                        if backward:
                            y.sum().backward()
                    if device.type == "cuda":
                        torch.cuda.synchronize(device)
                    times[fn].append(time.perf_counter() - t0)
                    outs[fn] = y.detach()
            fast, slow = (statistics.median(times[f]) for f in times)
            diff = float((outs[selective_scan] - outs[selective_scan_reference]).abs().max())
            print(
                f"| {l:,} | {'forward + backward' if backward else 'forward'} | "
                f"{fast * 1e3:,.1f} | {slow * 1e3:,.1f} | {slow / fast:.1f}x | {diff:.1e} |"
            )


def _dense_conv(conv, dense: torch.Tensor) -> torch.Tensor:
    """``torch.nn.functional.conv3d`` with a sparse conv layer's weights on its dense input
    ``(B, C, D, H, W)`` (a submanifold layer centred, as it is)."""
    weight = conv.weight.permute(0, 4, 1, 2, 3)  # (out, kD, kH, kW, in) -> (out, in, kD, kH, kW)
    padding = (
        tuple((k - 1) // 2 * d for k, d in zip(conv.kernel_size, conv.dilation))
        if conv.subm
        else conv.padding
    )
    return torch.nn.functional.conv3d(dense, weight, conv.bias, conv.stride, padding, conv.dilation)


def _timed(fn, device: torch.device, repeats: int) -> float:
    """Fewest seconds of ``fn()`` over ``repeats`` calls after one warm-up (the least disturbed
    call: another job on the same cores only ever adds time to a deterministic kernel)."""
    times = []
    for i in range(repeats + 1):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if i:
            times.append(time.perf_counter() - t0)
    return min(times)


def spconv_table(cfg_file: str, data_path: Path, args, device: torch.device) -> None:
    """Each sparse conv layer of a voxel config's 3D backbone on one val frame: rule building,
    the gather-GEMM-scatter forward and forward + backward, beside ``conv3d`` on the dense grid
    with the same weights; then the whole backbone."""
    from pcdet_atlas.ops.spconv import _SparseConvNd as SparseConv

    cfg, batches, _ = _config_frames(cfg_file, data_path, 1, device, start=args.spconv_frame)
    torch.manual_seed(0)
    model = build_network_from_config(cfg).to(device).eval()
    backbone = getattr(model, "backbone_3d", None)
    if backbone is None or not any(isinstance(m, SparseConv) for m in backbone.modules()):
        raise SystemExit(f"--spconv: {cfg_file} has no sparse conv 3D backbone")
    with torch.no_grad():
        batch = model.vfe(dict(batches[0]))
    if args.spconv_crop:  # the voxels within +-crop m of the sensor, on a grid of that size
        half = 8 * round(args.spconv_crop / cfg.MODEL.VFE.VOXEL_SIZE[0] / 8)
        coords = batch["voxel_coords"].clone()
        ny, nx = backbone.sparse_shape[1:]
        keep = ((coords[:, 2] - ny // 2).abs() < half) & ((coords[:, 3] - nx // 2).abs() < half)
        coords = coords[keep]
        coords[:, 2] -= ny // 2 - half
        coords[:, 3] -= nx // 2 - half
        batch.update(voxel_coords=coords, voxel_features=batch["voxel_features"][keep])
        backbone.sparse_shape = [backbone.sparse_shape[0], 2 * half, 2 * half]
    inputs = {}  # the input each layer sees in one forward, captured by hooks

    def capture(name):
        def hook(module, args):
            inputs.setdefault(name, (module, args[0]))  # returns None: the input is unchanged

        return hook

    hooks = [m.register_forward_pre_hook(capture(name))
             for name, m in backbone.named_modules() if isinstance(m, SparseConv)]  # fmt: skip
    with torch.no_grad():
        backbone(dict(batch))
    for hook in hooks:
        hook.remove()
    if args.spconv_layers:
        unknown = sorted(set(args.spconv_layers) - set(inputs))
        if unknown:
            raise SystemExit(f"--spconv_layers: no sparse conv layer {unknown}; has {list(inputs)}")
        inputs = {layer: inputs[layer] for layer in args.spconv_layers}
    reference = _spconv_reference()
    repeats = args.frames
    name = str(Path(cfg_file).resolve().relative_to(REPO_ROOT / "cfgs"))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"\nsparse conv layers of {name} ({type(backbone).__name__}, random weights) on val frame "
        f"{args.spconv_frame}{f' (within {args.spconv_crop:g} m)' if args.spconv_crop else ''}, "
        f"grid {backbone.sparse_shape}, device {device}, {torch.get_num_threads()} threads, "
        f"fastest of {repeats} (after 1 warm-up); dense: conv3d on the (B, C, D, H, W) grid; "
        f"load average {load:.2f}"
    )
    spconv_cols = (
        " | spconv fwd ms | ratio | spconv fwd + bwd ms | ratio | rel. diff" if reference else ""
    )
    print(
        "| layer | kind | sites in -> out | channels | pairs | aten ops fwd / fwd + bwd "
        "| rules ms | forward ms | fwd + bwd ms | dense forward ms | dense fwd + bwd ms "
        f"| forward ratio{spconv_cols} |"
    )
    print("|---" * (12 + 5 * bool(reference)) + "|")

    totals = {"sparse": 0.0, "dense": 0.0}
    keys = set()  # a submanifold layer reuses the rules of the first layer with its indice_key
    for layer, (conv, x) in inputs.items():
        t = _spconv_layer_times(conv, x, device, repeats, reference)
        built = not conv.subm or conv.indice_key is None or conv.indice_key not in keys
        keys.add(conv.indice_key)
        totals["sparse"] += t["rules"] * built + t["forward"]
        totals["dense"] += t["dense"]
        kind = "subm" if conv.subm else "spconv"
        kernel = "x".join(map(str, conv.kernel_size))
        stride = "" if conv.subm else " /" + "x".join(map(str, conv.stride))
        row = (
            f"| {layer} | {kind} {kernel}{stride} | {x.indices.shape[0]:,} -> {t['out_sites']:,} "
            f"| {conv.in_channels} -> {conv.out_channels} | {t['pairs']:,} "
            f"| {t['ops_forward']} / {t['ops_backward']} "
            f"| {t['rules'] * 1e3:,.1f} | {t['forward'] * 1e3:,.1f} | {t['backward'] * 1e3:,.1f} "
            f"| {t['dense'] * 1e3:,.1f} | {t['dense_backward'] * 1e3:,.1f} "
            f"| {t['dense'] / (t['rules'] + t['forward']):.1f}x |"
        )
        if reference:
            row += (
                f" {t['spconv'] * 1e3:,.1f} | **{t['ours'] / t['spconv']:.2f}x** "
                f"| {t['spconv_backward'] * 1e3:,.1f} "
                f"| **{t['ours_backward'] / t['spconv_backward']:.2f}x** | {t['diff']:.1e} |"
            )
        print(row)
    with torch.no_grad():
        whole_s = _timed(lambda: backbone(dict(batch)), device, repeats)
    print(
        f"\nwhole backbone forward (rules, convs, BatchNorm, ReLU): {whole_s * 1e3:,.1f} ms; "
        f"its conv layers' forward and the rules they build (a submanifold layer reuses its "
        f"indice_key's) {totals['sparse'] * 1e3:,.1f} ms against "
        f"{totals['dense'] * 1e3:,.1f} ms dense ({totals['dense'] / totals['sparse']:.1f}x)"
    )
    if reference:
        print(
            "spconv ratio: ours / spconv, rules included, fastest of alternating calls (below 1: "
            "ours faster); rel. diff: max |ours - spconv| / max |spconv| of the outputs"
        )


def _spconv_reference():
    """spconv 2.x's ``spconv.pytorch`` when importable, else None. Its CPU backward asks
    ``torch.cuda`` for a stream it does not use on the CPU, which raises on a CPU-only torch:
    that lookup answers 0 there (the benchmark's process only)."""
    try:
        import spconv.pytorch as reference
        import spconv.pytorch.ops as reference_ops
    except ImportError:
        return None
    if not torch.cuda.is_available():
        reference_ops.get_current_stream = lambda: 0
    return reference


def _count_ops(fn) -> int:
    """aten ops one call of ``fn`` runs (``torch.profiler`` on the CPU): what a GPU launches."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn()
    return sum(
        1
        for e in prof.events()
        if e.name.startswith("aten::")
        and (e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::"))
    )


def _spconv_layer_times(conv, x, device: torch.device, repeats: int, reference=None) -> dict:
    """Seconds of one sparse conv layer on its input ``x`` (rules from scratch, forward, forward
    + backward to the features and weights), of ``conv3d`` on ``x.dense()`` and, with
    ``reference`` (spconv), of spconv's layer with the same weights, alternating with ours."""
    from pcdet_atlas.ops.spconv import SparseConvTensor

    def fresh():  # no cached rules
        return SparseConvTensor(x.features, x.indices, x.spatial_shape, x.batch_size)

    def backward(fn, leaf):
        def run():
            leaf.grad = conv.weight.grad = None
            fn(leaf).square().mean().backward()

        return run

    rules = conv._rules(fresh())
    out = {"rules": _timed(lambda: conv._rules(fresh()), device, repeats)}
    with torch.no_grad():
        out["forward"] = _timed(lambda: conv.apply_rules(x.features, rules), device, repeats)
    feats = x.features.detach().clone().requires_grad_(True)
    out["backward"] = _timed(backward(lambda f: conv.apply_rules(f, rules), feats), device, repeats)
    dense = x.dense().detach().clone().requires_grad_(True)
    with torch.no_grad():
        out["dense"] = _timed(lambda: _dense_conv(conv, dense), device, repeats)
    out["dense_backward"] = _timed(backward(lambda d: _dense_conv(conv, d), dense), device, repeats)
    out["pairs"] = rules.num_pairs
    out["out_sites"] = int(rules.out_indices.shape[0])
    with torch.no_grad():
        out["ops_forward"] = _count_ops(lambda: conv(fresh()))
    out["ops_backward"] = _count_ops(
        backward(lambda f: conv(SparseConvTensor(f, x.indices, x.spatial_shape, x.batch_size))
                 .features, feats)
    )  # fmt: skip
    if reference is not None:
        out.update(_versus_spconv(conv, x, device, repeats, reference))
    return out


def _versus_spconv(conv, x, device: torch.device, repeats: int, reference) -> dict:
    """Our layer and spconv's with the same weights, each call from a fresh tensor (rules
    included), forward and forward + backward, alternating call by call; fastest of each."""
    from pcdet_atlas.ops.spconv import SparseConvTensor

    theirs_cls = reference.SubMConv3d if conv.subm else reference.SparseConv3d
    theirs = theirs_cls(
        conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride, conv.padding,
        conv.dilation, bias=conv.bias is not None, indice_key=conv.indice_key,
    ).to(device)  # fmt: skip
    theirs.load_state_dict(conv.state_dict())
    features = x.features.detach().contiguous()
    tensors = {"ours": SparseConvTensor, "spconv": reference.SparseConvTensor}
    layers = {"ours": conv, "spconv": theirs}

    def forward(side, leaf=None):
        sparse = tensors[side](
            features if leaf is None else leaf, x.indices, x.spatial_shape, x.batch_size
        )
        return layers[side](sparse)

    def backward(side):
        leaf = features.clone().requires_grad_(True)
        layers[side].weight.grad = None
        forward(side, leaf).features.square().mean().backward()

    def sort_rows(t):  # spconv's regular-conv output order may differ: compare by site
        return t.features[torch.argsort(_site_keys(t.indices, t.spatial_shape))]

    with torch.no_grad():
        ours, theirs_out = forward("ours"), forward("spconv")
        if not torch.equal(
            torch.sort(_site_keys(ours.indices, ours.spatial_shape)).values,
            torch.sort(_site_keys(theirs_out.indices, theirs_out.spatial_shape)).values,
        ):
            raise SystemExit("--spconv: our output sites differ from spconv's")
        want = sort_rows(theirs_out)
        diff = float((sort_rows(ours) - want).abs().max() / want.abs().max().clamp_min(1e-30))
    times: dict = {k: [] for k in ("ours", "spconv", "ours_backward", "spconv_backward")}
    for i in range(repeats + 1):
        for side in ("ours", "spconv"):
            with torch.no_grad():
                t = _timed_once(lambda side=side: forward(side), device)
            t_bwd = _timed_once(lambda side=side: backward(side), device)
            if i:  # the first round warms up
                times[side].append(t)
                times[f"{side}_backward"].append(t_bwd)
    return {"diff": diff, **{k: min(v) for k, v in times.items()}}


def _site_keys(indices: torch.Tensor, shape) -> torch.Tensor:
    d, h, w = shape
    idx = indices.long()
    return ((idx[:, 0] * d + idx[:, 1]) * h + idx[:, 2]) * w + idx[:, 3]


def _timed_once(fn, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def main() -> None:
    args = parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.child:  # one --train_step process (see train_step_table)
        print(json.dumps(_train_step_child(args.train_cfgs[0], args.data_path, args)))
        return
    device = torch.device(args.device)
    if args.latency_child:  # one --baseline_src latency process (see latency_compare_table)
        print(json.dumps(_latency_child(args.cfgs, Path(args.data_path), args, device)))
        return
    all_cfgs = sorted(str(p) for p in (REPO_ROOT / "cfgs" / "atlas").rglob("*.yaml"))
    cfg_files = all_cfgs if args.cfgs is None else args.cfgs
    # absolute: a --baseline_src tree would resolve a relative path against itself
    data_path = resolve_cli_path(args.data_path)
    tmp = None
    if not (data_path / "ImageSets" / "val.txt").is_file():
        from pcdet_atlas.datasets.synthetic import create_synthetic_waymo

        tmp = tempfile.TemporaryDirectory()
        data_path = Path(tmp.name)
        print(f"no dataset at {args.data_path}: generating a tiny one in {data_path}")
        create_synthetic_waymo(
            data_path, num_sequences={"train": 1, "val": 1},
            frames_per_sequence={"train": 10, "val": max(args.frames + 33, 34 + args.share_frames)},
            seed=0,
        )  # fmt: skip

    if args.train_step:
        train_step_table(args, data_path)
    elif args.vfe_forms:
        vfe_forms_table(cfg_files, data_path, args, device)
    elif cfg_files and args.baseline_src:
        latency_compare_table(cfg_files, data_path, args, device)
    elif cfg_files:
        latency_table(cfg_files, data_path, args, device)
    if args.share_cfg is not None:
        test_step_shares(args.share_cfg, data_path, args.share_frames, device)
    if args.bank_cfg is not None:
        bank_table(args.bank_cfg, data_path, args, device)
    if args.ssm:
        ssm_table(args.ssm_lengths, args.frames, device)
    if args.spconv is not None:
        spconv_table(args.spconv, data_path, args, device)
    if args.reuse_cfgs:
        reuse_table([str(Path(c).resolve()) for c in args.reuse_cfgs], data_path, args, device)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    run_tool(main)
