"""The results a report was made from, kept beside it: each model's ``results.json``
gzip-compressed into ``<report folder>/results/<model>.results.json.gz`` with bytes that depend
on the file's content only (gzip time stamp 0, no file name in the header), so that a committed
report can be rebuilt, and each of its numbers recomputed, from its folder alone
(``python tools/report.py --results <report folder>/results --out_dir <folder>``).
"""

from __future__ import annotations

import gzip
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

from pcdet_atlas.evaluation.results.io import load_results, read_results_bytes
from pcdet_atlas.evaluation.results.schema import ResultsError
from pcdet_atlas.utils.common import write_atomic

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
        ResultsError: an unreadable or invalid file, or two files whose models share an archived
            name, naming them.
    """
    folder = Path(folder)
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
        if not target.is_file() or target.read_bytes() != data:  # unchanged: left as it is
            write_atomic(target, lambda f, data=data: f.write(data))
        out.append(target)
    for stale in folder.glob(f"*{ARCHIVE_SUFFIX}"):
        if stale.name not in named:
            stale.unlink()
    return out


def archive_run_results(runs: Sequence[Mapping], out_dir: str | Path) -> list[dict]:
    """The ``runs`` of a ``tools/reproduce.py`` run record (``run.json`` in ``out_dir``: each
    with its evaluation's results file in ``'results'``) with every results file archived in
    ``out_dir/results`` (:func:`archive_results`) and ``'archived'`` naming the archived file
    relative to ``out_dir``. A run whose ``'results'`` file is not there (the record read on
    another machine, from a clone of the committed report) keeps the file its ``'archived'``
    names, which must exist.

    Raises:
        ResultsError: a run with neither file, or an ``'archived'`` that is not a relative path
            inside ``out_dir/results``, naming the run.
    """
    out_dir = Path(out_dir)
    folder = out_dir / ARCHIVE_DIR
    runs = [dict(run) for run in runs]
    sources = []
    for i, run in enumerate(runs):
        evaluated = Path(run["results"])
        archived = run.get("archived")
        if archived is not None and not (
            isinstance(archived, str) and Path(archived).parent == Path(ARCHIVE_DIR)
        ):
            raise ResultsError(
                f"{out_dir / 'run.json'}: runs[{i}].archived holds {archived!r}, expected a "
                f"file name under {ARCHIVE_DIR}/ (relative to the folder of run.json)"
            )
        if evaluated.is_file():
            sources.append(evaluated)
        elif archived is not None and (out_dir / archived).is_file():
            sources.append(out_dir / archived)
        else:
            where = "" if archived is None else f" nor its archived {out_dir / archived}"
            raise ResultsError(
                f"{out_dir / 'run.json'}: runs[{i}] ({run['config']}): neither its results "
                f"{evaluated}{where} exists; evaluate the model again (tools/reproduce.py)"
            )
    for run, path in zip(runs, archive_results(sources, folder)):
        run["archived"] = str(path.relative_to(out_dir))
    return runs
