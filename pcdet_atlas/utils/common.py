"""Logging and small numeric helpers shared by tools and library code."""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import math
import os
import pickle
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.utils.files import (  # write_atomic: save_pickle's, also imported from here
    open_regular_file,
    write_atomic,
)

LOG_FORMAT = "%(asctime)s  %(levelname)5s  %(message)s"


class _LogFileHandler(logging.StreamHandler):
    """Appends to a log file opened by :func:`~pcdet_atlas.utils.files.open_regular_file` (a
    symlink or special file at the log's name is refused, not written through); closes it."""

    def __init__(self, path: Path):
        fd = open_regular_file(path, os.O_WRONLY | os.O_APPEND, "log file")
        super().__init__(os.fdopen(fd, "a", encoding="utf-8"))

    def close(self) -> None:
        try:
            self.stream.close()
        finally:
            super().close()


def create_logger(log_file: str | Path | None = None, rank: int = 0, name: str = "pcdet_atlas"):
    """OpenPCDet-style logger: INFO on rank 0 (ERROR elsewhere), to the console and ``log_file``
    (appended to; a symlink there is refused)."""
    logger = logging.getLogger(name)
    logger.setLevel(logging.INFO if rank == 0 else logging.ERROR)
    logger.propagate = False
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
        if isinstance(handler, _LogFileHandler):
            handler.close()
    formatter = logging.Formatter(LOG_FORMAT)
    console = logging.StreamHandler()
    console.setFormatter(formatter)
    logger.addHandler(console)
    if log_file is not None:
        Path(log_file).parent.mkdir(parents=True, exist_ok=True)
        file_handler = _LogFileHandler(Path(log_file))
        file_handler.setFormatter(formatter)
        logger.addHandler(file_handler)
    return logger


def limit_period(val, offset: float = 0.5, period: float = 2 * math.pi):
    """Wrap ``val`` into ``[-offset * period, (1 - offset) * period)`` (numpy or torch)."""
    if isinstance(val, torch.Tensor):
        return val - torch.floor(val / period + offset) * period
    return val - np.floor(val / period + offset) * period


def resolve_device(name: str | None, local_rank: int = 0) -> torch.device:
    """``--device`` as a torch device: ``None`` -> CUDA when available, else CPU; a bare ``cuda``
    -> ``cuda:local_rank % device_count``. A device that is not there is a ValueError."""
    if name is None:
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"{name!r} is not a device here (expected cpu, cuda or cuda:N)")
    if device.type == "cpu":
        return device
    if not torch.cuda.is_available():
        raise ValueError(
            f"{name!r}: no CUDA GPU is visible to torch (torch.cuda.is_available() is False)"
        )
    count = torch.cuda.device_count()
    index = local_rank % count if device.index is None else device.index
    if index >= count:
        raise ValueError(f"{name!r}: only {count} CUDA device(s) are visible")
    return torch.device("cuda", index)


@contextlib.contextmanager
def deterministic_algorithms(enabled: bool, warn_only: bool = False) -> Iterator[None]:
    """Torch's deterministic mode (``torch.use_deterministic_algorithms``) set to ``enabled``
    and ``warn_only`` inside the block; on exit, also on an error, back to what it was, its
    ``warn_only`` setting included."""
    before = torch.are_deterministic_algorithms_enabled()
    before_warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(enabled, warn_only=warn_only)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before, warn_only=before_warn_only)


def load_tool(name: str):
    """Import ``tools/<name>.py`` of the repository as a module (tools are scripts, not a
    package), so that a test can call its ``main(argv)`` in the test's process. Tools never
    import each other (tests/test_tools.py): what two tools share lives in the package."""
    path = REPO_ROOT / "tools" / f"{name}.py"
    if not path.is_file():
        raise FileNotFoundError(f"no tool {path}")
    spec = importlib.util.spec_from_file_location(f"tool_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def save_pickle(obj, path: str | Path) -> Path:
    """Pickle ``obj`` to ``path`` atomically (:func:`write_atomic`)."""
    return write_atomic(path, lambda f: pickle.dump(obj, f))
