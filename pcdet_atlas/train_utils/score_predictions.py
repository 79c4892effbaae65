"""Scoring predictions a detector made anywhere: per-frame detections in, ``results.json`` out.

A detector this package does not implement (another toolkit's model, an in-house one) predicts
on the test split, clean or attacked (``tools/data/generate_atlas.py`` writes the attacked data);
its per-frame detections then get the same ``results.json`` entry :func:`evaluate_variant`
gives the project's own models: Waymo L1/L2 AP/APH and, for an attack variant, ASR with its
interval and per-run counts, confidence and lifecycle. The attack's targets, runs and lifecycle
come from the attack itself: the variant's ``AtlasWaymoDataset`` gives each frame's metadata
record exactly as it serves it to a model (a spoofed frame is simulated for it), or from the
records a ``tools/data/generate_atlas.py`` output holds (:func:`load_generated_variant`; the same
records, read instead of simulated).

Predictions are OpenPCDet anno dicts, one per frame of the split (any order): ``name`` ``(K,)``
class names of the data's ``CLASS_NAMES``, ``score`` ``(K,)`` in [0, 1], ``boxes_lidar``
``(K, 7)`` or ``(K, 9)`` (x, y, z, dx, dy, dz, heading[, vx, vy]) in the vehicle frame of the
converter, and ``frame_id`` or ``metadata`` with ``context_name`` and ``timestamp_micros`` to
find the frame. Scores and boxes are read as float32, as the project's models write them.
:func:`read_predictions` reads them from OpenPCDet's ``result.pkl`` (restricted unpickler), a
JSON list of such frames, a folder of one ``.npz`` per frame or Waymo's submission ``.bin``
(:mod:`pcdet_atlas.datasets.waymo_submission`; docs/evaluation.md "Scoring predictions made
anywhere").
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pcdet_atlas.attacks.base import BaseAttack, build_attack
from pcdet_atlas.config import ConfigError, cfg_from_yaml_file
from pcdet_atlas.datasets.fingerprint import sequence_label_sha256
from pcdet_atlas.datasets.waymo_submission import PredictionError, read_waymo_bin
from pcdet_atlas.evaluation import (
    build_results,
    save_results,
)
from pcdet_atlas.registry import DATASETS
from pcdet_atlas.train_utils.atlas_eval import (
    build_variant_attacks,
    entry_summary,
    resolve_variants,
    variant_entry,
    variant_fingerprints,
)
from pcdet_atlas.utils.provenance import source_revision
from pcdet_atlas.utils.safe_pickle import load_pickle

__all__ = [
    "ATLAS_METADATA",
    "FORMATS",
    "GeneratedVariant",
    "is_generated_spec",
    "load_generated_variant",
    "PredictionError",
    "match_predictions",
    "predictions_format",
    "read_predictions",
    "score_predictions",
    "score_variant",
]

#: the file formats :func:`read_predictions` reads
FORMATS = ("pkl", "json", "npz", "bin")
#: formats in which a frame without detections is absent (it has no object to write)
ABSENT_IS_EMPTY = ("bin",)
BOX_WIDTHS = (7, 9)
#: what ``tools/data/generate_atlas.py`` writes in its output root: the per-frame attack records
#: (``{'variant', 'attack_cfg', 'frames': {frame_id: record}}``) and the merged attack config
ATLAS_METADATA = "atlas_attack_metadata.pkl"
ATLAS_ATTACK_YAML = "atlas_attack.yaml"


@dataclass(frozen=True)
class GeneratedVariant:
    """A variant written by ``tools/data/generate_atlas.py``: its name, merged attack config,
    per-frame attack records (``{frame_id: record}``, the records ``AtlasWaymoDataset`` gives) and
    the SHA-256 of each source sequence's info pkl (``{sequence: sha}``; None from an output
    written before it was recorded)."""

    name: str
    attack_yaml: Path
    records: Mapping[str, Mapping]
    source_label_sha256: Mapping[str, str] | None = None


def check_generated_source(variant: GeneratedVariant, split) -> None:
    """Refuse scoring ``variant``'s records against a test split whose sequences carry other
    labels than the ones it was generated from (synthetic sequence names repeat across datasets
    generated with one seed); an output that recorded no source is scored with a warning."""
    meta = variant.attack_yaml.parent / ATLAS_METADATA
    if variant.source_label_sha256 is None:
        logging.getLogger("pcdet_atlas").warning(
            f"{meta}: records no source labels (written by an older version): its frames are "
            "matched to the test split by frame_id alone"
        )
        return
    recorded = variant.source_label_sha256
    names = sorted({i["point_cloud"]["lidar_sequence"] for i in split.infos} & set(recorded))
    now = sequence_label_sha256(split.root_path, names, split.processed_data_tag)
    differ = [n for n in names if recorded[n] != now[n]]  # one not recorded: its records lack
    if differ:
        raise PredictionError(
            f"{meta}: generated from other labels than the test split's for {len(differ)} of its "
            f"{len(names)} sequences, the first {differ[0]!r} (info pkl SHA-256 "
            f"{recorded[differ[0]]} there, {now[differ[0]]} in "
            f"{split.root_path}): generated from another dataset?"
        )


def is_generated_spec(spec: str) -> bool:
    """Whether a ``--predictions`` variant names a ``tools/data/generate_atlas.py`` output: a folder
    given as a path (``data/atlas/rem_40``, ``./rem_40``); a bare name (``rem_40``) is an attack
    name even where a folder of that name sits in the working directory."""
    return ("/" in spec or os.sep in spec) and Path(spec).is_dir()


def load_generated_variant(folder: str | Path) -> GeneratedVariant:
    """The variant of a ``tools/data/generate_atlas.py`` output root (restricted unpickler).

    Raises:
        PredictionError: naming the file, for a folder without the metadata or the attack
            config, or metadata that is not the generator's (and the frame, for a record that is
            not a dict).
    """
    folder = Path(folder)
    meta_path, yaml_path = folder / ATLAS_METADATA, folder / ATLAS_ATTACK_YAML
    for path in (meta_path, yaml_path):
        if not path.is_file():
            raise PredictionError(
                f"{folder}: no {path.name}; not a tools/data/generate_atlas.py output (variants "
                "are an attack name, an attack YAML or such an output folder)"
            )
    summary = load_pickle(meta_path)
    if (
        not isinstance(summary, Mapping)
        or not isinstance(summary.get("variant"), str)
        or not isinstance(summary.get("frames"), Mapping)
    ):
        raise PredictionError(
            f"{meta_path}: expected a dict with 'variant' (a name) and 'frames' ({{frame_id: "
            "record}}), as tools/data/generate_atlas.py writes it"
        )
    for frame, record in summary["frames"].items():
        if not isinstance(record, Mapping):
            raise PredictionError(
                f"{meta_path}: 'frames'[{frame!r}] is a {type(record).__name__}, expected a dict "
                "(the frame's attack record), as tools/data/generate_atlas.py writes it"
            )
    source = summary.get("source_label_sha256")
    if source is not None and not isinstance(source, Mapping):
        raise PredictionError(
            f"{meta_path}: 'source_label_sha256' is a {type(source).__name__}, expected a dict "
            "({sequence: sha256}), as tools/data/generate_atlas.py writes it"
        )
    return GeneratedVariant(summary["variant"], yaml_path.resolve(), summary["frames"], source)


def _frame_label(index: int, frame: object) -> str:
    """How an error names the ``index``-th frame of a file (with its id where it has one)."""
    if isinstance(frame, Mapping):
        if "frame_id" in frame:
            return f"frame {index} ({frame['frame_id']!r})"
        meta = frame.get("metadata")
        if isinstance(meta, Mapping) and {"context_name", "timestamp_micros"} <= set(meta):
            return f"frame {index} ({meta['context_name']!r}, {meta['timestamp_micros']!r})"
    return f"frame {index}"


def predictions_format(path: str | Path, fmt: str | None = None) -> str:
    """The format of a predictions file or folder: ``fmt`` (checked), else a folder is
    ``npz``, a file is known by its extension (``.pkl``, ``.json``, ``.bin``), else by its
    first byte (a pickle's protocol opcode, a JSON ``[``, an ``Objects`` message's first tag).

    Raises:
        PredictionError: naming the file, for an unknown format or a file that is not there.
    """
    path = Path(path)
    if fmt is not None and fmt not in FORMATS:
        raise PredictionError(f"{path}: unknown predictions format {fmt!r} (known: {FORMATS})")
    if fmt is None and path.is_dir():
        return "npz"
    if fmt != "npz" and not path.is_file():
        raise PredictionError(f"{path}: no such predictions file")
    return fmt or _detect_format(path)


def read_predictions(path: str | Path, fmt: str | None = None) -> tuple[list, list[str]]:
    """The per-frame prediction dicts of a file or folder and, per frame, where it was read
    (the file; each frame's own file for ``npz``).

    Formats (:data:`FORMATS`, :func:`predictions_format`): OpenPCDet's ``result.pkl``
    (``pkl``, a list of dicts, read without running code), a JSON list of frames (``json``), a
    folder of ``.npz`` files, one per frame (``npz``, read without pickles: arrays ``name``,
    ``score``, ``boxes_lidar`` and ``frame_id``, or ``context_name`` and ``timestamp_micros``),
    or Waymo's submission ``.bin`` (``bin``: only the frames with detections,
    :func:`~pcdet_atlas.datasets.waymo_submission.read_waymo_bin`).

    Raises:
        PredictionError: naming the file, for an unknown format, a file that holds no list, an
            unreadable ``.npz`` or a bad ``.bin``.
    """
    path = Path(path)
    fmt = predictions_format(path, fmt)
    if fmt == "npz":
        return _read_npz_folder(path)
    if fmt == "bin":
        frames = read_waymo_bin(path)
    elif fmt == "pkl":
        frames = load_pickle(path)
    else:
        try:
            frames = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise PredictionError(f"{path}: not a JSON predictions file ({err})") from None
    if not isinstance(frames, list):
        raise PredictionError(
            f"{path}: holds a {type(frames).__name__}, expected a list of per-frame dicts"
        )
    return frames, [str(path)] * len(frames)


def _read_npz_folder(path: Path) -> tuple[list, list[str]]:
    """The frames of a folder of ``.npz`` files (:func:`read_predictions`), in file-name order."""
    if not path.is_dir():
        raise PredictionError(f"{path}: no such folder of per-frame .npz files")
    files = sorted(path.glob("*.npz"))
    if not files:
        raise PredictionError(f"{path}: holds no .npz file (one per frame expected)")
    frames = []
    for file in files:
        try:
            with np.load(file, allow_pickle=False) as npz:
                frame = {key: npz[key] for key in npz.files}
        except (OSError, ValueError, zipfile.BadZipFile) as err:
            raise PredictionError(f"{file}: not a readable .npz of arrays ({err})") from None
        if "frame_id" in frame:
            frame["frame_id"] = str(frame["frame_id"])
        if "context_name" in frame and "timestamp_micros" in frame:
            context, stamp = frame.pop("context_name"), frame.pop("timestamp_micros")
            frame["metadata"] = {"context_name": str(context), "timestamp_micros": int(stamp)}
        frames.append(frame)
    return frames, [str(file) for file in files]


def _detect_format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix in (".pkl", ".pickle"):
        return "pkl"
    if suffix == ".json":
        return "json"
    if suffix == ".bin":
        return "bin"
    with path.open("rb") as f:
        raw = f.read(64)
    head = raw.lstrip()
    if head[:1] == b"\x80":
        return "pkl"
    if head[:1] == b"[":
        return "json"
    if raw[:1] == b"\x0a":  # field 1 (Objects.objects), length-delimited
        return "bin"
    raise PredictionError(
        f"{path}: cannot tell the predictions format from its name or content; pass --format "
        f"({' or '.join(FORMATS)})"
    )


def _float_array(value, where: str, field: str) -> np.ndarray:
    try:
        out = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise PredictionError(f"{where}: field {field!r} is not numeric") from None
    if not np.all(np.isfinite(out)):
        bad = np.argwhere(~np.isfinite(out))[0].tolist()
        raise PredictionError(
            f"{where}: field {field!r} holds a NaN or infinite value (at index {bad})"
        )
    return out


def _check_frame(frame: object, where: str, class_names: Sequence[str]) -> dict:
    """One frame's ``name``, ``score``, ``boxes_lidar`` and ``pred_labels``, checked."""
    if not isinstance(frame, Mapping):
        raise PredictionError(f"{where}: a {type(frame).__name__}, expected a dict")
    for field in ("name", "score", "boxes_lidar"):
        if field not in frame:
            raise PredictionError(f"{where}: no field {field!r}")
    names = np.asarray(frame["name"]).reshape(-1).astype(str)
    kinds, kind_of = np.unique(names, return_inverse=True)  # (U,) names, (K,) index into them
    unknown = sorted(set(kinds.tolist()) - set(class_names))
    if unknown:
        raise PredictionError(
            f"{where}: field 'name' holds unknown class name(s) {unknown} (known: "
            f"{list(class_names)})"
        )
    score = _float_array(frame["score"], where, "score")
    if score.ndim != 1 or len(score) != len(names):
        raise PredictionError(
            f"{where}: field 'score' has shape {score.shape}, expected ({len(names)},): one "
            "per name"
        )
    if len(score) and (score.min() < 0 or score.max() > 1):
        raise PredictionError(
            f"{where}: field 'score' holds {float(score.min() if score.min() < 0 else score.max())}"
            ", outside [0, 1]"
        )
    boxes = _float_array(frame["boxes_lidar"], where, "boxes_lidar")
    if boxes.size == 0 and len(names) == 0:
        boxes = np.zeros((0, boxes.shape[-1] if boxes.ndim == 2 else 7))
    if boxes.ndim != 2 or boxes.shape[1] not in BOX_WIDTHS or len(boxes) != len(names):
        raise PredictionError(
            f"{where}: field 'boxes_lidar' has shape {boxes.shape}, expected ({len(names)}, 7) "
            f"or ({len(names)}, 9)"
        )
    kind_labels = [list(class_names).index(kind) + 1 for kind in kinds.tolist()]
    labels = np.array(kind_labels, dtype=np.int64)[kind_of.reshape(-1)]  # 1-based
    if "pred_labels" in frame:
        given = np.asarray(frame["pred_labels"]).reshape(-1)
        if given.shape != labels.shape or np.any(given != labels):
            raise PredictionError(
                f"{where}: field 'pred_labels' disagrees with 'name' (1-based indices into "
                f"{list(class_names)})"
            )
    return {
        "name": names.astype(f"<U{max(map(len, class_names))}"),
        "score": score.astype(np.float32),
        "boxes_lidar": boxes.astype(np.float32),
        "pred_labels": labels,
    }


def _frame_index(frame: Mapping, where: str, by_id: Mapping, by_time: Mapping) -> int:
    """The split index of a frame, by ``frame_id`` or by (context name, timestamp)."""
    found = None
    if "frame_id" in frame:
        found = by_id.get(str(frame["frame_id"]))
        if found is None:
            raise PredictionError(
                f"{where}: field 'frame_id' {frame['frame_id']!r} is not a frame of the test split "
                "(its DATA_SPLIT and SAMPLED_INTERVAL)"
            )
    meta = frame.get("metadata")
    if isinstance(meta, Mapping) and {"context_name", "timestamp_micros"} <= set(meta):
        key = (str(meta["context_name"]), int(meta["timestamp_micros"]))
        by_key = by_time.get(key)
        if by_key is None:
            raise PredictionError(
                f"{where}: field 'metadata' (context_name {key[0]!r}, timestamp_micros {key[1]}) "
                "is not a frame of the test split (its DATA_SPLIT and SAMPLED_INTERVAL)"
            )
        if found is not None and by_key is not None and by_key != found:
            raise PredictionError(
                f"{where}: field 'metadata' (context_name {key[0]!r}, timestamp_micros {key[1]}) "
                f"names another frame than its frame_id {frame['frame_id']!r}"
            )
        found = by_key if found is None else found
    if found is None:
        raise PredictionError(
            f"{where}: no field 'frame_id' and no 'metadata' with 'context_name' and "
            "'timestamp_micros' to find the frame by"
        )
    return found


def match_predictions(
    frames: Sequence,
    infos: Sequence[Mapping],
    class_names: Sequence[str],
    source: str,
    frame_sources: Sequence[str] | None = None,
    *,
    absent_is_empty: bool = False,
) -> list[dict]:
    """``frames`` (per-frame prediction dicts read from ``source``) checked and put in the order
    of ``infos`` (the split's frame infos; ``frame_sources``: each frame's own file, where it
    has one), one anno dict per info with the info's ``frame_id``
    and ``metadata``.

    ``absent_is_empty``: a split frame absent from ``frames`` is a frame without detections (a
    format that writes only objects, :data:`ABSENT_IS_EMPTY`); a sequence of the split with no
    frame in ``frames`` is still an error (a file of another split or a lost sequence).

    Raises:
        PredictionError: naming ``source``, the frame and the field, for a frame that is not a
            dict, is not in the split, is there twice or is missing; a missing field, a class
            name not in ``class_names``, a NaN or infinite value, a score outside [0, 1], or
            boxes of a width other than 7 or 9.
    """
    by_id = {str(info["frame_id"]): i for i, info in enumerate(infos)}
    by_time = {}
    for i, info in enumerate(infos):
        meta = info.get("metadata")
        if isinstance(meta, Mapping) and {"context_name", "timestamp_micros"} <= set(meta):
            by_time[(str(meta["context_name"]), int(meta["timestamp_micros"]))] = i
    out: list[dict | None] = [None] * len(infos)
    seen: dict[int, str] = {}
    for k, frame in enumerate(frames):
        where = f"{frame_sources[k] if frame_sources else source} [{_frame_label(k, frame)}]"
        checked = _check_frame(frame, where, class_names)
        index = _frame_index(frame, where, by_id, by_time)
        if index in seen:
            raise PredictionError(
                f"{where}: frame {infos[index]['frame_id']!r} is there twice (also {seen[index]})"
            )
        seen[index] = _frame_label(k, frame)
        info = infos[index]
        out[index] = {**checked, "frame_id": info["frame_id"],
                      "metadata": info.get("metadata", info["frame_id"])}  # fmt: skip
    missing = [info["frame_id"] for info, anno in zip(infos, out) if anno is None]
    if missing and absent_is_empty:
        _check_sequences_present(infos, out, source)
        logging.getLogger("pcdet_atlas").warning(
            f"{source}: {len(missing)} of the test split's {len(infos)} frames have no "
            f"predictions there, scored as frames without detections (the first "
            f"{missing[0]!r}); a lost frame scores as a missed target"
        )
        for index, anno in enumerate(out):
            if anno is None:
                info = infos[index]
                out[index] = {**_check_frame(_EMPTY, source, class_names),
                              "frame_id": info["frame_id"],
                              "metadata": info.get("metadata", info["frame_id"])}  # fmt: skip
        missing = []
    if missing:
        raise PredictionError(
            f"{source}: {len(missing)} of the test split's {len(infos)} frames have no "
            f"predictions, the first {missing[0]!r} (a frame without detections is a dict with "
            "empty 'name', 'score' and 'boxes_lidar')"
        )
    return out


_EMPTY = {"name": [], "score": [], "boxes_lidar": np.zeros((0, 7))}


def _sequence_of(info: Mapping) -> str:
    return str(info["point_cloud"]["lidar_sequence"]) if "point_cloud" in info else "?"


def _check_sequences_present(infos: Sequence[Mapping], out: Sequence, source: str) -> None:
    """Raise naming the first sequence of the split none of whose frames has predictions."""
    found: dict[str, bool] = {}
    for info, anno in zip(infos, out):
        seq = _sequence_of(info)
        found[seq] = found.get(seq, False) or anno is not None
    lost = [seq for seq, any_frame in found.items() if not any_frame]
    if lost:
        raise PredictionError(
            f"{source}: {len(lost)} of the test split's {len(found)} sequences have no "
            f"detection in any frame, the first {lost[0]!r} (predictions of another split, or "
            "a sequence left out?)"
        )


def score_variant(
    data_cfg: Mapping,
    class_names: Sequence[str],
    variant: str,
    attack: Mapping | Path | BaseAttack,
    frames: Sequence,
    *,
    source: str,
    frame_sources: Sequence[str] | None = None,
    clean_det_annos: Sequence[Mapping] | None = None,
    temporal_window: int | None = None,
    absent_is_empty: bool = False,
    records: Mapping[str, Mapping] | None = None,
    records_source: str = "",
    logger: logging.Logger | None = None,
) -> tuple[dict, list[dict]]:
    """One variant's ``results.json`` entry from its per-frame predictions ``frames`` (read
    from ``source``), as :func:`~pcdet_atlas.train_utils.atlas_eval.evaluate_variant` scores a
    model's: the variant's ``AtlasWaymoDataset`` gives each frame's attack record.

    ``clean_det_annos``: the clean variant's predictions (as this returns them), which an
    attack whose confidence analysis is the removal one (``CONFIDENCE == 'removal'``) needs.
    ``absent_is_empty``: as :func:`match_predictions` takes it (a ``.bin``'s frames).
    ``records``: each frame's attack record by ``frame_id``, read from ``records_source`` (a
    :class:`GeneratedVariant`'s), instead of the dataset's (which simulates a spoofed frame).

    Returns:
        ``(entry, det_annos)``: the entry (``num_reused_frames`` not recorded; ``extra`` with
        the source file and its SHA-256) and the checked predictions in the split's order, each
        with its ``attack`` record.

    Raises:
        PredictionError: bad predictions (:func:`match_predictions`), or no clean predictions
            for a variant that needs them.
    """
    t0 = time.perf_counter()
    dataset = DATASETS.get("AtlasWaymoDataset")(
        dataset_cfg=data_cfg, class_names=class_names, attack_cfg=attack, training=False,
        logger=logger,
    )  # fmt: skip
    needs_clean = dataset.attack.CONFIDENCE == "removal"
    if needs_clean and clean_det_annos is None:
        raise PredictionError(
            f"variant {variant!r} ({dataset.attack.family}): its confidence is scored against "
            "the clean predictions; pass clean=FILE with --predictions"
        )
    det_annos = match_predictions(
        frames, dataset.infos, class_names, source, frame_sources, absent_is_empty=absent_is_empty
    )
    for anno, info in zip(det_annos, dataset.infos):
        point_cloud = info["point_cloud"]
        sequence = point_cloud["lidar_sequence"]
        if records is None:
            anno["attack"] = dataset.frame_attack_meta(sequence, int(point_cloud["sample_idx"]))
        elif info["frame_id"] in records:
            anno["attack"] = {**records[info["frame_id"]], "sequence_name": sequence}
        else:
            raise PredictionError(
                f"{records_source}: no attack record of frame {info['frame_id']!r} of the test "
                "split (generated from another split or with --max_sequences?)"
            )
    timings = {"attack_records": time.perf_counter() - t0}
    attack_infos = [anno["attack"] for anno in det_annos]
    entry = variant_entry(
        variant, dataset, det_annos, attack_infos, class_names=class_names,
        clean_det_annos=clean_det_annos, temporal_window=temporal_window, timings=timings,
        extra={"predictions": str(source)},
    )  # fmt: skip
    if logger is not None:
        logger.info(entry_summary(variant, entry))
    return entry, det_annos


def _sha256(path: Path) -> str:
    """SHA-256 of a file, or of a folder's ``.npz`` files (names and bytes, in name order)."""
    digest = hashlib.sha256()
    if path.is_dir():
        for file in sorted(path.glob("*.npz")):
            digest.update(f"{file.name}\n".encode())
            digest.update(hashlib.sha256(file.read_bytes()).digest())
    else:
        digest.update(path.read_bytes())
    return digest.hexdigest()


def score_predictions(
    data_cfg: Mapping,
    class_names: Sequence[str],
    predictions: Mapping[str, str | Path],
    out_dir: str | Path,
    *,
    model: str,
    config: str,
    atlas_cfg: Mapping | None = None,
    temporal_window: int | None = None,
    fmt: str | None = None,
    logger: logging.Logger | None = None,
) -> dict:
    """Score prediction files and write ``out_dir/results.json`` (schema of ``tools/test.py``).

    Args:
        data_cfg, class_names: the test split's data config and class names.
        predictions: ``{variant: file}``; a variant is an attack name (``cfgs/attacks/<name>.yaml``)
            or the path of an attack YAML, as ``tools/test.py --attacks`` takes it, or the path
            of a ``tools/data/generate_atlas.py`` output folder (:func:`is_generated_spec`; its
            variant, attack config and per-frame attack records: :func:`load_generated_variant`).
        model, config: the ``results.json`` ``model`` and ``config`` fields.
        atlas_cfg: the model config's ``ATLAS`` section, if any (checked as ``--attacks`` does).
        temporal_window: the lifecycle window (a model config's ``ATLAS.TEMPORAL_WINDOW``).
        fmt: the files' format (:data:`FORMATS`); None: each file's own (:func:`read_predictions`).

    Returns:
        The results dict written (``results.json``, once every variant is scored, clean first:
        scoring is fast enough to redo whole).

    Raises:
        PredictionError: a bad file, frame or field, or an attack variant needing the clean
            predictions without ``clean`` among ``predictions``; before anything is written.
    """
    if not predictions:
        raise PredictionError("no predictions to score: pass --predictions VARIANT=FILE ...")
    files: dict[str, tuple[Path, Path]] = {}
    generated: dict[str, GeneratedVariant] = {}
    for spec, path in predictions.items():
        if is_generated_spec(spec):
            variant = load_generated_variant(spec)
            name, yaml_path = variant.name, variant.attack_yaml
            generated[name] = variant
        else:
            resolved = resolve_variants(spec, atlas_cfg or {})
            if len(resolved) != 1:
                raise PredictionError(
                    f"--predictions {spec}=...: names {len(resolved)} variants, not one"
                )
            ((name, yaml_path),) = resolved
        if name in files:
            raise PredictionError(f"variant {name!r} has predictions twice ({spec!r})")
        files[name] = (yaml_path, Path(path))
    variants = sorted(((n, p) for n, (p, _) in files.items()), key=lambda v: v[0] != "clean")
    if "DATASET" not in data_cfg:
        raise ConfigError("DATA_CONFIG has no DATASET name")
    split = DATASETS.get(data_cfg["DATASET"])(
        dataset_cfg=data_cfg, class_names=class_names, training=False, logger=logger
    )
    built = build_variant_attacks([v for v in variants if v[0] not in generated], split.root_path)
    for name, variant in generated.items():  # the merged config: VARIANT is not its file name
        built[name] = build_attack(
            cfg_from_yaml_file(variant.attack_yaml), data_root=split.root_path
        )
        if built[name].variant != name:
            raise PredictionError(
                f"{variant.attack_yaml}: variant {built[name].variant!r}, but its "
                f"{ATLAS_METADATA} holds {name!r}"
            )
        check_generated_source(variant, split)
        missing = [i["frame_id"] for i in split.infos if i["frame_id"] not in variant.records]
        if missing:
            raise PredictionError(
                f"{variant.attack_yaml.parent / ATLAS_METADATA}: no attack record of "
                f"{len(missing)} of the test split's {len(split.infos)} frames, the first "
                f"{missing[0]!r} (generated from another split or with --max_sequences?)"
            )
    attacks = {name: built[name] for name, _ in variants}
    fingerprints = variant_fingerprints(variants, attacks)
    if "clean" not in files:
        needing = [n for n, a in attacks.items() if a.CONFIDENCE == "removal"]
        if needing:
            raise PredictionError(
                f"variant(s) {needing} score their confidence against the clean predictions; "
                "pass clean=FILE with --predictions"
            )
    formats = {name: predictions_format(path, fmt) for name, (_, path) in files.items()}
    frames = {name: read_predictions(path, formats[name]) for name, (_, path) in files.items()}
    for name, (_, path) in files.items():  # every file checked before anything is written
        match_predictions(
            frames[name][0], split.infos, class_names, str(path), frames[name][1],
            absent_is_empty=formats[name] in ABSENT_IS_EMPTY,
        )  # fmt: skip
    entries: dict = {}
    clean = None
    source = source_revision()
    for name, attack in attacks.items():
        path = files[name][1]
        entry, det_annos = score_variant(
            data_cfg, class_names, name, attack, frames[name][0], source=str(path),
            frame_sources=frames[name][1], absent_is_empty=formats[name] in ABSENT_IS_EMPTY,
            clean_det_annos=clean, temporal_window=temporal_window, logger=logger,
            records=generated[name].records if name in generated else None,
            records_source=str(files[name][0].parent / ATLAS_METADATA),
        )  # fmt: skip
        if name == "clean":
            clean = det_annos
        extra = {**entry["extra"], "attack_sha256": fingerprints[name],
                 "predictions_sha256": _sha256(path)}  # fmt: skip
        if name in generated:
            extra["attack_records"] = str(files[name][0].parent / ATLAS_METADATA)
        entries[name] = {**entry, "extra": extra}
    results = build_results(
        model=model, config=config, checkpoint=None, class_names=class_names, variants=entries,
        source=source,
        extra={"scored_from": "predictions", "variants_requested": list(attacks)},
    )  # fmt: skip
    save_results(results, Path(out_dir) / "results.json")
    return results
