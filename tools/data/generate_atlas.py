"""Write one ATLAS variant of a Waymo-format split to disk, in OpenPCDet's layout (docs/attacks.md).

    python tools/data/generate_atlas.py --data_cfg cfgs/dataset_configs/synthetic_waymo.yaml \
        --attack cfgs/attacks/inj_global_hard.yaml --out_dir data/atlas/inj_global_hard

Output under ``--out_dir`` (a dataset root that ``WaymoDataset`` reads unchanged)::

    ImageSets/<split>.txt
    waymo_processed_data_v0_5_0/<seq>/%04d.npy     # attacked frames, raw (N, 6) as the converter
    waymo_processed_data_v0_5_0/<seq>/<seq>.pkl    # the source infos (+ 'atlas' per frame)
    waymo_processed_data_v0_5_0/<seq>/<seq>_atlas.pkl   # per-frame attack metadata
    atlas_attack_metadata.pkl     # {'variant', 'attack_cfg', 'frames': {frame_id: meta}}
    atlas_attack.yaml                              # the merged attack config

Rows of an attacked frame: the kept source rows in their order (the attack acts on every row of
the file, NLZ rows included, as ``AtlasWaymoDataset`` does), then the phantom's rows
``[x, y, z, intensity, elongation, -1]`` with raw features. Loading the written frame with any
``DATA_CONFIG`` therefore gives exactly the points ``AtlasWaymoDataset`` serves on the fly with
that config. ``num_points_of_each_lidar`` counts the rows kept of each LiDAR, and the phantom
rows (returns of the TOP LiDAR the raycaster models) in the TOP count, so the counts sum to the
frame's rows; ``info['atlas']['num_injected_rows']`` is the number of phantom rows, the last rows
of the file (:func:`~pcdet_atlas.attacks.lidar_fit.top_lidar_points` finds the TOP rows by
both). Labels are the source labels (attack targets are in the metadata, apart from the ground
truth).

Resumable: a sequence whose ``<seq>.pkl`` and ``<seq>_atlas.pkl`` exist for the same variant and
the same merged attack config is skipped; another config (e.g. ``--set SEED 1``) is an error naming
the keys that differ, never a silent mix; a sequence interrupted midway is redone. An ``--out_dir``
that is, contains or lies inside the source ``DATA_PATH`` (symlinks resolved) is an error, and so
is a folder in it that leads out of it (a symlink); a file at a name the tool writes is replaced
whole, a symlink there included, never written through.
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pcdet_atlas.attacks.atlas_dataset import AtlasWaymoDataset
from pcdet_atlas.config import (
    ConfigError,
    cfg_from_list,
    cfg_from_yaml_file,
    resolve_cli_path,
    resolve_repo_path,
    save_config,
    to_plain,
)
from pcdet_atlas.datasets import waymo_format as wf
from pcdet_atlas.datasets.fingerprint import sequence_label_sha256
from pcdet_atlas.utils.cli import add_debug_flag, add_set_flag, run_tool
from pcdet_atlas.utils.common import create_logger, save_pickle
from pcdet_atlas.utils.files import write_atomic
from pcdet_atlas.utils.paths import join_under, safe_component
from pcdet_atlas.utils.safe_pickle import load_pickle

CLASS_NAMES = ["Vehicle", "Pedestrian", "Cyclist"]


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_debug_flag(parser)
    parser.add_argument("--data_cfg", required=True, help="DATA_CONFIG yaml of the source")
    parser.add_argument("--attack", required=True, help="attack yaml (cfgs/attacks/*.yaml)")
    parser.add_argument("--out_dir", required=True, help="root of the written dataset")
    parser.add_argument("--split", default=None, help="split name (default: DATA_SPLIT.test)")
    parser.add_argument("--max_sequences", type=int, default=None, help="first N sequences only")
    add_set_flag(parser, help="overrides of the attack config")
    return parser.parse_args(argv)


def _lidar_counts(keep_rows: np.ndarray, counts: list[int], num_injected: int) -> list[int]:
    """Rows per LiDAR of an attacked frame: the kept source rows of each (from the source's
    per-LiDAR row counts), plus the ``num_injected`` phantom rows in the TOP count."""
    edges = np.concatenate([[0], np.cumsum(counts)])
    kept = [int(keep_rows[a:b].sum()) for a, b in zip(edges[:-1], edges[1:])]
    kept[0] += int(num_injected)
    return kept


def _flatten(node, prefix: str = "") -> dict:
    """``{'A.B': value}`` of a nested plain config."""
    if not isinstance(node, dict):
        return {prefix: node}
    out: dict = {}
    for key, value in node.items():
        out.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def write_sequence(
    dataset: AtlasWaymoDataset, seq_name: str, out_root: Path, progress, attack_cfg: dict
) -> dict:
    """Attack and write every frame of one sequence; returns ``{frame_id: meta}``."""
    attack = dataset.attack
    seq = dataset.sequence_data(seq_name)
    out_seq = output_sequence_dir(out_root, seq_name, dataset.processed_data_tag)
    out_seq.mkdir(parents=True, exist_ok=True)
    infos, metas = [], {}
    for idx in range(seq.num_frames):
        src = wf.frame_npy_path(dataset.root_path, seq_name, idx, dataset.processed_data_tag)
        raw = wf.load_frame_points(src)
        info = copy.deepcopy(seq.infos[idx])
        if attack.needs_simulation(idx, seq.num_frames):
            result = attack.simulate(raw, seq, idx)  # every row of the file, as the loader does
            out = result.apply(raw, fill_value=-1.0)  # added rows: not in a no-label zone
            keep_rows = np.ones(len(raw), dtype=bool) if result.keep is None else result.keep
            info["num_points_of_each_lidar"] = _lidar_counts(
                keep_rows, info["num_points_of_each_lidar"], len(result.added)
            )
            info["atlas"] = {"variant": attack.variant, "num_injected_rows": len(result.added)}
            meta = result.meta
        else:
            out = raw
            info["atlas"] = {"variant": attack.variant, "num_injected_rows": 0}
            meta = attack.frame_meta(seq, idx)
        wf.save_frame_points(out_seq / f"{idx:04d}.npy", out)
        infos.append(info)
        metas[info["frame_id"]] = meta
        progress.update(1)
    saved = {"variant": attack.variant, "attack_cfg": attack_cfg, "frames": metas,
             "source": _source(dataset, seq_name)}  # fmt: skip
    save_pickle(saved, out_seq / f"{seq_name}_atlas.pkl")
    wf.save_sequence_infos(out_seq / f"{seq_name}.pkl", infos)  # written last: the done marker
    return metas


def output_sequence_dir(out_root: Path, seq_name: str, tag: str) -> Path:
    """A sequence's folder under ``--out_dir`` (the path ``waymo_format.sequence_dir`` names),
    kept there with its symlinks resolved: a resumed ``--out_dir`` whose sequence folder is a
    symlink leading out of it is refused, not written through."""
    return join_under(
        out_root, (tag, "PROCESSED_DATA_TAG"), (seq_name, "sequence name"),
        source=f"--out_dir {out_root}",
    )  # fmt: skip


def _source(dataset: AtlasWaymoDataset, seq_name: str) -> dict:
    """What a written sequence was attacked from: the source root and its frame count (synthetic
    sequence names repeat across datasets generated with the same seed)."""
    return {"root": str(Path(dataset.root_path).resolve()),
            "num_frames": len(dataset.seq_name_to_infos[seq_name])}  # fmt: skip


def _done(
    out_seq: Path, seq_name: str, variant: str, attack_cfg: dict, source: dict
) -> dict | None:
    meta_pkl, info_pkl = out_seq / f"{seq_name}_atlas.pkl", out_seq / f"{seq_name}.pkl"
    if not (meta_pkl.is_file() and info_pkl.is_file()):
        return None
    saved = load_pickle(meta_pkl)
    if not isinstance(saved, dict):
        raise ValueError(
            f"{meta_pkl}: expected a dict, as this tool writes it, got {type(saved).__name__}; "
            "use another --out_dir or delete it"
        )
    frames = saved.get("frames")
    if not isinstance(frames, dict):
        raise ValueError(
            f"{meta_pkl}: 'frames' is a {type(frames).__name__}, expected a dict "
            "{frame_id: record}; use another --out_dir or delete it"
        )
    for frame, record in frames.items():
        if not isinstance(record, dict):
            raise ValueError(
                f"{meta_pkl}: 'frames'[{frame!r}] is a {type(record).__name__}, expected a dict "
                "(the frame's attack record); use another --out_dir or delete it"
            )
    if saved.get("variant") != variant:
        raise ValueError(
            f"{meta_pkl}: holds variant {saved.get('variant')!r}, not {variant!r}; "
            "use another --out_dir"
        )
    if saved.get("source") != source:
        raise ValueError(
            f"{meta_pkl}: attacked from {saved.get('source')}, not {source}; use another "
            "--out_dir or delete it"
        )
    old, new = _flatten(saved.get("attack_cfg", {})), _flatten(attack_cfg)
    differ = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if differ:
        raise ValueError(
            f"{meta_pkl}: written with another attack config of {variant!r} (keys {differ}: "
            f"{[old.get(k) for k in differ]} there, {[new.get(k) for k in differ]} now); "
            "use another --out_dir or delete it"
        )
    return frames


def check_out_dir(out_root: Path, data_root: Path) -> None:
    """Refuse an output root that is, contains or lies inside the source dataset root (symlinks
    resolved): writing there would replace clean frames and sequence infos with attacked ones."""
    out_real, data_real = out_root.resolve(), data_root.resolve()
    if out_real == data_real:
        relation = "is"
    elif data_real in out_real.parents:
        relation = "lies inside"
    elif out_real in data_real.parents:
        relation = "contains"
    else:
        return
    raise ValueError(
        f"--out_dir {out_root} (resolved: {out_real}) {relation} the source DATA_PATH "
        f"{data_root} (resolved: {data_real}); writing there would overwrite the clean data: "
        "choose an --out_dir outside the source dataset"
    )


def main(argv=None) -> Path:
    args = parse_args(argv)
    logger = create_logger()
    data_cfg = cfg_from_yaml_file(args.data_cfg)
    out_root = resolve_cli_path(args.out_dir)
    if "DATA_PATH" not in data_cfg:
        raise ConfigError(f"{args.data_cfg}: no DATA_PATH (the source dataset root)")
    check_out_dir(out_root, resolve_repo_path(data_cfg.DATA_PATH))
    attack_cfg = cfg_from_yaml_file(args.attack)
    if args.set_cfgs:
        cfg_from_list(args.set_cfgs, attack_cfg)
    if args.split is not None:
        data_cfg.DATA_SPLIT["test"] = args.split
    data_cfg.SAMPLED_INTERVAL["test"] = 1
    dataset = AtlasWaymoDataset(data_cfg, CLASS_NAMES, attack_cfg, training=False, logger=logger)
    plain_cfg = to_plain(attack_cfg)
    names = list(dataset.seq_name_to_infos)[: args.max_sequences]
    listing = "".join(f"{name}.tfrecord\n" for name in names)
    image_sets = join_under(out_root, ("ImageSets", "folder"), source=f"--out_dir {out_root}")
    where = "--split" if args.split is not None else f"DATA_SPLIT.test of {args.data_cfg}"
    split = safe_component(dataset.split, "split", where)
    write_atomic(image_sets / f"{split}.txt", lambda f: f.write(listing.encode()))
    total = sum(len(dataset.seq_name_to_infos[n]) for n in names)
    frames: dict[str, dict] = {}
    with tqdm(total=total, desc=dataset.attack.variant, unit="frame") as progress:
        for name in names:
            out_seq = output_sequence_dir(out_root, name, dataset.processed_data_tag)
            done = _done(out_seq, name, dataset.attack.variant, plain_cfg, _source(dataset, name))
            if done is not None:
                frames.update(done)
                progress.update(len(dataset.seq_name_to_infos[name]))
                continue
            frames.update(write_sequence(dataset, name, out_root, progress, plain_cfg))
    summary = {
        "variant": dataset.attack.variant,
        "attack_cfg": plain_cfg,
        "frames": frames,
        "source_label_sha256": sequence_label_sha256(
            dataset.root_path, names, dataset.processed_data_tag
        ),
    }
    save_pickle(summary, out_root / "atlas_attack_metadata.pkl")
    save_config(attack_cfg, out_root / "atlas_attack.yaml")
    spoofed = sum(m["spoofed"] for m in frames.values())
    logger.info(
        f"wrote {len(frames)} frames ({spoofed} spoofed) of {len(names)} sequences to {out_root}"
    )
    return out_root


if __name__ == "__main__":
    run_tool(main)
