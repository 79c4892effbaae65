"""The results a report was made from, kept beside it: each model's ``results.json``
gzip-compressed into ``<report folder>/results/<model>.results.json.gz`` with bytes that depend
on the file's content only (gzip time stamp 0, no file name in the header), so that a committed
report can be rebuilt, and each of its numbers recomputed, from its folder alone
(``python tools/report.py --results <report folder>/results --out_dir <folder>``).

A report folder may come from someone else: its ``results`` folder is refused when it is a
symlink (its files are written and removed there), an archived file ``run.json`` names must be a
file of that folder (symlinks resolved), and a run's evaluated ``results`` is read only from under
the evaluations' root of this machine.
"""

from __future__ import annotations

import gzip
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

from pcdet_atlas.evaluation.results.io import load_results, read_results_bytes
from pcdet_atlas.evaluation.results.schema import ResultsError
from pcdet_atlas.utils.files import write_atomic
from pcdet_atlas.utils.paths import UnsafePathError, join_under

__all__ = [
    "ARCHIVE_DIR",
    "ARCHIVE_SUFFIX",
    "archive_name",
    "archive_results",
    "archive_run_results",
    "compress_results",
]

#: The folder of a report's archived results, inside the report's folder.
ARCHIVE_DIR = "results"
ARCHIVE_SUFFIX = ".results.json.gz"
_LOG = logging.getLogger(__name__)


def archive_name(model: str) -> str:
    """The archived file's name of a model: its name lower-cased, each run of other characters
    than ``a-z0-9`` one ``-`` (``PHiM+LOT`` -> ``phim-lot.results.json.gz``)."""
    slug = re.sub(r"[^a-z0-9]+", "-", model.lower()).strip("-")
    if not slug:
        raise ResultsError(f"model {model!r}: no letter or digit to name its archived results by")
    return slug + ARCHIVE_SUFFIX


def compress_results(path: str | Path) -> bytes:
    """The gzip bytes of a results file's JSON (a ``.gz`` file's content, uncompressed first):
    the same content gives the same bytes (level 9, time stamp 0, no file name)."""
    return gzip.compress(read_results_bytes(path), compresslevel=9, mtime=0)


def archive_results(paths: Sequence[str | Path], folder: str | Path) -> list[Path]:
    """Write each results file of ``paths`` (each validated and upgraded by
    :func:`load_results` first, so that a broken file is refused naming it; the bytes archived
    are the file's own) into ``folder`` as :func:`archive_name` of its model, and remove the
    archived files there of models not in ``paths`` (a report's folder holds the results of its
    own models only). Returns the archived paths, in the order of ``paths``.

    Raises:
        FileNotFoundError: a file of ``paths`` is missing.
        ResultsError: an unreadable or invalid file, or two files whose models share an archived
            name, naming them.
        UnsafePathError: ``folder`` is a symlink (nothing is written or removed through it).
    """
    folder = Path(folder)
    if folder.is_symlink():
        raise UnsafePathError(
            f"{folder}: a symlink to {os.readlink(folder)}, expected the folder of a report's "
            "archived results (its files are written and removed there, never through a link): "
            "remove the link"
        )
    named: dict[str, tuple[Path, str]] = {}
    for path in map(Path, paths):
        model = load_results(path)["model"]
        name = archive_name(model)
        if name in named:
            other, other_model = named[name]
            raise ResultsError(
                f"{other} (model {other_model!r}) and {path} (model {model!r}) would both be "
                f"archived as {folder / name}: give the models names that differ in letters or "
                "digits (ATLAS.MODEL_NAME)"
            )
        named[name] = (path, model)
    out = []
    for name, (path, _) in named.items():
        data = compress_results(path)
        target = folder / name
        unchanged = not target.is_symlink() and target.is_file() and target.read_bytes() == data
        if not unchanged:  # a symlink is replaced by the file, not written through
            write_atomic(target, lambda f, data=data: f.write(data))
        out.append(target)
    for stale in folder.glob(f"*{ARCHIVE_SUFFIX}"):
        if stale.name not in named:
            stale.unlink()
    return out


def archive_run_results(
    runs: Sequence[Mapping], out_dir: str | Path, *, eval_root: str | Path
) -> list[dict]:
    """The ``runs`` of a ``tools/reproduce.py`` run record (``run.json`` in ``out_dir``: each
    with its evaluation's results file in ``'results'``) with every results file archived in
    ``out_dir/results`` (:func:`archive_results`) and ``'archived'`` naming the archived file
    relative to ``out_dir``. A run's ``'results'`` is read only when it lies, symlinks resolved,
    under ``eval_root`` (the root of the evaluations, ``tools/reproduce.py --eval_dir``): a
    run record is data, and its paths do not lead the tool to read files elsewhere. A run whose
    ``'results'`` file is not there (the record read on another machine, from a clone of the
    committed report), or lies outside ``eval_root`` (then with a warning), keeps the file its
    ``'archived'`` names, which must exist.

    Raises:
        ResultsError: a run with neither file, or an ``'archived'`` that is not a relative path
            ``results/<file name>``, naming the run.
        UnsafePathError: an ``'archived'`` file that leads out of ``out_dir`` (a symlink), or a
            ``results`` folder that is a symlink.
    """
    out_dir = Path(out_dir)
    record = out_dir / "run.json"
    runs = [dict(run) for run in runs]
    sources = []
    for i, run in enumerate(runs):
        evaluated = Path(run["results"])
        archived = run.get("archived")
        parts = Path(archived).parts if isinstance(archived, str) else ()
        if archived is not None and (len(parts) != 2 or parts[0] != ARCHIVE_DIR):
            raise ResultsError(
                f"{record}: runs[{i}].archived holds {archived!r}, expected a "
                f"file name under {ARCHIVE_DIR}/ (relative to the folder of run.json)"
            )
        archived_path = None if archived is None else join_under(
            out_dir, (ARCHIVE_DIR, "archive folder"), (parts[1], "archived file name"),
            source=f"{record}: runs[{i}].archived",
        )  # fmt: skip
        inside = _lies_under(evaluated, eval_root)
        if inside and evaluated.is_file():
            sources.append(evaluated)
        elif archived_path is not None and archived_path.is_file():
            if not inside and evaluated.exists():
                _LOG.warning(
                    f"{record}: runs[{i}] ({run['config']}): its results file {evaluated} lies "
                    f"outside the evaluations' root {eval_root} (symlinks resolved) and is not "
                    f"read; the archived {archived_path} is used (pass the --eval_dir the run "
                    "evaluated into to read it)"
                )
            sources.append(archived_path)
        elif not inside and evaluated.exists():
            where = ("it has no archived copy" if archived is None
                     else f"its archived copy {archived_path} does not exist")  # fmt: skip
            raise ResultsError(
                f"{record}: runs[{i}] ({run['config']}): its results file {evaluated} lies "
                f"outside the evaluations' root {eval_root} (symlinks resolved) and is not read, "
                f"and {where}; pass the --eval_dir the run evaluated into"
            )
        else:
            where = "" if archived is None else f" nor its archived {archived_path}"
            raise ResultsError(
                f"{record}: runs[{i}] ({run['config']}): neither its results "
                f"{evaluated}{where} exists; evaluate the model again (tools/reproduce.py)"
            )
    for run, path in zip(runs, archive_results(sources, out_dir / ARCHIVE_DIR)):
        run["archived"] = str(path.relative_to(out_dir))
    return runs


def _lies_under(path: Path, root: str | Path) -> bool:
    """Whether ``path``, symlinks resolved, is ``root`` (resolved) or lies below it (not when
    its symlinks loop)."""
    try:
        real, real_root = path.resolve(), Path(root).resolve()
    except RuntimeError:  # a symlink loop (Python < 3.13)
        return False
    return real == real_root or real_root in real.parents
