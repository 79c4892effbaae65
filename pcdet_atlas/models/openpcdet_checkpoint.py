"""OpenPCDet checkpoints -> this project's ``model_state``: CenterPoint / CP4F (voxel or pillar),
CenterPoint with DSVT (``dsvt_voxel.yaml``), and the second stages of the MSF and PTT
repositories (OpenPCDet forks).

The mapping is built from the model the matching config builds, so it knows every tensor's name,
shape and kind:

- **Names.** Most stages use OpenPCDet's names (VFE ``pfn_layers``, ``backbone_3d``,
  ``backbone_2d``, ``shared_conv``). A stage whose names differ says so itself with an
  ``openpcdet_names()`` method (:meth:`CenterHead.openpcdet_names`,
  :meth:`MSFHead.openpcdet_names`, :meth:`PTTHead.openpcdet_names`). OpenPCDet's
  ``global_step`` (its step counter) is dropped; a buffer that OpenPCDet does not save (the
  head's ``code_weights``) is taken from the config.
- **Other layouts.** A name can come with a rule (:data:`ReleasedName`): the same elements in
  another shape (:class:`Reshaped`: a ``Conv1d`` kernel of size 1 for a ``Linear`` weight), a
  bias folded into the BatchNorm after it (:class:`FoldedBias`), input columns in another
  order (:class:`PermutedInputs`). Each is exact: the model computes what the released layers
  compute.
- **No counterpart.** A tensor of ours that no released tensor matches is declared
  :class:`NoCounterpart` (with the released modules of that step and why); released modules
  that the released forward never reads are listed by the stage's ``openpcdet_unused()``.
  Both are errors, naming the keys: a checkpoint maps completely or not at all, unless
  ``partial=True`` asks for what maps exactly (to train the rest).
- **Sparse conv weights.** Ours have spconv 2.x's default layout ``(out, kD, kH, kW, in)``.
  A checkpoint trained with spconv 1.x holds ``(kD, kH, kW, in, out)``, and spconv 2.x's
  native algorithm ``(kD, kH, kW, out, in)`` (OpenPCDet's own loader converts both). A
  checkpoint has a single layout. It is read from the weights whose shape fits only one layout,
  or given by the caller when every weight is ambiguous (``in == out`` for all of them).
- **Mismatches.** Unknown keys, missing keys and wrong shapes raise one
  :class:`CheckpointMismatchError` that names them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from pcdet_atlas.models.detectors.detector3d_template import (
    CheckpointMismatchError,
    check_finite_state,
    read_checkpoint,
)
from pcdet_atlas.models.model_utils.released_names import (
    FoldedBias,
    NoCounterpart,
    PermutedInputs,
    ReleasedName,
    Reshaped,
    renamed,
)
from pcdet_atlas.ops.spconv import SparseConv3d, SubMConv3d
from pcdet_atlas.utils.common import write_atomic
from pcdet_atlas.version import __version__

__all__ = [
    "OPENPCDET_IGNORED_KEYS",
    "OPENPCDET_SAFE_GLOBALS",
    "SPCONV_LAYOUTS",
    "FoldedBias",
    "NoCounterpart",
    "PermutedInputs",
    "ReleasedName",
    "Reshaped",
    "atlas_to_openpcdet_state",
    "convert_openpcdet_checkpoint",
    "detect_spconv_layout",
    "openpcdet_key_map",
    "openpcdet_to_atlas_state",
    "openpcdet_unused_modules",
    "renamed",
    "spconv_weight_keys",
]

#: keys of OpenPCDet's ``model_state`` that hold no weights of the model
OPENPCDET_IGNORED_KEYS = ("global_step",)

#: what OpenPCDet's checkpoints need beyond tensors and plain values: its ``adam_onecycle``
#: schedule sets the optimizer's ``lr`` and ``betas`` to numpy float64 scalars (``np.cos``),
#: saved in ``optimizer_state``, under numpy 1.x's name or 2.x's
_NUMPY_SCALAR = np.float64(0).__reduce__()[0]
OPENPCDET_SAFE_GLOBALS = (
    (_NUMPY_SCALAR, "numpy.core.multiarray.scalar"),
    (_NUMPY_SCALAR, "numpy._core.multiarray.scalar"),
    np.dtype,
    np.dtypes.Float64DType,
)

#: sparse conv weight layouts: name -> (axis order as described, permutation from ours
#: ``(out, kD, kH, kW, in)`` to it)
SPCONV_LAYOUTS: dict[str, tuple[str, tuple[int, ...]]] = {
    "spconv2": ("(out, kD, kH, kW, in), spconv 2.x default (KRSC)", (0, 1, 2, 3, 4)),
    "spconv2-native": ("(kD, kH, kW, out, in), spconv 2.x native algorithm", (1, 2, 3, 0, 4)),
    "spconv1": ("(kD, kH, kW, in, out), spconv 1.x", (1, 2, 3, 4, 0)),
}


def _sources(name: ReleasedName) -> tuple[str, ...]:
    """The released keys one of ours is read from."""
    if isinstance(name, str):
        return (name,)
    if isinstance(name, (Reshaped, PermutedInputs)):
        return (name.name,)
    if isinstance(name, FoldedBias):
        return (name.running_mean, name.bias)
    return ()


def _prefixed(name: ReleasedName, prefix: str) -> ReleasedName:
    if isinstance(name, str):
        return prefix + name
    if isinstance(name, (Reshaped, PermutedInputs)):
        return replace(name, name=prefix + name.name)
    if isinstance(name, FoldedBias):
        return FoldedBias(prefix + name.running_mean, prefix + name.bias)
    if isinstance(name, NoCounterpart):
        return replace(name, released=tuple(prefix + m for m in name.released))
    return None


def _to_released(name: ReleasedName, value: torch.Tensor) -> dict[str, torch.Tensor]:
    """Our tensor as the released tensors it is read from (for a folded bias: zero bias)."""
    if isinstance(name, str):
        return {name: value}
    if isinstance(name, Reshaped):
        return {name.name: value.reshape(name.shape)}
    if isinstance(name, FoldedBias):
        return {name.running_mean: value, name.bias: torch.zeros_like(value)}
    if isinstance(name, PermutedInputs):
        back = torch.argsort(torch.tensor(name.order))
        return {name.name: value[:, back].contiguous()}
    return {}


def _from_released(name: ReleasedName, state: Mapping[str, torch.Tensor], shape) -> torch.Tensor:
    if isinstance(name, str):
        return state[name]
    if isinstance(name, Reshaped):
        return state[name.name].reshape(shape).clone()
    if isinstance(name, FoldedBias):
        return state[name.running_mean] - state[name.bias]
    if isinstance(name, PermutedInputs):
        return state[name.name][:, list(name.order)].contiguous()
    raise TypeError(f"no released tensor for {name!r}")


def _under(key: str, module: str) -> bool:
    return key == module or key.startswith(module + ".")


def _inverse(perm: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(sorted(range(len(perm)), key=lambda i: perm[i]))


def _format(problems: list[str]) -> str:
    head = "; ".join(problems[:10])
    return head + (f"; ... ({len(problems)} in all)" if len(problems) > 10 else "")


def _describe(kind: str, keys: list[str]) -> list[str]:
    """Up to 10 keys by name; more, counted per stage with the first of each (a checkpoint of
    another architecture differs in hundreds of keys)."""
    if len(keys) <= 10:
        return [f"{kind} {k}" for k in keys]
    stages: dict[str, list[str]] = {}
    for key in keys:
        stages.setdefault(key.split(".")[0], []).append(key)
    per_stage = ", ".join(f"{len(v)} under {s} (first {v[0]})" for s, v in stages.items())
    return [f"{len(keys)} {kind} keys: {per_stage}"]


def openpcdet_key_map(model: nn.Module) -> dict[str, ReleasedName]:
    """Every key of ``model.state_dict()`` -> OpenPCDet's name of that tensor, or how it is
    read from OpenPCDet's tensors (:data:`ReleasedName`)."""
    out: dict[str, ReleasedName] = {}
    for stage_name, stage in model.named_children():
        own = (
            stage.openpcdet_names()
            if hasattr(stage, "openpcdet_names")
            else {key: key for key in stage.state_dict()}
        )
        for key, theirs in own.items():
            out[f"{stage_name}.{key}"] = _prefixed(theirs, f"{stage_name}.")
    missing = set(model.state_dict()) - set(out)
    if missing:  # a tensor registered on the detector itself, outside every stage
        raise ValueError(f"{type(model).__name__}: no OpenPCDet name for {sorted(missing)}")
    readers: dict[str, str] = {}
    for ours, theirs in out.items():
        for source in _sources(theirs):
            if source in readers:
                raise ValueError(f"{readers[source]} and {ours} both read OpenPCDet's {source}")
            readers[source] = ours
    return out


def openpcdet_unused_modules(model: nn.Module) -> dict[str, str]:
    """Released modules (a key or a module prefix) that the released forward never reads and
    that have no counterpart here -> why (the stages' ``openpcdet_unused()``)."""
    return {
        f"{stage_name}.{module}": why
        for stage_name, stage in model.named_children()
        if hasattr(stage, "openpcdet_unused")
        for module, why in stage.openpcdet_unused().items()
    }


def spconv_weight_keys(model: nn.Module) -> list[str]:
    """The ``state_dict`` keys of the sparse conv weights of ``model``."""
    return [
        f"{name}.weight"
        for name, module in model.named_modules()
        if isinstance(module, (SubMConv3d, SparseConv3d))
    ]


def _layout_candidates(shape: tuple[int, ...], ours: tuple[int, ...]) -> set[str]:
    return {
        name
        for name, (_, perm) in SPCONV_LAYOUTS.items()
        if tuple(ours[i] for i in perm) == tuple(shape)
    }


def detect_spconv_layout(
    shapes: Mapping[str, tuple[tuple[int, ...], tuple[int, ...]]], source: str
) -> str | None:
    """The one layout of :data:`SPCONV_LAYOUTS` that fits every sparse conv weight.

    Args:
        shapes: OpenPCDet's key -> (its shape in the checkpoint, our model's shape).
        source: the checkpoint's name in error messages.

    Returns:
        The layout's name; ``None`` when ``shapes`` is empty (no sparse convs).

    Raises:
        CheckpointMismatchError: a weight fits no layout, two weights fit different ones, or
            every weight fits several (then the caller must name it: ``spconv_layout``).
    """
    possible = set(SPCONV_LAYOUTS)
    narrowed_by = None  # the last weight that ruled a layout out
    problems = []
    for key, (shape, ours) in shapes.items():
        fits = _layout_candidates(tuple(shape), tuple(ours))
        if not fits:
            problems.append(f"{key}: checkpoint {tuple(shape)} fits no sparse conv layout of "
                            f"model {tuple(ours)}")  # fmt: skip
        elif not possible & fits and not problems:
            raise CheckpointMismatchError(
                f"checkpoint {source}: its sparse conv weights fit different layouts ({key} "
                f"{tuple(shape)}: {sorted(fits)}; {narrowed_by[0]} {narrowed_by[1]}: "
                f"{sorted(possible)}); a checkpoint has one"
            )
        else:
            if possible - fits:
                narrowed_by = (key, tuple(shape))
            possible &= fits
    if problems:
        raise CheckpointMismatchError(f"checkpoint {source}: {_format(problems)}")
    if not shapes:
        return None
    if len(possible) > 1:
        raise CheckpointMismatchError(
            f"checkpoint {source}: every sparse conv weight has in == out channels, so its "
            f"layout is one of {sorted(possible)}; name it (spconv_layout / --spconv_layout)"
        )
    return possible.pop()


def _modules(keys) -> str:
    """Keys as their modules below the stage (``roi_head.point_pool.*``)."""
    return ", ".join(sorted({".".join(k.split(".")[:2]) + ".*" for k in keys}))


def _without_counterpart(
    names: Mapping[str, ReleasedName],
    unused: Mapping[str, str],
    state: Mapping[str, torch.Tensor],
) -> list[str]:
    """The problems of a complete mapping that no checkpoint can fix: our tensors without a
    released counterpart, and released ones the released forward never reads."""
    groups: dict[NoCounterpart, list[str]] = {}
    for ours, theirs in names.items():
        if isinstance(theirs, NoCounterpart):
            groups.setdefault(theirs, []).append(ours)
    problems = [
        f"no counterpart of {_modules(keys)} in the released code (released "
        f"{', '.join(spec.released) or 'nothing'}): {spec.reason}"
        for spec, keys in groups.items()
    ]
    reasons: dict[str, list[str]] = {}
    for module, why in unused.items():
        if any(_under(k, module) for k in state):
            reasons.setdefault(why, []).append(module)
    problems += [
        f"released {', '.join(modules)} without counterpart here: {why}"
        for why, modules in reasons.items()
    ]
    return problems


def _hints(model: nn.Module, names, missing: list[str], unknown: list[str], state) -> list[str]:
    hints = []
    if any(".heads_list.1." in k for k in unknown):
        hints.append(
            "(the checkpoint has several CenterHead heads, one per CLASS_NAMES_EACH_HEAD group; "
            "this project has one head over all classes)"
        )
    for stage in model.children():
        hint = stage.openpcdet_hint(missing, unknown) if hasattr(stage, "openpcdet_hint") else None
        if hint:
            hints.append(f"({hint})")
    read = {source for theirs in names.values() for source in _sources(theirs)}
    if read and not read & set(state):
        hints.append(
            "(the checkpoint shares no tensor name with the model: another architecture; a "
            "two-stage model's RPN checkpoint converts with the config in MODEL.RPN.CFG)"
        )
    return hints


def openpcdet_to_atlas_state(
    state: Mapping[str, torch.Tensor],
    model: nn.Module,
    *,
    spconv_layout: str | None = None,
    source: str = "<state_dict>",
    partial: bool = False,
) -> tuple[dict[str, torch.Tensor], str | None]:
    """An OpenPCDet ``model_state`` -> the ``state_dict`` that ``model`` loads strictly.

    Args:
        state: OpenPCDet's names and layouts.
        model: built from the config matching the checkpoint (its names, shapes, config buffers).
        spconv_layout: a key of :data:`SPCONV_LAYOUTS`, or ``None`` to read it from the shapes.
        source: the checkpoint's name in error messages.
        partial: map what maps exactly and leave out our tensors without a released
            counterpart (:class:`NoCounterpart`; load with ``strict=False`` and train them),
            ignoring the released tensors without one. Not a model to evaluate.

    Returns:
        ``(state_dict, layout)``: our names and layouts; the sparse conv layout found (``None``
        for a model without sparse convs).

    Raises:
        CheckpointMismatchError: naming unknown, missing and wrongly shaped keys, and (unless
            ``partial``) tensors without a counterpart on either side.
    """
    if spconv_layout is not None and spconv_layout not in SPCONV_LAYOUTS:
        raise ValueError(
            f"spconv_layout {spconv_layout!r}: expected one of {sorted(SPCONV_LAYOUTS)}"
        )
    own = model.state_dict()
    names = openpcdet_key_map(model)
    unused = openpcdet_unused_modules(model)
    ours_of = {s: ours for ours, theirs in names.items() for s in _sources(theirs)}
    no_counterpart = [
        m for theirs in names.values() if isinstance(theirs, NoCounterpart) for m in theirs.released
    ]
    sparse = set(spconv_weight_keys(model))
    known = [*no_counterpart, *unused]
    unknown = sorted(
        k
        for k in set(state) - set(ours_of) - set(OPENPCDET_IGNORED_KEYS)
        if not any(_under(k, m) for m in known)
    )
    missing = sorted(theirs for theirs in ours_of if theirs not in state)
    problems = _describe("unexpected", unknown) + _describe("missing", missing)
    if problems:
        problems += _hints(model, names, missing, unknown, state)
    if not partial:
        problems += _without_counterpart(names, unused, state)
    if problems:
        raise CheckpointMismatchError(
            f"checkpoint {source} does not match {type(model).__name__} built from the config: "
            f"{_format(problems)}"
        )
    if spconv_layout is None:
        shapes = {names[k]: (tuple(state[names[k]].shape), tuple(own[k].shape)) for k in sparse}
        layout = detect_spconv_layout(dict(sorted(shapes.items())), source)
    else:
        layout = spconv_layout if sparse else None
    out: dict[str, torch.Tensor] = {}
    bad_shape = []
    for ours, theirs in names.items():
        if theirs is None:  # from the config
            out[ours] = own[ours].clone()
            continue
        if isinstance(theirs, NoCounterpart):  # partial: left out
            continue
        if ours in sparse:
            perm = SPCONV_LAYOUTS[layout][1]
            expected = tuple(own[ours].shape[i] for i in perm)
            if tuple(state[theirs].shape) != expected:
                bad_shape.append(
                    f"{theirs}: checkpoint {tuple(state[theirs].shape)} vs {expected} in "
                    f"layout {layout} = {SPCONV_LAYOUTS[layout][0]}"
                )
                continue
            out[ours] = state[theirs].permute(*_inverse(perm)).contiguous()
            continue
        wrong = [
            f"{key}: checkpoint {tuple(state[key].shape)} vs "
            + (
                f"model {tuple(value.shape)}"
                if isinstance(theirs, str)
                else f"{tuple(value.shape)} (model {ours} {tuple(own[ours].shape)})"
            )
            for key, value in _to_released(theirs, own[ours]).items()
            if tuple(state[key].shape) != tuple(value.shape)
        ]
        if wrong:
            bad_shape += wrong
            continue
        out[ours] = _from_released(theirs, state, own[ours].shape)
    if bad_shape:
        raise CheckpointMismatchError(
            f"checkpoint {source} does not match {type(model).__name__} built from the config: "
            f"{_format(bad_shape)}"
        )
    return out, layout


def atlas_to_openpcdet_state(
    state: Mapping[str, torch.Tensor], model: nn.Module, *, spconv_layout: str = "spconv2"
) -> dict[str, torch.Tensor]:
    """The inverse of :func:`openpcdet_to_atlas_state`: our ``state_dict`` (of ``model``'s
    architecture) under OpenPCDet's names, sparse conv weights in ``spconv_layout``, with a
    zero ``global_step`` (a folded bias comes out as zero bias and our running mean)."""
    if spconv_layout not in SPCONV_LAYOUTS:
        raise ValueError(
            f"spconv_layout {spconv_layout!r}: expected one of {sorted(SPCONV_LAYOUTS)}"
        )
    names = openpcdet_key_map(model)
    missing = sorted(set(names) - set(state))
    if missing:
        raise CheckpointMismatchError(f"state_dict lacks {_format(missing)}")
    lost = sorted(k for k, theirs in names.items() if isinstance(theirs, NoCounterpart))
    if lost:
        raise CheckpointMismatchError(
            f"{type(model).__name__}: {_modules(lost)} have no counterpart in the released code"
        )
    sparse = set(spconv_weight_keys(model))
    perm = SPCONV_LAYOUTS[spconv_layout][1]
    out = {"global_step": torch.zeros(1, dtype=torch.int64)}
    for ours, theirs in names.items():
        if ours in sparse:
            out[theirs] = state[ours].permute(*perm).contiguous()
        else:
            out.update(_to_released(theirs, state[ours]))
    return out


def convert_openpcdet_checkpoint(
    src: str | Path,
    dst: str | Path,
    model: nn.Module,
    *,
    spconv_layout: str | None = None,
) -> dict:
    """Read OpenPCDet's checkpoint ``src``, map it onto ``model`` and write ``dst``.

    ``dst`` holds ``model_state`` (loads strictly into ``model``), OpenPCDet's ``epoch`` and
    ``it`` when present, ``version``, ``converted_from`` (the source file, its ``version``
    and the sparse conv layout found) and, for a model that records what it was built with (a
    two-stage model's RPN), ``model_info``. Returns that dict.

    Raises:
        RefusedGlobalError: ``src`` needs more than tensors, plain values and
            :data:`OPENPCDET_SAFE_GLOBALS` to load (named; loading it could run code).
        ValueError: ``model_state`` is not a mapping of tensors, or holds NaN/inf (naming the
            tensors).
        CheckpointMismatchError: no ``model_state``, or one that does not fit ``model``.
    """
    ckpt = read_checkpoint(src, safe_globals=OPENPCDET_SAFE_GLOBALS)
    if "model_state" not in ckpt:
        raise CheckpointMismatchError(
            f"checkpoint {src} has no 'model_state' (keys: {sorted(ckpt)[:10]}); OpenPCDet "
            "saves the weights under that key"
        )
    released = ckpt["model_state"]
    if not isinstance(released, Mapping):
        raise ValueError(
            f"checkpoint {src}: 'model_state' is a {type(released).__name__}, expected a mapping "
            "of tensor names to tensors (OpenPCDet's model.state_dict())"
        )
    not_tensors = sorted(str(k) for k, v in released.items() if not isinstance(v, torch.Tensor))
    if not_tensors:
        raise ValueError(
            f"checkpoint {src}: 'model_state' entries {not_tensors[:10]} are not tensors; "
            "expected OpenPCDet's model.state_dict() (tensors only)"
        )
    check_finite_state(released, str(src))
    state, layout = openpcdet_to_atlas_state(
        released, model, spconv_layout=spconv_layout, source=str(src)
    )
    out = {k: ckpt[k] for k in ("epoch", "it") if ckpt.get(k) is not None}
    info = getattr(model, "checkpoint_info", None)
    if info is not None:  # the RPN the second stage meets: the config's
        out["model_info"] = info()
    out.update(
        model_state=state,
        version=f"pcdet_atlas+{__version__}",
        converted_from={
            "file": str(src),
            "version": ckpt.get("version"),
            "spconv_layout": layout,
        },
    )
    write_atomic(dst, lambda f: torch.save(out, f))
    return out
