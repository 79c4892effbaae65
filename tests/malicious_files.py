"""Files that run code when loaded the unsafe way: the entry points that read pickles and
checkpoints must refuse them, naming the file and what was refused, before anything runs."""

from __future__ import annotations

import pathlib
import pickle

import torch


class Touch:
    """Unpickled by ``pickle.load`` or ``torch.load(weights_only=False)``, this creates
    ``marker`` (where a malicious file would run a program)."""

    def __init__(self, marker: pathlib.Path):
        self.marker = pathlib.Path(marker)

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def malicious_pickle(path: pathlib.Path, marker: pathlib.Path, value=None) -> pathlib.Path:
    """Pickle ``{'data': value, 'payload': Touch(marker)}`` to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps({"data": value, "payload": Touch(marker)}))
    return path


def malicious_checkpoint(path: pathlib.Path, marker: pathlib.Path, **entries) -> pathlib.Path:
    """``torch.save`` a checkpoint dict of ``entries`` plus a ``Touch(marker)``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**entries, "payload": Touch(marker)}, path)
    return path
