"""Evaluate every shipped synthetic model on all 13 ATLAS variants and write the paper's report.

    python tools/reproduce.py --jobs 2                          # make reproduce's second step
    python tools/reproduce.py --data_path data/synthetic_waymo_val6 --out_dir docs/results
    python tools/reproduce.py --cfgs cfgs/atlas/synthetic/cp4f.yaml --out_dir /tmp/cp4f \
        --device cuda

For each model config (default: every config under ``cfgs/atlas/synthetic/`` whose
``ATLAS.CHECKPOINT`` file exists) this runs ``tools/test.py --attacks all`` on the dataset at
``--data_path`` (clean predictions reused where an attack leaves a frame's input untouched), then
``tools/report.py`` over the results into ``--out``, with the wall time of each model and of the
whole run appended to ``report.md`` and written to ``run.json``. The report is made from copies
of the results files archived in ``--out``'s ``results/`` (gzip-compressed, deterministic bytes;
``run.json`` names each by its path relative to ``--out``), so ``--report_only`` or
``tools/report.py --results <out>/results`` rebuild it from that folder alone (``--report_only``
reads a model's evaluated ``results.json`` only from under ``--eval_dir``, whatever path a
received ``run.json`` names, and its archived copy otherwise). The injection
variants' trace library is built from the dataset's train split first if it is missing. The
dataset: docs/synthetic.md "A larger validation split".

``--jobs N`` evaluates N models at once, each a ``tools/test.py`` process with ``--threads`` torch
threads (default: the cores divided among the jobs); its output goes to ``reproduce.log`` in the
folder above the model's ``reproduce/results.json``. The run resumes: a later call predicts
nothing again for a model whose variants ``tools/test.py --resume`` would all keep (same merged
config, checkpoint bytes, variants, device and test split: its info pkls and frame files, by the
dataset fingerprint in ``results.json``), whose kept predictions that call scores again with this
version's metric and analyses (seconds; not when this very commit wrote them), and lets a model
left unfinished go on from its last finished variant; any other model is evaluated again. A call
with the same data, models, variants, ``--set`` and ``--no_reuse`` as the one ``run.json`` in
``--out`` records continues that run (its calls and wall time add up); a call with another model
set starts a new run that still keeps what earlier calls evaluated of its models, and the report
marks those models (their time is their own evaluation's, not in the run's total; the run's first
call finds them, ``run.json``'s ``earlier_run_models``); a ``--no_reuse`` call keeps only its own
run's. A ``run.json`` that is truncated or holds a key of the wrong type is an error naming the
file and the key.
``--overwrite`` evaluates everything again. The models share a prediction store
(``tools/test.py --prediction_store``, under ``--eval_dir``; ``--no_store``: none) that the
two-stage models and the configs that are their RPN use, so a two-stage model reads the
proposals its RPN computed as a model of its own. A config that is
another model's RPN therefore starts first; the others start longest first by the times of
earlier runs that ``run.json`` keeps (``model_wall_s``), so that the jobs end close together;
the report lists them in the given order. The total wall time adds up every call's (``run.json``
is updated each minute, so a call that is killed still counts, with the work it lost); a
model's time is the sum of its variants' evaluation times, whichever calls ran them. A call holds
the lock of ``--out`` (a second call into it stops at once, naming the first), and the
``tools/test.py`` processes it starts die with it (Linux), so a killed call leaves no orphan
writing.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from pathlib import Path

from tqdm import tqdm

from pcdet_atlas.attacks.trace_library import write_trace_library
from pcdet_atlas.config import (
    REPO_ROOT,
    cfg_from_yaml_file,
    repo_relative,
    resolve_cli_path,
    resolve_repo_path,
)
from pcdet_atlas.datasets.fingerprint import data_config_fingerprint
from pcdet_atlas.evaluation.results import ResultsError, collect_results, write_report
from pcdet_atlas.evaluation.results.archive import archive_run_results
from pcdet_atlas.train_utils.atlas_eval import (
    build_variant_attacks,
    resolve_variants,
    trained_checkpoint,
    variant_fingerprints,
)
from pcdet_atlas.train_utils.eval_folder import eval_dir, finished_variants, resolve_checkpoint
from pcdet_atlas.train_utils.setup import load_cfg, lock_output_folder
from pcdet_atlas.utils.cli import RenamedFlag, add_debug_flag, add_set_flag, run_tool
from pcdet_atlas.utils.common import create_logger, resolve_device, write_atomic
from pcdet_atlas.utils.files import open_regular_file
from pcdet_atlas.utils.hashing import file_sha256
from pcdet_atlas.utils.processes import die_with_parent
from pcdet_atlas.utils.provenance import SourceRevision, source_revision

DEFAULT_DATA = REPO_ROOT / "data" / "synthetic_waymo_val6"
DEFAULT_OUT = REPO_ROOT / "docs" / "results"
TAG = "reproduce"


def shipped_configs() -> list[Path]:
    """Synthetic model configs whose checkpoint ships (stage configs without one are skipped)."""
    out = []
    for path in sorted((REPO_ROOT / "cfgs" / "atlas" / "synthetic").rglob("*.yaml")):
        if trained_checkpoint(cfg_from_yaml_file(path).get("ATLAS")) is not None:
            out.append(path.relative_to(REPO_ROOT))  # as results.json and the report name it
    return out


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_debug_flag(p)
    io = p.add_argument_group("inputs and outputs")
    io.add_argument(
        "--data_path",
        default=str(DEFAULT_DATA),
        help="synthetic dataset root (default: %(default)s)",
    )
    io.add_argument(
        "--out_dir",
        "--out",
        action=RenamedFlag,
        old=("--out",),
        default=str(DEFAULT_OUT),
        help="report folder (default: %(default)s)",
    )
    io.add_argument(
        "--eval_dir",
        "--output_root",
        action=RenamedFlag,
        old=("--output_root",),
        default=None,
        help="root of the evaluations, tools/test.py's output root (default: <repo>/output)",
    )
    io.add_argument("--cfgs", nargs="+", default=None, help="model configs (default: shipped)")
    io.add_argument("--attacks", default="all", help="variants of tools/test.py (default: all)")
    add_set_flag(io, help="KEY VALUE pairs passed on to tools/test.py's --set", default=[])
    run = p.add_argument_group("how it runs")
    run.add_argument("--device", default=None, help="cpu / cuda (default: auto)")
    run.add_argument("--workers", default="2", help="loader workers of tools/test.py")
    run.add_argument("--jobs", type=int, default=1, help="models evaluated at once")
    run.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads per job (default: CPU cores // jobs)",
    )
    run.add_argument("--no_reuse", action="store_true", help="run the model on every frame")
    run.add_argument(
        "--no_store",
        action="store_true",
        help="no prediction store shared by the RPNs and the two-stage models "
        "(default: <eval_dir>/prediction_store; tools/test.py "
        "--prediction_store)",
    )
    run.add_argument(
        "--overwrite", action="store_true", help="evaluate every model again (default: resume)"
    )
    run.add_argument(
        "--report_only",
        action="store_true",
        help="write the report of the run in --out_dir's run.json again, evaluating nothing "
        "(from the results under --eval_dir, else the copies archived in --out_dir)",
    )
    args = p.parse_args(argv)
    if args.jobs < 1 or (args.threads is not None and args.threads < 1):
        p.error(f"--jobs {args.jobs} / --threads {args.threads}: expected positive counts")
    return args


def ensure_trace_libraries(root: Path, cfgs: list[Path], attacks: str) -> None:
    """Build the trace library of every requested injection variant that lacks one."""
    for cfg_path in cfgs:
        atlas_cfg = cfg_from_yaml_file(REPO_ROOT / cfg_path).get("ATLAS", {})
        for _, attack_path in resolve_variants(attacks, atlas_cfg):
            library = cfg_from_yaml_file(attack_path).get("TRACE_LIBRARY")
            if library is None:
                continue
            path = Path(library.PATH)
            path = path if path.is_absolute() else root / path
            if not path.is_file():  # the config's split, filters and LIDAR origin
                print(f"building the trace library {path}", flush=True)
                write_trace_library(
                    attack_path, root, logger=create_logger(),
                    progress=lambda it: tqdm(list(it), desc="sequences", unit="seq"),
                )  # fmt: skip


def test_argv(
    cfg: Path, args, root: Path, threads: int, resume: bool, store: Path | None = None
) -> list[str]:
    """The ``tools/test.py`` arguments that evaluate one model config (``resume``: keep the
    variants an earlier call finished; otherwise evaluate them all again; ``store``: its
    ``--prediction_store``)."""
    argv = ["--cfg", str(cfg), "--attacks", args.attacks, "--extra_tag", TAG, "--eval_tag", TAG,
            "--resume" if resume else "--overwrite", "--no_progress",
            "--workers", args.workers, "--threads", str(threads)]  # fmt: skip
    if args.eval_dir:
        argv += ["--out_dir", args.eval_dir]
    if args.device:
        argv += ["--device", args.device]
    if args.no_reuse:
        argv.append("--no_reuse")
    if store is not None:
        argv += ["--prediction_store", str(store)]
    return argv + ["--set", "DATA_CONFIG.DATA_PATH", str(root), *args.set_cfgs]


def store_of(cfg: Path, rpns, args) -> Path | None:
    """The prediction store of a model of the run: the one folder the RPNs (``rpns``) and the
    two-stage models share; None for another model, or with ``--no_store``."""
    if args.no_store or (cfg not in rpns and rpn_config(cfg) is None):
        return None
    return store_path(args)


def store_path(args) -> Path:
    return eval_root(args) / "prediction_store"


def eval_root(args) -> Path:
    """The root of the evaluations (``--eval_dir``, tools/test.py's output root)."""
    return Path(args.eval_dir or REPO_ROOT / "output")


def evaluation_of(
    cfg: Path, args, root: Path, data_fingerprints: dict | None = None
) -> tuple[Path, set[str], set[str] | None]:
    """Where ``tools/test.py`` (:func:`test_argv`) writes the config's ``results.json``, the
    variants the call evaluates, and those an earlier call already finished there with the same
    merged config, checkpoint bytes, setting and test split (its dataset fingerprint;
    ``tools/test.py --resume`` keeps them), or ``None`` when that folder cannot be resumed
    (another model or setting wrote it). ``data_fingerprints``: the run's fingerprints by
    (split, processed-data tag), filled as they are computed (once per run)."""
    model_cfg = load_cfg(str(REPO_ROOT / cfg), ["DATA_CONFIG.DATA_PATH", str(root), *args.set_cfgs])
    output_root = args.eval_dir or str(REPO_ROOT / "output")
    ckpt = resolve_checkpoint(None, model_cfg.get("ATLAS", {}))
    variants = resolve_variants(args.attacks, model_cfg.get("ATLAS", {}))
    wanted = {name for name, _ in variants}
    attacks = build_variant_attacks(variants, root)
    requested = variant_fingerprints(variants, attacks)
    out_dir = eval_dir(model_cfg, output_root, TAG, ckpt, TAG)
    data_cfg = model_cfg.DATA_CONFIG
    split = (str(data_cfg.DATA_SPLIT["test"]), str(data_cfg.get("PROCESSED_DATA_TAG")))
    data_fingerprints = {} if data_fingerprints is None else data_fingerprints
    if split not in data_fingerprints:
        data_fingerprints[split] = data_config_fingerprint(data_cfg, "test")
    try:  # the setting tools/test.py gets from test_argv: one process, batch size 1
        kept, _ = finished_variants(
            out_dir, model_cfg, file_sha256(ckpt), requested, batch_size=1, world=1,
            device=str(resolve_device(args.device)), dataset_fingerprint=data_fingerprints[split],
        )  # fmt: skip
        finished = set(kept)
    except ResultsError:  # an unreadable results.json: named, not overwritten
        raise
    except ValueError:
        finished = None
    return out_dir / "results.json", wanted, finished


def scored_by(results: Path, revision: SourceRevision | None) -> bool:
    """Whether ``results`` was written by this very source, ``revision`` (the same commit,
    neither that tree nor this one with uncommitted changes): scoring its kept predictions again
    would give its entries as they are."""
    if revision is None or revision.dirty:
        return False
    written = json.loads(results.read_text())
    return written.get("source_commit") == revision.commit and written.get("source_dirty") is False


_NUMBER, _TEXT = (int, float), (str,)
#: The types of ``run.json``'s keys (None allowed where the tuple holds ``type(None)``).
RUN_RECORD_TYPES = {
    "setting": (dict,), "command": _TEXT, "jobs": (int,), "threads": (int,),
    "cpu_cores": (int, type(None)), "machine": _TEXT, "cpus": (list,),
    "device": (str, type(None)), "total_wall_s": _NUMBER, "calls": (int,), "runs": (list,),
    "model_wall_s": (dict,), "prediction_store": (str, type(None)),
    "earlier_run_models": (list,),
}  # fmt: skip
_RUN_TYPES = {"config": _TEXT, "results": _TEXT, "wall_s": _NUMBER}
#: Keys of a ``runs`` entry that a call of an older version did not write.
_OPTIONAL_RUN_TYPES = {"earlier_run": (bool,)}


def _typed(value, types: tuple) -> bool:
    return isinstance(value, types) and not (isinstance(value, bool) and bool not in types)


def read_run_record(path: Path) -> dict:
    """An earlier call's ``run.json``, checked: a truncated or hand-edited file is a
    ``ValueError`` naming the file and the key (keys a call of an older version did not write
    may be absent)."""

    def bad(key: str, value, expected: str) -> ValueError:
        return ValueError(
            f"{path}: key {key!r} holds {value!r}, expected {expected} (a truncated or "
            "hand-edited run record: fix the key, or delete the file to start a new record)"
        )

    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(
            f"{path}: not valid JSON ({err}); truncated? delete it to start a new run record"
        ) from err
    if not isinstance(record, dict):
        raise ValueError(f"{path}: holds a JSON {type(record).__name__}, expected an object")
    for key, types in RUN_RECORD_TYPES.items():
        if key in record and not _typed(record[key], types):
            raise bad(key, record[key], " or ".join(t.__name__ for t in types))
    for i, run in enumerate(record.get("runs", [])):
        for key, types in _RUN_TYPES.items():
            if not isinstance(run, dict) or not _typed(run.get(key), types):
                got = run.get(key) if isinstance(run, dict) else run
                raise bad(f"runs[{i}].{key}", got, " or ".join(t.__name__ for t in types))
        for key, types in _OPTIONAL_RUN_TYPES.items():
            if key in run and not _typed(run[key], types):
                raise bad(f"runs[{i}].{key}", run[key], " or ".join(t.__name__ for t in types))
    for name, wall in record.get("model_wall_s", {}).items():
        if not _typed(wall, _NUMBER):
            raise bad(f"model_wall_s.{name}", wall, "a number of seconds")
    for i, cpu in enumerate(record.get("cpus", [])):
        if not isinstance(cpu, str):
            raise bad(f"cpus[{i}]", cpu, "a CPU model name")
    for i, name in enumerate(record.get("earlier_run_models", [])):
        if not isinstance(name, str):
            raise bad(f"earlier_run_models[{i}]", name, "a model config path")
    return record


def known_times(run: dict) -> dict[str, float]:
    """Each model's evaluation time (s) an earlier ``run.json`` knows, from any setting."""
    known = dict(run.get("model_wall_s", {}))
    known.update({r["config"]: r["wall_s"] for r in run.get("runs", [])})
    return known


def start_order(cfgs: list[Path], known: dict[str, float], rpns=frozenset()) -> list[Path]:
    """The order the models start in: the ``rpns`` (configs that are another model's RPN,
    :func:`rpn_config`) first, since their predictions in the prediction store are the
    proposals of the models after them; then longest first by the earlier times ``known``, so
    that the ``--jobs`` lanes end close together; models without a time first, in the given
    order."""
    names = {str(cfg) for cfg in rpns}
    return sorted(cfgs, key=lambda cfg: (str(cfg) not in names, -known.get(str(cfg), math.inf)))


def evaluate_all(cfgs: list[Path], evaluate, jobs: int) -> None:
    """``evaluate(cfg)`` for each config in order, ``jobs`` at a time. When one fails, the
    models not started yet do not start (a two-stage model would otherwise run without the
    proposals of a failed RPN), those running finish, and the first failure is raised."""
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(evaluate, cfg) for cfg in cfgs]
        wait(futures, return_when=FIRST_EXCEPTION)
        failed = [f for f in futures if f.done() and not f.cancelled() and f.exception()]
        if failed:
            cancelled = sum(f.cancel() for f in futures)
            print(f"a model failed: {cancelled} model(s) not started are cancelled; waiting for "
                  "the running ones", flush=True)  # fmt: skip
            failed[0].result()
        for future in futures:
            future.result()


def rpn_config(cfg: Path) -> Path | None:
    """The config of a two-stage model's RPN (``MODEL.RPN.CFG``, as the run names configs),
    None for another model."""
    rpn = cfg_from_yaml_file(REPO_ROOT / cfg).get("MODEL", {}).get("RPN")
    return None if rpn is None else repo_relative(resolve_repo_path(rpn["CFG"]))


def open_log(path: Path, append: bool):
    """``path`` opened for ``tools/test.py``'s output, appended to (``append``) or emptied; a
    symlink or anything but a regular file there is refused naming it, not written through
    (:func:`~pcdet_atlas.utils.files.open_regular_file`)."""
    flags = os.O_WRONLY | (os.O_APPEND if append else os.O_TRUNC)
    return os.fdopen(
        open_regular_file(path, flags, "the log of tools/test.py"), "a" if append else "w"
    )


def evaluation_time(results: dict) -> float:
    """Seconds a model's evaluation took: its variants' prediction and metric times (from
    ``extra.timing_s`` of each variant), whichever calls of ``tools/test.py`` ran them."""
    timing = [v.get("extra", {}).get("timing_s", {}) for v in results["variants"].values()]
    return round(sum(t.get("predict_wall", 0.0) + t.get("metric", 0.0) for t in timing), 1)


def main(argv=None) -> dict:
    args = parse_args(argv)
    with contextlib.ExitStack() as held:  # one reproduce run per --out at a time
        lock_output_folder(Path(args.out_dir), held, "tools/reproduce.py")
        return reproduce(args, argv)


def reproduce(args, argv=None) -> dict:
    """The work of :func:`main` (``argv``: its command line, recorded in ``run.json``), under
    the lock of ``--out``."""
    if args.report_only:
        return rewrite_report(Path(args.out_dir), eval_root(args))
    root = resolve_cli_path(args.data_path)  # the tools/test.py processes run in the repo root
    if not (root / "ImageSets").is_dir():
        raise FileNotFoundError(
            f"{root}: no synthetic dataset there (generate it: see docs/synthetic.md "
            "'A larger validation split', or run make reproduce)"
        )
    cfgs = [repo_relative(Path(c)) for c in args.cfgs] if args.cfgs else shipped_configs()
    ensure_trace_libraries(root, cfgs, args.attacks)
    threads = args.threads or max(1, (os.cpu_count() or 1) // args.jobs)
    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    run_file = out_dir / "run.json"
    setting = {"data_path": str(root), "attacks": args.attacks, "cfgs": list(map(str, cfgs)),
               "set": list(args.set_cfgs), "no_reuse": args.no_reuse}  # fmt: skip
    elapsed_before, calls = 0.0, 1
    previous = read_run_record(run_file) if run_file.is_file() else {}
    known = known_times(previous)
    resume = not args.overwrite and previous.get("setting") == setting
    cpus = [cpu_model()]
    if resume:
        elapsed_before = float(previous.get("total_wall_s", 0.0))
        calls += int(previous.get("calls", 1))
        cpus = list(dict.fromkeys([*previous.get("cpus", []), *cpus]))
    data_fingerprints: dict = {}  # the test splits' (tools/test.py --resume), once per run
    # the models of which calls before this run (of another model set) evaluated variants that
    # it keeps: found in its first call, before it evaluates anything, and carried by the others
    earlier = set(previous.get("earlier_run_models", [])) if resume else set()
    found: dict = {}  # evaluation_of by config, looked up once: evaluate() reuses it
    if not (resume or args.overwrite or args.no_reuse):
        for cfg in cfgs:
            found[cfg] = evaluation_of(cfg, args, root, data_fingerprints)
            _, wanted, evaluated = found[cfg]
            if evaluated is not None and wanted & evaluated:
                earlier.add(str(cfg))
    command = shlex.join(sys.argv[1:] if argv is None else argv)
    state = {"setting": setting, "command": command, "jobs": args.jobs, "threads": threads,
             "cpu_cores": os.cpu_count(), "machine": platform.machine(), "cpus": cpus,
             "device": None,
             "total_wall_s": elapsed_before, "calls": calls, "runs": [],
             "model_wall_s": known, "earlier_run_models": sorted(earlier),
             "prediction_store": None if args.no_store else str(store_path(args))}  # fmt: skip
    lock = threading.Lock()
    start = time.perf_counter()
    finished = threading.Event()

    def write_state() -> None:  # atomic: a killed call keeps the previous state
        text = json.dumps(state, indent=2) + "\n"
        write_atomic(run_file, lambda f: f.write(text.encode()))

    def save_state(run: dict | None = None) -> None:
        with lock:
            if run is not None:
                state["runs"].append(run)
                state["model_wall_s"][run["config"]] = run["wall_s"]
            state["total_wall_s"] = round(elapsed_before + time.perf_counter() - start, 1)
            write_state()

    def heartbeat() -> None:  # the wall time of a call that is killed still counts
        while not finished.wait(60):
            save_state()

    def evaluate(cfg: Path) -> None:
        looked_up = found.pop(cfg, None)
        results, wanted, evaluated = looked_up or evaluation_of(cfg, args, root, data_fingerprints)
        # what an earlier call evaluated of this model is kept whichever models that call had:
        # a model's variants depend on its own config, checkpoint and data alone
        resumable = evaluated is not None and not args.overwrite and (resume or not args.no_reuse)
        earlier_run = resumable and str(cfg) in earlier
        done = resumable and wanted <= evaluated
        # a finished model written by another version runs too: tools/test.py --resume scores
        # its kept predictions again with this version's metric and analyses, predicting nothing
        if not done or not scored_by(results, revision):
            store = store_of(cfg, rpns, args)
            command = [sys.executable, str(REPO_ROOT / "tools" / "test.py"),
                       *test_argv(cfg, args, root, threads, resumable, store)]  # fmt: skip
            print("$ " + shlex.join(command[1:]), flush=True)
            log = results.parent.parent / "reproduce.log"
            log.parent.mkdir(parents=True, exist_ok=True)
            with open_log(log, append=resumable) as stream:
                code = subprocess.run(  # killed with this process: no orphan writes on
                    command, stdout=stream, stderr=subprocess.STDOUT, cwd=REPO_ROOT,
                    preexec_fn=die_with_parent(),
                ).returncode  # fmt: skip
            if code != 0:
                raise RuntimeError(f"{cfg}: tools/test.py exited with {code}; its output: {log}")
        wall = evaluation_time(json.loads(results.read_text()))
        when = "done in an earlier call, " if done else ""
        when += "evaluated by a run of another model set, " if earlier_run else ""
        print(f"{cfg}: {when}{wall / 60:.1f} min, {results}", flush=True)
        save_state({"config": str(cfg), "results": str(results), "wall_s": wall,
                    "earlier_run": earlier_run})  # fmt: skip

    rpns = {rpn_config(cfg) for cfg in cfgs} - {None}
    revision = source_revision()
    threading.Thread(target=heartbeat, daemon=True).start()
    evaluate_all(start_order(cfgs, known, rpns), evaluate, args.jobs)
    finished.set()
    save_state()
    order = {str(cfg): i for i, cfg in enumerate(cfgs)}
    state["runs"] = sorted(state["runs"], key=lambda r: order[r["config"]])
    out = write_run_report(state, out_dir, eval_root(args))
    write_state()
    print(f"report: {out['report']}  total {state['total_wall_s'] / 60:.1f} min")
    return {**out, "run": state}


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; ``platform.processor()`` elsewhere), so that a
    run's wall time can be read against the machine it ran on."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def write_run_report(state: dict, out_dir: Path, evaluations: Path) -> dict:
    """The report of a run (``state``: its ``run.json``) into ``out_dir``, with how it was
    produced (command, machine, wall times), from the results archived in ``out_dir/results``
    (``state['runs'][i]['archived']``; a run's evaluated results are read from under
    ``evaluations``, the ``--eval_dir``, only); sets ``state['device']``."""
    state["runs"] = archive_run_results(state["runs"], out_dir, eval_root=evaluations)
    found = collect_results([out_dir / r["archived"] for r in state["runs"]])
    results = [r for _, r in found]
    device = str(results[0].get("extra", {}).get("device", "?"))
    frames = next(iter(results[0]["variants"].values()))["num_frames"]
    total, calls = state["total_wall_s"], state["calls"]
    lines = [
        "## How these results were produced",
        "",
        f"`python tools/reproduce.py {state['command']}` on "
        f"`{Path(state['setting']['data_path']).name}` ({frames} val frames), device {device}, "
        f"{state['jobs']} model(s) at a time with {state['threads']} torch thread(s) each, "
        f"{state['cpu_cores']} CPU cores, {state['machine']}"
        + (f" ({', '.join(state['cpus'])})" if state.get("cpus") else "")
        + "; total wall time "
        f"**{total / 60:.1f} min**"
        + (
            f" over {calls} calls (a resumed run counts the work its interrupted calls lost)."
            if calls > 1
            else "."
        )
        + " A model's time is the sum of its variants' evaluation times."
        + (
            " Models marked † were evaluated, in whole or in part, by calls of another model set"
            " before this run: their time counts those calls' work, which the total does not."
            if any(run.get("earlier_run") for run in state["runs"])
            else ""
        ),
        "",
        "| Model | Wall time (min) | Frames recomputed | Frames reused | s per recomputed frame |",
        "|:---|---:|---:|---:|---:|",
    ]
    for run, r in zip(state["runs"], results):
        counts = [(v["num_recomputed_frames"], v["num_reused_frames"])
                  for v in r["variants"].values()]  # fmt: skip
        if any(c is None for pair in counts for c in pair):  # results.json from before the counts
            recomputed = reused = per_frame = "-"
        else:
            recomputed, reused = (sum(c[i] for c in counts) for i in (0, 1))
            per_frame = f"{run['wall_s'] / recomputed:.2f}" if recomputed else "-"
        mark = " †" if run.get("earlier_run") else ""
        lines.append(
            f"| {r['model']}{mark} | {run['wall_s'] / 60:.1f} | {recomputed} | {reused} "
            f"| {per_frame} |"
        )
    sources = [str(repo_relative(out_dir / r["archived"])) for r in state["runs"]]
    state["device"] = device
    return write_report(
        results, out_dir, sources=sources, latex=True, command=None, appendix="\n".join(lines),
    )  # fmt: skip


def rewrite_report(out_dir: Path, evaluations: Path) -> dict:
    """``--report_only``: the report of the run recorded in ``out_dir/run.json`` again, from its
    models' ``results.json`` under ``evaluations`` (the ``--eval_dir``) or else their archived
    copies (after a change to the report, say), evaluating nothing."""
    run_file = out_dir / "run.json"
    if not run_file.is_file():
        raise FileNotFoundError(f"--report_only: no {run_file} (run tools/reproduce.py first)")
    state = read_run_record(run_file)
    missing = [k for k in ("runs", "command", "cpu_cores", "machine") if not state.get(k)]
    if missing:
        raise ValueError(f"--report_only: {run_file} has no {', '.join(missing)}")
    out = write_run_report(state, out_dir, evaluations)
    write_atomic(run_file, lambda f: f.write((json.dumps(state, indent=2) + "\n").encode()))
    print(f"report: {out['report']}")
    return {**out, "run": state}


if __name__ == "__main__":
    run_tool(main)
