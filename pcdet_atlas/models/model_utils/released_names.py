"""The names a model stage gives its tensors in a released OpenPCDet checkpoint: what a stage's
``openpcdet_names()`` returns for each key of its ``state_dict`` (a released name, or a rule for
a tensor stored in another layout), read by :mod:`pcdet_atlas.models.openpcdet_checkpoint`.

Its own module, importing no model: the stages declare their names with it, and the converter,
which builds whole detectors, reads them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

__all__ = [
    "FoldedBias",
    "NoCounterpart",
    "PermutedInputs",
    "ReleasedName",
    "Reshaped",
    "renamed",
]


@dataclass(frozen=True)
class Reshaped:
    """The released tensor ``name``, of ``shape``: ours with the same elements in the same order
    (a ``Conv1d`` kernel of size 1 for a ``Linear`` weight, a token with other unit axes)."""

    name: str
    shape: tuple[int, ...]


@dataclass(frozen=True)
class FoldedBias:
    """Our BatchNorm's ``running_mean`` where the layer before it has no bias and the released
    one has: the released ``running_mean`` minus that ``bias``. BN(Wx + b) with mean m is
    BN(Wx) with mean m - b, with batch statistics (training) as with running ones."""

    running_mean: str
    bias: str


@dataclass(frozen=True)
class PermutedInputs:
    """The released weight ``name`` ``(out, in)`` whose input columns come in another order:
    our column ``j`` is the released column ``order[j]``."""

    name: str
    order: tuple[int, ...]


@dataclass(frozen=True)
class NoCounterpart:
    """A tensor of ours that no released tensor matches: the released modules of that step
    (``released``: a key or a module prefix) compute something else, ``reason`` says what."""

    reason: str
    released: tuple[str, ...] = ()


#: what a stage's ``openpcdet_names()`` gives for one key of its ``state_dict``: the released
#: name, ``None`` (not saved: the value comes from the config) or a rule
ReleasedName = str | Reshaped | FoldedBias | PermutedInputs | NoCounterpart | None


def renamed(key: str, modules: Mapping[str, str]) -> str | None:
    """``key`` with its longest module prefix in ``modules`` replaced by the released name
    (``None``: no prefix of ``key`` is in ``modules``)."""
    parts = key.split(".")
    for n in range(len(parts), 0, -1):
        theirs = modules.get(".".join(parts[:n]))
        if theirs is not None:
            return ".".join([theirs, *parts[n:]])
    return None
