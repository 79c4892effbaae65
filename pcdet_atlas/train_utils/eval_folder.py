"""An evaluation's folder: where a checkpoint's evaluation is written, and which variants an
earlier call finished there that a resumed call keeps (``tools/test.py --resume``).

Layout, per checkpoint: ``<output_root>/<group>/<tag>/<extra_tag>/eval/<name>/<split>/<eval_tag>/``
(:func:`eval_dir`; ``<name>`` is ``epoch_N`` for ``checkpoint_epoch_N.pth``, the file name
without ``.pth`` otherwise) holding ``results.json``, ``<TAG>.yaml`` (the merged config),
``log_eval_<time>.txt`` and per variant ``<variant>/result.pkl`` (and, for the clean variant of a
model with a proposal bank, ``clean/proposals_rank<r>.pkl``: each process's clean proposals).
A variant's ``results.json`` entry records the SHA-256 of those files (``extra.result_sha256``,
the clean one's ``extra.proposals_sha256``: ``{file name: SHA-256}``), which a resumed call
compares before it reuses them (:func:`finished_variants`).
``extra_tag``, ``eval_tag``, the checkpoint's and each variant's file name and the data's frame
ids must each be one file or folder name (letters, digits, ``.``, ``_``, ``-``; not ``..``).
While it writes an evaluation folder, a run (its rank 0) holds that folder's lock
(``.<eval_tag>.lock`` beside it).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import yaml

from pcdet_atlas.config import ConfigError, resolve_cli_path, resolve_repo_path, to_plain
from pcdet_atlas.evaluation import load_results
from pcdet_atlas.train_utils.atlas_eval import atlas_section
from pcdet_atlas.train_utils.checkpoint import CHECKPOINT_NAME
from pcdet_atlas.train_utils.setup import output_dir_for
from pcdet_atlas.utils.hashing import file_sha256

__all__ = [
    "changed_kept_file",
    "check_eval_dir",
    "eval_dir",
    "eval_name",
    "finished_variants",
    "missing_proposal_parts",
    "proposal_hashes",
    "proposal_part",
    "resolve_checkpoint",
]


def resolve_checkpoint(arg: str | None, atlas_cfg) -> Path:
    """``--ckpt`` as typed (relative to the working directory), else the config's
    ``ATLAS.CHECKPOINT`` (relative to the repository root)."""
    if arg is not None:
        ckpt, path = arg, resolve_cli_path(arg)
    elif (ckpt := atlas_section(atlas_cfg).checkpoint) is not None:
        path = resolve_repo_path(ckpt)
    else:
        raise ConfigError("no checkpoint: pass --ckpt (the config's ATLAS.CHECKPOINT is null)")
    if not path.is_file():
        raise FileNotFoundError(
            f"checkpoint {ckpt} not found (train one with tools/train.py, or pass --ckpt)"
        )
    return path


def eval_name(ckpt: Path) -> str:
    """The ``eval/`` folder of a checkpoint: ``epoch_N`` for ``checkpoint_epoch_N.pth`` (as
    OpenPCDet names it), the file name without ``.pth`` otherwise."""
    m = CHECKPOINT_NAME.fullmatch(ckpt.name)
    return f"epoch_{m.group(1)}" if m else ckpt.stem


def eval_dir(cfg, output_root: str, extra_tag: str, ckpt: Path, eval_tag: str) -> Path:
    """Where one checkpoint's evaluation is written (module docstring):
    ``<output_root>/<group>/<tag>/<extra_tag>/eval/<name>/<split>/<eval_tag>/``."""
    split = cfg.DATA_CONFIG.DATA_SPLIT["test"]
    return output_dir_for(
        cfg, output_root, extra_tag, ("eval", "folder"), (eval_name(ckpt), "checkpoint name"),
        (split, "DATA_CONFIG.DATA_SPLIT.test"), (eval_tag, "eval_tag"),
        source=f"the evaluation folder of checkpoint {ckpt}",
    )  # fmt: skip


def proposal_part(variant_dir: Path, rank: int) -> Path:
    """The clean proposals of process ``rank`` (a model with a proposal bank), for a resumed
    call to seed the attack variants' banks with."""
    return variant_dir / f"proposals_rank{rank}.pkl"


def check_eval_dir(out_dir: Path, overwrite: bool) -> None:
    """Refuse an evaluation directory that already holds files, unless ``--overwrite``."""
    if overwrite or not out_dir.is_dir() or not any(out_dir.iterdir()):
        return
    held = sorted(p.name for p in out_dir.iterdir())
    raise FileExistsError(
        f"evaluation directory {out_dir} already holds {', '.join(held[:5])}"
        + (" ..." if len(held) > 5 else "")
        + ": pass --overwrite to replace it, or another --eval_tag / --extra_tag"
    )


def finished_variants(
    out_dir: Path,
    cfg,
    ckpt_sha256: str,
    requested: Mapping[str, str],
    *,
    batch_size: int,
    world: int,
    device: str,
    dataset_fingerprint: str,
) -> tuple[dict[str, dict], dict[str, str]]:
    """``--resume``: the ``results.json`` entries of the requested variants an earlier call
    finished in ``out_dir`` that this call keeps. That call must have had the same merged config,
    checkpoint bytes, batch size, process count and device, or this is an error naming what
    differs.

    ``requested``: ``{variant: attack_sha256}`` of this call. A finished variant (entry and
    ``<variant>/result.pkl`` both there) is kept unless its entry's ``extra.attack_sha256``
    differs (or is missing), or it has targets but no per-run counts (``runs``: a file of
    schema 4 or older), or it is an attack variant evaluated without the clean predictions
    while this call evaluates ``clean``, or it is ``clean`` and a process's
    ``clean/proposals_rank<r>.pkl`` is missing where another's is there, or its ``result.pkl``
    (or the clean proposals) has another SHA-256 than its entry recorded
    (:func:`changed_kept_file`; an older version's entry records none): each of those is
    evaluated again, as one uninterrupted call would. Every finished variant is evaluated again
    when ``dataset_fingerprint`` (this call's test split) differs from the file's
    ``extra.dataset_fingerprint``, or the file has none. Returns the kept entries and
    ``{variant: reason}`` of those evaluated again.
    """
    path = out_dir / "results.json"
    if not path.is_file():
        return {}, {}
    earlier = load_results(path)
    extra = earlier.get("extra", {})
    config_file = out_dir / f"{cfg.TAG}.yaml"
    now = {"checkpoint_sha256": ckpt_sha256, "batch_size": batch_size, "processes": world,
           "device": device}  # fmt: skip
    differs = [f"{key} {extra.get(key)!r} (now {value!r})"
               for key, value in now.items() if extra.get(key) != value]  # fmt: skip
    if not config_file.is_file():
        differs.append(f"merged config: {config_file} is missing")
    elif config_file.read_text() != yaml.safe_dump(to_plain(cfg), sort_keys=False):
        differs.append(f"merged config ({config_file} differs from this call's)")
    if differs:
        raise ValueError(
            f"--resume: {path} was written by a call with another setting: {'; '.join(differs)}; "
            "pass --overwrite to evaluate again, or another --eval_tag / --extra_tag"
        )
    data_changed = None
    if "dataset_fingerprint" not in extra:
        data_changed = "results.json has no extra.dataset_fingerprint (an older version wrote it)"
    elif extra["dataset_fingerprint"] != dataset_fingerprint:
        data_changed = (
            "the test split's info pkls or frame files changed (dataset_fingerprint "
            f"{extra['dataset_fingerprint']}, now {dataset_fingerprint})"
        )
    kept, again = {}, {}
    for name, entry in earlier["variants"].items():
        if name not in requested or not (out_dir / name / "result.pkl").is_file():
            continue
        recorded = entry.get("extra", {})
        if data_changed is not None:
            again[name] = data_changed
        elif "attack_sha256" not in recorded:
            again[name] = "its entry has no extra.attack_sha256 (written by an older version)"
        elif recorded["attack_sha256"] != requested[name]:
            again[name] = (
                "its attack config or trace library changed (attack_sha256 "
                f"{recorded['attack_sha256']}, now {requested[name]})"
            )
        elif entry["runs"] is None and entry["num_targets"] > 0:
            again[name] = "its entry has no per-run counts (results.json schema 4 or older)"
        elif name != "clean" and "clean" in requested and not recorded.get("clean_predictions"):
            again[name] = "it was evaluated without the clean predictions this call has"
        elif name == "clean" and (missing := missing_proposal_parts(out_dir / name, world)):
            again[name] = f"{missing[0]} is missing (the clean proposals of its process)"
        elif changed := changed_kept_file(out_dir / name, recorded, world):
            again[name] = changed
        else:  # without targets there are no runs: an older file's null is []
            kept[name] = entry if entry["runs"] is not None else {**entry, "runs": []}
    return kept, again


def missing_proposal_parts(variant_dir: Path, world: int) -> list[Path]:
    """The ``proposals_rank<r>.pkl`` files of ``world`` processes that are missing beside
    another process's (none when no process wrote one: a model without a proposal bank)."""
    parts = [proposal_part(variant_dir, rank) for rank in range(world)]
    if not any(part.is_file() for part in parts):
        return []
    return [part for part in parts if not part.is_file()]


def changed_kept_file(variant_dir: Path, recorded: Mapping, world: int) -> str | None:
    """Why a finished variant's files may not be reused (None: they may): its ``result.pkl``
    (and the clean variant's ``proposals_rank<r>.pkl`` of ``world`` processes: those there) must
    have the SHA-256 its entry's ``extra`` (``recorded``) holds. An entry of an older version
    records none: its files are reused unverified, as that version reused them (evaluating
    again every finished model of a shared output folder would cost hours; the hashes guard
    against a file swapped or rewritten by mistake, as whoever can write the folder can also
    rewrite ``results.json``)."""
    if "result_sha256" not in recorded:
        return None
    expected, names = {"result.pkl": recorded["result_sha256"]}, ["result.pkl"]
    if variant_dir.name == "clean":
        if "proposals_sha256" not in recorded:
            return None
        expected.update(recorded["proposals_sha256"])
        names += [proposal_part(variant_dir, rank).name for rank in range(world)]
    if unknown := sorted(set(expected) - set(names)):
        return f"its entry records {unknown[0]}, not a proposal file of {world} processes"
    for path in (variant_dir / name for name in names):
        if path.name not in expected:
            if path.is_file():
                return f"{path} is not recorded by its entry (extra.proposals_sha256)"
        elif not path.is_file():
            return f"{path} is missing (its entry recorded its SHA-256)"
        elif (now := file_sha256(path)) != expected[path.name]:
            return (
                f"the SHA-256 of {path} differs from the one its entry recorded "
                f"({expected[path.name]}, now {now})"
            )
    return None


def proposal_hashes(variant_dir: Path, hashes: list[str | None]) -> dict[str, str]:
    """The clean variant's ``extra.proposals_sha256``: ``{file name: SHA-256}`` of each
    process's proposal part (``hashes[rank]``; None: that process wrote none)."""
    return {proposal_part(variant_dir, rank).name: sha for rank, sha in enumerate(hashes) if sha}
